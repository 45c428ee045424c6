//! Blender's pixel filter, so that edges composite cleanly over a Cycles render.
//!
//! Cycles filters every pixel with a separable Blackman–Harris window whose
//! "Filter Size" is 1.5 px by default. Cycles' film code (`filter_table`)
//! doubles the width for Blackman–Harris before tabulating it, so the window
//! spans `±width` px around the pixel centre:
//! `w(x) = 0.35875 − 0.48829 cos 2πt + 0.14128 cos 4πt − 0.01168 cos 6πt`,
//! `t = x/(2·width) + 1/2`, for `|x| ≤ width`, applied along x and y.
//!
//! Tyndall's images are smooth except where a view ray's surface changes
//! (silhouettes), at sharp beam and shadow edges, and at the image of a point
//! light (an integrable 1/r peak). A pixel is flagged when a neighbour within
//! the filter's reach sees another surface and the two centre samples differ
//! by more than the tolerance, or when the filter's second-order term below
//! exceeds it. Elsewhere the centre sample stands for the filtered value; for
//! a smooth image the filter changes it by `(σ²/2)·∇²L + O(σ⁴)` with `σ²` the
//! filter's per-axis variance. That term, from the 5-point Laplacian of the
//! centre samples, is added to the pixel's in-scatter (away from the frame's
//! edge; what is left is of fourth order) and its size is the pixel's filter
//! error estimate, now a conservative one. At 96×54 against converged Cycles
//! references it took the relative RMSE at tolerance 0.1 from 3.23 % to
//! 1.48 % (narrow beam) and from 8.7 % to 3.6 % (box occluder, without the
//! light's pixels), at no measurable cost (docs/benchmarks.md).
//!
//! Flagged pixels are integrated against the window on one **shared adaptive
//! lattice** ([`filter_adaptive`]): windows of neighbouring pixels overlap
//! (3 × 3 px each), so every view ray is traced once and feeds every window
//! that holds it. Root cells are ½ px squares whose corners are the lattice
//! points `pixel centre + (a/2, b/2)`; a window is exactly 6 × 6 root cells.
//! On each cell the image is interpolated bilinearly from its corners and
//! integrated exactly against the window (tabulated moments of `w`, see
//! [`WindowMoments`]), so the weights of a window sum to `(∫w)²` however it is
//! refined, and a constant or linear image is exact. A cell is split into
//! four while it is *not flat* (its corners' in-scatter spread exceeds ¼ of the tolerance of the brightest window that
//! holds it, or their transmittance spread ¼ of the tolerance) and some
//! pixel whose window holds it has not converged. A cell whose corners
//! differ is still flat where the image is smooth: when the bilinear
//! interpolant's error, estimated for a child from its parent (the parent's
//! interpolant against the five points the split added) and for a root cell
//! from the second differences of the root lattice around it, is within
//! the same ¼ — that bound then stands for the cell. Cells stop at 1/32 px,
//! except the cells at a point light's image, which go on to 1/2048 px (the
//! graded mesh that resolves the 1/r peak). An unconverged pixel does not
//! split every such cell of its window in a round, only the children of the
//! split cells whose error terms (first item below) are largest, until the
//! rest sum to at most half of what the tolerance leaves; the others keep
//! their terms. (Splitting them all refined the graded mesh at a light's
//! image while a shadow edge elsewhere in the window held the error: at
//! 96×54 the box occluder's lattice took 5624 → 4018 view rays at tolerance
//! 0.5, the unit tests' windows up to 3× fewer, as honest.) A pixel's error
//! estimate is
//!
//! - the sum over the split cells whose children are unsplit of the
//!   absolute change each made to the pixel's estimate (an absolute sum: a step crossing a
//!   window changes cells with both signs, and a signed sum let pixels stop
//!   early by cancellation; the bilinear rule has no Euler–Maclaurin
//!   cancellation to lose), each times [`step_factor`], the rate at which
//!   that cell's changes shrink, measured against its parent's: across a
//!   step the error falls as O(h), by less than half per split where the
//!   window's weight grows towards the step (the last change alone fell
//!   short of the error left by up to 1.8× on a step along a lattice line), plus
//! - twice the changes from splits after which no child can be refined
//!   further (the finest size, or every child flat), carried from the round
//!   they were made (across a step the error only halves per split), plus
//! - for every flat cell, its corners' spread times its share of the window
//!   (an unrefined flat cell cannot be off by more than that unless a feature
//!   hides between its corners), plus
//! - the samples' own error, filtered.
//!
//! At a point light's image the in-scatter has an integrable 1/ρ peak, inside
//! the beam's wedge, which near the apex can be far narrower than a cell: the
//! bilinear cells converge only as O(h) there and their estimate can miss the
//! wedge altogether. The 1 × 1 px squares (aligned with the window edges)
//! within ¼ px of the image are instead integrated in **polar coordinates
//! about the image** ([`PolarSquare`]): the Jacobian ρ cancels the peak, the
//! angle is cut where the light's cones' silhouettes pass through the image
//! (lines through it), and tensor Gauss–Kronrod rectangles are bisected
//! until each pixel holding the square is within a quarter of its
//! tolerance (shared among the polar squares its window holds). Their
//! error is carried into the pixel's estimate. Squares near the image that
//! a beam narrower than the lattice's cells crosses are polar as well
//! ([`PolarPlan::add_thin_squares`]): in the light's polar coordinates the
//! beam's edges are cut lines. (The graded mesh down to 1/2048 px remains
//! where two images share a square, and for filter widths whose window
//! edges are not on the ½ px grid.)
//!
//! Where a step crosses a pixel the estimate converges as O(h) only: hard
//! silhouettes are the one place the tolerance may not be met at 1/32 px,
//! and those pixels are counted (`edge_pixels_not_converged`). The window is
//! normalised by the rule's own weight sum, so a constant image is exact.

use rayon::prelude::*;
use rustc_hash::FxHashMap as HashMap;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// The pixel filter. JSON: `{"type": "blackman_harris", "width_px": 1.5}` or `{"type": "none"}`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum PixelFilter {
    /// Separable Blackman–Harris window (Blender/Cycles default).
    BlackmanHarris {
        /// Full width, px, 0.01..=10. Default 1.5 (Blender's Filter Size).
        #[serde(default = "default_width")]
        width_px: f64,
    },
    /// Point samples at pixel centres.
    None,
}

fn default_width() -> f64 {
    1.5
}

impl Default for PixelFilter {
    fn default() -> Self {
        PixelFilter::BlackmanHarris { width_px: 1.5 }
    }
}

/// The 4-term Blackman–Harris coefficients `a₀ … a₃` (Cycles' `filter_func_blackman_harris`).
const BLACKMAN_HARRIS: [f64; 4] = [0.35875, 0.48829, 0.14128, 0.01168];

impl PixelFilter {
    /// Window value at offset `x` px from the pixel centre (unnormalised).
    pub fn weight(&self, x: f64) -> f64 {
        match *self {
            PixelFilter::BlackmanHarris { width_px } => {
                if x.abs() > width_px {
                    return 0.0;
                }
                // cos(2π(x/2w + ½)) = −cos(πx/w): one cosine per weight.
                blackman_harris_of_cos(-(2.0 * PI * (x / (2.0 * width_px) + 0.5)).cos())
            }
            PixelFilter::None => {
                if x == 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
        }
    }

    /// The window at one point for neighbouring pixel centres one px
    /// apart ([`UnitSteps::weights`]).
    pub fn unit_steps(&self) -> UnitSteps {
        let step = match *self {
            PixelFilter::BlackmanHarris { width_px } => (PI / width_px).sin_cos(),
            PixelFilter::None => (0.0, 1.0),
        };
        UnitSteps { filter: *self, step }
    }

    /// Half of the support, px (Cycles' doubled Blackman–Harris width: `width_px`).
    pub fn radius(&self) -> f64 {
        match *self {
            PixelFilter::BlackmanHarris { width_px } => width_px,
            PixelFilter::None => 0.0,
        }
    }

    /// `n` midpoint nodes `(offset px, normalised weight)` along one axis.
    pub fn nodes(&self, n: usize) -> Vec<(f64, f64)> {
        let r = self.radius();
        if r == 0.0 || n == 0 {
            return vec![(0.0, 1.0)];
        }
        let h = 2.0 * r / n as f64;
        let raw: Vec<(f64, f64)> = (0..n)
            .map(|i| {
                let x = -r + (i as f64 + 0.5) * h;
                (x, self.weight(x))
            })
            .collect();
        let sum: f64 = raw.iter().map(|p| p.1).sum();
        raw.into_iter().map(|(x, w)| (x, w / sum)).collect()
    }

    /// Per-axis variance of the normalised window, px², in closed form. On
    /// `[−W/2, W/2]`, `W = 2·width_px`, the window is `a₀ + a₁cos(2πx/W) +
    /// a₂cos(4πx/W) + a₃cos(6πx/W)`, and `∫x²·cos(2πkx/W) dx = (−1)ᵏW³/(2π²k²)`
    /// there, so `σ² = W²·(1/12 − (a₁ − a₂/4 + a₃/9)/(2π²·a₀))`. (A 4 096-node
    /// midpoint sum took ≈ 0.2 ms of every render: 13 % of an 8 × 4 px one.)
    pub fn variance(&self) -> f64 {
        match *self {
            PixelFilter::BlackmanHarris { width_px } => {
                let [a0, a1, a2, a3] = BLACKMAN_HARRIS;
                let w = 2.0 * width_px;
                w * w * (1.0 / 12.0 - (a1 - a2 / 4.0 + a3 / 9.0) / (2.0 * PI * PI * a0))
            }
            PixelFilter::None => 0.0,
        }
    }
}

/// The Blackman–Harris window from `c = cos(πx/w)`, `w` the half-width:
/// `a₀ + a₁c + a₂cos 2a + a₃cos 3a`, the multiple angles from `c`
/// (Chebyshev), so one cosine per weight.
fn blackman_harris_of_cos(c: f64) -> f64 {
    let [a0, a1, a2, a3] = BLACKMAN_HARRIS;
    let c2 = 2.0 * c * c - 1.0;
    a0 + a1 * c + a2 * c2 + a3 * c * (2.0 * c2 - 1.0)
}

/// [`PixelFilter::weight`] at one point for pixel centres one px apart,
/// with the sine and cosine of the step `π/w` computed once.
#[derive(Debug, Clone, Copy)]
pub struct UnitSteps {
    filter: PixelFilter,
    /// `(sin, cos)` of `π/w`, `w` the half-width.
    step: (f64, f64),
}

impl UnitSteps {
    /// The filter's [`PixelFilter::radius`].
    pub fn radius(&self) -> f64 {
        self.filter.radius()
    }

    /// `weight(x₀ − m)` for `m = 0..N`. One sine and cosine for all of
    /// them: with `c = cos(πx/w)` the weight is a cubic in `c`, and
    /// `cos(π(x₀ − m)/w)` follows from `cos(πx₀/w)`, `sin(πx₀/w)` by the
    /// angle difference (equal to `weight` to rounding, ~1e-16).
    pub fn weights<const N: usize>(&self, x0: f64) -> [f64; N] {
        match self.filter {
            PixelFilter::BlackmanHarris { width_px } => {
                let (s0, c0) = (PI * x0 / width_px).sin_cos();
                let (ss, cs) = self.step;
                // (cos, sin) of π(x₀ − m)/w, rotated by −π/w per step.
                let (mut c, mut s) = (c0, s0);
                std::array::from_fn(|m| {
                    let weight = if (x0 - m as f64).abs() > width_px {
                        0.0
                    } else {
                        blackman_harris_of_cos(c)
                    };
                    (c, s) = (c * cs + s * ss, s * cs - c * ss);
                    weight
                })
            }
            PixelFilter::None => std::array::from_fn(|m| self.filter.weight(x0 - m as f64)),
        }
    }
}

/// What the adaptive filter integral needs of a view-ray sample.
pub(crate) trait FilterSample: Copy + Default + Send + Sync {
    /// In-scatter RGB: the quantity whose error is controlled.
    fn radiance(&self) -> [f64; 3];
    /// View transmittance RGB (0..1), held flat to the tolerance in absolute terms.
    fn transmittance(&self) -> [f64; 3];
    /// The sample's own error estimate, RGB.
    fn own_error(&self) -> [f64; 3];
    /// `self += weight · other` for every filtered quantity.
    fn add_weighted(&mut self, other: &Self, weight: f64);
}

/// Lattice units per pixel: a lattice point is `pixel centre + (k, l)/UNITS_PER_PX`.
const UNITS_PER_PX: i64 = 4096;
/// Root cell side, units (½ px).
const ROOT_CELL: i64 = UNITS_PER_PX / 2;
/// Smallest cell side away from a light's image, units (1/32 px).
const MIN_CELL: i64 = UNITS_PER_PX / 32;
/// Smallest cell side at a point light's image, units (1/2048 px).
const MIN_CELL_AT_LIGHT: i64 = 2;
/// The error left in a cell split for the last time is taken as this many
/// times the change the split made. Across a step the error only halves per
/// split (O(h)), so the finer error equals the change: a factor 1 has no
/// margin (a step along a lattice line was underestimated by 0.6 %).
const TERMINAL_FACTOR: f64 = 2.0;
/// A cell is at a light's image (never flat, refined down to
/// `MIN_CELL_AT_LIGHT`) when the image lies within this many of its own sizes
/// of it: a mesh graded towards the 1/r peak.
const AT_LIGHT_REACH: i64 = 3;
/// A cell is flat when its corners spread by at most this fraction of the tolerance.
const FLAT_FRACTION: f64 = 0.25;
/// A round splits the pending cells with the largest errors until the rest
/// hold at most this share of the pixel's error budget. (0.75 took 6 % fewer
/// rays on the demo stages at equal tolerance, but the box occluder's error
/// against Cycles at 96×54, tolerance 0.2, rose from 0.864 to 0.996 %, and its
/// time at 1 % error did not fall.)
const UNSPLIT_SHARE: f64 = 0.5;
/// Flagged pixels are grouped into tiles of this many pixels a side; each tile
/// has its own lattice (shared points at tile borders are traced twice), which
/// bounds memory and gives the threads independent work.
const TILE_PX: usize = 16;
/// A batch of view rays is split among the threads in chunks that take at
/// least this long (s), judged by the batch's first ray (rayon's own
/// splitting costs a few µs per chunk: cheap rays stay on one thread).
const PARALLEL_CHUNK_SECONDS: f64 = 100e-6;

/// Traces the view rays at `at` (pixel coordinates), in order, on every
/// thread that is free. The squares at lights' images and the lattice's
/// tiles are the units of work that the threads share, but each asks for
/// its rays in batches: where the image is small (one tile at 12×7, one
/// square) or one unit holds most of the refinement (a light's image), the
/// other threads would otherwise wait once every unit has started. Before
/// that (`spare_threads` false) the batch is traced here, in order
/// (batching and splitting every batch made the box occluder's render at
/// 96×54, whose threads are busy with tiles, 6 % slower). A ray's value does not
/// depend on the thread that traces it, so the image is bit-identical to
/// tracing the rays one by one.
fn trace_batch<S: FilterSample>(sample: &(dyn Fn(f64, f64) -> S + Sync), at: &[(f64, f64)], spare_threads: bool) -> Vec<S> {
    if !spare_threads {
        return at.iter().map(|&(x, y)| sample(x, y)).collect();
    }
    let Some((&(x, y), rest)) = at.split_first() else {
        return Vec::new();
    };
    let start = std::time::Instant::now();
    let first = sample(x, y);
    let cost = start.elapsed().as_secs_f64();
    let chunk = (PARALLEL_CHUNK_SECONDS / cost.max(1e-9)).ceil().min(1e6) as usize;
    let mut out = Vec::with_capacity(at.len());
    out.push(first);
    if rest.len() >= 2 * chunk.max(1) {
        out.par_extend(rest.par_iter().with_min_len(chunk.max(1)).map(|&(x, y)| sample(x, y)));
    } else {
        out.extend(rest.iter().map(|&(x, y)| sample(x, y)));
    }
    out
}

/// One flagged pixel after [`filter_adaptive`].
pub(crate) struct FilteredPixel<S> {
    /// Index `y·width + x` in the image.
    pub index: usize,
    /// Filtered sample (accumulated quantities only; depth, hit and surface stay default).
    pub value: S,
    /// Error estimate of the filtered in-scatter, RGB, absolute.
    pub error: [f64; 3],
}

/// What [`filter_adaptive`] needs about the image.
pub(crate) struct AdaptiveFilterJob<'a> {
    pub filter: PixelFilter,
    pub width: usize,
    pub height: usize,
    /// Relative tolerance of the filtered in-scatter (absolute for transmittance).
    pub tolerance: f64,
    /// Per in-image pixel index: the brightest centre sample its window sees
    /// (the scale its error is measured against).
    pub window_scale: &'a (dyn Fn(usize) -> f64 + Sync),
    /// Images of point lights, pixel coordinates (pixel `i` spans `[i, i+1)`).
    pub light_images: &'a [(f64, f64)],
    /// The same images with the directions of their features, for the
    /// polar rule ([`PolarSquare`]); empty: the graded mesh everywhere.
    pub polar_images: &'a [LightImage],
    /// Where the beam of `polar_images[n]`'s light may cross the 1 × 1 px
    /// square centred at `(x, y)` (pixel coordinates): its width across the
    /// image there, px (NaN where it cannot be told); `None` where it
    /// misses the square. Where it is narrower than the lattice's cells,
    /// which can then miss it, the square is integrated with the polar rule
    /// about that image ([`PolarPlan::add_thin_squares`]). `None`: no beam
    /// geometry known.
    pub beam_width: Option<&'a BeamWidth<'a>>,
    /// Set by another thread to stop: tiles not yet started are skipped
    /// (the caller then discards the result).
    pub cancel: Option<&'a std::sync::atomic::AtomicBool>,
    /// Called with `(pixels done, pixels flagged)` after each tile.
    pub progress: &'a (dyn Fn(usize, usize) + Sync),
}

