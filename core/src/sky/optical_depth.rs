//! Fast optical depths for the layered atmosphere ([`crate::sky::atmosphere`]):
//! the Rayleigh and Mie columns from tables of the Chapman function with a
//! measured interpolation error, the ozone column in closed form on the pieces
//! where its tent profile is linear, and a vectorisable `e^{−τ}` (its loop
//! over the wavelengths, `transmittances`, also compiled for AVX2 and used
//! where the CPU has it). Speed-up: the `sky` stage of a 2048 × 1024 sky at
//! 60° went from 192 ms to 48 ms (idle machine, 17-wavelength path) and is
//! 88–105 ms under a load of 3.4–4 with the spectral path that tolerance 1e-3 now
//! takes (docs/benchmarks.md); the columns no longer dominate an evaluation.
//!
//! The sky integral needs, at every scattering point P of a view ray, the
//! columns from P to the sun and from the observer to P. Integrating both
//! adaptively (as [`crate::sky::atmosphere::columns_to_boundary`] does) costs
//! a few hundred density evaluations per point; with the derivation below each
//! costs a handful of table look-ups and one logarithm per ozone piece.
//!
//! # Derivation
//!
//! **Chapman function.** For a species with density `ρ(h) = e^{−h/H}` over a
//! sphere of radius `R` (no top), the column from a point at radius
//! `r = R + h` along a ray with direction cosine `μ ≥ 0` to infinity is
//!
//! ```text
//! C∞(h, μ) = ∫₀^∞ ρ(h(t)) dt = H · ρ(h) · F(x, μ),     x = r / H,
//! ```
//!
//! where, with `u = (r(t) − r)/H` (height gained in scale heights, monotone in
//! t for μ ≥ 0), `dt = H r(t)/(t + rμ) du` and `t + rμ = √(r(t)² − r²(1 − μ²))`,
//!
//! ```text
//! F(x, μ) = ∫₀^∞ e^{−u} (x + u) / √(x²μ² + 2xu + u²) du
//!         = ∫₀^∞ e^{−w²} 2w (x + w²) / √(x²μ² + 2xw² + w⁴) dw     (u = w²).
//! ```
//!
//! `F` is Chapman's grazing-incidence function (1 for μ = 1 and
//! ≈ √(πx/2)(1 + 3/(8x)) ≈ 35 (Rayleigh), 91 (Mie) for μ = 0). The second form
//! has no square-root singularity at μ = 0; [`chapman_function`] integrates it
//! by adaptive Gauss–Kronrod (G7–K15) to an estimated 1e-12 on
//! `w ∈ [0, 6.5]` (the tail beyond is below `e^{−42}` of the value), split at
//! `w = μ√(x/2)` where the integrand turns; the Kronrod sums are far more
//! accurate than the `|K − G|` estimate (the tables built on them agree with
//! independently integrated columns to 1e-11, see the tests).
//!
//! **Downward rays** (μ < 0) that miss the ground pass a perigee at height
//! `h_p` (`r_p² − R² = h(2R + h) − (rμ)²`). Reflecting the part before the
//! perigee onto the part after it:
//!
//! ```text
//! C∞(h, μ) = 2 C∞(h_p, 0) − C∞(h, −μ)            (μ < 0)
//! ```
//!
//! (no cancellation: `C∞(h, −μ) ≤ C∞(h_p, 0)`, so the result is at least
//! `C∞(h_p, 0)` and its relative error at most three times the table's).
//!
//! **The atmosphere's top.** The model's densities stop at 60 km. A ray from
//! P leaves the top sphere `r_top` once, with direction cosine
//! `μ_top = √(r_top² − r² + (rμ)²)/r_top` there, and after that point it sees
//! only what the untruncated profile has above the top, so
//!
//! ```text
//! C(P → top) = C∞(h, μ) − C∞(h_top, μ_top).
//! ```
//!
//! The same argument gives the column between two points A, B of one ray
//! (B after A): `C(A → B) = C∞(A) − C∞(B)`, both in the ray's direction — the
//! view column from the observer to every scattering point from two look-ups,
//! with no integral along the view ray. For a view ray that hits the ground
//! the forward column is undefined; there the backward direction
//! (`μ → −μ`, which rises and never meets the ground) is used:
//! `C(A → B) = C∞_back(B) − C∞_back(A)`. The differences lose no accuracy
//! that matters: what the sky needs is the *absolute* optical depth
//! `σ·C`, whose error is the table's relative error times `σ·C∞` (≤ ~1e-8 for
//! the largest columns at the largest coefficients).
//!
//! **Tables.** `F(x(h), μ)` of both species is tabulated on
//! `h ∈ [0, 60 km] × μ ∈ [0, 1]` as tensor-product Chebyshev interpolants
//! (4 nodes in h, 10 in μ) on patches. μ is cut into octaves
//! `[1/2, 1], [1/4, 1/2], …, [1/64, 1/32]` and `[0, 1/64]` (near the horizon
//! `F` changes on the scale `μ ~ √(2/x)`, 0.05 for Rayleigh, 0.019 for Mie;
//! above it like 1/μ, which a polynomial follows equally well on every
//! octave), and each octave uniformly into `2^a × 2^b` patches, as many as its
//! check requires. The check compares every patch with [`chapman_function`]
//! at all points between its nodes (the extrema of `T_n`, where interpolation
//! errors peak); a patch that misses [`TABLE_REL_TOL`] refines its octave
//! along h or μ, whichever one-directional check (at the other direction's
//! nodes, where that interpolation is exact) misses more. The largest checked
//! error over the table, times a safety factor 4, is the relative error
//! ([`ChapmanTables::error`]) that the sky's error estimate charges to every
//! look-up (≈ 1e-11 relative to the column; denser off-grid points are tested
//! to stay within it). A look-up finds its patch from the binary exponent of
//! μ, without a search. The table depends on no parameter (the density
//! multipliers scale coefficients, not columns), so it is built once per
//! process (≈ 4 000 Chapman integrals, a few ms on two threads) and shared.
//!
//! **Ozone.** The tent `max(0, 1 − |h − 25 km|/15 km)` is linear in the radius
//! between its kinks (10, 25, 40 km). Along a line with perigee radius p, in
//! the signed distance s from the perigee, `r(s) = √(p² + s²)` and
//!
//! ```text
//! ∫ r ds = ½ (s r + p² ln(s + r)),
//! ```
//!
//! so each piece between two kink crossings contributes
//! `±(∫ r ds − r_k Δs)/15 km` in closed form. Written naively this
//! subtracts products of 6e12 m²; here `½(s_b r_b − s_a r_a)` is rewritten as
//! `½Δs[(r_a + r_b)/2 + (s_a + s_b)²/(2(r_a + r_b))]` and the logarithm of
//! `(s_b + r_b)/(s_a + r_a)` is taken by `ln_1p` of its excess over 1, computed
//! without cancellation (`s + r = p²/(r − s)` for s < 0). What remains is the
//! subtraction of `r_k Δs`, ~1e-3 m² of rounding, i.e. ~1e-7 m of column;
//! [`OZONE_ABS_ERROR_M`] = 1e-6 m and [`OZONE_REL_ERROR`] are charged (tested
//! against adaptive quadrature of the tent along grazing and steep lines, and
//! against the independently integrated columns of
//! [`crate::sky::atmosphere::columns_to_boundary`]).
//! The crossings are `s = ±√(s_ref² + (h_k − h_ref)(2R + h_k + h_ref))` from
//! any point (h_ref, s_ref) of the line; their radii are `R + h_k` exactly.
//! Along a view ray the column is kept cumulative at the crossings, so each
//! scattering point adds one piece.

