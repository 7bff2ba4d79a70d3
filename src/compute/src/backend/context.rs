//! The wgpu context: adapter selection, device limits and features, compiled kernels, buffer
//! upload/download and dispatch helpers (2D dispatch beyond the per-dimension limit).

use std::borrow::Cow;
use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use wgpu::util::DeviceExt;

use super::BackendError;
use super::kernel::{Kernel, Record, Workgroups};

/// Which adapters [`GpuContext::new`] may pick.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AdapterChoice {
    /// Discrete, integrated or virtual GPUs only (real work).
    Hardware,
    /// Also a software adapter such as Mesa lavapipe (tests); hardware is still preferred.
    AllowSoftware,
}

/// A compute kernel's WGSL text and entry point. `name` identifies the compiled pipeline in
/// the context's cache, so two sources with one name must be the same text.
#[derive(Clone, Debug)]
pub struct KernelSource {
    pub name: &'static str,
    pub wgsl: Cow<'static, str>,
    pub entry_point: &'static str,
}

/// A storage buffer with its length in elements (the buffer itself is at least 16 bytes so
/// that empty inputs still bind).
#[derive(Debug)]
pub struct GpuBuffer {
    pub buffer: wgpu::Buffer,
    pub len: usize,
}

/// The device, queue and everything derived from the adapter once.
pub struct GpuContext {
    info: wgpu::AdapterInfo,
    device: wgpu::Device,
    queue: wgpu::Queue,
    limits: wgpu::Limits,
    float_atomics: bool,
    /// Whether the device was opened with `SHADER_F16` (f16 in shaders and storage).
    f16: bool,
    /// The cooperative-matrix configuration the dense layers' mixed-precision path needs,
    /// where the device was opened with it (see [`TensorCores`]).
    tensor_cores: Option<TensorCores>,
    /// Whether timestamp queries inside encoders are on.
    timestamps: bool,
    /// Workgroups per dimension a dispatch may use before it goes 2D: the adapter limit,
    /// lowered in tests to exercise the 2D index arithmetic of every kernel.
    dispatch_limit: u32,
    kernels: Mutex<HashMap<&'static str, Arc<Kernel>>>,
    /// Host-device traffic through this context since it was made (see [`Transfers`]).
    transfers: TransferCounters,
}

/// Host-device traffic through one [`GpuContext`]: what a steady-state training step must
/// keep near zero (`--bench train` prints it per iteration, a test bounds it on lavapipe).
/// Uploads count buffers created with contents, uniforms and queue writes; readbacks count
/// each submit-and-map round trip ([`GpuContext::finish_downloads`]), however many buffers
/// it maps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Transfers {
    /// Round trips that waited for the device to map results back.
    pub readbacks: u64,
    /// Bytes written from the host into device buffers.
    pub bytes_up: u64,
    /// Bytes copied from the device back to the host.
    pub bytes_down: u64,
}

impl Transfers {
    /// The traffic between two snapshots (`self` the later one).
    pub fn since(&self, earlier: &Transfers) -> Transfers {
        Transfers {
            readbacks: self.readbacks - earlier.readbacks,
            bytes_up: self.bytes_up - earlier.bytes_up,
            bytes_down: self.bytes_down - earlier.bytes_down,
        }
    }
}

#[derive(Default)]
struct TransferCounters {
    readbacks: std::sync::atomic::AtomicU64,
    bytes_up: std::sync::atomic::AtomicU64,
    bytes_down: std::sync::atomic::AtomicU64,
}

impl TransferCounters {
    fn snapshot(&self) -> Transfers {
        use std::sync::atomic::Ordering::Relaxed;
        Transfers {
            readbacks: self.readbacks.load(Relaxed),
            bytes_up: self.bytes_up.load(Relaxed),
            bytes_down: self.bytes_down.load(Relaxed),
        }
    }

    fn up(&self, bytes: usize) {
        self.bytes_up
            .fetch_add(bytes as u64, std::sync::atomic::Ordering::Relaxed);
    }
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        formatter
            .debug_struct("GpuContext")
            .field("adapter", &self.info.name)
            .field("float_atomics", &self.float_atomics)
            .finish_non_exhaustive()
    }
}

