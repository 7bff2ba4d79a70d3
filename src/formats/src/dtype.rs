//! Numpy dtype strings (`<f8`, `|u1`, `<U5`, `|O`) and decoding raw element bytes.

use super::value::ArrayData;

/// The element kinds the readers support. Complex, datetime and structured types are
/// rejected with a message naming the type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    Bool,
    Int,
    UInt,
    Float,
    /// `U`: fixed-width UTF-32 strings.
    Unicode,
    /// `S`: fixed-width byte strings.
    Bytes,
    /// `O`: Python objects (stored pickled, never as raw bytes).
    Object,
}

/// A parsed scalar dtype.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct DType {
    pub kind: Kind,
    /// Bytes per element (for `U`, four per character). Zero for objects.
    pub itemsize: usize,
    pub big_endian: bool,
}

impl DType {
    /// Parses a numpy type string: an optional byte-order character (`<`, `>`, `|`, `=`), a
    /// kind character and a size. `U` sizes count characters, as numpy writes them.
    pub fn parse(descr: &str) -> Result<DType, String> {
        let (big_endian, rest) = match descr.as_bytes().first() {
            Some(b'>') | Some(b'!') => (true, &descr[1..]),
            Some(b'<') | Some(b'|') | Some(b'=') => (false, &descr[1..]),
            _ => (false, descr),
        };
        let mut chars = rest.chars();
        let kind_char = chars
            .next()
            .ok_or_else(|| format!("empty dtype string {descr:?}"))?;
        let size_text = chars.as_str();
        let size: Option<usize> = if size_text.is_empty() {
            None
        } else {
            Some(
                size_text
                    .parse()
                    .map_err(|_| format!("unsupported dtype {descr:?}"))?,
            )
        };
        let (kind, itemsize) = match (kind_char, size) {
            ('b', Some(1)) | ('?', None) => (Kind::Bool, 1),
            ('i', Some(n @ (1 | 2 | 4 | 8))) => (Kind::Int, n),
            ('u', Some(n @ (1 | 2 | 4 | 8))) => (Kind::UInt, n),
            ('f', Some(n @ (2 | 4 | 8))) => (Kind::Float, n),
            ('O', None | Some(4 | 8)) => (Kind::Object, 0),
            ('U', Some(n)) if n > 0 && n <= 1 << 20 => (Kind::Unicode, 4 * n),
            ('S', Some(n)) if n > 0 && n <= 1 << 22 => (Kind::Bytes, n),
            _ => {
                return Err(format!(
                    "unsupported dtype {descr:?} (supported: bool, integers, float16/32/64, \
                     fixed-width strings, objects)"
                ));
            }
        };
        Ok(DType {
            kind,
            itemsize,
            big_endian: big_endian && itemsize > 1 && kind != Kind::Bytes,
        })
    }

    /// The canonical numpy string of this dtype, e.g. `<f8`.
    pub fn descr(&self) -> String {
        let order = if self.itemsize <= 1 || matches!(self.kind, Kind::Bytes | Kind::Object) {
            '|'
        } else if self.big_endian {
            '>'
        } else {
            '<'
        };
        match self.kind {
            Kind::Bool => "|b1".to_owned(),
            Kind::Int => format!("{order}i{}", self.itemsize),
            Kind::UInt => format!("{order}u{}", self.itemsize),
            Kind::Float => format!("{order}f{}", self.itemsize),
            Kind::Unicode => format!("{order}U{}", self.itemsize / 4),
            Kind::Bytes => format!("|S{}", self.itemsize),
            Kind::Object => "|O".to_owned(),
        }
    }

    /// Bytes that [`DType::decode`] allocates for `count` elements (the widened element, or
    /// a `String`/`Vec<u8>` header plus its text per string), `None` on overflow.
    pub fn decoded_bytes(&self, count: usize) -> Option<usize> {
        let per_element = match (self.kind, self.itemsize) {
            (Kind::Bool, _) | (Kind::UInt, 1) => 1,
            (Kind::Float, 2 | 4) => 4,
            (Kind::Int | Kind::UInt | Kind::Float, _) => 8,
            (Kind::Unicode, n) => std::mem::size_of::<String>() + n,
            (Kind::Bytes, n) => std::mem::size_of::<Vec<u8>>() + n,
            (Kind::Object, _) => std::mem::size_of::<super::value::Value>(),
        };
        count.checked_mul(per_element)
    }

