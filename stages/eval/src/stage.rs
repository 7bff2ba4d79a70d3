//! The `eval` stage kind: renders every test (view, frame) of the ingest split with the trained
//! avatar, scores it with the paper protocol and measures rendering speed.
//!
//! Inputs: a `train` entry (the avatar), an `ingest` entry (the test split, cameras, body
//! parameters), optionally the `fit` entry (refined body parameters, as training used them)
//! and the `motion` entry (motion windows; required when the avatar's motion context uses
//! skeleton motion or velocities). The avatar must have been trained on the same cameras and
//! body model: otherwise the stage stops with an error naming both entries.
//!
//! Output: the arrays and attributes of `seqavatar_schema::eval` (docs/schema.md).

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context as _;
use serde::{Deserialize, Serialize};

use seqavatar_compute::backend::{Backend, DeviceChoice};
use seqavatar_compute::nn::Precision;
use seqavatar_compute::nn::gpu::MatmulPath;
use seqavatar_engine::{
    BACKEND_LOG_PREFIX, ConfigError, EntryReader, PictureKind, PictureOptions, StageContext,
    StageKind,
};

use seqavatar_compute::lpips::{Lpips, LpipsNet, LpipsWeights};
use seqavatar_evaluation::context_probe::{ContextProbe, ProbeResult, probe_result};
use seqavatar_evaluation::evaluate::{
    LpipsModels, MEAN_TABLE_HEADERS, SpeedRow, ViewRenderer, contact_sheet_rows, mean_table_row,
    measure_speed, pad_to, score_image, spread,
};
use seqavatar_evaluation::metrics::Protocol;
use seqavatar_evaluation::region::RegionScore;
use seqavatar_evaluation::report::{error_map, markdown_table, outline_region};
use seqavatar_evaluation::scores::{ImageScore, MeanScores, mean_scores};
use seqavatar_evaluation::testset::{TestImage, TestSet};

use seqavatar_schema::eval::{
    EVAL_KIND, GARMENT_TABLE_ATTRIBUTE, PerImageScores, SPEED_ATTRIBUTE, SUMMARY_ATTRIBUTE,
    ScoreColumns, TRAIN_IMAGE_PSNR_ATTRIBUTE, read_rgb, write_contact_sheet,
};
use seqavatar_schema::ingest::PlannedIngest;
use seqavatar_schema::train::PlannedTrain;

/// The `eval` stage configuration.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EvalConfig {
    /// Backend for rendering and LPIPS (`auto`, `cpu`, `gpu`).
    pub device: DeviceChoice,
    /// Background and bound-box rules (docs/method.md "Evaluation protocol").
    pub protocol: Protocol,
    /// LPIPS weights converted with `tests/lpips/convert_weights.py`; none: "unavailable".
    pub lpips_vgg_weights: Option<PathBuf>,
    pub lpips_alex_weights: Option<PathBuf>,
    /// Score at most this many test images, spread evenly over the split (0 = all).
    pub max_images: usize,
    /// Mean absolute error shown white in the error maps.
    pub error_full_scale: f64,
    /// Rows of the contact sheet.
    pub contact_sheet_rows: usize,
    /// Resolutions (factors of the first test view's size) the rendering speed is measured at.
    pub speed_scales: Vec<f64>,
    /// Timed renders per resolution (after one untimed warm-up render).
    pub speed_frames: usize,
    /// Score the test images again with the motion-history inputs zeroed and taken from
    /// another frame ([`seqavatar_evaluation::context_probe`]); avatars without such inputs are not probed.
    pub context_probes: bool,
    /// The "another frame" probe gives frame `i` the inputs of frame `(i + offset) mod n`.
    pub context_probe_offset: usize,
    /// How the avatar's networks' dense layers run on the `gpu` backend: `f32`, or `mixed`
    /// (f16 operands with f32 accumulation on tensor cores where the adapter has them, else
    /// f32). Absent means `mixed` (whatever the train entry's `precision`), and leaves the
    /// key of configs written before the setting existed unchanged (it is serialised only
    /// where set). `cpu` ignores it. The log's `networks:` line names the path.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub precision: Option<Precision>,
}

