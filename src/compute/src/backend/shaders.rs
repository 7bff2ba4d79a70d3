//! Shader text helpers: the include step every kernel goes through before it is compiled,
//! the f32 atomic-add variants of gradient kernels, and (in tests) the naga validation of
//! every `shaders/*.wgsl` and the layout check of every uniform and storage struct against
//! its Rust `#[repr(C)]` twin.
//!
//! WGSL has no `#include`. A struct or helper function several kernels share is declared
//! once in a header in `shaders/` ([`HEADERS`]) and a kernel names it on a line of its own,
//! `//#include "splat_types.wgsl"`, which [`expand_includes`] replaces by the header's text.
//! The step is strict: an unknown header, a malformed include line, a header included twice
//! or an include inside a header are errors naming the kernel. Every kernel is compiled
//! through it (`Kernel::compile`, for `GpuContext::kernel` and `NnGpu::new`), and a test
//! checks that no kernel defines a function a header already defines.
//!
//! Kernels that accumulate gradients include the portable compare-exchange `gradient_add`,
//! `//#include "atomic_add_cas.wgsl"`, alone between `// @atomic-add-begin` and
//! `// @atomic-add-end`; [`with_atomic_add`] swaps in the native `atomic<f32>` version of
//! `shaders/atomic_add_float.wgsl` when the adapter has it.

use super::BackendError;

/// wgpu's runtime checks for this project's kernels: every check on but naga's forced loop
/// bounding. That check adds a hidden iteration counter to every loop, so drivers cannot
/// unroll even a four-iteration constant loop. On an H100 (NVIDIA's Vulkan driver) the
/// network kernels ran at 198 GFLOP/s with it and 1616 without (the `paper` iteration at 5.5
/// against 40.7 it/s), measured together with the matrix product's accumulators moving
/// into vec4 values; gfx-rs/wgpu issue 7698 reports the same kind of regression.
/// Its only purpose is to keep an infinite loop from being undefined behaviour, and every
/// loop in `shaders/` ends: counted loops over bounded sizes, the nearest-neighbour
/// insertion whose slot decreases, and the compare-exchange add, which ends when its
/// exchange succeeds (GPUs guarantee the forward progress it needs). Buffer bounds checks
/// stay on.
pub fn runtime_checks() -> wgpu::ShaderRuntimeChecks {
    wgpu::ShaderRuntimeChecks {
        force_loop_bounding: false,
        ..wgpu::ShaderRuntimeChecks::checked()
    }
}

/// Compiles one kernel's expanded WGSL (see [`expand_includes`]) with [`runtime_checks`].
/// Every kernel goes through this function (`Kernel::compile`).
pub fn compile_module(device: &wgpu::Device, name: &str, wgsl: String) -> wgpu::ShaderModule {
    // SAFETY: the one check turned off, loop bounding, guards only against infinite loops,
    // and no kernel in `shaders/` has one (see `runtime_checks`); the source is this
    // project's own WGSL, never user input.
    unsafe {
        device.create_shader_module_trusted(
            wgpu::ShaderModuleDescriptor {
                label: Some(name),
                source: wgpu::ShaderSource::Wgsl(wgsl.into()),
            },
            runtime_checks(),
        )
    }
}

pub const ATOMIC_ADD_FLOAT_WGSL: &str = include_str!("../../../../shaders/atomic_add_float.wgsl");
pub const ATOMIC_ADD_CAS_WGSL: &str = include_str!("../../../../shaders/atomic_add_cas.wgsl");

/// `(file name, text)` of the given files in `shaders/`.
macro_rules! shader_files {
    ($($name:literal),+ $(,)?) => {
        &[$(($name, include_str!(concat!("../../../../shaders/", $name)))),+]
    };
}

/// The shared headers kernels may include, by file name (each is a file in `shaders/`).
pub const HEADERS: &[(&str, &str)] = shader_files![
    "splat_types.wgsl",
    "lpips_types.wgsl",
    "linear_index.wgsl",
    "splat_pixel.wgsl",
    "finite.wgsl",
    "quaternion.wgsl",
    "atomic_add_cas.wgsl",
];

const INCLUDE: &str = "//#include";

