//! Training checkpoints as Zarr v3 groups in the stage's work directory: every tensor
//! (Gaussian columns, network weights, Adam moments) as an f64 array, plus the iteration, the
//! generator state and free-form metadata as group attributes.
//!
//! Crash safety: a checkpoint is written into `ckpt-<iteration>.partial/`, its files are
//! synced, the directory is renamed to `ckpt-<iteration>/` and only then are checkpoints
//! older than the previous one deleted, so a killed run always leaves the last complete
//! checkpoint behind, and a damaged newest checkpoint has a previous one to fall back to
//! ([`resume_newest_good`]). A write that fails (a full disk) removes its `.partial` folder.
//! f32 values survive the f64 round trip exactly, so a resumed `cpu` run is bit-identical.
//!
//! Integrity: a checkpoint carries a blake3 digest of its whole content (iteration,
//! generator state, metadata, every tensor's name, shape and values) in attribute `digest`,
//! checked when it is read. A checkpoint whose digest does not match (edited, even with a
//! valid encoding), that cannot be read (a file in place of its folder included) or that
//! holds a non-finite value is unusable: [`resume_newest_good`] deletes it, says which and
//! why, and falls back to the previous one or starts over, so a rerun is never stuck.
//! Checkpoints are read through the engine's checked store
//! ([`seqavatar_engine::files::entry_storage`]): a FIFO or device in place of one of their
//! files is refused, naming it, without being opened. A file in place of the checkpoints'
//! folder is deleted the same way, with a note.

use std::fs;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use zarrs::array::ArraySubset;
use zarrs::array::codec::{BytesCodec, Crc32cCodec, ZstdCodec};
use zarrs::array::{Array, ArrayBuilder, data_type};
use zarrs::filesystem::FilesystemStore;
use zarrs::group::{Group, GroupBuilder};

/// One named tensor.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Array path inside the checkpoint, `/`-separated (for example `gaussians/xyz`).
    pub name: String,
    pub shape: Vec<usize>,
    /// One name per dimension (Zarr `dimension_names`).
    pub dimension_names: Vec<String>,
    pub values: Vec<f64>,
}

/// The complete resumable state of a run.
#[derive(Clone, Debug, PartialEq)]
pub struct Checkpoint {
    pub iteration: u64,
    pub rng_state: u64,
    pub metadata: serde_json::Value,
    pub tensors: Vec<Tensor>,
}

/// Why a checkpoint could not be written or read.
#[derive(Debug, thiserror::Error)]
pub enum CheckpointError {
    #[error("checkpoint {path}: {message}")]
    Invalid { path: PathBuf, message: String },
    // The cause is in the message, so it is not also a `source` (chains would repeat it).
    #[error("checkpoint {path}: {error}")]
    Io {
        path: PathBuf,
        error: std::io::Error,
    },
}

fn invalid(path: &Path, message: impl std::fmt::Display) -> CheckpointError {
    CheckpointError::Invalid {
        path: path.to_owned(),
        message: message.to_string(),
    }
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> CheckpointError + '_ {
    move |error| CheckpointError::Io {
        path: path.to_owned(),
        error,
    }
}

const PREFIX: &str = "ckpt-";
const PARTIAL: &str = ".partial";
/// Format 2 added the content digest; a format-1 checkpoint is unusable (no digest).
const FORMAT: u64 = 2;
/// Complete checkpoints kept: the newest and the one before it.
const KEEP: usize = 2;

/// Writes `checkpoint` under `dir` and removes all but the [`KEEP`] newest; returns its
/// directory.
pub fn save(dir: &Path, checkpoint: &Checkpoint) -> Result<PathBuf, CheckpointError> {
    fs::create_dir_all(dir).map_err(io(dir))?;
    let final_dir = dir.join(format!("{PREFIX}{:010}", checkpoint.iteration));
    let partial = dir.join(format!("{PREFIX}{:010}{PARTIAL}", checkpoint.iteration));
    if partial.exists() {
        fs::remove_dir_all(&partial).map_err(io(&partial))?;
    }
    let written = write_group(&partial, checkpoint)
        .and_then(|()| sync_tree(&partial))
        .and_then(|()| {
            if final_dir.exists() {
                fs::remove_dir_all(&final_dir).map_err(io(&final_dir))?;
            }
            fs::rename(&partial, &final_dir).map_err(io(&final_dir))
        });
    if let Err(error) = written {
        // A write that failed (most often on a full disk) takes its partial folder with it:
        // left behind, it would keep the disk full until the next run's listing.
        let _ = fs::remove_dir_all(&partial);
        return Err(error);
    }
    if let Ok(handle) = fs::File::open(dir) {
        // Persist the rename (directory fsync; not supported everywhere, hence best effort).
        let _ = handle.sync_all();
    }
    let complete = list(dir)?;
    for (_, old) in &complete[..complete.len().saturating_sub(KEEP)] {
        fs::remove_dir_all(old).map_err(io(old))?;
    }
    Ok(final_dir)
}