use crate::numeric::integrate_adaptive;
use crate::sky::atmosphere::{ATMOSPHERE_RADIUS_M, ATMOSPHERE_TOP_M, EARTH_RADIUS_M, MIE_SCALE_HEIGHT_M, RAYLEIGH_SCALE_HEIGHT_M};
use std::f64::consts::PI;
use std::sync::LazyLock;

const R: f64 = EARTH_RADIUS_M;

/// Largest relative interpolation error of the Chapman tables that the
/// build accepts at its check points (dimensionless).
pub const TABLE_REL_TOL: f64 = 1e-11;

/// Safety factor on the largest checked error for the error estimate.
const TABLE_SAFETY: f64 = 4.0;

/// Upper end of the `w` integral of [`chapman_function`].
const W_MAX: f64 = 6.5;

/// Chapman's grazing-incidence function `F(x, μ)` for `x = r/H` (radius over
/// scale height, dimensionless, > 0) and direction cosine `μ ∈ [0, 1]`
/// (clamped; 1 = straight up): the column of an exponential atmosphere from
/// radius r to infinity along the ray, in units of `H·ρ(r)`. Computed by
/// adaptive Gauss–Kronrod quadrature of the `w` form of the module docs to an
/// estimated relative 1e-12 (the `|K15 − G7|` estimate; the values are
/// accurate to rounding).
pub fn chapman_function(x: f64, mu: f64) -> f64 {
    let mu = mu.clamp(0.0, 1.0);
    let xm = x * mu;
    let f = |w: f64| {
        let w2 = w * w;
        [(-w2).exp() * 2.0 * w * (x + w2) / (xm * xm + w2 * (2.0 * x + w2)).sqrt()]
    };
    let turn = mu * (0.5 * x).sqrt();
    let mut breaks = vec![0.0];
    for b in [0.25 * turn, turn, 4.0 * turn] {
        if b > 0.0 && b < W_MAX {
            breaks.push(b);
        }
    }
    breaks.push(W_MAX);
    breaks
        .windows(2)
        .map(|w| integrate_adaptive(f, w[0], w[1], 0.0, 1e-12, 400).value[0])
        .sum()
}

// ---------------------------------------------------------------------------
// Chebyshev tables of F
// ---------------------------------------------------------------------------

/// Nodes per patch along h.
const NH: usize = 4;
/// Nodes per patch along μ.
const NM: usize = 10;
/// μ-octaves: `[2^−(o+1), 2^−o]` for o = 0…5, then `[0, 1/64]`.
const OCTAVES: usize = 7;
/// Deepest uniform subdivision (per direction, as a power of 2) of an octave.
const MAX_LEVEL: u32 = 6;
/// Species: Rayleigh, Mie.
const SCALE_HEIGHTS_M: [f64; 2] = [RAYLEIGH_SCALE_HEIGHT_M, MIE_SCALE_HEIGHT_M];

/// One tensor-product Chebyshev patch, both species.
#[derive(Debug, Clone)]
struct Patch {
    /// Maps h to `[−1, 1]`: `h̃ = h·sh + oh`; μ likewise.
    sh: f64,
    oh: f64,
    sm: f64,
    om: f64,
    /// `c[a][b][k]` multiplies `T_a(h̃) T_b(μ̃)` for species k (species
    /// innermost, so that both are evaluated in one pass).
    c: [[[f64; 2]; NM]; NH],
    /// The μ-polynomial at h = 60 km (`Σ_a c[a][b][k] T_a(h̃_top)`), for the
    /// exit point at the top.
    top: [[f64; 2]; NM],
}

#[inline(always)]
fn cheb<const N: usize>(x: f64) -> [f64; N] {
    let mut t = [0.0; N];
    t[0] = 1.0;
    if N > 1 {
        t[1] = x;
    }
    let x2 = 2.0 * x;
    for k in 2..N {
        t[k] = x2 * t[k - 1] - t[k - 2];
    }
    t
}

impl Patch {
    #[inline(always)]
    fn eval(&self, h: f64, mu: f64) -> [f64; 2] {
        let th = cheb::<NH>(h * self.sh + self.oh);
        let tm = cheb::<NM>(mu * self.sm + self.om);
        let mut out = [0.0; 2];
        for (row, &ta) in self.c.iter().zip(&th) {
            let mut r = [0.0; 2];
            for (c, t) in row.iter().zip(&tm) {
                r[0] += c[0] * t;
                r[1] += c[1] * t;
            }
            out[0] += ta * r[0];
            out[1] += ta * r[1];
        }
        out
    }

    #[inline(always)]
    fn eval_top(&self, mu: f64) -> [f64; 2] {
        let tm = cheb::<NM>(mu * self.sm + self.om);
        let mut out = [0.0; 2];
        for (c, t) in self.top.iter().zip(&tm) {
            out[0] += c[0] * t;
            out[1] += c[1] * t;
        }
        out
    }
}

/// One μ-octave, split uniformly into `2^level_h × 2^level_m` patches.
#[derive(Debug, Clone, Copy, Default)]
struct Octave {
    m0: f64,
    first: usize,
    /// Patches per unit of μ and of h (m⁻¹), for the index computation.
    per_mu: f64,
    per_h: f64,
    /// Patch counts along μ and h.
    nm: usize,
    nh: usize,
}

