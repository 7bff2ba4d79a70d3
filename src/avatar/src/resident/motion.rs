//! Motion inputs on the device (`shaders/avatar_knn.wgsl`): the sequence's motion arrays and
//! the canonical template uploaded once; per iteration the frame's skeleton-motion window,
//! the `tau` nearest template vertices of each canonical centre with the velocity gather
//! ([`crate::device::knn_velocity`]), and the nearest template vertex of each deformed centre.
//!
//! Order of calls in an iteration: [`ResidentMotion::set_iteration`] (host check of the window
//! rule and one 16-byte write), then, recorded into the step's encoder,
//! [`ResidentMotion::record_skeleton_window`], [`ResidentMotion::record_canonical_knn`] and
//! [`ResidentMotion::record_velocity`] (before the non-rigid network), and after the heads
//! are applied [`ResidentMotion::record_nearest`] (before the skinning).
//!
//! The nearest-vertex searches are a tiled brute force over the template vertices in f32:
//! `N x V` squared distances per search (50k Gaussians x 6890 vertices is 3.4e8 distance
//! evaluations and as many compares, twice per iteration: the canonical `tau` search and the
//! deformed nearest one). Their order is that of [`KnnGrid::query_all`] (squared distance,
//! then index) on the f32 values, so the result is the cpu one except where two candidates'
//! distances differ by less than f32 rounding (about 1e-7 relative): exact ties (duplicate or
//! symmetric vertices) resolve by index as on the cpu.

use std::borrow::Cow;
use std::sync::Arc;

use seqavatar_compute::backend::{GpuBuffer, GpuContext, Kernel, KernelSource};
use seqavatar_knn::{KnnGrid, as_points};
use seqavatar_schema::motion::MotionTrack;

const KNN_WGSL: &str = include_str!("../../../../shaders/avatar_knn.wgsl");

/// Threads per workgroup of every kernel of `avatar_knn.wgsl`.
const WORKGROUP: usize = 64;
/// Largest `k` of one search (the config's `MAX_TAU`).
pub const MAX_K: usize = 64;

fn kernel(
    context: &GpuContext,
    name: &'static str,
    entry: &'static str,
) -> anyhow::Result<Arc<Kernel>> {
    Ok(context.kernel(&KernelSource {
        name,
        wgsl: Cow::Borrowed(KNN_WGSL),
        entry_point: entry,
    })?)
}

/// What a resident motion input is made of, fixed for a training run.
pub struct MotionSetup<'a> {
    /// The motion entry's arrays; `None` for a motion context without history inputs (then
    /// only the nearest-vertex search runs, on any frame).
    pub track: Option<&'a MotionTrack>,
    /// Raw temporal scales the networks use, largest first (as [`crate::avatar::gather_frame_inputs`]).
    pub scales: &'a [u32],
    /// Window length `L`.
    pub length: usize,
    /// Canonical template vertices `V x 3` (the rig's `canonical_vertices`).
    pub template: &'a [f64],
    /// Nearest template vertices per Gaussian of the velocity gather (`tau`); 0 when the
    /// motion context has no velocity (no canonical search, no velocity blocks).
    pub tau: usize,
    /// Whether the motion context uses skeleton motion (the window is gathered).
    pub skeleton_motion: bool,
}

/// The sequence's motion arrays and the template on the device, with the per-iteration
/// outputs of the motion inputs sized for a capacity of Gaussians.
pub struct ResidentMotion {
    context: Arc<GpuContext>,
    num_frames: usize,
    length: usize,
    /// Steps of the scale slots in use, and the reach check's data.
    scale_steps: Vec<usize>,
    starts_recording: bool,
    past_frames: usize,
    joints: usize,
    vertices: usize,
    tau: usize,
    capacity: usize,
    /// Gaussians of this iteration ([`ResidentMotion::set_iteration`]).
    count: usize,
    record: GpuBuffer,
    steps: GpuBuffer,
    skeleton_motion: Option<GpuBuffer>,
    vertex_velocity: Option<GpuBuffer>,
    template: GpuBuffer,
    /// The skeleton-motion window `L x S x J x 3` of the frame of the last
    /// [`ResidentMotion::set_iteration`] (empty without skeleton motion).
    pub window: GpuBuffer,
    /// `N x tau` nearest template vertices (u32) of the canonical centres, nearest first.
    pub neighbours: GpuBuffer,
    /// `L` velocity blocks, each `N x (tau S 3)` (`[neighbour][scale][xyz]` per Gaussian):
    /// the non-rigid network's per-window-element velocity inputs.
    pub velocity: Vec<GpuBuffer>,
    /// `N` nearest template vertex (u32) of each deformed centre.
    pub nearest: GpuBuffer,
    skeleton_shape: wgpu::Buffer,
    tau_shape: wgpu::Buffer,
    nearest_shape: wgpu::Buffer,
    velocity_shapes: Vec<wgpu::Buffer>,
    knn: Arc<Kernel>,
    gather_skeleton: Arc<Kernel>,
    gather_velocity: Arc<Kernel>,
}

