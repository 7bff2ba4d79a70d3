//! The pure-Rust `.smc` (HDF5) reader on damaged and hostile files written by h5py
//! (`tests/fixtures/write_datasets.py`, committed in `tests/fixtures/data/dna/variants`):
//! invalid UTF-8 in a string attribute, datasets declaring far more than the file holds, and
//! flipped bytes. Each gives an error naming the file and the object, never a panic, and
//! nothing large is allocated (measured with a counting allocator).

mod hdf5_support;
mod support;

use seqavatar_core::rng::SplitMix64;
use seqavatar_datasets::dna_rendering::DnaRendering;
use seqavatar_datasets::smc::{self, MAX_DATASET_BYTES, MAX_DEFLATE_RATIO, SmcFile};
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

/// The system allocator, recording the largest single allocation of the current thread.
struct Counting;

thread_local! {
    static LARGEST: Cell<usize> = const { Cell::new(0) };
}

// SAFETY: forwards to `System`; only records sizes in a const-initialised thread local.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(layout.size())));
        // SAFETY: same contract as the caller's.
        unsafe { System.alloc(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: same contract as the caller's.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let _ = LARGEST.try_with(|l| l.set(l.get().max(new_size)));
        // SAFETY: same contract as the caller's.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// Runs `work` and returns its result with the largest allocation it made on this thread.
fn largest_allocation<T>(work: impl FnOnce() -> T) -> (T, usize) {
    LARGEST.with(|l| l.set(0));
    let result = work();
    (result, LARGEST.with(Cell::get))
}

fn error_text<T>(result: anyhow::Result<T>) -> String {
    match result {
        Ok(_) => panic!("expected an error"),
        Err(e) => format!("{e:#}"),
    }
}

fn assert_mentions(text: &str, parts: &[&str]) {
    for part in parts {
        assert!(text.contains(part), "`{part}` missing from: {text}");
    }
}

#[test]
fn invalid_utf8_in_a_string_attribute_is_a_clear_error() {
    let dir = support::dataset_fixture("dna");
    let bad = dir.path().join("variants/main_bad_utf8.smc");
    let file = SmcFile::open(&bad).unwrap();
    let text = error_text(file.string_attr("", "gender"));
    assert_mentions(&text, &["main_bad_utf8.smc", "attribute `gender`", "UTF-8"]);
    // The same file in place of the take's main file: opening the take fails the same way.
    let main = dir.path().join("dna_rendering_part1_main/0007_04.smc");
    std::fs::copy(&bad, &main).unwrap();
    let text = error_text(DnaRendering::open(&main, None, None));
    assert_mentions(&text, &["0007_04.smc", "attribute `gender`", "UTF-8"]);
    // The intact file reads the string.
    let good = support::fixture_data_dir().join("dna/dna_rendering_part1_main/0007_04.smc");
    let file = SmcFile::open(&good).unwrap();
    assert_eq!(
        file.string_attr("", "gender").unwrap().as_deref(),
        Some("female")
    );
    assert_eq!(file.string_attr("", "no_such").unwrap(), None);
}

#[test]
fn huge_declared_datasets_are_refused_before_allocating() {
    let dir = support::dataset_fixture("dna");
    let path = dir.path().join("variants/huge_declared.smc");
    let file = SmcFile::open(&path).unwrap();
    for (dataset, declared) in [
        ("contiguous", "[400000000, 3]"),
        ("chunked_gzip", "[400000000, 3]"),
        ("bytes", "[2000000000]"),
        ("medium", "[10000000, 3]"),
    ] {
        let (result, largest) = largest_allocation(|| file.read_f64s(dataset));
        let text = error_text(result);
        assert_mentions(
            &text,
            &[
                "huge_declared.smc",
                &format!("`{dataset}`"),
                declared,
                "can hold",
            ],
        );
        assert!(
            largest < 1 << 20,
            "{dataset}: allocated {largest} bytes before refusing"
        );
    }
    // Through the DNA reader: an annotation file whose `SMPLx/transl` declares (4e8, 3).
    let annotations = dir
        .path()
        .join("dna_rendering_part1_annotations/0007_04_annots.smc");
    std::fs::copy(
        dir.path().join("variants/annots_huge_transl.smc"),
        &annotations,
    )
    .unwrap();
    let main = dir.path().join("dna_rendering_part1_main/0007_04.smc");
    let (result, largest) = largest_allocation(|| DnaRendering::open(&main, None, None));
    let text = error_text(result);
    assert_mentions(
        &text,
        &["0007_04_annots.smc", "`SMPLx/transl`", "[400000000, 3]"],
    );
    assert!(largest < 8 << 20, "allocated {largest} bytes");
}

/// Flips bytes of the fixture files (every byte of the first 1 KiB one at a time, then
/// random bytes across the file) and reads everything: errors are fine, panics and large
/// allocations are not.
#[test]
fn flipped_bytes_give_errors_never_a_crash() {
    let root = support::fixture_data_dir().join("dna");
    let mut rng = SplitMix64::new(16);
    for name in [
        "dna_rendering_part1_main/0007_04.smc",
        "dna_rendering_part1_annotations/0007_04_annots.smc",
        "layouts.smc",
    ] {
        let original = std::fs::read(root.join(name)).unwrap();
        let objects = smc::read_all(&original).unwrap();
        assert!(objects >= 15, "{name}: read {objects} objects");
        let mut damaged = 0;
        let header = original.len().min(1024);
        let mut mutants: Vec<Vec<u8>> = (0..header)
            .map(|i| {
                let mut bytes = original.clone();
                bytes[i] ^= 0xff;
                bytes
            })
            .collect();
        for _ in 0..300 {
            let mut bytes = original.clone();
            for _ in 0..1 + rng.next_u64() % 4 {
                let at = (rng.next_u64() % bytes.len() as u64) as usize;
                bytes[at] ^= 1 << (rng.next_u64() % 8);
            }
            mutants.push(bytes);
        }
        // Truncations too.
        for cut in [0, 7, 100, original.len() / 2, original.len() - 1] {
            mutants.push(original[..cut].to_vec());
        }
        for bytes in &mutants {
            let (result, largest) = largest_allocation(|| smc::read_all(bytes));
            if result.is_err() {
                damaged += 1;
            }
            // At most what the file can hold (module docs of `smc`) plus 1 MiB of metadata.
            let bound = (bytes.len() as u64 * MAX_DEFLATE_RATIO).min(MAX_DATASET_BYTES) + (1 << 20);
            assert!(
                largest as u64 <= bound,
                "{name}: a damaged copy allocated {largest} bytes (bound {bound})"
            );
        }
        assert!(damaged > 0, "{name}: no damaged copy was detected");
    }
}

/// Every layout and type h5py writes (`write_layouts` in `tests/fixtures/write_datasets.py`)
/// reads back to the values recomputed here.
#[test]
fn every_layout_h5py_writes_reads_back() {
    let path = support::fixture_data_dir().join("dna/layouts.smc");
    let file = SmcFile::open(&path).unwrap();
    let bytes: Vec<u8> = (0..1500u32).map(|i| (i * 31 % 251) as u8).collect();
    let mut layouts = file.members("Camera_5mp/00/color").unwrap();
    layouts.sort();
    assert_eq!(
        layouts,
        ["chunked", "contiguous", "gzip", "shuffle_gzip"],
        "zero-padded group"
    );
    for layout in &layouts {
        let got = file
            .read_bytes(&format!("Camera_5mp/00/color/{layout}"))
            .unwrap();
        assert_eq!(got, bytes, "{layout}");
    }
    assert_eq!(
        file.read_bytes("Camera_5mp/2/color/contiguous").unwrap(),
        bytes
    );
    assert!(file.has_group("Camera_5mp/2").unwrap());
    assert!(file.has_group("Camera_5mp/00").unwrap());
    assert!(!file.has_group("Camera_5mp/0").unwrap());
    assert!(!file.has_group("Camera_12mp/0").unwrap());
    assert!(file.has_dataset("arrays/f64").unwrap());
    assert!(!file.has_dataset("arrays").unwrap());
    let eighths: Vec<f64> = (0..24).map(|i| f64::from(i) / 8.0).collect();
    for name in ["f64", "f32", "f64_gzip"] {
        let (shape, values) = file.read_f64s(&format!("arrays/{name}")).unwrap();
        assert_eq!(shape, vec![2, 3, 4], "{name}");
        assert_eq!(values, eighths, "{name}");
    }
    let shifted: Vec<f64> = (0..24).map(|i| f64::from(i - 5)).collect();
    for name in ["i32_be", "i16"] {
        let (shape, values) = file.read_f64s(&format!("arrays/{name}")).unwrap();
        assert_eq!(shape, vec![2, 3, 4], "{name}");
        assert_eq!(values, shifted, "{name}");
    }
    assert_eq!(
        hdf5_support::dataset_info(&path, "arrays/i32_be"),
        (vec![2, 3, 4], ">i4".to_owned())
    );
    // Bytes are only read from 1-byte datasets.
    let text = error_text(file.read_bytes("arrays/f64"));
    assert_mentions(
        &text,
        &["layouts.smc", "`arrays/f64`", "float64", "not bytes"],
    );
    let text = error_text(file.read_f64s("arrays/missing"));
    assert_mentions(&text, &["layouts.smc", "missing dataset `arrays/missing`"]);
    // Attributes.
    assert_eq!(
        file.string_attr("", "vlen_utf8").unwrap().as_deref(),
        Some("h\u{e9}llo")
    );
    assert_eq!(
        file.string_attr("", "fixed_ascii").unwrap().as_deref(),
        Some("fixed")
    );
    assert_eq!(file.f64s_attr("", "int").unwrap(), Some(vec![25.0]));
    assert_eq!(file.f64s_attr("", "float").unwrap(), Some(vec![1.7]));
    assert_eq!(file.f64s_attr("", "ints").unwrap(), Some(vec![32.0, 40.0]));
    assert_eq!(file.f64s_attr("", "missing").unwrap(), None);
    let text = error_text(file.string_attr("", "int"));
    assert_mentions(&text, &["layouts.smc", "attribute `int`"]);
}
