//! The sky's reduced spectral path ("RGB fast path"): the single-scattering
//! integrals evaluated at a few wavelengths only, and the full 81-sample
//! spectrum reconstructed from them before it is turned into Rec.709.
//!
//! **Why it can work.** Klassen (seed §4, *Efficiency Considerations*) warns
//! against converting the coefficients to three RGB values *before*
//! integrating: the integrand is non-linear in the coefficients, so the
//! integral and the change of colour space do not commute. This path does not
//! do that. Every integral is still a correct spectral integral, at a node
//! wavelength; only the number of wavelengths is reduced. What is
//! interpolated is the *smooth factor* of each phase-free component,
//!
//! ```text
//! S_k(λ) = c_k(λ) · g_k(λ),     g_k(λ) = ∫ ρ_k(t) · exp(−Σ_j σ_j(λ) D_j(t)) dt
//! ```
//!
//! where `c_k(λ)` (the sun's spectrum times the species' scattering
//! coefficient, with all its Fraunhofer lines) is known exactly at every
//! wavelength, and `g_k` depends on λ only through the extinction
//! coefficients `σ_j(λ)` of the species (Rayleigh and ozone for the layered
//! atmosphere — the aerosol is grey; the total haze + molecule κ for Klassen).
//! `ln g_k` is a smooth function of those (its Taylor series in σ is the
//! cumulant expansion of the path-length distribution `D(t)`), so it is fitted
//! by least squares with a low-degree polynomial in the `σ_j` (scaled to
//! [−1, 1]) through the node values, and evaluated at all 81 wavelengths.
//!
//! **When it is used** is decided per render by measuring, not assumed: see
//! [`crate::sky::texture`] (`ColourPath::Auto`).

use crate::spectrum::{SPECTRAL_SAMPLES, Spectrum};

/// A reduced wavelength set: node indices into the 81-sample grid and the
/// polynomial degree of the fit of `ln g` in one or two spectral variables.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Bands {
    /// 9 wavelengths, every 50 nm (380, 430, …, 780 nm); degree 4 in one
    /// variable, 2 in two.
    Nodes9,
    /// 17 wavelengths, every 25 nm (380, 405, …, 780 nm); degree 6 in one
    /// variable, 3 in two.
    Nodes17,
}

impl Bands {
    /// Spacing of the nodes on the 5 nm grid, samples.
    fn step(self) -> usize {
        match self {
            Bands::Nodes9 => 10,
            Bands::Nodes17 => 5,
        }
    }

    /// Node indices into the 81-sample grid (ascending, first 0, last 80).
    pub fn nodes(self) -> impl Iterator<Item = usize> {
        (0..SPECTRAL_SAMPLES).step_by(self.step())
    }

    /// Number of node wavelengths.
    pub fn len(self) -> usize {
        (SPECTRAL_SAMPLES - 1) / self.step() + 1
    }

    /// Always false (a band set has at least 9 nodes).
    pub fn is_empty(self) -> bool {
        false
    }

    /// Short description for reports.
    pub fn describe(self) -> String {
        format!("{} wavelengths every {} nm", self.len(), 5 * self.step())
    }

    fn degree(self, nvars: usize) -> usize {
        match (self, nvars) {
            (_, 0) => 0,
            (Bands::Nodes9, 1) => 4,
            (Bands::Nodes9, _) => 2,
            (Bands::Nodes17, 1) => 6,
            (Bands::Nodes17, _) => 3,
        }
    }

    /// Reconstructs `g` at all 81 wavelengths from its values `g_nodes` at
    /// [`Self::nodes`]. `vars[v]` are the spectral variables (e.g. extinction
    /// coefficients, any unit) on the full grid; constant ones are ignored.
    /// `ln g` is fitted when every node value is positive and finite, `g`
    /// itself otherwise (all zero gives zero). Same as
    /// `self.expander(vars).apply(g_nodes)`; build the [`Expander`] once when
    /// the variables do not change.
    pub fn expand(self, vars: &[&Spectrum], g_nodes: &[f64]) -> Spectrum {
        self.expander(vars).apply(g_nodes)
    }