impl Default for EvalConfig {
    fn default() -> Self {
        Self {
            device: DeviceChoice::Auto,
            protocol: Protocol::default(),
            lpips_vgg_weights: None,
            lpips_alex_weights: None,
            max_images: 0,
            error_full_scale: 0.25,
            contact_sheet_rows: 4,
            speed_scales: vec![1.0, 0.5],
            speed_frames: 5,
            context_probes: true,
            context_probe_offset: 50,
            precision: None,
        }
    }
}

impl EvalConfig {
    fn validate(&self) -> Result<(), ConfigError> {
        if !(self.error_full_scale.is_finite() && self.error_full_scale > 0.0) {
            return Err(ConfigError::at_key(
                "error_full_scale",
                format!("{} must be positive and finite", self.error_full_scale),
            ));
        }
        if self
            .protocol
            .background
            .iter()
            .any(|c| !(0.0..=1.0).contains(c))
        {
            return Err(ConfigError::at_key(
                "protocol",
                format!(
                    "background {:?} must be in [0, 1]",
                    self.protocol.background
                ),
            ));
        }
        if self.contact_sheet_rows == 0 {
            return Err(ConfigError::at_key(
                "contact_sheet_rows",
                "at least one row is needed",
            ));
        }
        if let Some(bad) = self
            .speed_scales
            .iter()
            .find(|scale| !(scale.is_finite() && **scale > 0.0 && **scale <= 4.0))
        {
            return Err(ConfigError::at_key(
                "speed_scales",
                format!("{bad} must be in (0, 4]"),
            ));
        }
        if self.context_probes && self.context_probe_offset == 0 {
            return Err(ConfigError::at_key(
                "context_probe_offset",
                "must be at least 1 (offset 0 gives every frame its own context)",
            ));
        }
        if self.speed_frames == 0 && !self.speed_scales.is_empty() {
            return Err(ConfigError::at_key(
                "speed_frames",
                "at least one timed render per resolution is needed",
            ));
        }
        Ok(())
    }
}

/// The sequence name of an ingest entry for tables: the dataset kind and its sequence id or
/// folder name.
pub fn sequence_name(ingest: &EntryReader) -> String {
    let dataset = ingest.config().get("dataset");
    let kind = dataset
        .and_then(|value| value.get("kind"))
        .and_then(|value| value.as_str())
        .unwrap_or("dataset");
    let detail = dataset.and_then(|value| {
        if let Some(sequence) = value.get("sequence").and_then(|v| v.as_str()) {
            return Some(sequence.to_owned());
        }
        ["root", "main_file"].iter().find_map(|field| {
            let path = value.get(*field)?.as_str()?;
            Path::new(path)
                .file_stem()
                .map(|stem| stem.to_string_lossy().into_owned())
        })
    });
    match detail {
        Some(detail) if !detail.is_empty() => format!("{kind}/{detail}"),
        _ => kind.to_owned(),
    }
}

/// Loads the configured LPIPS models on `backend`.
pub fn load_lpips(config: &EvalConfig, backend: &Backend) -> anyhow::Result<LpipsModels> {
    let load = |path: &Option<PathBuf>, net: LpipsNet| -> anyhow::Result<Option<Lpips>> {
        let Some(path) = path else {
            return Ok(None);
        };
        let weights = LpipsWeights::load(path, net)?;
        Ok(Some(Lpips::new(weights, backend)?))
    };
    Ok(LpipsModels {
        vgg: load(&config.lpips_vgg_weights, LpipsNet::Vgg)?,
        alex: load(&config.lpips_alex_weights, LpipsNet::Alex)?,
    })
}

/// The `eval` stage kind.
pub struct EvalStage;

impl StageKind for EvalStage {
    type Config = EvalConfig;

