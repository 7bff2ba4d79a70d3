//! The `ingest` stage kind: opens the dataset reader, resolves the plan, and writes the
//! arrays documented in `lib.rs` (through [`crate::schema`]).
//!
//! The items other crates import from this module are re-exported from their homes.

use std::path::PathBuf;

use anyhow::Context;
use rayon::prelude::*;
use seqavatar_core::body::{BodyModel, BodyParams};
use seqavatar_core::camera::Camera;
use seqavatar_engine::{
    ConfigError, EntryReader, EntryWriter, PictureKind, PictureOptions, StageContext, StageKind,
};

use crate::config::IngestConfig;
use crate::plan::IngestPlan;
use crate::world::{NamedCamera, geometry_warnings, world_offset};
use seqavatar_core::glam::DVec3;
use seqavatar_datasets::{BodyModelKind, DatasetReader, open_reader};
use seqavatar_formats::resample::{resample, resample_with_region};
use seqavatar_schema::ingest::{
    self as schema, ImageArrays, Keypoints3d, SourceCamera, write_body_model, write_body_params,
    write_keypoints_3d,
};

/// The `ingest` stage kind.
pub struct Ingest;

/// Implementation version: bump whenever the written arrays change for the same config.
/// 3: images and masks decode strictly (a truncated JPEG was accepted with grey rows), so
/// entries made by the lenient decoder are not served again.
/// 4: attribute `first_frame_index` (where the frame axis starts in the recording).
/// 5: array `garment_masks` and attribute `garment_region` (the synthetic skirt, ZJU-MoCap's
///    CIHP clothing labels); the other arrays are unchanged.
/// 6: array `garment_state` beside the garment history (the history scene's oscillator).
/// 7: the world re-centred on the subject (attribute `world_offset`): camera extrinsics,
///    body translations and keypoints are relative to it.
pub const INGEST_VERSION: u32 = 7;

impl StageKind for Ingest {
    type Config = IngestConfig;

    fn kind(&self) -> &'static str {
        "ingest"
    }

    fn version(&self) -> u32 {
        INGEST_VERSION
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        &[]
    }

    fn planned(&self, config: &IngestConfig) -> serde_json::Value {
        serde_json::to_value(config.planned()).unwrap_or_default()
    }

    fn resolve_config(&self, raw: &serde_json::Value) -> Result<IngestConfig, ConfigError> {
        let config: IngestConfig = seqavatar_engine::parse_config(raw)?;
        config.validate()?;
        Ok(config)
    }

    fn external_files(&self, config: &IngestConfig) -> anyhow::Result<Vec<PathBuf>> {
        let mut files: Vec<PathBuf> = config.body_model.iter().cloned().collect();
        files.extend(seqavatar_datasets::sources::source_files(&config.dataset));
        Ok(files)
    }

    fn run(&self, config: &IngestConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        // Ranges were checked when the pipeline loaded (resolve_config).
        let reader = open_reader(&config.dataset, config.body_model.as_deref())?;
        ctx.log(&format!("reading {}", reader.describe()));
        let split = config.split.apply(reader.default_split());
        let plan = IngestPlan::new(
            &split,
            reader.cameras().len(),
            reader.num_frames(),
            config.past_frames,
        )?;
        ctx.log(&format!(
            "{} views, {} frames ({} with images), {} images",
            plan.views.len(),
            plan.frames.len(),
            plan.frame_split.iter().filter(|s| **s != 0).count(),
            plan.images.len()
        ));
        let out = ctx.output();
        // In the dataset's world: images are resampled and the garment's history measured
        // there, where the reader's cameras and garment are.
        let cameras = ingested_cameras(reader.as_ref(), &plan, config.resolution_scale)?;
        check_staging_memory(reader.as_ref(), &plan, &cameras, config.resolution_scale)?;
        let sources: Vec<&SourceCamera> =
            plan.views.iter().map(|&v| &reader.cameras()[v]).collect();
        let (model, kind) = reader.body_model()?;
        write_body_model(out, &model)?;
        let (offset, fits) = write_frames(out, reader.as_ref(), &plan, &model)?;
        if offset != DVec3::ZERO {
            ctx.log(&format!(
                "world re-centred on the subject: the dataset's {offset} m is the origin"
            ));
        }
        let centred: Vec<Camera> = cameras.iter().map(|c| c.with_origin_at(offset)).collect();
        schema::write_cameras(out, &centred, &sources)?;
        schema::write_world_offset(out, offset)?;
        let named: Vec<NamedCamera<'_>> = centred
            .iter()
            .zip(&sources)
            .map(|(camera, source)| NamedCamera {
                id: source.id,
                camera,
            })
            .collect();
        let frame_ids: Vec<i64> = plan.frames.iter().map(|&f| reader.frame_id(f)).collect();
        for warning in geometry_warnings(&model, &fits, &frame_ids, &named)? {
            ctx.warn(&format!("{}: {warning}", reader.describe()));
        }
        if let Some(history) = garment_history(reader.as_ref(), &plan, &cameras)? {
            let flagged = history.frames.iter().filter(|f| **f).count();
            ctx.log(&format!(
                "garment history: {flagged} of {} frames move the garment by more than {} px from its static drape",
                history.frames.len(),
                schema::HISTORY_FRAME_PX
            ));
            schema::write_garment_history(out, &history)?;
        }

        write_images(ctx, reader.as_ref(), &plan, &cameras)?;
        write_attributes(out, config, &plan, kind)
    }

    fn pictures(&self) -> Vec<PictureKind> {
        vec![
            PictureKind {
                name: "contact_sheet",
                description: "grid of ingested images with their masks overlaid in green, history frames framed in red (options: split=train|test|all, max=N images, columns=N)",
            },
            PictureKind {
                name: "history",
                description: "the garment's history-only displacement per frame (px), history frames in red, the threshold in blue (history scene only; option: height=N)",
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
            "contact_sheet" => crate::contact_sheet::contact_sheet(entry, options),
            "history" => crate::contact_sheet::history_chart(entry, options),
            _ => Err(seqavatar_engine::unknown_picture(self, picture)),
        }
    }
}