/// What the dense layers' tensor-core path (`nn_matmul_coop.wgsl`) needs of an adapter, found
/// once when the context is made: cooperative matrices (`EXPERIMENTAL_COOPERATIVE_MATRIX`,
/// which wgpu-hal reports on Vulkan only with the Vulkan memory model's device scope) with
/// f16 shaders, a 16 x 16 x 16 configuration with f16 A and B and f32 C and result, and a
/// fixed subgroup size, so that a workgroup of that many invocations is one subgroup.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TensorCores {
    /// The adapter's one subgroup size: the kernel's workgroup size.
    pub subgroup_size: u32,
}

impl TensorCores {
    /// The cooperative-matrix shape the kernel uses: M = N = K = 16.
    pub const SHAPE: u32 = 16;

    /// `SEQAVATAR_TENSOR_CORES=off` opens the device without cooperative matrices. With
    /// them wgpu declares the Vulkan memory model for every kernel, not only the tensor-core
    /// one; whether that changes the f32 kernels' speed on hardware is measured by comparing
    /// runs with and without this variable (`.ci/gpu-check`).
    fn of_adapter(adapter: &wgpu::Adapter) -> Option<Self> {
        if std::env::var("SEQAVATAR_TENSOR_CORES").is_ok_and(|v| v == "off") {
            return None;
        }
        let needed = wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX | wgpu::Features::SHADER_F16;
        if !adapter.features().contains(needed) {
            return None;
        }
        let info = adapter.get_info();
        // The subgroup size may vary between launches where min and max differ: then a
        // workgroup cannot be made exactly one subgroup.
        if info.subgroup_min_size != info.subgroup_max_size || info.subgroup_min_size == 0 {
            return None;
        }
        let fits = adapter
            .cooperative_matrix_properties()
            .iter()
            .any(|properties| {
                properties.m_size == Self::SHAPE
                    && properties.n_size == Self::SHAPE
                    && properties.k_size == Self::SHAPE
                    && properties.ab_type == wgpu::CooperativeScalarType::F16
                    && properties.cr_type == wgpu::CooperativeScalarType::F32
            });
        fits.then_some(TensorCores {
            subgroup_size: info.subgroup_min_size,
        })
    }
}

fn is_hardware(info: &wgpu::AdapterInfo) -> bool {
    matches!(
        info.device_type,
        wgpu::DeviceType::DiscreteGpu
            | wgpu::DeviceType::IntegratedGpu
            | wgpu::DeviceType::VirtualGpu
    )
}

/// Preference order among acceptable adapters: discrete, integrated, virtual, other, software.
fn adapter_rank(info: &wgpu::AdapterInfo) -> u32 {
    match info.device_type {
        wgpu::DeviceType::DiscreteGpu => 0,
        wgpu::DeviceType::IntegratedGpu => 1,
        wgpu::DeviceType::VirtualGpu => 2,
        wgpu::DeviceType::Other => 3,
        wgpu::DeviceType::Cpu => 4,
    }
}

