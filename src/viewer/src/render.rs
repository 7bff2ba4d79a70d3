//! The render thread and its queue. Rendering is CPU- or GPU-bound and blocking, so one
//! dedicated thread owns the avatar and serves one request at a time (an image, or the
//! posed Gaussians of a few frames for the page's own renderer); the HTTP tasks only
//! queue requests and await the answers. The queue holds at most one pending request per
//! browser tab, "newest wins": a newer request of a tab replaces its pending one, which is
//! answered [`JobError::Superseded`] (HTTP 409) at once. Tabs are served first come, first
//! served, so several tabs share the renderer fairly, and the queue is bounded by
//! [`MAX_PENDING_TABS`] (beyond it: [`JobError::Busy`], HTTP 503).

use std::collections::VecDeque;
use std::io::Cursor;
use std::sync::{Condvar, Mutex};
use std::time::Instant;

use image::RgbImage;
use seqavatar_compute::image::ImageF32;
use seqavatar_evaluation::context_probe::ContextProbe;
use seqavatar_evaluation::evaluate::ViewRenderer;
use seqavatar_evaluation::metrics::{Mask, Protocol};
use seqavatar_evaluation::region::region_psnr;
use tokio::sync::oneshot;

use crate::request::{FrameRequest, GaussiansRequest, View};
use crate::scene::Scene;

/// The most tabs with a pending request; more are answered busy.
pub const MAX_PENDING_TABS: usize = 32;
/// JPEG quality of the frames.
pub const JPEG_QUALITY: u8 = 90;
/// Absolute error (mean over RGB) drawn white in the error map, eval's default
/// `error_full_scale`.
pub const ERROR_FULL_SCALE: f64 = 0.25;

/// A rendered frame, encoded.
#[derive(Debug)]
pub struct Rendered {
    pub jpeg: Vec<u8>,
    pub width: u32,
    pub height: u32,
    /// Seconds the avatar render took (without comparison and encoding).
    pub render_seconds: f64,
    /// With `compare`: the image is ground truth | render | error map side by side, with
    /// its PSNR, or why it is the render only.
    pub compare: Option<Result<ComparePsnr, String>>,
}

/// The compared frame's PSNR by eval's protocol (at the size shown): over the whole image and
/// over the garment region (`seqavatar_evaluation::region`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ComparePsnr {
    pub whole: f64,
    /// `None` where the ingest entry has no garment region; `Some(None)` where the region
    /// is empty in this image.
    pub garment: Option<Option<f64>>,
}

/// Why a request got no frame.
#[derive(Debug, PartialEq)]
pub enum JobError {
    /// A newer request of the same tab replaced it before it was rendered.
    Superseded,
    /// Too many tabs are waiting.
    Busy,
    /// The request cannot be served by this avatar (HTTP 400).
    BadRequest(String),
    /// Rendering failed (HTTP 500).
    Failed(String),
    /// The viewer is shutting down.
    Closed,
}

/// What the render thread is asked for.
#[derive(Clone, Debug, PartialEq)]
pub enum Work {
    /// An image rendered on the server.
    Image(FrameRequest),
    /// The posed Gaussians of frames.
    Gaussians(GaussiansRequest, GaussianFormat),
}

/// How posed Gaussians are answered.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GaussianFormat {
    /// The records of [`crate::stream`], one per frame.
    Stream,
    /// The 3DGS PLY file `pipeline export` writes (one frame).
    Ply,
}

impl Work {
    fn tab(&self) -> &str {
        match self {
            Work::Image(request) => &request.tab,
            Work::Gaussians(request, _) => &request.tab,
        }
    }

    fn probe(&self) -> Option<ContextProbe> {
        match self {
            Work::Image(request) => request.probe,
            Work::Gaussians(request, _) => request.probe,
        }
    }
}

/// What the render thread answers: an encoded image, or the records of [`crate::stream`].
#[derive(Debug)]
pub enum Answer {
    Image(Rendered),
    Gaussians(Vec<u8>),
}

pub type JobResult = Result<Answer, JobError>;

struct Job {
    work: Work,
    reply: oneshot::Sender<JobResult>,
}

#[derive(Default)]
struct Queue {
    pending: VecDeque<Job>,
    closed: bool,
}

/// The bounded, newest-wins queue between the HTTP tasks and the render thread.
#[derive(Default)]
pub struct Scheduler {
    queue: Mutex<Queue>,
    wake: Condvar,
}

