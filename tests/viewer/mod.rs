//! `pipeline view` on a tiny avatar trained through the real ingest, motion and train stages:
//! the endpoints over plain HTTP (statuses, validation, hostile paths, the Host check, the
//! access token beyond loopback, several tabs at once), the frames against eval's renderer, the
//! Gaussian stream against eval's posed Gaussians (layout version, bounds-checked frame
//! ranges, the PLY download), the command line (FILE.yaml:STAGE, port 0, loopback by
//! default), and the page in headless Chromium (WebGL2 on SwiftShader) driven over
//! WebDriver at 1280 x 720: the first frame splatted in the browser, not blank, the page's
//! splat against the server's render of the same view, orbiting and 1x playback measured
//! and printed (`viewer orbit: F FPS at 1280x720`, `viewer playback: P% of frames shown at
//! 1x`; figures, never asserted on), a compare sheet zoomed in 2D, the narrow layout, a
//! screenshot, no console error; a stopped server and its return; then the same page on a
//! viewer bound beyond loopback, opened with its token.
//!
//! The browser part needs `chromium` and `chromedriver` on PATH (Debian `chromium
//! chromium-driver`); without them it is skipped with a printed reason, unless `CI` is set,
//! where it fails. `SEQAVATAR_VIEWER_E2E_URL` points the browser part at a viewer already
//! running (e.g. a release `pipeline view pipelines/synthetic.yaml:train`, to measure the
//! demo avatar's frame rate); `SEQAVATAR_VIEWER_SCREENSHOT` names where the screenshot goes
//! (default: the test's temporary folder).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{SocketAddr, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use seqavatar_compute::backend::{Backend, DeviceChoice};
use seqavatar_engine::{EntryId, LocalStore, Pipeline, RunOptions, StageReport, Store as _};
use seqavatar_evaluation::avatar_render::AvatarRenderer;
use seqavatar_evaluation::evaluate::ViewRenderer;
use seqavatar_viewer::{Viewer, ViewerOptions};

use crate::support::registry;

/// The tiny avatar, through fit (`mode: off`) and motion; the remote tests render it too.
pub(crate) const PIPELINE: &str = r#"description: tiny viewer test
stages:
  - name: ingest
    kind: ingest
    config:
      dataset: {kind: synthetic, cameras: 3, frames: 10, width: 48, height: 40, supersample: 1, garment: false, body_grid_spacing: 0.05}
      past_frames: 0
  - {name: fit, kind: fit, inputs: [ingest], config: {mode: off}}
  - name: motion
    kind: motion
    inputs: [ingest]
    config: {scales: [1, 2], knn: 4}
  - name: train
    kind: train
    inputs: [ingest, fit, motion]
    config: {"preset": "fast", "device": "cpu", "seed": 5, "iterations": 30, "motion_context": "multiscale", "checkpoint_every": 100, "sh_degree": 1, "sh_degree_interval": 10}
"#;

fn cpu() -> Backend {
    Backend::select(DeviceChoice::Cpu).unwrap()
}

/// Trains the tiny avatar into `cache`; returns the train entry's key.
fn train_tiny_avatar(cache: &Path) -> String {
    let registry = registry();
    let store = LocalStore::open(cache).unwrap();
    let pipeline = Pipeline::parse(PIPELINE, Path::new("viewer.yaml"), &registry, &[]).unwrap();
    let options = RunOptions {
        until: Some("train".to_owned()),
        force: Vec::new(),
    };
    let reports: Vec<StageReport> =
        seqavatar_engine::run(&pipeline, &registry, &store, &options).unwrap();
    reports
        .iter()
        .find(|r| r.name == "train")
        .unwrap()
        .key
        .clone()
}

/// The train entry `key`'s avatar as eval renders it (on `cpu`, driven by its ingest and
/// motion entries), and its ingest entry.
fn eval_renderer(cache: &Path, key: &str) -> (AvatarRenderer, seqavatar_engine::EntryReader) {
    let store = LocalStore::open(cache).unwrap();
    let open = |kind: &str, key: &str| {
        seqavatar_engine::open_leased_verified(&store, &EntryId::new(kind, key)).unwrap()
    };
    let train = open("train", key);
    let input = |kind: &str| {
        let input = train
            .manifest()
            .inputs
            .iter()
            .find(|input| input.kind == kind)
            .unwrap()
            .clone();
        open(kind, &input.key)
    };
    let (ingest, fit, motion) = (input("ingest"), input("fit"), input("motion"));
    let renderer = AvatarRenderer::open(&train, &ingest, &fit, Some(&motion), &cpu()).unwrap();
    (renderer, ingest)
}

fn start(cache: &Path, avatar: &str, max_size: u32) -> Viewer {
    Viewer::start(ViewerOptions {
        cache: cache.to_owned(),
        avatar: avatar.to_owned(),
        poses: None,
        backend: cpu(),
        host: "127.0.0.1".to_owned(),
        port: 0,
        max_size,
    })
    .unwrap()
}

/// One HTTP/1.1 exchange over a fresh connection (`Connection: close`).
struct Reply {
    status: u16,
    headers: Vec<(String, String)>,
    body: Vec<u8>,
}

impl Reply {
    fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(key, _)| key.eq_ignore_ascii_case(name))
            .map(|(_, value)| value.as_str())
    }

    fn text(&self) -> String {
        String::from_utf8_lossy(&self.body).into_owned()
    }
}

