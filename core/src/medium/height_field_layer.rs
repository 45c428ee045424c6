//! A dense lower layer under a wavy boundary — dry ice on a stage (Nishita,
//! Miyawaki & Nakamae 1987 §4, Figs. 6 and 7c).
//!
//! **Model.** The boundary is the height field
//! `z = h(x, y) = z_b + Σ_k A_k sin(k_x,k x + k_y,k y + φ_k)`,
//! `(k_x, k_y) = 2π/λ_k (cos θ_k, sin θ_k)` — Nishita's "short sum of sine
//! waves". Below it the coefficients are `σ_s,lower, σ_t,lower` (phase
//! `p_lower`), above it `σ_s,upper, σ_t,upper` (default vacuum). The boundary
//! lies in the slab `z_b − Σ|A_k| ≤ z ≤ z_b + Σ|A_k| = z_top`.
//!
//! **Boundary crossings first** (Nishita: precompute the intersections so
//! that sampling cannot alias). Along `x(t) = o + t·d` the crossings are the
//! roots of `f(t) = z(t) − h(x(t), y(t))`, with
//! `f'(t) = d_z − Σ A_k ω_k cos(·)`, `ω_k = k_x,k d_x + k_y,k d_y`, and
//! `|f''| ≤ M = Σ |A_k| ω_k²`. Only the part of the ray inside the slab can
//! cross. On an interval `[a, b]` with midpoint `m` and half-width `r`:
//!
//! * if `|f'(m)| > M r`, `f'` has no zero there: `f` is monotone and there is
//!   a root iff `f(a)`, `f(b)` differ in sign; it is refined to full
//!   precision by safeguarded steps to the root of the Taylor parabola at the
//!   current point (Newton's step where the parabola has none, bisection where
//!   either leaves the bracket);
//! * else if `|f(m)| > |f'(m)| r + M r²/2`, Taylor's bound excludes a root;
//! * else if the parabola `f(m) + f'(m) s + (f''(m) − M₃ r/3) s²/2`,
//!   `|f'''| ≤ M₃ = Σ |A_k ω_k³|`, stays on the side of `f(m)` on `|s| ≤ r`,
//!   so does `f` (a ray just over a crest, where `f` is convex: the first
//!   test needs intervals as short as `√(f/M)` there, this one does not);
//! * else the interval is halved.
//!
//! At a midpoint the waves' sines and cosines come from the interval ends'
//! (the phase is linear in `t`: the normalised sum of the ends' unit vectors),
//! where a wave turns by at most π/2 over the interval; the tests carry
//! `1e-13 Σ|A|` of slack on `f` for that (and `1e-13 Σ|A ω|` on `f'`). Over
//! the search's first, longer intervals the left end's are turned by the
//! interval's half-width instead, one sine and cosine per depth for all its
//! intervals; the points the phases stand for then drift from where `f` is
//! evaluated by a few roundings of `t`, which the tests carry as slack too
//! (`Σ|A ω|`, `M` and `M₃` times that drift on `f`, `f'` and `f''`).
//!
//! Both tests are rigorous bounds (up to rounding of `f`), so no crossing is
//! missed except a pair so close that `f` between them is within its
//! rounding (a ray touching a crest): a point there may take the wrong sign,
//! and such a pair, about `2√(2δ/f'')` apart for a rounding `δ` of `f`, can
//! be missed (≈ 1e-7–1e-6 m for the demo's waves; the misclassified length
//! is that width). Each piece between roots
//! is labelled below (`f < 0`) or above by the signs of `f` the search
//! already has at its two ends (the ends of the intervals holding the roots
//! that bound it); only where those disagree (rounding beside a near-double
//! root) is `f` evaluated at its middle. The refinement starts from the
//! midpoint values the monotonicity test computed, where their slack cannot
//! flip the sign that brackets the root.
//!
//! **Optical depth** of any segment: `Σ_pieces σ_t,piece × length` — exact
//! given the crossings. Infinite rays inside the slab (exactly horizontal) are
//! processed in chunks and stopped where every non-zero channel's optical depth
//! has passed 745 (transmittance 0 in f64) or after 10⁶ evaluations of `f`;
//! the rest keeps the last piece's side.
//!
//! **Sunlight.** The sun's irradiance `E` is given at the crest plane `z_top`;
//! above it the upper medium does not dim the sun (as the world medium,
//! Ishiyama eq 11 — an unbounded medium would extinguish it), below it the sun
//! ray from `x` is clipped to `z ≤ z_top` and its optical depth `τ_sun(x)` is
//! computed with the same crossing finder.
//!
//! **Single scattering** on the view ray, piece by piece (`σ` constant on each,
//! `τ(s) = τ(t₀) + σ_t (s − t₀)`):
//!
//! * ambient: `σ_s L_amb e^{−τ(t₀)} (1 − e^{−σ_t ℓ})/σ_t` — closed form;
//! * sun: `σ_s p(μ) E ∫ e^{−τ(s) − τ_sun(x(s))} ds`. The sun ray from a point
//!   on the piece crosses the wavy boundary a varying number of times, so
//!   `τ_sun` is continuous but only piecewise smooth along the view ray; no
//!   closed form is attempted. **It is integrated numerically** by adaptive
//!   Gauss–Kronrod G7–K15 per piece to the scene tolerance (an infinite last
//!   piece mapped by `s = t₀ + u/(σ_t(1 − u))`), and the |K15 − G7| estimate
//!   is returned in [`RayResult::error`], relative in `rel_bound`.

use super::phase::PhaseFunction;
use super::{LightSet, RayResult, ViewRay, rounding_bound};
use crate::numeric::{EPS, integral_exp_neg, integrate_adaptive};
use glam::DVec3;
use smallvec::{SmallVec, smallvec};
use std::cell::RefCell;
use std::sync::atomic::{AtomicU64, Ordering};

/// One sine wave of the boundary: `A·sin(k_x x + k_y y + φ)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Wave {
    /// Amplitude A, m.
    pub amplitude: f64,
    /// Wave vector x component, rad/m.
    pub kx: f64,
    /// Wave vector y component, rad/m.
    pub ky: f64,
    /// Phase φ, rad.
    pub phase: f64,
}

impl Wave {
    /// From the scene's units: amplitude and wavelength in m, direction of
    /// travel and phase in degrees.
    pub fn new(amplitude_m: f64, wavelength_m: f64, direction_deg: f64, phase_deg: f64) -> Wave {
        let k = std::f64::consts::TAU / wavelength_m;
        let th = direction_deg.to_radians();
        Wave {
            amplitude: amplitude_m,
            kx: k * th.cos(),
            ky: k * th.sin(),
            phase: phase_deg.to_radians(),
        }
    }
}

/// Coefficients of one side of the boundary, per channel.
#[derive(Debug, Clone)]
pub struct Side<const C: usize> {
    /// Scattering σ_s, m⁻¹.
    pub scattering: [f64; C],
    /// Extinction σ_t, m⁻¹.
    pub extinction: [f64; C],
    /// Phase function.
    pub phase: PhaseFunction,
}

