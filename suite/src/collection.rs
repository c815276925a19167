//! Density control while collecting a dataset (spec §6.2) and the final processing grid filter (spec §6.4).
//!
//! Collection keeps every finished episode whose returns fall inside the recipe's ranges, and once the buffer holds
//! `filter_interval × max_trajectory` episodes it thins them back to `max_trajectory` with FSRL's grid filter, so
//! the kept episodes cover the (reward return, cost return) plane instead of piling up where the late, converged
//! policy lives. Randomness is CPython's `random` (MT19937) with an explicit seed, as in FSRL, so a recipe and
//! its seed decide the result.

use std::collections::HashMap;

use dsrl_pynumerics::numpy_math::floor_divide;
use dsrl_pynumerics::pyrandom::PyRandom;

/// The ranges and capacity of a trajectory buffer (FSRL `TrajectoryBuffer`).
#[derive(Debug, Clone, PartialEq)]
pub struct BufferLimits {
    /// Episodes kept after thinning.
    pub max_trajectory: usize,
    /// Thinning starts when the buffer holds `int(filter_interval * max_trajectory)` episodes; must exceed 1.
    pub filter_interval: f64,
    pub rmin: f64,
    pub rmax: f64,
    pub cmin: f64,
    pub cmax: f64,
}

/// A finished episode's returns with its payload (its transitions, or an index into them).
#[derive(Debug, Clone, PartialEq)]
pub struct Stored<T> {
    pub reward_return: f64,
    pub cost_return: f64,
    pub payload: T,
}

/// What happened to an episode offered to the buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Offer {
    /// Its returns fall outside the recipe's ranges.
    OutOfRange,
    Kept,
    /// Kept, and the buffer was then thinned back to `max_trajectory`.
    KeptAndThinned,
}

/// A buffer's counters and random state; with its episodes it is the whole buffer.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct BufferSnapshot {
    pub offered: u64,
    pub thinnings: u64,
    pub random_mt: Vec<u32>,
    pub random_index: usize,
}

pub struct TrajectoryBuffer<T> {
    limits: BufferLimits,
    threshold: usize,
    episodes: Vec<Stored<T>>,
    random: PyRandom,
    offered: u64,
    thinnings: u64,
}

impl<T> TrajectoryBuffer<T> {
    pub fn new(limits: BufferLimits, seed: u64) -> Result<TrajectoryBuffer<T>, String> {
        if limits.max_trajectory == 0 {
            return Err("max_trajectory must be at least 1".into());
        }
        if limits.filter_interval.is_nan() || limits.filter_interval <= 1.0 {
            return Err(format!(
                "filter_interval must be greater than 1, not {}",
                limits.filter_interval
            ));
        }
        let threshold = (limits.filter_interval * limits.max_trajectory as f64) as usize;
        Ok(TrajectoryBuffer {
            limits,
            threshold,
            episodes: Vec::new(),
            random: PyRandom::seed(seed),
            offered: 0,
            thinnings: 0,
        })
    }

    /// A buffer as [`TrajectoryBuffer::snapshot`] left it (resuming a collection).
    pub fn restore(
        limits: BufferLimits,
        snapshot: BufferSnapshot,
        episodes: Vec<Stored<T>>,
    ) -> Result<TrajectoryBuffer<T>, String> {
        let mut buffer = TrajectoryBuffer::new(limits, 0)?;
        buffer.random = PyRandom::from_state(&snapshot.random_mt, snapshot.random_index)
            .ok_or("the buffer's random state is malformed")?;
        buffer.episodes = episodes;
        buffer.offered = snapshot.offered;
        buffer.thinnings = snapshot.thinnings;
        Ok(buffer)
    }

    /// Everything but the episodes, for a checkpoint.
    pub fn snapshot(&self) -> BufferSnapshot {
        let (random_mt, random_index) = self.random.state();
        BufferSnapshot {
            offered: self.offered,
            thinnings: self.thinnings,
            random_mt,
            random_index,
        }
    }

