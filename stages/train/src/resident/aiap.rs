//! The as-isometric-as-possible loss on the device (`aiap_gaussians`' maths,
//! `shaders/train_aiap.wgsl`): the exact `k` nearest canonical neighbours of every Gaussian,
//! the loss value into a device log record, its gradients into the canonical columns and the
//! deformed centres and covariances.
//!
//! Buffers (f32 unless said, `N` = the Gaussians' count, allocated for a capacity):
//! - inputs: the canonical `xyz` `N x 3`, `log_scale` `N x 3`, `rotation` `N x 4` of
//!   [`ResidentGaussians`], the deformed centres `N x 3` and covariance upper triangles
//!   `N x 6` (`xx xy xz yy yz zz`) of the skinning piece;
//! - [`ResidentAiap::neighbours`]: `N x k` u32, nearest first by (squared distance, index),
//!   the Gaussian itself first unless an identical point has a smaller index;
//! - [`ResidentAiap::gradients`]: `xyz` `N x 3`, `log_scale` `N x 3`, `rotation` `N x 4`
//!   (what Adam adds to the skinning's), `deformed_centres` `N x 3`, `deformed_covariances`
//!   `N x 6` (what the skinning backward adds to the splatting's);
//! - [`ResidentAiap::log`]: 3 f32, `[centre x centres + covariance x covariances, centres,
//!   covariances]` (the weighted value and the unweighted mean terms).
//!
//! The neighbours are exact (ties included, the same lists as `MovingKnn`): Verlet candidate
//! lists (the 32 nearest at the last full search) from which each iteration selects the `k`
//! nearest at the current positions, rebuilt by a full tiled brute-force search when a
//! kernel finds that some Gaussian moved too far for them to be sure (the argument is in
//! `shaders/train_aiap_knn.wgsl`); the decision stays on the device (indirect dispatches).

use std::borrow::Cow;
use std::sync::Arc;

use anyhow::{Context, ensure};
use seqavatar_compute::backend::shaders::{AtomicAdd, with_atomic_add};
use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource, Workgroups};

use super::state::ResidentGaussians;
use crate::densify::names;
use crate::losses::AiapWeights;

const AIAP_WGSL: &str = include_str!("../../../../shaders/train_aiap.wgsl");
const KNN_WGSL: &str = include_str!("../../../../shaders/train_aiap_knn.wgsl");

/// The largest `k` the neighbour kernels keep in registers.
pub const MAX_NEIGHBOURS: usize = 16;

/// Candidates per Gaussian in the Verlet lists (`MAX_CANDIDATES` of train_aiap_knn.wgsl):
/// the `M = min(32, N)` nearest at the last full search.
pub const CANDIDATES: usize = 32;

/// The AIAP gradients, in the layouts of the module doc.
#[derive(Debug)]
pub struct AiapGradients {
    pub xyz: GpuBuffer,
    pub log_scale: GpuBuffer,
    pub rotation: GpuBuffer,
    pub deformed_centres: GpuBuffer,
    pub deformed_covariances: GpuBuffer,
}

/// Buffers sized for a capacity of Gaussians.
#[derive(Debug)]
struct Workspace {
    capacity: usize,
    neighbours: GpuBuffer,
    canonical_covariances: GpuBuffer,
    partials: GpuBuffer,
    /// Verlet lists: anchors `N x 3`, candidates `N x CANDIDATES` u32, slack `N`.
    anchors: GpuBuffer,
    candidates: GpuBuffer,
    slack: GpuBuffer,
    /// `[valid, smallest slack (f32 bits), rebuilds, calls]` u32.
    lists: GpuBuffer,
    /// The grids of the rebuild and its finalisation, written by the check kernel.
    grids: wgpu::Buffer,
    /// The atomic gradient scratch: canonical centres 3C | deformed centres 3C | canonical
    /// covariances 6C | deformed covariances 6C.
    scratch: GpuBuffer,
    gradients: AiapGradients,
}

/// The AIAP kernels, the workspace and the loss record.
#[derive(Debug)]
pub struct ResidentAiap {
    context: Arc<GpuContext>,
    weights: AiapWeights,
    check: Arc<Kernel>,
    rebuild: Arc<Kernel>,
    finalize: Arc<Kernel>,
    select: Arc<Kernel>,
    covariances: Arc<Kernel>,
    pairs: Arc<Kernel>,
    reduce_loss: Arc<Kernel>,
    finish: Arc<Kernel>,
    /// `params` of the shaders (three `vec4<u32>`), written when the count changes.
    params: wgpu::Buffer,
    written_for: Option<(usize, usize)>,
    log: GpuBuffer,
    workspace: Option<Workspace>,
}

