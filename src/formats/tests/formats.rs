//! The pickle, `.npy` and `.npz` readers against files written by Python's own `pickle` and
//! `numpy` (protocols 0 to 5, every supported dtype, both byte orders, Fortran order,
//! zero-dimensional and empty arrays, object arrays, `np.savez` and `np.savez_compressed`),
//! checked value by value; and a deterministic fuzz pass over mutations of those files.

#[path = "../../datasets/tests/support/mod.rs"]
mod support;

use std::path::Path;

use seqavatar_formats::{ArrayData, Value, npy, npz, pickle};
use serde_json::Value as Json;

fn float_of(json: &Json) -> f64 {
    match json {
        Json::String(s) if s == "nan" => f64::NAN,
        Json::String(s) if s == "inf" => f64::INFINITY,
        Json::String(s) if s == "-inf" => f64::NEG_INFINITY,
        Json::Number(n) => n.as_f64().expect("number"),
        other => panic!("not a float: {other}"),
    }
}

fn same_float(a: f64, b: f64) -> bool {
    (a.is_nan() && b.is_nan()) || a.to_bits() == b.to_bits() || a == b
}

fn check_items(actual: &[Value], expected: &Json, at: &str) {
    let expected = expected.as_array().expect("list");
    assert_eq!(actual.len(), expected.len(), "{at}: length");
    for (i, (a, e)) in actual.iter().zip(expected).enumerate() {
        check(a, e, &format!("{at}[{i}]"));
    }
}

/// Compares a decoded value with the tagged JSON the fixture writer produced.
fn check(actual: &Value, expected: &Json, at: &str) {
    let tag = expected["t"].as_str().expect("tag");
    let v = &expected["v"];
    match (tag, actual) {
        ("none", Value::None) => {}
        ("bool", Value::Bool(b)) => assert_eq!(Some(*b), v.as_bool(), "{at}"),
        ("int", Value::Int(i)) => assert_eq!(Some(*i), v.as_i64(), "{at}"),
        ("float", Value::Float(f)) => assert!(same_float(*f, float_of(v)), "{at}: {f} vs {v}"),
        ("str", Value::Str(s)) => assert_eq!(Some(s.as_str()), v.as_str(), "{at}"),
        ("bytes", Value::Bytes(b)) => {
            let e: Vec<u8> = v
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as u8)
                .collect();
            assert_eq!(b, &e, "{at}");
        }
        ("list", Value::List(items))
        | ("tuple", Value::Tuple(items))
        | ("set", Value::Set(items)) => check_items(items, v, at),
        ("dict", Value::Dict(pairs)) => {
            let expected = v.as_array().expect("pairs");
            assert_eq!(pairs.len(), expected.len(), "{at}: dict length");
            for ((k, val), e) in pairs.iter().zip(expected) {
                check(k, &e[0], &format!("{at} key"));
                check(val, &e[1], &format!("{at}[{k}]"));
            }
        }
        ("array", Value::Array(array)) => {
            let shape: Vec<usize> = expected["shape"]
                .as_array()
                .unwrap()
                .iter()
                .map(|d| d.as_u64().unwrap() as usize)
                .collect();
            assert_eq!(array.shape, shape, "{at}: shape");
            assert_eq!(
                array.dtype,
                expected["dtype"].as_str().unwrap(),
                "{at}: dtype"
            );
            let items = v.as_array().unwrap();
            assert_eq!(array.len(), items.len(), "{at}: element count");
            match &array.data {
                ArrayData::Object(values) => check_items(values, v, at),
                ArrayData::Str(strings) => {
                    for (s, e) in strings.iter().zip(items) {
                        assert_eq!(Some(s.as_str()), e.as_str(), "{at}");
                    }
                }
                ArrayData::Bytes(bytes) => {
                    for (b, e) in bytes.iter().zip(items) {
                        let e: Vec<u8> = e
                            .as_array()
                            .unwrap()
                            .iter()
                            .map(|x| x.as_u64().unwrap() as u8)
                            .collect();
                        assert_eq!(b, &e, "{at}");
                    }
                }
                ArrayData::Bool(bools) => {
                    for (b, e) in bools.iter().zip(items) {
                        assert_eq!(Some(*b), e.as_bool(), "{at}");
                    }
                }
                ArrayData::I64(_) | ArrayData::U8(_) => {
                    let ints: Vec<i64> = match &array.data {
                        ArrayData::U8(bytes) => bytes.iter().map(|&b| i64::from(b)).collect(),
                        ArrayData::I64(ints) => ints.clone(),
                        _ => unreachable!(),
                    };
                    for (i, e) in ints.iter().zip(items) {
                        assert_eq!(Some(*i), e.as_i64(), "{at}");
                    }
                }
                ArrayData::U64(ints) => {
                    for (i, e) in ints.iter().zip(items) {
                        assert_eq!(Some(*i), e.as_u64(), "{at}");
                    }
                }
                ArrayData::F32(_) | ArrayData::F64(_) => {
                    let floats = array.data.to_f64().unwrap();
                    for (i, (f, e)) in floats.iter().zip(items).enumerate() {
                        assert!(same_float(*f, float_of(e)), "{at}[{i}]: {f} vs {e}");
                    }
                }
            }
        }
        (tag, other) => panic!("{at}: expected a {tag}, decoded {other:?}"),
    }
}