impl Scheduler {
    /// Queues `work`; the receiver gets its answer. A pending request of the same tab is
    /// replaced and answered [`JobError::Superseded`].
    pub fn submit(&self, work: Work) -> oneshot::Receiver<JobResult> {
        let (reply, answer) = oneshot::channel();
        let mut queue = self
            .queue
            .lock()
            .unwrap_or_else(|poison| poison.into_inner());
        if queue.closed {
            let _ = reply.send(Err(JobError::Closed));
            return answer;
        }
        let job = Job { work, reply };
        if let Some(slot) = queue
            .pending
            .iter_mut()
            .find(|pending| pending.work.tab() == job.work.tab())
        {
            let older = std::mem::replace(slot, job);
            let _ = older.reply.send(Err(JobError::Superseded));
        } else if queue.pending.len() >= MAX_PENDING_TABS {
            let _ = job.reply.send(Err(JobError::Busy));
        } else {
            queue.pending.push_back(job);
            self.wake.notify_one();
        }
        answer
    }

    /// The next job whose asker still waits; `None` once closed.
    fn next(&self) -> Option<Job> {
        let mut queue = self
            .queue
            .lock()
            .unwrap_or_else(|poison| poison.into_inner());
        loop {
            if queue.closed {
                return None;
            }
            while let Some(job) = queue.pending.pop_front() {
                if !job.reply.is_closed() {
                    return Some(job);
                }
            }
            queue = self
                .wake
                .wait(queue)
                .unwrap_or_else(|poison| poison.into_inner());
        }
    }

    /// Answers every pending request [`JobError::Closed`] and stops the render thread.
    pub fn close(&self) {
        let mut queue = self
            .queue
            .lock()
            .unwrap_or_else(|poison| poison.into_inner());
        queue.closed = true;
        for job in queue.pending.drain(..) {
            let _ = job.reply.send(Err(JobError::Closed));
        }
        self.wake.notify_all();
    }

    /// Number of pending requests.
    pub fn pending(&self) -> usize {
        self.queue
            .lock()
            .unwrap_or_else(|poison| poison.into_inner())
            .pending
            .len()
    }
}

/// The render thread's loop: renders queued requests until the scheduler closes.
pub fn render_loop(scene: &mut Scene, scheduler: &Scheduler) {
    let mut probe: Option<ContextProbe> = None;
    while let Some(job) = scheduler.next() {
        // A panic in the render code answers 500 instead of taking the viewer down.
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            serve(scene, &mut probe, &job.work)
        }))
        .unwrap_or_else(|panic| {
            let message = panic
                .downcast_ref::<&str>()
                .map(|text| (*text).to_owned())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "no message".to_owned());
            Err(JobError::Failed(format!(
                "the renderer panicked: {message}"
            )))
        });
        let _ = job.reply.send(result);
    }
}

/// The largest size of aspect `width : height` inside `max_width x max_height` (so within
/// the `--max-size` cap), never enlarged, at least one pixel.
pub fn fitted_size(width: u32, height: u32, max_width: u32, max_height: u32) -> (u32, u32) {
    let scale = (f64::from(max_width) / f64::from(width))
        .min(f64::from(max_height) / f64::from(height))
        .min(1.0);
    (
        ((f64::from(width) * scale).round() as u32).clamp(1, width),
        ((f64::from(height) * scale).round() as u32).clamp(1, height),
    )
}

/// Serves `work` under its context probe (`probe`: the one the renderer has now).
fn serve(scene: &mut Scene, probe: &mut Option<ContextProbe>, work: &Work) -> JobResult {
    let wanted = work.probe();
    if wanted != *probe {
        if wanted.is_some() && !scene.context_probes {
            return Err(JobError::BadRequest(
                "`context`: this avatar takes no motion-history inputs to replace (its motion context is none or pose)".to_owned(),
            ));
        }
        scene.renderer.set_context_probe(wanted);
        *probe = wanted;
    }
    match work {
        Work::Image(request) => render_request(scene, request).map(Answer::Image),
        Work::Gaussians(request, format) => {
            posed_gaussians(scene, request, *format).map(Answer::Gaussians)
        }
    }
}

