//! `pipeline view`: a local web viewer of a trained avatar. One self-contained page (inline
//! script and style, nothing fetched from elsewhere) asks the server over plain HTTP GET
//! for each frame's posed Gaussians, which the server computes with eval's public rendering
//! API (networks, pose refiner, skinning: what eval's renders splat) on a dedicated render
//! thread, and splats them itself with a small WebGL2 renderer, so orbiting runs at the
//! display's rate and playback from frames buffered ahead. Compare mode (exact pixels:
//! ground truth | render | error) and pages without WebGL2 get JPEG images the server renders.
//!
//! Routes: `GET /` (the page), `GET /info` (the scene: frames, cameras, the orbit's frame and
//! home view, the splatting constants, limits, as JSON), `GET /gaussians?frame=F&count=K`
//! (the posed Gaussians of frames `F..F+K`, binary, see [`stream`]), `GET /frame?...` (one
//! image, see [`request`]), `GET /ply?frame=F` (frame `F`'s Gaussians as the 3DGS PLY file
//! `pipeline export` writes), `GET /favicon.ico`; anything else is 404.
//! The page's own query (`/?size=256&speed=4&camera=1&compare=1&play=1`) sets its controls'
//! starting state. A compared frame's reply carries its PSNR in `x-compare-psnr` and the
//! garment region's in `x-compare-garment-psnr` (`n/a` without a region, `empty`).
//! Plain HTTP requests rather than a WebSocket: each frame is one cacheable-free GET whose
//! status says what happened (200, 400 with a message, 409 superseded, 503 busy), the page
//! keeps at most two requests in flight, and there is no connection state to validate.
//!
//! Safety: the server binds to 127.0.0.1 unless told otherwise, serves only the page, the
//! scene description and renders (no request reaches the file system), validates every
//! parameter, and, when bound to a loopback address, answers only requests whose `Host` is a
//! loopback name (a web page elsewhere cannot reach it through DNS rebinding). Bound beyond
//! loopback, it answers only requests that carry the access token drawn when it started (as
//! a notebook server does): in the query (`?token=...`, on any route) or in the cookie the
//! page's first load with the token sets, so the page's own fetches carry it; anything else
//! is 403. On loopback no token is asked for: the address and the Host check guard it.

pub mod orbit;
pub mod render;
pub mod request;
pub mod scene;
pub mod stream;

use std::net::{IpAddr, SocketAddr, TcpListener};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::thread::JoinHandle;