/// Tables of `F(x(h), μ)` for Rayleigh and Mie on `h ∈ [0, 60 km]`,
/// `μ ∈ [0, 1]`; see the module docs. Patches: μ in octaves
/// (`[1/2, 1], [1/4, 1/2], …, [1/64, 1/32], [0, 1/64]`), each split uniformly
/// as far as its check requires; look-ups find their patch from the binary
/// exponent of μ, with no search.
#[derive(Debug, Clone)]
pub struct ChapmanTables {
    octaves: [Octave; OCTAVES],
    patches: Vec<Patch>,
    checked_error: [f64; 2],
    evaluations: usize,
}

/// An octave's patches, built and checked, or the direction to refine.
enum OctaveFit {
    Fits(Vec<Patch>, [f64; 2], usize),
    Refine { along_h: bool, evaluations: usize },
}

fn octave_range(o: usize) -> (f64, f64) {
    if o + 1 == OCTAVES {
        (0.0, 0.5f64.powi(OCTAVES as i32 - 1))
    } else {
        (0.5f64.powi(o as i32 + 1), 0.5f64.powi(o as i32))
    }
}

/// `F` of both species at height h and direction cosine μ, by quadrature.
fn exact2(h: f64, mu: f64) -> [f64; 2] {
    std::array::from_fn(|k| chapman_function((R + h) / SCALE_HEIGHTS_M[k], mu))
}

/// Fits one patch on `[h0, h1] × [m0, m1]` to the quadrature at its nodes.
fn fit_patch_unchecked(h0: f64, h1: f64, m0: f64, m1: f64) -> (Patch, (), ()) {
    let xh: [f64; NH] = std::array::from_fn(|i| (PI * (i as f64 + 0.5) / NH as f64).cos());
    let xm: [f64; NM] = std::array::from_fn(|j| (PI * (j as f64 + 0.5) / NM as f64).cos());
    let hv = |x: f64| 0.5 * (h0 + h1) + 0.5 * (h1 - h0) * x;
    let mv = |x: f64| 0.5 * (m0 + m1) + 0.5 * (m1 - m0) * x;
    let mut f = [[[0.0; NM]; NH]; 2];
    for i in 0..NH {
        for j in 0..NM {
            let v = exact2(hv(xh[i]), mv(xm[j]));
            f[0][i][j] = v[0];
            f[1][i][j] = v[1];
        }
    }
    // Discrete Chebyshev transform in both directions.
    let mut c = [[[0.0; 2]; NM]; NH];
    for k in 0..2 {
        for a in 0..NH {
            for b in 0..NM {
                let mut s = 0.0;
                for i in 0..NH {
                    let ca = (a as f64 * PI * (i as f64 + 0.5) / NH as f64).cos();
                    for j in 0..NM {
                        s += f[k][i][j] * ca * (b as f64 * PI * (j as f64 + 0.5) / NM as f64).cos();
                    }
                }
                let wa = if a == 0 { 1.0 } else { 2.0 };
                let wb = if b == 0 { 1.0 } else { 2.0 };
                c[a][b][k] = s * wa * wb / (NH * NM) as f64;
            }
        }
    }
    let (sh, oh) = (2.0 / (h1 - h0), -(h0 + h1) / (h1 - h0));
    let (sm, om) = (2.0 / (m1 - m0), -(m0 + m1) / (m1 - m0));
    let th = cheb::<NH>(ATMOSPHERE_TOP_M * sh + oh);
    let top = std::array::from_fn(|b| std::array::from_fn(|k| (0..NH).map(|a| c[a][b][k] * th[a]).sum()));
    (Patch { sh, oh, sm, om, c, top }, (), ())
}

/// Fits and checks one patch on `[h0, h1] × [m0, m1]`: (patch, relative
/// error per species at the check points, evaluations).
fn fit_patch(h0: f64, h1: f64, m0: f64, m1: f64) -> (Patch, [f64; 2], usize) {
    let (patch, _, _) = fit_patch_unchecked(h0, h1, m0, m1);
    let hv = |x: f64| 0.5 * (h0 + h1) + 0.5 * (h1 - h0) * x;
    let mv = |x: f64| 0.5 * (m0 + m1) + 0.5 * (m1 - m0) * x;
    // Check between the nodes (the extrema of T_n, where interpolation errors peak).
    let mut worst = [0.0f64; 2];
    for i in 1..NH {
        let h = hv((PI * i as f64 / NH as f64).cos());
        for j in 1..NM {
            let mu = mv((PI * j as f64 / NM as f64).cos());
            let e = exact2(h, mu);
            let got = patch.eval(h, mu);
            for k in 0..2 {
                worst[k] = worst[k].max((got[k] - e[k]).abs() / e[k]);
            }
        }
    }
    (patch, worst, NH * NM + (NH - 1) * (NM - 1))
}

/// Which direction of a patch that failed its check to refine: the
/// interpolation error along h alone (at μ nodes, where the μ-interpolation
/// is exact) against that along μ alone (at h nodes). Returns (along h, evaluations).
fn refine_along_h(h0: f64, h1: f64, m0: f64, m1: f64) -> (bool, usize) {
    let (patch, _, _) = fit_patch_unchecked(h0, h1, m0, m1);
    let hv = |x: f64| 0.5 * (h0 + h1) + 0.5 * (h1 - h0) * x;
    let mv = |x: f64| 0.5 * (m0 + m1) + 0.5 * (m1 - m0) * x;
    let node_h = |i: usize| hv((PI * (i as f64 + 0.5) / NH as f64).cos());
    let node_m = |j: usize| mv((PI * (j as f64 + 0.5) / NM as f64).cos());
    let ext_h = |i: usize| hv((PI * i as f64 / NH as f64).cos());
    let ext_m = |j: usize| mv((PI * j as f64 / NM as f64).cos());
    let miss = |h: f64, mu: f64| {
        let e = exact2(h, mu);
        let g = patch.eval(h, mu);
        (0..2).fold(0.0f64, |m, k| m.max((g[k] - e[k]).abs() / e[k]))
    };
    let mut eh = 0.0f64;
    let mut em = 0.0f64;
    for j in [0, NM / 2, NM - 1] {
        for i in 1..NH {
            eh = eh.max(miss(ext_h(i), node_m(j)));
        }
    }
    for i in [0, NH - 1] {
        for j in 1..NM {
            em = em.max(miss(node_h(i), ext_m(j)));
        }
    }
    (eh > em, 3 * (NH - 1) + 2 * (NM - 1) + NH * NM)
}

