//! The Gaussian stream: one frame's posed Gaussians (after the networks, the pose refiner
//! and skinning: what the server's render splats) in the compact binary layout the page
//! splats itself. Little-endian, layout [`LAYOUT_VERSION`]; a `/gaussians` reply is one
//! record per frame, back to back:
//!
//! ```text
//! offset       size  field
//! 0            4     magic "SAGS"
//! 4            4     u32 layout version (1)
//! 8            4     u32 frame
//! 12           4     u32 count n
//! 16           12    f32 x 3 centre: the mean of the positions (the orbit pivot)
//! 28           4     f32 lo: the smallest log scale of the record
//! 32           4     f32 hi: the largest log scale (at most LOG_SCALE_SPAN above lo)
//! 36           4     f32 sh: the largest magnitude of a degree-1 SH coefficient (0: none)
//! 40           12 n  f32 x 3 positions (world, metres)
//! 40 + 12 n    4 n   i8 x 4 unit rotations w x y z, times 127
//! 40 + 16 n    4 n   u8 x 4 colour r g b (0.5 + the SH degree-0 term, 0..=255) and opacity
//! 40 + 20 n    6 n   u16 x 3 log scales, lo + (hi - lo) q / 65535
//! 40 + 26 n    9 n   i8 x 3 x 3 the degree-1 SH coefficients (rgb of Y_1, Y_2, Y_3), sh q / 127
//! 40 + 35 n    0-3   zero padding to a multiple of 4 bytes
//! ```
//!
//! Each covariance is sent as scales and a rotation, its eigen decomposition
//! ([`seqavatar_avatar::ply::scale_rotation_of`], as `pipeline export` writes it), so every
//! decoded covariance is positive definite whatever the rounding. The quantisation keeps
//! scales within 0.02% and rotations within about half a degree: nothing a pixel shows.
//! Colour is SH up to degree 1 (higher degrees are dropped); the exact pixels are the
//! server's renders (compare mode).

use seqavatar_avatar::ply::scale_rotation_of;
use seqavatar_avatar::splatting::WorldGaussians;
use seqavatar_compute::splat::sh::SH_C0;

/// The first four bytes of every record.
pub const MAGIC: [u8; 4] = *b"SAGS";
/// The layout's version: change it with any change to the layout.
pub const LAYOUT_VERSION: u32 = 1;
/// Bytes before the positions.
pub const HEADER_BYTES: usize = 40;
/// Bytes per Gaussian (without the record's padding).
pub const BYTES_PER_GAUSSIAN: usize = 35;
/// Log scales more than this below the largest are raised to it (a scale 10^-6 of the
/// largest draws as nothing either way), so the 16 bits are spent where a pixel can see them.
pub const LOG_SCALE_SPAN: f32 = 13.8;

/// The bytes of a record of `count` Gaussians.
pub fn record_bytes(count: usize) -> usize {
    (HEADER_BYTES + BYTES_PER_GAUSSIAN * count).next_multiple_of(4)
}