    fn kind(&self) -> &'static str {
        EVAL_KIND
    }

    fn version(&self) -> u32 {
        // 2: on the gpu backend the networks run on the gpu in f32 (GpuNetworks).
        // 3: the avatar renders on the protocol's background (not its training background).
        // 4: reads the avatar config (attribute `avatar`) of train entries of version 5.
        // 5: on the cpu backend the networks run in f32 too.
        // 6: `summary.subsets` (history frames, held-out cameras / frames).
        // 7: `summary.context_probes` (context zeroed / from another frame) and
        //    `summary.train_image_psnr` (from the train entry).
        // 8: on the cpu backend the avatar splats in f32 (the lane path).
        // 9: on the gpu backend each frame is deformed and splatted on the device.
        // 10: the garment region's figures (`summary.garment_region`, `garment` in `means`
        //     and each subset, per-image `garment_*` arrays) where ingest has garment masks.
        // 11: the context probes score the garment region too (`psnr_change.garment`).
        // `precision` did not bump it: the f32 path is unchanged, so on machines
        // without tensor cores every output is as before, and a config without `precision`
        // keeps its key (the field is serialised only where set); an explicit one enters the
        // key through the canonical config. `mixed`, the default, changes results only on
        // adapters with tensor cores, which the key does not name (it names no adapter).
        11
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        &["train", "ingest", "fit", "motion"]
    }

    fn check_inputs(
        &self,
        _config: &EvalConfig,
        inputs: &[seqavatar_engine::StageInput<'_>],
    ) -> Result<(), String> {
        seqavatar_engine::require_one_input_of_each(inputs, &["train", "ingest"])?;
        // Evaluation measures the test images: a split without any is refused now, not
        // after training.
        let ingest = inputs
            .iter()
            .find(|input| input.kind == "ingest")
            .expect("checked above");
        if let Some(why) = PlannedIngest::of(ingest)?.no_test_images {
            return Err(format!("input {}: {why}", ingest.name));
        }
        // An avatar with skeleton-motion context renders from the motion entry.
        let train = inputs
            .iter()
            .find(|input| input.kind == "train")
            .expect("checked above");
        let plan = PlannedTrain::of(train)?;
        if plan.renders_from_motion_entry {
            seqavatar_engine::require_one_input_of_each(inputs, &["motion"]).map_err(|e| {
                format!(
                    "{e} (input {} trains with motion context {}, which renders from the \
                     motion entry)",
                    train.name, plan.motion_context
                )
            })?;
        }
        Ok(())
    }

    fn resolve_config(&self, raw: &serde_json::Value) -> Result<EvalConfig, ConfigError> {
        let config: EvalConfig = seqavatar_engine::parse_config(raw)?;
        config.validate()?;
        Ok(config)
    }

    fn external_files(&self, config: &EvalConfig) -> anyhow::Result<Vec<PathBuf>> {
        Ok([&config.lpips_vgg_weights, &config.lpips_alex_weights]
            .into_iter()
            .flatten()
            .cloned()
            .collect())
    }

    fn run(&self, config: &EvalConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        let train = ctx.input("train")?.clone();
        let ingest = ctx.input("ingest")?.clone();
        let backend = Backend::select(config.device)
            .with_context(|| format!("config `device: {}`", config.device))?;
        ctx.log(&format!("{BACKEND_LOG_PREFIX} {}", backend.describe()));
        let precision = config.precision.unwrap_or_default();
        // The path the renderer's networks take (`NnGpu::for_context` makes the same choice
        // from the same context and precision).
        ctx.log(&MatmulPath::of_backend(&backend, precision).describe());
        let lpips = load_lpips(config, &backend)?;
        if lpips.vgg.is_none() && lpips.alex.is_none() {
            ctx.log("LPIPS unavailable: no lpips_vgg_weights / lpips_alex_weights configured");
        }
        let optional = |kind: &str| -> anyhow::Result<Option<EntryReader>> {
            Ok(if ctx.inputs().iter().any(|input| input.kind() == kind) {
                Some(ctx.input(kind)?.clone())
            } else {
                None
            })
        };
        let fit = optional("fit")?;
        let motion = optional("motion")?;
        // Eval renders at its own precision, not the train entry's.
        let mut avatar = seqavatar_evaluation::avatar_render::AvatarRenderer::load_avatar(&train)?;
        avatar.config.precision = Some(precision);
        let mut renderer = seqavatar_evaluation::avatar_render::AvatarRenderer::open_loaded(
            avatar,
            &train,
            &ingest,
            fit.as_ref().unwrap_or(&ingest),
            motion.as_ref(),
            &backend,
        )?;
        // The avatar is rendered on the protocol's background, the colour the ground truth
        // outside its mask is set to, whatever background it was trained on.
        renderer.avatar.background = config.protocol.background.map(f64::from);
        // Train-image PSNR (the train entry's, by the same protocol) goes next to the
        // held-out scores: a large gap is memorisation, none with low scores under-fitting.
        let train_image_psnr = train
            .attribute(TRAIN_IMAGE_PSNR_ATTRIBUTE)
            .and_then(|value| value.as_f64());
        evaluate_entry(
            ctx,
            config,
            &ingest,
            &mut renderer,
            &lpips,
            &backend,
            train_image_psnr,
        )
    }

    fn pictures(&self) -> Vec<PictureKind> {
        vec![
            PictureKind {
                name: "contact_sheet",
                description: "ground truth | render | error map for a few test images (the garment region, where ingest has one, outlined in cyan on the ground truth)",
            },
            PictureKind {
                name: "render",
                description: "one scored render (--opt index=N)",
            },
            PictureKind {
                name: "error_map",
                description: "one error map (--opt index=N)",
            },
        ]
    }

    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        match picture {
            "contact_sheet" => read_rgb(entry, "contact_sheet", None),
            "render" | "error_map" => {
                let unknown = options.unknown_keys(&["index"]);
                anyhow::ensure!(
                    unknown.is_empty(),
                    "picture {picture}: unknown options {unknown:?} (known: index)"
                );
                let index = options.get_u64("index", 0)? as usize;
                let name = if picture == "render" {
                    "renders"
                } else {
                    "error_maps"
                };
                read_rgb(entry, name, Some(index))
            }
            other => Err(seqavatar_engine::unknown_picture(self, other)),
        }
    }
}

