//! `pipeline render`: drives a trained avatar with the body poses of another sequence (an
//! ingest entry) or of a pose file (`.npz` with `body_pose`, `global_orient`, `transl` and
//! optionally `betas`, as the SMPL/SMPL-X parameter files of the datasets), renders every frame
//! from one of the avatar's training cameras to PNG and, when `ffmpeg` is on `PATH`, encodes an
//! MP4. Motion windows for the new poses come from the motion crate's functions, with the
//! scales and velocity normalisation of the motion entry the avatar was trained with.

use std::path::{Path, PathBuf};
use std::process::Command;

use anyhow::Context as _;
use seqavatar_compute::backend::Backend;
use seqavatar_core::body::BodyParams;
use seqavatar_core::glam::DVec3;
use seqavatar_engine::{
    EntryId, EntryReader, EntryState, LocalStore, ReadLease, Store, open_store,
};
use seqavatar_formats::npz;
use seqavatar_schema::motion::FrameAxis;

use crate::avatar_render::AvatarRenderer;
use crate::evaluate::ViewRenderer;

/// Where the poses come from.
#[derive(Clone, Debug, PartialEq)]
pub enum PoseSource {
    /// An ingest entry (folder or key): its per-frame body parameters.
    Entry(String),
    /// A `.npz` pose file.
    File(PathBuf),
}

impl PoseSource {
    /// A path ending in `.npz` is a pose file; anything else names an ingest entry.
    pub fn parse(text: &str) -> Self {
        if text.to_ascii_lowercase().ends_with(".npz") {
            Self::File(PathBuf::from(text))
        } else {
            Self::Entry(text.to_owned())
        }
    }

    /// The source as the user named it, for messages.
    pub fn describe(&self) -> String {
        match self {
            Self::Entry(spec) => spec.clone(),
            Self::File(path) => path.display().to_string(),
        }
    }
}

/// Options of `pipeline render`.
#[derive(Clone, Debug)]
pub struct RenderOptions {
    /// A train entry: its folder in a cache, its key, or a unique key prefix.
    pub avatar: String,
    pub poses: PoseSource,
    /// View index of the avatar's training cameras.
    pub camera: usize,
    /// Image size factor applied to that camera.
    pub resolution_scale: f64,
    pub out: PathBuf,
    pub backend: Backend,
    /// Frames per second of the MP4.
    pub fps: u32,
    /// Render at most this many frames (0 = all).
    pub max_frames: usize,
}

/// What `pipeline render` wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderSummary {
    pub frames: Vec<PathBuf>,
    /// Leading frames not rendered: their motion windows reach before the first frame of a
    /// pose entry that does not start its recording.
    pub skipped: usize,
    /// The MP4, when ffmpeg was found and succeeded.
    pub video: Option<PathBuf>,
    /// Why no MP4 was written, when none was.
    pub video_note: Option<String>,
    pub seconds: f64,
}

/// Opens an entry of `kind` named by `spec`: the folder `<cache>/<kind>/<key>` of a published
/// entry, or a key (or unique key prefix) in `store`.
pub fn resolve_entry(store: &dyn Store, kind: &str, spec: &str) -> anyhow::Result<EntryReader> {
    let path = Path::new(spec);
    if path.is_dir() {
        let (local, id) = LocalStore::of_entry_folder(path)?;
        anyhow::ensure!(
            id.kind == kind,
            "{spec}: a \"{}\" entry, expected a \"{kind}\" entry",
            id.kind
        );
        anyhow::ensure!(
            local.entry_state(&id)? == EntryState::Complete,
            "{spec}: not a published cache entry (no completion marker; the entry may be incomplete)"
        );
        return seqavatar_engine::open_leased_verified(&local, &id);
    }
    let matches: Vec<EntryId> = store
        .list()?
        .into_iter()
        .filter(|id| id.kind == kind && id.key.starts_with(spec))
        .collect();
    match matches.as_slice() {
        [id] => seqavatar_engine::open_leased_verified(store, id),
        [] => anyhow::bail!(
            "{spec}: neither a folder nor the key of a \"{kind}\" entry in the cache at {}",
            store.describe()
        ),
        many => anyhow::bail!(
            "{spec}: {} \"{kind}\" entries start with this key; give more characters",
            many.len()
        ),
    }
}

