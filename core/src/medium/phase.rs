//! Phase functions, each normalised to 1 over the sphere.
//!
//! Convention: `mu = cos α`, where α is the angle between the direction the
//! light travels before scattering and the direction it travels after, so
//! `mu = 1` is forward scattering (looking into the light), `mu = −1` back
//! scattering. With `view_dir` the direction from the eye along the view ray
//! and `to_light` the unit vector from the scattering point to the light,
//! `mu = dot(view_dir, to_light)`.
//!
//! | name | p(μ) | source |
//! |---|---|---|
//! | isotropic | 1/(4π) | |
//! | Rayleigh | 3/(16π)·(1+μ²) | Nishita et al. 1987 eq 4, K = 3/(16π) |
//! | Henyey–Greenstein | (1−g²) / (4π (1+g²−2gμ)^{3/2}) | the form Cycles' Volume Scatter uses |
//! | Cornette–Shanks | 3/(8π)·(1−g²)/(2+g²)·(1+μ²)/(1+g²−2gμ)^{3/2} | Cornette & Shanks 1992 |
//! | Nishita hazy | K(1+9cos¹⁶(α/2)), K = 1/(8π) | Nishita et al. 1987 eq 4 |
//! | Nishita murky | K(1+50cos⁶⁴(α/2)), K = 33/(332π) | Nishita et al. 1987 eq 4 |
//!
//! Derivation of K for the Nishita lobes. With u = cos(α/2), cos α = 2u² − 1,
//! so d(cos α) = 4u du and
//! ∫ cos^{2n}(α/2) dΩ = 2π ∫₀¹ u^{2n}·4u du = 4π/(n+1).
//! Hazy (2n = 16, n = 8): ∫(1 + 9cos¹⁶) dΩ = 4π + 9·4π/9 = 8π, K = 1/(8π).
//! Murky (2n = 64, n = 32): ∫(1 + 50cos⁶⁴) dΩ = 4π + 50·4π/33 = 332π/33,
//! K = 33/(332π). cos^{2n}(α/2) is evaluated as ((1+μ)/2)^n, which needs no
//! angle and stays exact at μ = ±1. The tests integrate each function
//! numerically over the sphere.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// A phase function. JSON: `{"type": "henyey_greenstein", "g": 0.6}` etc.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
#[derive(Default)]
pub enum PhaseFunction {
    /// 1/(4π).
    #[default]
    Isotropic,
    /// 3/(16π)(1+μ²): molecules.
    Rayleigh,
    /// Henyey–Greenstein with asymmetry `g` (dimensionless, −1 < g < 1; 0 is isotropic).
    HenyeyGreenstein {
        /// Mean cosine of the scattering angle, −1 < g < 1, no default.
        g: f64,
    },
    /// Cornette–Shanks: a Rayleigh-corrected Henyey–Greenstein for aerosols.
    CornetteShanks {
        /// Asymmetry parameter, −1 < g < 1 (≈ 0.76 for haze), no default.
        g: f64,
    },
    /// Nishita's hazy-atmosphere lobe, K(1+9cos¹⁶(α/2)).
    NishitaHazy,
    /// Nishita's murky-atmosphere lobe, K(1+50cos⁶⁴(α/2)).
    NishitaMurky,
}

const INV_4PI: f64 = 1.0 / (4.0 * PI);

/// Henyey–Greenstein from `d = 1 + g² − 2gμ`, which each caller forms to suit
/// its input (μ, or the angle for needle lobes). `1 − g²` as `(1 − g)(1 + g)`
/// is exact near |g| = 1.
#[inline]
fn henyey_greenstein(g: f64, d: f64) -> f64 {
    INV_4PI * ((1.0 - g) * (1.0 + g)) / (d * d.sqrt())
}

/// Cornette–Shanks from `d = 1 + g² − 2gμ` and μ (see [`henyey_greenstein`]).
#[inline]
fn cornette_shanks(g: f64, d: f64, mu: f64) -> f64 {
    3.0 / (8.0 * PI) * ((1.0 - g) * (1.0 + g)) / (2.0 + g * g) * (1.0 + mu * mu) / (d * d.sqrt())
}

impl PhaseFunction {
    /// Phase function value in sr⁻¹ for `mu = cos α ∈ [−1, 1]` (clamped).
    #[inline]
    pub fn eval(&self, mu: f64) -> f64 {
        let mu = mu.clamp(-1.0, 1.0);
        match *self {
            PhaseFunction::Isotropic => INV_4PI,
            PhaseFunction::Rayleigh => 3.0 / (16.0 * PI) * (1.0 + mu * mu),
            PhaseFunction::HenyeyGreenstein { g } => henyey_greenstein(g, 1.0 + g * g - 2.0 * g * mu),
            PhaseFunction::CornetteShanks { g } => cornette_shanks(g, 1.0 + g * g - 2.0 * g * mu, mu),
            PhaseFunction::NishitaHazy => {
                let c = 0.5 * (1.0 + mu);
                (1.0 + 9.0 * c.powi(8)) / (8.0 * PI)
            }
            PhaseFunction::NishitaMurky => {
                let c = 0.5 * (1.0 + mu);
                33.0 / (332.0 * PI) * (1.0 + 50.0 * c.powi(32))
            }
        }
    }

