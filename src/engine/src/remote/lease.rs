//! Leases: the exclusive right, across machines, to compute one key. A lease is an object
//! created with a conditional put (`If-None-Match: *`); its holder renews it from a heartbeat
//! thread with conditional updates (`If-Match: ETag`), each changing its content. A waiter that
//! sees the same ETag for longer than the lease timeout (measured on its own monotonic clock,
//! so clocks of different machines never matter) takes the lease over with a conditional update
//! on that ETag; of several waiters exactly one succeeds.

use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use super::bucket::{Bucket, env_seconds};

/// Lease timing, from `SEQAVATAR_LEASE_TIMEOUT_S` (default 60 s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct LeaseSettings {
    /// A lease not renewed for this long is taken over.
    pub timeout: Duration,
    /// Interval between renewals (a quarter of the timeout).
    pub heartbeat: Duration,
    /// Interval between looks at a lease held by someone else.
    pub poll: Duration,
}

impl LeaseSettings {
    pub fn from_timeout(timeout: Duration) -> Self {
        Self {
            timeout,
            heartbeat: timeout / 4,
            poll: (timeout / 8).clamp(Duration::from_millis(50), Duration::from_secs(2)),
        }
    }

    pub fn from_env() -> anyhow::Result<Self> {
        Ok(Self::from_timeout(env_seconds(
            "SEQAVATAR_LEASE_TIMEOUT_S",
            60.0,
        )?))
    }
}

/// A name unique to this process and moment: host, process id, nanoseconds.
pub(crate) fn unique_name() -> String {
    let host = std::env::var("HOSTNAME")
        .ok()
        .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
        .map(|name| {
            name.trim()
                .chars()
                .filter(|c| c.is_ascii_alphanumeric() || *c == '-')
                .take(40)
                .collect::<String>()
        })
        .filter(|name| !name.is_empty())
        .unwrap_or_else(|| "host".to_string());
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default()
        .as_nanos();
    format!("{host}-{}-{nanos}", std::process::id())
}

fn lease_body(holder: &str, beat: u64, settings: &LeaseSettings) -> Vec<u8> {
    serde_json::json!({
        "holder": holder,
        "beat": beat,
        "timeout_s": settings.timeout.as_secs_f64(),
        "renewed_at": crate::timefmt::rfc3339(std::time::SystemTime::now()),
    })
    .to_string()
    .into_bytes()
}

/// How a lease was obtained.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) enum Acquired {
    /// Nobody held it.
    Fresh,
    /// Taken over from a holder that stopped renewing (its name).
    TakenOver(String),
}

struct Shared {
    bucket: Arc<Bucket>,
    object: String,
    holder: String,
    settings: LeaseSettings,
    state: Mutex<State>,
    wake: Condvar,
}

struct State {
    etag: String,
    beat: u64,
    stopping: bool,
    /// Why the lease may no longer be ours (renewal refused or failing past the timeout).
    lost: Option<String>,
}

/// A held lease; renewed by a heartbeat thread until dropped, then deleted.
pub(crate) struct Lease {
    shared: Arc<Shared>,
    heartbeat: Option<JoinHandle<()>>,
    acquired: Acquired,
}

impl Lease {
    /// Takes the lease object `object`. Waits (calling `on_wait` once) while someone else
    /// renews it when `wait`, else returns `None` when it is held.
    pub fn acquire(
        bucket: &Arc<Bucket>,
        object: &str,
        settings: LeaseSettings,
        wait: bool,
        on_wait: &mut dyn FnMut(),
    ) -> anyhow::Result<Option<Lease>> {
        let holder = unique_name();
        let mut observed: Option<(String, Instant)> = None;
        let mut waiting = false;
        loop {
            if let Some(etag) = bucket.put_create(object, lease_body(&holder, 0, &settings))? {
                return Ok(Some(Self::start(
                    bucket,
                    object,
                    holder,
                    etag,
                    settings,
                    Acquired::Fresh,
                )));
            }
            let Some((body, etag)) = bucket.get(object)? else {
                continue; // Released between our two requests: try again at once.
            };
            let etag = etag.unwrap_or_default();
            match &observed {
                Some((seen, since)) if *seen == etag => {
                    if since.elapsed() >= settings.timeout && !etag.is_empty() {
                        let previous = serde_json::from_slice::<serde_json::Value>(&body)
                            .ok()
                            .and_then(|value| value["holder"].as_str().map(str::to_string))
                            .unwrap_or_else(|| "an unknown holder".to_string());
                        if let Some(new_etag) =
                            bucket.put_update(object, lease_body(&holder, 0, &settings), &etag)?
                        {
                            return Ok(Some(Self::start(
                                bucket,
                                object,
                                holder,
                                new_etag,
                                settings,
                                Acquired::TakenOver(previous),
                            )));
                        }
                        observed = None; // Someone else took it over first.
                    }
                }
                _ => observed = Some((etag, Instant::now())),
            }
            if !wait {
                return Ok(None);
            }
            if !waiting {
                on_wait();
                waiting = true;
            }
            std::thread::sleep(settings.poll);
        }
    }