/// Complete checkpoints under `dir`, oldest first; removes leftovers of interrupted writes.
fn list(dir: &Path) -> Result<Vec<(u64, PathBuf)>, CheckpointError> {
    let mut found = Vec::new();
    if !dir.exists() {
        return Ok(found);
    }
    for entry in fs::read_dir(dir).map_err(io(dir))? {
        let entry = entry.map_err(io(dir))?;
        let name = entry.file_name().to_string_lossy().into_owned();
        let Some(rest) = name.strip_prefix(PREFIX) else {
            continue;
        };
        if rest.ends_with(PARTIAL) {
            remove(&entry.path())?;
            continue;
        }
        if let Ok(iteration) = rest.parse::<u64>() {
            found.push((iteration, entry.path()));
        }
    }
    found.sort();
    Ok(found)
}

/// Loads the newest complete checkpoint under `dir`, if any.
pub fn load_latest(dir: &Path) -> Result<Option<Checkpoint>, CheckpointError> {
    match list(dir)?.pop() {
        Some((_, path)) => read_group(&path).map(Some),
        None => Ok(None),
    }
}

/// Resumes from the newest checkpoint under `dir` that can be read and that `resume`
/// accepts. A checkpoint that fails either is deleted (so no later run trips over it again)
/// and the next older one is tried; each failure is described in the returned notes.
/// `None` when no usable checkpoint is left: the caller starts over.
pub fn resume_newest_good<T>(
    dir: &Path,
    mut resume: impl FnMut(Checkpoint) -> anyhow::Result<T>,
) -> Result<(Option<T>, Vec<String>), CheckpointError> {
    let mut notes = Vec::new();
    // A file (a FIFO, a link to one) in place of the checkpoints' folder would fail every
    // listing and every save ("Not a directory"): it is removed and training starts over.
    if fs::symlink_metadata(dir).is_ok() && !fs::metadata(dir).is_ok_and(|m| m.is_dir()) {
        remove(dir)?;
        notes.push(format!(
            "{} is not a folder of checkpoints and was deleted",
            dir.display()
        ));
    }
    for (_, path) in list(dir)?.into_iter().rev() {
        let failure = match read_group(&path) {
            Ok(checkpoint) => match resume(checkpoint) {
                Ok(resumed) => return Ok((Some(resumed), notes)),
                Err(error) => format!("{error:#}"),
            },
            Err(error) => error.to_string(),
        };
        remove(&path)?;
        notes.push(format!(
            "checkpoint {} is unusable and was deleted ({failure})",
            path.display()
        ));
    }
    Ok((None, notes))
}

/// Removes a folder with its content, or anything else (a file, a FIFO, a link) in its place.
fn remove(path: &Path) -> Result<(), CheckpointError> {
    if fs::symlink_metadata(path).is_ok_and(|m| m.is_dir()) {
        fs::remove_dir_all(path).map_err(io(path))
    } else {
        fs::remove_file(path).map_err(io(path))
    }
}

fn sync_tree(path: &Path) -> Result<(), CheckpointError> {
    for entry in fs::read_dir(path).map_err(io(path))? {
        let entry = entry.map_err(io(path))?;
        let p = entry.path();
        if entry.file_type().map_err(io(&p))?.is_dir() {
            sync_tree(&p)?;
        } else {
            fs::File::open(&p)
                .and_then(|f| f.sync_all())
                .map_err(io(&p))?;
        }
    }
    Ok(())
}

