//! A trained avatar driven by one sequence's frames (body parameters and motion track) and
//! rendered on the backend chosen once, by `frame_path` when the renderer is built: on `cpu`
//! the frame inputs are gathered on the host and the avatar's
//! [`crate::device::AvatarBackend`] deforms and splats (`HostPath`); on the `gpu` the whole
//! frame runs on the device ([`ResidentRenderer`]) and only the image comes back. Eval, the
//! held-out PSNR of training, `pipeline render`, `pipeline export` and `pipeline view` render
//! through it.

use seqavatar_compute::backend::Backend;
use seqavatar_compute::splat::RenderedImage;
use seqavatar_core::body::BodyParams;
use seqavatar_core::camera::Camera;
use seqavatar_schema::motion::MotionTrack;

use crate::avatar::{FrameInputs, TrainedAvatar, splat_on};
use crate::device::AvatarBackend;
pub use crate::resident::deform::History;
use crate::resident::render::ResidentRenderer;
use crate::splatting::WorldGaussians;

/// An avatar's renderer over the frames of one sequence. Every call takes the avatar it was
/// built for (the device path holds a snapshot of it made at [`SequenceRenderer::new`]).
pub struct SequenceRenderer {
    frames: Frames,
    path: Box<dyn FramePath>,
}

/// The frames of the sequence: their body parameters and motion track.
struct Frames {
    params: Vec<BodyParams>,
    motion: Option<MotionTrack>,
}

/// How frames are deformed and splatted, chosen once by `frame_path`.
trait FramePath: Send {
    /// Frame `frame` (with `history`) from `camera` on `background`.
    fn render(
        &mut self,
        avatar: &TrainedAvatar,
        frames: &Frames,
        at: (usize, History),
        camera: &Camera,
        background: [f64; 3],
    ) -> anyhow::Result<RenderedImage<f64>>;

    /// The deformed Gaussians of frame `frame` (with `history`).
    fn deform(
        &mut self,
        avatar: &TrainedAvatar,
        frames: &Frames,
        at: (usize, History),
    ) -> anyhow::Result<WorldGaussians>;

    /// Whether frames are deformed and splatted on the device.
    fn on_device(&self) -> bool;

    /// Deformations run on the host so far.
    fn host_deformations(&self) -> usize {
        0
    }

    /// Drops a kept deformed frame.
    fn forget_deformed_frame(&mut self) {}
}

/// The path of `avatar` over the frames `params` (with their motion `track`) on `backend`:
/// the host path on `cpu`, the device path on the gpu (the avatar, its networks, the poses
/// and the motion arrays uploaded here, once). The renderer's one backend factory.
fn frame_path(
    avatar: &TrainedAvatar,
    backend: &Backend,
    params: &[BodyParams],
    track: Option<&MotionTrack>,
) -> anyhow::Result<Box<dyn FramePath>> {
    Ok(match backend {
        Backend::Cpu => Box::new(HostPath {
            device: avatar.backend(backend.clone())?,
            last_deformed: None,
            deformations: 0,
        }),
        Backend::Gpu(context) => Box::new(ResidentRenderer::new(
            context.clone(),
            avatar,
            params,
            track,
        )?),
    })
}

impl SequenceRenderer {
    /// The renderer of `avatar` on `backend` over the frames `params` (one per frame) with
    /// their motion `track` (required when the motion context has history inputs). On the
    /// gpu the avatar, its networks, the poses and the motion arrays are uploaded here, once.
    pub fn new(
        avatar: &TrainedAvatar,
        backend: &Backend,
        params: Vec<BodyParams>,
        motion: Option<MotionTrack>,
    ) -> anyhow::Result<Self> {
        let path = frame_path(avatar, backend, &params, motion.as_ref())?;
        Ok(Self {
            frames: Frames { params, motion },
            path,
        })
    }

    /// Drops the kept deformed frame: the next render deforms its frame anew (speed
    /// measurements time the whole path).
    pub fn forget_deformed_frame(&mut self) {
        self.path.forget_deformed_frame();
    }

    /// Deformations run on the host path so far (a frame rendered again with the same
    /// history, from any camera, reuses the last one).
    pub fn host_deformations(&self) -> usize {
        self.path.host_deformations()
    }

