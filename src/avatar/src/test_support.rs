//! Small avatars for tests, here and in the crates that render avatars (eval): the procedural
//! body, networks whose output heads are moved off their near-zero initialisation (so the
//! networks change what renders), random Gaussians on template vertices, and a random motion
//! track. Seeded: the same description builds the same avatar.

use seqavatar_compute::nn::{Precision, Rng};
use seqavatar_core::body::procedural::procedural_body;
use seqavatar_schema::motion::{FrameAxis, MotionTrack};

use crate::avatar::{AvatarGaussians, TrainedAvatar};
use crate::config::{AvatarConfig, Background, MotionContext};
use crate::model::{NetworkConfig, Networks};
use crate::rig::BodyRig;

/// A small configuration: trunk 16 x 2, `tau` 2, `L` 2, SH degree 0, no refiners.
pub fn small_config(motion_context: MotionContext) -> AvatarConfig {
    AvatarConfig {
        motion_context,
        trunk_width: 16,
        trunk_depth: 2,
        tau: 2,
        sequence_length: 2,
        pose_refiner: false,
        lbs_offsets: false,
        sh_degree: 0,
        scale_min: 1e-5,
        scale_max: 0.5,
        background: Background::Black,
        // The gpu renders are compared with `cpu` at f32's tolerances (the tensor-core path
        // is tested against f32 in the compute crate).
        precision: Some(Precision::F32),
        skinning_smoothing: None,
        network_widths: None,
    }
}

/// What [`TestAvatar::build`] makes.
#[derive(Clone, Debug)]
pub struct TestAvatar {
    pub config: AvatarConfig,
    /// Raw temporal scales, largest first (one network input block each).
    pub scales: Vec<u32>,
    /// Gaussians, on template vertices (every 97th, cyclically).
    pub gaussians: usize,
    /// Whether the avatar has networks (absent: skinning only).
    pub networks: bool,
    pub seed: u64,
}

impl TestAvatar {
    /// 300 Gaussians, scales `[2, 1]`, with networks, seed 1.
    pub fn new(config: AvatarConfig) -> Self {
        Self {
            config,
            scales: vec![2, 1],
            gaussians: 300,
            networks: true,
            seed: 1,
        }
    }

    /// The avatar on the procedural body (0.05 m skirt); SH coefficients in `[-0.5, 0.5]`,
    /// opacity logits in `[0, 3]`, scales `e^[-3.5, -2.5]`, random rotations; the heads of
    /// the non-rigid and LBS-offset networks in `[-0.05, 0.05]`.
    pub fn build(&self) -> TrainedAvatar {
        let model = procedural_body(0.05);
        let rig = BodyRig::new(model).expect("the procedural body rigs");
        let j = rig.joint_count();
        let mut rng = Rng::new(self.seed);
        let networks = self.networks.then(|| {
            let config = NetworkConfig::from_avatar(&self.config, j, j, self.scales.len())
                .expect("a valid test configuration");
            let mut networks =
                Networks::<f32>::new(&config, self.seed).expect("networks of the configuration");
            for param in networks.parameters_mut() {
                if param.name.starts_with("non_rigid.heads")
                    || param.name.starts_with("lbs_offsets.4")
                {
                    for x in param.values.iter_mut() {
                        *x = rng.uniform(-0.05, 0.05) as f32;
                    }
                }
            }
            networks
        });
        let (n, v) = (self.gaussians, rig.vertex_count());
        let xyz: Vec<f64> = (0..n)
            .flat_map(|i| {
                let k = 3 * ((i * 97) % v);
                rig.canonical_vertices[k..k + 3].to_vec()
            })
            .collect();
        let gaussians = AvatarGaussians {
            xyz,
            sh: (0..n * 48).map(|_| rng.uniform(-0.5, 0.5)).collect(),
            opacity_logit: (0..n).map(|_| rng.uniform(0.0, 3.0)).collect(),
            log_scale: (0..3 * n).map(|_| rng.uniform(-3.5, -2.5)).collect(),
            rotation: (0..4 * n).map(|_| rng.uniform(-1.0, 1.0)).collect(),
        };
        TrainedAvatar::new(
            self.config.clone(),
            rig,
            gaussians,
            self.config.sh_degree,
            self.scales.clone(),
            networks,
        )
    }
}

/// A motion track of `frames` frames for `avatar` (its body, its scales as raw scales and
/// steps) whose values are `value(frame)` everywhere, from the start of the recording.
pub fn uniform_track(
    avatar: &TrainedAvatar,
    frames: usize,
    value: impl Fn(usize) -> f32,
) -> MotionTrack {
    let (j, v, s) = (
        avatar.rig.joint_count(),
        avatar.rig.vertex_count(),
        avatar.scales.len(),
    );
    let fill = |count: usize| -> Vec<f32> {
        (0..frames)
            .flat_map(|f| vec![value(f); s * count * 3])
            .collect()
    };
    MotionTrack {
        num_frames: frames,
        num_joints: j,
        garment_rows: 0,
        num_vertices: v,
        scales: avatar.scales.clone(),
        scale_steps: avatar.scales.iter().map(|&k| k as usize).collect(),
        skeleton_motion: fill(j),
        vertex_velocity: fill(v),
        axis: FrameAxis::FROM_START,
    }
}

/// A motion track of `frames` frames for `avatar` with values uniform in `[-1, 1]`.
pub fn random_track(avatar: &TrainedAvatar, frames: usize, seed: u64) -> MotionTrack {
    let mut track = uniform_track(avatar, frames, |_| 0.0);
    let mut rng = Rng::new(seed);
    for x in track
        .skeleton_motion
        .iter_mut()
        .chain(track.vertex_velocity.iter_mut())
    {
        *x = rng.uniform(-1.0, 1.0) as f32;
    }
    track
}