impl ResidentMotion {
    /// Uploads the motion arrays of the scale slots in use (`F x S x J x 3` and, with `tau`,
    /// `F x S x V x 3`) and the template once, and allocates the outputs for `capacity`
    /// Gaussians. Errors name the setting (unknown scale, `tau` beyond [`MAX_K`] or the finite
    /// template vertices, a buffer beyond the adapter's limit).
    pub fn new(
        context: &Arc<GpuContext>,
        setup: &MotionSetup<'_>,
        capacity: usize,
    ) -> anyhow::Result<Self> {
        // Without a track (no history inputs) only the template is used, on any frame.
        let (slots, s_all, j, v, f, starts_recording, past_frames) = match setup.track {
            Some(track) => (
                track.slots(setup.scales)?,
                track.scales.len(),
                track.num_joints,
                track.num_vertices,
                track.num_frames,
                track.axis.starts_recording,
                track.axis.past_frames,
            ),
            None => {
                anyhow::ensure!(
                    !setup.skeleton_motion && setup.tau == 0,
                    "a motion context with skeleton motion or velocities needs a motion track"
                );
                (
                    Vec::new(),
                    0,
                    0,
                    setup.template.len() / 3,
                    usize::MAX,
                    true,
                    0,
                )
            }
        };
        let s = slots.len();
        anyhow::ensure!(
            setup.template.len() == 3 * v,
            "template: {} values for the motion track's {v} vertices",
            setup.template.len()
        );
        anyhow::ensure!(
            setup.tau <= MAX_K,
            "tau = {} exceeds the device search's {MAX_K}",
            setup.tau
        );
        let grid = KnnGrid::new(&as_points(setup.template), 4.0);
        anyhow::ensure!(
            setup.tau <= grid.reference_count() && grid.reference_count() > 0,
            "tau = {} exceeds the {} finite template vertices",
            setup.tau,
            grid.reference_count()
        );
        // What the cpu search returns for a non-finite query: its first reference point.
        let fallback = grid.query_all(&[[f64::NAN; 3]], 1)[0];
        // The slots in use, in the order used.
        let repack = |data: &[f32], per: usize| -> Vec<f32> {
            let mut out = Vec::with_capacity(f * s * per);
            for frame in 0..f {
                for &slot in &slots {
                    let at = (frame * s_all + slot) * per;
                    out.extend_from_slice(&data[at..at + per]);
                }
            }
            out
        };
        let skeleton_motion = match setup.track {
            Some(track) if setup.skeleton_motion => {
                Some(context.upload("skeleton motion", &repack(&track.skeleton_motion, 3 * j))?)
            }
            _ => None,
        };
        let vertex_velocity = match setup.track {
            Some(track) if setup.tau > 0 => {
                Some(context.upload("vertex velocity", &repack(&track.vertex_velocity, 3 * v))?)
            }
            _ => None,
        };
        let template: Vec<f32> = setup.template.iter().map(|&x| x as f32).collect();
        let scale_steps: Vec<usize> = match setup.track {
            Some(track) => slots.iter().map(|&slot| track.scale_steps[slot]).collect(),
            None => Vec::new(),
        };
        let steps: Vec<u32> = scale_steps.iter().map(|&k| k as u32).collect();
        // The shape words of `avatar_knn.wgsl`: length, scales, joints, vertices, k, element,
        // fallback, padding.
        let shape = |k: usize, element: usize| {
            let words = [setup.length, s, j, v, k, element].map(|x| x as u32);
            context.uniform(
                "avatar motion shape",
                &[
                    words[0], words[1], words[2], words[3], words[4], words[5], fallback, 0,
                ],
            )
        };
        let mut motion = Self {
            num_frames: f,
            length: setup.length,
            starts_recording,
            past_frames,
            joints: j,
            vertices: v,
            tau: setup.tau,
            capacity: 0,
            count: 0,
            record: context.zeros("avatar motion record", 4, 4)?,
            steps: context.upload("avatar motion steps", &steps)?,
            skeleton_motion,
            vertex_velocity,
            template: context.upload("template vertices", &template)?,
            window: context.zeros(
                "skeleton motion window",
                if setup.skeleton_motion {
                    setup.length * s * j * 3
                } else {
                    0
                },
                4,
            )?,
            neighbours: context.zeros("canonical neighbours", 0, 4)?,
            velocity: Vec::new(),
            nearest: context.zeros("nearest template vertex", 0, 4)?,
            skeleton_shape: shape(0, 0),
            tau_shape: shape(setup.tau, 0),
            nearest_shape: shape(1, 0),
            velocity_shapes: (0..setup.length).map(|l| shape(setup.tau, l)).collect(),
            knn: kernel(context, "avatar_knn", "knn")?,
            gather_skeleton: kernel(context, "avatar_gather_skeleton", "gather_skeleton")?,
            gather_velocity: kernel(context, "avatar_gather_velocity", "gather_velocity")?,
            scale_steps,
            context: context.clone(),
        };
        motion.reserve(capacity)?;
        Ok(motion)
    }