    pub fn num_frames(&self) -> usize {
        self.frames.params.len()
    }

    pub fn params(&self) -> &[BodyParams] {
        &self.frames.params
    }

    /// The motion track, when the renderer has one.
    pub fn motion(&self) -> Option<&MotionTrack> {
        self.frames.motion.as_ref()
    }

    /// Whether frames are deformed and splatted on the device.
    pub fn on_device(&self) -> bool {
        self.path.on_device()
    }

    /// Whether the per-Gaussian networks run on a gpu: on the device path (the host path is
    /// `cpu`'s).
    pub fn networks_on_gpu(&self) -> bool {
        self.path.on_device()
    }

    /// The host-side inputs of frame `frame` with `history` (the `cpu` path's; the device
    /// path gathers the same on the device).
    pub fn frame_inputs(
        &self,
        avatar: &TrainedAvatar,
        frame: usize,
        history: History,
    ) -> anyhow::Result<FrameInputs> {
        self.frames.inputs(avatar, frame, history)
    }

    /// Renders frame `frame` (with `history`) from `camera` on `background`.
    pub fn render(
        &mut self,
        avatar: &TrainedAvatar,
        frame: usize,
        history: History,
        camera: &Camera,
        background: [f64; 3],
    ) -> anyhow::Result<RenderedImage<f64>> {
        self.frames.params(frame)?;
        self.path
            .render(avatar, &self.frames, (frame, history), camera, background)
    }

    /// The deformed Gaussians of frame `frame` (with `history`), as the splatting reads them.
    pub fn deform(
        &mut self,
        avatar: &TrainedAvatar,
        frame: usize,
        history: History,
    ) -> anyhow::Result<WorldGaussians> {
        self.frames.params(frame)?;
        self.path.deform(avatar, &self.frames, (frame, history))
    }
}

impl Frames {
    fn params(&self, frame: usize) -> anyhow::Result<&BodyParams> {
        self.params.get(frame).ok_or_else(|| {
            anyhow::anyhow!(
                "frame {frame}: the sequence has {} frames",
                self.params.len()
            )
        })
    }

    /// The host-side inputs of frame `frame` with `history`.
    fn inputs(
        &self,
        avatar: &TrainedAvatar,
        frame: usize,
        history: History,
    ) -> anyhow::Result<FrameInputs> {
        let params = self.params(frame)?;
        let Some(track) = &self.motion else {
            return Ok(FrameInputs {
                params: params.clone(),
                skeleton_motion: Vec::new(),
                vertex_velocity: Vec::new(),
            });
        };
        let mut inputs = avatar.frame_inputs(track, params, frame)?;
        match history {
            History::Own => {}
            History::Zeroed => {
                inputs.skeleton_motion.fill(0.0);
                inputs.vertex_velocity.fill(0.0);
            }
            History::Frame(donor) => {
                let donor = avatar.frame_inputs(track, self.params(donor)?, donor)?;
                inputs.skeleton_motion = donor.skeleton_motion;
                inputs.vertex_velocity = donor.vertex_velocity;
            }
        }
        Ok(inputs)
    }
}

/// The `cpu` path: frame inputs on the host, the avatar's backend for networks and splatting.
struct HostPath {
    device: AvatarBackend,
    /// The last deformed frame, with its frame and history: eval renders every camera of a
    /// frame in turn and the viewer re-renders a paused frame from new views, and on `cpu`
    /// the deformation (the per-Gaussian networks) is most of a frame's cost. Valid because
    /// every call takes the avatar the renderer was built for.
    last_deformed: Option<(usize, History, WorldGaussians)>,
    /// Deformations run (the cache's misses).
    deformations: usize,
}

impl HostPath {
    /// Makes `last_deformed` frame `at` (kept when it already is).
    fn deform_frame(
        &mut self,
        avatar: &TrainedAvatar,
        frames: &Frames,
        (frame, history): (usize, History),
    ) -> anyhow::Result<&WorldGaussians> {
        let cached = matches!(&self.last_deformed, Some((f, h, _)) if (*f, *h) == (frame, history));
        if !cached {
            self.last_deformed = None;
            let inputs = frames.inputs(avatar, frame, history)?;
            let world = avatar.deform(&inputs, &self.device)?.world;
            self.deformations += 1;
            self.last_deformed = Some((frame, history, world));
        }
        match &self.last_deformed {
            Some((_, _, world)) => Ok(world),
            None => unreachable!("filled above"),
        }
    }
}

