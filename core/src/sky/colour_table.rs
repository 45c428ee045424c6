//! The colour of attenuated sunlight as a function of two columns: the
//! layered atmosphere's spectral sum done once per sky, not at every
//! scattering point.
//!
//! # Derivation
//!
//! At a scattering point P of a view ray the single-scattering integrand of
//! [`crate::sky::atmosphere`] is, per wavelength,
//!
//! ```text
//! E₀(λ) β_k(λ) ρ_k(P) · exp(−a β_R(λ) C_R − d β_M,ext C_M − o β_O(λ) C_O)
//! ```
//!
//! (k = Rayleigh or Mie; `C_j` the columns observer → P → sun; a, d, o the
//! density multipliers). The image needs only its CIE XYZ,
//! `Σ_λ w_c(λ)·(…)` with the colour-matching weights `w_c` of
//! [`crate::spectrum::spectrum_to_xyz`] — a sum that is linear, so it
//! commutes with the integral along the ray *exactly* (this is not Klassen's
//! warned-against conversion of the coefficients to RGB before integrating:
//! every wavelength is still attenuated by its own exponential). The aerosol
//! is grey, so its factor `exp(−d β_M C_M)` leaves the sum, and what remains
//! is a function of two columns only:
//!
//! ```text
//! G_kc(C_R, C_O) = Σ_λ w_c(λ) E₀(λ) β_k(λ) · exp(−a β_R(λ) C_R − o β_O(λ) C_O)
//! XYZ_kc(P)      = ρ_k(P) · exp(−d β_M,ext C_M) · G_kc(C_R, C_O)
//! ```
//!
//! Six functions (two species × X, Y, Z), each a positive sum of
//! exponentials, so `ln G` is smooth and convex (its derivatives are the
//! cumulants of β_R and β_O under the weights `w E₀ β e^{−τ}`). The table
//! holds `ln G` and its first and mixed derivatives (computed exactly, from
//! the same sum) on a uniform grid in `C_R × C_O`; between the nodes it is
//! bicubic Hermite, `C¹`, with interpolation error ~ h⁴·∂⁴ln G/384 per axis.
//!
//! # Error, measured
//!
//! After the build, `ln G` is compared with the exact sum at the centre of
//! every cell (where a cubic Hermite interpolant's error peaks in both axes
//! at once). Twice the largest relative difference is the table's error
//! bound, charged to every point it serves
//! ([`ColourTable::relative_error`]); the table is refined (node spacing
//! halved) until that bound is at most the requested share of the
//! tolerance, or given up for the spectral path if that needs more than
//! [`MAX_NODES`] nodes. Columns beyond the table (they do not occur in this
//! atmosphere, whose longest column pair is tabulated) are summed directly.
//!
//! # Cost
//!
//! Building: one exponential per (node row, wavelength) and per (node
//! column, wavelength), then `81 × 28` multiply-adds per node (see
//! [`ColourTable::build`]). A look-up: 16 Hermite weights, `6 × 16`
//! multiply-adds and six exponentials, instead of 81 exponentials and
//! `2 × 81` products per point on the spectral path, and the quadrature
//! then carries six values per node instead of 162.

use crate::sky::optical_depth::exp_neg;
use crate::spectrum::{SPECTRAL_SAMPLES, Spectrum, solar_spectral_irradiance};
use rayon::prelude::*;

/// Largest number of table nodes before the spectral path is used instead.
pub const MAX_NODES: usize = 1 << 16;

/// Outputs per node: X, Y, Z of the Rayleigh part, then of the Mie part.
pub const OUTPUTS: usize = 6;

/// What one species contributes per unit column to the exponent and what
/// weights the colour sum, for [`ColourTable::build`].
#[derive(Debug, Clone)]
pub struct ColourSums {
    /// Rayleigh extinction per unit Rayleigh column, m⁻¹ per wavelength (`a β_R(λ)`), ≥ 0.
    pub sigma_rayleigh: Spectrum,
    /// Ozone absorption per unit ozone column, m⁻¹ per wavelength (`o β_O(λ)`), ≥ 0.
    pub sigma_ozone: Spectrum,
    /// Weights of the six outputs per wavelength (`w_c(λ) E₀(λ) β_k(λ)`), ≥ 0.
    pub weights: [Spectrum; OUTPUTS],
}