/// A piece `[t0, t1]` of a ray on one side of the boundary.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Piece {
    /// Start parameter.
    pub t0: f64,
    /// End parameter (may be ∞).
    pub t1: f64,
    /// Below the boundary (in the dense layer).
    pub below: bool,
}

/// The pieces of a ray: a few for a light or sun ray, kept off the heap
/// (the search runs for every quadrature node of the light's in-scatter).
pub type Pieces = SmallVec<[Piece; 8]>;

/// A crossing found by [`Search::isolate`].
#[derive(Debug, Clone, Copy)]
struct Root {
    t: f64,
    /// `f < 0` at the start of the interval that held it.
    below_before: bool,
    /// `f < 0` at its end.
    below_after: bool,
}

/// Evaluations of `f` after which a search stops (the rest keeps its side).
const MAX_EVALS: usize = 1_000_000;
/// Optical depth beyond which the transmittance is 0 in f64.
const SATURATED: f64 = 745.0;

static NEXT_ID: AtomicU64 = AtomicU64::new(1);

struct CacheEntry {
    key: [u64; 8],
    pieces: Pieces,
}

thread_local! {
    /// The crossings of the last few view rays (the renderer asks for optical
    /// depths along the same view ray many times).
    static VIEW_CACHE: RefCell<(usize, Vec<CacheEntry>)> = const { RefCell::new((0, Vec::new())) };
}

/// The layered height-field medium with coefficients resolved to `C` channels.
#[derive(Debug, Clone)]
pub struct HeightFieldLayer<const C: usize> {
    /// Name for reports.
    pub name: String,
    /// Base height z_b, m.
    pub base: f64,
    /// The sine waves.
    pub waves: Vec<Wave>,
    /// Below the boundary.
    pub lower: Side<C>,
    /// Above the boundary.
    pub upper: Side<C>,
    /// Relative tolerance of the numerical sun integral.
    pub tolerance: f64,
    id: u64,
}

/// Running state of one crossing search.
struct Search<'a, const C: usize> {
    layer: &'a HeightFieldLayer<C>,
    o: DVec3,
    d: DVec3,
    evals: usize,
    /// `ω_k = k_x,k d_x + k_y,k d_y` of the first [`FAST_WAVES`] waves.
    omega: [f64; FAST_WAVES],
}

/// Sines and cosines of the waves' phases at one point of a ray (the first
/// `FAST_WAVES` waves), for [`Search::isolate`].
type Phases = [(f64, f64); FAST_WAVES];

/// An interval of [`Search::isolate`]: `(a, b, f(a), f(b))`, the phases at
/// `a` and `b`, and its depth (0 for the whole interval, +1 per halving).
type Bracket = (f64, f64, f64, f64, Phases, Phases, u32);

/// Depths of [`Search::isolate`] whose midpoint phases may come from a
/// rotation of the left end's by the depth's half-width
/// ([`Search::phases_between`]); a chunk of a ray (`256/ω_max` long) needs
/// at most 8.
const ROTATED_DEPTHS: usize = 12;

/// A bound on [`Search::isolate`]'s depth for its drift slack: its intervals
/// stop at `1e-13` of `1 + |a| + |b|`, at most ≈ 44 halvings of any interval.
const SEARCH_DEPTHS: f64 = 64.0;

/// Layers with at most this many waves have their phases at an interval's
/// midpoint found from its ends' ([`Search::phases_between`]).
const FAST_WAVES: usize = 6;

