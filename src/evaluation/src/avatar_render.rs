//! The trained avatar as a [`ViewRenderer`]: `seqavatar_avatar::avatar::TrainedAvatar` driven
//! by per-frame body parameters and motion windows, plus the checks that an avatar and the
//! entry it is evaluated on belong together (same body model, same cameras).

use anyhow::Context as _;
use seqavatar_avatar::avatar::{FrameInputs, TrainedAvatar};
use seqavatar_avatar::sequence::{History, SequenceRenderer};
use seqavatar_avatar::splatting::WorldGaussians;
use seqavatar_compute::backend::Backend;
use seqavatar_core::body::BodyParams;
use seqavatar_core::camera::Camera;
use seqavatar_engine::EntryReader;
use seqavatar_schema::motion::MotionTrack;

use crate::context_probe::ContextProbe;
use crate::evaluate::ViewRenderer;
use seqavatar_compute::image::ImageF32;

/// Bytes per pixel of one frame in flight: the splatting's colour, alpha and depth in f32
/// and at its f64 boundary (60 bytes), its per-pixel compositing state, the frame as f32 and
/// 8-bit RGB, and its encoded file.
pub const FRAME_BYTES_PER_PIXEL: u64 = 128;

/// The memory `frames` frames in flight of `width x height` pixels are estimated to need
/// (for [`seqavatar_engine::check_memory_budget`], before any is drawn).
pub fn frames_memory_bytes(frames: u64, width: u32, height: u32) -> u64 {
    frames
        .saturating_mul(u64::from(width) * u64::from(height))
        .saturating_mul(FRAME_BYTES_PER_PIXEL)
}

/// Why an avatar cannot be evaluated on an entry.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MismatchError {
    #[error(
        "the avatar of train entry {avatar} uses body model \"{avatar_kind}\" ({avatar_vertices} vertices, {avatar_joints} joints), but ingest entry {ingest} has \"{ingest_kind}\" ({ingest_vertices} vertices, {ingest_joints} joints){detail}"
    )]
    BodyModel {
        avatar: String,
        ingest: String,
        avatar_kind: String,
        ingest_kind: String,
        avatar_vertices: usize,
        ingest_vertices: usize,
        avatar_joints: usize,
        ingest_joints: usize,
        detail: String,
    },
    #[error(
        "the avatar of train entry {avatar} was trained on the cameras of ingest entry {trained_on}, but it is evaluated on ingest entry {ingest}: {detail}"
    )]
    Cameras {
        avatar: String,
        trained_on: String,
        ingest: String,
        detail: String,
    },
}

/// Checks that the avatar's body model is the ingest entry's (kind and every array).
pub fn check_body_model(
    train: &EntryReader,
    avatar: &TrainedAvatar,
    ingest: &EntryReader,
) -> anyhow::Result<()> {
    let ingest_model = seqavatar_schema::ingest::read_body_model(ingest)?;
    let kind_of = seqavatar_schema::ingest::read_body_model_kind;
    let (avatar_kind, ingest_kind) = (kind_of(train), kind_of(ingest));
    let model = &avatar.rig.model;
    let same_kind = avatar_kind == ingest_kind;
    let same_arrays = model.arrays() == ingest_model.arrays();
    if same_kind && same_arrays {
        return Ok(());
    }
    Err(MismatchError::BodyModel {
        avatar: train.location().to_owned(),
        ingest: ingest.location().to_owned(),
        avatar_kind,
        ingest_kind,
        avatar_vertices: model.num_vertices(),
        ingest_vertices: ingest_model.num_vertices(),
        avatar_joints: model.num_joints(),
        ingest_joints: ingest_model.num_joints(),
        detail: if same_kind {
            " (their arrays differ)".to_owned()
        } else {
            String::new()
        },
    }
    .into())
}

/// The ingest key a train entry was computed from (its manifest inputs).
pub fn trained_on_ingest(train: &EntryReader) -> Option<String> {
    train
        .manifest()
        .inputs
        .iter()
        .find(|input| input.kind == "ingest")
        .map(|input| input.key.clone())
}

