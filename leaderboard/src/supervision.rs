//! What each evaluator task is doing, as its supervisor (`runner::spawn`) and the evaluator itself record it: for
//! `/healthz` (degraded while a process that should evaluate has none running), `/metrics` (restarts) and the
//! submissions' views (which evaluator scores a job).

use std::sync::Mutex;

use prometheus_client::metrics::counter::Counter;
use serde::Serialize;

use dsrl_service::db::now_rfc3339;

/// What a panicked task's payload says (a `String` or `&str` message), for the logs and `/healthz`.
pub fn panic_message(payload: Box<dyn std::any::Any + Send>) -> String {
    payload
        .downcast_ref::<String>()
        .cloned()
        .or_else(|| payload.downcast_ref::<&str>().map(|s| (*s).to_owned()))
        .unwrap_or_else(|| "a panic without a message".to_owned())
}

/// One evaluator as `/healthz` shows it.
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct EvaluatorState {
    pub index: usize,
    /// The lease owner it claims jobs as (new after every restart).
    pub owner: String,
    /// Running now: false between a panic and its restart.
    pub running: bool,
    /// The job it is scoring.
    pub job: Option<i64>,
    pub last_claim: Option<String>,
    pub last_heartbeat: Option<String>,
    pub restarts: u32,
    /// What its last panic said.
    pub last_panic: Option<String>,
}

pub struct Evaluators {
    states: Mutex<Vec<EvaluatorState>>,
    /// `dsrl_evaluator_restarts_total`: evaluators started again after a panic.
    pub restarts: Counter,
}

impl Default for Evaluators {
    fn default() -> Self {
        Evaluators {
            states: Mutex::new(Vec::new()),
            restarts: Counter::default(),
        }
    }
}

impl Evaluators {
    fn with<T>(&self, index: usize, f: impl FnOnce(&mut EvaluatorState) -> T) -> Option<T> {
        // A poisoned lock only means another thread panicked while holding it; the states are still plain data.
        let mut states = self.states.lock().unwrap_or_else(|e| e.into_inner());
        states.get_mut(index).map(f)
    }

    pub fn add(&self, index: usize) {
        let mut states = self.states.lock().unwrap_or_else(|e| e.into_inner());
        while states.len() <= index {
            let index = states.len();
            states.push(EvaluatorState {
                index,
                owner: String::new(),
                running: false,
                job: None,
                last_claim: None,
                last_heartbeat: None,
                restarts: 0,
                last_panic: None,
            });
        }
    }

    pub fn started(&self, index: usize, owner: &str) {
        self.with(index, |s| {
            s.owner = owner.to_owned();
            s.running = true;
            s.job = None;
        });
    }

    pub fn claimed(&self, index: usize, job: i64) {
        self.with(index, |s| {
            s.job = Some(job);
            s.last_claim = Some(now_rfc3339());
        });
    }

    pub fn heartbeat(&self, index: usize) {
        self.with(index, |s| s.last_heartbeat = Some(now_rfc3339()));
    }

    pub fn idle(&self, index: usize) {
        self.with(index, |s| s.job = None);
    }

    /// Records a panic; returns the job the evaluator held.
    pub fn panicked(&self, index: usize, message: &str) -> Option<i64> {
        self.restarts.inc();
        self.with(index, |s| {
            s.running = false;
            s.restarts += 1;
            s.last_panic = Some(message.to_owned());
            s.job.take()
        })
        .flatten()
    }

    pub fn states(&self) -> Vec<EvaluatorState> {
        self.states.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// The owner name of the evaluator scoring `job` here, if one is.
    pub fn scoring(&self, job: i64) -> Option<EvaluatorState> {
        self.states().into_iter().find(|s| s.job == Some(job))
    }
}

/// `/healthz` of a process that holds evaluators (the embedded server, `dsrl-evaluator`).
#[derive(Debug, Clone, Serialize, utoipa::ToSchema)]
pub struct Health {
    /// `ok`, or `degraded` (answered with 503) when the database does not answer or a process that should
    /// evaluate has no evaluator running.
    pub status: &'static str,
    pub database: String,
    /// Evaluators this process should run (`leaderboard.evaluators`).
    pub evaluators_configured: u32,
    pub evaluators: Vec<EvaluatorState>,
    /// The replays of scored episodes (`renders`): informational, never a reason for `degraded`.
    pub renderer: RendererState,
}

/// The renderer as `/healthz` shows it.
#[derive(Debug, Clone, Default, Serialize, utoipa::ToSchema)]
pub struct RendererState {
    /// Running now: false between a panic and its restart.
    pub running: bool,
    /// The episode being replayed (`submission/threshold-index/episode`).
    pub replaying: Option<String>,
    pub queued: usize,
    pub rendered: u64,
    pub failed: u64,
    /// Replays dropped (and queued again) because scoring needed the machine.
    pub yielded: u64,
    pub restarts: u32,
    pub last_error: Option<String>,
}
