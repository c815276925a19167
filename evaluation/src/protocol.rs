//! The protocol a leaderboard scores under: its catalog, the simulator pins compiled in here, its episodes per
//! threshold and scoring layout, the held-seed policy and the scorer's revision (`dsrl_scoring::protocol`). Every
//! result records the version it was scored under; the tables rank only the current one's, and the documents'
//! reference tables use it.

use dsrl_scoring::protocol::{Protocol, ProtocolParts};
use dsrl_suite::Catalog;

use crate::{SCORER_REVISION, SIMULATOR_PINS, seeds};

/// Episodes per cost threshold, the paper's (and the leaderboard's default `episodes_per_threshold`).
pub const DEFAULT_EPISODES_PER_THRESHOLD: u32 = 20;

/// The leaderboard's default scoring layout: environments per threshold, one session each.
pub use dsrl_scoring::protocol::DEFAULT_ENVS_PER_SESSION;

/// The protocol of a leaderboard with `catalog` that plays `episodes_per_threshold` episodes per threshold on
/// `envs_per_session` environments per threshold.
pub fn current(catalog: &Catalog, episodes_per_threshold: u32, envs_per_session: u32) -> Protocol {
    ProtocolParts {
        catalog,
        simulator_pins: SIMULATOR_PINS,
        episodes_per_threshold,
        envs_per_session,
        held_seeds: seeds::POLICY,
        scorer_revision: SCORER_REVISION,
    }
    .protocol()
}
