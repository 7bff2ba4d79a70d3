//! Pipeline files: YAML parsing, validation (unknown keys, wrong types, missing inputs,
//! unknown kinds, cycles), `matrix:` sweeps (`crate::matrix`), `--set` overrides and `${VAR}`
//! expansion; every error names the file, the line and the key, and all of it happens before
//! anything runs.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use crate::Registry;
use crate::config::{ConfigPathSegment, path_to_string};
use crate::erased::TypedConfig;
use crate::yaml_lines::LineMap;

/// A pipeline file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error("{file}:{line}: {message}")]
    At {
        file: String,
        line: usize,
        message: String,
    },
    #[error("{file}: {message}")]
    General { file: String, message: String },
}

/// One stage of a validated pipeline.
#[derive(Debug, Clone)]
pub struct StageSpec {
    pub name: String,
    pub kind: String,
    /// The effective config: overrides applied, variables expanded, defaults explicit.
    pub config: serde_json::Value,
    /// The same config as the stage kind resolved it, for its hooks.
    pub(crate) typed: TypedConfig,
    /// Names of upstream stages, in the order given.
    pub inputs: Vec<String>,
    /// Line of the stage in the file.
    pub line: usize,
}

/// A validated pipeline.
#[derive(Debug, Clone)]
pub struct Pipeline {
    pub file: PathBuf,
    pub description: Option<String>,
    /// Stages in file order.
    pub stages: Vec<StageSpec>,
    order: Vec<usize>,
}

const TOP_LEVEL_KEYS: &[&str] = &["stages", "description"];
const STAGE_KEYS: &[&str] = &["name", "kind", "config", "inputs"];

fn type_name(value: &serde_json::Value) -> &'static str {
    match value {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "a boolean",
        serde_json::Value::Number(_) => "a number",
        serde_json::Value::String(_) => "a string",
        serde_json::Value::Array(_) => "a list",
        serde_json::Value::Object(_) => "a mapping",
    }
}

fn key(name: &str) -> ConfigPathSegment {
    ConfigPathSegment::Key(name.to_string())
}

/// Checks a stage name: used in `--set`, `--until` and messages.
fn valid_stage_name(name: &str) -> bool {
    !name.is_empty()
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

struct Loader<'a> {
    file: String,
    lines: LineMap,
    registry: &'a Registry,
}

impl Loader<'_> {
    fn at(&self, path: &[ConfigPathSegment], message: String) -> PipelineError {
        PipelineError::At {
            file: self.file.clone(),
            line: self.lines.line_of(path),
            message,
        }
    }

    fn general(&self, message: String) -> PipelineError {
        PipelineError::General {
            file: self.file.clone(),
            message,
        }
    }

    /// The error at `path` for a value of the wrong type: `expected`, then what was found.
    fn unexpected(
        &self,
        path: &[ConfigPathSegment],
        expected: &str,
        found: &serde_json::Value,
    ) -> PipelineError {
        self.at(path, format!("{expected}, found {}", type_name(found)))
    }
}

impl Pipeline {
    /// Reads and validates a pipeline file; `overrides` are `stage.key=value` strings.
    pub fn load(
        file: &Path,
        registry: &Registry,
        overrides: &[String],
    ) -> Result<Self, PipelineError> {
        let general = |message| PipelineError::General {
            file: file.display().to_string(),
            message,
        };
        // Through the checked open: a FIFO, a device or a `/proc` file as the pipeline is
        // refused at once, and a file over the size bound is never read.
        let bytes = crate::files::read_regular_file_at_most(
            file,
            crate::yaml_lines::MAX_YAML_BYTES as u64,
            "a pipeline file",
        )
        .map_err(|error| general(format!("cannot read: {error:#}")))?;
        let text = String::from_utf8(bytes)
            .map_err(|error| general(format!("not UTF-8 text: {error}")))?;
        Self::parse(&text, file, registry, overrides)
    }

