//! The numpy `.npz` format: a zip archive of `.npy` members, stored (`np.savez`) or deflated
//! (`np.savez_compressed`), with or without zip64 records (numpy writes zip64 local headers).
//!
//! The zip reader is ours (a few hundred lines) so it can be fuzzed with the rest: sizes come
//! from the central directory and are checked against the archive length before any
//! allocation; deflated members are inflated with a bound on the output and their CRC-32 is
//! verified. Members may not overlap, and what the archive inflates to and decodes to is
//! charged to one [`Budget`] of the archive's size before it is allocated (limits: the
//! [`super`] module docs).

use std::borrow::Cow;
use std::io::Read;
use std::ops::Range;

use super::npy::{self, NpyError};
use super::value::Value;
use super::{Budget, OverBudget};

/// Why an `.npz` archive was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NpzError {
    #[error("not a zip archive (no end-of-central-directory record)")]
    NotZip,
    #[error("corrupt zip archive: {0}")]
    Corrupt(String),
    #[error("unsupported zip feature in member '{member}': {what}")]
    Unsupported { member: String, what: String },
    #[error("member '{member}': {source}")]
    TooLarge {
        member: String,
        #[source]
        source: OverBudget,
    },
    #[error("member '{member}': {source}")]
    Member {
        member: String,
        #[source]
        source: NpyError,
    },
}

/// One member of a zip archive, as described by the central directory.
#[derive(Clone, Debug, PartialEq)]
pub struct ZipEntry {
    pub name: String,
    method: u16,
    flags: u16,
    crc32: u32,
    compressed_size: u64,
    uncompressed_size: u64,
    local_header_offset: u64,
}

/// Reads every array of an `.npz` archive, in archive order, named without the `.npy` suffix.
/// The inflated members and their decoded arrays share one [`Budget`] of the archive's size
/// (see [`super`]), and members may not overlap (one compressed stream listed many times).
pub fn read(bytes: &[u8]) -> Result<Vec<(String, Value)>, NpzError> {
    let entries = list(bytes)?;
    check_disjoint(bytes, &entries)?;
    let mut budget = Budget::for_input(bytes.len());
    let mut out = Vec::with_capacity(entries.len());
    for entry in &entries {
        let data = extract_within(bytes, entry, &mut budget)?;
        let value = npy::read_within(&data, &mut budget).map_err(|source| NpzError::Member {
            member: entry.name.clone(),
            source,
        })?;
        let name = entry
            .name
            .strip_suffix(".npy")
            .unwrap_or(&entry.name)
            .to_owned();
        out.push((name, value));
    }
    Ok(out)
}

fn u16_at(b: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_le_bytes(
        b.get(at..at.checked_add(2)?)?.try_into().ok()?,
    ))
}

fn u32_at(b: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(
        b.get(at..at.checked_add(4)?)?.try_into().ok()?,
    ))
}

fn u64_at(b: &[u8], at: usize) -> Option<u64> {
    Some(u64::from_le_bytes(
        b.get(at..at.checked_add(8)?)?.try_into().ok()?,
    ))
}

fn corrupt(what: &str) -> NpzError {
    NpzError::Corrupt(what.to_owned())
}