/// Whether two cameras agree (extrinsics and intrinsics normalised by the image size, so an
/// avatar trained at a lower `resolution_scale` still matches).
pub fn same_camera(a: &Camera, b: &Camera) -> bool {
    let close = |x: f64, y: f64| (x - y).abs() <= 1e-6 * (1.0 + x.abs().max(y.abs()));
    let all_close = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(&x, &y)| close(x, y));
    let rotation_close = all_close(&a.rotation.to_cols_array(), &b.rotation.to_cols_array());
    let translation_close = all_close(&a.translation.to_array(), &b.translation.to_array());
    let (aw, ah) = (f64::from(a.width), f64::from(a.height));
    let (bw, bh) = (f64::from(b.width), f64::from(b.height));
    let intrinsics_close = close(a.intrinsics.fx / aw, b.intrinsics.fx / bw)
        && close(a.intrinsics.fy / ah, b.intrinsics.fy / bh)
        && close(a.intrinsics.cx / aw, b.intrinsics.cx / bw)
        && close(a.intrinsics.cy / ah, b.intrinsics.cy / bh)
        && close(aw / ah, bw / bh);
    rotation_close && translation_close && intrinsics_close
}

/// Checks that the avatar was trained on the ingest entry's cameras: by the cameras stored in
/// the train entry when it has them, else by the ingest key in its manifest.
pub fn check_cameras(train: &EntryReader, ingest: &EntryReader) -> anyhow::Result<()> {
    let trained_on = trained_on_ingest(train).unwrap_or_else(|| "(none recorded)".to_owned());
    let mismatch = |detail: String| MismatchError::Cameras {
        avatar: train.location().to_owned(),
        trained_on: trained_on.clone(),
        ingest: format!("{} ({})", ingest.key(), ingest.location()),
        detail,
    };
    if train.manifest().arrays.contains_key("camera_K") {
        let trained = seqavatar_schema::ingest::read_cameras(train)?;
        let evaluated = seqavatar_schema::ingest::read_cameras(ingest)?;
        if trained.len() != evaluated.len() {
            return Err(mismatch(format!(
                "{} cameras in the avatar, {} in the ingest entry",
                trained.len(),
                evaluated.len()
            ))
            .into());
        }
        if let Some(view) =
            (0..trained.len()).find(|&view| !same_camera(&trained[view], &evaluated[view]))
        {
            return Err(mismatch(format!("camera of view {view} differs")).into());
        }
        return Ok(());
    }
    if trained_on == ingest.key() {
        return Ok(());
    }
    Err(mismatch(
        "the train entry stores no cameras to compare, so the test split must come from the ingest entry it was trained on (render other poses with `pipeline render`)".to_owned(),
    )
    .into())
}

/// A trained avatar with the per-frame body parameters and motion track of a sequence.
pub struct AvatarRenderer {
    pub avatar: TrainedAvatar,
    /// The frames and the backend every render runs on, chosen when the renderer is built
    /// (on the gpu the avatar is uploaded then: change only its `background` afterwards).
    frames: SequenceRenderer,
    location: String,
    /// Replaces the motion-history inputs of every frame (eval's context probes).
    context_probe: Option<ContextProbe>,
}

impl AvatarRenderer {
    /// Loads the avatar of `train`; errors name the entry and the array.
    pub fn load_avatar(train: &EntryReader) -> anyhow::Result<TrainedAvatar> {
        TrainedAvatar::load(train).with_context(|| {
            format!(
                "cannot load the trained avatar of entry {}",
                train.location()
            )
        })
    }

