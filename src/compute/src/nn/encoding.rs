//! NeRF positional encoding on `cpu`: `[x, sin(2^0 x), cos(2^0 x), ..., sin(2^(F-1) x),
//! cos(2^(F-1) x)]`, forward and backward.
//!
//! The layout is the NeRF `Embedder`'s (`include_input`, log-sampled bands `2^0..2^(F-1)`,
//! no factor of pi): per row, the input's `d` values first, then for each frequency the `d`
//! sines followed by the `d` cosines. With `F = 10` and `d = 3` that is 63 values.

use rayon::prelude::*;

use super::scalar::NnScalar;
use super::{NnError, check_len};

/// Rows per parallel task: every row is independent, so the split only sets the task size
/// (about 30k sines and cosines for 3 inputs and 10 bands) and never the result.
const ROWS_PER_TASK: usize = 512;

/// The encoding's parameters.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PositionalEncoding {
    /// Number of frequency bands `F`; band `k` multiplies the input by `2^k`.
    pub frequencies: usize,
    /// Whether the raw input leads each encoded row.
    pub include_input: bool,
}

impl PositionalEncoding {
    /// The SeqAvatar encoding of canonical positions: 10 bands, input included (3 -> 63).
    pub const NERF_XYZ: PositionalEncoding = PositionalEncoding {
        frequencies: 10,
        include_input: true,
    };

    /// Encoded width for an input of `in_features` values per row.
    pub fn out_features(&self, in_features: usize) -> usize {
        in_features * (usize::from(self.include_input) + 2 * self.frequencies)
    }

    /// Column where the sines of band `band` start, for `in_features` inputs.
    pub fn sine_column(&self, in_features: usize, band: usize) -> usize {
        in_features * (usize::from(self.include_input) + 2 * band)
    }

    fn check(
        &self,
        rows: usize,
        in_features: usize,
        input: usize,
        output: usize,
    ) -> Result<(), NnError> {
        if self.frequencies > 30 {
            return Err(NnError::Config {
                field: "positional_encoding.frequencies".into(),
                message: format!(
                    "{} bands exceed 30 (2^30 x overflows any float phase)",
                    self.frequencies
                ),
            });
        }
        check_len("positional encoding input", rows * in_features, input)?;
        check_len(
            "positional encoding output",
            rows * self.out_features(in_features),
            output,
        )
    }
}

/// Encodes `input` (`rows x in_features`) into `output` (`rows x out_features`).
pub fn positional_encoding_forward<T: NnScalar>(
    encoding: PositionalEncoding,
    input: &[T],
    rows: usize,
    in_features: usize,
    output: &mut [T],
) -> Result<(), NnError> {
    encoding.check(rows, in_features, input.len(), output.len())?;
    let width = encoding.out_features(in_features);
    if width == 0 {
        return Ok(());
    }
    let encode_rows = |(input, output): (&[T], &mut [T])| {
        for (x, y) in input
            .chunks_exact(in_features)
            .zip(output.chunks_exact_mut(width))
        {
            if encoding.include_input {
                y[..in_features].copy_from_slice(x);
            }
            for band in 0..encoding.frequencies {
                let scale = T::from_f64((1u64 << band) as f64);
                let start = encoding.sine_column(in_features, band);
                for (i, &value) in x.iter().enumerate() {
                    let phase = value * scale;
                    y[start + i] = phase.sin();
                    y[start + in_features + i] = phase.cos();
                }
            }
        }
    };
    input
        .par_chunks(ROWS_PER_TASK * in_features)
        .zip(output.par_chunks_mut(ROWS_PER_TASK * width))
        .for_each(encode_rows);
    Ok(())
}

