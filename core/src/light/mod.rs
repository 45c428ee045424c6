//! Stage lights: point sources with an angular intensity distribution
//! `I(θ, φ)` (Nishita, Miyawaki & Nakamae 1987, appendix eqs 7–10), Blender's
//! point and spot lamps as Cycles shades them, UsdLux shaping, tables and IES
//! LM-63 profiles ([`ies`]); and parallel light through a window ([`window`]).
//!
//! **Angles.** θ is measured from the illumination axis, the light's local −Z
//! (Blender and USD lights shine along −Z), φ around the axis from the local
//! +X towards +Y (Nishita Fig. 8's reference plane is the local XZ plane).
//!
//! **Units.** A point light's radiant intensity towards ω, W·sr⁻¹ per channel,
//! is `I(ω) = colour · P · K · D(ω) · F_IES(ω)`: P is Blender's Power (W),
//! `K = 1/(4π)` sr⁻¹ is Cycles' conversion of a point lamp's watts to
//! intensity (`docs/cycles-conventions.md`), `D` the relative distribution
//! (1 on the axis) and `F_IES` the IES node's factor (1 without a profile).
//!
//! **Illumination volume.** Every distribution knows the half-angle outside
//! which it is exactly zero: the light's bounding cone. View rays that miss it
//! evaluate no integral, occluders outside it cast nothing. Non-axisymmetric
//! tables and IES profiles also get an elliptical cone (the least-area
//! axis-aligned ellipse in the gnomonic plane holding every lit direction,
//! [`bounding_ellipse_of_sectors`]); a ray's lit part is inside both.
//!
//! **Tables.** Their interpolation changes cell at the θ and φ nodes (kinks
//! for linear tables, jumps of the second derivative for IES Catmull-Rom), so
//! the in-scatter integral cuts rays at those cones and planes
//! ([`PointSource::cell_cones`], [`PointSource::cell_planes`]): every window
//! of the quadrature then lies in one cell, where the interpolant is smooth.

pub mod ies;
pub mod shadow;
pub mod window;

use crate::scene::{IntensityDistribution, Orientation, PointLight, SpotLight};
use glam::{DQuat, DVec3};
use std::f64::consts::{FRAC_PI_2, PI};
use std::sync::Arc;

/// Cycles' point/spot lamp conversion, W·sr⁻¹ of intensity per W of Power.
pub const CYCLES_WATTS_TO_INTENSITY: f64 = 1.0 / (4.0 * PI);

/// `smoothstep(0, 1, x)` = `3x² − 2x³` on [0, 1], clamped (Cycles' `smoothstepf`).
#[inline]
pub fn smoothstep01(x: f64) -> f64 {
    if x <= 0.0 {
        0.0
    } else if x >= 1.0 {
        1.0
    } else {
        x * x * (3.0 - 2.0 * x)
    }
}

/// The relative distribution, resolved for fast evaluation.
#[derive(Debug, Clone)]
pub enum Shape {
    /// 1 everywhere.
    Isotropic,
    /// Cycles' spot mask, `smoothstep((cos θ − cos_half)/smooth)`, a step when `smooth = 0`.
    CyclesSpot {
        /// cos of half the spot size.
        cos_half: f64,
        /// `blend · (1 − cos_half)`.
        smooth: f64,
    },
    /// Nishita eq 7 with the daisy / polka-dot factors of eqs 8–10.
    Nishita {
        /// cos γ.
        cos_gamma: f64,
        /// Edge sharpness q.
        q: f64,
        /// Petal period Δφ, rad (0: no petals).
        period_phi: f64,
        /// Polka period Δθ, rad (0: no dots).
        period_theta: f64,
        /// Minimum ratio p of eq 8.
        p: f64,
    },
    /// UsdLux ShapingAPI: `|cos θ|^focus · (1 − smoothstep(θ; θ_c(1−s), θ_c))`.
    UsdShaping {
        /// Cut-off half-angle θ_c, rad.
        cutoff: f64,
        /// Softness s.
        softness: f64,
        /// Focus exponent.
        focus: f64,
    },
    /// Bilinear table over (θ, φ), φ periodic.
    Tabulated(Arc<Table>),
}

/// A table of relative intensities.
#[derive(Debug, Clone)]
pub struct Table {
    /// θ samples, rad, increasing.
    pub theta: Vec<f64>,
    /// φ samples, rad, increasing, spanning < 2π.
    pub phi: Vec<f64>,
    /// `values[i_phi][i_theta]`.
    pub values: Vec<Vec<f64>>,
}

/// Linear interpolation in an increasing table: (index, weight of index+1);
/// `None` outside `[xs[0], xs[last]]`.
fn bracket(xs: &[f64], x: f64) -> Option<(usize, f64)> {
    let n = xs.len();
    if n == 1 {
        return if (x - xs[0]).abs() <= 1e-12 { Some((0, 0.0)) } else { None };
    }
    if x < xs[0] || x > xs[n - 1] {
        return None;
    }
    let i = xs.partition_point(|v| *v <= x).clamp(1, n - 1) - 1;
    let w = (x - xs[i]) / (xs[i + 1] - xs[i]);
    Some((i, w.clamp(0.0, 1.0)))
}

impl Table {
    fn column(&self, row: usize, theta: f64) -> f64 {
        let r = &self.values[row];
        if self.theta.len() == 1 {
            return if theta <= self.theta[0] { r[0] } else { 0.0 };
        }
        if theta < self.theta[0] {
            return r[0];
        }
        match bracket(&self.theta, theta) {
            Some((i, w)) => r[i] * (1.0 - w) + r[i + 1] * w,
            None => 0.0,
        }
    }