/// Bytes per pixel of an ingested image staged in flight: RGB, mask and garment mask, as
/// resampled, as padded into its chunk and as encoded.
const STAGED_BYTES_PER_PIXEL: u64 = 3 * (3 + 1 + 1);

/// Refuses, before any image is read, images in flight ([`write_images`]: one per thread,
/// its decoded source and its staged chunks) that would not fit the memory budget.
fn check_staging_memory(
    reader: &dyn DatasetReader,
    plan: &IngestPlan,
    cameras: &[Camera],
    resolution_scale: f64,
) -> anyhow::Result<()> {
    let pixels = |camera: &Camera| u64::from(camera.width) * u64::from(camera.height);
    let source = plan
        .views
        .iter()
        .map(|&view| pixels(&reader.cameras()[view].camera))
        .max()
        .unwrap_or(0);
    let staged = cameras.iter().map(pixels).max().unwrap_or(0);
    let threads = rayon::current_num_threads() as u64;
    let per_image = source
        .saturating_mul(seqavatar_formats::images::MAX_BYTES_PER_PIXEL)
        .saturating_add(staged.saturating_mul(STAGED_BYTES_PER_PIXEL));
    seqavatar_engine::check_memory_budget(
        &format!(
            "resolution_scale {resolution_scale}: the images in flight ({threads} threads, each \
             a source image of up to {source} pixels staged as up to {staged} pixels)"
        ),
        threads.saturating_mul(per_image),
        seqavatar_engine::memory_budget_bytes().map_err(anyhow::Error::msg)?,
        "lower resolution_scale",
    )
    .map_err(anyhow::Error::msg)
}

