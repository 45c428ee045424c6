//! Shared brute-force references for the integration tests.
//!
//! Everything here is written from the model definitions (Ishiyama eqs 4, 7–13;
//! Klassen eqs 1.6–1.11 and the flat-earth geometry of 3.3–3.12), **not** from
//! the closed forms and not with `tyndall_core::numeric` or the media's
//! `optical_depth` / `source`: the volume rendering equation
//!
//! `L = ∫₀^{s_max} T(0, s) μ_s(s) J(s) ds`,  `T(0, s) = exp(−∫₀ˢ μ_t(t) dt)`
//!
//! is integrated by composite Gauss–Legendre on panels small enough that the
//! integrand varies by at most a factor e^{±1} across each (nested: the optical
//! depth at every outer node is itself a Gauss–Legendre integral of μ_t from
//! the panel start). Panels are split at every point where the integrand is not
//! smooth (medium boundaries, the kinks of the sun path in a box, located by
//! bisection). Infinite rays are truncated where a rigorous bound on the rest of
//! the integral falls below 1e-17 of the value so far.
//!
//! Phase functions are re-implemented here from their textbook formulas.
#![allow(dead_code)]

use glam::DVec3;
use std::f64::consts::PI;
use std::sync::OnceLock;

// ------------------------------------------------------------------ Gauss–Legendre

/// Gauss–Legendre nodes and weights on [−1, 1], computed by Newton's method on
/// the Legendre recurrence (to full double precision).
pub struct GaussLegendre {
    /// Nodes.
    pub x: Vec<f64>,
    /// Weights.
    pub w: Vec<f64>,
}

impl GaussLegendre {
    /// `n`-point rule.
    pub fn new(n: usize) -> Self {
        let mut x = vec![0.0; n];
        let mut w = vec![0.0; n];
        for i in 0..n {
            let mut z = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            let mut dp = 0.0;
            for _ in 0..100 {
                let (mut p0, mut p1) = (1.0, z);
                for k in 2..=n {
                    let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                    p0 = p1;
                    p1 = p2;
                }
                dp = n as f64 * (z * p1 - p0) / (z * z - 1.0);
                let dz = p1 / dp;
                z -= dz;
                if dz.abs() < 1e-17 {
                    break;
                }
            }
            x[i] = z;
            w[i] = 2.0 / ((1.0 - z * z) * dp * dp);
        }
        GaussLegendre { x, w }
    }

    /// ∫_a^b f, vector-valued.
    pub fn integrate<const N: usize>(&self, f: &dyn Fn(f64) -> [f64; N], a: f64, b: f64) -> [f64; N] {
        let c = 0.5 * (a + b);
        let h = 0.5 * (b - a);
        let mut out = [0.0; N];
        for (x, w) in self.x.iter().zip(&self.w) {
            let v = f(c + h * x);
            for i in 0..N {
                out[i] += w * v[i];
            }
        }
        out.map(|v| v * h)
    }
}

/// [`adaptive_gauss_legendre`] accepts a panel whose relative difference
/// stalls at or below this: the integrand's own rounding (an optical depth
/// of 10⁴ m⁻¹ × a slab length that a 0.1° light path computes to 1e-12 m is
/// 1e-8 of the value), not a feature the rule has yet to resolve.
const NOISE_LIMIT: f64 = 1e-7;

fn gl_adaptive() -> &'static GaussLegendre {
    static G: OnceLock<GaussLegendre> = OnceLock::new();
    G.get_or_init(|| GaussLegendre::new(10))
}

/// `∫_a^b f` by adaptive bisection with a 10-point Gauss–Legendre rule,
/// to `rel` of the integral's first estimate.
///
/// `[a, b]` is first cut into `panels` equal panels (so a feature narrower
/// than the rule's spacing on the whole interval is still seen). A panel
/// whose rule on the whole and on its two halves differ by `δ` is accepted
/// (as the halves' sum) when `δ ≤ rel·first·(width / (b − a))` — the targets
/// add up to `rel·first` over the interval — or `δ ≤ floor·(|left| + |right|)`
/// (below about 1e-14 of its own value a panel's difference is rounding),
/// or when that relative difference has stopped falling for two levels in
/// a row at or below [`NOISE_LIMIT`] (the integrand's own rounding noise:
/// halving a panel halves such a difference no more than it halves the
/// panel's value, where a kink's falls at least twice as fast); else both
/// halves are refined, at most 40 times. On a smooth panel the
/// halves' sum is far more accurate than `δ` (the rule is exact to degree
/// 19), so `δ` is a loose bound; at a kink inside a panel the bisection
/// closes in on it.
///
/// Written for the brute-force references: it shares nothing with the
/// library's Gauss–Kronrod quadrature (its nodes come from
/// [`GaussLegendre::new`], its variable is the caller's).
pub fn adaptive_gauss_legendre(f: &dyn Fn(f64) -> f64, a: f64, b: f64, rel: f64, panels: usize, floor: f64) -> f64 {
    let gl = gl_adaptive();
    let rule = |a: f64, b: f64| -> f64 {
        let (c, h) = (0.5 * (a + b), 0.5 * (b - a));
        h * gl.x.iter().zip(&gl.w).map(|(x, w)| w * f(c + h * x)).sum::<f64>()
    };
    /// `stalls`: how many levels in a row the relative difference
    /// `δ/(|left| + |right|)` has not fallen below 0.7 of its parent's.
    #[allow(clippy::too_many_arguments)]
    fn refine(
        rule: &dyn Fn(f64, f64) -> f64,
        a: f64,
        b: f64,
        whole: f64,
        per_len: f64,
        floor: f64,
        parent_rho: f64,
        stalls: u32,
        depth: u32,
    ) -> f64 {
        let m = 0.5 * (a + b);
        let (left, right) = (rule(a, m), rule(m, b));
        let delta = (left + right - whole).abs();
        let size = left.abs() + right.abs();
        if depth == 0 || m <= a || m >= b || delta <= (per_len * (b - a)).max(floor * size) {
            return left + right;
        }
        let rho = delta / size;
        let stalls = if rho >= 0.7 * parent_rho { stalls + 1 } else { 0 };
        if stalls >= 2 && rho <= NOISE_LIMIT {
            return left + right;
        }
        refine(rule, a, m, left, per_len, floor, rho, stalls, depth - 1) + refine(rule, m, b, right, per_len, floor, rho, stalls, depth - 1)
    }
    if b <= a {
        return 0.0;
    }
    let n = panels.max(1);
    let edges: Vec<f64> = (0..=n)
        .map(|k| if k == n { b } else { a + (b - a) * k as f64 / n as f64 })
        .collect();
    let wholes: Vec<f64> = edges.windows(2).map(|w| rule(w[0], w[1])).collect();
    let first: f64 = wholes.iter().map(|v| v.abs()).sum();
    let per_len = rel * first / (b - a);
    edges
        .windows(2)
        .zip(&wholes)
        .map(|(w, &whole)| refine(&rule, w[0], w[1], whole, per_len, floor, f64::INFINITY, 0, 40))
        .sum()
}