fn decode(path: &Path) -> Value {
    let bytes = std::fs::read(path).unwrap();
    let name = path.file_name().unwrap().to_str().unwrap();
    if name.ends_with(".pkl") {
        pickle::load(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"))
    } else if name.ends_with(".npy") {
        npy::read(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"))
    } else {
        let members = npz::read(&bytes).unwrap_or_else(|e| panic!("{name}: {e}"));
        Value::Dict(
            members
                .into_iter()
                .map(|(k, v)| (Value::Str(k), v))
                .collect(),
        )
    }
}

/// The committed cases written by `tests/fixtures/write_format_cases.py`.
fn write_cases() -> tempfile::TempDir {
    support::dataset_fixture("formats")
}

#[test]
fn python_written_files_decode_value_by_value() {
    let dir = write_cases();
    let expected = support::read_json(&dir.path().join("expected.json"));
    let cases = expected.as_object().unwrap();
    assert!(
        cases.len() > 50,
        "the fixture writer wrote only {} cases",
        cases.len()
    );
    for (file, want) in cases {
        let value = decode(&dir.path().join(file));
        check(&value, want, file);
    }
    // Spot checks that do not go through the generic comparison.
    let annots = decode(&dir.path().join("npy_dict.npy"));
    let cams = annots.unwrap_object_scalar().get("cams").unwrap();
    let t = cams.get("T").unwrap().as_sequence().unwrap();
    assert_eq!(t[0].to_f64_array(), Some((vec![3, 1], vec![1.0, 2.0, 3.0])));
    // The numpy 1 spelling (numpy.core.multiarray) decodes like the numpy 2 one.
    let renamed = std::fs::read(dir.path().join("pickle_numpy1_names.pkl")).unwrap();
    assert!(renamed.windows(11).any(|w| w == b"numpy.core."));
}

/// A small deterministic generator (xorshift64*), so the fuzz pass is reproducible.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_f491_4f6c_dd1d)
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// One random mutation: bit flip, byte set to an interesting value, truncation, insertion,
/// deletion, duplication of a slice, or a little-endian length field set to a huge value.
fn mutate(rng: &mut Rng, input: &mut Vec<u8>) {
    if input.is_empty() {
        input.push(rng.next() as u8);
        return;
    }
    let at = rng.below(input.len());
    match rng.below(8) {
        0 => input[at] ^= 1 << rng.below(8),
        1 => input[at] = [0, 1, 0x7f, 0x80, 0xff, b'(', b'.', b'R'][rng.below(8)],
        2 => input.truncate(at),
        3 => input.insert(at, rng.next() as u8),
        4 => {
            input.remove(at);
        }
        5 => {
            let len = rng.below(64).min(input.len() - at);
            let slice = input[at..at + len].to_vec();
            let to = rng.below(input.len());
            input.splice(to..to, slice);
        }
        6 => {
            let end = (at + 4).min(input.len());
            for b in &mut input[at..end] {
                *b = 0xff;
            }
        }
        _ => {
            let end = (at + 8).min(input.len());
            for b in &mut input[at..end] {
                *b = rng.next() as u8;
            }
        }
    }
}

/// Feeds thousands of random and mutated byte strings to every reader: none may panic, and
/// none may allocate beyond what its input justifies (the process would abort).
#[test]
fn readers_survive_mutated_and_random_input() {
    let dir = write_cases();
    let mut corpus: Vec<(String, Vec<u8>)> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e != "json"))
        .map(|p| {
            (
                p.file_name().unwrap().to_string_lossy().into_owned(),
                std::fs::read(&p).unwrap(),
            )
        })
        .collect();
    corpus.sort();
    let iterations: usize = std::env::var("SEQAVATAR_FUZZ_ITERATIONS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(4000);
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let mut decoded_ok = 0usize;
    for i in 0..iterations {
        let mut input = if i % 10 == 0 {
            (0..rng.below(200)).map(|_| rng.next() as u8).collect()
        } else {
            corpus[rng.below(corpus.len())].1.clone()
        };
        for _ in 0..1 + rng.below(4) {
            mutate(&mut rng, &mut input);
        }
        decoded_ok += usize::from(pickle::load(&input).is_ok());
        decoded_ok += usize::from(npy::read(&input).is_ok());
        decoded_ok += usize::from(npz::read(&input).is_ok());
        // The readers also see valid prefixes of each other's formats.
        if let Some(pos) = input.iter().position(|&b| b == 0x80) {
            let _ = pickle::load(&input[pos..]);
        }
    }
    // Some mutations are harmless: the pass must exercise the success paths too.
    assert!(
        decoded_ok > iterations / 50,
        "only {decoded_ok} inputs decoded"
    );
}

#[test]
fn handmade_hostile_inputs_are_rejected_quickly() {
    // A memoised 100k-item list passed to set() 20k times would need 2e9 copies.
    let mut bytes = vec![0x80, 4, b'c'];
    bytes.extend(b"builtins\nset\n");
    bytes.extend([0x94, b'(']); // memo 0 = set
    bytes.extend(std::iter::repeat_n(b'N', 100_000));
    bytes.extend([b'l', 0x85, 0x94]); // memo 1 = (list,)
    for _ in 0..20_000 {
        bytes.extend([b'h', 0, b'h', 1, b'R', b'0']);
    }
    bytes.extend([b'N', b'.']);
    let start = std::time::Instant::now();
    assert!(matches!(
        pickle::load(&bytes),
        Err(pickle::PickleError::TooLarge { .. })
    ));
    assert!(start.elapsed().as_secs() < 10);
}