/// Scores every selected test image rendered by `renderer` and writes the eval entry.
pub fn evaluate_entry(
    ctx: &StageContext<'_>,
    config: &EvalConfig,
    ingest: &EntryReader,
    renderer: &mut dyn ViewRenderer,
    lpips: &LpipsModels,
    backend: &Backend,
    train_image_psnr: Option<f64>,
) -> anyhow::Result<()> {
    let testset = TestSet::read(ingest)?;
    anyhow::ensure!(
        !testset.images.is_empty(),
        "ingest entry {} has no test images to evaluate",
        ingest.location()
    );
    let selected: Vec<usize> = if config.max_images == 0 {
        (0..testset.images.len()).collect()
    } else {
        spread(testset.images.len(), config.max_images)
    };
    let tests: Vec<TestImage> = selected.iter().map(|&pick| testset.images[pick]).collect();
    let evaluation = Evaluation {
        ctx,
        config,
        ingest,
        testset: &testset,
        tests: &tests,
    };
    let scored = evaluation.score_test_images(renderer, lpips)?;
    evaluation.write_per_image_arrays(&scored, lpips)?;
    let speed = evaluation.measure_speeds(renderer)?;
    let scores = &scored.scores;
    let means = mean_scores(scores);
    let subsets = evaluation.subset_scores(scores)?;
    if let Some(value) = train_image_psnr {
        ctx.log(&format!("train images (train entry): PSNR {value:.2} dB"));
    }
    let probes = if config.context_probes {
        evaluation.run_context_probes(renderer, &means, &subsets)?
    } else {
        Vec::new()
    };
    let out = ctx.output();
    let sequence = sequence_name(ingest);
    let table = markdown_table(&MEAN_TABLE_HEADERS, &[mean_table_row(&sequence, &means)])
        .map_err(anyhow::Error::msg)?;
    let nets: Vec<&str> = [("vgg", lpips.vgg.is_some()), ("alex", lpips.alex.is_some())]
        .iter()
        .filter(|(_, present)| *present)
        .map(|(name, _)| *name)
        .collect();
    let garment_region = testset.garment_region.map(|region| region.as_str());
    match (&means.garment, garment_region) {
        (Some(garment), Some(region)) => ctx.log(&format!(
            "garment region ({region}): {}",
            seqavatar_evaluation::report::describe_region_means(garment)
        )),
        _ => ctx.log(seqavatar_evaluation::report::NO_GARMENT_REGION),
    }
    out.set_attribute(
        SUMMARY_ATTRIBUTE,
        serde_json::json!({
            "sequence": sequence,
            "means": means,
            "subsets": subsets,
            "train_image_psnr": train_image_psnr,
            "context_probes": probes,
            "lpips": if nets.is_empty() { "unavailable".to_owned() } else { nets.join(",") },
            "backend": backend.describe(),
            "garment_region": garment_region,
            "garment_lpips": (garment_region.is_some() && !nets.is_empty())
                .then_some(seqavatar_evaluation::region::REGION_LPIPS_METHOD),
        }),
    )?;
    out.set_attribute(SPEED_ATTRIBUTE, serde_json::to_value(&speed)?)?;
    out.set_attribute("mean_table", serde_json::Value::String(table.clone()))?;
    for line in table.lines() {
        ctx.log(line);
    }
    // The garment region beside the whole-image figures, per subset (Markdown), or the
    // sentence saying the dataset has none.
    let garment = seqavatar_evaluation::evaluate::garment_table(&means, &subsets)
        .unwrap_or_else(|| seqavatar_evaluation::report::NO_GARMENT_REGION.to_owned());
    out.set_attribute(
        GARMENT_TABLE_ATTRIBUTE,
        serde_json::Value::String(garment.clone()),
    )?;
    for line in garment.lines() {
        ctx.log(line);
    }
    Ok(())
}

