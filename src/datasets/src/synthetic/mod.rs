//! The built-in synthetic dataset: the procedural body wearing a simulated skirt, walking,
//! turning, stopping and starting again, rendered from a ring of cameras by a software
//! rasterizer. Ground-truth body parameters are known exactly; the "fitted" parameters are a
//! jittered copy.
//!
//! - [`motion`]: the scripted motion (pose, heading and path over time).
//! - [`history`]: the history scene's script (`scene: history`): poses of an integer gait
//!   phase visited at different speeds, holds, turns and restarts.
//! - [`garment`]: the skirt and its damped mass-spring simulation (position based), and the
//!   history scene's skirt, a damped pendulum driven by the body's motion.
//! - [`raster`]: the z-buffered, perspective-correct triangle rasterizer.
//! - [`scene`]: the whole scene: cameras, textures, shading, the per-camera backdrops, the
//!   [`DatasetReader`] impl.
//!
//! [`DatasetReader`]: crate::DatasetReader

pub mod garment;
pub mod history;
pub mod motion;
pub mod raster;
mod rng;
pub mod scene;

use serde::{Deserialize, Serialize};

pub use scene::SyntheticScene;

/// Noise added to the ground-truth body parameters to play the role of a body fit.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct JitterConfig {
    /// Standard deviation of each axis-angle component of every joint (radians).
    pub pose_radians: f64,
    /// Standard deviation of each translation component (metres).
    pub translation_metres: f64,
    /// Standard deviation added to the (per-subject) shape coefficients, once.
    pub betas: f64,
    /// Standard deviation of each coordinate of the 3D keypoints (metres): the ground-truth
    /// joint positions plus this noise, from a random stream separate from the fit jitter.
    pub keypoints_metres: f64,
}

impl Default for JitterConfig {
    fn default() -> Self {
        Self {
            pose_radians: 0.03,
            translation_metres: 0.01,
            betas: 0.05,
            keypoints_metres: 0.01,
        }
    }
}

/// What the cameras see behind the person.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SyntheticBackground {
    /// A textured backdrop per camera (seeded): colour gradient, tiles and stripes, as real
    /// captures have a background that training must not learn.
    Textured,
    /// Black (the images are then the person premultiplied by its coverage).
    Black,
}

/// Which motion script and garment the synthetic scene uses.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SceneKind {
    /// Walk, turn, stop and go again, scripted in fractions of the sequence, with the
    /// mass-spring skirt (the demo's scene).
    #[default]
    Walk,
    /// The history scene ([`history`]): exact poses recur under different histories, and the
    /// skirt is a damped pendulum driven by the body ([`garment::Swing`]), so the garment
    /// shows what the pose alone cannot explain. Needs `fps: 30` and at most
    /// [`history::LENGTH`] frames. The ingest entry then stores the garment's
    /// history-only displacement per frame.
    History,
}

fn is_true(value: &bool) -> bool {
    *value
}

/// Stripes around the skirt unless the config says otherwise.
pub const DEFAULT_SKIRT_STRIPES: u32 = 24;

fn is_default_stripes(value: &u32) -> bool {
    *value == DEFAULT_SKIRT_STRIPES
}

impl SceneKind {
    fn is_walk(&self) -> bool {
        *self == Self::Walk
    }
}

