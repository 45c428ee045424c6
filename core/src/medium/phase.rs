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

impl PhaseFunction {
    /// Phase function value in sr⁻¹ for `mu = cos α ∈ [−1, 1]` (clamped).
    #[inline]
    pub fn eval(&self, mu: f64) -> f64 {
        let mu = mu.clamp(-1.0, 1.0);
        match *self {
            PhaseFunction::Isotropic => INV_4PI,
            PhaseFunction::Rayleigh => 3.0 / (16.0 * PI) * (1.0 + mu * mu),
            PhaseFunction::HenyeyGreenstein { g } => {
                let d = 1.0 + g * g - 2.0 * g * mu;
                INV_4PI * (1.0 - g * g) / (d * d.sqrt())
            }
            PhaseFunction::CornetteShanks { g } => {
                let d = 1.0 + g * g - 2.0 * g * mu;
                3.0 / (8.0 * PI) * (1.0 - g * g) / (2.0 + g * g) * (1.0 + mu * mu) / (d * d.sqrt())
            }
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

    /// Phase function averaged over a uniform disc (spherical cap) of angular
    /// radius `radius_rad` centred `theta` radians from the view direction:
    /// what a sun of finite size really contributes, sr⁻¹.
    ///
    /// `p̄(θ) = ∫∫ p(cos α) sin r dr dψ / (2π(1 − cos δ))`, with
    /// `cos α = cos θ cos r + sin θ sin r cos ψ` (spherical law of cosines),
    /// integrated adaptively to 1e-10 relative.
    pub fn disc_average(&self, theta: f64, radius_rad: f64) -> f64 {
        if radius_rad <= 0.0 {
            return self.eval(theta.cos());
        }
        let (st, ct) = theta.sin_cos();
        // Cap solid angle 2π(1 − cos δ), written with sin² so small δ keeps its digits.
        let cap = 4.0 * PI * (0.5 * radius_rad).sin().powi(2);
        let outer = crate::numeric::integrate_adaptive(
            |r: f64| {
                let (sr, cr) = r.sin_cos();
                let inner =
                    crate::numeric::integrate_adaptive(|psi: f64| [self.eval(ct * cr + st * sr * psi.cos())], 0.0, PI, 0.0, 1e-11, 200);
                [2.0 * inner.value[0] * sr]
            },
            0.0,
            radius_rad,
            0.0,
            1e-10,
            200,
        );
        outer.value[0] / cap
    }

    /// Largest relative error, over all scattering angles, of treating a sun
    /// of angular diameter `diameter_rad` as a single direction:
    /// `max_θ |p̄(θ) − p(θ)| / p(θ)` with [`PhaseFunction::disc_average`],
    /// evaluated at angles clustered towards the forward peak where the
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
            let rel = (self.disc_average(theta, delta) - p).abs() / p;
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
/// sun's centre) on a uniform grid: `u ≈ θ/√2` near the sun, so the grid is
/// uniform in angle where the disc matters, and a lookup costs one square
/// root and one linear interpolation. Used instead of the point evaluation
/// when treating the sun as a point would exceed the tolerance.
///
/// The grid is doubled (from 256 nodes up to 2¹⁸) until linear interpolation
/// matches [`PhaseFunction::disc_average`] at every cell midpoint to
/// `rel_tol`, so the table's own error is bounded by `rel_tol`.
#[derive(Debug, Clone, PartialEq)]
pub struct DiscPhase {
    /// The phase function.
    pub phase: PhaseFunction,
    /// Angular radius of the disc, rad.
    pub radius: f64,
    values: Vec<f64>,
    scale: f64,
}

const U_MAX: f64 = std::f64::consts::SQRT_2;

impl DiscPhase {
    /// Tabulates `phase` averaged over a disc of angular radius `radius` (rad).
    pub fn build(phase: PhaseFunction, radius: f64, rel_tol: f64) -> DiscPhase {
        let f = |u: f64| {
            let mu = 1.0 - u * u;
            phase.disc_average(mu.clamp(-1.0, 1.0).acos(), radius)
        };
        let mut n = 256usize;
        let mut values: Vec<f64> = (0..=n).map(|i| f(U_MAX * i as f64 / n as f64)).collect();
        loop {
            let h = U_MAX / n as f64;
            let mids: Vec<f64> = (0..n).map(|i| f((i as f64 + 0.5) * h)).collect();
            let ok = mids
                .iter()
                .enumerate()
                .all(|(i, m)| (0.5 * (values[i] + values[i + 1]) - m).abs() <= rel_tol * m.abs());
            // Interleave: the midpoints are the new nodes of the doubled grid.
            let mut finer = Vec::with_capacity(2 * n + 1);
            for i in 0..n {
                finer.push(values[i]);
                finer.push(mids[i]);
            }
            finer.push(values[n]);
            values = finer;
            n *= 2;
            if ok || n >= 1 << 18 {
                break;
            }
        }
        DiscPhase {
            phase,
            radius,
            scale: n as f64 / U_MAX,
            values,
        }
    }

    /// Disc-averaged phase value, sr⁻¹, for `mu = cos θ` (view direction · direction to the sun's centre).
    #[inline]
    pub fn eval(&self, mu: f64) -> f64 {
        let x = (1.0 - mu.clamp(-1.0, 1.0)).sqrt() * self.scale;
        let i = (x as usize).min(self.values.len() - 2);
        let t = x - i as f64;
        self.values[i] + t * (self.values[i + 1] - self.values[i])
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
        assert!(t.len() <= (1 << 16) + 1, "{} nodes", t.len());
    }

    #[test]
    fn invalid_g_is_rejected() {
        assert!(PhaseFunction::HenyeyGreenstein { g: 1.0 }.validate().is_err());
        assert!(PhaseFunction::CornetteShanks { g: f64::NAN }.validate().is_err());
        assert!(PhaseFunction::HenyeyGreenstein { g: 0.5 }.validate().is_ok());
    }
}
