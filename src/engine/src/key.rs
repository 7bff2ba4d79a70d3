//! Key derivation: the one place where cache keys are hashed, plus digests of external files
//! (memoised by path, size, modification time, inode and change time).
//!
//! If you change anything that goes into a key, bump [`KEY_FORMAT_VERSION`].

use std::collections::BTreeMap;
use std::fs;
use std::io::Read as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use serde::{Deserialize, Serialize};

/// Version of the key derivation itself; mixed into every key.
pub const KEY_FORMAT_VERSION: u32 = 1;

/// Everything a stage key depends on.
#[derive(Debug, Clone)]
pub struct KeyMaterial<'a> {
    pub kind: &'a str,
    pub version: u32,
    /// The effective (resolved) config.
    pub config: &'a serde_json::Value,
    /// Keys of the input entries, in input order.
    pub input_keys: &'a [String],
    /// Digests of external files, in the order the stage lists them.
    pub external_digests: &'a [String],
}

/// The stage key: blake3 (hex) of the length-prefixed fields of `material`.
pub fn stage_key(material: &KeyMaterial<'_>) -> String {
    let mut hasher = blake3::Hasher::new();
    let mut field = |bytes: &[u8]| {
        hasher.update(&(bytes.len() as u64).to_le_bytes());
        hasher.update(bytes);
    };
    field(b"seqavatar-stage-key");
    field(&KEY_FORMAT_VERSION.to_le_bytes());
    field(material.kind.as_bytes());
    field(&material.version.to_le_bytes());
    field(canonical_json(material.config).as_bytes());
    field(&(material.input_keys.len() as u64).to_le_bytes());
    for key in material.input_keys {
        field(key.as_bytes());
    }
    field(&(material.external_digests.len() as u64).to_le_bytes());
    for digest in material.external_digests {
        field(digest.as_bytes());
    }
    hasher.finalize().to_hex().to_string()
}

/// Compact JSON with object keys sorted at every level, whatever the map implementation, and
/// a negative zero written as `0.0`.
pub fn canonical_json(value: &serde_json::Value) -> String {
    let mut text = String::new();
    write_canonical(value, &mut text);
    text
}

fn write_canonical(value: &serde_json::Value, text: &mut String) {
    match value {
        serde_json::Value::Object(map) => {
            let mut keys: Vec<&String> = map.keys().collect();
            keys.sort();
            text.push('{');
            for (position, key) in keys.iter().enumerate() {
                if position > 0 {
                    text.push(',');
                }
                text.push_str(&serde_json::Value::String((*key).clone()).to_string());
                text.push(':');
                write_canonical(&map[*key], text);
            }
            text.push('}');
        }
        serde_json::Value::Array(items) => {
            text.push('[');
            for (position, item) in items.iter().enumerate() {
                if position > 0 {
                    text.push(',');
                }
                write_canonical(item, text);
            }
            text.push(']');
        }
        // `-0.0` and `0.0` are the same value to every stage: one spelling, one key. (Other
        // numbers keep serde_json's spelling, so no existing key changes.)
        serde_json::Value::Number(number) if number.as_f64() == Some(0.0) && number.is_f64() => {
            text.push_str("0.0");
        }
        other => text.push_str(&other.to_string()),
    }
}

/// What the memo compares before it trusts a remembered digest. The change time and the
/// inode catch an edit of the same size whose modification time was set back (`touch -d`,
/// `cp -p`, an editor restoring it): the kernel sets `ctime` on every write and rename.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
struct FileStamp {
    size: u64,
    mtime_ns: u128,
    device: u64,
    inode: u64,
    ctime_ns: i128,
}

impl FileStamp {
    fn of(metadata: &fs::Metadata) -> Self {
        let mtime_ns = metadata
            .modified()
            .ok()
            .and_then(|time| time.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|duration| duration.as_nanos())
            .unwrap_or(0);
        #[cfg(unix)]
        let (device, inode, ctime_ns) = {
            use std::os::unix::fs::MetadataExt as _;
            (
                metadata.dev(),
                metadata.ino(),
                i128::from(metadata.ctime()) * 1_000_000_000 + i128::from(metadata.ctime_nsec()),
            )
        };
        #[cfg(not(unix))]
        let (device, inode, ctime_ns) = (0, 0, 0);
        Self {
            size: metadata.len(),
            mtime_ns,
            device,
            inode,
            ctime_ns,
        }
    }
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct MemoRecord {
    stamp: FileStamp,
    digest: String,
}

/// Digests of external files, remembered by (path, size, mtime, device, inode, ctime) in a
/// JSON file so raw dataset files are hashed once, not on every run.
#[derive(Debug)]
pub struct FileDigests {
    memo_path: PathBuf,
    memo: BTreeMap<String, MemoRecord>,
    changed: bool,
    /// How many files were read and hashed (not answered from the memo) since loading.
    hashed: usize,
    /// Canonical folders left out of folder digests (the cache, when it lies inside a
    /// dataset folder: it changes on every run).
    excluded: Vec<PathBuf>,
}

impl FileDigests {
    /// Loads the memo at `memo_path` (a missing or unreadable memo starts empty).
    pub fn load(memo_path: &Path) -> Self {
        let memo = crate::files::read_regular_file(memo_path)
            .ok()
            .and_then(|bytes| serde_json::from_slice(&bytes).ok())
            .unwrap_or_default();
        Self {
            memo_path: memo_path.to_path_buf(),
            memo,
            changed: false,
            hashed: 0,
            excluded: Vec::new(),
        }
    }