/// Sizes and settings of the synthetic scene (`dataset: {kind: synthetic, ...}`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SyntheticConfig {
    /// The motion script and garment (`walk`, the default, or `history`). Left out of the
    /// resolved config when `walk`, so the demo's ingest keys stay what they were.
    #[serde(skip_serializing_if = "SceneKind::is_walk")]
    pub scene: SceneKind,
    /// Number of cameras on the ring around the subject.
    pub cameras: usize,
    /// Number of frames of the sequence.
    pub frames: usize,
    /// Frames per second (the motion script's clock).
    pub fps: f64,
    /// Rendered image size in pixels.
    pub width: u32,
    pub height: u32,
    /// Samples per pixel along each axis (2 = 4 samples per pixel); masks are the coverage.
    pub supersample: u32,
    /// Horizontal distance of the cameras from the centre of the walk (metres).
    pub camera_distance: f64,
    /// Body shape (height, girth).
    pub betas: [f64; 2],
    /// Grid spacing of the procedural body surface (metres).
    pub body_grid_spacing: f64,
    /// Whether the subject wears the simulated skirt.
    pub garment: bool,
    /// History scene: whether the skirt swings (its oscillator driven by the body's motion).
    /// `false` keeps it in its static drape, carried by the pose alone: the control that
    /// separates what the deformation model cannot do from what only history explains. Left
    /// out of the resolved config when `true`, so existing keys stay.
    #[serde(skip_serializing_if = "is_true")]
    pub garment_swing: bool,
    /// Red and white stripes around the skirt (even, 2..=96). The default 24 are 6-7 cm
    /// wide, narrower than the history scene's swing; fewer, wider stripes make a texture
    /// whose photometric error does not alias a displacement of a few stripes' width onto
    /// the neighbouring stripe. Left out of the resolved config when 24.
    #[serde(skip_serializing_if = "is_default_stripes")]
    pub skirt_stripes: u32,
    /// The backdrop behind the person (`textured` or `black`); masks are the person's
    /// coverage either way.
    pub background: SyntheticBackground,
    pub jitter: JitterConfig,
    /// Seed of the jitter and of the camera ring's irregularities.
    pub seed: u64,
    /// Where the scene stands in its world (metres): the cameras, body fits, ground truth,
    /// keypoints and garment the reader hands out are moved by it, the images are the same
    /// (they are rendered at the origin). A far-away world for tests of numerical
    /// stability; left out of the resolved config when zero, so existing keys stay.
    #[serde(skip_serializing_if = "is_zero")]
    pub origin: [f64; 3],
}

fn is_zero(value: &[f64; 3]) -> bool {
    *value == [0.0; 3]
}

impl Default for SyntheticConfig {
    fn default() -> Self {
        Self {
            scene: SceneKind::Walk,
            cameras: 8,
            frames: 48,
            fps: 15.0,
            width: 256,
            height: 256,
            supersample: 2,
            camera_distance: 4.0,
            betas: [0.3, -0.2],
            body_grid_spacing: seqavatar_core::body::procedural::DEFAULT_GRID_SPACING,
            garment: true,
            garment_swing: true,
            skirt_stripes: DEFAULT_SKIRT_STRIPES,
            background: SyntheticBackground::Textured,
            jitter: JitterConfig::default(),
            seed: 7,
            origin: [0.0; 3],
        }
    }
}

/// The farthest `camera_distance`, in metres: at 1 km an f32 depth still resolves 0.1 mm.
const MAX_CAMERA_DISTANCE: f64 = 1000.0;
/// The farthest `origin` on each axis, in metres: about the Earth's radius, as geographic
/// coordinates can be.
const MAX_ORIGIN: f64 = 1e7;
/// Bytes per supersample of the rasteriser's visibility buffer (triangle, barycentrics,
/// depth).
const VISIBILITY_BYTES_PER_SAMPLE: u64 = 4 + 12 + 4;
/// Bytes per output pixel in flight while a view is rendered and stored (RGB and mask, and
/// their encoded chunks).
const IMAGE_BYTES_PER_PIXEL: u64 = 2 * (3 + 1);
/// Bytes the ingest plan and the entry's per-image records hold per (camera, frame) image.
const BYTES_PER_IMAGE: u64 = 64;
/// Bytes of simulated state kept per frame (body parameters, garment particles): an upper
/// bound for the procedural body at the finest grid spacing.
const STATE_BYTES_PER_FRAME: u64 = 64 << 10;