    /// Relative intensity at (θ, φ), rad.
    pub fn eval(&self, theta: f64, phi: f64) -> f64 {
        let n = self.phi.len();
        if n == 1 {
            return self.column(0, theta);
        }
        let two_pi = 2.0 * PI;
        let p0 = self.phi[0];
        let x = (phi - p0).rem_euclid(two_pi) + p0;
        let last = self.phi[n - 1];
        if x <= last {
            let (i, w) = bracket(&self.phi, x).unwrap_or((0, 0.0));
            self.column(i, theta) * (1.0 - w) + self.column(i + 1, theta) * w
        } else {
            // Wrap-around cell between the last sample and the first + 2π.
            let w = (x - last) / (p0 + two_pi - last);
            self.column(n - 1, theta) * (1.0 - w) + self.column(0, theta) * w
        }
    }

    /// Largest θ with a possibly non-zero value in row `r`.
    fn row_reach(&self, r: usize) -> f64 {
        let n = self.theta.len();
        match (0..n).rev().find(|&j| self.values[r][j] > 0.0) {
            None => 0.0,
            Some(j) if j + 1 < n => self.theta[j + 1],
            Some(j) => self.theta[j],
        }
    }

    /// An axis-aligned ellipse in the gnomonic plane (`tan θ cos φ`,
    /// `tan θ sin φ`) holding every direction the table lights, when that is
    /// tighter than the circular cone (non-axisymmetric tables, reach < 80°):
    /// between two φ rows the lit reach is at most the larger of theirs, so
    /// the support is inside the union of circular sectors with those radii
    /// ([`bounding_ellipse_of_sectors`]).
    pub fn bounding_ellipse(&self) -> Option<(f64, f64)> {
        let n = self.phi.len();
        if n < 2 {
            return None;
        }
        let sectors: Vec<(f64, f64, f64)> = (0..n)
            .map(|i| {
                let (p0, p1) = (self.phi[i], if i + 1 < n { self.phi[i + 1] } else { self.phi[0] + 2.0 * PI });
                (p0, p1, self.row_reach(i).max(self.row_reach((i + 1) % n)))
            })
            .collect();
        bounding_ellipse_of_sectors(&sectors, self.reach())
    }

    /// Largest θ with a possibly non-zero value.
    pub fn reach(&self) -> f64 {
        let n = self.theta.len();
        let mut last_nonzero = None;
        for j in 0..n {
            if self.values.iter().any(|r| r[j] > 0.0) {
                last_nonzero = Some(j);
            }
        }
        match last_nonzero {
            None => 0.0,
            Some(j) if j + 1 < n => self.theta[j + 1],
            Some(j) => self.theta[j],
        }
    }
}

/// The angles in `[0, span]` where Nishita's `k(x)` (eq 8, period `period`,
/// minimum ratio `p`) or eq 10's parity is not smooth: the period boundaries
/// (peaks of `k`, parity jumps), the troughs, and for `p < 0` where the
/// clamp at 0 starts and ends, `period/2 ± period/2 · (−p)/(1 − p)`.
fn pattern_kinks(period: f64, p: f64, span: f64) -> Vec<f64> {
    let half = 0.5 * period;
    let mut offsets = vec![0.0, half];
    if p < 0.0 {
        let z = half * (-p) / (1.0 - p);
        offsets.extend([half - z, half + z]);
    }
    let periods = (span / period).ceil() as usize;
    let mut out = Vec::with_capacity(periods * offsets.len() + 1);
    for n in 0..periods {
        for o in &offsets {
            let x = n as f64 * period + o;
            if x <= span {
                out.push(x);
            }
        }
    }
    out.push(span);
    out
}

/// Nishita eq 8: `k(x) = max(p + (1 − p)·|2 mod(x, Δ) − Δ|/Δ, 0)`.
#[inline]
fn nishita_k(x: f64, period: f64, p: f64) -> f64 {
    let m = x.rem_euclid(period);
    (p + (1.0 - p) * (2.0 * m - period).abs() / period).max(0.0)
}

impl Shape {
    /// Relative intensity for the direction with `cos θ` and azimuth `φ` (rad).
    /// (The common shapes inline; the others are evaluated out of line.)
    #[inline]
    pub fn eval(&self, cos_theta: f64, phi: f64) -> f64 {
        match self {
            Shape::Isotropic => 1.0,
            Shape::CyclesSpot { cos_half, smooth } => {
                if *smooth > 0.0 {
                    smoothstep01((cos_theta - cos_half) / smooth)
                } else if cos_theta > *cos_half {
                    1.0
                } else {
                    0.0
                }
            }
            _ => self.eval_other(cos_theta, phi),
        }
    }

