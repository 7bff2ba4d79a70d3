//! Render-only entry points: Gaussians and a camera to an 8-bit RGB image or a PNG file.

use std::path::Path;

use seqavatar_core::camera::Camera;

use super::{GaussianSet, RasterOptions, SplatDiagnostics, SplatError, cpu};
use crate::scalar::Scalar;

/// Renders one camera on the `cpu` backend and quantises the colour to 8 bits
/// (`round(255 clamp(c, 0, 1))`).
pub fn render_rgb8<S: Scalar>(
    gaussians: &GaussianSet<'_, S>,
    camera: &Camera,
    options: &RasterOptions,
) -> Result<(image::RgbImage, SplatDiagnostics), SplatError> {
    let forward = cpu::forward(gaussians, std::slice::from_ref(camera), options)?;
    let rendered = &forward.images[0];
    let bytes = rendered
        .colour
        .iter()
        .map(|c| (c.to_f64().clamp(0.0, 1.0) * 255.0).round() as u8)
        .collect();
    let image = image::RgbImage::from_raw(rendered.width, rendered.height, bytes)
        .expect("the renderer returns width * height * 3 values");
    Ok((image, forward.diagnostics[0]))
}

/// Renders one camera and writes it as a PNG file.
pub fn render_png<S: Scalar>(
    gaussians: &GaussianSet<'_, S>,
    camera: &Camera,
    options: &RasterOptions,
    path: &Path,
) -> Result<SplatDiagnostics, SplatError> {
    let (image, diagnostics) = render_rgb8(gaussians, camera, options)?;
    image
        .save_with_format(path, image::ImageFormat::Png)
        .map_err(|error| SplatError::Png {
            path: path.to_path_buf(),
            error,
        })?;
    Ok(diagnostics)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::splat::scene::{standard_camera, standard_scene};

    #[test]
    fn png_round_trips_the_quantised_render() {
        let scene = standard_scene(2_000, 3);
        let gaussians = scene.gaussians.convert::<f32>();
        let options = RasterOptions {
            background: [1.0, 1.0, 1.0],
            smooth_cutoff: false,
        };
        let camera = standard_camera();
        let (image, diagnostics) = render_rgb8(&gaussians.view(), &camera, &options).unwrap();
        assert!(diagnostics.visible > 1_500, "{diagnostics:?}");
        // White background in the corner, Gaussians in the middle.
        assert_eq!(image.get_pixel(0, 0).0, [255, 255, 255]);
        assert_ne!(image.get_pixel(256, 256).0, [255, 255, 255]);
        let path = std::env::temp_dir().join(format!("seqavatar-splat-{}.png", std::process::id()));
        render_png(&gaussians.view(), &camera, &options, &path).unwrap();
        let read = image::open(&path).unwrap().to_rgb8();
        std::fs::remove_file(&path).unwrap();
        assert_eq!(read, image);
        let missing = std::env::temp_dir()
            .join("no-such-directory-seqavatar")
            .join("x.png");
        assert!(matches!(
            render_png(&gaussians.view(), &camera, &options, &missing),
            Err(SplatError::Png { .. })
        ));
    }
}