/// [`AdaptiveFilterJob::beam_width`]: `(image index, square centre) → width, px`.
pub(crate) type BeamWidth<'a> = dyn Fn(usize, (f64, f64)) -> Option<f64> + Sync + 'a;

/// Totals of a [`filter_adaptive`] run.
#[derive(Debug, Default, Clone, Copy)]
pub(crate) struct AdaptiveFilterStats {
    /// View rays traced for the lattice.
    pub samples: u64,
    /// Lattice cells created (roots and refinements).
    pub cells: u64,
    /// Squares around point lights' images integrated by the polar rule
    /// ([`PolarSquare`]), and the view rays they took (within `samples`).
    pub polar_squares: u64,
    pub polar_samples: u64,
}

#[derive(Clone, Copy)]
struct Cell {
    k: i64,
    l: i64,
    size: i64,
    /// Sample indices of the corners (k,l), (k+s,l), (k,l+s), (k+s,l+s).
    corners: [u32; 4],
    /// Index of the first of four children, 0 when the cell is a leaf.
    child: u32,
    flat: bool,
    refinable: bool,
    /// Spread of the corners' in-scatter, RGB (used when flat).
    spread: [f64; 3],
    /// Tolerance scale of the brightest window holding the cell (inherited from its root).
    scale: f64,
    /// The root cell it descends from.
    root: u32,
    /// The cell it was split from (`u32::MAX` for a root).
    parent: u32,
    /// For a root cell of a polar square: the square (in
    /// [`TileLattice::polar`]) on the square's lower corner cell, which
    /// carries the whole square, [`POLAR_EMPTY`] on its other three;
    /// [`NOT_POLAR`] elsewhere.
    polar: u32,
}

/// [`Cell::polar`] of a cell outside every polar square.
const NOT_POLAR: u32 = u32::MAX;
/// [`Cell::polar`] of a polar square's cells other than its carrier.
const POLAR_EMPTY: u32 = u32::MAX - 1;

/// Where a new cell comes from.
struct CellOrigin {
    /// Tolerance scale (see [`Cell::scale`]).
    scale: f64,
    /// Its root; `None` for a root.
    root: Option<u32>,
    /// The cell it was split from; `None` for a root.
    parent: Option<u32>,
    /// For a child: how far the image at the parent's five new points (edge
    /// midpoints, centre) lies from the parent's bilinear interpolant, RGB
    /// in-scatter and the largest transmittance channel.
    parent_deviation: Option<([f64; 3], f64)>,
}

/// Moments of the window along one axis over the edge of a cell: for the
/// interval `[x0, x0 + s]` (px from the pixel centre), the integrals of
/// `w(x)·(x0 + s − x)/s` and `w(x)·(x − x0)/s`, i.e. the weights of the two
/// end points when the image is interpolated linearly along the edge. With a
/// bilinear interpolant on every cell, a window's weights sum to `(∫w)²` on
/// any partition, so partial refinement cannot shift the normalisation (the
/// product trapezoid rule, with `w` sampled at the corners, shifts it by
/// several per cent at ½ px cells). Computed by 8-point Gauss–Legendre: `w` is
/// a sum of cosines of at most 2π·(3/2)/width rad/px, and the rule is exact to
/// ~1e-12 on ½ px intervals. Tabulated for every cell size down to
/// `MIN_CELL`; smaller cells (at a light's image) are integrated when needed.
struct WindowMoments {
    half_units: i64,
    /// `(∫w)²`, the weight of a whole window.
    norm: f64,
    /// Per level `d` (cell side `ROOT_CELL >> d`): moments of the intervals from `−half` on.
    levels: Vec<Vec<(f64, f64)>>,
    filter: PixelFilter,
}

/// 8-point Gauss–Legendre nodes and weights on [−1, 1].
const GL8: [(f64, f64); 8] = [
    (-0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
    (-0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (-0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (-0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.525_532_409_916_329, 0.313_706_645_877_887_3),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_47),
    (0.960_289_856_497_536_3, 0.101_228_536_290_376_26),
];

impl WindowMoments {
    fn new(filter: PixelFilter, half_units: i64) -> Self {
        let mut levels: Vec<Vec<(f64, f64)>> = Vec::new();
        let mut size = ROOT_CELL;
        while size >= MIN_CELL {
            let n = (2 * half_units / size) as usize;
            levels.push(
                (0..n)
                    .map(|i| Self::integrate(&filter, i as i64 * size - half_units, size))
                    .collect(),
            );
            size /= 2;
        }
        let norm = levels.first().map_or(0.0f64, |l| l.iter().map(|(a, b)| a + b).sum::<f64>()).powi(2);
        WindowMoments {
            half_units,
            norm,
            levels,
            filter,
        }
    }

    fn integrate(filter: &PixelFilter, offset: i64, size: i64) -> (f64, f64) {
        let u = UNITS_PER_PX as f64;
        let (x0, s) = (offset as f64 / u, size as f64 / u);
        let (mut m0, mut m1) = (0.0, 0.0);
        for (z, g) in GL8 {
            let frac = 0.5 * (z + 1.0);
            let wx = filter.weight(x0 + frac * s) * 0.5 * g * s;
            m0 += wx * (1.0 - frac);
            m1 += wx * frac;
        }
        (m0, m1)
    }

    /// Moments of the interval `[offset, offset + size]` (units from the
    /// pixel centre) if they are 0 or tabulated; `None` for a cell finer
    /// than the tables.
    #[inline]
    fn tabulated(&self, offset: i64, size: i64) -> Option<(f64, f64)> {
        if offset >= self.half_units || offset + size <= -self.half_units {
            return Some((0.0, 0.0));
        }
        let level = (ROOT_CELL / size).trailing_zeros() as usize;
        match self.levels.get(level) {
            Some(table) if size == ROOT_CELL >> level => Some(table[((offset + self.half_units) / size) as usize]),
            _ => None,
        }
    }
}

/// A worker's view of the [`WindowMoments`]: the tables, and a memo of the
/// cells finer than them (at a light's image, down to 1/2048 px), which each
/// pixel of a window asks for in every round (8 Gauss–Legendre nodes of three
/// cosines each: 11 % of the filter's time in the box occluder at 96×54).
struct Moments<'a> {
    shared: &'a WindowMoments,
    fine: std::cell::RefCell<HashMap<(i64, i64), (f64, f64)>>,
}

impl Moments<'_> {
    #[inline]
    fn at(&self, offset: i64, size: i64) -> (f64, f64) {
        self.shared.tabulated(offset, size).unwrap_or_else(|| {
            *self
                .fine
                .borrow_mut()
                .entry((offset, size))
                .or_insert_with(|| WindowMoments::integrate(&self.shared.filter, offset, size))
        })
    }

    /// Weights of a cell's corners (k,l), (k+s,l), (k,l+s), (k+s,l+s) for the pixel centred at (kc, lc).
    #[inline]
    fn corner_weights(&self, c: &Cell, kc: i64, lc: i64) -> [f64; 4] {
        let (x0, x1) = self.at(c.k - kc, c.size);
        let (y0, y1) = self.at(c.l - lc, c.size);
        [x0 * y0, x1 * y0, x0 * y1, x1 * y1]
    }
}

/// A flagged pixel while its window is refined. The sums run over the
/// current leaves of its window and are updated as cells split.
struct PixelState {
    index: usize,
    kc: i64,
    lc: i64,
    /// Tolerance scale: the brightest centre sample its window sees.
    scale: f64,
    /// Root cells of its window.
    roots: Vec<u32>,
    /// `Σ w·L` over the leaves (unnormalised).
    sum: [f64; 3],
    /// `Σ w` = `(∫w)²`, unchanged by splitting.
    weight: f64,
    /// `Σ w·spread` over flat leaves (unnormalised).
    flat: [f64; 3],
    /// `Σ |change|` of cells whose children cannot be refined, normalised.
    carried: [f64; 3],
    /// Split cells of its window whose refinable children are not split yet:
    /// the error left in those children (the change the split made times
    /// [`step_factor`]) and the change itself (to measure the rate when the
    /// children are split).
    pending: HashMap<u32, Pending>,
    /// Cells of its window to split in the next round.
    frontier: Vec<u32>,
}

/// The cells split in one round that share a parent, as one pixel sees
/// them: their summed change, and each non-terminal one with its change.
type SplitGroup = ([f64; 3], Vec<(u32, [f64; 3])>);

/// A split cell whose refinable children are unsplit, as one pixel sees it.
#[derive(Clone, Copy)]
struct Pending {
    /// Error left in the children, normalised, RGB.
    error: [f64; 3],
    /// The change the split made to the pixel, normalised, RGB.
    change: [f64; 3],
}

struct TileLattice<'a, S> {
    job: &'a AdaptiveFilterJob<'a>,
    table: Moments<'a>,
    sample: &'a (dyn Fn(f64, f64) -> S + Sync),
    points: HashMap<(i64, i64), u32>,
    samples: Vec<S>,
    cells: Vec<Cell>,
    roots: HashMap<(i64, i64), u32>,
    /// Per-sample weight sums while a pixel is accumulated (all 0 between pixels).
    scratch: Vec<f64>,
    /// The job's polar squares, integrated before the tiles, and their
    /// index by square.
    plan: &'a PolarPlan,
    polar: &'a [PolarSquare<S>],
    polar_index: &'a HashMap<(i64, i64), u32>,
    /// Tiles the threads have taken so far, of `tiles`.
    tiles_started: &'a std::sync::atomic::AtomicUsize,
    tiles: usize,
}

