//! The Lagrange multiplier of the cost constraint and the cost limit it enforces, as DSRL's expert recipe moves it.

use serde::{Deserialize, Serialize};

/// PID Lagrange multiplier (Stooke et al. 2020, as FSRL's `LagrangianOptimizer`): with `e = mean(cost) − limit`,
/// `I ← max(0, I + e)`, `D = max(0, e − e_prev)`, `λ = max(0, Kp·e + Ki·I + Kd·D)`. With Kp = Kd = 0 it is plain
/// gradient ascent on λ.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PidLagrangian {
    pub kp: f64,
    pub ki: f64,
    pub kd: f64,
    pub error_old: f64,
    pub error_integral: f64,
    pub lagrangian: f64,
}

impl PidLagrangian {
    /// DSRL's expert settings (spec 6.1): Kp, Ki, Kd = 0.05, 0.005, 0.1.
    pub fn dsrl() -> PidLagrangian {
        PidLagrangian::new(0.05, 0.005, 0.1)
    }

    pub fn new(kp: f64, ki: f64, kd: f64) -> PidLagrangian {
        PidLagrangian {
            kp,
            ki,
            kd,
            error_old: 0.0,
            error_integral: 0.0,
            lagrangian: 0.0,
        }
    }

    /// One update from the episode costs of the last collection.
    pub fn step(&mut self, episode_costs: &[f64], limit: f64) -> f64 {
        if episode_costs.is_empty() {
            return self.lagrangian;
        }
        let error = episode_costs.iter().map(|c| c - limit).sum::<f64>() / episode_costs.len() as f64;
        let diff = (error - self.error_old).max(0.0);
        self.error_integral = (self.error_integral + error).max(0.0);
        self.error_old = error;
        self.lagrangian = (self.kp * error + self.ki * self.error_integral + self.kd * diff).max(0.0);
        self.lagrangian
    }

    /// The policy's objective mixes the advantages as `(A_r − λ·A_c) / (1 + λ)` (FSRL's `rescaling=True`), so the
    /// step size does not grow with λ.
    pub fn mix(&self, reward_advantage: f64, cost_advantage: f64) -> f64 {
        (reward_advantage - self.lagrangian * cost_advantage) / (1.0 + self.lagrangian)
    }
}

/// DSRL's moving cost limit (spec 6.1): constant `cost_start` until `epoch_start`, linear to `cost_end` at
/// `epoch_end`, constant after. The limit may rise or fall (DroneRun and the navigation tasks go down).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct CostLimitSchedule {
    pub cost_start: f64,
    pub cost_end: f64,
    pub epoch_start: u32,
    pub epoch_end: u32,
}

impl CostLimitSchedule {
    pub fn at(&self, epoch: u32) -> f64 {
        let span = self.epoch_end.saturating_sub(self.epoch_start);
        if span == 0 {
            return if epoch >= self.epoch_end {
                self.cost_end
            } else {
                self.cost_start
            };
        }
        let x = epoch.saturating_sub(self.epoch_start).min(span);
        self.cost_start - f64::from(x) * (self.cost_start - self.cost_end) / f64::from(span)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pid_follows_fsrl_by_hand() {
        let mut pid = PidLagrangian::new(0.05, 0.005, 0.1);
        // Costs 30 over a limit of 10: e = 20, D = 20, I = 20.
        let l1 = pid.step(&[25.0, 35.0], 10.0);
        assert!((l1 - (0.05 * 20.0 + 0.005 * 20.0 + 0.1 * 20.0)).abs() < 1e-12);
        // Same error again: D = 0, I = 40.
        let l2 = pid.step(&[30.0], 10.0);
        assert!((l2 - (0.05 * 20.0 + 0.005 * 40.0)).abs() < 1e-12);
        // Far under the limit: λ is projected to 0 and the integral shrinks but never below 0.
        let l3 = pid.step(&[0.0], 100.0);
        assert_eq!(l3, 0.0);
        assert_eq!(pid.error_integral, 0.0);
        assert_eq!(pid.step(&[], 10.0), 0.0, "no episodes, no update");
    }

    #[test]
    fn pure_integral_is_gradient_ascent() {
        let mut pid = PidLagrangian::new(0.0, 0.1, 0.0);
        for _ in 0..3 {
            pid.step(&[12.0], 10.0);
        }
        assert!((pid.lagrangian - 0.6).abs() < 1e-12);
    }

    #[test]
    fn mixing_rescales_by_one_plus_lambda() {
        let mut pid = PidLagrangian::new(1.0, 0.0, 0.0);
        pid.step(&[11.0], 10.0);
        assert_eq!(pid.lagrangian, 1.0);
        assert_eq!(pid.mix(4.0, 2.0), 1.0);
    }

    #[test]
    fn the_cost_limit_moves_linearly_between_the_epochs() {
        // SafetyCarRun-v0: 5 -> 100 between epochs 100 and 900.
        let up = CostLimitSchedule {
            cost_start: 5.0,
            cost_end: 100.0,
            epoch_start: 100,
            epoch_end: 900,
        };
        assert_eq!(up.at(0), 5.0);
        assert_eq!(up.at(100), 5.0);
        assert_eq!(up.at(500), 52.5);
        assert_eq!(up.at(900), 100.0);
        assert_eq!(up.at(1000), 100.0);
        // SafetyDroneRun-v0 goes down: 100 -> 5 between 50 and 800.
        let down = CostLimitSchedule {
            cost_start: 100.0,
            cost_end: 5.0,
            epoch_start: 50,
            epoch_end: 800,
        };
        assert_eq!(down.at(800), 5.0);
        assert!(down.at(425) > 5.0 && down.at(425) < 100.0);
    }
}
