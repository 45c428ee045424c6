//! World textures from a sky model: an equirectangular image as Blender's
//! World Environment Texture reads it, computed on an adaptively refined grid
//! and resampled, plus the sun disc and the values for a matching sun lamp.
//!
//! **What the sky depends on.** Both sky models are spherically symmetric
//! about the earth's centre, so the sky radiance seen from the observer
//! depends only on the view zenith angle θ and the azimuth difference
//! Δφ ∈ [0, π] from the sun (mirror symmetry about the sun's vertical plane).
//! The texture is therefore computed on the 2-D domain (θ, Δφ), not per pixel
//! (Klassen §4's "coherence": cost grows with the sky's structure, not with
//! the pixel count).
//!
//! **Adaptive grid with error control.** The domain is split at the horizon
//! θ_h (the radiance has a kink or a jump there: rays below it end on the
//! ground) into two k-d trees, each starting from 8 × 8 cells. A cell's value
//! is first bilinear in its four corners (quadratic cells below). At the midpoints of its edges and its
//! centre the model is compared with the bilinear value; a cell is split in
//! θ where the edges along θ miss `tolerance × Y` in any channel (Y the
//! luminance at that point), in Δφ where the edges along Δφ
//! miss it, and in both where only the centre does — so a sky that varies in
//! one direction is refined in that direction only — down to 2⁻¹⁴ of the
//! domain.
//!
//! **Log-luminance cells.** Where the bilinear interpolant misses, the same
//! cell is tried with each component written as luminance × chromaticity
//! (channels over luminance) and interpolated bilinearly in `ln Y` and in the
//! chromaticity (when Y is positive at all four corners: the Rec.709
//! channels of a saturated sky may be negative, its luminance cannot): a component that falls
//! off like `e^{−a·θ}` (extinction towards the horizon, the twilight sky) is
//! then reproduced exactly instead of needing ever smaller cells. The cell
//! keeps the form that misses less, checked at the same five points, so the
//! error control is unchanged; it saved 17 % of the evaluations at 60°,
//! 9 % at 2° and 26 % at −4° (2048 × 1024, measured with the grid at the
//! full tolerance 1e-3). Pixels of such cells cost one `exp` per component.
//!
//! **Quadratic cells.** Near the horizon the sky changes fast but smoothly
//! (with the sun at 2°, the blue channel's curvature is ~2 per deg² at
//! 0–0.5° elevation; with the sun at 0° it varies as fast along Δφ), so
//! bilinear cells had to go down to half a pixel there. A cell about to be
//! split is first tried quadratic in the direction of the split (through
//! the midpoints of its lines across that direction), in the channels or in
//! log-luminance × chromaticity; a cell quadratic in θ that still misses
//! along Δφ is tried biquadratic. The model is evaluated at the quarter
//! points in that direction, on every support line and midline: the check
//! points are the points of the cell's grid at half the support's spacing
//! that the support does not use. One on a support line sees the error in
//! one direction only, one off all of them (e.g. (¼, ½) of a cell quadratic
//! in θ) both parts at once: f − I = the interpolation error across plus
//! the lines' misses carried inwards. The quarter points are the edge
//! midpoints and centres of the halves the cell would otherwise be split
//! into, so a quadratic that misses costs no extra evaluation. A cell keeps
//! the quadratic where it meets the tolerance in that direction, and is
//! split in the other direction if it misses there. Rows of pixels see a
//! polynomial of degree ≤ 2 in Δφ within a cell.
//!
//! **Lit-length cells (twilight).** With the sun below the observer's
//! horizon the observer is in the earth's shadow, and a view ray sees
//! sunlight only beyond the point where it leaves the shadow: its sunlit
//! length ℓ = t_end − t_exit ([`SkyModel::lit_length`], closed form). Where
//! ℓ ≤ 0 (low views towards the anti-solar side) the single-scattered sky
//! is exactly zero — such grid points are not integrated at all — and
//! beyond, it grows as ℓ × the light scattered per metre at the ray's end:
//! a kink along a curve across (θ, Δφ) that no polynomial cell follows (at
//! −4° it left 941 cells at the pixel size, whose 6 434 pixels were
//! evaluated directly). The light scattered per metre S/ℓ is smooth across
//! that curve, so where the other forms miss, a cell is tried as
//! ℓ × (S/ℓ interpolated, in the channels or as log-luminance ×
//! chromaticity), with ℓ computed exactly at each pixel. At support points
//! with ℓ ≤ 0 the ratio is continued by the least-squares plane through
//! the cell's sunlit support points ([`extend_plane`]). Such a form is
//! exact wherever ℓ ≤ 0, so check points there prove nothing: a group of
//! check points (along θ, along Δφ, centre) without a sunlit one counts as
//! an unbounded miss. At 2048 × 1024, tolerance 1e-3, this took the sky
//! stage at −6° from 369 to 215 ms, at −4° from 367 to ≈ 263 ms (13 341
//! evaluations + 2 180 direct pixels instead of 20 470 + 6 434; 1 295 grid
//! points skipped in the shadow) and at −2° from 313 to 262 ms — still far
//! above 100 ms. At −2° the rays near the anti-solar point run almost
//! parallel to the shadow's edge, ℓ jumps by thousands of km per degree
//! and S/ℓ varies by orders of magnitude within a pixel.
//!
//! **Row fits.** A cell that reaches half a pixel in θ still missing the
//! tolerance (at −2°: rows 0–3° above the horizon, 130–180° from the sun,
//! where the sky reddens within a pixel as the view rays leave the earth's
//! shadow) is not interpolated. Each row of pixels through it has one θ,
//! though, and along the row the sky is often smooth in Δφ: a run of at
//! least [`ROW_FIT_MIN_PIXELS`] pixels is fitted by quadratics through model
//! values on the row, each checked at two more points as the grid checks its
//! cells and halved where it misses ([`fit_row`]); only pixels no fit covers
//! are evaluated directly. At 2048 × 1024 this took the model calls for
//! those pixels at −2° from 3 980 (one per pixel) to 2 664 + 44 direct, and
//! the sky stage from 244 to 217 ms (−3°: 282 → 254 ms; −4° and −6°, with
//! fewer such pixels, within noise). The every-pixel check against the model
//! is unchanged (`every_pixel_at_2048_against_direct`, and `…_twilight` for
//! −2, −3, −5, −6°: worst luminance 7.4–8.1e-4).
//!
//! **Thin cells go to the row fits.** A cell at most
//! [`ROW_FIT_MAX_HEIGHT_PX`] pixel rows tall that misses along Δφ is not
//! split along Δφ: it becomes a pixel-limited leaf and each of its (at most
//! two) pixel rows is fitted along Δφ at resampling. Splitting it would
//! evaluate two or three lines of grid points per cell — a cell half a pixel
//! tall holds a pixel row only every other time — where a row fit evaluates
//! on the one line a row needs. A row meets each Δφ twice (either side of
//! the sun's vertical), so the second run through a cell reuses the first
//! run's fits.
//!
//! **Error split.** The grid refines to [`GRID_TOLERANCE_FRACTION`] (0.8) of
//! the tolerance, because its check points estimate rather than bound the
//! error between them: checking every pixel of 2048 × 1024 textures against
//! the model found single pixels at 1.02–1.09 × the tolerance when the grid
//! used all of it (see docs/benchmarks.md). The model is evaluated to
//! [`MODEL_TOLERANCE_FRACTION`] (0.05) of it; its own estimate (quadrature,
//! and for the atmosphere the colour table's, [`crate::sky::colour_table`])
//! is reported beside the interpolation error.
//!
//! **Colour.** The grid stores Rec.709 components. The layered atmosphere
//! gives them directly ([`SkyModel::rgb_evaluator`]): the 81-wavelength
//! colour sum at every scattering point comes from a table over the Rayleigh
//! and ozone columns, exact in the spectral sense (the sum commutes with the
//! integral) up to the table's measured interpolation error, ~1e-7 relative.
//! At 2048 × 1024, tolerance 1e-3, that took the sky stage at 60° from
//! 37–51 to 33–43 ms and at −4° from 232–251 to 158–164 ms (before the
//! nested quadrature and the row limit below). Other models' spectra are
//! converted point by point.
//!
//! The largest difference at the check points over the final cells is the
//! reported interpolation error —
//! an estimate measured on points between nodes, not a bound.
//!
//! **Resampling.** Each pixel (Cycles' `direction_to_equirectangular`: centre
//! column towards +X, top row the zenith) maps to (θ, Δφ); the quadtree is
//! descended to its cell and interpolated. A row has one θ, so within a cell
//! the interpolant along the row is a polynomial of degree ≤ 2 in Δφ: it is set up once
//! per run of pixels sharing a cell, and the phase weights `p_k(μ)` of the
//! whole row are computed first in branch-free loops.
//!
//! **Sun disc** (optional): uniform radiance with linear limb darkening
//! `I(μ)/I(1) = 1 − u(1 − μ)` (u = 0.6), normalised so that the disc's
//! irradiance equals the model's sun irradiance; pixels near the disc edge
//! are supersampled 8 × 8.

use crate::medium::phase::PhaseFunction;
use crate::sky::optical_depth::exp_neg;
use crate::spectrum::{self, Spectrum};
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;
use std::f64::consts::PI;

/// Phase-free components in linear Rec.709 with their phase functions, and
/// the largest absolute error estimate over the channels of their
/// phase-weighted sum ([`RgbEvaluator`]).
pub type RgbComponents = (Vec<(Option<PhaseFunction>, [f64; 3])>, f64);

/// A model's own path to linear Rec.709 components ([`SkyModel::rgb_evaluator`]).
pub struct RgbEvaluator<'a> {
    /// The components along a unit view direction, at relative tolerance `rel_tol`.
    pub eval: Box<dyn Fn(DVec3, f64) -> RgbComponents + Sync + 'a>,
    /// Short name for the report (`path` of [`ColourDecision`]).
    pub label: String,
    /// What it does and its measured error, for the report.
    pub reason: String,
}

/// A sky: spectral radiance per view direction and the sun seen through it.
pub trait SkyModel: Sync {
    /// Spectral radiance along unit `view_dir` (+Z up at the observer),
    /// W·m⁻²·sr⁻¹·nm⁻¹, with an absolute error estimate, to `rel_tol`.
    fn sky_radiance(&self, view_dir: DVec3, rel_tol: f64) -> (Spectrum, Spectrum);

    /// The same radiance split as `Σ_k p_k(μ)·S_k + S_rest`, μ = view·sun:
    /// phase-free in-scatter spectra `S_k` of each scattering species with
    /// its phase function, which vary smoothly over the sky even where the
    /// phase function is sharp (the sun's aureole), plus the error estimate.
    /// The default is one component without a phase function.
    fn sky_components(&self, view_dir: DVec3, rel_tol: f64) -> (Vec<(Option<PhaseFunction>, Spectrum)>, Spectrum) {
        let (l, e) = self.sky_radiance(view_dir, rel_tol);
        (vec![(None, l)], e)
    }
    /// A faster way to [`Self::sky_components`] straight in linear Rec.709,
    /// prepared once per texture for evaluations at relative tolerance
    /// `rel_tol` (for the layered atmosphere: the colour sums tabulated over
    /// the columns, [`crate::sky::colour_table`]), or `None` if the model
    /// has none (the default) or cannot offer one for these parameters: the
    /// error says why, for the report.
    fn rgb_evaluator(&self, _rel_tol: f64) -> Result<RgbEvaluator<'_>, String> {
        Err("this model has no Rec.709 path of its own".into())
    }

    /// A cheap first estimate of the radiance along `view_dir` for Klassen's
    /// coherence test ([`Integrator::KlassenCoherence`]). Default: the model
    /// at relative tolerance 0.1.
    fn first_estimate(&self, view_dir: DVec3) -> Spectrum {
        self.sky_radiance(view_dir, 0.1).0
    }

    /// The radiance with the model's baseline integrator (Klassen: his
    /// adaptive Simpson), for [`Integrator::KlassenCoherence`]. Default:
    /// [`Self::sky_radiance`].
    fn baseline_radiance(&self, view_dir: DVec3, rel_tol: f64) -> (Spectrum, Spectrum) {
        self.sky_radiance(view_dir, rel_tol)
    }

    /// What the model adds beyond single scattering, for the report (`None`:
    /// single scattering only).
    fn multiple_scattering(&self) -> Option<String> {
        None
    }

    /// Unit vector from the observer towards the sun.
    fn sun_direction(&self) -> DVec3;
    /// Spectral irradiance of the sun at the observer, after the atmosphere, W·m⁻²·nm⁻¹.
    fn sun_irradiance(&self) -> Spectrum;
    /// Angular diameter of the sun, rad.
    fn sun_angular_diameter(&self) -> f64;
    /// Zenith angle of the horizon seen from the observer, rad (π/2 on the ground).
    fn horizon_zenith(&self) -> f64 {
        PI / 2.0
    }
    /// Where the sky is sunlight scattered once with the observer in the
    /// earth's shadow: the signed length ℓ, m, of the view ray's sunlit
    /// part. Every component of [`Self::sky_components`] is exactly zero
    /// where ℓ ≤ 0, ℓ is continuous in the direction, and the components
    /// are ≈ ℓ × (the scattered sunlight per metre), smooth across ℓ = 0,
    /// which the grid interpolates instead ([`LeafKind::Lit`]). `None` (the
    /// default): no such structure.
    fn lit_length(&self, _view_dir: DVec3) -> Option<f64> {
        None
    }
}

/// Settings of a world texture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TextureSettings {
    /// Width, px (height = width / 2).
    pub width: usize,
    /// Relative tolerance of the interpolated sky (per channel, relative to luminance), 1e-6..=0.5.
    pub tolerance: f64,
    /// Draw the sun disc.
    pub sun_disc: bool,
}

/// A finished world texture and what it cost.
#[derive(Debug, Clone)]
pub struct WorldTexture {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// Linear Rec.709 radiance, W·m⁻²·sr⁻¹ per channel, row 0 at the top.
    pub rgb: Vec<[f32; 3]>,
    /// Sky model evaluations.
    pub evaluations: usize,
    /// Final grid cells.
    pub cells: usize,
    /// Largest measured interpolation error relative to luminance.
    pub interpolation_error: f64,
    /// Largest model error estimate relative to luminance at the nodes.
    pub model_error: f64,
    /// Cells refined down to the output's pixel size that still miss the
    /// tolerance (steps in the sky: the earth's shadow, the horizon); pixels in
    /// them are evaluated directly at their centre ([`Self::direct_pixels`]).
    pub pixel_limited_cells: usize,
    /// Largest interpolation miss in those cells, relative to luminance.
    pub pixel_limited_error: f64,
    /// Pixels supersampled for the sun disc.
    pub sun_pixels: usize,
    /// The sun for a Blender sun lamp: RGB irradiance, W·m⁻² per channel.
    pub sun_rgb_irradiance: [f64; 3],
    /// Pixels whose colour lay outside Rec.709 (a negative channel) and were
    /// desaturated into it at their luminance ([`clip_to_gamut`]).
    pub gamut_clipped_pixels: usize,
    /// The colour path used and why.
    pub colour: ColourDecision,
    /// The sampling used.
    pub integrator: Integrator,
    /// Klassen coherence: first estimates computed (one per pixel); 0 for the grid.
    pub first_estimates: usize,
    /// Pixels in pixel-limited cells, evaluated directly at their centre
    /// instead of interpolated across the step.
    pub direct_pixels: usize,
    /// Pieces of rows through pixel-limited cells fitted along Δφ from model
    /// evaluations on the row ([`fit_row`]).
    pub row_fits: usize,
    /// Row fits that missed the tolerance at their check points (the piece
    /// was then halved, or its pixels evaluated directly: `direct_pixels`).
    pub row_fits_missed: usize,
    /// Pixels interpolated by the row fits.
    pub row_fitted_pixels: usize,
    /// Sky model evaluations spent on the row fits (not in `evaluations`).
    pub row_fit_evaluations: usize,
    /// Grid points whose view ray lies wholly in the earth's shadow
    /// ([`SkyModel::lit_length`] ≤ 0): exactly zero, no integral (not in `evaluations`).
    pub shadowed_points: usize,
}

/// Most phase-free components a sky model may return.
const MAX_COMPONENTS: usize = 4;

const TICKS_LOG2: u32 = 14;
const TICKS: u32 = 1 << TICKS_LOG2;
const START_LOG2: u32 = 3;

#[derive(Debug, Clone, Copy)]
struct Cell {
    /// Integer corner (u along θ, v along Δφ) in ticks of the half-domain, and sizes.
    u0: u32,
    v0: u32,
    su: u32,
    sv: u32,
}

