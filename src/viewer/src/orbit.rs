//! The orbit camera of the viewer: a pinhole [`Camera`] on a sphere around the avatar, given
//! by azimuth, elevation and distance in a frame whose pole is the scene's up direction, with a
//! pan of the look-at point in the view plane and intrinsics from a vertical field of view.

use seqavatar_core::camera::{Camera, Intrinsics};
use seqavatar_core::glam::DVec3;

/// The frame the orbit angles are measured in: `up` is the pole (elevation +90 degrees);
/// azimuth 0 lies along `reference`, azimuth +90 degrees along `up x reference`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrbitFrame {
    /// The point the camera looks at before panning (the avatar's centre).
    pub centre: DVec3,
    /// Unit vector, the scene's up direction.
    pub up: DVec3,
    /// Unit vector perpendicular to `up`: the direction of azimuth 0.
    pub reference: DVec3,
}

/// Where the orbit camera is, in the units the page sends (degrees, metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OrbitView {
    pub azimuth_deg: f64,
    pub elevation_deg: f64,
    /// Distance from the (panned) look-at point to the eye, metres.
    pub distance: f64,
    /// Vertical field of view, degrees.
    pub fov_deg: f64,
    /// Pan of the look-at point along the image's right and up directions, metres.
    pub pan_right: f64,
    pub pan_up: f64,
    pub width: u32,
    pub height: u32,
}

impl OrbitFrame {
    /// The frame with pole `up` (any non-zero length) and azimuth 0 towards `towards` projected
    /// onto the plane perpendicular to `up`; when `towards` is parallel to `up`, any
    /// perpendicular direction. `None` when `up` is zero or not finite.
    pub fn new(centre: DVec3, up: DVec3, towards: DVec3) -> Option<Self> {
        let up = up.try_normalize()?;
        let reference = (towards - up * towards.dot(up))
            .try_normalize()
            .unwrap_or_else(|| up.any_orthonormal_vector());
        Some(Self {
            centre,
            up,
            reference,
        })
    }

    /// Azimuth and elevation (degrees) and distance of `eye` seen from the centre: the
    /// inverse of the eye placement of [`OrbitFrame::camera`] without pan.
    pub fn angles_of(&self, eye: DVec3) -> (f64, f64, f64) {
        let offset = eye - self.centre;
        let distance = offset.length();
        let side = self.up.cross(self.reference);
        let azimuth = offset.dot(side).atan2(offset.dot(self.reference));
        let elevation = (offset.dot(self.up) / distance.max(f64::MIN_POSITIVE))
            .clamp(-1.0, 1.0)
            .asin();
        (azimuth.to_degrees(), elevation.to_degrees(), distance)
    }

    /// The camera of `view`: the eye at `distance` from the panned look-at point along the
    /// direction of (azimuth, elevation), looking at that point with `up` up in the image;
    /// square pixels with the principal point at the image centre. The elevation must stay
    /// away from the poles (the request validation keeps it within +-89 degrees), where the
    /// look-at basis is undefined.
    pub fn camera(&self, view: &OrbitView) -> Camera {
        let (azimuth, elevation) = (
            view.azimuth_deg.to_radians(),
            view.elevation_deg.to_radians(),
        );
        let side = self.up.cross(self.reference);
        let horizontal = self.reference * azimuth.cos() + side * azimuth.sin();
        let direction = horizontal * elevation.cos() + self.up * elevation.sin();
        // The image's right and up directions for this direction (the camera looks along
        // -direction): right = -direction x up, normalised; image up = right x -direction.
        let right = self.up.cross(direction).normalize();
        let image_up = direction.cross(right);
        let target = self.centre + right * view.pan_right + image_up * view.pan_up;
        let eye = target + direction * view.distance;
        let focal = 0.5 * f64::from(view.height) / (0.5 * view.fov_deg.to_radians()).tan();
        Camera::look_at(
            view.width,
            view.height,
            Intrinsics {
                fx: focal,
                fy: focal,
                cx: 0.5 * f64::from(view.width),
                cy: 0.5 * f64::from(view.height),
            },
            eye,
            target,
            self.up,
        )
    }
}

/// `degrees` wrapped into `[0, 360)` (`rem_euclid` alone rounds tiny negative angles up to
/// 360).
pub fn wrap_degrees(degrees: f64) -> f64 {
    let wrapped = degrees.rem_euclid(360.0);
    if wrapped >= 360.0 { 0.0 } else { wrapped }
}

/// The vertical field of view (degrees) of `camera`.
pub fn vertical_fov_deg(camera: &Camera) -> f64 {
    (2.0 * (0.5 * f64::from(camera.height) / camera.intrinsics.fy).atan()).to_degrees()
}

