//! `pipeline export`: a trained avatar's Gaussians as standard 3D Gaussian Splatting PLY
//! files ([`seqavatar_avatar::ply`]): `canonical.ply` (the canonical, big-pose Gaussians as
//! trained) and, with a pose source (the sources `pipeline render` takes), one
//! `frame_NNNNN.ply` per frame with the posed Gaussians exactly as the render path splats
//! them (networks, skinning), so a splat viewer draws what `pipeline render` draws. Posed
//! frames are in the dataset's world (ingest's re-centring undone); PLY positions are f32,
//! so a world far from its origin rounds them (to 1 mm at 10 km).

use std::path::{Path, PathBuf};

use anyhow::Context as _;
use seqavatar_avatar::ply::{SplatCloud, canonical_cloud, posed_cloud, write_ply};
use seqavatar_avatar::splatting::WorldGaussians;
use seqavatar_compute::backend::Backend;
use seqavatar_core::glam::DVec3;
use seqavatar_engine::open_store;

use crate::animate::{PoseSource, drive_avatar, frames_to_draw, resolve_entry};
use crate::avatar_render::AvatarRenderer;

/// Options of `pipeline export`.
#[derive(Clone, Debug)]
pub struct ExportOptions {
    /// A train entry: its folder in a cache, its key, or a unique key prefix.
    pub avatar: String,
    /// Where the poses of the posed frames come from; `None` writes the canonical file only.
    pub poses: Option<PoseSource>,
    pub out: PathBuf,
    pub backend: Backend,
    /// Export at most this many frames (0 = all).
    pub max_frames: usize,
    /// Show a progress bar (on a terminal).
    pub progress: bool,
}

/// What `pipeline export` wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct ExportSummary {
    pub canonical: PathBuf,
    pub frames: Vec<PathBuf>,
    /// Leading frames not exported (see [`crate::animate::RenderSummary::skipped`]).
    pub skipped: usize,
    pub gaussians: usize,
    pub seconds: f64,
}

fn write_file(path: &Path, cloud: &SplatCloud) -> anyhow::Result<()> {
    let bytes = write_ply(cloud).with_context(|| format!("cannot encode {}", path.display()))?;
    std::fs::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}

/// One frame's posed Gaussians `world` (from [`AvatarRenderer::deform`]) as the 3DGS PLY
/// file `pipeline export` writes: moved by `offset` back to the dataset's world (ingest's
/// re-centring undone; `read_world_offset` of the ingest entry), with the avatar's opacity
/// logits.
pub fn posed_ply(
    mut world: WorldGaussians,
    offset: DVec3,
    opacity_logit: &[f64],
) -> anyhow::Result<Vec<u8>> {
    for mean in world.means.chunks_exact_mut(3) {
        for (value, shift) in mean.iter_mut().zip(offset.to_array()) {
            *value += shift;
        }
    }
    let cloud = posed_cloud(&world, opacity_logit)?;
    Ok(write_ply(&cloud)?)
}

/// `pipeline export`.
pub fn export_avatar(cache: &Path, options: &ExportOptions) -> anyhow::Result<ExportSummary> {
    let store = open_store(cache)?;
    let started = std::time::Instant::now();
    let train = resolve_entry(store.as_ref(), "train", &options.avatar)?;
    let avatar = AvatarRenderer::load_avatar(&train)?;
    std::fs::create_dir_all(&options.out)
        .with_context(|| format!("cannot create {}", options.out.display()))?;
    let canonical = options.out.join("canonical.ply");
    let cloud = canonical_cloud(&avatar.gaussians, avatar.sh_degree)
        .with_context(|| format!("the avatar of entry {}", train.location()))?;
    write_file(&canonical, &cloud)?;
    let gaussians = cloud.len();
    let Some(poses) = &options.poses else {
        return Ok(ExportSummary {
            canonical,
            frames: Vec::new(),
            skipped: 0,
            gaussians,
            seconds: started.elapsed().as_secs_f64(),
        });
    };
    // Kept whole to the end: its entries' read leases keep `gc` away while frames are written.
    let mut driven = drive_avatar(
        store.as_ref(),
        &options.avatar,
        poses,
        &options.backend,
        options.max_frames,
    )?;
    let renderer = &mut driven.renderer;
    // The posed Gaussians go back to the dataset's world, where the poses were given (a
    // pose file's translations; an ingest entry of the same world's).
    let offset = seqavatar_schema::ingest::read_world_offset(&driven.trained_ingest)?;
    let range = frames_to_draw(renderer, options.max_frames);
    let skipped = range.start;
    let bar = if options.progress {
        indicatif::ProgressBar::new(range.len() as u64)
    } else {
        indicatif::ProgressBar::hidden()
    };
    bar.set_style(
        indicatif::ProgressStyle::with_template("exporting {bar:30} {pos}/{len} frames {eta}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let logits = renderer.avatar.gaussians.opacity_logit.clone();
    let mut frames = Vec::with_capacity(range.len());
    for frame in range {
        let bytes = posed_ply(renderer.deform(frame)?, offset, &logits)
            .with_context(|| format!("frame {frame} of the poses"))?;
        let path = options.out.join(format!("frame_{frame:05}.ply"));
        std::fs::write(&path, bytes).with_context(|| format!("cannot write {}", path.display()))?;
        frames.push(path);
        bar.inc(1);
    }
    bar.finish_and_clear();
    Ok(ExportSummary {
        canonical,
        frames,
        skipped,
        gaussians,
        seconds: started.elapsed().as_secs_f64(),
    })
}