impl<const C: usize> Search<'_, C> {
    /// The waves' `(sin, cos)` at `t`, directly.
    #[inline]
    fn phases_at(&self, t: f64) -> Phases {
        let (x, y) = (self.o.x + self.d.x * t, self.o.y + self.d.y * t);
        let mut out = [(0.0, 1.0); FAST_WAVES];
        for (slot, w) in out.iter_mut().zip(&self.layer.waves) {
            *slot = sin_cos(w.kx * x + w.ky * y + w.phase);
        }
        out
    }

    /// The waves' `(sin, cos)` at the midpoint `m` of `[a, b]` from those at
    /// its ends: the phase is linear along the ray, so at the midpoint it is
    /// the mean of the ends', whose unit vector bisects theirs when they are
    /// less than π apart — `(s_a + s_b, c_a + c_b)` normalised, a square root
    /// instead of a sine and cosine (which were most of the time of a low
    /// lamp's light paths over dry ice). Each halving adds a few ulp of error
    /// to the unit vector (the bisector of two vectors is no worse than they
    /// are), under 1e-13 over the search's depth: the tests of
    /// [`Self::isolate`] carry that as slack.
    ///
    /// Waves that turn by more than π/2 over the interval (the search's
    /// first few depths) are turned from the left end's phase by
    /// `rotation = (sin, cos)(ω·r)`, `r` the depth's half-width, which all
    /// the intervals of one depth share: one sine and cosine per depth
    /// instead of one per interval (58 of a light path's 119 over dry ice
    /// under a low lamp). There `m = a + r`: the phases are the left end's
    /// turned by exactly `r`, while `f` is evaluated at the rounding of
    /// `a + r`; the drift this adds up along the search is carried as slack
    /// ([`Self::isolate`]). `None` where no wave turns that far (or the
    /// depth has no rotation): every wave then takes the bisector.
    #[inline]
    fn phases_between(&self, a: &Phases, b: &Phases, span: f64, m: f64, rotation: Option<&Phases>) -> Phases {
        let mut out = [(0.0, 1.0); FAST_WAVES];
        for (k, w) in self.layer.waves.iter().enumerate() {
            if self.omega[k].abs() * span <= std::f64::consts::FRAC_PI_2 {
                let (s, c) = (a[k].0 + b[k].0, a[k].1 + b[k].1);
                // (|s|, |c| ≤ 2: no overflow, and `hypot`'s care costs more
                // than the rest of the evaluation.)
                let inv = 1.0 / (s * s + c * c).sqrt();
                out[k] = (s * inv, c * inv);
            } else if let Some(rot) = rotation {
                let ((sa, ca), (sr, cr)) = (a[k], rot[k]);
                out[k] = (sa * cr + ca * sr, ca * cr - sa * sr);
            } else {
                let (x, y) = (self.o.x + self.d.x * m, self.o.y + self.d.y * m);
                out[k] = sin_cos(w.kx * x + w.ky * y + w.phase);
            }
        }
        out
    }

    /// `(f, f', f'')` at `t` from the waves' phases there.
    #[inline]
    fn f_df_d2f_from(&mut self, t: f64, phases: &Phases) -> (f64, f64, f64) {
        self.evals += 1;
        let (o, d) = (self.o, self.d);
        let mut h = self.layer.base;
        let mut dh = 0.0;
        let mut d2f = 0.0;
        for ((w, &(s, c)), &om) in self.layer.waves.iter().zip(phases).zip(&self.omega) {
            h += w.amplitude * s;
            dh += w.amplitude * c * om;
            d2f += w.amplitude * s * om * om;
        }
        (o.z + d.z * t - h, d.z - dh, d2f)
    }

    /// `f` at `t` and the waves' phases there (none beyond
    /// [`FAST_WAVES`] waves), for an end of [`Self::isolate`]'s interval;
    /// the same `f` as [`Self::f_df`].
    #[inline]
    fn end_point(&mut self, t: f64) -> (f64, Phases) {
        if self.layer.waves.len() <= FAST_WAVES {
            let phases = self.phases_at(t);
            (self.f_df_d2f_from(t, &phases).0, phases)
        } else {
            (self.f_df(t).0, [(0.0, 1.0); FAST_WAVES])
        }
    }

    #[inline]
    fn f_df(&mut self, t: f64) -> (f64, f64) {
        let (f, df, _) = self.f_df_d2f(t);
        (f, df)
    }

    /// `(f, f', f'')` at `t` ([`HeightFieldLayer::height_above_along`]), for
    /// the convex Taylor test of [`Self::isolate`].
    #[inline]
    fn f_df_d2f(&mut self, t: f64) -> (f64, f64, f64) {
        self.evals += 1;
        self.layer.height_above_along(self.o, self.d, t)
    }

    /// Root of `f` in `[a, b]` where `f` is monotone and changes sign; the
    /// iteration starts at `m` inside, where `mid` is `(f, f', f'')` as the
    /// search saw them and whether those are exact (not from its phases,
    /// which carry its slack); `None`: evaluated here.
    ///
    /// Each step goes to the root of the Taylor parabola at the current
    /// point, `f + f' s + f'' s²/2 = 0` (`f''` costs nothing more than `f'`:
    /// the same sines and cosines); where it has no root in the bracket,
    /// Newton's step, else the bracket's midpoint. The parabola's root is
    /// off the true one by at most `M₃|s|³/(6|f'|)` (Taylor's remainder,
    /// `|f'''| ≤ m3_bound`), Newton's by `M|s|²/(2|f'|)` (`|f''| ≤ m_bound`),
    /// each up to the `O(s)` difference between `|f'|` here and at the root:
    /// once that, with a factor 4 of slack, is below `ε|t|`, the step's end
    /// is returned without evaluating `f` there once more — this rule is not
    /// applied to the search's inexact values at `m`. (Newton's
    /// steps alone took 3.5 evaluations per crossing of a low lamp's light
    /// paths over dry ice.)
    fn refine(
        &mut self,
        (a, b, fa): (f64, f64, f64),
        m: f64,
        mid: Option<((f64, f64, f64), bool)>,
        (m_bound, m3_bound): (f64, f64),
    ) -> f64 {
        let (mut lo, mut hi) = if fa < 0.0 { (a, b) } else { (b, a) };
        let mut t = m;
        let (mid, mut exact) = mid.unwrap_or_else(|| (self.f_df_d2f(m), true));
        let mut known = Some(mid);
        for _ in 0..200 {
            let (f, df, d2f) = match known.take() {
                Some(v) => v,
                None => {
                    exact = true;
                    self.f_df_d2f(t)
                }
            };
            if f == 0.0 && exact {
                return t;
            }
            if f < 0.0 {
                lo = t;
            } else {
                hi = t;
            }
            let (l, h) = (lo.min(hi), lo.max(hi));
            // The parabola's root nearer 0, in the cancellation-free form.
            let disc = df * df - 2.0 * f * d2f;
            let q = df + disc.max(0.0).sqrt().copysign(df);
            let parabola = t - 2.0 * f / q;
            let newton = t - f / df;
            let (next, bound) = if disc >= 0.0 && q != 0.0 && parabola > l && parabola < h {
                let step = (parabola - t).abs();
                (parabola, 4.0 * m3_bound / (6.0 * df.abs()) * step * step * step)
            } else if df != 0.0 && newton > l && newton < h {
                let step = newton - t;
                (newton, 2.0 * m_bound / df.abs() * step * step)
            } else {
                (0.5 * (l + h), f64::INFINITY)
            };
            if exact && bound <= EPS * next.abs() {
                return next;
            }
            let width = h - l;
            if (next - t).abs() <= 2.0 * EPS * t.abs() || width <= 2.0 * EPS * (l.abs() + h.abs()) || next == l || next == h {
                return next;
            }
            t = next;
        }
        t
    }

    /// Roots of `f` in `(a, b)`, appended in increasing order, each with the
    /// sides just before and after it (`f < 0` at the ends of the interval
    /// that held it).
    /// `(a, f(a), phases at a)` and the same at `b` come from [`Self::end_point`].
    fn isolate(
        &mut self,
        (a, fa, pa): (f64, f64, Phases),
        (b, fb, pb): (f64, f64, Phases),
        (m_bound, m3_bound): (f64, f64),
        roots: &mut SmallVec<[Root; 8]>,
    ) {
        // Midpoint phases from the ends' ([`Self::phases_between`]) where the
        // layer has few waves, with their rounding as slack on `f` and `f'`.
        let fast = self.layer.waves.len() <= FAST_WAVES;
        // The drift between the point a midpoint's phases stand for and the
        // point `f` is evaluated at: every depth, turned (`a + r` rounded) or
        // bisected (`(a + b)/2` rounded, the phases then at the mean of what
        // the ends' stand for), adds at most half an ulp at the chunk's
        // largest |t|, so at most `SEARCH_DEPTHS/2` of them in all, plus the
        // ends' own. It changes `f` by at most `Σ|A ω|` per metre, `f'` by
        // `M` and `f''` by `M₃`. (The bisected depths' share was never in
        // the 1e-13 slack: 2.5e-13 rad per rounding at 200 m for a wave
        // 0.55 m long.)
        let drift = (0.5 * SEARCH_DEPTHS + 2.0) * EPS * a.abs().max(b.abs());
        let omega_max = self.omega.iter().take(self.layer.waves.len()).fold(0.0f64, |m, w| m.max(w.abs()));
        let (slack_f, slack_df, slack_d2f) = if fast {
            let (mut sf, mut sdf) = (0.0, 0.0);
            for (w, om) in self.layer.waves.iter().zip(self.omega) {
                sf += w.amplitude.abs();
                sdf += (w.amplitude * om).abs();
            }
            (1e-13 * sf + sdf * drift, 1e-13 * sdf + m_bound * drift, m3_bound * drift)
        } else {
            (0.0, 0.0, 0.0)
        };
        let no_phases = [(0.0, 1.0); FAST_WAVES];
        // Per rotated depth: the waves' (sin, cos)(ω·r), `r` its half-width.
        let half_width = 0.5 * (b - a);
        let mut rotations: [Option<Phases>; ROTATED_DEPTHS] = [None; ROTATED_DEPTHS];
        let mut stack: SmallVec<[Bracket; 32]> = smallvec![(a, b, fa, fb, pa, pb, 0)];
        while let Some((a, b, fa, fb, pa, pb, depth)) = stack.pop() {
            let change = (fa < 0.0) != (fb < 0.0);
            let tiny = 1e-13 * (1.0 + a.abs() + b.abs());
            if b - a <= tiny {
                if change {
                    roots.push(Root {
                        t: 0.5 * (a + b),
                        below_before: fa < 0.0,
                        below_after: fb < 0.0,
                    });
                }
                continue;
            }
            let mut m = 0.5 * (a + b);
            let mut r = 0.5 * (b - a);
            let (pm, (fm, dfm, d2fm)) = if fast {
                // A rotated depth: some wave turns by more than π/2 over the
                // interval (its half-width `depth_r`: exact halvings).
                let rotated = (depth as usize) < ROTATED_DEPTHS && omega_max * (b - a) > std::f64::consts::FRAC_PI_2;
                let depth_r = if rotated { half_width / (1u64 << depth) as f64 } else { 0.0 };
                let rotation = if rotated && a + depth_r > a && a + depth_r < b {
                    m = a + depth_r;
                    r = (m - a).max(b - m);
                    let (omega, waves) = (self.omega, self.layer.waves.len());
                    Some(*rotations[depth as usize].get_or_insert_with(|| {
                        let mut rot = [(0.0, 1.0); FAST_WAVES];
                        for (slot, om) in rot.iter_mut().zip(omega).take(waves) {
                            *slot = sin_cos(om * depth_r);
                        }
                        rot
                    }))
                } else {
                    None
                };
                let pm = self.phases_between(&pa, &pb, b - a, m, rotation.as_ref());
                let v = self.f_df_d2f_from(m, &pm);
                (pm, v)
            } else {
                (no_phases, self.f_df_d2f(m))
            };
            if dfm.abs() > m_bound * r + slack_df {
                if change {
                    // (The midpoint's values where their error cannot flip
                    // the sign that brackets the root, else `f` there anew.)
                    let mid = (fm.abs() > slack_f).then_some((fm, dfm, d2fm));
                    let t = self.refine((a, b, fa), m, mid.map(|v| (v, !fast)), (m_bound, m3_bound));
                    roots.push(Root {
                        t,
                        below_before: fa < 0.0,
                        below_after: fb < 0.0,
                    });
                }
                continue;
            }
            // (Where the ends' signs differ there is a root: no exclusion,
            // which could only come from rounding and would break the
            // crossings' parity.)
            if !change && fm.abs() > (dfm.abs() + slack_df) * r + 0.5 * m_bound * r * r + slack_f {
                continue;
            }
            // The same with the curvature at the midpoint: where the ray
            // passes just over a crest (or under a trough) `f` is convex
            // there (concave), and its least value, not `|f'| r + M r²/2`
            // below `f(m)`, decides (a light path grazing the crests: most
            // of the evaluations of a low lamp over dry ice).
            let sign = if fm > 0.0 { 1.0 } else { -1.0 };
            if !change
                && least_on_interval(sign * fm - slack_f, sign * dfm, sign * d2fm - slack_d2f, (m_bound, m3_bound), r) - slack_df * r > 0.0
            {
                continue;
            }
            // Right half first: the left half is popped (and its roots pushed) first.
            stack.push((m, b, fm, fb, pm, pb, depth + 1));
            stack.push((a, m, fa, fm, pa, pm, depth + 1));
        }
    }
}

