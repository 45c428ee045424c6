//! Participating media, prepared for rendering.
//!
//! Every medium here has a closed form for its optical depth along a straight
//! ray and for the single-scattered radiance of sun and ambient light when it
//! is alone on the ray (derivations in the submodules). When several media
//! overlap on a ray the renderer integrates the sum numerically with the
//! pointwise [`PreparedMedium::extinction_and_source`] and the closed-form
//! optical depths, with an error estimate (see `render`).
//!
//! Two media of Nishita et al. 1987 §4 have no closed form for the sun's
//! in-scatter (the sun path crosses a curved boundary): the wavy dry-ice
//! layer ([`height_field_layer`]) and the smoke ellipsoid ([`ellipsoid`]).
//! Their optical depths are exact; their `closed_form` integrates the sun
//! term by adaptive Gauss–Kronrod and returns its error estimate.
//!
//! All quantities are per channel: `C = 3` (linear Rec.709) or
//! `C = SPECTRAL_SAMPLES` (380–780 nm at 5 nm); the caller chooses.

pub mod ellipsoid;
pub mod fog_layer;
pub mod height_field_layer;
pub mod height_fog;
pub mod homogeneous;
pub mod phase;

use glam::DVec3;

/// A sun reduced to what the media need: direction and irradiance per channel.
#[derive(Debug, Clone)]
pub struct SunSource<const C: usize> {
    /// Unit vector from the scene towards the sun.
    pub to_sun: DVec3,
    /// Irradiance on a surface facing the sun, W·m⁻² per channel.
    pub irradiance: [f64; C],
    /// Disc-averaged phase tables for the phase functions where treating this
    /// sun as a point would exceed the tolerance; empty otherwise.
    pub disc: std::sync::Arc<Vec<phase::DiscPhase>>,
}

impl<const C: usize> SunSource<C> {
    /// A sun treated as one direction.
    pub fn point(to_sun: DVec3, irradiance: [f64; C]) -> Self {
        SunSource {
            to_sun,
            irradiance,
            disc: Default::default(),
        }
    }

    /// The phase function `p` for light from this sun scattered into the view
    /// direction `view_dir`: disc-averaged where tabulated, else a point evaluation.
    #[inline]
    pub fn phase(&self, p: &phase::PhaseFunction, view_dir: DVec3) -> f64 {
        let mu = view_dir.dot(self.to_sun);
        if self.disc.is_empty() {
            return p.eval(mu);
        }
        match self.disc.iter().find(|d| d.phase == *p) {
            Some(d) => d.eval(mu),
            None => p.eval(mu),
        }
    }
}

/// The lights that media scatter, per channel.
#[derive(Debug, Clone)]
pub struct LightSet<const C: usize> {
    /// Directional lights.
    pub suns: Vec<SunSource<C>>,
    /// Sum of uniform ambient radiances, W·m⁻²·sr⁻¹ per channel.
    pub ambient: [f64; C],
}

/// A view ray: origin, unit direction, and the range `[0, s_max]` it covers.
#[derive(Debug, Clone, Copy)]
pub struct ViewRay {
    /// Origin (the eye, or the clip-start point), m.
    pub origin: DVec3,
    /// Unit direction.
    pub dir: DVec3,
    /// End of the ray: first surface, clip end, or `f64::INFINITY`.
    pub s_max: f64,
}

/// The medium's contribution to one view ray, alone.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RayResult<const C: usize> {
    /// In-scattered radiance, W·m⁻²·sr⁻¹ per channel.
    pub inscatter: [f64; C],
    /// Transmittance along the ray, per channel.
    pub transmittance: [f64; C],
    /// Transmittance of sunlight (first sun) to the end point of the ray.
    pub sun_transmittance: [f64; C],
    /// Absolute error bound on `inscatter` from floating-point rounding of the closed form.
    pub error: [f64; C],
    /// The same bound relative to `inscatter` (closed forms: a constant multiple of ε).
    pub rel_bound: f64,
}

impl<const C: usize> RayResult<C> {
    /// No medium: L = 0, T = 1.
    pub fn vacuum() -> Self {
        RayResult {
            inscatter: [0.0; C],
            transmittance: [1.0; C],
            sun_transmittance: [1.0; C],
            error: [0.0; C],
            rel_bound: 0.0,
        }
    }
}

/// Where a light path goes from a point `x(t)` of a view ray, for
/// [`PreparedMedium::light_path_kinks`].
pub enum LightPath<'a> {
    /// To a point light at this position.
    Point(DVec3),
    /// Along the unit `to_light` to a window's plane; `end(t)` is the path's
    /// end there for the view ray's `t` (affine in `t`).
    Parallel {
        /// Unit direction towards the light.
        to_light: DVec3,
        /// The path's end on the window's plane.
        end: &'a dyn Fn(f64) -> DVec3,
    },
}