    /// Leaves `dir` (if it exists) out of every folder digest: the cache's own folder, which
    /// a run changes, must not change the digest of a dataset folder that contains it.
    pub fn exclude(&mut self, dir: &Path) {
        if let Ok(canonical) = fs::canonicalize(dir) {
            self.excluded.push(canonical);
        }
    }

    /// Digest of a regular file, or of a folder (every regular file under it, by relative
    /// path, walked by [`crate::files::walk_regular_files`]: links out of the folder,
    /// devices, FIFOs and sockets are errors; excluded folders are skipped).
    pub fn digest(&mut self, path: &Path) -> anyhow::Result<String> {
        let metadata = fs::metadata(path)
            .with_context(|| format!("external input {} cannot be read", path.display()))?;
        if metadata.is_dir() {
            let mut digests = BTreeMap::new();
            for relative in crate::files::walk_regular_files(path, &self.excluded)? {
                let digest = self.digest(&path.join(&relative))?;
                digests.insert(relative, digest);
            }
            return Ok(format!("dir:{}", combined_digest(&digests)));
        }
        let metadata = crate::files::regular_file_metadata(path)
            .with_context(|| format!("external input {}", path.display()))?;
        let canonical = fs::canonicalize(path)
            .with_context(|| format!("external input {} cannot be resolved", path.display()))?;
        let memo_key = canonical.display().to_string();
        let stamp = FileStamp::of(&metadata);
        if let Some(record) = self.memo.get(&memo_key)
            && record.stamp == stamp
        {
            return Ok(record.digest.clone());
        }
        let digest = hash_file(&canonical)?;
        self.hashed += 1;
        // A file written while it was hashed gets a new stamp: remember nothing then, so the
        // next run hashes it again instead of pairing the new stamp with old content.
        let after = fs::metadata(&canonical)
            .map(|metadata| FileStamp::of(&metadata))
            .ok();
        if after == Some(stamp) {
            self.memo.insert(
                memo_key,
                MemoRecord {
                    stamp,
                    digest: digest.clone(),
                },
            );
            self.changed = true;
        }
        Ok(digest)
    }