/// How the pixels of a leaf cell are computed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LeafKind {
    /// Bilinear in the components.
    Linear,
    /// Each component as luminance × chromaticity (channels over
    /// luminance), bilinear in the logarithm of the luminance and in the
    /// chromaticity, where its luminance is positive at all four corners
    /// (bilinear in the channels otherwise): exact for a sky that falls off
    /// exponentially across the cell (extinction towards the horizon,
    /// twilight), where the bilinear interpolant needs far smaller cells.
    Log,
    /// The components over the sunlit length ℓ of the view ray
    /// ([`SkyModel::lit_length`]), bilinear (or quadratic) in the channels,
    /// times ℓ at the pixel (0 where ℓ ≤ 0): the sky at twilight is zero
    /// where the whole ray is in the earth's shadow and grows as ℓ beyond,
    /// a kink no polynomial in (θ, Δφ) follows, while the sunlight
    /// scattered per metre is smooth across it. At points where ℓ ≤ 0 the
    /// ratio is undefined; it is continued by the least-squares plane
    /// through the cell's sunlit support points ([`extend_plane`]; their
    /// values there only matter multiplied by a small ℓ on the sunlit side,
    /// and the check points measure the result).
    Lit,
    /// [`Self::Lit`] with the ratio as luminance × chromaticity, as in [`Self::Log`].
    LitLog,
    /// The cell reached the pixel size still missing the tolerance (a step):
    /// its pixels are evaluated directly.
    PixelLimited,
}

/// The points a leaf interpolates, of the nine at s, t ∈ {0, ½, 1}
/// (s along θ, t along Δφ, both 0..1 across the cell): the corners
/// (0 = (0, 0), 1 = (1, 0), 2 = (0, 1), 3 = (1, 1)); for a leaf quadratic
/// in θ also the θ-midpoints of the constant-Δφ edges (4 = (½, 0),
/// 5 = (½, 1)); quadratic in Δφ, the Δφ-midpoints of the constant-θ edges
/// (6 = (0, ½), 7 = (1, ½)); quadratic in both, the centre (8 = (½, ½)).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Support {
    points: [u32; 9],
    /// Quadratic along θ (through the midpoints) instead of linear.
    quad_u: bool,
    /// Quadratic along Δφ (through the midpoints) instead of linear.
    quad_v: bool,
}

impl Support {
    /// Which of the nine slots the interpolant uses.
    fn used_slots(&self) -> [bool; 9] {
        std::array::from_fn(|i| match i {
            0..=3 => true,
            4 | 5 => self.quad_u,
            6 | 7 => self.quad_v,
            _ => self.quad_u && self.quad_v,
        })
    }
    /// The points the interpolant uses.
    fn used(&self) -> impl Iterator<Item = u32> + '_ {
        let used = self.used_slots();
        self.points.iter().zip(used).filter_map(|(&p, u)| u.then_some(p))
    }
}

enum Node {
    /// The points the leaf interpolates and how.
    Leaf(Support, LeafKind),
    /// Split along u (θ) into [low, high].
    SplitU([u32; 2]),
    /// Split along v (Δφ) into [low, high].
    SplitV([u32; 2]),
}

/// The sky's components at grid points: `k` RGB values per point.
struct Components {
    /// Phase function of each component (`None`: weight 1).
    phases: Vec<Option<PhaseFunction>>,
    /// Point-major RGB values of the phase-free components.
    values: Vec<[f64; 3]>,
    /// Per point and component: the natural logarithm of its luminance (NaN
    /// where that is not positive) and its channels divided by the luminance.
    log_lum: Vec<(f64, [f64; 3])>,
    /// Per point: the sunlit length ℓ of its view ray ([`SkyModel::lit_length`]), NaN if none.
    lit: Vec<f64>,
}

impl Components {
    fn k(&self) -> usize {
        self.phases.len()
    }
    /// Phase weights at μ (at most [`MAX_COMPONENTS`]; the rest 0).
    fn weights(&self, mu: f64) -> [f64; MAX_COMPONENTS] {
        let mut w = [0.0; MAX_COMPONENTS];
        for (o, p) in w.iter_mut().zip(&self.phases) {
            *o = p.map(|p| p.eval(mu)).unwrap_or(1.0);
        }
        w
    }
    /// Σ_k w_k·S_k at point `i`.
    fn combine(&self, i: u32, w: &[f64]) -> [f64; 3] {
        let k = self.k();
        let mut out = [0.0; 3];
        for (j, wj) in w.iter().take(k).enumerate() {
            let v = self.values[i as usize * k + j];
            for c in 0..3 {
                out[c] += wj * v[c];
            }
        }
        out
    }
    /// Per component: whether its luminance is positive at every point of
    /// the support (so that its logarithm can be interpolated).
    fn log_mask(&self, support: &Support) -> [bool; MAX_COMPONENTS] {
        let k = self.k();
        let mut mask = [false; MAX_COMPONENTS];
        for (j, m) in mask.iter_mut().enumerate().take(k) {
            *m = support.used().all(|p| self.log_lum[p as usize * k + j].0.is_finite());
        }
        mask
    }
    /// Whether the [`LeafKind::Lit`] forms apply to the support: ℓ is known
    /// at every point it uses and positive at one at least (a cell whose
    /// rays are all in the shadow is exactly zero, and linear).
    fn lit_applies(&self, support: &Support) -> bool {
        support.used().all(|p| self.lit[p as usize].is_finite()) && support.used().any(|p| self.lit[p as usize] > 0.0)
    }
    /// What the leaf of form `kind` interpolates for component `j` at the
    /// nine support points: the channels (or chromaticity), and for the
    /// log forms the log-luminance, of the component ([`LeafKind::Linear`],
    /// [`LeafKind::Log`]) or of the component over ℓ ([`LeafKind::Lit`],
    /// [`LeafKind::LitLog`]; at points with ℓ ≤ 0 continued by the
    /// least-squares plane through the sunlit points used, [`extend_plane`]). A log form falls back to the channels for a component
    /// whose luminance is not positive where it is needed.
    fn support_values(&self, support: &Support, kind: LeafKind, j: usize) -> SupportValues {
        let k = self.k();
        let at = |p: u32| p as usize * k + j;
        let lit = matches!(kind, LeafKind::Lit | LeafKind::LitLog);
        let log = matches!(kind, LeafKind::Log | LeafKind::LitLog);
        let used = support.used_slots();
        // The slots whose values are the component's own (all but the shadowed ones of a
        // lit form), and those of them the interpolant uses (what the others are fitted to).
        let own: [bool; 9] = std::array::from_fn(|i| !lit || self.lit[support.points[i] as usize] > 0.0);
        let fit: [bool; 9] = std::array::from_fn(|i| used[i] && own[i]);
        let ln_lit = |i: usize| if lit { self.lit[support.points[i] as usize].ln() } else { 0.0 };
        if log && (0..9).all(|i| !fit[i] || self.log_lum[at(support.points[i])].0.is_finite()) {
            let mut ln_y = [0.0; 9];
            let mut chroma = [[0.0; 3]; 9];
            for i in (0..9).filter(|&i| own[i]) {
                let (l, c) = self.log_lum[at(support.points[i])];
                if l.is_finite() {
                    (ln_y[i], chroma[i]) = (l - ln_lit(i), c);
                }
            }
            if lit {
                extend_plane(&fit, &own, &mut ln_y);
                for ch in 0..3 {
                    let mut v = chroma.map(|c| c[ch]);
                    extend_plane(&fit, &own, &mut v);
                    for (c, x) in chroma.iter_mut().zip(v) {
                        c[ch] = x;
                    }
                }
            }
            return (chroma, Some(ln_y));
        }
        let mut vals = support.points.map(|p| self.values[at(p)]);
        if lit {
            for i in (0..9).filter(|&i| own[i]) {
                let l = self.lit[support.points[i] as usize];
                vals[i] = vals[i].map(|x| x / l);
            }
            for ch in 0..3 {
                let mut v = vals.map(|c| c[ch]);
                extend_plane(&fit, &own, &mut v);
                for (c, x) in vals.iter_mut().zip(v) {
                    c[ch] = x;
                }
            }
        }
        (vals, None)
    }
    /// Σ_k w_k·S_k interpolated in the form `kind` at (s, t) from `values`
    /// (per component, [`Self::support_values`]), with ℓ = `lit` there for the lit forms.
    #[allow(clippy::too_many_arguments)]
    fn interpolate_form(
        &self,
        support: &Support,
        kind: LeafKind,
        values: &[SupportValues],
        w: &[f64],
        s: f64,
        t: f64,
        lit: f64,
    ) -> [f64; 3] {
        let scale = match kind {
            LeafKind::Lit | LeafKind::LitLog => lit.max(0.0),
            _ => 1.0,
        };
        let mut out = [0.0; 3];
        if scale == 0.0 {
            return out;
        }
        for (wj, (vals, ln_y)) in w.iter().zip(values) {
            let y = ln_y.map_or(1.0, |l| exp_neg(-cell_interpolant(&l.map(|x| [x; 3]), support, s, t)[0]));
            let v = cell_interpolant(vals, support, s, t);
            for c in 0..3 {
                out[c] += wj * scale * y * v[c];
            }
        }
        out
    }
    /// Σ_k w_k·S_k interpolated from the support's points.
    fn interpolate(&self, support: &Support, w: &[f64], s: f64, t: f64) -> [f64; 3] {
        let vals = support.points.map(|p| self.combine(p, w));
        cell_interpolant(&vals, support, s, t)
    }
}

/// A leaf cell found by [`Half::find`]: its corner points and extent in ticks.
#[derive(Debug, Clone, Copy)]
struct Leaf {
    support: Support,
    /// How its pixels are computed.
    kind: LeafKind,
    u0: f64,
    v0: f64,
    su: f64,
    sv: f64,
}

impl Leaf {
    /// Whether the point lies in this leaf (same half-open rule as [`Half::find`]).
    #[inline]
    fn contains(&self, fu: f64, fv: f64) -> bool {
        fu >= self.u0 && fu < self.u0 + self.su && fv >= self.v0 && fv < self.v0 + self.sv
    }
}

/// A leaf's interpolant along one row of pixels ([`Half::row_run`]).
/// Per component the value along the row is `a + t·(d + t·e)` (t across
/// the leaf in Δφ; `e` = 0 unless the leaf is quadratic in Δφ).
struct RowRun {
    a: [[f64; 3]; MAX_COMPONENTS],
    d: [[f64; 3]; MAX_COMPONENTS],
    e: [[f64; 3]; MAX_COMPONENTS],
    /// Per component: whether it is luminance × chromaticity (a [`LeafKind::Log`]
    /// leaf), with `a`, `d`, `e` the chromaticity and `la + t·(ld + t·le)` the log-luminance.
    log: [bool; MAX_COMPONENTS],
    la: [f64; MAX_COMPONENTS],
    ld: [f64; MAX_COMPONENTS],
    le: [f64; MAX_COMPONENTS],
    /// A lit leaf ([`LeafKind::Lit`]): the value is multiplied by ℓ⁺ at the pixel.
    lit: bool,
}

/// One half of the domain: θ ∈ [theta0, theta1], Δφ ∈ [0, π].
struct Half {
    theta0: f64,
    theta1: f64,
    nodes: Vec<Node>,
    /// Root cells (8 × 8), row-major in (u, v).
    roots: Vec<u32>,
    comps: Components,
}

fn luminance(c: &[f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

/// The value at fraction `s` of the way along a line of the cell: linear
/// between the ends `a`, `b`, or quadratic through `a`, the midpoint `m`
/// and `b`.
#[inline]
fn edge_value(a: f64, m: f64, b: f64, quad: bool, s: f64) -> f64 {
    if quad {
        a * (1.0 - s) * (1.0 - 2.0 * s) + m * 4.0 * s * (1.0 - s) + b * s * (2.0 * s - 1.0)
    } else {
        a + s * (b - a)
    }
}

/// A cell's interpolant at (s, t) ∈ [0, 1]² from the values at the nine
/// points of its support ([`Support`]; unused ones are ignored): along θ (s)
/// linear or quadratic on the lines t = 0, 1 (and ½ when quadratic in Δφ),
/// then linear or quadratic in Δφ (t) between them.
fn cell_interpolant(c: &[[f64; 3]; 9], support: &Support, s: f64, t: f64) -> [f64; 3] {
    let mut out = [0.0; 3];
    for k in 0..3 {
        let lo = edge_value(c[0][k], c[4][k], c[1][k], support.quad_u, s);
        let hi = edge_value(c[2][k], c[5][k], c[3][k], support.quad_u, s);
        let mid = if support.quad_v {
            edge_value(c[6][k], c[8][k], c[7][k], support.quad_u, s)
        } else {
            0.0
        };
        out[k] = edge_value(lo, mid, hi, support.quad_v, t);
    }
    out
}

/// Positions (s along θ, t along Δφ) of the nine support slots ([`Support`]).
const SLOT_POSITIONS: [(f64, f64); 9] = [
    (0.0, 0.0),
    (1.0, 0.0),
    (0.0, 1.0),
    (1.0, 1.0),
    (0.5, 0.0),
    (0.5, 1.0),
    (0.0, 0.5),
    (1.0, 0.5),
    (0.5, 0.5),
];

/// Sets the values of the slots that are not `own` (a lit form's shadowed
/// points, where the ratio is undefined) to the least-squares plane
/// `a + b·s + c·t` through the `fit` slots, extrapolated: a direction in
/// which the fitted points do not spread (all on one line of the cell) gets
/// no slope, and a single point gives a constant. A linear trend of the
/// ratio (e.g. its logarithm falling towards the shadow) is continued
/// exactly instead of flattened.
fn extend_plane(fit: &[bool; 9], own: &[bool; 9], v: &mut [f64; 9]) {
    // The fitted slots (no allocation: this runs per component and cell).
    let pts = || (0..9).filter(|&i| fit[i]).map(|i| (SLOT_POSITIONS[i].0, SLOT_POSITIONS[i].1, v[i]));
    let count = pts().count();
    if count == 0 {
        return;
    }
    let n = count as f64;
    let (ms, mt, mv) = pts().fold((0.0, 0.0, 0.0), |a, p| (a.0 + p.0 / n, a.1 + p.1 / n, a.2 + p.2 / n));
    let (mut sss, mut stt, mut sst, mut ssv, mut stv) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for (s, t, x) in pts() {
        let (ds, dt, dx) = (s - ms, t - mt, x - mv);
        sss += ds * ds;
        stt += dt * dt;
        sst += ds * dt;
        ssv += ds * dx;
        stv += dt * dx;
    }
    const SPREAD: f64 = 1e-9;
    let det = sss * stt - sst * sst;
    let (b, c) = if det > SPREAD {
        ((ssv * stt - stv * sst) / det, (stv * sss - ssv * sst) / det)
    } else if sss > SPREAD && stt <= SPREAD {
        (ssv / sss, 0.0)
    } else if stt > SPREAD && sss <= SPREAD {
        (0.0, stv / stt)
    } else {
        // Collinear along a diagonal, or one point: no slope.
        (0.0, 0.0)
    };
    for i in (0..9).filter(|&i| !own[i]) {
        let (s, t) = SLOT_POSITIONS[i];
        v[i] = mv + b * (s - ms) + c * (t - mt);
    }
}

/// Refinement limits of one half of the domain.
struct Limits {
    /// Smallest cell extent along θ and Δφ, ticks (half an output pixel).
    min_su: u32,
    min_sv: u32,
    /// Cells at most this tall (ticks of θ, [`ROW_FIT_MAX_HEIGHT_PX`] pixel
    /// rows) are not split along Δφ.
    row_su: u32,
    /// Luminance floor for relative errors, as a fraction of the brightest sky.
    floor_fraction: f64,
}

/// What the refinement measured.
#[derive(Debug, Default)]
struct Stats {
    evaluations: usize,
    /// Largest interpolation miss of cells that met the tolerance.
    interpolation: f64,
    model_error: f64,
    brightest: f64,
    /// Cells that reached the pixel size without meeting the tolerance (a step: the earth's shadow, the horizon).
    pixel_limited: usize,
    pixel_limited_error: f64,
    /// Grid points whose view ray is wholly in the earth's shadow: zero, not evaluated.
    in_shadow: usize,
}

/// What a leaf interpolates for one component at its nine support slots: the
/// channels (or chromaticity), and the log-luminance for the log forms
/// ([`Components::support_values`]).
type SupportValues = ([[f64; 3]; 9], Option<[f64; 9]>);

/// A sky evaluation at one grid point: phase-free component RGB values and the error estimate.
type PointEval = RgbComponents;

/// What the grid asks of the sky at (θ, Δφ): the components
/// ([`PointEval`]), μ = view·sun, and the sunlit length ℓ ([`SkyModel::lit_length`]).
struct Probe<'a> {
    eval: &'a (dyn Fn(f64, f64) -> PointEval + Sync),
    cos_mu: &'a (dyn Fn(f64, f64) -> f64 + Sync),
    lit: &'a (dyn Fn(f64, f64) -> Option<f64> + Sync),
    /// True once the build is to stop ([`build_world_texture_cancellable`]):
    /// asked before each round of refinement.
    stop: &'a (dyn Fn() -> bool + Sync),
}

/// A cell's largest misses at its check points, relative to luminance:
/// (along θ, along Δφ, centre only).
type Misses = (f64, f64, f64);

/// An interpolant of a cell: its support, form and misses.
type Fit = (Support, LeafKind, Misses);

/// A cell waiting for a quadratic trial: the cell, its node, and its
/// current support, form and misses.
type Trial = (Cell, u32, Support, LeafKind, Misses);

/// The positions, in quarters of the cell, of its grid at half the
/// support's spacing along a direction that is quadratic or linear.
fn grid_quarters(quad: bool) -> &'static [u32] {
    if quad { &[0, 1, 2, 3, 4] } else { &[0, 2, 4] }
}

