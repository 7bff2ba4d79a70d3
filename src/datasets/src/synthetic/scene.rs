//! The synthetic scene: body, motion, garment simulation, cameras, textures and shading,
//! exposed as a [`DatasetReader`].
//!
//! World: metres, y up, the floor at y = 0, the walk centred on the origin. Cameras stand on
//! a ring (irregular by a few degrees and centimetres, seeded) looking at the subject's
//! centre; each camera's focal length is the largest that keeps the whole sequence inside
//! its image, and its principal point is off-centre by up to two pixels.
//!
//! Appearance: the body's albedo is a colour per body region times a 3D checkerboard and
//! stripes of a few centimetres evaluated at the rest-pose (template) position of the
//! surface point, so the texture moves with the skin and has detail at the pixel scale; the
//! skirt has stripes and bands in its own coordinates. Shading is Lambertian with one
//! directional light plus ambient; both sides of the skirt are lit.
//!
//! Background: each camera sees its own textured backdrop ([`Backdrop`], seeded per camera)
//! behind the person, or black (`background: black`). The masks are the person's coverage
//! of each pixel either way, so a pixel is `m F + (1 - m) B` for foreground colour `F`,
//! backdrop colour `B` and mask `m`.

use seqavatar_core::body::procedural::{self, procedural_body};
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::{Camera, Intrinsics};
use seqavatar_core::glam::{DAffine3, DVec2, DVec3};

use super::garment::{self, Skirt, Swing, SwingParams};
use super::history::{self, MonotoneCubic, path_sample};
use super::motion::sample_script;
use super::raster::{EMPTY, rasterize};
use super::rng::Rng;
use super::{SceneKind, SyntheticBackground, SyntheticConfig};
use crate::{
    BodyModelKind, DatasetReader, GARMENT_STATE_COMPONENTS, GarmentHistory, GarmentRegion,
    Keypoints3d, SourceCamera, SourceImage, Split,
};

/// Garment simulation rate (substeps per second).
const SIMULATION_RATE: f64 = 240.0;
/// Seconds simulated standing still before the first frame, so the skirt settles.
const WARMUP_SECONDS: f64 = 2.0;
/// Mixed into the seed for the keypoint noise, so adding keypoints leaves the fit jitter and
/// the camera ring of a seed unchanged.
const KEYPOINT_STREAM: u64 = 0x6b65_7970_6f69_6e74;
/// Mixed into the seed for the backdrops, so they leave the other streams of a seed unchanged.
const BACKDROP_STREAM: u64 = 0x6261_636b_6472_6f70;
/// Direction towards the light.
const LIGHT: DVec3 = DVec3::new(0.35, 0.85, 0.4);

/// A generated synthetic sequence. Images are rendered on demand by
/// [`DatasetReader::read_image`].
pub struct SyntheticScene {
    config: SyntheticConfig,
    model: BodyModel,
    /// The cameras the images are rendered with, at the origin.
    render_cameras: Vec<SourceCamera>,
    /// The cameras the reader hands out: `render_cameras` in the world of `config.origin`.
    cameras: Vec<SourceCamera>,
    ground_truth: Vec<BodyParams>,
    jittered: Vec<BodyParams>,
    /// Per frame, the skirt particle positions (empty without a garment).
    skirt: Vec<Vec<DVec3>>,
    /// History scene: per frame, the skirt's static drape (its oscillator at rest).
    drapes: Vec<Vec<DVec3>>,
    /// History scene: per frame, the oscillator's state in the body's heading frame.
    garment_states: Vec<[f64; GARMENT_STATE_COMPONENTS]>,
    skirt_triangles: Vec<[u32; 3]>,
    skirt_texture: Vec<DVec3>,
    /// Per body vertex: albedo region colour.
    body_colour: Vec<DVec3>,
    /// `(frame, joint)` noisy ground-truth joint positions (the 3D keypoints).
    keypoints: Vec<DVec3>,
    /// One per camera with a textured background; empty for a black one.
    backdrops: Vec<Backdrop>,
}

/// What one camera sees behind the person, in image coordinates: a vertical gradient between
/// two colours, tiles of a random size and orientation tinted in a third, and faint stripes.
/// Every parameter is drawn per camera, so no two cameras share a background.
#[derive(Clone, Debug, PartialEq)]
pub struct Backdrop {
    height: f64,
    top: DVec3,
    bottom: DVec3,
    /// Factor on the gradient colour of every other tile.
    tint: DVec3,
    /// Tile side, pixels.
    cell: f64,
    /// Tile grid direction (unit) and offset in cells.
    direction: DVec2,
    offset: DVec2,
    /// Stripe wave vector (radians per pixel) and amplitude.
    stripes: DVec2,
    stripe_amplitude: f64,
}

impl Backdrop {
    /// A backdrop for a `width x height` image drawn from `rng`.
    pub fn new(rng: &mut Rng, width: u32, height: u32) -> Self {
        let mut colour = |lo: f64, hi: f64| {
            DVec3::new(
                rng.uniform(lo, hi),
                rng.uniform(lo, hi),
                rng.uniform(lo, hi),
            )
        };
        let top = colour(0.15, 0.9);
        let bottom = colour(0.1, 0.8);
        let tint = colour(0.45, 0.8);
        let size = f64::from(width.min(height));
        let cell = size * rng.uniform(0.04, 0.1);
        let angle = rng.uniform(0.0, std::f64::consts::FRAC_PI_2);
        let offset = DVec2::new(rng.next_f64(), rng.next_f64());
        let stripe_angle = rng.uniform(0.0, std::f64::consts::PI);
        let period = size * rng.uniform(0.02, 0.05);
        Self {
            height: f64::from(height),
            top,
            bottom,
            tint,
            cell,
            direction: DVec2::new(angle.cos(), angle.sin()),
            offset,
            stripes: DVec2::new(stripe_angle.cos(), stripe_angle.sin()) * std::f64::consts::TAU
                / period,
            stripe_amplitude: rng.uniform(0.03, 0.08),
        }
    }