impl<S: FilterSample> TileLattice<'_, S> {
    /// The polar square whose root cells include the one at (k, l): its
    /// index in the job's squares and whether this root is its carrier.
    fn polar_root(&self, k: i64, l: i64) -> Option<(u32, bool)> {
        let u = UNITS_PER_PX as f64;
        let (sq, carrier) = self.plan.square_of(0.5 + k as f64 / u, 0.5 + l as f64 / u)?;
        self.polar_index.get(&sq).map(|&square| (square, carrier))
    }

    /// Whether every tile has started, so that a thread may be free for
    /// this tile's rays ([`trace_batch`]).
    fn spare_threads(&self) -> bool {
        self.tiles_started.load(std::sync::atomic::Ordering::Relaxed) >= self.tiles
    }

    /// Traces the lattice points of `wanted` not traced yet, as one batch
    /// on the spare threads ([`trace_batch`]); [`Self::point`] then finds
    /// them. Nothing while no thread is spare: `point` traces them then.
    fn prefetch(&mut self, mut wanted: Vec<(i64, i64)>) {
        if !self.spare_threads() {
            return;
        }
        wanted.retain(|p| !self.points.contains_key(p));
        wanted.sort_unstable();
        wanted.dedup();
        let u = UNITS_PER_PX as f64;
        let at: Vec<(f64, f64)> = wanted.iter().map(|&(k, l)| (0.5 + k as f64 / u, 0.5 + l as f64 / u)).collect();
        for (p, s) in wanted.into_iter().zip(trace_batch(self.sample, &at, true)) {
            let i = self.samples.len() as u32;
            self.samples.push(s);
            self.points.insert(p, i);
        }
    }

    fn point(&mut self, k: i64, l: i64) -> u32 {
        if let Some(&i) = self.points.get(&(k, l)) {
            return i;
        }
        let u = UNITS_PER_PX as f64;
        let s = (self.sample)(0.5 + k as f64 / u, 0.5 + l as f64 / u);
        let i = self.samples.len() as u32;
        self.samples.push(s);
        self.points.insert((k, l), i);
        i
    }

    fn at_light(&self, k: i64, l: i64, size: i64) -> bool {
        let u = UNITS_PER_PX as f64;
        let m = AT_LIGHT_REACH * size;
        let (x0, y0) = (0.5 + (k - m) as f64 / u, 0.5 + (l - m) as f64 / u);
        let (x1, y1) = (0.5 + (k + size + m) as f64 / u, 0.5 + (l + size + m) as f64 / u);
        self.job.light_images.iter().any(|&(x, y)| x >= x0 && x <= x1 && y >= y0 && y <= y1)
    }

    /// Smallest window scale of the in-image pixels whose windows hold the
    /// root cell at (k, l).
    fn root_scale(&self, k: i64, l: i64) -> f64 {
        let half = self.table.shared.half_units;
        // Pixel x holds [a, a + ROOT_CELL] when x·U − half ≤ a and a + ROOT_CELL ≤ x·U + half.
        let range = |a: i64| -> (i64, i64) {
            (
                -(half - ROOT_CELL - a).div_euclid(UNITS_PER_PX),
                (a + half).div_euclid(UNITS_PER_PX),
            )
        };
        let ((x0, x1), (y0, y1)) = (range(k), range(l));
        let mut m = f64::INFINITY;
        for y in y0.max(0)..=y1.min(self.job.height as i64 - 1) {
            for x in x0.max(0)..=x1.min(self.job.width as i64 - 1) {
                let i = y as usize * self.job.width + x as usize;
                m = m.min((self.job.window_scale)(i));
            }
        }
        if m.is_finite() { m } else { 0.0 }
    }

    /// The bilinear interpolation error of the root cell of side `s` with
    /// corner (k, l), estimated from the root lattice around it. For a smooth
    /// image the error on the cell is at most `(max|f_xx| + max|f_yy|)·s²/8`;
    /// the second differences `D_xx = f(k−s) − 2f(k) + f(k+s)` (and `D_yy`) at
    /// its four corners estimate `f_xx·s²` and `f_yy·s²`. A step of height Δ
    /// inside the cell gives second differences of only ±Δ (Δ/8 by that
    /// rule, where a split would measure Δ/2), but opposite ones at the two
    /// ends of the edge it crosses: the third differences along the cell's
    /// edges, `|D_xx(k) − D_xx(k+s)|/4` (and along y), are Δ/2 there and
    /// O(s³) for a smooth image, and are added. RGB in-scatter and the
    /// largest transmittance channel. Most of the points are the root
    /// lattice of the neighbouring windows anyway; a step or a feature
    /// within a few cells shows as a large difference, and the cell is split.
    fn root_deviation(&mut self, k: i64, l: i64, s: i64) -> ([f64; 3], f64) {
        // Second differences along x and y at the corners (k,l), (k+s,l), (k,l+s), (k+s,l+s).
        let mut dxx = [([0.0f64; 3], [0.0f64; 3]); 4];
        let mut dyy = [([0.0f64; 3], [0.0f64; 3]); 4];
        for (n, stencil) in deviation_stencils(k, l, s).into_iter().enumerate() {
            let ids = stencil.map(|(k, l)| self.point(k, l));
            let [c, xm, xp, ym, yp] = ids.map(|i| {
                let p = &self.samples[i as usize];
                (p.radiance(), p.transmittance())
            });
            dxx[n] = (
                std::array::from_fn(|ch| xm.0[ch] - 2.0 * c.0[ch] + xp.0[ch]),
                std::array::from_fn(|ch| xm.1[ch] - 2.0 * c.1[ch] + xp.1[ch]),
            );
            dyy[n] = (
                std::array::from_fn(|ch| ym.0[ch] - 2.0 * c.0[ch] + yp.0[ch]),
                std::array::from_fn(|ch| ym.1[ch] - 2.0 * c.1[ch] + yp.1[ch]),
            );
        }
        let bound = |d: [[f64; 3]; 4], e: [[f64; 3]; 4], ch: usize| -> f64 {
            // A non-finite sample is never smooth (f64::max would drop a NaN).
            if d.iter().chain(&e).any(|v| !v[ch].is_finite()) {
                return f64::INFINITY;
            }
            let max_abs = |v: &[[f64; 3]; 4]| v.iter().fold(0.0f64, |m, x| m.max(x[ch].abs()));
            // Edges along x join corners 0–1 and 2–3; along y, 0–2 and 1–3.
            let third =
                (d[0][ch] - d[1][ch]).abs().max((d[2][ch] - d[3][ch]).abs()) + (e[0][ch] - e[2][ch]).abs().max((e[1][ch] - e[3][ch]).abs());
            (max_abs(&d) + max_abs(&e)) / 8.0 + third / 4.0
        };
        let (lx, tx) = (dxx.map(|v| v.0), dxx.map(|v| v.1));
        let (ly, ty) = (dyy.map(|v| v.0), dyy.map(|v| v.1));
        let dev = std::array::from_fn(|ch| bound(lx, ly, ch));
        let t_dev = (0..3).fold(0.0f64, |m, ch| m.max(bound(tx, ty, ch)));
        (dev, t_dev)
    }

    /// Spread (max − min) of the corners' in-scatter, RGB, and of their
    /// transmittance, largest channel.
    fn corner_spread(&self, corners: &[u32; 4]) -> ([f64; 3], f64) {
        let mut spread = [0.0f64; 3];
        let mut t_spread = 0.0f64;
        for c in 0..3 {
            let (mut lo, mut hi, mut tlo, mut thi) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
            for &p in corners {
                let s = &self.samples[p as usize];
                let (v, t) = (s.radiance()[c], s.transmittance()[c]);
                lo = lo.min(v);
                hi = hi.max(v);
                tlo = tlo.min(t);
                thi = thi.max(t);
            }
            spread[c] = hi - lo;
            t_spread = t_spread.max(thi - tlo);
        }
        (spread, t_spread)
    }

    /// Whether a spread (or interpolation bound) `d`, transmittance `t`, is
    /// within [`FLAT_FRACTION`] of the tolerance at window scale `scale`.
    fn within_flat(&self, d: &[f64; 3], t: f64, scale: f64) -> bool {
        let tol = self.job.tolerance;
        d.iter().all(|d| *d <= FLAT_FRACTION * tol * scale) && t <= FLAT_FRACTION * tol
    }

    /// Adds the cell of side `size` with corner (k, l).
    fn new_cell(&mut self, k: i64, l: i64, size: i64, origin: CellOrigin) -> u32 {
        let CellOrigin {
            scale,
            root,
            parent,
            parent_deviation,
        } = origin;
        let corners = cell_corners(k, l, size).map(|(k, l)| self.point(k, l));
        let (mut spread, t_spread) = self.corner_spread(&corners);
        let at_light = self.at_light(k, l, size);
        // Flat: the corners agree, or the image is smooth here (splitting
        // the parent moved its interpolant by little: a steep but smooth
        // gradient, which bilinear interpolation follows); the bound used
        // for the cell is then that deviation. A non-finite corner is never
        // flat (it is refined, and its error shows).
        let mut flat = !at_light && self.within_flat(&spread, t_spread, scale);
        // A root has no parent: its interpolation error is estimated from the
        // differences of the root lattice around it instead.
        let parent_deviation = match (parent_deviation, root) {
            (None, None) if !flat && !at_light => Some(self.root_deviation(k, l, size)),
            (d, _) => d,
        };
        if !flat
            && !at_light
            && let Some((dev, t_dev)) = parent_deviation
            && self.within_flat(&dev, t_dev, scale)
        {
            flat = true;
            spread = dev;
        }
        let min = if at_light { MIN_CELL_AT_LIGHT } else { MIN_CELL };
        let refinable = !flat && size / 2 >= min;
        let i = self.cells.len() as u32;
        self.cells.push(Cell {
            k,
            l,
            size,
            corners,
            child: 0,
            flat,
            refinable,
            spread,
            scale,
            root: root.unwrap_or(i),
            parent: parent.unwrap_or(u32::MAX),
            polar: NOT_POLAR,
        });
        i
    }

    /// Adds the root cell at (k, l) of a polar square: the square's carrier
    /// (`polar` its index) or one of its other cells ([`POLAR_EMPTY`]).
    /// Never split; its share of a window is the square's polar integral.
    fn new_polar_cell(&mut self, k: i64, l: i64, polar: u32) -> u32 {
        let i = self.cells.len() as u32;
        self.cells.push(Cell {
            k,
            l,
            size: ROOT_CELL,
            corners: [0; 4],
            child: 0,
            flat: true,
            refinable: false,
            spread: [0.0; 3],
            scale: 0.0,
            root: i,
            parent: u32::MAX,
            polar,
        });
        i
    }

    fn split(&mut self, i: u32) {
        let c = self.cells[i as usize];
        if c.child != 0 {
            return;
        }
        let h = c.size / 2;
        // The parent's bilinear interpolant at the five new points against the image there.
        let corner = |j: usize| -> ([f64; 3], [f64; 3]) {
            let s = &self.samples[c.corners[j] as usize];
            (s.radiance(), s.transmittance())
        };
        let cs = [corner(0), corner(1), corner(2), corner(3)];
        let mut dev = [0.0f64; 3];
        let mut t_dev = 0.0f64;
        // The mixes of the corners at the points of `split_points`, in its order.
        let mixes = [
            [0.5, 0.5, 0.0, 0.0],
            [0.5, 0.0, 0.5, 0.0],
            [0.0, 0.5, 0.0, 0.5],
            [0.0, 0.0, 0.5, 0.5],
            [0.25; 4],
        ];
        for ((k, l), mix) in split_points(c.k, c.l, c.size).into_iter().zip(mixes) {
            let p = self.point(k, l);
            let (l, t) = (self.samples[p as usize].radiance(), self.samples[p as usize].transmittance());
            for ch in 0..3 {
                let il: f64 = (0..4).map(|j| mix[j] * cs[j].0[ch]).sum();
                let it: f64 = (0..4).map(|j| mix[j] * cs[j].1[ch]).sum();
                dev[ch] = dev[ch].max((l[ch] - il).abs());
                t_dev = t_dev.max((t[ch] - it).abs());
            }
        }
        let first = self.cells.len() as u32;
        for (dk, dl) in [(0, 0), (h, 0), (0, h), (h, h)] {
            self.new_cell(
                c.k + dk,
                c.l + dl,
                h,
                CellOrigin {
                    scale: c.scale,
                    root: Some(c.root),
                    parent: Some(i),
                    parent_deviation: Some((dev, t_dev)),
                },
            );
        }
        self.cells[i as usize].child = first;
    }

    /// Cell `i`'s share of the pixel centred at (kc, lc), with the image
    /// interpolated bilinearly from the corners: `(Σ w·L, Σ w)`.
    fn cell_sums(&self, i: u32, kc: i64, lc: i64) -> ([f64; 3], f64) {
        let c = &self.cells[i as usize];
        match c.polar {
            NOT_POLAR => {}
            POLAR_EMPTY => return ([0.0; 3], 0.0),
            square => {
                let s = self.polar[square as usize].share(kc, lc);
                return (s.sum, s.weight);
            }
        }
        let ws = self.table.corner_weights(c, kc, lc);
        let mut sum = [0.0; 3];
        let mut weight = 0.0;
        for (p, w) in c.corners.iter().zip(ws) {
            let l = self.samples[*p as usize].radiance();
            for ch in 0..3 {
                sum[ch] += w * l[ch];
            }
            weight += w;
        }
        (sum, weight)
    }

    /// The filtered sample of a pixel over the leaves of its window.
    fn accumulate(&mut self, px: &PixelState) -> S {
        let (kc, lc, weight) = (px.kc, px.lc, px.weight);
        // A lattice point is a corner of up to four leaves: its weights are
        // summed first (in `scratch`, indexed by sample), so each sample is
        // accumulated once.
        let scratch = &mut self.scratch;
        scratch.resize(self.samples.len(), 0.0);
        let mut touched: Vec<u32> = Vec::new();
        let mut polar: Vec<u32> = Vec::new();
        let mut stack = px.roots.clone();
        while let Some(i) = stack.pop() {
            let c = self.cells[i as usize];
            if c.child != 0 {
                stack.extend(c.child..c.child + 4);
                continue;
            }
            if c.polar != NOT_POLAR {
                if c.polar != POLAR_EMPTY {
                    polar.push(c.polar);
                }
                continue;
            }
            for (p, w) in c.corners.iter().zip(self.table.corner_weights(&c, kc, lc)) {
                if w != 0.0 {
                    if scratch[*p as usize] == 0.0 {
                        touched.push(*p);
                    }
                    scratch[*p as usize] += w;
                }
            }
        }
        let mut acc = S::default();
        for p in touched {
            acc.add_weighted(&self.samples[p as usize], scratch[p as usize] / weight);
            scratch[p as usize] = 0.0;
        }
        let filter = self.job.filter;
        let (pcx, pcy) = ((kc / UNITS_PER_PX) as f64 + 0.5, (lc / UNITS_PER_PX) as f64 + 0.5);
        for square in polar {
            // The current rectangles' nodes (a bisected rectangle's stay in the list).
            let square = &self.polar[square as usize];
            for rect in &square.rects {
                for (node, sample) in square.nodes[rect.nodes.clone()].iter().zip(&square.samples[rect.nodes.clone()]) {
                    let w = node.kk * filter.weight(node.x - pcx) * filter.weight(node.y - pcy);
                    if w != 0.0 {
                        acc.add_weighted(sample, w / weight);
                    }
                }
            }
        }
        acc
    }

    fn add_flat(&self, i: u32, w: f64, flat: &mut [f64; 3]) {
        let c = &self.cells[i as usize];
        if c.flat {
            for ch in 0..3 {
                flat[ch] += w * c.spread[ch];
            }
        }
    }

    fn finish(&mut self, px: &PixelState, err: [f64; 3]) -> FilteredPixel<S> {
        let value = self.accumulate(px);
        let own = value.own_error();
        FilteredPixel {
            index: px.index,
            value,
            error: [err[0] + own[0], err[1] + own[1], err[2] + own[2]],
        }
    }

    /// The pixel's frontier for the next round: the children of its
    /// pending cells with the largest errors, until the errors of the rest
    /// sum to at most [`UNSPLIT_SHARE`] of what the tolerance `allowed`
    /// leaves after the carried and flat errors (all of them when nothing is
    /// left). Splitting every refinable cell of an unconverged window, as
    /// before, refined the graded mesh at a light's image one level per round
    /// while a shadow edge elsewhere in the window was the error (box
    /// occluder, 96×54: half the lattice's view rays within 3 px of the light).
    fn choose_splits(&self, px: &mut PixelState, allowed: f64) {
        let budget: [f64; 3] = std::array::from_fn(|ch| allowed - px.carried[ch] - px.flat[ch] / px.weight);
        let children = |i: u32| {
            let first = self.cells[i as usize].child;
            (first..first + 4).filter(|&j| self.cells[j as usize].refinable)
        };
        if budget.iter().any(|b| b.is_nan() || *b <= 0.0) {
            for &i in px.pending.keys() {
                px.frontier.extend(children(i));
            }
            return;
        }
        // Each pending cell's error as a share of the budget (its largest channel).
        let mut order: Vec<(f64, u32)> = px
            .pending
            .iter()
            .map(|(&i, p)| ((0..3).fold(0.0f64, |m, ch| m.max(p.error[ch] / budget[ch])), i))
            .collect();
        // Largest share first; ties by cell index, so the order is reproducible.
        order.sort_unstable_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut rest: f64 = order.iter().map(|o| o.0).sum();
        for (share, i) in order {
            if rest <= UNSPLIT_SHARE {
                break;
            }
            rest -= share;
            px.frontier.extend(children(i));
        }
    }

    /// Traces, as two batches, the points round 0 reads: the corners of
    /// the new root cells of the windows of `pixels` (those not in a polar
    /// square), then the stencils of [`Self::root_deviation`] for the roots
    /// that [`Self::new_cell`] will find not flat by their corners (the same
    /// test, so no ray is traced that it would not trace).
    fn prefetch_roots(&mut self, pixels: &[usize]) {
        if !self.spare_threads() {
            return;
        }
        let half = self.table.shared.half_units;
        let n_roots = 2 * half / ROOT_CELL;
        let mut new_roots: Vec<(i64, i64)> = Vec::new();
        for &index in pixels {
            let (x, y) = ((index % self.job.width) as i64, (index / self.job.width) as i64);
            let (kc, lc) = (x * UNITS_PER_PX, y * UNITS_PER_PX);
            for b in 0..n_roots {
                for a in 0..n_roots {
                    let (k, l) = (kc - half + a * ROOT_CELL, lc - half + b * ROOT_CELL);
                    if self.polar_root(k, l).is_none() && !self.roots.contains_key(&(k, l)) {
                        new_roots.push((k, l));
                    }
                }
            }
        }
        new_roots.sort_unstable();
        new_roots.dedup();
        let s = ROOT_CELL;
        self.prefetch(new_roots.iter().flat_map(|&(k, l)| cell_corners(k, l, s)).collect());
        let mut stencils = Vec::new();
        for &(k, l) in &new_roots {
            let corners = cell_corners(k, l, s).map(|(k, l)| self.points[&(k, l)]);
            let (spread, t_spread) = self.corner_spread(&corners);
            if !self.at_light(k, l, s) && !self.within_flat(&spread, t_spread, self.root_scale(k, l)) {
                stencils.extend(deviation_stencils(k, l, s).into_iter().flatten());
            }
        }
        self.prefetch(stencils);
    }

    fn run(&mut self, pixels: &[usize]) -> Vec<FilteredPixel<S>> {
        let half = self.table.shared.half_units;
        let n_roots = 2 * half / ROOT_CELL;
        let tol = self.job.tolerance;
        let mut done = Vec::with_capacity(pixels.len());
        self.prefetch_roots(pixels);
        // Round 0: the root cells of every window.
        let mut active: Vec<PixelState> = Vec::with_capacity(pixels.len());
        for &index in pixels {
            let (x, y) = ((index % self.job.width) as i64, (index / self.job.width) as i64);
            let (kc, lc) = (x * UNITS_PER_PX, y * UNITS_PER_PX);
            let mut roots = Vec::with_capacity((n_roots * n_roots) as usize);
            for b in 0..n_roots {
                for a in 0..n_roots {
                    let (k, l) = (kc - half + a * ROOT_CELL, lc - half + b * ROOT_CELL);
                    let r = match self.roots.get(&(k, l)) {
                        Some(&r) => r,
                        None if let Some((square, carrier)) = self.polar_root(k, l) => {
                            let polar = if carrier { square } else { POLAR_EMPTY };
                            let r = self.new_polar_cell(k, l, polar);
                            self.roots.insert((k, l), r);
                            r
                        }
                        None => {
                            let scale = self.root_scale(k, l);
                            let origin = CellOrigin {
                                scale,
                                root: None,
                                parent: None,
                                parent_deviation: None,
                            };
                            let r = self.new_cell(k, l, ROOT_CELL, origin);
                            self.roots.insert((k, l), r);
                            r
                        }
                    };
                    roots.push(r);
                }
            }
            let scale = (self.job.window_scale)(index);
            let mut px = PixelState {
                index,
                kc,
                lc,
                scale,
                roots,
                sum: [0.0; 3],
                weight: 0.0,
                flat: [0.0; 3],
                carried: [0.0; 3],
                pending: HashMap::default(),
                frontier: Vec::new(),
            };
            // The polar squares' error estimates, unnormalised: carried,
            // since splitting the lattice's cells cannot reduce them.
            let mut polar_error = [0.0f64; 3];
            for j in 0..px.roots.len() {
                let r = px.roots[j];
                let square = self.cells[r as usize].polar;
                if square < POLAR_EMPTY {
                    let e = self.polar[square as usize].share(kc, lc).error;
                    for ch in 0..3 {
                        polar_error[ch] += e[ch];
                    }
                }
                let (s, w) = self.cell_sums(r, kc, lc);
                for ch in 0..3 {
                    px.sum[ch] += s[ch];
                }
                px.weight += w;
                self.add_flat(r, w, &mut px.flat);
                if self.cells[r as usize].refinable {
                    px.frontier.push(r);
                }
            }
            if px.weight > 0.0 {
                for ch in 0..3 {
                    px.carried[ch] += polar_error[ch] / px.weight;
                }
            }
            if px.frontier.is_empty() || px.weight <= 0.0 {
                let err: [f64; 3] = std::array::from_fn(|ch| {
                    if px.weight > 0.0 {
                        px.flat[ch] / px.weight + px.carried[ch]
                    } else {
                        0.0
                    }
                });
                done.push(self.finish(&px, err));
            } else {
                active.push(px);
            }
        }
        // Later rounds: split the frontiers of unconverged pixels, then update
        // every active pixel with the cells of its window that were split.
        while !active.is_empty() {
            let mut split: Vec<u32> = active.iter().flat_map(|p| p.frontier.iter().copied()).collect();
            split.sort_unstable();
            split.dedup();
            let wanted = split
                .iter()
                .map(|&i| self.cells[i as usize])
                .filter(|c| c.child == 0)
                .flat_map(|c| split_points(c.k, c.l, c.size))
                .collect();
            self.prefetch(wanted);
            let mut by_root: HashMap<u32, Vec<u32>> = HashMap::default();
            for &i in &split {
                self.split(i);
                by_root.entry(self.cells[i as usize].root).or_default().push(i);
            }
            let mut still = Vec::with_capacity(active.len());
            for mut px in active {
                px.frontier.clear();
                let est = px.sum.map(|v| v / px.weight);
                let mut terminal = [0.0f64; 3];
                // Per parent: the summed change of its children split this
                // round, and those children with their own changes.
                let mut by_parent: HashMap<u32, SplitGroup> = HashMap::default();
                for &r in &px.roots {
                    let Some(cells) = by_root.get(&r) else { continue };
                    for &i in cells {
                        let (s, w) = self.cell_sums(i, px.kc, px.lc);
                        let mut ds = [-s[0], -s[1], -s[2]];
                        let mut dw = -w;
                        let mut is_terminal = true;
                        let first = self.cells[i as usize].child;
                        for j in first..first + 4 {
                            let (sj, wj) = self.cell_sums(j, px.kc, px.lc);
                            for ch in 0..3 {
                                ds[ch] += sj[ch];
                            }
                            dw += wj;
                            self.add_flat(j, wj, &mut px.flat);
                            is_terminal &= !self.cells[j as usize].refinable;
                        }
                        let mut d = [0.0f64; 3];
                        for ch in 0..3 {
                            px.sum[ch] += ds[ch];
                            // The change of the normalised estimate (dw is 0 up to rounding).
                            d[ch] = ((ds[ch] - est[ch] * dw) / px.weight).abs();
                        }
                        let group = by_parent.entry(self.cells[i as usize].parent).or_default();
                        if is_terminal {
                            for ch in 0..3 {
                                terminal[ch] += d[ch];
                            }
                        } else {
                            for ch in 0..3 {
                                group.0[ch] += d[ch];
                            }
                            group.1.push((i, d));
                        }
                    }
                }
                // The error these splits left: each parent's children's change
                // times the rate measured against the parent's own change. A
                // parent's refinable children are always split together, so
                // its pending entry is replaced by theirs.
                for (parent, (sum, children)) in by_parent {
                    let last = px.pending.remove(&parent);
                    let factor: [f64; 3] = std::array::from_fn(|ch| step_factor(sum[ch], last.map_or(0.0, |l| l.change[ch])));
                    for (i, d) in children {
                        let error = std::array::from_fn(|ch| factor[ch] * d[ch]);
                        px.pending.insert(i, Pending { error, change: d });
                    }
                }
                let mut left = [0.0f64; 3];
                for p in px.pending.values() {
                    for ch in 0..3 {
                        left[ch] += p.error[ch];
                    }
                }
                let mut err = [0.0f64; 3];
                for ch in 0..3 {
                    px.carried[ch] += TERMINAL_FACTOR * terminal[ch];
                    err[ch] = left[ch] + px.carried[ch] + px.flat[ch] / px.weight;
                }
                let scale = px.sum.iter().fold(px.scale, |m, v| m.max((v / px.weight).abs()));
                // A pixel whose carried error (cells at their finest size,
                // e.g. a hard silhouette) already exceeds the tolerance cannot
                // converge: it stops once the cells that could still be
                // refined contribute no more than that, rather than refining
                // every smooth cell of its window to the finest size.
                let converged = err.iter().all(|e| *e <= tol * scale);
                let capped = (0..3).any(|ch| px.carried[ch] > tol * scale) && (0..3).all(|ch| left[ch] <= px.carried[ch].max(tol * scale));
                if px.pending.is_empty() || converged || capped {
                    done.push(self.finish(&px, err));
                } else {
                    self.choose_splits(&mut px, tol * scale);
                    still.push(px);
                }
            }
            active = still;
        }
        done
    }
}