/// A placeholder for a node that is about to be decided.
fn placeholder_support() -> Support {
    Support {
        points: [0; 9],
        quad_u: false,
        quad_v: false,
    }
}

/// Whether a cell with misses `m` (along θ, along Δφ, centre) is split along
/// θ: it misses along θ, or only at the centre (a cross term, split in θ
/// first), and is not yet at the pixel limit in θ.
fn split_along_theta(c: &Cell, m: Misses, tol: f64, limits: &Limits) -> bool {
    let (along_u, along_v, centre) = m;
    let cross = centre > tol && along_u <= tol && along_v <= tol;
    c.su > limits.min_su && (along_u > tol || cross)
}

/// Whether a cell with misses `m` that is not split along θ
/// ([`split_along_theta`]) is split along Δφ: it misses there, is not at the
/// pixel limit in Δφ, and is more than [`ROW_FIT_MAX_HEIGHT_PX`] pixel rows
/// tall (a thinner one holds at most that many rows, and fitting each of
/// them along Δφ at resampling costs fewer model calls than refining the
/// cell's 2–3 lines of grid points — half of which, in a cell half a pixel
/// tall, no pixel row would ever read). A thin cell that misses, in any
/// direction, becomes a pixel-limited leaf whose rows are fitted.
fn split_along_phi(c: &Cell, m: Misses, tol: f64, limits: &Limits) -> bool {
    !split_along_theta(c, m, tol, limits) && c.su > limits.row_su && c.sv > limits.min_sv && m.1 > tol
}

impl Half {
    fn theta(&self, u: u32) -> f64 {
        self.theta0 + (self.theta1 - self.theta0) * f64::from(u) / f64::from(TICKS)
    }
    fn dphi(v: u32) -> f64 {
        PI * f64::from(v) / f64::from(TICKS)
    }
    fn dphi_ticks(v: f64) -> f64 {
        PI * v / f64::from(TICKS)
    }

    /// Evaluates the sky at the points `need` (ticks) not yet in `cache`, in parallel.
    fn evaluate(
        &mut self,
        need: &mut Vec<(u32, u32)>,
        cache: &mut HashMap<(u32, u32), u32>,
        probe: &Probe,
        limits: &Limits,
        stats: &mut Stats,
    ) {
        need.retain(|key| !cache.contains_key(key));
        need.sort_unstable();
        need.dedup();
        // Points whose view ray is wholly in the earth's shadow (ℓ ≤ 0) are
        // exactly zero by the model's contract ([`SkyModel::lit_length`]):
        // no integral, once the components' phase functions are known.
        let phases = self.comps.phases.clone();
        let values: Vec<((u32, u32), f64, Option<PointEval>)> = need
            .par_iter()
            .map(|&(u, v)| {
                let (theta, dphi) = (self.theta(u), Half::dphi(v));
                let l = (probe.lit)(theta, dphi).unwrap_or(f64::NAN);
                let dark = !phases.is_empty() && l <= 0.0;
                ((u, v), l, (!dark).then(|| (probe.eval)(theta, dphi)))
            })
            .collect();
        for (key, l, point) in values {
            let (parts, err) = match point {
                Some(p) => {
                    stats.evaluations += 1;
                    p
                }
                None => {
                    stats.in_shadow += 1;
                    (phases.iter().map(|ph| (*ph, [0.0; 3])).collect(), 0.0)
                }
            };
            if self.comps.phases.is_empty() {
                self.comps.phases = parts.iter().map(|p| p.0).collect();
            }
            let w = self.comps.weights((probe.cos_mu)(self.theta(key.0), Half::dphi(key.1)));
            let mut total = [0.0; 3];
            for (j, (_, rgb)) in parts.iter().enumerate() {
                for c in 0..3 {
                    total[c] += w.get(j).copied().unwrap_or(1.0) * rgb[c];
                }
            }
            let y = luminance(&total).abs();
            stats.model_error = stats
                .model_error
                .max(err / y.max(limits.floor_fraction * stats.brightest).max(1e-300));
            stats.brightest = stats.brightest.max(y);
            let index = (self.comps.values.len() / self.comps.k().max(1)) as u32;
            self.comps.lit.push(l);
            for (_, rgb) in parts {
                self.comps.values.push(rgb);
                let y = luminance(&rgb);
                self.comps.log_lum.push(if y > 0.0 {
                    (y.ln(), rgb.map(|x| x / y))
                } else {
                    (f64::NAN, [0.0; 3])
                });
            }
            cache.insert(key, index);
        }
    }

    /// How well the cell `c` is interpolated from `support`: the largest
    /// miss, relative to the luminance there (but not less than `floor`),
    /// at each check point, grouped as (along θ, along Δφ, centre), for the
    /// interpolant in the channels and, where every component can be written
    /// as luminance × chromaticity, in those. The check points are those of
    /// [`Self::check_points`] that the support does not use.
    fn misses(
        &self,
        cache: &HashMap<(u32, u32), u32>,
        c: &Cell,
        support: &Support,
        cos_mu: &(dyn Fn(f64, f64) -> f64 + Sync),
        floor: f64,
        kind: LeafKind,
    ) -> Misses {
        let lit_form = matches!(kind, LeafKind::Lit | LeafKind::LitLog);
        // The form's values at the support, once per cell (not per check point).
        let values: Vec<SupportValues> = if kind == LeafKind::Linear {
            Vec::new()
        } else {
            (0..self.comps.k()).map(|j| self.comps.support_values(support, kind, j)).collect()
        };
        let miss = |pts: &[(u32, u32, f64, f64)]| -> f64 {
            // A lit form is exact where ℓ ≤ 0, so there its check points
            // say nothing: a group of them with no sunlit point has not
            // measured the cell's sunlit part in its direction at all.
            if lit_form
                && !pts.is_empty()
                && pts.iter().all(|&(du, dv, ..)| {
                    self.comps.lit[cache[&(c.u0 + du, c.v0 + dv)] as usize].partial_cmp(&0.0) != Some(std::cmp::Ordering::Greater)
                })
            {
                return f64::INFINITY;
            }
            let mut worst = 0.0f64;
            for &(du, dv, ss, tt) in pts {
                let w = self.comps.weights(cos_mu(self.theta(c.u0 + du), Half::dphi(c.v0 + dv)));
                let point = cache[&(c.u0 + du, c.v0 + dv)];
                let truth = self.comps.combine(point, &w);
                let fit = if kind == LeafKind::Linear {
                    self.comps.interpolate(support, &w, ss, tt)
                } else {
                    self.comps
                        .interpolate_form(support, kind, &values, &w, ss, tt, self.comps.lit[point as usize])
                };
                // Relative to the luminance at the point itself.
                let scale = luminance(&truth).abs().max(floor);
                for k in 0..3 {
                    worst = worst.max((truth[k] - fit[k]).abs() / scale);
                }
            }
            worst
        };
        // Check points: the points of the cell's grid at half the support's
        // spacing (θ and Δφ quarters where quadratic, halves where linear)
        // that the support does not use. One on a support line of constant
        // Δφ sees only the error along θ, one on a line of constant θ only
        // that along Δφ; the rest see both (f − I = the error of the
        // interpolation in one direction + the other's misses carried
        // inwards) and count for the linear direction, or as the centre
        // (a cross term) when both are alike.
        let on_support = |quarter: u32, quad: bool| quarter == 0 || quarter == 4 || (quad && quarter == 2);
        let (mut along_u, mut along_v, mut both) = (Vec::new(), Vec::new(), Vec::new());
        for &i in grid_quarters(support.quad_u) {
            for &j in grid_quarters(support.quad_v) {
                let (su_line, sv_line) = (on_support(i, support.quad_u), on_support(j, support.quad_v));
                let point = (c.su * i / 4, c.sv * j / 4, f64::from(i) / 4.0, f64::from(j) / 4.0);
                match (su_line, sv_line) {
                    (true, true) => {}
                    (false, true) => along_u.push(point),
                    (true, false) => along_v.push(point),
                    (false, false) => both.push(point),
                }
            }
        }
        let both = miss(&both);
        match (support.quad_u, support.quad_v) {
            (true, false) => (miss(&along_u), miss(&along_v).max(both), 0.0),
            (false, true) => (miss(&along_u).max(both), miss(&along_v), 0.0),
            _ => (miss(&along_u), miss(&along_v), both),
        }
    }

    /// The points of the cell's grid at half the support's spacing (θ and
    /// Δφ quarters where quadratic, halves where linear), as tick offsets in
    /// the cell: the support's own points and the check points of [`Self::misses`].
    fn check_points(c: &Cell, support: &Support) -> Vec<(u32, u32)> {
        let mut out = Vec::new();
        for &i in grid_quarters(support.quad_u) {
            for &j in grid_quarters(support.quad_v) {
                out.push((c.su * i / 4, c.sv * j / 4));
            }
        }
        out
    }

    /// The best of the interpolants on `support` in the channels, (where the
    /// components' luminances are positive) in log-luminance × chromaticity,
    /// and (where the model gives a sunlit length ℓ) the two lit forms
    /// ([`LeafKind::Lit`], [`LeafKind::LitLog`]): its kind and misses. Each
    /// further form is only tried where the ones before miss. Better means the smaller largest miss; for a
    /// quadratic trial along θ or Δφ (`trial` = Some(true / false)) first
    /// the form that meets the tolerance in that direction (a log form can
    /// miss less overall but break the quadratic it is tried for).
    #[allow(clippy::too_many_arguments)]
    fn best_fit(
        &self,
        cache: &HashMap<(u32, u32), u32>,
        c: &Cell,
        support: &Support,
        cos_mu: &(dyn Fn(f64, f64) -> f64 + Sync),
        floor: f64,
        tol: f64,
        trial: Option<bool>,
    ) -> (LeafKind, Misses) {
        let worst = |m: Misses| m.0.max(m.1).max(m.2);
        let rank = |m: Misses| -> (bool, f64) {
            match trial {
                // An unmeasured (infinite) miss fails whatever the direction.
                Some(true) => (m.0 > tol || !worst(m).is_finite(), worst(m)),
                Some(false) => (m.1 > tol || !worst(m).is_finite(), worst(m)),
                None => (false, worst(m)),
            }
        };
        let mut best = (LeafKind::Linear, self.misses(cache, c, support, cos_mu, floor, LeafKind::Linear));
        if worst(best.1) > tol && self.comps.log_mask(support).iter().any(|m| *m) {
            let log = self.misses(cache, c, support, cos_mu, floor, LeafKind::Log);
            if rank(log) < rank(best.1) {
                best = (LeafKind::Log, log);
            }
        }
        if worst(best.1) > tol && self.comps.lit_applies(support) {
            for kind in [LeafKind::Lit, LeafKind::LitLog] {
                let m = self.misses(cache, c, support, cos_mu, floor, kind);
                if rank(m) < rank(best.1) {
                    best = (kind, m);
                }
            }
        }
        best
    }

    fn build(theta0: f64, theta1: f64, probe: &Probe, tol: f64, limits: &Limits, stats: &mut Stats) -> Half {
        let mut half = Half {
            theta0,
            theta1,
            nodes: Vec::new(),
            roots: Vec::new(),
            comps: Components {
                phases: Vec::new(),
                values: Vec::new(),
                log_lum: Vec::new(),
                lit: Vec::new(),
            },
        };
        let mut cache: HashMap<(u32, u32), u32> = HashMap::new();
        let n0 = 1u32 << START_LOG2;
        let size0 = TICKS >> START_LOG2;
        let mut pending: Vec<(Cell, u32)> = Vec::new();
        for iu in 0..n0 {
            for iv in 0..n0 {
                let idx = half.nodes.len() as u32;
                half.nodes.push(Node::Leaf(placeholder_support(), LeafKind::Linear));
                half.roots.push(idx);
                pending.push((
                    Cell {
                        u0: iu * size0,
                        v0: iv * size0,
                        su: size0,
                        sv: size0,
                    },
                    idx,
                ));
            }
        }
        let worst = |m: Misses| m.0.max(m.1).max(m.2);
        while !pending.is_empty() {
            if (probe.stop)() {
                // The half is left unfinished; the caller returns no texture.
                break;
            }
            // Every point the pending cells need: corners, centre, edge midpoints.
            let mut need: Vec<(u32, u32)> = Vec::new();
            for (c, _) in &pending {
                let (hu, hv, su, sv) = (c.su / 2, c.sv / 2, c.su, c.sv);
                for (du, dv) in [(0, 0), (su, 0), (0, sv), (su, sv), (hu, hv), (hu, 0), (hu, sv), (0, hv), (su, hv)] {
                    need.push((c.u0 + du, c.v0 + dv));
                }
            }
            half.evaluate(&mut need, &mut cache, probe, limits, stats);
            // Errors are relative to the luminance at the point, but never to
            // less than a fraction of the brightest sky seen (the dark side of
            // twilight would otherwise ask for relative accuracy in the dark).
            let floor = (limits.floor_fraction * stats.brightest).max(1e-300);
            let mut next = Vec::new();
            // Cells about to be split are first tried quadratic in the
            // direction of the split ([`Self::misses`] checks them at the
            // quarter points, which the halves would need anyway).
            let mut try_theta: Vec<Trial> = Vec::new();
            let mut try_phi: Vec<Trial> = Vec::new();
            // Bilinear in the components first; where that misses and a
            // component's luminance is positive at every corner, bilinear in
            // its log-luminance and chromaticity (`LeafKind::Log`), then the
            // lit forms where the model gives ℓ (`LeafKind::Lit`, `LitLog`),
            // all checked at the same points; refinement follows whichever
            // misses least. The cells are fitted in parallel, then settled in order.
            let fits: Vec<(Support, LeafKind, Misses)> = pending
                .par_iter()
                .map(|(c, _)| {
                    let (hu, hv, su, sv) = (c.su / 2, c.sv / 2, c.su, c.sv);
                    let at = |du: u32, dv: u32| cache[&(c.u0 + du, c.v0 + dv)];
                    let support = Support {
                        points: [
                            at(0, 0),
                            at(su, 0),
                            at(0, sv),
                            at(su, sv),
                            at(hu, 0),
                            at(hu, sv),
                            at(0, hv),
                            at(su, hv),
                            at(hu, hv),
                        ],
                        quad_u: false,
                        quad_v: false,
                    };
                    let (mode, m) = half.best_fit(&cache, c, &support, probe.cos_mu, floor, tol, None);
                    (support, mode, m)
                })
                .collect();
            for ((c, idx), (support, mode, m)) in pending.into_iter().zip(fits) {
                if worst(m) > tol && split_along_theta(&c, m, tol, limits) && c.su % 4 == 0 {
                    try_theta.push((c, idx, support, mode, m));
                } else if worst(m) > tol && split_along_phi(&c, m, tol, limits) && c.sv % 4 == 0 {
                    try_phi.push((c, idx, support, mode, m));
                } else {
                    half.settle(c, idx, support, mode, m, tol, limits, stats, &mut next);
                }
            }
            // Quadratic in θ where that meets the tolerance along θ; such a
            // cell that misses along Δφ is then tried quadratic in Δφ too.
            let trials = half.try_quadratic(try_theta, true, tol, &mut cache, probe, limits, stats);
            for (c, idx, (support, mode, m), (quad, quad_mode, quad_m)) in trials {
                if quad_m.0 > tol {
                    half.settle(c, idx, support, mode, m, tol, limits, stats, &mut next);
                } else if worst(quad_m) > tol && split_along_phi(&c, quad_m, tol, limits) && c.sv % 4 == 0 {
                    try_phi.push((c, idx, quad, quad_mode, quad_m));
                } else {
                    half.settle(c, idx, quad, quad_mode, quad_m, tol, limits, stats, &mut next);
                }
            }
            // Quadratic in Δφ where that meets the tolerance along Δφ (the
            // cell may still be split along θ).
            let trials = half.try_quadratic(try_phi, false, tol, &mut cache, probe, limits, stats);
            for (c, idx, (support, mode, m), (quad, quad_mode, quad_m)) in trials {
                if quad_m.1 <= tol {
                    half.settle(c, idx, quad, quad_mode, quad_m, tol, limits, stats, &mut next);
                } else {
                    half.settle(c, idx, support, mode, m, tol, limits, stats, &mut next);
                }
            }
            pending = next;
        }
        half
    }

