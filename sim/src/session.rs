//! The rules of one session, checked in Rust before anything reaches Python: which environments a request names,
//! the actions' dtype, shape and values, and which environments have finished their episode.

use dsrl_proto::simulator::v1::{DType, Drive, Open, Play, Render, Reset, Step};

use crate::error::SimError;

/// The sides of a rendered frame, in pixels: large enough to see an agent, small enough that a frame (at most
/// 768 KiB) stays far below a gRPC message's limit.
pub const FRAME_SIDES: std::ops::RangeInclusive<u32> = 16..=512;

/// Capacity limits of a worker.
#[derive(Debug, Clone, Copy)]
pub struct Limits {
    pub max_envs_per_session: u32,
    /// Environments over all sessions of this worker.
    pub max_envs: u32,
}

/// The first-episode seeds of an `Open` (default 0..K), after checking K against the limits.
pub fn check_open(open: &Open, limits: Limits) -> Result<Vec<u64>, SimError> {
    let k = open.num_envs;
    if k == 0 {
        return Err(SimError::InvalidArgument("num_envs must be at least 1".into()));
    }
    if k > limits.max_envs_per_session {
        return Err(SimError::ResourceExhausted(format!(
            "num_envs {k} exceeds this worker's limit of {} environments per session",
            limits.max_envs_per_session
        )));
    }
    match open.seeds.len() {
        0 => Ok((0..u64::from(k)).collect()),
        n if n == k as usize => Ok(open.seeds.clone()),
        n => Err(SimError::InvalidArgument(format!(
            "{n} seeds for {k} environments: give one per environment or none"
        ))),
    }
}

pub struct SessionState {
    pub obs_dim: usize,
    pub act_dim: usize,
    auto_reset: bool,
    /// Whether each environment's episode has ended (and, without auto-reset, must be reset before stepping).
    finished: Vec<bool>,
}

impl SessionState {
    pub fn new(obs_dim: usize, act_dim: usize, num_envs: usize, auto_reset: bool) -> SessionState {
        SessionState {
            obs_dim,
            act_dim,
            auto_reset,
            finished: vec![false; num_envs],
        }
    }

    pub fn num_envs(&self) -> usize {
        self.finished.len()
    }

    /// The environments a request names (empty: all), each in range and named once.
    fn envs(&self, envs: &[u32]) -> Result<Vec<u32>, SimError> {
        if envs.is_empty() {
            return Ok((0..self.num_envs() as u32).collect());
        }
        let mut seen = vec![false; self.num_envs()];
        for &env in envs {
            let Some(slot) = seen.get_mut(env as usize) else {
                return Err(SimError::InvalidArgument(format!(
                    "env index {env} is out of range: this session has {} environments (0..{})",
                    self.num_envs(),
                    self.num_envs()
                )));
            };
            if std::mem::replace(slot, true) {
                return Err(SimError::InvalidArgument(format!("env index {env} is named twice")));
            }
        }
        Ok(envs.to_vec())
    }

    /// The first of `envs` whose episode has ended.
    fn first_finished(&self, envs: &[u32]) -> Option<u32> {
        envs.iter().copied().find(|&env| self.finished[env as usize])
    }

    pub fn check_reset(&self, reset: &Reset) -> Result<(Vec<u32>, Vec<u64>), SimError> {
        let envs = self.envs(&reset.envs)?;
        if reset.seeds.len() != envs.len() {
            return Err(SimError::InvalidArgument(format!(
                "{} seeds for {} environments: a reset needs one seed per environment",
                reset.seeds.len(),
                envs.len()
            )));
        }
        Ok((envs, reset.seeds.clone()))
    }

    pub fn after_reset(&mut self, envs: &[u32]) {
        for &env in envs {
            self.finished[env as usize] = false;
        }
    }