/// The corners of the cell of side `size` with corner (k, l), in the order
/// of [`Cell::corners`]: (k, l), (k + size, l), (k, l + size), (k + size, l + size).
fn cell_corners(k: i64, l: i64, size: i64) -> [(i64, i64); 4] {
    [(k, l), (k + size, l), (k, l + size), (k + size, l + size)]
}

/// The lattice points [`TileLattice::root_deviation`] reads for the root
/// cell of side `s` with corner (k, l): each corner and its four neighbours
/// at distance `s` (centre, −x, +x, −y, +y).
fn deviation_stencils(k: i64, l: i64, s: i64) -> [[(i64, i64); 5]; 4] {
    cell_corners(k, l, s).map(|(ck, cl)| [(ck, cl), (ck - s, cl), (ck + s, cl), (ck, cl - s), (ck, cl + s)])
}

/// The five lattice points [`TileLattice::split`] adds to the cell of side
/// `size` with corner (k, l): its edges' midpoints and its centre.
fn split_points(k: i64, l: i64, size: i64) -> [(i64, i64); 5] {
    let h = size / 2;
    [(k + h, l), (k, l + h), (k + 2 * h, l + h), (k + h, l + 2 * h), (k + h, l + h)]
}

/// The error a round of splits left, per unit of the change it made. Across
/// a step the filter integral converges as O(h): if each split of a cell
/// leaves `ρ` times its error, a split that changed the estimate by `d` left
/// `ρ/(1 − ρ)·d`. `ρ` is about ¼ where the image is smooth, ½ across a step
/// where the window is flat, and more where the window's weight grows towards
/// the step (at ½ px cells on a step along a lattice line, 0.64: the change
/// alone was 0.57× the error left). `ρ` is measured per cell: the summed
/// change of its children split this round over the change its own split
/// made in the last round. The factor is kept within [1, 4] (4 for `ρ` ≥ 0.8,
/// when the changes do not shrink); a cell without a measured split (a root,
/// or a change of 0) takes [`TERMINAL_FACTOR`].
fn step_factor(this_round: f64, last_round: f64) -> f64 {
    if last_round <= 0.0 || !last_round.is_finite() {
        return TERMINAL_FACTOR;
    }
    let rho = this_round / last_round;
    if rho >= 0.8 || !rho.is_finite() {
        4.0
    } else {
        (rho / (1.0 - rho)).clamp(1.0, 4.0)
    }
}

/// A point light's image, where the in-scatter has its 1/r peak, with the
/// directions in the image of the lines through it along which the peak has
/// features (see [`PolarSquare`]).
#[derive(Debug, Clone, Default)]
pub(crate) struct LightImage {
    /// Pixel coordinates (pixel `i` spans `[i, i + 1)`).
    pub at: (f64, f64),
    /// Image angles, radians in `[0, 2π)`, measured from +x towards +y (down):
    /// the images of the silhouette generators of the light's cones (the
    /// cones of [`crate::light::PointSource::kinks`]) as seen from the
    /// camera, both ways along each line.
    pub cuts: Vec<f64>,
}

