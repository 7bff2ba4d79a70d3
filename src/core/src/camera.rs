//! The pinhole camera model, the one place camera math lives.
//!
//! Conventions (see ARCHITECTURE.md, "Invariants"):
//! - World units are metres. Camera axes follow OpenCV: x right, y down, z forward.
//! - Extrinsics are world-to-camera: `x_cam = R x_world + t`.
//! - Pixel coordinates are continuous: pixel `(col, row)` covers `[col, col+1) x [row, row+1)`
//!   and its centre is `(col + 0.5, row + 0.5)`. OpenCV calibrations put pixel centres at
//!   integers, so [`Camera::from_opencv`] adds 0.5 to the principal point. In this convention
//!   rescaling an image by `s` multiplies `fx, fy, cx, cy` by `s` exactly.
//! - Distortion is OpenCV's `(k1, k2, p1, p2, k3)` on normalised coordinates.

use glam::{DMat3, DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics in the continuous pixel convention.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Intrinsics {
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

/// A calibrated camera: image size, intrinsics, world-to-camera pose and lens distortion.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    pub width: u32,
    pub height: u32,
    pub intrinsics: Intrinsics,
    /// World-to-camera rotation.
    pub rotation: DMat3,
    /// World-to-camera translation (metres).
    pub translation: DVec3,
    /// OpenCV `(k1, k2, p1, p2, k3)`; zeros for an ideal pinhole.
    pub distortion: [f64; 5],
}

/// Why a camera description was rejected.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum CameraError {
    #[error("image size {width}x{height} is empty")]
    EmptyImage { width: u32, height: u32 },
    #[error("focal lengths must be positive and finite, got fx={fx} fy={fy}")]
    BadFocal { fx: f64, fy: f64 },
    #[error("a camera value is not finite")]
    NotFinite,
    #[error("rotation is not orthonormal with determinant +1 (error {error:.3e})")]
    NotARotation { error: f64 },
}

impl Camera {
    /// Builds a camera from an OpenCV calibration (`K` with integer pixel centres).
    pub fn from_opencv(
        width: u32,
        height: u32,
        k: [[f64; 3]; 3],
        rotation: DMat3,
        translation: DVec3,
        distortion: [f64; 5],
    ) -> Result<Self, CameraError> {
        let camera = Self {
            width,
            height,
            intrinsics: Intrinsics {
                fx: k[0][0],
                fy: k[1][1],
                cx: k[0][2] + 0.5,
                cy: k[1][2] + 0.5,
            },
            rotation,
            translation,
            distortion,
        };
        camera.validate()?;
        Ok(camera)
    }

    /// A distortion-free camera at `eye` looking at `target`, with `up` roughly up in the image.
    pub fn look_at(
        width: u32,
        height: u32,
        intrinsics: Intrinsics,
        eye: DVec3,
        target: DVec3,
        up: DVec3,
    ) -> Self {
        let forward = (target - eye).normalize();
        // OpenCV axes: y points down in the image, so "down" is -up projected.
        let right = forward.cross(up).normalize();
        let down = forward.cross(right);
        // Rows of R are the camera axes expressed in world coordinates.
        let rotation = DMat3::from_cols(right, down, forward).transpose();
        let translation = -(rotation * eye);
        Self {
            width,
            height,
            intrinsics,
            rotation,
            translation,
            distortion: [0.0; 5],
        }
    }

