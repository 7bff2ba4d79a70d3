//! `.smc` (HDF5) read speed: every image dataset (`Camera_*/<id>/color/<frame>`) of one
//! DNA-Rendering main file, read with the pure-Rust reader ([`seqavatar_datasets::smc`])
//! and, with `--features bench-hdf5-c` (needs libhdf5-dev), with the C library through
//! `hdf5-metno` in the same run, on the same file; both must return the same bytes.
//!
//! `cargo bench -p seqavatar-datasets --bench smc_read [--features bench-hdf5-c] -- [FILE]`
//! (default: the committed DNA-Rendering fixture, which is tiny; pass a real take for
//! meaningful figures).

use std::path::{Path, PathBuf};
use std::time::Instant;

use seqavatar_datasets::smc::SmcFile;

/// Best of `repeats` timings of `work`, after one warm-up run, in seconds.
fn best_seconds(repeats: usize, mut work: impl FnMut()) -> f64 {
    work();
    (0..repeats)
        .map(|_| {
            let start = Instant::now();
            work();
            start.elapsed().as_secs_f64()
        })
        .fold(f64::INFINITY, f64::min)
}

/// The image dataset paths of a main file.
fn image_paths(file: &SmcFile) -> Vec<String> {
    let mut paths = Vec::new();
    for group in ["Camera_5mp", "Camera_12mp"] {
        if !file.has_group(group).expect("readable file") {
            continue;
        }
        for camera in file.members(group).expect("camera list") {
            let color = format!("{group}/{camera}/color");
            if !file.has_group(&color).expect("readable file") {
                continue;
            }
            for frame in file.members(&color).expect("frame list") {
                paths.push(format!("{color}/{frame}"));
            }
        }
    }
    paths
}

fn read_pure(path: &Path, datasets: &[String]) -> Vec<Vec<u8>> {
    let file = SmcFile::open(path).expect("open");
    datasets
        .iter()
        .map(|d| file.read_bytes(d).expect("read"))
        .collect()
}

#[cfg(feature = "bench-hdf5-c")]
fn read_c(path: &Path, datasets: &[String]) -> Vec<Vec<u8>> {
    let file = hdf5_metno::File::open(path).expect("open");
    datasets
        .iter()
        .map(|d| {
            file.dataset(d)
                .and_then(|d| d.read_raw::<u8>())
                .expect("read")
        })
        .collect()
}

fn main() {
    let path = std::env::args()
        .skip(1)
        .find(|a| !a.starts_with('-'))
        .map(PathBuf::from)
        .unwrap_or_else(|| {
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("../../tests/fixtures/data/dna/dna_rendering_part1_main/0007_04.smc")
        });
    let file = SmcFile::open(&path).expect("open");
    let datasets = image_paths(&file);
    drop(file);
    let reference = read_pure(&path, &datasets);
    let bytes: usize = reference.iter().map(Vec::len).sum();
    let mb = bytes as f64 / 1e6;
    println!(
        "{}: {} image datasets, {mb:.1} MB (best of 5, file in the page cache)",
        path.display(),
        datasets.len()
    );
    let pure = best_seconds(5, || {
        std::hint::black_box(read_pure(&path, &datasets));
    });
    println!(
        "pure Rust (hdf5-reader): {:.1} ms, {:.0} MB/s",
        pure * 1e3,
        mb / pure
    );
    #[cfg(feature = "bench-hdf5-c")]
    {
        assert!(
            read_c(&path, &datasets) == reference,
            "the two readers disagree"
        );
        let c = best_seconds(5, || {
            std::hint::black_box(read_c(&path, &datasets));
        });
        println!(
            "C libhdf5 (hdf5-metno):  {:.1} ms, {:.0} MB/s",
            c * 1e3,
            mb / c
        );
    }
    #[cfg(not(feature = "bench-hdf5-c"))]
    println!("C libhdf5 row: rebuild with `--features bench-hdf5-c` (needs libhdf5-dev)");
}