    /// Grows the per-Gaussian outputs to hold `capacity` Gaussians (no-op when they do);
    /// their contents are lost when they grow.
    pub fn reserve(&mut self, capacity: usize) -> anyhow::Result<()> {
        if capacity <= self.capacity && self.capacity > 0 {
            return Ok(());
        }
        let context = &self.context;
        let s = self.scale_steps.len();
        self.neighbours = context.zeros("canonical neighbours", capacity * self.tau, 4)?;
        self.velocity = if self.tau > 0 {
            (0..self.length)
                .map(|_| context.zeros("velocity block", capacity * self.tau * s * 3, 4))
                .collect::<Result<_, _>>()?
        } else {
            Vec::new()
        };
        self.nearest = context.zeros("nearest template vertex", capacity, 4)?;
        self.capacity = capacity;
        Ok(())
    }

    /// Gaussians the outputs hold.
    pub fn capacity(&self) -> usize {
        self.capacity
    }

    /// Joints of the skeleton-motion window (`J`).
    pub fn joints(&self) -> usize {
        self.joints
    }

    /// Template vertices (`V`).
    pub fn vertices(&self) -> usize {
        self.vertices
    }

    /// Writes this iteration's record (frame index, Gaussian count: 16 bytes) after the
    /// host-side checks of [`MotionTrack::gather`]: the frame exists, the count fits the
    /// capacity, and a window reaching before position 0 clamps only when position 0 starts
    /// the recording.
    pub fn set_iteration(&mut self, frame: usize, gaussians: usize) -> anyhow::Result<()> {
        anyhow::ensure!(
            frame < self.num_frames,
            "frame {frame} is outside the motion track ({} frames)",
            self.num_frames
        );
        anyhow::ensure!(
            gaussians <= self.capacity,
            "{gaussians} Gaussians exceed the motion inputs' capacity {} (reserve first)",
            self.capacity
        );
        let largest = self.scale_steps.iter().copied().max().unwrap_or(0);
        let reach = self.length.saturating_mul(largest);
        if reach > frame && !self.starts_recording {
            anyhow::bail!(
                "frame {frame}: the motion window reaches {reach} frames back (sequence length \
                 {} x largest scale step {largest}), before the first frame of the frame axis, \
                 and the recording starts earlier (ingest kept past_frames = {})",
                self.length,
                self.past_frames
            );
        }
        self.context.write(
            &self.record.buffer,
            0,
            &[frame as u32, gaussians as u32, 0, 0],
        )?;
        self.count = gaussians;
        Ok(())
    }