fn gl_outer() -> &'static GaussLegendre {
    static G: OnceLock<GaussLegendre> = OnceLock::new();
    G.get_or_init(|| GaussLegendre::new(14))
}
fn gl_inner() -> &'static GaussLegendre {
    static G: OnceLock<GaussLegendre> = OnceLock::new();
    G.get_or_init(|| GaussLegendre::new(12))
}

// ------------------------------------------------------------------ phase functions

/// Phase functions, from their formulas (μ = cos of the angle between the
/// view direction and the direction to the light).
#[derive(Debug, Clone, Copy)]
pub enum Phase {
    /// 1/4π.
    Iso,
    /// 3/(16π)(1+μ²).
    Rayleigh,
    /// Henyey–Greenstein.
    Hg(f64),
    /// Cornette–Shanks.
    Cs(f64),
    /// Nishita hazy: (1 + 9 cos¹⁶(α/2))/(8π).
    Hazy,
    /// Nishita murky: 33/(332π)(1 + 50 cos⁶⁴(α/2)).
    Murky,
}

impl Phase {
    /// Value, sr⁻¹.
    pub fn eval(self, mu: f64) -> f64 {
        let mu = mu.clamp(-1.0, 1.0);
        match self {
            Phase::Iso => 0.25 / PI,
            Phase::Rayleigh => 3.0 * (1.0 + mu * mu) / (16.0 * PI),
            Phase::Hg(g) => (1.0 - g * g) / (4.0 * PI * (1.0 + g * g - 2.0 * g * mu).powf(1.5)),
            Phase::Cs(g) => 1.5 * (1.0 - g * g) / (2.0 + g * g) * (1.0 + mu * mu) / (1.0 + g * g - 2.0 * g * mu).powf(1.5) / (4.0 * PI),
            Phase::Hazy => {
                // cos²(α/2) = (1 + cos α)/2
                let c2 = 0.5 * (1.0 + mu);
                (1.0 + 9.0 * c2.powi(8)) / (8.0 * PI)
            }
            Phase::Murky => {
                let c2 = 0.5 * (1.0 + mu);
                33.0 * (1.0 + 50.0 * c2.powi(32)) / (332.0 * PI)
            }
        }
    }

