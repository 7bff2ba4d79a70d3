//! Crafted small files against every reader (npz, npy, pickle, images): decompression
//! bombs, overlapping zip members, `|S1` arrays, PNG/JPEG headers claiming huge pictures,
//! truncated images. Each must be refused with an error (or read correctly), and a counting
//! global allocator (this binary's own) measures the peak each reader allocates: no input
//! file under 1 MB may make a reader allocate more than the documented limit
//! (`formats::PEAK_LIMIT_FACTOR` times the per-file limit for `.npy`/`.npz`, and times
//! `formats::decode_budget(file size)` for pickles; `images::MAX_BYTES_PER_PIXEL` per
//! checked pixel for images). Arrays are judged by the size they declare, never by how well
//! they compress.

use std::alloc::{GlobalAlloc, Layout, System};
use std::io::Write;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};

use seqavatar_formats::{self as formats, images, npy, npz, pickle};

/// Counts the bytes currently allocated and the peak since the last reset.
struct Counting;

static CURRENT: AtomicUsize = AtomicUsize::new(0);
static PEAK: AtomicUsize = AtomicUsize::new(0);

fn record_growth(bytes: usize) {
    let now = CURRENT.fetch_add(bytes, Ordering::SeqCst) + bytes;
    PEAK.fetch_max(now, Ordering::SeqCst);
}

// SAFETY: every method forwards to `System` with the caller's arguments; the counters are
// bookkeeping only.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded unchanged.
        let p = unsafe { System.alloc(layout) };
        if !p.is_null() {
            record_growth(layout.size());
        }
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // SAFETY: forwarded unchanged.
        let p = unsafe { System.alloc_zeroed(layout) };
        if !p.is_null() {
            record_growth(layout.size());
        }
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: forwarded unchanged.
        unsafe { System.dealloc(ptr, layout) };
        CURRENT.fetch_sub(layout.size(), Ordering::SeqCst);
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: forwarded unchanged.
        let p = unsafe { System.realloc(ptr, layout, new_size) };
        if !p.is_null() {
            // Counted as a new block next to the old one: a moving realloc briefly holds
            // both.
            record_growth(new_size);
            CURRENT.fetch_sub(layout.size(), Ordering::SeqCst);
        }
        p
    }
}

#[global_allocator]
static ALLOCATOR: Counting = Counting;

/// One measurement at a time: the tests of this binary run on several threads.
static MEASURING: Mutex<()> = Mutex::new(());

/// Runs `read` and returns its result with the peak bytes it allocated beyond what was
/// allocated before (printed with the caller's line, for `--nocapture`).
#[track_caller]
fn peak_of<T>(read: impl FnOnce() -> T) -> (T, usize) {
    let caller = std::panic::Location::caller();
    let base = CURRENT.load(Ordering::SeqCst);
    PEAK.store(base, Ordering::SeqCst);
    let out = read();
    let peak = PEAK.load(Ordering::SeqCst).saturating_sub(base);
    eprintln!("bombs.rs:{}: peak {peak} bytes", caller.line());
    (out, peak)
}

/// The documented peak limit of the pickle reader for a file.
fn format_limit(file: &[u8]) -> usize {
    formats::PEAK_LIMIT_FACTOR * formats::decode_budget(file.len())
}

/// The documented peak limit of the `.npy` and `.npz` readers within `limits`.
fn array_limit(limits: &formats::Limits) -> usize {
    formats::PEAK_LIMIT_FACTOR * limits.max_file_bytes
}

const MB: usize = 1_000_000;

fn npy_bytes(descr: &str, shape: &[usize], data: &[u8]) -> Vec<u8> {
    let shape: Vec<String> = shape.iter().map(|d| format!("{d},")).collect();
    let header = format!(
        "{{'descr': '{descr}', 'fortran_order': False, 'shape': ({}), }}\n",
        shape.join(" ")
    );
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((header.len() as u16).to_le_bytes());
    out.extend(header.as_bytes());
    out.extend(data);
    out
}