fn fit_octave(o: usize, level_h: u32, level_m: u32) -> OctaveFit {
    let (m0, m1) = octave_range(o);
    let (nh, nm) = (1usize << level_h, 1usize << level_m);
    let mut patches = Vec::with_capacity(nh * nm);
    let mut worst = [0.0f64; 2];
    let mut evaluations = 0;
    for ih in 0..nh {
        let (h0, h1) = (
            ATMOSPHERE_TOP_M * ih as f64 / nh as f64,
            ATMOSPHERE_TOP_M * (ih + 1) as f64 / nh as f64,
        );
        for im in 0..nm {
            let (a, b) = (m0 + (m1 - m0) * im as f64 / nm as f64, m0 + (m1 - m0) * (im + 1) as f64 / nm as f64);
            let (p, err, n) = fit_patch(h0, h1, a, b);
            evaluations += n;
            if err[0].max(err[1]) > TABLE_REL_TOL && level_h.max(level_m) < MAX_LEVEL {
                let (along_h, n) = refine_along_h(h0, h1, a, b);
                return OctaveFit::Refine {
                    along_h,
                    evaluations: evaluations + n,
                };
            }
            worst = [worst[0].max(err[0]), worst[1].max(err[1])];
            patches.push(p);
        }
    }
    OctaveFit::Fits(patches, worst, evaluations)
}

impl ChapmanTables {
    /// Builds and checks the tables (both species), octaves on two threads.
    pub fn build() -> ChapmanTables {
        let build_octave = |o: usize| {
            let (mut lh, mut lm, mut evals) = (0, 1, 0);
            loop {
                match fit_octave(o, lh, lm) {
                    OctaveFit::Fits(p, w, n) => return (lh, lm, p, w, evals + n),
                    OctaveFit::Refine { along_h, evaluations } => {
                        evals += evaluations;
                        if along_h { lh += 1 } else { lm += 1 }
                    }
                }
            }
        };
        // Octaves on two plain threads (not rayon: a first use from inside a
        // rayon task must not re-enter rayon while it holds the lazy lock).
        let fits: Vec<_> = std::thread::scope(|s| {
            let odd = s.spawn(|| {
                (0..OCTAVES)
                    .filter(|o| o % 2 == 1)
                    .map(|o| (o, build_octave(o)))
                    .collect::<Vec<_>>()
            });
            let mut all: Vec<_> = (0..OCTAVES).filter(|o| o % 2 == 0).map(|o| (o, build_octave(o))).collect();
            all.extend(odd.join().expect("Chapman table build"));
            all.sort_by_key(|x| x.0);
            all
        });
        let mut t = ChapmanTables {
            octaves: [Octave::default(); OCTAVES],
            patches: Vec::new(),
            checked_error: [0.0; 2],
            evaluations: 0,
        };
        for (o, (lh, lm, p, w, n)) in fits {
            let (m0, m1) = octave_range(o);
            let (nm, nh) = (1usize << lm, 1usize << lh);
            t.octaves[o] = Octave {
                m0,
                first: t.patches.len(),
                per_mu: nm as f64 / (m1 - m0),
                per_h: nh as f64 / ATMOSPHERE_TOP_M,
                nm,
                nh,
            };
            t.patches.extend(p);
            t.checked_error = [t.checked_error[0].max(w[0]), t.checked_error[1].max(w[1])];
            t.evaluations += n;
        }
        t
    }

    #[inline(always)]
    fn patch(&self, h: f64, mu: f64) -> &Patch {
        // μ ∈ [2^e, 2^(e+1)) ⇒ octave −e − 1 (μ = 1 belongs to octave 0).
        let e = ((mu.to_bits() >> 52) & 0x7ff) as i64 - 1023;
        let o = if mu < octave_range(OCTAVES - 1).1 {
            OCTAVES - 1
        } else {
            (-e - 1).clamp(0, OCTAVES as i64 - 2) as usize
        };
        let oct = &self.octaves[o];
        let jm = (((mu - oct.m0) * oct.per_mu) as usize).min(oct.nm - 1);
        let jh = ((h * oct.per_h) as usize).min(oct.nh - 1);
        &self.patches[oct.first + jh * oct.nm + jm]
    }

    /// `F(x(h), μ)` of `[Rayleigh, Mie]` from the tables; h (m) clamped to
    /// 0…60 km, μ to 0…1.
    #[inline]
    pub fn chapman(&self, h: f64, mu: f64) -> [f64; 2] {
        let h = h.clamp(0.0, ATMOSPHERE_TOP_M);
        let mu = mu.clamp(0.0, 1.0);
        self.patch(h, mu).eval(h, mu)
    }

    /// [`Self::chapman`] at the top of the atmosphere (h = 60 km).
    #[inline]
    pub fn chapman_top(&self, mu: f64) -> [f64; 2] {
        let mu = mu.clamp(0.0, 1.0);
        self.patch(ATMOSPHERE_TOP_M, mu).eval_top(mu)
    }

    /// Relative error charged to every look-up, per species: the largest
    /// error found at the check points, times a safety factor 4 (dimensionless).
    pub fn error(&self) -> [f64; 2] {
        self.checked_error.map(|e| TABLE_SAFETY * e.max(f64::EPSILON))
    }

    /// Patches in the table.
    pub fn patches(&self) -> usize {
        self.patches.len()
    }

    /// Evaluations of both species' [`chapman_function`] spent building and checking it.
    pub fn evaluations(&self) -> usize {
        self.evaluations
    }
}

/// The tables, built on first use.
static TABLES: LazyLock<ChapmanTables> = LazyLock::new(ChapmanTables::build);

/// The shared Chapman tables.
pub fn chapman_tables() -> &'static ChapmanTables {
    &TABLES
}

// ---------------------------------------------------------------------------
// Columns along rays from the tables
// ---------------------------------------------------------------------------

/// Rayleigh and Mie columns with their error bounds, m.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct Col2 {
    pub value: [f64; 2],
    /// Absolute error charged, m.
    pub error: [f64; 2],
}

#[inline(always)]
fn scale(tables: &ChapmanTables, f: [f64; 2], rho: [f64; 2]) -> Col2 {
    let err = tables.error();
    let value = [SCALE_HEIGHTS_M[0] * rho[0] * f[0], SCALE_HEIGHTS_M[1] * rho[1] * f[1]];
    Col2 {
        value,
        error: [err[0] * value[0], err[1] * value[1]],
    }
}

#[inline]
fn densities2(h: f64) -> [f64; 2] {
    [exp_neg(h / RAYLEIGH_SCALE_HEIGHT_M), exp_neg(h / MIE_SCALE_HEIGHT_M)]
}