    /// The scene-file JSON of this phase function.
    pub fn json(self) -> String {
        match self {
            Phase::Iso => r#"{"type":"isotropic"}"#.into(),
            Phase::Rayleigh => r#"{"type":"rayleigh"}"#.into(),
            Phase::Hg(g) => format!(r#"{{"type":"henyey_greenstein","g":{g:?}}}"#),
            Phase::Cs(g) => format!(r#"{{"type":"cornette_shanks","g":{g:?}}}"#),
            Phase::Hazy => r#"{"type":"nishita_hazy"}"#.into(),
            Phase::Murky => r#"{"type":"nishita_murky"}"#.into(),
        }
    }

    /// The library's phase function with the same parameters.
    pub fn lib(self) -> tyndall_core::medium::phase::PhaseFunction {
        use tyndall_core::medium::phase::PhaseFunction as P;
        match self {
            Phase::Iso => P::Isotropic,
            Phase::Rayleigh => P::Rayleigh,
            Phase::Hg(g) => P::HenyeyGreenstein { g },
            Phase::Cs(g) => P::CornetteShanks { g },
            Phase::Hazy => P::NishitaHazy,
            Phase::Murky => P::NishitaMurky,
        }
    }
}

/// The phase function averaged over a uniform sun disc of angular radius
/// `radius` (rad) whose centre is at angle `acos(mu)` from the scattering
/// direction: `(1/Ω) ∫_cap p(cos γ) dΩ`, by Gauss–Legendre in the cap's polar
/// angle r and azimuth ψ, `cos γ = cos θ cos r + sin θ sin r cos ψ`.
pub fn disc_average(phase: Phase, mu: f64, radius: f64) -> f64 {
    static GR: OnceLock<GaussLegendre> = OnceLock::new();
    static GP: OnceLock<GaussLegendre> = OnceLock::new();
    let gr = GR.get_or_init(|| GaussLegendre::new(24));
    let gp = GP.get_or_init(|| GaussLegendre::new(48));
    let ct = mu.clamp(-1.0, 1.0);
    let st = (1.0 - ct * ct).max(0.0).sqrt();
    let mut total = 0.0;
    for panel in 0..4 {
        let (a, b) = (radius * panel as f64 / 4.0, radius * (panel + 1) as f64 / 4.0);
        let v = gr.integrate(
            &|r: f64| {
                let (sr, cr) = r.sin_cos();
                // ∫₀^{2π} = 2∫₀^π by symmetry in ψ.
                let inner = gp.integrate(&|psi: f64| [phase.eval(ct * cr + st * sr * psi.cos())], 0.0, PI);
                [2.0 * inner[0] * sr]
            },
            a,
            b,
        );
        total += v[0];
    }
    let cap = 4.0 * PI * (0.5 * radius).sin().powi(2);
    total / cap
}

// ------------------------------------------------------------------ lights

/// One sun: unit direction to it and irradiance per RGB channel.
#[derive(Debug, Clone, Copy)]
pub struct Sun {
    /// Unit vector towards the sun.
    pub to_sun: DVec3,
    /// W·m⁻² per channel.
    pub e: [f64; 3],
}

/// Suns and ambient radiance.
#[derive(Debug, Clone)]
pub struct Lights {
    /// Suns.
    pub suns: Vec<Sun>,
    /// Ambient radiance per channel.
    pub ambient: [f64; 3],
}

impl Lights {
    /// The library's light set.
    pub fn lib(&self) -> tyndall_core::medium::LightSet<3> {
        tyndall_core::medium::LightSet {
            suns: self
                .suns
                .iter()
                .map(|s| tyndall_core::medium::SunSource::point(s.to_sun, s.e))
                .collect(),
            ambient: self.ambient,
        }
    }

    /// JSON `lights` array: suns as `color` × strength 1 and point-like (angular
    /// diameter 0, as the models of the papers), ambient as colour × radiance 1.
    pub fn json(&self) -> String {
        let mut parts: Vec<String> = self
            .suns
            .iter()
            .map(|s| {
                format!(
                    r#"{{"type":"sun","direction_to_sun":[{:?},{:?},{:?}],"color":[{:?},{:?},{:?}],"strength_w_m2":1.0,"angular_diameter_deg":0.0}}"#,
                    s.to_sun.x, s.to_sun.y, s.to_sun.z, s.e[0], s.e[1], s.e[2]
                )
            })
            .collect();
        parts.push(format!(
            r#"{{"type":"ambient","color":[{:?},{:?},{:?}],"radiance":1.0}}"#,
            self.ambient[0], self.ambient[1], self.ambient[2]
        ));
        format!("[{}]", parts.join(","))
    }
}

/// Unit vector from elevation and azimuth in degrees (azimuth from +X towards +Y).
pub fn dir_deg(elev: f64, azim: f64) -> DVec3 {
    let (se, ce) = elev.to_radians().sin_cos();
    let (sa, ca) = azim.to_radians().sin_cos();
    // Exact zeros for exact horizontal / vertical inputs.
    let se = if elev == 0.0 { 0.0 } else { se };
    let ce = if elev.abs() == 90.0 { 0.0 } else { ce };
    DVec3::new(ce * ca, ce * sa, se)
}

// ------------------------------------------------------------------ generic VRE quadrature

/// Result of a brute-force integration along one ray.
#[derive(Debug, Clone, Copy)]
pub struct Brute {
    /// In-scattered radiance per channel.
    pub l: [f64; 3],
    /// Optical depth to the end of the ray per channel (`∞` where the model's
    /// optical depth diverges, e.g. an infinite ray in a world medium).
    pub tau: [f64; 3],
    /// Panels used.
    pub panels: usize,
}

impl Brute {
    /// Transmittance `exp(−τ)`.
    pub fn t(&self) -> [f64; 3] {
        self.tau.map(|t| (-t).exp())
    }
}

/// What the tail bound says at the current point of an infinite ray.
pub enum Tail {
    /// Keep integrating.
    Continue,
    /// Bounds on what is left: (in-scatter per channel, optical depth per channel;
    /// `∞` where the remaining optical depth is infinite).
    Bound([f64; 3], [f64; 3]),
}

/// A distance along the ray as `anchor + offset`: the anchor is the last medium
/// boundary (or 0), so that panels far along a long ray keep their nodes exact
/// relative to the panel width.
pub type S = (f64, f64);

/// `anchor + offset`.
#[inline]
pub fn sv(p: S) -> f64 {
    p.0 + p.1
}

/// A ray through a medium, as pointwise functions of the distance s.
pub struct RayModel<'a> {
    /// Extinction μ_t(s), m⁻¹.
    pub mu_t: &'a dyn Fn(S) -> [f64; 3],
    /// Source μ_s(s)·J(s), W·m⁻³·sr⁻¹.
    pub source: &'a dyn Fn(S) -> [f64; 3],
    /// Longest panel that may start at s (the integrand changes by ≲ e across it).
    pub max_step: &'a dyn Fn(S) -> f64,
    /// Points where the integrand is not smooth, any order (outside [0, s_end] ignored).
    pub breaks: Vec<f64>,
    /// End of the ray (∞ allowed).
    pub s_end: f64,
    /// For infinite rays: bound on the rest of the integrals given (s, τ(s)).
    pub tail: &'a dyn Fn(S, &[f64; 3]) -> Tail,
    /// A bound K_c ≥ μ_s J / μ_t everywhere on the ray, so that the rest of the
    /// in-scatter integral from s is at most K_c·e^{−τ_c(s)}. Once that is below
    /// 1e-17 of the value, only the optical depth is integrated further.
    pub ratio: [f64; 3],
    /// Longest panel for the optical depth alone (μ_t changes by ≲ e across it).
    pub tau_step: &'a dyn Fn(S) -> f64,
}

/// Integrates the VRE for `m`.
pub fn integrate_vre(m: &RayModel<'_>) -> Brute {
    let outer = gl_outer();
    let inner = gl_inner();
    let mut breaks: Vec<f64> = m
        .breaks
        .iter()
        .copied()
        .filter(|b| b.is_finite() && *b > 0.0 && *b < m.s_end)
        .collect();
    breaks.sort_by(f64::total_cmp);
    breaks.dedup();
    let mut next_break = 0usize;
    let (mut anchor, mut u) = (0.0f64, 0.0f64);
    let mut tau = [0.0f64; 3];
    let mut l = [0.0f64; 3];
    let mut panels = 0usize;
    loop {
        let s = anchor + u;
        if s >= m.s_end {
            break;
        }
        if m.s_end.is_infinite()
            && let Tail::Bound(rem_l, rem_tau) = (m.tail)((anchor, u), &tau)
        {
            let l_ok = (0..3).all(|c| rem_l[c] <= 1e-17 * l[c] || rem_l[c] < 1e-300);
            let t_ok = (0..3).all(|c| rem_tau[c] == 0.0 || rem_tau[c] <= 1e-17 * tau[c] || rem_tau[c].is_infinite());
            if l_ok && t_ok {
                for c in 0..3 {
                    if rem_tau[c].is_infinite() {
                        tau[c] = f64::INFINITY;
                    }
                }
                break;
            }
        }
        while next_break < breaks.len() && breaks[next_break] <= s {
            next_break += 1;
        }
        let limit = if next_break < breaks.len() { breaks[next_break] } else { m.s_end };
        let seg_len = limit - anchor;
        let l_done = (0..3).all(|c| m.ratio[c] * (-tau[c]).exp() <= 1e-17 * l[c] || m.ratio[c] * (-tau[c]).exp() < 1e-300);
        let step = if l_done {
            (m.tau_step)((anchor, u))
        } else {
            (m.max_step)((anchor, u))
        };
        assert!(step > 0.0, "non-positive step {step} at s = {s}");
        let ub = if step >= seg_len - u { seg_len } else { u + step };
        assert!(
            ub.is_finite() && ub > u,
            "panel [{u}, {ub}] after {anchor} cannot be integrated (step {step}, limit {limit})"
        );
        let mu_t = |v: f64| (m.mu_t)((anchor, v));
        let (c, h) = (0.5 * (u + ub), 0.5 * (ub - u));
        if !l_done {
            for (x, w) in outer.x.iter().zip(&outer.w) {
                let xi = c + h * x;
                let src = (m.source)((anchor, xi));
                if src.iter().all(|v| *v == 0.0) {
                    continue;
                }
                let dt = inner.integrate(&mu_t, u, xi);
                for ch in 0..3 {
                    if src[ch] != 0.0 {
                        l[ch] += w * h * src[ch] * (-(tau[ch] + dt[ch])).exp();
                    }
                }
            }
        }
        let dt = inner.integrate(&mu_t, u, ub);
        for ch in 0..3 {
            tau[ch] += dt[ch];
        }
        if ub == seg_len {
            anchor = limit;
            u = 0.0;
        } else {
            u = ub;
        }
        panels += 1;
        assert!(panels < 20_000_000, "brute force did not finish: s = {s}, tau = {tau:?}");
    }
    Brute { l, tau, panels }
}

// ------------------------------------------------------------------ height fog (Ishiyama)

/// Ishiyama's height fog, parameters as in the paper (eqs 7–11).
#[derive(Debug, Clone, Copy)]
pub struct HeightFogModel {
    /// Scale height H, m.
    pub h: f64,
    /// Reference height, m.
    pub z_ref: f64,
    /// β_sR per channel at the reference height.
    pub beta_rs: [f64; 3],
    /// β_sM per channel.
    pub beta_ms: [f64; 3],
    /// β_t (Rayleigh + Mie, scattering + absorption) per channel.
    pub beta_t: [f64; 3],
    /// Mie phase function.
    pub mie_phase: Phase,
}

impl HeightFogModel {
    /// ln ρ at height z.
    fn ln_rho(&self, z: f64) -> f64 {
        -(z - self.z_ref) / self.h
    }

