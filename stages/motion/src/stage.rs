//! The `motion` stage kind: configuration, run, pictures.
//!
//! Inputs: an `ingest` entry (body model, cameras, frame axis) and optionally a `fit` entry
//! (refined parameters; without one the ingest fits are used).
//!
//! Output: the arrays and attributes of `seqavatar_schema::motion` (its writer, beside their reader).

use anyhow::Context;
use serde::{Deserialize, Serialize};

use seqavatar_core::camera::Camera;
use seqavatar_core::glam::DVec3;
use seqavatar_engine::picture;
use seqavatar_engine::{
    ConfigError, EntryReader, PictureKind, PictureOptions, StageContext, StageKind,
};
use seqavatar_schema::body::BodySequence;
use seqavatar_schema::ingest::{read_body_model, read_frame_interval, read_garment_history};

use seqavatar_context::compute::{canonical_template, compute_motion, effective_velocity};
use seqavatar_schema::motion::{
    FrameAxis, InputScales, InputScaling, MotionEntry, Scales, VelocityNormalisation,
    read_input_scales, write_entry, write_garment_oracle,
};

/// The `motion` stage configuration: only what changes the motion templates.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionConfig {
    /// Every sampling scale any run may ask for, in raw video frames (multiples of the
    /// ingest `frame_interval`). Stored largest first.
    pub scales: Vec<u32>,
    /// How displacements become velocities (`kind: per_scale` or
    /// `kind: reference, multi: 300`).
    pub velocity: VelocityNormalisation,
    /// Neighbours per vertex in the canonical KNN graph (self included).
    pub knn: usize,
    /// How the input blocks are scaled: `rms` (default: each block has RMS 1 on the
    /// sequence), `authors` (velocities x 300 / smallest scale, as the authors' code) or
    /// `none`.
    pub input_scaling: InputScaling,
    /// Whether the entry also holds the garment's true dynamic state (the ingest entry's
    /// `garment_state`: only the synthetic history scene has one), read by every row with
    /// skeleton motion as extra skeleton-motion rows: the ablation's oracle row, the upper
    /// bound of what a perfect motion context could give. Left out of the resolved config
    /// when off, so other entries keep their keys.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub garment_oracle: bool,
}

impl Default for MotionConfig {
    fn default() -> Self {
        Self {
            scales: vec![3, 2, 1],
            velocity: VelocityNormalisation::PerScale,
            knn: 8,
            input_scaling: InputScaling::Rms,
            garment_oracle: false,
        }
    }
}

/// The stage kind.
pub struct MotionStage;

/// Bump whenever the code changes the result.
/// 3: attributes `past_frames` and `starts_recording` (the ingest entry's frame axis).
/// 4: input blocks scaled to RMS 1 by default (`input_scaling`), scale factors recorded.
const VERSION: u32 = 4;

impl StageKind for MotionStage {
    type Config = MotionConfig;

