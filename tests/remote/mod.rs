//! Shared remote cache tests: the real `pipeline` binary against a real S3-compatible server
//! (moto, `python3 -m pip install 'moto[server]'`) on 127.0.0.1. Each test starts its own
//! server on a free port and gives every simulated machine its own local cache folder.
//!
//! Without moto the tests print `skipped: no S3 test server` and pass, except under CI (`CI`
//! set), where a missing moto is a failure: CI installs it and always runs them (the rule the
//! gpu tests follow for a Vulkan adapter).

use std::fs;
use std::io::{Read as _, Write as _};
use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};

const BUCKET: &str = "seqavatar-test";
const PREFIX: &str = "team/cache";

/// A moto S3 server on a free loopback port, stopped on drop.
struct Moto {
    child: Child,
    port: u16,
}

impl Moto {
    /// Starts a server, or `None` (after printing why) when moto is not installed and `CI`
    /// is unset (module docs).
    fn start() -> Option<Self> {
        let probe = Command::new("python3")
            .args(["-c", "import moto.server"])
            .output();
        match probe {
            Ok(output) if output.status.success() => {}
            _ if std::env::var_os("CI").is_some() => panic!(
                "CI is set but moto's S3 server is missing: python3 -m pip install 'moto[server]'"
            ),
            _ => {
                eprintln!(
                    "skipped: no S3 test server (python3 -m pip install 'moto[server]' runs these)"
                );
                return None;
            }
        }
        let port = TcpListener::bind("127.0.0.1:0")
            .and_then(|listener| listener.local_addr())
            .expect("free port")
            .port();
        let child = Command::new("python3")
            .args([
                "-m",
                "moto.server",
                "-H",
                "127.0.0.1",
                "-p",
                &port.to_string(),
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start python3 -m moto.server");
        let moto = Self { child, port };
        let started = Instant::now();
        loop {
            if let Ok((status, _)) = moto.request("PUT", &format!("/{BUCKET}"), &[])
                && status == 200
            {
                break;
            }
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "moto did not start on port {port}"
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        Some(moto)
    }

    fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// One path-style HTTP/1.1 request. moto does not check signatures, but it treats a
    /// request without credentials as anonymous (403 on objects), hence the dummy header.
    fn request(&self, method: &str, path: &str, body: &[u8]) -> std::io::Result<(u16, Vec<u8>)> {
        let mut stream = TcpStream::connect(("127.0.0.1", self.port))?;
        stream.set_read_timeout(Some(Duration::from_secs(20)))?;
        let head = format!(
            "{method} {path} HTTP/1.1\r\nHost: 127.0.0.1:{}\r\nContent-Length: {}\r\nAuthorization: AWS4-HMAC-SHA256 Credential=test/20250101/us-east-1/s3/aws4_request, SignedHeaders=host, Signature=0\r\nConnection: close\r\n\r\n",
            self.port,
            body.len()
        );
        stream.write_all(head.as_bytes())?;
        stream.write_all(body)?;
        let mut response = Vec::new();
        stream.read_to_end(&mut response)?;
        let split = response
            .windows(4)
            .position(|window| window == b"\r\n\r\n")
            .ok_or_else(|| std::io::Error::other("no HTTP header"))?;
        let header = String::from_utf8_lossy(&response[..split]).to_string();
        let status: u16 = header
            .split_whitespace()
            .nth(1)
            .and_then(|code| code.parse().ok())
            .ok_or_else(|| std::io::Error::other("no HTTP status"))?;
        let mut content = response[split + 4..].to_vec();
        if header
            .to_ascii_lowercase()
            .contains("transfer-encoding: chunked")
        {
            content = dechunk(&content);
        }
        Ok((status, content))
    }

    fn object_path(&self, key: &str) -> String {
        format!("/{BUCKET}/{PREFIX}/{key}")
    }

    fn get(&self, key: &str) -> Option<Vec<u8>> {
        let (status, body) = self
            .request("GET", &self.object_path(key), &[])
            .expect("GET");
        (status == 200).then_some(body)
    }

    fn put(&self, key: &str, body: &[u8]) {
        let (status, _) = self
            .request("PUT", &self.object_path(key), body)
            .expect("PUT");
        assert_eq!(status, 200, "PUT {key}");
    }

    fn delete(&self, key: &str) {
        let (status, _) = self
            .request("DELETE", &self.object_path(key), &[])
            .expect("DELETE");
        assert!(status == 204 || status == 200, "DELETE {key}: {status}");
    }

    /// Keys (relative to the prefix) of every object under `folder`.
    fn list(&self, folder: &str) -> Vec<String> {
        let (status, body) = self
            .request(
                "GET",
                &format!("/{BUCKET}?list-type=2&max-keys=1000&prefix={PREFIX}/{folder}"),
                &[],
            )
            .expect("LIST");
        assert_eq!(status, 200);
        let text = String::from_utf8_lossy(&body);
        text.split("<Key>")
            .skip(1)
            .filter_map(|part| part.split("</Key>").next())
            .map(|key| key.trim_start_matches(&format!("{PREFIX}/")).to_string())
            .collect()
    }

    fn signal(&self, signal: &str) {
        let status = Command::new("kill")
            .args([signal, &self.child.id().to_string()])
            .status()
            .expect("kill");
        assert!(status.success());
    }
}

fn dechunk(mut data: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    while let Some(end) = data.windows(2).position(|window| window == b"\r\n") {
        let size =
            usize::from_str_radix(String::from_utf8_lossy(&data[..end]).trim(), 16).unwrap_or(0);
        if size == 0 {
            break;
        }
        out.extend_from_slice(&data[end + 2..end + 2 + size]);
        data = &data[end + 4 + size..];
    }
    out
}

impl Drop for Moto {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-CONT", &self.child.id().to_string()])
            .status();
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A temporary folder holding pipelines, count files and one local cache per "machine".
struct Cluster {
    dir: tempfile::TempDir,
    moto: Moto,
    lease_timeout_s: f64,
    extra_env: Vec<(String, String)>,
}

impl Cluster {
    /// `None` when the test is skipped ([`Moto::start`]).
    fn new(lease_timeout_s: f64) -> Option<Self> {
        Some(Self {
            dir: tempfile::tempdir().expect("temporary folder"),
            moto: Moto::start()?,
            lease_timeout_s,
            extra_env: vec![],
        })
    }

    fn path(&self) -> &Path {
        self.dir.path()
    }

    fn write(&self, name: &str, text: &str) {
        fs::write(self.path().join(name), text).expect("write pipeline");
    }

    fn local(&self, machine: &str) -> PathBuf {
        self.path().join(format!("local-{machine}"))
    }

    fn command(&self, machine: &str, args: &[&str]) -> Command {
        let mut command = Command::new(env!("CARGO_BIN_EXE_pipeline"));
        command
            .current_dir(self.path())
            .env_remove("SEQAVATAR_CACHE")
            .env("SEQAVATAR_LOCAL_CACHE", self.local(machine))
            .env(
                "SEQAVATAR_LEASE_TIMEOUT_S",
                self.lease_timeout_s.to_string(),
            )
            .env("AWS_ENDPOINT_URL", self.moto.endpoint())
            .env("AWS_ACCESS_KEY_ID", "test")
            .env("AWS_SECRET_ACCESS_KEY", "test")
            .env("AWS_REGION", "us-east-1")
            .env("AWS_ALLOW_HTTP", "true")
            .envs(self.extra_env.iter().map(|(k, v)| (k.as_str(), v.as_str())))
            .arg("--cache")
            .arg(format!("s3://{BUCKET}/{PREFIX}"))
            .args(args);
        command
    }

    fn run(&self, machine: &str, args: &[&str]) -> Output {
        self.command(machine, args)
            .output()
            .expect("run pipeline binary")
    }

    fn ok(&self, machine: &str, args: &[&str]) -> (String, String) {
        let output = self.run(machine, args);
        let stdout = String::from_utf8_lossy(&output.stdout).into_owned();
        let stderr = String::from_utf8_lossy(&output.stderr).into_owned();
        assert!(
            output.status.success(),
            "pipeline {args:?} on {machine} failed:\nstdout:\n{stdout}\nstderr:\n{stderr}"
        );
        (stdout, stderr)
    }

    fn spawn(&self, machine: &str, args: &[&str]) -> Child {
        self.command(machine, args)
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("spawn pipeline binary")
    }

    fn count_lines(&self, name: &str) -> usize {
        fs::read_to_string(self.path().join(name))
            .map(|text| text.lines().count())
            .unwrap_or(0)
    }

    fn wait_for_lines(&self, name: &str, lines: usize) {
        let started = Instant::now();
        while self.count_lines(name) < lines {
            assert!(
                started.elapsed() < Duration::from_secs(60),
                "{name} never reached {lines} lines"
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// (stage, state) pairs and keys of `pipeline status` seen from `machine`.
    fn status(&self, machine: &str, file: &str) -> Vec<(String, String, String)> {
        self.ok(machine, &["status", file])
            .0
            .lines()
            .skip(1)
            .map(|line| {
                let cells: Vec<&str> = line.split_whitespace().collect();
                (
                    cells[0].to_string(),
                    cells[2].to_string(),
                    cells[3].to_string(),
                )
            })
            .collect()
    }

    fn key_of(&self, file: &str, stage: &str) -> String {
        self.status("probe", file)
            .into_iter()
            .find(|row| row.0 == stage)
            .expect("stage in status")
            .1
    }
}

fn wait_output(child: Child) -> (bool, String, String) {
    let output = child.wait_with_output().expect("wait for pipeline");
    (
        output.status.success(),
        String::from_utf8_lossy(&output.stdout).into_owned(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

fn two_stages(sleep_ms: u64) -> String {
    format!(
        "stages:\n  - name: a\n    kind: test_arrays\n    config: {{seed: 3, sleep_ms: {sleep_ms}, steps: 10, count_file: count.txt}}\n  - name: b\n    kind: test_arrays\n    inputs: [a]\n    config: {{count_file: count.txt}}\n"
    )
}

#[test]
fn two_machines_compute_each_stage_once_then_status_inspect_gc() {
    let Some(cluster) = Cluster::new(10.0) else {
        return;
    };
    cluster.write("p.yaml", &two_stages(1500));
    let first = cluster.spawn("m1", &["run", "p.yaml"]);
    let second = cluster.spawn("m2", &["run", "p.yaml"]);
    let (ok1, out1, err1) = wait_output(first);
    let (ok2, out2, err2) = wait_output(second);
    assert!(ok1 && ok2, "m1:\n{out1}\n{err1}\nm2:\n{out2}\n{err2}");
    assert_eq!(
        cluster.count_lines("count.txt"),
        2,
        "each stage computed exactly once across both machines:\n{err1}\n{err2}"
    );
    let ran: usize = [&out1, &out2]
        .iter()
        .map(|out| {
            out.lines()
                .filter(|line| line.split_whitespace().nth(3) == Some("ran"))
                .count()
        })
        .sum();
    assert_eq!(ran, 2, "{out1}\n{out2}");

    // A third machine reads both entries from the bucket, verified, into its local folder.
    assert_eq!(
        cluster
            .status("m3", "p.yaml")
            .iter()
            .map(|row| row.2.as_str())
            .collect::<Vec<_>>(),
        ["cached", "cached"]
    );
    let (out3, err3) = cluster.ok("m3", &["run", "p.yaml"]);
    assert!(out3.contains("2 stages: 0 ran, 2 cached"), "{out3}");
    assert_eq!(err3.matches("downloaded test_arrays/").count(), 2, "{err3}");
    let key_b = cluster.key_of("p.yaml", "b");
    assert!(
        cluster
            .local("m3")
            .join("test_arrays")
            .join(format!("{key_b}.complete"))
            .is_file()
    );
    // A warm local run does not download again.
    let (_, err3b) = cluster.ok("m3", &["run", "p.yaml"]);
    assert!(!err3b.contains("downloaded"), "{err3b}");

    // inspect on a fresh machine: b = (3 + i) + i.
    let (inspect, _) = cluster.ok("m4", &["inspect", "p.yaml:b:values"]);
    assert!(inspect.contains("values"), "{inspect}");
    assert!(inspect.contains("3.000000"), "min of b: {inspect}");
    assert!(inspect.contains("33.000000"), "max of b: {inspect}");

    // gc keeping p.yaml keeps everything; keeping another pipeline removes both, remotely too.
    cluster.ok("m5", &["gc", "--keep", "p.yaml"]);
    assert_eq!(cluster.status("m6", "p.yaml")[1].2, "cached");
    cluster.write(
        "other.yaml",
        "stages:\n  - name: x\n    kind: test_arrays\n",
    );
    let (gc, _) = cluster.ok("m5", &["gc", "--keep", "other.yaml"]);
    assert!(gc.contains("removed 2 entries"), "{gc}");
    assert_eq!(
        cluster
            .status("m7", "p.yaml")
            .iter()
            .map(|row| row.2.as_str())
            .collect::<Vec<_>>(),
        ["missing", "missing"]
    );
    assert!(cluster.moto.list("test_arrays/").is_empty());
}

#[test]
fn killed_lease_holder_is_taken_over_after_the_timeout() {
    let Some(cluster) = Cluster::new(1.5) else {
        return;
    };
    cluster.write("p.yaml", &two_stages(3000));
    let mut holder = cluster.spawn("m1", &["run", "p.yaml", "--until", "a"]);
    cluster.wait_for_lines("count.txt", 1);
    let waiter = cluster.spawn("m2", &["run", "p.yaml", "--until", "a"]);
    std::thread::sleep(Duration::from_millis(500));
    holder.kill().expect("kill the lease holder");
    let _ = holder.wait();
    let started = Instant::now();
    let (ok, out, err) = wait_output(waiter);
    assert!(ok, "{out}\n{err}");
    assert!(err.contains("waiting for another run"), "{err}");
    assert!(err.contains("took over the lease of test_arrays/"), "{err}");
    assert!(out.contains("1 stages: 1 ran"), "{out}");
    assert_eq!(cluster.count_lines("count.txt"), 2);
    assert!(started.elapsed() < Duration::from_secs(30));
    let (out, _) = cluster.ok("m3", &["run", "p.yaml", "--until", "a"]);
    assert!(out.contains("1 stages: 0 ran, 1 cached"), "{out}");
}

#[test]
fn entry_without_completion_marker_is_never_read() {
    let Some(cluster) = Cluster::new(5.0) else {
        return;
    };
    cluster.write("p.yaml", &two_stages(0));
    cluster.ok("m1", &["run", "p.yaml", "--until", "a"]);
    assert_eq!(cluster.count_lines("count.txt"), 1);
    let key = cluster.key_of("p.yaml", "a");
    let marker = format!("test_arrays/{key}/.complete");
    assert!(cluster.moto.get(&marker).is_some());
    // Every chunk stays; only the marker is gone, as after an upload killed before its end.
    cluster.moto.delete(&marker);
    assert!(cluster.moto.list(&format!("test_arrays/{key}/")).len() > 3);
    assert_eq!(cluster.status("m2", "p.yaml")[0].2, "missing");
    let (out, err) = cluster.ok("m2", &["run", "p.yaml", "--until", "a"]);
    assert!(out.contains("1 stages: 1 ran"), "{out}");
    assert!(!err.contains("downloaded"), "{err}");
    assert_eq!(cluster.count_lines("count.txt"), 2);
    assert!(cluster.moto.get(&marker).is_some(), "republished");
}

#[test]
fn wrong_checksum_in_a_remote_chunk_is_detected() {
    let Some(cluster) = Cluster::new(5.0) else {
        return;
    };
    cluster.write("p.yaml", &two_stages(0));
    cluster.ok("m1", &["run", "p.yaml", "--until", "a"]);
    let key = cluster.key_of("p.yaml", "a");
    let chunk = cluster
        .moto
        .list(&format!("test_arrays/{key}/"))
        .into_iter()
        .find(|name| name.ends_with("/values/c/1"))
        .expect("chunk 1 of values");
    let mut bytes = cluster.moto.get(&chunk).expect("chunk bytes");
    bytes[0] ^= 0x40;
    cluster.moto.put(&chunk, &bytes);
    let (out, err) = cluster.ok("m2", &["run", "p.yaml", "--until", "a"]);
    assert!(err.contains("does not match its digest"), "{err}");
    assert!(err.contains("is corrupt"), "{err}");
    assert!(out.contains("ran (corrupt entry)"), "{out}");
    assert_eq!(cluster.count_lines("count.txt"), 2);
    // Nothing corrupt was installed locally, and the recomputed entry is good everywhere.
    let (out, err) = cluster.ok("m3", &["run", "p.yaml", "--until", "a"]);
    assert!(out.contains("1 stages: 0 ran, 1 cached"), "{out}\n{err}");
    assert!(err.contains("downloaded"), "{err}");
}

#[test]
fn server_stopped_mid_run_gives_a_clear_error_then_the_upload_is_retried() {
    let Some(mut cluster) = Cluster::new(2.0) else {
        return;
    };
    cluster.extra_env = vec![
        ("SEQAVATAR_S3_TIMEOUT_S".into(), "1".into()),
        ("SEQAVATAR_S3_RETRY_TIMEOUT_S".into(), "2".into()),
    ];
    cluster.write("p.yaml", &two_stages(1500));
    let key = cluster.key_of("p.yaml", "a");
    let run = cluster.spawn("m1", &["run", "p.yaml", "--until", "a"]);
    cluster.wait_for_lines("count.txt", 1);
    cluster.moto.signal("-STOP");
    let (ok, out, err) = wait_output(run);
    cluster.moto.signal("-CONT");
    assert!(
        !ok,
        "the run must fail while the server is down:\n{out}\n{err}"
    );
    assert!(
        err.contains("could not be published to s3://seqavatar-test/team/cache"),
        "{err}"
    );
    assert!(
        err.contains("the next run with this cache retries the upload"),
        "{err}"
    );
    // Nothing is visible remotely: no completion marker.
    std::thread::sleep(Duration::from_millis(500));
    assert!(
        cluster
            .moto
            .get(&format!("test_arrays/{key}/.complete"))
            .is_none()
    );
    assert_eq!(cluster.status("m2", "p.yaml")[0].2, "missing");
    // The next run on the same machine publishes the kept result without recomputing.
    let (out, err) = cluster.ok("m1", &["run", "p.yaml", "--until", "a"]);
    assert!(
        err.contains("pending upload: published test_arrays/"),
        "{err}"
    );
    assert!(out.contains("1 stages: 0 ran, 1 cached"), "{out}");
    assert_eq!(cluster.count_lines("count.txt"), 1);
    let (out, err) = cluster.ok("m2", &["run", "p.yaml", "--until", "a"]);
    assert!(out.contains("1 stages: 0 ran, 1 cached"), "{out}\n{err}");
    assert!(err.contains("downloaded"), "{err}");
}

/// Read leases are objects in the bucket: `gc` on one machine skips an entry a run on
/// another machine reads (it deleted it when the leases were machine-local), and deletes
/// the lease objects of readers that stopped renewing them (killed) before removing the
/// entry.
#[test]
fn gc_on_another_machine_skips_an_entry_a_run_reads() {
    let Some(cluster) = Cluster::new(3.0) else {
        return;
    };
    cluster.write(
        "p.yaml",
        "stages:\n  - name: a\n    kind: test_arrays\n    config: {seed: 5}\n  - name: b\n    kind: test_arrays\n    inputs: [a]\n    config: {sleep_ms: 6000, steps: 30, count_file: count.txt}\n",
    );
    cluster.write(
        "other.yaml",
        "stages:\n  - name: x\n    kind: test_arrays\n",
    );
    cluster.ok("m1", &["run", "p.yaml", "--until", "a"]);
    let key_a = cluster.key_of("p.yaml", "a");
    // m1 computes b, reading a, for 6 s; m2 collects garbage meanwhile.
    let reader = cluster.spawn("m1", &["run", "p.yaml"]);
    cluster.wait_for_lines("count.txt", 1);
    let (gc, _) = cluster.ok("m2", &["gc", "--keep", "other.yaml"]);
    assert!(
        gc.contains(&format!(
            "skipped test_arrays/{key_a}: a running pipeline reads it"
        )),
        "{gc}"
    );
    assert!(
        cluster
            .moto
            .list(&format!(".readers/test_arrays/{key_a}/"))
            .iter()
            .all(|name| !name.ends_with("/.gc")),
        "the skipping gc removed its own lease object"
    );
    let (ok, out, err) = wait_output(reader);
    assert!(ok, "{out}\n{err}");
    assert_eq!(cluster.status("m3", "p.yaml")[0].2, "cached");
    // The run's lease objects went with it.
    assert!(cluster.moto.list(".readers/").is_empty());

    // A reader killed without deleting its object: once expired (not renewed for the 3 s
    // timeout, plus a second for whole-second timestamps), gc deletes it and the entry.
    let ghost = format!(".readers/test_arrays/{key_a}/ghost-1-1");
    cluster.moto.put(&ghost, b"{}");
    let put_at = Instant::now();
    // And one of a key never published (a killed run was computing it): swept by gc too.
    let unpublished = format!(".readers/test_arrays/{}/ghost-2-2", "0".repeat(64));
    cluster.moto.put(&unpublished, b"{}");
    let (gc, _) = cluster.ok("m2", &["gc", "--keep", "other.yaml"]);
    assert!(
        gc.contains(&format!(
            "skipped test_arrays/{key_a}: a running pipeline reads it"
        )),
        "a fresh lease object is a live reader: {gc}"
    );
    assert!(gc.contains("removed 1 entries"), "b has no reader: {gc}");
    // gc again every half second until the entry goes (a loaded machine may delay it).
    let mut outputs = String::new();
    loop {
        std::thread::sleep(Duration::from_millis(500));
        let (gc, _) = cluster.ok("m2", &["gc", "--keep", "other.yaml"]);
        outputs.push_str(&gc);
        if gc.contains(&format!("removed test_arrays/{key_a}")) {
            break;
        }
        assert!(
            put_at.elapsed() < Duration::from_secs(30),
            "the expired lease object kept the entry: {outputs}"
        );
    }
    assert!(
        put_at.elapsed() >= Duration::from_secs(3),
        "removed while its reader's lease object was younger than the timeout: {outputs}"
    );
    // The sweep of expired lease objects (the timeout plus a second for whole-second
    // timestamps) can come a gc after the entry's removal on a loaded machine.
    while !outputs.contains("removed expired read lease") {
        assert!(
            put_at.elapsed() < Duration::from_secs(30),
            "the expired lease objects were never swept: {outputs}"
        );
        std::thread::sleep(Duration::from_millis(500));
        let (gc, _) = cluster.ok("m2", &["gc", "--keep", "other.yaml"]);
        outputs.push_str(&gc);
    }
    assert!(cluster.moto.list(".readers/").is_empty());
    assert!(cluster.moto.list("test_arrays/").is_empty());
}

/// `gc` on another machine while `pipeline render` draws an avatar of the shared cache: the
/// render's read leases are objects in the bucket, so `gc` skips the train entry and every
/// entry it read (ingest, fit, motion), and the render goes on.
#[test]
fn gc_on_another_machine_skips_the_entries_a_render_reads() {
    let Some(cluster) = Cluster::new(10.0) else {
        return;
    };
    cluster.write("p.yaml", crate::viewer::PIPELINE);
    cluster.ok("m1", &["run", "p.yaml"]);
    let keys: Vec<String> = cluster
        .status("probe", "p.yaml")
        .into_iter()
        .map(|(stage, key, _)| format!("{stage}/{key}"))
        .collect();
    assert_eq!(keys.len(), 4, "{keys:?}");
    let train = keys[3].strip_prefix("train/").unwrap();
    let poses =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("stages/eval/tests/fixtures/poses_long.npz");
    let out = cluster.path().join("render");
    let mut render = cluster.spawn(
        "m1",
        &[
            "render",
            "--avatar",
            train,
            "--poses",
            poses.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--device",
            "cpu",
        ],
    );
    crate::support::wait_for_file(&mut render, &out.join("frame_00000.png"));
    let (gc, _) = cluster.ok("m2", &["gc"]);
    crate::support::assert_gc_skipped(&gc, &keys, &mut render);
    render.kill().unwrap();
    render.wait().unwrap();
}
