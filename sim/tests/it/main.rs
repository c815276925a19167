//! Tests against real `dsrl-sim-worker` processes hosting the real simulators (the `.venv-sim` environment made by
//! `sim/setup.sh`; a missing environment fails the tests with that instruction).

mod all_tasks;
mod compliance;
mod controller;
mod determinism;
mod package;
mod render;
mod smoke;
mod speedups;
mod support;
