//! Shader text helpers: the f32 atomic-add variants of gradient kernels, and (in tests) the
//! naga validation of every `shaders/*.wgsl`.
//!
//! Kernels that accumulate gradients carry the portable compare-exchange `gradient_add`
//! (the code of `shaders/atomic_add_cas.wgsl`) between `// @atomic-add-begin` and
//! `// @atomic-add-end`, so each file is valid WGSL on its own; [`with_atomic_add`] swaps in
//! the native `atomic<f32>` version when the adapter has it.

use super::BackendError;

pub const ATOMIC_ADD_FLOAT_WGSL: &str = include_str!("../../../../shaders/atomic_add_float.wgsl");
pub const ATOMIC_ADD_CAS_WGSL: &str = include_str!("../../../../shaders/atomic_add_cas.wgsl");

const BEGIN: &str = "// @atomic-add-begin";
const END: &str = "// @atomic-add-end";

/// How gradient kernels add floats atomically.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AtomicAdd {
    /// `atomic<f32>` with `atomicAdd` (needs `SHADER_FLOAT32_ATOMIC`).
    NativeFloat,
    /// `atomic<u32>` with a compare-exchange loop on the bit pattern.
    CompareExchange,
}

/// The code of a snippet file without its leading comment block.
fn snippet_code(snippet: &str) -> &str {
    let start = snippet
        .lines()
        .take_while(|line| line.trim_start().starts_with("//") || line.trim().is_empty())
        .map(|line| line.len() + 1)
        .sum::<usize>();
    snippet[start.min(snippet.len())..].trim()
}

/// The byte range of the marked region's contents in `wgsl`, if it has one. Markers are
/// whole lines, so comments may mention them.
fn region(wgsl: &str) -> Option<(usize, usize)> {
    let mut offset = 0;
    let mut begin = None;
    for line in wgsl.split_inclusive('\n') {
        let text = line.trim_end();
        if text == BEGIN && begin.is_none() {
            begin = Some(offset + line.len());
        } else if text == END
            && let Some(begin) = begin
        {
            return Some((begin, offset));
        }
        offset += line.len();
    }
    None
}

/// `wgsl` with its atomic-add region holding the `mode` implementation.
pub fn with_atomic_add(name: &str, wgsl: &str, mode: AtomicAdd) -> Result<String, BackendError> {
    let (begin, end) = region(wgsl).ok_or_else(|| BackendError::Shader {
        name: name.to_owned(),
        message: format!("no `{BEGIN}` ... `{END}` region"),
    })?;
    let snippet = match mode {
        AtomicAdd::NativeFloat => ATOMIC_ADD_FLOAT_WGSL,
        AtomicAdd::CompareExchange => ATOMIC_ADD_CAS_WGSL,
    };
    Ok(format!(
        "{}\n{}\n{}",
        &wgsl[..begin],
        snippet_code(snippet),
        &wgsl[end..]
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn validate(name: &str, wgsl: &str) {
        let module = naga::front::wgsl::parse_str(wgsl)
            .unwrap_or_else(|error| panic!("{name}: {}", error.emit_to_string(wgsl)));
        naga::valid::Validator::new(
            naga::valid::ValidationFlags::all(),
            naga::valid::Capabilities::SHADER_FLOAT32_ATOMIC,
        )
        .validate(&module)
        .unwrap_or_else(|error| panic!("{name}: {}", error.emit_to_string(wgsl)));
    }

    #[test]
    fn every_shader_parses_and_validates() {
        let folder = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders");
        let mut files: Vec<_> = std::fs::read_dir(&folder)
            .unwrap_or_else(|error| panic!("reading {}: {error}", folder.display()))
            .map(|entry| entry.unwrap().path())
            .filter(|path| path.extension().is_some_and(|ext| ext == "wgsl"))
            .collect();
        files.sort();
        assert!(
            files.len() >= 4,
            "found only {} shaders in {}",
            files.len(),
            folder.display()
        );
        let mut variants = 0;
        for path in &files {
            let name = path.display().to_string();
            let wgsl = std::fs::read_to_string(path).unwrap();
            validate(&name, &wgsl);
            if let Some((begin, end)) = region(&wgsl) {
                // The inline fallback must be exactly the shared snippet.
                assert_eq!(
                    wgsl[begin..end].trim(),
                    snippet_code(ATOMIC_ADD_CAS_WGSL),
                    "{name}: the atomic-add region differs from atomic_add_cas.wgsl"
                );
                for mode in [AtomicAdd::NativeFloat, AtomicAdd::CompareExchange] {
                    validate(
                        &format!("{name} ({mode:?})"),
                        &with_atomic_add(&name, &wgsl, mode).unwrap(),
                    );
                    variants += 1;
                }
            }
        }
        eprintln!(
            "validated {} shader files and {variants} atomic variants",
            files.len()
        );
    }

    #[test]
    fn a_shader_without_a_region_is_an_error() {
        let error = with_atomic_add("plain.wgsl", "fn f() {}", AtomicAdd::NativeFloat).unwrap_err();
        assert!(error.to_string().contains("plain.wgsl"), "{error}");
    }
}