impl GpuContext {
    /// Opens the best adapter allowed by `choice`, with the adapter's own limits and, when it
    /// has them, native f32 atomics.
    pub fn new(choice: AdapterChoice) -> Result<Self, BackendError> {
        let instance = compute_instance();
        let adapters = pollster::block_on(instance.enumerate_adapters(descriptor_backends()));
        let adapter = adapters
            .into_iter()
            .filter(|adapter| {
                let info = adapter.get_info();
                match choice {
                    AdapterChoice::Hardware => is_hardware(&info),
                    AdapterChoice::AllowSoftware => {
                        is_hardware(&info) || info.device_type == wgpu::DeviceType::Cpu
                    }
                }
            })
            .min_by_key(|adapter| adapter_rank(&adapter.get_info()))
            .ok_or(BackendError::NoAdapter {
                wanted: match choice {
                    AdapterChoice::Hardware => "hardware GPU",
                    AdapterChoice::AllowSoftware => "hardware or software Vulkan/Metal adapter",
                },
            })?;
        let info = adapter.get_info();
        let float_atomics = adapter
            .features()
            .contains(wgpu::Features::SHADER_FLOAT32_ATOMIC);
        // Timestamps between the commands of an encoder time the phases of a recorded
        // training iteration (`--bench train`); asked for where the adapter has them.
        let timestamp_features =
            wgpu::Features::TIMESTAMP_QUERY | wgpu::Features::TIMESTAMP_QUERY_INSIDE_ENCODERS;
        let timestamps = adapter.features().contains(timestamp_features);
        let mut required_features = wgpu::Features::empty();
        if float_atomics {
            required_features |= wgpu::Features::SHADER_FLOAT32_ATOMIC;
        }
        if timestamps {
            required_features |= timestamp_features;
        }
        let f16 = adapter.features().contains(wgpu::Features::SHADER_F16);
        if f16 {
            required_features |= wgpu::Features::SHADER_F16;
        }
        let tensor_cores = TensorCores::of_adapter(&adapter);
        let experimental_features = if tensor_cores.is_some() {
            required_features |= wgpu::Features::EXPERIMENTAL_COOPERATIVE_MATRIX;
            // SAFETY: `enabled` only lets the device be opened with wgpu's experimental
            // features, here cooperative matrices alone; wgpu may have bugs in them, which is
            // why the one kernel that uses them (`nn_matmul_coop.wgsl`) is checked against
            // the f32 kernel on the hardware that has them (`nn::gpu` tests) and is chosen
            // only by `Precision::Mixed`, with the f32 kernels kept on every device.
            unsafe { wgpu::ExperimentalFeatures::enabled() }
        } else {
            wgpu::ExperimentalFeatures::disabled()
        };
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("seqavatar"),
            required_features,
            required_limits: limits.clone(),
            experimental_features,
            memory_hints: wgpu::MemoryHints::Performance,
            trace: wgpu::Trace::Off,
        }))
        .map_err(|error| BackendError::DeviceRequest {
            adapter: info.name.clone(),
            message: error.to_string(),
        })?;
        Ok(Self {
            info,
            device,
            queue,
            limits: limits.clone(),
            float_atomics,
            f16,
            tensor_cores,
            timestamps,
            dispatch_limit: limits.max_compute_workgroups_per_dimension,
            kernels: Mutex::new(HashMap::new()),
            transfers: TransferCounters::default(),
        })
    }

    /// Lowers the number of workgroups per dimension before dispatches go 2D (tests only:
    /// small scenes then cover the 2D index arithmetic). Values above the adapter limit are
    /// clamped to it.
    pub fn with_dispatch_limit(mut self, limit: u32) -> Self {
        self.dispatch_limit = limit.clamp(1, self.limits.max_compute_workgroups_per_dimension);
        self
    }

    /// The most workgroups one dimension of a grid may have.
    pub fn max_workgroups_per_dimension(&self) -> u32 {
        self.limits.max_compute_workgroups_per_dimension
    }

    pub fn info(&self) -> &wgpu::AdapterInfo {
        &self.info
    }

    /// Adapter name, kind, driver and whether f32 atomics are native.
    pub fn describe(&self) -> String {
        format!(
            "{} [{:?}, {:?}, {}{}]",
            self.info.name,
            self.info.device_type,
            self.info.backend,
            self.info.driver,
            if self.float_atomics {
                ", f32 atomics"
            } else {
                ", no f32 atomics"
            }
        )
    }

    pub fn device(&self) -> &wgpu::Device {
        &self.device
    }

    pub fn queue(&self) -> &wgpu::Queue {
        &self.queue
    }

    pub fn limits(&self) -> &wgpu::Limits {
        &self.limits
    }

    /// Whether the device was opened with `SHADER_FLOAT32_ATOMIC`.
    pub fn has_float_atomics(&self) -> bool {
        self.float_atomics
    }

    /// Whether the device was opened with `SHADER_F16`.
    pub fn has_f16(&self) -> bool {
        self.f16
    }

    /// The tensor-core configuration of the device, if it was opened with one.
    pub fn tensor_cores(&self) -> Option<TensorCores> {
        self.tensor_cores
    }

    /// Whether timestamps can be written between the commands of an encoder
    /// (`TIMESTAMP_QUERY` and `TIMESTAMP_QUERY_INSIDE_ENCODERS`; see [`super::PhaseTimer`]).
    pub fn has_timestamps(&self) -> bool {
        self.timestamps
    }

    /// The largest storage buffer one binding may hold, in bytes.
    pub fn max_binding_bytes(&self) -> u64 {
        self.limits
            .max_storage_buffer_binding_size
            .min(self.limits.max_buffer_size)
    }

    /// Compiles (once, after [`super::shaders::expand_includes`]) and returns the pipeline
    /// for `source`.
    pub fn kernel(&self, source: &KernelSource) -> Result<Arc<Kernel>, BackendError> {
        let mut kernels = self.kernels.lock().map_err(|_| BackendError::Gpu {
            message: "kernel cache lock poisoned".to_owned(),
        })?;
        if let Some(kernel) = kernels.get(source.name) {
            return Ok(kernel.clone());
        }
        let kernel = Arc::new(Kernel::compile(
            &self.device,
            source.name,
            &source.wgsl,
            source.entry_point,
        )?);
        kernels.insert(source.name, kernel.clone());
        Ok(kernel)
    }

    /// [`GpuContext::kernel`] of WGSL text built into the binary.
    pub fn static_kernel(
        &self,
        name: &'static str,
        wgsl: &'static str,
        entry_point: &'static str,
    ) -> Result<Arc<Kernel>, BackendError> {
        self.kernel(&KernelSource {
            name,
            wgsl: Cow::Borrowed(wgsl),
            entry_point,
        })
    }

    fn check_size(&self, what: &str, bytes: u64) -> Result<(), BackendError> {
        let limit = self.max_binding_bytes();
        if bytes > limit {
            return Err(BackendError::BufferTooLarge {
                what: what.to_owned(),
                bytes,
                limit,
            });
        }
        Ok(())
    }

    /// Host-device traffic through this context so far; the difference of two snapshots
    /// ([`Transfers::since`]) is the traffic between them.
    pub fn transfers(&self) -> Transfers {
        self.transfers.snapshot()
    }

    /// Writes `data` into `buffer` at element `offset` (`T` elements) through the queue,
    /// ordered before the next submission: how per-iteration scalars reach a resident step.
    pub fn write<T: bytemuck::Pod>(
        &self,
        buffer: &wgpu::Buffer,
        offset: usize,
        data: &[T],
    ) -> Result<(), BackendError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        let start = (offset * std::mem::size_of::<T>()) as u64;
        if start + bytes.len() as u64 > buffer.size() {
            return Err(BackendError::Gpu {
                message: format!(
                    "writing {} bytes at byte {start} of a {}-byte buffer",
                    bytes.len(),
                    buffer.size()
                ),
            });
        }
        if !bytes.is_empty() {
            self.queue.write_buffer(buffer, start, bytes);
            self.transfers.up(bytes.len());
        }
        Ok(())
    }

    /// A storage buffer holding `data` (copyable back with [`GpuContext::download`]).
    pub fn upload<T: bytemuck::Pod>(
        &self,
        what: &str,
        data: &[T],
    ) -> Result<GpuBuffer, BackendError> {
        let bytes: &[u8] = bytemuck::cast_slice(data);
        self.check_size(what, bytes.len() as u64)?;
        self.transfers.up(bytes.len());
        // At least 16 bytes, so that empty inputs still bind.
        let mut padded = [0_u8; 16];
        let contents = if bytes.len() >= 16 {
            bytes
        } else {
            padded[..bytes.len()].copy_from_slice(bytes);
            &padded
        };
        let buffer = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(what),
                contents,
                usage: storage_usage(),
            });
        Ok(GpuBuffer {
            buffer,
            len: data.len(),
        })
    }

    /// A zero-filled storage buffer of `len` elements of `element_bytes` bytes each.
    pub fn zeros(
        &self,
        what: &str,
        len: usize,
        element_bytes: usize,
    ) -> Result<GpuBuffer, BackendError> {
        let bytes = (len as u64)
            .checked_mul(element_bytes as u64)
            .ok_or_else(|| BackendError::BufferTooLarge {
                what: what.to_owned(),
                bytes: u64::MAX,
                limit: self.max_binding_bytes(),
            })?;
        self.check_size(what, bytes)?;
        // Buffers are zero-initialised by wgpu; round up to 16 bytes so empty ones still bind.
        let size = bytes.max(16).div_ceil(4) * 4;
        let buffer = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size,
            usage: storage_usage(),
            mapped_at_creation: false,
        });
        Ok(GpuBuffer { buffer, len })
    }

    /// A small uniform buffer holding one `T`.
    pub fn uniform<T: bytemuck::Pod>(&self, what: &str, value: &T) -> wgpu::Buffer {
        self.transfers.up(std::mem::size_of::<T>());
        super::kernel::uniform_buffer(&self.device, what, value)
    }

    pub fn encoder(&self) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor { label: None })
    }

    /// Records one call of `kernel` ([`Kernel::call`]): `params` uploaded as its uniform
    /// block at binding 0, `bindings` at theirs, a [`Workgroups::Linear`] launch laid out in
    /// 2D beyond the per-dimension limit (shaders recover the linear index as
    /// `id.x + id.y * num.x`).
    pub fn call<P: bytemuck::Pod>(
        &self,
        target: &mut impl Record,
        kernel: &Kernel,
        params: &P,
        bindings: &[(u32, &wgpu::Buffer)],
        workgroups: impl Into<Workgroups>,
    ) {
        self.transfers.up(std::mem::size_of::<P>());
        kernel.call(target, params, bindings, self.layout(workgroups.into()));
    }

    /// [`GpuContext::call`] of a kernel whose uniform blocks, if any, are among `bindings`
    /// ([`Kernel::dispatch`]).
    pub fn dispatch(
        &self,
        target: &mut impl Record,
        kernel: &Kernel,
        bindings: &[(u32, &wgpu::Buffer)],
        workgroups: impl Into<Workgroups>,
    ) {
        kernel.dispatch(target, bindings, self.layout(workgroups.into()));
    }

    /// A 1D launch as a grid within [`GpuContext::dispatch_limit`].
    fn layout(&self, workgroups: Workgroups) -> Workgroups {
        match workgroups {
            Workgroups::Linear(count) => {
                let (x, y) = split_workgroups(count, self.dispatch_limit);
                Workgroups::Grid(x, y)
            }
            other => other,
        }
    }

    /// A zero-filled buffer of `len` u32 that kernels write as storage and
    /// [`Workgroups::Indirect`] reads as grids.
    pub fn indirect_args(&self, what: &str, len: usize) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(what),
            size: (4 * len as u64).max(16).div_ceil(4) * 4,
            usage: storage_usage() | wgpu::BufferUsages::INDIRECT,
            mapped_at_creation: false,
        })
    }

    /// Workgroups per dimension before [`GpuContext::dispatch`] goes 2D (the adapter limit,
    /// or a lower one in tests): what a kernel writing an indirect grid splits by.
    pub fn dispatch_limit(&self) -> u32 {
        self.dispatch_limit
    }

    /// Submits `encoder` and waits for the GPU to finish.
    pub fn submit_and_wait(&self, encoder: wgpu::CommandEncoder) -> Result<(), BackendError> {
        let index = self.queue.submit([encoder.finish()]);
        self.wait_for(index)
    }

    /// Waits for the GPU to finish submission `index`.
    fn wait_for(&self, index: wgpu::SubmissionIndex) -> Result<(), BackendError> {
        self.device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
            .map_err(|error| BackendError::Gpu {
                message: error.to_string(),
            })?;
        Ok(())
    }

    /// Copies the first `len` elements of `source` back to the host (submits pending work in
    /// `encoder` first).
    pub fn download<T: bytemuck::Pod>(
        &self,
        encoder: wgpu::CommandEncoder,
        source: &wgpu::Buffer,
        len: usize,
    ) -> Result<Vec<T>, BackendError> {
        Ok(self
            .download_all::<T>(encoder, &[(source, len)])?
            .pop()
            .unwrap_or_default())
    }

    /// Copies the first `len` elements of each `(source, len)` back to the host, in order
    /// (submits pending work in `encoder` first): [`GpuContext::download_many`] and
    /// [`GpuContext::finish_downloads`] in one call.
    pub fn download_all<T: bytemuck::Pod>(
        &self,
        mut encoder: wgpu::CommandEncoder,
        sources: &[(&wgpu::Buffer, usize)],
    ) -> Result<Vec<Vec<T>>, BackendError> {
        let mut pending = self.download_many::<T>(&mut encoder, sources)?;
        self.finish_downloads(encoder, &mut pending)?;
        Ok(pending.into_iter().map(|p| p.values).collect())
    }

    /// Records copies of several buffers into staging buffers; call
    /// [`GpuContext::finish_downloads`] to submit and read them.
    pub fn download_many<T: bytemuck::Pod>(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        sources: &[(&wgpu::Buffer, usize)],
    ) -> Result<Vec<PendingDownload<T>>, BackendError> {
        let element = std::mem::size_of::<T>() as u64;
        sources
            .iter()
            .map(|(source, len)| {
                let bytes = (*len as u64) * element;
                let size = bytes.max(4).div_ceil(4) * 4;
                let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
                    label: Some("download"),
                    size,
                    usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                    mapped_at_creation: false,
                });
                if bytes > 0 {
                    encoder.copy_buffer_to_buffer(source, 0, &staging, 0, size.min(source.size()));
                }
                Ok(PendingDownload {
                    staging,
                    len: *len,
                    values: Vec::new(),
                })
            })
            .collect()
    }

    /// Submits `encoder` and reads every pending download into its `values`.
    pub fn finish_downloads<T: bytemuck::Pod>(
        &self,
        encoder: wgpu::CommandEncoder,
        pending: &mut [PendingDownload<T>],
    ) -> Result<(), BackendError> {
        let index = self.queue.submit([encoder.finish()]);
        {
            use std::sync::atomic::Ordering::Relaxed;
            self.transfers.readbacks.fetch_add(1, Relaxed);
            let bytes: usize = pending
                .iter()
                .map(|p| p.len * std::mem::size_of::<T>())
                .sum();
            self.transfers.bytes_down.fetch_add(bytes as u64, Relaxed);
        }
        let (sender, receiver) = std::sync::mpsc::channel();
        for (position, download) in pending.iter().enumerate() {
            let sender = sender.clone();
            download
                .staging
                .map_async(wgpu::MapMode::Read, .., move |result| {
                    let _ = sender.send((position, result));
                });
        }
        drop(sender);
        self.wait_for(index)?;
        for (_, result) in receiver.iter() {
            result.map_err(|error| BackendError::Gpu {
                message: format!("mapping a download buffer: {error}"),
            })?;
        }
        for download in pending.iter_mut() {
            let element = std::mem::size_of::<T>();
            let view =
                download
                    .staging
                    .get_mapped_range(..)
                    .map_err(|error| BackendError::Gpu {
                        message: format!("reading a download buffer: {error}"),
                    })?;
            let bytes = &view[..download.len * element];
            download.values = bytemuck::pod_collect_to_vec(bytes);
            drop(view);
            download.staging.unmap();
        }
        Ok(())
    }
}