    /// Σ_j β_sj (p_j E + L_amb) at the reference density (eq 12's bracket).
    pub fn source_ref(&self, dir: DVec3, lights: &Lights) -> [f64; 3] {
        let mut s = [0.0; 3];
        for c in 0..3 {
            s[c] = (self.beta_rs[c] + self.beta_ms[c]) * lights.ambient[c];
        }
        for sun in &lights.suns {
            let mu = dir.dot(sun.to_sun);
            let (pr, pm) = (Phase::Rayleigh.eval(mu), self.mie_phase.eval(mu));
            for c in 0..3 {
                s[c] += (self.beta_rs[c] * pr + self.beta_ms[c] * pm) * sun.e[c];
            }
        }
        s
    }

    /// Brute-force L and τ along `origin + s·dir`, `s ∈ [0, s_max]`.
    pub fn brute(&self, origin: DVec3, dir: DVec3, s_max: f64, lights: &Lights) -> Brute {
        self.brute_with_source(origin, dir, s_max, self.source_ref(dir, lights))
    }

    /// As [`Self::brute`] with the bracket of eq 12 at the reference density given.
    pub fn brute_with_source(&self, origin: DVec3, dir: DVec3, s_max: f64, src_ref: [f64; 3]) -> Brute {
        let (z0, wz) = (origin.z, dir.z);
        let bt = self.beta_t;
        let bt_max = bt.iter().fold(0.0f64, |a, b| a.max(*b));
        let ln_bt_max = bt_max.ln();
        let ln_rho = |p: S| self.ln_rho((z0 + wz * p.0) + wz * p.1);
        let mu_t = |s: S| {
            let r = ln_rho(s).exp();
            bt.map(|b| if b == 0.0 { 0.0 } else { b * r })
        };
        let source = |s: S| {
            let r = ln_rho(s).exp();
            src_ref.map(|v| if v == 0.0 { 0.0 } else { v * r })
        };
        let h = self.h;
        let max_step = |s: S| {
            let ln_mu = ln_bt_max + ln_rho(s);
            let geo = if wz == 0.0 { f64::INFINITY } else { 0.5 * h / wz.abs() };
            if wz < 0.0 && ln_mu < -700.0 {
                // Density below e^-700 of anything that matters: skip to where it reaches e^-700
                // (the skipped part contributes < e^-700·H/|ω_z|).
                return ((-700.0 - ln_mu) * h / wz.abs()).max(geo);
            }
            let opt = 0.5 / ln_mu.exp();
            geo.min(opt)
        };
        let tail = |s: S, tau: &[f64; 3]| {
            let r = ln_rho(s).exp();
            let mut rem_l = [0.0; 3];
            let mut rem_t = [0.0; 3];
            for c in 0..3 {
                if bt[c] == 0.0 {
                    continue;
                }
                let e = (-tau[c]).exp();
                // ∫_s^∞ μ_t e^{-τ} ≤ e^{-τ(s)}, and μ_s J / μ_t is constant along the ray.
                let mut bound = src_ref[c] / bt[c] * e;
                if wz > 0.0 {
                    // Density falls as e^{-ω_z t/H}: ∫_s^∞ ρ ≤ ρ(s) H/ω_z.
                    let rest = r * h / wz;
                    bound = bound.min(src_ref[c] * rest * e);
                    rem_t[c] = bt[c] * rest;
                } else {
                    rem_t[c] = f64::INFINITY;
                }
                rem_l[c] = bound;
            }
            Tail::Bound(rem_l, rem_t)
        };
        integrate_vre(&RayModel {
            mu_t: &mu_t,
            source: &source,
            max_step: &max_step,
            breaks: vec![],
            s_end: s_max,
            tail: &tail,
            ratio: std::array::from_fn(|c| if bt[c] == 0.0 { 0.0 } else { src_ref[c] / bt[c] }),
            tau_step: &|_| if wz == 0.0 { f64::INFINITY } else { 0.5 * h / wz.abs() },
        })
    }