    /// Checks the parameters; `Err` names the offending one.
    pub fn validate(&self) -> Result<(), String> {
        match *self {
            PhaseFunction::HenyeyGreenstein { g } | PhaseFunction::CornetteShanks { g } => {
                if !g.is_finite() || g <= -1.0 || g >= 1.0 {
                    return Err(format!("g must be finite and in (-1, 1), got {g}"));
                }
                Ok(())
            }
            _ => Ok(()),
        }
    }

    /// Phase function value in sr⁻¹ at scattering angle `alpha` (rad, 0 = forward).
    /// Uses `1 − μ = 2 sin²(α/2)` (and `1 + μ = 2 cos²(α/2)`), so a lobe far
    /// narrower than √ε ≈ 1.5e-8 rad (HG with |g| → 1) keeps its digits near
    /// its peak, where `eval(cos α)` would round `1 + g² − 2gμ` away.
    #[inline]
    pub fn eval_at_angle(&self, alpha: f64) -> f64 {
        let s = (0.5 * alpha).sin();
        let one_minus_mu = (2.0 * s * s).clamp(0.0, 2.0);
        let mu = 1.0 - one_minus_mu;
        // 1 + g² − 2gμ as a sum of two non-negative terms: (1 − g)² + 2g(1 − μ)
        // for g ≥ 0 (forward lobe), (1 + g)² + 2|g|(1 + μ) for g < 0 (backward
        // lobe, 1 + μ = 2cos²(α/2)), so neither cancels at its peak.
        let d = |g: f64| {
            if g >= 0.0 {
                (1.0 - g) * (1.0 - g) + 2.0 * g * one_minus_mu
            } else {
                let c = (0.5 * alpha).cos();
                (1.0 + g) * (1.0 + g) - 4.0 * g * c * c
            }
        };
        match *self {
            PhaseFunction::HenyeyGreenstein { g } => henyey_greenstein(g, d(g)),
            PhaseFunction::CornetteShanks { g } => cornette_shanks(g, d(g), mu),
            _ => self.eval(mu),
        }
    }

    /// Phase function averaged over a uniform disc (spherical cap) of angular
    /// radius `radius_rad` (rad, 0 < δ ≤ π/2; 0 gives the point value) centred
    /// `theta` radians (0 … π) from the view direction: what a sun of finite
    /// size really contributes, sr⁻¹.
    ///
    /// `p̄(θ) = ∫_cap p dΩ / (2π(1 − cos δ))`. The phase function depends only
    /// on the angle α from the view direction, so the cap is swept in circles
    /// of radius α about the view direction, not about the disc centre:
    /// `∫_cap p dΩ = ∫ p(α) · w(α) · sin α dα`, where `w(α)` is the azimuth
    /// range of the circle that lies in the cap. From the spherical law of
    /// cosines in haversine form, `hav d = hav(θ − α) + sin θ sin α hav ψ`,
    /// a point at azimuth ψ is inside when
    /// `hav ψ ≤ H(α) = sin((δ − θ + α)/2) sin((δ + θ − α)/2) / (sin θ sin α)`
    /// (the numerator is `hav δ − hav(θ − α)` without the cancellation), so
    /// `w = 4 asin √H` for 0 < H < 1 and 2π for circles wholly inside.
    /// One 1-D integral per θ, whatever the lobe: a Henyey–Greenstein lobe of
    /// width 1 − g ≪ δ is a peak at one end of the α range, which the adaptive
    /// rule refines towards, where the former 2-D integral about the disc
    /// centre had to find it in the interior (0.8–1 s per call at g = 0.9999).
    /// The partial range `|θ − δ| … θ + δ` is mapped by `α = m − h cos t`,
    /// which removes the square-root ends of `w`. Integrated to 1e-12 relative
    /// ([`PhaseFunction::disc_average_with_error`] returns the quadrature's own estimate).
    pub fn disc_average(&self, theta: f64, radius_rad: f64) -> f64 {
        self.disc_average_with_error(theta, radius_rad).0
    }