/// `(sin x, cos x)` by the `libm` crate (musl's, within 1 ulp), not std's:
/// glibc's `sincos` saves and restores the rounding mode on every call, and
/// that alone was 11 % of a low lamp's time over dry ice (libm: 7 % less CPU
/// there, the same image).
#[inline]
fn sin_cos(x: f64) -> (f64, f64) {
    libm::sincos(x)
}

/// A lower bound on `f` over `[m − r, m + r]` from `f(m)`, `f'(m)`,
/// `f''(m)`, `|f''| ≤ m2` and `|f'''| ≤ m3`: Taylor with the integral remainder gives
/// `f(m + s) ≥ f(m) + f'(m) s + f''(m) s²/2 − m3 |s|³/6
/// ≥ f(m) + f'(m) s + c s²/2`, `c = f''(m) − m3 r/3`, for `|s| ≤ r`; the
/// least value of that parabola on the interval (its vertex where `c > 0`
/// and the vertex lies inside, else the lower end).
fn least_on_interval(f: f64, df: f64, d2f: f64, (m2, m3): (f64, f64), r: f64) -> f64 {
    // (With `1e-12·M` of slack for the rounding of `f''`, as the
    // second-order test has on `M`.)
    let c = d2f - m3 * r / 3.0 - 1e-12 * m2;
    if c > 0.0 && df.abs() < c * r {
        f - df * df / (2.0 * c)
    } else {
        f - df.abs() * r + 0.5 * c * r * r
    }
}

impl<const C: usize> HeightFieldLayer<C> {
    /// A layer; `tolerance` is the relative tolerance of the sun integral.
    pub fn new(name: String, base: f64, waves: Vec<Wave>, lower: Side<C>, upper: Side<C>, tolerance: f64) -> Self {
        HeightFieldLayer {
            name,
            base,
            waves,
            lower,
            upper,
            tolerance,
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
        }
    }

    /// Height above the boundary along `o + t·d` and its first two
    /// derivatives in `t`: `f = z − h`, `f' = d_z − Σ A_k ω_k cos(·)`,
    /// `f'' = Σ A_k ω_k² sin(·)`, `ω_k = k_x,k d_x + k_y,k d_y`.
    #[inline]
    fn height_above_along(&self, o: DVec3, d: DVec3, t: f64) -> (f64, f64, f64) {
        let (x, y, z) = (o.x + d.x * t, o.y + d.y * t, o.z + d.z * t);
        let mut h = self.base;
        let mut dh = 0.0;
        let mut d2f = 0.0;
        for w in &self.waves {
            let (s, c) = sin_cos(w.kx * x + w.ky * y + w.phase);
            let om = w.kx * d.x + w.ky * d.y;
            h += w.amplitude * s;
            dh += w.amplitude * c * om;
            d2f += w.amplitude * s * om * om;
        }
        (z - h, d.z - dh, d2f)
    }

    /// Boundary height at `(x, y)`, m (the sines of the crossing search's, [`sin_cos`]).
    pub fn height(&self, x: f64, y: f64) -> f64 {
        let mut h = self.base;
        for w in &self.waves {
            h += w.amplitude * sin_cos(w.kx * x + w.ky * y + w.phase).0;
        }
        h
    }

    /// Highest possible crest `z_b + Σ|A|`.
    pub fn top(&self) -> f64 {
        self.base + self.waves.iter().map(|w| w.amplitude.abs()).sum::<f64>()
    }

    /// Lowest possible trough `z_b − Σ|A|`.
    pub fn bottom(&self) -> f64 {
        self.base - self.waves.iter().map(|w| w.amplitude.abs()).sum::<f64>()
    }

    /// Whether `p` is below the boundary.
    pub fn is_below(&self, p: DVec3) -> bool {
        p.z < self.height(p.x, p.y)
    }

    fn side(&self, below: bool) -> &Side<C> {
        if below { &self.lower } else { &self.upper }
    }

    /// Steepest possible slope of the boundary, `Σ|A|·|k|` (a bound on `|∇h|`).
    pub fn max_slope(&self) -> f64 {
        self.waves.iter().map(|w| w.amplitude.abs() * w.kx.hypot(w.ky)).sum()
    }