fn kernel(
    context: &GpuContext,
    name: &'static str,
    wgsl: &str,
    entry_point: &'static str,
) -> anyhow::Result<Arc<Kernel>> {
    Ok(context.kernel(&KernelSource {
        name,
        wgsl: Cow::Owned(wgsl.to_owned()),
        entry_point,
    })?)
}

impl ResidentAiap {
    /// Compiles the kernels (with the adapter's f32 atomic add, or the compare-exchange one
    /// when it has none) for the given weights and neighbourhood.
    pub fn new(context: &Arc<GpuContext>, weights: AiapWeights) -> anyhow::Result<Self> {
        let mode = if context.has_float_atomics() {
            AtomicAdd::NativeFloat
        } else {
            AtomicAdd::CompareExchange
        };
        Self::with_atomic_add(context, weights, mode)
    }

    /// [`ResidentAiap::new`] with a chosen atomic-add variant (tests run both).
    pub fn with_atomic_add(
        context: &Arc<GpuContext>,
        weights: AiapWeights,
        mode: AtomicAdd,
    ) -> anyhow::Result<Self> {
        ensure!(
            weights.neighbours <= MAX_NEIGHBOURS,
            "aiap_neighbours = {} is above the device search's {MAX_NEIGHBOURS}",
            weights.neighbours
        );
        let wgsl = with_atomic_add("train_aiap.wgsl", AIAP_WGSL, mode)?;
        let pairs_name = match mode {
            AtomicAdd::NativeFloat => "train_aiap_pairs_float",
            AtomicAdd::CompareExchange => "train_aiap_pairs_cas",
        };
        let params = context.device().create_buffer(&wgpu::BufferDescriptor {
            label: Some("aiap params"),
            size: 48,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        Ok(ResidentAiap {
            context: context.clone(),
            weights,
            check: kernel(context, "train_aiap_knn_check", KNN_WGSL, "check")?,
            rebuild: kernel(context, "train_aiap_knn_rebuild", KNN_WGSL, "rebuild")?,
            finalize: kernel(context, "train_aiap_knn_finalize", KNN_WGSL, "finalize")?,
            select: kernel(context, "train_aiap_knn_select", KNN_WGSL, "select_nearest")?,
            covariances: kernel(context, "train_aiap_covariances", AIAP_WGSL, "covariances")?,
            pairs: kernel(context, pairs_name, &wgsl, "pairs")?,
            reduce_loss: kernel(context, "train_aiap_reduce_loss", AIAP_WGSL, "reduce_loss")?,
            finish: kernel(context, "train_aiap_finish", AIAP_WGSL, "finish")?,
            params,
            written_for: None,
            log: context.zeros("aiap log", 3, 4)?,
            workspace: None,
        })
    }

    /// Whether the loss is on for `n` Gaussians (`aiap_gaussians` returns `None` otherwise:
    /// both weights 0, or no pair).
    pub fn active(&self, n: usize) -> bool {
        (self.weights.centre > 0.0 || self.weights.covariance > 0.0) && n > 1
    }

    /// Neighbours per Gaussian for `n` Gaussians (itself included).
    pub fn k(&self, n: usize) -> usize {
        self.weights.neighbours.min(n)
    }

    fn ensure_workspace(&mut self, n: usize) -> anyhow::Result<()> {
        if self.workspace.as_ref().is_some_and(|w| w.capacity >= n) {
            return Ok(());
        }
        let capacity = (n + n / 2).max(16);
        let zeros = |what: &str, len: usize| {
            self.context
                .zeros(what, len, 4)
                .with_context(|| format!("allocating the AIAP workspace's `{what}`"))
        };
        self.workspace = Some(Workspace {
            capacity,
            neighbours: zeros("aiap neighbours", capacity * MAX_NEIGHBOURS)?,
            canonical_covariances: zeros("aiap canonical covariances", 6 * capacity)?,
            partials: zeros("aiap partial sums", 2 * capacity)?,
            anchors: zeros("aiap knn anchors", 3 * capacity)?,
            candidates: zeros("aiap knn candidates", CANDIDATES * capacity)?,
            slack: zeros("aiap knn slack", capacity)?,
            lists: zeros("aiap knn lists", 4)?,
            grids: self.context.indirect_args("aiap knn grids", 6),
            scratch: zeros("aiap gradient scratch", 18 * capacity)?,
            gradients: AiapGradients {
                xyz: zeros("aiap d xyz", 3 * capacity)?,
                log_scale: zeros("aiap d log_scale", 3 * capacity)?,
                rotation: zeros("aiap d rotation", 4 * capacity)?,
                deformed_centres: zeros("aiap d deformed centres", 3 * capacity)?,
                deformed_covariances: zeros("aiap d deformed covariances", 6 * capacity)?,
            },
        });
        self.written_for = None;
        Ok(())
    }

    /// Records one iteration's AIAP: neighbours, loss and gradients, for the Gaussians of
    /// `gaussians` and their deformation (`deformed_centres` `N x 3`,
    /// `deformed_covariances` `N x 6`). When the loss is off ([`ResidentAiap::active`]) it
    /// records zero gradients and a zero log. Writes its parameters (32 bytes) only when the
    /// count changed; allocates only when the count exceeds the workspace's capacity.
    ///
    /// Cost: linear in `N` (the check, `N x 32` candidate distances, `N (k - 1)` pairs) while
    /// the Verlet lists hold; a rebuild compares every pair of Gaussians (`N^2` distances,
    /// tiled through workgroup memory).
    pub fn record(
        &mut self,
        encoder: &mut wgpu::CommandEncoder,
        gaussians: &ResidentGaussians,
        deformed_centres: &GpuBuffer,
        deformed_covariances: &GpuBuffer,
    ) -> anyhow::Result<()> {
        let n = gaussians.len();
        ensure!(
            deformed_centres.len >= 3 * n && deformed_covariances.len >= 6 * n,
            "AIAP: the deformed centres ({}) and covariances ({}) must hold {n} Gaussians",
            deformed_centres.len,
            deformed_covariances.len
        );
        self.ensure_workspace(n)?;
        let k = self.k(n);
        self.write_params(n, k)?;
        let workspace = self.workspace.as_ref().expect("allocated above");
        let g = &workspace.gradients;
        for buffer in [
            &workspace.scratch,
            &g.xyz,
            &g.log_scale,
            &g.rotation,
            &g.deformed_centres,
            &g.deformed_covariances,
            &self.log,
        ] {
            encoder.clear_buffer(&buffer.buffer, 0, None);
        }
        if !self.active(n) {
            return Ok(());
        }
        let groups = u32::try_from(n.div_ceil(256)).context("AIAP: Gaussian count")?;
        let xyz = &gaussians.column(names::POSITION)?.values.buffer;
        let log_scale = &gaussians.column(names::LOG_SCALE)?.values.buffer;
        let rotation = &gaussians.column(names::ROTATION)?.values.buffer;
        self.record_neighbours(encoder, xyz, groups);
        let ctx = &self.context;
        ctx.dispatch(
            encoder,
            &self.covariances,
            &[
                (0, &self.params),
                (2, log_scale),
                (3, rotation),
                (7, &workspace.canonical_covariances.buffer),
            ],
            groups,
        );
        ctx.dispatch(
            encoder,
            &self.pairs,
            &[
                (0, &self.params),
                (1, xyz),
                (4, &deformed_centres.buffer),
                (5, &deformed_covariances.buffer),
                (6, &workspace.neighbours.buffer),
                (7, &workspace.canonical_covariances.buffer),
                (8, &workspace.partials.buffer),
                (15, &workspace.scratch.buffer),
            ],
            groups,
        );
        ctx.dispatch(
            encoder,
            &self.reduce_loss,
            &[
                (0, &self.params),
                (8, &workspace.partials.buffer),
                (9, &self.log.buffer),
            ],
            (1, 1),
        );
        ctx.dispatch(
            encoder,
            &self.finish,
            &[
                (0, &self.params),
                (2, log_scale),
                (3, rotation),
                (10, &workspace.scratch.buffer),
                (11, &g.xyz.buffer),
                (12, &g.log_scale.buffer),
                (13, &g.rotation.buffer),
            ],
            groups,
        );
        // The deformed gradients are regions of the scratch.
        let c = workspace.capacity as u64;
        encoder.copy_buffer_to_buffer(
            &workspace.scratch.buffer,
            4 * 3 * c,
            &g.deformed_centres.buffer,
            0,
            4 * 3 * n as u64,
        );
        encoder.copy_buffer_to_buffer(
            &workspace.scratch.buffer,
            4 * 12 * c,
            &g.deformed_covariances.buffer,
            0,
            4 * 6 * n as u64,
        );
        Ok(())
    }

    /// Writes the parameters (32 bytes) when the count or `k` changed; lists of another count
    /// are invalidated (a grown one's anchors are zeros).
    fn write_params(&mut self, n: usize, k: usize) -> anyhow::Result<()> {
        if self.written_for == Some((n, k)) {
            return Ok(());
        }
        let pairs = (n * k.saturating_sub(1)).max(1) as f64;
        let float = |v: f64| (v as f32).to_bits();
        let words: [u32; 12] = [
            u32::try_from(n).context("AIAP: Gaussian count")?,
            k as u32,
            self.workspace.as_ref().map_or(0, |w| w.capacity) as u32,
            self.context.dispatch_limit(),
            float(self.weights.centre / pairs),
            float(self.weights.covariance / pairs),
            float(self.weights.centre),
            float(self.weights.covariance),
            n.min(CANDIDATES) as u32,
            0,
            0,
            0,
        ];
        self.context.write(&self.params, 0, &words)?;
        // Lists of another count are not valid (a grown one's anchors are zeros).
        let lists = &self.workspace.as_ref().expect("allocated above").lists;
        self.context.write(&lists.buffer, 0, &[0_u32])?;
        self.written_for = Some((n, k));
        Ok(())
    }

    /// Records the neighbour search: the Verlet check, the rebuild when it is due (indirect
    /// dispatches sized by the check), and the `k` nearest from the candidate lists.
    fn record_neighbours(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        xyz: &wgpu::Buffer,
        groups: u32,
    ) {
        let workspace = self
            .workspace
            .as_ref()
            .expect("allocated by ensure_workspace");
        let ctx = &self.context;
        ctx.dispatch(
            encoder,
            &self.check,
            &[
                (0, &self.params),
                (1, xyz),
                (2, &workspace.anchors.buffer),
                (5, &workspace.lists.buffer),
                (6, &workspace.grids),
            ],
            (1, 1),
        );
        ctx.dispatch(
            encoder,
            &self.rebuild,
            &[
                (0, &self.params),
                (1, xyz),
                (2, &workspace.anchors.buffer),
                (3, &workspace.candidates.buffer),
                (4, &workspace.slack.buffer),
            ],
            Workgroups::Indirect(workspace.grids.clone(), 0),
        );
        ctx.dispatch(
            encoder,
            &self.finalize,
            &[
                (0, &self.params),
                (4, &workspace.slack.buffer),
                (5, &workspace.lists.buffer),
            ],
            Workgroups::Indirect(workspace.grids.clone(), 12),
        );
        ctx.dispatch(
            encoder,
            &self.select,
            &[
                (0, &self.params),
                (1, xyz),
                (3, &workspace.candidates.buffer),
                (7, &workspace.neighbours.buffer),
            ],
            groups,
        );
    }

    /// The gradients of the last recorded iteration (allocated by the first
    /// [`ResidentAiap::record`]).
    pub fn gradients(&self) -> Option<&AiapGradients> {
        self.workspace.as_ref().map(|w| &w.gradients)
    }

    /// The neighbour lists, `N x k` u32 with `k` = [`ResidentAiap::k`].
    pub fn neighbours(&self) -> Option<&GpuBuffer> {
        self.workspace.as_ref().map(|w| &w.neighbours)
    }

    /// The loss record, `[weighted value, centres, covariances]`.
    pub fn log(&self) -> &GpuBuffer {
        &self.log
    }

    /// Reads the loss record back (tests, logging).
    pub fn download_log(&self) -> anyhow::Result<[f32; 3]> {
        let values = self
            .context
            .download::<f32>(self.context.encoder(), &self.log.buffer, 3)?;
        Ok([values[0], values[1], values[2]])
    }

    /// Full neighbour searches and calls so far, `(rebuilds, calls)` (one read-back; the
    /// `cpu` twin is `Trainer::aiap_neighbour_searches`).
    pub fn download_searches(&self) -> anyhow::Result<(u64, u64)> {
        let Some(workspace) = &self.workspace else {
            return Ok((0, 0));
        };
        let words =
            self.context
                .download::<u32>(self.context.encoder(), &workspace.lists.buffer, 4)?;
        Ok((u64::from(words[2]), u64::from(words[3])))
    }

    /// Reads the neighbour lists of `n` Gaussians back (tests).
    pub fn download_neighbours(&self, n: usize) -> anyhow::Result<Vec<u32>> {
        let buffer = self.neighbours().context("AIAP: nothing recorded yet")?;
        Ok(self
            .context
            .download::<u32>(self.context.encoder(), &buffer.buffer, n * self.k(n))?)
    }
}