    fn kind(&self) -> &'static str {
        "motion"
    }

    fn version(&self) -> u32 {
        VERSION
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        &["ingest", "fit"]
    }

    fn check_inputs(
        &self,
        _config: &MotionConfig,
        inputs: &[seqavatar_engine::StageInput<'_>],
    ) -> Result<(), String> {
        seqavatar_engine::require_one_input_of_each(inputs, &["ingest"])
    }

    fn resolve_config(&self, raw: &serde_json::Value) -> Result<MotionConfig, ConfigError> {
        let mut config: MotionConfig = seqavatar_engine::parse_config(raw)?;
        // Interval 1 checks everything but divisibility, which needs the ingest entry.
        let scales = Scales::new(&config.scales, 1)
            .map_err(|e| ConfigError::at_key("scales", e.to_string()))?;
        if config.knn == 0 {
            return Err(ConfigError::at_key("knn", "knn must be at least 1"));
        }
        if let VelocityNormalisation::Reference { multi } = config.velocity
            && !(multi.is_finite() && multi > 0.0)
        {
            return Err(ConfigError::at_key(
                "velocity",
                format!("multi = {multi} must be positive and finite"),
            ));
        }
        if config.input_scaling == InputScaling::Authors
            && matches!(config.velocity, VelocityNormalisation::Reference { .. })
        {
            return Err(ConfigError::at_key(
                "input_scaling",
                "input_scaling: authors applies the reference velocity normalisation itself; leave `velocity` at per_scale",
            ));
        }
        // Canonical order (largest first) so [1, 2, 3] and [3, 2, 1] share a key.
        config.scales = scales.raw;
        Ok(config)
    }

    fn run(&self, config: &MotionConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        let ingest = ctx.input("ingest")?.clone();
        let fit = ctx.inputs().iter().find(|i| i.kind() == "fit").cloned();
        let params_entry = fit.as_ref().unwrap_or(&ingest);
        let interval = read_frame_interval(&ingest)?;
        let scales = Scales::new(&config.scales, interval)
            .with_context(|| format!("config `scales` against entry {}", ingest.location()))?;
        let model = read_body_model(&ingest)?;
        let sequence = BodySequence::read(params_entry, "body")?;
        // The oracle's input is checked before anything is computed.
        let garment_states = if config.garment_oracle {
            let history = read_garment_history(&ingest)?.ok_or_else(|| {
                anyhow::anyhow!(
                    "config `garment_oracle`: entry {} has no `garment_state` (only the synthetic \
                     history scene, `dataset.scene: history`, knows its garment's state)",
                    ingest.location()
                )
            })?;
            anyhow::ensure!(
                history.states.len() == sequence.num_frames,
                "entry {}: `garment_state` has {} frames, the body parameters {}",
                ingest.location(),
                history.states.len(),
                sequence.num_frames
            );
            Some(history.states)
        } else {
            None
        };
        let started = std::time::Instant::now();
        let velocity = effective_velocity(config.input_scaling, config.velocity);
        let mut motion = compute_motion(&model, &sequence, &scales, velocity)
            .with_context(|| format!("posing the fits of entry {}", params_entry.location()))?;
        let input_scales = InputScales::for_scaling(config.input_scaling, &motion, scales.len());
        motion.scale_inputs(&input_scales);
        ctx.log(&format!(
            "input scaling {:?}: skeleton motion x {:?}, vertex velocity x {:?} (scales {:?})",
            config.input_scaling,
            input_scales.skeleton_motion,
            input_scales.vertex_velocity,
            scales.raw
        ));
        let (canonical, graph) = canonical_template(&model, config.knn)?;
        let seconds = started.elapsed().as_secs_f64();
        ctx.log(&format!(
            "motion templates for {} frames x {} vertices x {} scales in {:.2} s ({:.2} ms per frame)",
            motion.num_frames,
            motion.num_vertices,
            scales.len(),
            seconds,
            1e3 * seconds / motion.num_frames.max(1) as f64
        ));

        write_entry(
            ctx.output(),
            &ingest,
            &MotionEntry {
                motion: &motion,
                scales: &scales,
                canonical: &canonical,
                graph: &graph,
                frame_interval: interval,
                velocity,
                input_scaling: config.input_scaling,
                input_scales: &input_scales,
                axis: FrameAxis::of_ingest(&ingest)?,
            },
        )?;
        if let Some(states) = &garment_states {
            write_garment_oracle(ctx.output(), states, scales.len())?;
            ctx.log("garment oracle: the true garment state appended to the skeleton motion");
        }
        Ok(())
    }

    fn pictures(&self) -> Vec<PictureKind> {
        vec![
            PictureKind {
                name: "speed",
                description: "posed template seen from a dataset camera, coloured by vertex speed, with a colour bar; options: frame, scale (raw frames), view, max (speed at the top of the bar), radius",
            },
            PictureKind {
                name: "skeleton_motion",
                description: "per-joint skeleton-motion magnitude (radians) over frames, one line per joint; options: scale (raw frames), width, height",
            },
        ]
    }

    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        match picture {
            "speed" => draw_speed(entry, options),
            "skeleton_motion" => draw_skeleton_motion(entry, options),
            _ => Err(seqavatar_engine::unknown_picture(self, picture)),
        }
    }
}

/// The scale slot of a raw scale given as a picture option (default: the smallest scale).
fn scale_slot(entry: &EntryReader, options: &PictureOptions) -> anyhow::Result<(usize, u32)> {
    let scales = entry.read::<u32>("scales")?.data;
    anyhow::ensure!(
        !scales.is_empty(),
        "entry {}: `scales` is empty",
        entry.location()
    );
    let smallest = *scales.iter().min().expect("non-empty");
    let wanted = options.get_u64("scale", u64::from(smallest))?;
    let slot = scales
        .iter()
        .position(|&s| u64::from(s) == wanted)
        .ok_or_else(|| {
            anyhow::anyhow!("picture option scale={wanted}: the entry has scales {scales:?}")
        })?;
    Ok((slot, scales[slot]))
}