fn deflate(data: &[u8]) -> Vec<u8> {
    let mut encoder =
        flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::default());
    encoder.write_all(data).unwrap();
    encoder.finish().unwrap()
}

/// A raw deflate stream of `mebibytes` MiB of zeros, made without inflating them: one
/// sync-flushed compressed MiB repeated (its matches reach back only into zeros), then a
/// final empty block. About 1 KB per MiB, near deflate's 1032:1 limit.
fn zeros_deflated(mebibytes: usize) -> Vec<u8> {
    let mut compress = flate2::Compress::new(flate2::Compression::best(), false);
    let mut block = Vec::with_capacity(1 << 16);
    compress
        .compress_vec(&vec![0u8; 1 << 20], &mut block, flate2::FlushCompress::Sync)
        .unwrap();
    assert!(
        compress.total_in() == 1 << 20,
        "one call compresses the MiB"
    );
    let mut out = Vec::with_capacity(block.len() * mebibytes + 2);
    for _ in 0..mebibytes {
        out.extend_from_slice(&block);
    }
    // A final fixed-Huffman block holding only its end code.
    out.extend_from_slice(&[0x03, 0x00]);
    out
}

/// One zip member: its name, its stored bytes, the method (0 stored, 8 deflate), the CRC
/// and uncompressed size the directory claims.
struct Member {
    name: String,
    data: Vec<u8>,
    method: u16,
    crc: u32,
    size: u32,
}

impl Member {
    fn stored(name: &str, data: Vec<u8>) -> Self {
        Self {
            name: name.to_owned(),
            crc: crc32fast::hash(&data),
            size: data.len() as u32,
            data,
            method: 0,
        }
    }

    fn deflated(name: &str, plain: &[u8]) -> Self {
        Self {
            name: name.to_owned(),
            crc: crc32fast::hash(plain),
            size: plain.len() as u32,
            data: deflate(plain),
            method: 8,
        }
    }
}

/// A zip archive of `members`; `directory` lists, per central record, which member's
/// local header it points at (`None`: each member once, in order).
fn zip(members: &[Member], directory: Option<&[usize]>) -> Vec<u8> {
    let mut out = Vec::new();
    let mut offsets = Vec::new();
    for m in members {
        offsets.push(out.len() as u32);
        out.extend(0x0403_4b50_u32.to_le_bytes());
        out.extend([20, 0, 0, 0]); // version, flags
        out.extend(m.method.to_le_bytes());
        out.extend([0; 4]); // time, date
        out.extend(m.crc.to_le_bytes());
        out.extend((m.data.len() as u32).to_le_bytes());
        out.extend(m.size.to_le_bytes());
        out.extend((m.name.len() as u16).to_le_bytes());
        out.extend(0u16.to_le_bytes());
        out.extend(m.name.as_bytes());
        out.extend(&m.data);
    }
    let order: Vec<usize> = directory.map_or_else(|| (0..members.len()).collect(), <[_]>::to_vec);
    let cd_start = out.len() as u32;
    for &i in &order {
        let m = &members[i];
        out.extend(0x0201_4b50_u32.to_le_bytes());
        out.extend([20, 0, 20, 0, 0, 0]); // made by, needed, flags
        out.extend(m.method.to_le_bytes());
        out.extend([0; 4]);
        out.extend(m.crc.to_le_bytes());
        out.extend((m.data.len() as u32).to_le_bytes());
        out.extend(m.size.to_le_bytes());
        out.extend((m.name.len() as u16).to_le_bytes());
        out.extend([0; 12]); // extra, comment, disk, internal and external attributes
        out.extend(offsets[i].to_le_bytes());
        out.extend(m.name.as_bytes());
    }
    let cd_size = out.len() as u32 - cd_start;
    out.extend(0x0605_4b50_u32.to_le_bytes());
    out.extend([0; 4]);
    out.extend((order.len() as u16).to_le_bytes());
    out.extend((order.len() as u16).to_le_bytes());
    out.extend(cd_size.to_le_bytes());
    out.extend(cd_start.to_le_bytes());
    out.extend([0; 2]);
    out
}

