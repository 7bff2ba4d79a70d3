//! The `gpu` twins of the dense-layer, positional-encoding and Adam operations (f32, WGSL).
//!
//! [`NnGpu`] compiles the kernels of `shaders/nn_*.wgsl` once for a device and records work
//! into a caller's `wgpu::CommandEncoder`, so a training step is one submission. Buffers are
//! the caller's: storage buffers of f32 in the layouts of the [`nn`](crate::nn) module. Every
//! operation here has a `cpu` twin with the same name and the same conventions, and a parity
//! test. One difference: [`NnGpu::linear_backward`] leaves `d_output` untouched (the ReLU mask
//! is applied while loading), where the `cpu` version masks it in place.
//!
//! The matrix product is one tiled kernel (`nn_matmul.wgsl`, 64 x 64 output tiles, shared
//! memory, fused bias and ReLU); backward reads `W` or `X` transposed through strides. The
//! weight gradient sums over all rows, which leaves few output tiles for a large reduction,
//! so it is split along the rows into partial products in a scratch buffer, then summed in
//! order by `nn_reduce.wgsl` (no float atomics, deterministic).
//!
//! Where the adapter has tensor cores ([`TensorCores`]) and [`Precision::Mixed`] asks for
//! them, [`NnGpu::for_context`] picks, once, the tensor-core path for all three products of a
//! layer (`Y = X W`, `dX = dY' W^T`, `dW = X^T dY'`): each operand is scaled by a power of two
//! and packed to padded f16 (`nn_matmul_f16.wgsl`), multiplied on 16 x 16 x 16 cooperative
//! matrices with f32 accumulators (`nn_matmul_coop.wgsl`), and unscaled, split-summed and
//! finished with the same epilogue (accumulate, bias, ReLU). Weights, gradients and Adam
//! state stay f32 buffers; only the products' operands are rounded to f16.

use std::sync::Mutex;

use super::adam::{AdamConfig, AdamStepFactors};
use super::encoding::PositionalEncoding;
use super::linear::{Activation, LinearShape, check_features, check_grad_count, check_widths};
use super::{NnError, Precision};
use crate::backend::{GpuContext, Kernel, TensorCores};
pub use crate::backend::{PreparedDispatch, Record};

const MATMUL_WGSL: &str = include_str!("../../../../shaders/nn_matmul.wgsl");
const REDUCE_WGSL: &str = include_str!("../../../../shaders/nn_reduce.wgsl");
const ADAM_WGSL: &str = include_str!("../../../../shaders/nn_adam.wgsl");
const POSENC_WGSL: &str = include_str!("../../../../shaders/nn_posenc.wgsl");
const RODRIGUES_WGSL: &str = include_str!("../../../../shaders/nn_rodrigues.wgsl");
const FINITE_WGSL: &str = include_str!("../../../../shaders/nn_finite.wgsl");
const MATMUL_F16_WGSL: &str = include_str!("../../../../shaders/nn_matmul_f16.wgsl");
const MATMUL_COOP_WGSL: &str = include_str!("../../../../shaders/nn_matmul_coop.wgsl");

/// Output block edge of the tensor-core kernel (a 2 x 2 of 16 x 16 tiles per subgroup), as in
/// `nn_matmul_coop.wgsl`; rows of A and columns of B are padded to multiples of it.
const COOP_BLOCK: usize = 32;
/// Reduction step of the tensor-core kernel (K of the 16 x 16 x 16 matrices).
const COOP_TILE_K: usize = 16;
/// Workgroups the tensor-core weight-gradient split aims for: each is one subgroup, so many
/// more than the f32 kernel's 256-thread groups are needed to fill a large GPU.
const COOP_TARGET_WORKGROUPS: usize = 2048;
/// Workgroup size of the staging kernels of `nn_matmul_f16.wgsl`.
const STAGING_WORKGROUP: usize = 256;

/// Output tile edge of the matrix kernel (rows and columns), as in `nn_matmul.wgsl`.
const TILE: usize = 64;
/// Reduction step of the matrix kernel; k slices are multiples of it.
const TILE_K: usize = 16;
/// Enough workgroups to fill a large GPU; the weight-gradient split aims for this many.
const TARGET_WORKGROUPS: usize = 512;
/// Rows summed by one workgroup of `column_sums`.
const COLUMN_SUM_ROWS: usize = 256;

// Bits of the matrix kernel's flags, as in `nn_matmul.wgsl`.
const ACCUMULATE: u32 = 1;
const ADD_BIAS: u32 = 2;
const RELU: u32 = 4;
const MASK_A: u32 = 8;
const MASK_B: u32 = 16;

/// One input block of a layer on the gpu: a `rows x cols` f32 storage buffer.
#[derive(Clone, Copy, Debug)]
pub struct GpuInputPart<'a> {
    /// The matrix, row-major, starting at offset 0.
    pub buffer: &'a wgpu::Buffer,
    /// Its number of columns.
    pub cols: usize,
}

/// Where the gradient with respect to one input part goes.
#[derive(Clone, Copy, Debug)]
pub enum GpuInputGrad<'a> {
    /// Not needed.
    Skip,
    /// Overwrite this `rows x cols` buffer.
    Write(&'a wgpu::Buffer),
    /// Add into this `rows x cols` buffer.
    Accumulate(&'a wgpu::Buffer),
}

/// A layer's gradient buffers: its parameters' (accumulated into) and its input parts'.
#[derive(Clone, Copy, Debug)]
pub struct GpuLinearGrads<'a> {
    /// `in x out`.
    pub weight: &'a wgpu::Buffer,
    /// `out`.
    pub bias: &'a wgpu::Buffer,
    /// One entry per input part.
    pub inputs: &'a [GpuInputGrad<'a>],
}

/// The values one Adam update steps (`len` of them) and their optimiser state.
#[derive(Clone, Copy, Debug)]
pub struct GpuAdamValues<'a> {
    pub params: &'a wgpu::Buffer,
    pub grads: &'a wgpu::Buffer,
    pub first_moment: &'a wgpu::Buffer,
    pub second_moment: &'a wgpu::Buffer,
    pub len: usize,
}

/// A dense layer on the gpu: its shape and its `in x out` weight buffer.
#[derive(Clone, Copy, Debug)]
pub struct GpuLinear<'a> {
    pub shape: LinearShape,
    pub weight: &'a wgpu::Buffer,
}

/// A layer's input on the gpu: `rows` rows, the concatenation of `parts`.
#[derive(Clone, Copy, Debug)]
pub struct GpuInput<'a> {
    pub parts: &'a [GpuInputPart<'a>],
    pub rows: usize,
}

impl<'a> GpuLinear<'a> {
    pub fn new(shape: LinearShape, weight: &'a wgpu::Buffer) -> Self {
        GpuLinear { shape, weight }
    }
}

impl<'a> GpuInput<'a> {
    pub fn new(parts: &'a [GpuInputPart<'a>], rows: usize) -> Self {
        GpuInput { parts, rows }
    }
}

/// One step of a [`NnProgram`].
#[derive(Clone, Debug)]
enum ProgramStep {
    Dispatch(PreparedDispatch),
    Clear(wgpu::Buffer),
}

/// A recorded sequence of `nn` operations whose uniform blocks and bind groups were created
/// once (by calling the [`NnGpu`] operations with the program as their [`Record`]); replayed
/// into an encoder by [`NnProgram::replay`] without creating or uploading anything. The
/// buffers it binds are kept alive by the program; their contents are read when the
/// replayed commands run.
#[derive(Clone, Debug, Default)]
pub struct NnProgram {
    steps: Vec<ProgramStep>,
}

impl Record for NnProgram {
    fn record_dispatch(&mut self, dispatch: PreparedDispatch) {
        self.steps.push(ProgramStep::Dispatch(dispatch));
    }

    fn record_clear(&mut self, buffer: &wgpu::Buffer) {
        self.steps.push(ProgramStep::Clear(buffer.clone()));
    }
}

impl NnProgram {
    pub fn new() -> Self {
        NnProgram::default()
    }

    /// Number of recorded steps (dispatches and clears).
    pub fn len(&self) -> usize {
        self.steps.len()
    }

    pub fn is_empty(&self) -> bool {
        self.steps.is_empty()
    }

    /// Records the program into `encoder`: consecutive dispatches share one compute pass
    /// (wgpu orders their storage accesses), clears run between passes.
    pub fn replay(&self, encoder: &mut wgpu::CommandEncoder) {
        let mut index = 0;
        while index < self.steps.len() {
            match &self.steps[index] {
                ProgramStep::Clear(buffer) => {
                    encoder.clear_buffer(buffer, 0, None);
                    index += 1;
                }
                ProgramStep::Dispatch(_) => {
                    let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor {
                        label: Some("nn program"),
                        timestamp_writes: None,
                    });
                    while let Some(ProgramStep::Dispatch(dispatch)) = self.steps.get(index) {
                        dispatch.record_into(&mut pass);
                        index += 1;
                    }
                }
            }
        }
    }
}

/// A strided operand of the matrix kernel: element `(i, j)` at
/// `offset + i * row_stride + j * col_stride`.
#[derive(Clone, Copy)]
struct Operand<'a> {
    buffer: &'a wgpu::Buffer,
    offset: usize,
    row_stride: usize,
    col_stride: usize,
}

impl<'a> Operand<'a> {
    fn new(buffer: &'a wgpu::Buffer, offset: usize, row_stride: usize, col_stride: usize) -> Self {
        Self {
            buffer,
            offset,
            row_stride,
            col_stride,
        }
    }
}

/// One product `C (+)= A (m x k) * B (k x n)` of the matrix kernel, `dims = (m, n, k)`: `mask`
/// (the ReLU mask, by `flags`) and `bias` where the flags use them, C row-major at `c_offset`.
#[derive(Clone, Copy)]
struct Product<'a> {
    dims: (usize, usize, usize),
    a: Operand<'a>,
    b: Operand<'a>,
    mask: Option<&'a wgpu::Buffer>,
    bias: Option<&'a wgpu::Buffer>,
    c: &'a wgpu::Buffer,
    c_offset: usize,
    flags: u32,
}

/// `Params` in `nn_matmul.wgsl` (its layout is checked against the WGSL by a test).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct MatmulParams {
    m: u32,
    n: u32,
    k: u32,
    flags: u32,
    a_offset: u32,
    a_row_stride: u32,
    a_col_stride: u32,
    b_offset: u32,
    b_row_stride: u32,
    b_col_stride: u32,
    c_offset: u32,
    c_row_stride: u32,
    k_per_split: u32,
    m_tiles: u32,
    split_stride: u32,
    pad: u32,
}

