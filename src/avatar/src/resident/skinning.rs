//! Skinning on the device (`shaders/avatar_skin.wgsl`), f32, with the maths of
//! [`crate::skinning`] (the oracle) and of [`crate::avatar::deform`]: the non-rigid heads to
//! deformed canonical Gaussians, skinning of centres and covariances, the activations into the
//! splatting layout, and the exact backward with the per-joint and per-vertex reductions the
//! pose backward reads.
//!
//! Buffers are f32 unless said, row-major, in the cpu layouts ([`GaussianColumns`],
//! [`SkinInputs`] and [`ResidentSkinning`]'s public fields say which).
//!
//! Order of calls in an iteration: [`ResidentSkinning::set_iteration`] (one 16-byte write),
//! then recorded into the step's encoder [`ResidentSkinning::record_deform`] (before the
//! nearest-vertex search and the LBS-offsets network, which read
//! [`ResidentSkinning::positions`]), [`ResidentSkinning::record_forward`] (before the
//! splatting), and after the splatting's backward [`ResidentSkinning::record_backward`] and
//! [`ResidentSkinning::record_activations_backward`].

use std::borrow::Cow;
use std::sync::Arc;

use seqavatar_compute::backend::shaders::{AtomicAdd, with_atomic_add};
use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};

use crate::avatar::SH_STORED;
use crate::model::HEAD_WIDTH;
use crate::skinning::WEIGHT_LOG_EPS;

const SKIN_WGSL: &str = include_str!("../../../../shaders/avatar_skin.wgsl");

/// Threads per workgroup of every kernel of `avatar_skin.wgsl`.
const WORKGROUP: usize = 64;
/// Gaussians per chunk of the per-joint reduction (partial sums `chunks x J x 12`).
const JOINT_CHUNK: usize = 4096;
/// `SkinShape.flags` bits.
const HAS_HEADS: u32 = 1;
const HAS_WEIGHT_OFFSETS: u32 = 2;

/// The canonical Gaussians' columns on the device (the optimiser's buffers).
#[derive(Clone, Copy)]
pub struct GaussianColumns<'a> {
    /// Canonical centres, `N x 3`.
    pub xyz: &'a GpuBuffer,
    /// `N x 3`.
    pub log_scale: &'a GpuBuffer,
    /// Canonical rotations `N x 4`, `[w x y z]`, unnormalised.
    pub rotation: &'a GpuBuffer,
    /// `N`.
    pub opacity_logit: &'a GpuBuffer,
    /// `N x 16 x 3`.
    pub sh: &'a GpuBuffer,
}

/// One iteration's skinning inputs from the other pieces.
#[derive(Clone, Copy)]
pub struct SkinInputs<'a> {
    /// Nearest template vertex of each deformed centre, `N` (u32).
    pub nearest: &'a GpuBuffer,
    /// LBS weight logit offsets `N x J`; given exactly when the skinning was made with
    /// `weight_offsets: true`.
    pub weight_offsets: Option<&'a GpuBuffer>,
    /// Target joint transforms `J x 12`.
    pub target_joints: &'a GpuBuffer,
    /// Per-vertex rest offsets `V x 3`.
    pub vertex_offsets: &'a GpuBuffer,
}

/// What a resident skinning is made of, fixed for a training run.
pub struct SkinningSetup<'a> {
    /// `J` big-pose joint transforms (the rig's `canonical_joints`).
    pub canonical_joints: &'a [[f64; 12]],
    /// Template skinning weights `V x J`.
    pub template_weights: &'a [f64],
    /// Bounds of the linear scale after the non-rigid offset.
    pub scale_min: f64,
    pub scale_max: f64,
    /// Whether a non-rigid network gives heads (else identity offsets).
    pub heads: bool,
    /// Whether an LBS-offsets network gives weight offsets.
    pub weight_offsets: bool,
    /// How the vertex-offset gradient is accumulated; `None` picks native f32 atomics when
    /// the adapter has them.
    pub atomic_add: Option<AtomicAdd>,
}

/// The skinning's device buffers and kernels, sized for a capacity of Gaussians.
pub struct ResidentSkinning {
    context: Arc<GpuContext>,
    joints: usize,
    vertices: usize,
    flags: u32,
    capacity: usize,
    shape: wgpu::Buffer,
    record: GpuBuffer,
    canonical_joints: GpuBuffer,
    template_log_weights: GpuBuffer,
    placeholder: GpuBuffer,
    /// Deformed canonical centres `x + d_xyz`, `N x 3` (the LBS-offsets network's and the
    /// nearest-vertex search's input).
    pub positions: GpuBuffer,
    /// Rotation offsets `N x 4` (`[1, 0, 0, 0]` is none).
    pub d_rotations: GpuBuffer,
    /// Linear scale offsets `N x 3`.
    pub d_scales: GpuBuffer,
    /// World means `N x 3` (the splatting's input).
    pub means: GpuBuffer,
    /// World covariances `N x 6`, upper triangle.
    pub covariances: GpuBuffer,
    /// Opacities `sigmoid(logit)`, `N`.
    pub opacities: GpuBuffer,
    /// SH of the active degree in the splatting layout, `N x k x 3` (capacity for `k = 16`).
    pub sh: GpuBuffer,
    /// `dL/d positions` (the deformed centres; the canonical `xyz`'s direct path), `N x 3`.
    pub grad_positions: GpuBuffer,
    /// `N x 3`.
    pub grad_log_scales: GpuBuffer,
    /// Canonical rotations' gradient `N x 4`.
    pub grad_rotations: GpuBuffer,
    /// The heads' gradient `N x 10`: `[d positions, d d_rot, d d_scale]` (the backward of
    /// the deformation; the non-rigid network's backward reads it).
    pub grad_heads: GpuBuffer,
    /// `N x J` (zeros without weight offsets).
    pub grad_weight_offsets: GpuBuffer,
    /// Target joints' gradient `J x 12` (deterministic reduction).
    pub grad_target_joints: GpuBuffer,
    /// Vertex offsets' gradient `V x 3` (atomic accumulation, cleared by each backward).
    pub grad_vertex_offsets: GpuBuffer,
    /// Opacity logits' gradient `N`.
    pub grad_opacity_logits: GpuBuffer,
    /// SH gradient in the stored layout `N x 16 x 3`.
    pub grad_sh: GpuBuffer,
    /// Non-finite values found, u32 x 4, sticky until [`ResidentSkinning::reset_status`]:
    /// `[forward count, first Gaussian (u32::MAX: none), backward count, first Gaussian]`
    /// (forward: a world mean or covariance; backward: a per-Gaussian gradient).
    pub status: GpuBuffer,
    blend_weights: GpuBuffer,
    grad_blend: GpuBuffer,
    joint_partials: GpuBuffer,
    deform: Arc<Kernel>,
    forward: Arc<Kernel>,
    backward: Arc<Kernel>,
    reduce_joints: Arc<Kernel>,
    finish_joints: Arc<Kernel>,
    activations_backward: Arc<Kernel>,
    /// Gaussians of this iteration and SH coefficients per channel of its active degree
    /// ([`ResidentSkinning::set_iteration`]).
    count: usize,
    sh_coefficients: usize,
}