    /// Checks sizes, finiteness and that the rotation is a proper rotation.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::EmptyImage {
                width: self.width,
                height: self.height,
            });
        }
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        let all = [fx, fy, cx, cy]
            .into_iter()
            .chain(self.rotation.to_cols_array())
            .chain(self.translation.to_array())
            .chain(self.distortion);
        if all.into_iter().any(|x| !x.is_finite()) {
            return Err(CameraError::NotFinite);
        }
        if !(fx > 0.0 && fy > 0.0) {
            return Err(CameraError::BadFocal { fx, fy });
        }
        let ortho = self.rotation * self.rotation.transpose() - DMat3::IDENTITY;
        let error = ortho
            .to_cols_array()
            .iter()
            .fold(0.0_f64, |m, x| m.max(x.abs()))
            .max((self.rotation.determinant() - 1.0).abs());
        if error > 1e-4 {
            return Err(CameraError::NotARotation { error });
        }
        Ok(())
    }

    /// World point to camera coordinates.
    pub fn world_to_camera(&self, point: DVec3) -> DVec3 {
        self.rotation * point + self.translation
    }

    /// The same camera in a world whose origin is the point `origin` of this camera's world
    /// (`x_new = x - origin`): `t' = t + R origin`. With `-origin` it maps back.
    pub fn with_origin_at(&self, origin: DVec3) -> Self {
        Self {
            translation: self.translation + self.rotation * origin,
            ..self.clone()
        }
    }

    /// Camera centre in world coordinates.
    pub fn center(&self) -> DVec3 {
        -(self.rotation.transpose() * self.translation)
    }

    /// Projects a world point to continuous pixel coordinates, ignoring distortion.
    /// `None` for points at or behind the camera plane.
    pub fn project(&self, point: DVec3) -> Option<DVec2> {
        let p = self.world_to_camera(point);
        if p.z <= 0.0 {
            return None;
        }
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        Some(DVec2::new(fx * p.x / p.z + cx, fy * p.y / p.z + cy))
    }

    /// Projects a world point through the lens distortion to continuous pixel coordinates.
    pub fn project_distorted(&self, point: DVec3) -> Option<DVec2> {
        let p = self.world_to_camera(point);
        if p.z <= 0.0 {
            return None;
        }
        let d = self.distort_normalized(DVec2::new(p.x / p.z, p.y / p.z));
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        Some(DVec2::new(fx * d.x + cx, fy * d.y + cy))
    }

    /// OpenCV's distortion model applied to normalised image coordinates.
    pub fn distort_normalized(&self, n: DVec2) -> DVec2 {
        let [k1, k2, p1, p2, k3] = self.distortion;
        let r2 = n.length_squared();
        let radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3));
        DVec2::new(
            n.x * radial + 2.0 * p1 * n.x * n.y + p2 * (r2 + 2.0 * n.x * n.x),
            n.y * radial + p1 * (r2 + 2.0 * n.y * n.y) + 2.0 * p2 * n.x * n.y,
        )
    }

    /// For a pixel of the undistorted image, the continuous pixel position in the distorted
    /// (captured) image to sample. Undistorting an image is a gather with this map.
    pub fn undistort_source_pixel(&self, undistorted_pixel: DVec2) -> DVec2 {
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        let n = DVec2::new(
            (undistorted_pixel.x - cx) / fx,
            (undistorted_pixel.y - cy) / fy,
        );
        let d = self.distort_normalized(n);
        DVec2::new(fx * d.x + cx, fy * d.y + cy)
    }

    /// The same camera for an image rescaled to `round(width * factor)` pixels wide.
    /// The exact per-axis ratio of the rounded sizes scales the intrinsics.
    pub fn rescaled(&self, factor: f64) -> Self {
        let width = ((self.width as f64 * factor).round() as u32).max(1);
        let height = ((self.height as f64 * factor).round() as u32).max(1);
        self.resized(width, height)
    }

    /// The same camera for an image resampled to `width x height` pixels.
    pub fn resized(&self, width: u32, height: u32) -> Self {
        let sx = width as f64 / self.width as f64;
        let sy = height as f64 / self.height as f64;
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        Self {
            width,
            height,
            intrinsics: Intrinsics {
                fx: fx * sx,
                fy: fy * sy,
                cx: cx * sx,
                cy: cy * sy,
            },
            ..self.clone()
        }
    }

    /// Intrinsics as a row-major 3x3 matrix (continuous pixel convention).
    pub fn k_matrix(&self) -> [[f64; 3]; 3] {
        let Intrinsics { fx, fy, cx, cy } = self.intrinsics;
        [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rotation::axis_angle_to_matrix;

    fn camera() -> Camera {
        Camera::from_opencv(
            640,
            480,
            [[500.0, 0.0, 319.5], [0.0, 510.0, 239.5], [0.0, 0.0, 1.0]],
            axis_angle_to_matrix(DVec3::new(0.1, -0.2, 0.05)),
            DVec3::new(0.1, -0.3, 3.0),
            [0.0; 5],
        )
        .unwrap()
    }

    #[test]
    fn opencv_principal_point_is_the_image_centre() {
        let cam = camera();
        // A point on the optical axis lands on the middle of the 640x480 image.
        let on_axis = cam.rotation.transpose() * (DVec3::new(0.0, 0.0, 2.0) - cam.translation);
        let px = cam.project(on_axis).unwrap();
        assert!((px - DVec2::new(320.0, 240.0)).length() < 1e-9);
    }

    #[test]
    fn rescaling_keeps_relative_position() {
        let cam = camera();
        let p = DVec3::new(0.2, 0.1, 0.5);
        let full = cam.project(p).unwrap();
        let half = cam.rescaled(0.5);
        assert_eq!((half.width, half.height), (320, 240));
        let px = half.project(p).unwrap();
        assert!((px - full * 0.5).length() < 1e-9);
    }

    /// Moving the origin moves every world point and the centre with it: projections stay.
    #[test]
    fn a_camera_with_another_origin_projects_the_moved_points_alike() {
        let intr = Intrinsics {
            fx: 100.0,
            fy: 90.0,
            cx: 50.0,
            cy: 40.0,
        };
        let eye = DVec3::new(3.0, 1.0, 0.5);
        let camera = Camera::look_at(100, 80, intr, eye, DVec3::new(0.0, 1.2, 0.0), DVec3::Y);
        let origin = DVec3::new(10_000.0, -3.0, 0.25);
        let moved = camera.with_origin_at(origin);
        assert!((moved.center() - (eye - origin)).length() < 1e-9);
        let point = DVec3::new(0.1, 1.5, -0.2);
        let (a, b) = (
            camera.project(point).unwrap(),
            moved.project(point - origin).unwrap(),
        );
        assert!((a - b).length() < 1e-9, "{a} {b}");
        let back = moved.with_origin_at(-origin);
        assert!((back.translation - camera.translation).length() < 1e-9);
    }

    #[test]
    fn look_at_centres_the_target_and_keeps_up_up() {
        let intr = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 50.0,
            cy: 50.0,
        };
        let cam = Camera::look_at(
            100,
            100,
            intr,
            DVec3::new(3.0, 1.0, 0.0),
            DVec3::new(0.0, 1.0, 0.0),
            DVec3::Y,
        );
        cam.validate().unwrap();
        assert!(
            (cam.project(DVec3::new(0.0, 1.0, 0.0)).unwrap() - DVec2::new(50.0, 50.0)).length()
                < 1e-9
        );
        // A point above the target appears higher in the image (smaller row).
        assert!(cam.project(DVec3::new(0.0, 1.5, 0.0)).unwrap().y < 50.0);
        assert!((cam.center() - DVec3::new(3.0, 1.0, 0.0)).length() < 1e-12);
    }

    #[test]
    fn behind_camera_does_not_project_and_bad_cameras_are_rejected() {
        let cam = camera();
        assert!(
            cam.project(cam.center() - cam.rotation.row(2) * 1.0)
                .is_none()
        );
        let mut bad = cam.clone();
        bad.intrinsics.fx = f64::NAN;
        assert_eq!(bad.validate(), Err(CameraError::NotFinite));
        let mut bad = cam.clone();
        bad.rotation = DMat3::from_diagonal(DVec3::new(1.0, 1.0, -1.0));
        assert!(matches!(
            bad.validate(),
            Err(CameraError::NotARotation { .. })
        ));
    }

    #[test]
    fn undistortion_map_inverts_distortion_for_a_point() {
        let mut cam = camera();
        cam.distortion = [-0.2, 0.05, 0.001, -0.002, 0.0];
        let p = DVec3::new(0.3, -0.2, 0.4);
        let ideal = cam.project(p).unwrap();
        let captured = cam.project_distorted(p).unwrap();
        assert!((cam.undistort_source_pixel(ideal) - captured).length() < 1e-9);
    }
}
