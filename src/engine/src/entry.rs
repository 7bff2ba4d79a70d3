//! Cache entries: writing arrays into a staging group, the manifest, chunk digests, and
//! reading published entries through zarrs storage traits (so any store can serve them).

use std::collections::BTreeMap;
use std::marker::PhantomData;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use anyhow::Context as _;
use serde::{Deserialize, Serialize};
use zarrs::array::codec::{BytesCodec, Crc32cCodec, ZstdCodec};
use zarrs::array::{Array, ArrayBuilder, ArraySubset};
use zarrs::filesystem::FilesystemStore;
use zarrs::group::{Group, GroupBuilder};
use zarrs::storage::{ReadableListableStorage, StoreKey, StorePrefix};

use crate::array::{Element, NdArray};

/// The group attribute holding the [`Manifest`].
pub const MANIFEST_ATTRIBUTE: &str = "manifest";
/// zstd level for every chunk.
const ZSTD_LEVEL: i32 = 3;

/// Provenance and integrity record of an entry, stored in the group attributes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub kind: String,
    pub version: u32,
    pub stage_name: String,
    pub key: String,
    pub config: serde_json::Value,
    pub inputs: Vec<ManifestInput>,
    pub external_files: Vec<ManifestExternalFile>,
    pub tool_version: String,
    /// blake3 of the entry's group metadata document (`zarr.json`: node type and the stage
    /// attributes) without the manifest itself, in canonical JSON ([`metadata_digest`]).
    /// Array metadata documents are digested with their chunks in `arrays`. Empty in entries
    /// written before it existed, which then fail verification.
    #[serde(default)]
    pub metadata_digest: String,
    pub arrays: BTreeMap<String, ManifestArray>,
    pub wall_time_s: f64,
    pub started_at: String,
    pub finished_at: String,
    pub log: Vec<String>,
    pub warnings: Vec<String>,
}

/// One upstream entry a stage read.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestInput {
    pub stage_name: String,
    pub kind: String,
    pub key: String,
}

/// One external file the key depends on.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestExternalFile {
    pub path: String,
    pub digest: String,
}

/// The store key of the entry's group metadata document.
const GROUP_METADATA_KEY: &str = "zarr.json";

/// blake3 of a group metadata document (`zarr.json` bytes) with the `manifest` attribute
/// left out, over canonical JSON: what [`Manifest::metadata_digest`] records.
pub fn metadata_digest(document: &[u8]) -> anyhow::Result<String> {
    let mut value: serde_json::Value =
        serde_json::from_slice(document).context("the group zarr.json is not JSON")?;
    if let Some(document) = value.as_object_mut() {
        if let Some(attributes) = document
            .get_mut("attributes")
            .and_then(serde_json::Value::as_object_mut)
        {
            attributes.remove(MANIFEST_ATTRIBUTE);
        }
        // Without attributes, Zarr leaves the field out: absent and empty are the same.
        if document
            .get("attributes")
            .and_then(serde_json::Value::as_object)
            .is_some_and(serde_json::Map::is_empty)
        {
            document.remove("attributes");
        }
    }
    let text = crate::key::canonical_json(&value);
    Ok(blake3::hash(text.as_bytes()).to_hex().to_string())
}

/// One array of an entry and the blake3 digests of its stored files.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestArray {
    pub dtype: String,
    pub shape: Vec<u64>,
    pub chunk_shape: Vec<u64>,
    pub dimension_names: Vec<String>,
    /// blake3 over the sorted (store key, file digest) pairs.
    pub digest: String,
    /// Store key (relative to the entry) -> blake3 of the stored bytes.
    pub files: BTreeMap<String, String>,
}

/// Checks an array name: a plain name usable as a folder and a Zarr node name.
fn check_array_name(name: &str) -> anyhow::Result<()> {
    anyhow::ensure!(
        !name.is_empty()
            && !name.starts_with('.')
            && name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-' || c == '.'),
        "array name \"{name}\" must be non-empty, not start with '.', and use only ASCII letters, digits, '_', '-', '.'"
    );
    Ok(())
}

/// Writes the arrays and attributes of one entry into its staging group. `Sync`: arrays can be
/// created and written from many threads (distinct chunks only).
pub struct EntryWriter {
    root: PathBuf,
    store: Arc<FilesystemStore>,
    /// The manifest records of the arrays created so far, digests filled in by `finish`.
    arrays: Mutex<BTreeMap<String, ManifestArray>>,
    attributes: Mutex<serde_json::Map<String, serde_json::Value>>,
    array_metadata_lock: Mutex<()>,
}

impl EntryWriter {
    /// A writer for a new, empty group in the existing directory `root`.
    pub(crate) fn create(root: &Path) -> anyhow::Result<Self> {
        let store = Arc::new(
            crate::files::filesystem_store(root)
                .with_context(|| format!("cannot open staging store {}", root.display()))?,
        );
        GroupBuilder::new()
            .build(store.clone(), "/")
            .context("cannot create the entry group")?
            .store_metadata()
            .with_context(|| format!("cannot write group metadata in {}", root.display()))?;
        Ok(Self {
            root: root.to_path_buf(),
            store,
            arrays: Mutex::new(BTreeMap::new()),
            attributes: Mutex::new(serde_json::Map::new()),
            array_metadata_lock: Mutex::new(()),
        })
    }