/// What the steps of [`evaluate_entry`] share: the stage, its config, the ingest entry, its
/// test set and the test images selected from it.
struct Evaluation<'a, 'c> {
    ctx: &'a StageContext<'c>,
    config: &'a EvalConfig,
    ingest: &'a EntryReader,
    testset: &'a TestSet,
    tests: &'a [TestImage],
}

/// The scores of the selected test images, with what the entry keeps of them.
struct ScoredImages {
    scores: Vec<ImageScore>,
    render_seconds: Vec<f64>,
    /// (truth, render, error map) of the contact sheet's rows.
    sheet_images: Vec<(image::RgbImage, image::RgbImage, image::RgbImage)>,
}

impl Evaluation<'_, '_> {
    /// Renders and scores each selected test image, writing the `renders` and `error_maps`
    /// arrays (one chunk per image, padded to the stored size).
    fn score_test_images(
        &self,
        renderer: &mut dyn ViewRenderer,
        lpips: &LpipsModels,
    ) -> anyhow::Result<ScoredImages> {
        let (ctx, config, testset) = (self.ctx, self.config, self.testset);
        let count = self.tests.len();
        let (height, width) = (testset.arrays.height, testset.arrays.width);
        let out = ctx.output();
        let image_dims = ["image", "height", "width", "rgb"];
        let image_shape = [count as u64, height, width, 3];
        let image_chunk = [1, height, width, 3];
        let renders_array =
            out.create_array::<u8>("renders", &image_dims, &image_shape, &image_chunk)?;
        let errors_array =
            out.create_array::<u8>("error_maps", &image_dims, &image_shape, &image_chunk)?;
        let sheet_picks: Vec<usize> = spread(count, config.contact_sheet_rows);
        let mut sheet_images = Vec::new();
        let mut scores = Vec::with_capacity(count);
        let mut render_seconds = Vec::with_capacity(count);
        let progress = ctx.progress_bar(count as u64, "render and score test images");
        for (slot, &test) in self.tests.iter().enumerate() {
            let camera = &testset.cameras[test.view];
            let started = Instant::now();
            let render = renderer.render(test.frame, camera).with_context(|| {
                format!(
                    "rendering test image {} (view {}, frame {})",
                    test.index, test.view, test.frame
                )
            })?;
            render_seconds.push(started.elapsed().as_secs_f64());
            anyhow::ensure!(
                render.width == camera.width as usize && render.height == camera.height as usize,
                "the avatar rendered {} x {} for view {} of {} x {}",
                render.width,
                render.height,
                test.view,
                camera.width,
                camera.height
            );
            let (truth, mask) = testset.load(self.ingest, &test)?;
            let garment = testset.load_garment(self.ingest, &test)?;
            let scored = score_image(
                &config.protocol,
                lpips,
                &render,
                &truth,
                &mask,
                garment.as_ref(),
            )
            .with_context(|| format!("scoring test image {}", test.index))?;
            let render_rgb = scored.pair.render.to_rgb_image();
            let error_rgb = error_map(
                &scored.pair.render,
                &scored.pair.truth,
                config.error_full_scale,
            )?;
            renders_array.write_chunk(
                &[slot as u64, 0, 0, 0],
                pad_to(&render_rgb, width as u32, height as u32).as_raw(),
            )?;
            errors_array.write_chunk(
                &[slot as u64, 0, 0, 0],
                pad_to(&error_rgb, width as u32, height as u32).as_raw(),
            )?;
            if sheet_picks.contains(&slot) {
                let mut truth_rgb = scored.pair.truth.to_rgb_image();
                if let Some(garment) = &garment {
                    outline_region(&mut truth_rgb, garment);
                }
                sheet_images.push((truth_rgb, render_rgb, error_rgb));
            }
            scores.push(scored.score);
            progress.inc(1);
        }
        progress.finish_and_clear();
        Ok(ScoredImages {
            scores,
            render_seconds,
            sheet_images,
        })
    }