fn write_group(path: &Path, checkpoint: &Checkpoint) -> Result<(), CheckpointError> {
    fs::create_dir_all(path).map_err(io(path))?;
    let store = Arc::new(FilesystemStore::new(path).map_err(|e| invalid(path, e))?);
    let mut attributes = serde_json::Map::new();
    attributes.insert("format".into(), FORMAT.into());
    attributes.insert("iteration".into(), checkpoint.iteration.into());
    // As a string: JSON readers outside Rust often hold numbers in f64.
    attributes.insert("rng_state".into(), checkpoint.rng_state.to_string().into());
    attributes.insert("metadata".into(), checkpoint.metadata.clone());
    let names: Vec<serde_json::Value> = checkpoint
        .tensors
        .iter()
        .map(|t| t.name.clone().into())
        .collect();
    attributes.insert("tensors".into(), names.into());
    attributes.insert("digest".into(), content_digest(checkpoint).into());
    GroupBuilder::new()
        .attributes(attributes)
        .build(store.clone(), "/")
        .and_then(|g| g.store_metadata().map_err(Into::into))
        .map_err(|e| invalid(path, e))?;
    for tensor in &checkpoint.tensors {
        check_tensor(path, tensor)?;
        let shape: Vec<u64> = tensor.shape.iter().map(|&d| d as u64).collect();
        let chunk: Vec<u64> = shape.iter().map(|&d| d.max(1)).collect();
        let array = ArrayBuilder::new(shape, chunk, data_type::float64(), 0.0f64)
            .array_to_bytes_codec(Arc::new(BytesCodec::little()))
            .bytes_to_bytes_codecs(vec![
                Arc::new(ZstdCodec::new(3, false)),
                Arc::new(Crc32cCodec::new()),
            ])
            .dimension_names(Some(tensor.dimension_names.clone()))
            .build(store.clone(), &format!("/{}", tensor.name))
            .map_err(|e| invalid(path, format!("array {}: {e}", tensor.name)))?;
        array.store_metadata().map_err(|e| invalid(path, e))?;
        if !tensor.values.is_empty() {
            let zeros = vec![0u64; tensor.shape.len()];
            // Stored even when every value is the fill value (zarrs skips such chunks by
            // default): the reader treats a missing chunk as damage, never as zeros.
            let options = zarrs::array::CodecOptions::default().with_store_empty_chunks(true);
            array
                .store_chunk_opt(&zeros, tensor.values.as_slice(), &options)
                .map_err(|e| invalid(path, format!("array {}: {e}", tensor.name)))?;
        }
    }
    Ok(())
}

/// The blake3 digest of everything a checkpoint restores, in a fixed order.
pub fn content_digest(checkpoint: &Checkpoint) -> String {
    let mut hasher = blake3::Hasher::new();
    hasher.update(&checkpoint.iteration.to_le_bytes());
    hasher.update(&checkpoint.rng_state.to_le_bytes());
    let metadata = checkpoint.metadata.to_string();
    hasher.update(&(metadata.len() as u64).to_le_bytes());
    hasher.update(metadata.as_bytes());
    hasher.update(&(checkpoint.tensors.len() as u64).to_le_bytes());
    for tensor in &checkpoint.tensors {
        hasher.update(&(tensor.name.len() as u64).to_le_bytes());
        hasher.update(tensor.name.as_bytes());
        hasher.update(&(tensor.shape.len() as u64).to_le_bytes());
        for (&extent, name) in tensor.shape.iter().zip(&tensor.dimension_names) {
            hasher.update(&(extent as u64).to_le_bytes());
            hasher.update(&(name.len() as u64).to_le_bytes());
            hasher.update(name.as_bytes());
        }
        for value in &tensor.values {
            hasher.update(&value.to_le_bytes());
        }
    }
    hasher.finalize().to_hex().to_string()
}

fn check_tensor(path: &Path, tensor: &Tensor) -> Result<(), CheckpointError> {
    let valid_name = !tensor.name.is_empty()
        && tensor.name.split('/').all(|part| {
            !part.is_empty()
                && part != "."
                && part != ".."
                && part
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || "_-.".contains(c))
        });
    if !valid_name {
        return Err(invalid(
            path,
            format!("tensor name `{}` is not a plain array path", tensor.name),
        ));
    }
    if tensor.shape.len() != tensor.dimension_names.len() || tensor.shape.is_empty() {
        return Err(invalid(
            path,
            format!(
                "tensor {}: {} dimensions but {} names",
                tensor.name,
                tensor.shape.len(),
                tensor.dimension_names.len()
            ),
        ));
    }
    if tensor.shape.iter().product::<usize>() != tensor.values.len() {
        return Err(invalid(
            path,
            format!(
                "tensor {}: shape {:?} does not hold {} values",
                tensor.name,
                tensor.shape,
                tensor.values.len()
            ),
        ));
    }
    Ok(())
}

