//! The `cpu` dense layer `Y = act(X W + b)` and its backward, on `gemm`, generic over f32/f64.
//!
//! Shapes and conventions are those of the [`nn`](crate::nn) module: row-major matrices,
//! `W: in x out`, the input given as one or more column blocks ([`InputPart`]), the ReLU
//! mask taken from the output, weight and bias gradients accumulated.

use rayon::prelude::*;

use super::scalar::NnScalar;
use super::{NnError, check_len};

/// The activation fused into a layer's epilogue.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Activation {
    /// `y = x`.
    Identity,
    /// `y = max(x, 0)`; its derivative at 0 is taken as 0, as PyTorch does.
    Relu,
}

impl Activation {
    /// Applies the activation to one value.
    #[inline]
    pub fn apply<T: NnScalar>(self, value: T) -> T {
        match self {
            Activation::Identity => value,
            Activation::Relu => {
                if value > T::ZERO {
                    value
                } else {
                    T::ZERO
                }
            }
        }
    }
}

/// The shape of one dense layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct LinearShape {
    /// Number of input features (the sum of the input parts' widths).
    pub in_features: usize,
    /// Number of output features.
    pub out_features: usize,
    /// The activation applied after the bias.
    pub activation: Activation,
}

impl LinearShape {
    /// Number of weight entries, `in_features * out_features`.
    pub fn weight_len(&self) -> usize {
        self.in_features * self.out_features
    }

    /// Multiply-adds of one forward pass over `rows` rows (backward costs twice this).
    pub fn forward_flops(&self, rows: usize) -> f64 {
        2.0 * rows as f64 * self.in_features as f64 * self.out_features as f64
    }
}

/// One column block of a layer's input: a row-major `rows x cols` matrix.
#[derive(Clone, Copy, Debug)]
pub struct InputPart<'a, T> {
    /// The matrix, `rows * cols` values.
    pub data: &'a [T],
    /// Its number of columns.
    pub cols: usize,
}

/// Where the gradient with respect to one input part goes.
#[derive(Debug)]
pub enum InputGrad<'a, T> {
    /// Not needed (the input is data, not a trained quantity).
    Skip,
    /// Overwrite this `rows x cols` buffer.
    Write(&'a mut [T]),
    /// Add into this `rows x cols` buffer (an input read by several layers).
    Accumulate(&'a mut [T]),
}

/// The gradient buffers of one layer's parameters; both are accumulated into.
#[derive(Debug)]
pub struct LinearGrads<'a, T> {
    /// `in x out`, like the weight.
    pub weight: &'a mut [T],
    /// `out`, like the bias.
    pub bias: &'a mut [T],
}

/// Rows per parallel work item in the element-wise passes; fixed so sums are deterministic.
const ROW_BLOCK: usize = 256;

/// Below this many multiply-adds a product runs on the calling thread.
const PARALLEL_THRESHOLD: usize = 1 << 18;

fn parallelism(m: usize, n: usize, k: usize) -> gemm::Parallelism {
    let threads = rayon::current_num_threads();
    if threads <= 1 || m.saturating_mul(n).saturating_mul(k) < PARALLEL_THRESHOLD {
        gemm::Parallelism::None
    } else {
        gemm::Parallelism::Rayon(threads)
    }
}

/// A strided read-only matrix view for `gemm`: element `(i, j)` is at
/// `data[offset + i * row_stride + j * col_stride]`.
struct View<'a, T> {
    data: &'a [T],
    offset: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<T> View<'_, T> {
    /// Whether every element of an `rows x cols` matrix lies inside `data`.
    fn fits(&self, rows: usize, cols: usize) -> bool {
        rows == 0
            || cols == 0
            || self.offset + (rows - 1) * self.row_stride + (cols - 1) * self.col_stride
                < self.data.len()
    }
}