const STATUS_CLEAR: [u32; 4] = [0, u32::MAX, 0, u32::MAX];

fn kernel(
    context: &GpuContext,
    name: &'static str,
    wgsl: Cow<'static, str>,
    entry: &'static str,
) -> anyhow::Result<Arc<Kernel>> {
    Ok(context.kernel(&KernelSource {
        name,
        wgsl,
        entry_point: entry,
    })?)
}

impl ResidentSkinning {
    /// Uploads the canonical joints and the template log weights `ln(w + 1e-9)` (computed in
    /// f64) once, compiles the kernels and allocates the buffers for `capacity` Gaussians.
    pub fn new(
        context: &Arc<GpuContext>,
        setup: &SkinningSetup<'_>,
        capacity: usize,
    ) -> anyhow::Result<Self> {
        let joints = setup.canonical_joints.len();
        anyhow::ensure!(joints > 0, "canonical_joints: no joints");
        anyhow::ensure!(
            setup.template_weights.len().is_multiple_of(joints),
            "template_weights: {} values are not V x {joints}",
            setup.template_weights.len()
        );
        anyhow::ensure!(
            setup.scale_min.is_finite()
                && setup.scale_max.is_finite()
                && 0.0 < setup.scale_min
                && setup.scale_min <= setup.scale_max,
            "scale_min {} and scale_max {} must be finite with 0 < scale_min <= scale_max",
            setup.scale_min,
            setup.scale_max
        );
        let vertices = setup.template_weights.len() / joints;
        let flags = (u32::from(setup.heads) * HAS_HEADS)
            | (u32::from(setup.weight_offsets) * HAS_WEIGHT_OFFSETS);
        let shape: [u32; 8] = [
            joints as u32,
            vertices as u32,
            flags,
            JOINT_CHUNK as u32,
            (setup.scale_min as f32).to_bits(),
            (setup.scale_max as f32).to_bits(),
            0,
            0,
        ];
        let canonical: Vec<f32> = setup
            .canonical_joints
            .iter()
            .flatten()
            .map(|&x| x as f32)
            .collect();
        let log_weights: Vec<f32> = setup
            .template_weights
            .iter()
            .map(|&w| (w + WEIGHT_LOG_EPS).ln() as f32)
            .collect();
        let mode = setup.atomic_add.unwrap_or(if context.has_float_atomics() {
            AtomicAdd::NativeFloat
        } else {
            AtomicAdd::CompareExchange
        });
        let backward = match mode {
            AtomicAdd::NativeFloat => kernel(
                context,
                "avatar_skin_backward_float_atomics",
                Cow::Owned(with_atomic_add("avatar_skin.wgsl", SKIN_WGSL, mode)?),
                "skin_backward",
            )?,
            AtomicAdd::CompareExchange => kernel(
                context,
                "avatar_skin_backward_compare_exchange",
                Cow::Borrowed(SKIN_WGSL),
                "skin_backward",
            )?,
        };
        let plain = |name, entry| kernel(context, name, Cow::Borrowed(SKIN_WGSL), entry);
        let mut skinning = Self {
            joints,
            vertices,
            flags,
            capacity: 0,
            shape: context.uniform("avatar skin shape", &shape),
            record: context.zeros("avatar skin record", 4, 4)?,
            canonical_joints: context.upload("canonical joints", &canonical)?,
            template_log_weights: context.upload("template log weights", &log_weights)?,
            placeholder: context.zeros("absent input", 1, 4)?,
            grad_target_joints: context.zeros("grad target joints", 12 * joints, 4)?,
            grad_vertex_offsets: context.zeros("grad vertex offsets", 3 * vertices, 4)?,
            status: context.upload("avatar skin status", &STATUS_CLEAR)?,
            positions: context.zeros("deformed positions", 0, 4)?,
            d_rotations: context.zeros("d_rotations", 0, 4)?,
            d_scales: context.zeros("d_scales", 0, 4)?,
            means: context.zeros("world means", 0, 4)?,
            covariances: context.zeros("world covariances", 0, 4)?,
            opacities: context.zeros("opacities", 0, 4)?,
            sh: context.zeros("active sh", 0, 4)?,
            grad_positions: context.zeros("grad positions", 0, 4)?,
            grad_log_scales: context.zeros("grad log scales", 0, 4)?,
            grad_rotations: context.zeros("grad rotations", 0, 4)?,
            grad_heads: context.zeros("grad heads", 0, 4)?,
            grad_weight_offsets: context.zeros("grad weight offsets", 0, 4)?,
            grad_opacity_logits: context.zeros("grad opacity logits", 0, 4)?,
            grad_sh: context.zeros("grad sh", 0, 4)?,
            blend_weights: context.zeros("blend weights", 0, 4)?,
            grad_blend: context.zeros("grad blended targets", 0, 4)?,
            joint_partials: context.zeros("joint partials", 0, 4)?,
            deform: plain("avatar_deform", "deform")?,
            forward: plain("avatar_skin_forward", "skin_forward")?,
            backward,
            reduce_joints: plain("avatar_reduce_joints", "reduce_joints")?,
            finish_joints: plain("avatar_finish_joints", "finish_joints")?,
            activations_backward: plain("avatar_activations_backward", "activations_backward")?,
            count: 0,
            sh_coefficients: 1,
            context: context.clone(),
        };
        skinning.reserve(capacity)?;
        Ok(skinning)
    }