    /// [`PhaseFunction::disc_average`] and the absolute error estimate of its
    /// quadrature, sr⁻¹ (below 1e-12 of the value unless the 2 000-panel
    /// budget ran out: then it says by how much the value may be off).
    pub fn disc_average_with_error(&self, theta: f64, radius_rad: f64) -> (f64, f64) {
        if radius_rad <= 0.0 {
            return (self.eval(theta.cos()), 0.0);
        }
        let theta = theta.clamp(0.0, PI);
        let delta = radius_rad.min(0.5 * PI);
        // Cap solid angle 2π(1 − cos δ), written with sin² so small δ keeps its digits.
        let cap = 4.0 * PI * (0.5 * delta).sin().powi(2);
        let full_circles = |a: f64, b: f64| -> (f64, f64) {
            if b <= a {
                return (0.0, 0.0);
            }
            let r = crate::numeric::integrate_adaptive(
                |alpha: f64| [2.0 * PI * self.eval_at_angle(alpha) * alpha.sin()],
                a,
                b,
                0.0,
                1e-12,
                2000,
            );
            (r.value[0], r.error[0])
        };
        let sin_theta = theta.sin();
        // Circles about the view direction wholly inside the cap: around α = 0
        // when the view direction is in the disc, around α = π when its opposite is.
        let (near, far) = (full_circles(0.0, delta - theta), full_circles(2.0 * PI - theta - delta, PI));
        let (mut total, mut error) = (near.0 + far.0, near.1 + far.1);
        // The partial range in the offset x = α − θ, whose ends are formed
        // without subtracting θ: |θ − δ| − θ and min(θ + δ, 2π − θ − δ) − θ.
        // `δ ± x` then keep their digits when θ ≫ δ (a 1e-4° sun at θ = 1 lost
        // 10 of them to α − θ, and the quadrature chased the noise).
        let x_lo = if theta >= delta { -delta } else { delta - 2.0 * theta };
        let x_hi = delta.min(2.0 * (PI - theta) - delta);
        if x_hi > x_lo && sin_theta > 0.0 {
            let (c, h) = (0.5 * (x_lo + x_hi), 0.5 * (x_hi - x_lo));
            let partial = crate::numeric::integrate_adaptive(
                |t: f64| {
                    let (st, ct) = t.sin_cos();
                    let x = (c - h * ct).clamp(x_lo, x_hi);
                    let alpha = theta + x;
                    let sin_alpha = alpha.sin();
                    if sin_alpha <= 0.0 {
                        return [0.0];
                    }
                    let num = (0.5 * (delta + x)).sin() * (0.5 * (delta - x)).sin();
                    let hav_psi = (num / (sin_theta * sin_alpha)).clamp(0.0, 1.0);
                    let w = 4.0 * hav_psi.sqrt().asin();
                    [self.eval_at_angle(alpha) * w * sin_alpha * h * st]
                },
                0.0,
                PI,
                0.0,
                1e-12,
                2000,
            );
            total += partial.value[0];
            error += partial.error[0];
        }
        (total / cap, error / cap)
    }

    /// Largest relative error, over all scattering angles, of treating a sun
    /// of angular diameter `diameter_rad` as a single direction:
    /// `max_θ |p̄(θ) − p(θ)| / p(θ)` with [`PhaseFunction::disc_average`]
    /// (plus its quadrature's error estimate), evaluated at angles clustered towards the forward peak where the
    /// blur is largest. Returns `(relative error, angle in radians where it is largest)`.
    pub fn point_sun_error(&self, diameter_rad: f64) -> (f64, f64) {
        let delta = 0.5 * diameter_rad;
        if delta <= 0.0 {
            return (0.0, 0.0);
        }
        let mut worst = (0.0, 0.0);
        let mut thetas: Vec<f64> = (0..=40).map(|i| delta * 0.25 * 1.2f64.powi(i)).filter(|t| *t < PI).collect();
        thetas.push(0.0);
        thetas.extend((1..=36).map(|i| PI * i as f64 / 36.0));
        for theta in thetas {
            let p = self.eval(theta.cos());
            // The quadrature's own error is added: the effect may be that much larger.
            let (average, error) = self.disc_average_with_error(theta, delta);
            let rel = ((average - p).abs() + error) / p;
            if rel > worst.0 {
                worst = (rel, theta);
            }
        }
        worst
    }

    /// A short human-readable name for reports.
    pub fn describe(&self) -> String {
        match *self {
            PhaseFunction::Isotropic => "isotropic".into(),
            PhaseFunction::Rayleigh => "Rayleigh".into(),
            PhaseFunction::HenyeyGreenstein { g } => format!("Henyey-Greenstein g={g}"),
            PhaseFunction::CornetteShanks { g } => format!("Cornette-Shanks g={g}"),
            PhaseFunction::NishitaHazy => "Nishita hazy".into(),
            PhaseFunction::NishitaMurky => "Nishita murky".into(),
        }
    }
}

/// A phase function averaged over a sun disc, tabulated against
/// `u = √(1 − μ)` (μ = cos θ, θ the angle between the view direction and the
/// sun's centre): `u ≈ θ/√2` near the sun, so the table is fine in angle where
/// the disc matters. Used instead of the point evaluation when treating the
/// sun as a point would exceed the tolerance.
///
/// The nodes are placed adaptively: starting from 256 uniform cells plus the
/// disc's rim, cells are halved, the worst first, until linear interpolation
/// matches [`PhaseFunction::disc_average`] at each midpoint to `rel_tol`. A lobe much
/// narrower than the disc (HG g = 0.9999: width 1e-4 rad against a 4.6e-3 rad
/// radius) turns the average into a plateau with a steep rim; the nodes crowd
/// there instead of refining the whole range (a uniform grid would need about
/// 10⁶ nodes). Cells are not split below [`DiscPhase::MIN_CELL`] in u nor past
/// [`DiscPhase::MAX_NODES`]; where that stops a cell short of `rel_tol`, twice
/// its midpoint mismatch (`UNMET_FACTOR`) is kept in
/// [`DiscPhase::table_error`], which the render reports.
/// A lookup is one square root, a bucket index and a short binary search.
#[derive(Debug, Clone, PartialEq)]
pub struct DiscPhase {
    /// The phase function.
    pub phase: PhaseFunction,
    /// Angular radius of the disc, rad.
    pub radius: f64,
    /// Node positions in u, increasing from 0 to √2.
    nodes: Vec<f64>,
    values: Vec<f64>,
    /// `bucket_start[b]`: the last node at or before `b / bucket_scale`.
    bucket_start: Vec<u32>,
    bucket_scale: f64,
    table_error: f64,
}

