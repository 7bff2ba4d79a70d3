//! Blocking access to a prefix of an S3-compatible bucket through `object_store`, driven by a
//! small tokio runtime owned by the [`Bucket`]. Endpoint, credentials and region come from the
//! standard AWS environment variables; timeouts and retries from `SEQAVATAR_S3_*`.

use std::path::Path;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context as _;
use futures_util::{StreamExt as _, TryStreamExt as _};
use object_store::aws::{AmazonS3Builder, AmazonS3ConfigKey};
use object_store::path::Path as ObjectPath;
use object_store::{
    BackoffConfig, ClientConfigKey, ObjectStore, ObjectStoreExt as _, PutMode, PutOptions,
    PutPayload, RetryConfig, UpdateVersion,
};

/// Concurrent requests when uploading or downloading the files of an entry.
const TRANSFER_CONCURRENCY: usize = 8;

/// Seconds from an environment variable, or `default` when it is unset.
pub(crate) fn env_seconds(name: &str, default: f64) -> anyhow::Result<Duration> {
    match std::env::var(name) {
        Err(_) => Ok(Duration::from_secs_f64(default)),
        Ok(text) => parse_seconds(name, &text),
    }
}

/// A positive, finite number of seconds (at most about 30 years).
fn parse_seconds(name: &str, text: &str) -> anyhow::Result<Duration> {
    match text.trim().parse::<f64>() {
        Ok(value) if value.is_finite() && value > 0.0 && value < 1e9 => {
            Ok(Duration::from_secs_f64(value))
        }
        _ => anyhow::bail!(
            "environment variable {name}={text}: expected a positive number of seconds"
        ),
    }
}

/// A parsed `s3://bucket/prefix` cache URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct S3Url {
    pub bucket: String,
    /// Path inside the bucket without leading or trailing `/` (may be empty).
    pub prefix: String,
}

impl S3Url {
    /// Parses `s3://bucket[/prefix]`.
    pub fn parse(text: &str) -> anyhow::Result<Self> {
        let rest = text
            .strip_prefix("s3://")
            .ok_or_else(|| anyhow::anyhow!("cache URL \"{text}\": expected s3://bucket/prefix"))?;
        let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
        anyhow::ensure!(
            !bucket.is_empty()
                && bucket
                    .chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.'),
            "cache URL \"{text}\": bucket name \"{bucket}\" must be non-empty and use lowercase letters, digits, '-' and '.'"
        );
        let prefix = prefix.trim_matches('/');
        for part in prefix.split('/').filter(|part| !part.is_empty()) {
            anyhow::ensure!(
                part != "." && part != ".." && !part.contains('\\'),
                "cache URL \"{text}\": invalid path component \"{part}\""
            );
        }
        Ok(Self {
            bucket: bucket.to_string(),
            prefix: prefix
                .split('/')
                .filter(|part| !part.is_empty())
                .collect::<Vec<_>>()
                .join("/"),
        })
    }
}

impl std::fmt::Display for S3Url {
    fn fmt(&self, formatter: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        if self.prefix.is_empty() {
            write!(formatter, "s3://{}", self.bucket)
        } else {
            write!(formatter, "s3://{}/{}", self.bucket, self.prefix)
        }
    }
}

/// One stored object: its path relative to the listed folder, its size and when it was last
/// written (the server's clock).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct ObjectInfo {
    pub name: String,
    pub size: u64,
    pub modified: std::time::SystemTime,
}

/// Blocking operations on the objects under one prefix of a bucket. Paths given to the methods
/// are relative to the prefix (`kind/key/.complete`).
pub(crate) struct Bucket {
    runtime: tokio::runtime::Runtime,
    store: Arc<dyn ObjectStore>,
    url: S3Url,
}