    /// The per-image columns (metrics, render time, which image) and the contact sheet.
    fn write_per_image_arrays(
        &self,
        scored: &ScoredImages,
        lpips: &LpipsModels,
    ) -> anyhow::Result<()> {
        let (out, tests, scores) = (self.ctx.output(), self.tests, &scored.scores);
        let column = |pick: &dyn Fn(&ImageScore) -> Option<f64>| -> Vec<f64> {
            scores.iter().map(|s| pick(s).unwrap_or(f64::NAN)).collect()
        };
        let region =
            |pick: fn(&RegionScore) -> Option<f64>| column(&|s| s.garment.as_ref().and_then(pick));
        let pixels = |s: &ImageScore| match s.garment {
            Some(RegionScore::Scored { pixels, .. }) => pixels as u32,
            _ => 0,
        };
        let garment = self.testset.garment_region.is_some().then(|| {
            let columns = ScoreColumns {
                psnr: region(|r| r.psnr()),
                ssim: region(|r| r.ssim()),
                lpips_vgg: lpips.vgg.as_ref().map(|_| region(|r| r.lpips_vgg())),
                lpips_alex: lpips.alex.as_ref().map(|_| region(|r| r.lpips_alex())),
            };
            (scores.iter().map(pixels).collect(), columns)
        });
        PerImageScores {
            whole: ScoreColumns {
                psnr: column(&|s| Some(s.psnr)),
                ssim: column(&|s| Some(s.ssim)),
                lpips_vgg: lpips.vgg.as_ref().map(|_| column(&|s| s.lpips_vgg)),
                lpips_alex: lpips.alex.as_ref().map(|_| column(&|s| s.lpips_alex)),
            },
            garment,
            render_seconds: scored.render_seconds.clone(),
            image_index: tests.iter().map(|t| t.index as u32).collect(),
            image_view: tests.iter().map(|t| t.view as u32).collect(),
            image_frame: tests.iter().map(|t| t.frame as u32).collect(),
        }
        .write(out)?;
        let (width, height) = (self.testset.arrays.width, self.testset.arrays.height);
        let sheet = contact_sheet_rows(&scored.sheet_images, width as u32, height as u32)?;
        write_contact_sheet(out, &sheet)
    }

