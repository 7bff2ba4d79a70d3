//! The fit entry's arrays, each writer beside its reader: the one place that knows how a fit
//! entry is laid out. The stage writes through these functions; later stages (motion, train,
//! eval) and the stage's pictures read through them.
//!
//! Arrays:
//! - `body_pose`, `body_world_rotation`, `body_world_translation`, `body_betas` and, when the
//!   input has it, `body_expression`: the refined body parameters, with the same names and
//!   layout as the ingest stage's parameter arrays (written and read with ingest's
//!   `write_body_params` / `read_body_params`), so a later stage reads a fit entry and an
//!   ingest entry the same way ([`BodySequence::read`]).
//! - `jitter_before`, `jitter_after` f64 `(frame)`: per-frame joint jitter (mean over joints
//!   of the second difference of world joint positions, metres per frame squared)
//!   ([`Jitter`]).
//! - Modes `smooth` and `keypoints` (the fit stage's evidence): `track_kept_input` u8 `(track)`
//!   (1 = the input fit was kept), `track_iou_change` and `track_keypoint_change` f64
//!   `(track)`: the change of the mean silhouette IoU and of the mean keypoint distance
//!   (metres) that refining that track made. Tracks: the joints, then the world rotation,
//!   then the translation ([`TrackVerdicts`]).
//! - Where the ingest entry has images: `silhouette_iou_before`/`_after` f64 `(view)`, the
//!   mean over that view's images of the IoU between the posed body's silhouette and the
//!   mask ([`SilhouetteIou`]).
//!
//! Attributes (set by the stage): `mode`, `mean_jitter_before`, `mean_jitter_after`;
//! `tracks_kept_input` (the names of the tracks whose input fit was kept);
//! `mean_silhouette_iou_before`/`_after` (over all images); where keypoints name joints,
//! `keypoint_distance_before`/`_after` (confidence-weighted mean distance between posed joints
//! and 3D keypoints, metres); and for the synthetic scene (input with `gt_` arrays)
//! `joint_error_before`/`_after` (mean joint position error against ground truth, metres) and
//! `velocity_error_before`/`_after` (mean template vertex velocity error against ground truth,
//! metres per frame).

use crate::body::BodySequence;
use crate::ingest::{read_body_params, write_body_params};
use seqavatar_core::body::BodyModel;
use seqavatar_engine::{EntryReader, EntryWriter};

impl BodySequence {
    /// Reads the parameter arrays `{prefix}_pose`, ... (`prefix` = `body` or `gt_body`) of an
    /// ingest or fit entry with the ingest stage's reader, and checks every value is finite.
    pub fn read(entry: &EntryReader, prefix: &str) -> anyhow::Result<Self> {
        let params = read_body_params(entry, prefix)?;
        let in_entry = |message: String| anyhow::anyhow!("entry {}: {message}", entry.location());
        let sequence = Self::from_params(&params).map_err(in_entry)?;
        sequence.check_finite(prefix).map_err(in_entry)?;
        Ok(sequence)
    }

    /// Writes the parameter arrays `body_*` with the ingest stage's writer.
    pub fn write(&self, out: &EntryWriter, model: &BodyModel) -> anyhow::Result<()> {
        write_body_params(out, "body", &self.to_params(), model)
    }
}

/// Writes the 1-D array `name` along `dimension`.
fn write_vector<T: seqavatar_engine::Element>(
    out: &EntryWriter,
    name: &str,
    dimension: &str,
    values: &[T],
) -> anyhow::Result<()> {
    let length = values.len() as u64;
    out.write_array(
        name,
        &[dimension],
        &[length],
        &[length.clamp(1, 1024)],
        values,
    )
}

/// Reads the 1-D array `name`, or an error naming the entry and the array.
fn read_vector<T: seqavatar_engine::Element>(
    entry: &EntryReader,
    name: &str,
) -> anyhow::Result<Vec<T>> {
    let array = entry.read::<T>(name)?;
    anyhow::ensure!(
        array.shape.len() == 1,
        "entry {}: array `{name}` has shape {:?}, expected one dimension",
        entry.location(),
        array.shape
    );
    Ok(array.data)
}

/// Reads the arrays `{stem}_before` and `{stem}_after`, checked to have the same length.
fn read_before_after(entry: &EntryReader, stem: &str) -> anyhow::Result<(Vec<f64>, Vec<f64>)> {
    let before = read_vector::<f64>(entry, &format!("{stem}_before"))?;
    let after = read_vector::<f64>(entry, &format!("{stem}_after"))?;
    anyhow::ensure!(
        before.len() == after.len(),
        "entry {}: array `{stem}_before` has {} values, `{stem}_after` {}",
        entry.location(),
        before.len(),
        after.len()
    );
    Ok((before, after))
}