/// `dst (m x n, row-major with row stride dst_stride) (+)= lhs (m x k) * rhs (k x n)`.
///
/// Panics only on a violated internal invariant (views not covering their shape), which the
/// public functions rule out by validating every length first.
#[allow(clippy::too_many_arguments)]
fn gemm_into<T: NnScalar>(
    m: usize,
    n: usize,
    k: usize,
    dst: &mut [T],
    dst_offset: usize,
    dst_stride: usize,
    accumulate: bool,
    lhs: View<'_, T>,
    rhs: View<'_, T>,
) {
    if m == 0 || n == 0 {
        return;
    }
    let dst_view = View {
        data: &*dst,
        offset: dst_offset,
        row_stride: dst_stride,
        col_stride: 1,
    };
    assert!(
        dst_view.fits(m, n) && lhs.fits(m, k) && rhs.fits(k, n),
        "gemm_into: operand views exceed their buffers (internal invariant)"
    );
    // SAFETY: the assertion above guarantees every element gemm touches lies inside the
    // slices; `dst` is uniquely borrowed and does not alias `lhs` or `rhs` (they are shared
    // borrows, which Rust forbids to coexist with the `&mut`).
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.as_mut_ptr().add(dst_offset),
            1,
            dst_stride as isize,
            accumulate,
            lhs.data.as_ptr().add(lhs.offset),
            lhs.col_stride as isize,
            lhs.row_stride as isize,
            rhs.data.as_ptr().add(rhs.offset),
            rhs.col_stride as isize,
            rhs.row_stride as isize,
            T::ONE,
            T::ONE,
            false,
            false,
            false,
            parallelism(m, n, k),
        );
    }
}

