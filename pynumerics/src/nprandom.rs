//! NumPy's `Generator(PCG64(seed))`, as far as DSRL's outlier and observation-noise filters use it: SeedSequence
//! seeding, PCG64 (XSL-RR 128/64) with NumPy's buffered 32-bit draws, bounded integers by Lemire's method,
//! `Generator.choice` with and without replacement (Floyd's algorithm or a tail shuffle, then a shuffle), and
//! ziggurat normals. Written from the published algorithms; checked bit for bit against NumPy 1.24.

use super::ziggurat_tables::{FI, KI, WI, ZIGGURAT_NOR_R};

/// SeedSequence(entropy).generate_state(n, uint64) for a non-negative integer entropy.
pub fn seed_sequence_u64(entropy: u64, n_words: usize) -> Vec<u64> {
    const INIT_A: u32 = 0x43b0_d7e5;
    const MULT_A: u32 = 0x931e_8875;
    const INIT_B: u32 = 0x8b51_f9dd;
    const MULT_B: u32 = 0x58f3_8ded;
    const MIX_MULT_L: u32 = 0xca01_f9dd;
    const MIX_MULT_R: u32 = 0x4973_f715;
    const POOL_SIZE: usize = 4;
    let entropy_words: Vec<u32> = if entropy >> 32 == 0 {
        vec![entropy as u32]
    } else {
        vec![entropy as u32, (entropy >> 32) as u32]
    };
    let mut hash_const = INIT_A;
    let mut hashmix = |value: u32| {
        let mut v = value ^ hash_const;
        hash_const = hash_const.wrapping_mul(MULT_A);
        v = v.wrapping_mul(hash_const);
        v ^ (v >> 16)
    };
    let mix = |x: u32, y: u32| {
        let r = MIX_MULT_L.wrapping_mul(x).wrapping_sub(MIX_MULT_R.wrapping_mul(y));
        r ^ (r >> 16)
    };
    let mut pool = [0u32; POOL_SIZE];
    for (i, slot) in pool.iter_mut().enumerate() {
        *slot = hashmix(entropy_words.get(i).copied().unwrap_or(0));
    }
    for src in 0..POOL_SIZE {
        for dst in 0..POOL_SIZE {
            if src != dst {
                let h = hashmix(pool[src]);
                pool[dst] = mix(pool[dst], h);
            }
        }
    }
    // Entropy beyond the pool size (never more than 2 words here) would be mixed in now.
    let mut hash_b = INIT_B;
    let words: Vec<u32> = (0..2 * n_words)
        .map(|i| {
            let mut v = pool[i % POOL_SIZE] ^ hash_b;
            hash_b = hash_b.wrapping_mul(MULT_B);
            v = v.wrapping_mul(hash_b);
            v ^ (v >> 16)
        })
        .collect();
    words.chunks(2).map(|p| p[0] as u64 | (p[1] as u64) << 32).collect()
}

const PCG_MULT: u128 = 0x2360_ED05_1FC6_5DA4_4385_DF64_9FCC_F645;

/// NumPy's PCG64 bit generator.
#[derive(Debug, Clone)]
pub struct Pcg64 {
    state: u128,
    inc: u128,
    /// NumPy hands out 64-bit draws in two 32-bit halves.
    spare_u32: Option<u32>,
}

impl Pcg64 {
    /// `PCG64(seed)`.
    pub fn new(seed: u64) -> Pcg64 {
        let w = seed_sequence_u64(seed, 4);
        let initstate = (w[0] as u128) << 64 | w[1] as u128;
        let initseq = (w[2] as u128) << 64 | w[3] as u128;
        let mut rng = Pcg64 {
            state: 0,
            inc: (initseq << 1) | 1,
            spare_u32: None,
        };
        rng.step();
        rng.state = rng.state.wrapping_add(initstate);
        rng.step();
        rng
    }

    fn step(&mut self) {
        self.state = self.state.wrapping_mul(PCG_MULT).wrapping_add(self.inc);
    }

