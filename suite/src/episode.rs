//! Episode summaries (start row, length, reward and cost return) and the float32 summation NumPy uses, so the
//! returns we publish are the bit-exact returns DSRL computes with `np.sum` on the same float32 slices.

use serde::{Deserialize, Serialize};

/// One episode (trajectory) of a dataset, as listed in the manifest's episode index. Filters and plots work from
/// this index alone, without reading observations.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EpisodeSummary {
    /// Row of the episode's first transition in the Parquet file.
    pub start: u64,
    /// Number of transitions.
    pub length: u32,
    /// Undiscounted sum of rewards, float32 pairwise as `np.sum`.
    pub reward_return: f32,
    /// Undiscounted sum of costs, float32 pairwise as `np.sum`.
    pub cost_return: f32,
}

pub use dsrl_pynumerics::numpy_math::numpy_sum_f32;

/// The smallest and largest value of an iterator of returns; `None` when empty.
pub fn return_range(values: impl Iterator<Item = f32>) -> Option<(f32, f32)> {
    values.fold(None, |acc, v| match acc {
        None => Some((v, v)),
        Some((lo, hi)) => Some((lo.min(v), hi.max(v))),
    })
}

/// What happened to one input episode (for plots).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Fate {
    Kept,
    Relabelled,
    RemovedByDensity,
    RemovedByInpaint,
    RemovedByEpsilon,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn short_arrays_sum_sequentially() {
        assert_eq!(numpy_sum_f32(&[]), 0.0);
        assert_eq!(numpy_sum_f32(&[1.0, 2.0, 3.5]), 6.5);
    }

    #[test]
    fn pairwise_order_differs_from_sequential_where_numpy_does() {
        // 1e8 absorbs small addends when added sequentially in f32; pairwise blocks keep them.
        let mut values = vec![1.0f32; 16];
        values[0] = 1e8;
        let sequential: f32 = values.iter().sum();
        assert_eq!(sequential, 1e8);
        // NumPy 1.24.4: v = np.ones(16, np.float32); v[0] = 1e8; np.sum(v) == 100000008 (repr 100000010.0).
        assert_eq!(numpy_sum_f32(&values), 100_000_008.0);
    }

    #[test]
    fn matches_values_numpy_1_24_printed() {
        // Reference: python -c "import numpy as np; a=(np.arange(300,dtype=np.float32)*np.float32(0.1)); print(repr(np.sum(a)))"
        let values: Vec<f32> = (0..300).map(|i| i as f32 * 0.1f32).collect();
        assert_eq!(numpy_sum_f32(&values), 4485.0f32);
    }

    #[test]
    fn ranges() {
        assert_eq!(return_range([3.0f32, -1.0, 2.0].into_iter()), Some((-1.0, 3.0)));
        assert_eq!(return_range(std::iter::empty()), None);
    }
}