    #[inline(never)]
    fn eval_other(&self, cos_theta: f64, phi: f64) -> f64 {
        match self {
            Shape::Isotropic | Shape::CyclesSpot { .. } => self.eval(cos_theta, phi),
            Shape::Nishita {
                cos_gamma,
                q,
                period_phi,
                period_theta,
                p,
            } => {
                if cos_theta < *cos_gamma {
                    return 0.0;
                }
                let one_minus = 1.0 - cos_gamma;
                let base = if one_minus > 0.0 {
                    (1.0 - q) * (cos_theta - cos_gamma) / one_minus + q
                } else {
                    1.0
                };
                let mut v = base;
                if *period_phi > 0.0 {
                    v *= nishita_k(phi.rem_euclid(2.0 * PI), *period_phi, *p);
                }
                if *period_theta > 0.0 {
                    let theta = cos_theta.clamp(-1.0, 1.0).acos();
                    let phi = phi.rem_euclid(2.0 * PI);
                    let parity = ((phi / period_phi).floor() as i64 + (theta / period_theta).floor() as i64).rem_euclid(2);
                    v *= nishita_k(theta, *period_theta, *p) * parity as f64;
                }
                v
            }
            Shape::UsdShaping { cutoff, softness, focus } => {
                let theta = cos_theta.clamp(-1.0, 1.0).acos();
                if theta > *cutoff {
                    return 0.0;
                }
                let start = cutoff * (1.0 - softness);
                let cone = if *softness > 0.0 && theta > start {
                    1.0 - smoothstep01((theta - start) / (cutoff - start))
                } else {
                    1.0
                };
                let f = if *focus > 0.0 { cos_theta.abs().powf(*focus) } else { 1.0 };
                cone * f
            }
            Shape::Tabulated(t) => t.eval(cos_theta.clamp(-1.0, 1.0).acos(), phi),
        }
    }

    /// Whether the value depends on φ (then φ is computed per evaluation).
    pub fn needs_phi(&self) -> bool {
        match self {
            Shape::Nishita { period_phi, .. } => *period_phi > 0.0,
            Shape::Tabulated(t) => t.phi.len() > 1,
            _ => false,
        }
    }

    /// cos of the half-angle outside which the shape is exactly 0 (−1: none).
    pub fn cos_reach(&self) -> f64 {
        match self {
            Shape::Isotropic => -1.0,
            Shape::CyclesSpot { cos_half, .. } => *cos_half,
            Shape::Nishita { cos_gamma, .. } => *cos_gamma,
            Shape::UsdShaping { cutoff, .. } => cutoff.cos(),
            Shape::Tabulated(t) => t.reach().cos(),
        }
    }

    /// cos of the angles where the shape has a kink or jump (quadrature splits there).
    pub fn kinks(&self) -> Kinks {
        let mut k = Kinks::default();
        match self {
            Shape::CyclesSpot { cos_half, smooth } => {
                k.push(*cos_half);
                if *smooth > 0.0 {
                    k.push((cos_half + smooth).min(1.0));
                }
            }
            Shape::Nishita { cos_gamma, .. } => k.push(*cos_gamma),
            Shape::UsdShaping { cutoff, softness, .. } => {
                k.push(cutoff.cos());
                k.push((cutoff * (1.0 - softness)).cos());
            }
            _ => {}
        }
        k
    }

    /// Upper bound of the shape's value.
    pub fn max_value(&self) -> f64 {
        match self {
            Shape::Tabulated(t) => t.values.iter().flatten().fold(0.0, |m: f64, v| m.max(*v)),
            _ => 1.0,
        }
    }

    /// The shape for a scene distribution.
    pub fn from_distribution(d: &IntensityDistribution) -> Shape {
        let rad = |deg: f64| deg.to_radians();
        match d {
            IntensityDistribution::Isotropic(_) => Shape::Isotropic,
            IntensityDistribution::NishitaSpot(n) => Shape::Nishita {
                cos_gamma: rad(n.beam_spread_deg).cos(),
                q: n.sharpness,
                period_phi: 0.0,
                period_theta: 0.0,
                p: 0.0,
            },
            IntensityDistribution::Daisy(n) => Shape::Nishita {
                cos_gamma: rad(n.beam_spread_deg).cos(),
                q: n.sharpness,
                period_phi: rad(n.period_phi_deg),
                period_theta: 0.0,
                p: n.min_ratio,
            },
            IntensityDistribution::PolkaDot(n) => Shape::Nishita {
                cos_gamma: rad(n.beam_spread_deg).cos(),
                q: n.sharpness,
                period_phi: rad(n.period_phi_deg),
                period_theta: rad(n.period_theta_deg),
                p: n.min_ratio,
            },
            IntensityDistribution::UsdShaping(u) => Shape::UsdShaping {
                cutoff: rad(u.cone_angle_deg),
                softness: u.cone_softness,
                focus: u.focus,
            },
            IntensityDistribution::Tabulated(t) => Shape::Tabulated(Arc::new(Table {
                theta: t.theta_deg.iter().map(|d| rad(*d)).collect(),
                phi: t.phi_deg.iter().map(|d| rad(*d)).collect(),
                values: t.values.clone(),
            })),
        }
    }
}

/// The distinct cosines where a distribution has kinks (at most four; no allocation).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Kinks {
    values: [f64; 4],
    len: usize,
}

impl Kinks {
    /// Adds `c` unless it is already listed (or the list is full).
    pub fn push(&mut self, c: f64) {
        if self.len < self.values.len() && !self.as_slice().contains(&c) {
            self.values[self.len] = c;
            self.len += 1;
        }
    }

    /// The listed cosines.
    pub fn as_slice(&self) -> &[f64] {
        &self.values[..self.len]
    }
}