/// Appends the record of frame `frame`'s Gaussians `world` to `out`; an error names the
/// Gaussian whose covariance or centre is not finite.
pub fn encode(frame: usize, world: &WorldGaussians, out: &mut Vec<u8>) -> Result<(), String> {
    let n = world.opacities.len();
    let coefficients = world.sh.len() / (3 * n.max(1));
    if world.means.len() != 3 * n
        || world.covariances.len() != 6 * n
        || world.sh.len() != 3 * coefficients * n
        || (n > 0 && coefficients == 0)
    {
        return Err(format!(
            "{n} opacities with {} centre, {} covariance and {} SH values",
            world.means.len(),
            world.covariances.len(),
            world.sh.len()
        ));
    }
    if let Some(index) = world.means.iter().position(|value| !value.is_finite()) {
        return Err(format!("Gaussian {}: its centre is not finite", index / 3));
    }
    let decomposed = world
        .covariances
        .chunks_exact(6)
        .enumerate()
        .map(|(index, upper)| {
            scale_rotation_of(upper)
                .ok_or_else(|| format!("Gaussian {index}: its covariance is not finite"))
        })
        .collect::<Result<Vec<_>, String>>()?;
    let log_scales: Vec<[f32; 3]> = decomposed
        .iter()
        .map(|(scales, _)| scales.map(|scale| scale.ln() as f32))
        .collect();
    let hi = log_scales
        .iter()
        .flatten()
        .copied()
        .fold(f32::NEG_INFINITY, f32::max);
    let lo = log_scales
        .iter()
        .flatten()
        .copied()
        .fold(f32::INFINITY, f32::min)
        .max(hi - LOG_SCALE_SPAN);
    let (lo, hi) = if n == 0 { (0.0, 0.0) } else { (lo, hi) };
    let step = (hi - lo).max(f32::MIN_POSITIVE);
    let centre = if n == 0 {
        [0.0; 3]
    } else {
        let mut sum = [0.0f64; 3];
        for mean in world.means.chunks_exact(3) {
            for (total, value) in sum.iter_mut().zip(mean) {
                *total += value;
            }
        }
        sum.map(|total| (total / n as f64) as f32)
    };
    let start = out.len();
    out.reserve(record_bytes(n));
    out.extend_from_slice(&MAGIC);
    for value in [LAYOUT_VERSION, frame as u32, n as u32] {
        out.extend_from_slice(&value.to_le_bytes());
    }
    // The degree-1 coefficients of each Gaussian (`N x K x 3`: coefficients 1..4).
    let degree_one = |index: usize| -> &[f64] {
        if coefficients >= 4 {
            &world.sh[index * 3 * coefficients + 3..][..9]
        } else {
            &[]
        }
    };
    let sh_scale = (0..n)
        .flat_map(degree_one)
        .fold(0.0f64, |largest, value| largest.max(value.abs())) as f32;
    if !sh_scale.is_finite() {
        return Err("an SH coefficient is not finite".to_owned());
    }
    for value in centre.into_iter().chain([lo, hi, sh_scale]) {
        out.extend_from_slice(&value.to_le_bytes());
    }
    for value in &world.means {
        out.extend_from_slice(&(*value as f32).to_le_bytes());
    }
    for (_, rotation) in &decomposed {
        out.extend(
            rotation.map(|component| (component.clamp(-1.0, 1.0) * 127.0).round() as i8 as u8),
        );
    }
    let unit = |value: f64| (value.clamp(0.0, 1.0) * 255.0).round() as u8;
    for (index, opacity) in world.opacities.iter().enumerate() {
        let dc = &world.sh[index * 3 * coefficients..][..3];
        out.extend(dc.iter().map(|&value| unit(0.5 + SH_C0 * value)));
        out.push(unit(*opacity));
    }
    for scales in &log_scales {
        for log_scale in scales {
            let level = ((log_scale.max(lo) - lo) / step * 65535.0).round() as u16;
            out.extend_from_slice(&level.to_le_bytes());
        }
    }
    for index in 0..n {
        let values = degree_one(index);
        for slot in 0..9 {
            let value = values.get(slot).map_or(0.0, |&value| value as f32);
            let level = if sh_scale > 0.0 {
                (value / sh_scale * 127.0).round() as i8
            } else {
                0
            };
            out.push(level as u8);
        }
    }
    out.resize(start + record_bytes(n), 0);
    Ok(())
}

/// One decoded record: the reference reader of the layout (the page's reader does the
/// same in JavaScript).
#[derive(Clone, Debug, PartialEq)]
pub struct Record {
    pub frame: usize,
    pub centre: [f32; 3],
    pub positions: Vec<[f32; 3]>,
    /// Unit `wxyz` rotations.
    pub rotations: Vec<[f32; 4]>,
    /// Standard deviations along the rotation's axes.
    pub scales: Vec<[f32; 3]>,
    /// Colour (0.5 + the degree-0 term) and opacity, `0..=1`.
    pub colours: Vec<[f32; 4]>,
    /// The degree-1 SH coefficients, rgb of `Y_1`, `Y_2`, `Y_3`.
    pub sh: Vec<[f32; 9]>,
}

