//! Cameras that generate the same view rays as Blender.
//!
//! **Perspective** (Cycles `blender_camera_viewplane`): the fitted sensor
//! dimension — `sensor_width_mm` for `auto` (spanning the larger image side)
//! and `horizontal`, `sensor_height_mm` for `vertical` — spans `sensor/f` at
//! unit distance; the other side follows the image aspect. Lens shift moves
//! the view plane by `shift × sensor/f` (shift is in units of the fitted
//! side's full extent, as Blender's "Shift X/Y" in units of the larger
//! dimension). The camera looks along its local −Z with +Y up. Pixel
//! `(x, y)` is measured from the top-left corner, pixel centres at `+0.5`, so
//! row 0 is the top row, as written to EXR.
//!
//! **Equirectangular**: world-aligned, mapped as Cycles maps an Environment
//! Texture (`direction_to_equirectangular`): `u = 0.5 − atan2(d_y, d_x)/2π`,
//! `v = 1 − acos(d_z)/π` with `v = 0` the bottom row. So the centre column
//! looks along +X, the top row straight up, and an image rendered with it can
//! be used directly as a World texture.

use crate::scene::{Camera, Orientation, SensorFit, quat_wxyz};
use glam::{DMat3, DVec3};
use std::f64::consts::PI;

/// A camera ready to generate rays.
#[derive(Debug, Clone)]
pub struct CameraRays {
    /// Image width, px.
    pub width: usize,
    /// Image height, px.
    pub height: usize,
    /// Eye position, m.
    pub position: DVec3,
    /// Where rays start along their direction, m.
    pub clip_start: f64,
    /// Where rays end, m (∞ allowed).
    pub clip_end: f64,
    inv_width: f64,
    inv_height: f64,
    kind: Kind,
}

#[derive(Debug, Clone)]
enum Kind {
    Perspective {
        /// Columns: camera right (+X), up (+Y), back (+Z) in world space.
        basis: DMat3,
        /// View-plane extent at unit distance: full width, full height.
        plane: (f64, f64),
        /// View-plane offset at unit distance from lens shift.
        shift: (f64, f64),
    },
    Equirectangular,
}

impl CameraRays {
    /// Builds the ray generator from a validated scene camera.
    pub fn new(camera: &Camera) -> CameraRays {
        match camera {
            Camera::Perspective(c) => {
                let (w, h) = (c.resolution[0] as f64, c.resolution[1] as f64);
                let position = DVec3::from(c.position);
                let basis = match &c.orientation {
                    Orientation::LookAt { target, up } => {
                        let fwd = (DVec3::from(*target) - position).normalize();
                        let back = -fwd;
                        let right = DVec3::from(*up).cross(back).normalize();
                        let upv = back.cross(right);
                        DMat3::from_cols(right, upv, back)
                    }
                    Orientation::QuaternionWxyz(q) => DMat3::from_quat(quat_wxyz(*q)),
                };
                let horizontal = match c.sensor_fit {
                    SensorFit::Auto => w >= h,
                    SensorFit::Horizontal => true,
                    SensorFit::Vertical => false,
                };
                let sensor = if c.sensor_fit == SensorFit::Vertical {
                    c.sensor_height_mm
                } else {
                    c.sensor_width_mm
                };
                let extent = sensor / c.focal_length_mm;
                let plane = if horizontal {
                    (extent, extent * h / w)
                } else {
                    (extent * w / h, extent)
                };
                let shift = (c.shift_x * extent, c.shift_y * extent);
                CameraRays {
                    width: c.resolution[0] as usize,
                    height: c.resolution[1] as usize,
                    position,
                    clip_start: c.clip_start_m,
                    clip_end: c.clip_end_m.unwrap_or(f64::INFINITY),
                    inv_width: 1.0 / w,
                    inv_height: 1.0 / h,
                    kind: Kind::Perspective { basis, plane, shift },
                }
            }
            Camera::Equirectangular(c) => CameraRays {
                width: c.resolution[0] as usize,
                height: c.resolution[1] as usize,
                position: DVec3::from(c.position),
                clip_start: 0.0,
                clip_end: c.clip_end_m.unwrap_or(f64::INFINITY),
                inv_width: 1.0 / f64::from(c.resolution[0]),
                inv_height: 1.0 / f64::from(c.resolution[1]),
                kind: Kind::Equirectangular,
            },
        }
    }