/// A staging buffer waiting to be read; `values` is filled by
/// [`GpuContext::finish_downloads`].
#[derive(Debug)]
pub struct PendingDownload<T> {
    staging: wgpu::Buffer,
    len: usize,
    pub values: Vec<T>,
}

/// The wgpu instance adapters are enumerated from: Vulkan and Metal, no display handle.
///
/// Where a Vulkan instance would enable window-system surface extensions (Unix but macOS),
/// it is created without them ([`headless_vulkan_instance`]); it falls back to wgpu's own
/// instance when that fails.
fn compute_instance() -> wgpu::Instance {
    #[cfg(all(unix, not(target_os = "macos"), not(target_os = "ios")))]
    if let Some(instance) = headless_vulkan_instance() {
        return instance;
    }
    let mut descriptor = wgpu::InstanceDescriptor::new_without_display_handle();
    descriptor.backends = descriptor_backends();
    wgpu::Instance::new(descriptor)
}

/// Window-system surface extensions a compute-only Vulkan instance leaves out.
#[cfg(all(unix, not(target_os = "macos"), not(target_os = "ios")))]
const WINDOW_SYSTEM_EXTENSIONS: [&std::ffi::CStr; 3] = [
    c"VK_KHR_wayland_surface",
    c"VK_KHR_xlib_surface",
    c"VK_KHR_xcb_surface",
];