    /// The library's prepared medium.
    pub fn lib(&self) -> tyndall_core::medium::height_fog::HeightFog<3> {
        tyndall_core::medium::height_fog::HeightFog {
            name: "hf".into(),
            scale_height: self.h,
            reference_height: self.z_ref,
            rayleigh_scattering: self.beta_rs,
            mie_scattering: self.beta_ms,
            extinction: self.beta_t,
            mie_phase: self.mie_phase.lib(),
        }
    }

    /// Scene JSON of the medium (absorption split evenly between the components).
    pub fn json(&self) -> String {
        let ra: [f64; 3] = std::array::from_fn(|c| 0.5 * (self.beta_t[c] - self.beta_rs[c] - self.beta_ms[c]));
        let ma: [f64; 3] = std::array::from_fn(|c| self.beta_t[c] - self.beta_rs[c] - self.beta_ms[c] - ra[c]);
        format!(
            r#"{{"type":"height_fog","scale_height_m":{:?},"reference_height_m":{:?},
              "rayleigh":{{"scattering":{},"absorption":{}}},
              "mie":{{"scattering":{},"absorption":{},"phase":{}}}}}"#,
            self.h,
            self.z_ref,
            arr(self.beta_rs),
            arr(ra),
            arr(self.beta_ms),
            arr(ma),
            self.mie_phase.json()
        )
    }
}

/// `[a,b,c]` with round-trip formatting.
pub fn arr(v: [f64; 3]) -> String {
    format!("[{:?},{:?},{:?}]", v[0], v[1], v[2])
}

// ------------------------------------------------------------------ fog layer (Klassen)

/// Klassen's uniform fog layer on a flat earth.
#[derive(Debug, Clone, Copy)]
pub struct FogLayerModel {
    /// Ground (fog bottom), m.
    pub ground: f64,
    /// Fog top, m.
    pub top: f64,
    /// Fog extinction β_ex,p per channel.
    pub fog_ext: [f64; 3],
    /// Air extinction β_ex,m inside the layer per channel.
    pub air_ext: [f64; 3],
    /// Single-scattering albedo of the droplets.
    pub albedo: f64,
    /// Droplet phase function.
    pub phase: Phase,
    /// `true`: d₂(z) = (z_top − z)/sin φ; `false`: (z_top − z_ground)/sin φ (eq 3.11).
    pub per_point: bool,
    /// Minimum sun elevation for direct light, degrees.
    pub min_sun_deg: f64,
}

impl FogLayerModel {
    /// B = β_ex,m + β_ex,p (eq 3.17).
    pub fn b(&self) -> [f64; 3] {
        std::array::from_fn(|c| self.fog_ext[c] + self.air_ext[c])
    }
    /// σ_s of the droplets.
    pub fn sigma_s(&self) -> [f64; 3] {
        self.fog_ext.map(|v| v * self.albedo)
    }
    /// Whether a sun lights the layer directly.
    pub fn direct(&self, to_sun: DVec3) -> bool {
        to_sun.z > 0.0 && to_sun.z >= self.min_sun_deg.to_radians().sin()
    }
    /// Sun path d₂ through the fog to height z (inside the layer).
    pub fn d2(&self, z: f64, sin_phi: f64) -> f64 {
        if self.per_point {
            (self.top - z) / sin_phi
        } else {
            (self.top - self.ground) / sin_phi
        }
    }
    fn inside(&self, z: f64) -> bool {
        z >= self.ground && z <= self.top
    }

