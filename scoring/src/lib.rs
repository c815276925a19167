//! Turning scored episodes into what the leaderboard shows: the bootstrap intervals and the interquartile mean of the
//! tables (`leaderboard`), the paper's complete results table (`paper`) and what methods beyond the paper publish
//! (`published`), our trained reference entries and their agreement with the paper's verdicts (`reference`), and the
//! protocol version that says which results compare (`protocol`). The per-episode arithmetic (normalized reward and
//! cost, the safety rule) is the domain's: `dsrl_suite::score`.

pub mod leaderboard;
pub mod paper;
pub mod protocol;
pub mod published;
pub mod reference;