impl ColourSums {
    /// The six weights for the scattering spectra `scattering[k]` (Rayleigh,
    /// Mie; m⁻¹ per wavelength) and the XYZ weights of
    /// [`crate::spectrum::spectrum_to_xyz`] times the solar spectrum.
    pub fn new(sigma_rayleigh: Spectrum, sigma_ozone: Spectrum, scattering: [&Spectrum; 2]) -> ColourSums {
        let e0 = solar_spectral_irradiance();
        let xyz = xyz_weights();
        ColourSums {
            sigma_rayleigh,
            sigma_ozone,
            weights: std::array::from_fn(|o| std::array::from_fn(|i| xyz[o % 3][i] * e0[i] * scattering[o / 3][i])),
        }
    }

    /// The six sums at columns (C_R, C_O), m, exactly (81 exponentials).
    fn sums(&self, c_r: f64, c_o: f64) -> [f64; OUTPUTS] {
        let mut out = [0.0; OUTPUTS];
        for i in 0..SPECTRAL_SAMPLES {
            let e = exp_neg(self.sigma_rayleigh[i] * c_r + self.sigma_ozone[i] * c_o);
            for (o, w) in self.weights.iter().enumerate() {
                out[o] += w[i] * e;
            }
        }
        out
    }

    /// The exponential factors per wavelength at the columns
    /// `(k + offset) · step` of each axis, `k < count`: one exponential per
    /// point and wavelength, so that a grid of sums needs only products.
    fn factors(&self, count: [usize; 2], step: [f64; 2], offset: [f64; 2]) -> (Vec<Spectrum>, Vec<Spectrum>) {
        let along = |sigma: &Spectrum, axis: usize| -> Vec<Spectrum> {
            (0..count[axis])
                .map(|k| std::array::from_fn(|l| exp_neg(sigma[l] * step[axis] * (k as f64 + offset[axis]))))
                .collect()
        };
        (along(&self.sigma_rayleigh, 0), along(&self.sigma_ozone, 1))
    }
}

/// The XYZ weights of [`crate::spectrum::spectrum_to_xyz`] (its response to a
/// unit sample at each wavelength).
fn xyz_weights() -> [Spectrum; 3] {
    let mut w = [[0.0; SPECTRAL_SAMPLES]; 3];
    for i in 0..SPECTRAL_SAMPLES {
        let mut unit = [0.0; SPECTRAL_SAMPLES];
        unit[i] = 1.0;
        let xyz = crate::spectrum::spectrum_to_xyz(&unit);
        for c in 0..3 {
            w[c][i] = xyz[c];
        }
    }
    w
}

/// Lanes per node quantity: the six outputs padded to eight, so that the
/// look-up's loops over outputs fill whole vector registers.
const LANES: usize = 8;

/// `ln G` and its derivatives `∂_R ln G`, `∂_O ln G`, `∂_R∂_O ln G` at one
/// node (per unit of the node spacing, so the Hermite basis works on
/// `[0, 1]`), each for the outputs in lanes `0..OUTPUTS` (the rest 0).
type NodeValues = [[f64; LANES]; 4];

/// A bicubic Hermite table of `ln G_kc(C_R, C_O)` (module docs).
#[derive(Debug, Clone)]
pub struct ColourTable {
    sums: ColourSums,
    /// 1 for the outputs present, 0 for those whose weights are all zero
    /// (e.g. no aerosol) and for the padding lanes.
    present: [f64; LANES],
    nodes: [usize; 2],
    step: [f64; 2],
    max: [f64; 2],
    values: Vec<NodeValues>,
    relative_error: f64,
}

