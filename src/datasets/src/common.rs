//! Helpers shared by the dataset readers: reading pickled/npy files with the file named in
//! every error, typed field access that names the field, and image/mask decoding (through
//! [`seqavatar_formats::images`]) with size checks.

use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use image::{GrayImage, RgbImage};

use seqavatar_formats::{Value, images, npy, pickle};

/// Reads a whole regular file, naming it in the error (devices, FIFOs and sockets are
/// refused: see [`seqavatar_engine::files`]).
pub fn read_bytes(path: &Path) -> anyhow::Result<Vec<u8>> {
    seqavatar_engine::files::read_regular_file(path)
}

/// Reads an `.npy` file; `np.save` of a dict comes back as the dict.
pub fn read_npy(path: &Path) -> anyhow::Result<Value> {
    let bytes = read_bytes(path)?;
    let value =
        npy::read(&bytes).with_context(|| format!("{}: not a readable .npy", path.display()))?;
    Ok(value.unwrap_object_scalar().clone())
}

pub fn read_pickle(path: &Path) -> anyhow::Result<Value> {
    let bytes = read_bytes(path)?;
    pickle::load(&bytes).with_context(|| format!("{}: not a readable pickle", path.display()))
}

/// A value inside a file, with its path for messages (`cams.K[3]`).
#[derive(Clone, Copy)]
pub struct Field<'a> {
    pub file: &'a Path,
    pub path: &'a str,
    pub value: &'a Value,
}

impl<'a> Field<'a> {
    pub fn root(file: &'a Path, value: &'a Value) -> Self {
        Self {
            file,
            path: "",
            value,
        }
    }

    fn describe(&self) -> String {
        if self.path.is_empty() {
            format!("{} (top level)", self.file.display())
        } else {
            format!("{} field `{}`", self.file.display(), self.path)
        }
    }

    /// A dict entry; `key_path` is the full dotted path used in messages.
    pub fn get(&self, key: &str, key_path: &'a str) -> anyhow::Result<Field<'a>> {
        if self.value.as_dict().is_none() {
            bail!("{}: expected a dict, found {}", self.describe(), self.value);
        }
        let value = self
            .value
            .get(key)
            .with_context(|| format!("{}: missing field `{key_path}`", self.file.display()))?;
        Ok(Field {
            file: self.file,
            path: key_path,
            value,
        })
    }

    /// The items of a list, tuple or 1-D object array.
    pub fn sequence(&self) -> anyhow::Result<&'a [Value]> {
        self.value
            .as_sequence()
            .with_context(|| format!("{}: expected a list, found {}", self.describe(), self.value))
    }

    /// A numeric array of exactly `len` finite values (any shape whose product is `len`,
    /// so `(1, 72)`, `(72,)` and `(24, 3)` all give 72 values).
    pub fn finite_f64s(&self, len: usize) -> anyhow::Result<Vec<f64>> {
        let (shape, values) = self.numeric_array()?;
        if values.len() != len {
            bail!(
                "{}: expected {len} values, found shape {shape:?} ({} values)",
                self.describe(),
                values.len()
            );
        }
        check_finite(&values, &self.describe())?;
        Ok(values)
    }

    /// A numeric array with its shape, all values finite.
    pub fn finite_array(&self) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
        let (shape, values) = self.numeric_array()?;
        check_finite(&values, &self.describe())?;
        Ok((shape, values))
    }

    /// A numeric array with its shape, not yet checked finite.
    fn numeric_array(&self) -> anyhow::Result<(Vec<usize>, Vec<f64>)> {
        self.value.to_f64_array().with_context(|| {
            format!(
                "{}: expected a numeric array, found {}",
                self.describe(),
                self.value
            )
        })
    }

    /// A 3 x 3 matrix (row-major).
    pub fn matrix3(&self) -> anyhow::Result<[[f64; 3]; 3]> {
        let v = self.finite_f64s(9)?;
        Ok([[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]])
    }

    /// OpenCV distortion coefficients `(k1, k2, p1, p2[, k3])`, zero-padded to five.
    pub fn distortion(&self) -> anyhow::Result<[f64; 5]> {
        let d = self.finite_array()?.1;
        if d.len() != 5 && d.len() != 4 {
            bail!(
                "{}: field `{}` has {} coefficients; expected 5 (k1 k2 p1 p2 k3)",
                self.file.display(),
                self.path,
                d.len()
            );
        }
        let mut out = [0.0; 5];
        out[..d.len()].copy_from_slice(&d);
        Ok(out)
    }
}

/// Errors on the first NaN or infinity, naming where it is.
pub fn check_finite(values: &[f64], what: &str) -> anyhow::Result<()> {
    if let Some(index) = values.iter().position(|v| !v.is_finite()) {
        bail!(
            "{what}: value {} at flat index {index} is not finite",
            values[index]
        );
    }
    Ok(())
}