fn http(address: SocketAddr, method: &str, target: &str, host: &str, body: &str) -> Reply {
    let mut stream = TcpStream::connect(address).unwrap();
    stream
        .set_read_timeout(Some(Duration::from_secs(300)))
        .unwrap();
    let mut head = format!("{method} {target} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n");
    if !body.is_empty() || method == "POST" {
        head.push_str(&format!(
            "Content-Type: application/json\r\nContent-Length: {}\r\n",
            body.len()
        ));
    }
    head.push_str("\r\n");
    stream.write_all(head.as_bytes()).unwrap();
    stream.write_all(body.as_bytes()).unwrap();
    // Read the head, then the body by its Content-Length or chunks (chromedriver keeps the
    // connection open despite `Connection: close`), else to the end of the stream.
    let mut raw = Vec::new();
    let mut buffer = [0u8; 16384];
    let mut read_more = |raw: &mut Vec<u8>| -> bool {
        let count = stream.read(&mut buffer).unwrap();
        raw.extend_from_slice(&buffer[..count]);
        count > 0
    };
    let split = loop {
        if let Some(at) = raw.windows(4).position(|window| window == b"\r\n\r\n") {
            break at;
        }
        assert!(
            read_more(&mut raw),
            "no header end in {:?}",
            String::from_utf8_lossy(&raw)
        );
    };
    let head = String::from_utf8_lossy(&raw[..split]).into_owned();
    let mut lines = head.split("\r\n");
    let status: u16 = lines
        .next()
        .unwrap()
        .split(' ')
        .nth(1)
        .unwrap()
        .parse()
        .unwrap();
    let headers: Vec<(String, String)> = lines
        .filter_map(|line| line.split_once(':'))
        .map(|(key, value)| (key.trim().to_owned(), value.trim().to_owned()))
        .collect();
    let find = |name: &str| {
        headers
            .iter()
            .find(|(key, _)| key.eq_ignore_ascii_case(name))
            .map(|(_, value)| value.to_ascii_lowercase())
    };
    let start = split + 4;
    let body = if let Some(length) = find("content-length") {
        let length: usize = length.parse().unwrap();
        while raw.len() < start + length {
            assert!(read_more(&mut raw), "the body ended early");
        }
        raw[start..start + length].to_vec()
    } else if find("transfer-encoding").as_deref() == Some("chunked") {
        let mut decoded = Vec::new();
        let mut at = start;
        loop {
            let line_end = loop {
                if let Some(end) = raw[at..].windows(2).position(|w| w == b"\r\n") {
                    break at + end;
                }
                assert!(read_more(&mut raw), "a chunk ended early");
            };
            let size_text = String::from_utf8_lossy(&raw[at..line_end]).into_owned();
            let size =
                usize::from_str_radix(size_text.split(';').next().unwrap().trim(), 16).unwrap();
            at = line_end + 2;
            if size == 0 {
                break;
            }
            while raw.len() < at + size + 2 {
                assert!(read_more(&mut raw), "a chunk ended early");
            }
            decoded.extend_from_slice(&raw[at..at + size]);
            at += size + 2;
        }
        decoded
    } else {
        while read_more(&mut raw) {}
        raw[start..].to_vec()
    };
    Reply {
        status,
        headers,
        body,
    }
}

fn get(viewer: &Viewer, target: &str) -> Reply {
    let address = viewer.address();
    http(address, "GET", target, &address.to_string(), "")
}

fn decode_jpeg(reply: &Reply) -> image::RgbImage {
    assert_eq!(reply.status, 200, "{}", reply.text());
    assert_eq!(reply.header("content-type"), Some("image/jpeg"));
    image::load_from_memory_with_format(&reply.body, image::ImageFormat::Jpeg)
        .unwrap()
        .to_rgb8()
}

/// Pixels brighter than a dark background in any channel.
fn lit_pixels(image: &image::RgbImage) -> usize {
    image
        .pixels()
        .filter(|pixel| pixel.0.iter().any(|&channel| channel > 24))
        .count()
}

