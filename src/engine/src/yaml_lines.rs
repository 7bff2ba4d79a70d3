//! Maps key paths of a YAML document to the line where each key (or list item) appears, from
//! saphyr-parser events, so that errors can name the line.

use std::collections::HashMap;

use saphyr_parser::{Event, Parser};

use crate::config::ConfigPathSegment;

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
    /// Parses `text` (the first document) and records where each key and item starts.
    pub(crate) fn build(text: &str) -> Result<Self, SyntaxError> {
        let mut map = LineMap::default();
        let mut stack: Vec<Frame> = Vec::new();
        let mut parser = Parser::new_from_str(text);
        let mut documents = 0usize;
        while let Some(next) = parser.next_event() {
            let (event, span) = next.map_err(|error| SyntaxError {
                line: error.marker().line(),
                message: error.info().to_string(),
            })?;
            let line = span.start.line();
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

#[cfg(test)]
mod tests {
    use super::*;
    use ConfigPathSegment::{Index, Key};

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

    #[test]
    fn syntax_errors_carry_a_line() {
        let error = LineMap::build("stages:\n  - name: a\n   bad: [\n").unwrap_err();
        assert!(error.line >= 2, "{error:?}");
    }
}