use anyhow::Context as _;
use axum::Router;
use axum::extract::{Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use seqavatar_compute::backend::Backend;
use seqavatar_engine::{Pipeline, Registry, open_store};
use seqavatar_evaluation::animate::PoseSource;
use seqavatar_evaluation::report::format_metric;
use tokio::sync::oneshot;

use crate::render::{Answer, GaussianFormat, JobError, Scheduler, Work};
use crate::request::{Limits, MIN_SIDE, parse_frame_request, parse_gaussians_request};
use crate::scene::Scene;

/// The page: one HTML file with its script and style inline.
pub const PAGE: &str = include_str!("page.html");
/// The icon browsers ask for (a splat on the page's dark background).
pub const FAVICON: &str = "<svg xmlns=\"http://www.w3.org/2000/svg\" viewBox=\"0 0 16 16\">\
<rect width=\"16\" height=\"16\" rx=\"3\" fill=\"#111318\"/>\
<ellipse cx=\"8\" cy=\"8\" rx=\"3.5\" ry=\"6\" transform=\"rotate(25 8 8)\" fill=\"#5fb3ff\"/></svg>";

/// The default `--max-size`: the largest image side rendered.
pub const DEFAULT_MAX_SIZE: u32 = 1024;
/// The largest `--max-size`: an 8192 x 8192 render is about 1 GiB of f64 colour.
pub const LARGEST_MAX_SIZE: u32 = 8192;

/// What `pipeline view` serves and where.
#[derive(Clone, Debug)]
pub struct ViewerOptions {
    pub cache: PathBuf,
    /// The train entry: its cache folder, its key or a unique key prefix.
    pub avatar: String,
    /// Drive the avatar with these poses instead of its trained sequence's.
    pub poses: Option<PoseSource>,
    pub backend: Backend,
    /// Address to bind (`127.0.0.1` unless the user asks otherwise).
    pub host: String,
    /// Port; 0 picks a free one.
    pub port: u16,
    /// The largest image side the page may ask for.
    pub max_size: u32,
}

/// The key of the entry of train stage `stage` of the pipeline `file` (with `sets`), which
/// must be in the cache: `pipeline view FILE.yaml:STAGE`.
pub fn train_key_of_stage(
    registry: &Registry,
    file: &Path,
    stage: &str,
    sets: &[String],
    cache: &Path,
) -> anyhow::Result<String> {
    let pipeline = Pipeline::load(file, registry, sets)?;
    let spec = pipeline.stage(stage).ok_or_else(|| {
        anyhow::anyhow!(
            "{}: no stage named \"{stage}\" (stages: {})",
            file.display(),
            pipeline.stage_names().join(", ")
        )
    })?;
    anyhow::ensure!(
        spec.kind == "train",
        "{}: stage \"{stage}\" is a {} stage; `pipeline view` shows the avatar of a train stage",
        file.display(),
        spec.kind
    );
    let store = open_store(cache)?;
    let keys = seqavatar_engine::compute_keys(&pipeline, registry, store.as_ref())?;
    let key = keys[&spec.name].key.clone();
    let id = seqavatar_engine::EntryId::new("train", &key);
    anyhow::ensure!(
        store.entry_state(&id)? == seqavatar_engine::EntryState::Complete,
        "stage \"{stage}\" ({id}) is not in the cache at {}; run `pipeline run {}` first",
        cache.display(),
        file.display()
    );
    Ok(key)
}

/// Splits `FILE.yaml:STAGE` (or `.yml`); `None` when `target` has no such form.
pub fn split_pipeline_target(target: &str) -> Option<(&Path, &str)> {
    [".yaml:", ".yml:"].iter().find_map(|suffix| {
        target.find(suffix).map(|at| {
            let colon = at + suffix.len() - 1;
            (Path::new(&target[..colon]), &target[colon + 1..])
        })
    })
}

struct AppState {
    scheduler: Arc<Scheduler>,
    limits: Limits,
    info: String,
    /// `Some`: the server is bound to a loopback address and answers only these hosts.
    allowed_hosts: Option<Vec<String>>,
    /// `Some`: the server is bound beyond loopback and answers only requests with the token.
    access: Option<Access>,
}

/// The access token of a server bound beyond loopback, and the cookie that carries it.
#[derive(Clone)]
struct Access {
    token: String,
    /// Named after the port: cookies are per host, not per port, so viewers side by side on
    /// one machine must not overwrite each other's.
    cookie: String,
}

impl Access {
    /// A fresh token: 24 bytes of the kernel's random source, as hex.
    fn draw(port: u16) -> anyhow::Result<Self> {
        use std::io::Read as _;
        let mut bytes = [0u8; 24];
        std::fs::File::open("/dev/urandom")
            .and_then(|mut source| source.read_exact(&mut bytes))
            .context("cannot draw the viewer's access token from /dev/urandom")?;
        Ok(Self {
            token: bytes.iter().map(|byte| format!("{byte:02x}")).collect(),
            cookie: format!("seqavatar-view-{port}"),
        })
    }

    /// Whether `given` is the token; compares every byte, so the time taken says nothing
    /// about how much of a guess was right.
    fn accepts(&self, given: &str) -> bool {
        given.len() == self.token.len()
            && given
                .bytes()
                .zip(self.token.bytes())
                .fold(0u8, |difference, (a, b)| difference | (a ^ b))
                == 0
    }

    /// The token the request carries: its `token` query parameter, else its cookie.
    fn presented<'a>(
        &self,
        query: &'a [(String, String)],
        headers: &'a HeaderMap,
    ) -> Option<&'a str> {
        let in_query = query
            .iter()
            .find(|(key, _)| key == "token")
            .map(|(_, value)| value.as_str());
        in_query.or_else(|| {
            headers
                .get_all(header::COOKIE)
                .iter()
                .filter_map(|value| value.to_str().ok())
                .flat_map(|value| value.split(';'))
                .filter_map(|pair| pair.trim().split_once('='))
                .find(|(name, _)| *name == self.cookie)
                .map(|(_, value)| value)
        })
    }
}

