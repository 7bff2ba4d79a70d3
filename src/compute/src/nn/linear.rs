//! The `cpu` dense layer `Y = act(X W + b)` and its backward, on `gemm`, generic over f32/f64.
//!
//! Shapes and conventions are those of the [`nn`](crate::nn) module: row-major matrices,
//! `W: in x out`, the input given as one or more column blocks ([`InputPart`]), the ReLU
//! mask taken from the output, weight and bias gradients accumulated.

use rayon::prelude::*;
use seqavatar_core::matmul::{Layout, Matrix, MatrixMut, Parallelism, matmul};

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

/// The gradient buffers of one layer: its parameters' (both accumulated into) and its
/// input parts'.
#[derive(Debug)]
pub struct LinearGrads<'a, 'b, T> {
    /// `in x out`, like the weight.
    pub weight: &'a mut [T],
    /// `out`, like the bias.
    pub bias: &'a mut [T],
    /// One entry per input part.
    pub inputs: &'a mut [InputGrad<'b, T>],
}

/// Bytes of input and output one row block spans (`rows * (in + out)` values): about an L2
/// cache, so the masked output gradient a block writes is still cached when its input
/// gradient product reads it, and `gemm` packs each weight panel once per several hundred
/// rows. 512 rows of a 512 x 512 f32 layer; measured best of 64-4096 rows on the target CPU.
const ROW_BLOCK_BYTES: usize = 2 << 20;

/// Fewest rows per block (smaller products leave `gemm` below its peak).
const MIN_BLOCK_ROWS: usize = 64;

/// Most rows per block.
const MAX_BLOCK_ROWS: usize = 4096;

/// Below this many multiply-adds a call runs on the calling thread.
const PARALLEL_THRESHOLD: usize = 1 << 20;

/// Fewest rows one weight-gradient partial product sums over: a partial costs one extra
/// `in x out` addition, negligible next to `2 * rows * in * out` flops from this many rows.
const WEIGHT_CHUNK_ROWS: usize = 2048;

/// Most weight-gradient partial products (row chunks) of one call.
const MAX_WEIGHT_CHUNKS: usize = 8;

/// The weight-gradient tasks of one call are a multiple of this many (divisible by 2, 4
/// and 8 threads), so equal tasks keep every thread equally busy.
const WEIGHT_TASKS: usize = 8;

/// Entries per task when the weight-gradient partials are added up.
const REDUCE_BLOCK: usize = 1 << 14;

/// Fewest weight rows (input features) one weight-gradient task covers.
const MIN_WEIGHT_TILE: usize = 16;

/// The row blocks of one call: every block has `size` rows but the last. They depend on the
/// shape, the row count and the scalar only, never on the thread count, so the bias
/// gradient (summed per block, then over blocks in order) is the same for any thread count.
#[derive(Clone, Copy, Debug)]
struct RowBlocks {
    size: usize,
    count: usize,
}

impl RowBlocks {
    fn new<T>(shape: LinearShape, rows: usize) -> Self {
        let row_bytes = (shape.in_features + shape.out_features) * std::mem::size_of::<T>();
        let target = (ROW_BLOCK_BYTES / row_bytes).clamp(MIN_BLOCK_ROWS, MAX_BLOCK_ROWS);
        // Equal blocks rather than full blocks and a short tail, for an even split.
        let size = rows.div_ceil(rows.div_ceil(target).max(1)).max(1);
        RowBlocks {
            size,
            count: rows.div_ceil(size),
        }
    }
}

/// How one call spreads over the rayon threads, chosen from its size.
#[derive(Clone, Copy, Debug)]
struct Plan {
    /// Row blocks (and weight-gradient tasks) are parallel tasks.
    across_tasks: bool,
    /// The parallelism inside each `gemm` call.
    inside_gemm: Parallelism,
}

impl Plan {
    /// Small products run on the calling thread; large ones run their row blocks as tasks
    /// (one `gemm` per block, no synchronisation inside) when there are enough blocks to
    /// keep every thread busy, and otherwise one block at a time with `gemm`'s own threads.
    fn new(multiply_adds: usize, blocks: usize) -> Self {
        let threads = rayon::current_num_threads();
        if threads <= 1 || multiply_adds < PARALLEL_THRESHOLD {
            Plan {
                across_tasks: false,
                inside_gemm: Parallelism::None,
            }
        } else if blocks >= threads {
            Plan {
                across_tasks: true,
                inside_gemm: Parallelism::None,
            }
        } else {
            Plan {
                across_tasks: false,
                inside_gemm: Parallelism::Rayon(threads),
            }
        }
    }

