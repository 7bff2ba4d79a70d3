//! Gaussians as standard 3D Gaussian Splatting PLY files, the layout the INRIA reference
//! writer (`GaussianModel.save_ply` of graphdeco-inria/gaussian-splatting) produces and the
//! common splat viewers and editors read:
//!
//! - `format binary_little_endian 1.0`, one element `vertex` with one `float` (f32) property
//!   per value, in this order: `x y z`, `nx ny nz` (zeros), `f_dc_0..2` (the SH DC coefficient
//!   of red, green, blue), `f_rest_0..44` (the other 15 coefficients of degree 3,
//!   channel-major: `f_rest_{c * 15 + k - 1}` is coefficient `k` of channel `c`),
//!   `opacity` (a logit: the opacity is its sigmoid), `scale_0..2` (natural logarithms of the
//!   standard deviations along the Gaussian's axes), `rot_0..3` (the rotation as a quaternion,
//!   `w` first; readers normalise it).
//!
//! [`write_ply`] always writes the degree-3 layout (coefficients beyond the cloud's degree are
//! zero, so a degree-3 renderer draws the same image); [`read_ply`] accepts any
//! degree 0..=3 (`f_rest` count `3 ((d + 1)^2 - 1)`), properties in any order, extra scalar
//! properties (skipped), comments, and nothing else: it is strict and never panics.
//!
//! This is the file format only, a plain Gaussian cloud ([`SplatCloud`]); the avatar stage
//! (`seqavatar_avatar::ply`) turns its trained and posed Gaussians into clouds. It lives here,
//! with the other readers of untrusted files, so that `fuzz/` fuzzes it (target `ply`).

use std::collections::HashSet;

/// SH coefficients per channel written to a file (degree 3).
const FILE_COEFFS: usize = 16;

/// Gaussians in the terms of a 3DGS PLY file (f32, the file's precision).
#[derive(Clone, Debug, PartialEq)]
pub struct SplatCloud {
    /// `N x 3` centres.
    pub xyz: Vec<f32>,
    /// `N x 3 x K` SH coefficients, channel-major per Gaussian (`K = (sh_degree + 1)^2`):
    /// `sh[(i * 3 + c) * K + k]`, the file's `f_dc_c` at `k = 0`, `f_rest_{c (K - 1) + k - 1}`
    /// after it.
    pub sh: Vec<f32>,
    /// SH degree of `sh` (0..=3).
    pub sh_degree: u32,
    /// `N` opacity logits.
    pub opacity: Vec<f32>,
    /// `N x 3` log standard deviations.
    pub log_scale: Vec<f32>,
    /// `N x 4` quaternions, `w` first (not necessarily unit).
    pub rotation: Vec<f32>,
}

/// Why a PLY file was rejected: what was wrong, and where.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum PlyError {
    #[error("PLY header: {0}")]
    Header(String),
    #[error("PLY header: missing property `{0}`")]
    MissingProperty(String),
    #[error("PLY data: {0}")]
    Data(String),
    #[error("Gaussian {index}: {field} is not finite")]
    NotFinite { index: usize, field: &'static str },
    #[error("{0}")]
    Input(String),
}