    /// Linear colour in `[0, 1]` at the continuous image point `(x, y)` (pixels).
    pub fn colour(&self, x: f64, y: f64) -> DVec3 {
        let point = DVec2::new(x, y);
        let gradient = self
            .top
            .lerp(self.bottom, (y / self.height).clamp(0.0, 1.0));
        let along = point.dot(self.direction) / self.cell + self.offset.x;
        let across = point.perp_dot(self.direction) / self.cell + self.offset.y;
        let odd = (along.floor() + across.floor()).rem_euclid(2.0) == 1.0;
        let tiled = if odd { gradient * self.tint } else { gradient };
        let stripe = self.stripe_amplitude * point.dot(self.stripes).sin();
        (tiled + DVec3::splat(stripe)).clamp(DVec3::ZERO, DVec3::ONE)
    }
}

/// What a scene's motion produces, per frame.
struct SceneSequence {
    /// The true body fits.
    ground_truth: Vec<BodyParams>,
    /// Skirt particle positions (empty without a garment).
    skirt_frames: Vec<Vec<DVec3>>,
    /// The skirt's static drape (history scene only, else empty).
    drapes: Vec<Vec<DVec3>>,
    /// The skirt's oscillator state in the body's heading frame (history scene only).
    garment_states: Vec<[f64; GARMENT_STATE_COMPONENTS]>,
}

/// Per-frame ground truth, simulated skirt and its static drape of the history scene
/// ([`history`]): the script's poses, the heading as the world rotation, the path integrated
/// from the interpolated speed and heading at the simulation rate, and the skirt's
/// oscillator ([`Swing`]) stepped by the same samples, starting at rest (the script starts
/// with a hold).
fn history_sequence(
    config: &SyntheticConfig,
    model: &BodyModel,
    shaped: &[DVec3],
    rest_joints: &[DVec3],
    pelvis_height: f64,
) -> anyhow::Result<SceneSequence> {
    let (phases, headings) = history::frame_values();
    let n = config.frames;
    let phase_curve = MonotoneCubic::new(&phases.iter().map(|&p| p as f64).collect::<Vec<_>>());
    let heading_curve = MonotoneCubic::new(&headings);
    let substeps = (SIMULATION_RATE / history::FPS).round() as usize;
    let dt = 1.0 / (history::FPS * substeps as f64);
    let swing_params = SwingParams::HISTORY;
    let mut swing = Swing::default();
    let mut position = DVec2::ZERO;
    let mut positions = vec![position];
    let mut states = vec![swing];
    for frame in 1..n {
        for sub in 0..substeps {
            let t = (frame - 1) as f64 + (sub as f64 + 0.5) / substeps as f64;
            let sample = path_sample(&phase_curve, &heading_curve, t);
            position += sample.velocity * dt;
            if !config.garment_swing {
                continue;
            }
            swing.step(
                &swing_params,
                sample.velocity,
                sample.acceleration,
                sample.heading_acceleration,
                dt,
            );
        }
        positions.push(position);
        states.push(swing);
    }
    let (lo, hi) = positions
        .iter()
        .fold((DVec2::MAX, DVec2::MIN), |(l, h), p| (l.min(*p), h.max(*p)));
    let centre = (lo + hi) * 0.5;
    let ground_truth: Vec<BodyParams> = (0..n)
        .map(|k| {
            let rotation = DVec3::new(0.0, headings[k], 0.0);
            let pelvis = DVec3::new(
                positions[k].x - centre.x,
                pelvis_height + history::bob(phases[k]),
                positions[k].y - centre.y,
            );
            BodyParams {
                pose: history::gait_pose(phases[k]),
                betas: config.betas.to_vec(),
                expression: Vec::new(),
                world_rotation: rotation,
                world_translation: pelvis
                    - seqavatar_core::rotation::axis_angle_to_matrix(rotation) * rest_joints[0],
            }
        })
        .collect();
    if !config.garment {
        return Ok(SceneSequence {
            ground_truth,
            skirt_frames: Vec::new(),
            drapes: Vec::new(),
            garment_states: Vec::new(),
        });
    }
    let scale = 1.0 + procedural::HEIGHT_PER_BETA * config.betas[0];
    let skirt = Skirt::new(model, shaped, scale);
    let (simulated, drapes) = ground_truth
        .iter()
        .zip(&states)
        .map(|(params, state)| {
            let transforms = model.joint_transforms(rest_joints, &params.pose);
            let world = DAffine3::from_mat3_translation(
                seqavatar_core::rotation::axis_angle_to_matrix(params.world_rotation),
                params.world_translation,
            );
            let drape = skirt.carried(&transforms, world);
            (state.apply(&swing_params, &drape), drape)
        })
        .unzip();
    let garment_states = states
        .iter()
        .zip(&headings)
        .map(|(state, &heading)| state.in_body_frame(heading))
        .collect();
    Ok(SceneSequence {
        ground_truth,
        skirt_frames: simulated,
        drapes,
        garment_states,
    })
}

/// The albedo region colour of a body vertex from its dominant joint.
fn region_colour(joint: usize) -> DVec3 {
    match joint {
        12 | 15 | 20..=23 => DVec3::new(0.85, 0.64, 0.52), // skin: neck, head, hands
        1 | 2 | 4 | 5 => DVec3::new(0.25, 0.35, 0.75),     // legs
        7 | 8 | 10 | 11 => DVec3::new(0.2, 0.2, 0.2),      // shoes
        _ => DVec3::new(0.9, 0.75, 0.2),                   // shirt
    }
}

/// High-frequency pattern on the body: 3 cm checkerboard in rest space and 1 cm stripes.
fn body_pattern(rest: DVec3) -> f64 {
    let cell = 0.03;
    let checker = ((rest.x / cell).floor() + (rest.y / cell).floor() + (rest.z / cell).floor())
        .rem_euclid(2.0);
    let stripe = ((rest.x + rest.y + rest.z) / 0.01).floor().rem_euclid(3.0) == 0.0;
    0.55 + 0.35 * checker + if stripe { 0.1 } else { 0.0 }
}

/// Skirt albedo from its (around, down) coordinates: `stripes` stripes around, bands down.
fn skirt_albedo(tc: DVec3, stripes: u32) -> DVec3 {
    let stripe = (tc.x * f64::from(stripes)).floor().rem_euclid(2.0) == 0.0;
    let band = (tc.y * 9.0).floor().rem_euclid(3.0) == 0.0;
    let base = if stripe {
        DVec3::new(0.8, 0.1, 0.15)
    } else {
        DVec3::new(0.95, 0.95, 0.9)
    };
    if band { base * 0.45 } else { base }
}

