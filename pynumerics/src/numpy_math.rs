//! The few NumPy 1.24 numerics the filters depend on, reproduced exactly: float floor division (`npy_divmod`),
//! `np.sum` of a float32 array (pairwise within 8192-element buffer blocks), and `np.std` of a float32 array.

/// Python/NumPy `a // b` for floats (`npy_divmod`): the floor of the true quotient, computed via `fmod` so it is
/// exact where `(a / b).floor()` would round across an integer.
pub fn floor_divide(a: f64, b: f64) -> f64 {
    let modulo = a % b; // C fmod
    if b == 0.0 {
        return a / b;
    }
    let mut div = (a - modulo) / b;
    if modulo != 0.0 && ((b < 0.0) != (modulo < 0.0)) {
        div -= 1.0;
    }
    if div != 0.0 {
        let floordiv = div.floor();
        if div - floordiv > 0.5 { floordiv + 1.0 } else { floordiv }
    } else {
        (0.0f64).copysign(a / b)
    }
}

/// NumPy's reduction buffer size: reductions over more than one axis run in blocks of this many elements.
const BUFFER: usize = 8192;

/// `np.sum(a)` of a float32 array with more than one dimension (C order): each 8192-element block is summed
/// pairwise, blocks are accumulated in order, all in float32.
pub fn numpy_sum_f32_nd(values: &[f32]) -> f32 {
    let mut total = 0.0f32;
    for block in values.chunks(BUFFER) {
        total += numpy_sum_f32(block);
    }
    total
}

/// `np.std(a)` of a float32 array with more than one dimension, as NumPy 1.24's `_var` computes it: the mean in
/// float32 (sum / count), squared deviations in float32, their sum, then `float32(sum / count)` where that
/// division happens in float64 (a NumPy float32 scalar divided by a Python int), then a float32 square root.
pub fn numpy_std_f32_nd(values: &[f32]) -> f32 {
    let count = values.len();
    let mean = numpy_sum_f32_nd(values) / count as f32;
    let squares: Vec<f32> = values.iter().map(|&v| (v - mean) * (v - mean)).collect();
    let sum = numpy_sum_f32_nd(&squares);
    let variance = (sum as f64 / count as f64) as f32;
    variance.sqrt()
}

/// `np.sum` of a contiguous float32 array as NumPy 1.24 computes it: pairwise summation with 8 accumulators
/// in blocks of at most 128 elements, every operation in float32.
pub fn numpy_sum_f32(values: &[f32]) -> f32 {
    let n = values.len();
    if n < 8 {
        let mut sum = 0.0f32;
        for &v in values {
            sum += v;
        }
        sum
    } else if n <= 128 {
        let mut r = [0.0f32; 8];
        r.copy_from_slice(&values[..8]);
        let whole = n - n % 8;
        let mut i = 8;
        while i < whole {
            for j in 0..8 {
                r[j] += values[i + j];
            }
            i += 8;
        }
        let mut sum = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]));
        for &v in &values[whole..] {
            sum += v;
        }
        sum
    } else {
        let mut half = n / 2;
        half -= half % 8;
        numpy_sum_f32(&values[..half]) + numpy_sum_f32(&values[half..])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_division_is_pythons() {
        assert_eq!(floor_divide(7.0, 2.0), 3.0);
        assert_eq!(floor_divide(-7.0, 2.0), -4.0);
        assert_eq!(floor_divide(7.0, -2.0), -4.0);
        assert_eq!(floor_divide(0.0, 3.0), 0.0);
        assert!(floor_divide(-0.0, 3.0).is_sign_negative());
        // Python: 1.0 // 0.1 == 9.0 although 1.0 / 0.1 == 10.0.
        assert_eq!(1.0f64 / 0.1, 10.0);
        assert_eq!(floor_divide(1.0, 0.1), 9.0);
        // Python: 0.3 // 0.1 == 2.0
        assert_eq!(floor_divide(0.3, 0.1), 2.0);
    }
}