    /// Runs `work` on every task, in parallel or in order; results come back in task order.
    fn run<I: Send, R: Send>(self, tasks: Vec<I>, work: impl Fn(I) -> R + Sync + Send) -> Vec<R> {
        if self.across_tasks {
            tasks.into_par_iter().map(work).collect()
        } else {
            tasks.into_iter().map(work).collect()
        }
    }
}

/// A strided read-only matrix view: element `(i, j)` is at
/// `data[offset + i * row_stride + j * col_stride]`. A transposed operand is the same
/// buffer with the strides swapped; `gemm` packs from any strides.
struct View<'a, T> {
    data: &'a [T],
    offset: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<'a, T> View<'a, T> {
    fn new(data: &'a [T], offset: usize, row_stride: usize, col_stride: usize) -> Self {
        Self {
            data,
            offset,
            row_stride,
            col_stride,
        }
    }

    /// The `rows x cols` matrix this view starts.
    fn matrix(&self, rows: usize, cols: usize) -> Matrix<'a, T> {
        Matrix::new(
            self.data,
            Layout::strided(rows, cols, self.row_stride, self.col_stride).at(self.offset),
        )
    }
}

/// `dst (m x n, row-major with row stride dst_stride) (+)= lhs (m x k) * rhs (k x n)`.
///
/// Panics only on a violated internal invariant (views not covering their shape), which the
/// public functions rule out by validating every length first.
fn gemm_into<T: NnScalar>(
    (m, n, k): (usize, usize, usize),
    dst: &mut [T],
    dst_stride: usize,
    accumulate: bool,
    lhs: View<'_, T>,
    rhs: View<'_, T>,
    parallelism: Parallelism,
) {
    matmul(
        MatrixMut::new(dst, Layout::strided(m, n, dst_stride, 1)),
        lhs.matrix(m, k),
        rhs.matrix(k, n),
        accumulate,
        parallelism,
    );
}

fn check_shape<T>(
    shape: LinearShape,
    weight: &[T],
    inputs: &[InputPart<'_, T>],
    rows: usize,
) -> Result<(), NnError> {
    check_features(shape)?;
    check_len("linear weight", shape.weight_len(), weight.len())?;
    check_widths(shape, inputs.iter().map(|part| part.cols))?;
    for (index, part) in inputs.iter().enumerate() {
        check_len(
            &format!("linear input part {index}"),
            rows * part.cols,
            part.data.len(),
        )?;
    }
    Ok(())
}

/// Both feature counts of `shape` must be positive (both backends check this first).
pub(super) fn check_features(shape: LinearShape) -> Result<(), NnError> {
    if shape.in_features == 0 || shape.out_features == 0 {
        return Err(NnError::Shape {
            operand: "linear layer".into(),
            message: format!(
                "in_features ({}) and out_features ({}) must be positive",
                shape.in_features, shape.out_features
            ),
        });
    }
    Ok(())
}

/// The input parts' widths must be positive and sum to `in_features`.
pub(super) fn check_widths(
    shape: LinearShape,
    widths: impl Iterator<Item = usize> + Clone,
) -> Result<(), NnError> {
    if widths.clone().sum::<usize>() != shape.in_features || widths.clone().any(|w| w == 0) {
        return Err(NnError::Shape {
            operand: "linear input".into(),
            message: format!(
                "input part widths {:?} must be positive and sum to in_features = {}",
                widths.collect::<Vec<_>>(),
                shape.in_features
            ),
        });
    }
    Ok(())
}

/// One gradient entry per input part.
pub(super) fn check_grad_count(grads: usize, parts: usize) -> Result<(), NnError> {
    if grads != parts {
        return Err(NnError::Shape {
            operand: "linear input gradients".into(),
            message: format!("{grads} entries for {parts} input parts"),
        });
    }
    Ok(())
}

/// Forward: `output = act(concat(inputs) W + b)`, `output` is `rows x out` and overwritten.
///
/// Each row block is one `gemm` per input part into its output rows, then the bias and the
/// activation in one pass over those rows while they are still cached.
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
    let blocks = RowBlocks::new::<T>(shape, rows);
    let plan = Plan::new(rows.saturating_mul(shape.weight_len()), blocks.count);
    let tasks: Vec<(usize, &mut [T])> = output.chunks_mut(blocks.size * out).enumerate().collect();
    plan.run(tasks, |(index, block)| {
        let first_row = index * blocks.size;
        let block_rows = block.len() / out;
        let mut weight_row = 0;
        for (part_index, part) in inputs.iter().enumerate() {
            gemm_into(
                (block_rows, out, part.cols),
                block,
                out,
                part_index > 0,
                View::new(part.data, first_row * part.cols, part.cols, 1),
                View::new(weight, weight_row * out, out, 1),
                plan.inside_gemm,
            );
            weight_row += part.cols;
        }
        match shape.activation {
            Activation::Identity => {
                for row in block.chunks_exact_mut(out) {
                    for (value, &b) in row.iter_mut().zip(bias) {
                        *value += b;
                    }
                }
            }
            Activation::Relu => {
                for row in block.chunks_exact_mut(out) {
                    for (value, &b) in row.iter_mut().zip(bias) {
                        *value = Activation::Relu.apply(*value + b);
                    }
                }
            }
        }
    });
    Ok(())
}