    /// Whether the straight path from some point of `o + t·d`, `t ∈ [a, b]`,
    /// to the point `light` may touch the boundary tangentially. Where it
    /// does, the path's optical depth has a square-root kink in `t` (a crest
    /// the path starts or stops cutting), which no breakpoint marks. A
    /// tangent path is no steeper than the boundary there,
    /// `|v_z| ≤ |v_h|·|∇h| ≤ |v_h|·max_slope`, and touches it between
    /// [`Self::bottom`] and [`Self::top`]: with the light above the top, only
    /// points at or below the top can have such a path, and their paths
    /// rise at least `(z_light − top)/ρ`, `ρ` their horizontal distance from
    /// the light, which is largest at an end of the clipped segment (likewise
    /// below the bottom). A light between the two may always graze.
    pub fn light_path_may_graze(&self, o: DVec3, d: DVec3, a: f64, b: f64, light: DVec3) -> bool {
        if b.partial_cmp(&a) != Some(std::cmp::Ordering::Greater) {
            return false;
        }
        let (top, bottom) = (self.top(), self.bottom());
        // The part of the segment on the layer's side of the light, and the
        // least height between the light and it.
        let (limit, gap, keep_below) = if light.z > top {
            (top, light.z - top, true)
        } else if light.z < bottom {
            (bottom, bottom - light.z, false)
        } else {
            return true;
        };
        let (mut lo, mut hi) = (a, b);
        let inside = |z: f64| if keep_below { z <= limit } else { z >= limit };
        if d.z == 0.0 {
            if !inside(o.z) {
                return false;
            }
        } else {
            let t = (limit - o.z) / d.z;
            // Below the top while t ≤ t_limit for a rising ray (keep_below), and so on.
            if (d.z > 0.0) == keep_below {
                hi = hi.min(t);
            } else {
                lo = lo.max(t);
            }
        }
        if hi.partial_cmp(&lo) != Some(std::cmp::Ordering::Greater) {
            return false;
        }
        if !hi.is_finite() {
            return true;
        }
        let rho = |t: f64| {
            let x = o + d * t;
            (x.x - light.x).hypot(x.y - light.y)
        };
        let rho_max = rho(lo).max(rho(hi));
        // (NaN: may.)
        gap.partial_cmp(&(rho_max * self.max_slope() * (1.0 + 1e-9))) != Some(std::cmp::Ordering::Greater)
    }

    /// A lower bound on the height of the segment `a → b` above the boundary,
    /// `min_s (z − h)(a + s·(b − a))`, m, for a segment that does not cross it
    /// and starts above it; 0 where it touches, `None` where it starts below or
    /// crosses. Branch and bound on the segment (where it meets the slab), with the
    /// crossing finder's Taylor bounds: on `[m − r, m + r]`,
    /// `f ≥ f(m) − |f'(m)|·r − M r²/2`, `|f''| ≤ M = Σ|A|ω²`, or the convex
    /// one of [`least_on_interval`], whichever is higher; an interval is
    /// done once its bound is at least half the least `f` seen (so the result
    /// is within a factor 2 of the true least height), or after 512
    /// evaluations with the bound reached so far (clamped at 0). A segment
    /// wholly above the crests gets its height above the crest plane.
    pub fn clearance_between(&self, a: DVec3, b: DVec3) -> Option<f64> {
        let v = b - a;
        if !v.length().is_finite() || self.is_below(a) {
            return None;
        }
        let (top, bottom) = (self.top(), self.bottom());
        // The segment's part in the slab, s ∈ [s0, s1]; above it, z − top bounds z − h.
        let (mut s0, mut s1) = (0.0f64, 1.0f64);
        if v.z != 0.0 {
            let (sa, sb) = ((bottom - a.z) / v.z, (top - a.z) / v.z);
            s0 = s0.max(sa.min(sb));
            s1 = s1.min(sa.max(sb));
        } else if a.z > top || a.z < bottom {
            s1 = -1.0;
        }
        if s1 < s0 {
            // Wholly above the crests (it starts above the boundary).
            return Some((a.z.min(b.z) - top).max(0.0));
        }
        if a.z.min(b.z) < bottom {
            return None; // (an end below every trough: below the boundary)
        }
        // The bound is taken over the whole segment (the parts above the slab
        // join the part in it continuously).
        let (s0, s1) = (0.0, 1.0);
        let mut best = f64::INFINITY;
        let (m_bound, m3_bound) = self.waves.iter().fold((0.0f64, 0.0f64), |(m2, m3), w| {
            let om = w.kx * v.x + w.ky * v.y;
            (m2 + w.amplitude.abs() * om * om, m3 + (w.amplitude * om * om * om).abs())
        });
        let f_df = |s: f64| self.height_above_along(a, v, s);
        let mut least_seen = f64::INFINITY;
        let mut stack: SmallVec<[(f64, f64); 32]> = smallvec![(s0, s1)];
        let mut evals = 0;
        while let Some((lo, hi)) = stack.pop() {
            let (m, r) = (0.5 * (lo + hi), 0.5 * (hi - lo));
            let (f, df, d2f) = f_df(m);
            evals += 1;
            if f.is_nan() || f < 0.0 {
                return None;
            }
            if f == 0.0 {
                return Some(0.0);
            }
            least_seen = least_seen.min(f);
            let bound = (f - df.abs() * r - 0.5 * m_bound * r * r).max(least_on_interval(f, df, d2f, (m_bound, m3_bound), r));
            if bound >= 0.5 * least_seen || r <= 1e-12 * (s1 - s0).max(1e-300) || evals >= 512 {
                best = best.min(bound);
                continue;
            }
            stack.push((lo, m));
            stack.push((m, hi));
        }
        Some(best.max(0.0))
    }

    /// How fast the paths from the points `x` of a line of unit direction `d`
    /// to `light` can come down to the boundary, m per m along the line, for
    /// points `x` no lower than `lowest_z`: a path whose
    /// [`Self::clearance_between`] is `c > 0` has every path from within
    /// `c / rate` of it clear of the boundary as well. The point a fraction
    /// `s` of the way from `x` to the light moves `(1 − s)` times as far as
    /// `x`, and its height above the boundary changes by at most
    /// `(1 − s)·(|d_z| + max_slope·|d_xy|)` per metre. Only points of a path
    /// at or below the crest plane can meet the boundary; with `x` above it
    /// and the light below it, those have `1 − s ≤ (top − z_L)/(z_x − z_L)`,
    /// largest at the lowest `x`; with both above it, none (rate 0). Else
    /// `1 − s ≤ 1`. (A low lamp over dry ice, eyes above the crests: about a
    /// seventh of the bound `1 + max_slope` this replaces, and as many times
    /// fewer points where the certificate of
    /// [`crate::numeric::integrate_adaptive_cut_at_changes_certified`] looks.)
    pub fn clearance_rate(&self, d: DVec3, lowest_z: f64, light: DVec3) -> f64 {
        let along = d.z.abs() + self.max_slope() * d.x.hypot(d.y);
        let top = self.top();
        // (`lowest_z` NaN: the whole path may reach the boundary.)
        let reach = if lowest_z > top {
            if light.z >= top {
                0.0
            } else {
                (top - light.z) / (lowest_z - light.z)
            }
        } else {
            1.0
        };
        along * reach
    }

