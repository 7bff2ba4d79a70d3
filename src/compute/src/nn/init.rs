//! Seeded deterministic random numbers and the PyTorch-default layer initialisation.
//!
//! PyTorch's `nn.Linear` draws its weight with `kaiming_uniform_(a = sqrt(5))`, whose bound
//! `gain * sqrt(3 / fan_in)` with `gain = sqrt(2 / (1 + a^2))` simplifies to
//! `1 / sqrt(fan_in)`, and its bias from the same `U(-1/sqrt(fan_in), 1/sqrt(fan_in))`.
//! The random stream is ours (xoshiro256** seeded through SplitMix64), not PyTorch's, so
//! values match in distribution, not bit for bit.

use super::scalar::NnScalar;

/// xoshiro256** with SplitMix64 seeding: small, fast, and the same stream on every platform.
#[derive(Clone, Debug)]
pub struct Rng {
    state: [u64; 4],
}

impl Rng {
    /// A generator whose whole stream is determined by `seed`.
    pub fn new(seed: u64) -> Self {
        let mut splitmix = seed;
        let mut next = || {
            splitmix = splitmix.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = splitmix;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            z ^ (z >> 31)
        };
        Rng {
            state: [next(), next(), next(), next()],
        }
    }

    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.state;
        let result = s[1].wrapping_mul(5).rotate_left(7).wrapping_mul(9);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[low, high)`.
    pub fn uniform(&mut self, low: f64, high: f64) -> f64 {
        low + (high - low) * self.next_f64()
    }
}

/// Fills `values` with independent draws from `U(-bound, bound)`.
pub fn uniform_fill<T: NnScalar>(rng: &mut Rng, values: &mut [T], bound: f64) {
    for value in values {
        *value = T::from_f64(rng.uniform(-bound, bound));
    }
}

/// PyTorch-default `nn.Linear` initialisation of an `in x out` weight and its bias:
/// both `U(-1/sqrt(in), 1/sqrt(in))`, weight first, then bias.
pub fn kaiming_uniform<T: NnScalar>(
    rng: &mut Rng,
    in_features: usize,
    weight: &mut [T],
    bias: &mut [T],
) {
    let bound = 1.0 / (in_features.max(1) as f64).sqrt();
    uniform_fill(rng, weight, bound);
    uniform_fill(rng, bias, bound);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stream_is_deterministic_and_seed_dependent() {
        let a: Vec<u64> = (0..4)
            .map({
                let mut rng = Rng::new(42);
                move |_| rng.next_u64()
            })
            .collect();
        let b: Vec<u64> = (0..4)
            .map({
                let mut rng = Rng::new(42);
                move |_| rng.next_u64()
            })
            .collect();
        let c = Rng::new(43).next_u64();
        assert_eq!(a, b);
        assert_ne!(a[0], c);
    }

    #[test]
    fn uniform_moments_match_closed_form() {
        // U(-1, 1): mean 0, variance 1/3; with 200k draws the standard errors are ~1.3e-3
        // (mean) and ~7e-4 (variance), so 6e-3 is a loose but failing-when-wrong bound.
        let mut rng = Rng::new(5);
        let n = 200_000;
        let draws: Vec<f64> = (0..n).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let mean = draws.iter().sum::<f64>() / n as f64;
        let variance = draws.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 6e-3, "mean {mean}");
        assert!((variance - 1.0 / 3.0).abs() < 6e-3, "variance {variance}");
        assert!(draws.iter().all(|x| (-1.0..1.0).contains(x)));
    }

    #[test]
    fn kaiming_uniform_uses_inverse_sqrt_fan_in_bound() {
        let mut rng = Rng::new(1);
        let mut weight = vec![0.0f64; 223 * 512];
        let mut bias = vec![0.0f64; 512];
        kaiming_uniform(&mut rng, 223, &mut weight, &mut bias);
        let bound = 1.0 / 223f64.sqrt();
        let max_w = weight.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let max_b = bias.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(max_w <= bound && max_w > 0.99 * bound, "{max_w} vs {bound}");
        assert!(max_b <= bound && max_b > 0.9 * bound, "{max_b} vs {bound}");
    }
}