    /// Evaluates what the cells of `trials` need to be checked quadratic
    /// along θ (`theta`) or Δφ, and returns each cell with its current fit
    /// and the quadratic one (support, form, misses).
    #[allow(clippy::too_many_arguments)]
    fn try_quadratic(
        &mut self,
        trials: Vec<Trial>,
        theta: bool,
        tol: f64,
        cache: &mut HashMap<(u32, u32), u32>,
        probe: &Probe,
        limits: &Limits,
        stats: &mut Stats,
    ) -> Vec<(Cell, u32, Fit, Fit)> {
        let quadratic = |s: &Support| {
            if theta {
                Support { quad_u: true, ..*s }
            } else {
                Support { quad_v: true, ..*s }
            }
        };
        let mut need: Vec<(u32, u32)> = Vec::new();
        for (c, _, support, ..) in &trials {
            for (du, dv) in Self::check_points(c, &quadratic(support)) {
                need.push((c.u0 + du, c.v0 + dv));
            }
        }
        self.evaluate(&mut need, cache, probe, limits, stats);
        let floor = (limits.floor_fraction * stats.brightest).max(1e-300);
        let (half, cache) = (&*self, &*cache);
        trials
            .into_par_iter()
            .map(|(c, idx, support, mode, m)| {
                let quad = quadratic(&support);
                let (quad_mode, quad_m) = half.best_fit(cache, &c, &quad, probe.cos_mu, floor, tol, Some(theta));
                (c, idx, (support, mode, m), (quad, quad_mode, quad_m))
            })
            .collect()
    }

    /// Makes the cell a leaf on `support` when its misses `m` meet the
    /// tolerance or it cannot be split further, else splits it (the halves
    /// go to `next`).
    #[allow(clippy::too_many_arguments)]
    fn settle(
        &mut self,
        c: Cell,
        idx: u32,
        support: Support,
        mode: LeafKind,
        m: Misses,
        tol: f64,
        limits: &Limits,
        stats: &mut Stats,
        next: &mut Vec<(Cell, u32)>,
    ) {
        let (along_u, along_v, centre) = m;
        let (hu, hv, su, sv) = (c.su / 2, c.sv / 2, c.su, c.sv);
        // Never finer than the output pixels: below that the pixel grid
        // itself is the resolution (counted and reported separately).
        let split_u = split_along_theta(&c, m, tol, limits);
        let split_v = split_along_phi(&c, m, tol, limits);
        if split_u || split_v {
            let mut child = |cell: Cell| -> u32 {
                let k = self.nodes.len() as u32;
                self.nodes.push(Node::Leaf(placeholder_support(), LeafKind::Linear));
                next.push((cell, k));
                k
            };
            // Split along u first when both are needed; the halves are
            // split along v on the next round if they still miss.
            self.nodes[idx as usize] = if split_u {
                let a = child(Cell { su: hu, ..c });
                let b = child(Cell {
                    u0: c.u0 + hu,
                    su: su - hu,
                    ..c
                });
                Node::SplitU([a, b])
            } else {
                let a = child(Cell { sv: hv, ..c });
                let b = child(Cell {
                    v0: c.v0 + hv,
                    sv: sv - hv,
                    ..c
                });
                Node::SplitV([a, b])
            };
        } else {
            let miss_all = along_u.max(along_v).max(centre);
            if miss_all > tol {
                stats.pixel_limited += 1;
                // An unmeasured miss (never chosen over a measured one) is not a number to report.
                if miss_all.is_finite() {
                    stats.pixel_limited_error = stats.pixel_limited_error.max(miss_all);
                }
            } else {
                stats.interpolation = stats.interpolation.max(miss_all);
            }
            self.nodes[idx as usize] = Node::Leaf(support, if miss_all > tol { LeafKind::PixelLimited } else { mode });
        }
    }

    /// (θ, Δφ) in ticks of this half.
    #[inline]
    fn ticks(&self, theta: f64, dphi: f64) -> (f64, f64) {
        let fu = ((theta - self.theta0) / (self.theta1 - self.theta0)).clamp(0.0, 1.0) * f64::from(TICKS);
        let fv = (dphi / PI).clamp(0.0, 1.0) * f64::from(TICKS);
        (fu, fv)
    }

    /// The leaf holding (fu, fv) ticks.
    fn find(&self, fu: f64, fv: f64) -> Leaf {
        let n0 = 1u32 << START_LOG2;
        let size0 = f64::from(TICKS >> START_LOG2);
        let iu = ((fu / size0) as u32).min(n0 - 1);
        let iv = ((fv / size0) as u32).min(n0 - 1);
        let mut idx = self.roots[(iu * n0 + iv) as usize];
        let (mut u0, mut v0, mut su, mut sv) = (f64::from(iu) * size0, f64::from(iv) * size0, size0, size0);
        loop {
            match &self.nodes[idx as usize] {
                Node::Leaf(support, kind) => {
                    return Leaf {
                        support: *support,
                        kind: *kind,
                        u0,
                        v0,
                        su,
                        sv,
                    };
                }
                Node::SplitU(kids) => {
                    let h = (su / 2.0).floor();
                    if fu >= u0 + h {
                        u0 += h;
                        su -= h;
                        idx = kids[1];
                    } else {
                        su = h;
                        idx = kids[0];
                    }
                }
                Node::SplitV(kids) => {
                    let h = (sv / 2.0).floor();
                    if fv >= v0 + h {
                        v0 += h;
                        sv -= h;
                        idx = kids[1];
                    } else {
                        sv = h;
                        idx = kids[0];
                    }
                }
            }
        }
    }

    /// The leaf's interpolant restricted to the row at `fu` ticks: per
    /// component, a polynomial in t (linear, or quadratic where the leaf is
    /// quadratic in Δφ), see [`RowRun`].
    #[inline]
    fn row_run(&self, leaf: &Leaf, fu: f64) -> RowRun {
        let s = ((fu - leaf.u0) / leaf.su).clamp(0.0, 1.0);
        let k = self.comps.k();
        let mut run = RowRun {
            a: [[0.0; 3]; MAX_COMPONENTS],
            d: [[0.0; 3]; MAX_COMPONENTS],
            e: [[0.0; 3]; MAX_COMPONENTS],
            log: [false; MAX_COMPONENTS],
            la: [0.0; MAX_COMPONENTS],
            ld: [0.0; MAX_COMPONENTS],
            le: [0.0; MAX_COMPONENTS],
            lit: matches!(leaf.kind, LeafKind::Lit | LeafKind::LitLog),
        };
        let (quad_u, quad_v) = (leaf.support.quad_u, leaf.support.quad_v);
        // The lines t = 0, (½,) 1 at this s, then the polynomial in t
        // through them (Lagrange through 0, ½, 1 expanded in powers of t).
        let lerp = |c: [f64; 9]| -> (f64, f64, f64) {
            let lo = edge_value(c[0], c[4], c[1], quad_u, s);
            let hi = edge_value(c[2], c[5], c[3], quad_u, s);
            if quad_v {
                let mid = edge_value(c[6], c[8], c[7], quad_u, s);
                (lo, 4.0 * mid - 3.0 * lo - hi, 2.0 * (lo + hi) - 4.0 * mid)
            } else {
                (lo, hi - lo, 0.0)
            }
        };
        for j in 0..k.min(MAX_COMPONENTS) {
            // A log form is polynomial along the row in the log-luminance and the chromaticity.
            let (vals, ln_y) = self.comps.support_values(&leaf.support, leaf.kind, j);
            for c in 0..3 {
                (run.a[j][c], run.d[j][c], run.e[j][c]) = lerp(vals.map(|v| v[c]));
            }
            if let Some(ln_y) = ln_y {
                run.log[j] = true;
                (run.la[j], run.ld[j], run.le[j]) = lerp(ln_y);
            }
        }
        run
    }

    fn cells(&self) -> usize {
        self.nodes.iter().filter(|n| matches!(n, Node::Leaf(..))).count()
    }
}

/// The weights `p(μ)` of a component with phase function `phase` (`None`: 1)
/// at every μ of a row. The phase functions of the two sky models are
/// spelled out (the same formulas as [`PhaseFunction::eval`], checked by a
/// test) so that the loop over pixels has no branch and vectorises.
fn phase_weights(phase: Option<PhaseFunction>, mu: &[f64], out: &mut [f64]) {
    use std::f64::consts::PI;
    match phase {
        None => out.fill(1.0),
        Some(PhaseFunction::Rayleigh) => {
            let k = 3.0 / (16.0 * PI);
            for (o, m) in out.iter_mut().zip(mu) {
                *o = k * (1.0 + m * m);
            }
        }
        Some(PhaseFunction::CornetteShanks { g }) => {
            let k = 3.0 / (8.0 * PI) * (1.0 - g * g) / (2.0 + g * g);
            let (a, b) = (1.0 + g * g, 2.0 * g);
            for (o, m) in out.iter_mut().zip(mu) {
                let d = a - b * m;
                *o = k * (1.0 + m * m) / (d * d.sqrt());
            }
        }
        Some(p) => {
            for (o, m) in out.iter_mut().zip(mu) {
                *o = p.eval(*m);
            }
        }
    }
}

/// Direction of equirectangular image point (x, y) (pixels from the top-left),
/// Cycles' environment mapping: centre column → +X, top row → +Z.
pub fn equirect_direction(x: f64, y: f64, width: usize, height: usize) -> DVec3 {
    let theta = PI * y / height as f64;
    let phi = PI - 2.0 * PI * x / width as f64;
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    DVec3::new(st * cp, st * sp, ct)
}

/// How the colour of the sky is computed at the points the texture evaluates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum ColourPath {
    /// Default. The model's own Rec.709 path ([`SkyModel::rgb_evaluator`]:
    /// for the layered atmosphere, the full 81-wavelength colour sums
    /// tabulated over the columns, their error charged to every point) if
    /// it has one, else spectral.
    #[default]
    Auto,
    /// Always the model's 81-sample spectra, converted to Rec.709 per point.
    Spectral,
}

/// How the sky is sampled.
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Integrator {
    /// Default: the adaptive (θ, Δφ) grid with error control, resampled.
    #[default]
    Adaptive,
    /// Klassen's baseline (seed §4): every pixel in raster order; a cheap
    /// first estimate of the integral is computed for each, and the full
    /// integral (Klassen's model: his adaptive Simpson) only when the first
    /// estimate differs from the one of the pixel whose result would be
    /// reused by more than `threshold` (relative to its luminance, per
    /// Rec.709 channel); otherwise that result is reused.
    KlassenCoherence {
        /// Relative threshold, dimensionless, 1e-6..=0.5 (the CLI uses the tolerance).
        threshold: f64,
    },
}

/// Options of [`build_world_texture_with`] beyond [`TextureSettings`].
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct BuildOptions {
    /// Colour path at the evaluated points (default [`ColourPath::Auto`]).
    pub colour: ColourPath,
    /// Sampling of the sky (default [`Integrator::Adaptive`]).
    pub integrator: Integrator,
}

/// What the colour-path decision measured.
#[derive(Debug, Clone, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct ColourDecision {
    /// The path used: `spectral` or the model's own (`xyz-table`).
    pub path: String,
    /// What it does and why it was taken, with its measured error.
    pub reason: String,
}

/// Builds the world texture of `model` with the default options.
pub fn build_world_texture(model: &dyn SkyModel, settings: &TextureSettings) -> WorldTexture {
    build_world_texture_with(model, settings, &BuildOptions::default())
}

fn sky_rgb(parts: Vec<(Option<PhaseFunction>, Spectrum)>, e: &Spectrum) -> PointEval {
    let err = spectrum::spectral_error_to_rec709(e).iter().fold(0.0f64, |a, b| a.max(*b));
    (parts.into_iter().map(|(p, l)| (p, spectrum::spectrum_to_rec709(&l))).collect(), err)
}

/// The luminance below which errors are measured against this fraction of
/// the brightest sky seen instead (relative errors of a nearly black sky mean nothing).
const LUMINANCE_FLOOR_FRACTION: f64 = 1e-4;

/// Cells at most this many pixel rows tall are not refined along Δφ: where
/// they miss, their rows are fitted along Δφ at resampling ([`fit_row`]).
/// Measured at 2048 × 1024, tolerance 1e-3 (sky stage; model calls): −2°
/// 104 → 68 ms (10 610 → 6 167), −4° 112 → 83 ms (14 136 → 9 790), −6°
/// 104 → 94 ms (13 562 → 14 784, more of them row calls); with a limit of
/// 1 row: 80, 97, 99 ms; 4 rows: 73, 86, 93 ms.
const ROW_FIT_MAX_HEIGHT_PX: f64 = 2.0;

/// Runs shorter than this (pixels of one row in one pixel-limited cell) are
/// evaluated directly: a row fit costs five evaluations, each halving two more.
const ROW_FIT_MIN_PIXELS: usize = 8;

/// The phase-free components along one row of pixels (fixed θ) across a
/// cell, quadratic in the cell's Δφ coordinate t ∈ [0, 1]: `a + t·(d + t·e)`
/// per component and channel.
struct RowFit {
    phases: Vec<Option<PhaseFunction>>,
    a: Vec<[f64; 3]>,
    d: Vec<[f64; 3]>,
    e: Vec<[f64; 3]>,
}

impl RowFit {
    /// Linear Rec.709 radiance at `t` for the phase cosine `mu`.
    fn at(&self, t: f64, mu: f64) -> [f64; 3] {
        let mut out = [0.0; 3];
        for (c, p) in self.phases.iter().enumerate() {
            let w = p.map_or(1.0, |p| p.eval(mu));
            for ch in 0..3 {
                out[ch] += w * (self.a[c][ch] + t * (self.d[c][ch] + t * self.e[c][ch]));
            }
        }
        out
    }
}

/// A model evaluation on a row: the phase-free components and the phase cosine μ.
type RowPoint = (Vec<(Option<PhaseFunction>, [f64; 3])>, f64);

/// What [`fit_row`] found: the pieces of the cell's Δφ range `[a, b]` (in the
/// cell's coordinate t ∈ [0, 1]) with their fit, `None` where the pixels are
/// to be evaluated directly; the model evaluations spent; the fits that missed;
/// and the largest check-point miss of the fits kept.
struct RowFits {
    pieces: Vec<(f64, f64, Option<RowFit>)>,
    evaluations: usize,
    missed: usize,
    miss: f64,
}

/// A row of pixels through a pixel-limited cell. Such a cell reached half
/// a pixel in θ still missing the tolerance there (at twilight: where the
/// sky reddens within a pixel as the view rays leave the earth's shadow),
/// yet a row has a single θ, and along it the sky is often smooth in Δφ.
/// `at(t)` evaluates the model on the row at the cell's Δφ coordinate t.
/// On `[0, 1]`, then on halves where that misses, the quadratic through the
/// ends and the middle is checked at the quarter points against the model,
/// in every Rec.709 channel relative to the luminance there (not less than
/// `floor`) — the grid's own check — and kept where both meet `tol`. A piece
/// holding fewer than [`ROW_FIT_MIN_PIXELS`]/2 of the row's pixels (`ts`,
/// their t) is not tried: its pixels are evaluated directly.
fn fit_row(at: &dyn Fn(f64) -> RowPoint, ts: &[f64], tol: f64, floor: f64) -> RowFits {
    let mut out = RowFits {
        pieces: Vec::new(),
        evaluations: 3,
        missed: 0,
        miss: 0.0,
    };
    let (p0, ph, p1) = (at(0.0), at(0.5), at(1.0));
    fit_piece(at, ts, tol, floor, (0.0, 1.0), [p0, ph, p1], &mut out);
    out
}

