//! What the viewer shows: a trained avatar opened through eval's public rendering API (the
//! renders eval scores), the dataset cameras of the ingest entry it was trained on, the orbit
//! frame around it, and the ground-truth images of that entry when the pose source is the
//! trained sequence itself.

use std::collections::HashMap;

use anyhow::Context as _;
use seqavatar_compute::backend::Backend;
use seqavatar_compute::image::ImageF32;
use seqavatar_core::camera::Camera;
use seqavatar_core::glam::DVec3;
use seqavatar_engine::{EntryReader, ReadLease, Store};
use seqavatar_evaluation::animate::{
    DrivenAvatar, PoseSource, drive_avatar, resolve_entry, upstream_input,
};
use seqavatar_evaluation::avatar_render::AvatarRenderer;
use seqavatar_evaluation::metrics::Mask;
use seqavatar_evaluation::testset::{TestImage, TestSet};

use crate::orbit::{OrbitFrame, mean_image_up, vertical_fov_deg};

/// The avatar to show and what drives it.
pub struct Scene {
    pub renderer: AvatarRenderer,
    /// The cameras of the ingest entry the avatar was trained on.
    pub cameras: Vec<Camera>,
    pub orbit: OrbitFrame,
    /// The orbit view that starts where dataset camera 0 is: azimuth, elevation (degrees),
    /// distance (metres) and vertical field of view (degrees).
    pub home: [f64; 4],
    /// Present when the poses are the trained sequence's: its images by (view, frame).
    pub truth: Option<GroundTruth>,
    /// Whether the avatar takes motion-history inputs that the context probes can replace.
    pub context_probes: bool,
    /// The train entry, for the page's title.
    pub avatar: String,
    /// Where the poses come from, in words.
    pub poses: String,
    /// What moves the avatar's world back to the dataset's (ingest's re-centring undone), as
    /// `pipeline export` writes posed frames.
    pub world_offset: DVec3,
    // The entries stay open (and under their read leases) while the viewer serves them, and
    // so do the leases of a driven avatar's other inputs.
    _entries: Vec<EntryReader>,
    _leases: Vec<Box<dyn ReadLease>>,
}

/// The images of an ingest entry, found by (view, frame) on any split.
pub struct GroundTruth {
    ingest: EntryReader,
    testset: TestSet,
    by_view_frame: HashMap<(usize, usize), usize>,
}

impl GroundTruth {
    /// Indexes the images of `ingest`, read with eval's reader of the ingest schema.
    pub fn read(ingest: &EntryReader) -> anyhow::Result<Self> {
        let testset = TestSet::read(ingest)?;
        let arrays = &testset.arrays;
        let by_view_frame = (0..arrays.len())
            .map(|index| {
                (
                    (arrays.view[index] as usize, arrays.frame[index] as usize),
                    index,
                )
            })
            .collect();
        Ok(Self {
            ingest: ingest.clone(),
            testset,
            by_view_frame,
        })
    }

    /// The image and foreground mask of `view` at `frame` at the camera's size, `None` when
    /// the entry has none.
    pub fn image(&self, view: usize, frame: usize) -> anyhow::Result<Option<(ImageF32, Mask)>> {
        let Some(&index) = self.by_view_frame.get(&(view, frame)) else {
            return Ok(None);
        };
        let image = TestImage { index, view, frame };
        Ok(Some(self.testset.load(&self.ingest, &image)?))
    }

    /// The garment mask of `view` at `frame` at the camera's size; `None` when the entry has
    /// no garment region or no image of (view, frame).
    pub fn garment(&self, view: usize, frame: usize) -> anyhow::Result<Option<Mask>> {
        let Some(&index) = self.by_view_frame.get(&(view, frame)) else {
            return Ok(None);
        };
        let image = TestImage { index, view, frame };
        self.testset.load_garment(&self.ingest, &image)
    }
}

