//! `pipeline report`: a Markdown report with PNG plots for one pipeline run, read from the
//! cache only: the metrics of every eval stage, loss curves from the train entries, the timing
//! of every stage from its manifest, cache reuse, and for a sweep (several eval stages) a table
//! over all of them with Pareto plots (PSNR vs training time, PSNR vs FPS), and for an
//! ablation with several seeds per configuration the seed-averaged table of [`crate::ablation`].

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context as _;
use seqavatar_engine::{
    EntryId, EntryReader, EntryState, Pipeline, Registry, StageSpec, Store, compute_keys,
    open_store,
};

use crate::ablation::{SeedRun, ablation_table};
use crate::evaluate::{MEAN_TABLE_HEADERS, SpeedRow, format_lpips_x1000, garment_table};
use crate::report::NO_GARMENT_REGION;
use crate::report::{
    self, PlotOptions, Series, format_metric, markdown_table, palette, pareto_front,
};
use crate::scores::MeanScores;
use crate::subsets::SubsetScores;
use seqavatar_schema::eval::{EVAL_KIND, SPEED_ATTRIBUTE, SUMMARY_ATTRIBUTE, read_summary_field};

/// What the report found for one eval stage.
#[derive(Clone, Debug)]
pub struct EvalRow {
    pub eval_stage: String,
    pub train_stage: Option<String>,
    /// The train stage's trade-off knobs, `(knob, value)`.
    pub settings: Vec<(String, String)>,
    pub sequence: String,
    pub means: MeanScores,
    /// Training wall time from the train entry's manifest.
    pub train_seconds: Option<f64>,
    /// FPS at the largest measured resolution, the whole render path.
    pub fps: Option<f64>,
    pub speed: Vec<SpeedRow>,
}

/// Train config fields shown per sweep run (the knobs of the trade-off).
const TRAIN_KNOBS: [&str; 7] = [
    "preset",
    "iterations",
    "resolution_scale",
    "max_gaussians",
    "trunk_width",
    "motion_context",
    "device",
];

fn knob_values(config: &serde_json::Value) -> Vec<(String, String)> {
    TRAIN_KNOBS
        .iter()
        .filter_map(|knob| {
            let value = config.get(*knob)?;
            let text = match value {
                serde_json::Value::String(text) => text.clone(),
                other => other.to_string(),
            };
            Some(((*knob).to_owned(), text))
        })
        .collect()
}

/// Per row, the `knob=value` settings that differ between rows (all of them for one row).
pub fn varying_settings(rows: &[EvalRow]) -> Vec<String> {
    let varies = |knob: &str| {
        let values: Vec<Option<&String>> = rows
            .iter()
            .map(|row| row.settings.iter().find(|(k, _)| k == knob).map(|(_, v)| v))
            .collect();
        rows.len() < 2 || values.iter().any(|value| *value != values[0])
    };
    rows.iter()
        .map(|row| {
            let parts: Vec<String> = row
                .settings
                .iter()
                .filter(|(knob, _)| varies(knob))
                .map(|(knob, value)| format!("{knob}={value}"))
                .collect();
            if parts.is_empty() {
                "-".to_owned()
            } else {
                parts.join(", ")
            }
        })
        .collect()
}

/// Reads the eval summary written by the eval stage.
pub fn eval_summary(entry: &EntryReader) -> anyhow::Result<(String, MeanScores, Vec<SpeedRow>)> {
    let summary = entry.attribute(SUMMARY_ATTRIBUTE).ok_or_else(|| {
        anyhow::anyhow!(
            "eval entry {}: no \"{SUMMARY_ATTRIBUTE}\" attribute",
            entry.location()
        )
    })?;
    let sequence = summary
        .get("sequence")
        .and_then(|value| value.as_str())
        .unwrap_or("?")
        .to_owned();
    let means: MeanScores = read_summary_field(entry, "means")?;
    let speed: Vec<SpeedRow> = match entry.attribute(SPEED_ATTRIBUTE) {
        None => Vec::new(),
        Some(value) => serde_json::from_value(value).with_context(|| {
            format!(
                "eval entry {}: attribute {SPEED_ATTRIBUTE}",
                entry.location()
            )
        })?,
    };
    Ok((sequence, means, speed))
}

