//! Sun and sky: Klassen's spectral sun and sky over a spherical earth with a
//! haze shell (`klassen`), and a layered exponential atmosphere with ozone and
//! twilight (`atmosphere`). [`texture`] turns either into a world texture for
//! Blender, and [`SunLamp`] gives the matching sun lamp.

pub mod atmosphere;
pub mod colour_table;
pub mod klassen;
pub mod optical_depth;
pub mod texture;

use crate::report::{Plan, Timing};
use glam::DVec3;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Direction towards the sun from Blender's Sky Texture angles, as Blender
/// renders them (measured with bpy 5.0.1, see `sky::atmosphere`):
/// `(cos e·sin ρ, cos e·cos ρ, sin e)`; rotation 0 puts the sun towards +Y,
/// increasing rotation turns it towards +X.
pub fn blender_sun_direction(elevation_rad: f64, rotation_rad: f64) -> DVec3 {
    let (se, ce) = elevation_rad.sin_cos();
    let (sr, cr) = rotation_rad.sin_cos();
    DVec3::new(ce * sr, ce * cr, se)
}

/// The report of a sky render.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SkyReport {
    /// Tyndall version.
    pub tyndall_version: String,
    /// Which model (`atmosphere` or `klassen`).
    pub model: String,
    /// Texture size `[width, height]`.
    pub resolution: [usize; 2],
    /// Wall time per stage.
    pub timings: Vec<Timing>,
    /// The matching sun lamp.
    pub sun_lamp: Option<SunLamp>,
    /// Requested relative tolerance (per channel, relative to luminance).
    pub tolerance: f64,
    /// Largest interpolation error measured between grid nodes, relative to luminance.
    pub interpolation_error: f64,
    /// Largest model (quadrature) error estimate at the nodes, relative to luminance.
    pub model_error: f64,
    /// Sky model evaluations (each a single-scattering integral, spectral or on the reduced wavelength set of `colour`).
    pub evaluations: usize,
    /// Grid cells.
    pub cells: usize,
    /// Pixels supersampled for the sun disc.
    pub sun_disc_pixels: usize,
    /// Grid cells refined to the pixel size that still miss the tolerance (steps in the sky).
    pub pixel_limited_cells: usize,
    /// Their largest interpolation miss, relative to luminance.
    pub pixel_limited_error: f64,
    /// Pixels of those cells, each evaluated directly at its centre (sky model
    /// evaluations beyond `evaluations`).
    pub direct_pixels: usize,
    /// Pieces of rows of pixels through such cells fitted along the row
    /// (quadratic in the azimuth, checked at two points against the model).
    pub row_fits: usize,
    /// Row fits that missed the tolerance at their check points (halved, or
    /// their pixels evaluated directly).
    pub row_fits_missed: usize,
    /// Pixels interpolated by the row fits.
    pub row_fitted_pixels: usize,
    /// Sky model evaluations spent on the row fits (beyond `evaluations`).
    pub row_fit_evaluations: usize,
    /// Grid points whose view ray lies wholly in the earth's shadow: exactly
    /// zero in single scattering, so no integral was computed there.
    pub shadowed_points: usize,
    /// The colour path (spectral or a reduced wavelength set) and the measurement that chose it.
    pub colour: texture::ColourDecision,
    /// The sampling used (`adaptive` grid or Klassen's coherence baseline).
    pub integrator: texture::Integrator,
    /// Whether the approximate multiple-scattering term is included.
    pub multiple_scattering: bool,
    /// What was computed and what was left out.
    pub plan: Plan,
}

/// Renders a world texture of `model` and the report (timings, error, sun lamp, plan)
/// with the default options (colour path decided per render, adaptive grid).
pub fn render_world(
    model: &dyn texture::SkyModel,
    model_name: &str,
    settings: &texture::TextureSettings,
) -> (texture::WorldTexture, SkyReport) {
    render_world_with(model, model_name, settings, &texture::BuildOptions::default())
}

/// [`render_world`] with explicit [`texture::BuildOptions`].
pub fn render_world_with(
    model: &dyn texture::SkyModel,
    model_name: &str,
    settings: &texture::TextureSettings,
    options: &texture::BuildOptions,
) -> (texture::WorldTexture, SkyReport) {
    render_world_cancellable(model, model_name, settings, options, None).expect("never cancelled")
}