    /// The least-squares fit of [`Self::expand`] as a linear map from the
    /// node values (of `ln g`, or of `g`) to all 81 wavelengths: the fit's
    /// coefficients are `(AᵀA)⁻¹Aᵀy` for the node design matrix A, so the
    /// reconstruction is `B(AᵀA)⁻¹Aᵀ y` with B the design matrix on the full
    /// grid, precomputed here once.
    pub fn expander(self, vars: &[&Spectrum]) -> Expander {
        // Scaled variables in [−1, 1]; constant ones dropped.
        let mut scaled: Vec<Spectrum> = Vec::with_capacity(2);
        for v in vars.iter().take(2) {
            let (lo, hi) = v
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(*x), b.max(*x)));
            if hi > lo && hi.is_finite() && lo.is_finite() {
                scaled.push(std::array::from_fn(|i| 2.0 * (v[i] - lo) / (hi - lo) - 1.0));
            }
        }
        let degree = self.degree(scaled.len());
        // Monomials of total degree ≤ `degree` in the scaled variables.
        let exps: Vec<(usize, usize)> = match scaled.len() {
            0 => vec![(0, 0)],
            1 => (0..=degree).map(|a| (a, 0)).collect(),
            _ => (0..=degree).flat_map(|a| (0..=degree - a).map(move |b| (a, b))).collect(),
        };
        let basis = |i: usize| -> Vec<f64> {
            let x = scaled.first().map_or(0.0, |s| s[i]);
            let y = scaled.get(1).map_or(0.0, |s| s[i]);
            exps.iter().map(|&(a, b)| x.powi(a as i32) * y.powi(b as i32)).collect()
        };
        let nodes: Vec<usize> = self.nodes().collect();
        let n = nodes.len();
        let p = exps.len();
        // (AᵀA)⁻¹Aᵀ by Gauss–Jordan elimination with pivoting on [AᵀA | Aᵀ]
        // (p ≤ 10, well scaled).
        let mut m = vec![vec![0.0; p + n]; p];
        for (row, &node) in nodes.iter().enumerate() {
            let b = basis(node);
            for r in 0..p {
                for c in 0..p {
                    m[r][c] += b[r] * b[c];
                }
                m[r][p + row] += b[r];
            }
        }
        for col in 0..p {
            let piv = (col..p).max_by(|a, b| m[*a][col].abs().total_cmp(&m[*b][col].abs())).unwrap_or(col);
            m.swap(col, piv);
            let d = m[col][col];
            if d.abs() < 1e-300 {
                continue;
            }
            for c in col..p + n {
                m[col][c] /= d;
            }
            for r in 0..p {
                if r != col {
                    let f = m[r][col];
                    if f != 0.0 {
                        for c in col..p + n {
                            m[r][c] -= f * m[col][c];
                        }
                    }
                }
            }
        }
        // Map row i: Σ_r basis_r(i) · [(AᵀA)⁻¹Aᵀ]_r.
        let mut map = vec![0.0; SPECTRAL_SAMPLES * n];
        for i in 0..SPECTRAL_SAMPLES {
            let b = basis(i);
            for j in 0..n {
                map[i * n + j] = (0..p).map(|r| if m[r][r] != 0.0 { b[r] * m[r][p + j] } else { 0.0 }).sum();
            }
        }
        Expander { bands: self, map }
    }
}

/// The reconstruction of [`Bands::expand`] for fixed spectral variables: a
/// precomputed 81 × (node count) linear map.
#[derive(Debug, Clone, PartialEq)]
pub struct Expander {
    bands: Bands,
    /// Row-major, 81 rows.
    map: Vec<f64>,
}

impl Expander {
    /// The band set.
    pub fn bands(&self) -> Bands {
        self.bands
    }

    /// Reconstructs `g` at all 81 wavelengths from its node values (see [`Bands::expand`]).
    pub fn apply(&self, g_nodes: &[f64]) -> Spectrum {
        let n = self.bands.len();
        debug_assert_eq!(g_nodes.len(), n);
        if g_nodes.iter().all(|g| *g == 0.0) {
            return [0.0; SPECTRAL_SAMPLES];
        }
        let log = g_nodes.iter().all(|g| g.is_finite() && *g > 0.0);
        let y: Vec<f64> = g_nodes.iter().map(|g| if log { g.ln() } else { *g }).collect();
        let mut out = [0.0; SPECTRAL_SAMPLES];
        for (i, o) in out.iter_mut().enumerate() {
            let v: f64 = self.map[i * n..(i + 1) * n].iter().zip(&y).map(|(m, y)| m * y).sum();
            *o = if log { v.exp() } else { v };
        }
        // The node values themselves are exact: keep them.
        for (k, node) in self.bands.nodes().enumerate() {
            out[node] = g_nodes[k];
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spectrum::wavelengths_nm;

    #[test]
    fn expansion_reproduces_a_mixture_of_exponentials() {
        // g(λ) = Σ w_j exp(−σ(λ) D_j): a path-length mixture, as in the sky. The
        // second case (optical depths up to ~16 at 380 nm) is a stress case: 17 nodes
        // give ~8e-3 there, which is why the texture measures before it uses a band set.
        let wl = wavelengths_nm();
        let sigma: Spectrum = std::array::from_fn(|i| (550.0 / wl[i]).powi(4));
        let ozone: Spectrum = std::array::from_fn(|i| (-((wl[i] - 600.0) / 80.0).powi(2)).exp());
        for (ds, tol) in [(&[0.1, 0.3][..], 2e-5), (&[0.5, 2.0, 4.0][..], 1e-2)] {
            let g: Spectrum = std::array::from_fn(|i| ds.iter().map(|d| (-sigma[i] * d - 0.3 * ozone[i] * d).exp()).sum());
            for bands in [Bands::Nodes9, Bands::Nodes17] {
                let nodes: Vec<f64> = bands.nodes().map(|n| g[n]).collect();
                let r = bands.expand(&[&sigma, &ozone], &nodes);
                let worst = (0..SPECTRAL_SAMPLES).fold(0.0f64, |m, i| m.max((r[i] - g[i]).abs() / g[i]));
                eprintln!("{bands:?} D = {ds:?}: worst relative error {worst:.2e}");
                if bands == Bands::Nodes17 {
                    assert!(worst < tol, "{bands:?} {ds:?}: {worst:.2e}");
                }
            }
        }
        // All zero stays zero; a single variable works; constants are ignored.
        assert_eq!(Bands::Nodes9.expand(&[&sigma], &[0.0; 9]), [0.0; SPECTRAL_SAMPLES]);
        let flat = [1.0; SPECTRAL_SAMPLES];
        let g: Spectrum = std::array::from_fn(|i| (-sigma[i]).exp());
        let nodes: Vec<f64> = Bands::Nodes17.nodes().map(|n| g[n]).collect();
        let r = Bands::Nodes17.expand(&[&flat, &sigma], &nodes);
        assert!((0..SPECTRAL_SAMPLES).all(|i| (r[i] - g[i]).abs() < 1e-9 * g[i]));
    }
}