/// Per-frame joint jitter of the input and of the output fits (`jitter_before`,
/// `jitter_after`); every fit entry has them.
#[derive(Clone, Debug, PartialEq)]
pub struct Jitter {
    pub before: Vec<f64>,
    pub after: Vec<f64>,
}

impl Jitter {
    pub fn write(&self, out: &EntryWriter) -> anyhow::Result<()> {
        write_vector(out, "jitter_before", "frame", &self.before)?;
        write_vector(out, "jitter_after", "frame", &self.after)
    }

    pub fn read(entry: &EntryReader) -> anyhow::Result<Self> {
        let (before, after) = read_before_after(entry, "jitter")?;
        Ok(Self { before, after })
    }
}

/// Per-view mean silhouette IoU of the input and of the output fits
/// (`silhouette_iou_before`, `silhouette_iou_after`); only where the ingest entry has images
/// and the mode refines.
#[derive(Clone, Debug, PartialEq)]
pub struct SilhouetteIou {
    pub before: Vec<f64>,
    pub after: Vec<f64>,
}

impl SilhouetteIou {
    pub fn write(&self, out: &EntryWriter) -> anyhow::Result<()> {
        write_vector(out, "silhouette_iou_before", "view", &self.before)?;
        write_vector(out, "silhouette_iou_after", "view", &self.after)
    }

    /// `None` when the entry has no silhouette arrays (mode `off`, or no images).
    pub fn read(entry: &EntryReader) -> anyhow::Result<Option<Self>> {
        if !entry.has_array("silhouette_iou_before") {
            return Ok(None);
        }
        let (before, after) = read_before_after(entry, "silhouette_iou")?;
        Ok(Some(Self { before, after }))
    }
}

/// What the fit stage's track choice found for one track.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackVerdict {
    /// Change of the mean IoU over all images that refining this track made (with the
    /// other tracks refined).
    pub iou_change: f64,
    /// Change of the mean keypoint distance (metres) that refining this track made.
    pub keypoint_change: f64,
    /// True when the evidence got worse and the input fit is kept.
    pub kept_input: bool,
}

/// The per-track verdicts of the fit stage's track choice (`track_kept_input`,
/// `track_iou_change`, `track_keypoint_change`); only where the mode refines.
#[derive(Clone, Debug, PartialEq)]
pub struct TrackVerdicts(pub Vec<TrackVerdict>);

impl TrackVerdicts {
    pub fn write(&self, out: &EntryWriter) -> anyhow::Result<()> {
        let kept: Vec<u8> = self.0.iter().map(|v| u8::from(v.kept_input)).collect();
        write_vector(out, "track_kept_input", "track", &kept)?;
        let iou: Vec<f64> = self.0.iter().map(|v| v.iou_change).collect();
        write_vector(out, "track_iou_change", "track", &iou)?;
        let keypoint: Vec<f64> = self.0.iter().map(|v| v.keypoint_change).collect();
        write_vector(out, "track_keypoint_change", "track", &keypoint)
    }