    /// The staging directory (for diagnostics).
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// Creates an array of zeros; fill it with [`ArrayWriter::write_chunk`] or
    /// [`ArrayWriter::write_region`].
    pub fn create_array<T: Element>(
        &self,
        name: &str,
        dimension_names: &[&str],
        shape: &[u64],
        chunk_shape: &[u64],
    ) -> anyhow::Result<ArrayWriter<T>> {
        check_array_name(name)?;
        anyhow::ensure!(
            dimension_names.len() == shape.len() && chunk_shape.len() == shape.len(),
            "array \"{name}\": shape {shape:?}, chunk shape {chunk_shape:?} and dimension names {dimension_names:?} must have the same length"
        );
        anyhow::ensure!(
            chunk_shape.iter().all(|&extent| extent > 0),
            "array \"{name}\": chunk shape {chunk_shape:?} has a zero extent"
        );
        anyhow::ensure!(
            dimension_names
                .iter()
                .all(|dimension| !dimension.is_empty()),
            "array \"{name}\": empty dimension name in {dimension_names:?}"
        );
        {
            let mut arrays = self.arrays.lock().expect("array table poisoned");
            anyhow::ensure!(
                !arrays.contains_key(name),
                "array \"{name}\" was already created in this entry"
            );
            arrays.insert(
                name.to_string(),
                ManifestArray {
                    dtype: T::DTYPE.to_string(),
                    shape: shape.to_vec(),
                    chunk_shape: chunk_shape.to_vec(),
                    dimension_names: dimension_names.iter().map(|d| d.to_string()).collect(),
                    digest: String::new(),
                    files: BTreeMap::new(),
                },
            );
        }
        let array = ArrayBuilder::new(
            shape.to_vec(),
            chunk_shape.to_vec(),
            T::zarr_data_type(),
            T::fill_value(),
        )
        .array_to_bytes_codec(Arc::new(BytesCodec::little()))
        .bytes_to_bytes_codecs(vec![
            Arc::new(ZstdCodec::new(ZSTD_LEVEL, false)),
            Arc::new(Crc32cCodec::new()),
        ])
        .dimension_names(Some(dimension_names.to_vec()))
        .build(self.store.clone(), &format!("/{name}"))
        .with_context(|| format!("cannot create array \"{name}\""))?;
        array
            .store_metadata()
            .with_context(|| format!("cannot write metadata of array \"{name}\""))?;
        Ok(ArrayWriter {
            name: name.to_string(),
            array,
            element: PhantomData,
        })
    }

    /// Creates an array and writes all of `data` (row-major) into it.
    pub fn write_array<T: Element>(
        &self,
        name: &str,
        dimension_names: &[&str],
        shape: &[u64],
        chunk_shape: &[u64],
        data: &[T],
    ) -> anyhow::Result<()> {
        let writer = self.create_array::<T>(name, dimension_names, shape, chunk_shape)?;
        let origin = vec![0u64; shape.len()];
        writer.write_region(&origin, shape, data)
    }

    /// [`EntryWriter::write_array`] as one chunk of the whole `shape`.
    pub fn write_whole<T: Element>(
        &self,
        name: &str,
        dimension_names: &[&str],
        shape: &[u64],
        data: &[T],
    ) -> anyhow::Result<()> {
        self.write_array(name, dimension_names, shape, shape, data)
    }

    /// Sets a stage-level attribute of the entry (the key `manifest` is reserved).
    pub fn set_attribute(&self, key: &str, value: serde_json::Value) -> anyhow::Result<()> {
        anyhow::ensure!(
            key != MANIFEST_ATTRIBUTE,
            "attribute name \"{MANIFEST_ATTRIBUTE}\" is reserved for the engine"
        );
        self.attributes
            .lock()
            .expect("attribute table poisoned")
            .insert(key.to_string(), value);
        Ok(())
    }

    /// Sets an attribute of an array created earlier.
    pub fn set_array_attribute(
        &self,
        array: &str,
        key: &str,
        value: serde_json::Value,
    ) -> anyhow::Result<()> {
        anyhow::ensure!(
            self.arrays
                .lock()
                .expect("array table poisoned")
                .contains_key(array),
            "cannot set attribute \"{key}\": no array \"{array}\" in this entry"
        );
        let _guard = self
            .array_metadata_lock
            .lock()
            .expect("array metadata lock poisoned");
        let mut opened = Array::open(self.store.clone(), &format!("/{array}"))
            .with_context(|| format!("cannot reopen array \"{array}\""))?;
        opened.attributes_mut().insert(key.to_string(), value);
        opened
            .store_metadata()
            .with_context(|| format!("cannot write metadata of array \"{array}\""))?;
        Ok(())
    }

    /// Names of the arrays created so far.
    pub fn array_names(&self) -> Vec<String> {
        self.arrays
            .lock()
            .expect("array table poisoned")
            .keys()
            .cloned()
            .collect()
    }