/// `C∞` of both species (Rayleigh, Mie) from height `h` (m, 0…60 km) with
/// direction cosine `mu` (any sign), for a ray that does not hit the ground
/// (below the perigee it is reflected, see the module docs); `rho` = the
/// densities at h.
#[inline]
pub(crate) fn column_to_infinity(tables: &ChapmanTables, h: f64, mu: f64, rho: [f64; 2]) -> Col2 {
    if mu >= 0.0 {
        return scale(tables, tables.chapman(h, mu), rho);
    }
    let r = R + h;
    let rm = r * mu;
    // r_p² − R² = h(2R + h) − (rμ)², clamped (a grazing ray may round below 0).
    let q = (h * (2.0 * R + h) - rm * rm).max(0.0);
    let rp = (R * R + q).sqrt();
    let hp = q / (rp + R);
    let full = scale(tables, tables.chapman(hp, 0.0), densities2(hp));
    let back = scale(tables, tables.chapman(h, -mu), rho);
    Col2 {
        value: std::array::from_fn(|k| 2.0 * full.value[k] - back.value[k]),
        error: std::array::from_fn(|k| 2.0 * full.error[k] + back.error[k]),
    }
}

/// Columns of both species from height `h` (m) along direction cosine `mu`
/// to the top of the atmosphere, for a ray that does not hit the ground.
#[inline]
pub(crate) fn column_to_top(tables: &ChapmanTables, h: f64, mu: f64, rho: [f64; 2]) -> Col2 {
    let a = column_to_infinity(tables, h, mu, rho);
    let r = R + h;
    let rm = r * mu;
    let d = ((ATMOSPHERE_TOP_M - h) * (2.0 * R + ATMOSPHERE_TOP_M + h)).max(0.0);
    let mu_top = ((d + rm * rm).sqrt() / ATMOSPHERE_RADIUS_M).min(1.0);
    let b = scale(tables, tables.chapman_top(mu_top), *TOP_DENSITIES);
    Col2 {
        value: std::array::from_fn(|k| (a.value[k] - b.value[k]).max(0.0)),
        error: std::array::from_fn(|k| a.error[k] + b.error[k]),
    }
}

static TOP_DENSITIES: LazyLock<[f64; 2]> = LazyLock::new(|| densities2(ATMOSPHERE_TOP_M));

// ---------------------------------------------------------------------------
// Transmittance
// ---------------------------------------------------------------------------

/// `e^{−τ}` for an optical depth `τ ≥ 0` (NaN propagates, `+∞` and anything
/// above 708 give 0), written without branches or calls so that loops over
/// wavelengths vectorise: `τ·log₂e = n + f` with n the nearest integer
/// (by the 1.5·2⁵² rounding trick, whose bits also hold n),
/// `r = −τ + n ln 2` in two parts (|r| ≤ ln2/2), `e^r` by the diagonal Padé
/// approximant of degree 6, `(E(r) + r·O(r))/(E(r) − r·O(r))` with
/// `E = 1 + 5r²/44 + r⁴/792 + r⁶/665280`, `O = 1/2 + r²/66 + r⁴/15840`
/// (truncation `(6!)²/(12!·13!)·|r|¹³ < 2e-19`), times `2^−n` assembled in
/// the exponent bits. Relative error ≤ 1e-15 (tested against `f64::exp`).
#[inline(always)]
pub fn exp_neg(tau: f64) -> f64 {
    const LOG2E: f64 = std::f64::consts::LOG2_E;
    const LN2_HI: f64 = 6.931_471_803_691_238e-1; // ln 2 rounded to 32 significant bits (n·LN2_HI is exact)
    const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;
    const MAGIC: f64 = 6_755_399_441_055_744.0; // 1.5·2⁵²
    let x = if tau > 708.0 { -708.0 } else { -tau };
    let v = x * LOG2E + MAGIC;
    let n = v - MAGIC;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let r2 = r * r;
    let e = 1.0 + r2 * (5.0 / 44.0 + r2 * (1.0 / 792.0 + r2 * (1.0 / 665_280.0)));
    let o = r * (0.5 + r2 * (1.0 / 66.0 + r2 * (1.0 / 15_840.0)));
    let p = (e + o) / (e - o);
    // v's low bits hold n (two's complement): the exponent field of 2ⁿ is n + 1023.
    let bits = (v.to_bits().wrapping_sub(MAGIC.to_bits()).wrapping_add(1023)) << 52;
    let y = p * f64::from_bits(bits);
    if tau > 708.0 { 0.0 } else { y }
}

/// `out[i] = e^{−(σ₀[i]·d₀ + σ₁[i]·d₁ + σ₂[i]·d₂)}` for `i < M/2`: the
/// transmittance at each wavelength from three species' extinction per unit
/// column `sigma` (m⁻¹) and their columns `d` (m). One loop of
/// [`exp_neg`]; compiled a second time for AVX2 and taken when the CPU has
/// it (4 wavelengths per instruction instead of 2; the same operations, so
/// the same results).
#[inline]
pub(crate) fn transmittances<const M: usize>(sigma: &[[f64; M]; 3], d: [f64; 3], out: &mut [f64; M]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { transmittances_avx2(sigma, d, out) };
        return;
    }
    transmittances_portable(sigma, d, out);
}