impl ColourTable {
    /// Builds a table over `C_R ∈ [0, max_columns[0]]`, `C_O ∈ [0, max_columns[1]]`
    /// (m, each > 0) whose measured error is at most `target_error`
    /// (relative, > 0). `None` if that takes more than [`MAX_NODES`] nodes.
    ///
    /// A coarse table (65 × 9 nodes) first measures each axis's error at
    /// its edge midpoints. A cubic Hermite interpolant's error falls as the
    /// spacing⁴, and the charged bound is twice the cell-centre error, about
    /// the sum of the two axes', so the node counts chosen are the fewest
    /// (halving each axis's spacing k times) whose predicted bound is within
    /// 0.8 × the target. The table of that size is built and measured;
    /// should it still miss, the worse axis is halved again.
    pub fn build(sums: ColourSums, max_columns: [f64; 2], target_error: f64) -> Option<ColourTable> {
        let absent: [bool; OUTPUTS] = std::array::from_fn(|o| sums.weights[o].iter().all(|w| *w == 0.0));
        // An axis whose species is absent is constant: two nodes suffice.
        let flat = [
            sums.sigma_rayleigh.iter().all(|s| *s == 0.0),
            sums.sigma_ozone.iter().all(|s| *s == 0.0),
        ];
        let mut nodes = [if flat[0] { 2 } else { 65 }, if flat[1] { 2 } else { 9 }];
        let coarse = Self::build_at(&sums, absent, nodes, max_columns);
        let axis_error = |axis: usize| {
            if flat[axis] {
                0.0
            } else {
                coarse.measure(if axis == 0 { [0.5, 0.0] } else { [0.0, 0.5] })
            }
        };
        let (e_r, e_o) = (axis_error(0), axis_error(1));
        // The fewest nodes whose predicted bound 2·(e_R + e_O) (after k
        // halvings an axis errs 16^k times less) is within 0.8 × the target.
        let mut best: Option<(usize, [usize; 2])> = None;
        for k_r in 0..=if flat[0] { 0 } else { 8 } {
            for k_o in 0..=if flat[1] { 0 } else { 8 } {
                let predicted = 2.0 * (e_r / 16f64.powi(k_r) + e_o / 16f64.powi(k_o));
                let n = [((nodes[0] - 1) << k_r) + 1, ((nodes[1] - 1) << k_o) + 1];
                if predicted <= 0.8 * target_error && best.is_none_or(|b| n[0] * n[1] < b.0) {
                    best = Some((n[0] * n[1], n));
                }
            }
        }
        nodes = best.map_or([(nodes[0] - 1) * 256 + 1, (nodes[1] - 1) * 256 + 1], |b| b.1);
        loop {
            if nodes[0] * nodes[1] > MAX_NODES {
                return None;
            }
            let table = Self::build_at(&sums, absent, nodes, max_columns);
            if table.relative_error <= target_error {
                return Some(table);
            }
            let axis = if flat[0] {
                1
            } else if flat[1] || table.measure([0.5, 0.0]) >= table.measure([0.0, 0.5]) {
                0
            } else {
                1
            };
            nodes[axis] = 2 * nodes[axis] - 1;
        }
    }

    fn build_at(sums: &ColourSums, absent: [bool; OUTPUTS], nodes: [usize; 2], max: [f64; 2]) -> ColourTable {
        let step = [max[0] / (nodes[0] - 1) as f64, max[1] / (nodes[1] - 1) as f64];
        let (rows, cols) = sums.factors(nodes, step, [0.0, 0.0]);
        let values: Vec<NodeValues> = (0..nodes[0] * nodes[1])
            .into_par_iter()
            .map(|n| {
                let (i, j) = (n / nodes[1], n % nodes[1]);
                // G, ∂_R G, ∂_O G, ∂_R∂_O G per output.
                let mut g = [[0.0; 4]; OUTPUTS];
                for l in 0..SPECTRAL_SAMPLES {
                    let e = rows[i][l] * cols[j][l];
                    let (sr, so) = (sums.sigma_rayleigh[l], sums.sigma_ozone[l]);
                    let terms = [e, -sr * e, -so * e, sr * so * e];
                    for (o, w) in sums.weights.iter().enumerate() {
                        for (q, t) in terms.iter().enumerate() {
                            g[o][q] += w[l] * t;
                        }
                    }
                }
                let mut node = [[0.0; LANES]; 4];
                for o in 0..OUTPUTS {
                    let [v, dr, dz, drz] = g[o];
                    if absent[o] || v <= 0.0 {
                        continue;
                    }
                    let (lr, lz) = (dr / v, dz / v);
                    let q = [v.ln(), lr * step[0], lz * step[1], (drz / v - lr * lz) * step[0] * step[1]];
                    for k in 0..4 {
                        node[k][o] = q[k];
                    }
                }
                node
            })
            .collect();
        let mut table = ColourTable {
            sums: sums.clone(),
            present: std::array::from_fn(|o| if o < OUTPUTS && !absent[o] { 1.0 } else { 0.0 }),
            nodes,
            step,
            max,
            values,
            relative_error: 0.0,
        };
        table.relative_error = 2.0 * table.measure([0.5, 0.5]);
        table
    }

