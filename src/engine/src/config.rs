//! Stage configuration: typed resolution of raw config values and the error that names the
//! offending key.

use std::fmt;

/// One step of a path into a config value.
#[derive(Debug, Clone, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum ConfigPathSegment {
    Key(String),
    Index(usize),
}

/// A config value that a stage kind rejected; `path` names the key (empty: the whole config).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub struct ConfigError {
    pub path: Vec<ConfigPathSegment>,
    pub message: String,
}

impl ConfigError {
    /// An error about the key at `path`.
    pub fn new(path: Vec<ConfigPathSegment>, message: impl Into<String>) -> Self {
        Self {
            path,
            message: message.into(),
        }
    }

    /// An error about the top-level key `key`.
    pub fn at_key(key: &str, message: impl Into<String>) -> Self {
        Self::new(vec![ConfigPathSegment::Key(key.to_string())], message)
    }

    /// The dotted path, e.g. `cameras[2].name`; empty for the whole config.
    pub fn path_string(&self) -> String {
        path_to_string(&self.path)
    }
}

/// Formats a config path as `a.b[2].c`.
pub fn path_to_string(path: &[ConfigPathSegment]) -> String {
    let mut text = String::new();
    for segment in path {
        match segment {
            ConfigPathSegment::Key(key) => {
                if !text.is_empty() {
                    text.push('.');
                }
                text.push_str(key);
            }
            ConfigPathSegment::Index(index) => text.push_str(&format!("[{index}]")),
        }
    }
    text
}

impl fmt::Display for ConfigError {
    fn fmt(&self, formatter: &mut fmt::Formatter<'_>) -> fmt::Result {
        if self.path.is_empty() {
            write!(formatter, "config: {}", self.message)
        } else {
            write!(
                formatter,
                "config key \"{}\": {}",
                self.path_string(),
                self.message
            )
        }
    }
}

/// Deserializes `raw` into `T` (normally `#[serde(deny_unknown_fields, default)]`; a null
/// config is an empty mapping). The engine re-serializes the stage's resolved config, so the
/// effective config has every default explicit and a canonical form.
///
/// An unknown field is reported at the path of the unknown key itself, so the engine can
/// point at its line.
pub fn parse_config<T: serde::de::DeserializeOwned>(
    raw: &serde_json::Value,
) -> Result<T, ConfigError> {
    let empty = serde_json::Value::Object(serde_json::Map::new());
    let raw = if raw.is_null() { &empty } else { raw };
    serde_path_to_error::deserialize(raw).map_err(|error| {
        let mut path: Vec<ConfigPathSegment> = error
            .path()
            .iter()
            .filter_map(|segment| match segment {
                serde_path_to_error::Segment::Map { key } => {
                    Some(ConfigPathSegment::Key(key.clone()))
                }
                serde_path_to_error::Segment::Seq { index } => {
                    Some(ConfigPathSegment::Index(*index))
                }
                serde_path_to_error::Segment::Enum { .. }
                | serde_path_to_error::Segment::Unknown => None,
            })
            .collect();
        let message = error.inner().to_string();
        if let Some(unknown) = unknown_field_name(&message)
            && path.last() != Some(&ConfigPathSegment::Key(unknown.clone()))
        {
            path.push(ConfigPathSegment::Key(unknown));
        }
        ConfigError::new(path, message)
    })
}