/// `input`, the entry of `kind` that the avatar's train entry read ([`upstream_input`]),
/// which the avatar needs.
fn required(
    input: anyhow::Result<Option<EntryReader>>,
    train: &EntryReader,
    kind: &str,
) -> anyhow::Result<EntryReader> {
    input?
        .ok_or_else(|| anyhow::anyhow!("train entry {} records no {kind} input", train.location()))
}

/// The entry of `kind` that `train` read (`None` when it read none), opened verified and
/// under a read lease; an input missing from the cache is an error naming it.
pub fn upstream_input(
    store: &dyn Store,
    train: &EntryReader,
    kind: &str,
) -> anyhow::Result<Option<EntryReader>> {
    let Some(input) = train
        .manifest()
        .inputs
        .iter()
        .find(|input| input.kind == kind)
    else {
        return Ok(None);
    };
    let id = EntryId::new(kind, &input.key);
    anyhow::ensure!(
        store.entry_state(&id)? == EntryState::Complete,
        "the avatar's {kind} entry {id} (stage \"{}\") is not in the cache at {}",
        input.stage_name,
        store.describe()
    );
    Ok(Some(seqavatar_engine::open_leased_verified(store, &id)?))
}

/// Reads a pose file: `body_pose` `(F, 3 K)` or `(F, K, 3)` (K = joints after the root, at
/// most J - 1; missing joints are zero), `global_orient` `(F, 3)`, `transl` `(F, 3)`, optional
/// `betas` `(F, B)` or `(B)`. Frames without `betas` use `default_betas`. Only the first
/// `limit` frames become parameters.
pub fn read_pose_file(
    path: &Path,
    num_joints: usize,
    default_betas: &[f64],
    limit: usize,
) -> anyhow::Result<Vec<BodyParams>> {
    let bytes = seqavatar_engine::files::read_regular_file(path)?;
    let arrays =
        npz::read(&bytes).with_context(|| format!("{}: not a readable .npz", path.display()))?;
    let file = path.display();
    let get = |key: &str| -> anyhow::Result<Option<(Vec<usize>, Vec<f64>)>> {
        let Some((_, value)) = arrays.iter().find(|(name, _)| name == key) else {
            return Ok(None);
        };
        let (shape, data) = value
            .to_f64_array()
            .ok_or_else(|| anyhow::anyhow!("{file}: array `{key}` is not numeric"))?;
        if let Some(bad) = data.iter().position(|v| !v.is_finite()) {
            anyhow::bail!("{file}: array `{key}` has a non-finite value at {bad}");
        }
        Ok(Some((shape, data)))
    };
    let require = |key: &str| -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
        get(key)?.ok_or_else(|| anyhow::anyhow!("{file}: missing array `{key}`"))
    };
    let (orient_shape, orient) = require("global_orient")?;
    anyhow::ensure!(
        orient_shape.len() == 2 && orient_shape[1] == 3 && orient_shape[0] > 0,
        "{file}: array `global_orient` has shape {orient_shape:?}, expected (frames, 3)"
    );
    let frames = orient_shape[0];
    let (pose_shape, body_pose) = require("body_pose")?;
    let per_frame = body_pose.len() / frames.max(1);
    let shape_ok = pose_shape.first() == Some(&frames)
        && body_pose.len() == frames * per_frame
        && per_frame % 3 == 0
        && (pose_shape.len() == 2 || (pose_shape.len() == 3 && pose_shape[2] == 3));
    anyhow::ensure!(
        shape_ok,
        "{file}: array `body_pose` has shape {pose_shape:?}, expected ({frames}, 3 K) or ({frames}, K, 3)"
    );
    let posed_joints = per_frame / 3;
    anyhow::ensure!(
        posed_joints < num_joints,
        "{file}: array `body_pose` has {posed_joints} joints, the avatar's body model has {} after the root",
        num_joints - 1
    );
    let (transl_shape, transl) = require("transl")?;
    anyhow::ensure!(
        transl_shape == [frames, 3],
        "{file}: array `transl` has shape {transl_shape:?}, expected ({frames}, 3)"
    );
    let betas: Option<(Vec<usize>, Vec<f64>)> = get("betas")?;
    let betas_of = |frame: usize| -> anyhow::Result<Vec<f64>> {
        match &betas {
            None => Ok(default_betas.to_vec()),
            Some((shape, data)) if shape.len() == 1 => Ok(data.clone()),
            Some((shape, data)) if shape.len() == 2 && shape[0] == frames => {
                Ok(data[frame * shape[1]..(frame + 1) * shape[1]].to_vec())
            }
            Some((shape, _)) => anyhow::bail!(
                "{file}: array `betas` has shape {shape:?}, expected (B) or ({frames}, B)"
            ),
        }
    };
    (0..frames.min(limit))
        .map(|frame| {
            let mut pose = vec![DVec3::ZERO; num_joints];
            pose[0] = DVec3::from_slice(&orient[frame * 3..frame * 3 + 3]);
            for joint in 0..posed_joints {
                let at = frame * per_frame + joint * 3;
                pose[joint + 1] = DVec3::from_slice(&body_pose[at..at + 3]);
            }
            Ok(BodyParams {
                pose,
                betas: betas_of(frame)?,
                expression: Vec::new(),
                world_rotation: DVec3::ZERO,
                world_translation: DVec3::from_slice(&transl[frame * 3..frame * 3 + 3]),
            })
        })
        .collect()
}

