//! Sweeps in one stanza: a `matrix:` item in a pipeline's stage list expands into named
//! stages, one copy of its `stages:` templates per combination of the matrix values (as DVC's
//! `matrix:` does).
//!
//! ```yaml
//! stages:
//!   - name: ingest
//!     kind: ingest
//!   - matrix:
//!       seed: [1, 2, 3]                    # the first variable is the outermost loop
//!       row:
//!         - {id: a_none, context: none}
//!         - {id: b_pose, context: pose}
//!     stages:
//!       - name: train_${row.id}_s${seed}
//!         kind: train
//!         inputs: [ingest]
//!         config:
//!           seed: ${seed}                  # the whole string: the value with its type
//!           motion_context: ${row.context}
//!       - name: eval_${row.id}_s${seed}
//!         kind: eval
//!         inputs: ["train_${row.id}_s${seed}", ingest]
//! ```
//!
//! A string that is exactly one reference (`${seed}`) becomes the bound value itself, typed
//! (a number stays a number, a mapping a mapping), so an expanded config is the same JSON as a
//! hand-written one and derives the same cache key. A reference inside a longer string is
//! replaced by the value's text (strings, numbers and booleans only). `${NAME}` whose first
//! segment is not a matrix variable is left for the environment-variable expansion that runs
//! on every config afterwards; `$$` stays a literal `$`. Inside YAML flow collections (`[...]`,
//! `{...}`) a reference must be quoted, since `{` and `}` are flow indicators there.

use crate::config::ConfigPathSegment;
use crate::yaml_lines::LineMap;

/// The keys of a matrix item.
const MATRIX_KEYS: &[&str] = &["matrix", "stages"];

/// An error at a place in the pipeline file.
pub(crate) struct MatrixError {
    pub path: Vec<ConfigPathSegment>,
    pub message: String,
}

fn at(path: &[ConfigPathSegment], message: String) -> MatrixError {
    MatrixError {
        path: path.to_vec(),
        message,
    }
}

fn key(name: &str) -> ConfigPathSegment {
    ConfigPathSegment::Key(name.to_string())
}

/// Whether a stage-list item is a matrix stanza (a mapping with a `matrix` key).
fn is_matrix(item: &serde_json::Value) -> bool {
    item.as_object()
        .is_some_and(|map| map.contains_key("matrix"))
}

/// Expands every matrix stanza of a stage list. Returns each stage with the path of the item
/// it came from (its template inside the stanza, for expanded stages), so errors about an
/// expanded stage point at the template's line.
pub(crate) fn expand_stage_list(
    items: &[serde_json::Value],
    stages_path: &[ConfigPathSegment],
    lines: &LineMap,
) -> Result<Vec<(serde_json::Value, Vec<ConfigPathSegment>)>, MatrixError> {
    let mut stages = Vec::with_capacity(items.len());
    for (index, item) in items.iter().enumerate() {
        let path = [stages_path, &[ConfigPathSegment::Index(index)]].concat();
        if is_matrix(item) {
            stages.extend(expand_stanza(item, &path, lines)?);
        } else {
            stages.push((item.clone(), path));
        }
    }
    Ok(stages)
}

/// One matrix variable: its name and its values, in file order.
struct Variable {
    name: String,
    values: Vec<serde_json::Value>,
}

/// The variables of a `matrix:` mapping, ordered by their line in the file (the mapping's
/// own key order is not kept by the JSON model), so the first is the outermost loop.
fn variables(
    matrix: &serde_json::Value,
    path: &[ConfigPathSegment],
    lines: &LineMap,
) -> Result<Vec<Variable>, MatrixError> {
    let serde_json::Value::Object(map) = matrix else {
        return Err(at(
            path,
            "key \"matrix\": expected a mapping of variable names to lists of values".into(),
        ));
    };
    if map.is_empty() {
        return Err(at(path, "key \"matrix\": no variables".into()));
    }
    let mut variables = Vec::with_capacity(map.len());
    for (name, values) in map {
        let variable_path = [path, &[key(name)]].concat();
        if name.is_empty() || !name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_') {
            return Err(at(
                &variable_path,
                format!("matrix variable \"{name}\": use only ASCII letters, digits and '_'"),
            ));
        }
        let values = match values {
            serde_json::Value::Array(values) if !values.is_empty() => values.clone(),
            _ => {
                return Err(at(
                    &variable_path,
                    format!("matrix variable \"{name}\": expected a non-empty list of values"),
                ));
            }
        };
        variables.push((
            lines.line_of(&variable_path),
            Variable {
                name: name.clone(),
                values,
            },
        ));
    }
    variables.sort_by_key(|(line, _)| *line);
    Ok(variables
        .into_iter()
        .map(|(_, variable)| variable)
        .collect())
}

