//! Seeded LPIPS weights that Python and Rust generate bit for bit alike, for the parity
//! fixture (`tests/lpips/make_fixture.py` has the same generator in numpy).
//!
//! The real trunks hold 2.5 M (AlexNet) and 14.7 M (VGG16) parameters, too many to commit, so
//! both sides derive them from a seed. The generator is counter-based splitmix64: element `i`
//! of tensor `name` is `mix64(stream + (i + 1) * GAMMA)` with `stream = mix64(seed ^
//! fnv1a64(name))`; its top 24 bits give an exact `u` in [0, 1). Values are formed in f64
//! with correctly rounded operations only (`2u - 1`, `sqrt(6 / fan_in)`, one product), then
//! rounded to f32, so both languages produce identical bits:
//! - conv weights: `(2u - 1) * sqrt(6 / fan_in)` (He uniform, keeps ReLU activations in scale),
//! - conv biases: `(2u - 1) / sqrt(fan_in)` (PyTorch's default bias bound),
//! - lin weights: `u * sqrt(6 / channels)` (non-negative like the trained ones).

use super::Step;
use super::{ConvWeights, LpipsNet, LpipsWeights, SCALING_SCALE, SCALING_SHIFT, steps};

const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

fn mix64(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

fn fnv1a64(text: &str) -> u64 {
    text.bytes().fold(0xCBF2_9CE4_8422_2325, |hash, byte| {
        (hash ^ u64::from(byte)).wrapping_mul(0x0000_0100_0000_01B3)
    })
}

/// `count` exact uniforms in [0, 1) of tensor `name` under `seed`.
pub fn uniforms(seed: u64, name: &str, count: usize) -> Vec<f64> {
    let stream = mix64(seed ^ fnv1a64(name));
    (0..count as u64)
        .map(|index| {
            let bits = mix64(stream.wrapping_add((index + 1).wrapping_mul(GAMMA)));
            (bits >> 40) as f64 / 16_777_216.0
        })
        .collect()
}

/// The seeded weights of `net` (see the module docs).
pub fn seeded_weights(net: LpipsNet, seed: u64) -> LpipsWeights {
    let mut convs = Vec::new();
    for step in steps(net) {
        if let Step::Conv(spec) = step {
            let fan_in = spec.in_channels * spec.kernel * spec.kernel;
            let weight_bound = (6.0 / fan_in as f64).sqrt();
            let bias_bound = 1.0 / (fan_in as f64).sqrt();
            let weight_name = format!("{}.weight", spec.name);
            let bias_name = format!("{}.bias", spec.name);
            let weight = uniforms(seed, &weight_name, spec.out_channels * fan_in)
                .into_iter()
                .map(|u| ((2.0 * u - 1.0) * weight_bound) as f32)
                .collect();
            let bias = uniforms(seed, &bias_name, spec.out_channels)
                .into_iter()
                .map(|u| ((2.0 * u - 1.0) * bias_bound) as f32)
                .collect();
            convs.push(ConvWeights { spec, weight, bias });
        }
    }
    let lins = net
        .tap_channels()
        .iter()
        .enumerate()
        .map(|(layer, &channels)| {
            let bound = (6.0 / channels as f64).sqrt();
            uniforms(seed, &format!("lin{layer}.model.1.weight"), channels)
                .into_iter()
                .map(|u| (u * bound) as f32)
                .collect()
        })
        .collect();
    LpipsWeights {
        net,
        convs,
        lins,
        shift: SCALING_SHIFT,
        scale: SCALING_SCALE,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix64_matches_the_reference_sequence() {
        // splitmix64 seeded with 0 yields these first outputs (Vigna's reference code):
        // state += GAMMA, then mix; our counter form is the same sequence.
        let expected = [
            0xE220_A839_7B1D_CDAF_u64,
            0x6E78_9E6A_A1B9_65F4,
            0x06C4_5D18_8009_454F,
        ];
        for (index, value) in expected.iter().enumerate() {
            assert_eq!(mix64((index as u64 + 1).wrapping_mul(GAMMA)), *value);
        }
    }

    #[test]
    fn fnv1a64_matches_published_vectors() {
        assert_eq!(fnv1a64(""), 0xCBF2_9CE4_8422_2325);
        assert_eq!(fnv1a64("a"), 0xAF63_DC4C_8601_EC8C);
        assert_eq!(fnv1a64("foobar"), 0x8594_4171_F739_67E8);
    }

    #[test]
    fn uniforms_are_in_range_and_differ_between_tensors() {
        let first = uniforms(1, "a", 1000);
        let second = uniforms(1, "b", 1000);
        assert!(first.iter().all(|u| (0.0..1.0).contains(u)));
        assert_ne!(first, second);
        let mean = first.iter().sum::<f64>() / 1000.0;
        assert!((mean - 0.5).abs() < 0.05, "{mean}");
    }

    #[test]
    fn seeded_weights_have_the_architecture_shapes() {
        for net in [LpipsNet::Alex, LpipsNet::Vgg] {
            let weights = seeded_weights(net, 3);
            weights.validate().unwrap();
            let parameters: usize = weights
                .convs
                .iter()
                .map(|conv| conv.weight.len() + conv.bias.len())
                .sum();
            // torchvision's feature trunks up to the last tapped ReLU.
            let expected = match net {
                LpipsNet::Alex => 2_469_696,
                LpipsNet::Vgg => 14_714_688,
            };
            assert_eq!(parameters, expected, "{net:?}");
        }
    }
}