impl Scene {
    /// Opens the avatar of the train entry `avatar` (folder, key or key prefix). Without
    /// `poses` it is driven as eval drives it (the body parameters of its fit entry, or of its
    /// ingest entry, and its motion entry), and the ingest images are its ground truth; with
    /// `poses` as `pipeline render` drives it.
    pub fn open(
        store: &dyn Store,
        avatar: &str,
        poses: Option<&PoseSource>,
        backend: &Backend,
    ) -> anyhow::Result<Self> {
        let (mut renderer, ingest, truth, poses_text, entries, leases) = match poses {
            Some(source) => {
                let DrivenAvatar {
                    train,
                    trained_ingest,
                    sources,
                    inputs_leased,
                    renderer,
                } = drive_avatar(store, avatar, source, backend, 0)?;
                let text = match source {
                    PoseSource::Entry(spec) => format!("ingest entry {spec}"),
                    PoseSource::File(path) => format!("pose file {}", path.display()),
                };
                let mut entries = vec![train, trained_ingest.clone()];
                entries.extend(sources);
                (renderer, trained_ingest, None, text, entries, inputs_leased)
            }
            None => {
                let train = resolve_entry(store, "train", avatar)?;
                let ingest = upstream_input(store, &train, "ingest")?.ok_or_else(|| {
                    anyhow::anyhow!("train entry {} records no ingest input", train.location())
                })?;
                let fit = upstream_input(store, &train, "fit")?;
                let motion = upstream_input(store, &train, "motion")?;
                let renderer = AvatarRenderer::open(
                    &train,
                    &ingest,
                    fit.as_ref().unwrap_or(&ingest),
                    motion.as_ref(),
                    backend,
                )?;
                let truth = GroundTruth::read(&ingest)
                    .with_context(|| format!("the images of ingest entry {}", ingest.location()))?;
                let text = format!(
                    "the trained sequence (body parameters of the {} entry)",
                    if fit.is_some() { "fit" } else { "ingest" }
                );
                let mut entries = vec![train, ingest.clone()];
                entries.extend(fit);
                entries.extend(motion);
                (renderer, ingest, Some(truth), text, entries, Vec::new())
            }
        };
        let cameras = seqavatar_schema::ingest::read_cameras(&ingest)?;
        let world_offset = seqavatar_schema::ingest::read_world_offset(&ingest)?;
        anyhow::ensure!(
            !cameras.is_empty(),
            "ingest entry {} has no cameras",
            ingest.location()
        );
        let first = renderer.first_frame();
        anyhow::ensure!(
            first < renderer.num_frames(),
            "the pose source has {} frames, none with a complete motion window (the first is {first})",
            renderer.num_frames()
        );
        // The avatar's centre: the mean of its Gaussians at the first drawable frame.
        let deformed = renderer.deform(first)?;
        let means = &deformed.means;
        anyhow::ensure!(!means.is_empty(), "the avatar has no Gaussians");
        let centre =
            means.chunks_exact(3).map(DVec3::from_slice).sum::<DVec3>() / (means.len() / 3) as f64;
        let up = mean_image_up(&cameras).unwrap_or(DVec3::NEG_Y);
        let orbit = OrbitFrame::new(centre, up, cameras[0].center() - centre).ok_or_else(|| {
            anyhow::anyhow!("cannot place an orbit camera: the avatar's centre is {centre}")
        })?;
        let (azimuth, elevation, distance) = orbit.angles_of(cameras[0].center());
        let limit = crate::request::MAX_ELEVATION_DEG;
        let home = [
            crate::orbit::wrap_degrees(azimuth),
            elevation.clamp(-limit, limit),
            distance.clamp(
                crate::request::DISTANCE_RANGE.0,
                crate::request::DISTANCE_RANGE.1,
            ),
            vertical_fov_deg(&cameras[0]).clamp(
                crate::request::FOV_RANGE_DEG.0,
                crate::request::FOV_RANGE_DEG.1,
            ),
        ];
        let mut renderer = renderer;
        // Whether the probes apply: set and cleared again.
        let context_probes = seqavatar_evaluation::evaluate::ViewRenderer::set_context_probe(
            &mut renderer,
            Some(seqavatar_evaluation::context_probe::ContextProbe::Zeroed),
        );
        seqavatar_evaluation::evaluate::ViewRenderer::set_context_probe(&mut renderer, None);
        let avatar = entries[0].location().to_owned();
        Ok(Self {
            renderer,
            cameras,
            orbit,
            home,
            truth,
            context_probes,
            avatar,
            poses: poses_text,
            world_offset,
            _entries: entries,
            _leases: leases,
        })
    }
}