/// Lists the members from the central directory.
pub fn list(bytes: &[u8]) -> Result<Vec<ZipEntry>, NpzError> {
    const EOCD: u32 = 0x0605_4b50;
    const EOCD64: u32 = 0x0606_4b50;
    const LOCATOR64: u32 = 0x0706_4b50;
    const CENTRAL: u32 = 0x0201_4b50;
    if bytes.len() < 22 {
        return Err(NpzError::NotZip);
    }
    // The end record is the last 22 bytes plus a comment of at most 65535 bytes.
    let lowest = bytes.len().saturating_sub(22 + 65535);
    let eocd = (lowest..=bytes.len() - 22)
        .rev()
        .find(|&at| u32_at(bytes, at) == Some(EOCD))
        .ok_or(NpzError::NotZip)?;
    let mut count = u64::from(u16_at(bytes, eocd + 10).ok_or_else(|| corrupt("end record"))?);
    let mut cd_size = u64::from(u32_at(bytes, eocd + 12).ok_or_else(|| corrupt("end record"))?);
    let mut cd_offset = u64::from(u32_at(bytes, eocd + 16).ok_or_else(|| corrupt("end record"))?);
    if count == 0xffff || cd_size == 0xffff_ffff || cd_offset == 0xffff_ffff {
        let locator = eocd
            .checked_sub(20)
            .filter(|&at| u32_at(bytes, at) == Some(LOCATOR64))
            .ok_or_else(|| corrupt("zip64 end record locator missing"))?;
        let record = u64_at(bytes, locator + 8).ok_or_else(|| corrupt("zip64 locator"))?;
        let record = usize::try_from(record).map_err(|_| corrupt("zip64 end record offset"))?;
        if u32_at(bytes, record) != Some(EOCD64) {
            return Err(corrupt("zip64 end record signature"));
        }
        count = u64_at(bytes, record + 32).ok_or_else(|| corrupt("zip64 end record"))?;
        cd_size = u64_at(bytes, record + 40).ok_or_else(|| corrupt("zip64 end record"))?;
        cd_offset = u64_at(bytes, record + 48).ok_or_else(|| corrupt("zip64 end record"))?;
    }
    let start = usize::try_from(cd_offset).map_err(|_| corrupt("central directory offset"))?;
    let size = usize::try_from(cd_size).map_err(|_| corrupt("central directory size"))?;
    let directory = start
        .checked_add(size)
        .and_then(|end| bytes.get(start..end))
        .ok_or_else(|| corrupt("central directory lies outside the archive"))?;
    // Each central record is at least 46 bytes: the count cannot exceed what fits.
    if count > (directory.len() / 46) as u64 {
        return Err(corrupt("more members than the central directory can hold"));
    }
    let mut entries = Vec::with_capacity(count as usize);
    let mut at = 0usize;
    for _ in 0..count {
        let field = |offset: usize| u32_at(directory, at + offset);
        if field(0) != Some(CENTRAL) {
            return Err(corrupt("central directory record signature"));
        }
        let short = |offset: usize| {
            u16_at(directory, at + offset).ok_or_else(|| corrupt("central directory record"))
        };
        let flags = short(8)?;
        let method = short(10)?;
        let crc32 = field(16).ok_or_else(|| corrupt("central directory record"))?;
        let mut compressed_size =
            u64::from(field(20).ok_or_else(|| corrupt("central directory record"))?);
        let mut uncompressed_size =
            u64::from(field(24).ok_or_else(|| corrupt("central directory record"))?);
        let name_len = usize::from(short(28)?);
        let extra_len = usize::from(short(30)?);
        let comment_len = usize::from(short(32)?);
        let mut local_header_offset =
            u64::from(field(42).ok_or_else(|| corrupt("central directory record"))?);
        let name_start = at + 46;
        let name = directory
            .get(name_start..name_start + name_len)
            .ok_or_else(|| corrupt("member name"))?;
        let name = String::from_utf8_lossy(name).into_owned();
        let extra = directory
            .get(name_start + name_len..name_start + name_len + extra_len)
            .ok_or_else(|| corrupt("extra field"))?;
        // Zip64 extended information: the 64-bit values of the fields saturated above,
        // in this order.
        let mut e = 0;
        while e + 4 <= extra.len() {
            let id = u16_at(extra, e).unwrap_or(0);
            let len = usize::from(u16_at(extra, e + 2).unwrap_or(0));
            let body = extra
                .get(e + 4..e + 4 + len)
                .ok_or_else(|| corrupt("extra field"))?;
            if id == 0x0001 {
                let mut p = 0;
                for value in [
                    &mut uncompressed_size,
                    &mut compressed_size,
                    &mut local_header_offset,
                ] {
                    if *value == 0xffff_ffff {
                        *value = u64_at(body, p).ok_or_else(|| corrupt("zip64 extra field"))?;
                        p += 8;
                    }
                }
            }
            e += 4 + len;
        }
        entries.push(ZipEntry {
            name,
            method,
            flags,
            crc32,
            compressed_size,
            uncompressed_size,
            local_header_offset,
        });
        at = name_start + name_len + extra_len + comment_len;
    }
    Ok(entries)
}

/// Where a member lies in the archive: its local header's offset and its data's range.
fn member_span(bytes: &[u8], entry: &ZipEntry) -> Result<(usize, Range<usize>), NpzError> {
    const LOCAL: u32 = 0x0403_4b50;
    let local =
        usize::try_from(entry.local_header_offset).map_err(|_| corrupt("local header offset"))?;
    if u32_at(bytes, local) != Some(LOCAL) {
        return Err(NpzError::Corrupt(format!(
            "member '{}': local header signature",
            entry.name
        )));
    }
    let name_len = usize::from(u16_at(bytes, local + 26).ok_or_else(|| corrupt("local header"))?);
    let extra_len = usize::from(u16_at(bytes, local + 28).ok_or_else(|| corrupt("local header"))?);
    let data_start = local + 30 + name_len + extra_len;
    let data_end = usize::try_from(entry.compressed_size)
        .ok()
        .and_then(|n| data_start.checked_add(n))
        .filter(|&end| end <= bytes.len())
        .ok_or_else(|| {
            NpzError::Corrupt(format!(
                "member '{}': {} compressed bytes run past the end of the archive",
                entry.name, entry.compressed_size
            ))
        })?;
    Ok((local, data_start..data_end))
}

/// Refuses archives whose members share bytes: a valid zip stores each member once, and
/// a directory that lists one stream many times multiplies what inflating costs.
fn check_disjoint(bytes: &[u8], entries: &[ZipEntry]) -> Result<(), NpzError> {
    let mut spans = entries
        .iter()
        .map(|entry| Ok((member_span(bytes, entry)?, entry.name.as_str())))
        .collect::<Result<Vec<_>, NpzError>>()?;
    spans.sort_by_key(|((local, _), _)| *local);
    for pair in spans.windows(2) {
        let (((_, first), first_name), ((second_start, _), second_name)) = (&pair[0], &pair[1]);
        if *second_start < first.end {
            return Err(NpzError::Corrupt(format!(
                "members '{first_name}' and '{second_name}' overlap"
            )));
        }
    }
    Ok(())
}