fn draw_speed(entry: &EntryReader, options: &PictureOptions) -> anyhow::Result<image::RgbImage> {
    let unknown = options.unknown_keys(&["frame", "scale", "view", "max", "radius"]);
    anyhow::ensure!(
        unknown.is_empty(),
        "picture speed: unknown options {unknown:?}"
    );
    let shape = entry.shape("posed_vertices")?;
    let (num_frames, num_vertices) = (shape[0], shape[1]);
    anyhow::ensure!(num_frames > 0, "entry {}: no frames", entry.location());
    let frame = options.get_u64("frame", num_frames / 2)?;
    anyhow::ensure!(
        frame < num_frames,
        "picture option frame={frame}: the entry has {num_frames} frames"
    );
    let (slot, _) = scale_slot(entry, options)?;
    let view = options.get_u64("view", 0)? as usize;
    let radius = options.get_u64("radius", 2)?.min(20) as i64;
    let posed = entry
        .read_region::<f32>("posed_vertices", &[frame, 0, 0], &[1, num_vertices, 3])?
        .data;
    let velocity = entry
        .read_region::<f32>(
            "vertex_velocity",
            &[frame, slot as u64, 0, 0],
            &[1, 1, num_vertices, 3],
        )?
        .data;
    // In the units of the velocity normalisation (the input scaling undone).
    let factor = read_input_scales(entry)?.1.vertex_velocity[slot];
    let speeds: Vec<f64> = velocity
        .chunks_exact(3)
        .map(|c| {
            f64::from(c[0])
                .hypot(f64::from(c[1]))
                .hypot(f64::from(c[2]))
                / factor
        })
        .collect();
    let auto_max = speeds.iter().copied().fold(0.0_f64, f64::max);
    let max = options.get_f64("max", auto_max)?.max(1e-12);
    let camera = read_camera(entry, view)?;
    let bar = 70;
    let mut img = image::RgbImage::from_pixel(camera.width + bar, camera.height, picture::WHITE);
    let points: Vec<(f64, f64, f64, image::Rgb<u8>)> = posed
        .chunks_exact(3)
        .zip(&speeds)
        .filter_map(|(p, &speed)| {
            let world = DVec3::new(f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
            let pixel = camera.project(world)?;
            let depth = camera.world_to_camera(world).z;
            Some((pixel.x, pixel.y, depth, picture::colour_map(speed / max)))
        })
        .collect();
    picture::splat_points(&mut img, &points, radius);
    let (w, h) = (i64::from(camera.width), i64::from(camera.height));
    picture::colour_bar(&mut img, w + 10, 20, 16, (h - 40).max(10), 0.0, max);
    Ok(img)
}

fn read_camera(entry: &EntryReader, view: usize) -> anyhow::Result<Camera> {
    let mut cameras = seqavatar_schema::ingest::read_cameras(entry)?;
    let views = cameras.len();
    anyhow::ensure!(
        view < views,
        "picture option view={view}: the entry has {views} views"
    );
    Ok(cameras.swap_remove(view))
}

fn draw_skeleton_motion(
    entry: &EntryReader,
    options: &PictureOptions,
) -> anyhow::Result<image::RgbImage> {
    let unknown = options.unknown_keys(&["scale", "width", "height"]);
    anyhow::ensure!(
        unknown.is_empty(),
        "picture skeleton_motion: unknown options {unknown:?}"
    );
    let (slot, _) = scale_slot(entry, options)?;
    let motion = entry.read::<f32>("skeleton_motion")?;
    let (f, s, j) = (motion.shape[0], motion.shape[1], motion.shape[2]);
    let series: Vec<Vec<f64>> = (0..j)
        .map(|joint| {
            (0..f)
                .map(|t| {
                    let at = ((t * s + slot) * j + joint) * 3;
                    let c = &motion.data[at..at + 3];
                    f64::from(c[0])
                        .hypot(f64::from(c[1]))
                        .hypot(f64::from(c[2]))
                })
                .collect()
        })
        .collect();
    let width = options.get_u64("width", 900)?.clamp(64, 8192) as u32;
    let height = options.get_u64("height", 400)?.clamp(48, 8192) as u32;
    Ok(picture::line_plot(width, height, &series))
}