fn vertex_normals(positions: &[DVec3], triangles: &[[u32; 3]]) -> Vec<DVec3> {
    let mut normals = vec![DVec3::ZERO; positions.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| positions[i as usize]);
        let n = (b - a).cross(c - a);
        for &i in t {
            normals[i as usize] += n;
        }
    }
    normals.iter().map(|n| n.normalize_or_zero()).collect()
}

fn jitter(
    params: &BodyParams,
    config: &super::JitterConfig,
    rng: &mut Rng,
    betas: &[f64],
) -> BodyParams {
    BodyParams {
        pose: params
            .pose
            .iter()
            .map(|p| {
                *p + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * config.pose_radians
            })
            .collect(),
        betas: betas.to_vec(),
        expression: Vec::new(),
        world_rotation: params.world_rotation,
        world_translation: params.world_translation
            + DVec3::new(rng.normal(), rng.normal(), rng.normal()) * config.translation_metres,
    }
}

/// The walk scene: ground-truth fits sampled from the motion script at each frame, and (with
/// a garment) the skirt simulated over every substep and recorded at the frames; no drapes.
fn walk_sequence(
    config: &SyntheticConfig,
    model: &BodyModel,
    shaped: &[DVec3],
    rest_joints: &[DVec3],
    pelvis_height: f64,
) -> anyhow::Result<SceneSequence> {
    let duration = config.frames as f64 / config.fps;
    let dt = 1.0 / SIMULATION_RATE;
    let samples = sample_script(duration, WARMUP_SECONDS, dt, pelvis_height);
    let frame_step =
        |frame: usize| (((frame as f64 / config.fps) + WARMUP_SECONDS) / dt).round() as usize;
    let params_at = |sample: usize| {
        let s = &samples[sample.min(samples.len() - 1)];
        BodyParams {
            pose: s.pose.clone(),
            betas: config.betas.to_vec(),
            expression: Vec::new(),
            world_rotation: DVec3::ZERO,
            // The pelvis joint of the shaped rest body sits at rest_joints[0].
            world_translation: s.position - rest_joints[0],
        }
    };
    let ground_truth: Vec<BodyParams> = (0..config.frames)
        .map(|f| params_at(frame_step(f)))
        .collect();

    // Garment simulation over every substep, recording the frames.
    let mut skirt_frames = Vec::new();
    if config.garment {
        let scale = 1.0 + procedural::HEIGHT_PER_BETA * config.betas[0];
        let mut skirt = Skirt::new(model, shaped, scale);
        let transforms = |sample: usize| {
            let p = params_at(sample);
            (
                model.joint_transforms(rest_joints, &p.pose),
                DAffine3::from_translation(p.world_translation),
            )
        };
        let (t0, w0) = transforms(0);
        skirt.reset(&t0, w0);
        let last = frame_step(config.frames - 1);
        let mut next_frame = 0;
        for step in 0..=last {
            if step > 0 {
                let (t, w) = transforms(step);
                skirt.step(&t, w, dt);
            }
            while next_frame < config.frames && frame_step(next_frame) == step {
                skirt_frames.push(skirt.positions().to_vec());
                next_frame += 1;
            }
        }
        anyhow::ensure!(
            skirt_frames.len() == config.frames,
            "garment simulation recorded {} of {} frames",
            skirt_frames.len(),
            config.frames
        );
    }
    Ok(SceneSequence {
        ground_truth,
        skirt_frames,
        drapes: Vec::new(),
        garment_states: Vec::new(),
    })
}

/// 3D keypoints: every joint's true world position plus Gaussian noise (its own random
/// stream).
fn noisy_keypoints(
    config: &SyntheticConfig,
    model: &BodyModel,
    ground_truth: &[BodyParams],
) -> anyhow::Result<Vec<DVec3>> {
    let mut keypoint_rng = super::rng::seeded(config.seed ^ KEYPOINT_STREAM);
    let mut keypoints = Vec::with_capacity(config.frames * model.num_joints());
    for params in ground_truth {
        let posed = model.forward(params)?;
        for joint in posed.joints {
            let noise = DVec3::new(
                keypoint_rng.normal(),
                keypoint_rng.normal(),
                keypoint_rng.normal(),
            );
            keypoints.push(joint + noise * config.jitter.keypoints_metres);
        }
    }
    Ok(keypoints)
}

/// Each body vertex's colour: that of the region of its dominant joint.
fn body_colours(model: &BodyModel) -> Vec<DVec3> {
    (0..model.num_vertices())
        .map(|v| {
            let dominant = model
                .vertex_weights(v)
                .max_by(|a, b| a.1.total_cmp(&b.1))
                .map_or(0, |(j, _)| j);
            region_colour(dominant)
        })
        .collect()
}