    /// Unit direction of the ray through image point `(x, y)` (pixels from the
    /// top-left corner; the centre of pixel (i, j) is (i + 0.5, j + 0.5)).
    #[inline]
    pub fn direction(&self, x: f64, y: f64) -> DVec3 {
        match &self.kind {
            Kind::Perspective { basis, plane, shift } => {
                let u = x * self.inv_width - 0.5;
                let v = 0.5 - y * self.inv_height;
                let local = DVec3::new(u * plane.0 + shift.0, v * plane.1 + shift.1, -1.0);
                (*basis * local).normalize()
            }
            Kind::Equirectangular => {
                let theta = PI * y * self.inv_height;
                let phi = PI - 2.0 * PI * x * self.inv_width;
                let (st, ct) = theta.sin_cos();
                let (sp, cp) = phi.sin_cos();
                DVec3::new(st * cp, st * sp, ct)
            }
        }
    }

    /// For a perspective camera, the ray's direction through image point
    /// `(x, y)` before it is normalised: `D₀ + x·Dₓ + y·D_y`, returned as
    /// `(D₀, Dₓ, D_y)`. Any quantity linear in the direction (the normal of
    /// the plane through a point and the ray, say) is then affine in the
    /// image point. `None` for an equirectangular camera.
    pub fn affine_direction(&self) -> Option<(DVec3, DVec3, DVec3)> {
        match &self.kind {
            Kind::Perspective { basis, plane, shift } => {
                let d0 = *basis * DVec3::new(-0.5 * plane.0 + shift.0, 0.5 * plane.1 + shift.1, -1.0);
                let dx = *basis * DVec3::new(self.inv_width * plane.0, 0.0, 0.0);
                let dy = *basis * DVec3::new(0.0, -self.inv_height * plane.1, 0.0);
                Some((d0, dx, dy))
            }
            Kind::Equirectangular => None,
        }
    }

    /// Image point `(x, y)` in pixels (as [`Self::direction`] takes them) of the world
    /// point `p`; `None` behind the camera or for an equirectangular camera.
    pub fn project(&self, p: DVec3) -> Option<(f64, f64)> {
        match &self.kind {
            Kind::Perspective { basis, plane, shift } => {
                let local = basis.transpose() * (p - self.position);
                if local.z >= -1e-300 || !local.is_finite() {
                    return None;
                }
                let (a, b) = (-local.x / local.z, -local.y / local.z);
                let u = (a - shift.0) / plane.0;
                let v = (b - shift.1) / plane.1;
                Some(((u + 0.5) / self.inv_width, (0.5 - v) / self.inv_height))
            }
            Kind::Equirectangular => None,
        }
    }