    /// Offers a finished episode (FSRL `store` at the end of a trajectory).
    pub fn offer(&mut self, episode: Stored<T>) -> Offer {
        self.offered += 1;
        let l = &self.limits;
        let (r, c) = (episode.reward_return, episode.cost_return);
        if r > l.rmax || r < l.rmin || c > l.cmax || c < l.cmin {
            return Offer::OutOfRange;
        }
        self.episodes.push(episode);
        if self.episodes.len() > self.limits.max_trajectory && self.episodes.len() >= self.threshold {
            self.thin();
            return Offer::KeptAndThinned;
        }
        Offer::Kept
    }

    /// Thins to `max_trajectory` episodes, keeping their relative order (FSRL `apply_grid_filter`).
    fn thin(&mut self) {
        let points: Vec<(f64, f64)> = self.episodes.iter().map(|e| (e.reward_return, e.cost_return)).collect();
        let mut keep = vec![false; points.len()];
        for i in filter_points(&points, self.limits.max_trajectory, &mut self.random) {
            keep[i] = true;
        }
        let mut flags = keep.into_iter();
        self.episodes.retain(|_| flags.next().expect("one flag per episode"));
        self.thinnings += 1;
    }

    pub fn episodes(&self) -> &[Stored<T>] {
        &self.episodes
    }

    pub fn into_episodes(self) -> Vec<Stored<T>> {
        self.episodes
    }

    /// Episodes offered so far, and how many times the buffer was thinned.
    pub fn counts(&self) -> (u64, u64) {
        (self.offered, self.thinnings)
    }
}

/// The index of `value` in a grid starting at `low` with cells of `size` (NumPy float64 `//`, then `int`); a
/// zero-width range puts every point in cell 0, where FSRL would raise.
fn cell(value: f64, low: f64, size: f64) -> i64 {
    if size == 0.0 {
        0
    } else {
        floor_divide(value - low, size) as i64
    }
}

/// FSRL `TrajectoryBuffer.filter_points`: indices of up to `target` points spread over a ceil(sqrt(target))² grid
/// on (reward, cost). One point from each non-empty cell first (the last inserted), then points from randomly
/// chosen non-empty cells (`random.choice`) until `target` are kept.
pub fn filter_points(points: &[(f64, f64)], target: usize, random: &mut PyRandom) -> Vec<usize> {
    if points.is_empty() {
        return Vec::new();
    }
    let grid_size = (target as f64).sqrt().ceil();
    let range = |axis: fn(&(f64, f64)) -> f64| {
        let (lo, hi) = points
            .iter()
            .map(axis)
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| (lo.min(v), hi.max(v)));
        (lo, (hi - lo) / grid_size)
    };
    let (r_low, r_size) = range(|p| p.0);
    let (c_low, c_size) = range(|p| p.1);
    // An insertion-ordered map from cell to its points, like Python's defaultdict(list).
    let mut order: Vec<(i64, i64)> = Vec::new();
    let mut cells: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
    for (i, &(r, c)) in points.iter().enumerate() {
        let key = (cell(r, r_low, r_size), cell(c, c_low, c_size));
        cells.entry(key).or_insert_with(|| {
            order.push(key);
            Vec::new()
        });
        cells.get_mut(&key).expect("cell").push(i);
    }
    let mut kept = Vec::with_capacity(target);
    for key in &order {
        kept.push(cells.get_mut(key).expect("cell").pop().expect("non-empty cell"));
    }
    let mut non_empty: Vec<(i64, i64)> = order.iter().copied().filter(|k| !cells[k].is_empty()).collect();
    while kept.len() < target && !non_empty.is_empty() {
        let pick = random.randbelow(non_empty.len());
        let key = non_empty[pick];
        let members = cells.get_mut(&key).expect("cell");
        kept.push(members.pop().expect("non-empty cell"));
        if members.is_empty() {
            non_empty.remove(pick);
        }
    }
    kept.truncate(target);
    kept
}