/// Expands one stanza: for each combination (the first variable outermost), each template.
fn expand_stanza(
    item: &serde_json::Value,
    path: &[ConfigPathSegment],
    lines: &LineMap,
) -> Result<Vec<(serde_json::Value, Vec<ConfigPathSegment>)>, MatrixError> {
    let map = item.as_object().expect("a matrix item is a mapping");
    for name in map.keys() {
        if !MATRIX_KEYS.contains(&name.as_str()) {
            return Err(at(
                &[path, &[key(name)]].concat(),
                format!(
                    "matrix stanza: unknown key \"{name}\", expected one of: {}",
                    MATRIX_KEYS.join(", ")
                ),
            ));
        }
    }
    let variables = variables(&map["matrix"], &[path, &[key("matrix")]].concat(), lines)?;
    let templates_path = [path, &[key("stages")]].concat();
    let templates = match map.get("stages") {
        Some(serde_json::Value::Array(templates)) if !templates.is_empty() => templates,
        _ => {
            return Err(at(
                path,
                "matrix stanza: expected a non-empty \"stages\" list of stage templates".into(),
            ));
        }
    };
    if let Some(nested) = templates.iter().position(is_matrix) {
        return Err(at(
            &[
                templates_path.as_slice(),
                &[ConfigPathSegment::Index(nested)],
            ]
            .concat(),
            "matrix stanzas do not nest: put every variable in one \"matrix\"".into(),
        ));
    }

    let combinations: usize = variables.iter().map(|v| v.values.len()).product();
    let mut stages = Vec::with_capacity(combinations * templates.len());
    for combination in 0..combinations {
        // Mixed-radix digits of `combination`, the last variable varying fastest.
        let mut rest = combination;
        let mut bindings = vec![serde_json::Value::Null; variables.len()];
        for (slot, variable) in variables.iter().enumerate().rev() {
            bindings[slot] = variable.values[rest % variable.values.len()].clone();
            rest /= variable.values.len();
        }
        let bindings: Vec<(&str, &serde_json::Value)> = variables
            .iter()
            .map(|variable| variable.name.as_str())
            .zip(bindings.iter())
            .collect();
        for (index, template) in templates.iter().enumerate() {
            let template_path = [
                templates_path.as_slice(),
                &[ConfigPathSegment::Index(index)],
            ]
            .concat();
            let stage = substitute(template, &bindings)
                .map_err(|message| at(&template_path, format!("matrix stage: {message}")))?;
            stages.push((stage, template_path));
        }
    }
    Ok(stages)
}

/// The value of a reference `name.field.field` under the bindings; `None` when its first
/// segment is not a matrix variable (an environment variable, expanded later).
fn lookup<'v>(
    reference: &str,
    bindings: &[(&str, &'v serde_json::Value)],
) -> Option<Result<&'v serde_json::Value, String>> {
    let mut segments = reference.split('.');
    let root = segments.next()?;
    let &(_, mut value) = bindings.iter().find(|(name, _)| *name == root)?;
    for field in segments {
        match value.get(field) {
            Some(inner) => value = inner,
            None => {
                return Some(Err(format!(
                    "\"${{{reference}}}\": the value of \"{root}\" has no field \"{field}\""
                )));
            }
        }
    }
    Some(Ok(value))
}

/// The text of a bound value inside a longer string.
fn text_of(reference: &str, value: &serde_json::Value) -> Result<String, String> {
    match value {
        serde_json::Value::String(text) => Ok(text.clone()),
        serde_json::Value::Number(number) => Ok(number.to_string()),
        serde_json::Value::Bool(flag) => Ok(flag.to_string()),
        _ => Err(format!(
            "\"${{{reference}}}\" is a list, mapping or null and cannot be part of a longer \
             string (write it alone to insert the value itself)"
        )),
    }
}

/// Substitutes the matrix references of every string in `value` (not in mapping keys).
fn substitute(
    value: &serde_json::Value,
    bindings: &[(&str, &serde_json::Value)],
) -> Result<serde_json::Value, String> {
    Ok(match value {
        serde_json::Value::String(text) => substitute_string(text, bindings)?,
        serde_json::Value::Array(items) => serde_json::Value::Array(
            items
                .iter()
                .map(|item| substitute(item, bindings))
                .collect::<Result<_, _>>()?,
        ),
        serde_json::Value::Object(map) => serde_json::Value::Object(
            map.iter()
                .map(|(name, item)| Ok((name.clone(), substitute(item, bindings)?)))
                .collect::<Result<_, String>>()?,
        ),
        other => other.clone(),
    })
}