/// A loss curve found in a train entry: a float array along an `iteration` axis.
#[derive(Clone, Debug)]
pub struct Curve {
    pub name: String,
    pub points: Vec<(f64, f64)>,
}

/// Every 1D float array of `entry` whose axis is named `iteration` (except the axis
/// coordinate itself), plotted against the `iteration` array when there is one.
pub fn loss_curves(entry: &EntryReader) -> anyhow::Result<Vec<Curve>> {
    let arrays = &entry.manifest().arrays;
    let along_iterations: Vec<&String> = arrays
        .iter()
        .filter(|(_, record)| record.dimension_names == ["iteration"])
        .map(|(name, _)| name)
        .collect();
    // Curves are floats, their `iteration` axis an integer or float array.
    let read_f64 = |name: &str| -> anyhow::Result<Vec<f64>> {
        let dtype = entry.dtype(name)?;
        if !["float32", "float64", "uint32", "uint64", "int64"].contains(&dtype.as_str()) {
            anyhow::bail!("array \"{name}\" has type {dtype}");
        }
        let shape = entry.shape(name)?;
        entry.read_region_f64(name, &vec![0; shape.len()], &shape)
    };
    let x_axis = if arrays.contains_key("iteration") {
        Some(read_f64("iteration")?)
    } else {
        None
    };
    let mut curves = Vec::new();
    for name in along_iterations {
        if name == "iteration" {
            continue;
        }
        let dtype = entry.dtype(name)?;
        if dtype != "float32" && dtype != "float64" {
            continue;
        }
        let values = read_f64(name)?;
        let points = values
            .iter()
            .enumerate()
            .map(|(index, &value)| {
                let x = x_axis
                    .as_ref()
                    .and_then(|axis| axis.get(index).copied())
                    .unwrap_or(index as f64);
                (x, value)
            })
            .collect();
        curves.push(Curve {
            name: name.clone(),
            points,
        });
    }
    Ok(curves)
}

/// Training time of a train entry: its `wall_seconds` attribute (the training loop), else
/// the manifest's wall time of the whole stage.
pub fn training_seconds(entry: &EntryReader) -> f64 {
    entry
        .attribute("wall_seconds")
        .and_then(|value| value.as_f64())
        .unwrap_or(entry.manifest().wall_time_s)
}

/// State of one stage for the report.
struct StageState<'p> {
    spec: &'p StageSpec,
    id: EntryId,
    entry: Option<EntryReader>,
}

fn format_seconds(seconds: f64) -> String {
    if seconds < 60.0 {
        format!("{seconds:.1} s")
    } else {
        let minutes = (seconds / 60.0).floor();
        format!("{minutes:.0} min {:.0} s", seconds - minutes * 60.0)
    }
}