    /// Validates pipeline `text`; `file` names it in errors.
    pub fn parse(
        text: &str,
        file: &Path,
        registry: &Registry,
        overrides: &[String],
    ) -> Result<Self, PipelineError> {
        let file_label = file.display().to_string();
        let lines = LineMap::build(text).map_err(|error| PipelineError::At {
            file: file_label.clone(),
            line: error.line,
            message: format!("YAML syntax error: {}", error.message),
        })?;
        let loader = Loader {
            file: file_label,
            lines,
            registry,
        };
        let TopLevel {
            description,
            stage_values,
            stages_path,
        } = loader.top_level(text)?;
        if stage_values.is_empty() {
            return Err(loader.at(&stages_path, "the pipeline has no stages".to_string()));
        }
        let mut parsed = loader.stage_list(&stage_values, &stages_path)?;
        loader.check_input_kinds(&parsed)?;
        let order = topological_order(&parsed.stages).map_err(|cycle| {
            let first = parsed.index_of[&cycle[0]];
            loader.at(
                &parsed.at_key(first, "inputs"),
                format!(
                    "the inputs form a cycle (data flows {})",
                    cycle.join(" -> ")
                ),
            )
        })?;
        // Overrides, then variable expansion, then the stage kind's own validation.
        let overridden = loader.apply_overrides(&mut parsed, overrides)?;
        loader.resolve_configs(&mut parsed, &overridden)?;
        loader.check_stage_inputs(&parsed)?;
        Ok(Self {
            file: file.to_path_buf(),
            description,
            stages: parsed.stages,
            order,
        })
    }

    /// Stage indices in a topological order (file order among independent stages).
    pub fn order(&self) -> &[usize] {
        &self.order
    }

    /// The stage named `name`.
    pub fn stage(&self, name: &str) -> Option<&StageSpec> {
        self.stages.iter().find(|stage| stage.name == name)
    }

    /// Stage names in file order.
    pub fn stage_names(&self) -> Vec<String> {
        self.stages.iter().map(|stage| stage.name.clone()).collect()
    }

    /// `name` and every stage it depends on, directly or not.
    pub fn ancestors_and_self(&self, name: &str) -> BTreeSet<String> {
        let mut found = BTreeSet::new();
        let mut pending = vec![name.to_string()];
        while let Some(current) = pending.pop() {
            if !found.insert(current.clone()) {
                continue;
            }
            if let Some(stage) = self.stage(&current) {
                pending.extend(stage.inputs.iter().cloned());
            }
        }
        found
    }
}

/// The top level of a pipeline document: its description and its (unexpanded) stage list.
struct TopLevel {
    description: Option<String>,
    stage_values: Vec<serde_json::Value>,
    /// Where the stage list is in the document (empty for a bare list).
    stages_path: Vec<ConfigPathSegment>,
}

/// The stages of a pipeline as validation goes: specs, raw configs and where each came from.
struct ParsedStages {
    /// Specs in file order (after `matrix:` expansion); configs resolved last.
    stages: Vec<StageSpec>,
    /// Each stage's config as written, then with `--set` overrides applied.
    raw_configs: Vec<serde_json::Value>,
    /// The path of the item (or template) each stage came from, for errors.
    paths: Vec<Vec<ConfigPathSegment>>,
    /// Stage index by name.
    index_of: BTreeMap<String, usize>,
}

impl ParsedStages {
    /// The path of key `name` in stage `index`.
    fn at_key(&self, index: usize, name: &str) -> Vec<ConfigPathSegment> {
        [self.paths[index].as_slice(), &[key(name)]].concat()
    }

    /// The stage names, sorted, for messages.
    fn names(&self) -> String {
        self.index_of.keys().cloned().collect::<Vec<_>>().join(", ")
    }
}

/// Config paths set with `--set`, by stage index.
type Overridden = BTreeMap<usize, Vec<Vec<ConfigPathSegment>>>;