    /// An avatar driven by `params` (one per frame) and `motion` (needed when the avatar's
    /// motion context uses skeleton motion or velocities), rendered on `backend`, chosen
    /// here once ([`SequenceRenderer`]): on the gpu the avatar, its networks and the
    /// sequence are uploaded once and every frame is deformed and splatted on the device
    /// (one read-back, the image), so renders and the frame rates measured on them are the
    /// device's.
    pub fn new(
        avatar: TrainedAvatar,
        params: Vec<BodyParams>,
        motion: Option<MotionTrack>,
        backend: Backend,
        location: String,
    ) -> anyhow::Result<Self> {
        let context = avatar.config.motion_context;
        if context.has_skeleton_motion() {
            let Some(track) = &motion else {
                anyhow::bail!(
                    "the avatar of {location} uses motion context {context:?}: it needs a motion entry (add the motion stage to the eval stage's inputs)"
                );
            };
            anyhow::ensure!(
                track.num_frames == params.len(),
                "the motion track has {} frames, the body parameters {}",
                track.num_frames,
                params.len()
            );
            let model = &avatar.rig.model;
            anyhow::ensure!(
                track.body_joints() == model.num_joints()
                    && track.num_vertices == model.num_vertices(),
                "the motion track has {} joints and {} vertices, the avatar's body model {} and {}",
                track.body_joints(),
                track.num_vertices,
                model.num_joints(),
                model.num_vertices()
            );
            if let Some(networks) = &avatar.networks
                && context.has_skeleton_motion()
            {
                let read = networks.config().motion_joints;
                anyhow::ensure!(
                    read == track.num_joints,
                    "the avatar of {location} reads {read} skeleton-motion rows, the motion entry \
                     gives {} ({} of them the garment oracle's): train and render with the same \
                     motion entry",
                    track.num_joints,
                    track.garment_rows
                );
            }
            track.slots(&avatar.scales).with_context(|| {
                format!(
                    "the avatar of {location} was trained with scales {:?}",
                    avatar.scales
                )
            })?;
        }
        let frames = SequenceRenderer::new(&avatar, &backend, params, motion)
            .with_context(|| format!("the avatar of {location}"))?;
        Ok(Self {
            avatar,
            frames,
            location,
            context_probe: None,
        })
    }

    /// The avatar of `train` driven by the body parameters of `params_entry` (a fit entry, or
    /// the ingest entry) and the motion entry, after checking body model and cameras against
    /// `ingest`; its networks run at the `precision` the train entry stored (`mixed` where it
    /// stored none), as `pipeline view` renders.
    pub fn open(
        train: &EntryReader,
        ingest: &EntryReader,
        params_entry: &EntryReader,
        motion: Option<&EntryReader>,
        backend: &Backend,
    ) -> anyhow::Result<Self> {
        Self::open_loaded(
            Self::load_avatar(train)?,
            train,
            ingest,
            params_entry,
            motion,
            backend,
        )
    }

    /// [`AvatarRenderer::open`] with `avatar` already loaded from `train` (eval sets its
    /// networks' `precision` before the renderer is built).
    pub fn open_loaded(
        avatar: TrainedAvatar,
        train: &EntryReader,
        ingest: &EntryReader,
        params_entry: &EntryReader,
        motion: Option<&EntryReader>,
        backend: &Backend,
    ) -> anyhow::Result<Self> {
        check_body_model(train, &avatar, ingest)?;
        check_cameras(train, ingest)?;
        let params = seqavatar_schema::ingest::read_body_params(params_entry, "body")?;
        let motion = motion.map(MotionTrack::read).transpose()?;
        Self::new(
            avatar,
            params,
            motion,
            backend.clone(),
            train.location().to_owned(),
        )
    }

    /// The first frame whose motion window lies inside the poses' frame axis: 0 unless the
    /// avatar gathers windows and the axis does not start its recording (then the frames
    /// before it cannot be drawn: their windows reach frames the source does not hold).
    pub fn first_frame(&self) -> usize {
        match self.frames.motion() {
            Some(track) if !track.axis.starts_recording => track
                .slots(&self.avatar.scales)
                .map(|slots| track.reach(self.avatar.config.sequence_length, &slots))
                .unwrap_or(0),
            _ => 0,
        }
    }

    /// The deformed Gaussians of frame `frame` (what [`ViewRenderer::render`] splats).
    pub fn deform(&mut self, frame: usize) -> anyhow::Result<WorldGaussians> {
        let history = self.history(frame)?;
        self.frames
            .deform(&self.avatar, frame, history)
            .with_context(|| format!("avatar {}: frame {frame}", self.location))
    }

    /// Whether frames are deformed and splatted on the device.
    pub fn on_device(&self) -> bool {
        self.frames.on_device()
    }

    /// Whether the per-Gaussian networks run on a gpu.
    pub fn networks_on_gpu(&self) -> bool {
        self.frames.networks_on_gpu()
    }

    /// Number of frames this renderer can draw.
    pub fn num_frames(&self) -> usize {
        self.frames.num_frames()
    }