    /// Largest relative difference to the exact sums at the points
    /// `(i + offset[0], j + offset[1])` (in node spacings) of every cell:
    /// offsets ½, ½ are the cell centres, ½, 0 the midpoints of the edges
    /// along C_R (where only the C_R interpolation errs), 0, ½ along C_O.
    fn measure(&self, offset: [f64; 2]) -> f64 {
        let cells = [self.nodes[0] - 1, self.nodes[1] - 1];
        let (rows, cols) = self.sums.factors(cells, self.step, offset);
        (0..cells[0] * cells[1])
            .into_par_iter()
            .map(|n| {
                let (i, j) = (n / cells[1], n % cells[1]);
                let mut exact = [0.0; OUTPUTS];
                for l in 0..SPECTRAL_SAMPLES {
                    let e = rows[i][l] * cols[j][l];
                    for (o, w) in self.sums.weights.iter().enumerate() {
                        exact[o] += w[l] * e;
                    }
                }
                let table = self.interpolate((i as f64 + offset[0]) * self.step[0], (j as f64 + offset[1]) * self.step[1]);
                (0..OUTPUTS).fold(0.0f64, |m, o| {
                    if exact[o] > 0.0 {
                        m.max(((table[o] - exact[o]) / exact[o]).abs())
                    } else {
                        m
                    }
                })
            })
            .reduce(|| 0.0, f64::max)
    }

    /// Twice the largest relative error measured at the cell centres: the
    /// bound charged to every value the table gives (an estimate from the
    /// points where the interpolation error peaks, not a proof).
    pub fn relative_error(&self) -> f64 {
        self.relative_error
    }

    /// Nodes along C_R and C_O.
    pub fn nodes(&self) -> [usize; 2] {
        self.nodes
    }

    /// The largest tabulated columns (C_R, C_O), m.
    pub fn max_columns(&self) -> [f64; 2] {
        self.max
    }

    /// The six sums at columns `c_r`, `c_o` (m, ≥ 0): from the table inside
    /// it, else summed exactly (negative columns taken as 0); NaN for a NaN
    /// column. Returns whether the table served.
    #[inline]
    pub fn lookup(&self, c_r: f64, c_o: f64) -> ([f64; OUTPUTS], bool) {
        if c_r >= 0.0 && c_r <= self.max[0] && c_o >= 0.0 && c_o <= self.max[1] {
            (self.interpolate(c_r, c_o), true)
        } else if c_r.is_nan() || c_o.is_nan() {
            ([f64::NAN; OUTPUTS], false)
        } else {
            (self.sums.sums(c_r.max(0.0), c_o.max(0.0)), false)
        }
    }