    fn workgroups(&self, threads: usize) -> anyhow::Result<u32> {
        u32::try_from(threads.div_ceil(WORKGROUP))
            .map_err(|_| anyhow::anyhow!("{threads} threads exceed one dispatch"))
    }

    /// Records the gather of the skeleton-motion window into [`ResidentMotion::window`]
    /// (nothing without skeleton motion).
    pub fn record_skeleton_window(&self, encoder: &mut wgpu::CommandEncoder) -> anyhow::Result<()> {
        let Some(skeleton) = &self.skeleton_motion else {
            return Ok(());
        };
        let groups = self.workgroups(self.window.len)?;
        self.context.dispatch(
            encoder,
            &self.gather_skeleton,
            &[
                (0, &self.skeleton_shape),
                (1, &self.record.buffer),
                (2, &self.steps.buffer),
                (3, &skeleton.buffer),
                (8, &self.window.buffer),
            ],
            groups,
        );
        Ok(())
    }

    /// Records the nearest template vertices of `queries` (`N x 3`, checked and named
    /// `what` in errors) into `out`, as many per query as `shape` says.
    fn record_knn(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        what: &str,
        shape: &wgpu::Buffer,
        queries: &GpuBuffer,
        out: &GpuBuffer,
    ) -> anyhow::Result<()> {
        anyhow::ensure!(
            queries.len >= 3 * self.count,
            "{what}: {} values, {} Gaussians need {}",
            queries.len,
            self.count,
            3 * self.count
        );
        let groups = self.workgroups(self.count)?;
        self.context.dispatch(
            encoder,
            &self.knn,
            &[
                (0, shape),
                (1, &self.record.buffer),
                (5, &self.template.buffer),
                (6, &queries.buffer),
                (7, &out.buffer),
            ],
            groups,
        );
        Ok(())
    }

    /// Records the `tau` nearest template vertices of the canonical centres `xyz` (`N x 3`)
    /// into [`ResidentMotion::neighbours`] (nothing when `tau` is 0).
    pub fn record_canonical_knn(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        xyz: &GpuBuffer,
    ) -> anyhow::Result<()> {
        if self.tau == 0 {
            return Ok(());
        }
        self.record_knn(encoder, "xyz", &self.tau_shape, xyz, &self.neighbours)
    }

    /// Records the velocity gather into the `L` blocks of [`ResidentMotion::velocity`] from
    /// [`ResidentMotion::neighbours`] (after [`ResidentMotion::record_canonical_knn`]).
    pub fn record_velocity(&self, encoder: &mut wgpu::CommandEncoder) -> anyhow::Result<()> {
        let Some(velocity) = &self.vertex_velocity else {
            return Ok(());
        };
        let groups = self.workgroups(self.count * self.tau * self.scale_steps.len() * 3)?;
        for (block, shape) in self.velocity.iter().zip(&self.velocity_shapes) {
            self.context.dispatch(
                encoder,
                &self.gather_velocity,
                &[
                    (0, shape),
                    (1, &self.record.buffer),
                    (2, &self.steps.buffer),
                    (4, &velocity.buffer),
                    (7, &self.neighbours.buffer),
                    (8, &block.buffer),
                ],
                groups,
            );
        }
        Ok(())
    }

    /// Records the nearest template vertex of each deformed centre (`positions`, `N x 3`)
    /// into [`ResidentMotion::nearest`].
    pub fn record_nearest(
        &self,
        encoder: &mut wgpu::CommandEncoder,
        positions: &GpuBuffer,
    ) -> anyhow::Result<()> {
        self.record_knn(
            encoder,
            "positions",
            &self.nearest_shape,
            positions,
            &self.nearest,
        )
    }