    /// `None` when the entry has no verdicts (mode `off`).
    pub fn read(entry: &EntryReader) -> anyhow::Result<Option<Self>> {
        if !entry.has_array("track_kept_input") {
            return Ok(None);
        }
        let kept = read_vector::<u8>(entry, "track_kept_input")?;
        let iou = read_vector::<f64>(entry, "track_iou_change")?;
        let keypoint = read_vector::<f64>(entry, "track_keypoint_change")?;
        anyhow::ensure!(
            iou.len() == kept.len() && keypoint.len() == kept.len(),
            "entry {}: arrays `track_kept_input`, `track_iou_change`, `track_keypoint_change` have {}, {}, {} tracks",
            entry.location(),
            kept.len(),
            iou.len(),
            keypoint.len()
        );
        if let Some(track) = kept.iter().position(|&k| k > 1) {
            anyhow::bail!(
                "entry {}: array `track_kept_input` holds {} at track {track}, expected 0 or 1",
                entry.location(),
                kept[track]
            );
        }
        Ok(Some(Self(
            kept.iter()
                .zip(iou)
                .zip(keypoint)
                .map(|((&kept, iou_change), keypoint_change)| TrackVerdict {
                    iou_change,
                    keypoint_change,
                    kept_input: kept == 1,
                })
                .collect(),
        )))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_engine::{
        EntryId, LocalStore, Pipeline, Registry, RunOptions, StageContext, StageKind, Store, run,
    };

    fn verdict(iou_change: f64, keypoint_change: f64, kept_input: bool) -> TrackVerdict {
        TrackVerdict {
            iou_change,
            keypoint_change,
            kept_input,
        }
    }

    /// Writes the arrays of `config.case` through the engine: `good` with this module's
    /// writers, the others as a damaged fit entry could hold them.
    struct Arrays;

    impl StageKind for Arrays {
        type Config = serde_json::Value;
        fn kind(&self) -> &'static str {
            "fit_arrays"
        }
        fn version(&self) -> u32 {
            1
        }
        fn input_kinds(&self) -> &'static [&'static str] {
            &[]
        }
        fn run(&self, config: &Self::Config, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
            let out = ctx.output();
            let vector = |name: &str, values: &[f64]| write_vector(out, name, "x", values);
            match config["case"].as_str().unwrap() {
                "good" => {
                    Jitter {
                        before: vec![0.5, 0.25, 1e-9],
                        after: vec![0.125, 0.0, 2.0],
                    }
                    .write(out)?;
                    SilhouetteIou {
                        before: vec![0.75],
                        after: vec![0.875],
                    }
                    .write(out)?;
                    TrackVerdicts(vec![verdict(0.01, -0.002, false), verdict(-0.5, 0.0, true)])
                        .write(out)
                }
                "lengths" => {
                    vector("jitter_before", &[1.0, 2.0, 3.0])?;
                    vector("jitter_after", &[1.0, 2.0])?;
                    out.write_array("track_kept_input", &["track"], &[2], &[2], &[0u8, 1])?;
                    vector("track_iou_change", &[0.0, 0.0])?;
                    vector("track_keypoint_change", &[0.0])?;
                    out.write_array(
                        "silhouette_iou_before",
                        &["view", "y"],
                        &[1, 2],
                        &[1, 2],
                        &[0.5, 0.5],
                    )?;
                    vector("silhouette_iou_after", &[0.5])
                }
                _ => {
                    out.write_array("track_kept_input", &["track"], &[2], &[2], &[0u8, 7])?;
                    vector("track_iou_change", &[0.0, 0.0])?;
                    vector("track_keypoint_change", &[0.0, 0.0])
                }
            }
        }
    }

    fn entry(store: &LocalStore, case: &str) -> EntryReader {
        let text =
            format!("stages:\n  - {{name: a, kind: fit_arrays, config: {{case: {case}}}}}\n");
        let mut registry = Registry::new();
        registry.add(Box::new(Arrays));
        let pipeline =
            Pipeline::parse(&text, std::path::Path::new("t.yaml"), &registry, &[]).unwrap();
        let reports = run(&pipeline, &registry, store, &RunOptions::default()).unwrap();
        store
            .open_entry(&EntryId::new("fit_arrays", &reports[0].key))
            .unwrap()
    }

    #[test]
    fn arrays_read_back_as_written() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let good = entry(&store, "good");
        assert_eq!(
            Jitter::read(&good).unwrap(),
            Jitter {
                before: vec![0.5, 0.25, 1e-9],
                after: vec![0.125, 0.0, 2.0],
            }
        );
        assert_eq!(
            SilhouetteIou::read(&good).unwrap(),
            Some(SilhouetteIou {
                before: vec![0.75],
                after: vec![0.875],
            })
        );
        assert_eq!(
            TrackVerdicts::read(&good).unwrap(),
            Some(TrackVerdicts(vec![
                verdict(0.01, -0.002, false),
                verdict(-0.5, 0.0, true)
            ]))
        );
        assert_eq!(good.shape("jitter_before").unwrap(), [3]);
        assert_eq!(good.dtype("track_kept_input").unwrap(), "uint8");
    }

    #[test]
    fn damaged_arrays_are_errors_naming_the_entry_and_the_arrays() {
        let dir = tempfile::tempdir().unwrap();
        let store = LocalStore::open(dir.path()).unwrap();
        let damaged = entry(&store, "lengths");
        let values = entry(&store, "values");
        for (reader, error, expected) in [
            (
                &damaged,
                Jitter::read(&damaged).unwrap_err(),
                "array `jitter_before` has 3 values, `jitter_after` 2",
            ),
            (
                &damaged,
                TrackVerdicts::read(&damaged).unwrap_err(),
                "have 2, 2, 1 tracks",
            ),
            (
                &damaged,
                SilhouetteIou::read(&damaged).unwrap_err(),
                "array `silhouette_iou_before` has shape [1, 2], expected one dimension",
            ),
            (
                &values,
                TrackVerdicts::read(&values).unwrap_err(),
                "array `track_kept_input` holds 7 at track 1, expected 0 or 1",
            ),
        ] {
            let message = format!("{error:#}");
            assert!(
                message.contains(expected) && message.contains(reader.location()),
                "{message}"
            );
        }
        // Entries without the optional arrays read as `None`; jitter is required.
        assert_eq!(SilhouetteIou::read(&values).unwrap(), None);
        let missing = format!("{:#}", Jitter::read(&values).unwrap_err());
        assert!(missing.contains("jitter_before"), "{missing}");
    }
}