    pub fn next_u64(&mut self) -> u64 {
        self.step();
        let s = self.state;
        ((s >> 64) as u64 ^ s as u64).rotate_right((s >> 122) as u32)
    }

    pub fn next_u32(&mut self) -> u32 {
        if let Some(v) = self.spare_u32.take() {
            return v;
        }
        let next = self.next_u64();
        self.spare_u32 = Some((next >> 32) as u32);
        next as u32
    }

    /// Uniform in [0, 1) with 53 random bits.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / 9_007_199_254_740_992.0)
    }
}

/// `numpy.random.Generator` over PCG64.
#[derive(Debug, Clone)]
pub struct NumpyGenerator {
    bits: Pcg64,
}

impl NumpyGenerator {
    /// `Generator(PCG64(seed))`.
    pub fn new(seed: u64) -> NumpyGenerator {
        NumpyGenerator { bits: Pcg64::new(seed) }
    }

    /// A uniform integer in `0..=rng` (NumPy's `random_bounded_uint64` without masking).
    pub fn bounded(&mut self, rng: u64) -> u64 {
        if rng == 0 {
            0
        } else if rng <= u32::MAX as u64 {
            if rng == u32::MAX as u64 {
                return self.bits.next_u32() as u64;
            }
            // Lemire's method on 32-bit draws.
            let rng = rng as u32;
            let excl = rng.wrapping_add(1);
            let mut m = self.bits.next_u32() as u64 * excl as u64;
            let mut leftover = m as u32;
            if leftover < excl {
                let threshold = (u32::MAX - rng) % excl;
                while leftover < threshold {
                    m = self.bits.next_u32() as u64 * excl as u64;
                    leftover = m as u32;
                }
            }
            m >> 32
        } else if rng == u64::MAX {
            self.bits.next_u64()
        } else {
            let excl = rng + 1;
            let mut m = self.bits.next_u64() as u128 * excl as u128;
            let mut leftover = m as u64;
            if leftover < excl {
                let threshold = (u64::MAX - rng) % excl;
                while leftover < threshold {
                    m = self.bits.next_u64() as u128 * excl as u128;
                    leftover = m as u64;
                }
            }
            (m >> 64) as u64
        }
    }

    /// `integers(low, high, size=n)` with `high` exclusive.
    pub fn integers(&mut self, low: i64, high: i64, n: usize) -> Vec<i64> {
        assert!(high > low, "integers: empty range");
        let rng = (high - 1 - low) as u64;
        (0..n).map(|_| low.wrapping_add(self.bounded(rng) as i64)).collect()
    }

    /// Positions drawn by `choice(a, size=n)` (with replacement) for a population of `pop` items.
    pub fn choice_with_replacement(&mut self, pop: usize, n: usize) -> Vec<usize> {
        self.integers(0, pop as i64, n)
            .into_iter()
            .map(|v| v as usize)
            .collect()
    }

    /// Positions drawn by `choice(a, size=n, replace=False)` (shuffle=True) for a population of `pop` items.
    pub fn choice_without_replacement(&mut self, pop: usize, n: usize) -> Vec<usize> {
        assert!(
            n <= pop,
            "cannot take a larger sample than the population without replacement"
        );
        let mut idx: Vec<i64>;
        if pop > 10_000 && n > pop / 50 {
            // Tail shuffle: shuffle the last n slots of 0..pop.
            idx = (0..pop as i64).collect();
            self.shuffle(&mut idx, (pop - n).max(1));
            idx.drain(..pop - n);
        } else {
            // Floyd's algorithm: only membership in the set matters for the result.
            idx = Vec::with_capacity(n);
            let mut chosen = std::collections::HashSet::with_capacity(n);
            for j in (pop - n)..pop {
                let val = self.bounded(j as u64) as i64;
                let pick = if chosen.contains(&val) { j as i64 } else { val };
                chosen.insert(pick);
                idx.push(pick);
            }
            self.shuffle(&mut idx, 1);
        }
        idx.into_iter().map(|v| v as usize).collect()
    }