/// A Vulkan instance without the window-system surface extensions: nothing here presents to
/// a window, and with `VK_KHR_wayland_surface` enabled Mesa's device-select layer connects to
/// a Wayland display while enumerating adapters, which prints `error: XDG_RUNTIME_DIR is
/// invalid or not set in the environment.` on stderr of every headless run. `None` when no
/// Vulkan loader or driver is there.
#[cfg(all(unix, not(target_os = "macos"), not(target_os = "ios")))]
fn headless_vulkan_instance() -> Option<wgpu::Instance> {
    use wgpu::hal;
    let defaults = wgpu::InstanceDescriptor::new_without_display_handle();
    let descriptor = hal::InstanceDescriptor {
        name: "seqavatar",
        flags: defaults.flags,
        memory_budget_thresholds: defaults.memory_budget_thresholds,
        backend_options: defaults.backend_options,
        telemetry: None,
        display: None,
    };
    let callback: Box<hal::vulkan::CreateInstanceCallback<'static>> = Box::new(|args| {
        args.extensions
            .retain(|name| !WINDOW_SYSTEM_EXTENSIONS.contains(name));
    });
    // SAFETY: the callback only removes surface extensions, which wgpu-hal uses for nothing
    // but creating window surfaces (it checks the enabled list first and reports the
    // extension missing); this crate never creates a surface.
    let instance =
        unsafe { hal::vulkan::Instance::init_with_callback(&descriptor, Some(callback)) };
    let instance = instance.ok()?;
    // SAFETY: a valid instance just created; wgpu takes ownership of it.
    Some(unsafe { wgpu::Instance::from_hal::<hal::api::Vulkan>(instance) })
}