    /// Reads the window, neighbours, velocity blocks and nearest vertices back (tests and
    /// diagnostics; one round trip): the first `gaussians` rows of each.
    pub fn download(&self, gaussians: usize) -> anyhow::Result<MotionOutputs> {
        let context = &self.context;
        let s = self.scale_steps.len();
        let encoder = context.encoder();
        let mut sources: Vec<(&wgpu::Buffer, usize)> = vec![(&self.window.buffer, self.window.len)];
        for block in &self.velocity {
            sources.push((&block.buffer, gaussians * self.tau * s * 3));
        }
        sources.push((&self.neighbours.buffer, gaussians * self.tau));
        sources.push((&self.nearest.buffer, gaussians));
        let mut all = context.download_all::<u32>(encoder, &sources)?;
        let nearest = all.pop().unwrap_or_default();
        let neighbours = all.pop().unwrap_or_default();
        let floats =
            |bits: Vec<u32>| -> Vec<f32> { bits.into_iter().map(f32::from_bits).collect() };
        let mut all = all.into_iter();
        let window = floats(all.next().unwrap_or_default());
        Ok(MotionOutputs {
            window,
            velocity: all.map(floats).collect(),
            neighbours,
            nearest,
        })
    }
}

/// The outputs of [`ResidentMotion`] on the host ([`ResidentMotion::download`]).
#[derive(Clone, Debug, PartialEq)]
pub struct MotionOutputs {
    /// `L x S x J x 3`.
    pub window: Vec<f32>,
    /// `L` blocks of `N x (tau S 3)`.
    pub velocity: Vec<Vec<f32>>,
    /// `N x tau`.
    pub neighbours: Vec<u32>,
    /// `N`.
    pub nearest: Vec<u32>,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::avatar::gather_frame_inputs;
    use crate::config::{AvatarConfig, MotionContext};
    use crate::device::knn_velocity;
    use crate::rig::BodyRig;
    use seqavatar_compute::backend::test_support::{
        gpu_test_context, gpu_test_context_alone, gpu_test_context_with_dispatch_limit,
    };
    use seqavatar_core::body::procedural::procedural_body;
    use seqavatar_core::rng::SplitMix64 as Rng;
    use seqavatar_schema::motion::FrameAxis;

    /// f32 rounding, back in f64: the values the device holds.
    fn round(values: &[f64]) -> Vec<f64> {
        values.iter().map(|&v| f64::from(v as f32)).collect()
    }

    /// A motion track of random values: `frames` frames, raw scales 4, 2, 1 (steps 4, 2, 1).
    fn track(frames: usize, joints: usize, vertices: usize, seed: u64) -> MotionTrack {
        let mut rng = Rng::new(seed);
        let s = 3;
        MotionTrack {
            num_frames: frames,
            num_joints: joints,
            garment_rows: 0,
            num_vertices: vertices,
            scales: vec![4, 2, 1],
            scale_steps: vec![4, 2, 1],
            skeleton_motion: (0..frames * s * joints * 3)
                .map(|_| rng.normal() as f32)
                .collect(),
            vertex_velocity: (0..frames * s * vertices * 3)
                .map(|_| rng.normal() as f32)
                .collect(),
            axis: FrameAxis::FROM_START,
        }
    }

    fn upload_points(context: &GpuContext, points: &[f64]) -> GpuBuffer {
        let values: Vec<f32> = points.iter().map(|&v| v as f32).collect();
        context.upload("queries", &values).unwrap()
    }

