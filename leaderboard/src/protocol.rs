//! The protocol this leaderboard scores under: its catalog, the simulator pins compiled into the evaluator, its
//! episodes per threshold, the held-seed policy and the scorer's revision (`dsrl_suite::protocol`). Every result
//! records the version it was scored under; the tables rank only the current one's.

use dsrl_suite::Catalog;
use dsrl_suite::protocol::{Protocol, ProtocolParts};

use super::seeds;

/// The protocol of a leaderboard with `catalog` that plays `episodes_per_threshold` episodes per threshold.
pub fn current(catalog: &Catalog, episodes_per_threshold: u32) -> Protocol {
    ProtocolParts {
        catalog,
        simulator_pins: dsrl_evaluation::SIMULATOR_PINS,
        episodes_per_threshold,
        held_seeds: seeds::POLICY,
        scorer_revision: dsrl_evaluation::SCORER_REVISION,
    }
    .protocol()
}
