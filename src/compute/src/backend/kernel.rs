//! One kernel call: a [`Kernel`], its params (the uniform block at binding 0), its buffers
//! and its [`Workgroups`], recorded into a [`Record`] (an encoder, or `nn::gpu::NnProgram`).
//! Every dispatch goes through [`Kernel::call`] or [`Kernel::dispatch`]; the context's
//! versions add its traffic counter and its 2D layout of long 1D launches.

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
#[derive(Clone, Debug)]
pub enum Workgroups {
    /// A 1D launch; [`GpuContext::call`](super::GpuContext::call) lays it out in 2D beyond the
    /// per-dimension limit (shaders recover the linear index as `id.x + id.y * num.x`).
    Linear(u32),
    /// An `x` by `y` grid.
    Grid(u32, u32),
    /// A grid the device wrote into the buffer at the byte offset (three u32), so that a kernel
    /// decides on the device whether and how widely another runs (`INDIRECT` usage:
    /// [`GpuContext::indirect_args`](super::GpuContext::indirect_args)).
    Indirect(wgpu::Buffer, u64),
}

impl From<u32> for Workgroups {
    fn from(count: u32) -> Self {
        Workgroups::Linear(count)
    }
}

impl From<(u32, u32)> for Workgroups {
    fn from((x, y): (u32, u32)) -> Self {
        Workgroups::Grid(x, y)
    }
}

impl Workgroups {
    fn is_empty(&self) -> bool {
        matches!(
            self,
            Workgroups::Linear(0) | Workgroups::Grid(0, _) | Workgroups::Grid(_, 0)
        )
    }
}

/// One call with its uniform block and bindings resolved: what a [`Record`] receives.
#[derive(Clone, Debug)]
pub struct PreparedDispatch {
    /// The kernel's name (the compute pass label).
    pub label: &'static str,
    pub pipeline: wgpu::ComputePipeline,
    /// Its uniform block and buffers.
    pub bind_group: wgpu::BindGroup,
    pub workgroups: Workgroups,
}

impl PreparedDispatch {
    /// Sets the pipeline and bindings on `pass` and dispatches.
    pub fn record_into(&self, pass: &mut wgpu::ComputePass<'_>) {
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.bind_group, &[]);
        match &self.workgroups {
            Workgroups::Linear(x) => pass.dispatch_workgroups(*x, 1, 1),
            Workgroups::Grid(x, y) => pass.dispatch_workgroups(*x, *y, 1),
            Workgroups::Indirect(buffer, offset) => {
                pass.dispatch_workgroups_indirect(buffer, *offset);
            }
        }
    }
}

/// Where kernel calls are recorded: straight into a command encoder (one compute pass per
/// call), or into a program that keeps the calls' uniform blocks and bind groups, so a
/// resident step creates them once per shape and replays them every iteration.
pub trait Record {
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
    /// at theirs. Empty workgroups record nothing.
    pub fn call<P: bytemuck::Pod>(
        &self,
        target: &mut impl Record,
        params: &P,
        bindings: &[(u32, &wgpu::Buffer)],
        workgroups: impl Into<Workgroups>,
    ) {
        let workgroups = workgroups.into();
        if workgroups.is_empty() {
            return;
        }
        let uniform = uniform_buffer(&self.device, self.name, params);
        self.dispatch(target, &[&[(0, &uniform)], bindings].concat(), workgroups);
    }

    /// Records one call whose uniform blocks, if any, are among `bindings` (blocks a resident
    /// step writes in place); otherwise as [`Kernel::call`].
    pub fn dispatch(
        &self,
        target: &mut impl Record,
        bindings: &[(u32, &wgpu::Buffer)],
        workgroups: impl Into<Workgroups>,
    ) {
        let workgroups = workgroups.into();
        if workgroups.is_empty() {
            return;
        }
        let entries: Vec<wgpu::BindGroupEntry<'_>> = bindings
            .iter()
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
        target.record_dispatch(PreparedDispatch {
            label: self.name,
            pipeline: self.pipeline.clone(),
            bind_group,
            workgroups,
        });
    }
}

/// A uniform block holding `value`, writable in place by the queue: every uniform buffer of
/// the gpu backend is made here (per call by [`Kernel::call`], once by
/// [`GpuContext::uniform`](super::GpuContext::uniform) for blocks a resident step rewrites).
pub(crate) fn uniform_buffer<T: bytemuck::Pod>(
    device: &wgpu::Device,
    label: &str,
    value: &T,
) -> wgpu::Buffer {
    device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
        label: Some(label),
        contents: bytemuck::bytes_of(value),
        usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
    })
}