/// `Params` in `nn_matmul_f16.wgsl` (operand staging and epilogue of the tensor-core path).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct StagingParams {
    rows: u32,
    cols: u32,
    offset: u32,
    row_stride: u32,
    col_stride: u32,
    mask_flags: u32,
    slot: u32,
    rows_pad: u32,
    cols_pad: u32,
    m: u32,
    n: u32,
    n_pad: u32,
    splits: u32,
    partial_stride: u32,
    c_offset: u32,
    c_row_stride: u32,
    c_flags: u32,
    pad: [u32; 3],
}

/// `Params` in `nn_matmul_coop.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct CoopParams {
    k_pad: u32,
    n_pad: u32,
    m_blocks: u32,
    k_per_split: u32,
    partial_stride: u32,
    pad: [u32; 3],
}

/// `Params` in `nn_adam.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct AdamParams {
    len: u32,
    slot: u32,
    pad0: [u32; 2],
    beta1: f32,
    beta2: f32,
    one_minus_beta1: f32,
    one_minus_beta2: f32,
    eps: f32,
    pad: [u32; 3],
}

/// `Params` in `nn_finite.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct FiniteParams {
    len: u32,
    slot: u32,
    pad: [u32; 2],
}

/// `Params` in `nn_rodrigues.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct RodriguesParams {
    count: u32,
    epsilon: f32,
    pad: [u32; 2],
}

/// `Params` in `nn_posenc.wgsl`.
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct PosencParams {
    rows: u32,
    in_features: u32,
    frequencies: u32,
    include_input: u32,
    pad: [u32; 4],
}

/// `Params` in `nn_reduce.wgsl`: `p0..p4` read per entry point (see the WGSL).
#[repr(C)]
#[derive(Clone, Copy, bytemuck::Pod, bytemuck::Zeroable)]
pub(crate) struct ReduceParams {
    p: [u32; 5],
    pad: [u32; 3],
}

/// This module's uniform structs for the layout test in `backend::shaders`.
#[cfg(test)]
pub(crate) fn wgsl_twins() -> Vec<crate::backend::shaders::tests::WgslTwin> {
    use crate::backend::shaders::tests::wgsl_twin;
    vec![
        wgsl_twin!(MatmulParams as "Params" in ["nn_matmul.wgsl"] {
            m, n, k, flags, a_offset, a_row_stride, a_col_stride, b_offset, b_row_stride,
            b_col_stride, c_offset, c_row_stride, k_per_split, m_tiles, split_stride, pad as "_pad",
        }),
        wgsl_twin!(StagingParams as "Params" in ["nn_matmul_f16.wgsl"] {
            rows, cols, offset, row_stride, col_stride, mask_flags, slot, rows_pad, cols_pad, m, n,
            n_pad, splits, partial_stride, c_offset, c_row_stride, c_flags, pad[0] as "_pad0",
            pad[1] as "_pad1", pad[2] as "_pad2",
        }),
        wgsl_twin!(CoopParams as "Params" in ["nn_matmul_coop.wgsl"] {
            k_pad, n_pad, m_blocks, k_per_split, partial_stride, pad[0] as "_pad0",
            pad[1] as "_pad1", pad[2] as "_pad2",
        }),
        wgsl_twin!(AdamParams as "Params" in ["nn_adam.wgsl"] {
            len, slot, pad0[0] as "_pad0", pad0[1] as "_pad1", beta1, beta2, one_minus_beta1,
            one_minus_beta2, eps, pad[0] as "_pad2", pad[1] as "_pad3", pad[2] as "_pad4",
        }),
        wgsl_twin!(FiniteParams as "Params" in ["nn_finite.wgsl"] {
            len, slot, pad[0] as "_pad0", pad[1] as "_pad1",
        }),
        wgsl_twin!(RodriguesParams as "Params" in ["nn_rodrigues.wgsl"] {
            count, epsilon, pad[0] as "_pad0", pad[1] as "_pad1",
        }),
        wgsl_twin!(PosencParams as "Params" in ["nn_posenc.wgsl"] {
            rows, in_features, frequencies, include_input, pad[0] as "_pad0", pad[1] as "_pad1",
            pad[2] as "_pad2", pad[3] as "_pad3",
        }),
        wgsl_twin!(ReduceParams as "Params" in ["nn_reduce.wgsl"] {
            p[0] as "p0", p[1] as "p1", p[2] as "p2", p[3] as "p3", p[4] as "p4", pad[0] as "_pad0",
            pad[1] as "_pad1", pad[2] as "_pad2",
        }),
    ]
}

/// How the dense layers' matrix products run on one [`NnGpu`], chosen once when it is made.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MatmulPath {
    /// `nn_matmul.wgsl`: f32 operands and accumulation, on every adapter; the reference.
    F32,
    /// `nn_matmul_coop.wgsl` on the adapter's tensor cores: f16 operands (scaled by powers
    /// of two), f32 accumulation.
    TensorCores(TensorCores),
}

impl MatmulPath {
    /// The path [`NnGpu::for_context`] takes on `context` for `precision`: the tensor cores
    /// where `precision` is [`Precision::Mixed`] and the device was opened with them
    /// ([`GpuContext::tensor_cores`]), else f32. The one place the choice is made, so a run's
    /// log line ([`MatmulPath::describe`]) always names the path its kernels take.
    pub fn choose(context: &GpuContext, precision: Precision) -> Self {
        match (precision, context.tensor_cores()) {
            (Precision::Mixed, Some(cores)) => Self::TensorCores(cores),
            _ => Self::F32,
        }
    }

    /// The path of the networks on `backend` for `precision`: [`MatmulPath::choose`] on the
    /// gpu, f32 on `cpu` (which always runs f32).
    pub fn of_backend(backend: &crate::backend::Backend, precision: Precision) -> Self {
        match backend {
            crate::backend::Backend::Cpu => Self::F32,
            crate::backend::Backend::Gpu(context) => Self::choose(context, precision),
        }
    }

    /// One line for run summaries: `networks: f16 tensor cores (16x16x16)` or
    /// `networks: f32`.
    pub fn describe(self) -> String {
        match self {
            Self::F32 => "networks: f32".to_owned(),
            Self::TensorCores(_) => {
                let shape = TensorCores::SHAPE;
                format!("networks: f16 tensor cores ({shape}x{shape}x{shape})")
            }
        }
    }
}

/// The kernels and scratch buffers of the tensor-core path.
#[derive(Debug)]
struct TensorCoreKernels {
    cores: TensorCores,
    operand_max: Kernel,
    pack: Kernel,
    multiply: Kernel,
    epilogue: Kernel,
    /// The two operands' largest magnitudes (`scales` in `nn_matmul_f16.wgsl`), cleared
    /// before each product.
    scales: wgpu::Buffer,
    /// The padded f16 copies of A and B and the f32 partial products; grown on demand and
    /// reused by every product (commands run in order).
    packed_a: Mutex<Option<wgpu::Buffer>>,
    packed_b: Mutex<Option<wgpu::Buffer>>,
    partials: Mutex<Option<wgpu::Buffer>>,
}

impl TensorCoreKernels {
    fn new(device: &wgpu::Device, cores: TensorCores) -> Result<Self, NnError> {
        let subgroup = [("SUBGROUP_SIZE", f64::from(cores.subgroup_size))];
        let multiply = compile(
            device,
            "nn_matmul_coop",
            MATMUL_COOP_WGSL,
            "multiply",
            &subgroup,
        )?;
        let staging = |name, entry| compile(device, name, MATMUL_F16_WGSL, entry, &[]);
        Ok(TensorCoreKernels {
            cores,
            operand_max: staging("nn_matmul_operand_max", "operand_max")?,
            pack: staging("nn_matmul_pack", "pack")?,
            multiply,
            epilogue: staging("nn_matmul_epilogue", "epilogue")?,
            scales: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("nn tensor-core scales"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            }),
            packed_a: Mutex::new(None),
            packed_b: Mutex::new(None),
            partials: Mutex::new(None),
        })
    }
}

/// [`Kernel::compile_with_constants`], its error as an [`NnError`].
fn compile(
    device: &wgpu::Device,
    name: &'static str,
    wgsl: &'static str,
    entry: &'static str,
    constants: &[(&str, f64)],
) -> Result<Kernel, NnError> {
    Kernel::compile_with_constants(device, name, wgsl, entry, constants)
        .map_err(|error| NnError::Gpu(error.to_string()))
}

/// The dense-network kernels compiled for one device.
#[derive(Debug)]
pub struct NnGpu {
    device: wgpu::Device,
    matmul: Kernel,
    column_sums: Kernel,
    accumulate_partials: Kernel,
    adam: Kernel,
    posenc_forward: Kernel,
    posenc_backward: Kernel,
    rodrigues_forward: Kernel,
    rodrigues_backward: Kernel,
    finite: Kernel,
    /// The tensor-core path's kernels, where it was chosen ([`NnGpu::for_context`]).
    tensor_cores: Option<TensorCoreKernels>,
    /// Bound to read-only slots a dispatch does not use.
    placeholder: wgpu::Buffer,
    /// Partial sums of the split reductions; grown on demand, reused across calls (commands
    /// run in order, so one region serves every reduction of a step).
    scratch: Mutex<Option<wgpu::Buffer>>,
    max_binding_bytes: u64,
    max_groups_per_dimension: u32,
}

fn to_u32(what: &str, value: usize) -> Result<u32, NnError> {
    u32::try_from(value).map_err(|_| {
        NnError::Gpu(format!(
            "{what} = {value} does not fit the kernels' 32-bit indices"
        ))
    })
}

impl NnGpu {
    /// Compiles every kernel for the context's device, choosing the matrix products' path
    /// once: the tensor cores where `precision` is [`Precision::Mixed`] and the device was
    /// opened with them ([`GpuContext::tensor_cores`]), else f32. A tensor-core kernel the
    /// driver rejects is an error, not a silent fallback.
    pub fn for_context(context: &GpuContext, precision: Precision) -> Result<Self, NnError> {
        let mut nn = Self::new(context.device())?;
        if let MatmulPath::TensorCores(cores) = MatmulPath::choose(context, precision) {
            nn.tensor_cores = Some(TensorCoreKernels::new(context.device(), cores)?);
        }
        Ok(nn)
    }

    /// The path the dense layers' products take.
    pub fn matmul_path(&self) -> MatmulPath {
        self.tensor_cores
            .as_ref()
            .map_or(MatmulPath::F32, |kernels| {
                MatmulPath::TensorCores(kernels.cores)
            })
    }

    /// One line for run summaries: `networks: f16 tensor cores (16x16x16)` or
    /// `networks: f32`.
    pub fn describe(&self) -> String {
        self.matmul_path().describe()
    }