    /// Rendering speed, the whole render path, on the first scored view at each configured
    /// scale; written as the `speed_*` arrays.
    fn measure_speeds(&self, renderer: &mut dyn ViewRenderer) -> anyhow::Result<Vec<SpeedRow>> {
        let (ctx, config, tests) = (self.ctx, self.config, self.tests);
        let out = ctx.output();
        let first = tests[0];
        let frames: Vec<usize> = (0..config.speed_frames)
            .map(|k| tests[k % tests.len()].frame)
            .collect();
        let mut speed: Vec<SpeedRow> = Vec::new();
        for &scale in &config.speed_scales {
            let camera = self.testset.cameras[first.view].rescaled(scale);
            let row = measure_speed(renderer, &camera, &frames).with_context(|| {
                format!("speed measurement at {} x {}", camera.width, camera.height)
            })?;
            ctx.log(&format!(
                "speed: {} x {}: {:.2} FPS ({:.1} ms per frame, networks included)",
                row.width,
                row.height,
                row.fps,
                1000.0 / row.fps
            ));
            speed.push(row);
        }
        let resolutions = speed.len() as u64;
        if resolutions > 0 {
            for (name, values) in [
                (
                    "speed_width",
                    speed.iter().map(|r| r.width).collect::<Vec<_>>(),
                ),
                ("speed_height", speed.iter().map(|r| r.height).collect()),
            ] {
                out.write_whole::<u32>(name, &["resolution"], &[resolutions], &values)?;
            }
            out.write_whole::<f64>(
                "speed_fps",
                &["resolution"],
                &[resolutions],
                &speed.iter().map(|r| r.fps).collect::<Vec<_>>(),
            )?;
        }
        Ok(speed)
    }

    /// Scores on the history frames and per protocol (held-out cameras / held-out frames),
    /// logged.
    fn subset_scores(
        &self,
        scores: &[ImageScore],
    ) -> anyhow::Result<seqavatar_evaluation::subsets::SubsetScores> {
        let subsets = seqavatar_evaluation::subsets::subset_scores(
            &seqavatar_evaluation::subsets::frame_flags(self.ingest)?,
            &self.tests.iter().map(|t| t.frame).collect::<Vec<_>>(),
            scores,
        )?;
        for (name, subset) in subsets.named() {
            if let Some(m) = subset {
                let garment = m.garment.as_ref().map_or_else(String::new, |g| {
                    format!(
                        "; garment region: {}",
                        seqavatar_evaluation::report::describe_region_means(g)
                    )
                });
                self.ctx.log(&format!(
                    "{name}: {} images, PSNR {:.2} dB, SSIM {:.4}{garment}",
                    m.images, m.psnr, m.ssim
                ));
            }
        }
        Ok(subsets)
    }