fn read_group(path: &Path) -> Result<Checkpoint, CheckpointError> {
    // Read through the checked store of cache entries: a FIFO or device in place of a
    // chunk or metadata file is an error naming it, not an open that waits forever.
    let store = seqavatar_engine::files::entry_storage(path)
        .map_err(|e| invalid(path, format!("{e:#}")))?;
    let group = Group::open(store.clone(), "/").map_err(|e| invalid(path, e))?;
    let attributes = group.attributes();
    let field = |name: &str| {
        attributes
            .get(name)
            .ok_or_else(|| invalid(path, format!("attribute `{name}` is missing")))
    };
    let format = field("format")?
        .as_u64()
        .ok_or_else(|| invalid(path, "attribute `format` is not an integer"))?;
    if format != FORMAT {
        return Err(invalid(
            path,
            format!("attribute `format` is {format}, this build reads {FORMAT}"),
        ));
    }
    let iteration = field("iteration")?
        .as_u64()
        .ok_or_else(|| invalid(path, "attribute `iteration` is not an integer"))?;
    let rng_state = field("rng_state")?
        .as_str()
        .and_then(|s| s.parse::<u64>().ok())
        .ok_or_else(|| invalid(path, "attribute `rng_state` is not a decimal u64 string"))?;
    let metadata = field("metadata")?.clone();
    let names = field("tensors")?
        .as_array()
        .ok_or_else(|| invalid(path, "attribute `tensors` is not a list"))?;
    let mut tensors = Vec::with_capacity(names.len());
    for name in names {
        let name = name
            .as_str()
            .ok_or_else(|| invalid(path, "attribute `tensors` holds a non-string"))?;
        let array = Array::open(store.clone(), &format!("/{name}"))
            .map_err(|e| invalid(path, format!("array {name}: {e}")))?;
        let shape: Vec<usize> = array.shape().iter().map(|&d| d as usize).collect();
        let dimension_names = array
            .dimension_names()
            .as_ref()
            .map(|names| {
                names
                    .iter()
                    .map(|n| n.clone().unwrap_or_default())
                    .collect()
            })
            .unwrap_or_default();
        let subset = ArraySubset::new_with_shape(array.shape().to_vec());
        let values: Vec<f64> = if shape.iter().product::<usize>() == 0 {
            Vec::new()
        } else {
            // Every tensor is one chunk; a missing one would read as zeros.
            let chunk = array.chunk_key(&vec![0u64; shape.len()]);
            let stored = zarrs::storage::ReadableStorageTraits::size_key(&*store, &chunk)
                .map_err(|e| invalid(path, format!("array {name}: {e}")))?;
            if stored.is_none() {
                return Err(invalid(
                    path,
                    format!("array {name}: chunk {} is missing", chunk.as_str()),
                ));
            }
            array
                .retrieve_array_subset(&subset)
                .map_err(|e| invalid(path, format!("array {name}: {e}")))?
        };
        tensors.push(Tensor {
            name: name.to_owned(),
            shape,
            dimension_names,
            values,
        });
    }
    let checkpoint = Checkpoint {
        iteration,
        rng_state,
        metadata,
        tensors,
    };
    let recorded = field("digest")?
        .as_str()
        .ok_or_else(|| invalid(path, "attribute `digest` is not a string"))?;
    let actual = content_digest(&checkpoint);
    if recorded != actual {
        return Err(invalid(
            path,
            format!(
                "its content digest is {actual}, the checkpoint records {recorded} (edited \
                 or damaged)"
            ),
        ));
    }
    for tensor in &checkpoint.tensors {
        if let Some(at) = tensor.values.iter().position(|v| !v.is_finite()) {
            return Err(invalid(
                path,
                format!(
                    "tensor {} holds the non-finite value {} at index {at}",
                    tensor.name, tensor.values[at]
                ),
            ));
        }
    }
    Ok(checkpoint)
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_engine::test_support::{finishes_within, make_fifo};

    fn sample(iteration: u64) -> Checkpoint {
        Checkpoint {
            iteration,
            rng_state: u64::MAX - 12345,
            metadata: serde_json::json!({"loss": [1.0, 0.5]}),
            tensors: vec![
                Tensor {
                    name: "gaussians/xyz".into(),
                    shape: vec![2, 3],
                    dimension_names: vec!["gaussian".into(), "xyz".into()],
                    values: vec![1.0, -2.5, f64::MIN_POSITIVE, 1e300, 0.1f32 as f64, -0.0],
                },
                Tensor {
                    name: "gaussians/empty".into(),
                    shape: vec![0, 4],
                    dimension_names: vec!["gaussian_empty".into(), "wxyz".into()],
                    values: vec![],
                },
                // All fill value: its chunk must still be stored (a loss curve of a loss
                // that is off is all zeros).
                Tensor {
                    name: "curve/zeros".into(),
                    shape: vec![3],
                    dimension_names: vec!["iteration".into()],
                    values: vec![0.0; 3],
                },
                Tensor {
                    name: "networks/trunk.0.weight".into(),
                    shape: vec![1],
                    dimension_names: vec!["one".into()],
                    values: vec![std::f64::consts::PI],
                },
            ],
        }
    }

    #[test]
    fn round_trip_is_exact_and_keeps_the_two_newest() {
        let dir = tempfile::tempdir().unwrap();
        assert!(load_latest(dir.path()).unwrap().is_none());
        save(dir.path(), &sample(10)).unwrap();
        let newest = sample(20);
        save(dir.path(), &newest).unwrap();
        let loaded = load_latest(dir.path()).unwrap().unwrap();
        assert_eq!(loaded.iteration, 20);
        assert_eq!(loaded.rng_state, newest.rng_state);
        assert_eq!(loaded.metadata, newest.metadata);
        for (a, b) in loaded.tensors.iter().zip(&newest.tensors) {
            assert_eq!(a.name, b.name);
            assert_eq!(a.shape, b.shape);
            assert_eq!(a.dimension_names, b.dimension_names);
            let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&a.values), bits(&b.values));
        }
        save(dir.path(), &sample(30)).unwrap();
        let mut entries: Vec<String> = fs::read_dir(dir.path())
            .unwrap()
            .map(|entry| entry.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        entries.sort();
        assert_eq!(entries, ["ckpt-0000000020", "ckpt-0000000030"]);
    }

    /// Flips a byte of the first chunk of `gaussians/xyz` in the checkpoint of `iteration`.
    fn damage(dir: &Path, iteration: u64) {
        let chunk = dir.join(format!("ckpt-{iteration:010}/gaussians/xyz/c/0/0"));
        let mut bytes = fs::read(&chunk).unwrap();
        bytes[0] ^= 1;
        fs::write(&chunk, bytes).unwrap();
    }

    #[test]
    fn a_damaged_checkpoint_falls_back_to_the_previous_one_then_to_none() {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &sample(10)).unwrap();
        save(dir.path(), &sample(20)).unwrap();
        damage(dir.path(), 20);
        assert!(load_latest(dir.path()).is_err(), "the damage is detected");
        let (resumed, notes) =
            resume_newest_good(dir.path(), |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!(resumed, Some(10));
        assert_eq!(notes.len(), 1, "{notes:?}");
        assert!(
            notes[0].contains("ckpt-0000000020") && notes[0].contains("deleted"),
            "{notes:?}"
        );
        // The damaged one is gone: the next run resumes from 10 without a note.
        let (resumed, notes) =
            resume_newest_good(dir.path(), |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!((resumed, notes.len()), (Some(10), 0));

        // A checkpoint the trainer rejects is skipped the same way; with none left the
        // caller starts over. A deleted chunk is an error, never zeros.
        let chunk = dir
            .path()
            .join("ckpt-0000000010/networks/trunk.0.weight/c/0");
        fs::remove_file(&chunk).unwrap();
        let (resumed, notes) =
            resume_newest_good(dir.path(), |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!(resumed, None);
        assert!(notes[0].contains("is missing"), "{notes:?}");
        save(dir.path(), &sample(30)).unwrap();
        let (resumed, notes) = resume_newest_good(dir.path(), |_| -> anyhow::Result<u64> {
            anyhow::bail!("the Gaussian count does not match")
        })
        .unwrap();
        assert_eq!(resumed, None);
        assert!(notes[0].contains("does not match"), "{notes:?}");
        assert!(list(dir.path()).unwrap().is_empty());
    }

    /// Rewrites the chunk of `name` in the checkpoint of `iteration` with `values`, validly
    /// encoded (zstd and CRC-32C recomputed): only the digest can tell.
    fn reencode(dir: &Path, iteration: u64, name: &str, values: &[f64]) {
        let path = dir.join(format!("ckpt-{iteration:010}"));
        let store = Arc::new(FilesystemStore::new(&path).unwrap());
        let array = Array::open(store, &format!("/{name}")).unwrap();
        let zeros = vec![0u64; array.shape().len()];
        array.store_chunk(&zeros, values).unwrap();
    }

    #[test]
    fn an_edited_but_validly_encoded_checkpoint_fails_its_digest() {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &sample(10)).unwrap();
        save(dir.path(), &sample(20)).unwrap();
        let mut edited = sample(20).tensors[0].values.clone();
        edited[0] += 3.0;
        reencode(dir.path(), 20, "gaussians/xyz", &edited);
        let error = load_latest(dir.path()).unwrap_err().to_string();
        assert!(error.contains("digest"), "{error}");
        let (resumed, notes) =
            resume_newest_good(dir.path(), |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!(resumed, Some(10));
        assert!(
            notes[0].contains("ckpt-0000000020") && notes[0].contains("digest"),
            "{notes:?}"
        );
    }

    #[test]
    fn a_checkpoint_with_a_non_finite_value_is_discarded() {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &sample(10)).unwrap();
        // Written with its digest: only the value check can refuse it.
        let mut poisoned = sample(20);
        poisoned.tensors[0].values[3] = f64::NAN;
        save(dir.path(), &poisoned).unwrap();
        let (resumed, notes) =
            resume_newest_good(dir.path(), |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!(resumed, Some(10));
        assert!(
            notes[0].contains("ckpt-0000000020")
                && notes[0].contains("gaussians/xyz")
                && notes[0].contains("non-finite"),
            "{notes:?}"
        );
        assert_eq!(list(dir.path()).unwrap().len(), 1);
    }

    #[test]
    fn a_file_in_place_of_a_checkpoint_is_discarded_not_stuck() {
        let dir = tempfile::tempdir().unwrap();
        fs::write(dir.path().join("ckpt-0000000020"), b"not a folder").unwrap();
        let (resumed, notes) =
            resume_newest_good(dir.path(), |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!(resumed, None);
        assert!(notes[0].contains("ckpt-0000000020"), "{notes:?}");
        assert!(!dir.path().join("ckpt-0000000020").exists());
        // The next run starts over without a note.
        let (resumed, notes) =
            resume_newest_good(dir.path(), |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!((resumed, notes.len()), (None, 0));
    }

    /// A FIFO in place of a chunk (or of the group document) is refused when the checkpoint
    /// is read, naming it, instead of an open that waits for a writer forever; the previous
    /// checkpoint is used.
    #[test]
    fn a_fifo_in_place_of_a_chunk_is_refused_at_once() {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &sample(10)).unwrap();
        save(dir.path(), &sample(20)).unwrap();
        save(dir.path(), &sample(30)).unwrap();
        let chunk = dir.path().join("ckpt-0000000030/gaussians/xyz/c/0/0");
        fs::remove_file(&chunk).unwrap();
        make_fifo(&chunk);
        let document = dir.path().join("ckpt-0000000020/zarr.json");
        fs::remove_file(&document).unwrap();
        make_fifo(&document);
        let root = dir.path().to_path_buf();
        let (resumed, notes) = finishes_within(5, move || {
            resume_newest_good(&root, |checkpoint| Ok(checkpoint.iteration)).unwrap()
        });
        assert_eq!(resumed, None, "{notes:?}");
        assert_eq!(notes.len(), 2, "{notes:?}");
        assert!(
            notes[0].contains("ckpt-0000000030/gaussians/xyz/c/0/0") && notes[0].contains("a FIFO"),
            "{notes:?}"
        );
        assert!(
            notes[1].contains("ckpt-0000000020/zarr.json") && notes[1].contains("a FIFO"),
            "{notes:?}"
        );
        assert!(list(dir.path()).unwrap().is_empty());
    }

    /// A file in place of the checkpoints' folder is deleted with a note (training starts
    /// over), not "Not a directory" on every run; the next save works.
    #[test]
    fn a_file_in_place_of_the_checkpoints_folder_is_deleted() {
        let parent = tempfile::tempdir().unwrap();
        let dir = parent.path().join("checkpoints");
        fs::write(&dir, b"not a folder").unwrap();
        let (resumed, notes) =
            resume_newest_good(&dir, |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!(resumed, None);
        assert_eq!(notes.len(), 1, "{notes:?}");
        assert!(
            notes[0].contains("checkpoints") && notes[0].contains("not a folder"),
            "{notes:?}"
        );
        save(&dir, &sample(10)).unwrap();
        let (resumed, notes) =
            resume_newest_good(&dir, |checkpoint| Ok(checkpoint.iteration)).unwrap();
        assert_eq!((resumed, notes.len()), (Some(10), 0));
        // A FIFO there, and a file named like an interrupted write, go the same way.
        fs::remove_dir_all(&dir).unwrap();
        make_fifo(&dir);
        let (resumed, notes) = finishes_within(5, {
            let dir = dir.clone();
            move || resume_newest_good(&dir, |checkpoint| Ok(checkpoint.iteration)).unwrap()
        });
        assert_eq!((resumed, notes.len()), (None, 1), "{notes:?}");
        fs::create_dir(&dir).unwrap();
        fs::write(dir.join("ckpt-0000000009.partial"), b"x").unwrap();
        save(&dir, &sample(10)).unwrap();
        assert_eq!(load_latest(&dir).unwrap().unwrap().iteration, 10);
        assert!(!dir.join("ckpt-0000000009.partial").exists());
    }

    #[test]
    fn interrupted_writes_are_ignored_and_cleaned() {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &sample(5)).unwrap();
        // A later checkpoint that died half-way.
        let partial = dir.path().join("ckpt-0000000009.partial");
        fs::create_dir_all(partial.join("gaussians")).unwrap();
        let loaded = load_latest(dir.path()).unwrap().unwrap();
        assert_eq!(loaded.iteration, 5);
        assert!(!partial.exists());
    }

    /// A checkpoint whose write fails half-way leaves no `.partial` folder to fill the disk.
    #[test]
    fn a_failed_write_removes_its_partial_folder() {
        let dir = tempfile::tempdir().unwrap();
        save(dir.path(), &sample(5)).unwrap();
        // The first tensor reaches the disk, the last fails: the same path as a write that
        // runs out of space part of the way through.
        let mut failing = sample(9);
        failing.tensors.last_mut().unwrap().values.pop();
        assert!(failing.tensors.len() > 1);
        save(dir.path(), &failing).unwrap_err();
        assert!(!dir.path().join("ckpt-0000000009.partial").exists());
        assert!(!dir.path().join("ckpt-0000000009").exists());
        assert_eq!(load_latest(dir.path()).unwrap().unwrap().iteration, 5);
    }

    #[test]
    fn bad_input_names_the_problem() {
        let dir = tempfile::tempdir().unwrap();
        let mut bad = sample(1);
        bad.tensors[0].values.pop();
        let err = save(dir.path(), &bad).unwrap_err().to_string();
        assert!(
            err.contains("gaussians/xyz") && err.contains("does not hold"),
            "{err}"
        );
        let mut bad = sample(1);
        bad.tensors[0].name = "../escape".into();
        assert!(
            save(dir.path(), &bad)
                .unwrap_err()
                .to_string()
                .contains("not a plain array path")
        );
        // A corrupted attribute is reported with the file and the field.
        save(dir.path(), &sample(2)).unwrap();
        let meta = dir.path().join("ckpt-0000000002/zarr.json");
        let text = fs::read_to_string(&meta)
            .unwrap()
            .replace("\"rng_state\"", "\"rng_stat\"");
        fs::write(&meta, text).unwrap();
        let err = load_latest(dir.path()).unwrap_err().to_string();
        assert!(
            err.contains("rng_state") && err.contains("ckpt-0000000002"),
            "{err}"
        );
    }
}
