//! The seeded random numbers of training: SplitMix64, uniform and standard-normal draws. Its whole state is one
//! `u64`, so a checkpoint can record it and a resumed run draws the same numbers.

use serde::{Deserialize, Serialize};

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Noise {
    state: u64,
}

impl Noise {
    pub fn seeded(seed: u64) -> Noise {
        Noise { state: seed }
    }

    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in the open interval (0, 1).
    pub fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 0.5) / (1u64 << 53) as f64
    }

    /// A standard normal draw (Box–Muller; the second value of each pair is not kept, which keeps the state one
    /// integer).
    pub fn normal(&mut self) -> f64 {
        let (u1, u2) = (self.uniform(), self.uniform());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }

    pub fn normals_f32(&mut self, n: usize) -> Vec<f32> {
        (0..n).map(|_| self.normal() as f32).collect()
    }

    /// Which of `n` elements a dropout of probability `p` keeps: an element is dropped when its uniform draw is below
    /// `p`, compared in integers: the draw is `((u >> 11) + 0.5) / 2⁵³`, so it is below `p` exactly when `u >> 11` is
    /// below `⌈p·2⁵³ − 0.5⌉`. One draw per element, in order.
    pub fn dropout_keep(&mut self, n: usize, p: f64) -> Vec<bool> {
        let below = (p * (1u64 << 53) as f64 - 0.5).ceil() as u64;
        (0..n).map(|_| (self.next_u64() >> 11) >= below).collect()
    }

    /// A uniformly random permutation of `0..n` (Fisher–Yates).
    pub fn permutation(&mut self, n: usize) -> Vec<u32> {
        let mut p: Vec<u32> = (0..n as u32).collect();
        for i in (1..n).rev() {
            let j = (self.next_u64() % (i as u64 + 1)) as usize;
            p.swap(i, j);
        }
        p
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_draws_have_unit_moments_and_repeat_with_the_seed() {
        let mut a = Noise::seeded(7);
        let xs: Vec<f64> = (0..200_000).map(|_| a.normal()).collect();
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64;
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.01, "variance {var}");
        let mut b = Noise::seeded(7);
        assert_eq!(b.normal(), xs[0]);
        let mut c = Noise::seeded(8);
        assert_ne!(c.normal(), xs[0]);
    }

    #[test]
    fn permutation_holds_every_index_once() {
        let mut p = Noise::seeded(3).permutation(1000);
        assert_ne!(p[..10], (0..10).collect::<Vec<u32>>()[..]);
        p.sort_unstable();
        assert_eq!(p, (0..1000).collect::<Vec<u32>>());
    }
}