/// Resamples every planned image (and its mask, and its garment mask where the reader has a
/// garment region) to its ingested camera and writes them, in parallel, one chunk each
/// (nothing but the images in flight is held), then the per-image view, frame and split
/// arrays.
fn write_images(
    ctx: &StageContext<'_>,
    reader: &dyn DatasetReader,
    plan: &IngestPlan,
    cameras: &[Camera],
) -> anyhow::Result<()> {
    let out = ctx.output();
    let max_h = cameras.iter().map(|c| c.height).max().unwrap_or(1) as u64;
    let max_w = cameras.iter().map(|c| c.width).max().unwrap_or(1) as u64;
    let n = plan.images.len() as u64;
    // `garment_masks` is chunked as `masks`, through the same resampling, so the two stay
    // aligned.
    let (images, masks, garment_masks) =
        ImageArrays::create(out, n, [max_h, max_w], reader.garment_region())?;
    let bar = ctx.progress_bar(n, "images");
    plan.images.par_iter().enumerate().try_for_each(
        |(index, &(view, frame, _))| -> anyhow::Result<()> {
            let source_view = plan.views[view];
            let source_frame = plan.frames[frame];
            let image_name = || {
                format!(
                    "{}: camera {} frame {}",
                    reader.describe(),
                    reader.cameras()[source_view].id,
                    reader.frame_id(source_frame)
                )
            };
            let source_camera = &reader.cameras()[source_view].camera;
            let (w, h) = (cameras[view].width as usize, cameras[view].height as usize);
            let (mw, mh) = (max_w as usize, max_h as usize);
            // One plane of `h x w` values per pixel into the top-left of a `mh x mw` chunk.
            let padded = |plane: &[u8], channels: usize| {
                let mut chunk = vec![0u8; mh * mw * channels];
                for row in 0..h {
                    chunk[row * mw * channels..(row * mw + w) * channels]
                        .copy_from_slice(&plane[row * w * channels..(row + 1) * w * channels]);
                }
                chunk
            };
            let (rgb, mask) = if let Some(garment_masks) = &garment_masks {
                let (source, garment) = reader
                    .read_image_with_garment(source_view, source_frame)
                    .with_context(image_name)?;
                let garment = garment
                    .ok_or_else(|| anyhow::anyhow!("the reader returned no garment mask"))
                    .with_context(image_name)?;
                let resampled =
                    resample_with_region(&source, &garment, source_camera, &cameras[view])
                        .with_context(image_name)?;
                garment_masks.write_chunk(&[index as u64, 0, 0], &padded(&resampled.region, 1))?;
                (resampled.rgb, resampled.mask)
            } else {
                let source = reader
                    .read_image(source_view, source_frame)
                    .with_context(image_name)?;
                resample(&source, source_camera, &cameras[view]).with_context(image_name)?
            };
            images.write_chunk(&[index as u64, 0, 0, 0], &padded(&rgb, 3))?;
            masks.write_chunk(&[index as u64, 0, 0], &padded(&mask, 1))?;
            bar.inc(1);
            Ok(())
        },
    )?;
    bar.finish_and_clear();
    ImageArrays::write_index(out, &plan.images)
}

/// The entry's attributes: where the data came from and how it was sampled.
fn write_attributes(
    out: &EntryWriter,
    config: &IngestConfig,
    plan: &IngestPlan,
    kind: BodyModelKind,
) -> anyhow::Result<()> {
    let dataset = serde_json::to_value(&config.dataset)?
        .get("kind")
        .cloned()
        .unwrap_or(serde_json::Value::Null);
    out.set_attribute("dataset", dataset)?;
    out.set_attribute("body_model_kind", kind.as_str().into())?;
    schema::write_frame_interval(out, plan.frame_interval)?;
    out.set_attribute("resolution_scale", config.resolution_scale.into())?;
    out.set_attribute("past_frames", config.past_frames.into())?;
    // Where the frame axis starts in the recording, so that motion windows clamp only at
    // the recording's true start (`seqavatar_schema::motion::FrameAxis`).
    out.set_attribute("first_frame_index", plan.frames[0].into())?;
    let train = plan.images.iter().filter(|image| image.2 == 0).count();
    out.set_attribute("num_train_images", train.into())?;
    out.set_attribute("num_test_images", (plan.images.len() - train).into())?;
    out.set_attribute("background", serde_json::json!([0, 0, 0]))?;
    Ok(())
}

/// The rescaled, distortion-free camera of every ingested view.
fn ingested_cameras(
    reader: &dyn DatasetReader,
    plan: &IngestPlan,
    scale: f64,
) -> anyhow::Result<Vec<Camera>> {
    plan.views
        .iter()
        .map(|&view| {
            let source = &reader.cameras()[view];
            source
                .camera
                .validate()
                .with_context(|| format!("{}: camera {}", reader.describe(), source.id))?;
            let mut camera = source.camera.rescaled(scale);
            camera.distortion = [0.0; 5];
            Ok(camera)
        })
        .collect()
}