impl FramePath for HostPath {
    fn render(
        &mut self,
        avatar: &TrainedAvatar,
        frames: &Frames,
        at: (usize, History),
        camera: &Camera,
        background: [f64; 3],
    ) -> anyhow::Result<RenderedImage<f64>> {
        self.deform_frame(avatar, frames, at)?;
        let Some((_, _, world)) = &self.last_deformed else {
            unreachable!("deformed above")
        };
        splat_on(world, camera, &self.device, background)
    }

    fn deform(
        &mut self,
        avatar: &TrainedAvatar,
        frames: &Frames,
        at: (usize, History),
    ) -> anyhow::Result<WorldGaussians> {
        self.deform_frame(avatar, frames, at).cloned()
    }

    fn on_device(&self) -> bool {
        false
    }

    fn host_deformations(&self) -> usize {
        self.deformations
    }

    fn forget_deformed_frame(&mut self) {
        self.last_deformed = None;
    }
}

/// The `gpu` path: everything on the device, one read-back per frame.
impl FramePath for ResidentRenderer {
    fn render(
        &mut self,
        _avatar: &TrainedAvatar,
        _frames: &Frames,
        (frame, history): (usize, History),
        camera: &Camera,
        background: [f64; 3],
    ) -> anyhow::Result<RenderedImage<f64>> {
        let image = ResidentRenderer::render(self, frame, history, camera, background)?;
        let widen = |values: Vec<f32>| values.into_iter().map(f64::from).collect();
        Ok(RenderedImage {
            width: image.width,
            height: image.height,
            colour: widen(image.colour),
            alpha: widen(image.alpha),
            depth: widen(image.depth),
        })
    }

    fn deform(
        &mut self,
        _avatar: &TrainedAvatar,
        _frames: &Frames,
        (frame, history): (usize, History),
    ) -> anyhow::Result<WorldGaussians> {
        ResidentRenderer::deform(self, frame, history)
    }