    /// Compiles every kernel for `device`, with f32 matrix products (see
    /// [`NnGpu::for_context`] for the choice of tensor cores).
    pub fn new(device: &wgpu::Device) -> Result<Self, NnError> {
        let compile = |name, wgsl, entry| compile(device, name, wgsl, entry, &[]);
        let limits = device.limits();
        Ok(NnGpu {
            device: device.clone(),
            matmul: compile("nn_matmul", MATMUL_WGSL, "main")?,
            column_sums: compile("nn_column_sums", REDUCE_WGSL, "column_sums")?,
            accumulate_partials: compile(
                "nn_accumulate_partials",
                REDUCE_WGSL,
                "accumulate_partials",
            )?,
            adam: compile("nn_adam", ADAM_WGSL, "main")?,
            posenc_forward: compile("nn_posenc_forward", POSENC_WGSL, "forward")?,
            posenc_backward: compile("nn_posenc_backward", POSENC_WGSL, "backward")?,
            rodrigues_forward: compile("nn_rodrigues_forward", RODRIGUES_WGSL, "forward")?,
            rodrigues_backward: compile("nn_rodrigues_backward", RODRIGUES_WGSL, "backward")?,
            finite: compile("nn_finite", FINITE_WGSL, "main")?,
            tensor_cores: None,
            placeholder: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("nn placeholder"),
                size: 16,
                usage: wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            }),
            scratch: Mutex::new(None),
            max_binding_bytes: limits
                .max_storage_buffer_binding_size
                .min(limits.max_buffer_size),
            max_groups_per_dimension: limits.max_compute_workgroups_per_dimension,
        })
    }

    /// Lays out 1D launches in 2D beyond `limit` workgroups per dimension (at most the
    /// device's limit): what [`GpuContext::with_dispatch_limit`](crate::backend::GpuContext::with_dispatch_limit)
    /// does for the context's kernels, so tests reach the 2D grids with small inputs.
    pub fn with_max_workgroups_per_dimension(mut self, limit: u32) -> Self {
        self.max_groups_per_dimension = self.max_groups_per_dimension.min(limit.max(1));
        self
    }

    /// Checks that `buffer` holds at least `elements` f32 values and can be bound whole.
    fn check_buffer(
        &self,
        operand: &str,
        buffer: &wgpu::Buffer,
        elements: usize,
    ) -> Result<(), NnError> {
        let available = (buffer.size() / 4) as usize;
        if available < elements {
            return Err(NnError::Length {
                operand: operand.to_owned(),
                expected: elements,
                actual: available,
            });
        }
        if buffer.size() > self.max_binding_bytes {
            return Err(NnError::Gpu(format!(
                "{operand}: buffer of {} bytes exceeds the device's binding limit of {} bytes",
                buffer.size(),
                self.max_binding_bytes
            )));
        }
        Ok(())
    }

    /// A storage buffer of at least `bytes` from `slot`, replaced by a larger one when it is
    /// too small (sizes rounded up to powers of two within the binding limit).
    fn grown(
        &self,
        slot: &Mutex<Option<wgpu::Buffer>>,
        label: &'static str,
        bytes: usize,
    ) -> Result<wgpu::Buffer, NnError> {
        let max_binding_bytes = self.max_binding_bytes;
        let bytes = (bytes as u64).max(16).div_ceil(4) * 4;
        if bytes > max_binding_bytes {
            return Err(NnError::Gpu(format!(
                "{label} of {bytes} bytes exceeds the device's binding limit of {max_binding_bytes} bytes"
            )));
        }
        let mut slot = slot
            .lock()
            .map_err(|_| NnError::Gpu(format!("{label} lock poisoned")))?;
        match &*slot {
            Some(buffer) if buffer.size() >= bytes => Ok(buffer.clone()),
            _ => {
                let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some(label),
                    size: bytes.next_power_of_two().min(max_binding_bytes),
                    usage: wgpu::BufferUsages::STORAGE,
                    mapped_at_creation: false,
                });
                *slot = Some(buffer.clone());
                Ok(buffer)
            }
        }
    }

    /// A scratch buffer of at least `elements` f32 values.
    fn scratch(&self, elements: usize) -> Result<wgpu::Buffer, NnError> {
        self.grown(&self.scratch, "reduction scratch", elements * 4)
    }

    /// A 1D launch of `workgroups` as a grid within the per-dimension limit: `(x, y)`.
    fn grid(&self, workgroups: usize) -> Result<(u32, u32), NnError> {
        let max = self.max_groups_per_dimension.max(1) as usize;
        let y = workgroups.div_ceil(max).max(1);
        let x = workgroups.div_ceil(y);
        if y > max {
            return Err(NnError::Gpu(format!(
                "{workgroups} workgroups exceed the device's grid"
            )));
        }
        Ok((to_u32("workgroups", x)?, to_u32("workgroups", y)?))
    }

    /// `C (+)= A (m x k) * B (k x n)` with the given flags; C row-major at `c_offset`.
    fn matmul(&self, encoder: &mut impl Record, product: Product<'_>) -> Result<(), NnError> {
        let Product {
            dims: (m, n, k),
            a,
            b,
            mask,
            bias,
            c,
            c_offset,
            flags,
        } = product;
        if m == 0 || n == 0 {
            return Ok(());
        }
        if let Some(kernels) = &self.tensor_cores {
            return self.matmul_tensor_cores(encoder, kernels, product);
        }
        let m_tiles = m.div_ceil(TILE);
        let n_tiles = n.div_ceil(TILE);
        // Split along k when the output has few tiles and the reduction is long (the weight
        // gradient); partials go to scratch and are summed in order afterwards.
        let wanted = if flags & (ADD_BIAS | RELU) != 0 {
            1
        } else {
            TARGET_WORKGROUPS
                .div_ceil(m_tiles * n_tiles)
                .min(k.div_ceil(256))
        };
        let (k_per_split, splits) =
            self.split_reduction((m, n, k), (m_tiles, n_tiles), TILE_K, wanted, m * n)?;
        let groups_y = m_tiles * splits;
        let scratch = if splits > 1 {
            Some(self.scratch(splits * m * n)?)
        } else {
            None
        };
        let (target, target_offset, kernel_flags) = match &scratch {
            None => (c, c_offset, flags),
            Some(partials) => (partials, 0, flags & !ACCUMULATE),
        };
        let params = MatmulParams {
            m: to_u32("rows", m)?,
            n: to_u32("columns", n)?,
            k: to_u32("reduction length", k)?,
            flags: kernel_flags,
            a_offset: to_u32("offset", a.offset)?,
            a_row_stride: to_u32("stride", a.row_stride)?,
            a_col_stride: to_u32("stride", a.col_stride)?,
            b_offset: to_u32("offset", b.offset)?,
            b_row_stride: to_u32("stride", b.row_stride)?,
            b_col_stride: to_u32("stride", b.col_stride)?,
            c_offset: to_u32("offset", target_offset)?,
            c_row_stride: to_u32("columns", n)?,
            k_per_split: to_u32("k slice", k_per_split)?,
            m_tiles: to_u32("tiles", m_tiles)?,
            split_stride: to_u32("partial size", if splits == 1 { 0 } else { m * n })?,
            pad: 0,
        };
        let mask = mask.unwrap_or(&self.placeholder);
        let bias = bias.unwrap_or(&self.placeholder);
        self.matmul.call(
            encoder,
            &params,
            &[
                (1, a.buffer),
                (2, b.buffer),
                (3, mask),
                (4, bias),
                (5, target),
            ],
            (to_u32("tiles", n_tiles)?, to_u32("tiles", groups_y)?),
        );
        if let Some(partials) = &scratch {
            self.accumulate_into(
                encoder,
                (partials, splits, m * n),
                (c, c_offset),
                flags & ACCUMULATE != 0,
            )?;
        }
        Ok(())
    }

    /// Splits the reduction of `k` of an `m x n` product of `blocks` output blocks into at
    /// most `wanted` slices of a multiple of `tile_k`, no more than partials of
    /// `partial_len` values fit a binding: `(k_per_split, splits)`, once the product's grid
    /// (`n_blocks x m_blocks * splits` workgroups) is within the device limit.
    fn split_reduction(
        &self,
        (m, n, k): (usize, usize, usize),
        (m_blocks, n_blocks): (usize, usize),
        tile_k: usize,
        wanted: usize,
        partial_len: usize,
    ) -> Result<(usize, usize), NnError> {
        let max_splits = (self.max_binding_bytes as usize / 4) / partial_len.max(1);
        let splits = wanted.min(max_splits).max(1);
        let k_per_split = k.div_ceil(splits).div_ceil(tile_k).max(1) * tile_k;
        let splits = k.div_ceil(k_per_split).max(1);
        let groups_y = m_blocks * splits;
        let max_groups = self.max_groups_per_dimension as usize;
        if groups_y > max_groups || n_blocks > max_groups {
            return Err(NnError::Gpu(format!(
                "a {m} x {n} product needs a {n_blocks} x {groups_y} grid, beyond the device limit {max_groups}"
            )));
        }
        Ok((k_per_split, splits))
    }

    /// [`NnGpu::matmul`] on the tensor cores: both operands' largest magnitudes, their
    /// scaled and padded f16 copies, the products split along k, and the epilogue.
    fn matmul_tensor_cores(
        &self,
        encoder: &mut impl Record,
        kernels: &TensorCoreKernels,
        Product {
            dims: (m, n, k),
            a,
            b,
            mask,
            bias,
            c,
            c_offset,
            flags,
        }: Product<'_>,
    ) -> Result<(), NnError> {
        let m_pad = m.div_ceil(COOP_BLOCK) * COOP_BLOCK;
        let n_pad = n.div_ceil(COOP_BLOCK) * COOP_BLOCK;
        let k_pad = k.div_ceil(COOP_TILE_K) * COOP_TILE_K;
        let (m_blocks, n_blocks) = (m_pad / COOP_BLOCK, n_pad / COOP_BLOCK);
        // Split along k when the output has few blocks and the reduction is long (the weight
        // gradient), within the scratch the device can bind.
        let partial_len = m_pad * n_pad;
        let wanted = COOP_TARGET_WORKGROUPS
            .div_ceil(m_blocks * n_blocks)
            .min(k_pad.div_ceil(256));
        let dims = (m, n, k_pad);
        let (k_per_split, splits) =
            self.split_reduction(dims, (m_blocks, n_blocks), COOP_TILE_K, wanted, partial_len)?;
        let groups_y = m_blocks * splits;
        // Every flat index of the kernels is a u32.
        to_u32("padded operand size", m_pad * k_pad)?;
        to_u32("padded operand size", k_pad * n_pad)?;
        to_u32("partial products", splits * partial_len)?;
        let packed_a = self.grown(&kernels.packed_a, "nn tensor-core A", m_pad * k_pad * 2)?;
        let packed_b = self.grown(&kernels.packed_b, "nn tensor-core B", k_pad * n_pad * 2)?;
        let partials = self.grown(
            &kernels.partials,
            "nn tensor-core partial products",
            splits * partial_len * 4,
        )?;
        let mask_buffer = mask.unwrap_or(&self.placeholder);
        encoder.record_clear(&kernels.scales);
        let operands = [
            (a, (m, k), (m_pad, k_pad), flags & MASK_A != 0, &packed_a),
            (b, (k, n), (k_pad, n_pad), flags & MASK_B != 0, &packed_b),
        ];
        let mut staging = Vec::with_capacity(2);
        for (slot, (operand, (rows, cols), (rows_pad, cols_pad), masked, _)) in
            operands.iter().enumerate()
        {
            staging.push(StagingParams {
                rows: to_u32("rows", *rows)?,
                cols: to_u32("columns", *cols)?,
                offset: to_u32("offset", operand.offset)?,
                row_stride: to_u32("stride", operand.row_stride)?,
                col_stride: to_u32("stride", operand.col_stride)?,
                mask_flags: u32::from(*masked),
                slot: slot as u32,
                rows_pad: to_u32("rows", *rows_pad)?,
                cols_pad: to_u32("columns", *cols_pad)?,
                ..StagingParams::default()
            });
        }
        for ((operand, (rows, cols), ..), params) in operands.iter().zip(&staging) {
            kernels.operand_max.call(
                encoder,
                params,
                &[(1, operand.buffer), (2, mask_buffer), (3, &kernels.scales)],
                self.grid((rows * cols).div_ceil(STAGING_WORKGROUP))?,
            );
        }
        for ((operand, _, (rows_pad, cols_pad), _, packed), params) in operands.iter().zip(&staging)
        {
            kernels.pack.call(
                encoder,
                params,
                &[
                    (1, operand.buffer),
                    (2, mask_buffer),
                    (3, &kernels.scales),
                    (4, *packed),
                ],
                self.grid((rows_pad * cols_pad).div_ceil(STAGING_WORKGROUP))?,
            );
        }
        let multiply = CoopParams {
            k_pad: to_u32("reduction length", k_pad)?,
            n_pad: to_u32("columns", n_pad)?,
            m_blocks: to_u32("blocks", m_blocks)?,
            k_per_split: to_u32("k slice", k_per_split)?,
            partial_stride: to_u32("partial size", partial_len)?,
            pad: [0; 3],
        };
        kernels.multiply.call(
            encoder,
            &multiply,
            &[(1, &packed_a), (2, &packed_b), (3, &partials)],
            (to_u32("blocks", n_blocks)?, to_u32("blocks", groups_y)?),
        );
        let epilogue = StagingParams {
            m: to_u32("rows", m)?,
            n: to_u32("columns", n)?,
            n_pad: to_u32("columns", n_pad)?,
            splits: to_u32("k splits", splits)?,
            partial_stride: to_u32("partial size", partial_len)?,
            c_offset: to_u32("offset", c_offset)?,
            c_row_stride: to_u32("columns", n)?,
            c_flags: flags & (ACCUMULATE | ADD_BIAS | RELU),
            ..StagingParams::default()
        };
        to_u32("product size", m * n)?;
        kernels.epilogue.call(
            encoder,
            &epilogue,
            &[
                (3, &kernels.scales),
                (5, &partials),
                (6, bias.unwrap_or(&self.placeholder)),
                (7, c),
            ],
            self.grid((m * n).div_ceil(STAGING_WORKGROUP))?,
        );
        Ok(())
    }

    /// `destination[offset + i] (+)= sum_s partials[s * len + i]` over the `slices` partials.
    fn accumulate_into(
        &self,
        encoder: &mut impl Record,
        (partials, slices, len): (&wgpu::Buffer, usize, usize),
        (destination, offset): (&wgpu::Buffer, usize),
        accumulate: bool,
    ) -> Result<(), NnError> {
        let (x, y) = self.grid(len.div_ceil(256))?;
        let params = ReduceParams {
            p: [
                to_u32("length", len)?,
                to_u32("slices", slices)?,
                to_u32("offset", offset)?,
                x,
                u32::from(accumulate),
            ],
            pad: [0; 3],
        };
        self.accumulate_partials
            .call(encoder, &params, &[(1, partials), (3, destination)], (x, y));
        Ok(())
    }

    fn check_layer(
        &self,
        shape: LinearShape,
        weight: &wgpu::Buffer,
        inputs: &[GpuInputPart<'_>],
        rows: usize,
    ) -> Result<(), NnError> {
        check_features(shape)?;
        check_widths(shape, inputs.iter().map(|part| part.cols))?;
        self.check_buffer("linear weight", weight, shape.weight_len())?;
        for (index, part) in inputs.iter().enumerate() {
            self.check_buffer(
                &format!("linear input part {index}"),
                part.buffer,
                rows * part.cols,
            )?;
        }
        Ok(())
    }

    /// Records `output = act(concat(inputs) W + b)` (`rows x out`, overwritten).
    pub fn linear_forward(
        &self,
        encoder: &mut impl Record,
        GpuLinear { shape, weight }: GpuLinear<'_>,
        bias: &wgpu::Buffer,
        GpuInput {
            parts: inputs,
            rows,
        }: GpuInput<'_>,
        output: &wgpu::Buffer,
    ) -> Result<(), NnError> {
        self.check_layer(shape, weight, inputs, rows)?;
        let out = shape.out_features;
        self.check_buffer("linear bias", bias, out)?;
        self.check_buffer("linear output", output, rows * out)?;
        let mut weight_row = 0;
        for (index, part) in inputs.iter().enumerate() {
            let last = index + 1 == inputs.len();
            let mut flags = if index > 0 { ACCUMULATE } else { 0 };
            if last {
                flags |= ADD_BIAS;
                if shape.activation == Activation::Relu {
                    flags |= RELU;
                }
            }
            self.matmul(
                encoder,
                Product {
                    dims: (rows, out, part.cols),
                    a: Operand::new(part.buffer, 0, part.cols, 1),
                    b: Operand::new(weight, weight_row * out, out, 1),
                    mask: None,
                    bias: Some(bias),
                    c: output,
                    c_offset: 0,
                    flags,
                },
            )?;
            weight_row += part.cols;
        }
        Ok(())
    }

    /// Records the backward of [`NnGpu::linear_forward`]: parameter gradients accumulated into
    /// `grads`, input gradients per `grads.inputs`. `output` is the forward output (ReLU mask);
    /// `d_output = dL/dY` is only read.
    pub fn linear_backward(
        &self,
        encoder: &mut impl Record,
        GpuLinear { shape, weight }: GpuLinear<'_>,
        GpuInput {
            parts: inputs,
            rows,
        }: GpuInput<'_>,
        output: &wgpu::Buffer,
        d_output: &wgpu::Buffer,
        grads: GpuLinearGrads<'_>,
    ) -> Result<(), NnError> {
        let d_inputs = grads.inputs;
        self.check_layer(shape, weight, inputs, rows)?;
        let out = shape.out_features;
        self.check_buffer("linear output", output, rows * out)?;
        self.check_buffer("linear output gradient", d_output, rows * out)?;
        self.check_buffer("linear weight gradient", grads.weight, shape.weight_len())?;
        self.check_buffer("linear bias gradient", grads.bias, out)?;
        check_grad_count(d_inputs.len(), inputs.len())?;
        for (index, (part, grad)) in inputs.iter().zip(d_inputs).enumerate() {
            if let GpuInputGrad::Write(buffer) | GpuInputGrad::Accumulate(buffer) = grad {
                self.check_buffer(
                    &format!("linear input part {index} gradient"),
                    buffer,
                    rows * part.cols,
                )?;
            }
        }
        let relu = shape.activation == Activation::Relu;
        let mask = relu.then_some(output);

        // Bias gradient: masked column sums by row chunks, then summed in order.
        if rows > 0 {
            let chunks = rows.div_ceil(COLUMN_SUM_ROWS);
            let scratch = self.scratch(chunks * out)?;
            let params = ReduceParams {
                p: [
                    to_u32("rows", rows)?,
                    to_u32("columns", out)?,
                    COLUMN_SUM_ROWS as u32,
                    u32::from(relu),
                    0,
                ],
                pad: [0; 3],
            };
            let groups_y = to_u32("row chunks", chunks)?;
            if groups_y > self.max_groups_per_dimension {
                return Err(NnError::Gpu(format!(
                    "{rows} rows exceed the column-sum grid"
                )));
            }
            self.column_sums.call(
                encoder,
                &params,
                &[
                    (1, d_output),
                    (2, mask.unwrap_or(&self.placeholder)),
                    (3, &scratch),
                ],
                (to_u32("column groups", out.div_ceil(64))?, groups_y),
            );
            self.accumulate_into(encoder, (&scratch, chunks, out), (grads.bias, 0), true)?;
        }

        let masked = if relu { MASK_B } else { 0 };
        let mut weight_row = 0;
        for (part, d_input) in inputs.iter().zip(d_inputs) {
            let cols = part.cols;
            // dW_part += X_part^T dY' (cols x rows times rows x out).
            self.matmul(
                encoder,
                Product {
                    dims: (cols, out, rows),
                    a: Operand::new(part.buffer, 0, 1, cols),
                    b: Operand::new(d_output, 0, out, 1),
                    mask,
                    bias: None,
                    c: grads.weight,
                    c_offset: weight_row * out,
                    flags: ACCUMULATE | masked,
                },
            )?;
            // dX_part (+)= dY' W_part^T (rows x out times out x cols).
            let (target, accumulate) = match d_input {
                GpuInputGrad::Skip => (None, false),
                GpuInputGrad::Write(buffer) => (Some(*buffer), false),
                GpuInputGrad::Accumulate(buffer) => (Some(*buffer), true),
            };
            if let Some(target) = target {
                self.matmul(
                    encoder,
                    Product {
                        dims: (rows, cols, out),
                        a: Operand::new(d_output, 0, out, 1),
                        b: Operand::new(weight, weight_row * out, 1, out),
                        mask,
                        bias: None,
                        c: target,
                        c_offset: 0,
                        flags: if accumulate { ACCUMULATE } else { 0 }
                            | if relu { MASK_A } else { 0 },
                    },
                )?;
            }
            weight_row += cols;
        }
        Ok(())
    }

    /// Records one Adam update of `len` values whose step factors are read on the device
    /// from `record.0` at slot `record.1` (`[step_size, correction]` at f32 index
    /// `2 slot`, as [`adam_factors_record`] lays them out; the `cpu` twin is
    /// [`adam_update`](super::adam::adam_update)). Recorded into a [`NnProgram`], the update
    /// replays every iteration while the host rewrites only the record.
    pub fn adam_update_from_record(
        &self,
        encoder: &mut impl Record,
        config: &AdamConfig,
        record: (&wgpu::Buffer, usize),
        values: GpuAdamValues<'_>,
    ) -> Result<(), NnError> {
        config.validate()?;
        let (factors, slot) = record;
        let GpuAdamValues {
            params,
            grads,
            first_moment,
            second_moment,
            len,
        } = values;
        self.check_buffer("adam parameters", params, len)?;
        self.check_buffer("adam gradient", grads, len)?;
        self.check_buffer("adam first moment", first_moment, len)?;
        self.check_buffer("adam second moment", second_moment, len)?;
        self.check_buffer("adam step factors", factors, 2 * slot + 2)?;
        let uniform = AdamParams {
            len: to_u32("adam length", len)?,
            slot: to_u32("adam factor slot", slot)?,
            pad0: [0; 2],
            beta1: config.beta1 as f32,
            beta2: config.beta2 as f32,
            one_minus_beta1: (1.0 - config.beta1) as f32,
            one_minus_beta2: (1.0 - config.beta2) as f32,
            eps: config.eps as f32,
            pad: [0; 3],
        };
        self.adam.call(
            encoder,
            &uniform,
            &[
                (1, params),
                (2, grads),
                (3, first_moment),
                (4, second_moment),
                (5, factors),
            ],
            self.grid(len.div_ceil(256))?,
        );
        Ok(())
    }

    /// Records the non-finite check of `len` values: `status[slot]` (a `u32` word, zero when
    /// cleared) becomes `0xffffffff - i` for the first non-finite `values[i]` (the largest
    /// flag wins; [`first_non_finite`] decodes it), and is left unchanged when every value
    /// is finite. The flag is sticky until the caller clears the status buffer.
    pub fn flag_non_finite(
        &self,
        encoder: &mut impl Record,
        values: &wgpu::Buffer,
        len: usize,
        status: &wgpu::Buffer,
        slot: usize,
    ) -> Result<(), NnError> {
        self.check_buffer("checked values", values, len)?;
        self.check_buffer("status", status, slot + 1)?;
        let params = FiniteParams {
            len: to_u32("checked length", len)?,
            slot: to_u32("status slot", slot)?,
            pad: [0; 2],
        };
        self.finite.call(
            encoder,
            &params,
            &[(1, values), (2, status)],
            self.grid(len.div_ceil(256))?,
        );
        Ok(())
    }

    /// Records the regularised Rodrigues map of `count` rotation vectors (`count x 3`) into
    /// `matrices` (`count x 9`, row-major): `theta = sqrt(epsilon + |v|^2)`, `k = v / theta`,
    /// `R = cos(theta) I + (1 - cos(theta)) k k^T + sin(theta) [k]x`.
    pub fn rodrigues_forward(
        &self,
        encoder: &mut impl Record,
        epsilon: f64,
        vectors: &wgpu::Buffer,
        count: usize,
        matrices: &wgpu::Buffer,
    ) -> Result<(), NnError> {
        self.check_buffer("rotation vectors", vectors, 3 * count)?;
        self.check_buffer("rotation matrices", matrices, 9 * count)?;
        let (params, grid) = self.rodrigues_params(epsilon, count)?;
        self.rodrigues_forward
            .call(encoder, &params, &[(1, vectors), (3, matrices)], grid);
        Ok(())
    }

    /// Records the backward of [`NnGpu::rodrigues_forward`]: `d_vectors` (`count x 3`) is
    /// overwritten with `dL/dv` from `d_matrices = dL/dR` (`count x 9`, row-major).
    pub fn rodrigues_backward(
        &self,
        encoder: &mut impl Record,
        epsilon: f64,
        vectors: &wgpu::Buffer,
        d_matrices: &wgpu::Buffer,
        count: usize,
        d_vectors: &wgpu::Buffer,
    ) -> Result<(), NnError> {
        self.check_buffer("rotation vectors", vectors, 3 * count)?;
        self.check_buffer("rotation matrix gradient", d_matrices, 9 * count)?;
        self.check_buffer("rotation vector gradient", d_vectors, 3 * count)?;
        let (params, grid) = self.rodrigues_params(epsilon, count)?;
        self.rodrigues_backward.call(
            encoder,
            &params,
            &[(1, vectors), (2, d_matrices), (3, d_vectors)],
            grid,
        );
        Ok(())
    }

    /// The uniform and grid of the Rodrigues kernels over `count` rotation vectors.
    fn rodrigues_params(
        &self,
        epsilon: f64,
        count: usize,
    ) -> Result<(RodriguesParams, (u32, u32)), NnError> {
        let grid = self.grid(count.div_ceil(64))?;
        let params = RodriguesParams {
            count: to_u32("rotation count", count)?,
            epsilon: epsilon as f32,
            pad: [0; 2],
        };
        Ok((params, grid))
    }

    fn posenc_params(
        &self,
        encoding: PositionalEncoding,
        rows: usize,
        in_features: usize,
    ) -> Result<(PosencParams, (u32, u32)), NnError> {
        if encoding.frequencies > 30 {
            return Err(NnError::Config {
                field: "positional_encoding.frequencies".into(),
                message: format!("{} bands exceed 30", encoding.frequencies),
            });
        }
        let grid = self.grid((rows * in_features).div_ceil(64))?;
        let params = PosencParams {
            rows: to_u32("rows", rows)?,
            in_features: to_u32("in_features", in_features)?,
            frequencies: encoding.frequencies as u32,
            include_input: u32::from(encoding.include_input),
            pad: [0; 4],
        };
        to_u32("encoding size", rows * encoding.out_features(in_features))?;
        Ok((params, grid))
    }

    /// Records the positional encoding of `input` (`rows x in_features`) into `output`.
    pub fn positional_encoding_forward(
        &self,
        encoder: &mut impl Record,
        encoding: PositionalEncoding,
        input: &wgpu::Buffer,
        (rows, in_features): (usize, usize),
        output: &wgpu::Buffer,
    ) -> Result<(), NnError> {
        self.check_buffer("positional encoding input", input, rows * in_features)?;
        self.check_buffer(
            "positional encoding output",
            output,
            rows * encoding.out_features(in_features),
        )?;
        let (params, grid) = self.posenc_params(encoding, rows, in_features)?;
        self.posenc_forward
            .call(encoder, &params, &[(1, input), (3, output)], grid);
        Ok(())
    }

    /// Records the encoding's backward: `d_input` (`rows x in_features`) is overwritten.
    pub fn positional_encoding_backward(
        &self,
        encoder: &mut impl Record,
        encoding: PositionalEncoding,
        output: &wgpu::Buffer,
        d_output: &wgpu::Buffer,
        (rows, in_features): (usize, usize),
        d_input: &wgpu::Buffer,
    ) -> Result<(), NnError> {
        let width = encoding.out_features(in_features);
        self.check_buffer("positional encoding output", output, rows * width)?;
        self.check_buffer(
            "positional encoding output gradient",
            d_output,
            rows * width,
        )?;
        self.check_buffer(
            "positional encoding input gradient",
            d_input,
            rows * in_features,
        )?;
        let (params, grid) = self.posenc_params(encoding, rows, in_features)?;
        self.posenc_backward.call(
            encoder,
            &params,
            &[(1, output), (2, d_output), (3, d_input)],
            grid,
        );
        Ok(())
    }
}