fn fit_piece(
    at: &dyn Fn(f64) -> RowPoint,
    ts: &[f64],
    tol: f64,
    floor: f64,
    (a, b): (f64, f64),
    [pa, pm, pb]: [RowPoint; 3],
    out: &mut RowFits,
) {
    let pixels = ts.iter().filter(|t| **t >= a && (**t < b || b == 1.0)).count();
    if pixels < ROW_FIT_MIN_PIXELS / 2 {
        out.pieces.push((a, b, None));
        return;
    }
    let k = pa.0.len();
    let fit = (pm.0.len() == k && pb.0.len() == k).then(|| {
        let mut fit = RowFit {
            phases: pa.0.iter().map(|c| c.0).collect(),
            a: vec![[0.0; 3]; k],
            d: vec![[0.0; 3]; k],
            e: vec![[0.0; 3]; k],
        };
        for c in 0..k {
            for ch in 0..3 {
                let (f0, fh, f1) = (pa.0[c].1[ch], pm.0[c].1[ch], pb.0[c].1[ch]);
                let e = 2.0 * (f1 - 2.0 * fh + f0);
                fit.a[c][ch] = f0;
                fit.e[c][ch] = e;
                fit.d[c][ch] = f1 - f0 - e;
            }
        }
        fit
    });
    let (q1, q3) = (at(a + 0.25 * (b - a)), at(a + 0.75 * (b - a)));
    out.evaluations += 2;
    let miss = fit.as_ref().map_or(f64::INFINITY, |fit| {
        [(0.25, &q1), (0.75, &q3)].iter().fold(0.0_f64, |m, (t, (parts, mu))| {
            let truth = total_rgb(parts, *mu);
            let ours = fit.at(*t, *mu);
            let y = luminance(&truth).abs().max(floor);
            // A NaN miss (a NaN from the model) must fail the check, not vanish in `max`.
            (0..3).fold(m, |m, ch| {
                let r = (ours[ch] - truth[ch]).abs() / y;
                if r.is_nan() { f64::INFINITY } else { m.max(r) }
            })
        })
    });
    if miss <= tol {
        out.miss = out.miss.max(miss);
        out.pieces.push((a, b, fit));
        return;
    }
    out.missed += 1;
    let m = 0.5 * (a + b);
    fit_piece(at, ts, tol, floor, (a, m), [pa, q1, pm.clone()], out);
    fit_piece(at, ts, tol, floor, (m, b), [pm, q3, pb], out);
}

fn total_rgb(parts: &[(Option<PhaseFunction>, [f64; 3])], mu: f64) -> [f64; 3] {
    let mut out = [0.0; 3];
    for (p, v) in parts {
        let w = p.map(|p| p.eval(mu)).unwrap_or(1.0);
        for c in 0..3 {
            out[c] += w * v[c];
        }
    }
    out
}

/// The colour path: the model's own Rec.709 path where it has one and
/// `colour` allows it, else its spectra converted per point.
fn decide_colour(model: &dyn SkyModel, tol: f64, colour: ColourPath) -> (Option<RgbEvaluator<'_>>, ColourDecision) {
    let reason = match colour {
        ColourPath::Spectral => "requested".to_string(),
        ColourPath::Auto => match model.rgb_evaluator(MODEL_TOLERANCE_FRACTION * tol) {
            Ok(e) => {
                let decision = ColourDecision {
                    path: e.label.clone(),
                    reason: e.reason.clone(),
                };
                return (Some(e), decision);
            }
            Err(why) => why,
        },
    };
    (
        None,
        ColourDecision {
            path: "spectral".into(),
            reason,
        },
    )
}

/// The model is evaluated to this fraction of the tolerance, so that
/// refinement does not chase quadrature noise.
const MODEL_TOLERANCE_FRACTION: f64 = 0.05;

/// The grid refines until its check points miss by at most this fraction of
/// the tolerance: the check points estimate, not bound, the error between
/// them (at 2048 × 1024 the worst pixel of a grid refined to the full
/// tolerance was up to 1.09 times the tolerance, at −4°).
pub const GRID_TOLERANCE_FRACTION: f64 = 0.8;

/// Builds the world texture of `model`.
pub fn build_world_texture_with(model: &dyn SkyModel, settings: &TextureSettings, options: &BuildOptions) -> WorldTexture {
    build_world_texture_cancellable(model, settings, options, None).expect("never cancelled")
}

/// [`build_world_texture_with`] that stops early, returning `None`, once
/// another thread sets `cancel`: asked before each round of the grid's
/// refinement and before each output row (the Klassen baseline integrator
/// is not interrupted).
pub fn build_world_texture_cancellable(
    model: &dyn SkyModel,
    settings: &TextureSettings,
    options: &BuildOptions,
    cancel: Option<&std::sync::atomic::AtomicBool>,
) -> Option<WorldTexture> {
    // Latched: once seen, a cancel stays seen (a flag cleared again must not
    // let a half left unfinished be used).
    let seen = std::sync::atomic::AtomicBool::new(false);
    let cancelled = || {
        use std::sync::atomic::Ordering::Relaxed;
        if !seen.load(Relaxed) && cancel.is_some_and(|c| c.load(Relaxed)) {
            seen.store(true, Relaxed);
        }
        seen.load(Relaxed)
    };
    let width = settings.width.max(2);
    let height = (width / 2).max(1);
    let sun = model.sun_direction();
    let sun_phi = sun.y.atan2(sun.x);
    let tol = settings.tolerance;
    let direction = |theta: f64, dphi: f64| {
        let (st, ct) = theta.sin_cos();
        let phi = sun_phi + dphi;
        DVec3::new(st * phi.cos(), st * phi.sin(), ct)
    };
    if let Integrator::KlassenCoherence { threshold } = options.integrator {
        if cancelled() {
            return None;
        }
        let tex = build_coherence(model, settings, threshold);
        return (!cancelled()).then_some(tex);
    }
    let (rgb_path, decision) = decide_colour(model, tol, options.colour);
    let grid_tol = GRID_TOLERANCE_FRACTION * tol;
    let model_tol = MODEL_TOLERANCE_FRACTION * tol;
    let eval = |theta: f64, dphi: f64| -> PointEval {
        let d = direction(theta, dphi);
        match &rgb_path {
            Some(e) => (e.eval)(d, model_tol),
            None => {
                let (parts, e) = model.sky_components(d, model_tol);
                sky_rgb(parts, &e)
            }
        }
    };
    let cos_mu = |theta: f64, dphi: f64| direction(theta, dphi).dot(sun);
    let horizon = model.horizon_zenith().clamp(1e-6, PI - 1e-6);
    let mut stats = Stats::default();
    // Each half is evaluated strictly on its own side of the horizon.
    const SIDE: f64 = 1e-9;
    // Cells stop at half an output pixel: θ pixels are π/height, Δφ pixels 2π/width.
    let limits = |theta_span: f64| Limits {
        min_su: ((f64::from(TICKS) * 0.5 * (PI / height as f64) / theta_span) as u32).max(1),
        row_su: ((f64::from(TICKS) * ROW_FIT_MAX_HEIGHT_PX * (PI / height as f64) / theta_span) as u32).max(1),
        min_sv: ((f64::from(TICKS) * 0.5 * (2.0 * PI / width as f64) / PI) as u32).max(1),
        floor_fraction: LUMINANCE_FLOOR_FRACTION,
    };
    let lit = |theta: f64, dphi: f64| model.lit_length(direction(theta, dphi));
    let probe = Probe {
        eval: &eval,
        cos_mu: &cos_mu,
        lit: &lit,
        stop: &cancelled,
    };
    let upper = Half::build(0.0, horizon - SIDE, &probe, grid_tol, &limits(horizon), &mut stats);
    let lower = Half::build(horizon + SIDE, PI, &probe, grid_tol, &limits(PI - horizon), &mut stats);
    if cancelled() {
        return None;
    }

    // Resampling. Pixel (i, j) looks along θ_j = π(j + ½)/H and φ_i = π − 2π(i + ½)/W
    // (Cycles' mapping, `equirect_direction`): Δφ depends on the column only, θ on
    // the row only, and μ = sin θ sin θ_s cos Δφ + cos θ cos θ_s. Columns are
    // precomputed once, rows once each; consecutive pixels mostly share a leaf.
    let theta_s = sun.z.clamp(-1.0, 1.0).acos();
    let (sts, cts) = theta_s.sin_cos();
    // Per column: Δφ, cos Δφ and Δφ in ticks (the same in both halves).
    let columns: Vec<(f64, f64, f64)> = (0..width)
        .map(|i| {
            let phi = PI - 2.0 * PI * (i as f64 + 0.5) / width as f64;
            let mut dphi = (phi - sun_phi).rem_euclid(2.0 * PI);
            if dphi > PI {
                dphi = 2.0 * PI - dphi;
            }
            (dphi, dphi.cos(), upper.ticks(0.0, dphi).1)
        })
        .collect();
    let cos_dphi: Vec<f64> = columns.iter().map(|c| c.1).collect();
    let mut rgb: Vec<[f32; 3]> = vec![[0.0; 3]; width * height];
    let direct = std::sync::atomic::AtomicUsize::new(0);
    let (row_fits, row_fits_missed, row_fitted, row_fit_evaluations) = (
        std::sync::atomic::AtomicUsize::new(0),
        std::sync::atomic::AtomicUsize::new(0),
        std::sync::atomic::AtomicUsize::new(0),
        std::sync::atomic::AtomicUsize::new(0),
    );
    // Largest check-point miss of the row fits, as f64 bits (non-negative floats order as their bits).
    let row_miss = std::sync::atomic::AtomicU64::new(0);
    let row_floor = (LUMINANCE_FLOOR_FRACTION * stats.brightest).max(1e-300);
    rgb.par_chunks_mut(width).enumerate().for_each_init(
        || {
            (
                vec![0.0; width],
                vec![0.0; MAX_COMPONENTS * width],
                Vec::<((u64, u64), RowFits)>::new(),
            )
        },
        |(mu, weights, fitted), (j, row)| {
            if cancelled() {
                return;
            }
            fitted.clear();
            let theta = PI * (j as f64 + 0.5) / height as f64;
            let (st, ct) = theta.sin_cos();
            let half = if theta <= horizon { &upper } else { &lower };
            let fu = half.ticks(theta, 0.0).0;
            let k = half.comps.k().min(MAX_COMPONENTS);
            // μ and the phase weights of the whole row first (loops that vectorise).
            let (mu_a, mu_b) = (st * sts, ct * cts);
            for (m, c) in mu.iter_mut().zip(&cos_dphi) {
                *m = (mu_a * c + mu_b).clamp(-1.0, 1.0);
            }
            for (c, phase) in half.comps.phases.iter().take(k).enumerate() {
                phase_weights(*phase, mu, &mut weights[c * width..(c + 1) * width]);
            }
            // Consecutive pixels of a row mostly share a leaf: within it the row is a
            // fixed θ, so the bilinear interpolant is linear in Δφ — precomputed per run.
            let mut i = 0;
            while i < width {
                let l = half.find(fu, columns[i].2);
                if l.kind == LeafKind::PixelLimited {
                    // A step in the sky (the earth's shadow edge): interpolating across it
                    // would miss the tolerance. Along this row (one θ) the sky may still be
                    // smooth in Δφ: a long enough run is fitted from five points on the row
                    // ([`fit_row`]); where that misses, each pixel centre is evaluated directly.
                    let mut n = 1;
                    while i + n < width && l.contains(fu, columns[i + n].2) {
                        n += 1;
                    }
                    // Each pixel's Δφ coordinate t across the cell.
                    let ts: Vec<f64> = (i..i + n).map(|px| ((columns[px].2 - l.v0) / l.sv).clamp(0.0, 1.0)).collect();
                    // A row crosses each Δφ twice (either side of the sun's
                    // vertical): the second run through the same cell reuses
                    // the first one's fits (they are functions of Δφ alone).
                    let key = (l.u0.to_bits(), l.v0.to_bits());
                    let fresh = n >= ROW_FIT_MIN_PIXELS && !fitted.iter().any(|f| f.0 == key);
                    if fresh {
                        let at = |t: f64| {
                            let dphi = Half::dphi_ticks(l.v0 + t * l.sv);
                            (eval(theta, dphi).0, (mu_a * dphi.cos() + mu_b).clamp(-1.0, 1.0))
                        };
                        fitted.push((key, fit_row(&at, &ts, grid_tol, row_floor)));
                    }
                    let fits = if n >= ROW_FIT_MIN_PIXELS {
                        fitted.iter().find(|f| f.0 == key).map(|f| &f.1)
                    } else {
                        None
                    };
                    let mut direct_here = 0;
                    for (px, &t) in (i..i + n).zip(&ts) {
                        let piece = fits
                            .and_then(|f| f.pieces.iter().find(|(a, b, _)| t >= *a && (t < *b || *b == 1.0)))
                            .and_then(|(a, b, fit)| fit.as_ref().map(|fit| (fit, (t - a) / (b - a))));
                        row[px] = match piece {
                            Some((fit, tt)) => fit.at(tt, mu[px]),
                            None => {
                                direct_here += 1;
                                total_rgb(&eval(theta, columns[px].0).0, mu[px])
                            }
                        }
                        .map(|v| v as f32);
                    }
                    direct.fetch_add(direct_here, std::sync::atomic::Ordering::Relaxed);
                    if let Some(f) = fits {
                        use std::sync::atomic::Ordering::Relaxed;
                        row_fitted.fetch_add(n - direct_here, Relaxed);
                        if fresh {
                            row_fits.fetch_add(f.pieces.iter().filter(|p| p.2.is_some()).count(), Relaxed);
                            row_fits_missed.fetch_add(f.missed, Relaxed);
                            row_fit_evaluations.fetch_add(f.evaluations, Relaxed);
                            row_miss.fetch_max(f.miss.to_bits(), Relaxed);
                        }
                    }
                    i += n;
                    continue;
                }
                let run = half.row_run(&l, fu);
                let (v0, inv_sv) = (l.v0, 1.0 / l.sv);
                loop {
                    let t = ((columns[i].2 - v0) * inv_sv).clamp(0.0, 1.0);
                    let mut out = [0.0; 3];
                    // ℓ⁺ at the pixel for a lit leaf (exactly 0 where its ray is all in the shadow).
                    let scale = if run.lit {
                        model.lit_length(direction(theta, columns[i].0)).map_or(0.0, |l| l.max(0.0))
                    } else {
                        1.0
                    };
                    for c in 0..k {
                        let mut w = weights[c * width + i] * scale;
                        if run.log[c] {
                            w *= exp_neg(-(run.la[c] + t * (run.ld[c] + t * run.le[c])));
                        }
                        for ch in 0..3 {
                            out[ch] += w * (run.a[c][ch] + t * (run.d[c][ch] + t * run.e[c][ch]));
                        }
                    }
                    row[i] = out.map(|v| v as f32);
                    i += 1;
                    if i == width || !l.contains(fu, columns[i].2) {
                        break;
                    }
                }
            }
        },
    );

    if cancelled() {
        return None;
    }
    let (sun_pixels, sun_rgb, gamut_clipped_pixels) = add_sun_disc(model, settings, width, height, &mut rgb);
    Some(WorldTexture {
        width,
        height,
        rgb,
        evaluations: stats.evaluations,
        cells: upper.cells() + lower.cells(),
        interpolation_error: stats.interpolation.max(f64::from_bits(row_miss.into_inner())),
        model_error: stats.model_error,
        pixel_limited_cells: stats.pixel_limited,
        pixel_limited_error: stats.pixel_limited_error,
        sun_pixels,
        sun_rgb_irradiance: sun_rgb,
        gamut_clipped_pixels,
        colour: decision,
        integrator: options.integrator,
        first_estimates: 0,
        direct_pixels: direct.into_inner(),
        row_fits: row_fits.into_inner(),
        row_fits_missed: row_fits_missed.into_inner(),
        row_fitted_pixels: row_fitted.into_inner(),
        row_fit_evaluations: row_fit_evaluations.into_inner(),
        shadowed_points: stats.in_shadow,
    })
}