/// The two silhouette generators of the cone with apex `apex`, unit `axis`
/// and half-angle `acos(cos_half)`, as seen from `eye`: the unit directions
/// along the cone whose tangent planes hold the eye. None when the eye is
/// inside the double cone (it then sees the cone all around its apex) or
/// the cone is a plane (cos_half 0) or a line (±1).
///
/// Derivation: a generator is `g(ψ) = cos γ·a + sin γ·(cos ψ·u + sin ψ·v)`
/// and its tangent plane has normal `n(ψ) = −sin γ·a + cos γ·(cos ψ·u + sin ψ·v)`;
/// `n(ψ)·(eye − apex) = 0` gives `U cos ψ + V sin ψ = tan γ·A` with `A, U, V`
/// the components of `eye − apex` along `a, u, v`, so
/// `ψ = atan2(V, U) ± acos(tan γ·A / √(U² + V²))`.
pub(crate) fn cone_silhouette_generators(
    apex: glam::DVec3,
    axis: glam::DVec3,
    cos_half: f64,
    eye: glam::DVec3,
) -> Option<[glam::DVec3; 2]> {
    if !(cos_half.abs() > 1e-12 && cos_half.abs() < 1.0 - 1e-15) {
        return None;
    }
    let sin_half = (1.0 - cos_half * cos_half).sqrt();
    let u = axis.any_orthonormal_vector();
    let v = axis.cross(u);
    let w = eye - apex;
    let (a, uu, vv) = (w.dot(axis), w.dot(u), w.dot(v));
    let r = uu.hypot(vv);
    let c = sin_half / cos_half * a / r;
    if !c.is_finite() || c.abs() > 1.0 {
        return None;
    }
    let (psi0, delta) = (vv.atan2(uu), c.acos());
    let g = |psi: f64| cos_half * axis + sin_half * (psi.cos() * u + psi.sin() * v);
    Some([g(psi0 + delta), g(psi0 - delta)])
}

/// Gauss–Kronrod 5-point rule on [−1, 1] with its embedded 2-point Gauss
/// rule: (node, Kronrod weight, Gauss weight). Exact for polynomials of
/// degree 7 (Kronrod) and 3 (Gauss).
const GK5: [(f64, f64, f64); 5] = [
    (-0.925_820_099_772_551_5, 0.197_979_797_979_797_98, 0.0),
    (-0.577_350_269_189_625_8, 0.490_909_090_909_090_9, 1.0),
    (0.0, 0.622_222_222_222_222_2, 0.0),
    (0.577_350_269_189_625_8, 0.490_909_090_909_090_9, 1.0),
    (0.925_820_099_772_551_5, 0.197_979_797_979_797_98, 0.0),
];

/// A polar square's rule stops growing at this many rectangles (25 view
/// rays each); its estimate then stands as it is.
const POLAR_MAX_RECTS: usize = 192;
/// Share of a pixel's tolerance its polar squares may use together (each
/// an equal part of it).
const POLAR_SHARE: f64 = 0.25;

/// One node of a [`PolarSquare`]: its pixel coordinates and weights
/// (Kronrod in both directions; Gauss in φ, Kronrod in s; Kronrod in φ,
/// Gauss in s), the Jacobian included.
#[derive(Clone, Copy)]
struct PolarNode {
    x: f64,
    y: f64,
    kk: f64,
    gk: f64,
    kg: f64,
}

/// A polar rectangle's angle range (radians) and radial fraction range, `(φ, s)`.
type RectRange = ((f64, f64), (f64, f64));

/// A rectangle of the polar rule: φ ∈ [φ₀, φ₁], s ∈ [s₀, s₁], its nodes.
#[derive(Clone)]
struct PolarRect {
    phi: (f64, f64),
    s: (f64, f64),
    nodes: std::ops::Range<usize>,
}

/// The 1 × 1 px square around a light's image whose share of every window is
/// integrated in polar coordinates about the image, where the Jacobian ρ
/// cancels the in-scatter's 1/ρ peak (the lattice's bilinear cells converge
/// only as O(h) there, and their estimate missed a narrow beam's apex: a
/// 0.2 rad wedge was 8× low at tolerance 0.03 with an estimate 15× too
/// small). With `ρ = ρ_in(φ) + s·(ρ_out(φ) − ρ_in(φ))` the ray from the image
/// at angle φ crosses the square for s ∈ [0, 1] and the integrand is
/// `(ρ_out − ρ_in)·ρ·W_p·L`, smooth in s (ρL tends to the beam's angular
/// profile as ρ → 0) and in φ between the cuts: the directions of the
/// square's corners (where ρ_in, ρ_out change edge) and of the light's cone
/// silhouettes ([`LightImage::cuts`]). Shadow edges of the light's own
/// casters are lines through the image as well, and other features (a
/// silhouette, another light's beam) are found by the rule's own estimate.
/// Rectangles in (φ, s) take the tensor Gauss–Kronrod 5-point rule (25 view
/// rays; the 7-point rule took twice the rays at tolerance 0.2 for the same
/// estimates); its error in each direction is the difference from the rule
/// with Gauss in that direction, and the sum of the two is charged. The
/// rectangle whose error is the largest share of its pixels' budget is
/// bisected in its worse direction until every pixel holding the square is
/// within its part of [`POLAR_SHARE`] of its tolerance (the share divided
/// among the polar squares its window holds), or [`POLAR_MAX_RECTS`].
/// Windows never straddle the square (their edges lie on the lines the
/// squares are aligned to), so each `W_p` is smooth on it.
struct PolarSquare<S> {
    /// The light's image, pixel coordinates.
    at: (f64, f64),
    nodes: Vec<PolarNode>,
    /// The nodes' view rays.
    samples: Vec<S>,
    rects: Vec<PolarRect>,
    /// The pixels whose windows hold the square, with their shares.
    holders: Vec<((i64, i64), PolarShare)>,
}

/// The polar squares of a filter job: per square (lower corner on the grid
/// of window edges, in whole px from `offset`), the image it is about.
pub(crate) struct PolarPlan {
    /// Where the window edges lie: `offset + integer` px.
    offset: f64,
    /// Square `(i, j)` (lower corner `(i + offset, j + offset)`) → image index.
    squares: HashMap<(i64, i64), usize>,
}

impl PolarPlan {
    /// The squares within ¼ px of each image (1, 2 or 4 of them), for
    /// filters whose window edges lie on a ½ px grid aligned with the root
    /// cells (2 × radius an integer; Blender's 1.5 px is). An image whose
    /// squares another image's squares share, or that hold or nearly hold
    /// another light's image, keeps the lattice's graded mesh.
    fn new(filter: PixelFilter, images: &[LightImage], all_images: &[(f64, f64)]) -> PolarPlan {
        let r = filter.radius();
        let offset = (0.5 + r).rem_euclid(1.0);
        let mut squares: HashMap<(i64, i64), usize> = HashMap::default();
        if r <= 0.0 || (2.0 * r - (2.0 * r).round()).abs() > 1e-12 {
            return PolarPlan { offset, squares };
        }
        let reach = 0.25;
        let mut claimed: HashMap<(i64, i64), Vec<usize>> = HashMap::default();
        let span =
            |c: f64| -> std::ops::RangeInclusive<i64> { ((c - reach - offset).floor() as i64)..=((c + reach - offset).floor() as i64) };
        for (n, img) in images.iter().enumerate() {
            let (cx, cy) = img.at;
            if !(cx.is_finite() && cy.is_finite()) || cx.abs() > 1e9 || cy.abs() > 1e9 {
                continue;
            }
            for j in span(cy) {
                for i in span(cx) {
                    claimed.entry((i, j)).or_default().push(n);
                }
            }
        }
        let mut excluded = vec![false; images.len()];
        for ((i, j), owners) in &claimed {
            let (x0, y0) = (*i as f64 + offset, *j as f64 + offset);
            // Another light's image within ¼ px of the square.
            let others = all_images
                .iter()
                .filter(|&&(x, y)| x >= x0 - reach && x <= x0 + 1.0 + reach && y >= y0 - reach && y <= y0 + 1.0 + reach)
                .count();
            if owners.len() > 1 || others > 1 {
                for &n in owners {
                    excluded[n] = true;
                }
            }
        }
        for (sq, owners) in claimed {
            if !excluded[owners[0]] {
                squares.insert(sq, owners[0]);
            }
        }
        PolarPlan { offset, squares }
    }

    /// The squares of the windows of pixel `(x, y)`, for a window of radius
    /// `r` (`2r` of them along each axis).
    fn window_squares(&self, r: f64, x: i64, y: i64) -> impl Iterator<Item = (i64, i64)> + use<> {
        // Square i spans [i + offset, i + offset + 1]; the window of x spans [x + ½ − r, x + ½ + r].
        let n = (2.0 * r).round() as i64;
        let (i0, j0) = (
            (x as f64 + 0.5 - r - self.offset).round() as i64,
            (y as f64 + 0.5 - r - self.offset).round() as i64,
        );
        (j0..j0 + n).flat_map(move |j| (i0..i0 + n).map(move |i| (i, j)))
    }

    /// Adds to the polar rule the squares among `candidates` that a thin
    /// beam crosses (`beam_width`, see [`AdaptiveFilterJob::beam_width`];
    /// `images` the polar images' positions): a beam narrower than the
    /// lattice's cells can pass between their corners, which then see it
    /// nowhere, and near the image its width tends to 0 (a 0.5° beam left
    /// a pixel 2.9 px from its lamp's image at 2.3e-5 ± 2.5e-5 against
    /// 1.1e-4). In polar coordinates about the
    /// light's image the beam's edges are the cut lines (its cones'
    /// silhouettes are lines through the image), so the rule resolves it at
    /// any width. A square is added about the one image whose light's beam
    /// is thin there, if that image's own squares are the polar rule's, no
    /// other image's beam is thin there too, and no image lies within ¼ px
    /// of it (those keep the lattice).
    fn add_thin_squares(
        &mut self,
        candidates: impl Iterator<Item = (i64, i64)>,
        images: &[(f64, f64)],
        all_images: &[(f64, f64)],
        beam_width: &BeamWidth<'_>,
    ) {
        if self.squares.is_empty() {
            return;
        }
        let reach = 0.25;
        // The images whose own squares are the polar rule's.
        let mut taken = vec![false; images.len()];
        for &n in self.squares.values() {
            taken[n] = true;
        }
        let mut seen: rustc_hash::FxHashSet<(i64, i64)> = Default::default();
        for sq in candidates {
            if self.squares.contains_key(&sq) || !seen.insert(sq) {
                continue;
            }
            let (x0, y0) = (sq.0 as f64 + self.offset, sq.1 as f64 + self.offset);
            let holds_image = all_images
                .iter()
                .any(|&(x, y)| x >= x0 - reach && x <= x0 + 1.0 + reach && y >= y0 - reach && y <= y0 + 1.0 + reach);
            if holds_image {
                continue;
            }
            let centre = (x0 + 0.5, y0 + 0.5);
            // Narrower than the graded mesh's cells there, about
            // 1/(AT_LIGHT_REACH + 1) of the distance to the image: a beam
            // that widens more slowly than that stays thin for the lattice
            // (a cap at ½ px, the root cells, left a toy wedge 0.54 px wide
            // with a pixel 1.08× outside its estimate; one at 1 px, a
            // wedge 1.1 px wide with one 2.3× outside). A beam that widens
            // faster (a 40° one, ≈ 0.7 px wide 1 px from its image) is
            // resolved by the graded mesh; squares for it cost the box
            // occluder 22 % at 96×54.)
            let narrow = |n: usize| {
                let (ix, iy) = images[n];
                let distance = (centre.0 - ix).hypot(centre.1 - iy);
                let cells = distance / (AT_LIGHT_REACH + 1) as f64;
                beam_width(n, centre).is_some_and(|w| w.is_nan() || w < cells)
            };
            let mut owners = (0..taken.len()).filter(|&n| taken[n] && narrow(n));
            if let (Some(n), None) = (owners.next(), owners.next()) {
                self.squares.insert(sq, n);
            }
        }
    }

    /// The square holding the root cell whose lower corner is at pixel
    /// coordinates (x, y), if it is a polar square, and whether the cell
    /// is the square's lower corner cell (which carries the square).
    fn square_of(&self, x: f64, y: f64) -> Option<((i64, i64), bool)> {
        if self.squares.is_empty() {
            return None;
        }
        // Root corners lie on a ½ px grid: round before flooring.
        let (i, j) = (((x - self.offset) * 2.0).round() / 2.0, ((y - self.offset) * 2.0).round() / 2.0);
        let sq = (i.floor() as i64, j.floor() as i64);
        self.squares.contains_key(&sq).then(|| (sq, i == i.floor() && j == j.floor()))
    }
}

/// Where the ray `from + ρ·dir` (ρ ≥ 0) lies inside the rectangle
/// `[lo, hi]`: `(ρ_in, ρ_out)`, or `(0, 0)` where it misses it (slab clipping).
fn ray_in_rect(from: (f64, f64), dir: (f64, f64), lo: (f64, f64), hi: (f64, f64)) -> (f64, f64) {
    let (mut near, mut far) = (0.0f64, f64::INFINITY);
    for (d, a, b) in [(dir.0, lo.0 - from.0, hi.0 - from.0), (dir.1, lo.1 - from.1, hi.1 - from.1)] {
        if d == 0.0 {
            if a > 0.0 || b < 0.0 {
                return (0.0, 0.0);
            }
            continue;
        }
        let (t0, t1) = if d > 0.0 { (a / d, b / d) } else { (b / d, a / d) };
        near = near.max(t0);
        far = far.min(t1);
    }
    if far > near { (near, far) } else { (0.0, 0.0) }
}

/// One pixel's share of a [`PolarSquare`]: `Σ w·L`, `Σ w` and the error
/// estimate of `Σ w·L` (unnormalised, RGB).
#[derive(Clone, Copy, Default)]
struct PolarShare {
    sum: [f64; 3],
    weight: f64,
    error: [f64; 3],
}

/// Per rectangle and pixel: `Σ w·L` and the two directional differences
/// (in-scatter RGB, and the largest transmittance channel).
#[derive(Clone, Copy, Default)]
struct RectShare {
    sum: [f64; 3],
    weight: f64,
    d_phi: [f64; 3],
    d_s: [f64; 3],
    t_phi: f64,
    t_s: f64,
}