/// A medium with its coefficients resolved to `C` channels.
#[derive(Debug, Clone)]
pub enum PreparedMedium<const C: usize> {
    /// Homogeneous, world or box.
    Homogeneous(homogeneous::Homogeneous<C>),
    /// Ishiyama's height fog.
    HeightFog(height_fog::HeightFog<C>),
    /// Klassen's fog layer.
    FogLayer(fog_layer::FogLayer<C>),
    /// Nishita's dense layer under a sine-wave height field (dry ice).
    HeightFieldLayer(height_field_layer::HeightFieldLayer<C>),
    /// Nishita's constant-density smoke ellipsoid.
    Ellipsoid(ellipsoid::Ellipsoid<C>),
}

impl<const C: usize> PreparedMedium<C> {
    /// The sub-range of `[0, ray.s_max]` where the medium is non-zero, if any.
    pub fn segment(&self, ray: &ViewRay) -> Option<(f64, f64)> {
        match self {
            PreparedMedium::Homogeneous(m) => m.segment(ray),
            PreparedMedium::HeightFog(_) => Some((0.0, ray.s_max)),
            PreparedMedium::FogLayer(m) => m.segment(ray),
            PreparedMedium::HeightFieldLayer(m) => m.segment(ray),
            PreparedMedium::Ellipsoid(m) => m.segment(ray),
        }
    }

    /// Closed-form single scattering of this medium alone on `ray`.
    pub fn closed_form(&self, ray: &ViewRay, lights: &LightSet<C>) -> RayResult<C> {
        match self {
            PreparedMedium::Homogeneous(m) => m.closed_form(ray, lights),
            PreparedMedium::HeightFog(m) => m.closed_form(ray, lights),
            PreparedMedium::FogLayer(m) => m.closed_form(ray, lights),
            PreparedMedium::HeightFieldLayer(m) => m.closed_form(ray, lights),
            PreparedMedium::Ellipsoid(m) => m.closed_form(ray, lights),
        }
    }

    /// Optical depth from the ray origin to distance `s` (closed form), per channel.
    pub fn optical_depth(&self, ray: &ViewRay, s: f64) -> [f64; C] {
        match self {
            PreparedMedium::Homogeneous(m) => m.optical_depth(ray, s),
            PreparedMedium::HeightFog(m) => m.optical_depth(ray, s),
            PreparedMedium::FogLayer(m) => m.optical_depth(ray, s),
            PreparedMedium::HeightFieldLayer(m) => m.optical_depth(ray, s),
            PreparedMedium::Ellipsoid(m) => m.optical_depth(ray, s),
        }
    }

    /// Source term at distance `s`: σ_s(x)·(Σ p·E·T_sun + ambient), W·m⁻³·sr⁻¹ per channel.
    pub fn source(&self, ray: &ViewRay, s: f64, lights: &LightSet<C>) -> [f64; C] {
        match self {
            PreparedMedium::Homogeneous(m) => m.source(ray, s, lights),
            PreparedMedium::HeightFog(m) => m.source(ray, s, lights),
            PreparedMedium::FogLayer(m) => m.source(ray, s, lights),
            PreparedMedium::HeightFieldLayer(m) => m.source(ray, s, lights),
            PreparedMedium::Ellipsoid(m) => m.source(ray, s, lights),
        }
    }

    /// `Σ σ_s(p)·phase(μ)` at the point `p`, m⁻¹·sr⁻¹ per channel, for light
    /// scattered by the cosine `mu` (μ = 1: forward). Zero outside the medium.
    pub fn scattering_phase_at(&self, p: DVec3, mu: f64) -> [f64; C] {
        match self {
            PreparedMedium::Homogeneous(m) => {
                if let Some(b) = m.bounds
                    && !b.contains(p)
                {
                    return [0.0; C];
                }
                let ph = m.phase.eval(mu);
                m.scattering.map(|s| s * ph)
            }
            PreparedMedium::HeightFog(m) => {
                let x = -(p.z - m.reference_height) / m.scale_height;
                let rho = x.exp();
                let (pr, pm) = (phase::PhaseFunction::Rayleigh.eval(mu), m.mie_phase.eval(mu));
                let mut out = [0.0; C];
                for (c, o) in out.iter_mut().enumerate() {
                    let v = m.rayleigh_scattering[c] * pr + m.mie_scattering[c] * pm;
                    *o = if v == 0.0 { 0.0 } else { v * rho };
                }
                out
            }
            PreparedMedium::FogLayer(m) => {
                if p.z < m.ground || p.z > m.top {
                    return [0.0; C];
                }
                let ph = m.phase.eval(mu);
                m.scattering.map(|s| s * ph)
            }
            PreparedMedium::HeightFieldLayer(m) => m.scattering_phase_at(p, mu),
            PreparedMedium::Ellipsoid(m) => m.scattering_phase_at(p, mu),
        }
    }