/// The uncompressed bytes of one member, with its CRC-32 checked; inflating may take
/// [`super::decode_budget`] of the archive's size.
pub fn extract<'a>(bytes: &'a [u8], entry: &ZipEntry) -> Result<Cow<'a, [u8]>, NpzError> {
    extract_within(bytes, entry, &mut Budget::for_input(bytes.len()))
}

/// [`extract`] with the inflated bytes charged to `budget` before they are allocated
/// (stored members are borrowed, not copied).
pub fn extract_within<'a>(
    bytes: &'a [u8],
    entry: &ZipEntry,
    budget: &mut Budget,
) -> Result<Cow<'a, [u8]>, NpzError> {
    let member = || entry.name.clone();
    if entry.flags & 1 != 0 {
        return Err(NpzError::Unsupported {
            member: member(),
            what: "encryption".into(),
        });
    }
    let (_, range) = member_span(bytes, entry)?;
    let compressed = &bytes[range];
    let data = match entry.method {
        0 => {
            if entry.uncompressed_size != entry.compressed_size {
                return Err(NpzError::Corrupt(format!(
                    "member '{}': stored sizes differ",
                    entry.name
                )));
            }
            Cow::Borrowed(compressed)
        }
        8 => {
            // Deflate expands at most about 1032 times: a larger claim is corrupt, and the
            // claim bounds the output buffer.
            let bound = (compressed.len() as u64)
                .saturating_mul(1032)
                .saturating_add(1024);
            if entry.uncompressed_size > bound {
                return Err(NpzError::Corrupt(format!(
                    "member '{}': claims {} bytes from {} deflated bytes",
                    entry.name,
                    entry.uncompressed_size,
                    compressed.len()
                )));
            }
            let expected = entry.uncompressed_size as usize;
            budget.charge(expected).map_err(|e| NpzError::TooLarge {
                member: member(),
                source: e,
            })?;
            let mut out = Vec::with_capacity(expected.min(compressed.len().saturating_mul(8)));
            flate2::read::DeflateDecoder::new(compressed)
                .take(entry.uncompressed_size + 1)
                .read_to_end(&mut out)
                .map_err(|e| NpzError::Corrupt(format!("member '{}': {e}", entry.name)))?;
            if out.len() != expected {
                return Err(NpzError::Corrupt(format!(
                    "member '{}': inflated to {} bytes, expected {}",
                    entry.name,
                    out.len(),
                    expected
                )));
            }
            Cow::Owned(out)
        }
        other => {
            return Err(NpzError::Unsupported {
                member: member(),
                what: format!("compression method {other}"),
            });
        }
    };
    let crc = crc32fast::hash(&data);
    if crc != entry.crc32 {
        return Err(NpzError::Corrupt(format!(
            "member '{}': CRC-32 {crc:08x} does not match {:08x}",
            entry.name, entry.crc32
        )));
    }
    Ok(data)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Found by `cargo fuzz run npz`: a zip64 locator whose record offset is `u64::MAX`
    /// made the field readers overflow `offset + width`.
    #[test]
    fn a_zip64_record_offset_at_the_end_of_the_address_space_is_an_error() {
        let mut bytes = vec![0x8a_u8; 8];
        // zip64 end-of-central-directory locator: signature, disk, record offset, disks.
        bytes.extend_from_slice(&0x0706_4b50_u32.to_le_bytes());
        bytes.extend_from_slice(&0_u32.to_le_bytes());
        bytes.extend_from_slice(&u64::MAX.to_le_bytes());
        bytes.extend_from_slice(&1_u32.to_le_bytes());
        // End record with every field saturated, so the zip64 path is taken.
        bytes.extend_from_slice(&0x0605_4b50_u32.to_le_bytes());
        bytes.extend_from_slice(&[0xff; 18]);
        assert!(
            matches!(list(&bytes), Err(NpzError::Corrupt(_))),
            "{:?}",
            list(&bytes)
        );
    }

    #[test]
    fn rejects_non_zip_and_bad_directories() {
        assert_eq!(read(b"PK"), Err(NpzError::NotZip));
        assert_eq!(read(&[0u8; 100]), Err(NpzError::NotZip));
        // An end record that points its directory past the end of the file.
        let mut eocd = vec![0u8; 22];
        eocd[..4].copy_from_slice(&0x0605_4b50u32.to_le_bytes());
        eocd[10..12].copy_from_slice(&1u16.to_le_bytes());
        eocd[12..16].copy_from_slice(&46u32.to_le_bytes());
        eocd[16..20].copy_from_slice(&1000u32.to_le_bytes());
        assert!(matches!(read(&eocd), Err(NpzError::Corrupt(_))));
        // An empty archive is valid and empty.
        let mut empty = vec![0u8; 22];
        empty[..4].copy_from_slice(&0x0605_4b50u32.to_le_bytes());
        assert_eq!(read(&empty), Ok(vec![]));
    }
}