    /// Decodes `bytes` (exactly `count * itemsize` long) into typed elements.
    pub fn decode(&self, bytes: &[u8], count: usize) -> Result<ArrayData, String> {
        if self.kind == Kind::Object {
            return Err("object arrays cannot be decoded from raw bytes".to_owned());
        }
        let expected = count.checked_mul(self.itemsize);
        if expected != Some(bytes.len()) {
            return Err(format!(
                "{} elements of {} need {} bytes, found {}",
                count,
                self.descr(),
                expected.map_or_else(|| "too many".to_owned(), |n| n.to_string()),
                bytes.len()
            ));
        }
        let n = self.itemsize;
        let be = self.big_endian;
        // Reads one element's bytes as a little-endian array of N bytes.
        fn word<const N: usize>(chunk: &[u8], big_endian: bool) -> [u8; N] {
            let mut out = [0u8; N];
            out.copy_from_slice(chunk);
            if big_endian {
                out.reverse();
            }
            out
        }
        let chunks = bytes.chunks_exact(n.max(1));
        // `ArrayData::$data` of the elements read as `$word`, each converted by `$convert`.
        macro_rules! numbers {
            ($data:ident, $word:ty $(, $convert:expr)?) => {
                ArrayData::$data(
                    chunks
                        .map(|c| <$word>::from_le_bytes(word(c, be)))
                        $(.map($convert))?
                        .collect(),
                )
            };
        }
        Ok(match (self.kind, n) {
            (Kind::Bool, _) => ArrayData::Bool(bytes.iter().map(|&b| b != 0).collect()),
            (Kind::UInt, 1) => ArrayData::U8(bytes.to_vec()),
            (Kind::Int, 1) => ArrayData::I64(bytes.iter().map(|&b| i64::from(b as i8)).collect()),
            (Kind::Int, 2) => numbers!(I64, i16, i64::from),
            (Kind::Int, 4) => numbers!(I64, i32, i64::from),
            (Kind::Int, 8) => numbers!(I64, i64),
            (Kind::UInt, 2) => numbers!(I64, u16, i64::from),
            (Kind::UInt, 4) => numbers!(I64, u32, i64::from),
            (Kind::UInt, 8) => numbers!(U64, u64),
            (Kind::Float, 2) => numbers!(F32, u16, f16_to_f32),
            (Kind::Float, 4) => numbers!(F32, f32),
            (Kind::Float, 8) => numbers!(F64, f64),
            (Kind::Unicode, _) => {
                let mut out = Vec::with_capacity(count);
                for c in chunks {
                    let mut s = String::new();
                    for unit in c.chunks_exact(4) {
                        let code = u32::from_le_bytes(word(unit, be));
                        if code == 0 {
                            break;
                        }
                        s.push(char::from_u32(code).ok_or_else(|| {
                            format!("invalid unicode code point {code:#x} in a string array")
                        })?);
                    }
                    out.push(s);
                }
                ArrayData::Str(out)
            }
            (Kind::Bytes, _) => ArrayData::Bytes(
                chunks
                    .map(|c| {
                        let end = c.iter().rposition(|&b| b != 0).map_or(0, |p| p + 1);
                        c[..end].to_vec()
                    })
                    .collect(),
            ),
            _ => return Err(format!("unsupported dtype {}", self.descr())),
        })
    }
}

