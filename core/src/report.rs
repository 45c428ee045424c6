//! The report every render returns: timings per stage, the error estimate,
//! and the plan — what was computed, how, and what the scene did not need.

use serde::{Deserialize, Serialize};
use std::time::Instant;

/// Wall time of one stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Timing {
    /// Stage name (`plan`, `bvh`, `render`, `write_exr`, …).
    pub stage: String,
    /// Wall time, s.
    pub seconds: f64,
}

/// Something the renderer computed, and how.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Computed {
    /// What (e.g. `medium "fog": height fog`).
    pub what: String,
    /// How (e.g. `closed form, Ishiyama eqs 22-23`).
    pub how: String,
}

/// Something the scene did not need, or that this build does not model, and why.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LeftOut {
    /// What was left out.
    pub what: String,
    /// Why.
    pub why: String,
}

/// What was computed and what was left out.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// `rgb` or `spectral (81 samples, 380-780 nm)`.
    pub colour_path: String,
    /// Things computed.
    pub computed: Vec<Computed>,
    /// Things left out, with reasons.
    pub left_out: Vec<LeftOut>,
}

impl Plan {
    /// Records a computed item.
    pub fn computed(&mut self, what: impl Into<String>, how: impl Into<String>) {
        self.computed.push(Computed {
            what: what.into(),
            how: how.into(),
        });
    }
    /// Records a left-out item.
    pub fn left_out(&mut self, what: impl Into<String>, why: impl Into<String>) {
        self.left_out.push(LeftOut {
            what: what.into(),
            why: why.into(),
        });
    }
}

/// The error estimate of the `inscatter` layer against the exact solution of
/// the model (not against the real atmosphere).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct ErrorEstimate {
    /// Relative tolerance requested for numerically integrated pixels.
    pub tolerance: f64,
    /// Largest per-pixel absolute error estimate, W·m⁻²·sr⁻¹ (f64 computation,
    /// before storage as f32).
    pub max_abs: f64,
    /// Largest per-pixel relative error estimate (error / value, pixels with value > 0).
    pub max_rel: f64,
    /// Relative error of storing the images as f32 (2⁻²⁴), added by the EXR output.
    pub f32_storage_rel: f64,
    /// Pixels solved in closed form.
    pub pixels_closed_form: u64,
    /// Pixels integrated numerically (several media overlapping).
    pub pixels_numeric: u64,
    /// Numerically integrated pixels whose estimate did not reach the tolerance.
    pub pixels_not_converged: u64,
    /// Pixels integrated against the pixel filter (silhouettes, sharp medium
    /// boundaries); their errors are summarised here, not in `max_abs`/`max_rel`.
    pub edge_pixels: u64,
    /// Largest error estimate of a filter-integrated pixel, W·m⁻²·sr⁻¹.
    pub edge_max_abs: f64,
    /// Largest relative error estimate of a filter-integrated pixel.
    pub edge_max_rel: f64,
    /// Filter-integrated pixels that did not reach the tolerance at 16×16 samples.
    pub edge_pixels_not_converged: u64,
    /// How the estimate was obtained.
    pub method: String,
    /// Largest relative change of a sun's in-scatter had its disc been
    /// integrated over instead of treated as one direction (a model
    /// approximation, not included in `max_rel`).
    pub sun_disc_rel: f64,
}

/// Counts.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Stats {
    /// Pixels rendered.
    pub pixels: u64,
    /// View rays that ended on a surface.
    pub rays_hit_surface: u64,
    /// View rays that crossed no medium: no integral evaluated. Of the
    /// pixels whose in-scatter was integrated (unlit, interpolated and
    /// outside-every-volume pixels are counted there instead).
    pub rays_without_medium: u64,
    /// Pixels whose in-scatter was not integrated: their tile misses every
    /// light's illumination volume (in-scatter exactly 0). Their view rays are
    /// not traced, or, when a requested layer needs them (transmittance,
    /// depth, surface transmittance; point samples only), followed to their
    /// surface alone.
    #[serde(default)]
    pub pixels_unlit: u64,
    /// Pixels not traced: interpolated between traced ones where the
    /// in-scatter is provably smooth, within the tolerance by their own
    /// error estimate (`render::smooth`).
    #[serde(default)]
    pub pixels_interpolated: u64,
    /// Pixels whose view ray was cast (surface hit, cone and prism tests)
    /// but crosses no light's illumination volume: in-scatter exactly 0,
    /// nothing integrated (with `pixels_interpolated`'s machinery on).
    #[serde(default)]
    pub pixels_outside_every_volume: u64,
    /// Of the pixels integrated against the pixel filter (`edge_pixels`),
    /// those filtered from a spot's angular profile without lattice rays,
    /// within the tolerance by their own estimate (`render::profile`).
    #[serde(default)]
    pub pixels_profile_filtered: u64,
    /// Pixels with a NaN or infinite value in any layer (0 unless there is a bug).
    pub non_finite_pixels: u64,
    /// Triangles in the BVH.
    pub triangles: u64,
    /// Threads used.
    pub threads: usize,
    /// Image positions `[x, y]` (pixel `i` spans `[i, i+1)`, rows from the top)
    /// of the point lights in front of a perspective camera, possibly outside
    /// the frame. The in-scatter has an integrable 1/r peak there.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub light_images: Vec<[f64; 2]>,
}

/// The whole report.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Report {
    /// Tyndall version that rendered.
    pub tyndall_version: String,
    /// Image size `[width, height]`.
    pub resolution: [usize; 2],
    /// Wall time per stage.
    pub timings: Vec<Timing>,
    /// Error estimate.
    pub error: ErrorEstimate,
    /// What was computed and left out.
    pub plan: Plan,
    /// Counts.
    pub stats: Stats,
    /// Anything the user should know (approximations that were applied).
    pub warnings: Vec<String>,
}

impl Report {
    /// Records the time since `start` under `stage` and returns a new start.
    pub fn time(&mut self, stage: &str, start: Instant) -> Instant {
        self.timings.push(Timing {
            stage: stage.into(),
            seconds: start.elapsed().as_secs_f64(),
        });
        Instant::now()
    }

    /// Pretty JSON.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    }
}

/// Pretty JSON of any report type (an error message in JSON if serialisation fails).
pub fn to_json_string<T: Serialize>(value: &T) -> String {
    serde_json::to_string_pretty(value).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
}