const U_MAX: f64 = std::f64::consts::SQRT_2;

/// A cell left unrefined short of the tolerance (node budget, width floor)
/// is charged this many times its midpoint mismatch: the mismatch estimates,
/// it does not bound, and filling the worst cells first leaves many near the
/// limit (HG g = 0.9999 asked for 2.5e-9: 1.15e-8 mismatch, 1.58e-8 found by
/// dense sampling beside the rim). Cells that meet the tolerance were within
/// 0.3× of it in the same sampling.
const UNMET_FACTOR: f64 = 2.0;

/// A table cell that failed its midpoint test, ordered by its mismatch.
struct PendingCell {
    mismatch: f64,
    /// Its ends and midpoint: (u, average).
    ends: [(f64, f64); 3],
}

impl PartialEq for PendingCell {
    fn eq(&self, other: &Self) -> bool {
        self.mismatch.total_cmp(&other.mismatch).is_eq()
    }
}
impl Eq for PendingCell {}
impl PartialOrd for PendingCell {
    fn partial_cmp(&self, other: &Self) -> Option<std::cmp::Ordering> {
        Some(self.cmp(other))
    }
}
impl Ord for PendingCell {
    fn cmp(&self, other: &Self) -> std::cmp::Ordering {
        self.mismatch.total_cmp(&other.mismatch)
    }
}

impl DiscPhase {
    /// Narrowest cell in u (≈ 1.4e-9 rad in angle near the sun).
    pub const MIN_CELL: f64 = 1e-9;
    /// Node budget: past it every remaining cell is accepted as it is and twice
    /// the largest mismatch among them goes into [`DiscPhase::table_error`].
    pub const MAX_NODES: usize = 1 << 18;
    /// Finest relative tolerance a table is built to (a tighter request gets
    /// this, and [`DiscPhase::table_error`] says so).
    pub const FINEST_TOLERANCE: f64 = 1e-10;

    /// Tabulates `phase` averaged over a disc of angular radius `radius` (rad)
    /// to `rel_tol` relative (see [`DiscPhase::table_error`] for what was achieved).
    pub fn build(phase: PhaseFunction, radius: f64, rel_tol: f64) -> DiscPhase {
        Self::build_unless(phase, radius, rel_tol, &|| false).expect("never stopped")
    }