    /// Checks a step: environments, then the actions tensor (FLOAT32 `[n, act_dim]`, every value finite), then
    /// that no named environment has finished. Out-of-range values are not an error: the simulator clips them.
    pub fn check_step<'a>(&self, step: &'a Step) -> Result<(Vec<u32>, &'a [u8]), SimError> {
        let envs = self.envs(&step.envs)?;
        let actions = step
            .actions
            .as_ref()
            .ok_or_else(|| SimError::InvalidArgument("step without actions".into()))?;
        if actions.dtype != DType::Float32 as i32 {
            let got = DType::try_from(actions.dtype).map(|d| d.as_str_name().to_owned());
            return Err(SimError::InvalidArgument(format!(
                "actions have dtype {}, expected FLOAT32",
                got.unwrap_or_else(|_| actions.dtype.to_string())
            )));
        }
        let want = [envs.len() as u64, self.act_dim as u64];
        if actions.shape != want {
            return Err(SimError::InvalidArgument(format!(
                "actions have shape {:?}, expected {:?} (environments stepped x action dimension)",
                actions.shape, want
            )));
        }
        if actions.data.len() != envs.len() * self.act_dim * 4 {
            return Err(SimError::InvalidArgument(format!(
                "actions hold {} bytes, shape {:?} of FLOAT32 needs {}",
                actions.data.len(),
                want,
                envs.len() * self.act_dim * 4
            )));
        }
        for (i, chunk) in actions.data.chunks_exact(4).enumerate() {
            let value = f32::from_le_bytes(chunk.try_into().expect("4-byte chunk"));
            if !value.is_finite() {
                return Err(SimError::InvalidArgument(format!(
                    "action of env {} dimension {} is {value}: actions must be finite",
                    envs[i / self.act_dim],
                    i % self.act_dim
                )));
            }
        }
        if !self.auto_reset
            && let Some(env) = self.first_finished(&envs)
        {
            return Err(SimError::FailedPrecondition(format!(
                "env {env} has finished its episode: reset it before stepping (or open the session with \
                 AUTO_RESET_SAME_STEP)"
            )));
        }
        Ok((envs, &actions.data))
    }

    /// Checks a drive: a session without auto-reset (a driven episode ends with its environment finished), the
    /// environments, and that none of them has finished. Whether the session has a controller is checked by the
    /// caller, which knows how the session was opened.
    pub fn check_drive(&self, drive: &Drive) -> Result<Vec<u32>, SimError> {
        if self.auto_reset {
            return Err(SimError::FailedPrecondition(
                "drive needs a session opened with AUTO_RESET_NONE: a driven episode ends, and the client resets it"
                    .into(),
            ));
        }
        let envs = self.envs(&drive.envs)?;
        if let Some(env) = self.first_finished(&envs) {
            return Err(SimError::FailedPrecondition(format!(
                "env {env} has finished its episode: reset it before driving it"
            )));
        }
        Ok(envs)
    }

    /// Checks a play: the environments, and that none of them has finished. Whether the session has a policy is
    /// checked by the caller.
    pub fn check_play(&self, play: &Play) -> Result<Vec<u32>, SimError> {
        let envs = self.envs(&play.envs)?;
        if let Some(env) = self.first_finished(&envs) {
            return Err(SimError::FailedPrecondition(format!(
                "env {env} has finished its episode: reset it before playing it"
            )));
        }
        Ok(envs)
    }

    /// Checks a render: the environments, and each side of the frame within [`FRAME_SIDES`]. A finished
    /// environment may be drawn (its last state).
    pub fn check_render(&self, render: &Render) -> Result<Vec<u32>, SimError> {
        let envs = self.envs(&render.envs)?;
        for (side, value) in [("width", render.width), ("height", render.height)] {
            if !FRAME_SIDES.contains(&value) {
                return Err(SimError::InvalidArgument(format!(
                    "a frame {side} of {value} pixels: give {} to {}",
                    FRAME_SIDES.start(),
                    FRAME_SIDES.end()
                )));
            }
        }
        Ok(envs)
    }

    /// Driven environments have played their episode to its end.
    pub fn after_drive(&mut self, envs: &[u32]) {
        for &env in envs {
            self.finished[env as usize] = true;
        }
    }

    /// Records which stepped environments ended their episode (with auto-reset they start a new one at once).
    pub fn after_step(&mut self, envs: &[u32], terminated: &[u8], truncated: &[u8]) {
        if self.auto_reset {
            return;
        }
        for (k, &env) in envs.iter().enumerate() {
            if terminated.get(k) == Some(&1) || truncated.get(k) == Some(&1) {
                self.finished[env as usize] = true;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use dsrl_proto::simulator::v1::Tensor;

    use super::*;

    fn step(envs: Vec<u32>, actions: Tensor) -> Step {
        Step {
            envs,
            actions: Some(actions),
        }
    }

    #[test]
    fn open_checks_num_envs_and_seeds() {
        let limits = Limits {
            max_envs_per_session: 4,
            max_envs: 8,
        };
        let open = |num_envs, seeds: Vec<u64>| Open {
            task: "t".into(),
            num_envs,
            seeds,
            auto_reset: 0,
            controller: None,
        };
        assert_eq!(check_open(&open(3, vec![]), limits).unwrap(), vec![0, 1, 2]);
        assert_eq!(check_open(&open(2, vec![7, 9]), limits).unwrap(), vec![7, 9]);
        assert!(matches!(
            check_open(&open(0, vec![]), limits),
            Err(SimError::InvalidArgument(_))
        ));
        assert!(matches!(
            check_open(&open(5, vec![]), limits),
            Err(SimError::ResourceExhausted(_))
        ));
        assert!(matches!(
            check_open(&open(2, vec![1]), limits),
            Err(SimError::InvalidArgument(_))
        ));
    }

    #[test]
    fn step_checks_envs_dtype_shape_values_and_finished() {
        let mut state = SessionState::new(3, 2, 2, false);
        let ok = step(vec![], Tensor::from_f32(&[2, 2], &[0.0, 1.0, 5.0, -5.0]));
        let (envs, _) = state.check_step(&ok).unwrap();
        assert_eq!(envs, vec![0, 1]);
        let bad = [
            step(vec![2], Tensor::from_f32(&[1, 2], &[0.0, 0.0])),
            step(vec![0, 0], Tensor::from_f32(&[2, 2], &[0.0; 4])),
            step(vec![], Tensor::from_f64(&[2, 2], &[0.0; 4])),
            step(vec![], Tensor::from_f32(&[2, 3], &[0.0; 6])),
            step(vec![], Tensor::from_f32(&[4], &[0.0; 4])),
            step(vec![], Tensor::from_f32(&[2, 2], &[0.0, f32::NAN, 0.0, 0.0])),
            step(vec![], Tensor::from_f32(&[2, 2], &[0.0, 0.0, f32::INFINITY, 0.0])),
            Step {
                envs: vec![],
                actions: None,
            },
        ];
        for request in &bad {
            assert!(
                matches!(state.check_step(request), Err(SimError::InvalidArgument(_))),
                "{request:?}"
            );
        }
        let mut short = Tensor::from_f32(&[2, 2], &[0.0; 4]);
        short.data.pop();
        assert!(matches!(
            state.check_step(&step(vec![], short)),
            Err(SimError::InvalidArgument(_))
        ));

        state.after_step(&[0, 1], &[0, 0], &[0, 1]);
        let only_first = step(vec![0], Tensor::from_f32(&[1, 2], &[0.0, 0.0]));
        assert!(state.check_step(&only_first).is_ok());
        let err = state.check_step(&ok).unwrap_err();
        assert!(matches!(err, SimError::FailedPrecondition(_)), "{err}");
        assert!(err.to_string().contains("env 1"), "{err}");
        state.after_reset(&[1]);
        assert!(state.check_step(&ok).is_ok());
    }

    #[test]
    fn auto_reset_sessions_never_block_finished_envs() {
        let mut state = SessionState::new(3, 1, 1, true);
        state.after_step(&[0], &[1], &[0]);
        assert!(
            state
                .check_step(&step(vec![], Tensor::from_f32(&[1, 1], &[0.0])))
                .is_ok()
        );
    }

    #[test]
    fn drive_needs_no_auto_reset_known_envs_and_unfinished_episodes() {
        let drive = |envs: Vec<u32>| Drive { envs };
        let auto = SessionState::new(3, 1, 2, true);
        assert!(matches!(
            auto.check_drive(&drive(vec![])),
            Err(SimError::FailedPrecondition(_))
        ));
        let mut state = SessionState::new(3, 1, 2, false);
        assert_eq!(state.check_drive(&drive(vec![])).unwrap(), vec![0, 1]);
        assert!(matches!(
            state.check_drive(&drive(vec![2])),
            Err(SimError::InvalidArgument(_))
        ));
        state.after_drive(&[1]);
        assert_eq!(state.check_drive(&drive(vec![0])).unwrap(), vec![0]);
        let err = state.check_drive(&drive(vec![0, 1])).unwrap_err();
        assert!(matches!(err, SimError::FailedPrecondition(_)), "{err}");
        state.after_reset(&[1]);
        assert!(state.check_drive(&drive(vec![0, 1])).is_ok());
    }

    #[test]
    fn render_checks_envs_and_frame_sides() {
        let mut state = SessionState::new(3, 1, 2, false);
        let render = |envs: Vec<u32>, width, height| Render { envs, width, height };
        assert_eq!(state.check_render(&render(vec![], 160, 120)).unwrap(), vec![0, 1]);
        for bad in [
            render(vec![2], 160, 160),
            render(vec![0, 0], 160, 160),
            render(vec![], 15, 160),
            render(vec![], 160, 513),
            render(vec![], 0, 0),
        ] {
            assert!(
                matches!(state.check_render(&bad), Err(SimError::InvalidArgument(_))),
                "{bad:?}"
            );
        }
        state.after_step(&[0], &[1], &[0]);
        assert_eq!(state.check_render(&render(vec![0], 16, 512)).unwrap(), vec![0]);
    }

    #[test]
    fn reset_needs_one_seed_per_env() {
        let state = SessionState::new(3, 1, 3, false);
        let reset = |envs: Vec<u32>, seeds: Vec<u64>| Reset {
            envs,
            seeds,
            controller: None,
        };
        assert_eq!(
            state.check_reset(&reset(vec![], vec![4, 5, 6])).unwrap(),
            (vec![0, 1, 2], vec![4, 5, 6])
        );
        assert_eq!(state.check_reset(&reset(vec![2], vec![9])).unwrap(), (vec![2], vec![9]));
        assert!(state.check_reset(&reset(vec![], vec![])).is_err());
        assert!(state.check_reset(&reset(vec![3], vec![1])).is_err());
    }
}
