//! `docs/schema.md` is generated from this crate's module docs (each entry's arrays and
//! attributes), so that a reader outside Rust (Python, zarr-python) has the same reference.
//! The test fails when the file and the docs differ; `SEQAVATAR_WRITE_SCHEMA_DOC=1 cargo test
//! -p seqavatar-schema --test schema_doc` rewrites it.

use std::path::Path;

/// The entries in pipeline order: title and the module whose docs describe the entry.
const ENTRIES: &[(&str, &str)] = &[
    ("ingest", "src/ingest.rs"),
    ("Body parameters (ingest and fit entries)", "src/body.rs"),
    ("fit", "src/fit.rs"),
    ("motion", "src/motion.rs"),
    ("train", "src/train.rs"),
    ("eval", "src/eval.rs"),
];

/// The leading `//!` block of a source file, as Markdown: intra-doc links become code spans.
fn module_doc(source: &str) -> String {
    let mut out = String::new();
    for line in source.lines() {
        let Some(text) = line.strip_prefix("//!") else {
            break;
        };
        out.push_str(text.strip_prefix(' ').unwrap_or(text));
        out.push('\n');
    }
    // [`a::b::Name`] -> `Name`; a link's target names Rust items, not files.
    let mut plain = String::with_capacity(out.len());
    let mut rest = out.as_str();
    while let Some(start) = rest.find("[`") {
        let Some(end) = rest[start..].find("`]") else {
            break;
        };
        let inner = &rest[start + 2..start + end];
        plain.push_str(&rest[..start]);
        plain.push('`');
        plain.push_str(inner.rsplit("::").next().unwrap_or(inner));
        plain.push('`');
        rest = &rest[start + end + 2..];
    }
    plain.push_str(rest);
    plain
}

fn schema_markdown(crate_dir: &Path) -> String {
    let mut doc = String::from(
        "# Cache entry schema\n\n\
         Every stage writes one Zarr v3 group per cache entry, `cache/<stage kind>/<key>/`. \
         Arrays carry `dimension_names`; attributes are in the group's `zarr.json`. This file \
         is generated from the docs of the `seqavatar-schema` crate (`src/schema`), which \
         holds the readers and writers the stages share: do not edit it by hand \
         (`SEQAVATAR_WRITE_SCHEMA_DOC=1 cargo test -p seqavatar-schema --test schema_doc`).\n",
    );
    for (title, file) in ENTRIES {
        let path = crate_dir.join(file);
        let source =
            std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let body = module_doc(&source);
        assert!(!body.trim().is_empty(), "{file} has no module docs");
        doc.push_str(&format!("\n## {title}\n\n{}", body.trim_end()));
        doc.push('\n');
    }
    doc
}

#[test]
fn docs_schema_md_is_generated_from_the_crate_docs() {
    let crate_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let target = crate_dir.join("../../docs/schema.md");
    let generated = schema_markdown(crate_dir);
    if std::env::var_os("SEQAVATAR_WRITE_SCHEMA_DOC").is_some() {
        std::fs::write(&target, &generated).unwrap();
        return;
    }
    let committed = std::fs::read_to_string(&target).unwrap_or_default();
    assert!(
        committed == generated,
        "docs/schema.md differs from the seqavatar-schema docs: run \
         `SEQAVATAR_WRITE_SCHEMA_DOC=1 cargo test -p seqavatar-schema --test schema_doc`"
    );
}

/// Every `.rs` file under `dir`, recursively.
fn rust_sources(dir: &Path, out: &mut String) {
    for entry in std::fs::read_dir(dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display())) {
        let path = entry.unwrap().path();
        if path.is_dir() {
            rust_sources(&path, out);
        } else if path.extension().is_some_and(|ext| ext == "rs") {
            let text = std::fs::read_to_string(&path).unwrap();
            for line in text
                .lines()
                .filter(|line| !line.trim_start().starts_with("//"))
            {
                out.push_str(line);
                out.push('\n');
            }
        }
    }
}

/// Every array the docs name with a dtype after it (`` `name` f64 ``) is spelled as a string
/// by some code of the workspace's libraries or stages: the schema does not describe arrays
/// that nothing writes or reads.
#[test]
fn every_documented_array_is_spelled_in_code() {
    let crate_dir = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut code = String::new();
    rust_sources(&crate_dir.join("../../src"), &mut code);
    rust_sources(&crate_dir.join("../../stages"), &mut code);
    let mut checked = 0;
    for (_, file) in ENTRIES {
        let doc = module_doc(&std::fs::read_to_string(crate_dir.join(file)).unwrap());
        let pieces: Vec<&str> = doc.split('`').collect();
        // Odd pieces are inside backticks.
        for at in (1..pieces.len().saturating_sub(1)).step_by(2) {
            let (name, after) = (pieces[at], pieces[at + 1]);
            let typed = ["f64 ", "f32 ", "u8 ", "u32 ", "i64 "]
                .iter()
                .any(|dtype| after.trim_start().starts_with(dtype));
            if !typed || name.contains([' ', '<', '{']) || name.is_empty() {
                continue;
            }
            checked += 1;
            // Prefixed families are spelled as their suffix (`{prefix}_pose`, `gt_` copies).
            let suffix = name.split_once('_').map_or(name, |(_, rest)| rest);
            assert!(
                code.contains(&format!("\"{name}\"")) || code.contains(&format!("_{suffix}\"")),
                "{file}: the docs name array `{name}`, which no code spells"
            );
        }
    }
    assert!(checked > 30, "only {checked} arrays found in the docs");
}