impl Bucket {
    /// Connects to the bucket of `url` with the AWS environment variables.
    pub fn open(url: &S3Url) -> anyhow::Result<Self> {
        // reqwest is built with rustls but no default crypto provider; install ring's once.
        let _ = rustls::crypto::ring::default_provider().install_default();
        let timeout = env_seconds("SEQAVATAR_S3_TIMEOUT_S", 30.0)?;
        let retry_timeout = env_seconds("SEQAVATAR_S3_RETRY_TIMEOUT_S", 120.0)?;
        let retry = RetryConfig {
            backoff: BackoffConfig {
                init_backoff: Duration::from_millis(100),
                max_backoff: Duration::from_secs(5).min(retry_timeout),
                base: 2.0,
            },
            max_retries: 10,
            retry_timeout,
        };
        let store = AmazonS3Builder::from_env()
            .with_bucket_name(&url.bucket)
            .with_config(
                AmazonS3ConfigKey::Client(ClientConfigKey::Timeout),
                format!("{}ms", timeout.as_millis()),
            )
            .with_config(
                AmazonS3ConfigKey::Client(ClientConfigKey::ConnectTimeout),
                format!("{}ms", timeout.as_millis().min(10_000)),
            )
            .with_retry(retry)
            .build()
            .with_context(|| {
                format!(
                    "cannot configure access to {url} (set AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION; AWS_ALLOW_HTTP=true for an http endpoint)"
                )
            })?;
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("seqavatar-s3")
            .enable_all()
            .build()
            .context("cannot start the tokio runtime for S3 access")?;
        Ok(Self {
            runtime,
            store: Arc::new(store),
            url: url.clone(),
        })
    }

    pub fn url(&self) -> &S3Url {
        &self.url
    }

    /// The object path of `relative` under the prefix.
    fn path(&self, relative: &str) -> ObjectPath {
        let relative = relative.trim_matches('/');
        let joined = match (self.url.prefix.is_empty(), relative.is_empty()) {
            (true, _) => relative.to_string(),
            (false, true) => self.url.prefix.clone(),
            (false, false) => format!("{}/{relative}", self.url.prefix),
        };
        ObjectPath::from(joined)
    }

    /// The `s3://` URL of `relative`, for messages.
    pub fn describe(&self, relative: &str) -> String {
        format!("s3://{}/{}", self.url.bucket, self.path(relative))
    }