fn substitute_string(
    text: &str,
    bindings: &[(&str, &serde_json::Value)],
) -> Result<serde_json::Value, String> {
    // The whole string is one reference: the value itself, with its type.
    if let Some(reference) = text.strip_prefix("${").and_then(|t| t.strip_suffix('}'))
        && !reference.contains(['$', '{', '}'])
        && let Some(value) = lookup(reference, bindings)
    {
        return value.cloned();
    }
    let mut result = String::with_capacity(text.len());
    let mut rest = text;
    while let Some(position) = rest.find('$') {
        result.push_str(&rest[..position]);
        let after = &rest[position + 1..];
        if let Some(stripped) = after.strip_prefix('$') {
            // Kept escaped for the environment-variable expansion.
            result.push_str("$$");
            rest = stripped;
        } else if let Some(body) = after.strip_prefix('{')
            && let Some(end) = body.find('}')
            && let Some(value) = lookup(&body[..end], bindings)
        {
            result.push_str(&text_of(&body[..end], value?)?);
            rest = &body[end + 1..];
        } else {
            result.push('$');
            rest = after;
        }
    }
    result.push_str(rest);
    Ok(serde_json::Value::String(result))
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn expand(text: &str) -> Result<Vec<serde_json::Value>, String> {
        let lines = LineMap::build(text).unwrap();
        let document: serde_json::Value = serde_saphyr::from_str(text).unwrap();
        let items = document["stages"].as_array().unwrap().clone();
        expand_stage_list(&items, &[key("stages")], &lines)
            .map(|stages| stages.into_iter().map(|(stage, _)| stage).collect())
            .map_err(|error| format!("line {}: {}", lines.line_of(&error.path), error.message))
    }

    #[test]
    fn combinations_in_file_order_with_typed_values() {
        let stages = expand(
            "stages:
  - name: source
    kind: k
  - matrix:
      seed: [1, 2]
      row:
        - {id: a, context: none, extra: {width: 8}}
        - {id: b, context: pose, extra: {width: 16}}
    stages:
      - name: train_${row.id}_s${seed}
        kind: train
        inputs: [source]
        config:
          seed: ${seed}
          motion_context: ${row.context}
          nested: ${row.extra}
          label: \"run ${row.id} seed ${seed} costs $$${HOME}\"
      - name: eval_${row.id}_s${seed}
        kind: eval
        inputs: [\"train_${row.id}_s${seed}\", source]
",
        )
        .unwrap();
        let names: Vec<&str> = stages.iter().map(|s| s["name"].as_str().unwrap()).collect();
        assert_eq!(
            names,
            [
                "source",
                "train_a_s1",
                "eval_a_s1",
                "train_b_s1",
                "eval_b_s1",
                "train_a_s2",
                "eval_a_s2",
                "train_b_s2",
                "eval_b_s2"
            ]
        );
        assert_eq!(
            stages[3]["config"],
            json!({
                "seed": 1,
                "motion_context": "pose",
                "nested": {"width": 16},
                // `$$` and environment references are left for the variable expansion.
                "label": "run b seed 1 costs $$${HOME}",
            })
        );
        assert_eq!(stages[8]["inputs"], json!(["train_b_s2", "source"]));
    }

    #[test]
    fn a_single_variable_and_a_single_value() {
        let stages = expand(
            "stages:
  - matrix: {only: [7]}
    stages:
      - {name: \"s${only}\", kind: k, config: {n: \"${only}\"}}
",
        )
        .unwrap();
        assert_eq!(
            stages,
            [json!({"name": "s7", "kind": "k", "config": {"n": 7}})]
        );
    }

    #[test]
    fn malformed_stanzas_name_line_and_cause() {
        let cases = [
            (
                "stages:\n  - matrix: [1, 2]\n    stages: [{name: a, kind: k}]\n",
                "line 2: key \"matrix\": expected a mapping",
            ),
            (
                "stages:\n  - matrix: {seed: []}\n    stages: [{name: a, kind: k}]\n",
                "line 2: matrix variable \"seed\": expected a non-empty list",
            ),
            (
                "stages:\n  - matrix: {seed: [1]}\n",
                "line 2: matrix stanza: expected a non-empty \"stages\" list",
            ),
            (
                "stages:\n  - matrix: {seed: [1]}\n    stages: [{name: a, kind: k}]\n    each: 1\n",
                "line 4: matrix stanza: unknown key \"each\"",
            ),
            (
                "stages:\n  - matrix: {row: [{id: a}]}\n    stages:\n      - name: t_${row.name}\n        kind: k\n",
                "line 4: matrix stage: \"${row.name}\": the value of \"row\" has no field \"name\"",
            ),
            (
                "stages:\n  - matrix: {row: [{id: a}]}\n    stages:\n      - name: t_${row}\n        kind: k\n",
                "line 4: matrix stage: \"${row}\" is a list, mapping or null",
            ),
            (
                "stages:\n  - matrix: {a: [1]}\n    stages:\n      - matrix: {b: [2]}\n        stages: []\n",
                "line 4: matrix stanzas do not nest",
            ),
        ];
        for (text, expected) in cases {
            let error = expand(text).expect_err(text);
            assert!(
                error.contains(expected),
                "expected {expected:?} in {error:?}"
            );
        }
    }
}
