//! Streaming validation of a dataset against its task: widths, finite values, episodes closed by a done flag,
//! contiguous steps, episodes no longer than the task's horizon. The first problem is reported with its row
//! and column so the uploader can find it; while checking, the tracker numbers episodes and steps and builds
//! the episode index.

use std::fmt;

use crate::episode::{EpisodeSummary, numpy_sum_f32};
use crate::transitions::TransitionChunk;

/// The first problem found in a dataset.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub struct ValidationError {
    /// Zero-based row of the offending transition, when the problem is in one row.
    pub row: Option<u64>,
    /// Column (and element, as `observations[5]`) of the offending value.
    pub column: Option<String>,
    pub message: String,
}

impl ValidationError {
    pub fn at(row: u64, column: impl Into<String>, message: impl Into<String>) -> Self {
        ValidationError {
            row: Some(row),
            column: Some(column.into()),
            message: message.into(),
        }
    }
    pub fn column(column: impl Into<String>, message: impl Into<String>) -> Self {
        ValidationError {
            row: None,
            column: Some(column.into()),
            message: message.into(),
        }
    }
    pub fn whole(message: impl Into<String>) -> Self {
        ValidationError {
            row: None,
            column: None,
            message: message.into(),
        }
    }
}

impl fmt::Display for ValidationError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match (&self.row, &self.column) {
            (Some(r), Some(c)) => write!(f, "row {r}, column {c}: {}", self.message),
            (Some(r), None) => write!(f, "row {r}: {}", self.message),
            (None, Some(c)) => write!(f, "column {c}: {}", self.message),
            (None, None) => f.write_str(&self.message),
        }
    }
}

/// What a dataset of one task must look like.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Expectation {
    pub obs_dim: usize,
    pub act_dim: usize,
    /// The task's time limit: no episode may be longer.
    pub max_episode_steps: u32,
}

/// Walks the rows of a dataset in order, checking each chunk and numbering episodes and steps.
#[derive(Debug)]
pub struct EpisodeTracker {
    expect: Expectation,
    next_row: u64,
    episode: u32,
    step: u32,
    open_start: u64,
    open_rewards: Vec<f32>,
    open_costs: Vec<f32>,
    episodes: Vec<EpisodeSummary>,
}

/// The episode and step columns of one checked chunk.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct Numbering {
    pub episode: Vec<u32>,
    pub step: Vec<u32>,
}

impl EpisodeTracker {
    pub fn new(expect: Expectation) -> Self {
        EpisodeTracker {
            expect,
            next_row: 0,
            episode: 0,
            step: 0,
            open_start: 0,
            open_rewards: Vec::new(),
            open_costs: Vec::new(),
            episodes: Vec::new(),
        }
    }

    pub fn rows_seen(&self) -> u64 {
        self.next_row
    }