/// Backward: overwrites `d_input` with `dL/dx` from `d_output = dL/d(encoding)`, using the
/// forward `output` (`d sin(s x)/dx = s cos(s x)`, `d cos(s x)/dx = -s sin(s x)`), so no
/// trigonometric function is evaluated again.
pub fn positional_encoding_backward<T: NnScalar>(
    encoding: PositionalEncoding,
    output: &[T],
    d_output: &[T],
    rows: usize,
    in_features: usize,
    d_input: &mut [T],
) -> Result<(), NnError> {
    encoding.check(rows, in_features, d_input.len(), output.len())?;
    check_len(
        "positional encoding output gradient",
        output.len(),
        d_output.len(),
    )?;
    let width = encoding.out_features(in_features);
    if width == 0 {
        // No encoded values (no inputs, or no bands and no raw input): x reaches nothing.
        d_input.fill(T::ZERO);
        return Ok(());
    }
    let backward_rows = |((output, d_output), d_input): ((&[T], &[T]), &mut [T])| {
        let rows_iter = output.chunks_exact(width).zip(d_output.chunks_exact(width));
        for ((y, dy), dx) in rows_iter.zip(d_input.chunks_exact_mut(in_features)) {
            for (i, d) in dx.iter_mut().enumerate() {
                let mut sum = if encoding.include_input {
                    dy[i]
                } else {
                    T::ZERO
                };
                for band in 0..encoding.frequencies {
                    let scale = T::from_f64((1u64 << band) as f64);
                    let sine = encoding.sine_column(in_features, band) + i;
                    let cosine = sine + in_features;
                    sum += scale * (y[cosine] * dy[sine] - y[sine] * dy[cosine]);
                }
                *d = sum;
            }
        }
    };
    output
        .par_chunks(ROWS_PER_TASK * width)
        .zip(d_output.par_chunks(ROWS_PER_TASK * width))
        .zip(d_input.par_chunks_mut(ROWS_PER_TASK * in_features))
        .for_each(backward_rows);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::init::Rng;

    #[test]
    fn layout_matches_the_nerf_embedder() {
        let encoding = PositionalEncoding::NERF_XYZ;
        assert_eq!(encoding.out_features(3), 63);
        let input = [0.1f64, -0.2, 0.3];
        let mut output = vec![0.0; 63];
        positional_encoding_forward(encoding, &input, 1, 3, &mut output).unwrap();
        assert_eq!(&output[..3], &input);
        // Band 2 (scale 4): sines at 3 + 2*2*3 = 15, cosines at 18.
        assert!((output[15 + 1] - (-0.8f64).sin()).abs() < 1e-15);
        assert!((output[18 + 2] - (1.2f64).cos()).abs() < 1e-15);
        // Last band (scale 512): sines at 57, cosines at 60.
        assert!((output[57] - 51.2f64.sin()).abs() < 1e-12);
        assert!((output[62] - (0.3f64 * 512.0).cos()).abs() < 1e-12);
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = Rng::new(4);
        for encoding in [
            PositionalEncoding::NERF_XYZ,
            PositionalEncoding {
                frequencies: 3,
                include_input: false,
            },
        ] {
            let (rows, d) = (3, 3);
            let width = encoding.out_features(d);
            let input: Vec<f64> = (0..rows * d).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let probe: Vec<f64> = (0..rows * width).map(|_| rng.uniform(-1.0, 1.0)).collect();
            let loss = |x: &[f64]| {
                let mut y = vec![0.0; rows * width];
                positional_encoding_forward(encoding, x, rows, d, &mut y).unwrap();
                y.iter().zip(&probe).map(|(a, b)| a * b).sum::<f64>()
            };
            let mut output = vec![0.0; rows * width];
            positional_encoding_forward(encoding, &input, rows, d, &mut output).unwrap();
            let mut d_input = vec![f64::NAN; rows * d];
            positional_encoding_backward(encoding, &output, &probe, rows, d, &mut d_input).unwrap();
            // Band 9 has scale 512: a step of 1e-7 keeps the phase error of central
            // differences (~(512 h)^2) far below the tolerance.
            let h = 1e-7;
            for i in 0..input.len() {
                let (mut plus, mut minus) = (input.clone(), input.clone());
                plus[i] += h;
                minus[i] -= h;
                let fd = (loss(&plus) - loss(&minus)) / (2.0 * h);
                let scale = 1.0 + fd.abs();
                assert!(
                    (d_input[i] - fd).abs() < 1e-5 * scale,
                    "dx[{i}] {} vs {fd}",
                    d_input[i]
                );
            }
        }
    }

    /// Over many row blocks (the parallel split), every row is the closed form: the forward
    /// `sin(2^k x)`, `cos(2^k x)`, the backward `dy_x + sum_k 2^k (cos dy_sin - sin dy_cos)`.
    #[test]
    fn every_row_block_is_the_closed_form() {
        let encoding = PositionalEncoding::NERF_XYZ;
        let (rows, d) = (2 * ROWS_PER_TASK + 37, 3);
        let width = encoding.out_features(d);
        let mut rng = Rng::new(11);
        let input: Vec<f64> = (0..rows * d).map(|_| rng.uniform(-1.5, 1.5)).collect();
        let d_output: Vec<f64> = (0..rows * width).map(|_| rng.uniform(-1.0, 1.0)).collect();
        let mut output = vec![f64::NAN; rows * width];
        positional_encoding_forward(encoding, &input, rows, d, &mut output).unwrap();
        let mut d_input = vec![f64::NAN; rows * d];
        positional_encoding_backward(encoding, &output, &d_output, rows, d, &mut d_input).unwrap();
        for row in [
            0,
            ROWS_PER_TASK - 1,
            ROWS_PER_TASK,
            2 * ROWS_PER_TASK,
            rows - 1,
        ] {
            for i in 0..d {
                let x = input[row * d + i];
                let (y, dy) = (&output[row * width..], &d_output[row * width..]);
                assert_eq!(y[i], x);
                let mut expected = dy[i];
                for band in 0..encoding.frequencies {
                    let scale = f64::from(1u32 << band);
                    let sine = d * (1 + 2 * band) + i;
                    assert_eq!(y[sine], (scale * x).sin(), "row {row} band {band}");
                    assert_eq!(y[sine + d], (scale * x).cos(), "row {row} band {band}");
                    expected +=
                        scale * ((scale * x).cos() * dy[sine] - (scale * x).sin() * dy[sine + d]);
                }
                let got = d_input[row * d + i];
                assert!(
                    (got - expected).abs() <= 1e-12 * expected.abs().max(1.0),
                    "row {row}: {got} vs {expected}"
                );
            }
        }
    }

    /// An encoding with no bands and no raw input encodes nothing, and its backward writes
    /// a zero gradient (the input reaches no output).
    #[test]
    fn an_empty_encoding_has_a_zero_gradient() {
        let encoding = PositionalEncoding {
            frequencies: 0,
            include_input: false,
        };
        let (rows, d) = (4, 3);
        positional_encoding_forward(encoding, &[1.0f64; 12], rows, d, &mut []).unwrap();
        let mut d_input = vec![f64::NAN; rows * d];
        positional_encoding_backward(encoding, &[], &[], rows, d, &mut d_input).unwrap();
        assert_eq!(d_input, vec![0.0; rows * d]);
    }

    #[test]
    fn rejects_bad_lengths() {
        let mut output = vec![0.0f32; 62];
        let error =
            positional_encoding_forward(PositionalEncoding::NERF_XYZ, &[0.0; 3], 1, 3, &mut output)
                .unwrap_err();
        assert_eq!(
            error,
            NnError::Length {
                operand: "positional encoding output".into(),
                expected: 63,
                actual: 62
            }
        );
    }
}