    /// Window, canonical search, velocity gather and nearest search against
    /// `gather_frame_inputs`, `KnnGrid::query_all` and `knn_velocity` on the procedural body,
    /// every frame (windows clamped at the recording's start included); steady-state calls
    /// upload one 16-byte record and read nothing back.
    fn motion_matches_cpu(context: Arc<GpuContext>) {
        let rig = BodyRig::new(procedural_body(0.05)).unwrap();
        let (j, v) = (rig.joint_count(), rig.vertex_count());
        let track = track(9, j, v, 3);
        let config = AvatarConfig {
            motion_context: MotionContext::Multiscale,
            sequence_length: 3,
            tau: 5,
            ..AvatarConfig::for_tests()
        };
        let scales = [4, 1];
        let template = round(&rig.canonical_vertices);
        let mut motion = ResidentMotion::new(
            &context,
            &MotionSetup {
                track: Some(&track),
                scales: &scales,
                length: config.sequence_length,
                template: &template,
                tau: config.tau,
                skeleton_motion: true,
            },
            10,
        )
        .unwrap();
        let n = 301;
        motion.reserve(n + 20).unwrap();
        let mut rng = Rng::new(5);
        let mut xyz = Vec::with_capacity(3 * n);
        for _ in 0..n {
            let at = rng.below(v);
            for a in 0..3 {
                xyz.push(rig.canonical_vertices[3 * at + a] + 0.05 * rng.normal());
            }
        }
        // Points far outside the template.
        xyz[0..3].copy_from_slice(&[40.0, -3.0, 7.0]);
        xyz[3..6].copy_from_slice(&[-300.0, 100.0, 0.5]);
        let xyz = round(&xyz);
        let deformed: Vec<f64> = round(&xyz.iter().map(|x| x + 0.01).collect::<Vec<_>>());
        let queries = upload_points(&context, &xyz);
        let deformed_queries = upload_points(&context, &deformed);
        let grid = KnnGrid::new(&as_points(&template), 4.0);
        let params = rig.model.zero_params();
        let tau = config.tau;
        for frame in 0..track.num_frames {
            let before = context.transfers();
            motion.set_iteration(frame, n).unwrap();
            let mut encoder = context.encoder();
            motion.record_skeleton_window(&mut encoder).unwrap();
            motion.record_canonical_knn(&mut encoder, &queries).unwrap();
            motion.record_velocity(&mut encoder).unwrap();
            motion
                .record_nearest(&mut encoder, &deformed_queries)
                .unwrap();
            context.submit_and_wait(encoder).unwrap();
            let traffic = context.transfers().since(&before);
            assert_eq!(
                (traffic.readbacks, traffic.bytes_up, traffic.bytes_down),
                (0, 16, 0),
                "frame {frame}"
            );
            let got = motion.download(n).unwrap();
            let inputs = gather_frame_inputs(&config, &scales, &track, &params, frame).unwrap();
            assert_eq!(got.window, inputs.skeleton_motion, "frame {frame}: window");
            assert_eq!(
                got.neighbours,
                grid.query_all(&as_points(&xyz), tau),
                "frame {frame}: neighbours"
            );
            assert_eq!(
                got.nearest,
                grid.query_all(&as_points(&deformed), 1),
                "frame {frame}: nearest"
            );
            let velocity: Vec<f32> = knn_velocity(
                &grid,
                &xyz,
                &inputs.vertex_velocity,
                config.sequence_length,
                scales.len(),
                tau,
            );
            let width = tau * scales.len() * 3;
            assert_eq!(got.velocity.len(), config.sequence_length);
            for (l, block) in got.velocity.iter().enumerate() {
                let want: Vec<f32> = (0..n)
                    .flat_map(|i| {
                        let at = (i * config.sequence_length + l) * width;
                        velocity[at..at + width].iter().copied()
                    })
                    .collect();
                assert_eq!(block, &want, "frame {frame}: velocity block {l}");
            }
        }
    }

    #[test]
    fn resident_motion_matches_cpu() {
        // A context of its own: the traffic counts are per context and tests run in parallel.
        if let Some(context) = gpu_test_context_alone() {
            motion_matches_cpu(context);
        }
    }

    #[test]
    fn resident_motion_matches_cpu_with_2d_dispatch() {
        if let Some(context) = gpu_test_context_with_dispatch_limit(2) {
            motion_matches_cpu(context);
        }
    }