    /// Checks the next chunk of rows; returns their episode and step numbers.
    pub fn check(&mut self, chunk: &TransitionChunk) -> Result<Numbering, ValidationError> {
        let base = self.next_row;
        let e = self.expect;
        if chunk.obs_dim != e.obs_dim {
            return Err(ValidationError::column(
                "observations",
                format!("{} features per observation, expected {}", chunk.obs_dim, e.obs_dim),
            ));
        }
        if chunk.act_dim != e.act_dim {
            return Err(ValidationError::column(
                "actions",
                format!("{} features per action, expected {}", chunk.act_dim, e.act_dim),
            ));
        }
        if !chunk.is_consistent() {
            return Err(ValidationError::whole(format!(
                "columns of rows {base}.. have different lengths (internal reader error)"
            )));
        }
        check_finite(base, "observations", &chunk.observations, e.obs_dim)?;
        check_finite(base, "next_observations", &chunk.next_observations, e.obs_dim)?;
        check_finite(base, "actions", &chunk.actions, e.act_dim)?;
        check_finite(base, "rewards", &chunk.rewards, 1)?;
        check_finite(base, "costs", &chunk.costs, 1)?;

        let n = chunk.len();
        let mut numbering = Numbering {
            episode: Vec::with_capacity(n),
            step: Vec::with_capacity(n),
        };
        for i in 0..n {
            let row = base + i as u64;
            if let Some(ep) = &chunk.episode
                && ep[i] != self.episode
            {
                return Err(ValidationError::at(
                    row,
                    "episode",
                    format!(
                        "episode {} but the done flags make this episode {} (episodes are numbered from 0, \
                         one per terminal/timeout flag)",
                        ep[i], self.episode
                    ),
                ));
            }
            if let Some(st) = &chunk.step
                && st[i] != self.step
            {
                return Err(ValidationError::at(
                    row,
                    "step",
                    format!(
                        "step {} but expected {} (steps count 0, 1, 2, ... within each episode)",
                        st[i], self.step
                    ),
                ));
            }
            if self.step >= e.max_episode_steps {
                return Err(ValidationError::at(
                    row,
                    "terminals",
                    format!(
                        "episode {} starting at row {} runs past the task's horizon of {} steps without a \
                         terminal or timeout flag",
                        self.episode, self.open_start, e.max_episode_steps
                    ),
                ));
            }
            numbering.episode.push(self.episode);
            numbering.step.push(self.step);
            self.open_rewards.push(chunk.rewards[i]);
            self.open_costs.push(chunk.costs[i]);
            if chunk.is_done(i) {
                self.episodes.push(EpisodeSummary {
                    start: self.open_start,
                    length: self.step + 1,
                    reward_return: numpy_sum_f32(&self.open_rewards),
                    cost_return: numpy_sum_f32(&self.open_costs),
                });
                self.open_rewards.clear();
                self.open_costs.clear();
                self.episode = self
                    .episode
                    .checked_add(1)
                    .ok_or_else(|| ValidationError::at(row, "episode", "more than 2^32 - 1 episodes"))?;
                self.step = 0;
                self.open_start = row + 1;
            } else {
                self.step += 1;
            }
        }
        self.next_row += n as u64;
        Ok(numbering)
    }

    /// Ends the walk: every row must belong to a closed episode, and there must be at least one.
    pub fn finish(self) -> Result<Vec<EpisodeSummary>, ValidationError> {
        if self.step > 0 {
            return Err(ValidationError::at(
                self.open_start,
                "terminals",
                format!(
                    "the last {} transitions (rows {}..{}) are not closed by a terminal or timeout flag; every \
                     episode must end with one",
                    self.step,
                    self.open_start,
                    self.next_row - 1
                ),
            ));
        }
        if self.episodes.is_empty() {
            return Err(ValidationError::whole("the dataset has no transitions"));
        }
        Ok(self.episodes)
    }
}

/// Done flags stored as numbers (integers or floats) as booleans; anything but 0 or 1 is an error naming its row
/// (DSRL tests `== 1`, so a 2 would silently not end an episode there).
pub fn flags_from_numbers(
    first_row: u64,
    column: &str,
    values: impl IntoIterator<Item = f64>,
) -> Result<Vec<bool>, ValidationError> {
    values
        .into_iter()
        .enumerate()
        .map(|(i, v)| match v {
            0.0 => Ok(false),
            1.0 => Ok(true),
            other => Err(ValidationError::at(
                first_row + i as u64,
                column,
                format!("flag value {other}; expected 0 or 1"),
            )),
        })
        .collect()
}

