//! `pipeline view`: a local web viewer of a trained avatar. One self-contained page (inline
//! script and style, nothing fetched from elsewhere) asks the server for frames over plain
//! HTTP GET; the server renders them with eval's public rendering API (networks, pose
//! refiner, skinning, splatting: the renders eval scores) on a dedicated render thread and
//! answers JPEG images.
//!
//! Routes: `GET /` (the page), `GET /info` (the scene: frames, cameras, the orbit's home view,
//! limits, as JSON), `GET /frame?...` (one image, see [`request`]); anything else is 404.
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
//! loopback name (a web page elsewhere cannot reach it through DNS rebinding).

pub mod orbit;
pub mod render;
pub mod request;
pub mod scene;

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

use crate::render::{JobError, Scheduler};
use crate::request::{Limits, MIN_SIDE, parse_frame_request};
use crate::scene::Scene;

/// The page: one HTML file with its script and style inline.
pub const PAGE: &str = include_str!("page.html");

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
        "stage \"{stage}\" ({id}) is not in the cache {}; run `pipeline run {}` first",
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
}

/// A running viewer: the render thread and the HTTP server. Dropping it stops both.
pub struct Viewer {
    address: SocketAddr,
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
        let state = Arc::new(AppState {
            scheduler: scheduler.clone(),
            limits,
            info,
            allowed_hosts,
        });
        let app = Router::new()
            .route("/", get(page))
            .route("/info", get(info_route))
            .route("/frame", get(frame))
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

    /// The page's URL.
    pub fn url(&self) -> String {
        let host = match self.address.ip() {
            IpAddr::V6(ip) => format!("[{ip}]"),
            IpAddr::V4(ip) if ip.is_unspecified() => "127.0.0.1".to_owned(),
            IpAddr::V4(ip) => ip.to_string(),
        };
        format!("http://{host}:{}/", self.address.port())
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

/// The 421 answer when a loopback-bound server is reached under another host name.
fn wrong_host(state: &AppState, headers: &HeaderMap) -> Option<Response> {
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

async fn page(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    if let Some(response) = wrong_host(&state, &headers) {
        return response;
    }
    let mut response = PAGE.into_response();
    response.headers_mut().insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("text/html; charset=utf-8"),
    );
    secured(response)
}

async fn info_route(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    if let Some(response) = wrong_host(&state, &headers) {
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
    query: Result<Query<Vec<(String, String)>>, axum::extract::rejection::QueryRejection>,
) -> Response {
    if let Some(response) = wrong_host(&state, &headers) {
        return response;
    }
    let pairs = match query {
        Ok(Query(pairs)) => pairs,
        Err(rejection) => {
            return secured(text(
                StatusCode::BAD_REQUEST,
                format!("malformed query: {}", rejection.body_text()),
            ));
        }
    };
    let request = match parse_frame_request(&pairs, &state.limits) {
        Ok(request) => request,
        Err(message) => return secured(text(StatusCode::BAD_REQUEST, message)),
    };
    let frame_index = request.frame;
    let answer = state.scheduler.submit(request).await;
    let response = match answer {
        Ok(Ok(rendered)) => {
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
        Ok(Err(JobError::Superseded)) => text(
            StatusCode::CONFLICT,
            "superseded by a newer request of the same tab",
        ),
        Ok(Err(JobError::Busy)) => text(
            StatusCode::SERVICE_UNAVAILABLE,
            "too many tabs are waiting for a render; try again",
        ),
        Ok(Err(JobError::BadRequest(message))) => text(StatusCode::BAD_REQUEST, message),
        Ok(Err(JobError::Failed(message))) => text(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("render failed: {message}"),
        ),
        Ok(Err(JobError::Closed)) | Err(_) => text(
            StatusCode::SERVICE_UNAVAILABLE,
            "the viewer is shutting down",
        ),
    };
    secured(response)
}

async fn not_found() -> Response {
    secured(text(
        StatusCode::NOT_FOUND,
        "not found: this viewer serves /, /info and /frame",
    ))
}
