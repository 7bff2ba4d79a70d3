//! One kernel call: a compiled [`Kernel`], its params (a uniform block at binding 0), its
//! buffers and its workgroups, recorded as one compute pass into a [`Record`]: a command
//! encoder, or a program that keeps the bind groups and replays them (`nn::gpu::NnProgram`).
//! Every dispatch of the gpu backend goes through [`Kernel::call`] or [`Kernel::dispatch`]
//! ([`GpuContext::call`](super::GpuContext::call) adds the context's traffic counter and its
//! 2D layout of long 1D launches).

use wgpu::util::DeviceExt;

use super::BackendError;

/// A compiled compute pipeline, its bind group layout (group 0) and the device it was
/// compiled for (whose bind groups and uniform blocks its calls create).
#[derive(Debug)]
pub struct Kernel {
    pub name: &'static str,
    pub(crate) pipeline: wgpu::ComputePipeline,
    pub(crate) layout: wgpu::BindGroupLayout,
    device: wgpu::Device,
}

/// The workgroups of one call.
#[derive(Clone, Copy, Debug)]
pub enum Workgroups<'a> {
    /// A 1D launch, laid out in 2D beyond the per-dimension limit by
    /// [`GpuContext::call`](super::GpuContext::call) (shaders recover the linear index as
    /// `id.x + id.y * num.x`); [`Kernel::call`] takes it as one row.
    Linear(u32),
    /// An `x` by `y` grid.
    Grid(u32, u32),
    /// A grid the device wrote into the buffer at the byte offset (three u32: x, y, z), so
    /// that a kernel decides on the device whether and how widely another runs. The buffer
    /// needs `INDIRECT` usage ([`GpuContext::indirect_args`](super::GpuContext::indirect_args)).
    Indirect(&'a wgpu::Buffer, u64),
}

impl From<u32> for Workgroups<'_> {
    fn from(count: u32) -> Self {
        Workgroups::Linear(count)
    }
}

impl From<(u32, u32)> for Workgroups<'_> {
    fn from((x, y): (u32, u32)) -> Self {
        Workgroups::Grid(x, y)
    }
}

/// The grid of a [`PreparedDispatch`].
#[derive(Clone, Debug)]
pub enum PreparedGrid {
    /// An `x` by `y` grid.
    Grid(u32, u32),
    /// Read by the device from the buffer at the byte offset.
    Indirect(wgpu::Buffer, u64),
}

/// One call with its uniform block and bindings resolved: what a [`Record`] receives.
#[derive(Clone, Debug)]
pub struct PreparedDispatch {
    /// The kernel's name (the compute pass label).
    pub label: &'static str,
    /// The compiled kernel.
    pub pipeline: wgpu::ComputePipeline,
    /// Its uniform block and buffers.
    pub bind_group: wgpu::BindGroup,
    /// Its workgroups.
    pub grid: PreparedGrid,
}

impl PreparedDispatch {
    /// Sets the pipeline and bindings on `pass` and dispatches.
    pub fn record_into(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        match &self.grid {
            PreparedGrid::Grid(x, y) => pass.dispatch_workgroups(*x, *y, 1),
            PreparedGrid::Indirect(buffer, offset) => {
                pass.dispatch_workgroups_indirect(buffer, *offset);
            }
        }
    }
}

/// Where kernel calls are recorded: straight into a command encoder (one compute pass per
/// call; the uniform blocks and bind groups of each call are created by the call), or into a
/// program that keeps them, so a resident step creates them once per shape and replays the
/// program every iteration with no allocation and no upload.
pub trait Record {
    /// Records one dispatch.
    fn record_dispatch(&mut self, dispatch: PreparedDispatch);
    /// Records the zeroing of a whole buffer.
    fn record_clear(&mut self, buffer: &wgpu::Buffer);
}

impl Record for wgpu::CommandEncoder {
    fn record_dispatch(&mut self, dispatch: PreparedDispatch) {
        let mut pass = self.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(dispatch.label),
            timestamp_writes: None,
        });
        dispatch.record_into(&mut pass);
    }

    fn record_clear(&mut self, buffer: &wgpu::Buffer) {
        self.clear_buffer(buffer, 0, None);
    }
}