    /// Digests every array and writes the group metadata with the stage attributes and the
    /// manifest (whose `arrays` field is filled in here).
    pub(crate) fn finish(&self, manifest: &mut Manifest) -> anyhow::Result<()> {
        let mut arrays = self.arrays.lock().expect("array table poisoned").clone();
        let storage: ReadableListableStorage = self.store.clone();
        for (name, record) in &mut arrays {
            record.files = digest_array_files(&storage, name)?;
            record.digest = crate::key::combined_digest(&record.files);
        }
        manifest.arrays = arrays;
        let mut attributes = self
            .attributes
            .lock()
            .expect("attribute table poisoned")
            .clone();
        let mut group = GroupBuilder::new()
            .build(self.store.clone(), "/")
            .context("cannot rebuild the entry group")?;
        // The group document without the manifest is written and digested first, so the
        // digest is taken over exactly what a reader will find.
        *group.attributes_mut() = attributes.clone();
        group
            .store_metadata()
            .context("cannot write the entry group metadata")?;
        let document = storage
            .get(&group_metadata_key())
            .context("cannot read back the entry group metadata")?
            .ok_or_else(|| anyhow::anyhow!("the entry group metadata vanished"))?;
        manifest.metadata_digest = metadata_digest(&document)?;
        attributes.insert(
            MANIFEST_ATTRIBUTE.to_string(),
            serde_json::to_value(&*manifest).context("cannot serialize manifest")?,
        );
        *group.attributes_mut() = attributes;
        group
            .store_metadata()
            .context("cannot write the entry group metadata")?;
        Ok(())
    }
}

/// blake3 of every stored file under the array `name`, keyed relative to the entry.
fn digest_array_files(
    storage: &ReadableListableStorage,
    name: &str,
) -> anyhow::Result<BTreeMap<String, String>> {
    let prefix = StorePrefix::new(format!("{name}/"))
        .with_context(|| format!("invalid array name \"{name}\""))?;
    let keys = storage
        .list_prefix(&prefix)
        .with_context(|| format!("cannot list the files of array \"{name}\""))?;
    let mut files = BTreeMap::new();
    for key in keys {
        let bytes = storage
            .get(&key)
            .with_context(|| format!("cannot read {}", key.as_str()))?
            .ok_or_else(|| anyhow::anyhow!("file {} vanished while digesting", key.as_str()))?;
        files.insert(
            key.as_str().to_string(),
            blake3::hash(&bytes).to_hex().to_string(),
        );
    }
    Ok(files)
}

fn group_metadata_key() -> StoreKey {
    StoreKey::new(GROUP_METADATA_KEY).expect("zarr.json is a valid store key")
}

/// Writes one array of an entry. `Sync`: distinct chunks may be written from many threads.
pub struct ArrayWriter<T: Element> {
    name: String,
    array: Array<FilesystemStore>,
    element: PhantomData<fn(T)>,
}

impl<T: Element> ArrayWriter<T> {
    pub fn name(&self) -> &str {
        &self.name
    }

    pub fn shape(&self) -> &[u64] {
        self.array.shape()
    }

    /// Writes a whole chunk (edge chunks have the full chunk shape; elements beyond the
    /// array are ignored).
    pub fn write_chunk(&self, chunk_indices: &[u64], data: &[T]) -> anyhow::Result<()> {
        let grid = self.array.chunk_grid_shape();
        anyhow::ensure!(
            chunk_indices.len() == grid.len()
                && chunk_indices
                    .iter()
                    .zip(grid)
                    .all(|(&index, &count)| index < count),
            "array \"{}\": chunk {chunk_indices:?} is outside the chunk grid {grid:?}",
            self.name
        );
        let chunk_shape = self
            .array
            .chunk_shape(chunk_indices)
            .with_context(|| format!("array \"{}\": chunk {chunk_indices:?}", self.name))?;
        let expected: u64 = chunk_shape.iter().map(|extent| extent.get()).product();
        anyhow::ensure!(
            data.len() as u64 == expected,
            "array \"{}\": chunk {chunk_indices:?} needs {expected} elements, got {}",
            self.name,
            data.len()
        );
        self.array
            .store_chunk(chunk_indices, data)
            .with_context(|| {
                format!(
                    "cannot write chunk {chunk_indices:?} of array \"{}\"",
                    self.name
                )
            })
    }

    /// Writes the region of `shape` starting at `start` (row-major data). Writing part of a
    /// chunk is a read-modify-write: threads must not share chunks.
    pub fn write_region(&self, start: &[u64], shape: &[u64], data: &[T]) -> anyhow::Result<()> {
        let ranges = region_ranges(&self.name, self.array.shape(), start, shape)?;
        let expected: u64 = shape.iter().product();
        anyhow::ensure!(
            data.len() as u64 == expected,
            "array \"{}\": region {shape:?} needs {expected} elements, got {}",
            self.name,
            data.len()
        );
        if expected == 0 {
            return Ok(());
        }
        self.array
            .store_array_subset(&ranges, data)
            .with_context(|| {
                format!(
                    "cannot write region at {start:?} of array \"{}\"",
                    self.name
                )
            })
    }
}

/// Checked ranges of a region inside an array.
fn region_ranges(
    name: &str,
    array_shape: &[u64],
    start: &[u64],
    shape: &[u64],
) -> anyhow::Result<Vec<Range<u64>>> {
    anyhow::ensure!(
        start.len() == array_shape.len() && shape.len() == array_shape.len(),
        "array \"{name}\": region start {start:?} and shape {shape:?} must have rank {}",
        array_shape.len()
    );
    let mut ranges = Vec::with_capacity(start.len());
    for ((&begin, &extent), &size) in start.iter().zip(shape).zip(array_shape) {
        let end = begin.checked_add(extent);
        match end {
            Some(end) if end <= size => ranges.push(begin..end),
            _ => anyhow::bail!(
                "array \"{name}\": region at {start:?} of shape {shape:?} exceeds the array shape {array_shape:?}"
            ),
        }
    }
    Ok(ranges)
}