    /// Grows the per-Gaussian buffers to hold `capacity` Gaussians (no-op when they do);
    /// their contents are lost when they grow.
    pub fn reserve(&mut self, capacity: usize) -> anyhow::Result<()> {
        if capacity <= self.capacity && self.capacity > 0 {
            return Ok(());
        }
        let (c, j) = (capacity, self.joints);
        let context = &self.context;
        let zeros = |what: &str, len: usize| context.zeros(what, len, 4);
        self.positions = zeros("deformed positions", 3 * c)?;
        self.d_rotations = zeros("d_rotations", 4 * c)?;
        self.d_scales = zeros("d_scales", 3 * c)?;
        self.means = zeros("world means", 3 * c)?;
        self.covariances = zeros("world covariances", 6 * c)?;
        self.opacities = zeros("opacities", c)?;
        self.sh = zeros("active sh", 3 * SH_STORED * c)?;
        self.grad_positions = zeros("grad positions", 3 * c)?;
        self.grad_log_scales = zeros("grad log scales", 3 * c)?;
        self.grad_rotations = zeros("grad rotations", 4 * c)?;
        self.grad_heads = zeros("grad heads", HEAD_WIDTH * c)?;
        self.grad_weight_offsets = zeros("grad weight offsets", j * c)?;
        self.grad_opacity_logits = zeros("grad opacity logits", c)?;
        self.grad_sh = zeros("grad sh", 3 * SH_STORED * c)?;
        self.blend_weights = zeros("blend weights", j * c)?;
        self.grad_blend = zeros("grad blended targets", 12 * c)?;
        self.joint_partials = zeros("joint partials", c.div_ceil(JOINT_CHUNK).max(1) * j * 12)?;
        self.capacity = capacity;
        Ok(())
    }

    /// Gaussians the buffers hold.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Writes this iteration's record (16 bytes): the Gaussian count (at most the capacity)
    /// and the active SH degree (0 to 3).
    pub fn set_iteration(&mut self, gaussians: usize, sh_degree: u32) -> anyhow::Result<()> {
        anyhow::ensure!(
            gaussians <= self.capacity,
            "{gaussians} Gaussians exceed the skinning's capacity {} (reserve first)",
            self.capacity
        );
        anyhow::ensure!(sh_degree <= 3, "sh_degree {sh_degree} is above 3");
        let coefficients = (sh_degree + 1) * (sh_degree + 1);
        let chunks = gaussians.div_ceil(JOINT_CHUNK) as u32;
        self.context.write(
            &self.record.buffer,
            0,
            &[gaussians as u32, coefficients, chunks, 0],
        )?;
        self.count = gaussians;
        self.sh_coefficients = coefficients as usize;
        Ok(())
    }

    fn workgroups(&self) -> anyhow::Result<u32> {
        u32::try_from(self.count.div_ceil(WORKGROUP))
            .map_err(|_| anyhow::anyhow!("{} Gaussians exceed one dispatch", self.count))
    }

    fn check(&self, what: &str, buffer: &GpuBuffer, per: usize) -> anyhow::Result<()> {
        let needed = per * self.count;
        anyhow::ensure!(
            buffer.len >= needed,
            "{what}: {} values, {} Gaussians need {needed}",
            buffer.len,
            self.count
        );
        Ok(())
    }

    fn check_inputs(
        &self,
        columns: &GaussianColumns<'_>,
        inputs: &SkinInputs<'_>,
    ) -> anyhow::Result<()> {
        self.check("log_scale", columns.log_scale, 3)?;
        self.check("rotation", columns.rotation, 4)?;
        self.check("opacity_logit", columns.opacity_logit, 1)?;
        self.check("sh", columns.sh, 3 * SH_STORED)?;
        self.check("nearest", inputs.nearest, 1)?;
        let j = self.joints;
        match (self.flags & HAS_WEIGHT_OFFSETS != 0, inputs.weight_offsets) {
            (true, Some(offsets)) => self.check("weight_offsets", offsets, j)?,
            (false, None) => {}
            (true, None) => anyhow::bail!("weight_offsets: required by the setup but not given"),
            (false, Some(_)) => {
                anyhow::bail!("weight_offsets: given but the setup has no weight offsets")
            }
        }
        anyhow::ensure!(
            inputs.target_joints.len == 12 * j,
            "target_joints: {} values for {j} joints",
            inputs.target_joints.len
        );
        anyhow::ensure!(
            inputs.vertex_offsets.len == 3 * self.vertices,
            "vertex_offsets: {} values for {} vertices",
            inputs.vertex_offsets.len,
            self.vertices
        );
        Ok(())
    }