/// A running viewer: the render thread and the HTTP server. Dropping it stops both.
pub struct Viewer {
    address: SocketAddr,
    /// The access token, when bound beyond loopback.
    token: Option<String>,
    scheduler: Arc<Scheduler>,
    shutdown: Option<oneshot::Sender<()>>,
    server: Option<JoinHandle<std::io::Result<()>>>,
    renderer: Option<JoinHandle<()>>,
}

impl Viewer {
    /// Opens the avatar (on the render thread), binds `host:port` and serves; returns once
    /// the server accepts connections.
    pub fn start(options: ViewerOptions) -> anyhow::Result<Self> {
        anyhow::ensure!(
            (MIN_SIDE..=LARGEST_MAX_SIZE).contains(&options.max_size),
            "--max-size {} must be in {MIN_SIDE}..={LARGEST_MAX_SIZE}",
            options.max_size
        );
        // One request is rendered at a time; with its comparison sheet (ground truth, the
        // prepared pair, the error map and the sheet) it holds less than two frames' bytes.
        seqavatar_engine::check_memory_budget(
            &format!(
                "--max-size {0}: frames of up to {0} x {0} pixels, one rendered at a time with \
                 its comparison sheet,",
                options.max_size
            ),
            seqavatar_evaluation::avatar_render::frames_memory_bytes(
                2,
                options.max_size,
                options.max_size,
            ),
            seqavatar_engine::memory_budget_bytes().map_err(anyhow::Error::msg)?,
            "lower --max-size",
        )
        .map_err(anyhow::Error::msg)?;
        let scheduler = Arc::new(Scheduler::default());
        let (ready_tx, ready_rx) = std::sync::mpsc::channel::<anyhow::Result<(Limits, String)>>();
        let renderer = {
            let scheduler = scheduler.clone();
            let options = options.clone();
            std::thread::Builder::new()
                .name("viewer-render".to_owned())
                .spawn(move || {
                    let opened = open_store(&options.cache).and_then(|store| {
                        Scene::open(
                            store.as_ref(),
                            &options.avatar,
                            options.poses.as_ref(),
                            &options.backend,
                        )
                    });
                    let mut scene = match opened {
                        Ok(scene) => scene,
                        Err(error) => {
                            let _ = ready_tx.send(Err(error));
                            return;
                        }
                    };
                    let limits = Limits {
                        first_frame: scene.renderer.first_frame(),
                        num_frames: scene.renderer.num_frames(),
                        num_cameras: scene.cameras.len(),
                        max_side: options.max_size,
                    };
                    let info = info_json(&scene, &limits, &options.backend);
                    if ready_tx.send(Ok((limits, info))).is_ok() {
                        render::render_loop(&mut scene, &scheduler);
                    }
                })
                .context("cannot start the render thread")?
        };
        let (limits, info) = match ready_rx.recv() {
            Ok(result) => result?,
            Err(_) => {
                let _ = renderer.join();
                anyhow::bail!("the render thread stopped while opening the avatar");
            }
        };
        let listener = match TcpListener::bind((options.host.as_str(), options.port)) {
            Ok(listener) => listener,
            Err(error) => {
                scheduler.close();
                let _ = renderer.join();
                return Err(error).with_context(|| {
                    format!("cannot listen on {}:{}", options.host, options.port)
                });
            }
        };
        listener.set_nonblocking(true)?;
        let address = listener.local_addr()?;
        let allowed_hosts = address.ip().is_loopback().then(|| loopback_hosts(address));
        let access = if address.ip().is_loopback() {
            None
        } else {
            match Access::draw(address.port()) {
                Ok(access) => Some(access),
                Err(error) => {
                    scheduler.close();
                    let _ = renderer.join();
                    return Err(error);
                }
            }
        };
        let token = access.as_ref().map(|access| access.token.clone());
        let state = Arc::new(AppState {
            scheduler: scheduler.clone(),
            limits,
            info,
            allowed_hosts,
            access,
        });
        let app = Router::new()
            .route("/", get(page))
            .route("/info", get(info_route))
            .route("/frame", get(frame))
            .route("/gaussians", get(gaussians::<false>))
            .route("/ply", get(gaussians::<true>))
            .route("/favicon.ico", get(favicon))
            .fallback(not_found)
            .with_state(state);
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("viewer-http")
            .enable_io()
            .build()
            .context("cannot start the HTTP runtime")?;
        let (shutdown, stopped) = oneshot::channel::<()>();
        let server = std::thread::Builder::new()
            .name("viewer-server".to_owned())
            .spawn(move || {
                runtime.block_on(async move {
                    let listener = tokio::net::TcpListener::from_std(listener)?;
                    axum::serve(listener, app)
                        .with_graceful_shutdown(async move {
                            let _ = stopped.await;
                        })
                        .await
                })
            })
            .context("cannot start the server thread")?;
        Ok(Self {
            address,
            token,
            scheduler,
            shutdown: Some(shutdown),
            server: Some(server),
            renderer: Some(renderer),
        })
    }