/// The first non-finite index flagged in a status word by [`NnGpu::flag_non_finite`], or
/// `None` when the word is clear.
pub fn first_non_finite(status: u32) -> Option<usize> {
    (status != 0).then(|| (u32::MAX - status) as usize)
}

/// The device layout of Adam step factors read by `nn_adam.wgsl`: `[step_size, correction]`
/// per slot, f32, in slot order (at least 4 values, so the buffer can be bound).
pub fn adam_factors_record(factors: &[AdamStepFactors]) -> Vec<f32> {
    let mut record: Vec<f32> = factors
        .iter()
        .flat_map(|f| [f.step_size as f32, f.bias_correction2_sqrt as f32])
        .collect();
    record.resize(record.len().max(4), 0.0);
    record
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;
    use crate::backend::test_support::gpu_test_context;
    use crate::nn::adam::{AdamState, adam_update};
    use crate::nn::encoding::{positional_encoding_backward, positional_encoding_forward};
    use crate::nn::init::{Rng, uniform_fill};
    use crate::nn::linear::{InputGrad, InputPart, LinearGrads, linear_backward, linear_forward};

    fn random(rng: &mut Rng, len: usize, bound: f64) -> Vec<f32> {
        let mut values = vec![0.0f32; len];
        uniform_fill(rng, &mut values, bound);
        values
    }

    fn upload(context: &GpuContext, data: &[f32]) -> wgpu::Buffer {
        context.upload("nn test", data).unwrap().buffer
    }

    fn upload_words(context: &GpuContext, data: &[u32]) -> wgpu::Buffer {
        context.upload("nn test", data).unwrap().buffer
    }

    /// One Adam update at rate `lr`, `t` being its 1-based index, from a record of its own.
    fn adam_step(
        context: &GpuContext,
        nn: &NnGpu,
        encoder: &mut wgpu::CommandEncoder,
        config: &AdamConfig,
        (lr, t): (f64, u64),
        values: GpuAdamValues<'_>,
    ) {
        let factors = adam_factors_record(&[AdamStepFactors::new(config, lr, t)]);
        let record = upload(context, &factors);
        nn.adam_update_from_record(encoder, config, (&record, 0), values)
            .unwrap();
    }

    fn download(
        context: &GpuContext,
        encoder: wgpu::CommandEncoder,
        buffer: &wgpu::Buffer,
        len: usize,
    ) -> Vec<f32> {
        context.download(encoder, buffer, len).unwrap()
    }

    /// `|gpu - cpu| <= tolerance * (1 + |cpu|)` everywhere, naming the first offender.
    fn assert_close(what: &str, gpu: &[f32], cpu: &[f32], tolerance: f32) {
        assert_eq!(gpu.len(), cpu.len(), "{what}: lengths");
        for (index, (g, c)) in gpu.iter().zip(cpu).enumerate() {
            assert!(
                (g - c).abs() <= tolerance * (1.0 + c.abs()),
                "{what}[{index}]: gpu {g} vs cpu {c}"
            );
        }
    }

    /// The largest differences [`check_linear_on`] allows: of the output, of the
    /// reductions over rows (`dW`, `db`) and of the input gradients.
    #[derive(Clone, Copy)]
    struct Tolerances {
        output: f32,
        row_sums: f32,
        input_gradient: f32,
    }

    /// Forward and backward of a two-part layer on both backends. `rows` above 256 makes the
    /// weight gradient take the split-and-reduce path.
    fn check_linear(rows: usize, widths: [usize; 2], out: usize, activation: Activation) {
        let Some(context) = gpu_test_context() else {
            return;
        };
        let nn = NnGpu::new(context.device()).unwrap();
        // Sums over `rows` terms: f32 rounding grows like sqrt(rows).
        let sum_tolerance = 1e-6 * (rows as f32).sqrt().max(8.0);
        let tolerances = Tolerances {
            output: 1e-5,
            row_sums: sum_tolerance,
            input_gradient: 1e-5,
        };
        check_linear_on(&context, &nn, rows, widths, out, activation, tolerances);
    }

    /// [`check_linear`] on a given [`NnGpu`]. The cpu backward takes its ReLU mask from the
    /// gpu's output, so an output that rounding puts on the other side of zero (likely with
    /// f16 operands) does not count as a backward error.
    fn check_linear_on(
        context: &GpuContext,
        nn: &NnGpu,
        rows: usize,
        widths: [usize; 2],
        out: usize,
        activation: Activation,
        tolerances: Tolerances,
    ) {
        let mut rng = Rng::new(rows as u64);
        let shape = LinearShape {
            in_features: widths[0] + widths[1],
            out_features: out,
            activation,
        };
        let weight = random(&mut rng, shape.weight_len(), 0.5);
        let bias = random(&mut rng, out, 0.5);
        let x0 = random(&mut rng, rows * widths[0], 1.0);
        let x1 = random(&mut rng, rows * widths[1], 1.0);
        let d_y = random(&mut rng, rows * out, 1.0);
        let d_weight0 = random(&mut rng, shape.weight_len(), 0.1);
        let d_bias0 = random(&mut rng, out, 0.1);
        let d_x1_0 = random(&mut rng, rows * widths[1], 0.1);

        // cpu reference.
        let parts = [
            InputPart {
                data: &x0[..],
                cols: widths[0],
            },
            InputPart {
                data: &x1[..],
                cols: widths[1],
            },
        ];
        let mut y = vec![0.0f32; rows * out];
        linear_forward(shape, &weight, &bias, &parts, rows, &mut y).unwrap();

        // gpu forward.
        let (g_weight, g_bias, g_x0, g_x1) = (
            upload(context, &weight),
            upload(context, &bias),
            upload(context, &x0),
            upload(context, &x1),
        );
        let g_y = upload(context, &vec![f32::NAN; rows * out]);
        let g_parts = [
            GpuInputPart {
                buffer: &g_x0,
                cols: widths[0],
            },
            GpuInputPart {
                buffer: &g_x1,
                cols: widths[1],
            },
        ];
        let mut encoder = context.encoder();
        nn.linear_forward(
            &mut encoder,
            GpuLinear::new(shape, &g_weight),
            &g_bias,
            GpuInput::new(&g_parts, rows),
            &g_y,
        )
        .unwrap();
        context.submit_and_wait(encoder).unwrap();
        let gpu_y = download(context, context.encoder(), &g_y, y.len());

        // cpu backward on the gpu's mask.
        let (mut d_weight, mut d_bias, mut d_x1) =
            (d_weight0.clone(), d_bias0.clone(), d_x1_0.clone());
        let mut d_x0 = vec![0.0f32; rows * widths[0]];
        let mut d_pre = d_y.clone();
        linear_backward(
            shape,
            &weight,
            &parts,
            rows,
            &gpu_y,
            &mut d_pre,
            LinearGrads {
                weight: &mut d_weight,
                bias: &mut d_bias,
                inputs: &mut [
                    InputGrad::Write(&mut d_x0),
                    InputGrad::Accumulate(&mut d_x1),
                ],
            },
        )
        .unwrap();

        // gpu backward.
        let g_dy = upload(context, &d_y);
        let g_dw = upload(context, &d_weight0);
        let g_db = upload(context, &d_bias0);
        let g_dx0 = upload(context, &vec![f32::NAN; rows * widths[0]]);
        let g_dx1 = upload(context, &d_x1_0);
        let mut encoder = context.encoder();
        nn.linear_backward(
            &mut encoder,
            GpuLinear::new(shape, &g_weight),
            GpuInput::new(&g_parts, rows),
            &g_y,
            &g_dy,
            GpuLinearGrads {
                weight: &g_dw,
                bias: &g_db,
                inputs: &[
                    GpuInputGrad::Write(&g_dx0),
                    GpuInputGrad::Accumulate(&g_dx1),
                ],
            },
        )
        .unwrap();
        context.submit_and_wait(encoder).unwrap();
        let label = format!("{rows}x{widths:?}x{out} {activation:?}");
        let read =
            |buffer: &wgpu::Buffer, len: usize| download(context, context.encoder(), buffer, len);
        assert_close(&format!("{label} Y"), &gpu_y, &y, tolerances.output);
        let sum_tolerance = tolerances.row_sums;
        assert_close(
            &format!("{label} dW"),
            &read(&g_dw, d_weight.len()),
            &d_weight,
            sum_tolerance,
        );
        assert_close(
            &format!("{label} db"),
            &read(&g_db, d_bias.len()),
            &d_bias,
            sum_tolerance,
        );
        assert_close(
            &format!("{label} dX0"),
            &read(&g_dx0, d_x0.len()),
            &d_x0,
            tolerances.input_gradient,
        );
        assert_close(
            &format!("{label} dX1"),
            &read(&g_dx1, d_x1.len()),
            &d_x1,
            tolerances.input_gradient,
        );
    }

    #[test]
    fn linear_matches_cpu_small() {
        check_linear(70, [5, 19], 67, Activation::Relu);
        check_linear(3, [1, 2], 1, Activation::Identity);
    }

    #[test]
    fn linear_matches_cpu_with_split_weight_gradient() {
        check_linear(600, [40, 23], 33, Activation::Relu);
    }

    #[test]
    fn adam_matches_cpu() {
        let Some(context) = gpu_test_context() else {
            return;
        };
        let nn = NnGpu::new(context.device()).unwrap();
        let mut rng = Rng::new(77);
        let len = 1000;
        let config = AdamConfig::default();
        let mut params = random(&mut rng, len, 1.0);
        let g_params = upload(&context, &params);
        let g_m = upload(&context, &vec![0.0; len]);
        let g_v = upload(&context, &vec![0.0; len]);
        let mut state = AdamState::<f32>::new(len);
        for step in 1..=3u64 {
            // Gradients spanning magnitudes, including exact zeros.
            let mut grads = random(&mut rng, len, 1.0);
            for (i, g) in grads.iter_mut().enumerate() {
                *g *= 10f32.powi((i % 7) as i32 - 4);
                if i % 11 == 0 {
                    *g = 0.0;
                }
            }
            let lr = 1e-3 * 0.9f64.powi(step as i32);
            adam_update(&config, lr, &mut params, &grads, &mut state).unwrap();
            let g_grads = upload(&context, &grads);
            let mut encoder = context.encoder();
            adam_step(
                &context,
                &nn,
                &mut encoder,
                &config,
                (lr, step),
                GpuAdamValues {
                    params: &g_params,
                    grads: &g_grads,
                    first_moment: &g_m,
                    second_moment: &g_v,
                    len,
                },
            );
            context.submit_and_wait(encoder).unwrap();
        }
        assert_close(
            "adam params",
            &download(&context, context.encoder(), &g_params, len),
            &params,
            1e-6,
        );
        assert_close(
            "adam m",
            &download(&context, context.encoder(), &g_m, len),
            &state.m,
            1e-6,
        );
        assert_close(
            "adam v",
            &download(&context, context.encoder(), &g_v, len),
            &state.v,
            1e-6,
        );
    }

    #[test]
    fn positional_encoding_matches_cpu() {
        let Some(context) = gpu_test_context() else {
            return;
        };
        let nn = NnGpu::new(context.device()).unwrap();
        let mut rng = Rng::new(5);
        let encoding = PositionalEncoding::NERF_XYZ;
        let (rows, d) = (70, 3);
        let width = encoding.out_features(d);
        let input = random(&mut rng, rows * d, 1.5);
        let d_output = random(&mut rng, rows * width, 1.0);
        let mut output = vec![0.0f32; rows * width];
        positional_encoding_forward(encoding, &input, rows, d, &mut output).unwrap();
        let mut d_input = vec![0.0f32; rows * d];
        positional_encoding_backward(encoding, &output, &d_output, rows, d, &mut d_input).unwrap();

        let g_input = upload(&context, &input);
        let g_output = upload(&context, &vec![f32::NAN; rows * width]);
        let g_d_output = upload(&context, &d_output);
        let g_d_input = upload(&context, &vec![f32::NAN; rows * d]);
        let mut encoder = context.encoder();
        nn.positional_encoding_forward(&mut encoder, encoding, &g_input, (rows, d), &g_output)
            .unwrap();
        nn.positional_encoding_backward(
            &mut encoder,
            encoding,
            &g_output,
            &g_d_output,
            (rows, d),
            &g_d_input,
        )
        .unwrap();
        context.submit_and_wait(encoder).unwrap();
        assert_close(
            "encoding",
            &download(&context, context.encoder(), &g_output, output.len()),
            &output,
            2e-5,
        );
        // Band 9 scales errors of the sines and cosines by 512.
        assert_close(
            "encoding gradient",
            &download(&context, context.encoder(), &g_d_input, rows * d),
            &d_input,
            2e-3,
        );
    }

    #[test]
    fn rejects_short_buffers_naming_the_operand() {
        let Some(context) = gpu_test_context() else {
            return;
        };
        let nn = NnGpu::new(context.device()).unwrap();
        let shape = LinearShape {
            in_features: 4,
            out_features: 3,
            activation: Activation::Relu,
        };
        let weight = upload(&context, &[0.0; 12]);
        let bias = upload(&context, &[0.0; 3]);
        let input = upload(&context, &[0.0; 8]);
        let output = upload(&context, &[0.0; 5]);
        let mut encoder = context.encoder();
        let error = nn
            .linear_forward(
                &mut encoder,
                GpuLinear::new(shape, &weight),
                &bias,
                GpuInput::new(
                    &[GpuInputPart {
                        buffer: &input,
                        cols: 4,
                    }],
                    2,
                ),
                &output,
            )
            .unwrap_err();
        assert_eq!(
            error,
            NnError::Length {
                operand: "linear output".into(),
                expected: 6,
                actual: 5
            }
        );
    }

    /// The tensor-core path, where the adapter has it, or `None` after printing why the
    /// test is skipped: lavapipe and most adapters have no cooperative matrices, so a
    /// missing feature skips even under `CI` (a missing adapter still fails there).
    fn tensor_core_test_nn(test: &str) -> Option<(Arc<GpuContext>, NnGpu)> {
        let context = gpu_test_context()?;
        if context.tensor_cores().is_none() {
            eprintln!(
                "skipped {test}: {} has no tensor cores for the f16 path (cooperative 16x16x16 \
                 f16 x f16 -> f32 matrices and a fixed subgroup size)",
                context.info().name
            );
            return None;
        }
        let nn = NnGpu::for_context(&context, Precision::Mixed).unwrap();
        assert!(
            matches!(nn.matmul_path(), MatmulPath::TensorCores(_)),
            "{}",
            nn.describe()
        );
        eprintln!("{test}: {} on {}", nn.describe(), context.info().name);
        Some((context, nn))
    }

    /// Tolerances of the f16 tensor-core path for a layer of `rows` rows, `in_features`
    /// inputs and `out_features` outputs. Rounding an operand to f16 (after its power-of-two
    /// scaling, so no operand is subnormal or overflows) errs by at most u = 2^-11 relative,
    /// uniformly, so a product term x y errs by x y (dx + dy) with variance (x y)^2 2u^2/3,
    /// and a sum of n terms with independent errors by sigma = u sqrt(2/3) sqrt(sum (x y)^2).
    /// The test's operands are uniform in [-1, 1] or narrower, so each term's RMS is at most
    /// 1/3: sigma <= u sqrt(2/3) sqrt(n) / 3. Each product is compared at 8 sigma of its own
    /// sum length (Y sums over the inputs, dW and db over the rows, dX over the outputs): the
    /// largest of ~10^5 independent errors is about 5 sigma, while a wrong tile, split or
    /// scale errs by the size of the values themselves. (A flat 1e-2 failed on the H100 at
    /// 5000 rows: dW off by 0.0145 = 1.5 sigma, which was rounding, not a fault.)
    fn f16_tolerances(rows: usize, in_features: usize, out_features: usize) -> Tolerances {
        let unit_roundoff = 2f32.powi(-11);
        let eight_sigma = |terms: usize| {
            8.0 * unit_roundoff * (2.0f32 / 3.0).sqrt() * (terms as f32).sqrt() / 3.0
        };
        Tolerances {
            output: eight_sigma(in_features),
            row_sums: eight_sigma(rows),
            input_gradient: eight_sigma(out_features),
        }
    }

    #[test]
    fn tensor_cores_match_cpu_on_random_layers() {
        let Some((context, nn)) = tensor_core_test_nn("tensor_cores_match_cpu_on_random_layers")
        else {
            return;
        };
        // Sizes off the 32 x 32 blocks and 16-deep steps, a split weight gradient (600 and
        // 5000 rows), a single input column, and a paper-width layer.
        for (rows, widths, out, activation) in [
            (70, [5, 19], 67, Activation::Relu),
            (3, [1, 2], 1, Activation::Identity),
            (600, [40, 23], 33, Activation::Relu),
            (5000, [256, 256], 512, Activation::Relu),
        ] {
            let tolerances = f16_tolerances(rows, widths[0] + widths[1], out);
            check_linear_on(&context, &nn, rows, widths, out, activation, tolerances);
        }
        // The f32 precision on the same context never takes the tensor cores.
        let f32_nn = NnGpu::for_context(&context, Precision::F32).unwrap();
        assert_eq!(f32_nn.matmul_path(), MatmulPath::F32);
        assert_eq!(f32_nn.describe(), "networks: f32");
    }

    /// Mean squared error of a two-layer network (`32 -> 64 ReLU -> 8`) fitting a fixed
    /// target, trained `steps` Adam steps on `nn`; the loss before each step.
    fn training_losses(context: &GpuContext, nn: &NnGpu, steps: usize) -> Vec<f64> {
        let (rows, inputs, hidden, outputs) = (512, 32, 64, 8);
        let mut rng = Rng::new(11);
        let x = random(&mut rng, rows * inputs, 1.0);
        let target = random(&mut rng, rows * outputs, 1.0);
        let shapes = [
            LinearShape {
                in_features: inputs,
                out_features: hidden,
                activation: Activation::Relu,
            },
            LinearShape {
                in_features: hidden,
                out_features: outputs,
                activation: Activation::Identity,
            },
        ];
        let params: Vec<[wgpu::Buffer; 2]> = shapes
            .iter()
            .map(|shape| {
                let bound = 1.0 / (shape.in_features as f64).sqrt();
                [
                    upload(context, &random(&mut rng, shape.weight_len(), bound)),
                    upload(context, &random(&mut rng, shape.out_features, bound)),
                ]
            })
            .collect();
        let zeros = |len: usize| upload(context, &vec![0.0f32; len]);
        let grads: Vec<[wgpu::Buffer; 2]> = shapes
            .iter()
            .map(|shape| [zeros(shape.weight_len()), zeros(shape.out_features)])
            .collect();
        let moments: Vec<[wgpu::Buffer; 4]> = shapes
            .iter()
            .map(|shape| {
                [
                    zeros(shape.weight_len()),
                    zeros(shape.weight_len()),
                    zeros(shape.out_features),
                    zeros(shape.out_features),
                ]
            })
            .collect();
        let g_x = upload(context, &x);
        let hidden_out = zeros(rows * hidden);
        let y = zeros(rows * outputs);
        let d_hidden = zeros(rows * hidden);
        let config = AdamConfig::default();
        let mut losses = Vec::new();
        for step in 1..=steps {
            let mut encoder = context.encoder();
            let input = [GpuInputPart {
                buffer: &g_x,
                cols: inputs,
            }];
            let hidden_part = [GpuInputPart {
                buffer: &hidden_out,
                cols: hidden,
            }];
            nn.linear_forward(
                &mut encoder,
                GpuLinear::new(shapes[0], &params[0][0]),
                &params[0][1],
                GpuInput::new(&input, rows),
                &hidden_out,
            )
            .unwrap();
            nn.linear_forward(
                &mut encoder,
                GpuLinear::new(shapes[1], &params[1][0]),
                &params[1][1],
                GpuInput::new(&hidden_part, rows),
                &y,
            )
            .unwrap();
            context.submit_and_wait(encoder).unwrap();
            let prediction = download(context, context.encoder(), &y, rows * outputs);
            let count = prediction.len() as f64;
            losses.push(
                prediction
                    .iter()
                    .zip(&target)
                    .map(|(p, t)| f64::from(p - t).powi(2))
                    .sum::<f64>()
                    / count,
            );
            // dL/dY of the mean: small values (~1e-3 and below), which f16 keeps only
            // because the operands are scaled.
            let d_y: Vec<f32> = prediction
                .iter()
                .zip(&target)
                .map(|(p, t)| (2.0 * f64::from(p - t) / count) as f32)
                .collect();
            let g_dy = upload(context, &d_y);
            let mut encoder = context.encoder();
            for [weight, bias] in &grads {
                encoder.clear_buffer(weight, 0, None);
                encoder.clear_buffer(bias, 0, None);
            }
            nn.linear_backward(
                &mut encoder,
                GpuLinear::new(shapes[1], &params[1][0]),
                GpuInput::new(&hidden_part, rows),
                &y,
                &g_dy,
                GpuLinearGrads {
                    weight: &grads[1][0],
                    bias: &grads[1][1],
                    inputs: &[GpuInputGrad::Write(&d_hidden)],
                },
            )
            .unwrap();
            nn.linear_backward(
                &mut encoder,
                GpuLinear::new(shapes[0], &params[0][0]),
                GpuInput::new(&input, rows),
                &hidden_out,
                &d_hidden,
                GpuLinearGrads {
                    weight: &grads[0][0],
                    bias: &grads[0][1],
                    inputs: &[GpuInputGrad::Skip],
                },
            )
            .unwrap();
            for ((shape, [weight, bias]), ([d_weight, d_bias], [m_w, v_w, m_b, v_b])) in
                shapes.iter().zip(&params).zip(grads.iter().zip(&moments))
            {
                let lr = 1e-2;
                let t = step as u64;
                let len = shape.weight_len();
                adam_step(
                    context,
                    nn,
                    &mut encoder,
                    &config,
                    (lr, t),
                    GpuAdamValues {
                        params: weight,
                        grads: d_weight,
                        first_moment: m_w,
                        second_moment: v_w,
                        len,
                    },
                );
                let len = shape.out_features;
                adam_step(
                    context,
                    nn,
                    &mut encoder,
                    &config,
                    (lr, t),
                    GpuAdamValues {
                        params: bias,
                        grads: d_bias,
                        first_moment: m_b,
                        second_moment: v_b,
                        len,
                    },
                );
            }
            context.submit_and_wait(encoder).unwrap();
        }
        losses
    }

    /// Training on the tensor cores lowers the loss as the f32 path does: the same network,
    /// data and steps end at most 10% of the starting loss above the f32 run, and below
    /// half the starting loss.
    #[test]
    fn tensor_cores_train_like_f32() {
        let Some((context, nn)) = tensor_core_test_nn("tensor_cores_train_like_f32") else {
            return;
        };
        let steps = 60;
        let mixed = training_losses(&context, &nn, steps);
        let reference = training_losses(&context, &NnGpu::new(context.device()).unwrap(), steps);
        let (first, last, last_f32) = (mixed[0], mixed[steps - 1], reference[steps - 1]);
        eprintln!(
            "loss: f16 tensor cores {first} -> {last}, f32 {} -> {last_f32}",
            reference[0]
        );
        assert!(mixed.iter().all(|loss| loss.is_finite()), "{mixed:?}");
        assert!(
            (first - reference[0]).abs() <= 1e-2 * reference[0],
            "{first} vs {}",
            reference[0]
        );
        assert!(last < 0.5 * first, "the loss did not decrease: {mixed:?}");
        assert!(last <= last_f32 + 0.1 * first, "{last} vs f32 {last_f32}");
    }

    /// f16 bits to f32 (normal, subnormal, zero, infinity, NaN).
    fn f16_to_f32(bits: u16) -> f32 {
        let sign = if bits & 0x8000 != 0 { -1.0 } else { 1.0 };
        let exponent = i32::from((bits >> 10) & 0x1f);
        let mantissa = f32::from(bits & 0x3ff);
        match exponent {
            0 => sign * mantissa * 2f32.powi(-24),
            31 if mantissa == 0.0 => sign * f32::INFINITY,
            31 => f32::NAN,
            _ => sign * (1.0 + mantissa / 1024.0) * 2f32.powi(exponent - 15),
        }
    }

    /// The staging kernels of the tensor-core path on one `rows x cols` operand (row-major,
    /// no mask): its scale exponent and its packed f16 values as f32 (still scaled by
    /// 2^exponent), padded to `rows_pad x cols_pad`.
    struct Staged {
        exponent: i32,
        values: Vec<f32>,
    }

    /// The staging kernels (`nn_matmul_f16.wgsl`), compiled on a context with f16 but no
    /// tensor cores (lavapipe), or `None` after printing why the test is skipped.
    /// A context with f16, its `NnGpu` and the three staging kernels.
    type Staging = (Arc<GpuContext>, NnGpu, [Kernel; 3]);

    fn staging_kernels(test: &str) -> Option<Staging> {
        let context = gpu_test_context()?;
        if !context.has_f16() {
            eprintln!("skipped {test}: {} has no f16 shaders", context.info().name);
            return None;
        }
        let nn = NnGpu::new(context.device()).unwrap();
        let compile =
            |name, entry| Kernel::compile(context.device(), name, MATMUL_F16_WGSL, entry).unwrap();
        let kernels = [
            compile("nn_matmul_operand_max", "operand_max"),
            compile("nn_matmul_pack", "pack"),
            compile("nn_matmul_epilogue", "epilogue"),
        ];
        Some((context, nn, kernels))
    }

    /// Stages `values` (`rows x cols`) as operand `slot` into `packed`, with `scales` shared
    /// by both operands of a product.
    fn stage(
        (context, nn, kernels): &Staging,
        values: &[f32],
        (rows, cols): (usize, usize),
        (rows_pad, cols_pad): (usize, usize),
        slot: u32,
        scales: &wgpu::Buffer,
        packed: &wgpu::Buffer,
    ) -> Staged {
        let source = upload(context, values);
        let params = StagingParams {
            rows: rows as u32,
            cols: cols as u32,
            row_stride: cols as u32,
            col_stride: 1,
            slot,
            rows_pad: rows_pad as u32,
            cols_pad: cols_pad as u32,
            ..StagingParams::default()
        };
        let mut encoder = context.encoder();
        let bindings = [(1, &source), (2, &nn.placeholder), (3, scales)];
        kernels[0].call(
            &mut encoder,
            &params,
            &bindings,
            nn.grid((rows * cols).div_ceil(STAGING_WORKGROUP)).unwrap(),
        );
        let bindings = [(1, &source), (2, &nn.placeholder), (3, scales), (4, packed)];
        kernels[1].call(
            &mut encoder,
            &params,
            &bindings,
            nn.grid((rows_pad * cols_pad).div_ceil(STAGING_WORKGROUP))
                .unwrap(),
        );
        context.submit_and_wait(encoder).unwrap();
        let max_bits: Vec<u32> = context.download(context.encoder(), scales, 2).unwrap();
        let max_bits = max_bits[slot as usize];
        // As scale_exponent in the WGSL.
        let exponent = if max_bits == 0 {
            0
        } else {
            (14 - (((max_bits >> 23) & 0xff) as i32 - 127)).min(126)
        };
        let words: Vec<u32> = context
            .download(context.encoder(), packed, (rows_pad * cols_pad).div_ceil(2))
            .unwrap();
        let values = words
            .iter()
            .flat_map(|word| [*word as u16, (*word >> 16) as u16])
            .take(rows_pad * cols_pad)
            .map(f16_to_f32)
            .collect();
        Staged { exponent, values }
    }

    /// Operands beyond f16's range (up to f32's largest) and far below its normal range
    /// (1e-30) are scaled so that every packed value is finite and within f16's range and
    /// keeps f16's 11 bits relative to the operand's largest magnitude; infinities and NaNs
    /// do not enter the scale. Runs wherever the adapter has f16 (lavapipe does).
    #[test]
    fn f16_staging_keeps_extreme_operands_finite_and_exact_to_f16_precision() {
        let Some(staging) = staging_kernels("f16_staging_extremes") else {
            return;
        };
        let context = &staging.0;
        let cases: [(&str, Vec<f32>); 4] = [
            (
                "near the f16 limit",
                vec![65504.0, -65504.0, 65519.0, 70000.0, 1.0, -0.5, 0.0, 3.0e-5],
            ),
            (
                "far beyond it",
                vec![f32::MAX, -3.0e38, 1.0e30, 1.0e6, -7.0e4, 1.0, 0.0, 2.0e37],
            ),
            (
                "tiny gradients",
                vec![
                    1.0e-30, -3.0e-30, 2.5e-31, 1.0e-35, 0.0, -1.0e-30, 7.0e-31, 1.0e-44,
                ],
            ),
            (
                "non-finite entries",
                vec![
                    f32::INFINITY,
                    f32::NAN,
                    2.0,
                    -4.0,
                    0.5,
                    f32::NEG_INFINITY,
                    1.0,
                    3.0,
                ],
            ),
        ];
        let scales = upload_words(context.as_ref(), &[0u32; 4]);
        let (rows, cols, rows_pad, cols_pad) = (2, 4, 32, 16);
        let packed = upload_words(context.as_ref(), &vec![0u32; rows_pad * cols_pad / 2]);
        for (what, values) in &cases {
            context.write(&scales, 0, &[0u32; 4]).unwrap();
            let staged = stage(
                &staging,
                values,
                (rows, cols),
                (rows_pad, cols_pad),
                0,
                &scales,
                &packed,
            );
            let largest = values
                .iter()
                .filter(|value| value.is_finite())
                .fold(0.0f64, |largest, value| largest.max(f64::from(value.abs())));
            for (index, &packed_value) in staged.values.iter().enumerate() {
                let (row, col) = (index / cols_pad, index % cols_pad);
                if row >= rows || col >= cols {
                    assert_eq!(packed_value, 0.0, "{what}: padding [{row}][{col}]");
                    continue;
                }
                let original = values[row * cols + col];
                if !original.is_finite() {
                    continue;
                }
                assert!(
                    packed_value.is_finite() && packed_value.abs() <= 65504.0,
                    "{what}: {original} packed as {packed_value}"
                );
                let unscaled = f64::from(packed_value) * 2f64.powi(-staged.exponent);
                // Half a unit in the last place of f16, relative to the largest magnitude
                // (smaller values may be f16 subnormals), and f32's own rounding.
                let allowed = largest * 2f64.powi(-11) + f64::from(original.abs()) * 1e-7;
                assert!(
                    (unscaled - f64::from(original)).abs() <= allowed,
                    "{what}: {original} came back as {unscaled} (exponent {})",
                    staged.exponent
                );
            }
            // The largest finite magnitude lands in [2^14, 2^15).
            if largest > 1e-37 {
                let scaled = largest * 2f64.powi(staged.exponent);
                assert!((16384.0..32768.0).contains(&scaled), "{what}: {scaled}");
            }
        }
    }

    /// The tensor-core product without tensor cores: A (entries near 1e5, beyond f16) and B
    /// (near 1e-7, below f16's normal range) staged on the gpu, multiplied on the cpu as
    /// the cooperative matrices do (f16 products summed in f32, two k splits), then
    /// unscaled, summed, biased and rectified by the epilogue kernel; the result matches an
    /// f64 product of the f32 operands to 1e-2 and is finite.
    #[test]
    fn f16_staging_and_epilogue_reproduce_the_product_of_out_of_range_operands() {
        let Some(staging) = staging_kernels("f16_staging_and_epilogue") else {
            return;
        };
        let (context, nn, kernels) = &staging;
        let (m, k, n) = (5, 40, 7);
        let (m_pad, k_pad, n_pad) = (32, 48, 32);
        let mut rng = Rng::new(3);
        let a: Vec<f32> = random(&mut rng, m * k, 1.0)
            .iter()
            .map(|v| v * 2.0e5)
            .collect();
        let b: Vec<f32> = random(&mut rng, k * n, 1.0)
            .iter()
            .map(|v| v * 3.0e-7)
            .collect();
        let bias = random(&mut rng, n, 0.01);
        let scales = upload_words(context.as_ref(), &[0u32; 4]);
        let packed_a = upload_words(context.as_ref(), &vec![0u32; m_pad * k_pad / 2]);
        let packed_b = upload_words(context.as_ref(), &vec![0u32; k_pad * n_pad / 2]);
        let staged_a = stage(&staging, &a, (m, k), (m_pad, k_pad), 0, &scales, &packed_a);
        let staged_b = stage(&staging, &b, (k, n), (k_pad, n_pad), 1, &scales, &packed_b);
        // What the multiply kernel computes on the scaled f16 values, in two k slices of 32
        // and 16.
        let splits = [(0, 32), (32, 48)];
        let mut partials = vec![0.0f32; splits.len() * m_pad * n_pad];
        for (split, (begin, end)) in splits.iter().enumerate() {
            for i in 0..m_pad {
                for j in 0..n_pad {
                    let mut sum = 0.0f32;
                    for kk in *begin..*end {
                        let a_value = staged_a.values[i * k_pad + kk];
                        let b_value = staged_b.values[kk * n_pad + j];
                        sum += a_value * b_value;
                    }
                    partials[split * m_pad * n_pad + i * n_pad + j] = sum;
                }
            }
        }
        let g_partials = upload(context.as_ref(), &partials);
        let g_bias = upload(context.as_ref(), &bias);
        let g_c = upload(context.as_ref(), &vec![f32::NAN; m * n]);
        let params = StagingParams {
            m: m as u32,
            n: n as u32,
            n_pad: n_pad as u32,
            splits: splits.len() as u32,
            partial_stride: (m_pad * n_pad) as u32,
            c_row_stride: n as u32,
            c_flags: ADD_BIAS | RELU,
            ..StagingParams::default()
        };
        let mut encoder = context.encoder();
        kernels[2].call(
            &mut encoder,
            &params,
            &[(3, &scales), (5, &g_partials), (6, &g_bias), (7, &g_c)],
            nn.grid((m * n).div_ceil(STAGING_WORKGROUP)).unwrap(),
        );
        context.submit_and_wait(encoder).unwrap();
        let c = download(context, context.encoder(), &g_c, m * n);
        let mut largest = 0.0f64;
        let mut expected = vec![0.0f64; m * n];
        for i in 0..m {
            for j in 0..n {
                let product: f64 = (0..k)
                    .map(|kk| f64::from(a[i * k + kk]) * f64::from(b[kk * n + j]))
                    .sum();
                expected[i * n + j] = (product + f64::from(bias[j])).max(0.0);
                largest = largest.max(product.abs());
            }
        }
        for (index, (&got, &want)) in c.iter().zip(&expected).enumerate() {
            assert!(got.is_finite(), "C[{index}] = {got}");
            assert!(
                (f64::from(got) - want).abs() <= 1e-2 * largest,
                "C[{index}]: {got} vs {want} (largest |product| {largest})"
            );
        }
    }
}