    /// The content and ETag of an object, `None` when it does not exist.
    pub fn get(&self, relative: &str) -> anyhow::Result<Option<(Vec<u8>, Option<String>)>> {
        let path = self.path(relative);
        let result = self.runtime.block_on(async {
            let response = self.store.get(&path).await?;
            let etag = response.meta.e_tag.clone();
            let bytes = response.bytes().await?;
            Ok::<_, object_store::Error>((bytes.to_vec(), etag))
        });
        match result {
            Ok(found) => Ok(Some(found)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(error) => {
                Err(error).with_context(|| format!("cannot read {}", self.describe(relative)))
            }
        }
    }

    /// The ETag of an object (`Some(None)` when the server gives none), `None` when absent.
    pub fn head(&self, relative: &str) -> anyhow::Result<Option<Option<String>>> {
        let path = self.path(relative);
        match self.runtime.block_on(self.store.head(&path)) {
            Ok(meta) => Ok(Some(meta.e_tag)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(error) => {
                Err(error).with_context(|| format!("cannot read {}", self.describe(relative)))
            }
        }
    }

    /// Creates an object only if none exists (`If-None-Match: *`); returns its ETag, or
    /// `None` when the object already existed.
    pub fn put_create(&self, relative: &str, bytes: Vec<u8>) -> anyhow::Result<Option<String>> {
        self.put_mode(relative, bytes, PutMode::Create)
    }

    /// Replaces an object only if its ETag is still `etag` (`If-Match`); returns the new ETag,
    /// or `None` when the object changed or vanished meanwhile.
    pub fn put_update(
        &self,
        relative: &str,
        bytes: Vec<u8>,
        etag: &str,
    ) -> anyhow::Result<Option<String>> {
        self.put_mode(
            relative,
            bytes,
            PutMode::Update(UpdateVersion {
                e_tag: Some(etag.to_string()),
                version: None,
            }),
        )
    }

    fn put_mode(
        &self,
        relative: &str,
        bytes: Vec<u8>,
        mode: PutMode,
    ) -> anyhow::Result<Option<String>> {
        let path = self.path(relative);
        let options = PutOptions {
            mode,
            ..PutOptions::default()
        };
        match self
            .runtime
            .block_on(self.store.put_opts(&path, PutPayload::from(bytes), options))
        {
            Ok(result) => Ok(Some(result.e_tag.unwrap_or_default())),
            Err(object_store::Error::AlreadyExists { .. })
            | Err(object_store::Error::Precondition { .. })
            | Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(error) => {
                Err(error).with_context(|| format!("cannot write {}", self.describe(relative)))
            }
        }
    }

    /// Deletes an object; an absent object is fine.
    pub fn delete(&self, relative: &str) -> anyhow::Result<()> {
        let path = self.path(relative);
        match self.runtime.block_on(self.store.delete(&path)) {
            Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(()),
            Err(error) => {
                Err(error).with_context(|| format!("cannot delete {}", self.describe(relative)))
            }
        }
    }

    /// The immediate sub-folders and the objects directly inside folder `relative`.
    pub fn list_folder(&self, relative: &str) -> anyhow::Result<(Vec<String>, Vec<ObjectInfo>)> {
        let path = self.path(relative);
        let listed = self
            .runtime
            .block_on(self.store.list_with_delimiter(Some(&path)))
            .with_context(|| format!("cannot list {}", self.describe(relative)))?;
        let folders = listed
            .common_prefixes
            .iter()
            .filter_map(|prefix| prefix.filename().map(str::to_string))
            .collect();
        let objects = listed
            .objects
            .iter()
            .filter_map(|meta| {
                meta.location.filename().map(|name| ObjectInfo {
                    name: name.to_string(),
                    size: meta.size,
                    modified: meta.last_modified.into(),
                })
            })
            .collect();
        Ok((folders, objects))
    }

    /// Every object under folder `relative`, named relative to it, sorted.
    pub fn list_tree(&self, relative: &str) -> anyhow::Result<Vec<ObjectInfo>> {
        let path = self.path(relative);
        let metas: Vec<object_store::ObjectMeta> = self
            .runtime
            .block_on(self.store.list(Some(&path)).try_collect())
            .with_context(|| format!("cannot list {}", self.describe(relative)))?;
        let base: Vec<_> = path.parts().collect();
        let mut objects: Vec<ObjectInfo> = metas
            .into_iter()
            .filter_map(|meta| {
                let parts: Vec<_> = meta.location.parts().collect();
                if parts.len() <= base.len() || parts[..base.len()] != base[..] {
                    return None;
                }
                let name = parts[base.len()..]
                    .iter()
                    .map(|part| part.as_ref())
                    .collect::<Vec<_>>()
                    .join("/");
                Some(ObjectInfo {
                    name,
                    size: meta.size,
                    modified: meta.last_modified.into(),
                })
            })
            .collect();
        objects.sort_by(|a, b| a.name.cmp(&b.name));
        Ok(objects)
    }

    /// Deletes every object under folder `relative`; returns their total size.
    pub fn delete_tree(&self, relative: &str) -> anyhow::Result<u64> {
        let objects = self.list_tree(relative)?;
        let bytes = objects.iter().map(|object| object.size).sum();
        let relative = relative.trim_matches('/');
        self.concurrently(objects.iter().map(|object| {
            let name = format!("{relative}/{}", object.name);
            let path = self.path(&name);
            async move {
                match self.store.delete(&path).await {
                    Ok(()) | Err(object_store::Error::NotFound { .. }) => Ok(0),
                    Err(error) => Err(anyhow::Error::new(error)
                        .context(format!("cannot delete {}", self.describe(&name)))),
                }
            }
        }))?;
        Ok(bytes)
    }

    /// Runs `transfers` ([`TRANSFER_CONCURRENCY`] at a time) until one fails; returns the sum
    /// of the byte counts they return.
    fn concurrently(
        &self,
        transfers: impl Iterator<Item = impl Future<Output = anyhow::Result<u64>>>,
    ) -> anyhow::Result<u64> {
        let sizes = self.runtime.block_on(
            futures_util::stream::iter(transfers)
                .buffer_unordered(TRANSFER_CONCURRENCY)
                .try_collect::<Vec<u64>>(),
        )?;
        Ok(sizes.iter().sum())
    }

    /// Uploads the files `names` (relative paths with `/`) of the local folder `source` to
    /// folder `relative`; returns the bytes sent.
    pub fn upload_files(
        &self,
        source: &Path,
        names: &[String],
        relative: &str,
    ) -> anyhow::Result<u64> {
        let relative = relative.trim_matches('/');
        self.concurrently(names.iter().map(|name| {
            let file = source.join(name);
            let target = format!("{relative}/{name}");
            async move {
                let bytes = crate::files::read_regular_file(&file)?;
                let size = bytes.len() as u64;
                let path = self.path(&target);
                self.store
                    .put(&path, PutPayload::from(bytes))
                    .await
                    .with_context(|| format!("cannot upload {}", self.describe(&target)))?;
                Ok::<u64, anyhow::Error>(size)
            }
        }))
    }

    /// Downloads the objects `names` of folder `relative` into the local folder `target`
    /// (creating sub-folders); returns the bytes received.
    pub fn download_files(
        &self,
        relative: &str,
        names: &[String],
        target: &Path,
    ) -> anyhow::Result<u64> {
        let relative = relative.trim_matches('/');
        self.concurrently(names.iter().map(|name| {
            let file = target.join(name);
            let source = format!("{relative}/{name}");
            async move {
                let path = self.path(&source);
                let bytes = async { self.store.get(&path).await?.bytes().await }
                    .await
                    .with_context(|| format!("cannot download {}", self.describe(&source)))?;
                if let Some(parent) = file.parent() {
                    std::fs::create_dir_all(parent)
                        .with_context(|| format!("cannot create {}", parent.display()))?;
                }
                std::fs::write(&file, &bytes)
                    .with_context(|| format!("cannot write {}", file.display()))?;
                Ok::<u64, anyhow::Error>(bytes.len() as u64)
            }
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_parse_with_and_without_prefix() {
        assert_eq!(
            S3Url::parse("s3://cache-bucket/team/avatars/").unwrap(),
            S3Url {
                bucket: "cache-bucket".into(),
                prefix: "team/avatars".into()
            }
        );
        let bare = S3Url::parse("s3://b1").unwrap();
        assert_eq!(bare.prefix, "");
        assert_eq!(bare.to_string(), "s3://b1");
        assert_eq!(
            S3Url::parse("s3://b1//a//b").unwrap().to_string(),
            "s3://b1/a/b"
        );
        for bad in ["b1/x", "s3://", "s3://Upper/x", "s3://b/../x", "s3://b/./x"] {
            assert!(S3Url::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn seconds_must_be_positive_and_finite() {
        assert_eq!(
            parse_seconds("X", " 2.5 ").unwrap(),
            Duration::from_millis(2500)
        );
        assert_eq!(
            env_seconds("SEQAVATAR_TEST_UNSET_VARIABLE_XYZ", 60.0).unwrap(),
            Duration::from_secs(60)
        );
        for bad in ["0", "-1", "nan", "inf", "1e300", "soon", ""] {
            let error = parse_seconds("SEQAVATAR_LEASE_TIMEOUT_S", bad).unwrap_err();
            assert!(
                error.to_string().contains("SEQAVATAR_LEASE_TIMEOUT_S"),
                "{error}"
            );
        }
    }
}