fn save_png(image: &image::RgbImage, path: &Path) -> anyhow::Result<()> {
    image
        .save(path)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// The line above the report's tables: the one command that recomputes every entry they
/// read (from the cache when present) and writes the report again.
pub fn reproduce_line(file: &Path) -> String {
    let file = file.display();
    format!("Reproduce: `pipeline run {file} && pipeline report {file}`")
}

/// Writes `report.md` and its PNGs into `out` and returns the Markdown path.
pub fn write_report(
    registry: &Registry,
    file: &Path,
    sets: &[String],
    cache: &Path,
    out: &Path,
) -> anyhow::Result<PathBuf> {
    let pipeline = Pipeline::load(file, registry, sets)?;
    let store = open_store(cache)?;
    write_report_for(registry, &pipeline, store.as_ref(), out)
}

/// [`write_report`] on a loaded pipeline and an open store.
pub fn write_report_for(
    registry: &Registry,
    pipeline: &Pipeline,
    store: &dyn Store,
    out: &Path,
) -> anyhow::Result<PathBuf> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let states = stage_states(registry, pipeline, store)?;
    let mut text = format!("# Report: {}\n\n", pipeline.file.display());
    let _ = writeln!(text, "{}\n", reproduce_line(&pipeline.file));
    if let Some(description) = &pipeline.description {
        let _ = writeln!(text, "{}\n", description.trim());
    }
    let _ = writeln!(text, "Cache: {}\n", store.describe());

    let (rows, seed_runs) = eval_rows(&states)?;
    let missing_evals: Vec<&str> = states
        .iter()
        .filter(|state| state.spec.kind == EVAL_KIND && state.entry.is_none())
        .map(|state| state.spec.name.as_str())
        .collect();

    write_metrics(&mut text, &rows)?;
    write_garment_region(&mut text, &states)?;
    if let Some(table) = ablation_table(&seed_runs)? {
        text.push_str(
            "## Per row: subsets and context probes (mean ± std over seeds)\n\n\
             Eval stages whose train stages differ only in `seed` form one row (a row of one \
             seed shows its values without a spread): PSNR (dB) on all test images, the \
             history frames, each protocol and the training images, and the PSNR change when \
             the motion context (skeleton motion, velocities) is zeroed or taken from another \
             frame (`-`: the row has no such inputs or subset), and the training time.\n\n",
        );
        text.push_str(&table);
        text.push('\n');
    }
    if !missing_evals.is_empty() {
        let _ = writeln!(
            text,
            "Not in the cache (run the pipeline first): {}\n",
            missing_evals.join(", ")
        );
    }

    write_pictures(&mut text, &states, out)?;
    if rows.len() > 1 {
        write_tradeoff(&mut text, &rows, out)?;
    }
    let curve_section = loss_curve_section(&states, out)?;
    if !curve_section.is_empty() {
        text.push_str("## Loss curves\n\n");
        text.push_str(&curve_section);
    }
    write_stages(&mut text, &states)?;
    let path = out.join("report.md");
    std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))?;
    Ok(path)
}

/// Each stage of the pipeline in topological order, with its entry when it is in the cache.
fn stage_states<'p>(
    registry: &Registry,
    pipeline: &'p Pipeline,
    store: &dyn Store,
) -> anyhow::Result<Vec<StageState<'p>>> {
    let keys = compute_keys(pipeline, registry, store)?;
    let mut states = Vec::new();
    for &index in pipeline.order() {
        let spec = &pipeline.stages[index];
        let id = EntryId::new(&spec.kind, &keys[&spec.name].key);
        let entry = match store.entry_state(&id)? {
            // Verified as `run` verifies it, under the read lease `gc` respects: a report
            // never shows numbers from a tampered or damaged entry.
            EntryState::Complete => Some(
                seqavatar_engine::open_leased_verified(store, &id)
                    .with_context(|| format!("stage \"{}\": cannot report {id}", spec.name))?,
            ),
            _ => None,
        };
        states.push(StageState { spec, id, entry });
    }
    Ok(states)
}

