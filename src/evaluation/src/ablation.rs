//! The seed-averaged ablation table of `pipeline report`: eval stages whose train stages differ
//! only in `seed` (same config otherwise, same input stages) form one row, reported as mean ±
//! sample standard deviation over the seeds for all test images, the history frames and the
//! others (whole image, and the garment region where ingest has one), each protocol, the
//! training images, and the context probes' PSNR changes ([`crate::context_probe`]).

use std::collections::BTreeMap;

use serde_json::Value;

use crate::report::markdown_table;

/// One evaluated training run.
#[derive(Clone, Debug, PartialEq)]
pub struct SeedRun {
    /// The train stage's name.
    pub train_stage: String,
    /// The train stage's config as written (before presets are filled in).
    pub train_config: Value,
    /// The train stage's input stages (by name): the ablation's oracle row trains like row
    /// (e) on another motion entry, so runs are seeds of one row only when these match too.
    pub train_inputs: Vec<String>,
    /// The eval entry's `summary` attribute.
    pub summary: Value,
    /// Training wall time (the train entry's `wall_seconds`), when known.
    pub train_seconds: Option<f64>,
}

/// The config without its `seed` as canonical JSON, and the input stages: runs with the same
/// key are seeds of one row.
pub fn group_key(config: &Value, inputs: &[String]) -> String {
    let mut config = config.clone();
    if let Some(map) = config.as_object_mut() {
        map.remove("seed");
    }
    // serde_json's maps are sorted, so equal configs print equally.
    format!("{config} {inputs:?}")
}