/// The least-area axis-aligned ellipse `(a, b)` in a light's gnomonic plane
/// (`tan θ cos φ`, `tan θ sin φ`; φ from local +X towards +Y) that holds
/// every direction of the given circular sectors `(φ₀, φ₁, θ_max)` (radians,
/// φ₀ ≤ φ₁), when its area is below 0.9 of the circular cone of half-angle
/// `reach` (rad) — otherwise `None` and the circle stays. Sector arcs are
/// sampled at 720 steps per turn (chord error `r(1 − cos(π/720))` < 1e-5 r),
/// every sector corner included; the aspect ratio `b/a` is searched over
/// [0.1, 10] on 201 log-spaced values, `a` is then the smallest that holds
/// every sample, and the result is inflated by 2e-5 to cover the chords.
/// Only for reaches below 80° (the gnomonic plane blows up towards 90°).
pub fn bounding_ellipse_of_sectors(sectors: &[(f64, f64, f64)], reach: f64) -> Option<(f64, f64)> {
    if sectors.is_empty() || !(reach > 0.0 && reach < 80f64.to_radians()) {
        return None;
    }
    let two_pi = 2.0 * PI;
    let mut pts: Vec<(f64, f64)> = Vec::new();
    for &(p0, p1, theta_max) in sectors {
        let r = theta_max.clamp(0.0, reach).tan();
        let steps = (((p1 - p0) / two_pi) * 720.0).ceil().max(1.0) as usize;
        for k in 0..=steps {
            let p = p0 + (p1 - p0) * k as f64 / steps as f64;
            pts.push((r * p.cos(), r * p.sin()));
        }
    }
    let inflate = 1.0 + 2e-5;
    let mut best: Option<(f64, f64, f64)> = None;
    for k in 0..=200 {
        let ratio = 10f64.powf(-1.0 + 2.0 * k as f64 / 200.0);
        let a = pts
            .iter()
            .map(|(x, y)| (x * x + (y / ratio) * (y / ratio)).sqrt())
            .fold(0.0, f64::max)
            * inflate;
        let area = a * a * ratio;
        if best.is_none_or(|b| area < b.2) {
            best = Some((a, a * ratio, area));
        }
    }
    let (a, b, area) = best?;
    let circle = reach.tan() * reach.tan();
    if a > 0.0 && b > 0.0 && area < 0.9 * circle {
        Some((a, b))
    } else {
        None
    }
}

/// A light's local frame in world space.
#[derive(Debug, Clone, Copy)]
pub struct LightFrame {
    /// Illumination axis (local −Z), unit.
    pub axis: DVec3,
    /// Local +X, unit (φ = 0).
    pub x: DVec3,
    /// Local +Y, unit (φ = 90°).
    pub y: DVec3,
}

impl LightFrame {
    /// The frame of an oriented light at `position`.
    pub fn new(position: DVec3, orientation: &Orientation) -> LightFrame {
        let q = match orientation {
            Orientation::QuaternionWxyz([w, x, y, z]) => DQuat::from_xyzw(*x, *y, *z, *w).normalize(),
            Orientation::LookAt { target, up } => {
                let f = (DVec3::from(*target) - position).normalize();
                let up = DVec3::from(*up).normalize();
                // Local −Z = forward, local +Y ≈ up.
                let zl = -f;
                let xl = up.cross(zl).try_normalize().unwrap_or_else(|| zl.any_orthonormal_vector());
                let yl = zl.cross(xl);
                DQuat::from_mat3(&glam::DMat3::from_cols(xl, yl, zl)).normalize()
            }
        };
        LightFrame {
            axis: q * DVec3::NEG_Z,
            x: q * DVec3::X,
            y: q * DVec3::Y,
        }
    }

    /// A unit world direction in local coordinates (light shines along local −Z).
    #[inline]
    pub fn to_local(&self, dir: DVec3) -> DVec3 {
        DVec3::new(dir.dot(self.x), dir.dot(self.y), -dir.dot(self.axis))
    }
}

/// A point or spot light, resolved to `C` channels.
#[derive(Debug, Clone)]
pub struct PointSource<const C: usize> {
    /// Name (for reports and per-light layers).
    pub name: String,
    /// Position, m.
    pub position: DVec3,
    /// Local frame.
    pub frame: LightFrame,
    /// Intensity on the axis before shape and IES factors, W·sr⁻¹ per channel.
    pub intensity: [f64; C],
    /// Relative distribution.
    pub shape: Shape,
    /// IES profile and its strength.
    pub ies: Option<(Arc<ies::IesProfile>, f64)>,
    /// View rays closer than this to the light are evaluated at this distance, m (> 0).
    pub min_distance: f64,
    /// cos of the bounding cone's half-angle about `frame.axis` (−1: the whole sphere).
    pub cos_reach: f64,
    /// Upper bound of `shape × IES factor`.
    pub max_factor: f64,
    /// A tighter, elliptical illumination volume for non-axisymmetric tables
    /// and IES profiles (intersected with the cone of `cos_reach`):
    /// `(a, b)` such that every lit direction has
    /// `(tan θ cos φ / a)² + (tan θ sin φ / b)² ≤ 1` (`None`: the circular cone only).
    pub ellipse: Option<(f64, f64)>,
    /// cos θ of the cones where a table's interpolation changes cell (its θ
    /// or IES vertical nodes inside the reach): the integrand is only C¹ (IES
    /// Catmull-Rom) or C⁰ (linear tables) across them, so rays are cut there.
    pub cell_cones: Vec<f64>,
    /// World normals of the planes through the axis where a table changes
    /// cell in φ (its φ nodes, IES horizontal angles); rays are cut there.
    pub cell_planes: Vec<DVec3>,
}

/// Closest distance at which a view ray is evaluated, m, for a light of
/// radius 0: a ray exactly through a point light has infinite in-scatter; a
/// floor keeps it finite (and the report says where it applied).
pub const MIN_LIGHT_DISTANCE: f64 = 1e-9;