/// The posed Gaussians of frames `request.frame..request.frame + request.count`, each
/// frame's as the server's render splats them ([`AvatarRenderer::deform`]): records of
/// [`crate::stream`], or the PLY file of the first frame.
///
/// [`AvatarRenderer::deform`]: seqavatar_evaluation::avatar_render::AvatarRenderer::deform
fn posed_gaussians(
    scene: &mut Scene,
    request: &GaussiansRequest,
    format: GaussianFormat,
) -> Result<Vec<u8>, JobError> {
    let failed = |error: anyhow::Error| JobError::Failed(format!("{error:#}"));
    if format == GaussianFormat::Ply {
        let world = scene.renderer.deform(request.frame).map_err(failed)?;
        return seqavatar_evaluation::export::posed_ply(
            world,
            scene.world_offset,
            &scene.renderer.avatar.gaussians.opacity_logit,
        )
        .map_err(failed);
    }
    let mut bytes = Vec::new();
    for frame in request.frame..request.frame + request.count {
        let world = scene.renderer.deform(frame).map_err(failed)?;
        crate::stream::encode(frame, &world, &mut bytes)
            .map_err(|error| JobError::Failed(format!("frame {frame}: {error}")))?;
    }
    Ok(bytes)
}

fn render_request(scene: &mut Scene, request: &FrameRequest) -> Result<Rendered, JobError> {
    let (camera, dataset_view) = match request.view {
        View::Dataset {
            camera,
            max_width,
            max_height,
        } => {
            let native = &scene.cameras[camera];
            let (width, height) = fitted_size(native.width, native.height, max_width, max_height);
            (native.resized(width, height), Some(camera))
        }
        View::Orbit(orbit) => (scene.orbit.camera(&orbit), None),
    };
    let started = Instant::now();
    let render = scene
        .renderer
        .render(request.frame, &camera)
        .map_err(|error| JobError::Failed(format!("{error:#}")))?;
    let render_seconds = started.elapsed().as_secs_f64();
    let failed = |error: anyhow::Error| JobError::Failed(format!("{error:#}"));
    let (image, compare) = match (request.compare, dataset_view) {
        (true, Some(view)) => {
            match comparison(scene, view, request.frame, &render).map_err(failed)? {
                Ok((sheet, psnr)) => (sheet, Some(Ok(psnr))),
                Err(why) => (render.to_rgb_image(), Some(Err(why))),
            }
        }
        _ => (render.to_rgb_image(), None),
    };
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(Cursor::new(&mut jpeg), JPEG_QUALITY)
        .encode_image(&image)
        .map_err(|error| JobError::Failed(format!("JPEG encoding: {error}")))?;
    Ok(Rendered {
        jpeg,
        width: image.width(),
        height: image.height(),
        render_seconds,
        compare,
    })
}