/// `wgsl` with every `//#include "NAME"` line replaced by the text of the header `NAME` of
/// [`HEADERS`]. One level only: a header that includes is an error, as are an unknown name,
/// a line that starts with `//#include` but is not exactly `//#include "NAME"`, and a header
/// included twice. `name` is the kernel's, for the error.
pub fn expand_includes(name: &str, wgsl: &str) -> Result<String, BackendError> {
    expand_with(name, wgsl, HEADERS)
}

fn expand_with(name: &str, wgsl: &str, headers: &[(&str, &str)]) -> Result<String, BackendError> {
    let error = |message: String| BackendError::Shader {
        name: name.to_owned(),
        message,
    };
    let mut expanded = String::with_capacity(wgsl.len());
    let mut included: Vec<&str> = Vec::new();
    for (index, line) in wgsl.split_inclusive('\n').enumerate() {
        let text = line.trim();
        let Some(rest) = text.strip_prefix(INCLUDE) else {
            expanded.push_str(line);
            continue;
        };
        let header = rest
            .strip_prefix(' ')
            .and_then(|quoted| quoted.strip_prefix('"'))
            .and_then(|quoted| quoted.strip_suffix('"'))
            .filter(|header| !header.is_empty() && !header.contains('"'))
            .ok_or_else(|| {
                error(format!(
                    "line {}: `{text}` is not of the form `{INCLUDE} \"NAME\"`",
                    index + 1
                ))
            })?;
        let (header, text_of_header) = headers
            .iter()
            .find(|(known, _)| *known == header)
            .copied()
            .ok_or_else(|| {
                let known: Vec<&str> = headers.iter().map(|(known, _)| *known).collect();
                error(format!(
                    "line {}: unknown header \"{header}\" (known: {})",
                    index + 1,
                    known.join(", ")
                ))
            })?;
        if included.contains(&header) {
            return Err(error(format!(
                "line {}: header \"{header}\" is included twice",
                index + 1
            )));
        }
        if text_of_header
            .lines()
            .any(|line| line.trim().starts_with(INCLUDE))
        {
            return Err(error(format!(
                "line {}: header \"{header}\" includes another header (one level only)",
                index + 1
            )));
        }
        included.push(header);
        expanded.push_str(text_of_header);
        if !text_of_header.ends_with('\n') {
            expanded.push('\n');
        }
    }
    Ok(expanded)
}

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
pub(crate) mod tests {
    use super::*;