#[inline(always)]
fn transmittances_portable<const M: usize>(sigma: &[[f64; M]; 3], d: [f64; 3], out: &mut [f64; M]) {
    for i in 0..M / 2 {
        out[i] = exp_neg(sigma[0][i] * d[0] + sigma[1][i] * d[1] + sigma[2][i] * d[2]);
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn transmittances_avx2<const M: usize>(sigma: &[[f64; M]; 3], d: [f64; 3], out: &mut [f64; M]) {
    transmittances_portable(sigma, d, out);
}

// ---------------------------------------------------------------------------
// Ozone
// ---------------------------------------------------------------------------

const OZONE_KINKS_M: [f64; 3] = [10_000.0, 25_000.0, 40_000.0];

/// A straight line through the atmosphere in perigee coordinates: `s` is the
/// signed distance along the line from its point closest to the earth's
/// centre. Anchored at a point of height `h_ref` (m) and coordinate `s_ref`
/// (m; `r·μ` there).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Line {
    h_ref: f64,
    r_ref: f64,
    s_ref: f64,
    /// Perigee radius squared, `r_ref²(1 − μ)(1 + μ)`, m².
    p2: f64,
}

/// The ozone tent's thickness on either side of its peak, m.
const OZONE_SIDE_M: f64 = 15_000.0;

impl Line {
    /// The line through a point at height `h` (m) with direction cosine `mu`.
    pub fn new(h: f64, mu: f64) -> Line {
        let r = R + h;
        Line {
            h_ref: h,
            r_ref: r,
            s_ref: r * mu,
            p2: r * r * (1.0 - mu) * (1.0 + mu),
        }
    }

    /// `s²` where the line meets the sphere of height `hk` (negative: it misses it).
    #[inline]
    pub fn s_squared_at_height(&self, hk: f64) -> f64 {
        self.s_ref * self.s_ref + (hk - self.h_ref) * (2.0 * R + hk + self.h_ref)
    }

    /// Radius at coordinate `s`, m.
    #[inline]
    pub fn radius(&self, s: f64) -> f64 {
        (self.r_ref * self.r_ref + (s - self.s_ref) * (s + self.s_ref)).sqrt()
    }

    /// `∫_{sa}^{sb} (r(s) − rk) ds` in closed form, from the end radii
    /// `ra`, `rb`: with `∫ r ds = ½(s r + p² ln(s + r))`,
    /// `½(s_b r_b − s_a r_a) = ½Δs[(r_a + r_b)/2 + (s_a + s_b)²/(2(r_a + r_b))]`
    /// (no difference of large products), and the logarithm of
    /// `(s_b + r_b)/(s_a + r_a)` by `ln_1p` of its excess over 1 (for s < 0,
    /// `s + r = p²/(r − s)`).
    #[inline]
    fn excess(&self, sa: f64, ra: f64, sb: f64, rb: f64, rk: f64) -> f64 {
        let ds = sb - sa;
        let (rs, ss) = (ra + rb, sa + sb);
        let half_sr = 0.5 * ds * (0.5 * rs + ss * ss / (2.0 * rs));
        // (s_b + r_b)/(s_a + r_a) − 1 = (Δs + Δr)/(s_a + r_a), Δr = Δs(s_a + s_b)/(r_a + r_b);
        // 1/(s_a + r_a) = (r_a − s_a)/p² for s_a < 0, and for s_b ≤ 0 the
        // same excess is Δs(1 − (s_a + s_b)/(r_a + r_b))/(r_b − s_b) (no p²).
        let log = if sa >= 0.0 {
            (ds * (1.0 + ss / rs) / (sa + ra)).ln_1p()
        } else if sb <= 0.0 {
            (ds * (1.0 - ss / rs) / (rb - sb)).ln_1p()
        } else {
            (ds * (1.0 + ss / rs) * (ra - sa) / self.p2).ln_1p()
        };
        half_sr + 0.5 * self.p2 * log - rk * ds
    }

    /// Ozone column over a piece `[sa, sb]` (end radii `ra`, `rb`) that
    /// crosses no kink, so that the tent is linear in r on it.
    #[inline]
    fn ozone_piece(&self, sa: f64, ra: f64, sb: f64, rb: f64) -> f64 {
        if sb <= sa {
            return 0.0;
        }
        // A radius inside the piece: the mean of the ends, or, if the piece
        // holds the perigee, of the perigee and the farther end.
        let inside = if sa < 0.0 && sb > 0.0 {
            0.5 * (self.p2.sqrt() + ra.max(rb))
        } else {
            0.5 * (ra + rb)
        };
        let [r10, r25, r40] = OZONE_KINKS_M.map(|h| R + h);
        if inside <= r10 || inside >= r40 {
            0.0
        } else if inside < r25 {
            (self.excess(sa, ra, sb, rb, r10) / OZONE_SIDE_M).max(0.0)
        } else {
            (-self.excess(sa, ra, sb, rb, r40) / OZONE_SIDE_M).max(0.0)
        }
    }

    /// The sorted kink crossings strictly inside `(s0, s1)` with their radii,
    /// and the ends (radii `r0`, `r1`).
    fn breaks(&self, s0: f64, r0: f64, s1: f64, r1: f64) -> ([(f64, f64); 8], usize) {
        let mut b = [(0.0, 0.0); 8];
        let mut n = 0;
        b[n] = (s0, r0);
        n += 1;
        for hk in OZONE_KINKS_M {
            let q = self.s_squared_at_height(hk);
            if q > 0.0 {
                let sk = q.sqrt();
                for s in [-sk, sk] {
                    if s > s0 && s < s1 {
                        b[n] = (s, R + hk);
                        n += 1;
                    }
                }
            }
        }
        b[n] = (s1, r1);
        n += 1;
        b[..n].sort_by(|x, y| x.0.total_cmp(&y.0));
        (b, n)
    }

    /// Ozone column from the anchor point to the top of the atmosphere along
    /// the line's direction (the anchor's radius is known exactly).
    pub fn ozone_to_top(&self) -> f64 {
        // Nothing to cross: the line stays above 40 km, or starts above it going up.
        if self.s_squared_at_height(OZONE_KINKS_M[2]) <= 0.0 || (self.h_ref >= OZONE_KINKS_M[2] && self.s_ref >= 0.0) {
            return 0.0;
        }
        let s1 = self.s_squared_at_height(ATMOSPHERE_TOP_M).max(0.0).sqrt();
        if s1 <= self.s_ref {
            return 0.0;
        }
        let (b, n) = self.breaks(self.s_ref, self.r_ref, s1, ATMOSPHERE_RADIUS_M);
        b[..n].windows(2).map(|w| self.ozone_piece(w[0].0, w[0].1, w[1].0, w[1].1)).sum()
    }
}

#[cfg(test)]
impl Line {
    /// `s` of the anchor point.
    pub fn s_ref(&self) -> f64 {
        self.s_ref
    }

    /// Height at coordinate `s`, m.
    #[inline]
    pub fn height(&self, s: f64) -> f64 {
        let d = (s - self.s_ref) * (s + self.s_ref);
        let r = (self.r_ref * self.r_ref + d).sqrt();
        self.h_ref + d / (r + self.r_ref)
    }

    /// Ozone column over `[s0, s1]` (m at the 25 km peak density).
    pub fn ozone(&self, s0: f64, s1: f64) -> f64 {
        if s1.partial_cmp(&s0) != Some(std::cmp::Ordering::Greater) {
            return 0.0;
        }
        let (b, n) = self.breaks(s0, self.radius(s0), s1, self.radius(s1));
        b[..n].windows(2).map(|w| self.ozone_piece(w[0].0, w[0].1, w[1].0, w[1].1)).sum()
    }
}

/// The ozone column along one view line from `s0`, cumulative at the kink
/// crossings so that each query integrates one piece only.
#[derive(Debug, Clone, Copy)]
pub(crate) struct OzoneCumulative {
    line: Line,
    breaks: [(f64, f64); 8],
    cum: [f64; 8],
    n: usize,
}

impl OzoneCumulative {
    /// For `line` over `[s0, s1]`.
    pub fn new(line: Line, s0: f64, s1: f64) -> OzoneCumulative {
        let (breaks, n) = if s1 > s0 {
            line.breaks(s0, line.radius(s0), s1, line.radius(s1))
        } else {
            ([(s0, line.radius(s0)); 8], 1)
        };
        let mut cum = [0.0; 8];
        for i in 1..n {
            let (a, b) = (breaks[i - 1], breaks[i]);
            cum[i] = cum[i - 1] + line.ozone_piece(a.0, a.1, b.0, b.1);
        }
        OzoneCumulative { line, breaks, cum, n }
    }

    /// Ozone column from `s0` to `s` (clamped to the range), given the radius `r` at s.
    #[inline]
    pub fn at(&self, s: f64, r: f64) -> f64 {
        let mut i = 0;
        while i + 1 < self.n && self.breaks[i + 1].0 <= s {
            i += 1;
        }
        if i + 1 >= self.n {
            return self.cum[self.n - 1];
        }
        let (sa, ra) = self.breaks[i];
        if s <= sa {
            return self.cum[i];
        }
        self.cum[i] + self.line.ozone_piece(sa, ra, s, r)
    }
}

/// Relative error bound charged to the closed-form ozone columns (rounding of
/// sums over up to seven pieces).
pub const OZONE_REL_ERROR: f64 = 1e-12;
/// Absolute error bound charged to the ozone columns, m: the closed form
/// subtracts `r_k Δs` from `∫ r ds` (both up to ~6e12 m²), which leaves
/// ~1e-3 m² of rounding, i.e. ~1e-7 m of column after the division by
/// 15 km; with margin.
pub const OZONE_ABS_ERROR_M: f64 = 1e-6;

/// The error charged to an ozone column `c`, m.
#[inline]
pub(crate) fn ozone_error(c: f64) -> f64 {
    OZONE_REL_ERROR * c + OZONE_ABS_ERROR_M
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sky::atmosphere::{RayEnd, columns_along_ray, columns_to_boundary, ozone_density};
    use std::time::Instant;

    #[test]
    fn chapman_function_limits() {
        // Vertical: F = 1 exactly; horizontal: √(πx/2)(1 + 1/(8x) + …).
        for x in [800.0, 5300.0] {
            assert!((chapman_function(x, 1.0) - 1.0).abs() < 1e-14);
            let f0 = chapman_function(x, 0.0);
            // Expanding (x + u)/√(2xu + u²) in u/x: √(πx/2)(1 + 3/(8x) − 15/(128x²) + O(x⁻³)).
            let asym = (PI * x / 2.0).sqrt() * (1.0 + 3.0 / (8.0 * x) - 15.0 / (128.0 * x * x));
            assert!((f0 - asym).abs() < 1e-8 * f0, "{f0} vs {asym}");
            // Large xμ: expanding in 2u/(xμ²),
            // F ≈ (1/μ)(1 + 1/x − 1/(xμ²) − 2/(x²μ²) + 3/(x²μ⁴) + O((xμ²)⁻³)).
            let mu = 0.5;
            let f = chapman_function(x, mu);
            let (m2, x2) = (mu * mu, x * x);
            let a = 1.0 / mu * (1.0 + 1.0 / x - 1.0 / (x * m2) - 2.0 / (x2 * m2) + 3.0 / (x2 * m2 * m2));
            assert!((f - a).abs() < 2e-5 * f, "{f} vs {a}");
        }
    }

    #[test]
    fn tables_meet_their_tolerance_between_the_check_points() {
        let t0 = Instant::now();
        let built = ChapmanTables::build();
        eprintln!(
            "tables built in {:.1} ms: {} patches, {} evaluations, charged error {:.1e} / {:.1e}",
            t0.elapsed().as_secs_f64() * 1e3,
            built.patches(),
            built.evaluations(),
            built.error()[0],
            built.error()[1]
        );
        for (o, oct) in built.octaves.iter().enumerate() {
            eprintln!("octave {o}: μ from {:.4}, {} × {} patches (h × μ)", oct.m0, oct.nh, oct.nm);
        }
        let t = chapman_tables();
        // Off-grid points (a different lattice from nodes and check points).
        let mut worst = [0.0f64; 2];
        for i in 0..=37 {
            let h = ATMOSPHERE_TOP_M * (i as f64 / 37.0).powf(1.3);
            for j in 0..=301 {
                let mu = (j as f64 / 301.0).powi(3);
                let e = exact2(h, mu);
                let got = t.chapman(h, mu);
                for k in 0..2 {
                    worst[k] = worst[k].max((got[k] - e[k]).abs() / e[k]);
                }
                if i == 37 {
                    // h = 60 km exactly: the top polynomial equals the full one.
                    let top = t.chapman_top(mu);
                    for k in 0..2 {
                        assert!((top[k] - got[k]).abs() <= 1e-13 * got[k], "top {mu}: {top:?} vs {got:?}");
                    }
                }
            }
        }
        eprintln!("worst off-grid: Rayleigh {:.1e}, Mie {:.1e}", worst[0], worst[1]);
        for k in 0..2 {
            assert!(
                worst[k] <= t.error()[k],
                "off-grid {:.2e} above the charged {:.2e}",
                worst[k],
                t.error()[k]
            );
            assert!(t.error()[k] <= TABLE_SAFETY * TABLE_REL_TOL);
        }
    }

    #[test]
    fn table_columns_match_adaptive_columns() {
        let tables = chapman_tables();
        let mut worst = [0.0f64; 3];
        let mut n = 0;
        for h in [0.0, 0.5, 900.0, 9_999.0, 10_000.0, 17_000.0, 25_000.0, 39_000.0, 55_000.0, 59_999.0] {
            for mu in [
                1.0, 0.9, 0.5, 0.2, 0.05, 0.01, 1e-3, 1e-6, 0.0, -1e-6, -1e-3, -0.01, -0.03, -0.05, -0.08, -0.1, -0.13,
            ] {
                let exact = columns_to_boundary(h, mu, 1e-13);
                if exact.end == RayEnd::Ground {
                    continue;
                }
                n += 1;
                let rho = densities2(h);
                let c = column_to_top(tables, h, mu, rho);
                let line = Line::new(h, mu);
                let s_top = line.s_squared_at_height(ATMOSPHERE_TOP_M).sqrt();
                let oz = line.ozone(line.s_ref(), s_top);
                assert!((line.ozone_to_top() - oz).abs() <= ozone_error(oz), "h {h} μ {mu}");
                let got = [c.value[0], c.value[1], oz];
                let want = [exact.columns.rayleigh_m, exact.columns.mie_m, exact.columns.ozone_m];
                let bound = [c.error[0], c.error[1], ozone_error(oz)];
                for k in 0..3 {
                    let d = (got[k] - want[k]).abs();
                    // The optical depth error is what matters: judge against the
                    // bound, plus the adaptive reference's own 1e-13.
                    assert!(
                        d <= bound[k] + 2e-13 * want[k] + 1e-12,
                        "h {h} μ {mu} species {k}: {} vs {} (diff {d:.2e}, bound {:.2e})",
                        got[k],
                        want[k],
                        bound[k]
                    );
                    if want[k] > 0.0 {
                        worst[k] = worst[k].max(d / want[k]);
                    }
                }
            }
        }
        eprintln!(
            "{n} rays: worst relative column error R {:.1e}, M {:.1e}, O {:.1e}",
            worst[0], worst[1], worst[2]
        );
        // Pieces of a view ray: the difference of two look-ups.
        for (h, mu) in [(0.0, 0.3), (0.0, 0.0), (2000.0, -0.02), (30_000.0, -0.1)] {
            let (_, t_end, end) = crate::sky::atmosphere::ray_segment(h, mu).expect("inside");
            for f in [1e-6, 0.01, 0.3, 0.9] {
                let t = f * t_end;
                let (exact, _) = columns_along_ray(h, mu, 0.0, t, 1e-13);
                let line = Line::new(h, mu);
                let s = line.s_ref() + t;
                let ht = line.height(s);
                let r = R + ht;
                let mut_ = s / r;
                let (a, b) = if end == RayEnd::Top {
                    (
                        column_to_infinity(tables, h, mu, densities2(h)),
                        column_to_infinity(tables, ht, mut_, densities2(ht)),
                    )
                } else {
                    (
                        column_to_infinity(tables, ht, -mut_, densities2(ht)),
                        column_to_infinity(tables, h, -mu, densities2(h)),
                    )
                };
                let oz = OzoneCumulative::new(line, line.s_ref(), line.s_ref() + t_end).at(s, line.radius(s));
                let got = [a.value[0] - b.value[0], a.value[1] - b.value[1], oz];
                let want = [exact.rayleigh_m, exact.mie_m, exact.ozone_m];
                for k in 0..3 {
                    let bound = if k < 2 { a.error[k] + b.error[k] } else { ozone_error(oz) };
                    let d = (got[k] - want[k]).abs();
                    assert!(
                        d <= bound + 2e-13 * want[k] + 1e-12,
                        "view piece h {h} μ {mu} t {t}: species {k} {} vs {} (bound {bound:.2e})",
                        got[k],
                        want[k]
                    );
                }
            }
        }
    }

    #[test]
    fn exp_neg_matches_std() {
        let mut worst = 0.0f64;
        for i in 0..200_000 {
            let tau = 710.0 * (i as f64 / 200_000.0).powi(3) + 1e-3 * (i % 7) as f64;
            let (a, b) = (exp_neg(tau), (-tau).exp());
            if tau <= 708.0 {
                worst = worst.max((a - b).abs() / b);
            } else {
                assert_eq!(a, 0.0);
            }
        }
        eprintln!("exp_neg: worst relative difference from f64::exp {worst:.2e}");
        assert!(worst < 1e-15);
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(f64::INFINITY), 0.0);
        assert!(exp_neg(f64::NAN).is_nan());
    }

    /// The AVX2 and portable builds of the transmittance loop give the same bits.
    #[test]
    fn transmittances_equal_the_scalar_loop() {
        const M: usize = 162;
        let sigma: [[f64; M]; 3] = std::array::from_fn(|k| std::array::from_fn(|i| 1e-6 * (1.0 + (i * (k + 3)) as f64 % 17.0)));
        for d in [
            [0.0; 3],
            [1e3, 2e2, 5e1],
            [3e5, 8e4, 2e4],
            [1e9, 0.0, 0.0],
            [f64::INFINITY, 1.0, 1.0],
        ] {
            let mut fast = [0.0; M];
            transmittances(&sigma, d, &mut fast);
            let mut plain = [0.0; M];
            transmittances_portable(&sigma, d, &mut plain);
            for i in 0..M / 2 {
                let want = exp_neg(sigma[0][i] * d[0] + sigma[1][i] * d[1] + sigma[2][i] * d[2]);
                assert_eq!(fast[i].to_bits(), want.to_bits(), "{d:?} #{i}");
                assert_eq!(plain[i].to_bits(), want.to_bits(), "{d:?} #{i}");
            }
            assert!(fast[M / 2..].iter().all(|x| *x == 0.0));
        }
    }

    #[test]
    fn ozone_closed_form_matches_adaptive_quadrature() {
        // Long grazing pieces are the hard case for a fixed rule.
        let mut worst = 0.0f64;
        for (h, mu) in [
            (0.0, 0.0),
            (10_000.0, 0.0),
            (24_000.0, 0.0),
            (39_999.0, -0.001),
            (5_000.0, 0.7),
            (60_000.0, -0.13),
        ] {
            let line = Line::new(h, mu);
            let q = line.s_squared_at_height(ATMOSPHERE_TOP_M);
            let (s0, s1) = (line.s_ref(), q.sqrt());
            let (b, n) = line.breaks(s0, line.radius(s0), s1, line.radius(s1));
            let mut exact = 0.0;
            for w in b[..n].windows(2) {
                exact += integrate_adaptive(|s| [ozone_density(line.height(s))], w[0].0, w[1].0, 0.0, 1e-15, 2000).value[0];
            }
            let got = line.ozone(s0, s1);
            // Both sides round the height near a kink to ~1e-11 m (see OZONE_ABS_ERROR_M).
            let d = (got - exact).abs();
            let rel = d / exact.max(1e-300);
            worst = worst.max(rel);
            assert!(d <= 0.1 * ozone_error(exact), "h {h} μ {mu}: {got} vs {exact}");
        }
        eprintln!("ozone closed form vs adaptive: worst relative {worst:.1e}");
    }
}