impl Kernel {
    /// Compiles kernel `name` (its WGSL through [`super::shaders::expand_includes`] and
    /// [`super::shaders::compile_module`]) into the pipeline of entry point `entry`; a
    /// validation error names the kernel. Every kernel is built here (`GpuContext::kernel`
    /// caches them, `NnGpu::new` keeps its own).
    pub(crate) fn compile(
        device: &wgpu::Device,
        name: &'static str,
        wgsl: &str,
        entry: &str,
    ) -> Result<Self, BackendError> {
        Self::compile_with_constants(device, name, wgsl, entry, &[])
    }

    /// [`Kernel::compile`] with values for the kernel's `override` constants (the
    /// tensor-core kernel's workgroup size is the adapter's subgroup size).
    pub(crate) fn compile_with_constants(
        device: &wgpu::Device,
        name: &'static str,
        wgsl: &str,
        entry: &str,
        constants: &[(&str, f64)],
    ) -> Result<Self, BackendError> {
        let wgsl = super::shaders::expand_includes(name, wgsl)?;
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let module = super::shaders::compile_module(device, name, wgsl);
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(name),
            layout: None,
            module: &module,
            entry_point: Some(entry),
            compilation_options: wgpu::PipelineCompilationOptions {
                constants,
                ..wgpu::PipelineCompilationOptions::default()
            },
            cache: None,
        });
        if let Some(error) = pollster::block_on(scope.pop()) {
            return Err(BackendError::Shader {
                name: name.to_owned(),
                message: error.to_string(),
            });
        }
        let layout = pipeline.get_bind_group_layout(0);
        Ok(Kernel {
            name,
            pipeline,
            layout,
            device: device.clone(),
        })
    }

    /// Records one call: `params` uploaded as a fresh uniform block at binding 0 (into a
    /// program it is created once and replayed), `bindings` (`(binding, buffer)` in group 0)
    /// at theirs. An empty grid records nothing; a [`Workgroups::Linear`] launch is one row.
    pub fn call<'a, P: bytemuck::Pod>(
        &self,
        target: &mut impl Record,
        params: &P,
        bindings: &[(u32, &wgpu::Buffer)],
        workgroups: impl Into<Workgroups<'a>>,
    ) {
        let workgroups = workgroups.into();
        if is_empty(workgroups) {
            return;
        }
        let uniform = self
            .device
            .create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some(self.name),
                contents: bytemuck::bytes_of(params),
                usage: wgpu::BufferUsages::UNIFORM,
            });
        self.record(target, Some(&uniform), bindings, workgroups);
    }

    /// Records one call whose uniform blocks, if any, are among `bindings` (blocks a resident
    /// step writes in place); otherwise as [`Kernel::call`].
    pub fn dispatch<'a>(
        &self,
        target: &mut impl Record,
        bindings: &[(u32, &wgpu::Buffer)],
        workgroups: impl Into<Workgroups<'a>>,
    ) {
        let workgroups = workgroups.into();
        if !is_empty(workgroups) {
            self.record(target, None, bindings, workgroups);
        }
    }

    fn record(
        &self,
        target: &mut impl Record,
        uniform: Option<&wgpu::Buffer>,
        bindings: &[(u32, &wgpu::Buffer)],
        workgroups: Workgroups<'_>,
    ) {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = uniform
            .map(|uniform| (0, uniform))
            .iter()
            .chain(bindings)
            .map(|(binding, buffer)| wgpu::BindGroupEntry {
                binding: *binding,
                resource: buffer.as_entire_binding(),
            })
            .collect();
        let bind_group = self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: Some(self.name),
            layout: &self.layout,
            entries: &entries,
        });
        let grid = match workgroups {
            Workgroups::Linear(x) => PreparedGrid::Grid(x, 1),
            Workgroups::Grid(x, y) => PreparedGrid::Grid(x, y),
            Workgroups::Indirect(buffer, offset) => PreparedGrid::Indirect(buffer.clone(), offset),
        };
        target.record_dispatch(PreparedDispatch {
            label: self.name,
            pipeline: self.pipeline.clone(),
            bind_group,
            grid,
        });
    }
}

fn is_empty(workgroups: Workgroups<'_>) -> bool {
    match workgroups {
        Workgroups::Linear(x) => x == 0,
        Workgroups::Grid(x, y) => x == 0 || y == 0,
        Workgroups::Indirect(..) => false,
    }
}