/// A hold on a published entry: shared while a run reads it, exclusive while `gc` deletes it.
/// Released on drop (and by the kernel when the process dies, so a killed reader never
/// blocks `gc`).
pub trait ReadLease: Send {}

/// Reads a published entry through a zarrs storage (local folder now, object store later).
#[derive(Clone)]
pub struct EntryReader {
    storage: ReadableListableStorage,
    location: String,
    manifest: Manifest,
    attributes: serde_json::Map<String, serde_json::Value>,
    /// The read lease `gc` respects, held while this reader or a clone of it lives (set by
    /// [`crate::open_leased_verified`]).
    _lease: Option<std::sync::Arc<std::sync::Mutex<Box<dyn ReadLease>>>>,
}

impl std::fmt::Debug for EntryReader {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        formatter
            .debug_struct("EntryReader")
            .field("location", &self.location)
            .field("kind", &self.manifest.kind)
            .field("key", &self.manifest.key)
            .finish()
    }
}

impl EntryReader {
    /// Opens the entry group at the root of `storage`; `location` names it in messages.
    pub fn open(storage: ReadableListableStorage, location: &str) -> anyhow::Result<Self> {
        let group = Group::open(storage.clone(), "/")
            .with_context(|| format!("{location}: cannot open the entry group"))?;
        let mut attributes = group.attributes().clone();
        let manifest_value = attributes.remove(MANIFEST_ATTRIBUTE).ok_or_else(|| {
            anyhow::anyhow!("{location}: the group has no \"manifest\" attribute")
        })?;
        let manifest: Manifest = serde_json::from_value(manifest_value)
            .with_context(|| format!("{location}: malformed manifest"))?;
        Ok(Self {
            storage,
            location: location.to_string(),
            manifest,
            attributes,
            _lease: None,
        })
    }

    /// This reader, holding `lease` until it and all its clones are dropped.
    pub fn holding(mut self, lease: Box<dyn ReadLease>) -> Self {
        self._lease = Some(std::sync::Arc::new(std::sync::Mutex::new(lease)));
        self
    }

    /// Where the entry lives (a path or URL), for messages.
    pub fn location(&self) -> &str {
        &self.location
    }

    pub fn kind(&self) -> &str {
        &self.manifest.kind
    }

    pub fn key(&self) -> &str {
        &self.manifest.key
    }

    pub fn stage_name(&self) -> &str {
        &self.manifest.stage_name
    }

