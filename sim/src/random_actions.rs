//! Seeded uniform actions inside an action box, for clients that step simulators with random actions (the
//! benchmark, the tests). SplitMix64: dependency-free and the same stream for the same seed everywhere.

pub struct UniformActions {
    state: u64,
}

impl UniformActions {
    pub fn new(seed: u64) -> UniformActions {
        UniformActions { state: seed }
    }

    fn next_unit(&mut self) -> f64 {
        self.state = self.state.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.state;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
    }

    /// `n` rows of actions, row-major `[n * low.len()]`, each component uniform in `[low, high]`.
    pub fn batch(&mut self, low: &[f64], high: &[f64], n: usize) -> Vec<f32> {
        let mut out = Vec::with_capacity(n * low.len());
        for _ in 0..n {
            for (l, h) in low.iter().zip(high) {
                out.push((l + (h - l) * self.next_unit()) as f32);
            }
        }
        out
    }
}