fn check_shape<T>(
    shape: LinearShape,
    weight: &[T],
    inputs: &[InputPart<'_, T>],
    rows: usize,
) -> Result<(), NnError> {
    if shape.in_features == 0 || shape.out_features == 0 {
        return Err(NnError::Shape {
            operand: "linear layer".into(),
            message: format!(
                "in_features ({}) and out_features ({}) must be positive",
                shape.in_features, shape.out_features
            ),
        });
    }
    check_len("linear weight", shape.weight_len(), weight.len())?;
    let total_cols: usize = inputs.iter().map(|part| part.cols).sum();
    if total_cols != shape.in_features || inputs.iter().any(|part| part.cols == 0) {
        return Err(NnError::Shape {
            operand: "linear input".into(),
            message: format!(
                "input part widths {:?} must be positive and sum to in_features = {}",
                inputs.iter().map(|part| part.cols).collect::<Vec<_>>(),
                shape.in_features
            ),
        });
    }
    for (index, part) in inputs.iter().enumerate() {
        check_len(
            &format!("linear input part {index}"),
            rows * part.cols,
            part.data.len(),
        )?;
    }
    Ok(())
}

/// Forward: `output = act(concat(inputs) W + b)`, `output` is `rows x out` and overwritten.
pub fn linear_forward<T: NnScalar>(
    shape: LinearShape,
    weight: &[T],
    bias: &[T],
    inputs: &[InputPart<'_, T>],
    rows: usize,
    output: &mut [T],
) -> Result<(), NnError> {
    check_shape(shape, weight, inputs, rows)?;
    check_len("linear bias", shape.out_features, bias.len())?;
    check_len("linear output", rows * shape.out_features, output.len())?;
    let out = shape.out_features;
    let mut weight_row = 0;
    for (index, part) in inputs.iter().enumerate() {
        gemm_into(
            rows,
            out,
            part.cols,
            output,
            0,
            out,
            index > 0,
            View {
                data: part.data,
                offset: 0,
                row_stride: part.cols,
                col_stride: 1,
            },
            View {
                data: weight,
                offset: weight_row * out,
                row_stride: out,
                col_stride: 1,
            },
        );
        weight_row += part.cols;
    }
    let activation = shape.activation;
    output.par_chunks_mut(ROW_BLOCK * out).for_each(|block| {
        for row in block.chunks_exact_mut(out) {
            for (value, &b) in row.iter_mut().zip(bias) {
                *value = activation.apply(*value + b);
            }
        }
    });
    Ok(())
}

/// Backward of [`linear_forward`].
///
/// `output` is the forward output (for the ReLU mask). `d_output` holds `dL/dY` on entry
/// and `dL/d(pre-activation)` on return (masked in place to avoid a `rows x out` copy).
/// Weight and bias gradients are accumulated into `grads`; `d_inputs` has one entry per
/// input part.
#[allow(clippy::too_many_arguments)]
pub fn linear_backward<T: NnScalar>(
    shape: LinearShape,
    weight: &[T],
    inputs: &[InputPart<'_, T>],
    rows: usize,
    output: &[T],
    d_output: &mut [T],
    grads: LinearGrads<'_, T>,
    d_inputs: &mut [InputGrad<'_, T>],
) -> Result<(), NnError> {
    check_shape(shape, weight, inputs, rows)?;
    let out = shape.out_features;
    check_len("linear output", rows * out, output.len())?;
    check_len("linear output gradient", rows * out, d_output.len())?;
    check_len(
        "linear weight gradient",
        shape.weight_len(),
        grads.weight.len(),
    )?;
    check_len("linear bias gradient", out, grads.bias.len())?;
    if d_inputs.len() != inputs.len() {
        return Err(NnError::Shape {
            operand: "linear input gradients".into(),
            message: format!(
                "{} entries for {} input parts",
                d_inputs.len(),
                inputs.len()
            ),
        });
    }
    for (index, (part, grad)) in inputs.iter().zip(d_inputs.iter()).enumerate() {
        if let InputGrad::Write(buffer) | InputGrad::Accumulate(buffer) = grad {
            check_len(
                &format!("linear input part {index} gradient"),
                rows * part.cols,
                buffer.len(),
            )?;
        }
    }

    if shape.activation == Activation::Relu {
        d_output
            .par_chunks_mut(ROW_BLOCK * out)
            .zip(output.par_chunks(ROW_BLOCK * out))
            .for_each(|(d_block, y_block)| {
                for (d, &y) in d_block.iter_mut().zip(y_block) {
                    if y <= T::ZERO {
                        *d = T::ZERO;
                    }
                }
            });
    }
    let d_pre: &[T] = d_output;

    // Bias gradient: column sums, by fixed row blocks then in order, so it is deterministic.
    let partial_sums: Vec<Vec<T>> = d_pre
        .par_chunks(ROW_BLOCK * out)
        .map(|block| {
            let mut sums = vec![T::ZERO; out];
            for row in block.chunks_exact(out) {
                for (sum, &d) in sums.iter_mut().zip(row) {
                    *sum += d;
                }
            }
            sums
        })
        .collect();
    for sums in &partial_sums {
        for (g, &s) in grads.bias.iter_mut().zip(sums) {
            *g += s;
        }
    }

    let mut weight_row = 0;
    for (part, d_input) in inputs.iter().zip(d_inputs.iter_mut()) {
        let cols = part.cols;
        // dW_part += X_part^T dY': (cols x rows) (rows x out).
        gemm_into(
            cols,
            out,
            rows,
            grads.weight,
            weight_row * out,
            out,
            true,
            View {
                data: part.data,
                offset: 0,
                row_stride: 1,
                col_stride: cols,
            },
            View {
                data: d_pre,
                offset: 0,
                row_stride: out,
                col_stride: 1,
            },
        );
        // dX_part (+)= dY' W_part^T: (rows x out) (out x cols).
        let (buffer, accumulate) = match d_input {
            InputGrad::Skip => (None, false),
            InputGrad::Write(buffer) => (Some(&mut **buffer), false),
            InputGrad::Accumulate(buffer) => (Some(&mut **buffer), true),
        };
        if let Some(buffer) = buffer {
            gemm_into(
                rows,
                cols,
                out,
                buffer,
                0,
                cols,
                accumulate,
                View {
                    data: d_pre,
                    offset: 0,
                    row_stride: out,
                    col_stride: 1,
                },
                View {
                    data: weight,
                    offset: weight_row * out,
                    row_stride: 1,
                    col_stride: out,
                },
            );
        }
        weight_row += cols;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::nn::init::Rng;

    fn random_vec(rng: &mut Rng, len: usize) -> Vec<f64> {
        (0..len).map(|_| rng.uniform(-1.0, 1.0)).collect()
    }

    /// Naive triple loop, the independent reference for the forward pass.
    fn naive_forward(
        shape: LinearShape,
        weight: &[f64],
        bias: &[f64],
        input: &[f64],
        rows: usize,
    ) -> Vec<f64> {
        let (n_in, n_out) = (shape.in_features, shape.out_features);
        let mut output = vec![0.0; rows * n_out];
        for r in 0..rows {
            for j in 0..n_out {
                let mut sum = bias[j];
                for i in 0..n_in {
                    sum += input[r * n_in + i] * weight[i * n_out + j];
                }
                output[r * n_out + j] = shape.activation.apply(sum);
            }
        }
        output
    }

    /// Splits a `rows x total` matrix into column blocks of the given widths.
    fn split_columns(matrix: &[f64], rows: usize, widths: &[usize]) -> Vec<Vec<f64>> {
        let total: usize = widths.iter().sum();
        let mut start = 0;
        widths
            .iter()
            .map(|&w| {
                let block = (0..rows)
                    .flat_map(|r| {
                        matrix[r * total + start..r * total + start + w]
                            .iter()
                            .copied()
                    })
                    .collect();
                start += w;
                block
            })
            .collect()
    }

    fn check_forward(rows: usize, widths: &[usize], out: usize, activation: Activation) {
        let mut rng = Rng::new(7);
        let n_in: usize = widths.iter().sum();
        let shape = LinearShape {
            in_features: n_in,
            out_features: out,
            activation,
        };
        let weight = random_vec(&mut rng, n_in * out);
        let bias = random_vec(&mut rng, out);
        let input = random_vec(&mut rng, rows * n_in);
        let blocks = split_columns(&input, rows, widths);
        let parts: Vec<_> = blocks
            .iter()
            .zip(widths)
            .map(|(data, &cols)| InputPart {
                data: data.as_slice(),
                cols,
            })
            .collect();
        // NaN start: the forward must overwrite, never read, the output buffer.
        let mut output = vec![f64::NAN; rows * out];
        linear_forward(shape, &weight, &bias, &parts, rows, &mut output).unwrap();
        let expected = naive_forward(shape, &weight, &bias, &input, rows);
        for (a, b) in output.iter().zip(&expected) {
            assert!((a - b).abs() < 1e-12, "{a} vs {b}");
        }
    }

    #[test]
    fn forward_matches_naive_product() {
        check_forward(5, &[3], 4, Activation::Identity);
        check_forward(37, &[13], 9, Activation::Relu);
        check_forward(300, &[20, 7, 1], 33, Activation::Relu);
        check_forward(0, &[2], 3, Activation::Relu);
        check_forward(600, &[70], 80, Activation::Identity);
    }

    /// Loss `L = sum(Y * G)` for a fixed random `G`, so `dL/dY = G`.
    fn loss(
        shape: LinearShape,
        weight: &[f64],
        bias: &[f64],
        blocks: &[Vec<f64>],
        widths: &[usize],
        rows: usize,
        probe: &[f64],
    ) -> f64 {
        let parts: Vec<_> = blocks
            .iter()
            .zip(widths)
            .map(|(data, &cols)| InputPart {
                data: data.as_slice(),
                cols,
            })
            .collect();
        let mut output = vec![0.0; rows * shape.out_features];
        linear_forward(shape, weight, bias, &parts, rows, &mut output).unwrap();
        output.iter().zip(probe).map(|(y, g)| y * g).sum()
    }

    #[test]
    fn backward_matches_finite_differences() {
        let mut rng = Rng::new(11);
        let rows = 6;
        let widths = [3, 2];
        let n_in = 5;
        let out = 4;
        for activation in [Activation::Identity, Activation::Relu] {
            let shape = LinearShape {
                in_features: n_in,
                out_features: out,
                activation,
            };
            let weight = random_vec(&mut rng, n_in * out);
            let bias = random_vec(&mut rng, out);
            let blocks: Vec<Vec<f64>> = widths
                .iter()
                .map(|&w| random_vec(&mut rng, rows * w))
                .collect();
            let probe = random_vec(&mut rng, rows * out);
            let parts: Vec<_> = blocks
                .iter()
                .zip(&widths)
                .map(|(data, &cols)| InputPart {
                    data: data.as_slice(),
                    cols,
                })
                .collect();
            let mut output = vec![0.0; rows * out];
            linear_forward(shape, &weight, &bias, &parts, rows, &mut output).unwrap();

            // Gradients start non-zero to check that parameters accumulate and inputs with
            // `Accumulate` add while `Write` overwrites.
            let mut d_weight = vec![0.5; n_in * out];
            let mut d_bias = vec![-0.25; out];
            let mut d_input0 = vec![f64::NAN; rows * widths[0]];
            let mut d_input1 = vec![2.0; rows * widths[1]];
            let mut d_output = probe.clone();
            linear_backward(
                shape,
                &weight,
                &parts,
                rows,
                &output,
                &mut d_output,
                LinearGrads {
                    weight: &mut d_weight,
                    bias: &mut d_bias,
                },
                &mut [
                    InputGrad::Write(&mut d_input0),
                    InputGrad::Accumulate(&mut d_input1),
                ],
            )
            .unwrap();

            let h = 1e-6;
            let f =
                |w: &[f64], b: &[f64], x: &[Vec<f64>]| loss(shape, w, b, x, &widths, rows, &probe);
            let central = |plus: f64, minus: f64| (plus - minus) / (2.0 * h);
            for i in 0..weight.len() {
                let (mut wp, mut wm) = (weight.clone(), weight.clone());
                wp[i] += h;
                wm[i] -= h;
                let fd = central(f(&wp, &bias, &blocks), f(&wm, &bias, &blocks));
                assert!(
                    (d_weight[i] - 0.5 - fd).abs() < 1e-6,
                    "dW[{i}] {} vs {fd}",
                    d_weight[i]
                );
            }
            for j in 0..out {
                let (mut bp, mut bm) = (bias.clone(), bias.clone());
                bp[j] += h;
                bm[j] -= h;
                let fd = central(f(&weight, &bp, &blocks), f(&weight, &bm, &blocks));
                assert!(
                    (d_bias[j] + 0.25 - fd).abs() < 1e-6,
                    "db[{j}] {} vs {fd}",
                    d_bias[j]
                );
            }
            for (p, (grad, offset)) in [(&d_input0, 0.0), (&d_input1, 2.0)].into_iter().enumerate()
            {
                for i in 0..blocks[p].len() {
                    let (mut xp, mut xm) = (blocks.clone(), blocks.clone());
                    xp[p][i] += h;
                    xm[p][i] -= h;
                    let fd = central(f(&weight, &bias, &xp), f(&weight, &bias, &xm));
                    assert!(
                        (grad[i] - offset - fd).abs() < 1e-6,
                        "dX{p}[{i}] {} vs {fd}",
                        grad[i]
                    );
                }
            }
        }
    }

    #[test]
    fn rejects_bad_lengths_naming_the_operand() {
        let shape = LinearShape {
            in_features: 3,
            out_features: 2,
            activation: Activation::Relu,
        };
        let weight = vec![0.0f32; 6];
        let bias = vec![0.0f32; 2];
        let input = [0.0f32; 9];
        let mut output = vec![0.0f32; 6];
        let parts = [InputPart {
            data: &input[..],
            cols: 3,
        }];
        assert!(linear_forward(shape, &weight, &bias, &parts, 3, &mut output).is_ok());
        let error = linear_forward(shape, &weight[..5], &bias, &parts, 3, &mut output).unwrap_err();
        assert_eq!(
            error,
            NnError::Length {
                operand: "linear weight".into(),
                expected: 6,
                actual: 5
            }
        );
        let error = linear_forward(shape, &weight, &bias, &parts, 4, &mut output).unwrap_err();
        assert!(error.to_string().contains("linear input part 0"), "{error}");
        let wide = [
            InputPart {
                data: &input[..],
                cols: 3,
            },
            InputPart {
                data: &input[..3],
                cols: 1,
            },
        ];
        let error = linear_forward(shape, &weight, &bias, &wide, 3, &mut output).unwrap_err();
        assert!(
            error.to_string().contains("sum to in_features = 3"),
            "{error}"
        );
    }

    #[test]
    fn f32_matches_f64() {
        let mut rng = Rng::new(3);
        let (rows, n_in, out) = (129, 67, 45);
        let shape = LinearShape {
            in_features: n_in,
            out_features: out,
            activation: Activation::Relu,
        };
        let weight = random_vec(&mut rng, n_in * out);
        let bias = random_vec(&mut rng, out);
        let input = random_vec(&mut rng, rows * n_in);
        let mut output = vec![0.0; rows * out];
        linear_forward(
            shape,
            &weight,
            &bias,
            &[InputPart {
                data: &input,
                cols: n_in,
            }],
            rows,
            &mut output,
        )
        .unwrap();
        let to32 = |v: &[f64]| v.iter().map(|&x| x as f32).collect::<Vec<f32>>();
        let mut output32 = vec![0.0f32; rows * out];
        let input32 = to32(&input);
        linear_forward(
            shape,
            &to32(&weight),
            &to32(&bias),
            &[InputPart {
                data: &input32,
                cols: n_in,
            }],
            rows,
            &mut output32,
        )
        .unwrap();
        for (a, b) in output32.iter().zip(&output) {
            assert!((f64::from(*a) - b).abs() < 1e-4, "{a} vs {b}");
        }
    }
}