/// Klassen's pixel-coherence baseline ([`Integrator::KlassenCoherence`]): rows in
/// parallel, pixels of a row in order.
fn build_coherence(model: &dyn SkyModel, settings: &TextureSettings, threshold: f64) -> WorldTexture {
    let width = settings.width.max(2);
    let height = (width / 2).max(1);
    let tol = settings.tolerance;
    let threshold = if threshold.is_finite() { threshold.clamp(1e-6, 0.5) } else { tol };
    let mut rgb: Vec<[f32; 3]> = vec![[0.0; 3]; width * height];
    let counts: Vec<(usize, usize, f64)> = rgb
        .par_chunks_mut(width)
        .enumerate()
        .map(|(j, row)| {
            let (mut full, mut firsts, mut model_err) = (0usize, 0usize, 0.0f64);
            // (first estimate of the reused pixel, its result)
            let mut anchor: Option<([f64; 3], [f32; 3])> = None;
            for (i, px) in row.iter_mut().enumerate() {
                let d = equirect_direction(i as f64 + 0.5, j as f64 + 0.5, width, height);
                let first = spectrum::spectrum_to_rec709(&model.first_estimate(d));
                firsts += 1;
                if let Some((a, v)) = anchor {
                    let scale = luminance(&a).abs().max(1e-300);
                    if (0..3).all(|c| (first[c] - a[c]).abs() <= threshold * scale) {
                        *px = v;
                        continue;
                    }
                }
                let (l, e) = model.baseline_radiance(d, tol);
                full += 1;
                let v = spectrum::spectrum_to_rec709(&l);
                let y = luminance(&v).abs();
                if y > 0.0 {
                    model_err = model_err.max(spectrum::spectrum_to_xyz(&e.map(f64::abs))[1] / y);
                }
                *px = v.map(|x| x as f32);
                anchor = Some((first, *px));
            }
            (full, firsts, model_err)
        })
        .collect();
    let (sun_pixels, sun_rgb, gamut_clipped_pixels) = add_sun_disc(model, settings, width, height, &mut rgb);
    WorldTexture {
        width,
        height,
        rgb,
        evaluations: counts.iter().map(|c| c.0).sum(),
        cells: 0,
        interpolation_error: f64::NAN,
        model_error: counts.iter().fold(0.0, |m, c| m.max(c.2)),
        pixel_limited_cells: 0,
        pixel_limited_error: 0.0,
        sun_pixels,
        sun_rgb_irradiance: sun_rgb,
        gamut_clipped_pixels,
        colour: ColourDecision {
            path: "spectral".into(),
            reason: "Klassen's coherence baseline is spectral at every evaluated pixel".into(),
        },
        integrator: Integrator::KlassenCoherence { threshold },
        first_estimates: counts.iter().map(|c| c.1).sum(),
        direct_pixels: 0,
        row_fits: 0,
        row_fits_missed: 0,
        row_fitted_pixels: 0,
        row_fit_evaluations: 0,
        shadowed_points: 0,
    }
}

/// A linear Rec.709 colour with no negative channel and the same luminance
/// (0.2126 R + 0.7152 G + 0.0722 B): desaturated towards its grey just far
/// enough; black where the luminance itself is ≤ 0. A deep-red setting sun's
/// spectrum lies outside Rec.709 (its blue came out −1.9 W·m⁻²), and a world
/// texture with negative radiance makes Cycles emit negative light.
pub fn clip_to_gamut(c: [f64; 3]) -> [f64; 3] {
    if c.iter().all(|v| *v >= 0.0) {
        return c;
    }
    let y = luminance(&c);
    if y.is_nan() || y <= 0.0 {
        return [0.0; 3];
    }
    let t = c.iter().filter(|v| **v < 0.0).map(|v| y / (y - v)).fold(1.0, f64::min);
    c.map(|v| (y + t * (v - y)).max(0.0))
}

/// The sun's limb darkening `1 − u(1 − μ')` at `rho` = (angle from the
/// disc's centre) / (its angular radius), μ' = √(1 − ρ²).
const LIMB_U: f64 = 0.6;
fn limb(rho: f64) -> f64 {
    1.0 - LIMB_U * (1.0 - (1.0 - rho * rho).max(0.0).sqrt())
}

/// The limb-weighted fraction of the sun's disc (centre `sun`, angular
/// radius `radius`) above the horizon at zenith angle `horizon`: 1 or 0 unless
/// the horizon crosses the disc, then a 64 × 64 polar quadrature.
fn disc_fraction_above(sun: DVec3, radius: f64, horizon: f64) -> f64 {
    let zenith = sun.z.clamp(-1.0, 1.0).acos();
    if radius <= 0.0 {
        return if zenith <= horizon { 1.0 } else { 0.0 };
    }
    if zenith + radius <= horizon {
        return 1.0;
    }
    if zenith - radius >= horizon {
        return 0.0;
    }
    let u = if sun.z.abs() < 1.0 - 1e-12 {
        sun.cross(DVec3::Z).normalize()
    } else {
        DVec3::X
    };
    let v = sun.cross(u);
    let (n, mut above, mut all) = (64, 0.0, 0.0);
    for i in 0..n {
        let rho = (i as f64 + 0.5) / n as f64;
        let (sa, ca) = (rho * radius).sin_cos();
        let w = limb(rho) * rho;
        for k in 0..n {
            let (sp, cp) = (2.0 * PI * (k as f64 + 0.5) / n as f64).sin_cos();
            let d = sun * ca + (u * cp + v * sp) * sa;
            all += w;
            if d.z.clamp(-1.0, 1.0).acos() <= horizon {
                above += w;
            }
        }
    }
    above / all
}