/// [`render_world_with`] that stops early, returning `None` (no texture,
/// no report), once another thread sets `cancel`
/// ([`texture::build_world_texture_cancellable`]).
pub fn render_world_cancellable(
    model: &dyn texture::SkyModel,
    model_name: &str,
    settings: &texture::TextureSettings,
    options: &texture::BuildOptions,
    cancel: Option<&std::sync::atomic::AtomicBool>,
) -> Option<(texture::WorldTexture, SkyReport)> {
    let t0 = Instant::now();
    let tex = texture::build_world_texture_cancellable(model, settings, options, cancel)?;
    let seconds = t0.elapsed().as_secs_f64();
    let colour = &tex.colour;
    let mut plan = Plan {
        colour_path: match colour.path.as_str() {
            "spectral" => format!(
                "spectral (81 samples) at the evaluated points ({}); pixels in linear Rec.709",
                colour.reason
            ),
            other => format!("{other}: {}; pixels in linear Rec.709", colour.reason),
        },
        ..Default::default()
    };
    if colour.path != "spectral" {
        plan.left_out(
            "81 exponentials per scattering point",
            format!(
                "the colour of the attenuated sunlight depends on the Rayleigh and ozone columns only (the aerosol is grey), so its CIE XYZ was tabulated once over them ({}); every wavelength still attenuates with its own exponential in the table",
                colour.path
            ),
        );
    }
    let ms = model.multiple_scattering();
    let order = if ms.is_some() {
        "single scattering plus an approximate multiple-scattering term"
    } else {
        "single scattering"
    };
    match options.integrator {
        texture::Integrator::Adaptive => {
            plan.computed(
                "sky",
                format!(
                    "{order}, {} evaluations on an adaptive grid of {} cells over (view zenith, azimuth from the sun), phase-free components interpolated and multiplied by the exact phase functions per pixel",
                    tex.evaluations, tex.cells
                ),
            );
            plan.left_out(
                format!("per-pixel integrals ({} of {} pixels)", tex.width * tex.height - tex.direct_pixels, tex.width * tex.height),
                "the sky depends only on the view zenith angle and the azimuth from the sun: pixels are interpolated from the grid within the tolerance",
            );
            if tex.shadowed_points > 0 {
                plan.left_out(
                    format!("sky integrals at {} grid points", tex.shadowed_points),
                    "their view rays lie wholly in the earth's shadow (found in closed form), where single scattering is exactly zero",
                );
            }
            if tex.row_fitted_pixels > 0 {
                plan.computed(
                    "pixels fitted along their row",
                    format!(
                        "{} pixels in grid cells that reached the pixel size, or at most two pixel rows tall, still missing the tolerance: along each row (one view zenith angle) quadratic in the azimuth on {} pieces, each checked against the model at two points ({} sky evaluations; {} pieces missed and were halved or evaluated per pixel)",
                        tex.row_fitted_pixels, tex.row_fits, tex.row_fit_evaluations, tex.row_fits_missed
                    ),
                );
            }
            if tex.direct_pixels > 0 {
                plan.computed(
                    "pixels evaluated directly",
                    format!(
                        "{} pixels in {} grid cells that reached the pixel size, or at most two pixel rows tall, still missing the tolerance (a step in the sky), where no fit along the row was tried (runs under 8 pixels) or met it, are evaluated at their centres",
                        tex.direct_pixels, tex.pixel_limited_cells
                    ),
                );
            }
        }
        texture::Integrator::KlassenCoherence { threshold } => {
            plan.computed(
                "sky",
                format!(
                    "{order}, Klassen's pixel coherence (threshold {threshold:.1e}): {} first estimates, {} full integrals with the model's baseline integrator, other pixels reuse a neighbour's value; no error control between pixels",
                    tex.first_estimates, tex.evaluations
                ),
            );
        }
    }
    match &ms {
        Some(how) => plan.computed("multiple scattering (approximation)", how.clone()),
        None => plan.left_out(
            "multiple scattering",
            "not included (single scattering only; the atmosphere offers an optional approximation)",
        ),
    }
    plan.left_out("ground", "rays below the horizon carry the light scattered by the air between the observer and the ground; the ground itself is not rendered");
    if settings.sun_disc {
        plan.computed(
            "sun disc",
            format!(
                "limb-darkened disc carrying the sun's irradiance after the atmosphere, {} pixels supersampled 8×8",
                tex.sun_pixels
            ),
        );
    } else {
        plan.left_out("sun disc", "not requested: use the sun lamp instead");
    }
    if tex.gamut_clipped_pixels > 0 {
        plan.computed(
            "colours outside Rec.709",
            format!(
                "{} pixels had a negative Rec.709 channel (spectra outside its gamut, e.g. the deep red of a low sun): desaturated into it at their luminance",
                tex.gamut_clipped_pixels
            ),
        );
    }
    let lamp = SunLamp::new(model.sun_direction(), tex.sun_rgb_irradiance, model.sun_angular_diameter());
    let report = SkyReport {
        tyndall_version: crate::VERSION.into(),
        model: model_name.into(),
        resolution: [tex.width, tex.height],
        timings: vec![Timing {
            stage: "sky".into(),
            seconds,
        }],
        sun_lamp: Some(lamp),
        tolerance: settings.tolerance,
        interpolation_error: tex.interpolation_error,
        model_error: tex.model_error,
        evaluations: tex.evaluations,
        cells: tex.cells,
        sun_disc_pixels: tex.sun_pixels,
        pixel_limited_cells: tex.pixel_limited_cells,
        pixel_limited_error: tex.pixel_limited_error,
        direct_pixels: tex.direct_pixels,
        row_fits: tex.row_fits,
        row_fits_missed: tex.row_fits_missed,
        row_fitted_pixels: tex.row_fitted_pixels,
        row_fit_evaluations: tex.row_fit_evaluations,
        shadowed_points: tex.shadowed_points,
        colour: tex.colour.clone(),
        integrator: options.integrator,
        multiple_scattering: ms.is_some(),
        plan,
    };
    Some((tex, report))
}

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
    /// The same direction as Blender's Sky Texture "Sun Rotation", degrees
    /// (0: sun towards +Y; increasing towards +X, clockwise seen from above).
    pub blender_sun_rotation_deg: f64,
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
            blender_sun_rotation_deg: d.x.atan2(d.y).to_degrees(),
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