/// Decodes the records of a `/gaussians` reply.
pub fn decode(mut bytes: &[u8]) -> Result<Vec<Record>, String> {
    let mut records = Vec::new();
    while !bytes.is_empty() {
        if bytes.len() < HEADER_BYTES {
            return Err(format!("{} bytes left, less than a header", bytes.len()));
        }
        let word = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().unwrap());
        let float = |at: usize| f32::from_bits(word(at));
        if bytes[..4] != MAGIC {
            return Err(format!("bad magic {:?}", &bytes[..4]));
        }
        if word(4) != LAYOUT_VERSION {
            return Err(format!("layout version {}, not {LAYOUT_VERSION}", word(4)));
        }
        let n = word(12) as usize;
        let length = record_bytes(n);
        if bytes.len() < length {
            return Err(format!(
                "a record of {n} Gaussians needs {length} bytes, {} are left",
                bytes.len()
            ));
        }
        let (lo, hi, sh_scale) = (float(28), float(32), float(36));
        let at =
            |section: usize, index: usize, size: usize| HEADER_BYTES + section * n + index * size;
        records.push(Record {
            frame: word(8) as usize,
            centre: [float(16), float(20), float(24)],
            positions: (0..n)
                .map(|i| [0, 1, 2].map(|c| float(at(0, i, 12) + 4 * c)))
                .collect(),
            rotations: (0..n)
                .map(|i| {
                    let q = [0, 1, 2, 3].map(|c| f32::from(bytes[at(12, i, 4) + c] as i8) / 127.0);
                    let norm = q
                        .iter()
                        .map(|v| v * v)
                        .sum::<f32>()
                        .sqrt()
                        .max(f32::MIN_POSITIVE);
                    q.map(|v| v / norm)
                })
                .collect(),
            colours: (0..n)
                .map(|i| [0, 1, 2, 3].map(|c| f32::from(bytes[at(16, i, 4) + c]) / 255.0))
                .collect(),
            scales: (0..n)
                .map(|i| {
                    [0, 1, 2].map(|c| {
                        let offset = at(20, i, 6) + 2 * c;
                        let level = u16::from_le_bytes([bytes[offset], bytes[offset + 1]]);
                        (lo + (hi - lo) * f32::from(level) / 65535.0).exp()
                    })
                })
                .collect(),
            sh: (0..n)
                .map(|i| {
                    std::array::from_fn(|c| {
                        f32::from(bytes[at(26, i, 9) + c] as i8) / 127.0 * sh_scale
                    })
                })
                .collect(),
        });
        bytes = &bytes[length..];
    }
    Ok(records)
}

#[cfg(test)]
mod tests {
    use super::*;
    use seqavatar_compute::splat::covariance::covariance_from_scale_rotation;

    /// Three Gaussians, one needle-thin and one tilted, with degree-1 SH.
    fn world() -> WorldGaussians {
        let scales = [0.02, 0.01, 0.005, 0.3, 1e-4, 1e-4, 1e-3, 2e-3, 3e-3];
        let rotations = [
            1.0, 0.0, 0.0, 0.0, 0.9, -0.3, 0.2, 0.5, 0.1, 0.8, -0.4, -0.6,
        ];
        let covariances = covariance_from_scale_rotation(&scales, &rotations)
            .unwrap()
            .covariances;
        WorldGaussians {
            means: vec![0.1, -0.2, 3.0, 1.0, 1.0, 1.0, -5.0, 0.25, 2.0],
            covariances,
            opacities: vec![0.5, 1.0, 0.001],
            sh: (0..36).map(|i| f64::from(i - 18) * 0.1).collect(),
            sh_degree: 1,
        }
    }