#[test]
fn the_viewer_serves_renders_of_a_trained_avatar_safely_and_in_a_browser() {
    let sandbox = crate::support::Sandbox::new();
    let cache = sandbox.cache();
    let key = train_tiny_avatar(&cache);
    for max_size in [15, 8193] {
        let refused = Viewer::start(ViewerOptions {
            cache: cache.clone(),
            avatar: key.clone(),
            poses: None,
            backend: cpu(),
            host: "127.0.0.1".to_owned(),
            port: 0,
            max_size,
        });
        let error = refused.err().unwrap().to_string();
        assert!(
            error.contains(&format!("--max-size {max_size} must be in 16..=8192")),
            "{error}"
        );
    }
    let viewer = start(&cache, &key[..12], 256);
    let address = viewer.address();
    assert!(address.ip().is_loopback());
    assert_eq!(
        viewer.url(),
        format!("http://127.0.0.1:{}/", address.port())
    );

    // The page: self-contained, nothing fetched from elsewhere.
    let page = get(&viewer, "/");
    assert_eq!(page.status, 200);
    assert_eq!(
        page.header("content-type"),
        Some("text/html; charset=utf-8")
    );
    let html = page.text();
    assert!(html.contains("<canvas id=\"view\""));
    assert!(!html.contains("://"), "the page names another origin");
    assert!(!html.contains("src=") && !html.contains("href="));
    assert!(
        page.header("content-security-policy")
            .is_some_and(|policy| policy.starts_with("default-src 'none'"))
    );

    // The scene.
    let info: serde_json::Value = serde_json::from_slice(&get(&viewer, "/info").body).unwrap();
    assert_eq!(info["num_frames"], 10);
    assert_eq!(info["cameras"].as_array().unwrap().len(), 3);
    assert_eq!(info["cameras"][0]["width"], 48);
    assert_eq!(info["ground_truth"], true);
    assert_eq!(info["context_probes"], true);
    assert_eq!(info["max_size"], 256);
    let first = info["first_frame"].as_u64().unwrap() as usize;
    assert!(first < 10, "{info}");

    // A dataset camera's frame is eval's render of it (up to JPEG rounding).
    let frame = first + 1;
    let image = decode_jpeg(&get(&viewer, &format!("/frame?frame={frame}&camera=0")));
    assert_eq!(image.dimensions(), (48, 40));
    let expected = {
        let (mut renderer, ingest) = eval_renderer(&cache, &key);
        let camera = &seqavatar_schema::ingest::read_cameras(&ingest).unwrap()[0];
        renderer.render(frame, camera).unwrap().to_rgb_image()
    };
    let difference: f64 = image
        .as_raw()
        .iter()
        .zip(expected.as_raw())
        .map(|(a, b)| f64::from(a.abs_diff(*b)))
        .sum::<f64>()
        / image.as_raw().len() as f64;
    assert!(
        difference < 2.0,
        "mean difference {difference} from eval's render"
    );
    assert!(lit_pixels(&expected) > 20, "the avatar is not visible");

    // Orbit views at the asked size, comparison sheets, context probes.
    let home = &info["home"];
    let orbit = format!(
        "/frame?frame={frame}&az={}&el={}&dist={}&fov={}&w=64&h=32",
        home["az"], home["el"], home["dist"], home["fov"]
    );
    let image = decode_jpeg(&get(&viewer, &orbit));
    assert_eq!(image.dimensions(), (64, 32));
    assert!(lit_pixels(&image) > 10, "the orbit view is blank");
    // Ground truth | render | error where the ingest entry has an image of (camera, frame);
    // the render alone, saying why, where it has none.
    let (mut compared, mut without) = (0, 0);
    for camera in 0..3 {
        for frame in first..10 {
            let sheet = get(
                &viewer,
                &format!("/frame?frame={frame}&camera={camera}&compare=1"),
            );
            let note = sheet.header("x-compare").unwrap().to_owned();
            if note == "truth|render|error" {
                assert_eq!(decode_jpeg(&sheet).dimensions(), (3 * 48, 40));
                // The frame's PSNR; no garment region (this scene has no skirt).
                let psnr: f64 = sheet.header("x-compare-psnr").unwrap().parse().unwrap();
                assert!(psnr > 5.0 && psnr.is_finite(), "{psnr}");
                assert_eq!(sheet.header("x-compare-garment-psnr"), Some("n/a"));
                compared += 1;
            } else {
                assert_eq!(
                    note,
                    format!("unavailable: no image of camera {camera} at frame {frame}")
                );
                assert_eq!(decode_jpeg(&sheet).dimensions(), (48, 40));
                without += 1;
            }
        }
    }
    assert!(
        compared > 0,
        "no (camera, frame) has a ground-truth image ({without} without)"
    );
    let small = get(&viewer, &format!("/frame?frame={frame}&camera=1&w=24"));
    assert_eq!(decode_jpeg(&small).dimensions(), (24, 20));
    assert_eq!(small.header("x-frame"), Some(frame.to_string().as_str()));
    for context in ["zeroed", "from:2", "on"] {
        let reply = get(
            &viewer,
            &format!("/frame?frame={frame}&camera=0&context={context}"),
        );
        decode_jpeg(&reply);
    }

    gaussian_stream_is_versioned_and_bounds_checked(&viewer, &cache, &key, first);

    // Bad parameters: 400 naming the parameter.
    for (target, needle) in [
        ("/frame", "missing parameter `frame`"),
        ("/frame?frame=10&camera=0", "`frame` 10 is out of range"),
        (
            "/frame?frame=abc&camera=0",
            "`frame` must be a non-negative integer",
        ),
        ("/frame?frame=5&camera=3", "`camera` 3 is out of range"),
        (
            "/frame?frame=5&az=0&el=0&dist=2&w=257&h=64",
            "`w` 257 is out of range 16..=256",
        ),
        (
            "/frame?frame=5&az=NaN&el=0&dist=2&w=64&h=64",
            "`az` must be finite",
        ),
        (
            "/frame?frame=5&az=0&el=0&dist=-1&w=64&h=64",
            "`dist` -1 is out of range",
        ),
        (
            "/frame?frame=5&az=0&el=0&dist=2&w=64&h=64&compare=1",
            "needs a dataset `camera`",
        ),
        (
            "/frame?frame=5&camera=0&file=/etc/passwd",
            "unknown parameter `file`",
        ),
        (
            "/frame?frame=5&camera=0&context=from:99",
            "offset 99 is out of range",
        ),
        ("/frame?frame=5&camera=0&frame=6", "given more than once"),
        ("/frame?frame=%FF&camera=0", "`frame` must be"),
    ] {
        let reply = get(&viewer, target);
        assert_eq!(reply.status, 400, "{target}: {}", reply.text());
        assert!(reply.text().contains(needle), "{target}: {}", reply.text());
    }
    // Hostile paths and unknown routes: 404, nothing from the file system.
    for target in [
        "/../../etc/passwd",
        "/%2e%2e/%2e%2e/etc/passwd",
        "/frame/../../../etc/passwd",
        "/frame/%2e%2e%2f%2e%2e%2fetc%2fpasswd",
        "//etc/passwd",
        "/etc/passwd",
        "/info/../Cargo.toml",
        "/page.html",
        "/index.html",
    ] {
        let reply = get(&viewer, target);
        assert_eq!(reply.status, 404, "{target}: {}", reply.text());
        assert!(!reply.text().contains("root:"), "{target}");
    }
    assert_eq!(
        http(
            address,
            "POST",
            "/frame?frame=5&camera=0",
            &address.to_string(),
            ""
        )
        .status,
        405
    );
    // A loopback server answers only loopback host names (no DNS rebinding).
    let rebound = http(address, "GET", "/info", "attacker.example", "");
    assert_eq!(rebound.status, 421, "{}", rebound.text());
    let by_name = http(
        address,
        "GET",
        "/info",
        &format!("localhost:{}", address.port()),
        "",
    );
    assert_eq!(by_name.status, 200);
    let remote = remote_viewer_needs_its_token(&cache, &key);

    // Several tabs at once: every one gets its frame.
    std::thread::scope(|scope| {
        let tabs: Vec<_> = (0..4)
            .map(|tab| {
                let viewer = &viewer;
                scope.spawn(move || {
                    get(
                        viewer,
                        &format!(
                            "/frame?tab=tab{tab}&frame={}&camera={}",
                            first + tab % 2,
                            tab % 3
                        ),
                    )
                })
            })
            .collect();
        for tab in tabs {
            decode_jpeg(&tab.join().unwrap());
        }
    });

    // On the gpu backend (lavapipe in CI) the viewer draws what the cpu one draws.
    if let Some(gpu) = seqavatar_compute::backend::test_support::gpu_test_backend() {
        let on_gpu = Viewer::start(ViewerOptions {
            cache: cache.clone(),
            avatar: key.clone(),
            poses: None,
            backend: gpu,
            host: "127.0.0.1".to_owned(),
            port: 0,
            max_size: 256,
        })
        .unwrap();
        let target = format!("/frame?frame={frame}&camera=0");
        let (cpu_image, gpu_image) = (
            decode_jpeg(&get(&viewer, &target)),
            decode_jpeg(&get(&on_gpu, &target)),
        );
        let difference: f64 = cpu_image
            .as_raw()
            .iter()
            .zip(gpu_image.as_raw())
            .map(|(a, b)| f64::from(a.abs_diff(*b)))
            .sum::<f64>()
            / cpu_image.as_raw().len() as f64;
        assert!(
            difference < 1.0,
            "gpu frame differs from cpu by {difference} on average"
        );
        let info: serde_json::Value = serde_json::from_slice(&get(&on_gpu, "/info").body).unwrap();
        assert!(
            info["device"].as_str().unwrap().starts_with("gpu"),
            "{info}"
        );
        println!(
            "the viewer on {} draws the cpu viewer's frame (mean difference {difference:.3})",
            info["device"]
        );
    }

    command_line_serves_a_pipeline_stage_on_loopback(&sandbox);

    // The browser, on this avatar or on the viewer the environment names.
    let screenshot = std::env::var_os("SEQAVATAR_VIEWER_SCREENSHOT")
        .map(PathBuf::from)
        .unwrap_or_else(|| sandbox.path().join("viewer.png"));
    match std::env::var("SEQAVATAR_VIEWER_E2E_URL") {
        Ok(url) => browser_end_to_end(&url, &screenshot, true),
        Err(_) => {
            browser_end_to_end(&viewer.url(), &screenshot, true);
            the_page_pauses_while_the_server_is_down(&cache, &key);
            // Beyond loopback, the page opened with the token works on through its cookie.
            let token = remote.url().rsplit_once('=').unwrap().1.to_owned();
            let port = remote.address().port();
            browser_end_to_end(
                &format!("http://127.0.0.1:{port}/?token={token}"),
                &screenshot.with_extension("remote.png"),
                false,
            );
        }
    }
    // The viewers of this process gone, the command line's alone holds the entries.
    drop((viewer, remote));
    a_read_only_cache_is_viewed_without_lock_files(&sandbox, &key);
    gc_leaves_the_entries_a_viewer_serves(&sandbox, &key);
}