/// The field name in serde's "unknown field `x`, expected ..." message.
fn unknown_field_name(message: &str) -> Option<String> {
    let rest = message.strip_prefix("unknown field `")?;
    let end = rest.find('`')?;
    Some(rest[..end].to_string())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(serde::Deserialize, serde::Serialize, Default)]
    #[serde(deny_unknown_fields, default)]
    struct Inner {
        name: String,
    }

    #[derive(serde::Deserialize, serde::Serialize)]
    #[serde(deny_unknown_fields, default)]
    struct Example {
        iterations: u32,
        rate: f64,
        cameras: Vec<Inner>,
    }

    impl Default for Example {
        fn default() -> Self {
            Self {
                iterations: 10,
                rate: 0.5,
                cameras: vec![],
            }
        }
    }

    fn resolve_typed<T: serde::de::DeserializeOwned + serde::Serialize>(
        raw: &serde_json::Value,
    ) -> Result<serde_json::Value, ConfigError> {
        parse_config::<T>(raw).map(|typed| serde_json::to_value(typed).unwrap())
    }

    #[test]
    fn defaults_become_explicit() {
        let resolved = resolve_typed::<Example>(&serde_json::json!({"rate": 1})).unwrap();
        assert_eq!(
            resolved,
            serde_json::json!({"iterations": 10, "rate": 1.0, "cameras": []})
        );
        let from_null = resolve_typed::<Example>(&serde_json::Value::Null).unwrap();
        assert_eq!(from_null["iterations"], 10);
    }

    #[test]
    fn unknown_field_names_the_key() {
        let error = resolve_typed::<Example>(&serde_json::json!({"iteratons": 3})).unwrap_err();
        assert_eq!(error.path_string(), "iteratons");
        assert!(error.message.contains("expected one of"), "{error}");
        let nested = resolve_typed::<Example>(&serde_json::json!({"cameras": [{}, {"nam": 1}]}))
            .unwrap_err();
        assert_eq!(nested.path_string(), "cameras[1].nam");
    }

    #[test]
    fn wrong_type_names_the_key() {
        let error =
            resolve_typed::<Example>(&serde_json::json!({"iterations": "many"})).unwrap_err();
        assert_eq!(error.path_string(), "iterations");
        assert!(
            error
                .to_string()
                .starts_with("config key \"iterations\": invalid type")
        );
    }
}

/// Environment variable overriding [`memory_budget_bytes`] (bytes, or with a `K`, `M` or `G`
/// suffix for KiB, MiB, GiB).
pub const MEMORY_BUDGET_VAR: &str = "SEQAVATAR_MEMORY_BUDGET";

/// The share of the machine's memory a stage may plan to use by default: three quarters.
pub const DEFAULT_MEMORY_FRACTION: f64 = 0.75;

/// The memory a stage's configuration may be estimated to need: [`MEMORY_BUDGET_VAR`] when
/// set, else [`DEFAULT_MEMORY_FRACTION`] of the least of [`machine_memory_bytes`] and the
/// process's own limits ([`process_memory_limit_bytes`]: `RLIMIT_AS`, `RLIMIT_DATA`, the
/// cgroup's memory limit); `None` where none is known (no check). A value that is not a size
/// is an error naming the variable.
pub fn memory_budget_bytes() -> Result<Option<u64>, String> {
    if let Some(value) = std::env::var_os(MEMORY_BUDGET_VAR) {
        let value = value.to_string_lossy();
        return parse_size(&value).map(Some).ok_or_else(|| {
            format!("{MEMORY_BUDGET_VAR}={value:?} is not a size in bytes (examples: 8G, 512M)")
        });
    }
    let least = [machine_memory_bytes(), process_memory_limit_bytes()]
        .into_iter()
        .flatten()
        .min();
    Ok(least.map(|bytes| (bytes as f64 * DEFAULT_MEMORY_FRACTION) as u64))
}

/// Refuses what is estimated to need `estimate` bytes when that exceeds `budget` (from
/// [`memory_budget_bytes`]; `None`: no check), before it is allocated. The message names
/// `what` (the field or option and the sizes that make it large), the estimate, the budget
/// and `remedy`.
pub fn check_memory_budget(
    what: &str,
    estimate: u64,
    budget: Option<u64>,
    remedy: &str,
) -> Result<(), String> {
    let bytes = |n: u64| match n {
        n if n >= 1_000_000_000 => format!("{:.1} GB", n as f64 / 1e9),
        n => format!("{:.1} MB", n as f64 / 1e6),
    };
    match budget {
        Some(budget) if estimate > budget => Err(format!(
            "{what} need about {}, over the memory budget of {}; {remedy} (or set \
             {MEMORY_BUDGET_VAR})",
            bytes(estimate),
            bytes(budget)
        )),
        _ => Ok(()),
    }
}