/// Ground truth | render | error map of `view` at `frame`, as eval's contact sheet shows them:
/// both prepared by eval's protocol (ground truth outside its foreground mask and render
/// outside the mask's bound box on the protocol background), the truth and mask resampled to
/// the render's size when it is smaller than the camera's; with the pair's PSNR over the whole
/// image and the garment region. `Ok(Err(why))` when there is no ground truth to compare with.
fn comparison(
    scene: &Scene,
    view: usize,
    frame: usize,
    render: &ImageF32,
) -> anyhow::Result<Result<(RgbImage, ComparePsnr), String>> {
    let Some(truth) = &scene.truth else {
        return Ok(Err(
            "no ground truth: the poses are not the trained sequence's".to_owned(),
        ));
    };
    let garment_mask = truth.garment(view, frame)?;
    let Some((truth, mask)) = truth.image(view, frame)? else {
        return Ok(Err(format!("no image of camera {view} at frame {frame}")));
    };
    let (width, height) = (render.width, render.height);
    let resize_mask = |mask: Mask| -> anyhow::Result<Mask> {
        if (mask.width, mask.height) == (width, height) {
            return Ok(mask);
        }
        let mask_image =
            image::GrayImage::from_raw(mask.width as u32, mask.height as u32, mask.data)
                .ok_or_else(|| anyhow::anyhow!("camera {view}: the mask's size is wrong"))?;
        let small = image::imageops::resize(
            &mask_image,
            width as u32,
            height as u32,
            image::imageops::FilterType::Nearest,
        );
        Ok(Mask::new(
            "ground-truth mask",
            width,
            height,
            small.into_raw(),
        )?)
    };
    let garment_mask = garment_mask.map(resize_mask).transpose()?;
    let (truth, mask) = if (truth.width, truth.height) == (width, height) {
        (truth, mask)
    } else {
        let (w, h) = (width as u32, height as u32);
        let truth_rgb = image::imageops::resize(
            &truth.to_rgb_image(),
            w,
            h,
            image::imageops::FilterType::Triangle,
        );
        (
            ImageF32::from_rgb8("ground truth", width, height, truth_rgb.as_raw())?,
            resize_mask(mask)?,
        )
    };
    let pair = Protocol::default().prepare(render, &truth, &mask)?;
    let psnr = ComparePsnr {
        whole: seqavatar_evaluation::metrics::psnr(&pair.render, &pair.truth)?,
        garment: garment_mask
            .map(|garment| region_psnr(&pair.render, &pair.truth, &garment))
            .transpose()?,
    };
    let error =
        seqavatar_evaluation::report::error_map(&pair.render, &pair.truth, ERROR_FULL_SCALE)?;
    let (w, h) = (width as u32, height as u32);
    let mut sheet = RgbImage::new(w * 3, h);
    let parts = [pair.truth.to_rgb_image(), pair.render.to_rgb_image(), error];
    for (slot, part) in parts.iter().enumerate() {
        image::imageops::replace(&mut sheet, part, i64::from(w) * slot as i64, 0);
    }
    Ok(Ok((sheet, psnr)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::orbit::OrbitView;

    fn request(tab: &str, frame: usize) -> Work {
        Work::Image(FrameRequest {
            tab: tab.to_owned(),
            frame,
            view: View::Orbit(OrbitView {
                azimuth_deg: 0.0,
                elevation_deg: 0.0,
                distance: 1.0,
                fov_deg: 40.0,
                pan_right: 0.0,
                pan_up: 0.0,
                width: 16,
                height: 16,
            }),
            probe: None,
            compare: false,
        })
    }

    fn frame_of(job: Job) -> usize {
        match job.work {
            Work::Image(request) => request.frame,
            Work::Gaussians(request, _) => request.frame,
        }
    }

    #[test]
    fn a_newer_request_of_a_tab_replaces_its_pending_one() {
        let scheduler = Scheduler::default();
        let mut first = scheduler.submit(request("a", 1));
        let other = scheduler.submit(request("b", 5));
        let second = scheduler.submit(request("a", 2));
        assert_eq!(first.try_recv().unwrap().unwrap_err(), JobError::Superseded);
        assert_eq!(scheduler.pending(), 2);
        // First come, first served across tabs; the replaced request keeps its tab's place.
        assert_eq!(frame_of(scheduler.next().unwrap()), 2);
        assert_eq!(frame_of(scheduler.next().unwrap()), 5);
        drop((other, second));
    }

    #[test]
    fn the_queue_is_bounded_and_skips_abandoned_requests() {
        let scheduler = Scheduler::default();
        let mut answers: Vec<_> = (0..MAX_PENDING_TABS)
            .map(|tab| scheduler.submit(request(&tab.to_string(), 0)))
            .collect();
        let mut refused = scheduler.submit(request("late", 0));
        assert_eq!(refused.try_recv().unwrap().unwrap_err(), JobError::Busy);
        // Tab "0" closed its connection: its request is skipped.
        drop(answers.remove(0));
        assert_eq!(scheduler.next().unwrap().work.tab(), "1");
        scheduler.close();
        assert!(scheduler.next().is_none());
        for mut answer in answers.into_iter().skip(1) {
            assert_eq!(answer.try_recv().unwrap().unwrap_err(), JobError::Closed);
        }
        let mut after = scheduler.submit(request("x", 0));
        assert_eq!(after.try_recv().unwrap().unwrap_err(), JobError::Closed);
    }

    #[test]
    fn fitted_sizes_keep_the_aspect_and_never_enlarge() {
        assert_eq!(fitted_size(256, 256, 512, 512), (256, 256));
        assert_eq!(fitted_size(256, 256, 128, 512), (128, 128));
        assert_eq!(fitted_size(1920, 1080, 480, 480), (480, 270));
        assert_eq!(fitted_size(1000, 100, 16, 16), (16, 2));
        assert_eq!(fitted_size(10, 8, 16, 16), (10, 8));
    }
}