/// SH coefficients per channel of degree `degree`: `(degree + 1)^2`.
pub fn coefficient_count(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

impl SplatCloud {
    pub fn len(&self) -> usize {
        self.opacity.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity.is_empty()
    }
}

/// Fails unless `degree` is an SH degree a file holds (0..=3).
pub fn check_degree(degree: u32) -> Result<(), PlyError> {
    if degree > 3 {
        return Err(PlyError::Input(format!("SH degree {degree} is not 0..=3")));
    }
    Ok(())
}

/// Property names of the degree-3 file layout, in order.
fn property_names() -> Vec<String> {
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    names.extend((0..3).map(|c| format!("f_dc_{c}")));
    names.extend((0..3 * (FILE_COEFFS - 1)).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names
}

/// The cloud as a binary little-endian 3DGS PLY file (degree-3 layout).
pub fn write_ply(cloud: &SplatCloud) -> Result<Vec<u8>, PlyError> {
    let n = cloud.len();
    check_degree(cloud.sh_degree)?;
    let k = coefficient_count(cloud.sh_degree);
    if cloud.xyz.len() != 3 * n
        || cloud.sh.len() != 3 * k * n
        || cloud.log_scale.len() != 3 * n
        || cloud.rotation.len() != 4 * n
    {
        return Err(PlyError::Input(format!(
            "splat cloud: {n} opacities but {} centre, {} SH, {} scale and {} rotation values",
            cloud.xyz.len(),
            cloud.sh.len(),
            cloud.log_scale.len(),
            cloud.rotation.len()
        )));
    }
    let names = property_names();
    let mut out = format!("ply\nformat binary_little_endian 1.0\nelement vertex {n}\n");
    for name in &names {
        out.push_str(&format!("property float {name}\n"));
    }
    out.push_str("end_header\n");
    let mut bytes = out.into_bytes();
    bytes.reserve(n * names.len() * 4);
    let mut put = |v: f32| bytes.extend_from_slice(&v.to_le_bytes());
    for i in 0..n {
        cloud.xyz[3 * i..3 * i + 3].iter().for_each(|&v| put(v));
        (0..3).for_each(|_| put(0.0));
        (0..3).for_each(|c| put(cloud.sh[(i * 3 + c) * k]));
        for c in 0..3 {
            for coeff in 1..FILE_COEFFS {
                put(if coeff < k {
                    cloud.sh[(i * 3 + c) * k + coeff]
                } else {
                    0.0
                });
            }
        }
        put(cloud.opacity[i]);
        cloud.log_scale[3 * i..3 * i + 3]
            .iter()
            .for_each(|&v| put(v));
        cloud.rotation[4 * i..4 * i + 4]
            .iter()
            .for_each(|&v| put(v));
    }
    Ok(bytes)
}

/// Scalar property types of the PLY format and their sizes in bytes.
fn scalar_size(name: &str) -> Option<usize> {
    Some(match name {
        "char" | "uchar" | "int8" | "uint8" => 1,
        "short" | "ushort" | "int16" | "uint16" => 2,
        "int" | "uint" | "int32" | "uint32" | "float" | "float32" => 4,
        "double" | "float64" => 8,
        _ => return None,
    })
}

/// The most Gaussians a file may declare (10^9; the data length is checked against the
/// file before anything is allocated).
const MAX_VERTICES: usize = 1_000_000_000;

/// Reads a 3DGS PLY file (see the module documentation for what is accepted). Every
/// problem is an error naming the header line or the Gaussian and property; nothing panics.
pub fn read_ply(bytes: &[u8]) -> Result<SplatCloud, PlyError> {
    const END: &[u8] = b"end_header\n";
    let end = bytes
        .windows(END.len())
        .position(|w| w == END)
        .filter(|&at| at == 0 || bytes[at - 1] == b'\n')
        .ok_or_else(|| PlyError::Header("no `end_header` line".into()))?;
    let header = std::str::from_utf8(&bytes[..end])
        .map_err(|_| PlyError::Header("the header is not UTF-8".into()))?;
    let data = &bytes[end + END.len()..];
    let mut lines = header.lines().enumerate();
    match lines.next() {
        Some((_, "ply")) => {}
        _ => {
            return Err(PlyError::Header(
                "the file does not start with `ply`".into(),
            ));
        }
    }
    let mut format_seen = false;
    let mut count: Option<usize> = None;
    // (name, offset in the record, size, is f32)
    let mut properties: Vec<(String, usize, usize, bool)> = Vec::new();
    let mut stride = 0usize;
    // Property names seen so far (a set: a fuzzed header may hold many thousands).
    let mut names: HashSet<&str> = HashSet::new();
    for (number, line) in lines {
        let line_no = number + 1;
        let words: Vec<&str> = line.split_whitespace().collect();
        match words.as_slice() {
            [] => {}
            ["comment", ..] | ["obj_info", ..] => {}
            ["format", "binary_little_endian", "1.0"] if !format_seen => format_seen = true,
            ["format", other, ..] => {
                return Err(PlyError::Header(format!(
                    "line {line_no}: format `{other}` (only one `binary_little_endian 1.0` is read)"
                )));
            }
            ["element", "vertex", n] if count.is_none() => {
                let n: usize = n.parse().map_err(|_| {
                    PlyError::Header(format!("line {line_no}: vertex count `{n}` is not a count"))
                })?;
                if n > MAX_VERTICES {
                    return Err(PlyError::Header(format!(
                        "line {line_no}: {n} vertices, more than {MAX_VERTICES}"
                    )));
                }
                count = Some(n);
            }
            ["element", name, ..] => {
                return Err(PlyError::Header(format!(
                    "line {line_no}: element `{name}` (only one `vertex` element is read)"
                )));
            }
            ["property", "list", ..] => {
                return Err(PlyError::Header(format!(
                    "line {line_no}: list properties are not part of a splat file"
                )));
            }
            ["property", kind, name] => {
                if count.is_none() {
                    return Err(PlyError::Header(format!(
                        "line {line_no}: property before `element vertex`"
                    )));
                }
                let size = scalar_size(kind).ok_or_else(|| {
                    PlyError::Header(format!("line {line_no}: unknown property type `{kind}`"))
                })?;
                if !names.insert(*name) {
                    return Err(PlyError::Header(format!(
                        "line {line_no}: property `{name}` appears twice"
                    )));
                }
                let is_f32 = matches!(*kind, "float" | "float32");
                properties.push((name.to_string(), stride, size, is_f32));
                stride += size;
            }
            _ => {
                return Err(PlyError::Header(format!(
                    "line {line_no}: unexpected `{line}`"
                )));
            }
        }
    }
    if !format_seen {
        return Err(PlyError::Header(
            "no `format binary_little_endian 1.0` line".into(),
        ));
    }
    let n = count.ok_or_else(|| PlyError::Header("no `element vertex` line".into()))?;
    let expected = n
        .checked_mul(stride)
        .ok_or_else(|| PlyError::Header(format!("{n} vertices of {stride} bytes overflow")))?;
    if data.len() != expected {
        return Err(PlyError::Data(format!(
            "{} bytes after the header, {n} vertices of {stride} bytes need {expected}",
            data.len()
        )));
    }
    let offset_of = |name: &str| -> Result<usize, PlyError> {
        let p = properties
            .iter()
            .find(|p| p.0 == name)
            .ok_or_else(|| PlyError::MissingProperty(name.to_string()))?;
        if !p.3 {
            return Err(PlyError::Header(format!(
                "property `{name}` must be `float` (f32)"
            )));
        }
        Ok(p.1)
    };
    let rest = properties
        .iter()
        .filter(|p| p.0.starts_with("f_rest_"))
        .count();
    let sh_degree = (0..=3u32)
        .find(|&d| 3 * (coefficient_count(d) - 1) == rest)
        .ok_or_else(|| {
            PlyError::Header(format!(
                "{rest} `f_rest_*` properties: expected 0, 9, 24 or 45 (SH degree 0..=3)"
            ))
        })?;
    let k = coefficient_count(sh_degree);
    let column = |names: &[String]| -> Result<Vec<usize>, PlyError> {
        names.iter().map(|name| offset_of(name)).collect()
    };
    let xyz_at = column(&["x", "y", "z"].map(String::from))?;
    let dc_at = column(&(0..3).map(|c| format!("f_dc_{c}")).collect::<Vec<_>>())?;
    let rest_at = column(&(0..rest).map(|i| format!("f_rest_{i}")).collect::<Vec<_>>())?;
    let opacity_at = offset_of("opacity")?;
    let scale_at = column(&(0..3).map(|i| format!("scale_{i}")).collect::<Vec<_>>())?;
    let rot_at = column(&(0..4).map(|i| format!("rot_{i}")).collect::<Vec<_>>())?;
    let value = |record: &[u8], at: usize| -> f32 {
        let mut b = [0u8; 4];
        b.copy_from_slice(&record[at..at + 4]);
        f32::from_le_bytes(b)
    };
    let mut cloud = SplatCloud {
        xyz: Vec::with_capacity(3 * n),
        sh: Vec::with_capacity(3 * k * n),
        sh_degree,
        opacity: Vec::with_capacity(n),
        log_scale: Vec::with_capacity(3 * n),
        rotation: Vec::with_capacity(4 * n),
    };
    if stride == 0 {
        return Ok(cloud);
    }
    for (i, record) in data.chunks_exact(stride).enumerate() {
        let read = |at: &[usize], field: &'static str| -> Result<Vec<f32>, PlyError> {
            at.iter()
                .map(|&o| {
                    let v = value(record, o);
                    if v.is_finite() {
                        Ok(v)
                    } else {
                        Err(PlyError::NotFinite { index: i, field })
                    }
                })
                .collect()
        };
        cloud.xyz.extend(read(&xyz_at, "x/y/z")?);
        let dc = read(&dc_at, "f_dc")?;
        let rest_values = read(&rest_at, "f_rest")?;
        for c in 0..3 {
            cloud.sh.push(dc[c]);
            cloud
                .sh
                .extend_from_slice(&rest_values[c * (k - 1)..(c + 1) * (k - 1)]);
        }
        cloud.opacity.extend(read(&[opacity_at], "opacity")?);
        cloud.log_scale.extend(read(&scale_at, "scale")?);
        let rotation = read(&rot_at, "rot")?;
        if rotation.iter().all(|&q| q == 0.0) {
            return Err(PlyError::Data(format!(
                "Gaussian {i}: rotation `rot_0..3` is zero"
            )));
        }
        cloud.rotation.extend(rotation);
    }
    Ok(cloud)
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_core::rng::SplitMix64 as Rng;

    fn random_cloud(rng: &mut Rng, n: usize, degree: u32) -> SplatCloud {
        let k = coefficient_count(degree);
        let mut uniform = |lo: f64, hi: f64, count: usize| -> Vec<f32> {
            (0..count).map(|_| rng.uniform(lo, hi) as f32).collect()
        };
        SplatCloud {
            xyz: uniform(-1.0, 1.0, 3 * n),
            sh: uniform(-0.5, 0.5, 3 * k * n),
            sh_degree: degree,
            opacity: uniform(-3.0, 3.0, n),
            log_scale: uniform(-5.0, -1.0, 3 * n),
            rotation: uniform(-1.0, 1.0, 4 * n),
        }
    }

    /// The header is the reference writer's: 62 float properties in its order.
    #[test]
    fn header_has_the_reference_layout() {
        let mut rng = Rng::new(1);
        let bytes = write_ply(&random_cloud(&mut rng, 2, 3)).unwrap();
        let text = String::from_utf8_lossy(&bytes);
        let header = &text[..text.find("end_header\n").unwrap()];
        let props: Vec<&str> = header
            .lines()
            .filter_map(|l| l.strip_prefix("property float "))
            .collect();
        assert_eq!(props.len(), 62);
        assert_eq!(
            &props[..9],
            &[
                "x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"
            ]
        );
        assert_eq!(props[9], "f_rest_0");
        assert_eq!(props[53], "f_rest_44");
        assert_eq!(
            &props[54..],
            &[
                "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"
            ]
        );
        assert!(header.starts_with("ply\nformat binary_little_endian 1.0\nelement vertex 2\n"));
        assert_eq!(
            bytes.len(),
            header.len() + "end_header\n".len() + 2 * 62 * 4
        );
    }

    /// Values land where the reference writer puts them: `f_rest` channel-major.
    #[test]
    fn values_are_channel_major_and_round_trip() {
        let mut rng = Rng::new(2);
        for degree in 0..=3 {
            let cloud = random_cloud(&mut rng, 5, degree);
            let bytes = write_ply(&cloud).unwrap();
            let back = read_ply(&bytes).unwrap();
            // Written as degree 3: the active coefficients, zeros after them.
            assert_eq!(back.sh_degree, 3);
            let k = coefficient_count(degree);
            for i in 0..5 {
                for c in 0..3 {
                    for coeff in 0..16 {
                        let want = if coeff < k {
                            cloud.sh[(i * 3 + c) * k + coeff]
                        } else {
                            0.0
                        };
                        assert_eq!(back.sh[(i * 3 + c) * 16 + coeff], want);
                    }
                }
            }
            assert_eq!(back.xyz, cloud.xyz);
            assert_eq!(back.opacity, cloud.opacity);
            assert_eq!(back.log_scale, cloud.log_scale);
            assert_eq!(back.rotation, cloud.rotation);
        }
        // Gaussian 1's `f_rest_16` is coefficient 2 of green (index 1 * 15 + 2 - 1).
        let cloud = random_cloud(&mut rng, 3, 3);
        let bytes = write_ply(&cloud).unwrap();
        let start = bytes.len() - 3 * 62 * 4;
        let record = &bytes[start + 62 * 4..start + 2 * 62 * 4];
        let at = (9 + 16) * 4;
        let v = f32::from_le_bytes(record[at..at + 4].try_into().unwrap());
        assert_eq!(v, cloud.sh[(3 + 1) * 16 + 2]);
    }

    /// Files of lower degrees, reordered properties, extra properties and comments read.
    #[test]
    fn reads_other_writers_layouts() {
        let names = [
            "rot_0", "rot_1", "rot_2", "rot_3", "x", "y", "z", "opacity", "red", "scale_0",
            "scale_1", "scale_2", "f_dc_0", "f_dc_1", "f_dc_2",
        ];
        let mut header = String::from(
            "ply\ncomment made by hand\nformat binary_little_endian 1.0\nelement vertex 2\n",
        );
        for name in names {
            if name == "red" {
                header.push_str("property uchar red\n");
            } else {
                header.push_str(&format!("property float {name}\n"));
            }
        }
        header.push_str("end_header\n");
        let mut bytes = header.into_bytes();
        for i in 0..2 {
            for name in names {
                if name == "red" {
                    bytes.push(200);
                } else {
                    let v: f32 = match name {
                        "rot_0" => 1.0,
                        "x" => i as f32,
                        _ => 0.25,
                    };
                    bytes.extend_from_slice(&v.to_le_bytes());
                }
            }
        }
        let cloud = read_ply(&bytes).unwrap();
        assert_eq!(cloud.sh_degree, 0);
        assert_eq!(cloud.xyz, vec![0.0, 0.25, 0.25, 1.0, 0.25, 0.25]);
        assert_eq!(cloud.rotation[..4], [1.0, 0.25, 0.25, 0.25]);
        assert_eq!(cloud.sh, vec![0.25; 6]);
    }

    /// Bad files are errors naming what is wrong, never panics: every truncation and a
    /// set of corruptions of a valid file.
    #[test]
    fn rejects_bad_files_without_panicking() {
        let mut rng = Rng::new(3);
        let good = write_ply(&random_cloud(&mut rng, 3, 1)).unwrap();
        for cut in 0..good.len() {
            assert!(read_ply(&good[..cut]).is_err(), "truncated at {cut}");
        }
        // Edits of the header text, the binary data kept as it is.
        let split = good.windows(11).position(|w| w == b"end_header\n").unwrap() + 11;
        let header = std::str::from_utf8(&good[..split]).unwrap();
        let edit = |from: &str, to: &str| -> Vec<u8> {
            let mut bytes = header.replacen(from, to, 1).into_bytes();
            bytes.extend_from_slice(&good[split..]);
            bytes
        };
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (edit("ply\n", "plx\n"), "start"),
            (edit("binary_little_endian", "ascii"), "format"),
            (edit("element vertex 3", "element vertex 4"), "bytes"),
            (edit("element vertex 3", "element vertex x"), "count"),
            (
                edit("property float opacity", "property float opacitx"),
                "opacity",
            ),
            (edit("property float x\n", "property int x\n"), "x"),
            (
                edit("property float f_rest_44\n", "property float f_rest_x\n"),
                "f_rest_44",
            ),
            (edit("property float y", "property float x"), "twice"),
            (edit("property float y", "property blob y"), "type"),
            (edit("element vertex 3", "element face 3"), "face"),
        ];
        for (bad, needle) in cases {
            let error = read_ply(&bad).unwrap_err().to_string();
            assert!(error.contains(needle), "{needle}: {error}");
        }
        // Non-finite values and a zero rotation name the Gaussian.
        let header_len = good.len() - 3 * 62 * 4;
        let mut nan = good.clone();
        nan[header_len + 62 * 4..header_len + 62 * 4 + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(
            read_ply(&nan).unwrap_err(),
            PlyError::NotFinite {
                index: 1,
                field: "x/y/z"
            }
        );
        let mut zero = good.clone();
        for r in 0..4 {
            let at = header_len + (58 + r) * 4;
            zero[at..at + 4].copy_from_slice(&0f32.to_le_bytes());
        }
        assert!(
            read_ply(&zero)
                .unwrap_err()
                .to_string()
                .contains("Gaussian 0")
        );
        // A huge declared count is refused before anything is allocated.
        let huge = edit("element vertex 3", "element vertex 999999999999");
        assert!(read_ply(&huge).is_err());
    }

    /// The committed fuzzing seed `tests/fixtures/data/ply/export.ply` (listed in its
    /// MANIFEST.json; `fuzz/` target `ply` starts from it).
    fn seed_path() -> std::path::PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../tests/fixtures/data/ply/export.ply")
    }

    /// Four Gaussians of SH degree 2 (so the file holds zeros beyond the active
    /// coefficients), every value a closed form of its indices.
    fn seed_cloud() -> SplatCloud {
        let n = 4;
        let k = coefficient_count(2);
        let value = |i: usize, j: usize, scale: f32| scale * ((i * 7 + j * 3) % 11) as f32 - 0.5;
        SplatCloud {
            xyz: (0..3 * n).map(|j| value(j / 3, j, 0.1)).collect(),
            sh: (0..3 * k * n)
                .map(|j| value(j / (3 * k), j, 0.05))
                .collect(),
            sh_degree: 2,
            opacity: (0..n).map(|i| value(i, 1, 0.5)).collect(),
            log_scale: (0..3 * n).map(|j| -2.0 - value(j / 3, j, 0.2)).collect(),
            rotation: (0..4 * n).map(|j| value(j / 4, j, 0.2) + 0.1).collect(),
        }
    }

    /// The committed seed is exactly what [`write_ply`] writes for [`seed_cloud`], and
    /// reads back to it. `SEQAVATAR_WRITE_PLY_SEED=1` (re)writes the file instead of
    /// comparing; then update its MANIFEST.json entry (size and blake3 digest).
    #[test]
    fn committed_seed_is_the_writers_output() {
        let cloud = seed_cloud();
        let bytes = write_ply(&cloud).unwrap();
        let path = seed_path();
        if std::env::var_os("SEQAVATAR_WRITE_PLY_SEED").is_some() {
            std::fs::create_dir_all(path.parent().unwrap()).unwrap();
            std::fs::write(&path, &bytes).unwrap();
        }
        let committed = std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert!(
            committed == bytes,
            "{} is not write_ply's output: rewrite it with SEQAVATAR_WRITE_PLY_SEED=1",
            path.display()
        );
        let back = read_ply(&committed).unwrap();
        assert_eq!(back.len(), 4);
        assert_eq!(back.sh_degree, 3);
        assert_eq!(back.xyz, cloud.xyz);
        assert_eq!(back.opacity, cloud.opacity);
        assert_eq!(back.log_scale, cloud.log_scale);
        assert_eq!(back.rotation, cloud.rotation);
        // Coefficient 4 (degree 2) of green of Gaussian 3, and zeros beyond degree 2.
        assert_eq!(back.sh[(3 * 3 + 1) * 16 + 4], cloud.sh[(3 * 3 + 1) * 9 + 4]);
        assert!((9..16).all(|coeff| back.sh[(3 * 3 + 1) * 16 + coeff] == 0.0));
    }
}