/// The scene's up direction seen by a set of cameras: the mean of their image-up directions
/// (OpenCV cameras: -y of each camera, the negated second row of the world-to-camera
/// rotation). `None` without cameras or when the directions cancel.
pub fn mean_image_up(cameras: &[Camera]) -> Option<DVec3> {
    cameras
        .iter()
        .map(|camera| -camera.rotation.row(1))
        .sum::<DVec3>()
        .try_normalize()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame() -> OrbitFrame {
        OrbitFrame::new(
            DVec3::new(0.2, 1.0, -0.5),
            DVec3::new(0.0, 2.0, 0.0),
            DVec3::new(0.0, 0.3, 3.0),
        )
        .unwrap()
    }

    fn view(azimuth_deg: f64, elevation_deg: f64) -> OrbitView {
        OrbitView {
            azimuth_deg,
            elevation_deg,
            distance: 2.5,
            fov_deg: 40.0,
            pan_right: 0.0,
            pan_up: 0.0,
            width: 320,
            height: 200,
        }
    }

    #[test]
    fn the_frame_is_orthonormal_and_its_reference_is_the_projected_direction() {
        let frame = frame();
        assert!((frame.up - DVec3::Y).length() < 1e-15);
        assert!((frame.reference - DVec3::Z).length() < 1e-15);
        // Towards parallel to up: any perpendicular unit vector.
        let polar = OrbitFrame::new(DVec3::ZERO, DVec3::Y, DVec3::Y * 4.0).unwrap();
        assert!(polar.reference.dot(DVec3::Y).abs() < 1e-15);
        assert!((polar.reference.length() - 1.0).abs() < 1e-15);
        assert!(OrbitFrame::new(DVec3::ZERO, DVec3::ZERO, DVec3::X).is_none());
        assert!(OrbitFrame::new(DVec3::ZERO, DVec3::NAN, DVec3::X).is_none());
    }

    /// Closed forms: the eye of (az, el, d) is centre + d (cos el (cos az Z + sin az X) +
    /// sin el Y) for up Y and reference Z (side = Y x Z = X); the centre projects to the
    /// principal point, the centre + up to above it, and a point at half the field of view
    /// above the optical axis to the top edge.
    #[test]
    fn the_orbit_camera_matches_the_closed_form() {
        let frame = frame();
        for (az, el) in [
            (0.0, 0.0),
            (90.0, 0.0),
            (-135.0, 30.0),
            (400.0, -89.0),
            (10.0, 89.0),
        ] {
            let orbit = view(az, el);
            let camera = frame.camera(&orbit);
            camera.validate().unwrap();
            let (a, e) = (f64::to_radians(az), f64::to_radians(el));
            let expected_eye = frame.centre
                + 2.5 * (e.cos() * (a.cos() * DVec3::Z + a.sin() * DVec3::X) + e.sin() * DVec3::Y);
            assert!(
                (camera.center() - expected_eye).length() < 1e-12,
                "az {az} el {el}: eye {} expected {expected_eye}",
                camera.center()
            );
            let centre = camera.project(frame.centre).unwrap();
            assert!((centre.x - 160.0).abs() < 1e-9 && (centre.y - 100.0).abs() < 1e-9);
            let above = camera.project(frame.centre + DVec3::Y * 0.01).unwrap();
            assert!(
                above.y < centre.y,
                "az {az} el {el}: up is not up in the image"
            );
            // The point at the top edge: fov / 2 above the optical axis, at the centre's depth.
            let forward = (frame.centre - camera.center()).normalize();
            let image_up = -camera.rotation.row(1);
            let top = frame.centre + image_up * 2.5 * f64::to_radians(20.0).tan();
            assert!(image_up.dot(forward).abs() < 1e-12);
            assert!((camera.project(top).unwrap().y - 0.0).abs() < 1e-9);
            // angles_of inverts the placement (azimuth modulo 360).
            let (az2, el2, d2) = frame.angles_of(camera.center());
            let wrapped = (az2 - az).rem_euclid(360.0);
            assert!(wrapped < 1e-9 || 360.0 - wrapped < 1e-9, "az {az} -> {az2}");
            assert!((el2 - el).abs() < 1e-9 && (d2 - 2.5).abs() < 1e-12);
        }
    }

    #[test]
    fn panning_moves_the_look_at_point_in_the_image_plane() {
        let frame = frame();
        let mut orbit = view(30.0, 20.0);
        orbit.pan_right = 0.3;
        orbit.pan_up = -0.1;
        let camera = frame.camera(&orbit);
        let right = camera.rotation.row(0);
        let image_up = -camera.rotation.row(1);
        let target = frame.centre + right * 0.3 - image_up * 0.1;
        let projected = camera.project(target).unwrap();
        assert!((projected.x - 160.0).abs() < 1e-9 && (projected.y - 100.0).abs() < 1e-9);
        // The pan keeps the distance to the look-at point.
        assert!((camera.center().distance(target) - 2.5).abs() < 1e-12);
        // The centre itself now lies left of and above the image centre.
        let centre = camera.project(frame.centre).unwrap();
        assert!(centre.x < 160.0 && centre.y < 100.0);
    }

    #[test]
    fn the_field_of_view_and_up_of_cameras_are_recovered() {
        let frame = frame();
        let camera = frame.camera(&view(15.0, 10.0));
        assert!((vertical_fov_deg(&camera) - 40.0).abs() < 1e-12);
        let up = mean_image_up(&[camera.clone(), frame.camera(&view(-100.0, -30.0))]).unwrap();
        // Both cameras roll-free about the pole: their mean image up leans towards the pole.
        assert!(up.dot(DVec3::Y) > 0.8);
        assert!(mean_image_up(&[]).is_none());
    }

    #[test]
    fn angles_wrap_into_one_turn() {
        assert_eq!(wrap_degrees(-1e-15), 0.0);
        assert_eq!(wrap_degrees(360.0), 0.0);
        assert_eq!(wrap_degrees(-90.0), 270.0);
        assert_eq!(wrap_degrees(725.0), 5.0);
    }
}