/// One input part's rows of one block: its gradient rows and whether to add into them.
type BlockInputGrad<'a, T> = Option<(&'a mut [T], bool)>;

/// One row block of the backward's first phase.
struct BackwardBlock<'a, T> {
    /// `dL/dY` of the block's rows, masked in place.
    d_output: &'a mut [T],
    /// The forward output of the block's rows.
    output: &'a [T],
    /// Per input part: the block's rows of its gradient and whether to add into them.
    d_inputs: Vec<BlockInputGrad<'a, T>>,
}

/// One weight-gradient task: `dst (+)= X_part[rows, cols]^T dY'[rows, :]`.
struct WeightTask<'a, T> {
    first_row: usize,
    rows: usize,
    part: usize,
    first_col: usize,
    /// `cols x out`, row-major: the task's rows of the weight gradient or of a partial.
    dst: &'a mut [T],
    accumulate: bool,
}

fn gcd(mut a: usize, mut b: usize) -> usize {
    while b != 0 {
        (a, b) = (b, a % b);
    }
    a
}

/// Backward of [`linear_forward`].
///
/// `output` is the forward output (for the ReLU mask). `d_output` holds `dL/dY` on entry
/// and `dL/d(pre-activation)` on return (masked in place to avoid a `rows x out` copy).
/// Weight and bias gradients are accumulated into `grads`, whose `inputs` has one entry per
/// input part.
///
/// Two phases, each a set of parallel tasks. Per row block: the ReLU mask and the bias
/// column sums in one pass, then `dX_part (+)= dY' W_part^T` (one `gemm`, the weight read
/// through swapped strides). Then `dW_part += X_part^T dY'`: the rows are cut into at most
/// `MAX_WEIGHT_CHUNKS` chunks (a function of `rows` only, so the sum order never depends
/// on the thread count), the first chunk's product accumulated straight into the weight
/// gradient by `gemm`, the others into partials added after in chunk order; each chunk's
/// product is split over weight rows into tiles so that there are a multiple of
/// `WEIGHT_TASKS` equal tasks. Chunks and tiles depend on the shape and `rows` only.
pub fn linear_backward<T: NnScalar>(
    shape: LinearShape,
    weight: &[T],
    inputs: &[InputPart<'_, T>],
    rows: usize,
    output: &[T],
    d_output: &mut [T],
    grads: LinearGrads<'_, '_, T>,
) -> Result<(), NnError> {
    let LinearGrads {
        weight: d_weight,
        bias: d_bias,
        inputs: d_inputs,
    } = grads;
    check_shape(shape, weight, inputs, rows)?;
    let out = shape.out_features;
    check_len("linear output", rows * out, output.len())?;
    check_len("linear output gradient", rows * out, d_output.len())?;
    check_len("linear weight gradient", shape.weight_len(), d_weight.len())?;
    check_len("linear bias gradient", out, d_bias.len())?;
    check_grad_count(d_inputs.len(), inputs.len())?;
    for (index, (part, grad)) in inputs.iter().zip(d_inputs.iter()).enumerate() {
        if let InputGrad::Write(buffer) | InputGrad::Accumulate(buffer) = grad {
            check_len(
                &format!("linear input part {index} gradient"),
                rows * part.cols,
                buffer.len(),
            )?;
        }
    }
    if rows == 0 {
        return Ok(());
    }

    let blocks = RowBlocks::new::<T>(shape, rows);
    let plan = Plan::new(rows.saturating_mul(shape.weight_len()), blocks.count);

    // Phase 1: per row block, mask + bias sums, then the input gradients.
    let mut d_input_blocks: Vec<std::vec::IntoIter<BlockInputGrad<'_, T>>> = d_inputs
        .iter_mut()
        .zip(inputs)
        .map(|(grad, part)| {
            let (buffer, accumulate) = match grad {
                InputGrad::Skip => {
                    return (0..blocks.count)
                        .map(|_| None)
                        .collect::<Vec<_>>()
                        .into_iter();
                }
                InputGrad::Write(buffer) => (&mut **buffer, false),
                InputGrad::Accumulate(buffer) => (&mut **buffer, true),
            };
            buffer
                .chunks_mut(blocks.size * part.cols)
                .map(|block| Some((block, accumulate)))
                .collect::<Vec<_>>()
                .into_iter()
        })
        .collect();
    let block_tasks: Vec<BackwardBlock<'_, T>> = d_output
        .chunks_mut(blocks.size * out)
        .zip(output.chunks(blocks.size * out))
        .map(|(d_block, y_block)| BackwardBlock {
            d_output: d_block,
            output: y_block,
            d_inputs: d_input_blocks
                .iter_mut()
                .map(|blocks| blocks.next().flatten())
                .collect(),
        })
        .collect();
    let column_sums = plan.run(block_tasks, |task| {
        backward_block(shape, weight, inputs, task, plan.inside_gemm)
    });
    // Bias gradient: column sums per block, then over blocks in order (deterministic).
    for sums in &column_sums {
        for (g, &s) in d_bias.iter_mut().zip(sums) {
            *g += s;
        }
    }

    // Phase 2: the weight gradient.
    let d_pre: &[T] = d_output;
    let chunks = (rows / WEIGHT_CHUNK_ROWS).clamp(1, MAX_WEIGHT_CHUNKS);
    let chunk_rows = rows.div_ceil(chunks);
    // Tasks = chunks x tiles, a multiple of WEIGHT_TASKS. The tiles, too, depend on the
    // shape and the row count only: a tile's width can change how `gemm` blocks its sums.
    let tiles = WEIGHT_TASKS / gcd(chunks, WEIGHT_TASKS);
    let mut partials: Vec<Vec<T>> = (1..chunks)
        .map(|_| vec![T::ZERO; shape.weight_len()])
        .collect();
    let mut weight_tasks: Vec<WeightTask<'_, T>> = Vec::new();
    let destinations =
        std::iter::once(&mut *d_weight).chain(partials.iter_mut().map(Vec::as_mut_slice));
    for (chunk, mut rest) in destinations.enumerate() {
        let first_row = chunk * chunk_rows;
        let chunk_len = chunk_rows.min(rows - first_row);
        for (part_index, part) in inputs.iter().enumerate() {
            let part_tiles = tiles.min(part.cols / MIN_WEIGHT_TILE).max(1);
            let tile_cols = part.cols.div_ceil(part_tiles);
            let mut first_col = 0;
            while first_col < part.cols {
                let cols = tile_cols.min(part.cols - first_col);
                let (dst, tail) = rest.split_at_mut(cols * out);
                rest = tail;
                weight_tasks.push(WeightTask {
                    first_row,
                    rows: chunk_len,
                    part: part_index,
                    first_col,
                    dst,
                    accumulate: chunk == 0,
                });
                first_col += cols;
            }
        }
    }
    plan.run(weight_tasks, |task| {
        let part = &inputs[task.part];
        gemm_into(
            (task.dst.len() / out, out, task.rows),
            task.dst,
            out,
            task.accumulate,
            View::new(
                part.data,
                task.first_row * part.cols + task.first_col,
                1,
                part.cols,
            ),
            View::new(d_pre, task.first_row * out, out, 1),
            plan.inside_gemm,
        );
    });
    if !partials.is_empty() {
        // In chunk order for every entry, so the sum does not depend on the threads.
        let block = REDUCE_BLOCK;
        let add = |(index, dst): (usize, &mut [T])| {
            let start = index * block;
            for partial in &partials {
                for (g, &p) in dst.iter_mut().zip(&partial[start..]) {
                    *g += p;
                }
            }
        };
        if plan.across_tasks {
            d_weight.par_chunks_mut(block).enumerate().for_each(add);
        } else {
            d_weight.chunks_mut(block).enumerate().for_each(add);
        }
    }
    Ok(())
}

/// Phase 1 of [`linear_backward`] on one row block; returns the block's bias column sums.
fn backward_block<T: NnScalar>(
    shape: LinearShape,
    weight: &[T],
    inputs: &[InputPart<'_, T>],
    task: BackwardBlock<'_, T>,
    parallelism: Parallelism,
) -> Vec<T> {
    let out = shape.out_features;
    let mut sums = vec![T::ZERO; out];
    match shape.activation {
        Activation::Identity => {
            for d_row in task.d_output.chunks_exact(out) {
                for (sum, &d) in sums.iter_mut().zip(d_row) {
                    *sum += d;
                }
            }
        }
        Activation::Relu => {
            for (d_row, y_row) in task
                .d_output
                .chunks_exact_mut(out)
                .zip(task.output.chunks_exact(out))
            {
                // An unconditional store (of `d` or 0) lets the loop vectorise.
                for ((sum, d), &y) in sums.iter_mut().zip(d_row).zip(y_row) {
                    let masked = if y > T::ZERO { *d } else { T::ZERO };
                    *d = masked;
                    *sum += masked;
                }
            }
        }
    }
    let block_rows = task.d_output.len() / out;
    let d_pre: &[T] = task.d_output;
    let mut weight_row = 0;
    for (part, d_input) in inputs.iter().zip(task.d_inputs) {
        if let Some((buffer, accumulate)) = d_input {
            // dX_part (+)= dY' W_part^T: (block x out) (out x cols), W read transposed.
            gemm_into(
                (block_rows, part.cols, out),
                buffer,
                part.cols,
                accumulate,
                View::new(d_pre, 0, out, 1),
                View::new(weight, weight_row * out, 1, out),
                parallelism,
            );
        }
        weight_row += part.cols;
    }
    sums
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

    /// The input parts of column blocks of the given widths.
    fn input_parts<'a>(blocks: &'a [Vec<f64>], widths: &[usize]) -> Vec<InputPart<'a, f64>> {
        blocks
            .iter()
            .zip(widths)
            .map(|(data, &cols)| InputPart { data, cols })
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
        let parts = input_parts(&blocks, widths);
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
        let parts = input_parts(blocks, widths);
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
            let parts = input_parts(&blocks, &widths);
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
                    inputs: &mut [
                        InputGrad::Write(&mut d_input0),
                        InputGrad::Accumulate(&mut d_input1),
                    ],
                },
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

    /// The backward by naive loops over the concatenated input: `(dW, db, dX)` for
    /// `dL/dY = d_output`, independent of `gemm`, the row blocks and the threads.
    fn naive_backward(
        shape: LinearShape,
        weight: &[f64],
        input: &[f64],
        rows: usize,
        output: &[f64],
        d_output: &[f64],
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let (n_in, n_out) = (shape.in_features, shape.out_features);
        let d_pre: Vec<f64> = d_output
            .iter()
            .zip(output)
            .map(|(&d, &y)| match shape.activation {
                Activation::Relu if y <= 0.0 => 0.0,
                _ => d,
            })
            .collect();
        let mut d_weight = vec![0.0; n_in * n_out];
        let mut d_bias = vec![0.0; n_out];
        let mut d_input = vec![0.0; rows * n_in];
        for r in 0..rows {
            for j in 0..n_out {
                let d = d_pre[r * n_out + j];
                d_bias[j] += d;
                for i in 0..n_in {
                    d_weight[i * n_out + j] += input[r * n_in + i] * d;
                    d_input[r * n_in + i] += d * weight[i * n_out + j];
                }
            }
        }
        (d_weight, d_bias, d_input)
    }

    /// Every way a call spreads over threads (serial; row blocks and weight-gradient chunks
    /// and tiles as tasks; one block with `gemm`'s own threads) against the naive product,
    /// with several input parts, the weight read transposed for `dX` and the input read
    /// transposed for `dW`. The results must also be bitwise the same for every thread count.
    #[test]
    fn backward_matches_naive_products_on_every_plan() {
        // (rows, part widths, out): 6200 rows are 2 blocks and 3 weight chunks (the wider
        // part in 2 tiles), tasks on 2 threads, gemm's own threads on 3; 4 rows stay
        // serial; 70 rows of 200 x 150 are one block and one chunk in 12 tiles, large
        // enough for gemm's own threads.
        let cases: [(usize, &[usize], usize); 3] = [
            (6200, &[40, 13], 24),
            (4, &[3, 2], 5),
            (70, &[120, 80], 150),
        ];
        for (rows, widths, out) in cases {
            let mut rng = Rng::new(5);
            let n_in: usize = widths.iter().sum();
            for activation in [Activation::Relu, Activation::Identity] {
                let shape = LinearShape {
                    in_features: n_in,
                    out_features: out,
                    activation,
                };
                let weight = random_vec(&mut rng, n_in * out);
                let bias = random_vec(&mut rng, out);
                let input = random_vec(&mut rng, rows * n_in);
                let d_output = random_vec(&mut rng, rows * out);
                let blocks = split_columns(&input, rows, widths);
                let parts = input_parts(&blocks, widths);
                let output = naive_forward(shape, &weight, &bias, &input, rows);
                let (d_weight, d_bias, d_input) =
                    naive_backward(shape, &weight, &input, rows, &output, &d_output);
                let d_input_blocks = split_columns(&d_input, rows, widths);
                let mut first: Option<Vec<Vec<f64>>> = None;
                for threads in [1, 2, 3] {
                    let pool = rayon::ThreadPoolBuilder::new()
                        .num_threads(threads)
                        .build()
                        .unwrap();
                    let results = pool.install(|| {
                        let mut forward = vec![f64::NAN; rows * out];
                        linear_forward(shape, &weight, &bias, &parts, rows, &mut forward).unwrap();
                        // Parameter gradients start non-zero (they accumulate); part 0 is
                        // written over NaN, part 1 added to 1.
                        let mut grad_weight = vec![0.5; n_in * out];
                        let mut grad_bias = vec![-0.25; out];
                        let mut grad_input0 = vec![f64::NAN; rows * widths[0]];
                        let mut grad_input1 = vec![1.0; rows * widths[1]];
                        let mut d_pre = d_output.clone();
                        linear_backward(
                            shape,
                            &weight,
                            &parts,
                            rows,
                            &forward,
                            &mut d_pre,
                            LinearGrads {
                                weight: &mut grad_weight,
                                bias: &mut grad_bias,
                                inputs: &mut [
                                    InputGrad::Write(&mut grad_input0),
                                    InputGrad::Accumulate(&mut grad_input1),
                                ],
                            },
                        )
                        .unwrap();
                        vec![forward, grad_weight, grad_bias, grad_input0, grad_input1]
                    });
                    let expected: [(&[f64], f64); 5] = [
                        (&output, 0.0),
                        (&d_weight, 0.5),
                        (&d_bias, -0.25),
                        (&d_input_blocks[0], 0.0),
                        (&d_input_blocks[1], 1.0),
                    ];
                    for (name, (got, (want, offset))) in ["Y", "dW", "db", "dX0", "dX1"]
                        .iter()
                        .zip(results.iter().zip(expected))
                    {
                        assert_eq!(got.len(), want.len());
                        for (index, (a, b)) in got.iter().zip(want).enumerate() {
                            let b = b + offset;
                            assert!(
                                (a - b).abs() <= 1e-10 * (1.0 + b.abs()),
                                "{rows} rows, {threads} threads, {activation:?}: \
                                 {name}[{index}] {a} vs {b}"
                            );
                        }
                    }
                    match &first {
                        None => first = Some(results),
                        Some(first) => assert!(
                            first
                                .iter()
                                .flatten()
                                .zip(results.iter().flatten())
                                .all(|(a, b)| a.to_bits() == b.to_bits()),
                            "{rows} rows: {threads} threads differ bitwise from 1 thread"
                        ),
                    }
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