    #[test]
    fn a_record_decodes_to_the_gaussians_within_the_quantisation() {
        let world = world();
        let mut bytes = vec![];
        encode(7, &world, &mut bytes).unwrap();
        encode(8, &world, &mut bytes).unwrap();
        assert_eq!(bytes.len(), 2 * record_bytes(3));
        assert_eq!(record_bytes(3), 40 + 105 + 3);
        assert_eq!(&bytes[..4], b"SAGS");
        assert_eq!(bytes[4..8], 1u32.to_le_bytes());
        let records = decode(&bytes).unwrap();
        assert_eq!(records.len(), 2);
        assert_eq!((records[0].frame, records[1].frame), (7, 8));
        let record = &records[0];
        assert!((record.centre[0] - (0.1 + 1.0 - 5.0) / 3.0).abs() < 1e-6);
        for i in 0..3 {
            for c in 0..3 {
                assert_eq!(record.positions[i][c], world.means[3 * i + c] as f32);
            }
            // The decoded covariance against the original, relative to its largest entry.
            let scales: Vec<f64> = record.scales[i].iter().map(|&s| f64::from(s)).collect();
            let rotation: Vec<f64> = record.rotations[i].iter().map(|&q| f64::from(q)).collect();
            let decoded = covariance_from_scale_rotation(&scales, &rotation)
                .unwrap()
                .covariances;
            let original = &world.covariances[6 * i..6 * i + 6];
            let largest = original.iter().fold(0.0f64, |a, b| a.max(b.abs()));
            for (a, b) in decoded.iter().zip(original) {
                assert!(
                    (a - b).abs() < 0.03 * largest,
                    "Gaussian {i}: {decoded:?} against {original:?}"
                );
            }
            let dc = &world.sh[i * 12..i * 12 + 3];
            for (decoded, value) in record.colours[i].iter().zip(dc) {
                let expected = (0.5 + SH_C0 * value).clamp(0.0, 1.0) as f32;
                assert!((decoded - expected).abs() <= 0.5 / 255.0 + 1e-6);
            }
            let opacity = world.opacities[i] as f32;
            assert!((record.colours[i][3] - opacity).abs() <= 0.5 / 255.0 + 1e-6);
            // Degree 1 to half a step of 1.7 / 127 (the largest magnitude here).
            for c in 0..9 {
                let expected = world.sh[i * 12 + 3 + c] as f32;
                assert!((record.sh[i][c] - expected).abs() <= 0.5 * 1.7 / 127.0 + 1e-6);
            }
        }
        // The scales themselves, above the span's floor, to 0.02%.
        let expected = [[0.02f32, 0.01, 0.005], [0.3, 1e-4, 1e-4]];
        for (decoded, expected) in records[0].scales.iter().zip(expected) {
            let mut decoded = *decoded;
            decoded.sort_by(f32::total_cmp);
            let mut expected = expected;
            expected.sort_by(f32::total_cmp);
            for (a, b) in decoded.iter().zip(expected) {
                assert!(
                    (a / b - 1.0).abs() < 2e-4,
                    "{decoded:?} against {expected:?}"
                );
            }
        }
    }

    #[test]
    fn bad_input_and_bad_records_are_refused() {
        let mut world = world();
        world.covariances[7] = f64::NAN;
        let error = encode(0, &world, &mut vec![]).unwrap_err();
        assert!(
            error.contains("Gaussian 1: its covariance is not finite"),
            "{error}"
        );
        let mut world = self::world();
        world.means.pop();
        assert!(encode(0, &world, &mut vec![]).is_err());
        let mut bytes = vec![];
        encode(0, &self::world(), &mut bytes).unwrap();
        let mut other = bytes.clone();
        other[4] = 2;
        assert!(decode(&other).unwrap_err().contains("layout version 2"));
        assert!(
            decode(&bytes[..bytes.len() - 4])
                .unwrap_err()
                .contains("needs")
        );
        other = bytes.clone();
        other[0] = b'X';
        assert!(decode(&other).unwrap_err().contains("magic"));
        // No Gaussians: a header only.
        let empty = WorldGaussians {
            means: vec![],
            covariances: vec![],
            opacities: vec![],
            sh: vec![],
            sh_degree: 0,
        };
        let mut bytes = vec![];
        encode(3, &empty, &mut bytes).unwrap();
        assert_eq!(bytes.len(), HEADER_BYTES);
        assert_eq!(decode(&bytes).unwrap()[0].positions.len(), 0);
    }
}