    /// [`DiscPhase::build`] that gives up, returning `None`, once `stop()` is
    /// true (asked every 64 averages, ≈ 1 ms; a table at its node budget takes seconds).
    pub fn build_unless(phase: PhaseFunction, radius: f64, rel_tol: f64, stop: &dyn Fn() -> bool) -> Option<DiscPhase> {
        // The averages are good to ≈ 1e-12; a finer target would only chase
        // their noise up to the node budget.
        let rel_tol = rel_tol.max(Self::FINEST_TOLERANCE);
        // The largest relative error of the averages themselves (their
        // quadrature's estimate): the table can be no better than its nodes.
        let node_error = std::cell::Cell::new(0.0f64);
        let calls = std::cell::Cell::new(0u32);
        let stopped = std::cell::Cell::new(false);
        // θ = 2 asin(u/√2) keeps the digits of small angles that acos(1 − u²) loses.
        let f = |u: f64| -> f64 {
            calls.set(calls.get().wrapping_add(1));
            if !stopped.get() && calls.get().is_multiple_of(64) && stop() {
                stopped.set(true);
            }
            if stopped.get() {
                return 0.0;
            }
            let (v, e) = phase.disc_average_with_error(2.0 * (u / U_MAX).clamp(0.0, 1.0).asin(), radius);
            let rel = e / v.abs().max(f64::MIN_POSITIVE);
            node_error.set(node_error.get().max(if rel.is_nan() { f64::INFINITY } else { rel }));
            v
        };
        let rim = U_MAX * (0.5 * radius.clamp(0.0, 0.5 * PI)).sin();
        let mut starts: Vec<f64> = (0..=256).map(|i| U_MAX * i as f64 / 256.0).collect();
        starts.push(rim);
        starts.sort_by(f64::total_cmp);
        starts.dedup();
        // Every evaluated point is a node: (u, average).
        let mut points: Vec<(f64, f64)> = starts.iter().map(|&u| (u, f(u))).collect();
        let mut table_error = 0.0f64;
        // A cell is tested at its midpoint against linear interpolation; the
        // cells that fail wait in a max-heap by mismatch and the worst is
        // halved first, so a node budget that runs out leaves the error spread
        // evenly (refining depth-first, left to right, spent the budget on the
        // first cells: HG g = 0.9999 asked for 2.5e-9 ended at 7.9e-2).
        type Heap = std::collections::BinaryHeap<PendingCell>;
        let mut pending = Heap::new();
        let test = |ua: f64, fa: f64, ub: f64, fb: f64, points: &mut Vec<(f64, f64)>, table_error: &mut f64, pending: &mut Heap| {
            let um = 0.5 * (ua + ub);
            let fm = f(um);
            points.push((um, fm));
            let mismatch = (0.5 * (fa + fb) - fm).abs() / fm.abs().max(f64::MIN_POSITIVE);
            // A NaN mismatch is a failure, and is counted as one (∞).
            let mismatch = if mismatch.is_nan() { f64::INFINITY } else { mismatch };
            if mismatch <= rel_tol {
                return;
            }
            if ub - ua <= Self::MIN_CELL {
                *table_error = table_error.max(UNMET_FACTOR * mismatch);
            } else {
                pending.push(PendingCell {
                    mismatch,
                    ends: [(ua, fa), (um, fm), (ub, fb)],
                });
            }
        };
        for w in points.clone().windows(2) {
            test(w[0].0, w[0].1, w[1].0, w[1].1, &mut points, &mut table_error, &mut pending);
        }
        while let Some(cell) = pending.pop() {
            if stopped.get() {
                return None;
            }
            if points.len() + 2 > Self::MAX_NODES {
                // Out of budget: this cell and every one still waiting (none
                // worse) stay as they are.
                table_error = table_error.max(UNMET_FACTOR * cell.mismatch);
                break;
            }
            let [(ua, fa), (um, fm), (ub, fb)] = cell.ends;
            test(ua, fa, um, fm, &mut points, &mut table_error, &mut pending);
            test(um, fm, ub, fb, &mut points, &mut table_error, &mut pending);
        }
        if stopped.get() {
            return None;
        }
        points.sort_by(|a, b| a.0.total_cmp(&b.0));
        points.dedup_by(|a, b| a.0 == b.0);
        let (nodes, values): (Vec<f64>, Vec<f64>) = points.into_iter().unzip();
        let buckets = nodes.len().next_power_of_two();
        let bucket_scale = buckets as f64 / U_MAX;
        let bucket_start = (0..=buckets)
            .map(|b| {
                let u = b as f64 / bucket_scale;
                (nodes.partition_point(|x| *x <= u).max(1) - 1).min(nodes.len() - 2) as u32
            })
            .collect();
        Some(DiscPhase {
            phase,
            radius,
            nodes,
            values,
            bucket_start,
            bucket_scale,
            table_error: table_error.max(rel_tol) + node_error.get(),
        })
    }

    /// Disc-averaged phase value, sr⁻¹, for `mu = cos θ` (view direction · direction to the sun's centre).
    #[inline]
    pub fn eval(&self, mu: f64) -> f64 {
        let u = (1.0 - mu.clamp(-1.0, 1.0)).sqrt();
        let b = ((u * self.bucket_scale) as usize).min(self.bucket_start.len() - 2);
        let (lo, hi) = (self.bucket_start[b] as usize, self.bucket_start[b + 1] as usize);
        // The cell [nodes[i], nodes[i+1]] holding u lies between the two bucket starts.
        let i = lo + self.nodes[lo..=hi].partition_point(|x| *x <= u).max(1) - 1;
        let i = i.min(self.nodes.len() - 2);
        let (u0, u1) = (self.nodes[i], self.nodes[i + 1]);
        let t = ((u - u0) / (u1 - u0)).clamp(0.0, 1.0);
        self.values[i] + t * (self.values[i + 1] - self.values[i])
    }

    /// Relative accuracy the table reached: `rel_tol`, or more where a cell
    /// reached [`DiscPhase::MIN_CELL`] or the node budget before meeting it,
    /// plus the largest relative error estimate of the averages at its nodes.
    pub fn table_error(&self) -> f64 {
        self.table_error
    }

    /// Number of table nodes.
    pub fn len(&self) -> usize {
        self.values.len()
    }