    /// Whether the upper side has any extinction.
    pub fn upper_is_vacuum(&self) -> bool {
        self.upper.extinction.iter().all(|v| *v == 0.0)
    }

    fn saturated(&self, below: f64, above: f64) -> bool {
        (0..C).all(|c| {
            let (l, u) = (self.lower.extinction[c], self.upper.extinction[c]);
            (l == 0.0 && u == 0.0) || (l > 0.0 && l * below >= SATURATED) || (u > 0.0 && u * above >= SATURATED)
        })
    }

    /// The pieces of `o + t·d`, `t ∈ [a, b]` (`b` may be ∞), on each side of
    /// the boundary, adjacent pieces on the same side merged.
    pub fn pieces(&self, o: DVec3, d: DVec3, a: f64, b: f64) -> Pieces {
        let mut out = Pieces::new();
        if b.partial_cmp(&a) != Some(std::cmp::Ordering::Greater) {
            return out;
        }
        let push = |out: &mut Pieces, t0: f64, t1: f64, below: bool| {
            if t1.partial_cmp(&t0) != Some(std::cmp::Ordering::Greater) {
                return;
            }
            match out.last_mut() {
                Some(l) if l.below == below => l.t1 = t1,
                _ => out.push(Piece { t0, t1, below }),
            }
        };
        let (zlo, zhi) = (self.bottom(), self.top());
        let (u0, u1) = if d.z == 0.0 {
            if o.z > zhi {
                push(&mut out, a, b, false);
                return out;
            }
            if o.z < zlo {
                push(&mut out, a, b, true);
                return out;
            }
            (f64::NEG_INFINITY, f64::INFINITY)
        } else {
            let (p, q) = ((zlo - o.z) / d.z, (zhi - o.z) / d.z);
            (p.min(q), p.max(q))
        };
        let rising = d.z > 0.0;
        // Before the slab: below if the ray rises into it, above if it falls.
        push(&mut out, a, b.min(u0), rising);
        let (p, q) = (a.max(u0), b.min(u1));
        if q > p {
            self.slab_pieces(o, d, p, q, &mut out, push);
        }
        push(&mut out, a.max(u1), b, !rising);
        out
    }

    fn slab_pieces(&self, o: DVec3, d: DVec3, p: f64, q: f64, out: &mut Pieces, push: impl Fn(&mut Pieces, f64, f64, bool)) {
        let mut omega = [0.0; FAST_WAVES];
        for (slot, w) in omega.iter_mut().zip(&self.waves) {
            *slot = w.kx * d.x + w.ky * d.y;
        }
        let mut s = Search {
            layer: self,
            o,
            d,
            evals: 0,
            omega,
        };
        let mut m_bound = 0.0f64;
        let mut m3_bound = 0.0f64;
        let mut omega_max = 0.0f64;
        for w in &self.waves {
            let om = w.kx * d.x + w.ky * d.y;
            m_bound += w.amplitude.abs() * om * om;
            m3_bound += w.amplitude.abs() * (om * om * om).abs();
            omega_max = omega_max.max(om.abs());
        }
        // A little slack for rounding in the bounds.
        m_bound *= 1.0 + 1e-12;
        m3_bound *= 1.0 + 1e-12;
        let chunk = if omega_max > 0.0 { 256.0 / omega_max } else { f64::INFINITY };
        let (mut below_len, mut above_len) = (0.0f64, 0.0f64);
        for piece in out.iter() {
            let l = piece.t1 - piece.t0;
            if piece.below { below_len += l } else { above_len += l }
        }
        let mut t = p;
        let mut roots: SmallVec<[Root; 8]> = SmallVec::new();
        let mut last_below = None;
        // `f` and the phases at `t`: the last chunk's end after the first.
        let mut at_t = None;
        while t < q {
            let e = if q - t > chunk { t + chunk } else { q };
            let (ft, pt) = at_t.take().unwrap_or_else(|| s.end_point(if t.is_finite() { t } else { 0.0 }));
            if !e.is_finite() {
                // f does not vary along the ray (no wave changes along it and
                // d_z = 0): one side all the way.
                let below = ft < 0.0;
                push(out, t, e, below);
                return;
            }
            let (fe, pe) = s.end_point(e);
            at_t = Some((fe, pe));
            roots.clear();
            s.isolate((t, ft, pt), (e, fe, pe), (m_bound, m3_bound), &mut roots);
            // A piece's side: the sign of `f` at its two ends as the search
            // saw them (just after the root that opens it, just before the
            // one that closes it) when they agree, else at its middle. They
            // can disagree beside a near-double root, where rounding of `f`
            // flips signs that the Taylor test then steps over (a ray tangent
            // to the surface: a 1e-8 m pair).
            let mut start = t;
            for k in 0..=roots.len() {
                let end = if k < roots.len() { roots[k].t } else { e };
                if end > start {
                    let left = if k == 0 { ft < 0.0 } else { roots[k - 1].below_after };
                    let right = if k < roots.len() { roots[k].below_before } else { fe < 0.0 };
                    let below = if left == right { left } else { s.f_df(0.5 * (start + end)).0 < 0.0 };
                    push(out, start, end, below);
                    if below {
                        below_len += end - start
                    } else {
                        above_len += end - start
                    }
                    last_below = Some(below);
                }
                start = start.max(end);
            }
            t = e;
            if t < q && (s.evals > MAX_EVALS || self.saturated(below_len, above_len)) {
                push(out, t, q, last_below.unwrap_or(ft < 0.0));
                return;
            }
        }
    }

    fn depth_of(&self, pieces: &[Piece], upto: f64) -> [f64; C] {
        let mut tau = [0.0; C];
        for p in pieces {
            let len = p.t1.min(upto) - p.t0;
            if len.is_nan() || len <= 0.0 {
                continue;
            }
            let side = self.side(p.below);
            for c in 0..C {
                let k = side.extinction[c];
                if k != 0.0 {
                    tau[c] += k * len;
                }
            }
        }
        tau
    }

    /// Calls `f` with the pieces of `[0, s_max]` of the view ray (cached per thread).
    fn with_view_pieces<R>(&self, ray: &ViewRay, f: impl FnOnce(&[Piece]) -> R) -> R {
        let key = [
            self.id,
            ray.origin.x.to_bits(),
            ray.origin.y.to_bits(),
            ray.origin.z.to_bits(),
            ray.dir.x.to_bits(),
            ray.dir.y.to_bits(),
            ray.dir.z.to_bits(),
            ray.s_max.to_bits(),
        ];
        VIEW_CACHE.with(|cell| {
            let mut cache = cell.borrow_mut();
            if let Some(e) = cache.1.iter().find(|e| e.key == key) {
                return f(&e.pieces);
            }
            let pieces = self.pieces(ray.origin, ray.dir, 0.0, ray.s_max);
            let r = f(&pieces);
            let entry = CacheEntry { key, pieces };
            if cache.1.len() < 4 {
                cache.1.push(entry);
            } else {
                let slot = cache.0 % 4;
                cache.1[slot] = entry;
                cache.0 += 1;
            }
            r
        })
    }