    /// Distance along the unit ray `dir` where the ray starts (Blender's clip
    /// start is a distance along the view axis for perspective cameras).
    #[inline]
    pub fn start_distance(&self, dir: DVec3) -> f64 {
        match &self.kind {
            Kind::Perspective { basis, .. } if self.clip_start > 0.0 => {
                let along_axis = -dir.dot(basis.z_axis);
                self.clip_start / along_axis.max(1e-12)
            }
            _ => self.clip_start,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{EquirectangularCamera, PerspectiveCamera};

    fn persp(res: [u32; 2], fit: SensorFit, shift: (f64, f64)) -> CameraRays {
        CameraRays::new(&Camera::Perspective(PerspectiveCamera {
            position: [0.0, 0.0, 0.0],
            orientation: Orientation::LookAt {
                target: [0.0, 1.0, 0.0],
                up: [0.0, 0.0, 1.0],
            },
            focal_length_mm: 50.0,
            sensor_width_mm: 36.0,
            sensor_height_mm: 24.0,
            sensor_fit: fit,
            shift_x: shift.0,
            shift_y: shift.1,
            resolution: res,
            clip_start_m: 0.0,
            clip_end_m: None,
        }))
    }

    #[test]
    fn project_inverts_direction() {
        for (fit, shift) in [
            (SensorFit::Auto, (0.0, 0.0)),
            (SensorFit::Vertical, (0.1, -0.2)),
            (SensorFit::Horizontal, (-0.05, 0.3)),
        ] {
            let cam = persp([64, 36], fit, shift);
            for &(x, y) in &[(0.5, 0.5), (31.7, 12.25), (63.9, 35.1), (-3.0, 40.0)] {
                let d = cam.direction(x, y);
                let (px, py) = cam.project(cam.position + d * 7.5).unwrap();
                assert!((px - x).abs() < 1e-9 && (py - y).abs() < 1e-9, "{fit:?}: ({x}, {y}) → ({px}, {py})");
            }
            assert!(cam.project(cam.position - cam.direction(10.0, 10.0)).is_none());
        }
    }

    #[test]
    fn affine_direction_is_the_unnormalised_direction() {
        for (fit, shift) in [(SensorFit::Auto, (0.0, 0.0)), (SensorFit::Vertical, (0.1, -0.2))] {
            let cam = persp([64, 36], fit, shift);
            let (d0, dx, dy) = cam.affine_direction().unwrap();
            for &(x, y) in &[(0.5, 0.5), (31.7, 12.25), (63.9, 35.1), (-3.0, 40.0)] {
                let d = (d0 + dx * x + dy * y).normalize();
                assert!((d - cam.direction(x, y)).length() < 1e-14, "{fit:?}: ({x}, {y})");
            }
        }
    }
    #[test]
    fn horizontal_field_of_view_is_blenders() {
        // 36 mm sensor, 50 mm lens: horizontal FOV 2·atan(18/50) = 39.5978°.
        let c = persp([1920, 1080], SensorFit::Auto, (0.0, 0.0));
        let left = c.direction(0.0, 540.0);
        let right = c.direction(1920.0, 540.0);
        let fov = left.angle_between(right).to_degrees();
        assert!((fov - 2.0 * (18.0f64 / 50.0).atan().to_degrees()).abs() < 1e-9);
        // Looks along +Y (target), top of the image is +Z.
        assert!((c.direction(960.0, 540.0) - DVec3::Y).length() < 1e-12);
        assert!(c.direction(960.0, 0.0).z > 0.0);
        assert!(c.direction(1920.0, 540.0).x > 0.0);
    }

    #[test]
    fn portrait_auto_fit_uses_width_for_the_long_side() {
        let c = persp([1080, 1920], SensorFit::Auto, (0.0, 0.0));
        let fov = c.direction(540.0, 0.0).angle_between(c.direction(540.0, 1920.0)).to_degrees();
        assert!((fov - 2.0 * (18.0f64 / 50.0).atan().to_degrees()).abs() < 1e-9);
        let v = persp([1000, 500], SensorFit::Vertical, (0.0, 0.0));
        let fov = v.direction(500.0, 0.0).angle_between(v.direction(500.0, 500.0)).to_degrees();
        assert!((fov - 2.0 * (12.0f64 / 50.0).atan().to_degrees()).abs() < 1e-9);
    }

    #[test]
    fn shift_moves_the_centre_by_shift_times_sensor_over_focal() {
        let c = persp([1920, 1080], SensorFit::Auto, (0.1, -0.2));
        let d = c.direction(960.0, 540.0);
        // At unit forward distance the centre ray is offset by (0.1, -0.2)·36/50.
        assert!((d.x / d.y - 0.1 * 0.72).abs() < 1e-12);
        assert!((d.z / d.y + 0.2 * 0.72).abs() < 1e-12);
    }

    #[test]
    fn equirectangular_matches_cycles_environment_mapping() {
        let c = CameraRays::new(&Camera::Equirectangular(EquirectangularCamera {
            position: [0.0; 3],
            resolution: [360, 180],
            clip_end_m: None,
        }));
        // Centre column → +X; quarter column → +Y; top row → up.
        assert!((c.direction(180.0, 90.0) - DVec3::X).length() < 1e-12);
        assert!((c.direction(90.0, 90.0) - DVec3::Y).length() < 1e-12);
        assert!(c.direction(10.0, 0.0).z > 0.999);
        // Invert with Cycles' formula: u = 0.5 − atan2(y, x)/2π, v = 1 − acos(z)/π.
        for &(x, y) in &[(12.5, 33.5), (300.5, 150.5), (179.5, 89.5)] {
            let d = c.direction(x, y);
            let u = 0.5 - d.y.atan2(d.x) / (2.0 * PI);
            let v = 1.0 - d.z.acos() / PI;
            assert!((u - x / 360.0).abs() < 1e-12 && (v - (1.0 - y / 180.0)).abs() < 1e-12);
        }
    }
}