    /// Bicubic Hermite interpolation of `ln G`, exponentiated; columns inside
    /// the table. Compiled a second time for AVX2 and taken where the CPU has
    /// it (the same operations, so the same results).
    #[inline]
    fn interpolate(&self, c_r: f64, c_o: f64) -> [f64; OUTPUTS] {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            return unsafe { self.interpolate_avx2(c_r, c_o) };
        }
        self.interpolate_portable(c_r, c_o)
    }

    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    fn interpolate_avx2(&self, c_r: f64, c_o: f64) -> [f64; OUTPUTS] {
        self.interpolate_portable(c_r, c_o)
    }

    #[inline(always)]
    fn interpolate_portable(&self, c_r: f64, c_o: f64) -> [f64; OUTPUTS] {
        let (x, y) = (c_r / self.step[0], c_o / self.step[1]);
        let i = (x as usize).min(self.nodes[0] - 2);
        let j = (y as usize).min(self.nodes[1] - 2);
        let (s, t) = (x - i as f64, y - j as f64);
        let hs = hermite(s);
        let ht = hermite(t);
        let n = self.nodes[1];
        let corners = [
            (&self.values[i * n + j], 0, 0),
            (&self.values[i * n + j + 1], 0, 1),
            (&self.values[(i + 1) * n + j], 1, 0),
            (&self.values[(i + 1) * n + j + 1], 1, 1),
        ];
        let mut ln_g = [0.0; LANES];
        for (node, a, b) in corners {
            // Weights of (value, ∂s, ∂t, ∂s∂t) at this corner.
            let (fs, ds) = (hs[a], hs[2 + a]);
            let (ft, dt) = (ht[b], ht[2 + b]);
            let w = [fs * ft, ds * ft, fs * dt, ds * dt];
            for q in 0..4 {
                for o in 0..LANES {
                    ln_g[o] += w[q] * node[q][o];
                }
            }
        }
        let mut g = [0.0; LANES];
        for o in 0..LANES {
            g[o] = self.present[o] * exp_neg(-ln_g[o]);
        }
        std::array::from_fn(|o| g[o])
    }
}

/// Cubic Hermite basis on `[0, 1]` at `s`: `[h00, h01, h10, h11]` — the
/// weights of the value at 0, the value at 1, the slope at 0, the slope at 1.
#[inline]
fn hermite(s: f64) -> [f64; 4] {
    let s2 = s * s;
    let s3 = s2 * s;
    [2.0 * s3 - 3.0 * s2 + 1.0, -2.0 * s3 + 3.0 * s2, s3 - 2.0 * s2 + s, s3 - s2]
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sky::atmosphere::{AtmosphereParams, ozone_absorption_spectrum, rayleigh_scattering_spectrum};

    fn sums_of(p: &AtmosphereParams) -> ColourSums {
        let r = rayleigh_scattering_spectrum();
        let o = ozone_absorption_spectrum();
        let air: Spectrum = std::array::from_fn(|i| p.air_density * r[i]);
        let mie = [p.aerosol_density * crate::sky::atmosphere::MIE_SCATTERING_PER_M; SPECTRAL_SAMPLES];
        ColourSums::new(air, std::array::from_fn(|i| p.ozone_density * o[i]), [&air, &mie])
    }

    /// The table's claimed error holds at random columns against the exact sum,
    /// and the table meets the target it was built for.
    #[test]
    fn table_matches_the_spectral_sum_within_its_bound() {
        let p = AtmosphereParams::default();
        for target in [1e-5, 1e-7] {
            let t = ColourTable::build(sums_of(&p), [1.2e6, 1.5e6], target).expect("fits");
            assert!(t.relative_error() <= target, "{} > {target}", t.relative_error());
            let mut worst = 0.0f64;
            let mut rnd = crate::test_support::uniform(0x2545F4914F6CDD1D);
            for _ in 0..20_000 {
                let (c_r, c_o) = (1.2e6 * rnd(), 1.5e6 * rnd());
                let (got, served) = t.lookup(c_r, c_o);
                assert!(served);
                let exact = t.sums.sums(c_r, c_o);
                for o in 0..OUTPUTS {
                    worst = worst.max(((got[o] - exact[o]) / exact[o]).abs());
                }
            }
            eprintln!(
                "target {target:e}: nodes {:?}, claimed {:.2e}, worst at random points {worst:.2e}",
                t.nodes(),
                t.relative_error()
            );
            assert!(worst <= t.relative_error(), "{worst} > {}", t.relative_error());
            // Outside the table: summed exactly; a NaN column stays NaN.
            let (beyond, served) = t.lookup(3e6, 0.0);
            assert!(!served && beyond == t.sums.sums(3e6, 0.0));
            assert!(t.lookup(f64::NAN, 1.0).0.iter().all(|x| x.is_nan()));
        }
    }
}