/// `pipeline view` on a read-only cache serves the scene and its frames, and makes no lock
/// file (see `engine::a_read_only_cache_serves_reads` for how the cache is made read-only).
fn a_read_only_cache_is_viewed_without_lock_files(sandbox: &crate::support::Sandbox, key: &str) {
    let locks = sandbox.cache().join(".locks");
    std::fs::remove_dir_all(&locks).unwrap();
    let Some(cache) = crate::support::ReadOnlyCache::new(sandbox) else {
        return;
    };
    let (_child, address) =
        serve(cache.command(&["view", "--avatar", key, "--port", "0", "--device", "cpu"]));
    let reply = http(address, "GET", "/info", &address.to_string(), "");
    assert_eq!(reply.status, 200, "{}", reply.text());
    let host = address.to_string();
    let frame = http(address, "GET", "/frame?frame=5&camera=0", &host, "");
    assert_eq!(decode_jpeg(&frame).dimensions(), (48, 40));
    assert!(!locks.exists(), "lock files were made in a read-only cache");
}

/// `gc` while `pipeline view` serves the avatar skips every entry the viewer holds (its fit
/// entry too), and the viewer serves on; once it is gone, `gc` removes them.
fn gc_leaves_the_entries_a_viewer_serves(sandbox: &crate::support::Sandbox, key: &str) {
    let entries: Vec<String> = LocalStore::open(&sandbox.cache())
        .unwrap()
        .list()
        .unwrap()
        .iter()
        .map(ToString::to_string)
        .collect();
    assert_eq!(entries.len(), 4, "{entries:?}");
    let (mut child, address) =
        serve(sandbox.command(&["view", "--avatar", key, "--port", "0", "--device", "cpu"]));
    crate::support::assert_gc_skipped(&sandbox.ok(&["gc"]), &entries, &mut child.0);
    let host = address.to_string();
    let frame = http(address, "GET", "/frame?frame=5&camera=1", &host, "");
    assert_eq!(decode_jpeg(&frame).dimensions(), (48, 40));
    drop(child);
    let report = sandbox.ok(&["gc"]);
    for id in &entries {
        assert!(report.contains(&format!("removed {id}")), "{report}");
    }
}