    /// Brute-force L and τ along `origin + s·dir`, `s ∈ [0, s_max]` (eq 1.11 with
    /// d₁ = 0: the sun irradiance is given at the fog top).
    pub fn brute(&self, origin: DVec3, dir: DVec3, s_max: f64, lights: &Lights) -> Brute {
        let (z0, wz) = (origin.z, dir.z);
        let b = self.b();
        let b_max = b.iter().fold(0.0f64, |a, x| a.max(*x));
        let sig = self.sigma_s();
        let suns: Vec<(f64, f64, [f64; 3])> = lights
            .suns
            .iter()
            .filter(|s| self.direct(s.to_sun))
            .map(|s| (s.to_sun.z, self.phase.eval(dir.dot(s.to_sun)), s.e))
            .collect();
        let z_at = |p: S| (z0 + wz * p.0) + wz * p.1;
        let mu_t = |s: S| if self.inside(z_at(s)) { b } else { [0.0; 3] };
        let source = |s: S| {
            let z = z_at(s);
            if !self.inside(z) {
                return [0.0; 3];
            }
            let mut j = lights.ambient;
            for (sin_phi, p, e) in &suns {
                let d2 = self.d2(z, *sin_phi);
                for c in 0..3 {
                    j[c] += p * e[c] * (-b[c] * d2).exp();
                }
            }
            std::array::from_fn(|c| sig[c] * j[c])
        };
        let mut breaks = vec![];
        if wz != 0.0 {
            breaks.push((self.ground - z0) / wz);
            breaks.push((self.top - z0) / wz);
        }
        let max_step = |s: S| {
            if self.inside(z_at(s)) && b_max > 0.0 {
                0.5 / b_max
            } else {
                f64::INFINITY
            }
        };
        let j_max: [f64; 3] = std::array::from_fn(|c| lights.ambient[c] + suns.iter().map(|(_, p, e)| p * e[c]).sum::<f64>());
        // Past the last crossing of the slab boundaries nothing is left (decided on s,
        // not on a rounded z).
        let s_exit = if wz == 0.0 {
            if self.inside(z0) { f64::INFINITY } else { 0.0 }
        } else {
            ((self.ground - z0) / wz).max((self.top - z0) / wz)
        };
        let tail = |s: S, tau: &[f64; 3]| {
            if sv(s) >= s_exit {
                return Tail::Bound([0.0; 3], [0.0; 3]);
            }
            if wz == 0.0 {
                let rem_l = std::array::from_fn(|c| {
                    if b[c] == 0.0 {
                        0.0
                    } else {
                        sig[c] * j_max[c] / b[c] * (-tau[c]).exp()
                    }
                });
                let rem_t = b.map(|v| if v == 0.0 { 0.0 } else { f64::INFINITY });
                return Tail::Bound(rem_l, rem_t);
            }
            Tail::Continue
        };
        integrate_vre(&RayModel {
            mu_t: &mu_t,
            source: &source,
            max_step: &max_step,
            breaks,
            s_end: s_max,
            tail: &tail,
            ratio: std::array::from_fn(|c| if b[c] == 0.0 { 0.0 } else { sig[c] * j_max[c] / b[c] }),
            tau_step: &|_| f64::INFINITY,
        })
    }

    /// Sun transmittance at a point in the layer, independent (eq 3.13 with d₂ of the model).
    pub fn sun_t(&self, z: f64, to_sun: DVec3) -> [f64; 3] {
        if !self.direct(to_sun) {
            return [0.0; 3];
        }
        let d = self.d2(z, to_sun.z);
        self.b().map(|v| (-v * d).exp())
    }

    /// Library struct.
    pub fn lib(&self) -> tyndall_core::medium::fog_layer::FogLayer<3> {
        tyndall_core::medium::fog_layer::FogLayer {
            name: "fl".into(),
            ground: self.ground,
            top: self.top,
            extinction: self.b(),
            scattering: self.sigma_s(),
            phase: self.phase.lib(),
            sun_path: if self.per_point {
                tyndall_core::scene::SunPath::PerPoint
            } else {
                tyndall_core::scene::SunPath::FullLayer
            },
            min_sin_elevation: self.min_sun_deg.to_radians().sin(),
        }
    }

    /// Scene JSON.
    pub fn json(&self) -> String {
        format!(
            r#"{{"type":"fog_layer","ground_height_m":{:?},"top_height_m":{:?},"extinction":{},"air_extinction":{},
               "single_scattering_albedo":{:?},"phase":{},"sun_path":"{}","min_sun_elevation_deg":{:?}}}"#,
            self.ground,
            self.top,
            arr(self.fog_ext),
            arr(self.air_ext),
            self.albedo,
            self.phase.json(),
            if self.per_point { "per_point" } else { "full_layer" },
            self.min_sun_deg
        )
    }
}

// ------------------------------------------------------------------ homogeneous (world, box)

/// Homogeneous medium, world or axis-aligned box.
#[derive(Debug, Clone, Copy)]
pub struct HomogeneousModel {
    /// σ_s per channel.
    pub sigma_s: [f64; 3],
    /// σ_t per channel.
    pub sigma_t: [f64; 3],
    /// Phase function.
    pub phase: Phase,
    /// Box corners, or `None` for the world.
    pub bounds: Option<(DVec3, DVec3)>,
    /// The box turned about its centre: unit axis and angle, rad (box → world).
    pub turn: Option<(DVec3, f64)>,
}

/// `v` turned by `angle` about the unit `axis` (Rodrigues' formula; written
/// out here so that the model does not share the library's quaternion code).
pub fn rodrigues(v: DVec3, axis: DVec3, angle: f64) -> DVec3 {
    let (s, c) = angle.sin_cos();
    v * c + axis.cross(v) * s + axis * (axis.dot(v) * (1.0 - c))
}

/// Exit distance from a point inside a box along `d`, and the axis of the exit face.
fn box_exit(p: DVec3, d: DVec3, lo: DVec3, hi: DVec3) -> (f64, usize) {
    let mut best = (f64::INFINITY, 3usize);
    for i in 0..3 {
        let t = if d[i] > 0.0 {
            (hi[i] - p[i]) / d[i]
        } else if d[i] < 0.0 {
            (lo[i] - p[i]) / d[i]
        } else {
            continue;
        };
        if t < best.0 {
            best = (t, i);
        }
    }
    (best.0.max(0.0), best.1)
}