/// The npy header of a `|u1` array of `len` zeros, to prefix a deflated run of zeros.
fn zeros_npy_header(len: usize) -> Vec<u8> {
    npy_bytes("|u1", &[len], &[])
}

#[test]
fn a_deflate_bomb_is_refused_before_inflating() {
    let _guard = MEASURING
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let limits = formats::Limits::default();
    // 800 MiB of zeros in under 1 MB: the npy header deflated with a sync flush, then the
    // deflated zeros. The header declares the 800 MiB: over the per-array limit.
    let len = 800usize << 20;
    assert!(len > limits.max_array_bytes);
    let header = zeros_npy_header(len);
    let stream = header_then_zeros(&header, 800);
    let mut crc = crc32fast::Hasher::new();
    crc.update(&header);
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..800 {
        crc.update(&zeros);
    }
    drop(zeros);
    let member = Member {
        name: "bomb.npy".into(),
        data: stream,
        method: 8,
        crc: crc.finalize(),
        size: (header.len() + len) as u32,
    };
    let archive = zip(&[member], None);
    assert!(archive.len() < MB, "{} bytes", archive.len());
    let (result, peak) = peak_of(|| npz::read_with(&archive, &limits));
    let error = result.unwrap_err();
    assert!(
        matches!(
            error,
            npz::NpzError::Member {
                source: npy::NpyError::ArrayTooLarge { .. },
                ..
            }
        ),
        "{error}"
    );
    assert!(
        error.to_string().contains(formats::MAX_ARRAY_BYTES_VAR),
        "{error}"
    );
    assert!(peak <= array_limit(&limits), "peak {peak}");
    // Refused before inflating: nothing near the claimed size was allocated.
    assert!(peak < 1 << 20, "peak {peak}");

    // A header declaring 10 MiB under a directory that claims 20 MiB: a mismatch, refused
    // before inflating the data.
    let small = zeros_npy_header(10 << 20);
    let lying = zip(
        &[Member {
            name: "liar.npy".into(),
            data: header_then_zeros(&small, 800),
            method: 8,
            crc: 0,
            size: (small.len() + (20 << 20)) as u32,
        }],
        None,
    );
    let (result, peak) = peak_of(|| npz::read_with(&lying, &limits));
    let error = result.unwrap_err();
    assert!(error.to_string().contains("zip directory says"), "{error}");
    assert!(peak < 1 << 20, "peak {peak}");

    // A header and directory that agree on 10 MiB, over a stream of 800 MiB: inflating
    // stops one byte past the declared size.
    let lying = zip(
        &[Member {
            name: "liar.npy".into(),
            data: header_then_zeros(&small, 800),
            method: 8,
            crc: 0,
            size: (small.len() + (10 << 20)) as u32,
        }],
        None,
    );
    let (result, peak) = peak_of(|| npz::read_with(&lying, &limits));
    let error = result.unwrap_err();
    assert!(
        error.to_string().contains("inflated to more than"),
        "{error}"
    );
    assert!(peak <= array_limit(&limits), "peak {peak}");
    assert!(peak < 30 << 20, "peak {peak}");

    // Honestly declared and within a raised limit, the 800 MiB are not refused for their
    // compression ratio: the limits decide (here a per-file limit too small for them,
    // refused from the header, so the test stays small).
    let raised = formats::Limits {
        max_array_bytes: 1 << 30,
        max_file_bytes: 1 << 20,
    };
    let (result, peak) = peak_of(|| npz::read_with(&archive, &raised));
    let error = result.unwrap_err();
    assert!(
        matches!(
            error,
            npz::NpzError::Member {
                source: npy::NpyError::ArrayTooLarge { limit, .. },
                ..
            } if limit == 1 << 20
        ),
        "{error}"
    );
    assert!(peak < 1 << 20, "peak {peak}");
}