    /// The address the server listens on.
    pub fn address(&self) -> SocketAddr {
        self.address
    }

    /// The page's URL, with the access token where one is needed. Bound to every interface
    /// (`0.0.0.0`, `::`), it names this machine by its host name, which others can reach
    /// (127.0.0.1 would send them to their own machine).
    pub fn url(&self) -> String {
        let ip = self.address.ip();
        let host = match ip {
            _ if ip.is_unspecified() => this_host_name(),
            IpAddr::V6(ip) => format!("[{ip}]"),
            IpAddr::V4(ip) => ip.to_string(),
        };
        let query = match &self.token {
            Some(token) => format!("?token={token}"),
            None => String::new(),
        };
        format!("http://{host}:{}/{query}", self.address.port())
    }

    /// Serves until the server stops (an I/O error of the listener); `pipeline view` runs
    /// until interrupted.
    pub fn wait(mut self) -> anyhow::Result<()> {
        let result = match self.server.take() {
            Some(server) => server
                .join()
                .map_err(|_| anyhow::anyhow!("the viewer's server thread panicked"))?
                .context("the viewer's server stopped"),
            None => Ok(()),
        };
        self.stop();
        result
    }

    fn stop(&mut self) {
        if let Some(shutdown) = self.shutdown.take() {
            let _ = shutdown.send(());
        }
        if let Some(server) = self.server.take() {
            let _ = server.join();
        }
        self.scheduler.close();
        if let Some(renderer) = self.renderer.take() {
            let _ = renderer.join();
        }
    }
}

impl Drop for Viewer {
    fn drop(&mut self) {
        self.stop();
    }
}

/// This machine's host name (Linux's, from /proc), or `localhost` where it cannot be read.
fn this_host_name() -> String {
    std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .map(|name| name.trim().to_owned())
        .filter(|name| !name.is_empty() && name.bytes().all(|b| b.is_ascii_graphic()))
        .unwrap_or_else(|| "localhost".to_owned())
}

/// The `Host` values a loopback-bound server answers.
fn loopback_hosts(address: SocketAddr) -> Vec<String> {
    let port = address.port();
    vec![
        format!("127.0.0.1:{port}"),
        format!("localhost:{port}"),
        format!("[::1]:{port}"),
        address.to_string(),
    ]
}