impl Loader<'_> {
    /// Parses the YAML document and checks its top-level keys.
    fn top_level(&self, text: &str) -> Result<TopLevel, PipelineError> {
        let document: serde_json::Value = if text.trim().is_empty() {
            serde_json::Value::Null
        } else {
            serde_saphyr::from_str(text)
                .map_err(|error| self.at(&[], format!("YAML error: {error}")))?
        };
        match &document {
            serde_json::Value::Object(map) => {
                for name in map.keys() {
                    if !TOP_LEVEL_KEYS.contains(&name.as_str()) {
                        return Err(self.at(
                            &[key(name)],
                            format!(
                                "unknown top-level key \"{name}\", expected one of: {}",
                                TOP_LEVEL_KEYS.join(", ")
                            ),
                        ));
                    }
                }
                let description = match map.get("description") {
                    None | Some(serde_json::Value::Null) => None,
                    Some(serde_json::Value::String(text)) => Some(text.clone()),
                    Some(other) => {
                        return Err(self.unexpected(
                            &[key("description")],
                            "key \"description\": expected a string",
                            other,
                        ));
                    }
                };
                match map.get("stages") {
                    Some(serde_json::Value::Array(items)) => Ok(TopLevel {
                        description,
                        stage_values: items.clone(),
                        stages_path: vec![key("stages")],
                    }),
                    Some(other) => Err(self.unexpected(
                        &[key("stages")],
                        "key \"stages\": expected a list of stages",
                        other,
                    )),
                    None => {
                        Err(self.at(&[], "missing key \"stages\" (a list of stages)".to_string()))
                    }
                }
            }
            serde_json::Value::Array(items) => Ok(TopLevel {
                description: None,
                stage_values: items.clone(),
                stages_path: vec![],
            }),
            other => Err(self.unexpected(&[], "expected a mapping with a \"stages\" list", other)),
        }
    }

    /// Expands `matrix:` stanzas and validates each stage mapping; names are unique.
    fn stage_list(
        &self,
        stage_values: &[serde_json::Value],
        stages_path: &[ConfigPathSegment],
    ) -> Result<ParsedStages, PipelineError> {
        // `matrix:` stanzas expand into stages; each stage keeps the path of the item (or
        // template) it came from, for errors.
        let (stage_values, paths): (Vec<_>, Vec<_>) =
            crate::matrix::expand_stage_list(stage_values, stages_path, &self.lines)
                .map_err(|error| self.at(&error.path, error.message))?
                .into_iter()
                .unzip();
        let mut stages: Vec<StageSpec> = Vec::with_capacity(stage_values.len());
        let mut raw_configs = Vec::with_capacity(stage_values.len());
        let mut index_of: BTreeMap<String, usize> = BTreeMap::new();
        for (value, path) in stage_values.iter().zip(&paths) {
            let index = stages.len();
            let (spec, raw_config) = self.stage(value, path)?;
            if let Some(&first) = index_of.get(&spec.name) {
                return Err(self.at(
                    &[path.as_slice(), &[key("name")]].concat(),
                    format!(
                        "stage name \"{}\" is used twice (first at line {})",
                        spec.name, stages[first].line
                    ),
                ));
            }
            index_of.insert(spec.name.clone(), index);
            stages.push(spec);
            raw_configs.push(raw_config);
        }
        Ok(ParsedStages {
            stages,
            raw_configs,
            paths,
            index_of,
        })
    }

    /// Inputs: they exist, and their kinds are accepted.
    fn check_input_kinds(&self, parsed: &ParsedStages) -> Result<(), PipelineError> {
        let stages = &parsed.stages;
        for (index, stage) in stages.iter().enumerate() {
            let kind = self.registry.get(&stage.kind).expect("kind checked above");
            for (input_index, input) in stage.inputs.iter().enumerate() {
                let path = [
                    parsed.paths[index].as_slice(),
                    &[key("inputs"), ConfigPathSegment::Index(input_index)],
                ]
                .concat();
                let Some(&upstream) = parsed.index_of.get(input) else {
                    return Err(self.at(
                        &path,
                        format!(
                            "stage \"{}\": input \"{input}\" is not a stage of this pipeline (stages: {})",
                            stage.name,
                            parsed.names()
                        ),
                    ));
                };
                let upstream_kind = &stages[upstream].kind;
                if !kind.input_kinds().contains(&upstream_kind.as_str()) {
                    return Err(self.at(
                        &path,
                        format!(
                            "stage \"{}\" (kind {}): input \"{input}\" has kind {upstream_kind}, accepted input kinds: {}",
                            stage.name,
                            stage.kind,
                            if kind.input_kinds().is_empty() {
                                "none".to_string()
                            } else {
                                kind.input_kinds().join(", ")
                            }
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Applies the `--set stage.key=value` overrides to the raw configs; returns what was set.
    fn apply_overrides(
        &self,
        parsed: &mut ParsedStages,
        overrides: &[String],
    ) -> Result<Overridden, PipelineError> {
        let mut overridden = Overridden::new();
        for assignment in overrides {
            let (stage_name, config_path, value) = parse_override(assignment)
                .map_err(|message| self.general(format!("--set {assignment}: {message}")))?;
            let Some(&index) = parsed.index_of.get(&stage_name) else {
                return Err(self.general(format!(
                    "--set {assignment}: no stage named \"{stage_name}\" (stages: {})",
                    parsed.names()
                )));
            };
            set_path(&mut parsed.raw_configs[index], &config_path, value)
                .map_err(|message| self.general(format!("--set {assignment}: {message}")))?;
            overridden.entry(index).or_default().push(config_path);
        }
        Ok(overridden)
    }

    /// Expands variables in each raw config and resolves it with the stage kind; errors on a
    /// key set with `--set` say so.
    fn resolve_configs(
        &self,
        parsed: &mut ParsedStages,
        overridden: &Overridden,
    ) -> Result<(), PipelineError> {
        for index in 0..parsed.stages.len() {
            let config_root = parsed.at_key(index, "config");
            let from_command_line = |path: &[ConfigPathSegment]| {
                overridden
                    .get(&index)
                    .is_some_and(|paths| paths.iter().any(|set| path.starts_with(set)))
            };
            let set_note = |path: &[ConfigPathSegment]| {
                if from_command_line(path) {
                    " (set with --set)"
                } else {
                    ""
                }
            };
            let stage = &mut parsed.stages[index];
            let mut raw = parsed.raw_configs[index].clone();
            expand_variables(&mut raw, &mut Vec::new()).map_err(|(path, message)| {
                let text = format!(
                    "stage \"{}\": config key \"{}\": {message}{}",
                    stage.name,
                    path_to_string(&path),
                    set_note(&path)
                );
                self.at(&[config_root.as_slice(), &path].concat(), text)
            })?;
            let kind = self.registry.get(&stage.kind).expect("kind checked above");
            (stage.config, stage.typed) = kind.resolve_config(&raw).map_err(|error| {
                let text = format!("stage \"{}\": {error}{}", stage.name, set_note(&error.path));
                self.at(&[config_root.as_slice(), &error.path].concat(), text)
            })?;
        }
        Ok(())
    }

    /// Each stage's inputs give it what its run needs (with what their entries will hold).
    fn check_stage_inputs(&self, parsed: &ParsedStages) -> Result<(), PipelineError> {
        let stages = &parsed.stages;
        let planned: Vec<serde_json::Value> = stages
            .iter()
            .map(|stage| {
                let kind = self.registry.get(&stage.kind).expect("kind checked above");
                kind.planned(&stage.typed)
            })
            .collect();
        for (index, stage) in stages.iter().enumerate() {
            let kind = self.registry.get(&stage.kind).expect("kind checked above");
            let inputs: Vec<crate::StageInput<'_>> = stage
                .inputs
                .iter()
                .map(|name| {
                    let upstream = parsed.index_of[name];
                    crate::StageInput {
                        name,
                        kind: &stages[upstream].kind,
                        planned: &planned[upstream],
                    }
                })
                .collect();
            kind.check_inputs(&stage.typed, &inputs)
                .map_err(|message| {
                    self.at(
                        &parsed.at_key(index, "inputs"),
                        format!("stage \"{}\" (kind {}): {message}", stage.name, stage.kind),
                    )
                })?;
        }
        Ok(())
    }

    /// Validates one stage mapping; returns the spec (config unresolved) and the raw config.
    fn stage(
        &self,
        value: &serde_json::Value,
        path: &[ConfigPathSegment],
    ) -> Result<(StageSpec, serde_json::Value), PipelineError> {
        let serde_json::Value::Object(map) = value else {
            return Err(self.unexpected(
                path,
                &format!(
                    "a stage must be a mapping with keys {}",
                    STAGE_KEYS.join(", ")
                ),
                value,
            ));
        };
        self.check_stage_keys(map, path)?;
        let name = self.stage_name(map, path)?;
        let kind = self.stage_kind(map, path, &name)?;
        let inputs = self.stage_inputs(map, path, &name)?;
        let raw_config = self.stage_raw_config(map, path, &name)?;
        Ok((
            StageSpec {
                name,
                kind,
                config: serde_json::Value::Null,
                typed: std::sync::Arc::new(()),
                inputs,
                line: self.lines.line_of(path),
            },
            raw_config,
        ))
    }

    /// Every key of a stage mapping is one of `STAGE_KEYS`.
    fn check_stage_keys(
        &self,
        map: &serde_json::Map<String, serde_json::Value>,
        path: &[ConfigPathSegment],
    ) -> Result<(), PipelineError> {
        for name in map.keys() {
            if !STAGE_KEYS.contains(&name.as_str()) {
                let label = map
                    .get("name")
                    .and_then(|n| n.as_str())
                    .map(|n| format!("stage \"{n}\": "))
                    .unwrap_or_default();
                return Err(self.at(
                    &[path, &[key(name)]].concat(),
                    format!(
                        "{label}unknown key \"{name}\", expected one of: {}",
                        STAGE_KEYS.join(", ")
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The stage's `name`: a valid stage name.
    fn stage_name(
        &self,
        map: &serde_json::Map<String, serde_json::Value>,
        path: &[ConfigPathSegment],
    ) -> Result<String, PipelineError> {
        let at_name = [path, &[key("name")]].concat();
        match map.get("name") {
            Some(serde_json::Value::String(name)) if valid_stage_name(name) => Ok(name.clone()),
            Some(serde_json::Value::String(name)) => Err(self.at(
                &at_name,
                format!("stage name \"{name}\" must be non-empty and use only ASCII letters, digits, '_' and '-'"),
            )),
            Some(other) => Err(self.unexpected(&at_name, "key \"name\": expected a string", other)),
            None => Err(self.at(path, "stage without a \"name\"".to_string())),
        }
    }

    /// The stage's `kind`: one the registry knows.
    fn stage_kind(
        &self,
        map: &serde_json::Map<String, serde_json::Value>,
        path: &[ConfigPathSegment],
        name: &str,
    ) -> Result<String, PipelineError> {
        let at_kind = [path, &[key("kind")]].concat();
        let kind = match map.get("kind") {
            Some(serde_json::Value::String(kind)) => kind.clone(),
            Some(other) => {
                return Err(self.unexpected(
                    &at_kind,
                    &format!("stage \"{name}\": key \"kind\": expected a string"),
                    other,
                ));
            }
            None => {
                return Err(self.at(path, format!("stage \"{name}\" has no \"kind\"")));
            }
        };
        if self.registry.get(&kind).is_none() {
            return Err(self.at(
                &at_kind,
                format!(
                    "stage \"{name}\": unknown stage kind \"{kind}\", known kinds: {}",
                    self.registry.kind_names().join(", ")
                ),
            ));
        }
        Ok(kind)
    }

    /// The stage's `inputs`: none, one name, or a list of distinct names.
    fn stage_inputs(
        &self,
        map: &serde_json::Map<String, serde_json::Value>,
        path: &[ConfigPathSegment],
        name: &str,
    ) -> Result<Vec<String>, PipelineError> {
        let items = match map.get("inputs") {
            None | Some(serde_json::Value::Null) => return Ok(vec![]),
            Some(serde_json::Value::String(single)) => return Ok(vec![single.clone()]),
            Some(serde_json::Value::Array(items)) => items,
            Some(other) => {
                return Err(self.unexpected(
                    &[path, &[key("inputs")]].concat(),
                    &format!("stage \"{name}\": key \"inputs\": expected a list of stage names"),
                    other,
                ));
            }
        };
        let mut inputs = Vec::with_capacity(items.len());
        for (index, item) in items.iter().enumerate() {
            let at_item = [path, &[key("inputs"), ConfigPathSegment::Index(index)]].concat();
            match item {
                serde_json::Value::String(input) => {
                    if inputs.contains(input) {
                        return Err(self.at(
                            &at_item,
                            format!("stage \"{name}\": input \"{input}\" is listed twice"),
                        ));
                    }
                    inputs.push(input.clone())
                }
                other => {
                    return Err(self.unexpected(
                        &at_item,
                        &format!("stage \"{name}\": key \"inputs\": expected stage names"),
                        other,
                    ));
                }
            }
        }
        Ok(inputs)
    }

    /// The stage's `config` as written: a mapping (empty when absent).
    fn stage_raw_config(
        &self,
        map: &serde_json::Map<String, serde_json::Value>,
        path: &[ConfigPathSegment],
        name: &str,
    ) -> Result<serde_json::Value, PipelineError> {
        match map.get("config") {
            None | Some(serde_json::Value::Null) => {
                Ok(serde_json::Value::Object(serde_json::Map::new()))
            }
            Some(config @ serde_json::Value::Object(_)) => Ok(config.clone()),
            Some(other) => Err(self.unexpected(
                &[path, &[key("config")]].concat(),
                &format!("stage \"{name}\": key \"config\": expected a mapping"),
                other,
            )),
        }
    }
}

/// Kahn's algorithm, taking ready stages in file order; on a cycle returns the stage names
/// around it.
fn topological_order(stages: &[StageSpec]) -> Result<Vec<usize>, Vec<String>> {
    let index_of: BTreeMap<&str, usize> = stages
        .iter()
        .enumerate()
        .map(|(index, stage)| (stage.name.as_str(), index))
        .collect();
    let mut remaining_inputs: Vec<usize> = stages.iter().map(|stage| stage.inputs.len()).collect();
    let mut order = Vec::with_capacity(stages.len());
    let mut done = vec![false; stages.len()];
    while order.len() < stages.len() {
        let Some(next) =
            (0..stages.len()).find(|&index| !done[index] && remaining_inputs[index] == 0)
        else {
            // Every remaining stage waits on another: follow inputs until a stage repeats.
            let start = (0..stages.len())
                .find(|&index| !done[index])
                .expect("a stage remains");
            let mut walk = vec![start];
            loop {
                let current = *walk.last().expect("walk is non-empty");
                let upstream = stages[current]
                    .inputs
                    .iter()
                    .map(|input| index_of[input.as_str()])
                    .find(|&index| !done[index])
                    .expect("a waiting stage has an unfinished input");
                if let Some(position) = walk.iter().position(|&index| index == upstream) {
                    let mut cycle: Vec<String> = walk[position..]
                        .iter()
                        .rev()
                        .map(|&index| stages[index].name.clone())
                        .collect();
                    cycle.push(cycle[0].clone());
                    return Err(cycle);
                }
                walk.push(upstream);
            }
        };
        done[next] = true;
        order.push(next);
        for (index, stage) in stages.iter().enumerate() {
            if stage.inputs.iter().any(|input| input == &stages[next].name) {
                remaining_inputs[index] -= 1;
            }
        }
    }
    Ok(order)
}

/// Splits `stage.key.sub=value` and parses the value as YAML.
fn parse_override(
    assignment: &str,
) -> Result<(String, Vec<ConfigPathSegment>, serde_json::Value), String> {
    let (target, value_text) = assignment
        .split_once('=')
        .ok_or_else(|| "expected stage.key=value".to_string())?;
    let mut parts = target.trim().split('.');
    let stage = parts.next().unwrap_or_default().to_string();
    let path: Vec<ConfigPathSegment> = parts.map(key).collect();
    if stage.is_empty() || path.is_empty() || path.iter().any(|segment| *segment == key("")) {
        return Err("expected stage.key=value".to_string());
    }
    let value = if value_text.trim().is_empty() {
        serde_json::Value::String(String::new())
    } else {
        crate::yaml_lines::LineMap::build(value_text)
            .map_err(|error| format!("the value is refused: {}", error.message))?;
        serde_saphyr::from_str::<serde_json::Value>(value_text)
            .map_err(|error| format!("the value is not valid YAML: {error}"))?
    };
    Ok((stage, path, value))
}

/// Sets `path` in `config`, creating mappings on the way.
fn set_path(
    config: &mut serde_json::Value,
    path: &[ConfigPathSegment],
    value: serde_json::Value,
) -> Result<(), String> {
    let mut current = config;
    for (depth, segment) in path.iter().enumerate() {
        let ConfigPathSegment::Key(name) = segment else {
            return Err("list indices are not supported".to_string());
        };
        if current.is_null() {
            *current = serde_json::Value::Object(serde_json::Map::new());
        }
        let serde_json::Value::Object(map) = current else {
            return Err(format!(
                "config key \"{}\" is {}, not a mapping",
                path_to_string(&path[..depth]),
                type_name(current)
            ));
        };
        if depth + 1 == path.len() {
            map.insert(name.clone(), value);
            return Ok(());
        }
        current = map.entry(name.clone()).or_insert(serde_json::Value::Null);
    }
    Ok(())
}

/// Expands `${NAME}` in every string (`$$` is a literal `$`); errors carry the key path.
fn expand_variables(
    value: &mut serde_json::Value,
    path: &mut Vec<ConfigPathSegment>,
) -> Result<(), (Vec<ConfigPathSegment>, String)> {
    match value {
        serde_json::Value::String(text) if text.contains('$') => {
            *text = expand_string(text).map_err(|message| (path.clone(), message))?;
        }
        serde_json::Value::Array(items) => {
            for (index, item) in items.iter_mut().enumerate() {
                path.push(ConfigPathSegment::Index(index));
                expand_variables(item, path)?;
                path.pop();
            }
        }
        serde_json::Value::Object(map) => {
            for (name, item) in map.iter_mut() {
                path.push(key(name));
                expand_variables(item, path)?;
                path.pop();
            }
        }
        _ => {}
    }
    Ok(())
}

fn expand_string(text: &str) -> Result<String, String> {
    let mut result = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(position) = rest.find('$') {
        result.push_str(&rest[..position]);
        let after = &rest[position + 1..];
        if let Some(stripped) = after.strip_prefix('$') {
            result.push('$');
            rest = stripped;
        } else if let Some(body) = after.strip_prefix('{') {
            let end = body
                .find('}')
                .ok_or_else(|| format!("unterminated \"${{\" in \"{text}\""))?;
            let name = &body[..end];
            if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
                return Err(format!("invalid variable name \"{name}\" in \"{text}\""));
            }
            let value = std::env::var(name).map_err(|_| {
                format!("environment variable {name} is not set (used in \"{text}\")")
            })?;
            result.push_str(&value);
            rest = &body[end + 1..];
        } else {
            result.push('$');
            rest = after;
        }
    }
    result.push_str(rest);
    Ok(result)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str, overrides: &[&str]) -> Result<Pipeline, String> {
        let overrides: Vec<String> = overrides.iter().map(|s| s.to_string()).collect();
        Pipeline::parse(text, Path::new("p.yaml"), &Registry::new(), &overrides)
            .map_err(|error| error.to_string())
    }

    fn check_error(text: &str, overrides: &[&str], expected: &str) {
        let error = parse(text, overrides).expect_err("must be rejected");
        assert!(
            error.contains(expected),
            "expected {expected:?} in {error:?}"
        );
    }

    const GOOD: &str = "description: demo\nstages:\n  - name: a\n    kind: test_arrays\n    config:\n      size: 8\n  - name: b\n    kind: test_arrays\n    inputs: [a]\n    config: {seed: 2, size: 8}\n";

    #[test]
    fn valid_pipeline_resolves_defaults() {
        let pipeline = parse(GOOD, &[]).unwrap();
        assert_eq!(pipeline.stage_names(), ["a", "b"]);
        assert_eq!(pipeline.stages[0].config["chunk"], 4);
        assert_eq!(pipeline.stages[1].config["seed"], 2);
        assert_eq!(pipeline.stages[1].line, 7);
        assert_eq!(pipeline.order(), [0, 1]);
        assert_eq!(pipeline.ancestors_and_self("b").len(), 2);
    }

    #[test]
    fn malformed_files_name_line_and_key() {
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    config:\n      size: 8\n      seeed: 1\n",
            &[],
            "p.yaml:6: stage \"a\": config key \"seeed\": unknown field `seeed`, expected one of",
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    config:\n      size: many\n",
            &[],
            "p.yaml:5: stage \"a\": config key \"size\": invalid type",
        );
        check_error(
            "stages:\n  - name: a\n    kind: nope\n",
            &[],
            "p.yaml:3: stage \"a\": unknown stage kind \"nope\", known kinds: test_arrays",
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    inputs: [ghost]\n",
            &[],
            "p.yaml:4: stage \"a\": input \"ghost\" is not a stage of this pipeline",
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    inputs: [b]\n  - name: b\n    kind: test_arrays\n    inputs: [a]\n",
            &[],
            "p.yaml:7: the inputs form a cycle (data flows b -> a -> b)",
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    inputs: [a]\n",
            &[],
            "p.yaml:4: the inputs form a cycle (data flows a -> a)",
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    confg: {}\n",
            &[],
            "p.yaml:4: stage \"a\": unknown key \"confg\", expected one of: name, kind, config, inputs",
        );
        check_error(
            "stage:\n  - name: a\n",
            &[],
            "p.yaml:1: unknown top-level key \"stage\"",
        );
        check_error(
            "stages:\n  - name: a\n    kind: 3\n",
            &[],
            "p.yaml:3: stage \"a\": key \"kind\": expected a string, found a number",
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    config: [1]\n",
            &[],
            "p.yaml:4: stage \"a\": key \"config\": expected a mapping, found a list",
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n  - name: a\n    kind: test_arrays\n",
            &[],
            "p.yaml:4: stage name \"a\" is used twice (first at line 2)",
        );
        check_error("stages: [\n", &[], "p.yaml:");
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    config:\n      size: 0\n",
            &[],
            "p.yaml:5: stage \"a\": config key \"size\": must be in 1..=4096",
        );
    }

    /// A kind that needs one `test_arrays` input, to test the load-time input check.
    struct NeedsArrays;

    impl crate::StageKind for NeedsArrays {
        type Config = serde_json::Value;
        fn kind(&self) -> &'static str {
            "needs_arrays"
        }
        fn version(&self) -> u32 {
            1
        }
        fn input_kinds(&self) -> &'static [&'static str] {
            &["test_arrays"]
        }
        fn check_inputs(
            &self,
            _config: &serde_json::Value,
            inputs: &[crate::StageInput<'_>],
        ) -> Result<(), String> {
            crate::require_one_input_of_each(inputs, &["test_arrays"])
        }
        fn run(
            &self,
            _config: &serde_json::Value,
            _ctx: &mut crate::StageContext<'_>,
        ) -> anyhow::Result<()> {
            anyhow::bail!("never run by these tests")
        }
    }

    #[test]
    fn missing_required_inputs_are_found_at_load() {
        let mut registry = Registry::new();
        registry.add(Box::new(NeedsArrays));
        let load = |text: &str| {
            Pipeline::parse(text, Path::new("p.yaml"), &registry, &[])
                .map(|_| ())
                .map_err(|error| error.to_string())
        };
        let a = "stages:\n  - name: a\n    kind: test_arrays\n";
        let error = load(&format!("{a}  - name: needs\n    kind: needs_arrays\n")).unwrap_err();
        assert!(
            error.contains(
                "stage \"needs\" (kind needs_arrays): needs an input of kind test_arrays; it has no \
                 inputs"
            ),
            "{error}"
        );
        load(&format!(
            "{a}  - name: needs\n    kind: needs_arrays\n    inputs: [a]\n"
        ))
        .unwrap();
        let two = format!(
            "{a}  - name: b\n    kind: test_arrays\n  - name: needs\n    kind: needs_arrays\n    \
             inputs: [a, b]\n"
        );
        let error = load(&two).unwrap_err();
        assert!(
            error.contains("has several inputs of kind test_arrays (a, b)"),
            "{error}"
        );
    }

    #[test]
    fn overrides_parse_yaml_scalars() {
        let pipeline = parse(GOOD, &["b.seed=7", "a.count_file=/tmp/x"]).unwrap();
        assert_eq!(pipeline.stages[1].config["seed"], 7);
        assert_eq!(pipeline.stages[0].config["count_file"], "/tmp/x");
        check_error(GOOD, &["c.seed=1"], "--set c.seed=1: no stage named \"c\"");
        check_error(GOOD, &["b.seed"], "expected stage.key=value");
        check_error(
            GOOD,
            &["b.seeed=1"],
            "stage \"b\": config key \"seeed\": unknown field `seeed`, expected one of",
        );
        check_error(GOOD, &["b.seed=x"], "(set with --set)");
    }

    #[test]
    fn unreadable_file_error_names_its_cause_once() {
        let dir = tempfile::tempdir().unwrap();
        let missing = dir.path().join("missing.yaml");
        let error = Pipeline::load(&missing, &Registry::new(), &[]).unwrap_err();
        // The binary prints the whole chain (`{:#}`): the cause must not appear twice.
        let chain = format!("{:#}", anyhow::Error::from(error));
        assert!(chain.contains("missing.yaml: cannot read: "), "{chain}");
        assert_eq!(
            chain.matches("No such file or directory").count(),
            1,
            "{chain}"
        );
    }

    #[test]
    fn variables_expand_in_strings() {
        // SAFETY: the variable name is unique to this test; nothing else reads or writes it.
        unsafe { std::env::set_var("SEQAVATAR_ENGINE_TEST_ROOT", "/data/root") };
        let text = "stages:\n  - name: a\n    kind: test_arrays\n    config:\n      count_file: ${SEQAVATAR_ENGINE_TEST_ROOT}/count$$1\n";
        let pipeline = parse(text, &[]).unwrap();
        assert_eq!(
            pipeline.stages[0].config["count_file"],
            "/data/root/count$1"
        );
        check_error(
            "stages:\n  - name: a\n    kind: test_arrays\n    config:\n      count_file: ${SEQAVATAR_ENGINE_TEST_UNSET_VARIABLE}\n",
            &[],
            "p.yaml:5: stage \"a\": config key \"count_file\": environment variable SEQAVATAR_ENGINE_TEST_UNSET_VARIABLE is not set",
        );
        assert!(expand_string("${unterminated").is_err());
        assert_eq!(expand_string("cost $5").unwrap(), "cost $5");
    }
}