    /// The effective config the entry was computed with.
    pub fn config(&self) -> &serde_json::Value {
        &self.manifest.config
    }

    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }

    /// The zarrs storage the entry is read from.
    pub fn storage(&self) -> &ReadableListableStorage {
        &self.storage
    }

    /// Array names, sorted.
    pub fn array_names(&self) -> Vec<String> {
        self.manifest.arrays.keys().cloned().collect()
    }

    /// Whether the entry holds the array `name`.
    pub fn has_array(&self, name: &str) -> bool {
        self.manifest.arrays.contains_key(name)
    }

    fn open_array(
        &self,
        name: &str,
    ) -> anyhow::Result<Array<dyn zarrs::storage::ReadableListableStorageTraits>> {
        anyhow::ensure!(
            self.manifest.arrays.contains_key(name),
            "entry {} ({}): no array \"{name}\" (arrays: {})",
            self.manifest.stage_name,
            self.location,
            self.array_names().join(", ")
        );
        Array::open(self.storage.clone(), &format!("/{name}"))
            .with_context(|| format!("entry {}: cannot open array \"{name}\"", self.location))
    }

    /// The shape of array `name`.
    pub fn shape(&self, name: &str) -> anyhow::Result<Vec<u64>> {
        Ok(self.open_array(name)?.shape().to_vec())
    }

    /// The data type name of array `name` (`float32`, ...).
    pub fn dtype(&self, name: &str) -> anyhow::Result<String> {
        Ok(self.record(name)?.dtype.clone())
    }

    /// The manifest's record of array `name`.
    fn record(&self, name: &str) -> anyhow::Result<&ManifestArray> {
        self.manifest
            .arrays
            .get(name)
            .ok_or_else(|| anyhow::anyhow!("entry {}: no array \"{name}\"", self.location))
    }

    fn checked_array<T: Element>(
        &self,
        name: &str,
    ) -> anyhow::Result<Array<dyn zarrs::storage::ReadableListableStorageTraits>> {
        let array = self.open_array(name)?;
        if <T as zarrs::array::Element>::validate_data_type(array.data_type()).is_err() {
            let stored = serde_json::to_value(array.metadata())
                .ok()
                .and_then(|metadata| metadata.get("data_type").cloned())
                .map(|value| value.to_string())
                .unwrap_or_else(|| "an unknown type".to_string());
            anyhow::bail!(
                "entry {} ({}): array \"{name}\" holds {stored}, read as {}",
                self.manifest.stage_name,
                self.location,
                T::DTYPE
            );
        }
        Ok(array)
    }

    /// Reads the whole array `name`.
    pub fn read<T: Element>(&self, name: &str) -> anyhow::Result<NdArray<T>> {
        let array = self.checked_array::<T>(name)?;
        let shape = array.shape().to_vec();
        self.read_subset(name, &array, &array.subset_all(), &shape, "")
    }

    /// Reads the region of `shape` starting at `start` of array `name`.
    pub fn read_region<T: Element>(
        &self,
        name: &str,
        start: &[u64],
        shape: &[u64],
    ) -> anyhow::Result<NdArray<T>> {
        let array = self.checked_array::<T>(name)?;
        let ranges = region_ranges(name, array.shape(), start, shape)?;
        let subset = ArraySubset::new_with_ranges(&ranges);
        self.read_subset(name, &array, &subset, shape, "a region of ")
    }

    /// Reads `subset` (of `shape`) of array `name`, its chunks checked against the manifest
    /// before and after; `what` says in errors what was read (`a region of ` or nothing).
    fn read_subset<T: Element>(
        &self,
        name: &str,
        array: &Array<dyn zarrs::storage::ReadableListableStorageTraits>,
        subset: &ArraySubset,
        shape: &[u64],
        what: &str,
    ) -> anyhow::Result<NdArray<T>> {
        self.check_chunks(name, array, subset)?;
        let data: Vec<T> = array.retrieve_array_subset(subset).with_context(|| {
            format!(
                "entry {}: cannot read {what}array \"{name}\"",
                self.location
            )
        })?;
        // A chunk removed while it was read would have come back as the fill value.
        self.check_chunks(name, array, subset)?;
        NdArray::new(to_usize_shape(shape)?, data)
    }

    /// [`EntryReader::read_region`] of whatever element type the array stores, as `f64`.
    pub fn read_region_f64(
        &self,
        name: &str,
        start: &[u64],
        shape: &[u64],
    ) -> anyhow::Result<Vec<f64>> {
        fn typed<T: Element>(
            entry: &EntryReader,
            name: &str,
            start: &[u64],
            shape: &[u64],
        ) -> anyhow::Result<Vec<f64>> {
            let data = entry.read_region::<T>(name, start, shape)?.data;
            Ok(data.into_iter().map(Element::to_f64).collect())
        }
        match self.dtype(name)?.as_str() {
            "uint8" => typed::<u8>(self, name, start, shape),
            "uint16" => typed::<u16>(self, name, start, shape),
            "uint32" => typed::<u32>(self, name, start, shape),
            "uint64" => typed::<u64>(self, name, start, shape),
            "int32" => typed::<i32>(self, name, start, shape),
            "int64" => typed::<i64>(self, name, start, shape),
            "float32" => typed::<f32>(self, name, start, shape),
            "float64" => typed::<f64>(self, name, start, shape),
            other => anyhow::bail!("array \"{name}\": unsupported dtype {other}"),
        }
    }

    /// Checks that the stored chunk files under `subset` are exactly those the manifest
    /// lists: a listed chunk the store lacks is an error (zarrs would read it as the fill
    /// value), and so is a stored chunk the manifest does not list.
    fn check_chunks(
        &self,
        name: &str,
        array: &Array<dyn zarrs::storage::ReadableListableStorageTraits>,
        subset: &ArraySubset,
    ) -> anyhow::Result<()> {
        let record = self.record(name)?;
        let chunks = array
            .chunks_in_array_subset(subset)
            .ok()
            .flatten()
            .ok_or_else(|| {
                anyhow::anyhow!(
                    "entry {}: array \"{name}\": cannot list the chunks of a region",
                    self.location
                )
            })?;
        for indices in &chunks.indices() {
            let key = array.chunk_key(&indices);
            let listed = record.files.contains_key(key.as_str());
            let present = self
                .storage
                .size_key(&key)
                .with_context(|| {
                    format!(
                        "entry {}: array \"{name}\": cannot read chunk file {}",
                        self.location,
                        key.as_str()
                    )
                })?
                .is_some();
            if listed != present {
                anyhow::bail!(
                    "entry {} ({}): array \"{name}\": chunk file {} {}",
                    self.manifest.stage_name,
                    self.location,
                    key.as_str(),
                    if listed {
                        "is listed in the manifest but missing from the store"
                    } else {
                        "is stored but not listed in the manifest"
                    }
                );
            }
        }
        Ok(())
    }

    /// A stage-level attribute.
    pub fn attribute(&self, key: &str) -> Option<serde_json::Value> {
        self.attributes.get(key).cloned()
    }

    /// All stage-level attributes.
    pub fn attributes(&self) -> &serde_json::Map<String, serde_json::Value> {
        &self.attributes
    }

    /// An attribute of array `array`.
    pub fn array_attribute(&self, array: &str, key: &str) -> Option<serde_json::Value> {
        let opened = self.open_array(array).ok()?;
        opened.attributes().get(key).cloned()
    }

    /// The stored chunk files of array `name` and their compressed size in bytes.
    pub fn stored_bytes(&self, name: &str) -> u64 {
        self.manifest.arrays.get(name).map_or(0, |record| {
            record
                .files
                .keys()
                .filter_map(|key| StoreKey::new(key.clone()).ok())
                .filter_map(|key| self.storage.size_key(&key).ok().flatten())
                .sum()
        })
    }

    /// Checks every stored file against the manifest digests; returns one line per problem,
    /// naming the array and the file.
    pub fn verify(&self) -> Vec<String> {
        let mut problems = self.verify_metadata();
        for name in self.manifest.arrays.keys() {
            problems.extend(self.verify_array(name));
        }
        problems
    }

    /// Checks the group metadata (the stage's attributes) against its digest.
    pub fn verify_metadata(&self) -> Vec<String> {
        let mut problems = Vec::new();
        if self.manifest.metadata_digest.is_empty() {
            problems.push(
                "the manifest has no digest of the group metadata (written by an older version)"
                    .to_string(),
            );
        } else {
            match self.storage.get(&group_metadata_key()) {
                Ok(Some(bytes)) => match metadata_digest(&bytes) {
                    Ok(digest) if digest == self.manifest.metadata_digest => {}
                    Ok(_) => problems
                        .push("zarr.json (group attributes) does not match its digest".to_string()),
                    Err(error) => problems.push(format!("zarr.json: {error:#}")),
                },
                Ok(None) => problems.push("zarr.json (group metadata) is missing".to_string()),
                Err(error) => problems.push(format!("zarr.json unreadable: {error}")),
            }
        }
        problems
    }

    /// Checks the stored files of the array `name` against the manifest: each listed file is
    /// there with its digest, and no other file is.
    pub fn verify_array(&self, name: &str) -> Vec<String> {
        let mut problems = Vec::new();
        let Some(record) = self.manifest.arrays.get(name) else {
            return vec![format!("array \"{name}\" is not in the manifest")];
        };
        match StorePrefix::new(format!("{name}/")).map(|prefix| self.storage.list_prefix(&prefix)) {
            Ok(Ok(stored)) => {
                for key in stored {
                    if !record.files.contains_key(key.as_str()) {
                        problems.push(format!(
                            "array \"{name}\": file {} is not in the manifest",
                            key.as_str()
                        ));
                    }
                }
            }
            Ok(Err(error)) => {
                problems.push(format!("array \"{name}\": cannot list its files: {error}"))
            }
            Err(_) => problems.push(format!("array \"{name}\": invalid array name")),
        }
        for (key, expected) in &record.files {
            let store_key = match StoreKey::new(key.clone()) {
                Ok(store_key) => store_key,
                Err(_) => {
                    problems.push(format!("array \"{name}\": invalid file name {key}"));
                    continue;
                }
            };
            match self.storage.get(&store_key) {
                Ok(Some(bytes)) => {
                    if blake3::hash(&bytes).to_hex().as_str() != expected {
                        problems.push(format!(
                            "array \"{name}\": file {key} does not match its digest"
                        ));
                    }
                }
                Ok(None) => problems.push(format!("array \"{name}\": file {key} is missing")),
                Err(error) => {
                    problems.push(format!("array \"{name}\": file {key} unreadable: {error}"))
                }
            }
        }
        problems
    }
}