fn info_json(scene: &Scene, limits: &Limits, backend: &Backend) -> String {
    use seqavatar_compute::splat;
    let cameras: Vec<serde_json::Value> = scene
        .cameras
        .iter()
        .map(|camera| {
            // Where the camera sits in the orbit frame: the page orbits on from there.
            let (azimuth, elevation, distance) = scene.orbit.angles_of(camera.center());
            let limit = request::MAX_ELEVATION_DEG;
            serde_json::json!({
                "width": camera.width,
                "height": camera.height,
                "az": orbit::wrap_degrees(azimuth),
                "el": elevation.clamp(-limit, limit),
                "dist": distance.clamp(request::DISTANCE_RANGE.0, request::DISTANCE_RANGE.1),
                "fov": orbit::vertical_fov_deg(camera)
                    .clamp(request::FOV_RANGE_DEG.0, request::FOV_RANGE_DEG.1),
            })
        })
        .collect();
    let [azimuth, elevation, distance, fov] = scene.home;
    let vector = |v: seqavatar_core::glam::DVec3| [v.x, v.y, v.z];
    serde_json::json!({
        "avatar": scene.avatar,
        "poses": scene.poses,
        "device": backend.describe(),
        "first_frame": limits.first_frame,
        "num_frames": limits.num_frames,
        "cameras": cameras,
        "max_size": limits.max_side,
        "min_size": MIN_SIDE,
        "ground_truth": scene.truth.is_some(),
        "context_probes": scene.context_probes,
        "home": {"az": azimuth, "el": elevation, "dist": distance, "fov": fov},
        // The frame the orbit angles are measured in (`orbit::OrbitFrame`), for the page's
        // own camera; its centre is the pivot of the first drawable frame.
        "orbit": {
            "centre": vector(scene.orbit.centre),
            "up": vector(scene.orbit.up),
            "reference": vector(scene.orbit.reference),
        },
        "background": scene.renderer.avatar.background,
        "error_full_scale": render::ERROR_FULL_SCALE,
        // What the page's splatting does as the server's does.
        "splat": {
            "blur_variance": splat::BLUR_VARIANCE,
            "near_plane": splat::NEAR_PLANE,
            "alpha_threshold": splat::ALPHA_THRESHOLD,
            "max_alpha": splat::MAX_ALPHA,
            "max_extent_sigmas": splat::MAX_EXTENT_SIGMAS,
            "sh_c1": splat::sh::SH_C1,
        },
        "stream": {
            "layout_version": stream::LAYOUT_VERSION,
            "max_frames": request::MAX_STREAM_FRAMES,
        },
        "limits": {
            "max_elevation": request::MAX_ELEVATION_DEG,
            "distance": [request::DISTANCE_RANGE.0, request::DISTANCE_RANGE.1],
            "fov": [request::FOV_RANGE_DEG.0, request::FOV_RANGE_DEG.1],
            "pan": request::MAX_PAN,
        },
    })
    .to_string()
}

fn text(status: StatusCode, message: impl Into<String>) -> Response {
    let mut response = (status, format!("{}\n", message.into())).into_response();
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/plain; charset=utf-8"),
    );
    response
}

/// Common headers: no caching, no content sniffing, nothing loaded from elsewhere.
fn secured(mut response: Response) -> Response {
    let headers = response.headers_mut();
    headers.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-store"));
    headers.insert(
        header::X_CONTENT_TYPE_OPTIONS,
        HeaderValue::from_static("nosniff"),
    );
    headers.insert(
        header::CONTENT_SECURITY_POLICY,
        HeaderValue::from_static(
            "default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; \
             img-src 'self' blob:; connect-src 'self'; base-uri 'none'; form-action 'none'",
        ),
    );
    response
}

