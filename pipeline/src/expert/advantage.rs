//! Generalized advantage estimation over a batch of steps from several episodes, for the reward and the cost
//! critics alike.

/// One step as the learner stored it. `next_value` is the critic's value of the next observation: used when the
/// episode goes on or was cut by the time limit (truncated), ignored when it terminated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StepValue {
    pub signal: f64,
    pub value: f64,
    pub next_value: f64,
    pub terminated: bool,
    /// The episode ends here (terminated or truncated): no advantage flows back across this step.
    pub episode_end: bool,
}

/// GAE(γ, λ): `δ_t = s_t + γ·V(s_{t+1})·(1 − terminated_t) − V(s_t)`, `A_t = δ_t + γλ·(1 − end_t)·A_{t+1}`.
/// Returns advantages and the critic targets `A_t + V(s_t)`.
pub fn gae(steps: &[StepValue], gamma: f64, lambda: f64) -> (Vec<f64>, Vec<f64>) {
    let mut advantages = vec![0.0; steps.len()];
    let mut next = 0.0;
    for (t, s) in steps.iter().enumerate().rev() {
        let bootstrap = if s.terminated { 0.0 } else { gamma * s.next_value };
        let delta = s.signal + bootstrap - s.value;
        let carry = if s.episode_end { 0.0 } else { gamma * lambda * next };
        next = delta + carry;
        advantages[t] = next;
    }
    let targets = advantages.iter().zip(steps).map(|(a, s)| a + s.value).collect();
    (advantages, targets)
}

/// Advantages scaled to zero mean and unit variance (population), as policy-gradient learners do per batch.
pub fn normalize(values: &mut [f64]) {
    let n = values.len() as f64;
    if values.len() < 2 {
        return;
    }
    let mean = values.iter().sum::<f64>() / n;
    let std = (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    for v in values.iter_mut() {
        *v = (*v - mean) / (std + 1e-8);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn step(signal: f64, value: f64, next_value: f64, terminated: bool, episode_end: bool) -> StepValue {
        StepValue {
            signal,
            value,
            next_value,
            terminated,
            episode_end,
        }
    }

    #[test]
    fn one_step_episodes_are_td_errors() {
        let steps = [step(1.0, 0.5, 2.0, false, true), step(1.0, 0.5, 2.0, true, true)];
        let (adv, targets) = gae(&steps, 0.9, 0.95);
        assert!(
            (adv[0] - (1.0 + 0.9 * 2.0 - 0.5)).abs() < 1e-12,
            "truncation bootstraps"
        );
        assert!((adv[1] - (1.0 - 0.5)).abs() < 1e-12, "termination does not");
        assert!((targets[1] - 1.0).abs() < 1e-12);
    }

    #[test]
    fn lambda_one_gives_discounted_returns_and_episodes_do_not_mix() {
        // Two episodes: [1, 2, 3] terminated, then [10] terminated. With λ = 1 and zero values the advantage is
        // the discounted return to the episode's end.
        let steps = [
            step(1.0, 0.0, 0.0, false, false),
            step(2.0, 0.0, 0.0, false, false),
            step(3.0, 0.0, 0.0, true, true),
            step(10.0, 0.0, 0.0, true, true),
        ];
        let (adv, _) = gae(&steps, 0.5, 1.0);
        assert_eq!(adv, vec![1.0 + 0.5 * 2.0 + 0.25 * 3.0, 2.0 + 0.5 * 3.0, 3.0, 10.0]);
    }

    #[test]
    fn lambda_zero_gives_one_step_td() {
        let steps = [step(1.0, 1.0, 3.0, false, false), step(0.0, 3.0, 0.0, true, true)];
        let (adv, _) = gae(&steps, 0.9, 0.0);
        assert!((adv[0] - (1.0 + 0.9 * 3.0 - 1.0)).abs() < 1e-12);
        assert!((adv[1] - (0.0 - 3.0)).abs() < 1e-12);
    }

    #[test]
    fn normalize_centres_and_scales() {
        let mut v = vec![1.0, 2.0, 3.0, 4.0];
        normalize(&mut v);
        assert!(v.iter().sum::<f64>().abs() < 1e-9);
        assert!((v.iter().map(|x| x * x).sum::<f64>() / 4.0 - 1.0).abs() < 1e-6);
    }
}