    /// Appends the parameters in `(0, s_max)` where the medium's density jumps
    /// along `ray` (box faces, ellipsoid surface, the height-field boundary,
    /// fog-layer planes), so that quadratures can split there.
    pub fn breakpoints(&self, ray: &ViewRay, out: &mut Vec<f64>) {
        match self {
            PreparedMedium::HeightFog(_) => {}
            PreparedMedium::HeightFieldLayer(m) => {
                let pieces = m.pieces(ray.origin, ray.dir, 0.0, ray.s_max);
                for p in pieces.iter().skip(1) {
                    out.push(p.t0);
                }
            }
            _ => {
                if let Some((a, b)) = self.segment(ray) {
                    for t in [a, b] {
                        if t > 0.0 && t < ray.s_max {
                            out.push(t);
                        }
                    }
                }
            }
        }
    }

    /// Whether the path from some point of `o + t·d`, `t ∈ [a, b]`, to the
    /// point light at `light` may graze the medium's boundary where no
    /// [`Self::light_path_kinks`] marks it: a height-field layer's crests
    /// ([`height_field_layer::HeightFieldLayer::light_path_may_graze`]).
    pub fn light_path_may_graze(&self, o: DVec3, d: DVec3, a: f64, b: f64, light: DVec3) -> bool {
        matches!(self, PreparedMedium::HeightFieldLayer(m) if m.light_path_may_graze(o, d, a, b, light))
    }

    /// Appends the parameters where the optical depth of the light path from
    /// `x(t)` on `ray` kinks as `t` moves (see [`LightPath`]): a box that does
    /// not hold a point light where the path passes its corners, an
    /// ellipsoid where the path turns tangent to it. A fog layer's planes
    /// give kinks only where `x(t)` crosses them (the view ray's own
    /// breakpoints). A height-field layer's path can graze its waves; those
    /// kinks are not listed here: where a path may graze, the stage
    /// integral cuts its windows where the path's crossings of the boundary
    /// change (`integrate_adaptive_cut_at_changes_certified`).
    pub fn light_path_kinks(&self, ray: &ViewRay, light: &LightPath<'_>, out: &mut Vec<f64>) {
        match (self, light) {
            (PreparedMedium::Homogeneous(m), LightPath::Point(l)) => {
                // Also for a box that holds the light: from a point outside it, the
                // light path leaves the box through a face, and where it passes a
                // corner of the section the length inside kinks (a lamp in a box
                // under world haze: 54 of 576 pixels up to 200× outside their
                // estimates at tolerance 1e-6 without these cuts).
                if let Some(b) = m.bounds {
                    b.light_path_kinks(ray.origin, ray.dir, *l, out);
                }
            }
            (PreparedMedium::Homogeneous(m), LightPath::Parallel { to_light, end }) => {
                if let Some(b) = m.bounds {
                    b.parallel_path_kinks(ray.origin, ray.dir, *to_light, end, out);
                }
            }
            (PreparedMedium::Ellipsoid(e), LightPath::Point(l)) if !e.contains(*l) => {
                e.light_path_kinks(ray.origin, ray.dir, *l, false, out);
            }
            (PreparedMedium::Ellipsoid(e), LightPath::Parallel { to_light, .. }) => {
                e.light_path_kinks(ray.origin, ray.dir, *to_light, true, out);
            }
            _ => {}
        }
    }

    /// Optical depth of the straight segment from `a` to `b`, per channel.
    pub fn optical_depth_between(&self, a: DVec3, b: DVec3) -> [f64; C] {
        match self {
            // Not through `optical_depth`: that caches the crossings of view rays.
            PreparedMedium::HeightFieldLayer(m) => return m.optical_depth_between(a, b),
            PreparedMedium::Ellipsoid(m) => return m.optical_depth_between(a, b),
            _ => {}
        }
        let v = b - a;
        let len = v.length();
        if len.is_nan() || len <= 0.0 {
            return [0.0; C];
        }
        let ray = ViewRay {
            origin: a,
            dir: v / len,
            s_max: len,
        };
        self.optical_depth(&ray, len)
    }