/// Mean and sample standard deviation (0 for one value); `None` for no values.
pub fn mean_std(values: &[f64]) -> Option<(f64, f64)> {
    if values.is_empty() {
        return None;
    }
    let n = values.len() as f64;
    let mean = values.iter().sum::<f64>() / n;
    let var = if values.len() > 1 {
        values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    Some((mean, var.sqrt()))
}

/// The columns of the table: header and where the value sits in an eval summary.
const COLUMNS: [(&str, Metric); 12] = [
    ("all test images", Metric::Path(&["means", "psnr"])),
    (
        "history frames",
        Metric::Path(&["subsets", "history", "psnr"]),
    ),
    (
        "other frames",
        Metric::Path(&["subsets", "not_history", "psnr"]),
    ),
    (
        "garment region, history frames",
        Metric::Path(&["subsets", "history", "garment", "psnr"]),
    ),
    (
        "garment region, other frames",
        Metric::Path(&["subsets", "not_history", "garment", "psnr"]),
    ),
    (
        "held-out cameras",
        Metric::Path(&["subsets", "held_out_cameras", "psnr"]),
    ),
    (
        "held-out frames",
        Metric::Path(&["subsets", "held_out_frames", "psnr"]),
    ),
    ("training images", Metric::Path(&["train_image_psnr"])),
    (
        "context zeroed: change, history frames",
        Metric::Probe("zeroed", &["history"]),
    ),
    (
        "context zeroed: change, garment region, history frames",
        Metric::Probe("zeroed", &["garment", "history"]),
    ),
    (
        "context zeroed: change, all",
        Metric::Probe("zeroed", &["all"]),
    ),
    (
        "context from another frame: change, history frames",
        Metric::Probe("from_frame", &["history"]),
    ),
];

#[derive(Clone, Copy)]
enum Metric {
    /// A number at this path of the summary.
    Path(&'static [&'static str]),
    /// `psnr_change.<path>` of the context probe of this kind.
    Probe(&'static str, &'static [&'static str]),
}

impl Metric {
    fn read(self, summary: &Value) -> Option<f64> {
        match self {
            Metric::Path(path) => path
                .iter()
                .try_fold(summary, |value, key| value.get(key))
                .and_then(Value::as_f64),
            Metric::Probe(kind, path) => summary
                .get("context_probes")?
                .as_array()?
                .iter()
                .find(|probe| {
                    probe
                        .get("probe")
                        .and_then(|p| p.get("kind"))
                        .and_then(Value::as_str)
                        == Some(kind)
                })?
                .get("psnr_change")
                .and_then(|change| path.iter().try_fold(change, |value, key| value.get(key)))?
                .as_f64(),
        }
    }
}

/// The longest common prefix of the names, without a trailing seed suffix (`_s` and the
/// digits of a seed number, or `_`); digits that belong to the row's own name stay
/// (`train_iter3000` and `train_iter3000_s2` are `train_iter3000`).
fn common_label(names: &[&str]) -> String {
    let first = names.first().copied().unwrap_or("");
    let mut end = first.len();
    for name in &names[1..] {
        end = end.min(
            first
                .chars()
                .zip(name.chars())
                .take_while(|(a, b)| a == b)
                .map(|(a, _)| a.len_utf8())
                .sum(),
        );
    }
    let mut label = &first[..end];
    if names.len() > 1 {
        let without_digits = label.trim_end_matches(|c: char| c.is_ascii_digit());
        if let Some(stripped) = without_digits.strip_suffix("_s") {
            label = stripped;
        }
        label = label.trim_end_matches('_');
    }
    if label.is_empty() {
        first.to_owned()
    } else {
        label.to_owned()
    }
}

/// The Markdown table of the ablation, or `None` when no row has more than one seed and no run
/// has a history-frame subset (a sweep on a history scene gets the table with one seed per row:
/// its main table shows only the PSNR on all images). Rows keep the order of their first run;
/// cells are `mean ± std` in dB (changes signed) over two or more seeds, the value itself for
/// one, `-` where no run has the value.
pub fn ablation_table(runs: &[SeedRun]) -> anyhow::Result<Option<String>> {
    let mut order: Vec<String> = Vec::new();
    let mut groups: BTreeMap<String, Vec<&SeedRun>> = BTreeMap::new();
    for run in runs {
        let key = group_key(&run.train_config, &run.train_inputs);
        if !groups.contains_key(&key) {
            order.push(key.clone());
        }
        groups.entry(key).or_default().push(run);
    }
    let has_history = runs
        .iter()
        .any(|run| COLUMNS[1].1.read(&run.summary).is_some());
    if groups.values().all(|group| group.len() < 2) && !has_history {
        return Ok(None);
    }
    let mut headers = vec!["row", "seeds"];
    headers.extend(COLUMNS.iter().map(|(name, _)| *name));
    headers.push("train time (s)");
    let mut table = Vec::new();
    for key in &order {
        let group = &groups[key];
        let names: Vec<&str> = group.iter().map(|run| run.train_stage.as_str()).collect();
        let mut cells = vec![common_label(&names), group.len().to_string()];
        for (_, metric) in &COLUMNS {
            let values: Vec<f64> = group
                .iter()
                .filter_map(|run| metric.read(&run.summary))
                .filter(|value| value.is_finite())
                .collect();
            let signed = matches!(metric, Metric::Probe(..));
            // Changes get a third decimal: "no effect" and "a few hundredths" differ.
            cells.push(match (mean_std(&values), values.len()) {
                (None, _) => "-".to_owned(),
                (Some((mean, _)), 1) if signed => format!("{mean:+.3}"),
                (Some((mean, _)), 1) => format!("{mean:.2}"),
                (Some((mean, std)), _) if signed => format!("{mean:+.3} ± {std:.3}"),
                (Some((mean, std)), _) => format!("{mean:.2} ± {std:.2}"),
            });
        }
        let seconds: Vec<f64> = group.iter().filter_map(|run| run.train_seconds).collect();
        cells.push(match (mean_std(&seconds), seconds.len()) {
            (None, _) => "-".to_owned(),
            (Some((mean, _)), 1) => format!("{mean:.0}"),
            (Some((mean, std)), _) => format!("{mean:.0} ± {std:.0}"),
        });
        table.push(cells);
    }
    Ok(Some(
        markdown_table(&headers, &table).map_err(anyhow::Error::msg)?,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn run(name: &str, context: &str, seed: u64, all: f64, history: f64, zeroed: f64) -> SeedRun {
        SeedRun {
            train_stage: name.to_owned(),
            train_config: json!({"preset": "fast", "seed": seed, "motion_context": context}),
            train_inputs: vec!["ingest".into(), "motion".into()],
            summary: json!({
                "means": {"psnr": all},
                "subsets": {
                    "history": {"psnr": history, "garment": {"psnr": history - 14.0}},
                    "held_out_frames": null
                },
                "train_image_psnr": 30.0,
                "context_probes": [
                    {"probe": {"kind": "zeroed"}, "psnr_change": {"all": zeroed / 2.0, "history": zeroed,
                                                                  "garment": {"all": zeroed, "history": 2.0 * zeroed}}},
                    {"probe": {"kind": "from_frame", "offset": 50}, "psnr_change": {"all": 0.0, "history": -0.1}}
                ],
            }),
            train_seconds: Some(100.0 * seed as f64),
        }
    }

    #[test]
    fn mean_and_sample_standard_deviation() {
        let (mean, std) = mean_std(&[1.0, 2.0, 3.0, 4.0]).unwrap();
        assert_eq!(mean, 2.5);
        assert!((std - (5.0f64 / 3.0).sqrt()).abs() < 1e-12);
        assert_eq!(mean_std(&[7.0]), Some((7.0, 0.0)));
        assert_eq!(mean_std(&[]), None);
    }

    #[test]
    fn seeds_of_one_config_form_one_row() {
        let runs = [
            run("train_b_pose_s1", "pose", 1, 27.0, 26.0, 0.0),
            run("train_e_multiscale_s1", "multiscale", 1, 28.0, 27.0, -1.0),
            run("train_b_pose_s2", "pose", 2, 27.2, 26.4, 0.0),
            run("train_e_multiscale_s2", "multiscale", 2, 28.4, 27.0, -3.0),
        ];
        let table = ablation_table(&runs).unwrap().unwrap();
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(lines.len(), 4, "{table}");
        assert!(lines[2].starts_with(
            "| train_b_pose | 2 | 27.10 ± 0.14 | 26.20 ± 0.28 | - | 12.20 ± 0.28 | - |"
        ));
        assert!(lines[3].starts_with("| train_e_multiscale | 2 | 28.20 ± 0.28 | 27.00 ± 0.00 |"));
        // Missing subsets are "-", changes are signed.
        assert!(
            lines[3].ends_with(
                "| - | - | 30.00 ± 0.00 | -2.000 ± 1.414 | -4.000 ± 2.828 | -1.000 ± 0.707 | -0.100 ± 0.000 | 150 ± 71 |"
            ),
            "{table}"
        );
        // The oracle row: (e)'s config on another motion entry is a row of its own.
        let mut oracle = runs.to_vec();
        for run in &mut oracle[2..] {
            run.train_inputs = vec!["ingest".into(), "motion_oracle".into()];
        }
        let table = ablation_table(&oracle).unwrap().unwrap();
        assert_eq!(table.lines().count(), 6, "{table}");
        // One run per config with history subsets (a sweep on the history scene): the table,
        // values without a spread.
        let single = ablation_table(&runs[..2]).unwrap().unwrap();
        let lines: Vec<&str> = single.lines().collect();
        assert_eq!(lines.len(), 4, "{single}");
        assert!(
            lines[2].starts_with(
                "| train_b_pose_s1 | 1 | 27.00 | 26.00 | - | 12.00 | - | - | - | 30.00 | +0.000 |"
            ),
            "{single}"
        );
        assert!(lines[3].ends_with("| -0.100 | 100 |"), "{single}");
        // One run per config and no history frames: no ablation table.
        let plain: Vec<SeedRun> = runs[..2]
            .iter()
            .cloned()
            .map(|mut run| {
                run.summary["subsets"] = json!({});
                run
            })
            .collect();
        assert_eq!(ablation_table(&plain).unwrap(), None);
    }

    #[test]
    fn labels_drop_the_seed_suffix() {
        assert_eq!(
            common_label(&["train_c_s1", "train_c_s2", "train_c_s3"]),
            "train_c"
        );
        assert_eq!(common_label(&["a_seed1", "a_seed2"]), "a_seed");
        assert_eq!(common_label(&["x_s12", "x_s13"]), "x");
        assert_eq!(
            common_label(&["train_iter3000", "train_iter3000_s2", "train_iter3000_s1"]),
            "train_iter3000"
        );
        assert_eq!(common_label(&["only"]), "only");
        assert_eq!(common_label(&["x1", "y1"]), "x1");
    }
}
