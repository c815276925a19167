//! CPython's `random` module, as far as DSRL's density filter uses it: `random.seed(int)` (MT19937 seeded with
//! `init_by_array` over the integer's 32-bit words), `getrandbits`, `_randbelow` and `random.sample`. Written from
//! the algorithms CPython documents (MT19937 reference implementation, `Lib/random.py`), checked against
//! CPython 3.11's outputs.

const N: usize = 624;
const M: usize = 397;

#[derive(Clone)]
pub struct PyRandom {
    mt: [u32; N],
    index: usize,
}

impl PyRandom {
    /// `random.seed(seed)` for a non-negative integer.
    pub fn seed(seed: u64) -> PyRandom {
        // CPython uses the absolute value's 32-bit words, least significant first; 0 gives [0].
        let key: Vec<u32> = if seed >> 32 == 0 {
            vec![seed as u32]
        } else {
            vec![seed as u32, (seed >> 32) as u32]
        };
        let mut r = PyRandom {
            mt: init_genrand(19_650_218),
            index: N,
        };
        r.init_by_array(&key);
        r
    }

    /// The generator's state (`random.getstate()` without the Gauss cache), for checkpoints.
    pub fn state(&self) -> (Vec<u32>, usize) {
        (self.mt.to_vec(), self.index)
    }

    /// A generator from [`PyRandom::state`]; `None` if the state is malformed.
    pub fn from_state(mt: &[u32], index: usize) -> Option<PyRandom> {
        Some(PyRandom {
            mt: mt.try_into().ok()?,
            index: if index <= N { index } else { return None },
        })
    }

    fn init_by_array(&mut self, key: &[u32]) {
        let mt = &mut self.mt;
        let (mut i, mut j) = (1usize, 0usize);
        for _ in 0..N.max(key.len()) {
            let prev = mt[i - 1] ^ (mt[i - 1] >> 30);
            mt[i] = (mt[i] ^ prev.wrapping_mul(1_664_525))
                .wrapping_add(key[j])
                .wrapping_add(j as u32);
            i += 1;
            j += 1;
            if i >= N {
                mt[0] = mt[N - 1];
                i = 1;
            }
            if j >= key.len() {
                j = 0;
            }
        }
        for _ in 0..N - 1 {
            let prev = mt[i - 1] ^ (mt[i - 1] >> 30);
            mt[i] = (mt[i] ^ prev.wrapping_mul(1_566_083_941)).wrapping_sub(i as u32);
            i += 1;
            if i >= N {
                mt[0] = mt[N - 1];
                i = 1;
            }
        }
        mt[0] = 0x8000_0000;
        self.index = N;
    }

    fn twist(&mut self) {
        let mt = &mut self.mt;
        for k in 0..N {
            let y = (mt[k] & 0x8000_0000) | (mt[(k + 1) % N] & 0x7fff_ffff);
            let mut v = mt[(k + M) % N] ^ (y >> 1);
            if y & 1 != 0 {
                v ^= 0x9908_b0df;
            }
            mt[k] = v;
        }
        self.index = 0;
    }

    pub fn next_u32(&mut self) -> u32 {
        if self.index >= N {
            self.twist();
        }
        let mut y = self.mt[self.index];
        self.index += 1;
        y ^= y >> 11;
        y ^= (y << 7) & 0x9d2c_5680;
        y ^= (y << 15) & 0xefc6_0000;
        y ^ (y >> 18)
    }

    /// `getrandbits(k)` for `1 <= k <= 32`.
    pub fn getrandbits(&mut self, k: u32) -> u32 {
        debug_assert!((1..=32).contains(&k));
        self.next_u32() >> (32 - k)
    }

    /// `_randbelow(n)`: uniform in `0..n` by rejection on `n.bit_length()` bits.
    pub fn randbelow(&mut self, n: usize) -> usize {
        debug_assert!(n >= 1 && n <= u32::MAX as usize);
        let k = usize::BITS - n.leading_zeros();
        loop {
            let r = self.getrandbits(k) as usize;
            if r < n {
                return r;
            }
        }
    }

    /// `random.sample(population, k)` with CPython's choice between the pool method and the set method.
    pub fn sample<T: Clone>(&mut self, population: &[T], k: usize) -> Vec<T> {
        let n = population.len();
        assert!(k <= n, "sample larger than population");
        let mut setsize = 21usize;
        if k > 5 {
            // 4 ** ceil(log(k * 3, 4)), with CPython's floating-point log.
            let exponent = (((k * 3) as f64).ln() / 4f64.ln()).ceil() as u32;
            setsize += 4usize.pow(exponent);
        }
        let mut result = Vec::with_capacity(k);
        if n <= setsize {
            let mut pool = population.to_vec();
            for i in 0..k {
                let j = self.randbelow(n - i);
                result.push(pool[j].clone());
                pool[j] = pool[n - i - 1].clone();
            }
        } else {
            let mut selected = std::collections::HashSet::with_capacity(k);
            for _ in 0..k {
                let mut j = self.randbelow(n);
                while selected.contains(&j) {
                    j = self.randbelow(n);
                }
                selected.insert(j);
                result.push(population[j].clone());
            }
        }
        result
    }
}

fn init_genrand(s: u32) -> [u32; N] {
    let mut mt = [0u32; N];
    mt[0] = s;
    for i in 1..N {
        mt[i] = 1_812_433_253u32
            .wrapping_mul(mt[i - 1] ^ (mt[i - 1] >> 30))
            .wrapping_add(i as u32);
    }
    mt
}

#[cfg(test)]
mod tests {
    use super::*;

    // Expected values printed by CPython 3.11.7.
    #[test]
    fn matches_cpython_getrandbits() {
        let mut r = PyRandom::seed(0);
        let got: Vec<u32> = (0..3).map(|_| r.getrandbits(32)).collect();
        assert_eq!(got, [3626764237, 1654615998, 3255389356]);
        // random.seed(12345678901234567890): two 32-bit key words.
        let mut r = PyRandom::seed(12345678901234567890);
        assert_eq!([r.getrandbits(32), r.getrandbits(32)], [2199100970, 3695432519]);
    }

    #[test]
    fn matches_cpython_sample_pool_and_set_methods() {
        let mut r = PyRandom::seed(3);
        let hundred: Vec<u32> = (0..100).collect();
        assert_eq!(r.sample(&hundred, 5), [30, 75, 69, 16, 47]); // set method (100 > 21)
        let ten: Vec<u32> = (0..10).collect();
        assert_eq!(r.sample(&ten, 7), [9, 7, 1, 4, 0, 3, 2]); // pool method
        let mut r = PyRandom::seed(3);
        let thousand: Vec<u32> = (0..1000).collect();
        assert_eq!(
            r.sample(&thousand, 20),
            [
                243, 606, 557, 133, 378, 937, 618, 485, 640, 594, 67, 620, 13, 930, 857, 480, 265, 564, 239, 196
            ]
        );
    }
}
