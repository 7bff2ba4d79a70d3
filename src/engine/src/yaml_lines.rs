//! Maps key paths of a YAML document to the line where each key (or list item) appears, from
//! saphyr-parser events, so that errors can name the line. The same pass bounds the document
//! before anything builds its nodes: at most [`MAX_YAML_BYTES`] bytes, [`MAX_YAML_DEPTH`]
//! levels of nesting (block indentation or brackets) and [`MAX_YAML_NODES`] nodes, each
//! refused at the line that crosses it (deep block nesting once took gigabytes).

use std::collections::HashMap;

use saphyr_parser::{Event, Parser};

use crate::config::ConfigPathSegment;

/// The largest pipeline document read, in bytes (the shipped pipelines are a few KB).
pub const MAX_YAML_BYTES: usize = 1 << 20;
/// The deepest nesting of mappings and lists (a pipeline needs under ten levels).
pub const MAX_YAML_DEPTH: usize = 64;
/// The most nodes (scalars, aliases, mappings and lists) in one document.
pub const MAX_YAML_NODES: usize = 100_000;

/// Key path -> 1-based line.
#[derive(Debug, Default)]
pub(crate) struct LineMap {
    lines: HashMap<Vec<ConfigPathSegment>, usize>,
}

enum Frame {
    Mapping {
        path: Vec<ConfigPathSegment>,
        pending_key: Option<String>,
        is_key: bool,
    },
    Sequence {
        path: Vec<ConfigPathSegment>,
        next_index: usize,
        is_key: bool,
    },
}

/// A YAML syntax error: 1-based line and message.
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct SyntaxError {
    pub line: usize,
    pub message: String,
}

impl LineMap {
    /// Parses `text` (the first document) and records where each key and item starts;
    /// refuses a document beyond the bounds of this module, naming the line.
    pub(crate) fn build(text: &str) -> Result<Self, SyntaxError> {
        check_size(text)?;
        let mut map = LineMap::default();
        let mut stack: Vec<Frame> = Vec::new();
        let mut parser = Parser::new_from_str(text);
        let mut documents = 0usize;
        let mut nodes = 0usize;
        while let Some(next) = parser.next_event() {
            let (event, span) = next.map_err(|error| SyntaxError {
                line: error.marker().line(),
                message: error.info().to_string(),
            })?;
            let line = span.start.line();
            check_node(&event, line, stack.len(), &mut nodes)?;
            match event {
                Event::DocumentStart(_) => {
                    documents += 1;
                    if documents > 1 {
                        return Err(SyntaxError {
                            line,
                            message: "a pipeline file holds one YAML document".to_string(),
                        });
                    }
                }
                Event::Scalar(value, ..) => {
                    map.node_start(&mut stack, line, Some(value.as_ref()), false);
                }
                Event::Alias(_) => {
                    map.node_start(&mut stack, line, None, false);
                }
                Event::MappingStart(..) | Event::SequenceStart(..) => {
                    let is_mapping = matches!(event, Event::MappingStart(..));
                    let (path, is_key) = map.node_start(&mut stack, line, None, true);
                    stack.push(if is_mapping {
                        Frame::Mapping {
                            path,
                            pending_key: None,
                            is_key,
                        }
                    } else {
                        Frame::Sequence {
                            path,
                            next_index: 0,
                            is_key,
                        }
                    });
                }
                Event::MappingEnd | Event::SequenceEnd => {
                    let was_key = match stack.pop() {
                        Some(Frame::Mapping { is_key, .. } | Frame::Sequence { is_key, .. }) => {
                            is_key
                        }
                        None => false,
                    };
                    if let Some(Frame::Mapping { pending_key, .. }) = stack.last_mut() {
                        *pending_key = if was_key {
                            Some("<complex key>".to_string())
                        } else {
                            None
                        };
                    }
                }
                _ => {}
            }
        }
        Ok(map)
    }

    /// Handles the start of a node; returns its path and whether it is a mapping key.
    fn node_start(
        &mut self,
        stack: &mut [Frame],
        line: usize,
        scalar: Option<&str>,
        is_container: bool,
    ) -> (Vec<ConfigPathSegment>, bool) {
        match stack.last_mut() {
            None => {
                self.lines.entry(vec![]).or_insert(line);
                (vec![], false)
            }
            Some(Frame::Sequence {
                path, next_index, ..
            }) => {
                let mut item = path.clone();
                item.push(ConfigPathSegment::Index(*next_index));
                *next_index += 1;
                self.lines.insert(item.clone(), line);
                (item, false)
            }
            Some(Frame::Mapping {
                path, pending_key, ..
            }) => match pending_key.take() {
                None => {
                    // This node is a key.
                    let name = scalar.unwrap_or("<complex key>").to_string();
                    let mut key_path = path.clone();
                    key_path.push(ConfigPathSegment::Key(name.clone()));
                    self.lines.insert(key_path.clone(), line);
                    if !is_container {
                        *pending_key = Some(name);
                    }
                    (key_path, true)
                }
                Some(key) => {
                    let mut value_path = path.clone();
                    value_path.push(ConfigPathSegment::Key(key.clone()));
                    if is_container {
                        // Cleared when the container ends.
                        *pending_key = Some(key);
                    }
                    (value_path, false)
                }
            },
        }
    }

    /// The line of `path`, or of its longest recorded prefix.
    pub(crate) fn line_of(&self, path: &[ConfigPathSegment]) -> usize {
        (0..=path.len())
            .rev()
            .find_map(|length| self.lines.get(&path[..length]).copied())
            .unwrap_or(1)
    }
}