impl<const C: usize> PointSource<C> {
    /// Relative factor `D(ω)·F_IES(ω)` for the unit world direction from the light.
    #[inline]
    pub fn factor(&self, dir: DVec3) -> f64 {
        let cos_theta = dir.dot(self.frame.axis);
        if cos_theta < self.cos_reach {
            return 0.0;
        }
        let phi = if self.shape.needs_phi() {
            dir.dot(self.frame.y).atan2(dir.dot(self.frame.x))
        } else {
            0.0
        };
        let mut f = self.shape.eval(cos_theta, phi);
        if let Some((profile, strength)) = &self.ies
            && f > 0.0
        {
            f *= strength * profile.cycles_factor(self.frame.to_local(dir));
        }
        f
    }

    /// Whether the factor depends on cos θ alone (no IES profile, no φ
    /// dependence), so that [`PointSource::factor_cos`] applies.
    pub fn is_axial(&self) -> bool {
        self.ies.is_none() && !self.shape.needs_phi()
    }

    /// [`PointSource::factor`] of a direction with this cos θ, for a light
    /// that [`PointSource::is_axial`].
    #[inline]
    pub fn factor_cos(&self, cos_theta: f64) -> f64 {
        if cos_theta < self.cos_reach {
            return 0.0;
        }
        self.shape.eval(cos_theta, 0.0)
    }

    /// Whether the factor is smooth and monotone in θ between the cones of
    /// [`Self::kinks`]: Blender's point and spot lamps (constant, or a
    /// smoothstep across the blend), without an IES profile. Then along a
    /// view ray, between the cuts of the in-scatter integral, it has no
    /// feature narrower than the piece, and a low-order rule that agrees
    /// with the next lower one can be trusted. (Not so for tables and IES
    /// cells, periodic patterns or a sharp focus lobe, which can peak between
    /// three nodes.)
    pub fn smooth_between_kinks(&self) -> bool {
        self.ies.is_none() && matches!(self.shape, Shape::Isotropic | Shape::CyclesSpot { .. })
    }

    /// The distinct cos θ values where the factor has kinks or jumps.
    pub fn kinks(&self) -> Kinks {
        let mut k = self.shape.kinks();
        if self.cos_reach > -1.0 {
            k.push(self.cos_reach);
        }
        k
    }

    /// Resolves a scene point light (`ies` already loaded).
    pub fn from_point(l: &PointLight, colour: [f64; C], ies: Option<(Arc<ies::IesProfile>, f64)>) -> Self {
        let position = DVec3::from(l.position);
        let shape = Shape::from_distribution(&l.distribution);
        Self::assemble(&l.name, position, &l.orientation, l.power_w, l.radius_m, colour, shape, ies)
    }

    /// Resolves a scene spot light (`ies` already loaded).
    pub fn from_spot(l: &SpotLight, colour: [f64; C], ies: Option<(Arc<ies::IesProfile>, f64)>) -> Self {
        let position = DVec3::from(l.position);
        let cos_half = (0.5 * l.spot_size_deg).to_radians().cos();
        let shape = Shape::CyclesSpot {
            cos_half,
            smooth: l.spot_blend * (1.0 - cos_half),
        };
        Self::assemble(&l.name, position, &l.orientation, l.power_w, l.radius_m, colour, shape, ies)
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        name: &str,
        position: DVec3,
        orientation: &Orientation,
        power_w: f64,
        radius_m: f64,
        colour: [f64; C],
        shape: Shape,
        ies: Option<(Arc<ies::IesProfile>, f64)>,
    ) -> Self {
        let frame = LightFrame::new(position, orientation);
        // The elliptical volume is intersected with the circular cone of
        // `cos_reach` where rays are cut (both bound the lit directions).
        let ellipse = match (&shape, &ies) {
            (_, Some((p, _))) => p.bounding_ellipse(),
            (Shape::Tabulated(t), None) => t.bounding_ellipse(),
            _ => None,
        };
        let mut cos_reach = shape.cos_reach();
        let mut max_factor = shape.max_value();
        if let Some((p, s)) = &ies {
            cos_reach = cos_reach.max(p.bounding_half_angle().cos());
            max_factor *= s * p.max_cycles_factor();
        }
        // Cell boundaries of tabulated distributions, as cones (θ nodes) and
        // planes through the axis (φ nodes; a plane holds φ and φ + π).
        let (mut cell_theta, mut cell_phi): (Vec<f64>, Vec<f64>) = (Vec::new(), Vec::new());
        if let Shape::Tabulated(t) = &shape {
            cell_theta.extend(t.theta.iter().copied());
            if t.phi.len() > 1 {
                cell_phi.extend(t.phi.iter().copied());
            }
        }
        if let Shape::Nishita {
            period_phi,
            period_theta,
            p,
            ..
        } = &shape
        {
            // Eq 8's k is a triangle wave clamped at 0, and eq 10's parity
            // jumps at the period boundaries: both are smooth between the
            // angles of `pattern_kinks` (φ restarts at 0, taken mod 2π).
            if *period_phi > 0.0 {
                cell_phi.extend(pattern_kinks(*period_phi, *p, 2.0 * PI));
            }
            if *period_theta > 0.0 {
                cell_theta.extend(pattern_kinks(*period_theta, *p, PI));
            }
        }
        if let Some((p, _)) = &ies {
            let (v, h) = p.cell_angles();
            cell_theta.extend(v);
            // Cycles' C-plane h lies along local (−sin h, −cos h): φ = −π/2 − h.
            cell_phi.extend(h.iter().map(|h| -FRAC_PI_2 - h));
        }
        let reach = cos_reach.clamp(-1.0, 1.0).acos();
        let mut cell_cones: Vec<f64> = cell_theta
            .iter()
            .filter(|t| **t > 1e-9 && **t < reach - 1e-9 && **t < PI - 1e-9)
            .map(|t| t.cos())
            .collect();
        cell_cones.sort_by(f64::total_cmp);
        cell_cones.dedup_by(|a, b| (*a - *b).abs() < 1e-12);
        // One plane per azimuth mod π (sorted, so that thousands of pattern
        // azimuths dedup in O(n log n)).
        let mut half_turns: Vec<f64> = cell_phi.iter().map(|phi| phi.rem_euclid(PI)).collect();
        half_turns.sort_by(f64::total_cmp);
        half_turns.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        if half_turns.len() > 1 && half_turns[half_turns.len() - 1] > PI - 1e-9 && half_turns[0] < 1e-9 {
            half_turns.pop();
        }
        let cell_planes: Vec<DVec3> = half_turns
            .iter()
            .map(|phi| frame.axis.cross(frame.x * phi.cos() + frame.y * phi.sin()).normalize_or_zero())
            .filter(|n| *n != DVec3::ZERO)
            .collect();
        PointSource {
            name: name.to_string(),
            position,
            frame,
            intensity: colour.map(|c| c * power_w * CYCLES_WATTS_TO_INTENSITY),
            shape,
            ies,
            min_distance: radius_m.max(MIN_LIGHT_DISTANCE),
            cos_reach,
            max_factor,
            ellipse,
            cell_cones,
            cell_planes,
        }
    }
}