impl SyntheticScene {
    /// Builds the body, runs the motion script and the garment simulation, and places the
    /// cameras. Cost: about a second for the default sizes; images are rendered later.
    pub fn generate(config: &SyntheticConfig) -> anyhow::Result<Self> {
        config.validate()?;
        let model = procedural_body(config.body_grid_spacing);
        let mut rest_params = model.zero_params();
        rest_params.betas = config.betas.to_vec();
        let shaped = model.shaped_vertices(&rest_params);
        let rest_joints = model.regress_joints(&shaped);
        // Pelvis height so the soles touch the floor when standing.
        let sole = shaped.iter().map(|v| v.y).fold(f64::INFINITY, f64::min);
        let pelvis_height = rest_joints[0].y - sole;

        let SceneSequence {
            ground_truth,
            skirt_frames,
            drapes,
            garment_states,
        } = match config.scene {
            SceneKind::History => {
                history_sequence(config, &model, &shaped, &rest_joints, pelvis_height)?
            }
            SceneKind::Walk => walk_sequence(config, &model, &shaped, &rest_joints, pelvis_height)?,
        };
        anyhow::ensure!(
            skirt_frames.iter().flatten().all(|p| p.is_finite()),
            "garment simulation diverged"
        );

        let mut rng = super::rng::seeded(config.seed);
        let fitted_betas: Vec<f64> = config
            .betas
            .iter()
            .map(|b| b + rng.normal() * config.jitter.betas)
            .collect();
        let jittered = ground_truth
            .iter()
            .map(|p| jitter(p, &config.jitter, &mut rng, &fitted_betas))
            .collect();

        let keypoints = noisy_keypoints(config, &model, &ground_truth)?;
        let body_colour = body_colours(&model);
        let backdrops = match config.background {
            SyntheticBackground::Black => Vec::new(),
            SyntheticBackground::Textured => {
                let mut backdrop_rng = super::rng::seeded(config.seed ^ BACKDROP_STREAM);
                (0..config.cameras)
                    .map(|_| Backdrop::new(&mut backdrop_rng, config.width, config.height))
                    .collect()
            }
        };
        let mut scene = Self {
            config: config.clone(),
            model,
            render_cameras: Vec::new(),
            cameras: Vec::new(),
            ground_truth,
            jittered,
            skirt: skirt_frames,
            drapes,
            garment_states,
            skirt_triangles: if config.garment {
                garment::triangles()
            } else {
                Vec::new()
            },
            skirt_texture: garment::texture_coordinates(),
            body_colour,
            keypoints,
            backdrops,
        };
        scene.render_cameras = scene.place_cameras(&mut rng)?;
        scene.cameras = scene
            .render_cameras
            .iter()
            .map(|source| SourceCamera {
                id: source.id,
                camera: source.camera.with_origin_at(-scene.origin()),
            })
            .collect();
        Ok(scene)
    }

    /// `config.origin`: where the reader's world puts the scene's origin.
    fn origin(&self) -> DVec3 {
        DVec3::from_array(self.config.origin)
    }

    /// `params` in the reader's world.
    fn in_world(&self, mut params: BodyParams) -> BodyParams {
        params.world_translation += self.origin();
        params
    }

    /// World-space points of frame `frame`: body vertices then skirt particles.
    fn frame_geometry(&self, frame: usize) -> anyhow::Result<(Vec<DVec3>, usize)> {
        let posed = self.model.forward(&self.ground_truth[frame])?;
        let body_count = posed.vertices.len();
        let mut points = posed.vertices;
        if let Some(skirt) = self.skirt.get(frame) {
            points.extend_from_slice(skirt);
        }
        Ok((points, body_count))
    }

    fn place_cameras(&self, rng: &mut Rng) -> anyhow::Result<Vec<SourceCamera>> {
        let config = &self.config;
        // Every 7th point of every frame bounds the sequence.
        let mut points = Vec::new();
        for frame in 0..config.frames {
            let (p, _) = self.frame_geometry(frame)?;
            points.extend(p.into_iter().step_by(7));
        }
        let (lo, hi) = points
            .iter()
            .fold((DVec3::MAX, DVec3::MIN), |(l, h), p| (l.min(*p), h.max(*p)));
        let target = (lo + hi) * 0.5;
        let (w, h) = (config.width as f64, config.height as f64);
        let mut cameras = Vec::with_capacity(config.cameras);
        for index in 0..config.cameras {
            let azimuth = std::f64::consts::TAU * index as f64 / config.cameras as f64
                + (rng.next_f64() - 0.5) * 0.1;
            let height = 1.3 + (rng.next_f64() - 0.5) * 0.3;
            let eye = DVec3::new(
                target.x + config.camera_distance * azimuth.sin(),
                height,
                target.z + config.camera_distance * azimuth.cos(),
            );
            let offset = DVec2::new(rng.next_f64() - 0.5, rng.next_f64() - 0.5) * 4.0;
            let aspect = 1.0 + (rng.next_f64() - 0.5) * 0.004;
            let unit = Intrinsics {
                fx: 1.0,
                fy: aspect,
                cx: 0.0,
                cy: 0.0,
            };
            let probe = Camera::look_at(config.width, config.height, unit, eye, target, DVec3::Y);
            // Largest focal length keeping every point 4 % inside the image borders.
            let (cx, cy) = (0.5 * w + offset.x, 0.5 * h + offset.y);
            let margin = 0.04 * w.min(h);
            let mut focal = f64::INFINITY;
            for p in &points {
                let c = probe.world_to_camera(*p);
                anyhow::ensure!(
                    c.z > 0.5,
                    "a synthetic camera is too close to the subject; increase dataset.camera_distance"
                );
                let (nx, ny) = ((c.x / c.z).abs(), (aspect * c.y / c.z).abs());
                let room_x = if c.x >= 0.0 {
                    w - margin - cx
                } else {
                    cx - margin
                };
                let room_y = if c.y >= 0.0 {
                    h - margin - cy
                } else {
                    cy - margin
                };
                if nx > 0.0 {
                    focal = focal.min(room_x / nx);
                }
                if ny > 0.0 {
                    focal = focal.min(room_y / ny);
                }
            }
            let intrinsics = Intrinsics {
                fx: focal,
                fy: focal * aspect,
                cx,
                cy,
            };
            let camera = Camera::look_at(
                config.width,
                config.height,
                intrinsics,
                eye,
                target,
                DVec3::Y,
            );
            camera.validate()?;
            cameras.push(SourceCamera {
                id: index as i64,
                camera,
            });
        }
        Ok(cameras)
    }

    /// The exact body parameters of every frame.
    pub fn ground_truth(&self) -> &[BodyParams] {
        &self.ground_truth
    }

    /// The backdrop camera `view` sees (`None` with a black background).
    pub fn backdrop(&self, view: usize) -> Option<&Backdrop> {
        self.backdrops.get(view)
    }

    /// Skirt particle positions of a frame (empty without a garment).
    pub fn skirt_positions(&self, frame: usize) -> &[DVec3] {
        self.skirt.get(frame).map_or(&[], |s| s.as_slice())
    }