/// A raw deflate stream of `header` (sync-flushed) then `mebibytes` MiB of zeros.
fn header_then_zeros(header: &[u8], mebibytes: usize) -> Vec<u8> {
    let mut compress = flate2::Compress::new(flate2::Compression::best(), false);
    let mut stream = Vec::with_capacity(1 << 20);
    compress
        .compress_vec(header, &mut stream, flate2::FlushCompress::Sync)
        .unwrap();
    stream.extend(zeros_deflated(mebibytes));
    stream
}

#[test]
fn overlapping_members_are_refused() {
    let _guard = MEASURING
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    // One 8 MB member listed 2000 times: 16 GB if each listing were inflated.
    let plain = npy_bytes("|u1", &[8 * MB], &vec![7u8; 8 * MB]);
    let archive = zip(
        &[Member::deflated("a.npy", &plain)],
        Some(&vec![0usize; 2000]),
    );
    assert!(archive.len() < MB, "{} bytes", archive.len());
    let (result, peak) = peak_of(|| npz::read(&archive));
    let error = result.unwrap_err().to_string();
    assert!(error.contains("overlap"), "{error}");
    assert!(peak <= format_limit(&archive), "peak {peak}");
    // The same member once reads fine.
    let single = zip(&[Member::deflated("a.npy", &plain)], None);
    let members = npz::read(&single).unwrap();
    assert_eq!(members.len(), 1);
    assert_eq!(members[0].0, "a");
}

#[test]
fn string_arrays_are_charged_per_element() {
    let _guard = MEASURING
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    // 2 M one-byte strings inflate from a few KB to 2 MB (within a 24 MiB limit per
    // array) but would decode to 2 M `Vec<u8>`s (about 50 MB): refused before inflating.
    let limits = formats::Limits {
        max_array_bytes: 24 << 20,
        max_file_bytes: 24 << 20,
    };
    let count = 2 * MB;
    let plain = npy_bytes("|S1", &[count], &vec![b'a'; count]);
    let archive = zip(&[Member::deflated("s.npy", &plain)], None);
    assert!(archive.len() < 64_000);
    let (result, peak) = peak_of(|| npz::read_with(&archive, &limits));
    let error = result.unwrap_err();
    assert!(
        matches!(
            &error,
            npz::NpzError::Member {
                source: npy::NpyError::ArrayTooLarge { .. },
                ..
            }
        ),
        "{error}"
    );
    assert!(peak <= array_limit(&limits), "peak {peak}");
    assert!(peak < 1 << 20, "peak {peak}");

    // Stored, the file must hold every byte: a 900 KB `|S1` npy decodes within the limit.
    let count = 900_000;
    let file = npy_bytes("|S1", &[count], &vec![b'b'; count]);
    let (result, peak) = peak_of(|| npy::read_with(&file, &limits));
    let value = result.unwrap();
    let formats::Value::Array(array) = value else {
        panic!("not an array")
    };
    assert_eq!(array.len(), count);
    assert!(peak <= array_limit(&limits), "peak {peak}");
    drop(array);
    let (result, peak) = peak_of(|| {
        npz::read_with(
            &zip(&[Member::stored("s.npy", file.clone())], None),
            &limits,
        )
    });
    assert_eq!(result.unwrap().len(), 1);
    assert!(peak <= array_limit(&limits) + 2 * file.len(), "peak {peak}");
}