/// The parameter intervals `[t0, t1] ⊂ [lo, hi]` where `o + t·d` lies in the
/// cone `{x : (x − apex)·axis ≥ c·|x − apex|}` (`c` = cos of the half-angle,
/// any value in [−1, 1]; `d` unit). Robust form: the quadratic's roots only
/// propose break points; every piece is classified by testing its midpoint
/// with the exact predicate, so grazing rays and the second nappe never
/// produce wrong intervals. Segments clearly outside a cone with `c ≥ 0` (most
/// view rays, for a spot) are rejected first by [`far_outside_cone`].
#[allow(clippy::too_many_arguments)]
pub fn ray_cone_intervals(o: DVec3, d: DVec3, lo: f64, hi: f64, apex: DVec3, axis: DVec3, c: f64, out: &mut Vec<(f64, f64)>) {
    out.clear();
    if hi <= lo {
        return;
    }
    if c <= -1.0 {
        out.push((lo, hi));
        return;
    }
    let w = o - apex;
    let (da, wa) = (d.dot(axis), w.dot(axis));
    if c >= 0.0 && far_outside_cone(w, d, lo, hi, axis, c, da, wa) {
        return;
    }
    let wl = w.length();
    let inside = |t: f64| -> bool {
        let v = if t.is_finite() { w + d * t } else { d };
        v.dot(axis) >= c * v.length()
    };
    // (v·a)² − c²|v|² = 0 with v = w + t d, factored to limit cancellation.
    let qa = (da - c) * (da + c);
    let qb = 2.0 * (da * wa - c * c * d.dot(w));
    let qc = (wa - c * wl) * (wa + c * wl);
    let mut cuts: [f64; 6] = [lo, f64::NAN, f64::NAN, f64::NAN, f64::NAN, hi];
    let mut n = 1;
    let mut push = |t: f64| {
        if t.is_finite() && t > lo && t < hi {
            cuts[n] = t;
            n += 1;
        }
    };
    if qa.abs() > 1e-300 {
        // (qb/2)² − qa·qc, rewritten without the cancellation of its two large
        // terms (which loses every digit for rays passing close to the apex):
        // = c²·(|(d·a)w − (w·a)d|² − c²|w × d|²)   (|d| = 1).
        let disc4 = c * c * ((w * da - d * wa).length_squared() - c * c * w.cross(d).length_squared());
        if disc4 >= 0.0 {
            let s = disc4.sqrt();
            let half_b = 0.5 * qb;
            let q = -(half_b + half_b.signum() * s);
            if q != 0.0 {
                push(q / qa);
                push(qc / q);
            } else {
                push(-half_b / qa);
            }
        }
    } else if qb != 0.0 {
        push(-qc / qb);
    }
    // The plane through the apex ⊥ the axis: for c = 0 the cone is that half
    // space and the quadratic has a double root that rounding may lose.
    if da != 0.0 {
        push(-wa / da);
    }
    // The apex itself, where the predicate changes on a ray through it.
    let tc = -w.dot(d);
    if (w + d * tc).length() <= 1e-12 * (1.0 + wl) {
        push(tc);
    }
    cuts[n] = hi;
    let cuts = &mut cuts[..=n];
    cuts.sort_by(f64::total_cmp);
    for k in 0..n {
        let (a, b) = (cuts[k], cuts[k + 1]);
        if b <= a {
            continue;
        }
        let mid = if b.is_finite() {
            0.5 * (a + b)
        } else if a.is_finite() {
            a.abs().max(1.0) * 2.0 + a.abs() * 1e6 + 1e6
        } else {
            0.0
        };
        if inside(mid) {
            match out.last_mut() {
                Some(last) if last.1 >= a => last.1 = b,
                _ => out.push((a, b)),
            }
        }
    }
}