impl<S: FilterSample> PolarSquare<S> {
    /// Integrates the polar square `sq` of `plan` (see [`PolarSquare`]) to
    /// [`POLAR_SHARE`] of the tolerance of every pixel whose window holds it.
    fn integrate(
        job: &AdaptiveFilterJob<'_>,
        plan: &PolarPlan,
        norm: f64,
        sample: &(dyn Fn(f64, f64) -> S + Sync),
        sq: (i64, i64),
        spare_threads: &(dyn Fn() -> bool + Sync),
    ) -> Self {
        let img = &job.polar_images[plan.squares[&sq]];
        let (x0, y0) = (sq.0 as f64 + plan.offset, sq.1 as f64 + plan.offset);
        let (x1, y1) = (x0 + 1.0, y0 + 1.0);
        let (cx, cy) = img.at;
        let r = job.filter.radius();
        let tol = job.tolerance;
        // The pixels whose windows hold the square: centres within r − ½ of its centre.
        let first = ((x0 + 0.5 - r).round() as i64, (y0 + 0.5 - r).round() as i64);
        let n = (2.0 * r).round() as i64;
        let mut holders: Vec<((i64, i64), f64)> = Vec::with_capacity((n * n) as usize);
        for py in first.1..first.1 + n {
            for px in first.0..first.0 + n {
                let inside = px >= 0 && py >= 0 && (px as usize) < job.width && (py as usize) < job.height;
                let scale = if inside {
                    (job.window_scale)(py as usize * job.width + px as usize)
                } else {
                    f64::INFINITY
                };
                holders.push(((px, py), scale));
            }
        }
        // How many polar squares each holder's window holds: they share its budget.
        let shared_by: Vec<usize> = holders
            .iter()
            .map(|&((px, py), _)| {
                plan.window_squares(r, px, py)
                    .filter(|sq| plan.squares.contains_key(sq))
                    .count()
                    .max(1)
            })
            .collect();
        // The ray from the image at angle φ inside the square: ρ ∈ [ρ_in, ρ_out].
        let clip = |phi: f64| -> (f64, f64) {
            let (dy, dx) = phi.sin_cos();
            ray_in_rect((cx, cy), (dx, dy), (x0, y0), (x1, y1))
        };
        let two_pi = 2.0 * PI;
        let mut cuts: Vec<f64> = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
            .iter()
            .filter(|&&(x, y)| x != cx || y != cy)
            .map(|&(x, y)| (y - cy).atan2(x - cx).rem_euclid(two_pi))
            .chain(img.cuts.iter().map(|c| c.rem_euclid(two_pi)))
            .filter(|c| c.is_finite())
            .collect();
        cuts.sort_by(f64::total_cmp);
        cuts.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
        if cuts.is_empty() {
            cuts.push(0.0);
        }
        cuts.push(cuts[0] + two_pi);
        let mut square = PolarSquare {
            at: (cx, cy),
            nodes: Vec::new(),
            samples: Vec::new(),
            rects: Vec::new(),
            holders: Vec::new(),
        };
        let pieces: Vec<RectRange> = cuts
            .windows(2)
            .map(|piece| (piece[0], piece[1]))
            .filter(|&(a, b)| {
                let (lo, hi) = clip(0.5 * (a + b));
                b - a > 1e-12 && hi - lo > 1e-12
            })
            .map(|phi| (phi, (0.0, 1.0)))
            .collect();
        let mut shares: Vec<Vec<RectShare>> = Vec::new();
        for rect in square.trace(sample, &clip, &pieces, spare_threads()) {
            shares.push(square.shares(job.filter, &rect, &holders));
            square.rects.push(rect);
        }
        // Bisect the worst rectangle until every pixel is within its share.
        loop {
            let mut total = vec![([0.0f64; 3], [0.0f64; 3], 0.0f64); holders.len()];
            for rs in &shares {
                for (t, s) in total.iter_mut().zip(rs) {
                    for ch in 0..3 {
                        t.0[ch] += s.sum[ch];
                        t.1[ch] += s.d_phi[ch].abs() + s.d_s[ch].abs();
                    }
                    t.2 += s.t_phi.abs() + s.t_s.abs();
                }
            }
            // Each pixel's budget: its share of the tolerance at the larger of
            // its window scale and what the square alone gives it.
            let budget: Vec<f64> = holders
                .iter()
                .zip(&shared_by)
                .zip(&total)
                .map(|(((_, scale), k), t)| {
                    let own = t.0.iter().fold(0.0f64, |m, v| m.max(v.abs())) / norm;
                    POLAR_SHARE * tol * scale.max(own) * norm / *k as f64
                })
                .collect();
            let t_budget = POLAR_SHARE * tol * norm;
            let converged = total
                .iter()
                .zip(&budget)
                .all(|(t, b)| t.1.iter().all(|e| *e <= *b) && t.2 <= t_budget);
            let cancelled = job.cancel.is_some_and(|c| c.load(std::sync::atomic::Ordering::Relaxed));
            if converged || cancelled || square.rects.len() >= POLAR_MAX_RECTS {
                break;
            }
            // The worst rectangle, by its largest share of any pixel's budget.
            let over = |err: f64, b: f64| if err <= b { err / b.max(f64::MIN_POSITIVE) } else { err / b };
            let mut worst = (0usize, -1.0f64, true);
            for (k, rs) in shares.iter().enumerate() {
                let (mut score, mut along_phi, mut along_s) = (0.0f64, 0.0f64, 0.0f64);
                for (s, b) in rs.iter().zip(&budget) {
                    for ch in 0..3 {
                        let (p, q) = (over(s.d_phi[ch].abs(), *b), over(s.d_s[ch].abs(), *b));
                        score = score.max(p + q);
                        along_phi = along_phi.max(p);
                        along_s = along_s.max(q);
                    }
                    let (p, q) = (over(s.t_phi.abs(), t_budget), over(s.t_s.abs(), t_budget));
                    score = score.max(p + q);
                    along_phi = along_phi.max(p);
                    along_s = along_s.max(q);
                }
                if score > worst.1 {
                    worst = (k, score, along_phi >= along_s);
                }
            }
            let (k, _, phi_first) = worst;
            let old = square.rects[k].clone();
            let (halves_phi, halves_s) = if phi_first {
                let m = 0.5 * (old.phi.0 + old.phi.1);
                ([(old.phi.0, m), (m, old.phi.1)], [old.s, old.s])
            } else {
                let m = 0.5 * (old.s.0 + old.s.1);
                ([old.phi, old.phi], [(old.s.0, m), (m, old.s.1)])
            };
            if (halves_phi[0].1 - halves_phi[0].0) < 1e-12 || (halves_s[0].1 - halves_s[0].0) < 1e-12 {
                break;
            }
            let halves = [(halves_phi[0], halves_s[0]), (halves_phi[1], halves_s[1])];
            let mut halves = square.trace(sample, &clip, &halves, spare_threads()).into_iter();
            let (Some(a), Some(b)) = (halves.next(), halves.next()) else {
                break;
            };
            shares[k] = square.shares(job.filter, &a, &holders);
            square.rects[k] = a;
            shares.push(square.shares(job.filter, &b, &holders));
            square.rects.push(b);
        }
        // Each holder's share, kept for the lattice.
        for &((px, py), _) in &holders {
            let share = square.share_of(job.filter, (px, py));
            square.holders.push(((px, py), share));
        }
        square
    }

    /// Traces the 25 nodes of each rectangle `(φ range, s range)` of
    /// `rects`, all as one batch ([`trace_batch`], on other threads too
    /// where `spare_threads`).
    fn trace(
        &mut self,
        sample: &(dyn Fn(f64, f64) -> S + Sync),
        clip: &dyn Fn(f64) -> (f64, f64),
        rects: &[RectRange],
        spare_threads: bool,
    ) -> Vec<PolarRect> {
        let (cx, cy) = self.at;
        let mut out = Vec::with_capacity(rects.len());
        let first_node = self.nodes.len();
        for &(phi, s) in rects {
            let start = self.nodes.len();
            let (hp, hs) = (0.5 * (phi.1 - phi.0), 0.5 * (s.1 - s.0));
            for &(zp, kp, gp) in &GK5 {
                let angle = 0.5 * (phi.0 + phi.1) + hp * zp;
                let (lo, hi) = clip(angle);
                let (dy, dx) = angle.sin_cos();
                for &(zs, ks, gs) in &GK5 {
                    let t = 0.5 * (s.0 + s.1) + hs * zs;
                    let rho = lo + t * (hi - lo);
                    let (x, y) = (cx + rho * dx, cy + rho * dy);
                    let jac = hp * hs * (hi - lo) * rho;
                    self.nodes.push(PolarNode {
                        x,
                        y,
                        kk: kp * ks * jac,
                        gk: gp * ks * jac,
                        kg: kp * gs * jac,
                    });
                }
            }
            out.push(PolarRect {
                phi,
                s,
                nodes: start..self.nodes.len(),
            });
        }
        let at: Vec<(f64, f64)> = self.nodes[first_node..].iter().map(|n| (n.x, n.y)).collect();
        self.samples.extend(trace_batch(sample, &at, spare_threads));
        out
    }

    /// The rectangle's sums for each pixel of `holders` (pixel, scale).
    fn shares(&self, filter: PixelFilter, rect: &PolarRect, holders: &[((i64, i64), f64)]) -> Vec<RectShare> {
        holders
            .iter()
            .map(|&((px, py), _)| {
                let (pcx, pcy) = (px as f64 + 0.5, py as f64 + 0.5);
                let mut out = RectShare::default();
                let (mut t_phi, mut t_s) = ([0.0f64; 3], [0.0f64; 3]);
                for (node, sample) in self.nodes[rect.nodes.clone()].iter().zip(&self.samples[rect.nodes.clone()]) {
                    let w = filter.weight(node.x - pcx) * filter.weight(node.y - pcy);
                    if w == 0.0 {
                        continue;
                    }
                    let (l, t) = (sample.radiance(), sample.transmittance());
                    out.weight += node.kk * w;
                    for ch in 0..3 {
                        out.sum[ch] += node.kk * w * l[ch];
                        out.d_phi[ch] += (node.kk - node.gk) * w * l[ch];
                        out.d_s[ch] += (node.kk - node.kg) * w * l[ch];
                        t_phi[ch] += (node.kk - node.gk) * w * t[ch];
                        t_s[ch] += (node.kk - node.kg) * w * t[ch];
                    }
                }
                out.t_phi = t_phi.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                out.t_s = t_s.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                out
            })
            .collect()
    }

    /// The share of the pixel centred at (kc, lc) (lattice units; its window holds the square).
    fn share(&self, kc: i64, lc: i64) -> PolarShare {
        let pixel = (kc / UNITS_PER_PX, lc / UNITS_PER_PX);
        self.holders.iter().find(|h| h.0 == pixel).map_or_else(PolarShare::default, |h| h.1)
    }

    /// The share of `pixel` (whose window holds the square), summed over the rectangles.
    fn share_of(&self, filter: PixelFilter, pixel: (i64, i64)) -> PolarShare {
        let holder = [(pixel, 0.0)];
        let mut out = PolarShare::default();
        for rect in &self.rects {
            let s = self.shares(filter, rect, &holder)[0];
            out.weight += s.weight;
            for ch in 0..3 {
                out.sum[ch] += s.sum[ch];
                out.error[ch] += s.d_phi[ch].abs() + s.d_s[ch].abs();
            }
        }
        out
    }
}

/// Integrates the pixels `flagged` (image indices) against the filter on a
/// shared adaptive lattice (see the module documentation). `sample(x, y)`
/// traces the view ray through pixel coordinates (x, y) (pixel `i` spans
/// `[i, i+1)`); it is called for points outside the image too.
pub(crate) fn filter_adaptive<S: FilterSample>(
    job: &AdaptiveFilterJob<'_>,
    flagged: &[usize],
    sample: &(dyn Fn(f64, f64) -> S + Sync),
) -> (Vec<FilteredPixel<S>>, AdaptiveFilterStats) {
    let radius = job.filter.radius();
    if flagged.is_empty() || radius <= 0.0 {
        return (Vec::new(), AdaptiveFilterStats::default());
    }
    // The window rounded up to whole root cells (the weight is 0 beyond the radius).
    let half_units = ((radius * UNITS_PER_PX as f64 / ROOT_CELL as f64).ceil() as i64).max(1) * ROOT_CELL;
    let table = WindowMoments::new(job.filter, half_units);
    let mut plan = PolarPlan::new(job.filter, job.polar_images, job.light_images);
    if let Some(thin) = job.beam_width {
        let squares: Vec<(i64, i64)> = flagged
            .iter()
            .flat_map(|&i| plan.window_squares(radius, (i % job.width) as i64, (i / job.width) as i64))
            .collect();
        let images: Vec<(f64, f64)> = job.polar_images.iter().map(|p| p.at).collect();
        plan.add_thin_squares(squares.into_iter(), &images, job.light_images, thin);
    }
    // The polar squares, once for every tile whose windows hold them (one
    // thread each).
    // Only the squares some flagged pixel's window holds.
    let flagged_set: rustc_hash::FxHashSet<usize> = flagged.iter().copied().collect();
    let holders_flagged = |&(i, j): &(i64, i64)| -> bool {
        let n = (2.0 * radius).round() as i64;
        let first = (
            (i as f64 + plan.offset + 0.5 - radius).round() as i64,
            (j as f64 + plan.offset + 0.5 - radius).round() as i64,
        );
        (first.1..first.1 + n).any(|y| {
            (first.0..first.0 + n).any(|x| {
                x >= 0
                    && y >= 0
                    && (x as usize) < job.width
                    && (y as usize) < job.height
                    && flagged_set.contains(&(y as usize * job.width + x as usize))
            })
        })
    };
    let mut keys: Vec<(i64, i64)> = plan.squares.keys().copied().filter(holders_flagged).collect();
    keys.sort_unstable();
    // Once every square has started, a thread may be free for the rays of
    // the squares still running ([`trace_batch`]).
    let squares_started = std::sync::atomic::AtomicUsize::new(0);
    let squares = if rayon::current_num_threads() > 1 { keys.len() } else { usize::MAX };
    let spare_threads = || squares_started.load(std::sync::atomic::Ordering::Relaxed) >= squares;
    let polar: Vec<PolarSquare<S>> = keys
        .par_iter()
        .map(|&sq| {
            squares_started.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            PolarSquare::integrate(job, &plan, table.norm, sample, sq, &spare_threads)
        })
        .collect();
    let tiles_started = std::sync::atomic::AtomicUsize::new(0);
    let polar_index: HashMap<(i64, i64), u32> = keys.iter().enumerate().map(|(i, &k)| (k, i as u32)).collect();
    let mut tiles: HashMap<(usize, usize), Vec<usize>> = HashMap::default();
    for &i in flagged {
        let (x, y) = (i % job.width, i / job.width);
        tiles.entry((x / TILE_PX, y / TILE_PX)).or_default().push(i);
    }
    let mut groups: Vec<Vec<usize>> = tiles.into_values().collect();
    // Tiles whose windows hold a light's image first (their graded meshes
    // are the costliest: half the lattice's view rays of the box occluder at
    // 96×54 in one tile), then the largest, so the threads finish together.
    let holds_light = |g: &Vec<usize>| {
        g.iter().any(|&i| {
            let (x, y) = ((i % job.width) as f64 + 0.5, (i / job.width) as f64 + 0.5);
            job.light_images
                .iter()
                .any(|&(lx, ly)| (lx - x).abs() <= radius && (ly - y).abs() <= radius)
        })
    };
    groups.sort_by_cached_key(|g| (std::cmp::Reverse(holds_light(g)), std::cmp::Reverse(g.len())));
    // Pixels done; counted and reported under one lock, so that the calls
    // arrive in order and the last reports the total.
    let pixels_done = std::sync::Mutex::new(0usize);
    // The workers take the tiles in that order from one queue (rayon's
    // splitting of an indexed range did not keep it: at 192×108 the light's
    // tile first made the box occluder's lattice slower, 7.6 → 9.8 ms). Each
    // keeps one lattice and reuses its buffers from tile to tile (a sample
    // is ~1 kB: fresh buffers per tile cost more in page faults than the
    // view rays).
    let results: Vec<(Vec<FilteredPixel<S>>, AdaptiveFilterStats)> = super::queued(
        &groups,
        || TileLattice {
            job,
            table: Moments {
                shared: &table,
                fine: Default::default(),
            },
            sample,
            points: HashMap::default(),
            samples: Vec::with_capacity(4096),
            cells: Vec::with_capacity(4096),
            roots: HashMap::default(),
            scratch: Vec::with_capacity(4096),
            plan: &plan,
            polar: &polar,
            polar_index: &polar_index,
            tiles_started: &tiles_started,
            tiles: if rayon::current_num_threads() > 1 {
                groups.len()
            } else {
                usize::MAX
            },
        },
        |lattice, pixels| {
            tiles_started.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            if job.cancel.is_some_and(|c| c.load(std::sync::atomic::Ordering::Relaxed)) {
                return (Vec::new(), AdaptiveFilterStats::default());
            }
            lattice.points.clear();
            lattice.samples.clear();
            lattice.cells.clear();
            lattice.roots.clear();
            let out = lattice.run(pixels);
            let mut done = pixels_done.lock().unwrap_or_else(|e| e.into_inner());
            *done += pixels.len();
            (job.progress)(*done, flagged.len());
            drop(done);
            let stats = AdaptiveFilterStats {
                samples: lattice.samples.len() as u64,
                cells: lattice.cells.len() as u64,
                ..Default::default()
            };
            (out, stats)
        },
    );
    let polar_samples: u64 = polar.iter().map(|p| p.samples.len() as u64).sum();
    let mut stats = AdaptiveFilterStats {
        samples: polar_samples,
        cells: 0,
        polar_squares: polar.len() as u64,
        polar_samples,
    };
    let mut out = Vec::with_capacity(flagged.len());
    for (px, s) in results {
        out.extend(px);
        stats.samples += s.samples;
        stats.cells += s.cells;
    }
    (out, stats)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blackman_harris_window_shape() {
        let f = PixelFilter::default();
        // Peak 1.0 at the centre (0.35875 + 0.48829 + 0.14128 + 0.01168), ~6e-5 at the ends.
        assert!((f.weight(0.0) - 1.0).abs() < 1e-12);
        assert!((f.weight(1.5) - 6e-5).abs() < 1e-5);
        assert_eq!(f.weight(1.51), 0.0);
        let s: f64 = f.nodes(16).iter().map(|p| p.1).sum();
        assert!((s - 1.0).abs() < 1e-12);
        // The closed-form variance against an independent 200 000-node
        // midpoint sum of x²·w over the window, for widths across the
        // allowed range (0.01 ..= 10 px).
        for width_px in [0.01, 1.2, 1.5, 2.0, 10.0] {
            let f = PixelFilter::BlackmanHarris { width_px };
            let sum: f64 = f.nodes(200_000).iter().map(|(x, w)| x * x * w).sum();
            assert!((f.variance() - sum).abs() < 1e-9 * sum, "{width_px}: {} vs {sum}", f.variance());
        }
        assert_eq!(PixelFilter::None.variance(), 0.0);
    }

    #[test]
    fn weights_at_unit_steps_equal_weight() {
        for width_px in [0.5, 1.0, 1.5, 2.75] {
            let f = PixelFilter::BlackmanHarris { width_px };
            for i in 0..=400 {
                let x0 = -3.0 + 9.0 * i as f64 / 400.0;
                let got: [f64; 7] = f.unit_steps().weights(x0);
                for (m, g) in got.iter().enumerate() {
                    let want = f.weight(x0 - m as f64);
                    assert!((g - want).abs() < 1e-14, "{width_px} px at {x0} − {m}: {g} vs {want}");
                }
            }
        }
        let none: [f64; 3] = PixelFilter::None.unit_steps().weights(1.0);
        assert_eq!(none, [0.0, 1.0, 0.0]);
    }
}