    /// The sub-range of `[0, s_max]` where the medium is non-zero: the whole ray
    /// if the upper side is not vacuum, else the hull of the pieces below.
    pub fn segment(&self, ray: &ViewRay) -> Option<(f64, f64)> {
        if ray.s_max.is_nan() || ray.s_max <= 0.0 {
            return None;
        }
        if !self.upper_is_vacuum() {
            return Some((0.0, ray.s_max));
        }
        self.with_view_pieces(ray, |pieces| {
            let mut below = pieces.iter().filter(|p| p.below);
            let first = below.next()?;
            let last = below.next_back().unwrap_or(first);
            Some((first.t0, last.t1))
        })
    }

    /// Optical depth from the origin to `s`.
    pub fn optical_depth(&self, ray: &ViewRay, s: f64) -> [f64; C] {
        if s.is_nan() || s <= 0.0 {
            return [0.0; C];
        }
        if s <= ray.s_max {
            self.with_view_pieces(ray, |pieces| self.depth_of(pieces, s))
        } else {
            self.depth_of(&self.pieces(ray.origin, ray.dir, 0.0, s), s)
        }
    }

    /// Optical depth of the straight segment `a → b` (no caching).
    pub fn optical_depth_between(&self, a: DVec3, b: DVec3) -> [f64; C] {
        self.optical_depth_and_pieces_between(a, b).0
    }

    /// [`Self::optical_depth_between`] and the number of pieces of the
    /// segment on alternating sides of the boundary (1 + its crossings).
    pub fn optical_depth_and_pieces_between(&self, a: DVec3, b: DVec3) -> ([f64; C], usize) {
        let v = b - a;
        let len = v.length();
        if len.is_nan() || len <= 0.0 {
            return ([0.0; C], 0);
        }
        let pieces = self.pieces(a, v / len, 0.0, len);
        (self.depth_of(&pieces, len), pieces.len())
    }

    /// Optical depth of the sun path from `p`, clipped to `z ≤ z_top`.
    pub fn sun_depth(&self, p: DVec3, to_sun: DVec3) -> [f64; C] {
        let top = self.top();
        let (a, b) = if to_sun.z > 0.0 {
            (0.0, (top - p.z) / to_sun.z)
        } else if p.z > top {
            if to_sun.z == 0.0 {
                return [0.0; C];
            }
            ((top - p.z) / to_sun.z, f64::INFINITY)
        } else {
            (0.0, f64::INFINITY)
        };
        if b.partial_cmp(&a) != Some(std::cmp::Ordering::Greater) {
            return [0.0; C];
        }
        self.depth_of(&self.pieces(p, to_sun, a, b), f64::INFINITY)
    }

    /// Sun transmittance at `p`.
    pub fn sun_transmittance_at(&self, p: DVec3, to_sun: DVec3) -> [f64; C] {
        self.sun_depth(p, to_sun).map(|t| if t == 0.0 { 1.0 } else { (-t).exp() })
    }

    /// `σ_s·p(μ)` of the side `p` is on.
    pub fn scattering_phase_at(&self, p: DVec3, mu: f64) -> [f64; C] {
        let side = self.side(self.is_below(p));
        let ph = side.phase.eval(mu);
        side.scattering.map(|s| s * ph)
    }

    /// Source σ_s J at distance `s`.
    pub fn source(&self, ray: &ViewRay, s: f64, lights: &LightSet<C>) -> [f64; C] {
        let p = ray.origin + ray.dir * s;
        let side = self.side(self.is_below(p));
        if side.scattering.iter().all(|v| *v == 0.0) {
            return [0.0; C];
        }
        super::scattering_source(&side.scattering, &side.phase, ray.dir, lights, |sun| {
            Some(self.sun_transmittance_at(p, sun.to_sun))
        })
    }

    /// Single scattering of the layer alone on the ray: ambient in closed form
    /// per piece, sun by adaptive Gauss–Kronrod per piece with its estimate.
    pub fn closed_form(&self, ray: &ViewRay, lights: &LightSet<C>) -> RayResult<C> {
        let mut r = RayResult::vacuum();
        if let (Some(sun), true) = (lights.suns.first(), ray.s_max.is_finite()) {
            r.sun_transmittance = self.sun_transmittance_at(ray.origin + ray.dir * ray.s_max, sun.to_sun);
        }
        if ray.s_max.is_nan() || ray.s_max <= 0.0 {
            return r;
        }
        let pieces = self.with_view_pieces(ray, |p| p.to_vec());
        // Optical depth at the start of each piece.
        let mut starts = Vec::with_capacity(pieces.len());
        let mut tau = [0.0; C];
        for p in &pieces {
            starts.push(tau);
            let side = self.side(p.below);
            let len = p.t1 - p.t0;
            for c in 0..C {
                let k = side.extinction[c];
                if k != 0.0 {
                    tau[c] += k * len;
                }
            }
        }
        r.transmittance = tau.map(|t| (-t).exp());
        // Ambient, closed form.
        for (p, t0) in pieces.iter().zip(&starts) {
            let side = self.side(p.below);
            let len = p.t1 - p.t0;
            for c in 0..C {
                let (s, k) = (side.scattering[c], side.extinction[c]);
                if s == 0.0 || lights.ambient[c] == 0.0 {
                    continue;
                }
                let v = s * lights.ambient[c] * (-t0[c]).exp() * integral_exp_neg(k, len);
                r.inscatter[c] += v;
                r.error[c] += rounding_bound(v, 16.0);
            }
        }
        // Sun, numerically per piece.
        for sun in &lights.suns {
            let work: Vec<usize> = (0..pieces.len())
                .filter(|i| self.side(pieces[*i].below).scattering.iter().any(|v| *v > 0.0))
                .collect();
            let integrand = |i: usize, s: f64| -> [f64; C] {
                let p = pieces[i];
                let side = self.side(p.below);
                let ts = self.sun_depth(ray.origin + ray.dir * s, sun.to_sun);
                let mut out = [0.0; C];
                for c in 0..C {
                    out[c] = (-(starts[i][c] + side.extinction[c] * (s - p.t0) + ts[c])).exp();
                }
                out
            };
            let run = |i: usize, abs_tol: f64, rel_tol: f64, panels: usize| {
                let p = pieces[i];
                if p.t1.is_finite() {
                    integrate_adaptive(|s| integrand(i, s), p.t0, p.t1, abs_tol, rel_tol, panels)
                } else {
                    let rate = self.side(p.below).extinction.iter().copied().fold(0.0f64, f64::max).max(1e-300);
                    let scale = 1.0 / rate;
                    integrate_adaptive(
                        |u| {
                            let s = p.t0 + scale * u / (1.0 - u);
                            let jac = scale / ((1.0 - u) * (1.0 - u));
                            if !s.is_finite() {
                                return [0.0; C];
                            }
                            integrand(i, s).map(|v| v * jac)
                        },
                        0.0,
                        1.0,
                        abs_tol,
                        rel_tol,
                        panels,
                    )
                }
            };
            let ph: Vec<f64> = work
                .iter()
                .map(|i| sun.phase(&self.side(pieces[*i].below).phase, ray.dir))
                .collect();
            // A coarse pass sizes the whole sum so that a negligible piece is not
            // refined to a relative accuracy of its own.
            let mut coarse = [0.0f64; C];
            for (j, &i) in work.iter().enumerate() {
                let q = run(i, f64::INFINITY, 0.0, 1);
                let side = self.side(pieces[i].below);
                for c in 0..C {
                    coarse[c] += side.scattering[c] * ph[j] * q.value[c].abs();
                }
            }
            let smallest = coarse.iter().copied().filter(|v| *v > 0.0).fold(f64::INFINITY, f64::min);
            for (j, &i) in work.iter().enumerate() {
                let side = self.side(pieces[i].below);
                let wmax = side.scattering.iter().fold(0.0f64, |m, v| m.max(*v)) * ph[j];
                let abs_tol = if smallest.is_finite() && wmax > 0.0 {
                    self.tolerance * smallest / (work.len() as f64 * wmax)
                } else {
                    1e-300
                };
                let q = run(i, abs_tol, self.tolerance, 400);
                for c in 0..C {
                    let w = side.scattering[c] * ph[j] * sun.irradiance[c];
                    if w != 0.0 {
                        r.inscatter[c] += w * q.value[c];
                        r.error[c] += w * q.error[c] + rounding_bound(w * q.value[c], 16.0);
                    }
                }
            }
        }
        r.rel_bound = (0..C)
            .filter(|c| r.inscatter[*c] > 0.0)
            .map(|c| r.error[c] / r.inscatter[c])
            .fold(0.0, f64::max);
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The dry-ice waves of the demo, the shortest `short_wavelength` m long.
    fn three_waves(short_wavelength: f64) -> HeightFieldLayer<1> {
        let side = Side {
            scattering: [1.0],
            extinction: [1.0],
            phase: PhaseFunction::Isotropic,
        };
        let waves = vec![
            Wave::new(0.1, 2.3, 15.0, 0.0),
            Wave::new(0.06, 1.1, 100.0, 40.0),
            Wave::new(0.03, short_wavelength, -50.0, 120.0),
        ];
        HeightFieldLayer::new("t".into(), 0.35, waves, side.clone(), side, 1e-3)
    }

    /// The `k`-th test path's search: its direction turns by 0.7 rad per
    /// `k`, rising by `dz` per unit of horizontal length.
    fn search_along(layer: &HeightFieldLayer<1>, k: usize, dz: f64) -> Search<'_, 1> {
        let d = DVec3::new((k as f64 * 0.7).cos(), (k as f64 * 0.7).sin(), dz).normalize();
        let mut omega = [0.0; FAST_WAVES];
        for (slot, w) in omega.iter_mut().zip(&layer.waves) {
            *slot = w.kx * d.x + w.ky * d.y;
        }
        Search {
            layer,
            o: DVec3::new(-3.0 + 0.1 * k as f64, 1.0, 0.4),
            d,
            evals: 0,
            omega,
        }
    }