/// Refuses a document larger than [`MAX_YAML_BYTES`], before it is parsed.
fn check_size(text: &str) -> Result<(), SyntaxError> {
    if text.len() > MAX_YAML_BYTES {
        return Err(SyntaxError {
            line: 1,
            message: format!(
                "the document is {} bytes, more than the {MAX_YAML_BYTES} a pipeline may have",
                text.len()
            ),
        });
    }
    Ok(())
}

/// Counts `event` if it starts a node and refuses it when it crosses [`MAX_YAML_NODES`] or,
/// opening a mapping or list `depth` levels deep, [`MAX_YAML_DEPTH`].
fn check_node(
    event: &Event<'_>,
    line: usize,
    depth: usize,
    nodes: &mut usize,
) -> Result<(), SyntaxError> {
    let opens = matches!(event, Event::MappingStart(..) | Event::SequenceStart(..));
    if opens || matches!(event, Event::Scalar(..) | Event::Alias(..)) {
        *nodes += 1;
        if *nodes > MAX_YAML_NODES {
            return Err(SyntaxError {
                line,
                message: format!(
                    "the document holds more than {MAX_YAML_NODES} values: refused before \
                     reading it further"
                ),
            });
        }
    }
    if opens && depth >= MAX_YAML_DEPTH {
        return Err(SyntaxError {
            line,
            message: format!(
                "mappings and lists nest more than {MAX_YAML_DEPTH} levels deep here (by \
                 indentation or brackets): refused before reading it further"
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use ConfigPathSegment::{Index, Key};
    use std::path::Path;

    fn key(name: &str) -> ConfigPathSegment {
        Key(name.to_string())
    }

    #[test]
    fn lines_of_nested_keys_and_items() {
        let text = "stages:\n  - name: a\n    config:\n      size: 3\n      nested: {x: 1,\n        y: 2}\n  - name: b\n    inputs: [a]\n";
        let map = LineMap::build(text).unwrap();
        assert_eq!(map.line_of(&[key("stages")]), 1);
        assert_eq!(map.line_of(&[key("stages"), Index(0)]), 2);
        assert_eq!(
            map.line_of(&[key("stages"), Index(0), key("config"), key("size")]),
            4
        );
        assert_eq!(
            map.line_of(&[
                key("stages"),
                Index(0),
                key("config"),
                key("nested"),
                key("y")
            ]),
            6
        );
        assert_eq!(map.line_of(&[key("stages"), Index(1), key("inputs")]), 8);
        assert_eq!(map.line_of(&[key("stages"), Index(1), key("name")]), 7);
        // Unknown paths fall back to the nearest recorded ancestor.
        assert_eq!(
            map.line_of(&[key("stages"), Index(0), key("config"), key("missing")]),
            3
        );
    }

    /// Lines `"  " * i + "k:"` nest one mapping per line: the 4.5 MB of them took
    /// 521 MB. Refused at the line that crosses the depth bound, in milliseconds.
    #[test]
    fn deep_block_indentation_is_refused_at_its_line() {
        let text: String = (0..200)
            .map(|i| format!("{}k:\n", "  ".repeat(i)))
            .collect();
        let start = std::time::Instant::now();
        let error = LineMap::build(&text).unwrap_err();
        assert!(start.elapsed() < std::time::Duration::from_millis(500));
        // The root mapping opens on line 1, so line 65 opens the 65th level.
        assert_eq!(error.line, MAX_YAML_DEPTH + 1, "{error:?}");
        assert!(
            error.message.contains("more than 64 levels deep"),
            "{error:?}"
        );
        assert_eq!(LineMap::build(&text).unwrap_err(), error);
        // Just under the bound parses.
        let text: String = (0..MAX_YAML_DEPTH)
            .map(|i| format!("{}k:\n", "  ".repeat(i)))
            .collect();
        LineMap::build(&text).unwrap();
    }

    #[test]
    fn deep_brackets_many_nodes_and_large_documents_are_refused() {
        let text = format!("a: {}{}\n", "[".repeat(100), "]".repeat(100));
        let error = LineMap::build(&text).unwrap_err();
        assert_eq!(error.line, 1);
        assert!(error.message.contains("levels deep"), "{error:?}");

        let text = "- 1\n".repeat(MAX_YAML_NODES + 1);
        let error = LineMap::build(&text).unwrap_err();
        assert!(
            error.message.contains("more than 100000 values"),
            "{error:?}"
        );
        // The sequence itself is the first node: the last item crosses the bound.
        assert_eq!(error.line, MAX_YAML_NODES);

        let text = format!("description: \"{}\"\n", "x".repeat(MAX_YAML_BYTES));
        let error = LineMap::build(&text).unwrap_err();
        assert_eq!(error.line, 1);
        assert!(
            error.message.contains("bytes, more than the 1048576"),
            "{error:?}"
        );
    }

    /// The shipped pipelines are well inside the bounds.
    #[test]
    fn shipped_pipelines_pass_the_bounds() {
        let folder = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../pipelines");
        let mut checked = 0;
        for entry in std::fs::read_dir(&folder).unwrap() {
            let path = entry.unwrap().path();
            if path
                .extension()
                .is_some_and(|extension| extension == "yaml")
            {
                let text = std::fs::read_to_string(&path).unwrap();
                LineMap::build(&text)
                    .unwrap_or_else(|error| panic!("{}: {error:?}", path.display()));
                checked += 1;
            }
        }
        assert!(
            checked >= 5,
            "only {checked} pipelines found in {}",
            folder.display()
        );
    }

    #[test]
    fn syntax_errors_carry_a_line() {
        let error = LineMap::build("stages:\n  - name: a\n   bad: [\n").unwrap_err();
        assert!(error.line >= 2, "{error:?}");
    }
}