    /// Writes the memo back (atomically) if it changed.
    pub fn save(&mut self) -> anyhow::Result<()> {
        if !self.changed {
            return Ok(());
        }
        let temporary = self
            .memo_path
            .with_extension(format!("tmp.{}", std::process::id()));
        let bytes = serde_json::to_vec(&self.memo).context("cannot serialize the file memo")?;
        fs::write(&temporary, bytes)
            .with_context(|| format!("cannot write {}", temporary.display()))?;
        fs::rename(&temporary, &self.memo_path)
            .with_context(|| format!("cannot write {}", self.memo_path.display()))?;
        self.changed = false;
        Ok(())
    }
}

/// blake3 over sorted (name, digest) pairs: of a folder's files, or of an array's stored files.
pub(crate) fn combined_digest(files: &BTreeMap<String, String>) -> String {
    let mut hasher = blake3::Hasher::new();
    for (key, digest) in files {
        hasher.update(key.as_bytes());
        hasher.update(&[0]);
        hasher.update(digest.as_bytes());
        hasher.update(&[0]);
    }
    hasher.finalize().to_hex().to_string()
}

fn hash_file(path: &Path) -> anyhow::Result<String> {
    let mut file = crate::files::open_regular_file(path)?;
    let mut hasher = blake3::Hasher::new();
    let mut buffer = vec![0u8; 1 << 20];
    loop {
        let count = file
            .read(&mut buffer)
            .with_context(|| format!("cannot read {}", path.display()))?;
        if count == 0 {
            break;
        }
        hasher.update(&buffer[..count]);
    }
    Ok(hasher.finalize().to_hex().to_string())
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// A cache kept inside a dataset folder (a run from inside the dataset) is left out of
    /// the folder's digest: what a run writes there must not give the next run a new key.
    #[test]
    fn an_excluded_cache_inside_a_folder_does_not_change_its_digest() {
        let dataset = tempfile::tempdir().unwrap();
        std::fs::write(dataset.path().join("frame.jpg"), b"pixels").unwrap();
        let cache = dataset.path().join("cache");
        std::fs::create_dir(&cache).unwrap();
        let mut digests = FileDigests::load(&cache.join("memo.json"));
        digests.exclude(&cache);
        let before = digests.digest(dataset.path()).unwrap();
        std::fs::create_dir_all(cache.join("ingest/abc")).unwrap();
        std::fs::write(cache.join("ingest/abc/zarr.json"), b"{}").unwrap();
        digests.save().unwrap();
        assert_eq!(digests.digest(dataset.path()).unwrap(), before);
        // Without the exclusion the same cache changes the digest (what made every run a
        // new key).
        let mut plain = FileDigests::load(&cache.join("memo.json"));
        assert_ne!(plain.digest(dataset.path()).unwrap(), before);
        // The dataset's own files still count.
        std::fs::write(dataset.path().join("frame.jpg"), b"other").unwrap();
        assert_ne!(digests.digest(dataset.path()).unwrap(), before);
    }

    /// `/dev/zero`, a FIFO and `/proc` files as external inputs are refused from their metadata,
    /// at once.
    #[cfg(unix)]
    #[test]
    fn devices_and_fifos_are_not_hashed() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe");
        crate::test_support::make_fifo(&fifo);
        let mut digests = FileDigests::load(&dir.path().join("memo.json"));
        for path in [Path::new("/dev/zero"), fifo.as_path()] {
            let start = std::time::Instant::now();
            let error = format!("{:#}", digests.digest(path).unwrap_err());
            assert!(start.elapsed() < std::time::Duration::from_secs(1));
            assert!(error.contains("only regular files"), "{error}");
        }
        // `/proc/self/pagemap` looks regular with size 0 and yields gigabytes: refused from
        // its file system before a byte is hashed.
        #[cfg(target_os = "linux")]
        for name in ["/proc/self/pagemap", "/proc/self/status"] {
            let start = std::time::Instant::now();
            let error = format!("{:#}", digests.digest(Path::new(name)).unwrap_err());
            assert!(
                start.elapsed() < std::time::Duration::from_secs(1),
                "{error}"
            );
            assert!(error.contains("kernel's proc file system"), "{error}");
            assert!(error.contains(name), "{error}");
        }
        assert_eq!(digests.hashed, 0);
    }

    fn key_of(config: serde_json::Value, inputs: &[&str], version: u32) -> String {
        let input_keys: Vec<String> = inputs.iter().map(|s| s.to_string()).collect();
        stage_key(&KeyMaterial {
            kind: "test_arrays",
            version,
            config: &config,
            input_keys: &input_keys,
            external_digests: &[],
        })
    }