    /// The skirt the frame's pose alone determines: the rest skirt carried by the pose (no
    /// velocity), left to settle for `seconds` while the body holds the pose. It starts from
    /// the rest shape, not from the frame's skirt, because the settled shape depends on the
    /// start (the skirt can come to rest in several folds around the legs), and that
    /// dependence is history too. The difference to [`Self::skirt_positions`] is the
    /// history-dependent part of the garment (swing, lag and fold from the motion before the
    /// frame), what only a model with motion context can render.
    ///
    /// In the history scene the drape is exact and `seconds` is not used: the rest state of
    /// the skirt's oscillator, the rest skirt carried by the pose ([`Skirt::carried`]).
    pub fn static_drape(&self, frame: usize, seconds: f64) -> anyhow::Result<Vec<DVec3>> {
        anyhow::ensure!(
            self.config.garment && frame < self.skirt.len(),
            "frame {frame}: the scene has no garment state for it"
        );
        if let Some(drape) = self.drapes.get(frame) {
            return Ok(drape.clone());
        }
        let mut rest_params = self.model.zero_params();
        rest_params.betas = self.config.betas.to_vec();
        let shaped = self.model.shaped_vertices(&rest_params);
        let rest_joints = self.model.regress_joints(&shaped);
        let scale = 1.0 + procedural::HEIGHT_PER_BETA * self.config.betas[0];
        let mut skirt = Skirt::new(&self.model, &shaped, scale);
        let params = &self.ground_truth[frame];
        let transforms = self.model.joint_transforms(&rest_joints, &params.pose);
        let world = DAffine3::from_translation(params.world_translation);
        skirt.reset(&transforms, world);
        let dt = 1.0 / SIMULATION_RATE;
        for _ in 0..(seconds / dt).ceil() as usize {
            skirt.step(&transforms, world, dt);
        }
        Ok(skirt.positions().to_vec())
    }

    /// Renders camera `view` at frame `frame`: supersampled visibility, shading, box filter.
    pub fn render(&self, view: usize, frame: usize) -> anyhow::Result<SourceImage> {
        Ok(self.render_with_garment(view, frame)?.0)
    }

    /// [`Self::render`] and the skirt's coverage of each pixel: the fraction (0..255) of the
    /// pixel's supersamples whose visible surface after the depth test is a skirt triangle,
    /// counted on the same samples as the foreground mask, so it never exceeds it. `None`
    /// without a garment.
    pub fn render_with_garment(
        &self,
        view: usize,
        frame: usize,
    ) -> anyhow::Result<(SourceImage, Option<image::GrayImage>)> {
        let (points, body_count) = self.frame_geometry(frame)?;
        let (image, garment) = self.render_points(view, &points, body_count)?;
        Ok((image, self.config.garment.then_some(garment)))
    }

    /// [`Self::render`] with the frame's skirt replaced by `skirt` (one position per
    /// particle), e.g. its [`Self::static_drape`].
    pub fn render_with_skirt(
        &self,
        view: usize,
        frame: usize,
        skirt: &[DVec3],
    ) -> anyhow::Result<SourceImage> {
        let (mut points, body_count) = self.frame_geometry(frame)?;
        anyhow::ensure!(
            points.len() - body_count == skirt.len(),
            "{} skirt positions for {} particles",
            skirt.len(),
            points.len() - body_count
        );
        points.truncate(body_count);
        points.extend_from_slice(skirt);
        Ok(self.render_points(view, &points, body_count)?.0)
    }

    /// Renders body vertices `points[..body_count]` followed by the skirt particles: the image
    /// with its foreground mask, and the skirt's coverage (all zero without a garment).
    fn render_points(
        &self,
        view: usize,
        points: &[DVec3],
        body_count: usize,
    ) -> anyhow::Result<(SourceImage, image::GrayImage)> {
        let config = &self.config;
        let camera = &self.render_cameras[view].camera;
        let s = config.supersample as usize;
        let fine = camera.resized(camera.width * s as u32, camera.height * s as u32);
        let body_faces = self.model.faces();
        let mut triangles: Vec<[u32; 3]> = body_faces.to_vec();
        triangles.extend(
            self.skirt_triangles
                .iter()
                .map(|t| t.map(|i| i + body_count as u32)),
        );
        let normals = {
            let mut n = vertex_normals(&points[..body_count], body_faces);
            n.extend(vertex_normals(&points[body_count..], &self.skirt_triangles));
            n
        };
        let buffer = rasterize(&fine, points, &triangles);
        let light = LIGHT.normalize();
        let centre = camera.center();
        let num_body_faces = body_faces.len();
        let shade = |sample: usize| -> Option<DVec3> {
            let tri = buffer.triangle[sample];
            if tri == EMPTY {
                return None;
            }
            let corners = triangles[tri as usize];
            let bary = buffer.barycentric[sample].map(|b| b as f64);
            let interpolate = |values: &dyn Fn(usize) -> DVec3| -> DVec3 {
                (0..3).map(|k| values(corners[k] as usize) * bary[k]).sum()
            };
            let position = interpolate(&|i| points[i]);
            let mut normal = interpolate(&|i| normals[i]).normalize_or_zero();
            let albedo = if (tri as usize) < num_body_faces {
                let rest = interpolate(&|i| self.model.template_vertex(i));
                interpolate(&|i| self.body_colour[i]) * body_pattern(rest)
            } else {
                // Both sides of the skirt are seen: light the side facing the camera.
                if normal.dot(centre - position) < 0.0 {
                    normal = -normal;
                }
                skirt_albedo(
                    interpolate(&|i| self.skirt_texture[i - body_count]),
                    self.config.skirt_stripes,
                )
            };
            let lambert = normal.dot(light).max(0.0);
            Some(albedo * (0.45 + 0.55 * lambert))
        };
        let (width, height) = (camera.width as usize, camera.height as usize);
        let fine_width = width * s;
        let mut rgb = image::RgbImage::new(camera.width, camera.height);
        let mut mask = image::GrayImage::new(camera.width, camera.height);
        let mut garment = image::GrayImage::new(camera.width, camera.height);
        let samples_per_pixel = (s * s) as f64;
        let backdrop = self.backdrops.get(view);
        for row in 0..height {
            for col in 0..width {
                let mut colour = DVec3::ZERO;
                let mut covered = 0usize;
                let mut skirt_covered = 0usize;
                for dy in 0..s {
                    for dx in 0..s {
                        let sample = (row * s + dy) * fine_width + col * s + dx;
                        if let Some(c) = shade(sample) {
                            colour += c;
                            covered += 1;
                            // Triangles after the body's are the skirt's.
                            if buffer.triangle[sample] as usize >= num_body_faces {
                                skirt_covered += 1;
                            }
                        } else if let Some(backdrop) = backdrop {
                            // The sample's centre in image pixels.
                            let x = col as f64 + (dx as f64 + 0.5) / s as f64;
                            let y = row as f64 + (dy as f64 + 0.5) / s as f64;
                            colour += backdrop.colour(x, y);
                        }
                    }
                }
                let c = (colour / samples_per_pixel * 255.0)
                    .round()
                    .clamp(DVec3::ZERO, DVec3::splat(255.0));
                rgb.put_pixel(
                    col as u32,
                    row as u32,
                    image::Rgb([c.x as u8, c.y as u8, c.z as u8]),
                );
                let coverage = (covered as f64 / samples_per_pixel * 255.0).round() as u8;
                mask.put_pixel(col as u32, row as u32, image::Luma([coverage]));
                let skirt_coverage =
                    (skirt_covered as f64 / samples_per_pixel * 255.0).round() as u8;
                garment.put_pixel(col as u32, row as u32, image::Luma([skirt_coverage]));
            }
        }
        Ok((SourceImage { rgb, mask }, garment))
    }
}