    #[test]
    fn midpoint_phases_stay_within_the_slack_over_a_deep_search() {
        // Halving towards a point 60 times, the phases from the ends' stay
        // within 1e-13 of direct sines and cosines (the slack the tests of
        // `isolate` carry on `f`, per unit amplitude; measured 8.4e-14, most
        // of it the direct ones' own rounding of phases up to 750 rad).
        let layer = three_waves(0.05);
        let mut worst = 0.0f64;
        for k in 0..50 {
            let s = search_along(&layer, k, 0.05);
            let target = 0.37 * k as f64 / 50.0 + 0.123_456_789;
            let (mut a, mut b) = (0.0, 6.0);
            let (mut pa, mut pb) = (s.phases_at(a), s.phases_at(b));
            for _ in 0..60 {
                let m = 0.5 * (a + b);
                if m <= a || m >= b {
                    break;
                }
                let pm = s.phases_between(&pa, &pb, b - a, m, None);
                let direct = s.phases_at(m);
                for w in 0..3 {
                    worst = worst.max((pm[w].0 - direct[w].0).abs()).max((pm[w].1 - direct[w].1).abs());
                }
                if target < m {
                    (b, pb) = (m, pm);
                } else {
                    (a, pa) = (m, pm);
                }
            }
        }
        assert!(worst < 1e-13, "{worst:e}");
    }

    #[test]
    fn rotated_midpoint_phases_stay_within_the_drift_slack() {
        // The search as `slab_pieces` runs it on long light paths: chunks
        // `256/ω_max` long starting up to 200 m along the path (a wave
        // 0.55 m long), each halved 60 times towards points across the
        // whole chunk, turning the phases at the first depths and bisecting
        // them below, as `isolate` does. Against direct sines and cosines at
        // the point `f` is evaluated at, per radian per metre of `ω`, the
        // phases must stay within the drift `isolate` carries as slack (plus
        // the bisector's 1e-13).
        let layer = three_waves(0.55);
        let (mut worst, mut rotated) = (0.0f64, 0usize);
        for k in 0..120 {
            let s = search_along(&layer, k, 0.01);
            let omega = s.omega;
            let omega_max = omega.iter().fold(0.0f64, |m, w| m.max(w.abs()));
            let start = [0.0, 3.7, 41.3, 187.9][k % 4];
            let (mut a, mut b) = (start, start + 256.0 / omega_max);
            let drift = (0.5 * SEARCH_DEPTHS + 2.0) * EPS * a.abs().max(b.abs());
            let target = a + (b - a) * ((k / 4) as f64 + 0.123_456_789) / 30.0;
            let half_width = 0.5 * (b - a);
            let (mut pa, mut pb) = (s.phases_at(a), s.phases_at(b));
            for depth in 0..60 {
                let turns = omega_max * (b - a) > std::f64::consts::FRAC_PI_2 && (depth as usize) < ROTATED_DEPTHS;
                let (m, rotation) = if turns {
                    let depth_r = half_width / (1u64 << depth) as f64;
                    let mut rot = [(0.0, 1.0); FAST_WAVES];
                    for (slot, om) in rot.iter_mut().zip(omega) {
                        *slot = sin_cos(om * depth_r);
                    }
                    rotated += 1;
                    (a + depth_r, Some(rot))
                } else {
                    (0.5 * (a + b), None)
                };
                if m <= a || m >= b {
                    break;
                }
                let pm = s.phases_between(&pa, &pb, b - a, m, rotation.as_ref());
                let direct = s.phases_at(m);
                for w in 0..3 {
                    let diff = (pm[w].0 - direct[w].0).abs().max((pm[w].1 - direct[w].1).abs());
                    worst = worst.max(diff / (1e-13 + omega[w].abs() * drift));
                }
                if target < m {
                    (b, pb) = (m, pm);
                } else {
                    (a, pa) = (m, pm);
                }
            }
        }
        assert!(rotated > 120 * 6, "{rotated} rotated depths");
        assert!(worst <= 1.0, "phase error {worst:.3}× the slack");
        eprintln!("rotated depths: {rotated}, worst phase error {worst:.3}× the slack");
    }
}