/// The answer to a request the server refuses: 403 without the access token (bound beyond
/// loopback), 421 under another host name (bound to loopback).
fn refused(state: &AppState, query: &[(String, String)], headers: &HeaderMap) -> Option<Response> {
    if let Some(access) = &state.access {
        return match access.presented(query, headers) {
            Some(token) if access.accepts(token) => None,
            _ => Some(secured(text(
                StatusCode::FORBIDDEN,
                "this viewer needs its access token: open the URL `pipeline view` printed \
                 (it ends in ?token=...)",
            ))),
        };
    }
    let allowed = state.allowed_hosts.as_ref()?;
    let host = headers
        .get(header::HOST)
        .and_then(|value| value.to_str().ok())
        .unwrap_or("");
    if allowed.iter().any(|name| name.eq_ignore_ascii_case(host)) {
        None
    } else {
        Some(secured(text(
            StatusCode::MISDIRECTED_REQUEST,
            "this viewer listens on a loopback address and answers only Host 127.0.0.1, localhost or [::1] with its port",
        )))
    }
}

/// The query's pairs; a malformed query carries no token (and `/frame` says what is wrong).
type QueryPairs = Result<Query<Vec<(String, String)>>, axum::extract::rejection::QueryRejection>;

fn pairs_of(query: &QueryPairs) -> &[(String, String)] {
    query.as_ref().map_or(&[], |Query(pairs)| pairs.as_slice())
}

async fn page(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    query: QueryPairs,
) -> Response {
    if let Some(response) = refused(&state, pairs_of(&query), &headers) {
        return response;
    }
    let mut response = PAGE.into_response();
    let response_headers = response.headers_mut();
    response_headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/html; charset=utf-8"),
    );
    if let Some(access) = &state.access {
        // The page's fetches of /info and /frame carry the token in this cookie; HttpOnly:
        // no script reads it; Strict: no other site's page sends it.
        let cookie = format!(
            "{}={}; Path=/; HttpOnly; SameSite=Strict",
            access.cookie, access.token
        );
        if let Ok(cookie) = HeaderValue::from_str(&cookie) {
            response_headers.insert(header::SET_COOKIE, cookie);
        }
    }
    secured(response)
}

async fn info_route(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    query: QueryPairs,
) -> Response {
    if let Some(response) = refused(&state, pairs_of(&query), &headers) {
        return response;
    }
    let mut response = state.info.clone().into_response();
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    secured(response)
}

async fn frame(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    query: QueryPairs,
) -> Response {
    if let Some(response) = refused(&state, pairs_of(&query), &headers) {
        return response;
    }
    let pairs = match parameters(query) {
        Ok(pairs) => pairs,
        Err(message) => return secured(text(StatusCode::BAD_REQUEST, message)),
    };
    let request = match parse_frame_request(&pairs, &state.limits) {
        Ok(request) => request,
        Err(message) => return secured(text(StatusCode::BAD_REQUEST, message)),
    };
    let frame_index = request.frame;
    let answer = state.scheduler.submit(Work::Image(request)).await;
    let response = match answer {
        Ok(Ok(Answer::Gaussians(_))) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the render thread answered Gaussians to an image request",
        ),
        Ok(Ok(Answer::Image(rendered))) => {
            let mut response = rendered.jpeg.into_response();
            let headers = response.headers_mut();
            headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/jpeg"));
            let mut put = |name: &'static str, value: String| {
                if let Ok(value) = HeaderValue::from_str(&value) {
                    headers.insert(name, value);
                }
            };
            put("x-frame", frame_index.to_string());
            put(
                "x-render-ms",
                format!("{:.1}", rendered.render_seconds * 1e3),
            );
            put(
                "x-image-size",
                format!("{}x{}", rendered.width, rendered.height),
            );
            match rendered.compare {
                Some(Ok(psnr)) => {
                    put("x-compare", "truth|render|error".to_owned());
                    put("x-compare-psnr", format_metric(Some(psnr.whole), 2));
                    // "n/a": the entry has no garment region; "empty": none in this image.
                    put(
                        "x-compare-garment-psnr",
                        match psnr.garment {
                            None => "n/a".to_owned(),
                            Some(None) => "empty".to_owned(),
                            Some(value) => format_metric(value, 2),
                        },
                    );
                }
                Some(Err(why)) => put("x-compare", format!("unavailable: {why}")),
                None => {}
            }
            response
        }
        Ok(Err(error)) => refusal(error),
        Err(_) => refusal(JobError::Closed),
    };
    secured(response)
}