/// Limits at or above this many bytes mean "no limit" (cgroup v1 writes `2^63 - 4096`).
const NO_LIMIT_BYTES: u64 = 1 << 60;

/// The least memory limit set on this process: its `RLIMIT_AS` and `RLIMIT_DATA` soft limits
/// and its cgroup's (v2 `memory.max`, v1 `memory.limit_in_bytes`); `None` where none is set.
pub fn process_memory_limit_bytes() -> Option<u64> {
    let cgroup = std::fs::read_to_string("/proc/self/cgroup")
        .ok()
        .and_then(|text| cgroup_memory_limit(&text, |path| std::fs::read_to_string(path).ok()));
    [
        rlimit_bytes(libc::RLIMIT_AS),
        rlimit_bytes(libc::RLIMIT_DATA),
        cgroup,
    ]
    .into_iter()
    .flatten()
    .filter(|&bytes| bytes < NO_LIMIT_BYTES)
    .min()
}

/// The soft limit of `resource`, `None` when unlimited or unknown.
fn rlimit_bytes(resource: libc::__rlimit_resource_t) -> Option<u64> {
    let mut limit = libc::rlimit {
        rlim_cur: 0,
        rlim_max: 0,
    };
    // SAFETY: `getrlimit` writes one `rlimit` through a pointer to a live, aligned value.
    let status = unsafe { libc::getrlimit(resource, &mut limit) };
    (status == 0 && limit.rlim_cur != libc::RLIM_INFINITY).then_some(limit.rlim_cur)
}

/// The memory limit of the cgroup named in `/proc/self/cgroup` (`proc_cgroup`): v2
/// (`0::<path>`, file `memory.max`, `max` = none) or v1 (the `memory` controller's path,
/// file `memory.limit_in_bytes`), read with `read` at the group's path and, inside a
/// container whose namespace hides the path, at the mount's root.
fn cgroup_memory_limit(proc_cgroup: &str, read: impl Fn(&str) -> Option<String>) -> Option<u64> {
    let parse = |text: String| -> Option<u64> {
        let text = text.trim();
        if text == "max" {
            return None;
        }
        text.parse::<u64>()
            .ok()
            .filter(|&bytes| bytes < NO_LIMIT_BYTES)
    };
    let mut limits = Vec::new();
    for line in proc_cgroup.lines() {
        let mut fields = line.splitn(3, ':');
        let (Some(_), Some(controllers), Some(path)) =
            (fields.next(), fields.next(), fields.next())
        else {
            continue;
        };
        let path = path.trim_end_matches('/');
        let (root, file) = if controllers.is_empty() {
            ("/sys/fs/cgroup", "memory.max")
        } else if controllers.split(',').any(|c| c == "memory") {
            ("/sys/fs/cgroup/memory", "memory.limit_in_bytes")
        } else {
            continue;
        };
        let limit = read(&format!("{root}{path}/{file}"))
            .or_else(|| read(&format!("{root}/{file}")))
            .and_then(parse);
        limits.extend(limit);
    }
    limits.into_iter().min()
}

/// `123`, `800K`, `800M`, `2G` (binary multiples) as bytes; `None` for anything else or 0.
pub fn parse_size(text: &str) -> Option<u64> {
    let text = text.trim();
    let (digits, shift) = match text.char_indices().last()? {
        (at, 'k' | 'K') => (&text[..at], 10),
        (at, 'm' | 'M') => (&text[..at], 20),
        (at, 'g' | 'G') => (&text[..at], 30),
        _ => (text, 0),
    };
    let n: u64 = digits.trim().parse().ok()?;
    n.checked_mul(1u64 << shift).filter(|&bytes| bytes > 0)
}

/// The machine's physical memory in bytes (`MemTotal` of `/proc/meminfo`), for the
/// memory estimates that stage configs check when the pipeline loads; `None` where the
/// system does not say (the estimate is then not checked).
pub fn machine_memory_bytes() -> Option<u64> {
    let text = std::fs::read_to_string("/proc/meminfo").ok()?;
    parse_mem_total(&text)
}