fn descriptor_backends() -> wgpu::Backends {
    wgpu::Backends::VULKAN | wgpu::Backends::METAL
}

fn storage_usage() -> wgpu::BufferUsages {
    wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC | wgpu::BufferUsages::COPY_DST
}

/// Splits `workgroups` into an `x` by `y` grid with `x <= max_per_dimension` and
/// `x * y >= workgroups` (the excess workgroups must return early).
pub fn split_workgroups(workgroups: u32, max_per_dimension: u32) -> (u32, u32) {
    if workgroups <= max_per_dimension {
        (workgroups, 1)
    } else {
        let y = workgroups.div_ceil(max_per_dimension);
        (workgroups.div_ceil(y), y)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_workgroups_covers_and_respects_the_limit() {
        for (count, max) in [
            (1, 65535),
            (65535, 65535),
            (65536, 65535),
            (10_000_000, 65535),
            (7, 3),
        ] {
            let (x, y) = split_workgroups(count, max);
            assert!(x <= max && y <= max, "{count} {max}: {x} {y}");
            assert!(u64::from(x) * u64::from(y) >= u64::from(count));
            // No whole row of excess workgroups.
            assert!(u64::from(x) * u64::from(y - 1) < u64::from(count));
        }
    }

    /// The instance adapters come from enables no window-system surface extension (with
    /// `VK_KHR_wayland_surface`, Mesa's device-select layer prints an `XDG_RUNTIME_DIR`
    /// error on headless machines).
    #[cfg(all(unix, not(target_os = "macos"), not(target_os = "ios")))]
    #[test]
    fn the_compute_instance_enables_no_window_system_extension() {
        let Some(instance) = headless_vulkan_instance() else {
            assert!(
                std::env::var_os("CI").is_none(),
                "CI is set but no Vulkan instance could be created"
            );
            eprintln!("skipped: no Vulkan loader");
            return;
        };
        // SAFETY: the hal instance is only read.
        let hal =
            unsafe { instance.as_hal::<wgpu::hal::api::Vulkan>() }.expect("a Vulkan instance");
        let enabled = hal.shared_instance().extensions();
        println!("enabled instance extensions: {enabled:?}");
        assert!(
            enabled
                .iter()
                .all(|name| !WINDOW_SYSTEM_EXTENSIONS.contains(name)),
            "{enabled:?}"
        );
        assert!(enabled.contains(&c"VK_KHR_get_physical_device_properties2"));
    }
}