    /// Whether the table is empty (never, after `build`).
    pub fn is_empty(&self) -> bool {
        self.values.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::numeric::integrate_adaptive;

    /// ∮ p dΩ = 2π ∫₋₁¹ p(μ) dμ, integrated with a tight adaptive rule.
    fn sphere_integral(p: PhaseFunction) -> f64 {
        // Split at μ = 1 − 1e-3 so the sharp forward lobes are resolved.
        let f = |mu: f64| [p.eval(mu)];
        let a = integrate_adaptive(f, -1.0, 0.999, 0.0, 1e-13, 4000);
        let b = integrate_adaptive(f, 0.999, 1.0, 0.0, 1e-13, 4000);
        2.0 * PI * (a.value[0] + b.value[0])
    }

    #[test]
    fn all_phase_functions_integrate_to_one() {
        let all = [
            PhaseFunction::Isotropic,
            PhaseFunction::Rayleigh,
            PhaseFunction::HenyeyGreenstein { g: 0.0 },
            PhaseFunction::HenyeyGreenstein { g: 0.7 },
            PhaseFunction::HenyeyGreenstein { g: -0.4 },
            PhaseFunction::HenyeyGreenstein { g: 0.99 },
            PhaseFunction::CornetteShanks { g: 0.76 },
            PhaseFunction::CornetteShanks { g: -0.3 },
            PhaseFunction::NishitaHazy,
            PhaseFunction::NishitaMurky,
        ];
        for p in all {
            let s = sphere_integral(p);
            assert!((s - 1.0).abs() < 1e-9, "{p:?} integrates to {s}");
        }
    }

    #[test]
    fn nishita_lobes_match_the_cosine_half_angle_form() {
        for i in 0..=100 {
            let alpha = PI * i as f64 / 100.0;
            let mu = alpha.cos();
            let hazy = (1.0 + 9.0 * (alpha / 2.0).cos().powi(16)) / (8.0 * PI);
            let murky = 33.0 / (332.0 * PI) * (1.0 + 50.0 * (alpha / 2.0).cos().powi(64));
            assert!((PhaseFunction::NishitaHazy.eval(mu) - hazy).abs() < 1e-12 * hazy.max(1.0));
            assert!((PhaseFunction::NishitaMurky.eval(mu) - murky).abs() < 1e-12 * murky.max(1.0));
        }
    }

    #[test]
    fn hg_mean_cosine_is_g() {
        let g = 0.63;
        let p = PhaseFunction::HenyeyGreenstein { g };
        let r = integrate_adaptive(|mu| [mu * p.eval(mu)], -1.0, 1.0, 0.0, 1e-13, 4000);
        assert!((2.0 * PI * r.value[0] - g).abs() < 1e-10);
    }

    #[test]
    fn point_sun_error_matches_the_second_order_estimate() {
        // For a smooth lobe the cap average is p + (δ²/8)·Δ_S p to second order;
        // at θ = 0, Δ_S p = 2 p''(0). For HG, p''(0)/p(0) = −3g/(1−g)².
        let g: f64 = 0.76;
        let p = PhaseFunction::HenyeyGreenstein { g };
        let d = 0.526f64.to_radians();
        let delta = d / 2.0;
        let second_order = (delta * delta / 8.0) * 2.0 * 3.0 * g / ((1.0 - g) * (1.0 - g));
        let at_zero = (p.disc_average(0.0, delta) - p.eval(1.0)).abs() / p.eval(1.0);
        assert!((at_zero - second_order).abs() < 0.02 * second_order, "{at_zero} vs {second_order}");
        let (worst, where_) = p.point_sun_error(d);
        assert!(worst >= at_zero * 0.999 && where_ < 0.05, "{worst} at {where_}");
        // Isotropic: no blur at all.
        assert!(PhaseFunction::Isotropic.point_sun_error(d).0 < 1e-9);
        // A very sharp lobe: the blur is large and the estimate says so.
        assert!(PhaseFunction::HenyeyGreenstein { g: 0.995 }.point_sun_error(d).0 > 0.05);
    }

    /// The former 2-D form: `∫₀^δ ∫₀^{2π} p(cos α) dψ sin r dr` about the
    /// disc centre, `cos α = cos θ cos r + sin θ sin r cos ψ`; independent of
    /// the circles-about-the-view-direction form it checks.
    fn disc_average_about_the_centre(p: PhaseFunction, theta: f64, delta: f64) -> f64 {
        let (st, ct) = theta.sin_cos();
        let cap = 4.0 * PI * (0.5 * delta).sin().powi(2);
        let outer = integrate_adaptive(
            |r: f64| {
                let (sr, cr) = r.sin_cos();
                let inner = integrate_adaptive(|psi: f64| [p.eval(ct * cr + st * sr * psi.cos())], 0.0, PI, 0.0, 1e-12, 400);
                [2.0 * inner.value[0] * sr]
            },
            0.0,
            delta,
            0.0,
            1e-11,
            400,
        );
        outer.value[0] / cap
    }

    #[test]
    fn disc_average_matches_the_integral_about_the_disc_centre() {
        let phases = [
            PhaseFunction::Isotropic,
            PhaseFunction::Rayleigh,
            PhaseFunction::HenyeyGreenstein { g: 0.76 },
            PhaseFunction::HenyeyGreenstein { g: 0.99 },
            PhaseFunction::HenyeyGreenstein { g: -0.9 },
            PhaseFunction::CornetteShanks { g: 0.76 },
            PhaseFunction::NishitaMurky,
        ];
        for delta in [0.5 * 0.526f64.to_radians(), 0.3, 1.2, 0.5 * PI] {
            for theta in [0.0, 0.1 * delta, 0.5 * delta, delta, 1.5 * delta, 1.0, 2.0, PI - 0.5 * delta, PI] {
                for p in phases {
                    let a = p.disc_average(theta, delta);
                    let b = disc_average_about_the_centre(p, theta, delta);
                    assert!((a - b).abs() <= 1e-9 * b, "{p:?} δ={delta} θ={theta}: {a} vs {b}");
                }
            }
        }
    }

    proptest::proptest! {
        #![proptest_config(proptest::prelude::ProptestConfig { cases: 64, ..Default::default() })]
        /// Random lobes, disc sizes and angles (wrapping past the anti-solar
        /// point included) against the 2-D integral about the disc centre.
        #[test]
        fn disc_average_matches_the_integral_about_the_centre_for_random_inputs(
            g in -0.99f64..0.99,
            cornette_shanks in proptest::bool::ANY,
            theta in 0.0f64..PI,
            log_delta in -7.0f64..0.196,
        ) {
            let delta = 10f64.powf(log_delta).min(0.5 * PI);
            let p = if cornette_shanks { PhaseFunction::CornetteShanks { g } } else { PhaseFunction::HenyeyGreenstein { g } };
            let a = p.disc_average(theta, delta);
            let b = disc_average_about_the_centre(p, theta, delta);
            proptest::prop_assert!((a - b).abs() <= 1e-9 * b, "{:?} δ={} θ={}: {} vs {}", p, delta, theta, a, b);
        }
    }

    /// A disc far smaller than the lobe changes it only at second order,
    /// (δ²/8)·Δp/p ≲ 1e-12 here, at every angle (far from the disc the
    /// partial range is a sliver 2δ wide around θ).
    #[test]
    fn disc_average_of_a_tiny_disc_is_the_point_value() {
        let delta = 0.5 * 1e-4f64.to_radians();
        for p in [
            PhaseFunction::HenyeyGreenstein { g: 0.9 },
            PhaseFunction::Rayleigh,
            PhaseFunction::NishitaMurky,
        ] {
            for theta in [0.0, delta, 1e-2, 1.0, 3.0, PI] {
                let (a, b) = (p.disc_average(theta, delta), p.eval(theta.cos()));
                assert!((a - b).abs() <= 1e-10 * b, "{p:?} θ={theta}: {a} vs {b}");
            }
        }
    }

    /// At θ = 0 the cap average of HG has a closed form:
    /// 2π∫_{cos δ}^1 p dμ = (1 − g²)/(2g) · (1/(1 − g) − 1/√(1 + g² − 2g cos δ)).
    #[test]
    fn disc_average_of_a_needle_lobe_matches_the_closed_form() {
        let delta = 0.5 * 0.526f64.to_radians();
        let cap = 4.0 * PI * (0.5 * delta).sin().powi(2);
        for g in [0.9, 0.999, 0.9999, 0.999999] {
            let p = PhaseFunction::HenyeyGreenstein { g };
            let d0 = (1.0 - g) * (1.0 - g) + 4.0 * g * (0.5 * delta).sin().powi(2);
            let exact = ((1.0 - g) * (1.0 + g)) / (2.0 * g) * (1.0 / (1.0 - g) - 1.0 / d0.sqrt()) / cap;
            let got = p.disc_average(0.0, delta);
            assert!((got - exact).abs() <= 1e-10 * exact, "g={g}: {got} vs {exact}");
            // A backward lobe averaged about the anti-solar point is the mirror image.
            let back = PhaseFunction::HenyeyGreenstein { g: -g }.disc_average(PI, delta);
            assert!((back - exact).abs() <= 1e-10 * exact, "g={}: {back} vs {exact}", -g);
        }
        // At its peak a needle lobe is (1 + |g|)/(4π(1 − |g|)²), however narrow.
        for g in [0.999999999, -0.999999999] {
            let p = PhaseFunction::HenyeyGreenstein { g };
            let peak = (1.0 + g.abs()) / (4.0 * PI * (1.0 - g.abs()).powi(2));
            let got = p.eval_at_angle(if g > 0.0 { 0.0 } else { PI });
            assert!((got - peak).abs() <= 1e-12 * peak, "g={g}: {got} vs {peak}");
        }
    }

    /// Averaging over a cap preserves the integral over the sphere:
    /// 2π∫₀^π p̄(θ) sin θ dθ = 1, however narrow the lobe.
    #[test]
    fn disc_average_of_a_needle_lobe_keeps_the_sphere_integral() {
        let delta = 0.5 * 0.526f64.to_radians();
        for g in [0.9999, -0.9999] {
            let p = PhaseFunction::HenyeyGreenstein { g };
            let f = |theta: f64| [2.0 * PI * p.disc_average(theta, delta) * theta.sin()];
            let mut total = 0.0;
            for (a, b) in [
                (0.0, delta),
                (delta, 2.0 * delta),
                (2.0 * delta, PI - 2.0 * delta),
                (PI - 2.0 * delta, PI - delta),
                (PI - delta, PI),
            ] {
                total += integrate_adaptive(f, a, b, 0.0, 1e-10, 400).value[0];
            }
            assert!((total - 1.0).abs() < 1e-8, "g={g}: {total}");
        }
    }

    #[test]
    fn disc_phase_table_of_a_needle_lobe_stays_small_and_within_tolerance() {
        let r = 0.5 * 0.526f64.to_radians();
        for g in [0.9999, -0.9999] {
            let p = PhaseFunction::HenyeyGreenstein { g };
            let tol = 2.5e-4;
            let t = DiscPhase::build(p, r, tol);
            // The tolerance plus the averages' own quadrature error (≈ 1e-11 relative).
            assert!(
                t.table_error() >= tol && t.table_error() < tol * (1.0 + 1e-6),
                "{}",
                t.table_error()
            );
            assert!(t.len() < 20_000, "g={g}: {} nodes", t.len());
            // Dense around the rim, where the plateau falls off, and across the sphere.
            let rim: Vec<f64> = (0..400).map(|i| r * (0.9 + 0.2 * i as f64 / 399.0)).collect();
            let spread: Vec<f64> = (0..400).map(|i| PI * (i as f64 / 399.0).powi(3)).collect();
            for theta in rim.into_iter().chain(spread) {
                let direct = p.disc_average(theta, r);
                let tab = t.eval(theta.cos());
                // The lookup's μ = cos θ carries ≈ 1e-16 absolute, i.e. a shift of
                // ≈ 1e-16/θ in angle; near θ = 0 the plateau is flat, so this is small.
                assert!((tab - direct).abs() <= 2.0 * tol * direct, "g={g} θ={theta}: {tab} vs {direct}");
            }
        }
    }

    #[test]
    fn a_disc_table_out_of_budget_spreads_its_error_and_says_so() {
        // Linear interpolation of HG g = 0.9999 to 2.5e-9 would need about 10⁶
        // nodes; the budget is 2¹⁸. The budget goes to the worst cells first,
        // so what is left is near what 2¹⁸ nodes can reach (2.3e-8 reported,
        // twice the largest mismatch; refining left to right it ended at 7.9e-2,
        // the last cells left coarse).
        let r = 0.5 * 0.526f64.to_radians();
        let p = PhaseFunction::HenyeyGreenstein { g: 0.9999 };
        let t = DiscPhase::build(p, r, 2.5e-9);
        assert!(t.len() <= DiscPhase::MAX_NODES, "{} nodes", t.len());
        assert!(t.table_error() > 2.5e-9 && t.table_error() < 1e-7, "{}", t.table_error());
        // And the reported error holds, across the sphere and densely at the rim.
        // (Without the factor 2 on cells left short, 1.15e-8 was reported and
        // 1.58e-8 found here, at θ = 0.9998 r.)
        let rim = (0..4000).map(|i| r * (0.98 + 0.04 * i as f64 / 3999.0));
        let spread = (0..1000).map(|i| PI * (i as f64 / 999.0).powi(3));
        for theta in rim.chain(spread) {
            let direct = p.disc_average(theta, r);
            let tab = t.eval(theta.cos());
            assert!((tab - direct).abs() <= t.table_error() * direct, "θ={theta}: {tab} vs {direct}");
        }
    }

    #[test]
    fn a_disc_table_stops_when_asked() {
        let r = 0.5 * 0.526f64.to_radians();
        let p = PhaseFunction::HenyeyGreenstein { g: 0.9999 };
        let asked = std::cell::Cell::new(0u32);
        let stop = || {
            asked.set(asked.get() + 1);
            asked.get() >= 20
        };
        // Asked every 64 averages: it gives up at the 20th question (average
        // 1 280), inside the worst-first refinement (the first 515 averages are
        // the initial cells), before the table's ≈ 1 900 nodes are done.
        assert!(DiscPhase::build_unless(p, r, 2.5e-4, &stop).is_none());
        assert_eq!(asked.get(), 20);
        assert_eq!(
            DiscPhase::build_unless(p, r, 2.5e-4, &|| false),
            Some(DiscPhase::build(p, r, 2.5e-4))
        );
    }

    #[test]
    fn disc_phase_table_matches_direct_averages() {
        let p = PhaseFunction::HenyeyGreenstein { g: 0.9 };
        let r = 0.5 * 0.526f64.to_radians();
        let tol = 1e-5;
        let t = DiscPhase::build(p, r, tol);
        for i in 0..200 {
            let theta = PI * (i as f64 / 199.0).powi(3);
            let direct = p.disc_average(theta, r);
            let tab = t.eval(theta.cos());
            assert!((tab - direct).abs() <= 2.0 * tol * direct, "θ={theta}: {tab} vs {direct}");
        }
        assert!(t.len() <= 5000, "{} nodes", t.len());
    }

    #[test]
    fn invalid_g_is_rejected() {
        assert!(PhaseFunction::HenyeyGreenstein { g: 1.0 }.validate().is_err());
        assert!(PhaseFunction::CornetteShanks { g: f64::NAN }.validate().is_err());
        assert!(PhaseFunction::HenyeyGreenstein { g: 0.5 }.validate().is_ok());
    }
}