/// Converts a stored shape to `usize`.
fn to_usize_shape(shape: &[u64]) -> anyhow::Result<Vec<usize>> {
    shape
        .iter()
        .map(|&extent| {
            usize::try_from(extent)
                .map_err(|_| anyhow::anyhow!("array extent {extent} does not fit in memory"))
        })
        .collect()
}

/// Opens a finished but not yet published entry the way every later reader will (the group
/// document, the manifest, each array's metadata and shape) and fails if any of it cannot be
/// read back, so an entry that cannot be opened is never marked complete.
pub(crate) fn validate_staged(output_dir: &Path, location: &str) -> anyhow::Result<()> {
    let storage = crate::files::entry_storage(output_dir)
        .with_context(|| format!("{location}: cannot open the staged entry"))?;
    let reader = EntryReader::open(storage, location)?;
    for (name, record) in &reader.manifest.arrays {
        let shape = reader.shape(name)?;
        anyhow::ensure!(
            shape == record.shape,
            "{location}: array \"{name}\" reads back with shape {shape:?}, the manifest says {:?}",
            record.shape
        );
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use rayon::prelude::*;

    #[test]
    fn staged_entries_that_cannot_be_read_back_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let writer = EntryWriter::create(dir.path()).unwrap();
        writer
            .write_array::<u8>("mask", &["y", "x"], &[2, 2], &[2, 2], &[0, 1, 254, 255])
            .unwrap();
        let mut record = manifest();
        writer.finish(&mut record).unwrap();
        validate_staged(dir.path(), "staged").unwrap();
        // Array metadata that does not parse (as invalid UTF-8 from a dataset string once
        // produced) is found before the entry is published.
        std::fs::write(
            dir.path().join("mask/zarr.json"),
            b"{\"zarr_format\": 3, \xff}",
        )
        .unwrap();
        let error = format!("{:#}", validate_staged(dir.path(), "staged").unwrap_err());
        assert!(error.contains("mask"), "{error}");
        // So is a group document that does not parse.
        std::fs::write(dir.path().join("zarr.json"), b"\xfe\xff").unwrap();
        let error = format!("{:#}", validate_staged(dir.path(), "staged").unwrap_err());
        assert!(error.contains("staged"), "{error}");
    }

    fn manifest() -> Manifest {
        Manifest {
            kind: "test_arrays".into(),
            version: 1,
            stage_name: "s".into(),
            key: "k".into(),
            config: serde_json::json!({}),
            inputs: vec![],
            external_files: vec![],
            tool_version: "0".into(),
            metadata_digest: String::new(),
            arrays: BTreeMap::new(),
            wall_time_s: 0.0,
            started_at: String::new(),
            finished_at: String::new(),
            log: vec![],
            warnings: vec![],
        }
    }

    fn reopen(dir: &Path) -> EntryReader {
        let store = FilesystemStore::new(dir).unwrap();
        EntryReader::open(Arc::new(store), &dir.display().to_string()).unwrap()
    }

    #[test]
    fn arrays_round_trip_through_chunks_and_regions() {
        let dir = tempfile::tempdir().unwrap();
        let writer = EntryWriter::create(dir.path()).unwrap();
        // 5 x 7 float32 written one 2 x 3 chunk per thread (edge chunks padded).
        let grid: Vec<(u64, u64)> = (0..3).flat_map(|i| (0..3).map(move |j| (i, j))).collect();
        let array = writer
            .create_array::<f32>("field", &["row", "col"], &[5, 7], &[2, 3])
            .unwrap();
        grid.par_iter()
            .try_for_each(|&(chunk_row, chunk_col)| {
                let mut data = Vec::new();
                for row in chunk_row * 2..chunk_row * 2 + 2 {
                    for col in chunk_col * 3..chunk_col * 3 + 3 {
                        data.push((row * 10 + col) as f32);
                    }
                }
                array.write_chunk(&[chunk_row, chunk_col], &data)
            })
            .unwrap();
        assert!(array.write_chunk(&[3, 0], &[0.0; 6]).is_err());
        assert!(array.write_chunk(&[0, 0], &[0.0; 5]).is_err());
        writer
            .write_array::<u8>("mask", &["y", "x"], &[2, 2], &[2, 2], &[0, 1, 254, 255])
            .unwrap();
        writer
            .set_attribute("note", serde_json::json!("hi"))
            .unwrap();
        assert!(
            writer
                .set_attribute(MANIFEST_ATTRIBUTE, serde_json::json!(1))
                .is_err()
        );
        writer
            .set_array_attribute("mask", "meaning", serde_json::json!("foreground"))
            .unwrap();
        assert!(
            writer
                .set_array_attribute("nope", "a", serde_json::json!(1))
                .is_err()
        );
        assert!(
            writer
                .create_array::<u8>("mask", &["y"], &[1], &[1])
                .is_err()
        );
        assert!(
            writer
                .create_array::<u8>("../x", &["y"], &[1], &[1])
                .is_err()
        );
        assert!(writer.create_array::<u8>("z", &["y"], &[1], &[0]).is_err());
        let mut record = manifest();
        writer.finish(&mut record).unwrap();
        assert_eq!(
            record.arrays["field"].files.len(),
            10,
            "9 chunks and zarr.json"
        );

        let reader = reopen(dir.path());
        assert_eq!(reader.array_names(), ["field", "mask"]);
        let field = reader.read::<f32>("field").unwrap();
        assert_eq!(field.shape, [5, 7]);
        for row in 0..5 {
            for col in 0..7 {
                assert_eq!(field.get(&[row, col]), Some(&((row * 10 + col) as f32)));
            }
        }
        let region = reader
            .read_region::<f32>("field", &[3, 2], &[2, 4])
            .unwrap();
        assert_eq!(
            region.data,
            [32.0, 33.0, 34.0, 35.0, 42.0, 43.0, 44.0, 45.0]
        );
        assert!(
            reader
                .read_region::<f32>("field", &[4, 0], &[2, 1])
                .is_err()
        );
        let error = reader.read::<f64>("field").unwrap_err().to_string();
        assert!(
            error.contains("array \"field\" holds \"float32\", read as float64"),
            "{error}"
        );
        assert!(reader.read::<u8>("missing").is_err());
        assert_eq!(reader.read::<u8>("mask").unwrap().data, [0, 1, 254, 255]);
        assert_eq!(reader.attribute("note"), Some(serde_json::json!("hi")));
        assert_eq!(
            reader.array_attribute("mask", "meaning"),
            Some(serde_json::json!("foreground"))
        );
        assert!(reader.verify().is_empty());
    }

    #[test]
    fn verify_names_the_damaged_file() {
        let dir = tempfile::tempdir().unwrap();
        let writer = EntryWriter::create(dir.path()).unwrap();
        let data: Vec<f64> = (0..8).map(f64::from).collect();
        writer
            .write_array::<f64>("values", &["index"], &[8], &[4], &data)
            .unwrap();
        writer.finish(&mut manifest()).unwrap();
        let chunk = dir.path().join("values/c/1");
        let mut bytes = std::fs::read(&chunk).unwrap();
        bytes[0] ^= 1;
        std::fs::write(&chunk, &bytes).unwrap();
        let reader = reopen(dir.path());
        assert_eq!(
            reader.verify(),
            ["array \"values\": file values/c/1 does not match its digest"]
        );
        // The crc32c codec independently rejects the damaged chunk on decode.
        assert!(reader.read::<f64>("values").is_err());
        std::fs::remove_file(&chunk).unwrap();
        assert_eq!(
            reader.verify(),
            ["array \"values\": file values/c/1 is missing"]
        );
    }

    /// A chunk replaced by a FIFO (the failure 4, in a published entry): read
    /// through the storage the store opens entries with, `verify` names it at once instead
    /// of waiting for a writer forever.
    #[cfg(unix)]
    #[test]
    fn a_fifo_in_place_of_a_chunk_is_named_not_waited_on() {
        let dir = tempfile::tempdir().unwrap();
        let writer = EntryWriter::create(dir.path()).unwrap();
        let data: Vec<f64> = (0..8).map(f64::from).collect();
        writer
            .write_array::<f64>("values", &["index"], &[8], &[4], &data)
            .unwrap();
        writer.finish(&mut manifest()).unwrap();
        let chunk = dir.path().join("values/c/1");
        std::fs::remove_file(&chunk).unwrap();
        crate::test_support::make_fifo(&chunk);
        let root = dir.path().to_path_buf();
        let (problems, read) = crate::test_support::finishes_within(2, move || {
            let storage = crate::files::entry_storage(&root).unwrap();
            let reader = EntryReader::open(storage, &root.display().to_string()).unwrap();
            let read = reader.read::<f64>("values").map(|_| ());
            (reader.verify(), read.map_err(|error| format!("{error:#}")))
        });
        assert_eq!(problems.len(), 1, "{problems:?}");
        assert!(
            problems[0].starts_with("array \"values\": file values/c/1 unreadable")
                && problems[0].contains("a FIFO (named pipe)"),
            "{problems:?}"
        );
        let error = read.unwrap_err();
        assert!(error.contains("a FIFO (named pipe)"), "{error}");
    }

    #[test]
    fn missing_or_unlisted_chunks_are_errors_not_fill_values() {
        let dir = tempfile::tempdir().unwrap();
        let writer = EntryWriter::create(dir.path()).unwrap();
        let data: Vec<f64> = (1..=8).map(f64::from).collect();
        writer
            .write_array::<f64>("values", &["index"], &[8], &[4], &data)
            .unwrap();
        // Chunk 1 is never written: it reads as the fill value, legitimately.
        let sparse = writer
            .create_array::<f64>("sparse", &["index"], &[8], &[4])
            .unwrap();
        sparse.write_chunk(&[0], &[1.0; 4]).unwrap();
        writer.finish(&mut manifest()).unwrap();
        let reader = reopen(dir.path());
        assert_eq!(
            reader.read::<f64>("sparse").unwrap().data,
            [1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0]
        );

        let chunk = dir.path().join("values/c/1");
        let bytes = std::fs::read(&chunk).unwrap();
        std::fs::remove_file(&chunk).unwrap();
        let expected = "array \"values\": chunk file values/c/1 is listed in the manifest but missing from the store";
        let error = reader.read::<f64>("values").unwrap_err().to_string();
        assert!(
            error.contains(expected) && error.contains("entry s ("),
            "{error}"
        );
        let error = reader
            .read_region::<f64>("values", &[5], &[2])
            .unwrap_err()
            .to_string();
        assert!(error.contains(expected), "{error}");
        // A region that does not touch the missing chunk still reads.
        assert_eq!(
            reader
                .read_region::<f64>("values", &[0], &[3])
                .unwrap()
                .data,
            [1.0, 2.0, 3.0]
        );
        std::fs::write(&chunk, bytes).unwrap();
        assert_eq!(reader.read::<f64>("values").unwrap().data, data);

        // A chunk file the manifest does not list is not read either.
        std::fs::copy(dir.path().join("sparse/c/0"), dir.path().join("sparse/c/1")).unwrap();
        let error = reader.read::<f64>("sparse").unwrap_err().to_string();
        assert!(
            error.contains("chunk file sparse/c/1 is stored but not listed in the manifest"),
            "{error}"
        );
        assert_eq!(
            reader.verify(),
            ["array \"sparse\": file sparse/c/1 is not in the manifest"]
        );
    }

    #[test]
    fn manifest_covers_group_and_array_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let writer = EntryWriter::create(dir.path()).unwrap();
        writer
            .write_array::<f64>("values", &["index"], &[2], &[2], &[1.0, 2.0])
            .unwrap();
        writer
            .set_array_attribute("values", "units", serde_json::json!("m"))
            .unwrap();
        writer
            .set_attribute("background", serde_json::json!(0.0))
            .unwrap();
        writer.finish(&mut manifest()).unwrap();
        let reader = reopen(dir.path());
        assert!(reader.verify().is_empty(), "{:?}", reader.verify());
        assert_eq!(reader.manifest().metadata_digest.len(), 64);

        // The stage attribute `background` edited in the group zarr.json.
        let group = dir.path().join("zarr.json");
        let original = std::fs::read_to_string(&group).unwrap();
        assert!(original.contains("\"background\": 0.0"), "{original}");
        std::fs::write(
            &group,
            original.replace("\"background\": 0.0", "\"background\": 1.0"),
        )
        .unwrap();
        assert_eq!(
            reopen(dir.path()).verify(),
            ["zarr.json (group attributes) does not match its digest"]
        );
        // Reformatting the document (same content) is not a change.
        let value: serde_json::Value = serde_json::from_str(&original).unwrap();
        std::fs::write(&group, serde_json::to_string(&value).unwrap()).unwrap();
        assert!(reopen(dir.path()).verify().is_empty());

        // An array attribute edited in the array's zarr.json.
        let array = dir.path().join("values/zarr.json");
        let text = std::fs::read_to_string(&array).unwrap();
        std::fs::write(&array, text.replace("\"m\"", "\"km\"")).unwrap();
        assert_eq!(
            reopen(dir.path()).verify(),
            ["array \"values\": file values/zarr.json does not match its digest"]
        );
    }
}