    /// Scores the test images again under each context probe ([`seqavatar_evaluation::context_probe`]), PSNR
    /// and SSIM (no LPIPS), and logs the PSNR change per subset; empty when the renderer has
    /// no motion history inputs.
    fn run_context_probes(
        &self,
        renderer: &mut dyn ViewRenderer,
        means: &MeanScores,
        subsets: &seqavatar_evaluation::subsets::SubsetScores,
    ) -> anyhow::Result<Vec<ProbeResult>> {
        let (ctx, config, ingest, testset, tests) =
            (self.ctx, self.config, self.ingest, self.testset, self.tests);
        let flags = seqavatar_evaluation::subsets::frame_flags(ingest)?;
        let frames: Vec<usize> = tests.iter().map(|t| t.frame).collect();
        let mut results = Vec::new();
        for probe in [
            ContextProbe::Zeroed,
            ContextProbe::FromFrame {
                offset: config.context_probe_offset,
            },
        ] {
            if !renderer.set_context_probe(Some(probe)) {
                ctx.log(
                    "context probes: the avatar has no motion-history inputs, nothing to probe",
                );
                return Ok(Vec::new());
            }
            let progress = ctx.progress_bar(tests.len() as u64, &probe.describe());
            let mut scores = Vec::with_capacity(tests.len());
            for test in tests {
                let camera = &testset.cameras[test.view];
                let render = renderer.render(test.frame, camera).with_context(|| {
                    format!(
                        "{}: rendering test image {} (view {}, frame {})",
                        probe.describe(),
                        test.index,
                        test.view,
                        test.frame
                    )
                })?;
                let (truth, mask) = testset.load(ingest, test)?;
                let garment = testset.load_garment(ingest, test)?;
                let scored = score_image(
                    &config.protocol,
                    &LpipsModels::default(),
                    &render,
                    &truth,
                    &mask,
                    garment.as_ref(),
                )?;
                scores.push(scored.score);
                progress.inc(1);
            }
            progress.finish_and_clear();
            let probe_subsets =
                seqavatar_evaluation::subsets::subset_scores(&flags, &frames, &scores)?;
            let result = probe_result(probe, &scores, probe_subsets, means, subsets);
            let change = &result.psnr_change;
            let show =
                |value: Option<f64>| value.map_or_else(|| "-".to_owned(), |v| format!("{v:+.2}"));
            let garment = change.garment.as_ref().map_or_else(String::new, |g| {
                format!(
                    "; garment region {:+.2} dB, history frames {}",
                    g.all,
                    show(g.history)
                )
            });
            ctx.log(&format!(
                "{}: PSNR change {:+.2} dB on all {} images, history frames {}, other frames {}, held-out frames {}{garment}",
                probe.describe(),
                change.all,
                scores.len(),
                show(change.history),
                show(change.not_history),
                show(change.held_out_frames)
            ));
            results.push(result);
        }
        renderer.set_context_probe(None);
        Ok(results)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    /// `precision: f32 | mixed` resolves into the config; absent, it is `mixed` and the
    /// resolved config, and so the key, is what it was before the setting existed; a bad
    /// value is an error naming the field and the choices.
    #[test]
    fn precision_parses_defaults_to_mixed_and_leaves_the_key_alone() {
        use seqavatar_engine::key::{KeyMaterial, stage_key};
        for (text, precision) in [("f32", Precision::F32), ("mixed", Precision::Mixed)] {
            let config = EvalStage
                .resolve_config(&json!({"precision": text}))
                .unwrap();
            assert_eq!(
                serde_json::to_value(&config).unwrap()["precision"],
                json!(text)
            );
            assert_eq!(config.precision, Some(precision));
        }
        let config = EvalStage.resolve_config(&json!({})).unwrap();
        let absent = serde_json::to_value(&config).unwrap();
        assert!(absent.get("precision").is_none(), "{absent}");
        assert_eq!(config.precision.unwrap_or_default(), Precision::Mixed);
        // The key of the default config at version 9 as it was before `precision` existed
        // (commit 8f18229). A change to a field's default changes it (update it then); a
        // new optional field must not.
        let key = stage_key(&KeyMaterial {
            kind: "eval",
            version: 9,
            config: &absent,
            input_keys: &[],
            external_digests: &[],
        });
        assert_eq!(
            key,
            "8dcb34cc48ded13d5addeb04349ffb1eeb793a8b2dff8297ece0a496032da22e"
        );
        let error = EvalStage
            .resolve_config(&json!({"precision": "f16"}))
            .unwrap_err()
            .to_string();
        for part in ["precision", "f16", "f32", "mixed"] {
            assert!(error.contains(part), "`{error}` lacks {part}");
        }
    }

    /// `device` is the compute crate's `DeviceChoice`, spelled as before (`auto`, `cpu`,
    /// `gpu`: the resolved config, and so the key, is unchanged); an unknown name is an error
    /// naming the field, the value and the choices.
    #[test]
    fn device_is_spelled_as_before_and_unknown_names_are_errors() {
        for text in ["auto", "cpu", "gpu"] {
            let resolved = EvalStage.resolve_config(&json!({"device": text})).unwrap();
            assert_eq!(
                serde_json::to_value(resolved).unwrap()["device"],
                json!(text)
            );
        }
        let defaults = EvalStage.resolve_config(&json!({})).unwrap();
        assert_eq!(
            serde_json::to_value(defaults).unwrap()["device"],
            json!("auto")
        );
        let err = EvalStage
            .resolve_config(&json!({"device": "cuda"}))
            .unwrap_err()
            .to_string();
        for part in ["device", "cuda", "auto", "cpu", "gpu"] {
            assert!(err.contains(part), "`{err}` lacks {part}");
        }
    }
}