/// Starts `command`, a `pipeline view` on port 0, and reads the URL it prints first: the
/// child (killed when dropped) and the loopback address it serves.
fn serve(mut command: Command) -> (ChildGuard, SocketAddr) {
    let mut child = ChildGuard(
        command
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap(),
    );
    let mut line = String::new();
    BufReader::new(child.0.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .strip_prefix("viewer: ")
        .and_then(|rest| rest.split_whitespace().next())
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"));
    let address: SocketAddr = url
        .strip_prefix("http://")
        .and_then(|rest| rest.strip_suffix('/'))
        .unwrap()
        .parse()
        .unwrap();
    assert_eq!(address.ip().to_string(), "127.0.0.1");
    (child, address)
}

/// Bound beyond loopback, the viewer answers only requests carrying the token of its URL, in
/// the query or in the cookie the page sets.
/// Returns the viewer, for the browser.
fn remote_viewer_needs_its_token(cache: &Path, key: &str) -> Viewer {
    let start = |cache: &Path| {
        Viewer::start(ViewerOptions {
            cache: cache.to_owned(),
            avatar: key.to_owned(),
            poses: None,
            backend: cpu(),
            host: "0.0.0.0".to_owned(),
            port: 0,
            max_size: 256,
        })
        .unwrap()
    };
    let (viewer, other) = (start(cache), start(cache));
    let url = viewer.url();
    let token = url.rsplit_once("/?token=").unwrap().1.to_owned();
    assert!(
        token.len() == 48 && token.bytes().all(|b| b.is_ascii_hexdigit()),
        "{url}"
    );
    assert!(!url.contains("0.0.0.0"), "{url} names no reachable host");
    // Drawn anew at every start.
    assert!(!other.url().ends_with(&token));
    let address = SocketAddr::from(([127, 0, 0, 1], viewer.address().port()));
    let (host, frame) = ("example.org", "/frame?frame=5&camera=0");
    let stream = "/gaussians?frame=5";
    let get_with = |target: &str, cookie: Option<&str>| {
        let mut stream = TcpStream::connect(address).unwrap();
        let cookie = cookie.map_or(String::new(), |cookie| format!("Cookie: {cookie}\r\n"));
        write!(
            stream,
            "GET {target} HTTP/1.1\r\nHost: {host}\r\nConnection: close\r\n{cookie}\r\n"
        )
        .unwrap();
        let mut reply = Vec::new();
        stream.read_to_end(&mut reply).unwrap();
        String::from_utf8_lossy(&reply).into_owned()
    };
    let status = |reply: &str| reply.split(' ').nth(1).unwrap_or("").to_owned();
    // Without the token, or with a wrong one: 403 on every route.
    for target in [
        "/",
        "/info",
        frame,
        stream,
        "/ply?frame=5",
        "/?token=",
        &format!("/info?token={}", &token[1..]),
    ] {
        let reply = get_with(target, None);
        assert_eq!(status(&reply), "403", "{target}: {reply}");
        assert!(reply.contains("access token"), "{reply}");
    }
    let port = viewer.address().port();
    let other_port = other.address().port();
    // The token with its first digit changed (a fixed "0" would be the token itself one time
    // in sixteen).
    let changed_first = if token.starts_with('0') { '1' } else { '0' };
    let wrong_cookie = format!("seqavatar-view-{port}={changed_first}{}", &token[1..]);
    assert_eq!(status(&get_with("/info", Some(&wrong_cookie))), "403");
    // Another viewer's cookie opens only that viewer.
    let other_token = other.url().rsplit_once("=").unwrap().1.to_owned();
    let other_cookie = format!("seqavatar-view-{other_port}={other_token}");
    assert_eq!(status(&get_with("/info", Some(&other_cookie))), "403");
    // With it: the page sets the cookie its fetches then carry.
    let page = get_with(&format!("/?token={token}&camera=1"), None);
    assert_eq!(status(&page), "200", "{page}");
    let cookie = format!("seqavatar-view-{port}={token}");
    assert!(
        page.lines()
            .any(|line| line.to_ascii_lowercase().starts_with("set-cookie:")
                && line.contains(&cookie)
                && line.contains("HttpOnly")),
        "{page}"
    );
    for target in ["/info", frame, stream] {
        let reply = get_with(target, Some(&format!("theme=dark; {cookie}")));
        assert_eq!(status(&reply), "200", "{target}: {reply}");
    }
    for target in [frame, stream] {
        let reply = get_with(&format!("{target}&token={token}"), None);
        assert_eq!(status(&reply), "200", "{reply}");
    }
    viewer
}

/// `pipeline view FILE.yaml:train --port 0` prints a loopback URL that serves the avatar.
fn command_line_serves_a_pipeline_stage_on_loopback(sandbox: &crate::support::Sandbox) {
    let file = sandbox.write("viewer.yaml", PIPELINE);
    let help = sandbox.ok(&["view", "--help"]);
    assert!(help.contains("[default: 127.0.0.1]"), "{help}");
    let stage = format!("{}:train", file.display());
    let (_child, address) =
        serve(sandbox.command(&["view", &stage, "--port", "0", "--device", "cpu"]));
    let reply = http(address, "GET", "/info", &address.to_string(), "");
    assert_eq!(reply.status, 200, "{}", reply.text());
    // A stage that is not a train stage is refused.
    let stderr = sandbox.fails(&["view", &format!("{}:motion", file.display()), "--port", "0"]);
    assert!(
        stderr.contains("stage \"motion\" is a motion stage"),
        "{stderr}"
    );
}

/// Kills and reaps the child process it holds when dropped.
struct ChildGuard(Child);

impl Drop for ChildGuard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn on_path(program: &str) -> Option<PathBuf> {
    seqavatar_evaluation::animate::on_path(program)
}

/// A WebDriver session of chromedriver.
struct Driver {
    address: SocketAddr,
    session: String,
}

impl Driver {
    fn call(&self, method: &str, path: &str, body: serde_json::Value) -> serde_json::Value {
        let target = format!("/session/{}{path}", self.session);
        let body = if method == "GET" {
            String::new()
        } else {
            body.to_string()
        };
        let reply = http(
            self.address,
            method,
            &target,
            &self.address.to_string(),
            &body,
        );
        let value: serde_json::Value = serde_json::from_slice(&reply.body)
            .unwrap_or_else(|_| panic!("{method} {path}: {}", reply.text()));
        assert_eq!(reply.status, 200, "{method} {path}: {value}");
        value["value"].clone()
    }

    fn script(&self, script: &str) -> serde_json::Value {
        self.call(
            "POST",
            "/execute/sync",
            serde_json::json!({"script": script, "args": []}),
        )
    }

    /// Polls `script` until it returns true.
    fn wait_for(&self, what: &str, script: &str, timeout: Duration) {
        let started = Instant::now();
        while self.script(script) != serde_json::Value::Bool(true) {
            assert!(
                started.elapsed() < timeout,
                "waited {timeout:?} for {what}; page state {}",
                self.script("return window.viewer")
            );
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// Opens `url` with the query parameter `parameter` (`name=value`) added.
    fn open(&self, url: &str, parameter: &str) {
        let separator = if url.contains('?') { '&' } else { '?' };
        self.call(
            "POST",
            "/url",
            serde_json::json!({"url": format!("{url}{separator}{parameter}")}),
        );
    }

    fn click(&self, css: &str) {
        let element = self.call(
            "POST",
            "/element",
            serde_json::json!({"using": "css selector", "value": css}),
        );
        let id = element["element-6066-11e4-a52e-4f735466cecf"]
            .as_str()
            .unwrap()
            .to_owned();
        self.call(
            "POST",
            &format!("/element/{id}/click"),
            serde_json::json!({}),
        );
    }
}

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn base64_decode(text: &str) -> Vec<u8> {
    let value = |byte: u8| -> u32 {
        match byte {
            b'A'..=b'Z' => u32::from(byte - b'A'),
            b'a'..=b'z' => u32::from(byte - b'a') + 26,
            b'0'..=b'9' => u32::from(byte - b'0') + 52,
            b'+' => 62,
            b'/' => 63,
            _ => panic!("not base64: {byte}"),
        }
    };
    let digits: Vec<u8> = text
        .bytes()
        .filter(|byte| !byte.is_ascii_whitespace() && *byte != b'=')
        .collect();
    let mut out = Vec::with_capacity(digits.len() * 3 / 4);
    for chunk in digits.chunks(4) {
        let bits = chunk
            .iter()
            .fold(0u32, |acc, &byte| (acc << 6) | value(byte))
            << (6 * (4 - chunk.len()));
        let bytes = bits.to_be_bytes();
        out.extend_from_slice(&bytes[1..chunk.len()]);
    }
    out
}

/// A script for WebDriver's `execute/async`: drags across the stage with synthetic pointer
/// events, one move per display frame for three seconds, and answers the page's counters.
const ORBIT_SCRIPT: &str = "const done = arguments[arguments.length - 1];
  const stage = document.getElementById('stage'), stats = window.viewerStats;
  const box = stage.getBoundingClientRect();
  const x = box.left + box.width / 2, y = box.top + box.height / 2;
  const azimuth = stats.view.az;
  stats.reset();
  const pointer = (type, dx) => stage.dispatchEvent(new PointerEvent(type,
    {pointerId: 7, clientX: x + dx, clientY: y, button: 0, bubbles: true}));
  pointer('pointerdown', 0);
  const started = performance.now();
  let moves = 0;
  function step(now) {
    if (now - started > 3000) {
      pointer('pointerup', 2 * moves);
      done({draws: stats.draws, ms: now - started, moves,
        turned: stats.view.az !== azimuth});
      return;
    }
    moves++;
    pointer('pointermove', 2 * moves);
    requestAnimationFrame(step);
  }
  requestAnimationFrame(step);";

/// The page in headless Chromium (software GL) at 1280 x 720: the first frame splatted in
/// the browser, a canvas that is not blank; with `measure`, orbiting a paused frame and 1x
/// playback once the frames are buffered, printing the display rate and the share of frames
/// shown (figures, never asserted on), a compare sheet zoomed in 2D with its labels and PSNR,
/// and a screenshot; never a console error.
/// Headless Chromium driven over WebDriver by its chromedriver; the session ends when dropped.
struct Browser {
    driver: Driver,
    _profile: tempfile::TempDir,
    _process: ChildGuard,
}

impl Drop for Browser {
    fn drop(&mut self) {
        let address = self.driver.address;
        let _ = http(
            address,
            "DELETE",
            &format!("/session/{}", self.driver.session),
            &address.to_string(),
            "",
        );
    }
}

/// A browser session, `None` (the test skipped, said why) without chromium and chromedriver
/// outside CI.
fn open_browser() -> Option<Browser> {
    let browser = ["chromium", "chromium-browser", "google-chrome"]
        .into_iter()
        .find_map(on_path);
    let (Some(browser), Some(chromedriver)) = (browser, on_path("chromedriver")) else {
        let reason =
            "chromium and chromedriver are not on PATH (apt-get install chromium chromium-driver)";
        assert!(
            std::env::var_os("CI").is_none(),
            "CI is set: the browser test must run, but {reason}"
        );
        eprintln!("skipped the browser test: {reason}");
        return None;
    };
    let port = free_port();
    let driver_process = ChildGuard(
        Command::new(&chromedriver)
            .arg(format!("--port={port}"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let address: SocketAddr = format!("127.0.0.1:{port}").parse().unwrap();
    let started = Instant::now();
    loop {
        if TcpStream::connect(address).is_ok() {
            let status = http(address, "GET", "/status", &address.to_string(), "");
            let ready = serde_json::from_slice::<serde_json::Value>(&status.body)
                .map(|value| value["value"]["ready"] == true)
                .unwrap_or(false);
            if ready {
                break;
            }
        }
        assert!(
            started.elapsed() < Duration::from_secs(30),
            "chromedriver did not start"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let profile = tempfile::tempdir().unwrap();
    let capabilities = serde_json::json!({"capabilities": {"alwaysMatch": {
        "browserName": "chrome",
        "goog:loggingPrefs": {"browser": "ALL"},
        "goog:chromeOptions": {
            "binary": browser,
            // WebGL2 on SwiftShader, Chromium's software GL.
            "args": [
                "--headless", "--no-sandbox", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--disable-quic",
                "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync",
                "--disable-dev-shm-usage", "--window-size=1280,900",
                format!("--user-data-dir={}", profile.path().display()),
            ],
        },
    }}});
    let reply = http(
        address,
        "POST",
        "/session",
        &address.to_string(),
        &capabilities.to_string(),
    );
    let created: serde_json::Value = serde_json::from_slice(&reply.body).unwrap();
    assert_eq!(reply.status, 200, "new session: {created}");
    let driver = Driver {
        address,
        session: created["value"]["sessionId"].as_str().unwrap().to_owned(),
    };
    Some(Browser {
        driver,
        _profile: profile,
        _process: driver_process,
    })
}

fn browser_end_to_end(url: &str, screenshot: &Path, measure: bool) {
    let Some(browser) = open_browser() else {
        return;
    };
    let driver = &browser.driver;
    driver.open(url, "speed=1");
    driver.wait_for(
        "the first frame splatted in the browser",
        "return !!window.viewerStats && viewerStats.mode === 'webgl2' && viewerStats.frame >= 0 \
         && viewerStats.draws >= 1",
        Duration::from_secs(120),
    );
    // The stage (the canvas) at 1280 x 720: the window is the stage and the controls.
    let height = driver.script("return viewerStats.height").as_i64().unwrap();
    let window = driver.call("GET", "/window/rect", serde_json::Value::Null);
    let outer = window["height"].as_i64().unwrap();
    driver.call(
        "POST",
        "/window/rect",
        serde_json::json!({"width": 1280, "height": outer + 720 - height}),
    );
    driver.wait_for(
        "the canvas at the window's size",
        "return viewerStats.width === 1280 && viewerStats.height === 720",
        Duration::from_secs(20),
    );
    let canvas = driver.script("return viewerStats.sample()");
    assert_eq!(canvas["width"], 1280, "{canvas}");
    assert!(
        canvas["lit"].as_u64().unwrap() > 100 && canvas["colours"].as_u64().unwrap() > 16,
        "the canvas is blank: {canvas}"
    );
    // The page's splat of the orbit view is the server's render of it.
    let against = driver.call(
        "POST",
        "/execute/async",
        serde_json::json!({"script": "const done = arguments[arguments.length - 1];
            viewerStats.againstServer(256, 144).then(done, (error) => done({error: String(error)}));",
            "args": []}),
    );
    let psnr = against["psnr"].as_f64().unwrap_or(0.0);
    assert!(
        psnr > 35.0,
        "the page's splat against the server's render: {against}"
    );
    println!("the page's splat of the orbit view against the server's render: PSNR {psnr:.1} dB");
    if !measure {
        server_renders_without_webgl(driver, url);
    }
    if measure {
        measure_orbit_and_playback(driver);
        records_the_playing_view_as_webm(driver);
        compare_zooms_in_2d(driver);
        // Back to the orbit for the screenshot.
        driver.script(
            "const select = document.getElementById('camera'); select.value = '-1';
             select.dispatchEvent(new Event('change'));",
        );
        driver.wait_for(
            "the orbit view",
            "return viewerStats.mode === 'webgl2'",
            Duration::from_secs(10),
        );
        let png = driver.call("GET", "/screenshot", serde_json::Value::Null);
        // A narrow window wraps the controls and the cache key: no horizontal scrollbar.
        driver.call(
            "POST",
            "/window/rect",
            serde_json::json!({"width": 420, "height": 700}),
        );
        driver.wait_for(
            "the narrow layout",
            "return innerWidth <= 440 && document.documentElement.scrollWidth <= innerWidth",
            Duration::from_secs(20),
        );
        let bytes = base64_decode(png.as_str().unwrap());
        image::load_from_memory_with_format(&bytes, image::ImageFormat::Png).unwrap();
        std::fs::write(screenshot, &bytes).unwrap();
        println!("screenshot: {}", screenshot.display());
    }
    let state = driver.script("return window.viewerStats");
    assert_eq!(state["errors"], 0, "{state}");
    // Chromium's console: no error of any kind (a refused request, a missing favicon, a
    // script error) in normal use.
    let log = driver.call("POST", "/se/log", serde_json::json!({"type": "browser"}));
    let errors: Vec<&serde_json::Value> = log
        .as_array()
        .unwrap()
        .iter()
        .filter(|entry| entry["level"] == "SEVERE")
        .collect();
    assert!(errors.is_empty(), "console errors: {errors:?}");
}

/// Orbits a paused frame and plays at 1x once every frame is buffered; prints the display
/// rate of the orbit and the share of the frames due that were shown.
fn measure_orbit_and_playback(driver: &Driver) {
    let orbit = driver.call(
        "POST",
        "/execute/async",
        serde_json::json!({"script": ORBIT_SCRIPT, "args": []}),
    );
    let draws = orbit["draws"].as_f64().unwrap();
    let seconds = orbit["ms"].as_f64().unwrap() / 1e3;
    assert!(draws >= 1.0 && orbit["turned"] == true, "{orbit}");
    println!(
        "viewer orbit: {:.1} FPS at 1280x720 ({draws} frames drawn in {seconds:.2} s, {} moves)",
        draws / seconds,
        orbit["moves"]
    );
    driver.wait_for(
        "every frame buffered",
        "return viewerStats.buffered >= viewerStats.span",
        Duration::from_secs(180),
    );
    driver.script("viewerStats.reset()");
    driver.click("#play");
    std::thread::sleep(Duration::from_secs(4));
    driver.click("#play");
    let state = driver.script("return window.viewerStats");
    let (shown, playing_ms) = (
        state["playFrames"].as_f64().unwrap(),
        state["playMs"].as_f64().unwrap(),
    );
    let due = playing_ms / 1e3 * 25.0;
    // Playing moved on (where it stops may be where it started: it loops).
    assert!(shown >= 1.0, "{state}");
    let counter = driver
        .script("return [document.getElementById('counter').textContent, viewerStats.frame];");
    assert!(
        counter[0]
            .as_str()
            .unwrap()
            .starts_with(&format!("frame {} / ", counter[1])),
        "{counter}"
    );
    println!(
        "viewer playback: {:.0}% of frames shown at 1x ({shown} of {due:.0} due in {:.2} s, {} stalls)",
        100.0 * shown / due,
        playing_ms / 1e3,
        state["stalls"]
    );
    // Paused, the HUD shows no frame rate.
    let hud = driver.script("return document.getElementById('hud').textContent");
    assert!(!hud.as_str().unwrap().contains("FPS"), "{hud}");
}

/// "record" while playing saves a WebM video of the view (MediaRecorder on the canvas).
fn records_the_playing_view_as_webm(driver: &Driver) {
    driver.click("#record");
    driver.click("#play");
    std::thread::sleep(Duration::from_secs(2));
    driver.click("#play");
    driver.click("#record");
    driver.wait_for(
        "the recording saved",
        "const saved = viewerStats.saved;
         return !!saved && saved.name.endsWith('.webm') && saved.type === 'video/webm'
           && saved.bytes > 1000",
        Duration::from_secs(20),
    );
    let saved = driver.script("return viewerStats.saved");
    println!("viewer record: {saved}");
}

/// A dataset camera's compare sheet fills the stage, is labelled with the frame's PSNR and
/// the error scale, and zooms and pans in 2D without leaving compare.
fn compare_zooms_in_2d(driver: &Driver) {
    driver.script(
        "const select = document.getElementById('camera'); select.value = '0';
         select.dispatchEvent(new Event('change'));
         const compare = document.getElementById('compare');
         if (!compare.checked) compare.click();",
    );
    driver.wait_for(
        "a compare sheet or its reason",
        "return viewerStats.mode === 'server' && viewerStats.compare !== ''",
        Duration::from_secs(120),
    );
    let sheet = driver.script(
        "const box = document.getElementById('imagebox').getBoundingClientRect();
         const stage = document.getElementById('stage').getBoundingClientRect();
         return {compare: viewerStats.compare, psnr: viewerStats.psnr, width: box.width,
           height: box.height, stageWidth: stage.width, stageHeight: stage.height,
           legend: document.getElementById('legend').textContent,
           legendShown: getComputedStyle(document.getElementById('legend')).display !== 'none',
           labels: document.getElementById('panels').textContent};",
    );
    let fits = |a: &serde_json::Value, b: &serde_json::Value| {
        (a.as_f64().unwrap() - b.as_f64().unwrap()).abs() < 2.0
    };
    assert!(
        fits(&sheet["width"], &sheet["stageWidth"])
            || fits(&sheet["height"], &sheet["stageHeight"]),
        "the image does not fit the stage: {sheet}"
    );
    if sheet["compare"] == "truth|render|error" {
        assert!(sheet["legendShown"] == true, "{sheet}");
        let legend = sheet["legend"].as_str().unwrap();
        assert!(legend.contains("PSNR") && legend.contains("dB"), "{sheet}");
        let labels = sheet["labels"].as_str().unwrap();
        assert!(
            labels.contains("ground truth") && labels.contains("error"),
            "{sheet}"
        );
    }
    let zoomed = driver.script(
        "const stage = document.getElementById('stage'), box = stage.getBoundingClientRect();
         const before = document.getElementById('imagebox').getBoundingClientRect().width;
         stage.dispatchEvent(new WheelEvent('wheel', {deltaY: -500, clientX: box.left + 100,
           clientY: box.top + 100, bubbles: true, cancelable: true}));
         stage.dispatchEvent(new PointerEvent('pointerdown', {pointerId: 8, clientX: 200, clientY: 200, bubbles: true}));
         stage.dispatchEvent(new PointerEvent('pointermove', {pointerId: 8, clientX: 150, clientY: 180, bubbles: true}));
         stage.dispatchEvent(new PointerEvent('pointerup', {pointerId: 8, bubbles: true}));
         return {before, after: document.getElementById('imagebox').getBoundingClientRect().width,
           camera: document.getElementById('camera').value,
           compare: document.getElementById('compare').checked, mode: viewerStats.mode};",
    );
    assert!(
        zoomed["after"].as_f64().unwrap() > 1.5 * zoomed["before"].as_f64().unwrap(),
        "{zoomed}"
    );
    assert!(
        zoomed["camera"] == "0" && zoomed["compare"] == true && zoomed["mode"] == "server",
        "zooming left compare: {zoomed}"
    );
}

/// `/gaussians` streams the posed Gaussians eval's renderer splats, in the versioned layout
/// of `seqavatar_viewer::stream`, for drawable frame ranges only; `/ply` is the PLY file
/// `pipeline export` writes of the same frame; the favicon is served.
fn gaussian_stream_is_versioned_and_bounds_checked(
    viewer: &Viewer,
    cache: &Path,
    key: &str,
    first: usize,
) {
    use seqavatar_viewer::stream;
    let reply = get(viewer, &format!("/gaussians?frame={first}&count=3"));
    assert_eq!(reply.status, 200, "{}", reply.text());
    assert_eq!(
        reply.header("content-type"),
        Some("application/octet-stream")
    );
    assert_eq!(reply.header("x-layout-version"), Some("1"));
    assert_eq!(&reply.body[..4], b"SAGS");
    assert_eq!(reply.body[4..8], stream::LAYOUT_VERSION.to_le_bytes());
    let records = stream::decode(&reply.body).unwrap();
    let frames: Vec<usize> = records.iter().map(|record| record.frame).collect();
    assert_eq!(frames, vec![first, first + 1, first + 2]);
    // The Gaussians the server's render splats: eval's renderer's, within the quantisation.
    let (mut renderer, _) = eval_renderer(cache, key);
    let world = renderer.deform(first + 1).unwrap();
    let record = &records[1];
    let n = world.opacities.len();
    assert!(n > 10, "{n} Gaussians");
    assert_eq!(record.positions.len(), n);
    assert_eq!(reply.body.len(), 3 * stream::record_bytes(n));
    for (index, position) in record.positions.iter().enumerate() {
        for axis in 0..3 {
            let expected = world.means[3 * index + axis];
            assert!(
                (f64::from(position[axis]) - expected).abs() < 1e-5,
                "Gaussian {index}: {position:?}"
            );
        }
        let opacity = world.opacities[index] as f32;
        assert!((record.colours[index][3] - opacity).abs() <= 0.5 / 255.0 + 1e-6);
    }
    // Frame ranges inside the drawable frames only, named in the 400.
    let last = 9;
    for (target, needle) in [
        (
            "/gaussians".to_owned(),
            "missing parameter `frame`".to_owned(),
        ),
        (
            format!("/gaussians?frame={}", last + 1),
            format!("`frame` {} is out of range", last + 1),
        ),
        (
            format!("/gaussians?frame={last}&count=2"),
            format!(
                "frames {last}..={} reach past the last frame {last}",
                last + 1
            ),
        ),
        (
            format!("/gaussians?frame={first}&count=0"),
            "`count` 0 is out of range 1..=8".to_owned(),
        ),
        (
            format!("/gaussians?frame={first}&count=9"),
            "`count` 9 is out of range".to_owned(),
        ),
        (
            format!("/gaussians?frame={first}&camera=0"),
            "unknown parameter `camera`".to_owned(),
        ),
        (
            format!("/gaussians?frame={first}&context=from:99"),
            "offset 99 is out of range".to_owned(),
        ),
        (
            format!("/ply?frame={first}&count=2"),
            "a PLY file holds one frame".to_owned(),
        ),
    ] {
        let reply = get(viewer, &target);
        assert_eq!(reply.status, 400, "{target}: {}", reply.text());
        assert!(reply.text().contains(&needle), "{target}: {}", reply.text());
    }
    if first > 0 {
        let reply = get(viewer, &format!("/gaussians?frame={}", first - 1));
        assert_eq!(reply.status, 400, "{}", reply.text());
    }
    // Under a context probe too.
    let zeroed = get(viewer, &format!("/gaussians?frame={first}&context=zeroed"));
    assert_eq!(zeroed.status, 200, "{}", zeroed.text());
    assert_eq!(stream::decode(&zeroed.body).unwrap()[0].positions.len(), n);
    // The PLY file of a frame: `pipeline export`'s writer, read back by its reader.
    let ply = get(viewer, &format!("/ply?frame={first}"));
    assert_eq!(ply.status, 200, "{}", ply.text());
    assert!(
        ply.header("content-disposition")
            .is_some_and(|value| value.contains(&format!("frame_{first:05}.ply"))),
        "{:?}",
        ply.headers
    );
    let cloud = seqavatar_avatar::ply::read_ply(&ply.body).unwrap();
    assert_eq!(cloud.len(), n);
    let favicon = get(viewer, "/favicon.ico");
    assert_eq!(favicon.status, 200);
    assert_eq!(favicon.header("content-type"), Some("image/svg+xml"));
}

/// A stopped server: the page pauses, says so and retries with back-off; once a server
/// listens again it goes on streaming.
fn the_page_pauses_while_the_server_is_down(cache: &Path, key: &str) {
    let Some(browser) = open_browser() else {
        return;
    };
    let driver = &browser.driver;
    let viewer = start(cache, key, 256);
    let port = viewer.address().port();
    driver.call("POST", "/url", serde_json::json!({"url": viewer.url()}));
    driver.wait_for(
        "the first frame",
        "return !!window.viewerStats && viewerStats.frame >= 0",
        Duration::from_secs(120),
    );
    driver.click("#play");
    drop(viewer);
    driver.wait_for(
        "the page to notice the stopped server",
        "return document.getElementById('message').textContent.startsWith('server stopped') \
         && document.getElementById('play').textContent === 'Play'",
        Duration::from_secs(60),
    );
    let _again = Viewer::start(ViewerOptions {
        cache: cache.to_owned(),
        avatar: key.to_owned(),
        poses: None,
        backend: cpu(),
        host: "127.0.0.1".to_owned(),
        port,
        max_size: 256,
    })
    .unwrap();
    driver.wait_for(
        "the page to reconnect",
        "return !document.getElementById('message').textContent.startsWith('server stopped')",
        Duration::from_secs(60),
    );
    // A context probe needs new Gaussians from the new server.
    let received = driver
        .script("return viewerStats.received")
        .as_u64()
        .unwrap();
    driver.script(
        "const context = document.getElementById('context'); context.value = 'zeroed';
         context.dispatchEvent(new Event('change'));",
    );
    driver.wait_for(
        "frames from the new server",
        &format!("return viewerStats.received > {received} && viewerStats.errors === 0"),
        Duration::from_secs(120),
    );
}

/// The fallback for browsers without WebGL2 (`?renderer=server` forces it): the server's
/// JPEG renders of the orbit view, fitted to the stage.
fn server_renders_without_webgl(driver: &Driver, url: &str) {
    driver.open(url, "renderer=server");
    driver.wait_for(
        "a frame rendered by the server",
        "return !!window.viewerStats && viewerStats.mode === 'server' && viewerStats.frame >= 0 \
         && viewerStats.size !== ''",
        Duration::from_secs(120),
    );
    let canvas = driver.script(
        "const c = document.getElementById('view');
         const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
         let lit = 0;
         for (let i = 0; i < d.length; i += 4) if (Math.max(d[i], d[i + 1], d[i + 2]) > 24) lit++;
         return {width: c.width, height: c.height, lit, shown: document.getElementById('imagebox')
           .getBoundingClientRect().height};",
    );
    assert!(
        canvas["lit"].as_u64().unwrap() > 20 && canvas["shown"].as_f64().unwrap() > 100.0,
        "the server's render is blank or not fitted: {canvas}"
    );
}