    /// Exact ties on an integer lattice (distances exact in f32 and f64), a duplicated and a
    /// non-finite template vertex, far and non-finite queries: the order of
    /// `KnnGrid::query_all` (distance, then index; the first reference point for a
    /// non-finite query).
    #[test]
    fn resident_knn_resolves_ties_like_the_grid() {
        let Some(context) = gpu_test_context() else {
            return;
        };
        let mut template = Vec::new();
        for z in 0..5 {
            for y in 0..5 {
                for x in 0..5 {
                    template.extend([x as f64, y as f64, z as f64]);
                }
            }
        }
        // A duplicate of vertex 62 (the centre) and a non-finite vertex.
        template.extend([2.0, 2.0, 2.0]);
        template.extend([f64::NAN, 0.0, 0.0]);
        let v = template.len() / 3;
        let track = track(2, 2, v, 1);
        let tau = 27;
        let motion = |capacity| {
            ResidentMotion::new(
                &context,
                &MotionSetup {
                    track: Some(&track),
                    scales: &[1],
                    length: 1,
                    template: &template,
                    tau,
                    skeleton_motion: false,
                },
                capacity,
            )
            .unwrap()
        };
        let mut queries = vec![
            [2.0, 2.0, 2.0],
            [2.5, 2.5, 2.5],
            [0.5, 0.0, 0.0],
            [4.0, 4.0, 4.0],
            [1e3, 0.0, 0.0],
            [-500.0, 200.0, 1.0],
            [1e25, -1e25, 3.0],
            [f64::NAN, 0.0, 0.0],
            [0.0, f64::INFINITY, 0.0],
        ];
        let mut rng = Rng::new(9);
        for _ in 0..60 {
            // Half-integer points: many exact ties.
            queries.push(std::array::from_fn(|_| 0.5 * rng.below(13) as f64 - 1.0));
        }
        let n = queries.len();
        let mut motion = motion(n);
        let flat: Vec<f64> = queries.iter().flatten().copied().collect();
        let buffer = upload_points(&context, &flat);
        motion.set_iteration(0, n).unwrap();
        let mut encoder = context.encoder();
        motion.record_canonical_knn(&mut encoder, &buffer).unwrap();
        motion.record_nearest(&mut encoder, &buffer).unwrap();
        context.submit_and_wait(encoder).unwrap();
        let got = motion.download(n).unwrap();
        let grid = KnnGrid::new(&as_points(&template), 4.0);
        let want = grid.query_all(&queries, tau);
        for i in 0..n {
            assert_eq!(
                got.neighbours[i * tau..(i + 1) * tau],
                want[i * tau..(i + 1) * tau],
                "query {i} {:?}",
                queries[i]
            );
        }
        assert_eq!(got.nearest, grid.query_all(&queries, 1));
        // Settings the device cannot serve are errors naming them.
        let setup = |tau| MotionSetup {
            track: Some(&track),
            scales: &[1],
            length: 1,
            template: &template,
            tau,
            skeleton_motion: false,
        };
        let error = ResidentMotion::new(&context, &setup(MAX_K + 1), 1)
            .err()
            .unwrap()
            .to_string();
        assert!(error.contains("tau"), "{error}");
        let error = ResidentMotion::new(
            &context,
            &MotionSetup {
                scales: &[3],
                ..setup(1)
            },
            1,
        )
        .err()
        .unwrap()
        .to_string();
        assert!(error.contains("scale 3"), "{error}");
        assert!(motion.set_iteration(2, 1).is_err());
        assert!(motion.set_iteration(0, n + 1).is_err());
    }

    /// A window reaching before position 0 of a frame axis that does not start the recording
    /// is the same error as `MotionTrack::gather`'s.
    #[test]
    fn resident_window_never_clamps_at_the_edge_of_what_ingest_kept() {
        let Some(context) = gpu_test_context() else {
            return;
        };
        let mut track = track(6, 1, 4, 2);
        track.axis = FrameAxis {
            past_frames: 2,
            starts_recording: false,
        };
        let template = [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
        let mut motion = ResidentMotion::new(
            &context,
            &MotionSetup {
                track: Some(&track),
                scales: &[2, 1],
                length: 2,
                template: &template,
                tau: 0,
                skeleton_motion: true,
            },
            1,
        )
        .unwrap();
        let error = motion.set_iteration(3, 1).unwrap_err().to_string();
        assert!(
            error.contains("frame 3") && error.contains("reaches 4 frames back"),
            "{error}"
        );
        assert!(track.gather(3, 2, &[1, 2]).is_err());
        motion.set_iteration(4, 1).unwrap();
        // No Gaussians: nothing to search or gather, the window still is.
        motion.set_iteration(5, 0).unwrap();
        let mut encoder = context.encoder();
        motion.record_skeleton_window(&mut encoder).unwrap();
        let empty = context.zeros("no queries", 0, 4).unwrap();
        motion.record_nearest(&mut encoder, &empty).unwrap();
        context.submit_and_wait(encoder).unwrap();
        let got = motion.download(0).unwrap();
        let slots = track.slots(&[2, 1]).unwrap();
        assert_eq!(got.window, track.gather(5, 2, &slots).unwrap().0);
        assert!(got.nearest.is_empty() && got.velocity.is_empty());
    }
}