/// Where a ray from `o` along `d` is inside the closed box, as (entry, exit) parameters.
pub fn box_span(o: DVec3, d: DVec3, lo: DVec3, hi: DVec3) -> Option<(f64, f64)> {
    let (mut a, mut b) = (f64::NEG_INFINITY, f64::INFINITY);
    for i in 0..3 {
        if d[i] == 0.0 {
            if o[i] < lo[i] || o[i] > hi[i] {
                return None;
            }
            continue;
        }
        let (t0, t1) = ((lo[i] - o[i]) / d[i], (hi[i] - o[i]) / d[i]);
        a = a.max(t0.min(t1));
        b = b.min(t0.max(t1));
    }
    if a <= b { Some((a, b)) } else { None }
}

impl HomogeneousModel {
    /// A world point in the box's frame (turned back about the centre).
    fn box_point(&self, p: DVec3) -> DVec3 {
        match (self.bounds, self.turn) {
            (Some((lo, hi)), Some((axis, angle))) => {
                let c = 0.5 * (lo + hi);
                c + rodrigues(p - c, axis, -angle)
            }
            _ => p,
        }
    }

    /// A world direction in the box's frame.
    fn box_dir(&self, d: DVec3) -> DVec3 {
        match self.turn {
            Some((axis, angle)) => rodrigues(d, axis, -angle),
            None => d,
        }
    }

    fn inside(&self, p: DVec3) -> bool {
        match self.bounds {
            None => true,
            Some((lo, hi)) => {
                // A turned box's faces are found to within rounding: a ray's
                // entry point, where the step size is chosen, must count as
                // inside (the faces themselves have measure zero).
                let slack = if self.turn.is_some() { 1e-9 * (hi - lo).max_element() } else { 0.0 };
                let q = self.box_point(p);
                q.cmpge(lo - slack).all() && q.cmple(hi + slack).all()
            }
        }
    }

    /// Brute-force L and τ.
    pub fn brute(&self, origin: DVec3, dir: DVec3, s_max: f64, lights: &Lights) -> Brute {
        let st = self.sigma_t;
        let ss = self.sigma_s;
        let st_max = st.iter().fold(0.0f64, |a, x| a.max(*x));
        let at = |p: S| (origin + dir * p.0) + dir * p.1;
        let suns: Vec<(DVec3, f64, [f64; 3])> = lights
            .suns
            .iter()
            .map(|s| (s.to_sun, self.phase.eval(dir.dot(s.to_sun)), s.e))
            .collect();
        let mu_t = |s: S| if self.inside(at(s)) { st } else { [0.0; 3] };
        let source = |s: S| {
            let p = at(s);
            if !self.inside(p) {
                return [0.0; 3];
            }
            let mut j = lights.ambient;
            for (to_sun, ph, e) in &suns {
                let d = match self.bounds {
                    None => 0.0, // world: sun unattenuated (Ishiyama eq 11)
                    Some((lo, hi)) => box_exit(self.box_point(p), self.box_dir(*to_sun), lo, hi).0,
                };
                for c in 0..3 {
                    j[c] += ph * e[c] * (-st[c] * d).exp();
                }
            }
            std::array::from_fn(|c| ss[c] * j[c])
        };
        let mut breaks = vec![];
        let mut span_end = f64::INFINITY;
        if let Some((lo, hi)) = self.bounds {
            if let Some((a, b)) = box_span(self.box_point(origin), self.box_dir(dir), lo, hi) {
                breaks.push(a);
                breaks.push(b);
                span_end = b;
                // Kinks of the sun path d(s): where the exit face changes. The exit
                // distance is a minimum of linear functions (concave), so each face
                // owns one interval; bisection finds the switch points.
                let (s0, s1) = (a.max(0.0), b.min(s_max));
                if s1 > s0 {
                    for (to_sun, _, _) in &suns {
                        let face = |s: f64| box_exit(self.box_point(at((0.0, s))), self.box_dir(*to_sun), lo, hi).1;
                        find_switches(&face, s0, s1, face(s0), face(s1), &mut breaks);
                    }
                }
            } else {
                span_end = -1.0;
            }
        }
        let max_step = |s: S| {
            if self.inside(at(s)) && st_max > 0.0 {
                0.5 / st_max
            } else {
                f64::INFINITY
            }
        };
        let j_max: [f64; 3] = std::array::from_fn(|c| lights.ambient[c] + suns.iter().map(|(_, p, e)| p * e[c]).sum::<f64>());
        let tail = |s: S, tau: &[f64; 3]| {
            if sv(s) >= span_end {
                return Tail::Bound([0.0; 3], [0.0; 3]);
            }
            if self.bounds.is_none() {
                let rem_l = std::array::from_fn(|c| {
                    if st[c] == 0.0 {
                        0.0
                    } else {
                        ss[c] * j_max[c] / st[c] * (-tau[c]).exp()
                    }
                });
                let rem_t = st.map(|v| if v == 0.0 { 0.0 } else { f64::INFINITY });
                return Tail::Bound(rem_l, rem_t);
            }
            Tail::Continue
        };
        integrate_vre(&RayModel {
            mu_t: &mu_t,
            source: &source,
            max_step: &max_step,
            breaks,
            s_end: s_max,
            tail: &tail,
            ratio: std::array::from_fn(|c| if st[c] == 0.0 { 0.0 } else { ss[c] * j_max[c] / st[c] }),
            tau_step: &|_| f64::INFINITY,
        })
    }