impl SyntheticConfig {
    /// The memory generating this scene is estimated to need at its peak: one visibility
    /// buffer of `width x height x supersample^2` samples and one image per rendering
    /// thread, records per camera and frame, and the per-frame simulation state.
    pub fn memory_estimate_bytes(&self) -> u64 {
        let threads = rayon::current_num_threads() as u64;
        let pixels = u64::from(self.width) * u64::from(self.height);
        let samples = pixels * u64::from(self.supersample).pow(2);
        let per_render = samples
            .saturating_mul(VISIBILITY_BYTES_PER_SAMPLE)
            .saturating_add(pixels.saturating_mul(IMAGE_BYTES_PER_PIXEL));
        let images = (self.cameras as u64).saturating_mul(self.frames as u64);
        threads
            .saturating_mul(per_render)
            .saturating_add(images.saturating_mul(BYTES_PER_IMAGE))
            .saturating_add((self.frames as u64).saturating_mul(STATE_BYTES_PER_FRAME))
    }

    /// Refuses a scene whose [`Self::memory_estimate_bytes`] exceeds `budget` bytes, naming
    /// the fields that make it large.
    pub fn check_memory(&self, budget: u64) -> anyhow::Result<()> {
        let estimate = self.memory_estimate_bytes();
        anyhow::ensure!(
            estimate <= budget,
            "dataset.width x dataset.height x dataset.supersample^2 ({} x {} x {}^2 samples \
             per view, {} rendering threads) and dataset.cameras x dataset.frames ({} x {}) \
             need about {:.1} GB, over the memory budget of {:.1} GB (set {} to raise it)",
            self.width,
            self.height,
            self.supersample,
            rayon::current_num_threads(),
            self.cameras,
            self.frames,
            estimate as f64 / 1e9,
            budget as f64 / 1e9,
            seqavatar_engine::MEMORY_BUDGET_VAR
        );
        Ok(())
    }

    /// Checks ranges, then the memory estimate against the memory budget
    /// ([`seqavatar_engine::memory_budget_bytes`]); errors name the config field.
    pub fn validate(&self) -> anyhow::Result<()> {
        self.validate_ranges()?;
        if let Some(budget) = seqavatar_engine::memory_budget_bytes().map_err(anyhow::Error::msg)? {
            self.check_memory(budget)?;
        }
        Ok(())
    }

    /// Checks ranges; errors name the config field.
    fn validate_ranges(&self) -> anyhow::Result<()> {
        anyhow::ensure!(self.cameras >= 1, "dataset.cameras must be at least 1");
        anyhow::ensure!(self.frames >= 1, "dataset.frames must be at least 1");
        anyhow::ensure!(
            self.fps.is_finite() && self.fps > 0.0,
            "dataset.fps must be positive"
        );
        anyhow::ensure!(
            (8..=8192).contains(&self.width) && (8..=8192).contains(&self.height),
            "dataset.width and dataset.height must be within 8..8192 pixels"
        );
        anyhow::ensure!(
            (1..=8).contains(&self.supersample),
            "dataset.supersample must be within 1..8"
        );
        anyhow::ensure!(
            !self.camera_distance.is_nan(),
            "dataset.camera_distance is not a number"
        );
        anyhow::ensure!(
            self.camera_distance >= 2.0,
            "dataset.camera_distance = {} is too close to the subject: it must be at least 2 \
             metres",
            self.camera_distance
        );
        // Farther, the f32 camera coordinates the renderers use no longer resolve the
        // subject's depth (and by 1e155 the f64 projection overflows to infinity).
        anyhow::ensure!(
            self.camera_distance <= MAX_CAMERA_DISTANCE,
            "dataset.camera_distance = {} is too far from the subject: it must be at most \
             {MAX_CAMERA_DISTANCE} metres, beyond which its projection loses precision and then \
             is not finite",
            self.camera_distance
        );
        anyhow::ensure!(
            self.origin
                .iter()
                .all(|x| x.is_finite() && x.abs() <= MAX_ORIGIN),
            "dataset.origin must be finite and within {MAX_ORIGIN} metres of zero on each axis"
        );
        anyhow::ensure!(
            self.betas.iter().all(|b| b.is_finite() && b.abs() <= 3.0),
            "dataset.betas must be within -3..3"
        );
        anyhow::ensure!(
            (0.005..=0.05).contains(&self.body_grid_spacing),
            "dataset.body_grid_spacing must be within 0.005..0.05 metres"
        );
        anyhow::ensure!(
            (2..=96).contains(&self.skirt_stripes) && self.skirt_stripes.is_multiple_of(2),
            "dataset.skirt_stripes = {} must be even and within 2..96",
            self.skirt_stripes
        );
        anyhow::ensure!(
            self.garment_swing || self.scene == SceneKind::History,
            "dataset.garment_swing = false needs scene: history (the walk's skirt is a cloth \
             simulation)"
        );
        if self.scene == SceneKind::History {
            anyhow::ensure!(
                self.fps == history::FPS,
                "dataset.fps must be {} for scene: history (its script is written in frames at \
                 that rate)",
                history::FPS
            );
            anyhow::ensure!(
                self.frames <= history::LENGTH,
                "dataset.frames must be at most {} for scene: history (the script's length)",
                history::LENGTH
            );
        }
        let j = &self.jitter;
        anyhow::ensure!(
            [
                j.pose_radians,
                j.translation_metres,
                j.betas,
                j.keypoints_metres
            ]
            .iter()
            .all(|x| x.is_finite() && *x >= 0.0 && *x <= 1.0),
            "dataset.jitter values must be within 0..1"
        );
        Ok(())
    }
}

