//! The numpy `.npz` format: a zip archive of `.npy` members, stored (`np.savez`) or deflated
//! (`np.savez_compressed`), with or without zip64 records (numpy writes zip64 local headers).
//!
//! The zip reader is ours (a few hundred lines) so it can be fuzzed with the rest: sizes come
//! from the central directory and are checked against the archive length before any
//! allocation; deflated members are inflated with a bound on the output and their CRC-32 is
//! verified. Members may not overlap. Each member's `.npy` header is inflated first: the
//! array it declares must fit the per-array limit, the arrays of the archive together the
//! per-file limit, and the member's size must be what the directory records, all before
//! its data is inflated; inflating stops one byte past that size (limits: the [`super`]
//! module docs). Nothing depends on how well a member compresses.

use std::borrow::Cow;
use std::io::Read;
use std::ops::Range;

use super::npy::{self, NpyError};
use super::value::Value;
use super::{BadLimit, Budget, Limits};

/// Why an `.npz` archive was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum NpzError {
    #[error("not a zip archive (no end-of-central-directory record)")]
    NotZip,
    #[error("corrupt zip archive: {0}")]
    Corrupt(String),
    #[error("unsupported zip feature in member '{member}': {what}")]
    Unsupported { member: String, what: String },
    #[error(transparent)]
    Limit(#[from] BadLimit),
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

/// Reads every array of an `.npz` archive, in archive order, named without the `.npy` suffix,
/// within the [`Limits::from_env`] (see [`super`]). Members may not overlap (one compressed
/// stream listed many times).
pub fn read(bytes: &[u8]) -> Result<Vec<(String, Value)>, NpzError> {
    read_with(bytes, &Limits::from_env()?)
}

/// [`read`] within explicit limits.
pub fn read_with(bytes: &[u8], limits: &Limits) -> Result<Vec<(String, Value)>, NpzError> {
    let entries = list(bytes)?;
    check_disjoint(bytes, &entries)?;
    let mut file = Budget::with_limit(limits.max_file_bytes);
    let mut out = Vec::with_capacity(entries.len());
    for entry in &entries {
        let value = read_member_within(bytes, entry, limits, &mut file)?;
        let name = entry
            .name
            .strip_suffix(".npy")
            .unwrap_or(&entry.name)
            .to_owned();
        out.push((name, value));
    }
    Ok(out)
}

/// The array of one member (without reading the others), within the [`Limits::from_env`].
pub fn read_member(bytes: &[u8], entry: &ZipEntry) -> Result<Value, NpzError> {
    let limits = Limits::from_env()?;
    let mut file = Budget::with_limit(limits.max_file_bytes);
    read_member_within(bytes, entry, &limits, &mut file)
}

/// [`read_member`] with the decoded array charged to `file`, the archive's budget.
fn read_member_within(
    bytes: &[u8],
    entry: &ZipEntry,
    limits: &Limits,
    file: &mut Budget,
) -> Result<Value, NpzError> {
    let member_error = |source| NpzError::Member {
        member: entry.name.clone(),
        source,
    };
    let data = extract_declared(bytes, entry, limits, file.left())?;
    let header = npy::read_header(&data).map_err(member_error)?;
    npy::decode_within(&data, &header, limits, file).map_err(member_error)
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

/// The most bytes an `.npy` header may take (numpy itself reads at most 10000).
pub const MAX_NPY_HEADER_BYTES: usize = 1 << 20;

/// The uncompressed bytes of one member (an `.npy` file), with its CRC-32 checked. A
/// deflated member's header is inflated first: the array it declares must fit `limits` (and
/// `file_left`, what the archive's earlier members left of the per-file limit) and, with the
/// header, make up exactly the size the directory records, before the rest is inflated;
/// inflating stops one byte past that size. Stored members are borrowed.
pub fn extract_declared<'a>(
    bytes: &'a [u8],
    entry: &ZipEntry,
    limits: &Limits,
    file_left: usize,
) -> Result<Cow<'a, [u8]>, NpzError> {
    let member = || entry.name.clone();
    let member_error = |source| NpzError::Member {
        member: member(),
        source,
    };
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
            let header = npy::read_header(compressed).map_err(member_error)?;
            check_declared_size(entry, &header, limits, file_left)?;
            Cow::Borrowed(compressed)
        }
        8 => {
            let mut inflate = flate2::read::DeflateDecoder::new(compressed);
            let inflate_error =
                |e: std::io::Error| NpzError::Corrupt(format!("member '{}': {e}", entry.name));
            let mut out = inflate_header(&mut inflate, entry)?;
            let header = npy::read_header(&out).map_err(member_error)?;
            check_declared_size(entry, &header, limits, file_left)?;
            // Within the limits: at most the decoded size of the declared array.
            let expected = usize::try_from(entry.uncompressed_size).unwrap_or(usize::MAX);
            out.reserve_exact(expected.saturating_sub(out.len()));
            let rest = expected.saturating_sub(out.len()) as u64;
            (&mut inflate)
                .take(rest)
                .read_to_end(&mut out)
                .map_err(inflate_error)?;
            // One byte more would be data past the declared size (read aside, so the buffer
            // never grows past it).
            let mut extra = [0u8; 1];
            let more = inflate.read(&mut extra).map_err(inflate_error)? > 0;
            if more || out.len() != expected {
                return Err(NpzError::Corrupt(format!(
                    "member '{}': inflated to {}{} bytes, its header and the zip directory \
                     declare {expected}",
                    entry.name,
                    if more { "more than " } else { "" },
                    out.len()
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

/// Inflates the `.npy` header of a deflated member (the magic string, version and header
/// length, then the header), and nothing of its data.
fn inflate_header(
    inflate: &mut flate2::read::DeflateDecoder<&[u8]>,
    entry: &ZipEntry,
) -> Result<Vec<u8>, NpzError> {
    let member_error = |source| NpzError::Member {
        member: entry.name.clone(),
        source,
    };
    let inflate_error =
        |e: std::io::Error| NpzError::Corrupt(format!("member '{}': {e}", entry.name));
    let mut out = Vec::with_capacity(256);
    inflate
        .take(12)
        .read_to_end(&mut out)
        .map_err(inflate_error)?;
    let header_end = npy_header_end(&out).map_err(member_error)?;
    if header_end > MAX_NPY_HEADER_BYTES {
        return Err(member_error(NpyError::BadHeader(format!(
            "the header is {header_end} bytes, more than the {MAX_NPY_HEADER_BYTES} allowed"
        ))));
    }
    inflate
        .take(header_end.saturating_sub(out.len()) as u64)
        .read_to_end(&mut out)
        .map_err(inflate_error)?;
    Ok(out)
}

/// The `.npy` header of one member (the shape and dtype it declares), read without
/// inflating its data: what an array will be, before deciding to read it.
pub fn member_header(bytes: &[u8], entry: &ZipEntry) -> Result<npy::NpyHeader, NpzError> {
    let member_error = |source| NpzError::Member {
        member: entry.name.clone(),
        source,
    };
    let (_, range) = member_span(bytes, entry)?;
    let compressed = &bytes[range];
    match entry.method {
        0 => npy::read_header(compressed).map_err(member_error),
        8 => {
            let mut inflate = flate2::read::DeflateDecoder::new(compressed);
            let out = inflate_header(&mut inflate, entry)?;
            npy::read_header(&out).map_err(member_error)
        }
        other => Err(NpzError::Unsupported {
            member: entry.name.clone(),
            what: format!("compression method {other}"),
        }),
    }
}

/// Refuses a member whose declared array is over the limits (`file_left`: what the
/// archive's earlier members left of the per-file limit), or whose numeric array and header
/// do not make up the size the zip directory records. An object array's pickle has no
/// declared size: the directory's must fit the limits (its values are charged as it
/// decodes).
fn check_declared_size(
    entry: &ZipEntry,
    header: &npy::NpyHeader,
    limits: &Limits,
    file_left: usize,
) -> Result<(), NpzError> {
    let member_error = |source| NpzError::Member {
        member: entry.name.clone(),
        source,
    };
    npy::check_declared(header, limits, file_left).map_err(member_error)?;
    match npy::declared_sizes(header).map_err(member_error)? {
        Some((stored, _)) => {
            let declared = header.data_offset.checked_add(stored);
            if declared.map(|n| n as u64) != Some(entry.uncompressed_size) {
                return Err(NpzError::Corrupt(format!(
                    "member '{}': its header declares shape {:?} of {} ({} bytes with the \
                     header), the zip directory says {} bytes",
                    entry.name,
                    header.shape,
                    header.dtype.descr(),
                    declared.map_or_else(|| "too many".into(), |n| n.to_string()),
                    entry.uncompressed_size
                )));
            }
        }
        None => {
            let limit = limits.max_array_bytes.min(file_left);
            if entry.uncompressed_size > limit as u64 {
                return Err(member_error(NpyError::ArrayTooLarge {
                    shape: header.shape.clone(),
                    dtype: header.dtype.descr(),
                    bytes: usize::try_from(entry.uncompressed_size).unwrap_or(usize::MAX),
                    limit,
                }));
            }
        }
    }
    Ok(())
}

/// Where the header of an `.npy` starting with `prefix` (at least its first 12 bytes, or
/// all of a shorter file) ends.
fn npy_header_end(prefix: &[u8]) -> Result<usize, NpyError> {
    if prefix.len() < 8 || &prefix[..6] != b"\x93NUMPY" {
        return Err(NpyError::NotNpy);
    }
    let truncated = || NpyError::Truncated("header length".into());
    match prefix[6] {
        1 => {
            let b = prefix.get(8..10).ok_or_else(truncated)?;
            Ok(10 + usize::from(u16::from_le_bytes([b[0], b[1]])))
        }
        2 | 3 => {
            let b = prefix.get(8..12).ok_or_else(truncated)?;
            let len = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            Ok(12usize.saturating_add(usize::try_from(len).unwrap_or(usize::MAX)))
        }
        major => Err(NpyError::UnsupportedVersion {
            major,
            minor: prefix[7],
        }),
    }
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