#[cfg(test)]
mod adaptive_tests {
    use super::*;

    #[derive(Clone, Copy, Default, Debug)]
    struct Toy {
        l: [f64; 3],
        weight: f64,
    }

    impl FilterSample for Toy {
        fn radiance(&self) -> [f64; 3] {
            self.l
        }
        fn transmittance(&self) -> [f64; 3] {
            [1.0; 3]
        }
        fn own_error(&self) -> [f64; 3] {
            [0.0; 3]
        }
        fn add_weighted(&mut self, other: &Self, weight: f64) {
            for c in 0..3 {
                self.l[c] += weight * other.l[c];
            }
            self.weight += weight;
        }
    }

    /// Image size of the toy tests, px.
    const TOY_SIZE: (usize, usize) = (12, 10);

    /// The brightest centre sample within ±2 px of pixel `i` (the window scale).
    fn toy_window_max(f: &dyn Fn(f64, f64) -> f64, i: usize) -> f64 {
        let (w, h) = TOY_SIZE;
        let (x, y) = ((i % w) as i64, (i / w) as i64);
        let mut m = 0.0f64;
        for dy in -2..=2i64 {
            for dx in -2..=2i64 {
                let (nx, ny) = (x + dx, y + dy);
                if nx >= 0 && ny >= 0 && nx < w as i64 && ny < h as i64 {
                    m = m.max(f(nx as f64 + 0.5, ny as f64 + 0.5).abs());
                }
            }
        }
        m
    }

    /// Every pixel of the toy image `f` through the adaptive filter.
    fn filter_toy(f: &(dyn Fn(f64, f64) -> f64 + Sync), tol: f64, lights: &[(f64, f64)]) -> (Vec<FilteredPixel<Toy>>, AdaptiveFilterStats) {
        filter_toy_polar(f, tol, lights, &[], None)
    }

    /// [`filter_toy`] with the polar rule at `polar`'s images.
    fn filter_toy_polar(
        f: &(dyn Fn(f64, f64) -> f64 + Sync),
        tol: f64,
        lights: &[(f64, f64)],
        polar: &[LightImage],
        beam_width: Option<&BeamWidth<'_>>,
    ) -> (Vec<FilteredPixel<Toy>>, AdaptiveFilterStats) {
        let sample = |x: f64, y: f64| Toy {
            l: [f(x, y); 3],
            weight: 0.0,
        };
        filter_toy_sampled(f, tol, lights, polar, beam_width, &sample)
    }

    /// [`filter_toy_polar`] with the view rays traced by `sample`.
    fn filter_toy_sampled(
        f: &(dyn Fn(f64, f64) -> f64 + Sync),
        tol: f64,
        lights: &[(f64, f64)],
        polar: &[LightImage],
        beam_width: Option<&BeamWidth<'_>>,
        sample: &(dyn Fn(f64, f64) -> Toy + Sync),
    ) -> (Vec<FilteredPixel<Toy>>, AdaptiveFilterStats) {
        let (w, h) = TOY_SIZE;
        let scale_of = |i: usize| toy_window_max(f, i);
        let job = AdaptiveFilterJob {
            cancel: None,
            progress: &|_, _| {},
            filter: PixelFilter::default(),
            width: w,
            height: h,
            tolerance: tol,
            window_scale: &scale_of,
            light_images: lights,
            polar_images: polar,
            beam_width,
        };
        let flagged: Vec<usize> = (0..w * h).collect();
        filter_adaptive(&job, &flagged, sample)
    }

    /// Brute force: n×n midpoint rule of f·w over the window, normalised.
    fn brute(filter: &PixelFilter, f: &dyn Fn(f64, f64) -> f64, cx: f64, cy: f64, n: usize) -> f64 {
        let nodes = filter.nodes(n);
        let mut s = 0.0;
        for &(dy, wy) in &nodes {
            for &(dx, wx) in &nodes {
                s += wx * wy * f(cx + dx, cy + dy);
            }
        }
        s
    }

    /// Composite 8-point Gauss–Legendre (the module's `GL8`) on `panels`
    /// equal panels of [−1, 1].
    fn composite_gl8(panels: usize) -> Vec<(f64, f64)> {
        (0..panels)
            .flat_map(|k| {
                GL8.iter().map(move |&(z, g)| {
                    let (lo, hi) = (k as f64 / panels as f64, (k + 1) as f64 / panels as f64);
                    (2.0 * (lo + 0.5 * (hi - lo) * (z + 1.0)) - 1.0, g / panels as f64)
                })
            })
            .collect()
    }

    /// Brute force for a window holding the singular point `(px, py)` of
    /// `f = a/ρ + b` (ρ the distance to it): polar coordinates about the
    /// point, where the Jacobian ρ cancels the peak, Gauss–Legendre in ρ and
    /// in θ, with θ split at the window's corners (where ρ_max(θ) has kinks).
    fn brute_polar(filter: &PixelFilter, light: (f64, f64), a: f64, b: f64, cx: f64, cy: f64) -> f64 {
        brute_polar_profile(filter, light, &|_| a, b, (16, &composite_gl8(8)), &[], cx, cy)
    }

    /// Brute force of a window of `f = A(θ)/ρ` (holding the singular point
    /// or not), with `A` smooth between the angles `kinks`: θ in 64 parts of
    /// each piece, 8-point Gauss–Legendre in each.
    fn brute_wedge(filter: &PixelFilter, light: (f64, f64), a: &dyn Fn(f64) -> f64, kinks: &[f64], cx: f64, cy: f64) -> f64 {
        brute_polar_profile(filter, light, a, 0.0, (64, &GL8), kinks, cx, cy)
    }

    /// `f = a(θ)/ρ + b` over the window of the pixel centred at (cx, cy),
    /// polar about `(px, py)` (inside the window or not): each θ piece
    /// between the window's corners and `kinks` in `theta.0` equal parts,
    /// each with the nodes `theta.1` on [−1, 1]; ρ across the window by
    /// [`composite_gl8`]`(8)`.
    #[allow(clippy::too_many_arguments)]
    fn brute_polar_profile(
        filter: &PixelFilter,
        (px, py): (f64, f64),
        a: &dyn Fn(f64) -> f64,
        b: f64,
        theta: (usize, &[(f64, f64)]),
        kinks: &[f64],
        cx: f64,
        cy: f64,
    ) -> f64 {
        let r = filter.radius();
        let rho_nodes = composite_gl8(8);
        let (x0, x1, y0, y1) = (cx - r, cx + r, cy - r, cy + r);
        let mut cuts: Vec<f64> = [(x0, y0), (x1, y0), (x0, y1), (x1, y1)]
            .iter()
            .map(|&(x, y)| (y - py).atan2(x - px))
            .chain(kinks.iter().copied())
            .map(|t| t.rem_euclid(2.0 * PI))
            .collect();
        cuts.push(0.0);
        cuts.push(2.0 * PI);
        cuts.sort_by(f64::total_cmp);
        let norm = (0.35875 * 2.0 * r).powi(2);
        let (parts, nodes) = theta;
        // Where the ray from the point along (c, s) is inside the window.
        let clip = |c: f64, s: f64| ray_in_rect((px, py), (c, s), (x0, y0), (x1, y1));
        let mut total = 0.0;
        for seg in cuts.windows(2) {
            for sub in 0..parts {
                let (t0, t1) = (
                    seg[0] + (seg[1] - seg[0]) * sub as f64 / parts as f64,
                    seg[0] + (seg[1] - seg[0]) * (sub + 1) as f64 / parts as f64,
                );
                for &(zt, wt) in nodes {
                    let th = 0.5 * (t0 + t1) + 0.5 * (t1 - t0) * zt;
                    let (c, s) = (th.cos(), th.sin());
                    let (lo, hi) = clip(c, s);
                    if hi <= lo {
                        continue;
                    }
                    let at = a(th);
                    for &(zr, wr) in &rho_nodes {
                        let rho = lo + 0.5 * (hi - lo) * (zr + 1.0);
                        let (x, y) = (px + rho * c, py + rho * s);
                        let g = (at + b * rho) * filter.weight(x - cx) * filter.weight(y - cy);
                        total += g * 0.5 * (hi - lo) * wr * 0.5 * (t1 - t0) * wt;
                    }
                }
            }
        }
        total / norm
    }

    /// Checks every filtered pixel of a toy image with a light at `light`
    /// against `exact(cx, cy, holds)` (`holds`: the window holds the image,
    /// its edge included when `closed`): the number within their estimates,
    /// and the worst error over `scale(index, exact)`.
    fn honest_at_light(
        out: &[FilteredPixel<Toy>],
        light: (f64, f64),
        exact: &dyn Fn(f64, f64, bool) -> f64,
        scale: &dyn Fn(usize, f64) -> f64,
        closed: bool,
    ) -> (usize, f64) {
        let (w, r) = (TOY_SIZE.0, PixelFilter::default().radius());
        let (mut honest, mut worst) = (0, 0.0f64);
        for p in out {
            let (cx, cy) = ((p.index % w) as f64 + 0.5, (p.index / w) as f64 + 0.5);
            let (dx, dy) = ((light.0 - cx).abs(), (light.1 - cy).abs());
            let holds = if closed { dx <= r && dy <= r } else { dx < r && dy < r };
            let want = exact(cx, cy, holds);
            let err = (p.value.l[0] - want).abs();
            worst = worst.max(err / scale(p.index, want));
            if err <= p.error[0] + 1e-9 * scale(p.index, 0.0) {
                honest += 1;
            } else {
                eprintln!(
                    "  ({cx}, {cy}) holds {holds}: {} vs {want}: err {err:.3e} > estimate {:.3e}",
                    p.value.l[0], p.error[0]
                );
            }
        }
        (honest, worst)
    }