    fn on_device(&self) -> bool {
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::MotionContext;
    use crate::test_support::{TestAvatar, random_track, small_config};
    use seqavatar_compute::backend::DeviceChoice;
    use seqavatar_core::camera::Intrinsics;
    use seqavatar_core::glam::DVec3;

    /// An avatar with every network (multiscale motion context, pose refiner, LBS offsets)
    /// and heads well away from zero, on a 5-frame sequence of distinct poses and random
    /// motion values.
    fn avatar_and_sequence() -> (TrainedAvatar, Vec<BodyParams>, MotionTrack) {
        let mut config = small_config(MotionContext::Multiscale);
        config.tau = 3;
        config.pose_refiner = true;
        config.lbs_offsets = true;
        config.sh_degree = 1;
        let avatar = TestAvatar {
            gaussians: 400,
            seed: 17,
            ..TestAvatar::new(config)
        }
        .build();
        let (model, frames) = (&avatar.rig.model, 5);
        let j = model.num_joints();
        let params: Vec<BodyParams> = (0..frames)
            .map(|f| {
                let mut params = model.zero_params();
                params.pose[1] = DVec3::new(0.1 * f as f64, 0.0, 0.2);
                params.pose[16 % j] = DVec3::new(0.0, -0.15 * f as f64, 0.3);
                params.world_rotation = DVec3::new(0.0, 0.2 * f as f64, 0.0);
                params.world_translation = DVec3::new(0.02 * f as f64, 0.1, 0.0);
                params
            })
            .collect();
        let track = random_track(&avatar, frames, 23);
        (avatar, params, track)
    }

    fn camera(width: u32, height: u32) -> Camera {
        Camera::look_at(
            width,
            height,
            Intrinsics {
                fx: 1.2 * f64::from(width),
                fy: 1.2 * f64::from(width),
                cx: 0.5 * f64::from(width),
                cy: 0.5 * f64::from(height),
            },
            DVec3::new(0.4, 0.2, 2.4),
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        )
    }

    fn psnr(a: &[f64], b: &[f64]) -> f64 {
        let mse = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum::<f64>() / a.len() as f64;
        10.0 * (1.0 / mse.max(1e-20)).log10()
    }

    /// The device path (deformation and splatting on the gpu, f32) renders and deforms what
    /// the `cpu` path does, for the frame's own history, zeroed history and another frame's
    /// history; the history changes the render on both.
    #[test]
    fn the_device_path_renders_and_deforms_as_the_cpu_path() {
        let Some(gpu) = seqavatar_compute::backend::test_support::gpu_test_backend() else {
            return;
        };
        let cpu = Backend::select(DeviceChoice::Cpu).unwrap();
        let (avatar, params, track) = avatar_and_sequence();
        let mut on_cpu =
            SequenceRenderer::new(&avatar, &cpu, params.clone(), Some(track.clone())).unwrap();
        let mut on_gpu = SequenceRenderer::new(&avatar, &gpu, params, Some(track)).unwrap();
        assert!(!on_cpu.on_device() && on_gpu.on_device());
        let view = camera(64, 48);
        let background = [0.2, 0.5, 0.9];
        let mut own = None;
        for history in [History::Own, History::Zeroed, History::Frame(1)] {
            let a = on_cpu
                .render(&avatar, 3, history, &view, background)
                .unwrap();
            let b = on_gpu
                .render(&avatar, 3, history, &view, background)
                .unwrap();
            assert_eq!((a.width, a.height), (b.width, b.height));
            let colour = psnr(&a.colour, &b.colour);
            let alpha = psnr(&a.alpha, &b.alpha);
            assert!(
                colour > 50.0 && alpha > 50.0,
                "{history:?}: {colour} / {alpha} dB"
            );
            match &own {
                None => own = Some(a.colour.clone()),
                Some(own) => {
                    let change = own
                        .iter()
                        .zip(&a.colour)
                        .map(|(x, y)| (x - y).abs())
                        .fold(0.0, f64::max);
                    assert!(
                        change > 1e-3,
                        "{history:?} renders as the frame's own history"
                    );
                }
            }
            let x = on_cpu.deform(&avatar, 3, history).unwrap();
            let y = on_gpu.deform(&avatar, 3, history).unwrap();
            // f32 on the device against the f64 oracle. Lavapipe stays within 2e-5 on means
            // (metres) and 1e-6 on covariances; an NVIDIA H100 measured 1.9e-4 and 2.0e-5
            // (its transcendentals are looser, and Vulkan guarantees sin and cos only to
            // 2^-11; fused multiply-adds can also tip a nearest-vertex choice between two
            // near-equidistant vertices). The tolerances leave 5x over the H100: 1 mm on
            // means and 1e-4 on covariances (the largest is 1.5e-2 here); a wrong frame,
            // history or joint moves means by centimetres.
            let mut report = Vec::new();
            for (name, p, q, tolerance) in [
                ("means", &x.means, &y.means, 1e-3),
                ("covariances", &x.covariances, &y.covariances, 1e-4),
                ("opacities", &x.opacities, &y.opacities, 1e-5),
                ("sh", &x.sh, &y.sh, 1e-5),
            ] {
                assert_eq!(p.len(), q.len(), "{name}");
                let worst = p
                    .iter()
                    .zip(q)
                    .map(|(a, b)| (a - b).abs())
                    .fold(0.0, f64::max);
                let largest = p.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                eprintln!(
                    "{history:?} {name}: worst gpu - cpu {worst:.3e} (tolerance {tolerance:.0e}, largest value {largest:.3e})"
                );
                if worst > tolerance {
                    report.push(format!("{name}: {worst:.3e} > {tolerance:.0e}"));
                }
            }
            assert!(report.is_empty(), "{history:?}: {}", report.join("; "));
        }
        // Another frame's history is exactly that frame's own on the device.
        let borrowed = on_gpu
            .render(&avatar, 3, History::Frame(1), &view, background)
            .unwrap();
        let mut again = SequenceRenderer::new(
            &avatar,
            &gpu,
            vec![on_gpu.params()[3].clone(); 5],
            on_gpu.motion().cloned(),
        )
        .unwrap();
        let direct = again
            .render(&avatar, 1, History::Own, &view, background)
            .unwrap();
        assert_eq!(borrowed.colour, direct.colour);
        // A frame outside the sequence is an error naming it, on both paths.
        for renderer in [&mut on_cpu, &mut on_gpu] {
            let error = format!(
                "{:#}",
                renderer
                    .render(&avatar, 5, History::Own, &view, background)
                    .unwrap_err()
            );
            assert!(error.contains("frame 5"), "{error}");
        }
    }

    /// On `cpu` a frame rendered again with the same history, from another camera or on
    /// another background, reuses its deformation and renders what a fresh renderer does;
    /// another frame or history deforms again.
    #[test]
    fn a_host_frame_is_deformed_once_for_every_view() {
        let cpu = Backend::select(DeviceChoice::Cpu).unwrap();
        let (avatar, params, track) = avatar_and_sequence();
        let fresh = || SequenceRenderer::new(&avatar, &cpu, params.clone(), Some(track.clone()));
        let mut renderer = fresh().unwrap();
        let (near, far) = (camera(32, 24), camera(40, 30));
        let (grey, blue) = ([0.5; 3], [0.1, 0.2, 0.9]);
        let mut views = Vec::new();
        for (frame, history, view, background, deformations) in [
            (3, History::Own, &near, grey, 1),
            (3, History::Own, &far, grey, 1),
            (3, History::Own, &near, blue, 1),
            (3, History::Zeroed, &near, grey, 2),
            (2, History::Zeroed, &near, grey, 3),
            (3, History::Own, &far, grey, 4),
        ] {
            let image = renderer
                .render(&avatar, frame, history, view, background)
                .unwrap();
            assert_eq!(
                renderer.host_deformations(),
                deformations,
                "frame {frame} {history:?}"
            );
            let expected = fresh()
                .unwrap()
                .render(&avatar, frame, history, view, background)
                .unwrap();
            assert_eq!(image.colour, expected.colour, "frame {frame} {history:?}");
            views.push(image.colour);
        }
        assert_ne!(
            views[0], views[3],
            "zeroed history renders as the frame's own"
        );
        renderer.forget_deformed_frame();
        renderer
            .render(&avatar, 3, History::Own, &far, grey)
            .unwrap();
        assert_eq!(
            renderer.host_deformations(),
            5,
            "a forgotten frame deforms again"
        );
        // The deformed Gaussians of the frame just rendered come from the same deformation.
        let world = renderer.deform(&avatar, 3, History::Own).unwrap();
        assert_eq!(renderer.host_deformations(), 5);
        assert_eq!(
            world,
            fresh().unwrap().deform(&avatar, 3, History::Own).unwrap()
        );
    }

    /// On the device a frame costs one submission and one read-back (the image and the
    /// splatting status), and uploads only its small per-frame records.
    #[test]
    fn a_device_frame_reads_back_once_and_uploads_only_records() {
        let Some(gpu) = seqavatar_compute::backend::test_support::gpu_test_backend_alone() else {
            return;
        };
        let (avatar, params, track) = avatar_and_sequence();
        let mut renderer = SequenceRenderer::new(&avatar, &gpu, params, Some(track)).unwrap();
        let view = camera(96, 64);
        // The first frames size the splatting's pair capacity.
        for frame in 0..3 {
            renderer
                .render(&avatar, frame, History::Own, &view, [0.0; 3])
                .unwrap();
        }
        let before = gpu.transfers();
        for frame in [3, 4, 2] {
            renderer
                .render(&avatar, frame, History::Own, &view, [0.0; 3])
                .unwrap();
        }
        let traffic = gpu.transfers().since(&before);
        assert_eq!(traffic.readbacks, 3, "{traffic:?}");
        // Per frame: colour, alpha, depth (5 floats per pixel) and a few hundred bytes of
        // diagnostics and status.
        let image_bytes = 96 * 64 * 5 * 4;
        assert!(
            traffic.bytes_down <= 3 * (image_bytes + 1024),
            "{traffic:?}"
        );
        assert!(traffic.bytes_up <= 3 * 1024, "{traffic:?}");
    }
}
