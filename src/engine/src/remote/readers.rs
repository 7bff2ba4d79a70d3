//! Read leases visible to every machine sharing the bucket: each reader of an entry keeps a
//! lease object of its own, `.readers/<kind>/<key>/<reader>`, and `gc` deleting the entry
//! keeps `.readers/<kind>/<key>/.gc`. Both are [`Lease`]s: created with a conditional put,
//! renewed by the heartbeat of the write leases (every quarter of the lease timeout), deleted
//! when dropped.
//!
//! The protocol (S3 is strongly consistent, listings included):
//! - a reader creates its object, then lists the folder; if a live `.gc` is there it deletes
//!   its object and waits, else it reads (the caller then checks the entry still exists);
//! - `gc` creates `.gc`, then lists the folder; if a live reader is there it deletes `.gc`
//!   and skips the entry, else it deletes the entry while holding `.gc`.
//!
//! Whichever of the two objects is created second, its owner's listing sees the other, so a
//! reader and a deletion never overlap. An object not renewed for longer than the lease
//! timeout belongs to a killed process: it is expired, ignored, and deleted by `gc`. Ages
//! are differences of the server's own timestamps (the lister's fresh object against the
//! others), so the machines' clocks never matter.

use std::sync::Arc;
use std::time::{Duration, SystemTime};

use super::bucket::{Bucket, ObjectInfo};
use super::lease::{Lease, LeaseSettings, unique_name};
use crate::entry::ReadLease;
use crate::store::EntryId;

/// Remote folder of read leases.
pub(crate) const READERS_DIR: &str = ".readers";
/// The name of `gc`'s lease object in an entry's readers folder (reader names never start
/// with a dot).
const GC_OBJECT: &str = ".gc";
/// The resolution of S3's `Last-Modified` (whole seconds), added to the timeout before an
/// object counts as expired.
const TIMESTAMP_RESOLUTION: Duration = Duration::from_secs(1);

/// The readers folder of an entry.
pub(crate) fn readers_folder(id: &EntryId) -> String {
    format!("{READERS_DIR}/{}/{}", id.kind, id.key)
}

/// A read lease of the remote store: the remote lease object (a reader's or `gc`'s) and the
/// local front's read lease, released together on drop.
struct RemoteReadLease {
    // Field order is drop order: the remote object goes first.
    _remote: Lease,
    _local: Box<dyn ReadLease>,
}

impl ReadLease for RemoteReadLease {}

/// The lease objects of one entry's readers folder as seen by the holder of `own`.
#[derive(Debug, Default, PartialEq, Eq)]
pub(crate) struct Holders {
    /// Readers renewed within the timeout (other than `own`).
    pub live_readers: Vec<String>,
    /// Objects (readers or `.gc`) not renewed for longer than the timeout.
    pub expired: Vec<String>,
    /// Whether a `gc` (other than `own`) holds a live `.gc` object.
    pub gc_live: bool,
}

/// Whether an object last written at `modified` has expired at `now` (both the server's
/// clock): not renewed for longer than `timeout` plus the timestamps' resolution.
pub(crate) fn is_expired(modified: SystemTime, now: SystemTime, timeout: Duration) -> bool {
    now.duration_since(modified)
        .is_ok_and(|age| age > timeout + TIMESTAMP_RESOLUTION)
}

/// Sorts the listing `objects` of a readers folder, in which `own` was just written: its
/// timestamp is the server's "now" the others' ages are measured against.
pub(crate) fn classify(
    objects: &[ObjectInfo],
    own: &str,
    timeout: Duration,
) -> anyhow::Result<Holders> {
    let now = objects
        .iter()
        .find(|object| object.name == own)
        .map(|object| object.modified)
        .ok_or_else(|| anyhow::anyhow!("the lease object {own} just written is not listed"))?;
    let mut holders = Holders::default();
    for object in objects.iter().filter(|object| object.name != own) {
        if is_expired(object.modified, now, timeout) {
            holders.expired.push(object.name.clone());
        } else if object.name == GC_OBJECT {
            holders.gc_live = true;
        } else {
            holders.live_readers.push(object.name.clone());
        }
    }
    Ok(holders)
}

/// Takes a shared read lease on `id`: the local front's, then a reader object in the bucket,
/// waiting while a live `gc` deletes the entry (printing once that it waits).
pub(crate) fn read_lease(
    bucket: &Arc<Bucket>,
    settings: LeaseSettings,
    id: &EntryId,
    local: Box<dyn ReadLease>,
) -> anyhow::Result<Box<dyn ReadLease>> {
    let folder = readers_folder(id);
    let mut waiting = false;
    loop {
        let name = unique_name();
        let object = format!("{folder}/{name}");
        let lease = Lease::acquire(bucket, &object, settings, false, &mut || {})?
            .ok_or_else(|| anyhow::anyhow!("{} exists already", bucket.describe(&object)))?;
        let (_, objects) = bucket.list_folder(&folder)?;
        let holders = classify(&objects, &name, settings.timeout)?;
        if !holders.gc_live {
            return Ok(Box::new(RemoteReadLease {
                _remote: lease,
                _local: local,
            }));
        }
        drop(lease);
        if !waiting {
            eprintln!("waiting: gc on another machine is deleting {id}");
            waiting = true;
        }
        std::thread::sleep(settings.poll);
    }
}