#[cfg(test)]
mod memory_tests {
    use super::*;

    /// 4096 x 4096 at 8 x 8 samples per pixel passes the range checks but would need tens
    /// of GB per rendering thread: refused at once, from the config alone, naming the fields.
    #[test]
    fn a_scene_over_the_memory_budget_is_refused_before_any_work() {
        let config = SyntheticConfig {
            width: 4096,
            height: 4096,
            supersample: 8,
            ..SyntheticConfig::default()
        };
        config.validate_ranges().unwrap();
        let start = std::time::Instant::now();
        let error = config.check_memory(16 << 30).unwrap_err().to_string();
        assert!(start.elapsed() < std::time::Duration::from_secs(1));
        for field in [
            "dataset.width",
            "dataset.supersample",
            "SEQAVATAR_MEMORY_BUDGET",
        ] {
            assert!(error.contains(field), "{error}");
        }
        assert!(config.memory_estimate_bytes() > 4096 * 4096 * 64 * 20);
        // Cameras x frames count too.
        let many = SyntheticConfig {
            cameras: 1024,
            frames: 100_000,
            ..SyntheticConfig::default()
        };
        let error = many.check_memory(4 << 30).unwrap_err().to_string();
        assert!(
            error.contains("dataset.cameras x dataset.frames"),
            "{error}"
        );
        // The demo's scene fits a small budget.
        SyntheticConfig::default().check_memory(1 << 30).unwrap();
    }

    /// A huge or non-finite camera distance once said "too close to the subject".
    #[test]
    fn camera_distances_and_origins_out_of_range_say_which_way() {
        for (distance, says) in [
            (1e308, "too far"),
            (f64::INFINITY, "too far"),
            (1001.0, "too far"),
            (1.0, "too close"),
            (f64::NAN, "not a number"),
        ] {
            let config = SyntheticConfig {
                camera_distance: distance,
                ..SyntheticConfig::default()
            };
            let error = config.validate_ranges().unwrap_err().to_string();
            assert!(
                error.contains("dataset.camera_distance") && error.contains(says),
                "{distance}: {error}"
            );
        }
        // The scene's place in its world: anywhere finite within the Earth's radius.
        for (origin, good) in [
            ([1e4, -3.0, 1e4], true),
            ([0.0, 0.0, -MAX_ORIGIN], true),
            ([2e7, 0.0, 0.0], false),
            ([0.0, f64::NAN, 0.0], false),
        ] {
            let checked = SyntheticConfig {
                origin,
                ..SyntheticConfig::default()
            }
            .validate_ranges();
            assert_eq!(checked.is_ok(), good, "{origin:?}: {checked:?}");
            if let Err(error) = checked {
                assert!(error.to_string().contains("dataset.origin"), "{error}");
            }
        }
        for distance in [2.0, MAX_CAMERA_DISTANCE] {
            SyntheticConfig {
                camera_distance: distance,
                ..SyntheticConfig::default()
            }
            .validate_ranges()
            .unwrap();
        }
    }
}