/// Whether `program` is an executable file on `PATH`.
pub fn on_path(program: &str) -> Option<PathBuf> {
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(program))
        .find(|candidate| candidate.is_file())
}

/// A trained avatar driven by a pose source: what `pipeline render` and `pipeline export`
/// share.
pub struct DrivenAvatar {
    /// The avatar's train entry.
    pub train: EntryReader,
    /// The ingest entry the avatar was trained on (its cameras).
    pub trained_ingest: EntryReader,
    /// The other entries it is driven from (its motion entry, the poses' ingest entry), kept
    /// so that their read leases, like the two above, last as long as the avatar is driven:
    /// `gc` meanwhile leaves every entry a render, export or view reads.
    pub sources: Vec<EntryReader>,
    /// The read leases of every entry the train entry read (its fit entry too, of which
    /// drawing reads nothing), held as long as the avatar is driven: `gc` meanwhile leaves
    /// the avatar's whole pipeline.
    pub inputs_leased: Vec<Box<dyn ReadLease>>,
    /// The avatar with the source's body parameters and motion windows.
    pub renderer: AvatarRenderer,
}

/// Opens the avatar `avatar` (a train entry: folder, key or key prefix) of the cache in
/// `store` and drives it with `poses` on `backend`: the source's poses with the avatar's
/// shape, and (for motion contexts with skeleton motion) motion windows computed from them
/// at the scales and velocity normalisation of the avatar's motion entry. With
/// `max_frames > 0` the poses are cut, before anything is computed from them, to what
/// drawing that many frames reads (windows look back only, so cutting the tail is exact);
/// the motion windows' memory is estimated against the budget before they are computed.
pub fn drive_avatar(
    store: &dyn Store,
    avatar: &str,
    poses: &PoseSource,
    backend: &Backend,
    max_frames: usize,
) -> anyhow::Result<DrivenAvatar> {
    let train = resolve_entry(store, "train", avatar)?;
    // Every entry the train entry read is leased at once, before any is verified or read, so
    // that a `gc` starting meanwhile finds them in use, and for as long as the avatar is
    // driven; those the avatar needs are opened below under leases of their own.
    let inputs_leased = train
        .manifest()
        .inputs
        .iter()
        .map(|input| store.read_lease(&EntryId::new(&input.kind, &input.key)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let trained_ingest = required(upstream_input(store, &train, "ingest"), &train, "ingest")?;
    let avatar = AvatarRenderer::load_avatar(&train)?;
    let model = avatar.rig.model.clone();
    let trained_params = seqavatar_schema::ingest::read_body_params(&trained_ingest, "body")?;
    let default_betas = trained_params
        .first()
        .map(|params| params.betas.clone())
        .unwrap_or_default();
    let motion_entry = if avatar.config.motion_context.has_skeleton_motion() {
        Some(required(
            upstream_input(store, &train, "motion"),
            &train,
            "motion",
        )?)
    } else {
        None
    };
    let raw_scales = match &motion_entry {
        Some(entry) => entry.read::<u32>("scales")?.data,
        None => Vec::new(),
    };
    let interval = seqavatar_schema::ingest::read_frame_interval(&trained_ingest)?;
    // The poses drawing `max_frames` frames reads: the first drawn frame is at most one
    // full window after the axis start.
    let pose_limit = if max_frames == 0 {
        usize::MAX
    } else {
        let largest_step = raw_scales
            .iter()
            .max()
            .map_or(0, |&s| (s / interval) as usize);
        let reach = avatar.config.sequence_length.saturating_mul(largest_step);
        max_frames.saturating_add(reach)
    };
    let mut sources: Vec<EntryReader> = motion_entry.iter().cloned().collect();
    // The avatar lives in its ingest entry's re-centred world, and so must its poses: a pose
    // file's translations are in the dataset's world, an ingest entry's in its own.
    let trained_offset = seqavatar_schema::ingest::read_world_offset(&trained_ingest)?;
    let moved = |params: Vec<BodyParams>, offset: DVec3| -> Vec<BodyParams> {
        params
            .into_iter()
            .map(|mut frame| {
                frame.world_translation += offset;
                frame
            })
            .collect()
    };
    // A pose file declares its frames in a few bytes (700 000 compress to 400 KB): their
    // motion windows are estimated from the arrays' headers, before any array is inflated.
    if let (Some(_), PoseSource::File(path)) = (&motion_entry, poses) {
        check_motion_memory(
            poses,
            declared_pose_frames(path)?.min(pose_limit),
            (model.num_vertices(), model.num_joints(), raw_scales.len()),
            seqavatar_engine::memory_budget_bytes().map_err(anyhow::Error::msg)?,
        )?;
    }
    let (params, axis) = match poses {
        PoseSource::File(path) => (
            moved(
                read_pose_file(path, model.num_joints(), &default_betas, pose_limit)?,
                -trained_offset,
            ),
            FrameAxis::FROM_START,
        ),
        PoseSource::Entry(spec) => {
            let entry = resolve_entry(store, "ingest", spec)?;
            sources.push(entry.clone());
            let source_model = seqavatar_schema::ingest::read_body_model(&entry)?;
            anyhow::ensure!(
                source_model.num_joints() == model.num_joints(),
                "poses of ingest entry {} have {} joints, the avatar's body model {}",
                entry.location(),
                source_model.num_joints(),
                model.num_joints()
            );
            // The subject's shape is the avatar's: keep the poses and world transform only.
            let offset = seqavatar_schema::ingest::read_world_offset(&entry)? - trained_offset;
            let params = seqavatar_schema::ingest::read_body_params(&entry, "body")?
                .into_iter()
                .take(pose_limit)
                .map(|mut frame| {
                    frame.betas = default_betas.clone();
                    frame.expression.clear();
                    frame
                })
                .collect();
            (moved(params, offset), FrameAxis::of_ingest(&entry)?)
        }
    };
    for (frame, frame_params) in params.iter().enumerate() {
        model
            .check_params(frame_params)
            .with_context(|| format!("poses, frame {frame}"))?;
    }
    let motion = if let Some(motion_entry) = &motion_entry {
        anyhow::ensure!(
            !seqavatar_schema::motion::has_garment_oracle(motion_entry),
            "the avatar's motion entry {} holds the garment oracle (the synthetic scene's true \
             garment state, motion config `garment_oracle`): other poses have no such state; \
             render the avatar on its own sequence (`pipeline run` with an eval stage)",
            motion_entry.location()
        );
        let (normalisation, input_scales) =
            seqavatar_schema::motion::read_input_scales(motion_entry)?;
        check_motion_memory(
            poses,
            params.len(),
            (model.num_vertices(), model.num_joints(), raw_scales.len()),
            seqavatar_engine::memory_budget_bytes().map_err(anyhow::Error::msg)?,
        )?;
        Some(seqavatar_context::compute::motion_track_for(
            &model,
            &params,
            &raw_scales,
            interval,
            normalisation,
            axis,
            &input_scales,
        )?)
    } else {
        None
    };
    let renderer = AvatarRenderer::new(
        avatar,
        params,
        motion,
        backend.clone(),
        train.location().to_owned(),
    )?;
    Ok(DrivenAvatar {
        train,
        trained_ingest,
        sources,
        inputs_leased,
        renderer,
    })
}

/// The frames a pose file declares (the first dimension of its `global_orient`), from that
/// array's header alone.
fn declared_pose_frames(path: &Path) -> anyhow::Result<usize> {
    let bytes = seqavatar_engine::files::read_regular_file(path)?;
    let file = path.display();
    let entries = npz::list(&bytes).with_context(|| format!("{file}: not a readable .npz"))?;
    let entry = entries
        .iter()
        .find(|entry| entry.name == "global_orient.npy")
        .ok_or_else(|| anyhow::anyhow!("{file}: missing array `global_orient`"))?;
    let header = npz::member_header(&bytes, entry)
        .with_context(|| format!("{file}: not a readable .npz"))?;
    Ok(header.shape.first().copied().unwrap_or(0))
}

/// Refuses motion windows for `frames` poses whose arrays would not fit the memory budget
/// `budget` (a pose file's frames are cheap to declare: 100 000 compress to 60 KB).
fn check_motion_memory(
    poses: &PoseSource,
    frames: usize,
    (vertices, joints, scales): (usize, usize, usize),
    budget: Option<u64>,
) -> anyhow::Result<()> {
    // Per frame, f32: posed vertices and their velocity per scale, joint rotations and their
    // motion per scale; twice, for the arrays and the track built from them.
    let (v, j, s) = (vertices as u64, joints as u64, scales as u64);
    let per_frame = 4 * 2 * (v * 3 * (1 + s) + j * (9 + 3 * s));
    seqavatar_engine::check_memory_budget(
        &format!(
            "--poses {}: motion windows for {frames} frames ({vertices} template vertices, \
             {scales} scales)",
            poses.describe()
        ),
        per_frame.saturating_mul(frames as u64),
        budget,
        "draw fewer with --max-frames",
    )
    .map_err(anyhow::Error::msg)
}

/// The frames of a driven avatar to draw: from its first frame with a complete motion
/// window, at most `max_frames` of them (0 = all).
pub fn frames_to_draw(renderer: &AvatarRenderer, max_frames: usize) -> std::ops::Range<usize> {
    let first = renderer.first_frame().min(renderer.num_frames());
    let count = renderer.num_frames() - first;
    let count = if max_frames == 0 {
        count
    } else {
        max_frames.min(count)
    };
    first..first + count
}

/// `pipeline render`.
pub fn render_poses(cache: &Path, options: &RenderOptions) -> anyhow::Result<RenderSummary> {
    anyhow::ensure!(
        options.resolution_scale.is_finite()
            && options.resolution_scale > 0.0
            && options.resolution_scale <= 4.0,
        "--resolution-scale {} must be in (0, 4]",
        options.resolution_scale
    );
    anyhow::ensure!(options.fps > 0, "--fps must be positive");
    let store = open_store(cache)?;
    // Kept whole to the end: its entries' read leases keep `gc` away while frames render.
    let mut driven = drive_avatar(
        store.as_ref(),
        &options.avatar,
        &options.poses,
        &options.backend,
        options.max_frames,
    )?;
    let renderer = &mut driven.renderer;
    let cameras = seqavatar_schema::ingest::read_cameras(&driven.trained_ingest)?;
    let camera = cameras
        .get(options.camera)
        .ok_or_else(|| {
            anyhow::anyhow!(
                "--camera {}: the avatar's ingest entry has {} cameras (0..{})",
                options.camera,
                cameras.len(),
                cameras.len().saturating_sub(1)
            )
        })?
        .rescaled(options.resolution_scale);
    // One frame in flight: drawn and written before the next is.
    seqavatar_engine::check_memory_budget(
        &format!(
            "--resolution-scale {}: frames of {} x {} pixels (camera {}), one in flight,",
            options.resolution_scale, camera.width, camera.height, options.camera
        ),
        crate::avatar_render::frames_memory_bytes(1, camera.width, camera.height),
        seqavatar_engine::memory_budget_bytes().map_err(anyhow::Error::msg)?,
        "lower --resolution-scale",
    )
    .map_err(anyhow::Error::msg)?;
    let range = frames_to_draw(renderer, options.max_frames);
    let skipped = range.start;
    std::fs::create_dir_all(&options.out)
        .with_context(|| format!("cannot create {}", options.out.display()))?;
    let started = std::time::Instant::now();
    let mut frames = Vec::with_capacity(range.len());
    for frame in range {
        let image = renderer.render(frame, &camera)?;
        let path = options.out.join(format!("frame_{frame:05}.png"));
        image
            .to_rgb_image()
            .save(&path)
            .with_context(|| format!("cannot write {}", path.display()))?;
        frames.push(path);
    }
    let seconds = started.elapsed().as_secs_f64();
    let (video, video_note) = match on_path("ffmpeg") {
        None => (
            None,
            Some("ffmpeg is not on PATH: PNG frames only".to_owned()),
        ),
        Some(ffmpeg) => {
            let video = options.out.join("render.mp4");
            let output = Command::new(ffmpeg)
                .args(["-y", "-loglevel", "error", "-framerate"])
                .arg(options.fps.to_string())
                .arg("-start_number")
                .arg(skipped.to_string())
                .arg("-i")
                .arg(options.out.join("frame_%05d.png"))
                .args([
                    "-vf",
                    "pad=ceil(iw/2)*2:ceil(ih/2)*2",
                    "-pix_fmt",
                    "yuv420p",
                ])
                .arg(&video)
                .output()
                .context("cannot run ffmpeg")?;
            if output.status.success() {
                (Some(video), None)
            } else {
                (
                    None,
                    Some(format!(
                        "ffmpeg failed ({}): {}",
                        output.status,
                        String::from_utf8_lossy(&output.stderr).trim()
                    )),
                )
            }
        }
    };
    Ok(RenderSummary {
        frames,
        skipped,
        video,
        video_note,
        seconds,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 100 000 frames of an SMPL-sized template at 3 scales need about 66 GB of motion
    /// windows: refused against a 16 GB budget, naming the file, the estimate and
    /// `--max-frames`; 100 frames pass.
    #[test]
    fn motion_windows_over_the_budget_are_refused_before_they_are_computed() {
        let poses = PoseSource::parse("long.npz");
        let smpl = (6890, 24, 3);
        let error = check_motion_memory(&poses, 100_000, smpl, Some(16 << 30))
            .unwrap_err()
            .to_string();
        for part in ["long.npz", "100000 frames", "66.5 GB", "--max-frames"] {
            assert!(error.contains(part), "`{error}` lacks {part}");
        }
        check_motion_memory(&poses, 100, smpl, Some(16 << 30)).unwrap();
        check_motion_memory(&poses, 100_000, smpl, None).unwrap();
    }
}