    /// Transmittance of sunlight from direction `to_sun` to point `p`, per channel.
    pub fn sun_transmittance_at(&self, p: DVec3, to_sun: DVec3) -> [f64; C] {
        match self {
            PreparedMedium::Homogeneous(m) => m.sun_transmittance_at(p, to_sun),
            PreparedMedium::HeightFog(_) => [1.0; C],
            PreparedMedium::FogLayer(m) => m.sun_transmittance_at(p, to_sun),
            PreparedMedium::HeightFieldLayer(m) => m.sun_transmittance_at(p, to_sun),
            PreparedMedium::Ellipsoid(m) => m.sun_transmittance_at(p, to_sun),
        }
    }

    /// `ln σ_t(p)` of a height fog in the channels where its extinction is not
    /// 0, at any height (the log density clamped to `f64::MAX`, so never ∞ or
    /// NaN), `None` in the others and for the other media.
    pub fn height_fog_log_extinction_at(&self, p: DVec3) -> [Option<f64>; C] {
        match self {
            PreparedMedium::HeightFog(m) => {
                let log_density = (-(p.z - m.reference_height) / m.scale_height).min(f64::MAX);
                m.extinction.map(|b| (b > 0.0).then(|| b.ln() + log_density))
            }
            _ => [None; C],
        }
    }

    /// Along `ray`, the length over which the medium's density falls by e where
    /// it falls for ever: H/d_z for a height fog seen upwards (its source dies
    /// out over that length, however thin the fog and so however long its
    /// extinction's own scale). `None` for media bounded along the ray or of
    /// constant density.
    pub fn density_decay_length(&self, ray: &ViewRay) -> Option<f64> {
        match self {
            PreparedMedium::HeightFog(m) if ray.dir.z > 0.0 => Some(m.scale_height / ray.dir.z),
            _ => None,
        }
    }

    /// The channels in which a height fog is opaque at once at `p`: σ_t >
    /// 1e20 m⁻¹, a 1/e length far below any length a scene holds (the density
    /// itself overflows f64 only some 700 scale heights below the reference
    /// height, much deeper). There the fog's saturated closed form, which
    /// works in log space, is the exact value; a numeric path would have to
    /// find a layer thinner than 1e-20 m.
    pub fn opaque_at(&self, p: DVec3) -> [bool; C] {
        self.height_fog_log_extinction_at(p)
            .map(|l| l.is_some_and(|l| l > OPAQUE_EXTINCTION.ln()))
    }

    /// The medium's name for reports.
    pub fn name(&self) -> &str {
        match self {
            PreparedMedium::Homogeneous(m) => &m.name,
            PreparedMedium::HeightFog(m) => &m.name,
            PreparedMedium::FogLayer(m) => &m.name,
            PreparedMedium::HeightFieldLayer(m) => &m.name,
            PreparedMedium::Ellipsoid(m) => &m.name,
        }
    }
}

/// The extinction, m⁻¹, beyond which a height fog is taken as opaque at once
/// at a view ray's origin ([`PreparedMedium::opaque_at`]).
pub const OPAQUE_EXTINCTION: f64 = 1e20;

/// `σ_s·(L_amb + Σ_k p(μ_k)·E_k·T_k)`: the single-scattering source of a medium
/// with one phase function at a point (Klassen eq 1.11's integrand without the
/// view transmittance). `sun_t` gives each sun's transmittance to the point, or
/// `None` where the sun does not reach it directly.
#[inline]
pub(crate) fn scattering_source<const C: usize>(
    scattering: &[f64; C],
    phase: &phase::PhaseFunction,
    view_dir: DVec3,
    lights: &LightSet<C>,
    sun_t: impl Fn(&SunSource<C>) -> Option<[f64; C]>,
) -> [f64; C] {
    let mut out = lights.ambient;
    for sun in &lights.suns {
        let Some(ts) = sun_t(sun) else { continue };
        let ph = sun.phase(phase, view_dir);
        for c in 0..C {
            out[c] += ph * sun.irradiance[c] * ts[c];
        }
    }
    for c in 0..C {
        out[c] *= scattering[c];
    }
    out
}

/// Rounding bound on a closed form of the shape `a·(1 − e^{−τ})` evaluated
/// with expm1 and a handful of products: relative `k·ε`, the number of
/// roundings `k` counted generously.
#[inline]
pub(crate) fn rounding_bound(value: f64, ops: f64) -> f64 {
    value.abs() * ops * crate::numeric::EPS
}

/// The relative form of [`rounding_bound`].
#[inline]
pub(crate) fn rounding_rel(ops: f64) -> f64 {
    ops * crate::numeric::EPS
}
