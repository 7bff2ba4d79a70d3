//! Key derivation: the one place where cache keys are hashed, plus digests of external files
//! (memoised by path, size and modification time).
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

/// Compact JSON with object keys sorted at every level, whatever the map implementation.
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
        other => text.push_str(&other.to_string()),
    }
}

#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
struct MemoRecord {
    size: u64,
    mtime_ns: u128,
    digest: String,
}

/// Digests of external files, remembered by (path, size, mtime) in a JSON file so raw
/// dataset files are hashed once.
#[derive(Debug)]
pub struct FileDigests {
    memo_path: PathBuf,
    memo: BTreeMap<String, MemoRecord>,
    changed: bool,
}

impl FileDigests {
    /// Loads the memo at `memo_path` (a missing or unreadable memo starts empty).
    pub fn load(memo_path: &Path) -> Self {
        let memo = fs::read(memo_path)
            .ok()
            .and_then(|bytes| serde_json::from_slice(&bytes).ok())
            .unwrap_or_default();
        Self {
            memo_path: memo_path.to_path_buf(),
            memo,
            changed: false,
        }
    }

    /// Digest of a file, or of a folder (every file under it, by relative path).
    pub fn digest(&mut self, path: &Path) -> anyhow::Result<String> {
        let metadata = fs::metadata(path)
            .with_context(|| format!("external input {} cannot be read", path.display()))?;
        if metadata.is_dir() {
            let mut files = Vec::new();
            collect_files(path, path, &mut files)?;
            files.sort();
            let mut hasher = blake3::Hasher::new();
            for relative in files {
                let digest = self.digest(&path.join(&relative))?;
                hasher.update(relative.as_bytes());
                hasher.update(&[0]);
                hasher.update(digest.as_bytes());
                hasher.update(&[0]);
            }
            return Ok(format!("dir:{}", hasher.finalize().to_hex()));
        }
        let canonical = fs::canonicalize(path)
            .with_context(|| format!("external input {} cannot be resolved", path.display()))?;
        let memo_key = canonical.display().to_string();
        let mtime_ns = metadata
            .modified()
            .ok()
            .and_then(|time| time.duration_since(std::time::UNIX_EPOCH).ok())
            .map(|duration| duration.as_nanos())
            .unwrap_or(0);
        if let Some(record) = self.memo.get(&memo_key)
            && record.size == metadata.len()
            && record.mtime_ns == mtime_ns
        {
            return Ok(record.digest.clone());
        }
        let digest = hash_file(&canonical)?;
        self.memo.insert(
            memo_key,
            MemoRecord {
                size: metadata.len(),
                mtime_ns,
                digest: digest.clone(),
            },
        );
        self.changed = true;
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

fn collect_files(root: &Path, dir: &Path, files: &mut Vec<String>) -> anyhow::Result<()> {
    for entry in fs::read_dir(dir).with_context(|| format!("cannot list {}", dir.display()))? {
        let entry = entry.with_context(|| format!("cannot list {}", dir.display()))?;
        let path = entry.path();
        if path.is_dir() {
            collect_files(root, &path, files)?;
        } else if path.is_file() {
            let relative = path.strip_prefix(root).unwrap_or(&path);
            files.push(relative.to_string_lossy().replace('\\', "/"));
        }
    }
    Ok(())
}

fn hash_file(path: &Path) -> anyhow::Result<String> {
    let mut file =
        fs::File::open(path).with_context(|| format!("cannot open {}", path.display()))?;
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
}