    /// The bindings `skin_forward` and `skin_backward` share (shape, record, the deformed
    /// canonical Gaussians and the skinning inputs), after checking the inputs.
    fn skin_bindings<'a>(
        &'a self,
        columns: &GaussianColumns<'a>,
        inputs: &SkinInputs<'a>,
    ) -> anyhow::Result<[(u32, &'a wgpu::Buffer); 13]> {
        self.check_inputs(columns, inputs)?;
        let offsets = inputs.weight_offsets.unwrap_or(&self.placeholder);
        Ok([
            (0, &self.shape),
            (1, &self.record.buffer),
            (3, &columns.log_scale.buffer),
            (4, &columns.rotation.buffer),
            (6, &self.positions.buffer),
            (7, &self.d_rotations.buffer),
            (8, &self.d_scales.buffer),
            (9, &offsets.buffer),
            (10, &inputs.nearest.buffer),
            (11, &self.canonical_joints.buffer),
            (12, &inputs.target_joints.buffer),
            (13, &self.template_log_weights.buffer),
            (14, &inputs.vertex_offsets.buffer),
        ])
    }

    /// Records the deformation: [`ResidentSkinning::positions`] `= xyz + d_xyz`,
    /// [`ResidentSkinning::d_rotations`], [`ResidentSkinning::d_scales`] from the trunk's
    /// `heads` (`N x 10`), given exactly when the setup has heads; identity offsets without.
    pub fn record_deform(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        xyz: &GpuBuffer,
        heads: Option<&GpuBuffer>,
    ) -> anyhow::Result<()> {
        self.check("xyz", xyz, 3)?;
        let heads = match (self.flags & HAS_HEADS != 0, heads) {
            (true, Some(heads)) => {
                self.check("heads", heads, HEAD_WIDTH)?;
                heads
            }
            (false, None) => &self.placeholder,
            (true, None) => anyhow::bail!("heads: required by the setup but not given"),
            (false, Some(_)) => anyhow::bail!("heads: given but the setup has no heads"),
        };
        self.context.dispatch(
            encoder,
            &self.deform,
            &[
                (0, &self.shape),
                (1, &self.record.buffer),
                (2, &xyz.buffer),
                (5, &heads.buffer),
                (6, &self.positions.buffer),
                (7, &self.d_rotations.buffer),
                (8, &self.d_scales.buffer),
            ],
            self.workgroups()?,
        );
        Ok(())
    }

    /// Records the skinning forward into [`ResidentSkinning::means`],
    /// [`ResidentSkinning::covariances`], [`ResidentSkinning::opacities`] and
    /// [`ResidentSkinning::sh`] (after [`ResidentSkinning::record_deform`]).
    pub fn record_forward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        columns: &GaussianColumns<'_>,
        inputs: &SkinInputs<'_>,
    ) -> anyhow::Result<()> {
        let bindings = [
            self.skin_bindings(columns, inputs)?.as_slice(),
            &[
                (16, &self.means.buffer),
                (17, &self.covariances.buffer),
                (18, &self.opacities.buffer),
                (19, &self.sh.buffer),
                (20, &columns.opacity_logit.buffer),
                (21, &columns.sh.buffer),
                (31, &self.status.buffer),
            ],
        ]
        .concat();
        self.context
            .dispatch(encoder, &self.forward, &bindings, self.workgroups()?);
        Ok(())
    }

    /// Records the skinning backward from the splatting's gradients of the means
    /// (`grad_means`, `N x 3`) and covariances (`grad_covariances`, `N x 6`, off-diagonals
    /// counting both halves): the per-Gaussian gradients, [`ResidentSkinning::grad_heads`],
    /// and the reductions into [`ResidentSkinning::grad_target_joints`] and
    /// [`ResidentSkinning::grad_vertex_offsets`] (both overwritten).
    pub fn record_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        columns: &GaussianColumns<'_>,
        inputs: &SkinInputs<'_>,
        grad_means: &GpuBuffer,
        grad_covariances: &GpuBuffer,
    ) -> anyhow::Result<()> {
        let skin = self.skin_bindings(columns, inputs)?;
        self.check("grad_means", grad_means, 3)?;
        self.check("grad_covariances", grad_covariances, 6)?;
        encoder.clear_buffer(&self.grad_vertex_offsets.buffer, 0, None);
        let bindings = [
            skin.as_slice(),
            &[
                (15, &self.grad_vertex_offsets.buffer),
                (16, &grad_means.buffer),
                (17, &grad_covariances.buffer),
                (22, &self.grad_positions.buffer),
                (23, &self.grad_log_scales.buffer),
                (24, &self.grad_rotations.buffer),
                (25, &self.grad_heads.buffer),
                (26, &self.grad_weight_offsets.buffer),
                (27, &self.blend_weights.buffer),
                (28, &self.grad_blend.buffer),
                (31, &self.status.buffer),
            ],
        ]
        .concat();
        self.context
            .dispatch(encoder, &self.backward, &bindings, self.workgroups()?);
        let chunks = self.count.div_ceil(JOINT_CHUNK).max(1) as u32;
        self.context.dispatch(
            encoder,
            &self.reduce_joints,
            &[
                (0, &self.shape),
                (1, &self.record.buffer),
                (27, &self.blend_weights.buffer),
                (28, &self.grad_blend.buffer),
                (29, &self.joint_partials.buffer),
            ],
            (chunks, self.joints as u32),
        );
        self.context.dispatch(
            encoder,
            &self.finish_joints,
            &[
                (0, &self.shape),
                (1, &self.record.buffer),
                (29, &self.joint_partials.buffer),
                (30, &self.grad_target_joints.buffer),
            ],
            (12 * self.joints).div_ceil(WORKGROUP) as u32,
        );
        Ok(())
    }

    /// Records the activations' backward from the splatting's gradients of the opacities
    /// (`N`) and of the active SH (`N x k x 3`) into
    /// [`ResidentSkinning::grad_opacity_logits`] and [`ResidentSkinning::grad_sh`]
    /// (`N x 16 x 3`, zeros beyond the active degree).
    pub fn record_activations_backward(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        opacity_logit: &GpuBuffer,
        grad_opacities: &GpuBuffer,
        grad_sh: &GpuBuffer,
    ) -> anyhow::Result<()> {
        self.check("opacity_logit", opacity_logit, 1)?;
        self.check("grad_opacities", grad_opacities, 1)?;
        self.check("grad_sh", grad_sh, 3 * self.sh_coefficients)?;
        self.context.dispatch(
            encoder,
            &self.activations_backward,
            &[
                (1, &self.record.buffer),
                (18, &grad_opacities.buffer),
                (19, &grad_sh.buffer),
                (20, &opacity_logit.buffer),
                (32, &self.grad_opacity_logits.buffer),
                (33, &self.grad_sh.buffer),
            ],
            self.workgroups()?,
        );
        Ok(())
    }

    /// Clears [`ResidentSkinning::status`] (a 16-byte write; after the host read it).
    pub fn reset_status(&self) -> anyhow::Result<()> {
        self.context.write(&self.status.buffer, 0, &STATUS_CLEAR)?;
        Ok(())
    }

    /// Reads [`ResidentSkinning::status`] back (one round trip).
    pub fn download_status(&self) -> anyhow::Result<[u32; 4]> {
        let values: Vec<u32> =
            self.context
                .download(self.context.encoder(), &self.status.buffer, 4)?;
        Ok([values[0], values[1], values[2], values[3]])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::BodyRig;
    use crate::skinning::{GaussianParams, SkinningGrads, skin_backward, skin_forward};
    use glam::DVec3;
    use seqavatar_compute::backend::test_support::{
        gpu_test_context, gpu_test_context_with_dispatch_limit,
    };
    use seqavatar_compute::splat::sh_coefficient_count;
    use seqavatar_core::body::procedural::procedural_body;
    use seqavatar_core::rng::SplitMix64 as Rng;
    use seqavatar_knn::{KnnGrid, as_points};

    /// f32 rounding, back in f64: the values the device holds, for the f64 oracle.
    fn round(values: &[f64]) -> Vec<f64> {
        values.iter().map(|&v| f64::from(v as f32)).collect()
    }

    fn to_f32(values: &[f64]) -> Vec<f32> {
        values.iter().map(|&v| v as f32).collect()
    }

    /// Random Gaussians around the template with the extremes the kernels must handle.
    struct Scene {
        rig: BodyRig,
        n: usize,
        target_joints: Vec<[f64; 12]>,
        vertex_offsets: Vec<f64>,
        xyz: Vec<f64>,
        log_scale: Vec<f64>,
        rotation: Vec<f64>,
        opacity_logit: Vec<f64>,
        sh: Vec<f64>,
        heads: Vec<f64>,
        weight_offsets: Vec<f64>,
    }

    fn scene(n: usize, seed: u64) -> Scene {
        let rig = BodyRig::new(procedural_body(0.05)).unwrap();
        let mut rng = Rng::new(seed);
        let mut params = rig.model.zero_params();
        for p in params.pose.iter_mut() {
            *p = DVec3::new(rng.normal(), rng.normal(), rng.normal()) * 0.3;
        }
        for b in params.betas.iter_mut() {
            *b = 0.5 * rng.normal();
        }
        params.world_rotation = DVec3::new(0.3, -1.2, 0.4);
        params.world_translation = DVec3::new(0.2, -0.1, 1.5);
        let (pose, _) = rig.pose_with_chain(&params).unwrap();
        let v = rig.vertex_count();
        let j = rig.joint_count();
        let mut xyz = Vec::with_capacity(3 * n);
        for _ in 0..n {
            let at = rng.below(v);
            for a in 0..3 {
                xyz.push(rig.canonical_vertices[3 * at + a] + 0.02 * rng.normal());
            }
        }
        let mut log_scale: Vec<f64> = (0..3 * n).map(|_| rng.uniform(-6.0, -1.5)).collect();
        let mut rotation: Vec<f64> = (0..4 * n).map(|_| rng.normal()).collect();
        if n >= 8 {
            // Tiny and huge scales.
            log_scale[0..3].copy_from_slice(&[-30.0, -25.0, -20.0]);
            log_scale[3..6].copy_from_slice(&[4.0, 5.0, 6.5]);
            // Degenerate quaternions: zero and far below the threshold.
            rotation[8..12].copy_from_slice(&[0.0; 4]);
            rotation[12..16].copy_from_slice(&[1e-14, 0.0, -1e-14, 0.0]);
        }
        let mut heads = Vec::with_capacity(10 * n);
        for _ in 0..n {
            heads.extend((0..3).map(|_| 0.01 * rng.normal()));
            heads.extend((0..4).map(|_| 0.1 * rng.normal()));
            heads.extend((0..3).map(|_| 0.003 * rng.normal()));
        }
        if n >= 8 {
            // A rotation offset cancelling the identity bias: a degenerate product.
            heads[10 * 7 + 3..10 * 7 + 7].copy_from_slice(&[-1.0, 0.0, 0.0, 0.0]);
        }
        Scene {
            target_joints: pose.target_joints,
            vertex_offsets: round(&pose.vertex_offsets),
            xyz: round(&xyz),
            log_scale,
            rotation: round(&rotation),
            opacity_logit: round(&(0..n).map(|_| 2.0 * rng.normal()).collect::<Vec<_>>()),
            sh: round(&(0..48 * n).map(|_| rng.normal()).collect::<Vec<_>>()),
            heads: round(&heads),
            weight_offsets: round(&(0..j * n).map(|_| rng.normal()).collect::<Vec<_>>()),
            n,
            rig,
        }
    }

    /// The f64 oracle's inputs from the f32 device values: deformed positions and offsets
    /// (as `deform` and `split_heads` make them), nearest vertices of the deformed centres.
    struct Oracle {
        positions: Vec<f64>,
        d_scales: Vec<f64>,
        d_rotations: Vec<f64>,
        nearest: Vec<u32>,
        canonical_joints: Vec<[f64; 12]>,
        target_joints: Vec<[f64; 12]>,
        template_weights: Vec<f64>,
    }

    fn oracle(s: &Scene, heads: bool) -> Oracle {
        let n = s.n;
        let (mut positions, mut d_scales, mut d_rotations) = (
            s.xyz.clone(),
            vec![0.0; 3 * n],
            [1.0, 0.0, 0.0, 0.0].repeat(n),
        );
        if heads {
            for i in 0..n {
                let h = &s.heads[10 * i..10 * i + 10];
                for a in 0..3 {
                    // The device adds in f32.
                    positions[3 * i + a] = f64::from(s.xyz[3 * i + a] as f32 + h[a] as f32);
                    d_scales[3 * i + a] = h[7 + a];
                }
                d_rotations[4 * i] = f64::from(h[3] as f32 + 1.0);
                d_rotations[4 * i + 1..4 * i + 4].copy_from_slice(&h[4..7]);
            }
        }
        let grid = KnnGrid::new(&as_points(&s.rig.canonical_vertices), 4.0);
        let nearest = grid.query_all(&as_points(&positions), 1);
        // The device holds the joints and weights in f32; its log weights are rounded from
        // f64 logarithms, which the oracle keeps (the difference is far below tolerance).
        let round12 = |t: &[[f64; 12]]| -> Vec<[f64; 12]> {
            t.iter().map(|m| m.map(|x| f64::from(x as f32))).collect()
        };
        Oracle {
            positions,
            d_scales,
            d_rotations,
            nearest,
            canonical_joints: round12(&s.rig.canonical_joints),
            target_joints: round12(&s.target_joints),
            template_weights: s.rig.template_weights.clone(),
        }
    }

    /// Row by row: `|got - want| <= rel (max |want| of the row + 1e-3 max |want|) + abs`: f32
    /// against f64, where rows that cancel to nearly zero (a rotation gradient of an isotropic
    /// clamped Gaussian) keep rounding noise at the array's scale.
    fn assert_rows(name: &str, got: &[f32], want: &[f64], width: usize, rel: f64, abs: f64) {
        assert_eq!(got.len(), want.len(), "{name}: lengths");
        let global = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        for (row, (g, w)) in got.chunks(width).zip(want.chunks(width)).enumerate() {
            let scale = w.iter().fold(0.0f64, |m, v| m.max(v.abs())) + 1e-3 * global;
            for (e, (a, b)) in g.iter().zip(w).enumerate() {
                let a = f64::from(*a);
                assert!(
                    a.is_finite() && (a - b).abs() <= rel * scale + abs,
                    "{name}[{row}][{e}]: device {a}, cpu {b} (row scale {scale})"
                );
            }
        }
    }

    fn download(context: &GpuContext, buffer: &GpuBuffer, len: usize) -> Vec<f32> {
        context
            .download::<f32>(context.encoder(), &buffer.buffer, len)
            .unwrap()
    }

    struct Case {
        heads: bool,
        weight_offsets: bool,
        bounds: (f64, f64),
        atomic_add: Option<AtomicAdd>,
        dispatch_limit: Option<u32>,
        sh_degree: u32,
        gaussians: usize,
    }

    fn run_case(case: &Case) {
        // A context of its own: the traffic counts are per context and tests run in parallel.
        let context = gpu_test_context_with_dispatch_limit(case.dispatch_limit.unwrap_or(u32::MAX));
        let Some(context) = context else {
            return;
        };
        if case.atomic_add == Some(AtomicAdd::NativeFloat) && !context.has_float_atomics() {
            eprintln!("skipped: the adapter has no f32 atomics");
            return;
        }
        let s = scene(case.gaussians, 7);
        let (n, j) = (s.n, s.rig.joint_count());
        let o = oracle(&s, case.heads);
        let mut skinning = ResidentSkinning::new(
            &context,
            &SkinningSetup {
                canonical_joints: &s.rig.canonical_joints,
                template_weights: &s.rig.template_weights,
                scale_min: case.bounds.0,
                scale_max: case.bounds.1,
                heads: case.heads,
                weight_offsets: case.weight_offsets,
                atomic_add: case.atomic_add,
            },
            // Larger than the count: kernels must stop at the count.
            n + 50,
        )
        .unwrap();
        let up = |what: &str, values: &[f64]| context.upload(what, &to_f32(values)).unwrap();
        let xyz = up("xyz", &s.xyz);
        let log_scale = up("log_scale", &s.log_scale);
        let rotation = up("rotation", &s.rotation);
        let opacity_logit = up("opacity", &s.opacity_logit);
        let sh = up("sh", &s.sh);
        let heads = up("heads", &s.heads);
        let offsets = up("weight offsets", &s.weight_offsets);
        let nearest = context.upload("nearest", &o.nearest).unwrap();
        let target: Vec<f64> = s.target_joints.iter().flatten().copied().collect();
        let target_joints = up("target joints", &target);
        let vertex_offsets = up("vertex offsets", &s.vertex_offsets);
        let columns = GaussianColumns {
            xyz: &xyz,
            log_scale: &log_scale,
            rotation: &rotation,
            opacity_logit: &opacity_logit,
            sh: &sh,
        };
        let inputs = SkinInputs {
            nearest: &nearest,
            weight_offsets: case.weight_offsets.then_some(&offsets),
            target_joints: &target_joints,
            vertex_offsets: &vertex_offsets,
        };
        let mut rng = Rng::new(11);
        let d_means: Vec<f64> = round(&(0..3 * n).map(|_| rng.normal()).collect::<Vec<_>>());
        let d_covs: Vec<f64> = round(&(0..6 * n).map(|_| 100.0 * rng.normal()).collect::<Vec<_>>());
        let k = sh_coefficient_count(case.sh_degree);
        let d_opacities: Vec<f64> = round(&(0..n).map(|_| rng.normal()).collect::<Vec<_>>());
        let d_sh: Vec<f64> = round(&(0..3 * k * n).map(|_| rng.normal()).collect::<Vec<_>>());
        let grad_means = up("grad means", &d_means);
        let grad_covs = up("grad covariances", &d_covs);
        let grad_opacities = up("grad opacities", &d_opacities);
        let grad_sh = up("grad sh", &d_sh);
        let iteration = |skinning: &mut ResidentSkinning| {
            skinning.set_iteration(n, case.sh_degree).unwrap();
            let mut encoder = context.encoder();
            skinning
                .record_deform(&mut encoder, &xyz, case.heads.then_some(&heads))
                .unwrap();
            skinning
                .record_forward(&mut encoder, &columns, &inputs)
                .unwrap();
            skinning
                .record_backward(&mut encoder, &columns, &inputs, &grad_means, &grad_covs)
                .unwrap();
            skinning
                .record_activations_backward(
                    &mut encoder,
                    &opacity_logit,
                    &grad_opacities,
                    &grad_sh,
                )
                .unwrap();
            context.submit_and_wait(encoder).unwrap();
        };
        iteration(&mut skinning);
        // The steady state: one 16-byte record, nothing read back.
        let before = context.transfers();
        iteration(&mut skinning);
        let traffic = context.transfers().since(&before);
        assert_eq!(traffic.readbacks, 0, "{traffic:?}");
        assert_eq!(traffic.bytes_up, 16, "{traffic:?}");
        assert_eq!(traffic.bytes_down, 0, "{traffic:?}");

        // Deformation.
        assert_rows(
            "positions",
            &download(&context, &skinning.positions, 3 * n),
            &o.positions,
            3,
            0.0,
            1e-7,
        );
        assert_rows(
            "d_scales",
            &download(&context, &skinning.d_scales, 3 * n),
            &o.d_scales,
            3,
            0.0,
            0.0,
        );
        assert_rows(
            "d_rotations",
            &download(&context, &skinning.d_rotations, 4 * n),
            &o.d_rotations,
            4,
            0.0,
            0.0,
        );
        // Forward against the f64 oracle.
        let frame = crate::skinning::SkinningFrame {
            joint_count: j,
            canonical_joints: &o.canonical_joints,
            target_joints: &o.target_joints,
            template_weights: &o.template_weights,
            vertex_offsets: &s.vertex_offsets,
            scale_min: f64::from(case.bounds.0 as f32),
            scale_max: f64::from(case.bounds.1 as f32),
        };
        let params = GaussianParams {
            positions: &o.positions,
            log_scales: &s.log_scale,
            d_scales: &o.d_scales,
            rotations: &s.rotation,
            d_rotations: &o.d_rotations,
            weight_offsets: case.weight_offsets.then_some(s.weight_offsets.as_slice()),
            nearest: &o.nearest,
        };
        let want = skin_forward(&frame, &params);
        assert_rows(
            "means",
            &download(&context, &skinning.means, 3 * n),
            &want.positions,
            3,
            0.0,
            2e-5,
        );
        assert_rows(
            "covariances",
            &download(&context, &skinning.covariances, 6 * n),
            &want.covariances,
            6,
            2e-4,
            1e-12,
        );
        let opacities: Vec<f64> = s
            .opacity_logit
            .iter()
            .map(|l| 1.0 / (1.0 + (-l).exp()))
            .collect();
        assert_rows(
            "opacities",
            &download(&context, &skinning.opacities, n),
            &opacities,
            1,
            0.0,
            1e-6,
        );
        let active: Vec<f64> = (0..n)
            .flat_map(|i| s.sh[48 * i..48 * i + 3 * k].iter().copied())
            .collect();
        assert_rows(
            "sh",
            &download(&context, &skinning.sh, 3 * k * n),
            &active,
            3 * k,
            0.0,
            0.0,
        );
        // Backward.
        let grads: SkinningGrads = skin_backward(&frame, &params, &d_means, &d_covs);
        let rel = 2e-3;
        assert_rows(
            "grad positions",
            &download(&context, &skinning.grad_positions, 3 * n),
            &grads.positions,
            3,
            rel,
            1e-5,
        );
        assert_rows(
            "grad log scales",
            &download(&context, &skinning.grad_log_scales, 3 * n),
            &grads.log_scales,
            3,
            rel,
            1e-7,
        );
        assert_rows(
            "grad rotations",
            &download(&context, &skinning.grad_rotations, 4 * n),
            &grads.rotations,
            4,
            rel,
            1e-7,
        );
        let heads_want: Vec<f64> = (0..n)
            .flat_map(|i| {
                let mut row = grads.positions[3 * i..3 * i + 3].to_vec();
                row.extend_from_slice(&grads.d_rotations[4 * i..4 * i + 4]);
                row.extend_from_slice(&grads.d_scales[3 * i..3 * i + 3]);
                row
            })
            .collect();
        assert_rows(
            "grad heads",
            &download(&context, &skinning.grad_heads, 10 * n),
            &heads_want,
            10,
            rel,
            1e-6,
        );
        if case.weight_offsets {
            assert_rows(
                "grad weight offsets",
                &download(&context, &skinning.grad_weight_offsets, j * n),
                &grads.weight_offsets,
                j,
                rel,
                1e-6,
            );
        }
        // Reductions: relative to the largest entry of the whole array.
        let scale = |v: &[f64]| v.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let tj = &grads.target_joints;
        assert_rows(
            "grad target joints",
            &download(&context, &skinning.grad_target_joints, 12 * j),
            tj,
            12 * j,
            rel,
            0.0,
        );
        assert!(n == 0 || scale(tj) > 0.0);
        let vo = &grads.vertex_offsets;
        let got_vo = download(&context, &skinning.grad_vertex_offsets, vo.len());
        assert_rows("grad vertex offsets", &got_vo, vo, vo.len(), rel, 0.0);
        // Activations.
        let d_logit: Vec<f64> = (0..n)
            .map(|i| d_opacities[i] * opacities[i] * (1.0 - opacities[i]))
            .collect();
        assert_rows(
            "grad opacity logits",
            &download(&context, &skinning.grad_opacity_logits, n),
            &d_logit,
            1,
            0.0,
            1e-6,
        );
        let mut d_sh_stored = vec![0.0; 48 * n];
        for i in 0..n {
            d_sh_stored[48 * i..48 * i + 3 * k].copy_from_slice(&d_sh[3 * k * i..3 * k * (i + 1)]);
        }
        assert_rows(
            "grad sh",
            &download(&context, &skinning.grad_sh, 48 * n),
            &d_sh_stored,
            48,
            0.0,
            0.0,
        );
        assert_eq!(skinning.download_status().unwrap(), STATUS_CLEAR);
    }

    #[test]
    fn resident_skinning_matches_cpu_with_heads_and_offsets() {
        run_case(&Case {
            heads: true,
            weight_offsets: true,
            bounds: (1e-6, 1e3),
            atomic_add: None,
            dispatch_limit: None,
            sh_degree: 3,
            gaussians: 333,
        });
    }

    #[test]
    fn resident_skinning_matches_cpu_without_networks_compare_exchange() {
        run_case(&Case {
            heads: false,
            weight_offsets: false,
            bounds: (1e-6, 1e3),
            atomic_add: Some(AtomicAdd::CompareExchange),
            dispatch_limit: None,
            sh_degree: 0,
            gaussians: 333,
        });
    }

    #[test]
    fn resident_skinning_matches_cpu_with_the_scale_clamp_active_native_atomics() {
        run_case(&Case {
            heads: true,
            weight_offsets: false,
            bounds: (0.01, 0.03),
            atomic_add: Some(AtomicAdd::NativeFloat),
            dispatch_limit: None,
            sh_degree: 1,
            gaussians: 333,
        });
    }

    #[test]
    fn resident_skinning_matches_cpu_with_2d_dispatch() {
        run_case(&Case {
            heads: true,
            weight_offsets: true,
            bounds: (0.005, 0.1),
            atomic_add: Some(AtomicAdd::CompareExchange),
            dispatch_limit: Some(2),
            sh_degree: 2,
            gaussians: 333,
        });
    }

    /// No Gaussians and one: kernels stop at the count, reductions are zeros or one term.
    #[test]
    fn resident_skinning_handles_empty_and_single_inputs() {
        for gaussians in [0, 1] {
            run_case(&Case {
                heads: true,
                weight_offsets: true,
                bounds: (1e-6, 1e3),
                atomic_add: None,
                dispatch_limit: None,
                sh_degree: 3,
                gaussians,
            });
        }
    }

    #[test]
    fn resident_skinning_flags_non_finite_values() {
        let Some(context) = gpu_test_context() else {
            return;
        };
        let s = scene(70, 3);
        let (n, j) = (s.n, s.rig.joint_count());
        let mut skinning = ResidentSkinning::new(
            &context,
            &SkinningSetup {
                canonical_joints: &s.rig.canonical_joints,
                template_weights: &s.rig.template_weights,
                scale_min: 1e-6,
                scale_max: 1.0,
                heads: false,
                weight_offsets: false,
                atomic_add: None,
            },
            n,
        )
        .unwrap();
        let mut xyz = to_f32(&s.xyz);
        xyz[3 * 41 + 1] = f32::NAN;
        xyz[3 * 65] = f32::INFINITY;
        let xyz = context.upload("xyz", &xyz).unwrap();
        let up = |what: &str, values: &[f64]| context.upload(what, &to_f32(values)).unwrap();
        let (log_scale, rotation) = (up("ls", &s.log_scale), up("rot", &s.rotation));
        let (opacity, sh) = (up("op", &s.opacity_logit), up("sh", &s.sh));
        let nearest = context.upload("nearest", &vec![0u32; n]).unwrap();
        let target: Vec<f64> = s.target_joints.iter().flatten().copied().collect();
        let (target, offsets) = (up("tj", &target), up("vo", &s.vertex_offsets));
        let columns = GaussianColumns {
            xyz: &xyz,
            log_scale: &log_scale,
            rotation: &rotation,
            opacity_logit: &opacity,
            sh: &sh,
        };
        let inputs = SkinInputs {
            nearest: &nearest,
            weight_offsets: None,
            target_joints: &target,
            vertex_offsets: &offsets,
        };
        let grad_means = context.zeros("gm", 3 * n, 4).unwrap();
        let grad_covs = up("gc", &vec![1.0; 6 * n]);
        skinning.set_iteration(n, 0).unwrap();
        let mut encoder = context.encoder();
        skinning.record_deform(&mut encoder, &xyz, None).unwrap();
        skinning
            .record_forward(&mut encoder, &columns, &inputs)
            .unwrap();
        skinning
            .record_backward(&mut encoder, &columns, &inputs, &grad_means, &grad_covs)
            .unwrap();
        context.submit_and_wait(encoder).unwrap();
        let status = skinning.download_status().unwrap();
        assert_eq!(status[0], 2, "{status:?}");
        assert_eq!(status[1], 41, "{status:?}");
        assert_eq!(status[3], 41, "{status:?}");
        skinning.reset_status().unwrap();
        assert_eq!(skinning.download_status().unwrap(), STATUS_CLEAR);
        // Inputs that do not match the setup are errors naming the field.
        let mut encoder = context.encoder();
        let error = skinning
            .record_deform(&mut encoder, &xyz, Some(&xyz))
            .unwrap_err()
            .to_string();
        assert!(error.contains("heads"), "{error}");
        let short = context.zeros("short", 3, 4).unwrap();
        let error = skinning
            .record_forward(
                &mut encoder,
                &columns,
                &SkinInputs {
                    target_joints: &short,
                    ..inputs
                },
            )
            .unwrap_err()
            .to_string();
        assert!(
            error.contains("target_joints") && error.contains(&format!("{j} joints")),
            "{error}"
        );
        assert!(skinning.set_iteration(n + 1, 0).is_err());
    }
}