fn parse_mem_total(meminfo: &str) -> Option<u64> {
    let line = meminfo.lines().find(|l| l.starts_with("MemTotal:"))?;
    let mut words = line["MemTotal:".len()..].split_whitespace();
    let value: u64 = words.next()?.parse().ok()?;
    match words.next() {
        Some("kB") => value.checked_mul(1024),
        None => Some(value),
        Some(_) => None,
    }
}

#[cfg(test)]
mod memory_tests {
    use super::*;

    #[test]
    fn mem_total_parses() {
        let text = "MemTotal:       16303940 kB\nMemFree:         1234 kB\n";
        assert_eq!(parse_mem_total(text), Some(16_303_940 * 1024));
        assert_eq!(parse_mem_total("MemFree: 1 kB\n"), None);
        assert_eq!(parse_mem_total("MemTotal: x kB\n"), None);
        if cfg!(target_os = "linux") {
            assert!(machine_memory_bytes().is_some_and(|bytes| bytes > 1 << 26));
        }
    }

    /// The cgroup limit is read where `/proc/self/cgroup` points, v2 and v1, falling back to
    /// the mount's root inside a container; "max" and v1's huge sentinel mean no limit.
    #[test]
    fn cgroup_limits_parse() {
        let files = |entries: &'static [(&'static str, &'static str)]| {
            move |path: &str| {
                entries
                    .iter()
                    .find(|(name, _)| *name == path)
                    .map(|(_, text)| (*text).to_owned())
            }
        };
        let v2 = "0::/user.slice/job\n";
        let job = files(&[("/sys/fs/cgroup/user.slice/job/memory.max", "6000000000\n")]);
        assert_eq!(cgroup_memory_limit(v2, job), Some(6_000_000_000));
        let unlimited = files(&[("/sys/fs/cgroup/user.slice/job/memory.max", "max\n")]);
        assert_eq!(cgroup_memory_limit(v2, unlimited), None);
        let v1 = "9:pids:/\n4:memory:/process_api/abc\n0::/\n";
        let hidden = files(&[("/sys/fs/cgroup/memory/memory.limit_in_bytes", "4294967296")]);
        assert_eq!(cgroup_memory_limit(v1, hidden), Some(4 << 30));
        let sentinel = files(&[(
            "/sys/fs/cgroup/memory/memory.limit_in_bytes",
            "9223372036854771712",
        )]);
        assert_eq!(cgroup_memory_limit(v1, sentinel), None);
        assert_eq!(cgroup_memory_limit("garbage", files(&[])), None);
    }

    /// A process started under `RLIMIT_AS` plans within three quarters of it.
    #[test]
    fn the_address_space_limit_bounds_the_budget() {
        if std::env::var_os("SEQAVATAR_RLIMIT_CHILD").is_some() {
            let budget = memory_budget_bytes().unwrap().unwrap();
            assert!(budget <= 3 << 30, "{budget}");
            return;
        }
        let exe = std::env::current_exe().unwrap();
        let mut child = std::process::Command::new(exe);
        child
            .args([
                "--exact",
                "config::memory_tests::the_address_space_limit_bounds_the_budget",
            ])
            .env("SEQAVATAR_RLIMIT_CHILD", "1")
            .env_remove(MEMORY_BUDGET_VAR);
        // SAFETY: the closure runs in the forked child before exec and only calls
        // `setrlimit`, which is async-signal-safe.
        unsafe {
            std::os::unix::process::CommandExt::pre_exec(&mut child, || {
                let limit = libc::rlimit {
                    rlim_cur: 4 << 30,
                    rlim_max: libc::RLIM_INFINITY,
                };
                if libc::setrlimit(libc::RLIMIT_AS, &limit) != 0 {
                    return Err(std::io::Error::last_os_error());
                }
                Ok(())
            });
        }
        let status = child.status().unwrap();
        assert!(
            status.success(),
            "the child under RLIMIT_AS = 4 GiB: {status}"
        );
    }
}