    /// A WGSL uniform or storage struct and its Rust `#[repr(C)]` twin, as the layout test
    /// compares them: each module that uploads such a struct lists its twins next to it
    /// (`wgsl_twins()`, built with `wgsl_twin!`).
    pub(crate) struct WgslTwin {
        /// The kernel files (in `shaders/`) whose struct this is.
        pub kernels: &'static [&'static str],
        pub wgsl_struct: &'static str,
        pub rust_struct: &'static str,
        pub size: usize,
        /// The Rust places of the WGSL members, in the WGSL order.
        pub fields: Vec<TwinField>,
    }

    /// Where the Rust twin keeps one WGSL member.
    pub(crate) struct TwinField {
        pub wgsl: &'static str,
        pub offset: usize,
        pub size: usize,
        pub kind: naga::ScalarKind,
    }

    /// The scalar kind of a Rust field's elements, to compare with the WGSL member's.
    pub(crate) trait TwinScalar {
        const KIND: naga::ScalarKind;
    }

    impl TwinScalar for u32 {
        const KIND: naga::ScalarKind = naga::ScalarKind::Uint;
    }

    impl TwinScalar for i32 {
        const KIND: naga::ScalarKind = naga::ScalarKind::Sint;
    }

    impl TwinScalar for f32 {
        const KIND: naga::ScalarKind = naga::ScalarKind::Float;
    }

    impl<T: TwinScalar, const N: usize> TwinScalar for [T; N] {
        const KIND: naga::ScalarKind = T::KIND;
    }

    impl TwinField {
        /// The place `field` inside `value` (a reference into it) holding the WGSL member `wgsl`.
        pub fn of<T, F: TwinScalar>(wgsl: &'static str, value: &T, field: &F) -> Self {
            let start = std::ptr::from_ref(value).addr();
            let at = std::ptr::from_ref(field).addr();
            assert!(
                at >= start && at + size_of::<F>() <= start + size_of::<T>(),
                "{wgsl}: the place given is not inside the value"
            );
            Self {
                wgsl,
                offset: at - start,
                size: size_of::<F>(),
                kind: F::KIND,
            }
        }
    }

    /// Describes a Rust twin of a WGSL struct for the layout test:
    /// `wgsl_twin!(CameraUniform as "SplatCamera" in ["splat_project.wgsl"] {
    /// rotation[0] as "rotation0", intrinsics, ... })`, one entry per WGSL member in order,
    /// each naming the Rust field (and array index) that holds it, and the member's name where
    /// it is not the field's.
    macro_rules! wgsl_twin {
        (@member $field:ident) => {
            stringify!($field)
        };
        (@member $field:ident $member:literal) => {
            $member
        };
        ($rust:ty as $wgsl:literal in [$($kernel:literal),+ $(,)?] {
            $($field:ident $([$index:literal])? $(as $member:literal)?),+ $(,)?
        }) => {{
            let value: $rust = bytemuck::Zeroable::zeroed();
            $crate::backend::shaders::tests::WgslTwin {
                kernels: &[$($kernel),+],
                wgsl_struct: $wgsl,
                rust_struct: stringify!($rust),
                size: size_of::<$rust>(),
                fields: vec![$(
                    $crate::backend::shaders::tests::TwinField::of(
                        $crate::backend::shaders::tests::wgsl_twin!(@member $field $($member)?),
                        &value,
                        &value.$field $([$index])?,
                    )
                ),+],
            }
        }};
    }
    pub(crate) use wgsl_twin;

    /// The capabilities a kernel may use: f32 atomics (the native atomic-add variant), and
    /// f16 or cooperative matrices only where the kernel enables them, so an f32 kernel that
    /// slips into f16 fails here.
    fn capabilities(wgsl: &str) -> naga::valid::Capabilities {
        use naga::valid::Capabilities;
        let enables = |extension: &str| {
            wgsl.lines()
                .any(|line| line.trim() == format!("enable {extension};"))
        };
        let mut capabilities = Capabilities::SHADER_FLOAT32_ATOMIC;
        if enables("f16") {
            capabilities |= Capabilities::SHADER_FLOAT16;
        }
        if enables("wgpu_cooperative_matrix") {
            capabilities |= Capabilities::COOPERATIVE_MATRIX;
        }
        capabilities
    }

    fn validate_with_info(name: &str, wgsl: &str) -> (naga::Module, naga::valid::ModuleInfo) {
        let module = naga::front::wgsl::parse_str(wgsl)
            .unwrap_or_else(|error| panic!("{name}: {}", error.emit_to_string(wgsl)));
        let info =
            naga::valid::Validator::new(naga::valid::ValidationFlags::all(), capabilities(wgsl))
                .validate(&module)
                .unwrap_or_else(|error| panic!("{name}: {}", error.emit_to_string(wgsl)));
        (module, info)
    }

    fn validate(name: &str, wgsl: &str) -> naga::Module {
        validate_with_info(name, wgsl).0
    }

    /// Every `shaders/*.wgsl` as (file name, text), sorted; at least a few, so a wrong
    /// folder cannot make the tests check nothing.
    fn shader_files() -> Vec<(String, String)> {
        let folder = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../shaders");
        let mut files: Vec<_> = std::fs::read_dir(&folder)
            .unwrap_or_else(|error| panic!("reading {}: {error}", folder.display()))
            .map(|entry| entry.unwrap().path())
            .filter(|path| path.extension().is_some_and(|ext| ext == "wgsl"))
            .map(|path| {
                let name = path.file_name().unwrap().to_string_lossy().into_owned();
                (name, std::fs::read_to_string(&path).unwrap())
            })
            .collect();
        files.sort();
        assert!(
            files.len() >= 4,
            "found only {} shaders in {}",
            files.len(),
            folder.display()
        );
        files
    }

    /// The shader files that are not headers: headers that are helpers need declarations of
    /// their includer (`WORKGROUP`, `ALPHA_THRESHOLD`), so they are validated inside every
    /// kernel that includes them (and a test checks each is included by one).
    fn kernel_files() -> Vec<(String, String)> {
        shader_files()
            .into_iter()
            .filter(|(name, _)| !HEADERS.iter().any(|(header, _)| header == name))
            .collect()
    }

    #[test]
    fn every_shader_parses_and_validates() {
        let files = kernel_files();
        let mut variants = 0;
        for (name, raw) in &files {
            let wgsl = expand_includes(name, raw).unwrap();
            validate(name, &wgsl);
            if let Some((begin, end)) = region(raw) {
                // The fallback is the shared header, never a copy of it.
                assert_eq!(
                    raw[begin..end].trim(),
                    r#"//#include "atomic_add_cas.wgsl""#,
                    "{name}: the atomic-add region must only include atomic_add_cas.wgsl"
                );
                for mode in [AtomicAdd::NativeFloat, AtomicAdd::CompareExchange] {
                    validate(
                        &format!("{name} ({mode:?})"),
                        &with_atomic_add(name, &wgsl, mode).unwrap(),
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

    /// SPIR-V opcodes and operands the tensor-core check reads (SPIR-V 1.6 with
    /// SPV_KHR_cooperative_matrix).
    mod spirv_op {
        pub const MEMORY_MODEL: u32 = 14;
        pub const CAPABILITY: u32 = 17;
        pub const TYPE_FLOAT: u32 = 22;
        pub const CONSTANT: u32 = 43;
        pub const TYPE_COOPERATIVE_MATRIX: u32 = 4456;
        pub const COOPERATIVE_MATRIX_LOAD: u32 = 4457;
        pub const COOPERATIVE_MATRIX_STORE: u32 = 4458;
        pub const COOPERATIVE_MATRIX_MUL_ADD: u32 = 4459;
        pub const CAPABILITY_FLOAT16: u32 = 9;
        pub const CAPABILITY_COOPERATIVE_MATRIX: u32 = 6022;
        pub const MEMORY_MODEL_VULKAN: u32 = 3;
    }

    /// A cooperative-matrix type of a SPIR-V module: (float width, rows, columns, use).
    type CoopType = (u32, u32, u32, u32);

    /// What the tensor-core kernel's SPIR-V says about its cooperative matrices: the types of
    /// each multiply-add's A, B and result, and the numbers of loads and stores.
    struct CoopSummary {
        capabilities: Vec<u32>,
        memory_model: u32,
        multiply_adds: Vec<[CoopType; 3]>,
        loads: usize,
        stores: usize,
    }

    fn summarise_cooperative_matrices(words: &[u32]) -> CoopSummary {
        use std::collections::HashMap;
        assert_eq!(words[0], 0x0723_0203, "not a SPIR-V module");
        let mut float_width: HashMap<u32, u32> = HashMap::new();
        let mut constant: HashMap<u32, u32> = HashMap::new();
        let mut coop_type: HashMap<u32, CoopType> = HashMap::new();
        // The result type of every value that is a cooperative matrix.
        let mut value_type: HashMap<u32, u32> = HashMap::new();
        let mut summary = CoopSummary {
            capabilities: Vec::new(),
            memory_model: u32::MAX,
            multiply_adds: Vec::new(),
            loads: 0,
            stores: 0,
        };
        let mut at = 5;
        while at < words.len() {
            let count = (words[at] >> 16) as usize;
            let opcode = words[at] & 0xffff;
            assert!(count > 0 && at + count <= words.len(), "truncated SPIR-V");
            let operands = &words[at + 1..at + count];
            match opcode {
                spirv_op::CAPABILITY => summary.capabilities.push(operands[0]),
                spirv_op::MEMORY_MODEL => summary.memory_model = operands[1],
                spirv_op::TYPE_FLOAT => {
                    float_width.insert(operands[0], operands[1]);
                }
                spirv_op::CONSTANT => {
                    constant.insert(operands[1], operands[2]);
                }
                spirv_op::TYPE_COOPERATIVE_MATRIX => {
                    // Result id, component type, scope, rows, columns, use (ids of constants).
                    let width = float_width[&operands[1]];
                    let [rows, columns, role] = [3, 4, 5].map(|index| constant[&operands[index]]);
                    coop_type.insert(operands[0], (width, rows, columns, role));
                }
                spirv_op::COOPERATIVE_MATRIX_LOAD => {
                    value_type.insert(operands[1], operands[0]);
                    summary.loads += 1;
                }
                spirv_op::COOPERATIVE_MATRIX_STORE => summary.stores += 1,
                spirv_op::COOPERATIVE_MATRIX_MUL_ADD => {
                    value_type.insert(operands[1], operands[0]);
                    let a = coop_type[&value_type[&operands[2]]];
                    let b = coop_type[&value_type[&operands[3]]];
                    let result = coop_type[&operands[0]];
                    summary.multiply_adds.push([a, b, result]);
                }
                _ => {}
            }
            at += count;
        }
        summary
    }

    /// The tensor-core kernel validates with the capabilities the device is opened with (f16
    /// and cooperative matrices), and naga's SPIR-V backend, with wgpu's bounds checks,
    /// writes it as f16 x f16 products accumulated in f32 on 16 x 16 x 16 matrices: the
    /// configuration `nn::gpu` requires of the adapter. Runs without any adapter.
    #[test]
    fn tensor_core_kernel_writes_spirv_with_f16_operands_and_f32_accumulators() {
        let name = "nn_matmul_coop.wgsl";
        let (_, raw) = kernel_files()
            .into_iter()
            .find(|(file, _)| file == name)
            .expect("the tensor-core kernel is a file of shaders/");
        let wgsl = expand_includes(name, &raw).unwrap();
        let (module, info) = validate_with_info(name, &wgsl);
        // Without f16 or cooperative matrices the kernel is rejected, so the capability
        // check above is not vacuous.
        for missing in [
            naga::valid::Capabilities::SHADER_FLOAT16,
            naga::valid::Capabilities::COOPERATIVE_MATRIX,
        ] {
            let capabilities = capabilities(&wgsl) - missing;
            assert!(
                naga::valid::Validator::new(naga::valid::ValidationFlags::all(), capabilities)
                    .validate(&module)
                    .is_err(),
                "{name} validated without {missing:?}"
            );
        }
        let mut constants = naga::back::PipelineConstants::default();
        constants.insert("SUBGROUP_SIZE".to_owned(), 32.0);
        let (module, info) = naga::back::pipeline_constants::process_overrides(
            &module,
            &info,
            Some((naga::ShaderStage::Compute, "multiply")),
            &constants,
        )
        .unwrap();
        // wgpu-hal's Vulkan options: SPIR-V 1.6 on Vulkan 1.3, indices restricted, buffer
        // accesses restricted unless the device has robustBufferAccess2.
        use naga::proc::BoundsCheckPolicy;
        for buffer in [BoundsCheckPolicy::Restrict, BoundsCheckPolicy::Unchecked] {
            let options = naga::back::spv::Options {
                lang_version: (1, 6),
                bounds_check_policies: naga::proc::BoundsCheckPolicies {
                    index: BoundsCheckPolicy::Restrict,
                    buffer,
                    image_load: BoundsCheckPolicy::Restrict,
                    binding_array: BoundsCheckPolicy::Unchecked,
                },
                ..naga::back::spv::Options::default()
            };
            let pipeline = naga::back::spv::PipelineOptions {
                shader_stage: naga::ShaderStage::Compute,
                entry_point: "multiply".to_owned(),
            };
            let words = naga::back::spv::write_vec(&module, &info, &options, Some(&pipeline))
                .unwrap_or_else(|error| panic!("{name} ({buffer:?}): SPIR-V: {error}"));
            let summary = summarise_cooperative_matrices(&words);
            for capability in [
                spirv_op::CAPABILITY_FLOAT16,
                spirv_op::CAPABILITY_COOPERATIVE_MATRIX,
            ] {
                assert!(
                    summary.capabilities.contains(&capability),
                    "capability {capability} missing: {:?}",
                    summary.capabilities
                );
            }
            assert_eq!(summary.memory_model, spirv_op::MEMORY_MODEL_VULKAN);
            // (width, rows, columns, use): use 0 is A, 1 is B, 2 the accumulator.
            let expected = [(16, 16, 16, 0), (16, 16, 16, 1), (32, 16, 16, 2)];
            assert_eq!(summary.multiply_adds, vec![expected; 4], "{buffer:?}");
            // Four tile loads; one store, in `store_tile`, called four times.
            assert_eq!((summary.loads, summary.stores), (4, 1), "{buffer:?}");
        }
    }

    /// The names of the functions `wgsl` defines (`fn NAME(` at the start of a line).
    fn defined_functions(wgsl: &str) -> Vec<&str> {
        wgsl.lines()
            .filter_map(|line| line.strip_prefix("fn "))
            .filter_map(|rest| rest.split('(').next())
            .map(str::trim)
            .collect()
    }

    #[test]
    fn no_kernel_repeats_a_header_function() {
        let files = shader_files();
        let mut checked = 0;
        for (header, text) in HEADERS {
            for function in defined_functions(text) {
                for (name, raw) in &files {
                    // The headers themselves, and the native variant that replaces the
                    // compare-exchange header, define them.
                    if HEADERS.iter().any(|(known, _)| known == name)
                        || name == "atomic_add_float.wgsl"
                    {
                        continue;
                    }
                    assert!(
                        !defined_functions(raw).contains(&function),
                        "{name} defines `{function}`, which {header} already has: include it"
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 0, "no header function was checked");
    }

    #[test]
    fn a_shader_without_a_region_is_an_error() {
        let error = with_atomic_add("plain.wgsl", "fn f() {}", AtomicAdd::NativeFloat).unwrap_err();
        assert!(error.to_string().contains("plain.wgsl"), "{error}");
    }

    #[test]
    fn includes_expand_strictly() {
        let headers = [
            ("a.wgsl", "struct A { x: u32, }"),
            (
                "nested.wgsl",
                "//#include \"a.wgsl\"\nstruct B { y: u32, }\n",
            ),
        ];
        let expanded = expand_with(
            "k.wgsl",
            "// top\n  //#include \"a.wgsl\"  \nfn f() {}",
            &headers,
        )
        .unwrap();
        assert_eq!(expanded, "// top\nstruct A { x: u32, }\nfn f() {}");
        // Comments may mention the directive mid-line.
        let plain = "// see //#include \"b.wgsl\"\n";
        assert_eq!(expand_with("k.wgsl", plain, &headers).unwrap(), plain);
        for (text, expected) in [
            (
                "//#include \"zzz.wgsl\"\n",
                "unknown header \"zzz.wgsl\" (known: a.wgsl, nested.wgsl)",
            ),
            (
                "//#include a.wgsl\n",
                "line 1: `//#include a.wgsl` is not of the form",
            ),
            ("//#include \"\"\n", "is not of the form"),
            ("//#include\"a.wgsl\"\n", "is not of the form"),
            (
                "//#include \"a.wgsl\"\n//#include \"a.wgsl\"\n",
                "line 2: header \"a.wgsl\" is included twice",
            ),
            (
                "//#include \"nested.wgsl\"\n",
                "header \"nested.wgsl\" includes another header",
            ),
        ] {
            let error = expand_with("k.wgsl", text, &headers)
                .unwrap_err()
                .to_string();
            assert!(
                error.contains("k.wgsl") && error.contains(expected),
                "{text:?}: {error}"
            );
        }
        // The real headers include nothing and are included by some kernel each.
        let files = shader_files();
        for (header, text) in HEADERS {
            expand_includes(header, text).unwrap();
            assert!(
                files
                    .iter()
                    .any(|(name, raw)| name == header && raw == text),
                "{header} is not a file of shaders/"
            );
            let directive = format!("//#include \"{header}\"");
            assert!(
                files
                    .iter()
                    .any(|(_, raw)| raw.lines().any(|line| line.trim() == directive)),
                "no kernel includes {header}"
            );
        }
    }

    /// A struct of a shared header is declared there only: no kernel declares its own copy.
    #[test]
    fn header_structs_are_declared_once() {
        let files = shader_files();
        let mut structs = 0;
        for (header, text) in HEADERS {
            for line in text.lines() {
                let Some(rest) = line.strip_prefix("struct ") else {
                    continue;
                };
                let declaration = format!("struct {}", rest.trim_end_matches([' ', '{']));
                structs += 1;
                for (name, raw) in &files {
                    if name != header {
                        assert!(
                            !raw.lines()
                                .any(|line| line.trim_end_matches([' ', '{']) == declaration),
                            "{name} declares `{declaration}` again; include {header} instead"
                        );
                    }
                }
            }
        }
        assert!(structs >= 2, "only {structs} header structs checked");
    }

    /// The scalar kind of a naga type's elements (`None` for structs and opaque types).
    fn scalar_kind(
        module: &naga::Module,
        ty: naga::Handle<naga::Type>,
    ) -> Option<naga::ScalarKind> {
        match module.types[ty].inner {
            naga::TypeInner::Scalar(scalar) | naga::TypeInner::Atomic(scalar) => Some(scalar.kind),
            naga::TypeInner::Vector { scalar, .. } | naga::TypeInner::Matrix { scalar, .. } => {
                Some(scalar.kind)
            }
            naga::TypeInner::Array { base, .. } => scalar_kind(module, base),
            _ => None,
        }
    }

    /// Every difference between a WGSL struct (as naga lays it out) and its Rust twin.
    fn layout_differences(
        file: &str,
        module: &naga::Module,
        layouter: &naga::proc::Layouter,
        ty: naga::Handle<naga::Type>,
        twin: &WgslTwin,
    ) -> Vec<String> {
        let naga::TypeInner::Struct { members, span } = &module.types[ty].inner else {
            unreachable!("only structs are compared");
        };
        let what = format!(
            "{file}: `{}` vs Rust `{}`",
            twin.wgsl_struct, twin.rust_struct
        );
        let mut differences = Vec::new();
        if *span as usize != twin.size {
            differences.push(format!(
                "{what}: size {span} bytes in WGSL, {} in Rust",
                twin.size
            ));
        }
        let wgsl_names: Vec<&str> = members
            .iter()
            .map(|member| member.name.as_deref().unwrap_or("?"))
            .collect();
        let rust_names: Vec<&str> = twin.fields.iter().map(|field| field.wgsl).collect();
        if wgsl_names != rust_names {
            differences.push(format!(
                "{what}: members {wgsl_names:?} in WGSL, the twin maps {rust_names:?}"
            ));
            return differences;
        }
        for (member, field) in members.iter().zip(&twin.fields) {
            let size = layouter[member.ty].size as usize;
            if member.offset as usize != field.offset || size != field.size {
                differences.push(format!(
                    "{what}: `{}` at offset {} ({size} bytes) in WGSL, {} ({} bytes) in Rust",
                    field.wgsl, member.offset, field.offset, field.size
                ));
            }
            let kind = scalar_kind(module, member.ty);
            if kind != Some(field.kind) {
                differences.push(format!(
                    "{what}: `{}` holds {kind:?} in WGSL, {:?} in Rust",
                    field.wgsl, field.kind
                ));
            }
        }
        differences
    }

    /// Every uniform and storage struct of every kernel (after includes) has a registered
    /// Rust twin with the same size, members, offsets, sizes and scalar kinds.
    #[test]
    fn uniform_and_storage_structs_match_their_rust_twins() {
        let twins: Vec<WgslTwin> = [
            crate::backend::primitives::wgsl_twins(),
            crate::splat::gpu::wgsl_twins(),
            crate::lpips::gpu::wgsl_twins(),
            crate::lpips::gpu::resident_wgsl_twins(),
            crate::nn::gpu::wgsl_twins(),
        ]
        .into_iter()
        .flatten()
        .collect();
        let mut differences = Vec::new();
        let mut checked = Vec::new();
        for (file, raw) in kernel_files() {
            let wgsl = expand_includes(&file, &raw).unwrap();
            let module = naga::front::wgsl::parse_str(&wgsl)
                .unwrap_or_else(|error| panic!("{file}: {}", error.emit_to_string(&wgsl)));
            let mut layouter = naga::proc::Layouter::default();
            layouter.update(module.to_ctx()).unwrap();
            for (_, global) in module.global_variables.iter() {
                if !matches!(
                    global.space,
                    naga::AddressSpace::Uniform | naga::AddressSpace::Storage { .. }
                ) {
                    continue;
                }
                let mut ty = global.ty;
                if let naga::TypeInner::Array { base, .. } = module.types[ty].inner {
                    ty = base;
                }
                if !matches!(module.types[ty].inner, naga::TypeInner::Struct { .. }) {
                    continue;
                }
                let name = module.types[ty].name.clone().unwrap_or_default();
                let Some(twin) = twins
                    .iter()
                    .find(|twin| twin.wgsl_struct == name && twin.kernels.contains(&file.as_str()))
                else {
                    differences.push(format!(
                        "{file}: struct `{name}` is bound but has no Rust twin (add one with wgsl_twin!)"
                    ));
                    continue;
                };
                differences.extend(layout_differences(&file, &module, &layouter, ty, twin));
                checked.push(format!("{file}:{name}"));
            }
        }
        for twin in &twins {
            for kernel in twin.kernels {
                let key = format!("{kernel}:{}", twin.wgsl_struct);
                if !checked.contains(&key) {
                    differences.push(format!(
                        "the twin `{}` names {key}, which binds no such struct",
                        twin.rust_struct
                    ));
                }
            }
        }
        assert!(differences.is_empty(), "{}", differences.join("\n"));
        eprintln!(
            "{} bound structs match their Rust twins: {checked:?}",
            checked.len()
        );
        assert!(checked.len() >= 12, "{checked:?}");
    }
}