/// Takes the read lease of `id` exclusively for `gc`: `None` while a reader on any machine
/// holds an unexpired lease object (or another `gc` deletes the entry). Expired reader
/// objects are deleted.
pub(crate) fn try_exclusive_read_lease(
    bucket: &Arc<Bucket>,
    settings: LeaseSettings,
    id: &EntryId,
    local: Box<dyn ReadLease>,
) -> anyhow::Result<Option<Box<dyn ReadLease>>> {
    let folder = readers_folder(id);
    let object = format!("{folder}/{GC_OBJECT}");
    let mut lease = Lease::acquire(bucket, &object, settings, false, &mut || {})?;
    if lease.is_none() {
        // Another gc's object: live (it is deleting the entry), or left by a killed gc.
        // A fresh object of our own gives the server's "now" to measure its age against.
        let probe = unique_name();
        let probe_object = format!("{folder}/{probe}");
        bucket.put_create(&probe_object, Vec::new())?;
        let listed = bucket.list_folder(&folder);
        bucket.delete(&probe_object)?;
        let (_, objects) = listed?;
        let holders = classify(&objects, &probe, settings.timeout)?;
        if !holders.expired.iter().any(|name| name == GC_OBJECT) {
            return Ok(None);
        }
        bucket.delete(&object)?;
        lease = Lease::acquire(bucket, &object, settings, false, &mut || {})?;
    }
    let Some(lease) = lease else {
        return Ok(None); // Another gc took it first.
    };
    let (_, objects) = bucket.list_folder(&folder)?;
    let holders = classify(&objects, GC_OBJECT, settings.timeout)?;
    for name in &holders.expired {
        bucket.delete(&format!("{folder}/{name}"))?;
    }
    if !holders.live_readers.is_empty() {
        return Ok(None); // Dropping the lease deletes `.gc`.
    }
    Ok(Some(Box::new(RemoteReadLease {
        _remote: lease,
        _local: local,
    })))
}

/// Deletes the expired lease objects of every entry's readers folder (those of killed
/// readers of entries `gc` never visits: unpublished keys a killed run was computing);
/// returns their names. Ages are measured against a fresh probe object's timestamp.
pub(crate) fn remove_expired(
    bucket: &Arc<Bucket>,
    settings: LeaseSettings,
) -> anyhow::Result<Vec<String>> {
    let probe = format!(".probe-{}", unique_name());
    let probe_object = format!("{READERS_DIR}/{probe}");
    bucket.put_create(&probe_object, Vec::new())?;
    let listed = bucket.list_tree(READERS_DIR);
    bucket.delete(&probe_object)?;
    let objects = listed?;
    let holders = classify(&objects, &probe, settings.timeout)?;
    let mut removed = Vec::new();
    for name in holders.expired {
        // Only `<kind>/<key>/<object>`: anything else is not ours to judge.
        if name.split('/').count() == 3 {
            bucket.delete(&format!("{READERS_DIR}/{name}"))?;
            removed.push(format!("{READERS_DIR}/{name}"));
        }
    }
    Ok(removed)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn object(name: &str, seconds: u64) -> ObjectInfo {
        ObjectInfo {
            name: name.to_string(),
            size: 0,
            modified: SystemTime::UNIX_EPOCH + Duration::from_secs(1_000_000 + seconds),
        }
    }

    #[test]
    fn ages_are_measured_against_the_listers_own_object() {
        let timeout = Duration::from_secs(10);
        // gc's object written at t = 100: a reader renewed at 95 is live, one last renewed
        // at 80 (20 s ago, over 10 s + 1 s) is expired, one at 89 (11 s) is still live.
        let listing = [
            object(GC_OBJECT, 100),
            object("m1-7-1", 95),
            object("m2-8-2", 80),
            object("m3-9-3", 89),
        ];
        let holders = classify(&listing, GC_OBJECT, timeout).unwrap();
        assert_eq!(
            holders,
            Holders {
                live_readers: vec!["m1-7-1".into(), "m3-9-3".into()],
                expired: vec!["m2-8-2".into()],
                gc_live: false,
            }
        );
        // A reader sees a live gc, or an expired one it may ignore.
        let reader = classify(&listing, "m1-7-1", timeout).unwrap();
        assert!(reader.gc_live);
        let late = [object(GC_OBJECT, 100), object("m4-1-1", 112)];
        let reader = classify(&late, "m4-1-1", timeout).unwrap();
        assert!(!reader.gc_live);
        assert_eq!(reader.expired, [GC_OBJECT]);
        // Clock skew between server timestamps and the lister never matters; a timestamp
        // after the lister's own (written meanwhile) is live.
        let ahead = [object(GC_OBJECT, 100), object("m5-1-1", 130)];
        assert_eq!(
            classify(&ahead, GC_OBJECT, timeout).unwrap().live_readers,
            ["m5-1-1"]
        );
        // The lister's own object must be listed.
        assert!(classify(&ahead, "absent", timeout).is_err());
    }

    #[test]
    fn expiry_allows_for_whole_second_timestamps() {
        let t = SystemTime::UNIX_EPOCH + Duration::from_secs(1_000);
        let timeout = Duration::from_secs(2);
        assert!(!is_expired(t, t + Duration::from_secs(3), timeout));
        assert!(is_expired(t, t + Duration::from_millis(3_001), timeout));
        assert!(!is_expired(t + Duration::from_secs(5), t, timeout));
    }

    #[test]
    fn readers_folders_follow_the_layout() {
        let id = EntryId::new("train", "abc");
        assert_eq!(readers_folder(&id), ".readers/train/abc");
    }
}