#[test]
fn pickles_stay_within_the_limit() {
    let _guard = MEASURING
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    // Opcodes that each create an object: the machine's scratch grows with the input.
    for opcode in [b']', b'}', b')', b'N'] {
        let mut bytes = vec![0x80, 4];
        bytes.extend(std::iter::repeat_n(opcode, 999_000));
        let (result, peak) = peak_of(|| pickle::load(&bytes));
        assert!(result.is_err(), "no STOP");
        assert!(
            peak <= format_limit(&bytes),
            "opcode {}: peak {peak} > {}",
            opcode as char,
            format_limit(&bytes)
        );
    }
    // A list of 999 000 Nones: its values would pass the budget, so it is refused, within
    // the limit; a tenth as many decode.
    for (count, fits) in [(999_000, false), (100_000, true)] {
        let mut bytes = vec![0x80, 4, b'('];
        bytes.extend(std::iter::repeat_n(b'N', count));
        bytes.extend([b'l', b'.']);
        let (result, peak) =
            peak_of(|| pickle::load(&bytes).map(|v| v.as_sequence().map(<[_]>::len)));
        if fits {
            assert_eq!(result.unwrap(), Some(count));
        } else {
            assert!(matches!(result, Err(pickle::PickleError::TooLarge { .. })));
        }
        assert!(peak <= format_limit(&bytes), "{count}: peak {peak}");
    }
}

fn png_bytes(image: &image::DynamicImage) -> Vec<u8> {
    let mut out = Vec::new();
    image
        .write_to(&mut std::io::Cursor::new(&mut out), image::ImageFormat::Png)
        .unwrap();
    out
}

#[test]
fn image_bombs_are_refused_before_decoding() {
    let _guard = MEASURING
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    // A real 4096 x 4096 grey PNG of zeros: a few KB.
    let big = png_bytes(&image::DynamicImage::ImageLuma8(image::GrayImage::new(
        4096, 4096,
    )));
    assert!(big.len() < MB);
    // As a mask of a 64 x 48 camera: refused from the header.
    let (result, peak) = peak_of(|| images::decode_mask(&big, Some((64, 48)), true).map(|_| ()));
    assert!(
        matches!(result, Err(images::ImageError::WrongSize { .. })),
        "{result:?}"
    );
    assert!(peak < 1 << 20, "peak {peak}");
    // Without an expected size it decodes, within the documented bytes per pixel.
    let (result, peak) = peak_of(|| images::decode_rgb(&big, None).map(|rgb| rgb.dimensions()));
    assert_eq!(result.unwrap(), (4096, 4096));
    let limit = 4096 * 4096 * images::MAX_BYTES_PER_PIXEL as usize;
    assert!(peak <= limit, "peak {peak} > {limit}");

    // A JPEG whose frame header claims 65535 x 65535: over the pixel limit, from the header.
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new(&mut jpeg)
        .encode_image(&image::RgbImage::new(16, 16))
        .unwrap();
    let sof = jpeg
        .windows(2)
        .position(|w| w == [0xff, 0xc0])
        .expect("a baseline frame header");
    jpeg[sof + 5..sof + 9].copy_from_slice(&[0xff, 0xff, 0xff, 0xff]);
    let (result, peak) = peak_of(|| images::decode_rgb(&jpeg, None).map(|_| ()));
    assert!(result.is_err());
    assert!(peak < 1 << 20, "peak {peak}");
    // Claiming 8000 x 8000 (within the pixel limit) with 16 x 16 of data. The scan ends
    // with its end-of-image marker (the decoder would pad the rest), but it is far too short
    // for the declared picture: refused before decoding.
    jpeg[sof + 5..sof + 9].copy_from_slice(&[0x1f, 0x40, 0x1f, 0x40]);
    let (result, peak) = peak_of(|| images::decode_rgb(&jpeg, None).map(|rgb| rgb.dimensions()));
    let error = result.unwrap_err();
    assert!(error.to_string().contains("runs short"), "{error}");
    assert!(peak < 1 << 20, "peak {peak}");
    let limit = 8000 * 8000 * images::MAX_BYTES_PER_PIXEL as usize;
    assert!(peak <= limit, "peak {peak} > {limit}");
    // As a camera's 64 x 48 image: refused from the header.
    let (result, peak) = peak_of(|| images::decode_rgb(&jpeg, Some((64, 48))).map(|_| ()));
    assert!(matches!(result, Err(images::ImageError::WrongSize { .. })));
    assert!(peak < 1 << 20, "peak {peak}");
}
