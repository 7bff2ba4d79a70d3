//! The generator whose state checkpoints store: the project's SplitMix64
//! (`seqavatar_core::rng`), whose whole state is one `u64`, so a resumed run draws exactly
//! the numbers an uninterrupted one would.

pub use seqavatar_core::rng::SplitMix64 as Rng;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_first_output_and_resume() {
        // Reference value of SplitMix64 seeded with 0 (from the published C code).
        let mut rng = Rng::new(0);
        assert_eq!(rng.next_u64(), 0xE220_A839_7B1D_CDAF);
        let saved = rng.state();
        let a: Vec<u64> = (0..5).map(|_| rng.next_u64()).collect();
        let mut resumed = Rng::from_state(saved);
        let b: Vec<u64> = (0..5).map(|_| resumed.next_u64()).collect();
        assert_eq!(a, b);
    }

    #[test]
    fn moments_of_uniform_and_normal() {
        let mut rng = Rng::new(42);
        let n = 200_000;
        let u: Vec<f64> = (0..n).map(|_| rng.next_f64()).collect();
        let mean = u.iter().sum::<f64>() / n as f64;
        assert!((mean - 0.5).abs() < 0.005);
        assert!(u.iter().all(|v| (0.0..1.0).contains(v)));
        let g: Vec<f64> = (0..n).map(|_| rng.normal()).collect();
        let mean = g.iter().sum::<f64>() / n as f64;
        let var = g.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(
            mean.abs() < 0.01 && (var - 1.0).abs() < 0.02,
            "{mean} {var}"
        );
        let counts = (0..30_000).fold([0usize; 3], |mut c, _| {
            c[rng.below(3)] += 1;
            c
        });
        assert!(
            counts.iter().all(|&c| (9_500..10_500).contains(&c)),
            "{counts:?}"
        );
    }
}