/// The final processing grid filter of DSRL's `scripts/process_dataset.py` (spec §6.4): episodes outside
/// `[cmin, cmax] × [rmin, rmax]` are dropped; the rest fall into `(cbins + 1) × (rbins + 1)` cells (a point on
/// the upper edge gets its own cell, as in DSRL), and a cell with more than `npb` episodes keeps a `random.sample`
/// of `npb`. Unlike the density filter there is no `min_npb`: lone episodes stay. Returns the kept indices in
/// DSRL's output order (cells by first appearance).
#[derive(Debug, Clone, PartialEq)]
pub struct FinalGrid {
    pub cmin: f64,
    pub cmax: f64,
    pub rmin: f64,
    pub rmax: f64,
    pub cbins: u32,
    pub rbins: u32,
    pub npb: usize,
}

impl FinalGrid {
    /// DSRL's command-line defaults with the task's cost cap.
    pub fn dsrl_defaults(cost_cap: f64) -> FinalGrid {
        FinalGrid {
            cmin: 0.0,
            cmax: cost_cap,
            rmin: 0.0,
            rmax: 1000.0,
            cbins: 60,
            rbins: 50,
            npb: 1000,
        }
    }

    pub fn apply(&self, returns: &[(f64, f64)], random: &mut PyRandom) -> Vec<usize> {
        let cstep = (self.cmax - self.cmin) / f64::from(self.cbins);
        let rstep = (self.rmax - self.rmin) / f64::from(self.rbins);
        let mut order: Vec<(i64, i64)> = Vec::new();
        let mut cells: HashMap<(i64, i64), Vec<usize>> = HashMap::new();
        for (i, &(r, c)) in returns.iter().enumerate() {
            if c < self.cmin || c > self.cmax || r < self.rmin || r > self.rmax {
                continue;
            }
            let key = (cell(c, self.cmin, cstep), cell(r, self.rmin, rstep));
            cells.entry(key).or_insert_with(|| {
                order.push(key);
                Vec::new()
            });
            cells.get_mut(&key).expect("cell").push(i);
        }
        let mut kept = Vec::new();
        for key in &order {
            let members = &cells[key];
            if members.len() > self.npb {
                kept.extend(random.sample(members, self.npb));
            } else {
                kept.extend_from_slice(members);
            }
        }
        kept
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn limits(max_trajectory: usize) -> BufferLimits {
        BufferLimits {
            max_trajectory,
            filter_interval: 1.5,
            rmin: -10.0,
            rmax: 1000.0,
            cmin: 0.0,
            cmax: 100.0,
        }
    }

    #[test]
    fn out_of_range_episodes_are_refused() {
        let mut buffer = TrajectoryBuffer::new(limits(4), 0).unwrap();
        let offer = |r, c| Stored {
            reward_return: r,
            cost_return: c,
            payload: (),
        };
        assert_eq!(buffer.offer(offer(-11.0, 0.0)), Offer::OutOfRange);
        assert_eq!(buffer.offer(offer(5.0, 100.5)), Offer::OutOfRange);
        assert_eq!(buffer.offer(offer(5.0, 100.0)), Offer::Kept);
        assert_eq!(buffer.episodes().len(), 1);
        assert!(
            TrajectoryBuffer::<()>::new(
                BufferLimits {
                    filter_interval: 1.0,
                    ..limits(4)
                },
                0
            )
            .is_err()
        );
    }

    #[test]
    fn the_buffer_thins_at_the_threshold_and_keeps_order_and_spread() {
        // 90 episodes crowd one corner, 10 are spread out: thinning to 20 must keep every spread-out one that has a
        // grid cell of its own (episode 10 shares the crowd's cell of the final 5x5 grid, as FSRL would have it).
        let mut buffer = TrajectoryBuffer::new(limits(20), 7).unwrap();
        let mut thinned = 0;
        for i in 0..100u32 {
            let (r, c) = if i % 10 == 0 {
                (f64::from(i) * 9.0, f64::from(i))
            } else {
                (1.0 + f64::from(i) * 1e-3, 0.5)
            };
            if buffer.offer(Stored {
                reward_return: r,
                cost_return: c,
                payload: i,
            }) == Offer::KeptAndThinned
            {
                thinned += 1;
            }
            assert!(buffer.episodes().len() < 30, "never more than 1.5 x capacity");
        }
        assert!(thinned >= 1);
        let kept: Vec<u32> = buffer.episodes().iter().map(|e| e.payload).collect();
        assert!(kept.windows(2).all(|w| w[0] < w[1]), "relative order is kept: {kept:?}");
        for spread in [20, 30, 40, 50, 60, 70, 80, 90] {
            assert!(kept.contains(&spread), "{spread} was thinned away: {kept:?}");
        }
        assert_eq!(buffer.counts().0, 100);
    }

    #[test]
    fn a_restored_buffer_continues_exactly_like_the_original() {
        let episode = |i: u32| Stored {
            reward_return: f64::from(i * 37 % 101),
            cost_return: f64::from(i * 13 % 97),
            payload: i,
        };
        let mut original = TrajectoryBuffer::new(limits(10), 5).unwrap();
        for i in 0..23 {
            original.offer(episode(i));
        }
        assert!(original.counts().1 >= 1, "the snapshot must carry a used random state");
        let snapshot = original.snapshot();
        let mut restored =
            TrajectoryBuffer::restore(limits(10), snapshot.clone(), original.episodes().to_vec()).unwrap();
        assert_eq!(restored.snapshot(), snapshot);
        for i in 23..80 {
            assert_eq!(original.offer(episode(i)), restored.offer(episode(i)));
        }
        assert_eq!(original.episodes(), restored.episodes());
        let broken = BufferSnapshot {
            random_mt: vec![1, 2, 3],
            ..snapshot
        };
        assert!(TrajectoryBuffer::<u32>::restore(limits(10), broken, Vec::new()).is_err());
    }

    #[test]
    fn filter_points_matches_fsrl_by_hand() {
        // target 4 -> 2x2 grid over R in [0, 4], C in [0, 2]; cells: (0,0): 0,1  (1,1): 2  (2,2): 3 (the max point).
        let points = [(0.0, 0.0), (1.0, 0.5), (3.0, 1.5), (4.0, 2.0), (0.5, 0.2)];
        let mut random = PyRandom::seed(0);
        let kept = filter_points(&points, 4, &mut random);
        // One from each cell in first-appearance order, the last inserted of each: 4 (cell (0,0)), 2, 3; then one
        // more from the only non-empty cell left.
        assert_eq!(&kept[..3], &[4, 2, 3]);
        assert_eq!(kept.len(), 4);
        assert!(kept[3] == 1, "{kept:?}");
        // Identical points: a zero-width range puts everything in one cell instead of failing.
        let same = [(1.0, 1.0); 5];
        assert_eq!(filter_points(&same, 3, &mut PyRandom::seed(1)).len(), 3);
    }

    #[test]
    fn final_grid_drops_out_of_range_and_caps_cells() {
        let grid = FinalGrid {
            cmin: 0.0,
            cmax: 10.0,
            rmin: 0.0,
            rmax: 10.0,
            cbins: 2,
            rbins: 2,
            npb: 2,
        };
        let returns = [
            (1.0, 1.0),
            (1.5, 1.2),
            (1.2, 1.1),
            (9.0, 9.0),
            (11.0, 1.0),
            (5.0, -1.0),
            (10.0, 10.0),
        ];
        let kept = grid.apply(&returns, &mut PyRandom::seed(3));
        assert_eq!(kept.len(), 4, "{kept:?}"); // 2 of the crowded cell, the lone (9,9), the edge cell (10,10)
        assert!(!kept.contains(&4) && !kept.contains(&5));
        assert!(kept.contains(&3) && kept.contains(&6));
        assert_eq!(kept, grid.apply(&returns, &mut PyRandom::seed(3)), "seeded");
    }
}