/// Decodes an RGB image (JPEG or PNG, sniffed from the content) of the size its camera is
/// calibrated for, `(width, height)`; the size is checked from the header before decoding.
/// Errors name `source`.
pub fn decode_rgb(bytes: &[u8], source: &str, size: (u32, u32)) -> anyhow::Result<RgbImage> {
    images::decode_rgb(bytes, Some(size))
        .with_context(|| format!("{source}: cannot decode the image"))
}

/// Decodes a mask of its image's size `(width, height)` (see [`images::decode_mask`]):
/// the maximum over its channels, scaled to 0..255 when the file stores labels 0/1
/// (`binary` = any non-zero value is foreground). Errors name `source`.
pub fn decode_mask(
    bytes: &[u8],
    source: &str,
    binary: bool,
    size: (u32, u32),
) -> anyhow::Result<GrayImage> {
    images::decode_mask(bytes, Some(size), binary)
        .with_context(|| format!("{source}: cannot decode the mask"))
}

/// [`decode_rgb`] of the image file at `path`, named in errors.
pub fn read_rgb(path: &Path, size: (u32, u32)) -> anyhow::Result<RgbImage> {
    decode_rgb(&read_bytes(path)?, &path.display().to_string(), size)
}

/// [`decode_mask`] of the mask file at `path`, named in errors.
pub fn read_mask(path: &Path, binary: bool, size: (u32, u32)) -> anyhow::Result<GrayImage> {
    decode_mask(
        &read_bytes(path)?,
        &path.display().to_string(),
        binary,
        size,
    )
}

/// Image width and height from the file's header (format sniffed from the content).
pub fn image_size(path: &Path) -> anyhow::Result<(u32, u32)> {
    images::dimensions(&read_bytes(path)?)
        .with_context(|| format!("{}: cannot read the image size", path.display()))
}

/// `path` joined with a relative path from a dataset file, refusing absolute paths and `..`
/// (a dataset file must not point outside its dataset).
pub fn join_relative(
    root: &Path,
    relative: &str,
    file: &Path,
    field: &str,
) -> anyhow::Result<PathBuf> {
    let rel = Path::new(relative);
    if rel.is_absolute()
        || rel
            .components()
            .any(|c| matches!(c, std::path::Component::ParentDir))
    {
        bail!(
            "{} field `{field}`: path {relative:?} leaves the dataset folder",
            file.display()
        );
    }
    Ok(root.join(rel))
}

/// The trailing decimal number of a name (`Camera_B12` -> 12, `000123` -> 123).
pub fn trailing_number(name: &str) -> Option<i64> {
    let digits = &name[name.trim_end_matches(|c: char| c.is_ascii_digit()).len()..];
    if digits.is_empty() || digits.len() > 15 {
        return None;
    }
    digits.parse().ok()
}

/// Prints a warning about the data; readers also keep them for the stage to report.
pub fn warn(warnings: &mut Vec<String>, message: String) {
    eprintln!("warning: {message}");
    warnings.push(message);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn trailing_numbers() {
        assert_eq!(trailing_number("Camera_B12"), Some(12));
        assert_eq!(trailing_number("000123"), Some(123));
        assert_eq!(trailing_number("abc"), None);
        assert_eq!(trailing_number("x99999999999999999999"), None);
    }

    /// Issue 12: PNG bytes named `.jpg` failed as "Format error decoding Jpeg"; issue 16:
    /// a truncated image must be an error naming the file.
    #[test]
    fn images_are_read_by_content_and_errors_name_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("000000.jpg");
        let rgb = RgbImage::from_fn(6, 4, |x, y| image::Rgb([x as u8 * 40, y as u8 * 60, 7]));
        rgb.save_with_format(&path, image::ImageFormat::Png)
            .unwrap();
        assert_eq!(image_size(&path).unwrap(), (6, 4));
        let bytes = read_bytes(&path).unwrap();
        assert_eq!(decode_rgb(&bytes, "000000.jpg", (6, 4)).unwrap(), rgb);
        let error =
            decode_rgb(&bytes[..bytes.len() - 20], "Camera_B1/000000.jpg", (6, 4)).unwrap_err();
        assert!(
            format!("{error:#}").starts_with("Camera_B1/000000.jpg: cannot decode the image"),
            "{error:#}"
        );
        let error = decode_mask(&bytes, "mask/000000.png", true, (8, 8)).unwrap_err();
        assert!(
            format!("{error:#}").contains("mask/000000.png"),
            "{error:#}"
        );
    }

    #[test]
    fn relative_paths_stay_inside() {
        let root = Path::new("/data");
        let file = Path::new("/data/annots.npy");
        assert_eq!(
            join_relative(root, "Camera_B1/000000.jpg", file, "ims").unwrap(),
            PathBuf::from("/data/Camera_B1/000000.jpg")
        );
        assert!(join_relative(root, "../etc/passwd", file, "ims").is_err());
        assert!(join_relative(root, "/etc/passwd", file, "ims").is_err());
    }
}
