//! Pieces of the safe-RL expert trainer that DSRL's Bullet and Safety-Gymnasium datasets come from (spec 6.1:
//! a Lagrangian policy-gradient learner whose cost limit sweeps from `cost_start` to `cost_end`, so the episodes
//! it plays cover the reward–cost frontier). This module holds the algorithm's arithmetic, independent of the
//! network library: advantages, the PID Lagrange multiplier and the cost-limit schedule; `ppo` is the candle learner
//! (PPO-Lagrangian with a Gaussian actor from `dsrl-policy`), `train` the loop that drives it through the simulator
//! workers and keeps what it plays.

pub mod advantage;
pub mod lagrangian;
pub mod normalization;
pub mod ppo;
pub mod train;