    /// The motion-history inputs frame `frame` reads under the context probe.
    fn history(&self, frame: usize) -> anyhow::Result<History> {
        let frames = self.num_frames();
        anyhow::ensure!(
            frame < frames,
            "frame {frame}: the sequence has {frames} frames"
        );
        Ok(match self.context_probe {
            None => History::Own,
            Some(ContextProbe::Zeroed) => History::Zeroed,
            Some(probe) => match probe.donor(frame, self.first_frame(), frames) {
                Some(donor) => History::Frame(donor),
                None => History::Zeroed,
            },
        })
    }

    /// The host-side inputs of frame `frame` (under the context probe).
    pub fn frame_inputs(&self, frame: usize) -> anyhow::Result<FrameInputs> {
        let history = self.history(frame)?;
        self.frames.frame_inputs(&self.avatar, frame, history)
    }
}

impl ViewRenderer for AvatarRenderer {
    fn set_context_probe(&mut self, probe: Option<ContextProbe>) -> bool {
        if !self.avatar.config.motion_context.has_skeleton_motion()
            || self.frames.motion().is_none()
        {
            return false;
        }
        self.context_probe = probe;
        true
    }

    fn render(&mut self, frame: usize, camera: &Camera) -> anyhow::Result<ImageF32> {
        let history = self.history(frame)?;
        let image = self
            .frames
            .render(&self.avatar, frame, history, camera, self.avatar.background)
            .with_context(|| format!("avatar {}: frame {frame}", self.location))?;
        let colour: Vec<f32> = image.colour.iter().map(|&value| value as f32).collect();
        ImageF32::from_f32(
            "avatar render",
            image.width as usize,
            image.height as usize,
            colour,
        )
        .map_err(anyhow::Error::from)
    }

