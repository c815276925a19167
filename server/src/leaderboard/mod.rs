//! The leaderboard as the API serves it: the REST handlers live in `http::leaderboard`, the gRPC service in `grpc`,
//! the HTML page in `page`. Submissions, the queue and the evaluators are the `dsrl-leaderboard` crate's,
//! re-exported here at the paths the API uses.

pub mod grpc;
pub mod page;

pub use dsrl_leaderboard::*;