/// IEEE half precision to single precision, exact for every input including subnormals,
/// infinities and NaN.
pub fn f16_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0f32 } else { 1.0 };
    let exponent = i32::from((h >> 10) & 0x1f);
    let mantissa = f32::from(h & 0x3ff);
    match exponent {
        0 => sign * mantissa * 2f32.powi(-24),
        31 if mantissa == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        e => sign * (1.0 + mantissa / 1024.0) * 2f32.powi(e - 15),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_numpy_strings() {
        let d = DType::parse("<f8").unwrap();
        assert_eq!((d.kind, d.itemsize, d.big_endian), (Kind::Float, 8, false));
        assert_eq!(DType::parse(">i4").unwrap().descr(), ">i4");
        assert_eq!(DType::parse("U5").unwrap().itemsize, 20);
        assert_eq!(DType::parse("|O").unwrap().kind, Kind::Object);
        assert_eq!(DType::parse("O8").unwrap().kind, Kind::Object);
        assert_eq!(DType::parse("b1").unwrap().kind, Kind::Bool);
        assert!(!DType::parse(">u1").unwrap().big_endian);
        for bad in [
            "",
            "<",
            "<c16",
            "<M8",
            "<f3",
            "<U0",
            "V8",
            "<f8x",
            "<U99999999999999",
        ] {
            assert!(DType::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn decodes_both_byte_orders() {
        let le = DType::parse("<i2").unwrap();
        let be = DType::parse(">i2").unwrap();
        assert_eq!(
            le.decode(&[0x01, 0x80], 1).unwrap(),
            ArrayData::I64(vec![-32767])
        );
        assert_eq!(
            be.decode(&[0x01, 0x80], 1).unwrap(),
            ArrayData::I64(vec![384])
        );
        let f = DType::parse(">f8").unwrap();
        assert_eq!(
            f.decode(&1.5f64.to_be_bytes(), 1).unwrap(),
            ArrayData::F64(vec![1.5])
        );
        assert!(f.decode(&[0; 7], 1).is_err());
        assert!(f.decode(&[], usize::MAX).is_err());
    }

    /// The estimate the readers charge before decoding is what decoding really takes.
    #[test]
    fn decoded_bytes_match_the_decoded_vectors() {
        let count = 5;
        for (descr, expected) in [
            ("|b1", count),
            ("|u1", count),
            ("<i2", 8 * count),
            ("<u8", 8 * count),
            ("<f2", 4 * count),
            ("<f4", 4 * count),
            ("<f8", 8 * count),
            ("<U3", count * (std::mem::size_of::<String>() + 12)),
            ("|S2", count * (std::mem::size_of::<Vec<u8>>() + 2)),
        ] {
            let dtype = DType::parse(descr).unwrap();
            assert_eq!(dtype.decoded_bytes(count), Some(expected), "{descr}");
            // The vector of a decode of non-empty elements has exactly this footprint
            // (strings: header plus at most itemsize bytes of UTF-8).
            let bytes = vec![b'a'; count * dtype.itemsize];
            let bytes: Vec<u8> = if dtype.kind == Kind::Unicode {
                bytes
                    .chunks(4)
                    .flat_map(|_| (b'a' as u32).to_le_bytes())
                    .collect()
            } else {
                bytes
            };
            let data = dtype.decode(&bytes, count).unwrap();
            let footprint = data.footprint();
            assert!(footprint <= expected, "{descr}: {footprint} > {expected}");
        }
        assert_eq!(DType::parse("|S1").unwrap().decoded_bytes(usize::MAX), None);
    }

    #[test]
    fn decodes_strings_without_padding() {
        let u = DType::parse("<U3").unwrap();
        let mut bytes = Vec::new();
        for c in ['a', 'é', '\0', 'x', '\0', '\0'] {
            bytes.extend((c as u32).to_le_bytes());
        }
        assert_eq!(
            u.decode(&bytes, 2).unwrap(),
            ArrayData::Str(vec!["aé".into(), "x".into()])
        );
        let s = DType::parse("|S2").unwrap();
        assert_eq!(
            s.decode(b"a\0bc", 2).unwrap(),
            ArrayData::Bytes(vec![b"a".to_vec(), b"bc".to_vec()])
        );
    }

    #[test]
    fn half_precision_matches_known_values() {
        // Values from the IEEE 754 binary16 table.
        assert_eq!(f16_to_f32(0x3c00), 1.0);
        assert_eq!(f16_to_f32(0xc000), -2.0);
        assert_eq!(f16_to_f32(0x7bff), 65504.0);
        assert_eq!(f16_to_f32(0x0001), 2f32.powi(-24));
        assert_eq!(f16_to_f32(0x3555), 0.333_251_95);
        assert_eq!(f16_to_f32(0x7c00), f32::INFINITY);
        assert!(f16_to_f32(0x7e00).is_nan());
        assert_eq!(f16_to_f32(0x8000), 0.0);
    }
}