/// The garment's history-only displacement per frame of the plan, where the reader knows it:
/// RMS over particles of `|simulated - drape|` (mm), and RMS over particles and ingested views
/// of the distance between their projections (pixels of the ingested images; a particle
/// behind a camera is left out of that view).
fn garment_history(
    reader: &dyn DatasetReader,
    plan: &IngestPlan,
    cameras: &[Camera],
) -> anyhow::Result<Option<schema::GarmentHistoryArrays>> {
    let Some(first) = plan.frames.first() else {
        return Ok(None);
    };
    if reader.garment_history(*first)?.is_none() {
        return Ok(None);
    }
    let rows = plan
        .frames
        .par_iter()
        .map(|&f| {
            let context = || {
                format!(
                    "{}: garment of frame {}",
                    reader.describe(),
                    reader.frame_id(f)
                )
            };
            let garment = reader
                .garment_history(f)
                .with_context(context)?
                .ok_or_else(|| anyhow::anyhow!("no garment history"))
                .with_context(context)?;
            anyhow::ensure!(
                garment.simulated.len() == garment.drape.len() && !garment.drape.is_empty(),
                "{}: {} simulated particles, {} draped",
                context(),
                garment.simulated.len(),
                garment.drape.len()
            );
            let pairs = garment.simulated.iter().zip(&garment.drape);
            let metres = (pairs
                .clone()
                .map(|(a, b)| (*a - *b).length_squared())
                .sum::<f64>()
                / garment.drape.len() as f64)
                .sqrt();
            let (mut squared, mut count) = (0.0, 0usize);
            for camera in cameras {
                for (a, b) in pairs.clone() {
                    if let (Some(pa), Some(pb)) = (camera.project(*a), camera.project(*b)) {
                        squared += (pa - pb).length_squared();
                        count += 1;
                    }
                }
            }
            Ok((
                metres * 1e3,
                (squared / count.max(1) as f64).sqrt(),
                garment.state,
            ))
        })
        .collect::<anyhow::Result<Vec<(f64, f64, _)>>>()?;
    let pixels: Vec<f64> = rows.iter().map(|r| r.1).collect();
    Ok(Some(schema::GarmentHistoryArrays {
        frames: pixels
            .iter()
            .map(|p| *p > schema::HISTORY_FRAME_PX)
            .collect(),
        millimetres: rows.iter().map(|r| r.0).collect(),
        pixels,
        states: rows.iter().map(|r| r.2).collect(),
    }))
}