/// The answer to a job the render thread did not do.
fn refusal(error: JobError) -> Response {
    match error {
        JobError::Superseded => text(
            StatusCode::CONFLICT,
            "superseded by a newer request of the same tab",
        ),
        JobError::Busy => text(
            StatusCode::SERVICE_UNAVAILABLE,
            "too many tabs are waiting for a render; try again",
        ),
        JobError::BadRequest(message) => text(StatusCode::BAD_REQUEST, message),
        JobError::Failed(message) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("render failed: {message}"),
        ),
        JobError::Closed => text(
            StatusCode::SERVICE_UNAVAILABLE,
            "the viewer is shutting down",
        ),
    }
}

/// The query's pairs without the token (the server's, not a parameter), or what is wrong
/// with a malformed query.
fn parameters(query: QueryPairs) -> Result<Vec<(String, String)>, String> {
    match query {
        Ok(Query(pairs)) => Ok(pairs
            .into_iter()
            .filter(|(key, _)| key != "token")
            .collect()),
        Err(rejection) => Err(format!("malformed query: {}", rejection.body_text())),
    }
}

/// `/gaussians` (`PLY` false: the records of [`stream`]) and `/ply` (`PLY` true: the frame's
/// Gaussians as the PLY file `pipeline export` writes).
async fn gaussians<const PLY: bool>(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    query: QueryPairs,
) -> Response {
    let format = if PLY {
        GaussianFormat::Ply
    } else {
        GaussianFormat::Stream
    };
    posed_gaussians(&state, &headers, query, format).await
}

async fn posed_gaussians(
    state: &AppState,
    headers: &HeaderMap,
    query: QueryPairs,
    format: GaussianFormat,
) -> Response {
    if let Some(response) = refused(state, pairs_of(&query), headers) {
        return response;
    }
    let pairs = match parameters(query) {
        Ok(pairs) => pairs,
        Err(message) => return secured(text(StatusCode::BAD_REQUEST, message)),
    };
    let request = match parse_gaussians_request(&pairs, &state.limits) {
        Ok(request) if format == GaussianFormat::Ply && request.count != 1 => {
            return secured(text(
                StatusCode::BAD_REQUEST,
                "a PLY file holds one frame: `count` must be 1",
            ));
        }
        Ok(request) => request,
        Err(message) => return secured(text(StatusCode::BAD_REQUEST, message)),
    };
    let frame = request.frame;
    let response = match state
        .scheduler
        .submit(Work::Gaussians(request, format))
        .await
    {
        Ok(Ok(Answer::Gaussians(bytes))) => {
            let mut response = bytes.into_response();
            let headers = response.headers_mut();
            headers.insert(
                header::CONTENT_TYPE,
                HeaderValue::from_static("application/octet-stream"),
            );
            let mut put = |name: header::HeaderName, value: String| {
                if let Ok(value) = HeaderValue::from_str(&value) {
                    headers.insert(name, value);
                }
            };
            match format {
                GaussianFormat::Stream => put(
                    header::HeaderName::from_static("x-layout-version"),
                    stream::LAYOUT_VERSION.to_string(),
                ),
                GaussianFormat::Ply => put(
                    header::CONTENT_DISPOSITION,
                    format!("attachment; filename=\"frame_{frame:05}.ply\""),
                ),
            }
            response
        }
        Ok(Ok(Answer::Image(_))) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            "the render thread answered an image to a Gaussians request",
        ),
        Ok(Err(error)) => refusal(error),
        Err(_) => refusal(JobError::Closed),
    };
    secured(response)
}

async fn favicon() -> Response {
    let mut response = FAVICON.into_response();
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("image/svg+xml"),
    );
    secured(response)
}

async fn not_found() -> Response {
    secured(text(
        StatusCode::NOT_FOUND,
        "not found: this viewer serves /, /info, /gaussians, /frame and /ply",
    ))
}
