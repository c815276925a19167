//! Pieces of the safe-RL expert trainer that DSRL's Bullet and Safety-Gymnasium datasets come from (spec 6.1:
//! a Lagrangian policy-gradient learner whose cost limit sweeps from `cost_start` to `cost_end`, so the episodes
//! it plays cover the reward–cost frontier). This module holds the algorithm's arithmetic, independent of the
//! network library: advantages, the PID Lagrange multiplier and the cost-limit schedule. The candle policy and
//! the training loop that use them are the next step of the pipeline.

pub mod advantage;
pub mod lagrangian;