    /// NumPy's `_shuffle_int`: Fisher-Yates over positions `n-1` down to `first`.
    fn shuffle(&mut self, data: &mut [i64], first: usize) {
        for i in (first..data.len()).rev() {
            let j = self.bounded(i as u64) as usize;
            data.swap(i, j);
        }
    }

    /// `standard_normal()`: the 256-layer ziggurat NumPy uses.
    pub fn standard_normal(&mut self) -> f64 {
        loop {
            let mut r = self.bits.next_u64();
            let idx = (r & 0xff) as usize;
            r >>= 8;
            let sign = r & 1;
            let rabs = (r >> 1) & 0x000f_ffff_ffff_ffff;
            let mut x = rabs as f64 * f64::from_bits(WI[idx]);
            if sign & 1 == 1 {
                x = -x;
            }
            if rabs < KI[idx] {
                return x;
            }
            if idx == 0 {
                let inv_r = 1.0 / ZIGGURAT_NOR_R;
                loop {
                    let xx = -inv_r * (-self.bits.next_f64()).ln_1p();
                    let yy = -(-self.bits.next_f64()).ln_1p();
                    if yy + yy > xx * xx {
                        return if (rabs >> 8) & 1 == 1 {
                            -(ZIGGURAT_NOR_R + xx)
                        } else {
                            ZIGGURAT_NOR_R + xx
                        };
                    }
                }
            } else {
                let (f_prev, f) = (f64::from_bits(FI[idx - 1]), f64::from_bits(FI[idx]));
                if (f_prev - f) * self.bits.next_f64() + f < (-0.5 * x * x).exp() {
                    return x;
                }
            }
        }
    }

    /// `normal(loc, scale)`.
    pub fn normal(&mut self, loc: f64, scale: f64) -> f64 {
        loc + scale * self.standard_normal()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    // Expected values printed by NumPy 1.24.4.
    #[test]
    fn seed_sequence_and_pcg64_match_numpy() {
        assert_eq!(
            seed_sequence_u64(1234, 4),
            [
                0x5f83044cad3f26a6,
                0xa0d9b3700cea3a6f,
                0xa8647d8b1e3e7527,
                0x687a8e7300372192
            ]
        );
        let mut bits = Pcg64::new(1234);
        assert_eq!(
            [bits.next_u64(), bits.next_u64(), bits.next_u64()],
            [0xfa08fef3fab6bbba, 0x615481f7fce9ac81, 0xec59dd7c2bde3cb4]
        );
        let mut bits = Pcg64::new(1234);
        assert_eq!(
            [bits.next_u32(), bits.next_u32(), bits.next_u32()],
            [4206279610, 4194893555, 4243172481]
        );
        let mut bits = Pcg64::new(1234);
        assert_eq!(bits.next_f64(), 0.9766997666981422);
    }

    #[test]
    fn integers_and_choice_match_numpy() {
        assert_eq!(
            NumpyGenerator::new(1234).integers(0, 10, 10),
            [9, 9, 9, 3, 1, 9, 1, 2, 1, 3]
        );
        assert_eq!(
            NumpyGenerator::new(1234).choice_without_replacement(100, 7),
            [36, 16, 91, 95, 10, 92, 94]
        );
        assert_eq!(
            NumpyGenerator::new(1234).choice_with_replacement(15, 7),
            [14, 14, 14, 5, 2, 13, 1]
        );
    }

    #[test]
    fn normals_match_numpy() {
        let mut g = NumpyGenerator::new(1234);
        let got: Vec<f64> = (0..5).map(|_| g.standard_normal()).collect();
        assert_eq!(
            got,
            [
                -1.6038368053963015,
                0.06409991400376411,
                0.7408912958767259,
                0.15261919356565307,
                0.8637438913233318
            ]
        );
    }
}