/// The sun: its irradiance after the atmosphere, as RGB for a sun lamp, and
/// optionally its disc added to `rgb`. Returns (disc pixels, RGB irradiance,
/// pixels whose colour had to be brought into Rec.709).
///
/// Every pixel is first brought into Rec.709 ([`clip_to_gamut`]), and so is
/// the sun's colour. Where the horizon crosses the disc, only the part above
/// it shines: the lamp's irradiance is scaled by that part's limb-weighted
/// share (the atmosphere's transmittance is still the disc centre's), and the
/// disc is drawn above the horizon only. The disc's pixels carry exactly that
/// irradiance: each pixel's share is its solid-angle-weighted, limb-darkened
/// coverage (8 × 8 subsamples weighted by sin θ), divided by the pixel's exact
/// solid angle. (Subsamples equal in pixel coordinates once made the disc
/// 6.3× too bright at the zenith at 256 px; a disc that falls between every
/// subsample of a coarse texture now lights the pixel holding it.)
fn add_sun_disc(
    model: &dyn SkyModel,
    settings: &TextureSettings,
    width: usize,
    height: usize,
    rgb: &mut [[f32; 3]],
) -> (usize, [f64; 3], usize) {
    let mut clipped = 0;
    for px in rgb.iter_mut() {
        if px.iter().any(|v| *v < 0.0) {
            clipped += 1;
            *px = clip_to_gamut(px.map(f64::from)).map(|v| v as f32);
        }
    }
    let sun = model.sun_direction();
    let sun_spec = model.sun_irradiance();
    let radius = 0.5 * model.sun_angular_diameter();
    let horizon = model.horizon_zenith();
    let visible = disc_fraction_above(sun, radius, horizon);
    let sun_rgb = clip_to_gamut(spectrum::spectrum_to_rec709(&sun_spec)).map(|v| v * visible);
    let mut sun_pixels = 0;
    if !(settings.sun_disc && radius > 0.0 && sun_rgb.iter().any(|v| *v > 0.0)) {
        return (sun_pixels, sun_rgb, clipped);
    }
    let disc_value = |d: DVec3| -> f64 {
        let ang = d.angle_between(sun);
        if ang > radius || d.z.clamp(-1.0, 1.0).acos() > horizon {
            return 0.0;
        }
        limb(ang / radius)
    };
    let pixel_angle = 2.0 * PI / width as f64;
    let reach = radius + 1.5 * pixel_angle;
    // Pixels whose centre is within reach of the disc: only the rows around
    // the sun's zenith angle can hold any; supersample those 8×8.
    let theta_s = sun.z.clamp(-1.0, 1.0).acos();
    let row_of = |theta: f64| theta / PI * height as f64;
    let j0 = row_of((theta_s - reach - pixel_angle).max(0.0)).floor().max(0.0) as usize;
    let j1 = (row_of((theta_s + reach + pixel_angle).min(PI)).ceil() as usize).min(height);
    let candidates: Vec<usize> = (j0..j1)
        .flat_map(|j| (0..width).map(move |i| j * width + i))
        .filter(|&p| {
            equirect_direction((p % width) as f64 + 0.5, (p / width) as f64 + 0.5, width, height).angle_between(sun) <= reach + pixel_angle
        })
        .collect();
    let mut cover: Vec<(usize, f64)> = Vec::new();
    for p in candidates {
        let (i, j) = ((p % width) as f64, (p / width) as f64);
        let mut acc = 0.0;
        for b in 0..8 {
            let y = j + (f64::from(b) + 0.5) / 8.0;
            let sin_theta = (PI * y / height as f64).sin();
            for a in 0..8 {
                let d = equirect_direction(i + (f64::from(a) + 0.5) / 8.0, y, width, height);
                acc += disc_value(d) * sin_theta;
            }
        }
        if acc > 0.0 {
            cover.push((p, acc));
        }
    }
    if cover.is_empty() {
        // The disc fell between every subsample: the pixel holding its centre
        // (or, set partly, the point of it just above the horizon) takes it.
        let d = if theta_s <= horizon {
            sun
        } else {
            let up = (DVec3::Z - sun * sun.z).normalize_or(DVec3::X);
            (sun * (theta_s - horizon).cos() + up * (theta_s - horizon).sin()).normalize()
        };
        let x = ((PI - d.y.atan2(d.x)) / (2.0 * PI) * width as f64).rem_euclid(width as f64);
        let mut y = d.z.clamp(-1.0, 1.0).acos() / PI * height as f64;
        // (Not a row wholly below the horizon: a point on the horizon itself
        // falls on the boundary between the rows above and below it.)
        let last_row_above = ((horizon / PI * height as f64).ceil() - 1.0).max(0.0);
        y = y.min(last_row_above + 0.5).min(height as f64 - 0.5);
        cover.push(((y as usize).min(height - 1) * width + (x as usize).min(width - 1), 1.0));
    }
    let total: f64 = cover.iter().map(|c| c.1).sum();
    for (p, acc) in cover {
        let j = (p / width) as f64;
        let pixel_solid_angle = 2.0 * PI / width as f64 * ((PI * j / height as f64).cos() - (PI * (j + 1.0) / height as f64).cos());
        let share = acc / total / pixel_solid_angle;
        sun_pixels += 1;
        for k in 0..3 {
            rgb[p][k] += (sun_rgb[k] * share) as f32;
        }
    }
    (sun_pixels, sun_rgb, clipped)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spectrum::SPECTRAL_SAMPLES;

    /// A smooth toy sky with a sharp sun glow, spectral and cheap.
    pub(super) struct Toy {
        pub(super) sun: DVec3,
    }
    impl SkyModel for Toy {
        fn sky_radiance(&self, d: DVec3, _tol: f64) -> (Spectrum, Spectrum) {
            let mu = d.dot(self.sun);
            let glow = 0.05 / (1.0 + 0.81 - 1.8 * mu).powf(1.5);
            let horizon = if d.z >= 0.0 { 1.0 + 2.0 * (-d.z * 8.0).exp() } else { 0.2 };
            let wl = spectrum::wavelengths_nm();
            let mut s = [0.0; SPECTRAL_SAMPLES];
            for (k, l) in wl.iter().enumerate() {
                s[k] = (glow + 0.01 * horizon * (550.0 / l).powi(4)) * 1e-2;
            }
            (s, [0.0; SPECTRAL_SAMPLES])
        }
        fn sky_components(&self, d: DVec3, _tol: f64) -> (Vec<(Option<PhaseFunction>, Spectrum)>, Spectrum) {
            // glow = 0.05·(1.81 − 1.8μ)^-1.5 = 0.05·4π/(1 − 0.81)·p_HG(μ; g = 0.9).
            let k = 0.05 * 4.0 * PI / (1.0 - 0.81);
            let horizon = if d.z >= 0.0 { 1.0 + 2.0 * (-d.z * 8.0).exp() } else { 0.2 };
            let wl = spectrum::wavelengths_nm();
            let mut mie = [0.0; SPECTRAL_SAMPLES];
            let mut rest = [0.0; SPECTRAL_SAMPLES];
            for (i, l) in wl.iter().enumerate() {
                mie[i] = k * 1e-2;
                rest[i] = 0.01 * horizon * (550.0 / l).powi(4) * 1e-2;
            }
            (
                vec![(Some(PhaseFunction::HenyeyGreenstein { g: 0.9 }), mie), (None, rest)],
                [0.0; SPECTRAL_SAMPLES],
            )
        }
        fn sun_direction(&self) -> DVec3 {
            self.sun
        }
        fn sun_irradiance(&self) -> Spectrum {
            *spectrum::solar_spectral_irradiance()
        }
        fn sun_angular_diameter(&self) -> f64 {
            0.545f64.to_radians()
        }
    }

    /// A toy twilight: zero where a synthetic sunlit length ℓ ≤ 0 (views
    /// below a curve from the horizon towards the sun up to 11.5° away
    /// from it, and everything below the horizon),
    /// ℓ × a smooth spectrum beyond — the kink of the earth's shadow, with
    /// (`hint`) and without telling the grid about ℓ.
    struct Twilight {
        hint: bool,
    }
    impl Twilight {
        const SUN_ELEVATION: f64 = -0.07;
        /// ℓ, m: 100 km × (z − 0.1·(1 − x)), continuous over the sphere (the sun towards +x).
        fn lit(d: DVec3) -> f64 {
            1e5 * (d.z - 0.1 * (1.0 - d.x))
        }
    }
    impl SkyModel for Twilight {
        fn sky_radiance(&self, d: DVec3, _tol: f64) -> (Spectrum, Spectrum) {
            let smooth = (-3.0 * d.z).exp() * (1.0 + 0.5 * d.x);
            let scale = Self::lit(d).max(0.0) * smooth * 1e-6;
            let wl = spectrum::wavelengths_nm();
            (std::array::from_fn(|i| scale * (550.0 / wl[i]).powi(4)), [0.0; SPECTRAL_SAMPLES])
        }
        fn sun_direction(&self) -> DVec3 {
            let (s, c) = Self::SUN_ELEVATION.sin_cos();
            DVec3::new(c, 0.0, s)
        }
        fn sun_irradiance(&self) -> Spectrum {
            [0.0; SPECTRAL_SAMPLES]
        }
        fn sun_angular_diameter(&self) -> f64 {
            0.545f64.to_radians()
        }
        fn lit_length(&self, d: DVec3) -> Option<f64> {
            self.hint.then(|| Self::lit(d))
        }
    }

    #[test]
    fn lit_length_cells_follow_the_kink_of_the_shadow() {
        let settings = TextureSettings {
            width: 512,
            tolerance: 1e-3,
            sun_disc: false,
        };
        let run = |hint: bool| {
            let model = Twilight { hint };
            let t = build_world_texture(&model, &settings);
            let (worst_y, worst_uv, _) = worst_pixel_errors(&t.rgb, &exact_xyz(&model, t.width, t.height));
            eprintln!(
                "twilight toy, ℓ {}: {} evaluations, {} shadowed points, {} cells, {} at the pixel size ({} direct pixels, {} fitted along their rows with {} evaluations); worst luminance {worst_y:.2e}, Δu′v′ {worst_uv:.2e}",
                if hint { "known" } else { "unknown" },
                t.evaluations,
                t.shadowed_points,
                t.cells,
                t.pixel_limited_cells,
                t.direct_pixels,
                t.row_fitted_pixels,
                t.row_fit_evaluations
            );
            (t, worst_y, worst_uv)
        };
        let (plain, y0, uv0) = run(false);
        let (lit, y1, uv1) = run(true);
        for (y, uv) in [(y0, uv0), (y1, uv1)] {
            assert!(y <= 1e-3 && uv <= 1e-3, "luminance {y:.2e}, Δu′v′ {uv:.2e}");
        }
        // Without ℓ the kink is refined to the pixel size and its pixels are
        // evaluated directly or fitted along their rows; with it the cells
        // across the kink interpolate (measured: 6 976 → 1 536 pixels in cells
        // at the pixel size or left to row fits, 4 139 → 2 262 model calls;
        // before cells two rows tall were left to the row fits: 739 → 131
        // pixels, 7 114 → 2 208 calls).
        assert_eq!(plain.shadowed_points, 0);
        assert!(lit.shadowed_points > 0);
        let calls = |t: &WorldTexture| t.evaluations + t.direct_pixels + t.row_fit_evaluations;
        let limited = |t: &WorldTexture| t.direct_pixels + t.row_fitted_pixels;
        assert!(
            limited(&lit) * 4 <= limited(&plain) && calls(&lit) * 3 <= calls(&plain) * 2,
            "pixels in cells at the pixel size {} vs {}, model calls {} vs {}",
            limited(&lit),
            limited(&plain),
            calls(&lit),
            calls(&plain)
        );
    }

    /// A sky with a step in θ far narrower than a pixel (a band 20° above the
    /// horizon brightens five-fold within 0.01°) and smooth in Δφ, in two
    /// components: one isotropic, one with the Rayleigh phase function about
    /// a sun 30° high (so μ changes along every row).
    struct Ledge;
    impl Ledge {
        const SUN: DVec3 = DVec3::new(0.866_025_403_784_438_6, 0.0, 0.5);
        fn parts(d: DVec3) -> (Spectrum, Spectrum) {
            let elevation = d.z.clamp(-1.0, 1.0).asin().to_degrees();
            let step = 1.0 + 2.0 * (1.0 + ((elevation - 20.0) / 0.01).tanh());
            let azimuth = d.y.atan2(d.x);
            let scale = step * (1.0 + 0.3 * azimuth.cos() + 0.1 * (2.0 * azimuth).sin().abs()) * 1e-3;
            let wl = spectrum::wavelengths_nm();
            (
                std::array::from_fn(|i| scale * (550.0 / wl[i]).powf(2.0 + elevation / 90.0)),
                std::array::from_fn(|i| 0.7 * scale * (550.0 / wl[i]).powi(4)),
            )
        }
    }
    impl SkyModel for Ledge {
        fn sky_radiance(&self, d: DVec3, _tol: f64) -> (Spectrum, Spectrum) {
            let (iso, ray) = Self::parts(d);
            let p = PhaseFunction::Rayleigh.eval(d.normalize().dot(Self::SUN));
            (std::array::from_fn(|i| iso[i] + p * ray[i]), [0.0; SPECTRAL_SAMPLES])
        }
        fn sky_components(&self, d: DVec3, _tol: f64) -> (Vec<(Option<PhaseFunction>, Spectrum)>, Spectrum) {
            let (iso, ray) = Self::parts(d);
            (vec![(None, iso), (Some(PhaseFunction::Rayleigh), ray)], [0.0; SPECTRAL_SAMPLES])
        }
        fn sun_direction(&self) -> DVec3 {
            Self::SUN
        }
        fn sun_irradiance(&self) -> Spectrum {
            [0.0; SPECTRAL_SAMPLES]
        }
        fn sun_angular_diameter(&self) -> f64 {
            0.545f64.to_radians()
        }
    }

    #[test]
    fn rows_through_a_step_are_fitted_along_the_row() {
        // The grid stops at half a pixel across the step; the rows in those
        // cells have one θ each and a smooth sky along them, so they are
        // fitted (and checked) along Δφ instead of evaluated per pixel.
        let settings = TextureSettings {
            width: 512,
            tolerance: 1e-3,
            sun_disc: false,
        };
        let model = Ledge;
        let t = build_world_texture(&model, &settings);
        let w = t.width;
        let (worst_y, worst_uv, _) = worst_pixel_errors(&t.rgb, &exact_xyz(&model, t.width, t.height));
        eprintln!(
            "ledge: {} evaluations, {} cells at the pixel size, {} row fits ({} missed) covering {} pixels with {} evaluations, {} direct pixels; worst luminance {worst_y:.2e}, Δu′v′ {worst_uv:.2e}",
            t.evaluations,
            t.pixel_limited_cells,
            t.row_fits,
            t.row_fits_missed,
            t.row_fitted_pixels,
            t.row_fit_evaluations,
            t.direct_pixels
        );
        assert!(worst_y <= 1e-3 && worst_uv <= 1e-3, "luminance {worst_y:.2e}, Δu′v′ {worst_uv:.2e}");
        assert!(t.pixel_limited_cells > 0, "the step must reach the pixel size");
        // The rows across the step (one or two of the 256) are fitted, not evaluated per pixel.
        assert!(
            t.row_fitted_pixels >= w && t.direct_pixels * 10 <= t.row_fitted_pixels,
            "{} fitted, {} direct",
            t.row_fitted_pixels,
            t.direct_pixels
        );
        assert!(
            t.row_fit_evaluations * 4 <= t.row_fitted_pixels,
            "{} evaluations for {} pixels",
            t.row_fit_evaluations,
            t.row_fitted_pixels
        );
        assert!(t.row_fits > 0);
    }

    #[test]
    fn row_phase_weights_equal_the_phase_functions() {
        let mu: Vec<f64> = (0..=400).map(|i| -1.0 + i as f64 / 200.0).collect();
        let mut out = vec![0.0; mu.len()];
        for p in [
            None,
            Some(PhaseFunction::Rayleigh),
            Some(PhaseFunction::CornetteShanks { g: 0.8 }),
            Some(PhaseFunction::HenyeyGreenstein { g: 0.9 }),
        ] {
            phase_weights(p, &mu, &mut out);
            for (m, o) in mu.iter().zip(&out) {
                let want = p.map(|p| p.eval(*m)).unwrap_or(1.0);
                assert!((o - want).abs() <= 1e-15 * want, "{p:?} μ {m}: {o} vs {want}");
            }
        }
    }

    #[test]
    fn interpolated_texture_meets_the_tolerance_at_every_pixel() {
        let toy = Toy {
            sun: DVec3::new(0.3, 0.8, 0.25).normalize(),
        };
        let tol = 1e-3;
        let t = build_world_texture(
            &toy,
            &TextureSettings {
                width: 256,
                tolerance: tol,
                sun_disc: false,
            },
        );
        let mut worst = 0.0f64;
        for j in 0..t.height {
            for i in 0..t.width {
                let d = equirect_direction(i as f64 + 0.5, j as f64 + 0.5, t.width, t.height);
                let exact = spectrum::spectrum_to_rec709(&toy.sky_radiance(d, 0.0).0);
                let y = luminance(&exact);
                for k in 0..3 {
                    worst = worst.max((f64::from(t.rgb[j * t.width + i][k]) - exact[k]).abs() / y);
                }
            }
        }
        eprintln!(
            "toy sky: worst pixel error {worst:.3e} (reported {:.3e}), {} evaluations, {} cells",
            t.interpolation_error, t.evaluations, t.cells
        );
        // The measured error between nodes is an estimate; allow it a factor 4 at pixels.
        assert!(
            worst <= 4.0 * tol,
            "worst pixel error {worst:.3e}, reported {:.3e}",
            t.interpolation_error
        );
        assert!(
            t.evaluations < t.width * t.height / 4,
            "{} evaluations for {} pixels",
            t.evaluations,
            t.width * t.height
        );
    }

    /// A sky biquadratic in the zenith angle θ and the azimuth from the sun
    /// Δφ on each side of the horizon (the Δφ terms vanish at the zenith and
    /// the nadir, where Δφ is undefined).
    struct Biquadratic;
    impl Biquadratic {
        fn spectrum(d: DVec3) -> Spectrum {
            let theta = d.z.clamp(-1.0, 1.0).acos();
            let sun = Biquadratic.sun_direction();
            let mut dphi = (d.y.atan2(d.x) - sun.y.atan2(sun.x)).rem_euclid(2.0 * PI);
            if dphi > PI {
                dphi = 2.0 * PI - dphi;
            }
            let y = if d.z >= 0.0 {
                1.0 + 3.0 * theta * theta + 0.5 * theta * dphi * dphi
            } else {
                0.5 + (theta - 2.0).powi(2) + 0.2 * (PI - theta) * dphi * dphi
            };
            let wl = spectrum::wavelengths_nm();
            std::array::from_fn(|i| y * 1e-2 * (550.0 / wl[i]).powi(2))
        }
    }
    impl SkyModel for Biquadratic {
        fn sky_radiance(&self, d: DVec3, _tol: f64) -> (Spectrum, Spectrum) {
            (Self::spectrum(d), [0.0; SPECTRAL_SAMPLES])
        }
        fn sky_components(&self, d: DVec3, _tol: f64) -> (Vec<(Option<PhaseFunction>, Spectrum)>, Spectrum) {
            (vec![(None, Self::spectrum(d))], [0.0; SPECTRAL_SAMPLES])
        }
        fn sun_direction(&self) -> DVec3 {
            DVec3::new(0.0, 0.6, 0.8)
        }
        fn sun_irradiance(&self) -> Spectrum {
            *spectrum::solar_spectral_irradiance()
        }
        fn sun_angular_diameter(&self) -> f64 {
            0.545f64.to_radians()
        }
    }

    /// A sky biquadratic in (θ, Δφ) is reproduced by the root cells
    /// themselves, made quadratic in θ and then in Δφ after the checks at
    /// their quarter points (a bilinear root cell misses it by a few per
    /// cent), and every pixel is exact to rounding, even at a tolerance of 1e-9.
    #[test]
    fn quadratic_cells_reproduce_a_biquadratic_sky() {
        let t = build_world_texture(
            &Biquadratic,
            &TextureSettings {
                width: 512,
                // Only an exact interpolant meets this: every cell is refined
                // or made quadratic until it reproduces the sky to rounding.
                tolerance: 1e-9,
                sun_disc: false,
            },
        );
        let mut worst = 0.0f64;
        for j in 0..t.height {
            for i in (0..t.width).step_by(7) {
                let d = equirect_direction(i as f64 + 0.5, j as f64 + 0.5, t.width, t.height);
                let exact = spectrum::spectrum_to_rec709(&Biquadratic::spectrum(d));
                let y = luminance(&exact);
                for k in 0..3 {
                    worst = worst.max((f64::from(t.rgb[j * t.width + i][k]) - exact[k]).abs() / y);
                }
            }
        }
        eprintln!(
            "biquadratic sky: {} cells, {} evaluations, worst pixel {worst:.2e}",
            t.cells, t.evaluations
        );
        assert_eq!(t.cells, 2 * 64, "every root cell should be a biquadratic leaf");
        assert!(t.interpolation_error < 1e-9, "reported {:.2e}", t.interpolation_error);
        // f32 storage: 6e-8 relative.
        assert!(worst < 1e-6, "worst pixel error {worst:.2e}");
    }

    /// Largest error, relative to luminance, of a 128-px texture at every 3rd
    /// pixel of the upper hemisphere against the model evaluated directly to 1e-8.
    fn worst_pixel_error(model: &dyn SkyModel, tol: f64, label: &str) -> f64 {
        let t = build_world_texture(
            model,
            &TextureSettings {
                width: 128,
                tolerance: tol,
                sun_disc: false,
            },
        );
        let mut worst = 0.0f64;
        for j in (0..t.height / 2).step_by(3) {
            for i in (0..t.width).step_by(3) {
                let d = equirect_direction(i as f64 + 0.5, j as f64 + 0.5, t.width, t.height);
                let exact = spectrum::spectrum_to_rec709(&model.sky_radiance(d, 1e-8).0);
                let y = luminance(&exact);
                for k in 0..3 {
                    worst = worst.max((f64::from(t.rgb[j * t.width + i][k]) - exact[k]).abs() / y);
                }
            }
        }
        eprintln!(
            "{label}: worst pixel {worst:.3e}, reported {:.3e}, {} evaluations",
            t.interpolation_error, t.evaluations
        );
        worst
    }

    #[test]
    fn atmosphere_texture_matches_direct_evaluation() {
        use crate::sky::atmosphere::AtmosphereParams;
        for elevation in [40.0f64, 5.0] {
            let atm = AtmosphereParams {
                sun_elevation_rad: elevation.to_radians(),
                sun_rotation_rad: 0.7,
                ..Default::default()
            };
            let worst = worst_pixel_error(&atm, 1e-3, &format!("atmosphere, sun {elevation}°"));
            assert!(worst <= 2e-3, "sun {elevation}°: worst pixel error {worst:.3e}");
        }
    }

    #[test]
    fn klassen_texture_matches_direct_evaluation() {
        use crate::sky::klassen::{KlassenParams, KlassenSky, KlassenWorld};
        let world = KlassenWorld {
            sky: KlassenSky::new(KlassenParams::default()).unwrap_or_else(|e| panic!("{e:?}")),
            sun: crate::sky::blender_sun_direction(25f64.to_radians(), 0.4),
            sun_diameter_rad: 0.545f64.to_radians(),
        };
        let worst = worst_pixel_error(&world, 1e-3, "klassen");
        assert!(worst <= 2e-3, "worst pixel error {worst:.3e}");
    }

    const ELEVATIONS: [f64; 8] = [-4.0, 0.0, 2.0, 5.0, 10.0, 20.0, 40.0, 80.0];

    fn atmosphere(elevation_deg: f64) -> crate::sky::atmosphere::AtmosphereParams {
        crate::sky::atmosphere::AtmosphereParams {
            sun_elevation_rad: elevation_deg.to_radians(),
            sun_rotation_rad: 0.7,
            ..Default::default()
        }
    }

    fn klassen(elevation_deg: f64) -> crate::sky::klassen::KlassenWorld {
        use crate::sky::klassen::{KlassenParams, KlassenSky, KlassenWorld};
        KlassenWorld {
            sky: KlassenSky::new(KlassenParams::default()).unwrap_or_else(|e| panic!("{e:?}")),
            sun: crate::sky::blender_sun_direction(elevation_deg.to_radians(), 0.7),
            sun_diameter_rad: 0.545f64.to_radians(),
        }
    }

    fn uv(xyz: [f64; 3]) -> (f64, f64) {
        let d = xyz[0] + 15.0 * xyz[1] + 3.0 * xyz[2];
        (4.0 * xyz[0] / d, 9.0 * xyz[1] / d)
    }

    /// The atmosphere's Rec.709 path (colour sums from the table over the
    /// columns) against its spectral path converted per point, on a dense set
    /// of directions (both hemispheres) at the 8 elevations: the difference
    /// of the two (both at the grid's model tolerance, 5e-5) stays within the
    /// sum of their error estimates and is far below the tolerance, in every
    /// Rec.709 channel relative to luminance and in chromaticity.
    #[test]
    fn rgb_path_matches_the_spectral_path_within_its_estimate() {
        let tol = 1e-3;
        for e in ELEVATIONS {
            let atm = atmosphere(e);
            let sun = atm.sun_direction();
            let sun_phi = sun.y.atan2(sun.x);
            let direction = |theta: f64, dphi: f64| {
                let (st, ct) = theta.sin_cos();
                DVec3::new(st * (sun_phi + dphi).cos(), st * (sun_phi + dphi).sin(), ct)
            };
            let (path, decision) = decide_colour(&atm, tol, ColourPath::Auto);
            let path = path.expect("the atmosphere has a Rec.709 path");
            assert_eq!(decision.path, "xyz-table");
            // 24 zenith angles (finer near the horizon, and below it) × 9 azimuths.
            let mut dirs = Vec::new();
            for k in 0..24 {
                let theta = if k < 10 {
                    (k as f64 + 0.5) / 10.0 * 80f64.to_radians()
                } else if k < 20 {
                    (80.0 + (k - 10) as f64 * 1.0 + 0.3).to_radians()
                } else {
                    (90.5 + (k - 20) as f64 * 10.0).to_radians()
                };
                for m in 0..9 {
                    dirs.push(direction(theta, PI * m as f64 / 8.0));
                }
            }
            let mu = |d: DVec3| d.dot(sun);
            let model_tol = MODEL_TOLERANCE_FRACTION * tol;
            let rows: Vec<([f64; 3], [f64; 3], f64)> = dirs
                .par_iter()
                .map(|&d| {
                    let (p, err) = atm.sky_components(d, model_tol);
                    let (spectral, spectral_err) = sky_rgb(p, &err);
                    let (fast, fast_err) = (path.eval)(d, model_tol);
                    (total_rgb(&spectral, mu(d)), total_rgb(&fast, mu(d)), spectral_err + fast_err)
                })
                .collect();
            let brightest = rows.iter().fold(0.0f64, |m, r| m.max(luminance(&r.0)));
            let (mut worst, mut worst_uv, mut over) = (0.0f64, 0.0f64, 0.0f64);
            for (spectral, fast, err) in &rows {
                let y = luminance(spectral).max(1e-4 * brightest);
                for c in 0..3 {
                    let d = (fast[c] - spectral[c]).abs();
                    worst = worst.max(d / y);
                    over = over.max(d / (err + 1e-300));
                }
                if luminance(spectral) > 1e-4 * brightest {
                    let (u0, v0) = uv(spectrum::rec709_to_xyz(*spectral));
                    let (u1, v1) = uv(spectrum::rec709_to_xyz(*fast));
                    worst_uv = worst_uv.max(((u1 - u0).powi(2) + (v1 - v0).powi(2)).sqrt());
                }
            }
            eprintln!(
                "sun {e:>4}°: Rec.709 path vs spectral, {} directions: worst {worst:.1e} of luminance, Δu′v′ {worst_uv:.1e}, difference / summed estimates ≤ {over:.2}",
                dirs.len()
            );
            assert!(over <= 1.0, "sun {e}°: difference {over:.2} × the summed estimates");
            assert!(
                worst <= 2.0 * model_tol && worst_uv <= 1e-4,
                "sun {e}°: {worst:.2e}, Δu′v′ {worst_uv:.2e}"
            );
        }
    }

    /// The Rec.709 path on stiff and extreme atmospheres: no air, no aerosol,
    /// no ozone, all ten times denser, an observer at 100 km, the sun at
    /// exactly 0°, −0°, 90° and −6°; views at the zenith, the nadir, exactly
    /// at the horizon, grazing it, and at the sun. Every value is finite,
    /// the luminance is not negative, and the difference from the spectral
    /// path stays within the summed estimates. Where the colour table would
    /// need more than its node budget the path is not offered (spectral instead).
    #[test]
    fn rgb_path_handles_extreme_atmospheres() {
        use crate::sky::atmosphere::AtmosphereParams;
        let base = atmosphere(15.0);
        let cases: Vec<(&str, AtmosphereParams)> = vec![
            ("no air", AtmosphereParams { air_density: 0.0, ..base }),
            (
                "no aerosol",
                AtmosphereParams {
                    aerosol_density: 0.0,
                    ..base
                },
            ),
            (
                "no ozone",
                AtmosphereParams {
                    ozone_density: 0.0,
                    ..base
                },
            ),
            (
                "nothing",
                AtmosphereParams {
                    air_density: 0.0,
                    aerosol_density: 0.0,
                    ozone_density: 0.0,
                    ..base
                },
            ),
            ("air ×10", AtmosphereParams { air_density: 10.0, ..base }),
            (
                "all ×10",
                AtmosphereParams {
                    air_density: 10.0,
                    aerosol_density: 10.0,
                    ozone_density: 10.0,
                    ..base
                },
            ),
            (
                "100 km, sun −10°",
                AtmosphereParams {
                    altitude_m: 100_000.0,
                    sun_elevation_rad: -10f64.to_radians(),
                    ..base
                },
            ),
            (
                "sun 0°",
                AtmosphereParams {
                    sun_elevation_rad: 0.0,
                    ..base
                },
            ),
            (
                "sun −0°",
                AtmosphereParams {
                    sun_elevation_rad: -0.0,
                    ..base
                },
            ),
            (
                "sun 90°",
                AtmosphereParams {
                    sun_elevation_rad: std::f64::consts::FRAC_PI_2,
                    ..base
                },
            ),
            (
                "sun −6°",
                AtmosphereParams {
                    sun_elevation_rad: -6f64.to_radians(),
                    ..base
                },
            ),
        ];
        let tol = 1e-3;
        let model_tol = MODEL_TOLERANCE_FRACTION * tol;
        for (label, atm) in &cases {
            let (path, decision) = decide_colour(atm, tol, ColourPath::Auto);
            let Some(path) = path else {
                eprintln!("{label}: {} ({})", decision.path, decision.reason);
                assert_eq!(decision.path, "spectral");
                continue;
            };
            let sun = atm.sun_direction();
            let horizon = atm.horizon_zenith();
            let mut dirs = vec![DVec3::Z, -DVec3::Z, sun];
            for theta in [horizon, horizon - 1e-9, horizon + 1e-9, 0.5 * PI, 0.5 * PI - 1e-6] {
                for phi in [0.0, 1.0, 2.0, PI] {
                    dirs.push(DVec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()));
                }
            }
            let mut over = 0.0f64;
            for d in dirs {
                let (p, err) = atm.sky_components(d, model_tol);
                let (spectral, spectral_err) = sky_rgb(p, &err);
                let (fast, fast_err) = (path.eval)(d, model_tol);
                let (a, b) = (total_rgb(&spectral, d.dot(sun)), total_rgb(&fast, d.dot(sun)));
                assert!(
                    b.iter().all(|x| x.is_finite()) && fast_err.is_finite(),
                    "{label} {d}: {b:?} ± {fast_err}"
                );
                assert!(luminance(&b) >= 0.0, "{label} {d}: {b:?}");
                for c in 0..3 {
                    over = over.max((a[c] - b[c]).abs() / (spectral_err + fast_err + 1e-300));
                }
            }
            eprintln!("{label}: {}; difference / summed estimates ≤ {over:.2}", decision.reason);
            assert!(over <= 1.0, "{label}: {over}");
        }
    }

    /// Klassen's pixel-coherence baseline against the adaptive grid: both
    /// against the model evaluated directly at every pixel.
    #[test]
    fn klassen_coherence_baseline_against_the_grid() {
        use std::time::Instant;
        let tol = 1e-3;
        let w = 128;
        for e in [60.0, 2.0] {
            let world = klassen(e);
            let settings = TextureSettings {
                width: w,
                tolerance: tol,
                sun_disc: false,
            };
            let t = Instant::now();
            let grid = build_world_texture(&world, &settings);
            let t_grid = t.elapsed().as_secs_f64();
            let t = Instant::now();
            let coh = build_world_texture_with(
                &world,
                &settings,
                &BuildOptions {
                    integrator: Integrator::KlassenCoherence { threshold: tol },
                    ..Default::default()
                },
            );
            let t_coh = t.elapsed().as_secs_f64();
            let h = grid.height;
            let exact: Vec<[f64; 3]> = (0..w * h)
                .into_par_iter()
                .map(|p| {
                    let d = equirect_direction((p % w) as f64 + 0.5, (p / w) as f64 + 0.5, w, h);
                    // (The texture's colours are brought into Rec.709: so is the reference.)
                    clip_to_gamut(spectrum::spectrum_to_rec709(&world.sky_radiance(d, 1e-8).0))
                })
                .collect();
            let brightest = exact.iter().fold(0.0f64, |m, c| m.max(luminance(c)));
            let worst = |t: &WorldTexture| {
                (0..w * h).fold(0.0f64, |m, p| {
                    let y = luminance(&exact[p]).max(1e-4 * brightest);
                    (0..3).fold(m, |m, c| m.max((f64::from(t.rgb[p][c]) - exact[p][c]).abs() / y))
                })
            };
            let (eg, ec) = (worst(&grid), worst(&coh));
            eprintln!(
                "klassen {e}° {w}x{h}: grid {:.1} ms, {} evals, worst {eg:.2e}; coherence {:.1} ms, {} first estimates + {} Simpson integrals, worst {ec:.2e}",
                t_grid * 1e3,
                grid.evaluations,
                t_coh * 1e3,
                coh.first_estimates,
                coh.evaluations
            );
            assert_eq!(coh.first_estimates, w * h);
            assert!(coh.evaluations < w * h, "coherence must skip pixels");
            assert!(coh.rgb.iter().flatten().all(|v| v.is_finite()));
            assert!(eg <= 2.0 * tol, "grid {eg}");
        }
    }

    /// The optional multiple-scattering approximation only adds light and stays
    /// finite for sun elevations −6…90°.
    #[test]
    fn multiple_scattering_only_adds_light() {
        use crate::sky::atmosphere::AtmosphereWithMultipleScattering;
        for e in [-6.0, -4.0, 0.0, 5.0, 20.0, 45.0, 90.0] {
            let atm = atmosphere(e);
            let ms = AtmosphereWithMultipleScattering::new(atm, 1e-3);
            assert!(ms.ambient.iter().all(|x| x.is_finite() && *x >= 0.0), "{e}°");
            // Model level, exactly: every direction, every wavelength.
            for k in 0..24 {
                let d = equirect_direction(5.3 * k as f64 + 0.5, 1.3 * k as f64 + 0.5, 128, 64);
                let (single, _) = atm.sky_radiance(d, 1e-4);
                let (multi, err) = ms.sky_radiance(d, 1e-4);
                for i in 0..SPECTRAL_SAMPLES {
                    assert!(multi[i].is_finite() && err[i].is_finite(), "{e}° {d}");
                    assert!(
                        multi[i] >= single[i] - 1e-4 * single[i].abs(),
                        "{e}° {d} λ#{i}: {} < {}",
                        multi[i],
                        single[i]
                    );
                }
            }
            // Texture level: finite everywhere, never below single scattering by more
            // than the two textures' interpolation tolerances.
            let settings = TextureSettings {
                width: 64,
                tolerance: 1e-3,
                sun_disc: false,
            };
            let a = build_world_texture(&atm, &settings);
            let b = build_world_texture(&ms, &settings);
            let ymax = a.rgb.iter().fold(0.0f64, |m, c| m.max(luminance(&c.map(f64::from))));
            let mut gain = 0.0f64;
            for (pa, pb) in a.rgb.iter().zip(&b.rgb) {
                let (ya, yb) = (luminance(&pa.map(f64::from)), luminance(&pb.map(f64::from)));
                assert!(pb.iter().all(|v| v.is_finite()));
                assert!(yb >= ya - 2e-3 * ya.max(1e-4 * ymax), "{e}°: {yb} < {ya}");
                gain = gain.max(if ya > 1e-4 * ymax { yb / ya - 1.0 } else { 0.0 });
            }
            eprintln!("multiple scattering, sun {e:>4}°: largest luminance gain {:.1} %", 100.0 * gain);
        }
    }

    /// Every pixel of a small texture against the model evaluated directly at
    /// that pixel's centre to 1e-7 (the direct evaluation is itself checked
    /// against the independent brute-force references in `atmosphere` and
    /// `klassen`): luminance relative error ≤ 0.1 % and Δu′v′ ≤ 0.001 at the 8
    /// elevations, both models. Pixels darker than 10⁻⁴ of the brightest
    /// (deep in the earth's shadow) are compared in absolute terms against that floor.
    #[test]
    fn every_pixel_fast_vs_direct_at_all_elevations() {
        let w = 64;
        let tol = 1e-3;
        for e in ELEVATIONS {
            let atm = atmosphere(e);
            let kl = klassen(e);
            let models: [(&str, &dyn SkyModel); 2] = [("atmosphere", &atm), ("klassen", &kl)];
            for (name, model) in models {
                let (t, worst_y, worst_uv, dark) = texture_against_direct(model, w, tol);
                eprintln!(
                    "every pixel {name:<10} sun {e:>4}°: {} ({} evals): worst luminance {worst_y:.2e}, Δu′v′ {worst_uv:.2e}, {dark} dark pixels",
                    t.colour.path, t.evaluations
                );
                assert!(worst_y <= 1e-3, "{name} {e}°: luminance {worst_y:.2e}");
                assert!(worst_uv <= 1e-3, "{name} {e}°: Δu′v′ {worst_uv:.2e}");
            }
        }
    }

    /// The texture of `model` at `width` and `tolerance` (no sun disc) and its
    /// [`worst_pixel_errors`] against the model evaluated at every pixel
    /// centre to 1e-7.
    fn texture_against_direct(model: &dyn SkyModel, width: usize, tolerance: f64) -> (WorldTexture, f64, f64, usize) {
        let t = build_world_texture(
            model,
            &TextureSettings {
                width,
                tolerance,
                sun_disc: false,
            },
        );
        let (w, h) = (width, t.height);
        let exact: Vec<[f64; 3]> = (0..w * h)
            .into_par_iter()
            .map(|p| {
                let d = equirect_direction((p % w) as f64 + 0.5, (p / w) as f64 + 0.5, w, h);
                in_gamut_xyz(spectrum::spectrum_to_xyz(&model.sky_radiance(d, 1e-7).0))
            })
            .collect();
        let (worst_y, worst_uv, dark) = worst_pixel_errors(&t.rgb, &exact);
        (t, worst_y, worst_uv, dark)
    }

    /// Worst luminance error and Δu′v′ of a texture against per-pixel XYZ;
    /// pixels darker than 1e-4 of the brightest are judged in absolute terms
    /// against that floor (and counted, third value).
    /// CIE XYZ of `model` at every pixel centre of a `w` × `h` texture, evaluated directly.
    fn exact_xyz(model: &dyn SkyModel, w: usize, h: usize) -> Vec<[f64; 3]> {
        (0..w * h)
            .map(|p| {
                let d = equirect_direction((p % w) as f64 + 0.5, (p / w) as f64 + 0.5, w, h);
                in_gamut_xyz(spectrum::spectrum_to_xyz(&model.sky_radiance(d, 0.0).0))
            })
            .collect()
    }

    /// CIE XYZ brought into Rec.709 as the texture's pixels are ([`clip_to_gamut`]).
    fn in_gamut_xyz(xyz: [f64; 3]) -> [f64; 3] {
        spectrum::rec709_to_xyz(clip_to_gamut(spectrum::xyz_to_rec709(xyz)))
    }

    fn worst_pixel_errors(rgb: &[[f32; 3]], exact: &[[f64; 3]]) -> (f64, f64, usize) {
        let ymax = exact.iter().fold(0.0f64, |m, c| m.max(c[1]));
        let (mut worst_y, mut worst_uv, mut dark) = (0.0f64, 0.0f64, 0usize);
        for (px, x) in rgb.iter().zip(exact) {
            let xyz = spectrum::rec709_to_xyz(px.map(f64::from));
            if x[1] <= 1e-4 * ymax {
                dark += 1;
                worst_y = worst_y.max((xyz[1] - x[1]).abs() / (1e-4 * ymax).max(1e-300));
                continue;
            }
            worst_y = worst_y.max((xyz[1] - x[1]).abs() / x[1]);
            let (u, v) = uv(xyz);
            let (ur, vr) = uv(*x);
            worst_uv = worst_uv.max(((u - ur).powi(2) + (v - vr).powi(2)).sqrt());
        }
        (worst_y, worst_uv, dark)
    }

    /// The issue's acceptance check at full size: every pixel of the
    /// 2048 × 1024 atmosphere texture at the 8 elevations against the model
    /// evaluated directly at that pixel's centre to 1e-7, with the same
    /// criteria as [`every_pixel_fast_vs_direct_at_all_elevations`]. Minutes
    /// on two cores (2 M direct evaluations per elevation): run with `--ignored`.
    #[test]
    #[ignore = "minutes: every pixel of eight 2048 × 1024 textures against the direct model"]
    fn every_pixel_at_2048_against_direct() {
        let w = 2048;
        for e in ELEVATIONS {
            let atm = atmosphere(e);
            let (t, worst_y, worst_uv, _) = texture_against_direct(&atm, w, 1e-3);
            eprintln!(
                "2048 × 1024, sun {e:>4}°: {} ({} evals): worst luminance {worst_y:.2e}, Δu′v′ {worst_uv:.2e}",
                t.colour.path, t.evaluations
            );
            assert!(worst_y <= 1e-3, "{e}°: luminance {worst_y:.2e}");
            assert!(worst_uv <= 1e-3, "{e}°: Δu′v′ {worst_uv:.2e}");
        }
    }

    /// The same check at the twilight elevations between the issue's −4°
    /// and the −6° limit, where the cells at the pixel size (and their row
    /// fits) are: run with `--ignored`.
    #[test]
    #[ignore = "minutes: every pixel of four 2048 × 1024 twilight textures against the direct model"]
    fn every_pixel_at_2048_against_direct_twilight() {
        for e in [-2.0, -3.0, -5.0, -6.0] {
            let atm = atmosphere(e);
            let (t, worst_y, worst_uv, _) = texture_against_direct(&atm, 2048, 1e-3);
            eprintln!(
                "2048 × 1024, sun {e:>4}°: {} evals, {} pixels fitted along rows ({} evals), {} direct: worst luminance {worst_y:.2e}, Δu′v′ {worst_uv:.2e}",
                t.evaluations, t.row_fitted_pixels, t.row_fit_evaluations, t.direct_pixels
            );
            assert!(worst_y <= 1e-3, "{e}°: luminance {worst_y:.2e}");
            assert!(worst_uv <= 1e-3, "{e}°: Δu′v′ {worst_uv:.2e}");
        }
    }

    #[test]
    fn cost_grows_far_below_the_pixel_count() {
        let toy = Toy {
            sun: DVec3::new(0.0, 1.0, 0.1).normalize(),
        };
        let s = |w| {
            build_world_texture(
                &toy,
                &TextureSettings {
                    width: w,
                    tolerance: 1e-3,
                    sun_disc: false,
                },
            )
            .evaluations
        };
        let (a, b, c) = (s(128), s(2048), s(4096));
        // Small textures stop refining at their pixel size; once the pixels are finer
        // than the sky's structure the grid no longer depends on the output size.
        assert!(a <= b, "{a} > {b}");
        assert_eq!(b, c);
    }

    #[test]
    fn sun_disc_carries_the_sun_irradiance() {
        let toy = Toy {
            sun: DVec3::new(0.2, 0.9, 0.4).normalize(),
        };
        let w = 4096;
        let with = build_world_texture(
            &toy,
            &TextureSettings {
                width: w,
                tolerance: 1e-2,
                sun_disc: true,
            },
        );
        let without = build_world_texture(
            &toy,
            &TextureSettings {
                width: w,
                tolerance: 1e-2,
                sun_disc: false,
            },
        );
        // ∫ (with − without) dΩ over the texture = the sun's irradiance (per channel).
        let h = with.height;
        let mut e = [0.0f64; 3];
        for j in 0..h {
            let theta = PI * (j as f64 + 0.5) / h as f64;
            let domega = theta.sin() * (PI / h as f64) * (2.0 * PI / w as f64);
            for i in 0..w {
                for k in 0..3 {
                    e[k] += f64::from(with.rgb[j * w + i][k] - without.rgb[j * w + i][k]) * domega;
                }
            }
        }
        for k in 0..3 {
            assert!(
                (e[k] - with.sun_rgb_irradiance[k]).abs() < 0.02 * with.sun_rgb_irradiance[k],
                "channel {k}: {} vs {}",
                e[k],
                with.sun_rgb_irradiance[k]
            );
        }
        assert!(with.sun_pixels > 0);
    }
}