    /// Library struct.
    pub fn lib(&self) -> tyndall_core::medium::homogeneous::Homogeneous<3> {
        tyndall_core::medium::homogeneous::Homogeneous {
            name: "h".into(),
            scattering: self.sigma_s,
            extinction: self.sigma_t,
            phase: self.phase.lib(),
            bounds: self.bounds.map(|(lo, hi)| {
                tyndall_core::medium::homogeneous::MediumBox::new(
                    lo,
                    hi,
                    self.turn.map(|(axis, angle)| glam::DQuat::from_axis_angle(axis, angle)),
                )
            }),
        }
    }

    /// Scene JSON.
    pub fn json(&self) -> String {
        let abs: [f64; 3] = std::array::from_fn(|c| self.sigma_t[c] - self.sigma_s[c]);
        let bounds = match self.bounds {
            None => r#""world""#.to_string(),
            Some((lo, hi)) => {
                let turn = match self.turn {
                    Some((axis, angle)) => {
                        let (s, c) = (0.5 * angle).sin_cos();
                        format!(r#","rotation_wxyz":[{c:e},{:e},{:e},{:e}]"#, s * axis.x, s * axis.y, s * axis.z)
                    }
                    None => String::new(),
                };
                format!(r#"{{"box":{{"min":{},"max":{}{turn}}}}}"#, arr(lo.to_array()), arr(hi.to_array()))
            }
        };
        format!(
            r#"{{"type":"homogeneous","scattering":{},"absorption":{},"phase":{},"bounds":{}}}"#,
            arr(self.sigma_s),
            arr(abs),
            self.phase.json(),
            bounds
        )
    }
}

fn find_switches(face: &dyn Fn(f64) -> usize, a: f64, b: f64, fa: usize, fb: usize, out: &mut Vec<f64>) {
    if fa == fb {
        return;
    }
    if b - a <= 1e-14 * a.abs().max(b.abs()).max(1e-300) {
        out.push(0.5 * (a + b));
        return;
    }
    let m = 0.5 * (a + b);
    let fm = face(m);
    find_switches(face, a, m, fa, fm, out);
    find_switches(face, m, b, fm, fb, out);
}

// ------------------------------------------------------------------ comparison bookkeeping

/// Relative difference `|a − b| / |b|`; `0` when both are 0.
pub fn rel(a: f64, b: f64) -> f64 {
    if a == b { 0.0 } else { (a - b).abs() / b.abs() }
}

/// Tracks comparisons and the largest relative difference.
#[derive(Debug, Default)]
pub struct Stats {
    /// Comparisons made.
    pub n: usize,
    /// Largest relative difference.
    pub max_rel: f64,
    /// Where it was.
    pub worst: String,
    /// Failures (messages).
    pub failures: Vec<String>,
    /// Per quantity (L, T, tau, T_sun, depth): comparisons and largest relative difference.
    pub kinds: std::collections::BTreeMap<&'static str, (usize, f64)>,
}

impl Stats {
    /// Compares `got` against the reference `want` to relative `tol`; values whose
    /// reference is exactly 0 or below `floor` in magnitude must be below `floor` too.
    pub fn check(&mut self, got: f64, want: f64, tol: f64, floor: f64, what: impl Fn() -> String) {
        self.n += 1;
        if !got.is_finite() && got != want {
            self.failures.push(format!("{}: got {got}, want {want}", what()));
            return;
        }
        if want.abs() < floor || want == 0.0 {
            if got.abs() > floor && got != want {
                self.failures
                    .push(format!("{}: got {got:e}, want {want:e} (below floor {floor:e})", what()));
            }
            return;
        }
        let r = rel(got, want);
        let w = what();
        let kind = if w.contains("T_sun[") || w.contains("sun transmittance") {
            "T_sun"
        } else if w.contains("tau[") || w.contains("τ[") {
            "tau"
        } else if w.contains(" T[") {
            "T"
        } else if w.contains(" L[") {
            "L"
        } else if w.contains("depth") {
            "depth"
        } else {
            "value"
        };
        let k = self.kinds.entry(kind).or_insert((0, 0.0));
        k.0 += 1;
        k.1 = k.1.max(r);
        if r > self.max_rel {
            self.max_rel = r;
            self.worst = format!("{}: got {got:e}, want {want:e}", what());
        }
        if r.is_nan() || r > tol {
            self.failures.push(format!("{}: got {got:e}, want {want:e}, rel {r:e}", what()));
        }
    }

    /// Adds another set of comparisons.
    pub fn merge(&mut self, o: Stats) {
        self.n += o.n;
        if o.max_rel > self.max_rel {
            self.max_rel = o.max_rel;
            self.worst = o.worst;
        }
        self.failures.extend(o.failures);
        for (k, (n, m)) in o.kinds {
            let e = self.kinds.entry(k).or_insert((0, 0.0));
            e.0 += n;
            e.1 = e.1.max(m);
        }
    }

    /// Panics with the first failures, otherwise prints the summary.
    pub fn finish(&self, name: &str) {
        eprintln!(
            "[{name}] {} comparisons, max relative difference {:e} at {}",
            self.n, self.max_rel, self.worst
        );
        for (k, (n, m)) in &self.kinds {
            eprintln!("    {k}: {n} relative comparisons, max {m:e}");
        }
        if !self.failures.is_empty() {
            let shown: Vec<&String> = self.failures.iter().take(25).collect();
            panic!("[{name}] {} of {} comparisons failed:\n{:#?}", self.failures.len(), self.n, shown);
        }
    }
}

/// A large square ground quad at height z (two triangles), as a `meshes` entry.
pub fn ground_mesh_json(z: f64, half: f64) -> String {
    format!(
        r#"{{"name":"ground","positions":[[{m:?},{m:?},{z:?}],[{p:?},{m:?},{z:?}],[{p:?},{p:?},{z:?}],[{m:?},{p:?},{z:?}]],"triangles":[[0,1,2],[0,2,3]]}}"#,
        m = -half,
        p = half,
        z = z
    )
}