/// Metrics of every eval stage in the cache: a row each, and a seed run each where a train
/// stage feeds it.
fn eval_rows(states: &[StageState<'_>]) -> anyhow::Result<(Vec<EvalRow>, Vec<SeedRun>)> {
    let by_name: BTreeMap<&str, &StageState> = states
        .iter()
        .map(|state| (state.spec.name.as_str(), state))
        .collect();
    let mut rows: Vec<EvalRow> = Vec::new();
    let mut seed_runs: Vec<SeedRun> = Vec::new();
    for state in states.iter().filter(|state| state.spec.kind == EVAL_KIND) {
        let Some(entry) = &state.entry else {
            continue;
        };
        let (sequence, means, speed) = eval_summary(entry)?;
        let train_state = state
            .spec
            .inputs
            .iter()
            .filter_map(|input| by_name.get(input.as_str()))
            .find(|input| input.spec.kind == "train");
        let train_entry = train_state.and_then(|train| train.entry.as_ref());
        if let Some(train) = train_state {
            seed_runs.push(SeedRun {
                train_stage: train.spec.name.clone(),
                train_config: train.spec.config.clone(),
                train_inputs: train.spec.inputs.clone(),
                summary: entry
                    .attribute(SUMMARY_ATTRIBUTE)
                    .unwrap_or(serde_json::Value::Null),
                train_seconds: train.entry.as_ref().map(training_seconds),
            });
        }
        rows.push(EvalRow {
            eval_stage: state.spec.name.clone(),
            train_stage: train_state.map(|train| train.spec.name.clone()),
            settings: train_state
                .map(|train| knob_values(&train.spec.config))
                .unwrap_or_default(),
            sequence,
            means,
            train_seconds: train_entry.map(training_seconds),
            fps: speed
                .iter()
                .max_by_key(|row| u64::from(row.width) * u64::from(row.height))
                .map(|row| row.fps),
            speed,
        });
    }
    Ok((rows, seed_runs))
}

/// The "Metrics" section: the mean scores of each eval stage and its rendering speed.
fn write_metrics(text: &mut String, rows: &[EvalRow]) -> anyhow::Result<()> {
    text.push_str("## Metrics\n\n");
    if rows.is_empty() {
        text.push_str("No eval stage of this pipeline is in the cache yet.\n\n");
    } else {
        text.push_str(
            "Paper protocol (docs/method.md): render outside the bound mask and ground truth \
             outside the foreground mask set to background, PSNR over the whole image, SSIM \
             with an 11 px Gaussian window (sigma 1.5), LPIPS x 1000 (\"unavailable\" when no \
             weights were configured).\n\n",
        );
        let mut headers = vec!["eval stage"];
        headers.extend(MEAN_TABLE_HEADERS);
        let table: Vec<Vec<String>> = rows
            .iter()
            .map(|row| {
                let mut cells = vec![row.eval_stage.clone()];
                cells.extend(crate::evaluate::mean_table_row(&row.sequence, &row.means));
                cells
            })
            .collect();
        text.push_str(&markdown_table(&headers, &table).map_err(anyhow::Error::msg)?);
        text.push('\n');
        for row in rows {
            if row.speed.is_empty() {
                continue;
            }
            let _ = writeln!(
                text,
                "Rendering speed of `{}` (whole render path, networks included):\n",
                row.eval_stage
            );
            let speed_rows: Vec<Vec<String>> = row
                .speed
                .iter()
                .map(|speed| {
                    vec![
                        format!("{} x {}", speed.width, speed.height),
                        speed.frames.to_string(),
                        format_metric(Some(speed.fps), 2),
                        format_metric(Some(1000.0 * speed.seconds / speed.frames as f64), 1),
                    ]
                })
                .collect();
            text.push_str(
                &markdown_table(&["resolution", "frames", "FPS", "ms / frame"], &speed_rows)
                    .map_err(anyhow::Error::msg)?,
            );
            text.push('\n');
        }
    }
    Ok(())
}

/// The "Garment region" section: for each eval stage in the cache, its garment-region table
/// (per subset, the whole-image figures beside the garment region's), or the sentence saying
/// its dataset has none.
fn write_garment_region(text: &mut String, states: &[StageState<'_>]) -> anyhow::Result<()> {
    let evals: Vec<(&str, &EntryReader)> = states
        .iter()
        .filter(|state| state.spec.kind == EVAL_KIND)
        .filter_map(|state| Some((state.spec.name.as_str(), state.entry.as_ref()?)))
        .collect();
    if evals.is_empty() {
        return Ok(());
    }
    text.push_str(
        "## Garment region

",
    );
    text.push_str(
        "The same protocol on the garment region's pixels only (the ingest entry's \
         `garment_masks`: the synthetic scene's skirt, ZJU-MoCap's CIHP clothing labels): PSNR \
         over the region's pixels, SSIM as the mean of the SSIM map over them, LPIPS on the \
         crop of the region's bounding box; images whose region is empty are left out and \
         counted.\n\n",
    );
    for (name, entry) in evals {
        let field = |key| read_summary_field::<serde_json::Value>(entry, key);
        let means: MeanScores = read_summary_field(entry, "means")?;
        let subsets = read_summary_field::<Option<SubsetScores>>(entry, "subsets")?;
        let subsets = subsets.unwrap_or_default();
        let region = field("garment_region")?;
        match (region.as_str(), garment_table(&means, &subsets)) {
            (Some(region), Some(table)) => {
                let lpips = field("garment_lpips")?;
                let lpips = lpips.as_str().unwrap_or("unavailable (no LPIPS weights)");
                let _ = writeln!(
                    text,
                    "`{name}`: garment region `{region}`; region LPIPS: {lpips}.\n"
                );
                text.push_str(&table);
                text.push('\n');
            }
            _ => {
                let _ = writeln!(text, "`{name}`: {NO_GARMENT_REGION}.\n");
            }
        }
    }
    Ok(())
}

/// Pictures of each eval entry: its PNGs in a folder named after the stage, the contact sheet
/// shown.
fn write_pictures(text: &mut String, states: &[StageState<'_>], out: &Path) -> anyhow::Result<()> {
    for state in states.iter().filter(|state| state.spec.kind == EVAL_KIND) {
        let Some(entry) = &state.entry else {
            continue;
        };
        let folder = out.join(&state.spec.name);
        std::fs::create_dir_all(&folder)
            .with_context(|| format!("cannot create {}", folder.display()))?;
        let written = seqavatar_schema::eval::export_pngs(entry, &folder)?;
        let _ = writeln!(
            text,
            "### {}\n\n![contact sheet of {}]({}/contact_sheet.png)\n\n{} renders and error maps in `{}/`.\n",
            state.spec.name, state.spec.name, state.spec.name, written, state.spec.name
        );
    }
    Ok(())
}

/// Sweep: one row per eval stage with the knobs that differ, and the Pareto plots.
fn write_tradeoff(text: &mut String, rows: &[EvalRow], out: &Path) -> anyhow::Result<()> {
    text.push_str("## Trade-off\n\n");
    let settings = varying_settings(rows);
    let table: Vec<Vec<String>> = rows
        .iter()
        .zip(&settings)
        .map(|(row, settings)| {
            vec![
                row.train_stage.clone().unwrap_or_else(|| "-".to_owned()),
                settings.clone(),
                format_metric(Some(row.means.psnr), 2),
                format_metric(Some(row.means.ssim), 4),
                format_lpips_x1000(row.means.lpips_vgg),
                row.train_seconds
                    .map(format_seconds)
                    .unwrap_or_else(|| "n/a".to_owned()),
                format_metric(row.fps, 2),
            ]
        })
        .collect();
    text.push_str(
        &markdown_table(
            &[
                "train stage",
                "settings (those that differ)",
                "PSNR",
                "SSIM",
                "LPIPS-VGG x1000",
                "train time",
                "FPS",
            ],
            &table,
        )
        .map_err(anyhow::Error::msg)?,
    );
    text.push('\n');
    let time_points: Vec<(f64, f64)> = rows
        .iter()
        .map(|row| (row.train_seconds.unwrap_or(f64::NAN), row.means.psnr))
        .collect();
    // Cost axis of the FPS plot: milliseconds per frame (lower is better).
    let fps_points: Vec<(f64, f64)> = rows
        .iter()
        .map(|row| (row.fps.map_or(f64::NAN, |fps| 1000.0 / fps), row.means.psnr))
        .collect();
    for (points, name, what) in [
        (
            &time_points,
            "pareto_psnr_time.png",
            "PSNR (dB, y) vs training time (s, x)",
        ),
        (
            &fps_points,
            "pareto_psnr_fps.png",
            "PSNR (dB, y) vs render time per frame (ms, x; 1000 / FPS)",
        ),
    ] {
        let front = pareto_front(points);
        let plot = pareto_plot(points, &front);
        save_png(&plot, &out.join(name))?;
        let names: Vec<String> = front
            .iter()
            .map(|&index| rows[index].train_stage.clone().unwrap_or_default())
            .collect();
        let _ = writeln!(
            text,
            "![{what}]({name})\n\n{what}; one colour per run in table order, the Pareto front joined in black: {}.\n",
            names.join(", ")
        );
    }
    let legend: Vec<Vec<String>> = rows
        .iter()
        .enumerate()
        .map(|(index, row)| {
            let color = palette(index).0;
            vec![
                row.train_stage.clone().unwrap_or_default(),
                format!("#{:02x}{:02x}{:02x}", color[0], color[1], color[2]),
            ]
        })
        .collect();
    text.push_str(&markdown_table(&["run", "colour"], &legend).map_err(anyhow::Error::msg)?);
    text.push('\n');
    Ok(())
}

/// Loss curves of every train entry (empty when none has any).
fn loss_curve_section(states: &[StageState<'_>], out: &Path) -> anyhow::Result<String> {
    let mut curve_section = String::new();
    for state in states.iter().filter(|state| state.spec.kind == "train") {
        let Some(entry) = &state.entry else {
            continue;
        };
        let curves = loss_curves(entry)?;
        // Losses on a log axis; PSNR (dB) and counts (Gaussians) each on their own linear
        // plot, since they share neither unit nor scale with the losses.
        let (losses, others): (Vec<Curve>, Vec<Curve>) = curves
            .into_iter()
            .partition(|curve| !curve.name.contains("psnr") && !curve.name.contains("gaussians"));
        let mut groups: Vec<(String, Vec<Curve>, bool)> = Vec::new();
        if !losses.is_empty() {
            groups.push(("loss".to_owned(), losses, true));
        }
        for curve in others {
            let label = curve.name.trim_start_matches("loss_").to_owned();
            groups.push((label, vec![curve], false));
        }
        if groups.is_empty() {
            continue;
        }
        let _ = writeln!(
            curve_section,
            "### {}
",
            state.spec.name
        );
        for (label, curves, log_y) in groups {
            let series: Vec<Series> = curves
                .iter()
                .enumerate()
                .map(|(index, curve)| Series {
                    name: curve.name.clone(),
                    points: curve.points.clone(),
                    color: palette(index),
                })
                .collect();
            let plot = report::plot(
                &series,
                PlotOptions {
                    log_y,
                    ..PlotOptions::default()
                },
                &[],
            );
            let name = format!("{label}_{}.png", state.spec.name);
            save_png(&plot, &out.join(&name))?;
            let legend: Vec<String> = curves
                .iter()
                .enumerate()
                .map(|(index, curve)| {
                    let color = palette(index).0;
                    let last = curve.points.last().map(|point| point.1);
                    format!(
                        "`{}` (#{:02x}{:02x}{:02x}, last {})",
                        curve.name,
                        color[0],
                        color[1],
                        color[2],
                        format_metric(last, 5)
                    )
                })
                .collect();
            let _ = writeln!(
                curve_section,
                "![{label} of {}]({name})\n\n{} scale against iteration: {}.\n",
                state.spec.name,
                if log_y { "Log" } else { "Linear" },
                legend.join(", ")
            );
        }
    }
    Ok(curve_section)
}

/// Timing and cache reuse: the "Stages" section.
fn write_stages(text: &mut String, states: &[StageState<'_>]) -> anyhow::Result<()> {
    text.push_str("## Stages\n\n");
    let mut references: BTreeMap<&EntryId, Vec<&str>> = BTreeMap::new();
    for state in states {
        references
            .entry(&state.id)
            .or_default()
            .push(state.spec.name.as_str());
    }
    let timing: Vec<Vec<String>> = states
        .iter()
        .map(|state| {
            let [status, time, finished, backend] = match &state.entry {
                None => ["missing", "-", "-", "-"].map(str::to_owned),
                Some(entry) => {
                    let manifest = entry.manifest();
                    let backend = seqavatar_engine::backend_of(&manifest.log)
                        .unwrap_or_else(|| "-".to_owned());
                    [
                        "cached".to_owned(),
                        format_seconds(manifest.wall_time_s),
                        manifest.finished_at.clone(),
                        backend,
                    ]
                }
            };
            let consumers: Vec<&str> = states
                .iter()
                .filter(|other| other.spec.inputs.contains(&state.spec.name))
                .map(|other| other.spec.name.as_str())
                .collect();
            vec![
                state.spec.name.clone(),
                state.spec.kind.clone(),
                state.id.key.chars().take(12).collect(),
                status,
                time,
                finished,
                backend,
                if consumers.is_empty() {
                    "-".to_owned()
                } else {
                    consumers.join(", ")
                },
            ]
        })
        .collect();
    text.push_str(
        &markdown_table(
            &[
                "stage",
                "kind",
                "key",
                "entry",
                "compute time",
                "finished",
                "backend",
                "read by",
            ],
            &timing,
        )
        .map_err(anyhow::Error::msg)?,
    );
    let cached = states.iter().filter(|state| state.entry.is_some()).count();
    let total_seconds: f64 = references
        .keys()
        .filter_map(|id| {
            states
                .iter()
                .find(|state| &&state.id == id)
                .and_then(|state| state.entry.as_ref())
                .map(|entry| entry.manifest().wall_time_s)
        })
        .sum();
    let _ = writeln!(
        text,
        "\n{cached} of {} stages have their entry in the cache; {} distinct entries, {} s of \
         compute in all. Each entry is computed once and read from the cache by every stage \
         listed under \"read by\" (one ingest and one motion entry serve every run of a sweep).",
        states.len(),
        references.len(),
        format_metric(Some(total_seconds), 1)
    );
    let shared: Vec<String> = references
        .iter()
        .filter(|(_, names)| names.len() > 1)
        .map(|(id, names)| format!("`{id}` is shared by {}", names.join(", ")))
        .collect();
    if !shared.is_empty() {
        let _ = writeln!(text, "Shared entries (cache hits): {}.", shared.join("; "));
    }
    Ok(())
}

/// A scatter of (cost, PSNR) points, one colour per run, with the Pareto front in black.
pub fn pareto_plot(points: &[(f64, f64)], front: &[usize]) -> image::RgbImage {
    let series: Vec<Series> = points
        .iter()
        .enumerate()
        .map(|(index, &point)| Series {
            name: index.to_string(),
            points: vec![point],
            color: palette(index),
        })
        .collect();
    let highlight: Vec<(f64, f64)> = front.iter().map(|&index| points[index]).collect();
    report::plot(
        &series,
        PlotOptions {
            lines: false,
            ..PlotOptions::default()
        },
        &highlight,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn row(settings: &[(&str, &str)]) -> EvalRow {
        EvalRow {
            eval_stage: "eval".to_owned(),
            train_stage: Some("train".to_owned()),
            settings: settings
                .iter()
                .map(|(knob, value)| ((*knob).to_owned(), (*value).to_owned()))
                .collect(),
            sequence: "synthetic".to_owned(),
            means: MeanScores {
                images: 1,
                psnr: 20.0,
                ssim: 0.9,
                lpips_vgg: None,
                lpips_alex: None,
                garment: None,
            },
            train_seconds: Some(1.0),
            fps: Some(2.0),
            speed: Vec::new(),
        }
    }

    #[test]
    fn sweep_tables_show_only_the_knobs_that_vary() {
        let rows = [
            row(&[
                ("preset", "fast"),
                ("iterations", "400"),
                ("trunk_width", "64"),
            ]),
            row(&[
                ("preset", "fast"),
                ("iterations", "800"),
                ("trunk_width", "64"),
            ]),
            row(&[
                ("preset", "fast"),
                ("iterations", "400"),
                ("trunk_width", "128"),
            ]),
        ];
        assert_eq!(
            varying_settings(&rows),
            [
                "iterations=400, trunk_width=64",
                "iterations=800, trunk_width=64",
                "iterations=400, trunk_width=128"
            ]
        );
        // A single run shows every knob; identical runs show none.
        assert_eq!(
            varying_settings(&rows[..1]),
            ["preset=fast, iterations=400, trunk_width=64"]
        );
        assert_eq!(
            varying_settings(&[rows[0].clone(), rows[0].clone()]),
            ["-", "-"]
        );
    }
}
