//! A chunk of consecutive transitions in columnar form: the unit that flows from a reader (HDF5 or Parquet)
//! through validation into the canonical Parquet writer, so no stage ever holds a whole dataset in memory.

/// Consecutive rows of a dataset. Matrices are row-major: row `i` of `observations` is
/// `observations[i * obs_dim..(i + 1) * obs_dim]`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TransitionChunk {
    pub obs_dim: usize,
    pub act_dim: usize,
    pub observations: Vec<f32>,
    pub next_observations: Vec<f32>,
    pub actions: Vec<f32>,
    pub rewards: Vec<f32>,
    pub costs: Vec<f32>,
    pub terminals: Vec<bool>,
    pub timeouts: Vec<bool>,
    /// Episode number of each row, when the source had such a column (checked, never trusted).
    pub episode: Option<Vec<u32>>,
    /// Step within the episode of each row, when the source had such a column (checked, never trusted).
    pub step: Option<Vec<u32>>,
}

impl TransitionChunk {
    pub fn empty(obs_dim: usize, act_dim: usize) -> Self {
        TransitionChunk {
            obs_dim,
            act_dim,
            ..Default::default()
        }
    }

    pub fn len(&self) -> usize {
        self.rewards.len()
    }

    pub fn is_empty(&self) -> bool {
        self.rewards.is_empty()
    }

    /// Whether every column has `len()` rows of the declared widths.
    pub fn is_consistent(&self) -> bool {
        let n = self.len();
        self.observations.len() == n * self.obs_dim
            && self.next_observations.len() == n * self.obs_dim
            && self.actions.len() == n * self.act_dim
            && self.costs.len() == n
            && self.terminals.len() == n
            && self.timeouts.len() == n
            && self.episode.as_ref().is_none_or(|e| e.len() == n)
            && self.step.as_ref().is_none_or(|s| s.len() == n)
    }

    /// Appends all rows of `other` (same widths). Source episode/step columns are dropped: only validated,
    /// freshly numbered rows are appended by the writer.
    pub fn append(&mut self, other: &TransitionChunk) {
        debug_assert_eq!((self.obs_dim, self.act_dim), (other.obs_dim, other.act_dim));
        self.observations.extend_from_slice(&other.observations);
        self.next_observations.extend_from_slice(&other.next_observations);
        self.actions.extend_from_slice(&other.actions);
        self.rewards.extend_from_slice(&other.rewards);
        self.costs.extend_from_slice(&other.costs);
        self.terminals.extend_from_slice(&other.terminals);
        self.timeouts.extend_from_slice(&other.timeouts);
    }

    /// Removes and returns the first `n` rows.
    pub fn take_front(&mut self, n: usize) -> TransitionChunk {
        fn front<T>(v: &mut Vec<T>, k: usize) -> Vec<T> {
            let rest = v.split_off(k);
            let mut front = std::mem::replace(v, rest);
            // The front keeps the whole vector's allocation otherwise: splitting a file into its episodes would
            // hold one full-size buffer per episode.
            front.shrink_to_fit();
            front
        }
        TransitionChunk {
            obs_dim: self.obs_dim,
            act_dim: self.act_dim,
            observations: front(&mut self.observations, n * self.obs_dim),
            next_observations: front(&mut self.next_observations, n * self.obs_dim),
            actions: front(&mut self.actions, n * self.act_dim),
            rewards: front(&mut self.rewards, n),
            costs: front(&mut self.costs, n),
            terminals: front(&mut self.terminals, n),
            timeouts: front(&mut self.timeouts, n),
            episode: self.episode.as_mut().map(|e| front(e, n)),
            step: self.step.as_mut().map(|s| front(s, n)),
        }
    }

    /// A copy of rows `start..start + n`.
    pub fn rows(&self, start: usize, n: usize) -> TransitionChunk {
        let (o, a) = (self.obs_dim, self.act_dim);
        TransitionChunk {
            obs_dim: o,
            act_dim: a,
            observations: self.observations[start * o..(start + n) * o].to_vec(),
            next_observations: self.next_observations[start * o..(start + n) * o].to_vec(),
            actions: self.actions[start * a..(start + n) * a].to_vec(),
            rewards: self.rewards[start..start + n].to_vec(),
            costs: self.costs[start..start + n].to_vec(),
            terminals: self.terminals[start..start + n].to_vec(),
            timeouts: self.timeouts[start..start + n].to_vec(),
            episode: self.episode.as_ref().map(|e| e[start..start + n].to_vec()),
            step: self.step.as_ref().map(|s| s[start..start + n].to_vec()),
        }
    }

    /// Whether row `i` ends an episode (terminal or time-limit truncation), DSRL's split rule.
    pub fn is_done(&self, i: usize) -> bool {
        self.terminals[i] || self.timeouts[i]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn chunk(n: usize) -> TransitionChunk {
        TransitionChunk {
            obs_dim: 2,
            act_dim: 1,
            observations: (0..2 * n).map(|v| v as f32).collect(),
            next_observations: (0..2 * n).map(|v| v as f32 + 0.5).collect(),
            actions: (0..n).map(|v| v as f32).collect(),
            rewards: (0..n).map(|v| v as f32).collect(),
            costs: vec![0.0; n],
            terminals: vec![false; n],
            timeouts: (0..n).map(|i| i + 1 == n).collect(),
            episode: None,
            step: None,
        }
    }

    #[test]
    fn take_front_splits_every_column() {
        let mut c = chunk(5);
        let head = c.take_front(2);
        assert!(head.is_consistent() && c.is_consistent());
        assert_eq!(head.len(), 2);
        assert_eq!(c.len(), 3);
        assert_eq!(head.observations, vec![0.0, 1.0, 2.0, 3.0]);
        // The head does not keep the whole chunk's allocation (splitting a file into episodes once held one
        // full-size buffer per episode and ran out of memory).
        assert!(
            head.observations.capacity() < 10,
            "capacity {}",
            head.observations.capacity()
        );
        assert_eq!(c.observations[0], 4.0);
        assert!(c.is_done(2));
        let mut joined = head.clone();
        joined.append(&c);
        assert_eq!(joined, chunk(5));
    }
}