/// Writes the frame axis and the per-frame body parameters (fits and, where known, truth)
/// and keypoints, relative to the world offset; returns it and the fits as written.
fn write_frames(
    out: &EntryWriter,
    reader: &dyn DatasetReader,
    plan: &IngestPlan,
    model: &BodyModel,
) -> anyhow::Result<(DVec3, Vec<BodyParams>)> {
    let n = plan.frames.len() as u64;
    let ids: Vec<i64> = plan.frames.iter().map(|&f| reader.frame_id(f)).collect();
    out.write_array("frame_source_id", &["frame"], &[n], &[n], &ids)?;
    out.write_array("frame_split", &["frame"], &[n], &[n], &plan.frame_split)?;
    let fit_of = |f: usize| {
        format!(
            "{}: body fit of frame {}",
            reader.describe(),
            reader.frame_id(f)
        )
    };
    let fits = plan
        .frames
        .par_iter()
        .map(|&f| reader.body_params(f).with_context(|| fit_of(f)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let offset = world_offset(&fits, &reader.describe())?;
    let centred = |mut params: BodyParams| {
        params.world_translation -= offset;
        params
    };
    // Checked relative to the offset: the translation limit is about the scene, not about
    // where its world put it.
    let fits = plan
        .frames
        .par_iter()
        .zip(fits)
        .map(|(&f, params)| {
            let params = centred(params);
            model.check_params(&params).with_context(|| fit_of(f))?;
            Ok(params)
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    write_body_params(out, "body", &fits, model)?;
    let truth = plan
        .frames
        .iter()
        .map(|&f| reader.ground_truth_body_params(f))
        .collect::<anyhow::Result<Vec<_>>>()?;
    if truth.iter().all(Option::is_some) {
        let truth: Vec<BodyParams> = truth.into_iter().flatten().map(centred).collect();
        write_body_params(out, "gt_body", &truth, model)?;
    }
    if let Some(keypoints) = reader.keypoints_3d()? {
        let describe = reader.describe();
        let rows = keypoints.num_frames();
        let k = keypoints.num_keypoints();
        anyhow::ensure!(
            keypoints.positions.len() == rows * k
                && keypoints.confidence.len() == rows * k
                && rows >= reader.num_frames(),
            "{describe}: 3D keypoints have {} positions and {} confidences for {k} keypoints; expected {} frames x {k}",
            keypoints.positions.len(),
            keypoints.confidence.len(),
            reader.num_frames()
        );
        let selected = Keypoints3d {
            joints: keypoints.joints.clone(),
            positions: plan
                .frames
                .iter()
                .flat_map(|&f| keypoints.positions[f * k..(f + 1) * k].iter())
                .map(|p| *p - offset)
                .collect(),
            confidence: plan
                .frames
                .iter()
                .flat_map(|&f| keypoints.confidence[f * k..(f + 1) * k].iter().copied())
                .collect(),
        };
        write_keypoints_3d(out, &selected, model)
            .with_context(|| format!("{describe}: 3D keypoints"))?;
    }
    Ok((offset, fits))
}

#[cfg(test)]
mod stage_tests {
    use super::*;
    use seqavatar_datasets::DatasetConfig;
    use seqavatar_engine::{EntryId, LocalStore, Pipeline, Registry, RunOptions, Store};
    use seqavatar_schema::ingest::{read_body_model, read_body_params, read_keypoints_3d};

    const TINY: &str = "stages:\n  - name: ingest\n    kind: ingest\n    config:\n      dataset: {kind: synthetic, cameras: 3, frames: 4, width: 48, height: 40, supersample: 1, body_grid_spacing: 0.04}\n      past_frames: 2\n";

    fn run_pipeline(text: &str) -> (tempfile::TempDir, EntryReader) {
        let dir = tempfile::tempdir().unwrap();
        let mut registry = Registry::new();
        crate::register(&mut registry);
        let file = dir.path().join("p.yaml");
        std::fs::write(&file, text).unwrap();
        let pipeline = Pipeline::load(&file, &registry, &[]).unwrap();
        let store = LocalStore::open(&dir.path().join("cache")).unwrap();
        let reports =
            seqavatar_engine::run(&pipeline, &registry, &store, &RunOptions::default()).unwrap();
        let entry = store
            .open_entry(&EntryId::new("ingest", &reports[0].key))
            .unwrap();
        (dir, entry)
    }

    #[test]
    fn synthetic_ingest_writes_the_documented_schema() {
        let (_dir, entry) = run_pipeline(TINY);
        // 3 cameras: view 1 tests, views 0 and 2 train on all 4 frames; test every 2nd frame.
        assert_eq!(entry.shape("images").unwrap(), vec![10, 40, 48, 3]);
        assert_eq!(entry.shape("masks").unwrap(), vec![10, 40, 48]);
        let split = entry.read::<u8>("image_split").unwrap().data;
        assert_eq!(split.iter().filter(|s| **s == 0).count(), 8);
        assert_eq!(
            entry.read::<i64>("frame_source_id").unwrap().data,
            vec![0, 1, 2, 3]
        );
        assert_eq!(
            entry.attribute("body_model_kind"),
            Some("procedural".into())
        );
        assert_eq!(entry.attribute("num_test_images"), Some(2.into()));

        let model = read_body_model(&entry).unwrap();
        assert_eq!(model.num_joints(), 24);
        let fits = read_body_params(&entry, "body").unwrap();
        let truth = read_body_params(&entry, "gt_body").unwrap();
        assert_eq!(fits.len(), 4);
        assert_eq!(truth.len(), 4);
        assert!(fits[0].pose != truth[0].pose, "the fits are jittered");
        let pose_error: f64 = fits[2]
            .pose
            .iter()
            .zip(&truth[2].pose)
            .map(|(a, b)| (*a - *b).length())
            .sum::<f64>()
            / 24.0;
        assert!(pose_error > 0.01 && pose_error < 0.2, "{pose_error}");

        // 3D keypoints: keypoint j is joint j, the true joint position plus ~1 cm noise.
        let keypoints = read_keypoints_3d(&entry)
            .unwrap()
            .expect("synthetic keypoints");
        assert_eq!(entry.shape("keypoints_3d").unwrap(), vec![4, 24, 3]);
        assert_eq!(keypoints.joints, (0..24).map(Some).collect::<Vec<_>>());
        assert!(keypoints.confidence.iter().all(|c| *c == 1.0));
        let mut squared = 0.0;
        for (f, params) in truth.iter().enumerate() {
            let joints = model.forward(params).unwrap().joints;
            for (j, joint) in joints.iter().enumerate() {
                squared += (keypoints.positions[f * 24 + j] - *joint).length_squared();
            }
        }
        // Mean squared distance of 3 coordinates with sigma 1 cm: 3e-4 m^2.
        let mean_squared = squared / 96.0;
        assert!(
            mean_squared > 1.5e-4 && mean_squared < 5e-4,
            "{mean_squared}"
        );

        // Camera convention: the true pelvis and a point on the torso surface project onto
        // the foreground of every image through the stored K, R, t.
        let k = entry.read::<f64>("camera_K").unwrap().data;
        let r = entry.read::<f64>("camera_R").unwrap().data;
        let t = entry.read::<f64>("camera_t").unwrap().data;
        let views = entry.read::<u32>("image_view").unwrap().data;
        let frames = entry.read::<u32>("image_frame").unwrap().data;
        for image in 0..views.len() {
            let (v, f) = (views[image] as usize, frames[image] as usize);
            let posed = model.forward(&truth[f]).unwrap();
            let x = posed.joints[3];
            let cam: Vec<f64> = (0..3)
                .map(|row| {
                    (0..3)
                        .map(|col| r[v * 9 + row * 3 + col] * x[col])
                        .sum::<f64>()
                        + t[v * 3 + row]
                })
                .collect();
            let u = k[v * 9] * cam[0] / cam[2] + k[v * 9 + 2];
            let w = k[v * 9 + 4] * cam[1] / cam[2] + k[v * 9 + 5];
            let mask = entry
                .read_region::<u8>("masks", &[image as u64, 0, 0], &[1, 40, 48])
                .unwrap();
            let (col, row) = (u.floor() as usize, w.floor() as usize);
            assert!(
                mask.data[row * 48 + col] > 128,
                "image {image}: spine1 at ({u}, {w}) is background"
            );
            // The image border is background (the focal length keeps 4 % margins).
            assert_eq!(mask.data[0], 0);
        }
        // Garment region: the skirt's coverage, chunked as the masks, never above the mask,
        // non-empty in every image (the skirt is in every view), and inside the box the
        // skirt's particles (the scene's own, independently) project to.
        assert_eq!(
            schema::read_garment_region(&entry).unwrap(),
            Some(seqavatar_datasets::GarmentRegion::SyntheticSkirt)
        );
        assert_eq!(entry.shape("garment_masks").unwrap(), vec![10, 40, 48]);
        let scene = seqavatar_datasets::synthetic::SyntheticScene::generate(
            &seqavatar_datasets::synthetic::SyntheticConfig {
                cameras: 3,
                frames: 4,
                width: 48,
                height: 40,
                supersample: 1,
                body_grid_spacing: 0.04,
                ..Default::default()
            },
        )
        .unwrap();
        // The scene's own skirt is in the dataset's world; the entry's cameras are re-centred.
        let offset = schema::read_world_offset(&entry).unwrap();
        let cameras: Vec<Camera> = schema::read_cameras(&entry)
            .unwrap()
            .iter()
            .map(|camera| camera.with_origin_at(-offset))
            .collect();
        for image in 0..views.len() {
            let (v, f) = (views[image] as usize, frames[image] as usize);
            let read = |name: &str| {
                entry
                    .read_region::<u8>(name, &[image as u64, 0, 0], &[1, 40, 48])
                    .unwrap()
                    .data
            };
            let (garment, mask) = (read("garment_masks"), read("masks"));
            assert!(
                garment.iter().zip(&mask).all(|(g, m)| g <= m),
                "image {image}"
            );
            let pixels: Vec<usize> = (0..garment.len()).filter(|&p| garment[p] >= 128).collect();
            assert!(
                pixels.len() >= 10,
                "image {image}: {} skirt pixels",
                pixels.len()
            );
            let projected: Vec<_> = scene
                .skirt_positions(f)
                .iter()
                .filter_map(|p| cameras[v].project(*p))
                .collect();
            let (lo, hi) = projected
                .iter()
                .fold((projected[0], projected[0]), |(lo, hi), p| {
                    (lo.min(*p), hi.max(*p))
                });
            for p in pixels {
                let (x, y) = ((p % 48) as f64 + 0.5, (p / 48) as f64 + 0.5);
                assert!(
                    x >= lo.x - 1.0 && x <= hi.x + 1.0 && y >= lo.y - 1.0 && y <= hi.y + 1.0,
                    "image {image}: skirt pixel ({x}, {y}) outside the skirt's box {lo:?} {hi:?}"
                );
            }
            // Body pixels exist that are not skirt: the region is not the whole person.
            assert!(
                mask.iter()
                    .zip(&garment)
                    .any(|(m, g)| *m >= 128 && *g < 128)
            );
        }
        // Contact sheet.
        let options =
            PictureOptions::parse(&["split=train".to_string(), "max=3".to_string()]).unwrap();
        let sheet = Ingest
            .draw_picture(&entry, "contact_sheet", &options)
            .unwrap();
        assert_eq!(sheet.dimensions(), (3 * 48, 40));
        assert!(Ingest.draw_picture(&entry, "nope", &options).is_err());
        // The walk scene records no garment history.
        assert!(schema::read_garment_history(&entry).unwrap().is_none());
        assert!(Ingest.draw_picture(&entry, "history", &options).is_err());
    }

    /// A scene 10 km from its world's origin (body, cameras and keypoints moved together,
    /// the same images) is stored as at the origin, up to f64 rounding: the offset holds the
    /// 10 km, the world-space arrays are near the origin, and nothing is warned about. Before
    /// re-centring, its translations were refused as beyond 10 km, or, at 9 km, trained in
    /// f32 millimetres.
    #[test]
    fn a_scene_far_from_the_origin_is_stored_as_at_the_origin() {
        let moved = TINY.replace(
            "body_grid_spacing: 0.04}",
            "body_grid_spacing: 0.04, origin: [10000, -3, 10000]}",
        );
        assert_ne!(moved, TINY);
        let (_here_dir, here) = run_pipeline(TINY);
        let (_there_dir, there) = run_pipeline(&moved);
        let offset = |entry: &EntryReader| schema::read_world_offset(entry).unwrap();
        assert_eq!(
            offset(&there) - offset(&here),
            DVec3::new(10_000.0, -3.0, 10_000.0)
        );
        for entry in [&here, &there] {
            assert!(
                entry.manifest().warnings.is_empty(),
                "{:?}",
                entry.manifest().warnings
            );
        }
        for name in [
            "camera_K",
            "camera_R",
            "camera_t",
            "body_pose",
            "body_world_translation",
            "gt_body_world_translation",
            "keypoints_3d",
        ] {
            let (a, b) = (
                here.read::<f64>(name).unwrap().data,
                there.read::<f64>(name).unwrap().data,
            );
            assert_eq!(a.len(), b.len(), "{name}");
            let largest = a
                .iter()
                .zip(&b)
                .map(|(x, y)| (x - y).abs())
                .fold(0.0, f64::max);
            assert!(largest < 1e-9, "{name}: differs by {largest}");
            let farthest = b.iter().map(|x| x.abs()).fold(0.0, f64::max);
            assert!(farthest < 100.0, "{name}: {farthest} from the origin");
        }
        assert_eq!(
            here.read::<u8>("images").unwrap().data,
            there.read::<u8>("images").unwrap().data
        );
    }

    /// The history scene's entry records the garment's history-only displacement per frame:
    /// the same millimetres the scene gives, at least 2 px RMS over the history frames at
    /// 256 x 256, zero while the skirt is at rest; the default scene records none.
    #[test]
    fn history_scene_records_the_history_only_displacement() {
        use seqavatar_datasets::synthetic::history;
        let last = history::LENGTH - 1;
        let text = format!(
            "stages:\n  - name: ingest\n    kind: ingest\n    config:\n      dataset: {{kind: synthetic, scene: history, fps: 30, frames: {}, cameras: 3, width: 256, height: 256, supersample: 1, body_grid_spacing: 0.04}}\n      split: {{train_views: [0, 1, 2], test_views: [], train_frames: {{start: 0, end: null, step: {last}}}}}\n",
            history::LENGTH
        );
        let (_dir, entry) = run_pipeline(&text);
        let arrays = schema::read_garment_history(&entry).unwrap().unwrap();
        assert_eq!(arrays.pixels.len(), history::LENGTH);
        for (f, (&px, &flag)) in arrays.pixels.iter().zip(&arrays.frames).enumerate() {
            assert_eq!(flag, px > schema::HISTORY_FRAME_PX, "frame {f}");
        }
        // At rest before the first step: no displacement and the oscillator at rest.
        assert_eq!(arrays.millimetres[0], 0.0);
        assert_eq!(arrays.pixels[0], 0.0);
        assert_eq!(arrays.states[0], [0.0; schema::GARMENT_STATE_COMPONENTS]);
        // The state moves the skirt: a frame with a displaced hem has a deflection.
        let moving = arrays.millimetres.iter().position(|&mm| mm > 50.0).unwrap();
        let [forward, across, ..] = arrays.states[moving];
        assert!(
            forward.hypot(across) > 0.01,
            "frame {moving}: {:?}",
            arrays.states[moving]
        );
        // The millimetres are the scene's own RMS of simulated minus drape.
        let scene = seqavatar_datasets::synthetic::SyntheticScene::generate(
            &seqavatar_datasets::synthetic::SyntheticConfig {
                scene: seqavatar_datasets::synthetic::SceneKind::History,
                fps: 30.0,
                frames: history::LENGTH,
                cameras: 3,
                width: 256,
                height: 256,
                supersample: 1,
                body_grid_spacing: 0.04,
                ..Default::default()
            },
        )
        .unwrap();
        for frame in [20, 100, 190] {
            let drape = scene.static_drape(frame, 0.0).unwrap();
            let simulated = scene.skirt_positions(frame);
            let rms = (simulated
                .iter()
                .zip(&drape)
                .map(|(a, b)| (*a - *b).length_squared())
                .sum::<f64>()
                / drape.len() as f64)
                .sqrt();
            assert!(
                (arrays.millimetres[frame] - rms * 1e3).abs() < 1e-9,
                "frame {frame}"
            );
        }
        let flagged: Vec<f64> = arrays
            .pixels
            .iter()
            .zip(&arrays.frames)
            .filter(|(_, f)| **f)
            .map(|(p, _)| *p)
            .collect();
        let rms = (flagged.iter().map(|p| p * p).sum::<f64>() / flagged.len() as f64).sqrt();
        eprintln!(
            "history frames: {} of {}, {rms:.2} px RMS over them; largest {:.2} px, {:.1} mm",
            flagged.len(),
            history::LENGTH,
            flagged.iter().copied().fold(0.0, f64::max),
            arrays.millimetres.iter().copied().fold(0.0, f64::max)
        );
        assert!(rms >= 2.0, "{rms} px RMS over the history frames");
        assert!(
            flagged.len() >= history::LENGTH / 3,
            "{} history frames",
            flagged.len()
        );
        assert!(
            flagged.len() < history::LENGTH,
            "every frame is a history frame"
        );
        // Pictures: the chart (3 px per frame) and the contact sheet.
        let options = PictureOptions::parse(&["height=50".to_string()]).unwrap();
        let chart = Ingest.draw_picture(&entry, "history", &options).unwrap();
        assert_eq!(chart.dimensions(), (3 * history::LENGTH as u32, 50));
        let sheet = Ingest
            .draw_picture(
                &entry,
                "contact_sheet",
                &PictureOptions::parse(&[]).unwrap(),
            )
            .unwrap();
        assert_eq!(sheet.dimensions().1, 2 * 256);
    }

    #[test]
    fn config_errors_name_the_field() {
        let raw = serde_json::json!({"dataset": {"kind": "synthetic", "cameras": 2, "colour": 1}});
        let err = Ingest.resolve_config(&raw).unwrap_err().to_string();
        assert!(err.contains("colour"), "{err}");
        let resolved =
            serde_json::to_value(Ingest.resolve_config(&serde_json::json!({})).unwrap()).unwrap();
        assert_eq!(resolved["dataset"]["kind"], "synthetic");
        assert_eq!(resolved["dataset"]["cameras"], 8);
        // The default scene and split resolve as before the history scene and the temporal
        // hold-out existed, so the demo's ingest keys are unchanged.
        assert!(resolved["dataset"].get("scene").is_none(), "{resolved}");
        assert!(
            resolved["split"].get("held_out_frames").is_none(),
            "{resolved}"
        );
        let history = Ingest
            .resolve_config(&serde_json::json!({"dataset": {"kind": "synthetic", "scene": "history", "fps": 30.0, "frames": 150}, "split": {"held_out_frames": {"start": 5, "end": null, "step": 10}}}))
            .unwrap();
        let history = serde_json::to_value(history).unwrap();
        assert_eq!(history["dataset"]["scene"], "history");
        assert_eq!(history["split"]["held_out_frames"]["step"], 10);
        // The history scene's script fixes its rate and length.
        for (raw, field) in [
            (
                serde_json::json!({"dataset": {"kind": "synthetic", "scene": "history"}}),
                "dataset.fps",
            ),
            (
                serde_json::json!({"dataset": {"kind": "synthetic", "scene": "history", "fps": 30.0, "frames": 100000}}),
                "dataset.frames",
            ),
        ] {
            let err = Ingest.resolve_config(&raw).unwrap_err().to_string();
            assert!(err.contains(field), "{raw}: {err}");
        }
        let bad = IngestConfig {
            dataset: DatasetConfig::Synthetic(seqavatar_datasets::synthetic::SyntheticConfig {
                frames: 0,
                ..Default::default()
            }),
            ..Default::default()
        };
        let err = format!(
            "{:#}",
            open_reader(&bad.dataset, bad.body_model.as_deref())
                .err()
                .unwrap()
        );
        assert!(err.contains("dataset.frames"), "{err}");
    }
}