    #[test]
    fn adaptive_lattice_resolves_a_point_lights_image() {
        // f = a/ρ + b about a light's image: inside a pixel, and on a pixel
        // boundary (as the spot of the Cycles scene `spot_box_occluder`).
        let filter = PixelFilter::default();
        for (light, tol) in [((5.37, 4.81), 1e-2), ((6.0, 4.2), 1e-2), ((5.37, 4.81), 1e-3)] {
            let (a, b) = (0.05, 0.1);
            let f = move |x: f64, y: f64| a / (x - light.0).hypot(y - light.1) + b;
            let scale_of = |i: usize| toy_window_max(&f, i);
            let (out, stats) = filter_toy(&f, tol, &[light]);
            let exact = |cx: f64, cy: f64, holds: bool| {
                if holds {
                    brute_polar(&filter, light, a, b, cx, cy)
                } else {
                    brute(&filter, &f, cx, cy, 512)
                }
            };
            let (honest, worst) = honest_at_light(&out, light, &exact, &|i, _| scale_of(i), false);
            eprintln!(
                "light at {light:?}, tol {tol:e}: honest {honest}/{}, worst rel {worst:.3e}, {} rays, {} cells",
                out.len(),
                stats.samples,
                stats.cells
            );
            assert_eq!(honest, out.len());
            assert!(worst <= tol, "worst {worst:e}");
        }
    }

    /// A beam's apex at a light's image: `f = A(θ)/ρ`, `A` a smoothstep
    /// wedge (the cone seen from the side) of half-angle `half` about `axis`
    /// (image angles), integrated with the polar rule at the image (cuts at
    /// the wedge's edges, where the blend starts and ends). Every pixel of
    /// the toy image is filtered and checked against [`brute_wedge`] (a
    /// 512² midpoint rule, used before for the windows that do not hold the
    /// image, was 2.3 % off where the thin wedge grazes a window's edge).
    /// Where the wedge's geometry is given ([`AdaptiveFilterJob::beam_width`]),
    /// the squares it crosses while narrower than 1 px are polar too. The
    /// lattice's graded mesh alone (no polar images) missed the
    /// narrow wedges: at tolerance 0.03 the 0.1 rad wedge's pixel (5, 4) was
    /// 4.7e-4 against 3.7e-3 with an estimate of 2.0e-4, and pixels whose
    /// centre samples all miss the wedge claimed an error of 0.
    #[test]
    fn polar_rule_resolves_a_beams_apex_at_the_lights_image() {
        let filter = PixelFilter::default();
        let smooth = |e0: f64, e1: f64, x: f64| {
            let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
            t * t * (3.0 - 2.0 * t)
        };
        // (image, wedge axis, half-angle, tolerance, whether every pixel meets
        // it, whether the wedge's geometry is given to the lattice)
        for (light, axis, half, tol, meets, geometry) in [
            ((5.37, 4.81), 1.2, 0.35, 0.3, true, false),
            ((5.37, 4.81), 1.2, 0.35, 0.1, true, false),
            ((6.0, 4.69), std::f64::consts::FRAC_PI_2, 0.35, 0.3, true, false),
            // On a pixel corner: four polar squares meet at the image.
            ((6.0, 5.0), 2.5, 0.2, 0.1, true, false),
            ((5.43, 4.74), 0.3, 0.1, 0.3, true, false),
            ((5.43, 4.74), 0.3, 0.1, 0.03, true, false),
            ((5.43, 4.74), 0.3, 0.1, 1e-3, true, false),
            // 0.05 rad: 0.15 px wide 1.5 px out, narrower than the lattice's
            // root cells beyond the polar square. Without its geometry it is
            // honest, but a pixel along it does not converge.
            ((5.5, 5.0), -2.0, 0.05, 0.1, false, false),
            // With the wedges' geometry, the squares they cross while
            // narrower than the lattice's cells are polar too. Without it,
            // the 0.02 rad wedge left 15 pixels outside their estimates at
            // tolerance 0.01 (the worst 73 % of its window's scale), the
            // 0.05 rad one 8 at 0.1 (91 %), the 0.03 rad one 4 at 0.03 (61 %).
            ((5.5, 5.0), -2.0, 0.05, 0.1, true, true),
            ((5.5, 5.0), -2.0, 0.05, 1e-3, true, true),
            ((5.43, 4.74), 0.3, 0.01, 0.01, true, true),
            ((5.43, 4.74), 0.3, 0.02, 0.01, true, true),
            ((5.43, 4.74), 0.3, 0.05, 0.01, true, true),
            ((5.43, 4.74), 0.3, 0.05, 0.1, true, true),
            ((5.43, 4.74), 2.3, 0.03, 0.03, true, true),
            ((5.43, 4.74), 2.3, 0.07, 0.03, true, true),
            ((5.43, 4.74), 2.3, 0.07, 3e-3, true, true),
            ((5.43, 4.74), 2.3, 0.1, 3e-3, true, true),
            // A lamp just outside the frame, its beam entering it: without
            // the geometry, the 0.05 rad wedge left two pixels at the frame's
            // edge outside their estimates (by up to 8×); a rule taking
            // only beams narrower than ½ px left one, 1.08× (its beam 0.54
            // px wide there), while it was a test for the rule.
            ((-0.2, 4.6), 0.8, 0.05, 0.1, true, true),
            ((-0.2, 4.6), 0.8, 0.05, 0.01, true, true),
            ((-0.2, 4.6), 1.2, 0.05, 0.01, true, true),
            // 0.15 rad is not thin by that rule (≈ 0.3 px per px from the
            // image): the lattice's, honest, but a pixel converges only to
            // 5.8e-2 of its scale.
            ((5.43, 4.74), 2.3, 0.15, 3e-3, false, true),
        ] {
            let a = move |th: f64| {
                let d = ((th - axis + PI).rem_euclid(2.0 * PI) - PI).abs();
                0.05 * (1.0 - smooth(half * 0.85, half, d))
            };
            let f = move |x: f64, y: f64| {
                let th = (y - light.1).atan2(x - light.0);
                a(th) / (x - light.0).hypot(y - light.1)
            };
            let scale_of = |i: usize| toy_window_max(&f, i);
            let cuts = vec![axis + half, axis - half, axis + 0.85 * half, axis - 0.85 * half];
            let polar = [LightImage {
                at: light,
                cuts: cuts.clone(),
            }];
            // The wedge's width at c, where it may cross the 1 px square
            // centred there (its edges, lines through the image, pass within
            // the square's half-diagonal of c).
            let width = move |_: usize, c: (f64, f64)| {
                let (dx, dy) = (c.0 - light.0, c.1 - light.1);
                let d = dx.hypot(dy);
                let off = ((dy.atan2(dx) - axis + PI).rem_euclid(2.0 * PI) - PI).abs();
                let outside = (off - half).max(0.0);
                let gap = if outside >= std::f64::consts::FRAC_PI_2 {
                    d
                } else {
                    d * outside.sin()
                };
                (gap <= std::f64::consts::FRAC_1_SQRT_2).then_some(2.0 * d * half.tan())
            };
            let geometry: Option<&BeamWidth<'_>> = if geometry { Some(&width) } else { None };
            let (out, stats) = filter_toy_polar(&f, tol, &[light], &polar, geometry);
            // Polar about the image for every pixel, cut where the blend starts and ends.
            let exact = |cx: f64, cy: f64, _: bool| brute_wedge(&filter, light, &a, &cuts, cx, cy);
            // The window's scale, or the pixel's own value where its centre samples all miss the wedge.
            let (honest, worst) = honest_at_light(&out, light, &exact, &|i, exact| scale_of(i).max(exact), true);
            eprintln!(
                "wedge at {light:?}, axis {axis}, half-angle {half}, tolerance {tol:e}: honest {honest}/{}, worst {worst:.2e}, {} rays",
                out.len(),
                stats.samples
            );
            assert_eq!(honest, out.len());
            assert!(worst <= tol || !meets, "worst {worst:e}");
        }
    }

    fn check(name: &str, f: &(dyn Fn(f64, f64) -> f64 + Sync), tol: f64, lights: &[(f64, f64)], expect_honest: f64) {
        let filter = PixelFilter::default();
        let (w, h) = TOY_SIZE;
        let scale_of = |i: usize| toy_window_max(f, i);
        let (out, stats) = filter_toy(f, tol, lights);
        assert_eq!(out.len(), w * h);
        let mut honest = 0;
        let mut worst = 0.0f64;
        for p in &out {
            let (x, y) = ((p.index % w) as f64 + 0.5, (p.index / w) as f64 + 0.5);
            let exact = brute(&filter, f, x, y, 1024);
            let err = (p.value.l[0] - exact).abs();
            assert!((p.value.weight - 1.0).abs() < 1e-12, "{name}: weights sum to {}", p.value.weight);
            worst = worst.max(err / scale_of(p.index).max(1e-300));
            if err <= p.error[0] + 1e-9 * scale_of(p.index) {
                honest += 1;
            } else {
                eprintln!(
                    "  {name} ({x}, {y}): value {} exact {exact} err {err:.3e} estimate {:.3e}",
                    p.value.l[0], p.error[0]
                );
            }
        }
        let frac = honest as f64 / out.len() as f64;
        eprintln!(
            "{name}: tol {tol:e}: honest {honest}/{}, worst rel {worst:.3e}, {} rays, {} cells",
            out.len(),
            stats.samples,
            stats.cells
        );
        assert!(frac >= expect_honest, "{name}: only {honest}/{} honest", out.len());
    }

    #[test]
    fn step_factor_extrapolates_the_measured_rate() {
        // No earlier round: the terminal factor.
        assert_eq!(step_factor(1.0, 0.0), TERMINAL_FACTOR);
        // ρ = ½ (the error halves per round): what is left equals the change.
        assert!((step_factor(0.5, 1.0) - 1.0).abs() < 1e-15);
        // ρ = 0.64 (the aligned step at ½ px cells): 0.64/0.36.
        assert!((step_factor(0.64, 1.0) - 0.64 / 0.36).abs() < 1e-12);
        // Faster than halving is still charged once; no shrinking at all, four times.
        assert_eq!(step_factor(0.1, 1.0), 1.0);
        assert_eq!(step_factor(2.0, 1.0), 4.0);
        assert_eq!(step_factor(f64::NAN, 1.0), 4.0);
    }

    #[test]
    fn adaptive_lattice_against_brute_force() {
        let bump = |x: f64, y: f64| (-((x - 5.3).powi(2) + (y - 4.1).powi(2)) / 2.0).exp();
        let narrow = |x: f64, y: f64| (-((x - 5.3 - 0.2 * y).powi(2)) / 0.3).exp();
        let step = |x: f64, y: f64| if y > 0.37 * x + 2.1 { 1.0 } else { 0.2 };
        for tol in [1e-1, 5e-2, 1e-2, 1e-3] {
            check("constant", &|_, _| 0.7, tol, &[], 1.0);
            check("bump", &bump, tol, &[], 1.0);
            check("narrow beam", &narrow, tol, &[], 1.0);
            // A line 0.2 px wide (1/e half-width), narrower than the root cells.
            check(
                "thin line",
                &|x: f64, y: f64| (-((x - 5.3 - 0.2 * y).powi(2)) / 0.04).exp(),
                tol,
                &[],
                1.0,
            );
            // A gradient steep on the scale of a root cell but smooth: the
            // root cells' second differences see it.
            check(
                "steep ramp",
                &|x: f64, y: f64| 1.0 / (1.0 + (-(x + 0.3 * y - 6.0) / 0.4).exp()),
                tol,
                &[],
                1.0,
            );
            check("step", &step, tol, &[], 1.0);
            // A low-contrast step (height the tolerance): its second differences
            // alone (Δ/8) would let a root cell it crosses pass as flat.
            check(
                "low step",
                &|x: f64, y: f64| if y > 0.37 * x + 2.1 { 1.0 + tol } else { 1.0 },
                tol,
                &[],
                1.0,
            );
            // A step along a lattice line (the pixel boundary y = 5), just off it.
            check(
                "aligned step",
                &|_: f64, y: f64| if y > 5.0 - 1e-5 { 0.1 } else { 0.0 },
                tol,
                &[],
                1.0,
            );
        }
    }

    /// The toy image's rays, costly (each sleeps 100 µs) and counted per
    /// thread, through the filter on a pool of `threads`.
    fn filter_costly_rays(
        threads: usize,
        f: &(dyn Fn(f64, f64) -> f64 + Sync),
        polar: &[LightImage],
    ) -> (Vec<FilteredPixel<Toy>>, Vec<usize>) {
        let lights: Vec<(f64, f64)> = polar.iter().map(|p| p.at).collect();
        let per_thread: Vec<std::sync::atomic::AtomicUsize> = (0..threads).map(|_| Default::default()).collect();
        let sample = |x: f64, y: f64| {
            std::thread::sleep(std::time::Duration::from_micros(100));
            if let Some(i) = rayon::current_thread_index() {
                per_thread[i].fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            }
            Toy {
                l: [f(x, y); 3],
                weight: 0.0,
            }
        };
        let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("a thread pool");
        let (out, _) = pool.install(|| filter_toy_sampled(f, 1e-2, &lights, polar, None, &sample));
        (
            out,
            per_thread.iter().map(|n| n.load(std::sync::atomic::Ordering::Relaxed)).collect(),
        )
    }

    /// The toy image is one tile and its light's image one polar square, so
    /// before the batches of [`trace_batch`] a second thread had nothing to
    /// do. With costly rays both threads now trace, the same rays, and the
    /// pixels are bit-identical to one thread's.
    #[test]
    fn one_tiles_costly_rays_are_shared_by_the_threads_and_change_nothing() {
        let light = (4.3, 5.6);
        let step = |x: f64, y: f64| if 0.3 * x + y > 6.1 { 1.0 } else { 0.25 };
        let with_light = |x: f64, y: f64| step(x, y) + 0.2 / (x - light.0).hypot(y - light.1).max(1e-9);
        let polar = [LightImage {
            at: light,
            cuts: Vec::new(),
        }];
        // The lattice alone (a step), and with a polar square, whose rays
        // could otherwise make up the second thread's share by themselves.
        type Image<'a> = &'a (dyn Fn(f64, f64) -> f64 + Sync);
        let cases: [(Image, &[LightImage]); 2] = [(&step, &[]), (&with_light, &polar)];
        for (f, polar) in cases {
            let (one, calls_one) = filter_costly_rays(1, f, polar);
            let (two, calls_two) = filter_costly_rays(2, f, polar);
            let total: usize = calls_one.iter().sum();
            assert_eq!(
                total,
                calls_two.iter().sum::<usize>(),
                "the same rays, {calls_one:?} vs {calls_two:?}"
            );
            assert!(
                calls_two.iter().all(|&n| n >= total / 5),
                "both threads trace a share of the {total} rays: {calls_two:?}"
            );
            assert_eq!(one.len(), two.len());
            for (a, b) in one.iter().zip(&two) {
                assert_eq!(a.index, b.index);
                assert_eq!(a.value.l.map(f64::to_bits), b.value.l.map(f64::to_bits), "pixel {}", a.index);
                assert_eq!(a.error.map(f64::to_bits), b.error.map(f64::to_bits), "pixel {}", a.index);
            }
        }
    }
}