/// Quick rejection for [`ray_cone_intervals`] with `c ≥ 0` (`w` = origin −
/// apex, `da = d·axis`, `wa = w·axis`): whether `o + t·d`, `t ∈ [lo, hi]`,
/// stays clearly outside the cone.
///
/// For `c ≥ 0`, `g(t) = v·a − c|v|` (`v = w + t·d`) is concave in `t` (a
/// linear function minus `c` times a convex one) and the cone is `g ≥ 0`. With
/// `p = w·d`, `m = w − p·d` (apex to the closest point of the line),
/// `q = |m|` and `s = t + p`: `|v| = √(q² + s²)` and
/// `g = m·a + da·s − c√(q² + s²)`. When `|da| < c` it is maximal at
/// `s* = da·q/√(c² − da²)`, with maximum `m·a − q√(c² − da²)`; it increases
/// (decreases) without bound when `da ≥ c` (`da ≤ −c`). The maximum over
/// `[lo, hi]` is therefore at `t* = s* − p` clamped to `[lo, hi]`. Every
/// comparison is made on squares of non-negative sides, so no square root or
/// division is taken: the test costs a few dot products. A segment is
/// rejected when the maximum is below `−M`, `M = 1e-12` of the scale (far
/// above rounding); anything closer is left to the exact classification.
#[allow(clippy::too_many_arguments)]
#[inline]
fn far_outside_cone(w: DVec3, d: DVec3, lo: f64, hi: f64, axis: DVec3, c: f64, da: f64, wa: f64) -> bool {
    let scale = w.abs().element_sum();
    // g(t) < −M at one point, as v·a + M < c|v|.
    let outside_at = |t: f64| -> bool {
        if !t.is_finite() {
            return false;
        }
        let v = w + d * t;
        let lhs = v.dot(axis) + 1e-12 * (scale + t.abs());
        lhs < 0.0 || lhs * lhs < c * c * v.length_squared()
    };
    if da >= c {
        return outside_at(hi);
    }
    if da <= -c {
        return outside_at(lo);
    }
    let p = w.dot(d);
    let q2 = (w - d * p).length_squared();
    let k2 = (c - da) * (c + da);
    // Whether s* = da·√(q²/k²) < x, by the signs and squares of both sides.
    let s_star_below = |x: f64| -> bool {
        if da >= 0.0 {
            x > 0.0 && da * da * q2 < x * x * k2
        } else {
            x >= 0.0 || da * da * q2 > x * x * k2
        }
    };
    if s_star_below(lo + p) {
        return outside_at(lo);
    }
    if !s_star_below(hi + p) {
        return outside_at(hi);
    }
    // t* inside [lo, hi]: the line's maximum m·a − q√k² < −M.
    let lhs = wa - da * p + 1e-12 * (scale + p.abs());
    lhs < 0.0 || lhs * lhs < q2 * k2
}