/// The synthetic scene's split for `n` cameras (what `default_split` gives; also resolved
/// from the config alone when the pipeline loads): every fourth camera (1, 5, ...) is a test
/// view, the others train; training uses every frame, testing every second frame.
pub fn default_split(n: usize) -> Split {
    let test_views: Vec<usize> = (1..n).step_by(4).collect();
    let train_views = (0..n).filter(|v| !test_views.contains(v)).collect();
    Split::first_frames(train_views, test_views, None, 2)
}

impl DatasetReader for SyntheticScene {
    fn describe(&self) -> String {
        format!(
            "synthetic scene ({} cameras, {} frames, {}x{})",
            self.config.cameras, self.config.frames, self.config.width, self.config.height
        )
    }

    fn cameras(&self) -> &[SourceCamera] {
        &self.cameras
    }

    fn num_frames(&self) -> usize {
        self.config.frames
    }

    fn default_split(&self) -> Split {
        default_split(self.cameras.len())
    }

    fn body_model(&self) -> anyhow::Result<(BodyModel, BodyModelKind)> {
        Ok((self.model.clone(), BodyModelKind::Procedural))
    }

    fn body_params(&self, frame: usize) -> anyhow::Result<BodyParams> {
        self.jittered
            .get(frame)
            .map(|params| self.in_world(params.clone()))
            .ok_or_else(|| anyhow::anyhow!("synthetic scene has no frame {frame}"))
    }

    /// Keypoint `j` is joint `j`: the true joint position plus seeded noise, confidence 1.
    fn keypoints_3d(&self) -> anyhow::Result<Option<Keypoints3d>> {
        Ok(Some(Keypoints3d {
            joints: (0..self.model.num_joints()).map(Some).collect(),
            positions: self.keypoints.iter().map(|p| *p + self.origin()).collect(),
            confidence: vec![1.0; self.keypoints.len()],
        }))
    }

    fn ground_truth_body_params(&self, frame: usize) -> anyhow::Result<Option<BodyParams>> {
        Ok(Some(
            self.ground_truth
                .get(frame)
                .cloned()
                .map(|params| self.in_world(params))
                .ok_or_else(|| anyhow::anyhow!("synthetic scene has no frame {frame}"))?,
        ))
    }

    /// The history scene's skirt and its exact static drape; `None` for the walk scene (its
    /// drape needs seconds of simulation per frame: `examples/garment_history.rs`).
    fn garment_history(&self, frame: usize) -> anyhow::Result<Option<GarmentHistory>> {
        if self.drapes.is_empty() {
            return Ok(None);
        }
        anyhow::ensure!(
            frame < self.drapes.len(),
            "synthetic scene has no frame {frame}"
        );
        let in_world = |points: &[DVec3]| points.iter().map(|p| *p + self.origin()).collect();
        Ok(Some(GarmentHistory {
            simulated: in_world(&self.skirt[frame]),
            drape: in_world(&self.drapes[frame]),
            state: self.garment_states[frame],
        }))
    }

    fn read_image(&self, view: usize, frame: usize) -> anyhow::Result<SourceImage> {
        Ok(self.read_image_with_garment(view, frame)?.0)
    }

    /// The skirt's pixels, where the scene has a garment.
    fn garment_region(&self) -> Option<GarmentRegion> {
        self.config.garment.then_some(GarmentRegion::SyntheticSkirt)
    }

