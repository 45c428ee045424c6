//! Sun and sky: Klassen's spectral sun and sky over a spherical earth with a
//! haze shell (`klassen`), and a layered exponential atmosphere with ozone and
//! twilight (`atmosphere`). [`texture`] turns either into a world texture for
//! Blender, and [`SunLamp`] gives the matching sun lamp.

pub mod atmosphere;
pub mod klassen;
pub mod texture;

use glam::DVec3;
use serde::{Deserialize, Serialize};

/// The values for a Blender sun lamp that matches a sky: direction, colour and
/// strength from the same model as the sky.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SunLamp {
    /// Unit vector from the observer towards the sun (+Z up).
    pub direction_to_sun: [f64; 3],
    /// Sun elevation above the horizon, degrees.
    pub elevation_deg: f64,
    /// Sun azimuth, degrees, measured from +Y towards +X (compass bearing with +Y north).
    pub azimuth_deg: f64,
    /// Blender object rotation (XYZ Euler, radians) that points a sun lamp's
    /// local −Z along the sunlight (away from the sun).
    pub rotation_euler_xyz_rad: [f64; 3],
    /// Linear Rec.709 colour, max channel 1.
    pub color: [f64; 3],
    /// Blender's Strength: irradiance of the brightest channel, W·m⁻².
    pub strength_w_m2: f64,
    /// RGB irradiance after the atmosphere, W·m⁻² per channel (color × strength).
    pub rgb_irradiance_w_m2: [f64; 3],
    /// Angular diameter, degrees (Blender's Angle).
    pub angle_deg: f64,
}

impl SunLamp {
    /// The lamp for a sun in `direction_to_sun` with RGB irradiance `rgb` (W·m⁻²) and
    /// angular diameter `diameter_rad`.
    pub fn new(direction_to_sun: DVec3, rgb: [f64; 3], diameter_rad: f64) -> SunLamp {
        let d = direction_to_sun.normalize();
        let elevation = d.z.clamp(-1.0, 1.0).asin();
        let azimuth = d.x.atan2(d.y);
        let strength = rgb.iter().fold(0.0f64, |a, b| a.max(*b)).max(0.0);
        let color = if strength > 0.0 {
            rgb.map(|v| (v / strength).max(0.0))
        } else {
            [1.0; 3]
        };
        // Rotating local −Z by Rx(α) then Rz(β): Rx(α)(0,0,−1) = (0, sin α, −cos α);
        // Rz(β) turns it to (−sin β sin α, cos β sin α, −cos α). Setting this equal
        // to −d gives cos α = d.z, and (sin β, cos β) ∝ (d.x, −d.y)/sin α.
        let alpha = d.z.clamp(-1.0, 1.0).acos();
        let beta = if alpha.sin().abs() > 1e-15 { d.x.atan2(-d.y) } else { 0.0 };
        SunLamp {
            direction_to_sun: d.to_array(),
            elevation_deg: elevation.to_degrees(),
            azimuth_deg: azimuth.to_degrees(),
            rotation_euler_xyz_rad: [alpha, 0.0, beta],
            color,
            strength_w_m2: strength,
            rgb_irradiance_w_m2: rgb,
            angle_deg: diameter_rad.to_degrees(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{DMat3, DQuat, EulerRot};

    #[test]
    fn lamp_rotation_points_minus_z_along_the_sunlight() {
        for d in [
            DVec3::new(0.3, 0.8, 0.5),
            DVec3::new(-0.7, 0.1, 0.2),
            DVec3::new(0.0, 0.0, 1.0),
            DVec3::new(0.5, -0.5, -0.1),
        ] {
            let lamp = SunLamp::new(d, [1.0, 0.9, 0.8], 0.01);
            let r = lamp.rotation_euler_xyz_rad;
            // Blender's XYZ Euler: R = Rz · Ry · Rx.
            let m = DMat3::from_quat(DQuat::from_euler(EulerRot::ZYX, r[2], r[1], r[0]));
            let light_travel = m * DVec3::new(0.0, 0.0, -1.0);
            assert!((light_travel + d.normalize()).length() < 1e-12, "{d}: {light_travel}");
        }
        let lamp = SunLamp::new(DVec3::new(0.0, 1.0, 1.0), [2.0, 1.0, 0.5], 0.0);
        assert_eq!(lamp.color, [1.0, 0.5, 0.25]);
        assert_eq!(lamp.strength_w_m2, 2.0);
        assert!((lamp.elevation_deg - 45.0).abs() < 1e-12 && lamp.azimuth_deg.abs() < 1e-12);
    }
}