/// The intervals of `[lo, hi]` where `o + t·d` is inside the elliptical cone
/// of a light (`ellipse = (a, b)` in the gnomonic plane of its frame): the
/// light frame scaled by `1/a`, `1/b` maps it onto the circular cone of
/// half-angle 45°, and the ray's parameter is kept by normalising the mapped
/// direction.
#[allow(clippy::too_many_arguments)]
pub fn ray_elliptic_cone_intervals(
    o: DVec3,
    d: DVec3,
    lo: f64,
    hi: f64,
    apex: DVec3,
    frame: &LightFrame,
    ellipse: (f64, f64),
    out: &mut Vec<(f64, f64)>,
) {
    let map = |v: DVec3| DVec3::new(v.dot(frame.x) / ellipse.0, v.dot(frame.y) / ellipse.1, v.dot(frame.axis));
    let (w, dm) = (map(o - apex), map(d));
    let len = dm.length();
    if len == 0.0 || !len.is_finite() {
        out.clear();
        return;
    }
    ray_cone_intervals(
        w,
        dm / len,
        lo * len,
        hi * len,
        DVec3::ZERO,
        DVec3::Z,
        std::f64::consts::FRAC_1_SQRT_2,
        out,
    );
    for iv in out.iter_mut() {
        iv.0 /= len;
        iv.1 /= len;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn headlight_table_gets_a_tight_ellipse_holding_every_lit_direction() {
        // Wide along local X (±40°), narrow along Y (±8°), like a low-beam headlight.
        let theta: Vec<f64> = (0..=45).map(|k| (k as f64).to_radians()).collect();
        let phi: Vec<f64> = (0..24).map(|k| (15.0 * k as f64).to_radians()).collect();
        let values: Vec<Vec<f64>> = phi
            .iter()
            .map(|p| {
                let reach = 1.0 / ((p.cos() / 40f64.to_radians().tan()).powi(2) + (p.sin() / 8f64.to_radians().tan()).powi(2)).sqrt();
                theta
                    .iter()
                    .map(|t| if t.tan() < reach { 1.0 - t.tan() / reach } else { 0.0 })
                    .collect()
            })
            .collect();
        let t = Table { theta, phi, values };
        let (a, b) = t.bounding_ellipse().expect("non-axisymmetric: an ellipse");
        assert!(a > 2.0 * b, "a = {a}, b = {b}");
        let frame = LightFrame {
            axis: DVec3::NEG_Z,
            x: DVec3::X,
            y: DVec3::Y,
        };
        let mut rng = 5u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((rng >> 11) as f64) / ((1u64 << 53) as f64)
        };
        let mut lit = 0;
        for _ in 0..200_000 {
            let (th, ph) = (next() * 0.8, next() * 2.0 * PI);
            if t.eval(th, ph) > 0.0 {
                lit += 1;
                let (x, y) = (th.tan() * ph.cos(), th.tan() * ph.sin());
                assert!(
                    (x / a).powi(2) + (y / b).powi(2) <= 1.0,
                    "lit direction θ={th} φ={ph} outside the ellipse"
                );
            }
        }
        assert!(lit > 1000);
        // Ray intervals agree with the pointwise test.
        let apex = DVec3::new(0.0, 0.0, 1.0);
        let mut out = Vec::new();
        for _ in 0..300 {
            let o = DVec3::new(next() * 8.0 - 4.0, next() * 8.0 - 4.0, next() * 2.0 - 1.5);
            let d = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
            ray_elliptic_cone_intervals(o, d, 0.0, 10.0, apex, &frame, (a, b), &mut out);
            for k in 0..200 {
                let s = 10.0 * (k as f64 + 0.5) / 200.0;
                let v = o + d * s - apex;
                let z = -v.z;
                let inside = z > 0.0 && (v.x / a).powi(2) + (v.y / b).powi(2) <= z * z;
                let listed = out.iter().any(|(p, q)| s >= *p && s <= *q);
                let q = ((v.x / a).powi(2) + (v.y / b).powi(2)).sqrt() - z;
                assert!(q.abs() < 1e-9 || inside == listed, "s={s} inside={inside} listed={listed}");
            }
        }
    }

    #[test]
    fn cone_intervals_match_pointwise_predicate() {
        let apex = DVec3::new(0.3, -0.2, 4.0);
        let axis = DVec3::new(0.1, 0.2, -1.0).normalize();
        let mut out = Vec::new();
        let mut rng = 12345u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((rng >> 11) as f64) / ((1u64 << 53) as f64) * 2.0 - 1.0
        };
        for &c in &[0.99999, 0.9, 0.5, 0.0, -0.3, -0.9] {
            for _ in 0..300 {
                let o = DVec3::new(next() * 6.0, next() * 6.0, next() * 6.0);
                let d = DVec3::new(next(), next(), next()).normalize();
                ray_cone_intervals(o, d, 0.0, 20.0, apex, axis, c, &mut out);
                for k in 0..400 {
                    let t = 20.0 * (k as f64 + 0.5) / 400.0;
                    let v = o + d * t - apex;
                    let inside = v.dot(axis) >= c * v.length();
                    let near_edge = (v.dot(axis) - c * v.length()).abs() < 1e-6 * v.length();
                    let in_list = out.iter().any(|(a, b)| t >= *a && t <= *b);
                    assert!(near_edge || inside == in_list, "c={c} t={t} inside={inside} list={out:?}");
                }
            }
        }
    }

    /// The quick rejection never drops a segment that has a point inside the cone.
    #[test]
    fn quick_cone_rejection_is_conservative() {
        let mut rng = 777u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((rng >> 11) as f64) / ((1u64 << 53) as f64) * 2.0 - 1.0
        };
        let mut rejected = 0;
        for &c in &[0.999999, 0.99, 0.9, 0.7, 0.3, 0.0] {
            let axis = DVec3::new(next(), next(), next()).normalize();
            for k in 0..2000 {
                let w = DVec3::new(next(), next(), next()) * 5.0;
                let d = DVec3::new(next(), next(), next()).normalize();
                let (lo, hi) = (
                    next().abs() * 2.0,
                    if k % 3 == 0 { f64::INFINITY } else { 2.0 + 6.0 * next().abs() },
                );
                if !far_outside_cone(w, d, lo, hi, axis, c, d.dot(axis), w.dot(axis)) {
                    continue;
                }
                rejected += 1;
                let end = if hi.is_finite() { hi } else { 1e4 };
                for j in 0..=2000 {
                    let t = lo + (end - lo) * (j as f64 / 2000.0).powi(3);
                    let v = w + d * t;
                    assert!(v.dot(axis) < c * v.length(), "c={c} t={t}: inside, but rejected");
                }
            }
        }
        assert!(rejected > 1000, "{rejected}");
    }

    #[test]
    fn spot_mask_is_cycles_smoothstep() {
        let cos_half = (22.5f64).to_radians().cos();
        let s = Shape::CyclesSpot {
            cos_half,
            smooth: 0.15 * (1.0 - cos_half),
        };
        assert_eq!(s.eval(1.0, 0.0), 1.0);
        assert_eq!(s.eval(cos_half - 1e-9, 0.0), 0.0);
        let mid = cos_half + 0.5 * 0.15 * (1.0 - cos_half);
        assert!((s.eval(mid, 0.0) - 0.5).abs() < 1e-12);
    }

    #[test]
    fn nishita_eq7_limits() {
        let s = Shape::Nishita {
            cos_gamma: 0.5,
            q: 0.25,
            period_phi: 0.0,
            period_theta: 0.0,
            p: 0.0,
        };
        assert!((s.eval(1.0, 0.0) - 1.0).abs() < 1e-15);
        assert!((s.eval(0.5, 0.0) - 0.25).abs() < 1e-15);
        assert_eq!(s.eval(0.49, 0.0), 0.0);
    }

    #[test]
    fn table_reproduces_nodes_and_wraps() {
        let t = Table {
            theta: vec![0.0, 0.5, 1.0],
            phi: vec![0.0, PI],
            values: vec![vec![1.0, 0.5, 0.0], vec![2.0, 1.0, 0.0]],
        };
        assert!((t.eval(0.5, 0.0) - 0.5).abs() < 1e-15);
        assert!((t.eval(0.5, PI) - 1.0).abs() < 1e-15);
        assert!((t.eval(0.5, 1.5 * PI) - 0.75).abs() < 1e-12);
        assert!((t.eval(0.5, -0.5 * PI) - 0.75).abs() < 1e-12);
        assert_eq!(t.eval(1.2, 0.0), 0.0);
        assert!((t.reach() - 1.0).abs() < 1e-15);
    }
}