    fn read_image_with_garment(
        &self,
        view: usize,
        frame: usize,
    ) -> anyhow::Result<(SourceImage, Option<image::GrayImage>)> {
        anyhow::ensure!(
            view < self.cameras.len(),
            "synthetic scene has no camera {view}"
        );
        anyhow::ensure!(
            frame < self.config.frames,
            "synthetic scene has no frame {frame}"
        );
        self.render_with_garment(view, frame)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    /// Renders every view of a frame in parallel.
    fn render_frame(scene: &SyntheticScene, frame: usize) -> anyhow::Result<Vec<SourceImage>> {
        (0..scene.cameras.len())
            .into_par_iter()
            .map(|v| scene.render(v, frame))
            .collect()
    }

    #[test]
    fn static_drape_removes_the_swing_and_renders_in_place_of_the_skirt() {
        let config = SyntheticConfig {
            cameras: 1,
            frames: 30,
            width: 48,
            height: 48,
            supersample: 1,
            body_grid_spacing: 0.04,
            ..Default::default()
        };
        let scene = SyntheticScene::generate(&config).unwrap();
        // Frames 19 and 22 share one standing pose and place (see the test below) while the
        // skirt still swings: their drapes are the same, their simulated skirts are not.
        let largest = |a: &[DVec3], b: &[DVec3]| {
            a.iter()
                .zip(b)
                .map(|(x, y)| (*x - *y).length())
                .fold(0.0, f64::max)
        };
        let (drape_a, drape_b) = (
            scene.static_drape(19, 6.0).unwrap(),
            scene.static_drape(22, 6.0).unwrap(),
        );
        let simulated = largest(scene.skirt_positions(19), scene.skirt_positions(22));
        let draped = largest(&drape_a, &drape_b);
        assert!(
            draped < 1e-9 && simulated > 0.005,
            "drapes differ by {draped} m, simulated skirts by {simulated} m"
        );
        // The drape hangs: no particle is above the waist ring's lowest particle.
        let waist = drape_a[..garment::AROUND]
            .iter()
            .map(|p| p.y)
            .fold(f64::INFINITY, f64::min);
        assert!(
            drape_a[garment::AROUND..]
                .iter()
                .all(|p| p.y < waist + 1e-9)
        );
        // Rendering with the frame's own skirt reproduces the frame; a wrong count is an error.
        let own = scene
            .render_with_skirt(0, 19, scene.skirt_positions(19))
            .unwrap();
        assert_eq!(own.rgb, scene.render(0, 19).unwrap().rgb);
        assert!(scene.render_with_skirt(0, 19, &drape_a[1..]).is_err());
    }

    #[test]
    fn same_pose_different_garment_and_textured_images() {
        let config = SyntheticConfig {
            cameras: 2,
            frames: 30,
            width: 64,
            height: 64,
            supersample: 1,
            body_grid_spacing: 0.04,
            ..Default::default()
        };
        let scene = SyntheticScene::generate(&config).unwrap();
        // During the stop (normalised time 0.62..0.78) the pose is the same standing pose,
        // but the skirt is still swinging from the stop.
        let (a, b) = (19, 22);
        let pose_change: f64 = scene.ground_truth()[a]
            .pose
            .iter()
            .zip(&scene.ground_truth()[b].pose)
            .map(|(x, y)| (*x - *y).length())
            .sum();
        assert!(pose_change < 1e-6, "pose changed by {pose_change}");
        let skirt_change = scene
            .skirt_positions(a)
            .iter()
            .zip(scene.skirt_positions(b))
            .map(|(x, y)| (*x - *y).length())
            .fold(0.0, f64::max);
        assert!(skirt_change > 0.005, "skirt moved only {skirt_change} m");
        // Images: a foreground with texture contrast.
        let image = scene.render(0, 10).unwrap();
        let foreground: Vec<u8> = image
            .rgb
            .pixels()
            .zip(image.mask.pixels())
            .filter(|(_, m)| m.0[0] == 255)
            .map(|(p, _)| p.0[1])
            .collect();
        assert!(
            foreground.len() > 200,
            "{} foreground pixels",
            foreground.len()
        );
        let (lo, hi) = foreground
            .iter()
            .fold((255, 0), |(l, h), &g| (l.min(g), h.max(g)));
        assert!(hi - lo > 80, "texture contrast {lo}..{hi}");
    }

    #[test]
    fn backdrops_are_textured_per_camera_and_masks_stay_exact() {
        let config = SyntheticConfig {
            cameras: 3,
            frames: 4,
            width: 48,
            height: 40,
            supersample: 2,
            body_grid_spacing: 0.05,
            ..Default::default()
        };
        assert_eq!(config.background, SyntheticBackground::Textured);
        let textured = SyntheticScene::generate(&config).unwrap();
        let black = SyntheticScene::generate(&SyntheticConfig {
            background: SyntheticBackground::Black,
            ..config.clone()
        })
        .unwrap();
        // The backdrop changes nothing else: cameras and bodies are those of the black scene,
        // and generation is deterministic.
        assert_eq!(textured.cameras, black.cameras);
        assert_eq!(textured.jittered, black.jittered);
        assert!(black.backdrop(0).is_none());
        let again = SyntheticScene::generate(&config).unwrap();
        assert_eq!(again.backdrop(2), textured.backdrop(2));
        let mut backgrounds = Vec::new();
        for view in 0..3 {
            let (a, b) = (
                textured.render(view, 1).unwrap(),
                black.render(view, 1).unwrap(),
            );
            // Exact masks: the coverage of the person, whatever is behind it.
            assert_eq!(a.mask, b.mask, "view {view}");
            let backdrop = textured.backdrop(view).unwrap();
            let mut seen = Vec::new();
            for (index, ((pa, pb), m)) in a
                .rgb
                .pixels()
                .zip(b.rgb.pixels())
                .zip(a.mask.pixels())
                .enumerate()
            {
                let (col, row) = ((index % 48) as f64, (index / 48) as f64);
                // The backdrop at the pixel's 2 x 2 sample centres.
                let samples: Vec<DVec3> = [0.25, 0.75]
                    .iter()
                    .flat_map(|dy| [0.25, 0.75].map(|dx| backdrop.colour(col + dx, row + dy)))
                    .collect();
                // The exact coverage (the stored mask is it rounded to a byte).
                let m = (f64::from(m.0[0]) / 255.0 * 4.0).round() / 4.0;
                for c in 0..3 {
                    // The black image is m F; the textured one adds (1 - m) times the mean
                    // backdrop of the uncovered samples, which lies between their extremes
                    // (each image rounded to a byte once).
                    let lo = samples.iter().map(|b| b[c]).fold(f64::INFINITY, f64::min);
                    let hi = samples.iter().map(|b| b[c]).fold(0.0, f64::max);
                    let added = f64::from(pa.0[c]) - f64::from(pb.0[c]);
                    let (low, high) = ((1.0 - m) * lo * 255.0, (1.0 - m) * hi * 255.0);
                    assert!(
                        added >= low - 1.0 && added <= high + 1.0,
                        "view {view} pixel {index} channel {c}: added {added}, not in \
                         [{low}, {high}] (mask {m})"
                    );
                    if m == 0.0 {
                        let mean = samples.iter().map(|b| b[c]).sum::<f64>() / 4.0 * 255.0;
                        assert!((added - mean).abs() <= 0.5 + 1e-9, "{added} vs {mean}");
                    }
                }
                if m == 0.0 {
                    assert_eq!(pb.0, [0, 0, 0]);
                    seen.push(pa.0);
                }
            }
            assert!(seen.len() > 500, "{} background pixels", seen.len());
            // Textured, not uniform: a wide spread of values in every channel.
            let spreads = [0, 1, 2].map(|c| {
                let values: Vec<f64> = seen.iter().map(|p| f64::from(p[c])).collect();
                let mean = values.iter().sum::<f64>() / values.len() as f64;
                (values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / values.len() as f64)
                    .sqrt()
            });
            eprintln!("view {view}: background spread per channel {spreads:.1?}");
            assert!(
                spreads.iter().all(|s| *s > 5.0) && spreads.iter().any(|s| *s > 12.0),
                "view {view}: spreads {spreads:?}"
            );
            backgrounds.push(a.rgb);
        }
        // Each camera its own backdrop: the corners (background in every view) differ.
        for (i, j) in [(0, 1), (0, 2), (1, 2)] {
            let differing = backgrounds[i]
                .pixels()
                .zip(backgrounds[j].pixels())
                .take(48 * 4)
                .filter(|(p, q)| p.0 != q.0)
                .count();
            assert!(
                differing > 150,
                "views {i} and {j}: {differing} of 192 differ"
            );
        }
    }

    fn history_scene(size: u32, cameras: usize) -> SyntheticScene {
        SyntheticScene::generate(&SyntheticConfig {
            scene: SceneKind::History,
            cameras,
            frames: history::LENGTH,
            fps: history::FPS,
            width: size,
            height: size,
            supersample: 1,
            body_grid_spacing: 0.04,
            ..Default::default()
        })
        .unwrap()
    }

    /// Per frame: every hem particle's displacement from the static drape, in the body's
    /// heading frame (so displacements at different headings compare).
    fn hem_displacements(scene: &SyntheticScene) -> Vec<Vec<DVec3>> {
        (0..scene.skirt.len())
            .map(|frame| {
                let heading = scene.ground_truth[frame].world_rotation;
                let to_body = seqavatar_core::rotation::axis_angle_to_matrix(-heading);
                let drape = scene.static_drape(frame, 0.0).unwrap();
                (0..garment::AROUND)
                    .map(|k| {
                        let i = garment::particle(garment::ROWS - 1, k);
                        to_body * (scene.skirt[frame][i] - drape[i])
                    })
                    .collect()
            })
            .collect()
    }

    #[test]
    fn history_scene_recurs_poses_under_different_histories_and_the_skirt_remembers() {
        let scene = history_scene(64, 2);
        let truth = scene.ground_truth();
        let hem = hem_displacements(&scene);
        let peak = |frame: usize| hem[frame].iter().map(|d| d.length()).fold(0.0, f64::max);
        // The static drape is the oscillator's rest state: at frame 0 (after a hold from
        // rest) the skirt is its drape, and a state at rest leaves any drape unchanged.
        let drape = scene.static_drape(0, 0.0).unwrap();
        assert_eq!(scene.skirt_positions(0), drape.as_slice());
        assert_eq!(
            Swing::default().apply(&SwingParams::HISTORY, &scene.static_drape(90, 0.0).unwrap()),
            scene.static_drape(90, 0.0).unwrap()
        );
        // Peak hem swing >= 10 cm.
        let largest = (0..truth.len()).map(peak).fold(0.0, f64::max);
        assert!(largest >= 0.10, "peak hem swing {largest} m");
        // Stop-and-hold: frames 46..=91 and 139..=184 repeat one pose and place exactly,
        // while the skirt swings and settles (its amplitude decays).
        for (start, end) in [(46, 91), (139, 184)] {
            for frame in start + 1..=end {
                assert_eq!(truth[frame], truth[start], "frame {frame}");
            }
            let early = (start..start + 15).map(peak).fold(0.0, f64::max);
            let late = (end - 6..=end).map(peak).fold(0.0, f64::max);
            assert!(early >= 0.03, "hold from {start}: early swing {early} m");
            assert!(
                late < 0.35 * early,
                "hold from {start}: {early} m then {late} m"
            );
        }
        // Identical poses under different histories give hems that differ by >= 10 cm (in
        // the body's frame), and the same pose recurs at both speeds and in the holds.
        let mut differ: f64 = 0.0;
        let mut pairs = 0;
        for a in 0..truth.len() {
            for b in a + 1..truth.len() {
                if truth[a].pose == truth[b].pose {
                    pairs += 1;
                    let d = hem[a]
                        .iter()
                        .zip(&hem[b])
                        .map(|(x, y)| (*x - *y).length())
                        .fold(0.0, f64::max);
                    differ = differ.max(d);
                }
            }
        }
        eprintln!(
            "history scene: peak hem swing {largest:.3} m; {pairs} same-pose frame pairs, hems differ by up to {differ:.3} m"
        );
        assert!(pairs > 1000, "{pairs} pairs of frames share a pose");
        assert!(
            differ >= 0.10,
            "same-pose hems differ by at most {differ} m"
        );
    }

    /// Timing of the demo's default scene (`SEQAVATAR_SLOW_TESTS=1`).
    #[test]
    fn default_scene_timing() {
        if std::env::var("SEQAVATAR_SLOW_TESTS").is_err() {
            return;
        }
        let started = std::time::Instant::now();
        let scene = SyntheticScene::generate(&SyntheticConfig::default()).unwrap();
        let generated = started.elapsed();
        let started = std::time::Instant::now();
        let images = render_frame(&scene, 24).unwrap();
        let rendered = started.elapsed();
        println!(
            "default synthetic scene: generate {:.2} s, render {} views {:.3} s ({:.1} ms per image)",
            generated.as_secs_f64(),
            images.len(),
            rendered.as_secs_f64(),
            rendered.as_secs_f64() * 1e3 / images.len() as f64
        );
        let started = std::time::Instant::now();
        let history = SyntheticScene::generate(&SyntheticConfig {
            scene: SceneKind::History,
            fps: history::FPS,
            frames: history::LENGTH,
            ..Default::default()
        })
        .unwrap();
        println!(
            "history scene ({} frames, {} cameras): generate {:.2} s",
            history.skirt.len(),
            history.cameras.len(),
            started.elapsed().as_secs_f64()
        );
        if let Ok(dir) = std::env::var("SEQAVATAR_PREVIEW_DIR") {
            for (v, image) in images.iter().enumerate() {
                image
                    .rgb
                    .save(format!("{dir}/synthetic_view{v}.png"))
                    .unwrap();
            }
        }
    }
}
