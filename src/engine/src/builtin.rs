//! The built-in `test_arrays` stage kind: small but real computations over real arrays, used
//! by the engine tests (kill mid-stage, concurrency, corruption, resume). Compiled only for
//! tests (feature `test-stages`): its `count_file` appends to any path it is given.

use std::fs::OpenOptions;
use std::io::Write as _;
use std::time::Duration;

use anyhow::Context as _;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::config::{ConfigError, parse_config};
use crate::entry::EntryReader;
use crate::runner::StageContext;
use crate::{PictureKind, PictureOptions, StageKind};

/// Writes `values[i] = seed + i + sum of the inputs' values[i]` (float64, `size` elements in
/// chunks of `chunk`) and a `size x size` RGB `image` derived from it.
pub struct TestArrays;

/// Config of `test_arrays`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TestArraysConfig {
    /// Number of values (and the image side).
    pub size: u64,
    /// Chunk length of `values`.
    pub chunk: u64,
    /// Added to every value.
    pub seed: i64,
    /// Total time spent sleeping, spread over `steps`, so tests can kill the stage mid-way.
    pub sleep_ms: u64,
    /// Resumable steps; finished steps are recorded in the work folder.
    pub steps: u32,
    /// Fail (with an error) when reaching this step.
    pub fail_at: Option<u32>,
    /// Append one line per actual computation to this file.
    pub count_file: Option<String>,
}

impl Default for TestArraysConfig {
    fn default() -> Self {
        Self {
            size: 16,
            chunk: 4,
            seed: 0,
            sleep_ms: 0,
            steps: 1,
            fail_at: None,
            count_file: None,
        }
    }
}

const STEPS_DONE_FILE: &str = "steps_done";

impl StageKind for TestArrays {
    type Config = TestArraysConfig;

    fn kind(&self) -> &'static str {
        "test_arrays"
    }

    fn version(&self) -> u32 {
        1
    }

    fn input_kinds(&self) -> &'static [&'static str] {
        &["test_arrays"]
    }

    fn resolve_config(&self, raw: &serde_json::Value) -> Result<TestArraysConfig, ConfigError> {
        let config: TestArraysConfig = parse_config(raw)?;
        if config.size == 0 || config.size > 4096 {
            return Err(ConfigError::at_key("size", "must be in 1..=4096"));
        }
        if config.chunk == 0 {
            return Err(ConfigError::at_key("chunk", "must be at least 1"));
        }
        if config.steps == 0 {
            return Err(ConfigError::at_key("steps", "must be at least 1"));
        }
        Ok(config)
    }

    fn run(&self, config: &TestArraysConfig, ctx: &mut StageContext<'_>) -> anyhow::Result<()> {
        if let Some(count_file) = &config.count_file {
            let mut file = OpenOptions::new()
                .create(true)
                .append(true)
                .open(count_file)
                .with_context(|| format!("count_file {count_file}"))?;
            file.write_all(format!("{} {}\n", ctx.stage_name(), ctx.key()).as_bytes())
                .with_context(|| format!("count_file {count_file}"))?;
        }
        let steps_path = ctx.work_dir().join(STEPS_DONE_FILE);
        let mut done: u32 = std::fs::read_to_string(&steps_path)
            .ok()
            .and_then(|text| text.trim().parse().ok())
            .unwrap_or(0);
        if done > 0 {
            ctx.log(&format!("resuming at step {done} of {}", config.steps));
        }
        let bar = ctx.progress_bar(u64::from(config.steps), "steps");
        bar.set_position(u64::from(done));
        let step_sleep = Duration::from_millis(config.sleep_ms / u64::from(config.steps));
        while done < config.steps {
            if config.fail_at == Some(done) {
                anyhow::bail!("failing at step {done} as configured (fail_at)");
            }
            std::thread::sleep(step_sleep);
            done += 1;
            std::fs::write(&steps_path, done.to_string())
                .with_context(|| format!("cannot record progress in {}", steps_path.display()))?;
            bar.set_position(u64::from(done));
        }
        bar.finish_and_clear();

        let size = usize::try_from(config.size).context("size")?;
        let mut values: Vec<f64> = (0..size)
            .map(|index| config.seed as f64 + index as f64)
            .collect();
        for input in ctx.inputs() {
            let upstream = input.read::<f64>("values")?;
            anyhow::ensure!(
                upstream.shape == [size],
                "input {} has {} values, this stage has size {size}",
                input.stage_name(),
                upstream.len()
            );
            for (value, addend) in values.iter_mut().zip(&upstream.data) {
                *value += addend;
            }
        }
        let output = ctx.output();
        let writer =
            output.create_array::<f64>("values", &["index"], &[config.size], &[config.chunk])?;
        let chunk = usize::try_from(config.chunk).context("chunk")?;
        values.par_chunks(chunk).enumerate().try_for_each(
            |(chunk_index, block)| -> anyhow::Result<()> {
                let mut padded = block.to_vec();
                padded.resize(chunk, 0.0);
                writer.write_chunk(&[chunk_index as u64], &padded)
            },
        )?;
        output.set_array_attribute("values", "units", serde_json::json!("counts"))?;

        let mut image = vec![0u8; size * size * 3];
        for row in 0..size {
            for col in 0..size {
                let pixel = &mut image[(row * size + col) * 3..][..3];
                pixel[0] = (values[col].rem_euclid(256.0)) as u8;
                pixel[1] = (values[row].rem_euclid(256.0)) as u8;
                pixel[2] = ((row + col) % 256) as u8;
            }
        }
        output.write_whole::<u8>(
            "image",
            &["height", "width", "channel"],
            &[config.size, config.size, 3],
            &image,
        )?;
        output.set_attribute("sum", serde_json::json!(values.iter().sum::<f64>()))?;
        ctx.log("backend: cpu");
        Ok(())
    }

    fn pictures(&self) -> Vec<PictureKind> {
        vec![PictureKind {
            name: "values",
            description: "values as a bar chart (option: height)",
        }]
    }

    fn draw_picture(
        &self,
        entry: &EntryReader,
        picture: &str,
        options: &PictureOptions,
    ) -> anyhow::Result<image::RgbImage> {
        if picture != "values" {
            return Err(crate::unknown_picture(self, picture));
        }
        let height = options.get_u64("height", 32)?.clamp(1, 4096) as u32;
        let values = entry.read::<f64>("values")?;
        let maximum = values
            .data
            .iter()
            .copied()
            .filter(|value| value.is_finite())
            .fold(0.0f64, f64::max);
        let width = values.len().max(1) as u32;
        let mut picture = image::RgbImage::new(width, height);
        for (column, &value) in values.data.iter().enumerate() {
            let filled = if maximum > 0.0 {
                ((value.max(0.0) / maximum) * f64::from(height)).round() as u32
            } else {
                0
            };
            for row in 0..filled.min(height) {
                picture.put_pixel(column as u32, height - 1 - row, image::Rgb([255, 255, 255]));
            }
        }
        Ok(picture)
    }
}