    #[test]
    fn key_ignores_key_order_but_not_values() {
        let first: serde_json::Value =
            serde_json::from_str(r#"{"a": 1, "b": {"y": [1, 2], "x": "s"}}"#).unwrap();
        let second: serde_json::Value =
            serde_json::from_str(r#"{"b": {"x": "s", "y": [1, 2]}, "a": 1}"#).unwrap();
        assert_eq!(key_of(first.clone(), &[], 1), key_of(second, &[], 1));
        assert_ne!(
            key_of(first.clone(), &[], 1),
            key_of(json!({"a": 2}), &[], 1)
        );
        assert_ne!(key_of(first.clone(), &[], 1), key_of(first.clone(), &[], 2));
        assert_ne!(
            key_of(first.clone(), &["u"], 1),
            key_of(first.clone(), &["v"], 1)
        );
        assert_ne!(
            key_of(first.clone(), &["u", "v"], 1),
            key_of(first, &["v", "u"], 1)
        );
    }

    #[test]
    fn key_is_a_pinned_value() {
        // Changing this value means existing caches are invalidated: bump KEY_FORMAT_VERSION.
        let key = key_of(json!({"size": 4}), &[], 1);
        assert_eq!(key.len(), 64);
        let mut hasher = blake3::Hasher::new();
        for field in [
            &b"seqavatar-stage-key"[..],
            &KEY_FORMAT_VERSION.to_le_bytes(),
            b"test_arrays",
            &1u32.to_le_bytes(),
            br#"{"size":4}"#,
            &0u64.to_le_bytes(),
            &0u64.to_le_bytes(),
        ] {
            hasher.update(&(field.len() as u64).to_le_bytes());
            hasher.update(field);
        }
        assert_eq!(key, hasher.finalize().to_hex().to_string());
    }

    /// `-0.0` and `0.0` give one key (the issue's "small one"); other numbers keep their
    /// spelling, so keys of configs without a negative zero are unchanged.
    #[test]
    fn a_negative_zero_gives_the_key_of_zero() {
        let negative: serde_json::Value =
            serde_json::from_str(r#"{"x": -0.0, "y": [-0.0]}"#).unwrap();
        let positive: serde_json::Value =
            serde_json::from_str(r#"{"x": 0.0, "y": [0.0]}"#).unwrap();
        assert_eq!(canonical_json(&negative), r#"{"x":0.0,"y":[0.0]}"#);
        assert_eq!(key_of(negative, &[], 1), key_of(positive, &[], 1));
        // From YAML too (how configs arrive).
        let yaml: serde_json::Value = serde_saphyr::from_str("x: -0.0\ny: [-0.0]\n").unwrap();
        assert_eq!(canonical_json(&yaml), r#"{"x":0.0,"y":[0.0]}"#);
        assert_eq!(
            canonical_json(&json!({"a": 0, "b": 0.5, "c": -1.5, "d": 1.0, "e": -3})),
            r#"{"a":0,"b":0.5,"c":-1.5,"d":1.0,"e":-3}"#
        );
    }

    #[test]
    fn canonical_json_sorts_nested_keys() {
        let value: serde_json::Value =
            serde_json::from_str(r#"{"z": {"b": 1, "a": [{"d": 1, "c": 2}]}, "y": null}"#).unwrap();
        assert_eq!(
            canonical_json(&value),
            r#"{"y":null,"z":{"a":[{"c":2,"d":1}],"b":1}}"#
        );
    }

    #[test]
    fn file_digests_are_memoised_and_track_changes() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("data.bin");
        fs::write(&file, b"hello").unwrap();
        let memo_path = dir.path().join("memo.json");
        let mut digests = FileDigests::load(&memo_path);
        let first = digests.digest(&file).unwrap();
        assert_eq!(first, blake3::hash(b"hello").to_hex().to_string());
        digests.save().unwrap();
        let mut reloaded = FileDigests::load(&memo_path);
        assert_eq!(reloaded.digest(&file).unwrap(), first);
        assert!(!reloaded.changed, "memo hit must not rehash");
        fs::write(&file, b"hello, longer").unwrap();
        assert_ne!(reloaded.digest(&file).unwrap(), first);
        let folder_digest = reloaded.digest(dir.path()).unwrap();
        assert!(folder_digest.starts_with("dir:"));
        let missing = reloaded.digest(&dir.path().join("nope")).unwrap_err();
        assert!(missing.to_string().contains("nope"));
    }

    #[test]
    fn same_size_edit_with_restored_mtime_is_rehashed() {
        let dir = tempfile::tempdir().unwrap();
        let folder = dir.path().join("dataset");
        fs::create_dir_all(folder.join("Camera_B1")).unwrap();
        let image = folder.join("Camera_B1/000000.jpg");
        fs::write(&image, b"first image").unwrap();
        fs::write(folder.join("annots.npy"), b"annotations").unwrap();
        let memo_path = dir.path().join("memo.json");
        let mut digests = FileDigests::load(&memo_path);
        let original = digests.digest(&folder).unwrap();
        assert_eq!(digests.hashed, 2);
        digests.save().unwrap();

        // Nothing changed: answered from the memo, no file read.
        let mut unchanged = FileDigests::load(&memo_path);
        assert_eq!(unchanged.digest(&folder).unwrap(), original);
        assert_eq!(unchanged.hashed, 0);

        // Same size, modification time set back: the change time still moves.
        let modified = fs::metadata(&image).unwrap().modified().unwrap();
        std::thread::sleep(std::time::Duration::from_millis(20));
        fs::write(&image, b"other image").unwrap();
        fs::File::options()
            .write(true)
            .open(&image)
            .unwrap()
            .set_modified(modified)
            .unwrap();
        assert_eq!(fs::metadata(&image).unwrap().modified().unwrap(), modified);
        let mut edited = FileDigests::load(&memo_path);
        let after_edit = edited.digest(&folder).unwrap();
        assert_ne!(
            after_edit, original,
            "a same-size edit must change the digest"
        );
        assert_eq!(edited.hashed, 1, "only the edited file is read");
    }
}