    fn start(
        bucket: &Arc<Bucket>,
        object: &str,
        holder: String,
        etag: String,
        settings: LeaseSettings,
        acquired: Acquired,
    ) -> Self {
        let shared = Arc::new(Shared {
            bucket: bucket.clone(),
            object: object.to_string(),
            holder,
            settings,
            state: Mutex::new(State {
                etag,
                beat: 0,
                stopping: false,
                lost: None,
            }),
            wake: Condvar::new(),
        });
        let thread_shared = shared.clone();
        let heartbeat = std::thread::Builder::new()
            .name("seqavatar-lease".to_string())
            .spawn(move || heartbeat_loop(&thread_shared))
            .ok();
        Self {
            shared,
            heartbeat,
            acquired,
        }
    }

    pub fn acquired(&self) -> &Acquired {
        &self.acquired
    }

    /// Why the lease may have been lost, if it may have.
    pub fn lost(&self) -> Option<String> {
        self.shared
            .state
            .lock()
            .expect("lease poisoned")
            .lost
            .clone()
    }
}

/// Renews the lease every heartbeat interval until stopped or lost.
fn heartbeat_loop(shared: &Shared) {
    let mut last_renewal = Instant::now();
    let mut state = shared.state.lock().expect("lease poisoned");
    loop {
        let (guard, _) = shared
            .wake
            .wait_timeout(state, shared.settings.heartbeat)
            .expect("lease poisoned");
        state = guard;
        if state.stopping || state.lost.is_some() {
            return;
        }
        let beat = state.beat + 1;
        let etag = state.etag.clone();
        drop(state);
        let body = lease_body(&shared.holder, beat, &shared.settings);
        let outcome = shared.bucket.put_update(&shared.object, body, &etag);
        state = shared.state.lock().expect("lease poisoned");
        match outcome {
            Ok(Some(new_etag)) => {
                state.etag = new_etag;
                state.beat = beat;
                last_renewal = Instant::now();
            }
            Ok(None) => {
                state.lost = Some(format!(
                    "{} was taken over by another worker",
                    shared.bucket.describe(&shared.object)
                ));
            }
            Err(error) if last_renewal.elapsed() >= shared.settings.timeout => {
                state.lost = Some(format!(
                    "{} could not be renewed for {:.1} s: {error:#}",
                    shared.bucket.describe(&shared.object),
                    last_renewal.elapsed().as_secs_f64()
                ));
            }
            Err(_) => {} // Transient; the next beat retries.
        }
    }
}

impl Drop for Lease {
    fn drop(&mut self) {
        let lost = {
            let mut state = self.shared.state.lock().expect("lease poisoned");
            state.stopping = true;
            state.lost.is_some()
        };
        self.shared.wake.notify_all();
        if let Some(handle) = self.heartbeat.take() {
            let _ = handle.join();
        }
        if !lost {
            // Failing to delete only delays the next holder by the lease timeout.
            let _ = self.shared.bucket.delete(&self.shared.object);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn timing_follows_the_timeout() {
        let settings = LeaseSettings::from_timeout(Duration::from_secs(60));
        assert_eq!(settings.heartbeat, Duration::from_secs(15));
        assert_eq!(settings.poll, Duration::from_secs(2));
        let short = LeaseSettings::from_timeout(Duration::from_millis(200));
        assert_eq!(short.heartbeat, Duration::from_millis(50));
        assert_eq!(short.poll, Duration::from_millis(50));
    }

    #[test]
    fn unique_names_differ() {
        let first = unique_name();
        std::thread::sleep(Duration::from_millis(1));
        assert_ne!(first, unique_name());
        assert!(first.chars().all(|c| c.is_ascii_alphanumeric() || c == '-'));
    }
}
