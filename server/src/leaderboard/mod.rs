//! The leaderboard as the API serves it, each side in this folder: the REST routes (`rest`), the gRPC service
//! (`grpc`) and the HTML pages (`page`). Submissions, the queue, the evaluators and the replays are the
//! `dsrl-leaderboard` crate's, re-exported here at the paths the API uses.

pub mod grpc;
pub mod page;
pub mod rest;

pub use dsrl_leaderboard::*;