    fn forget_deformed_frame(&mut self) {
        self.frames.forget_deformed_frame();
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_compute::backend::DeviceChoice;
    use seqavatar_core::glam::DVec3;

    fn camera() -> Camera {
        Camera::look_at(
            200,
            100,
            seqavatar_core::camera::Intrinsics {
                fx: 120.0,
                fy: 121.0,
                cx: 100.5,
                cy: 50.25,
            },
            DVec3::new(0.3, -1.0, 3.0),
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        )
    }

    #[test]
    fn a_rescaled_camera_is_the_same_camera_and_a_moved_one_is_not() {
        let base = camera();
        assert!(same_camera(&base, &base));
        // Training at resolution_scale 0.5 keeps the camera.
        assert!(same_camera(&base, &base.rescaled(0.5)));
        let mut moved = base.clone();
        moved.translation.x += 1e-3;
        assert!(!same_camera(&base, &moved));
        let mut zoomed = base.clone();
        zoomed.intrinsics.fx *= 1.01;
        assert!(!same_camera(&base, &zoomed));
        // A different aspect ratio is a different sensor even with proportional intrinsics.
        assert!(!same_camera(&base, &base.resized(200, 200)));
    }

    /// On the gpu backend the renderer uploads the avatar's networks and renders with them
    /// the image the `cpu` renderer draws (PSNR above 50 dB; f32 networks and gpu splatting
    /// against f64 networks and cpu splatting).
    #[test]
    fn a_gpu_renderer_uses_gpu_networks_and_matches_cpu() {
        use seqavatar_avatar::config::MotionContext;
        use seqavatar_avatar::test_support::{TestAvatar, small_config};
        let Some(backend) = seqavatar_compute::backend::test_support::gpu_test_backend() else {
            return;
        };
        let mut config = small_config(MotionContext::Pose);
        config.tau = 4;
        config.pose_refiner = true;
        config.lbs_offsets = true;
        config.sh_degree = 1;
        let description = TestAvatar {
            scales: vec![1],
            seed: 8,
            ..TestAvatar::new(config)
        };
        let model = description.build().rig.model.clone();
        let mut params = model.zero_params();
        params.pose[1] = DVec3::new(0.3, 0.0, 0.1);
        params.pose[16] = DVec3::new(0.0, 0.0, -0.8);
        params.world_translation = DVec3::new(0.0, 0.2, 0.0);
        let build = |backend: Backend| {
            AvatarRenderer::new(
                description.build(),
                vec![params.clone()],
                None,
                backend,
                "test".into(),
            )
            .unwrap()
        };
        let mut cpu = build(Backend::select(DeviceChoice::Cpu).unwrap());
        let mut gpu = build(backend);
        assert!(!cpu.networks_on_gpu() && !cpu.on_device());
        assert!(gpu.networks_on_gpu() && gpu.on_device());
        let camera = Camera::look_at(
            48,
            64,
            seqavatar_core::camera::Intrinsics {
                fx: 60.0,
                fy: 60.0,
                cx: 24.0,
                cy: 32.0,
            },
            DVec3::new(0.0, 0.0, 2.5),
            DVec3::new(0.0, 0.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
        );
        let a = cpu.render(0, &camera).unwrap();
        let b = gpu.render(0, &camera).unwrap();
        let lit = a.data.iter().filter(|&&x| x > 0.05).count();
        assert!(
            lit > a.data.len() / 50,
            "{lit} lit values of {}",
            a.data.len()
        );
        let db = crate::metrics::psnr(&b, &a).unwrap();
        eprintln!("eval render, gpu vs cpu: PSNR {db:.1} dB");
        assert!(db > 50.0, "PSNR {db} dB");
    }

    /// `pipeline render`'s rule at the first frames of a pose source: an avatar with skeleton
    /// motion (window 2 x step 2 = 4 frames) draws every frame of a source that starts its
    /// recording (windows clamp at frame 0), and only frames 4.. of one whose recording starts
    /// earlier (the earlier frames' windows reach frames the source does not hold: gathering
    /// them is an error, never a clamp).
    #[test]
    fn render_frames_follow_the_recording_start() {
        use crate::animate::frames_to_draw;
        use seqavatar_avatar::avatar::AvatarGaussians;
        use seqavatar_avatar::config::{AvatarConfig, MotionContext};
        use seqavatar_avatar::rig::BodyRig;
        use seqavatar_core::body::procedural::procedural_body;
        use seqavatar_schema::motion::FrameAxis;

        let model = procedural_body(0.05);
        let (j, v, frames) = (model.num_joints(), model.num_vertices(), 6);
        let config = AvatarConfig {
            trunk_width: 8,
            trunk_depth: 1,
            tau: 1,
            ..seqavatar_avatar::test_support::small_config(MotionContext::Skeleton)
        };
        let renderer = |axis: FrameAxis| {
            let rig = BodyRig::new(model.clone()).unwrap();
            let gaussians = AvatarGaussians {
                xyz: rig.canonical_vertices[..3].to_vec(),
                sh: vec![0.0; 48],
                opacity_logit: vec![0.0],
                log_scale: vec![-3.0; 3],
                rotation: vec![1.0, 0.0, 0.0, 0.0],
            };
            let avatar = TrainedAvatar::new(config.clone(), rig, gaussians, 0, vec![2], None);
            let track = MotionTrack {
                num_frames: frames,
                num_joints: j,
                garment_rows: 0,
                num_vertices: v,
                scales: vec![2],
                scale_steps: vec![2],
                skeleton_motion: vec![0.0; frames * j * 3],
                vertex_velocity: vec![0.0; frames * v * 3],
                axis,
            };
            AvatarRenderer::new(
                avatar,
                vec![model.zero_params(); frames],
                Some(track),
                Backend::select(DeviceChoice::Cpu).unwrap(),
                "test".into(),
            )
            .unwrap()
        };
        let from_start = renderer(FrameAxis::FROM_START);
        assert_eq!(from_start.first_frame(), 0);
        assert_eq!(frames_to_draw(&from_start, 0), 0..6);
        from_start.frame_inputs(0).unwrap();
        let late = renderer(FrameAxis {
            past_frames: 2,
            starts_recording: false,
        });
        assert_eq!(late.first_frame(), 4);
        assert_eq!(frames_to_draw(&late, 0), 4..6);
        assert_eq!(frames_to_draw(&late, 1), 4..5);
        let error = format!("{:#}", late.frame_inputs(3).unwrap_err());
        assert!(
            error.contains("frame 3") && error.contains("past_frames = 2"),
            "{error}"
        );
        late.frame_inputs(4).unwrap();
    }
}