fn check_finite(base: u64, column: &str, values: &[f32], width: usize) -> Result<(), ValidationError> {
    match values.iter().position(|v| !v.is_finite()) {
        None => Ok(()),
        Some(i) => {
            let row = base + (i / width) as u64;
            let name = if width == 1 {
                column.to_owned()
            } else {
                format!("{column}[{}]", i % width)
            };
            Err(ValidationError::at(
                row,
                name,
                format!("value {} is not finite", values[i]),
            ))
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const EXPECT: Expectation = Expectation {
        obs_dim: 2,
        act_dim: 1,
        max_episode_steps: 4,
    };

    /// Two episodes: lengths 3 (terminal) and 2 (timeout).
    fn chunk() -> TransitionChunk {
        let n = 5;
        TransitionChunk {
            obs_dim: 2,
            act_dim: 1,
            observations: vec![0.5; 2 * n],
            next_observations: vec![0.5; 2 * n],
            actions: vec![0.1; n],
            rewards: vec![1.0, 2.0, 3.0, 10.0, 20.0],
            costs: vec![0.0, 1.0, 0.0, 1.0, 1.0],
            terminals: vec![false, false, true, false, false],
            timeouts: vec![false, false, false, false, true],
            episode: None,
            step: None,
        }
    }

    #[test]
    fn numbers_episodes_and_builds_the_index() {
        let mut t = EpisodeTracker::new(EXPECT);
        let c = chunk();
        // Split across two chunks to check state carries over.
        let mut rest = c.clone();
        let head = rest.take_front(2);
        let a = t.check(&head).unwrap();
        let b = t.check(&rest).unwrap();
        assert_eq!([a.episode, b.episode].concat(), vec![0, 0, 0, 1, 1]);
        assert_eq!([a.step, b.step].concat(), vec![0, 1, 2, 0, 1]);
        let eps = t.finish().unwrap();
        assert_eq!(eps.len(), 2);
        assert_eq!(
            eps[0],
            EpisodeSummary {
                start: 0,
                length: 3,
                reward_return: 6.0,
                cost_return: 1.0
            }
        );
        assert_eq!(
            eps[1],
            EpisodeSummary {
                start: 3,
                length: 2,
                reward_return: 30.0,
                cost_return: 2.0
            }
        );
    }

    #[test]
    fn names_the_first_non_finite_value() {
        let mut c = chunk();
        c.next_observations[7] = f32::NAN;
        let err = EpisodeTracker::new(EXPECT).check(&c).unwrap_err();
        assert_eq!(err.row, Some(3));
        assert_eq!(err.column.as_deref(), Some("next_observations[1]"));
        assert!(
            err.to_string()
                .starts_with("row 3, column next_observations[1]: value NaN"),
            "{err}"
        );
        let mut c = chunk();
        c.costs[4] = f32::INFINITY;
        let err = EpisodeTracker::new(EXPECT).check(&c).unwrap_err();
        assert_eq!((err.row, err.column.as_deref()), (Some(4), Some("costs")));
    }

    #[test]
    fn rejects_unclosed_trailing_transitions() {
        let mut c = chunk();
        c.timeouts[4] = false;
        let mut t = EpisodeTracker::new(EXPECT);
        t.check(&c).unwrap();
        let err = t.finish().unwrap_err();
        assert_eq!(err.row, Some(3));
        assert!(err.message.contains("rows 3..4"), "{err}");
    }

    #[test]
    fn rejects_wrong_widths_steps_and_episodes() {
        let mut c = chunk();
        c.obs_dim = 3;
        assert_eq!(
            EpisodeTracker::new(EXPECT).check(&c).unwrap_err().column.as_deref(),
            Some("observations")
        );

        let mut c = chunk();
        c.step = Some(vec![0, 1, 3, 0, 1]);
        let err = EpisodeTracker::new(EXPECT).check(&c).unwrap_err();
        assert_eq!((err.row, err.column.as_deref()), (Some(2), Some("step")));

        let mut c = chunk();
        c.episode = Some(vec![0, 0, 0, 2, 2]);
        let err = EpisodeTracker::new(EXPECT).check(&c).unwrap_err();
        assert_eq!((err.row, err.column.as_deref()), (Some(3), Some("episode")));
    }

    #[test]
    fn rejects_episodes_longer_than_the_horizon() {
        let mut c = chunk();
        c.terminals[2] = false; // first episode now runs 5 steps > 4
        let err = EpisodeTracker::new(EXPECT).check(&c).unwrap_err();
        assert_eq!(err.row, Some(4));
        assert!(err.message.contains("horizon of 4"), "{err}");
    }

    #[test]
    fn rejects_empty_datasets() {
        let t = EpisodeTracker::new(EXPECT);
        assert!(t.finish().unwrap_err().message.contains("no transitions"));
    }
}
