//! Visible-range spectra, CIE colorimetry and the extraterrestrial solar spectrum.
//!
//! This module is the bridge between per-wavelength physics (scattering and
//! absorption coefficients, transmittances, the Sun) and the linear Rec.709 RGB
//! values a renderer writes out. Everything here is **linear**: no gamma, no
//! tone mapping, no clamping (except in [`spectral_transmittance_to_rgb`], which
//! is an averaging and cannot leave `[0, 1]` anyway).
//!
//! # Spectral grid
//!
//! A [`Spectrum`] holds [`SPECTRAL_SAMPLES`] = 81 samples at
//! λᵢ = [`LAMBDA_MIN_NM`] + i·[`LAMBDA_STEP_NM`], i.e. 380, 385, …, 780 nm
//! inclusive ([`wavelengths_nm`]). Wavelengths are in vacuum nanometres. The
//! samples are point values of a spectral density (e.g. spectral radiance in
//! W·m⁻²·sr⁻¹·nm⁻¹, spectral irradiance in W·m⁻²·nm⁻¹) or of a dimensionless
//! spectral factor (transmittance, albedo, …).
//!
//! # Integration rule and normalisation
//!
//! All integrals over wavelength are **simple Riemann sums** on the grid,
//! Σᵢ f(λᵢ)·Δλ with Δλ = 5 nm and all 81 samples weighted equally — the
//! summation CIE 15 prescribes for its 5 nm tables. Tristimulus values are
//!
//! ```text
//! X = k · Σᵢ S(λᵢ) x̄(λᵢ) Δλ,  Y = k · Σᵢ S(λᵢ) ȳ(λᵢ) Δλ,  Z = k · Σᵢ S(λᵢ) z̄(λᵢ) Δλ
//! k = (LAMBDA_MAX_NM − LAMBDA_MIN_NM) / (Σᵢ ȳ(λᵢ) Δλ) = 400 nm / 106.856635 nm ≈ 3.7433
//! ```
//!
//! so a flat spectrum of value c (say W·m⁻²·sr⁻¹·nm⁻¹) has Y = 400·c
//! (W·m⁻²·sr⁻¹): Y is the radiance that an equal-energy spectrum of the same
//! luminance carries between 380 and 780 nm. XYZ and Rec.709 RGB therefore
//! have the units of the spectrum times nanometres (radiance for a spectral
//! radiance, irradiance for a spectral irradiance). The photometric
//! luminance is L_v = 683 lm/W · Σ ȳ S Δλ = 683 · (106.856635 / 400) · Y
//! ≈ 182.46 · Y cd/m² when S is a spectral radiance in W·m⁻²·sr⁻¹·nm⁻¹.
//!
//! # Colour spaces
//!
//! [`xyz_to_rec709`] uses linear Rec.709 / sRGB primaries (ITU-R BT.709-6,
//! *Parameter values for the HDTV standards*, 2015, items 1.3–1.4:
//! R (0.640, 0.330), G (0.300, 0.600), B (0.150, 0.060)) with the D65 white
//! normalised to Y = 1. The 3×3 matrix ([`XYZ_TO_REC709`]) is derived exactly
//! (in `const` evaluation) from those primaries and the CIE D65 white
//! tristimulus values for the 1931 observer, (X, Y, Z) = (0.95047, 1, 1.08883)
//! (CIE 15:2004 *Colorimetry*, 3rd ed., Table T.3); this is the widely used
//! matrix tabulated by B. Lindbloom (`3.2404542 −1.5371385 −0.4985314 …`) and
//! agrees with the rounded four-decimal matrix of IEC 61966-2-1:1999 (sRGB)
//! to within 3.7·10⁻⁴ per element. With it, D65 maps to RGB (1, 1, 1).
//!
//! [`rec709_to_spectrum`] is a **linear** spectral upsampling (the least-norm
//! spectrum with the requested colour) whose only promise is the exact
//! round-trip `spectrum_to_rec709(rec709_to_spectrum(c)) == c`; see its docs.
//!
//! # Data tables (embedded CSV under `data/`)
//!
//! * `data/cie1931_2deg_5nm.csv` — **CIE 1931 2° standard colorimetric observer
//!   colour-matching functions** x̄, ȳ, z̄, 380–780 nm at 5 nm (International
//!   Commission on Illumination, CIE 15:2004 *Colorimetry*, 3rd ed., Table
//!   T.4). The numbers were taken from the 1 nm CIE 1931 table as distributed
//!   by the Colour & Vision Research Laboratory (CVRL, file `ciexyz31_1.csv`;
//!   the CIE publishes the 1 nm table in ISO/CIE 11664-1:2019 and as the
//!   dataset *Colour-matching functions of CIE 1931 standard colorimetric
//!   observer*, 2019, DOI 10.25039/CIE.DS.xvudnb9b) as copied in the public
//!   repositories
//!   `hexiruwu/2025_huashu_C_problem` (`CIE_xyz_1931_2deg.csv`) and
//!   `coloria-dev/color-data` (`observers/cie-1931-2.json`), which agree to
//!   5·10⁻⁶ relative; the rows at multiples of 5 nm were taken and rounded to
//!   six decimals, which reproduces the CIE 15 5 nm table (ȳ(555) = 1.000000,
//!   ȳ(560) = 0.995000, x̄(600) = 1.062200, z̄(450) = 1.772110, and the
//!   published column sums 21.371524, 21.371327, 21.371540).
//! * `data/astm_e490_am0_5nm.csv` — **ASTM E490-00a AM0 extraterrestrial solar
//!   spectral irradiance** at 1 AU (ASTM International, *Standard Solar Constant
//!   and Zero Air Mass Solar Spectral Irradiance Tables*, E490-00a, 2000, solar
//!   constant 1366.1 W/m²), in W·m⁻²·nm⁻¹. Source numbers: NREL's distribution
//!   file `E490_00a_AM0` (rredc.nrel.gov/solar/spectra/am0/ASTM2000.html) as
//!   copied in the public repository `aphalo/photobiologySun`
//!   (`data-raw/reference-spectra/E490_00a_AM0.csv`, columns
//!   `Wavelength microns`, `E-490 W/m2/micron`). The source table has 1 nm
//!   steps below 630 nm and 2 nm steps above; each 5 nm value here is the
//!   **box average over [λ − 2.5, λ + 2.5] nm of the linear interpolant** of
//!   the source table (so line structure is smoothed, energy is conserved).
//!   The source table integrates (trapezoid) to 654.95 W/m² over 380–780 nm,
//!   48 % of the solar constant; the ASTM G173-03 extraterrestrial column
//!   (same repository, `ASTMG173.csv`) gives 655.88 W/m².
//!
//! The CSV files start with one `#` comment line citing the source, then a
//! header line, then one row per grid wavelength. They are parsed once, on
//! first use (`LazyLock`); a malformed embedded table is a programming error
//! and panics with a message naming the table and line.

use std::sync::LazyLock;

/// Shortest wavelength of the spectral grid, in nm.
pub const LAMBDA_MIN_NM: f64 = 380.0;
/// Longest wavelength of the spectral grid (inclusive), in nm.
pub const LAMBDA_MAX_NM: f64 = 780.0;
/// Spacing of the spectral grid, in nm (also the Δλ of every wavelength sum).
pub const LAMBDA_STEP_NM: f64 = 5.0;
/// Number of samples of a [`Spectrum`]: 380–780 nm inclusive at 5 nm.
pub const SPECTRAL_SAMPLES: usize = 81;

/// A function of wavelength sampled at [`wavelengths_nm`] (380, 385, …, 780 nm).
///
/// Units are those of the quantity sampled (e.g. W·m⁻²·sr⁻¹·nm⁻¹ for a
/// spectral radiance, 1 for a transmittance).
pub type Spectrum = [f64; SPECTRAL_SAMPLES];

const _: () = assert!(
    LAMBDA_MIN_NM + (SPECTRAL_SAMPLES - 1) as f64 * LAMBDA_STEP_NM == LAMBDA_MAX_NM,
    "spectral grid constants are inconsistent"
);

static WAVELENGTHS: Spectrum = {
    let mut a = [0.0; SPECTRAL_SAMPLES];
    let mut i = 0;
    while i < SPECTRAL_SAMPLES {
        a[i] = LAMBDA_MIN_NM + i as f64 * LAMBDA_STEP_NM;
        i += 1;
    }
    a
};

/// The grid wavelengths in nm: `[380.0, 385.0, …, 780.0]` (exact values).
pub fn wavelengths_nm() -> &'static Spectrum {
    &WAVELENGTHS
}

/// Samples `f(λ)` (λ in nm) on the spectral grid.
pub fn spectrum_from_fn(mut f: impl FnMut(f64) -> f64) -> Spectrum {
    std::array::from_fn(|i| f(WAVELENGTHS[i]))
}

// ---------------------------------------------------------------------------
// Rec.709 matrices (const-evaluated from the primaries and the D65 white)
// ---------------------------------------------------------------------------

/// Chromaticities (x, y) of the Rec.709 R, G, B primaries (ITU-R BT.709-6).
const REC709_PRIMARIES_XY: [[f64; 2]; 3] = [[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]];

/// CIE D65 tristimulus values for the 1931 2° observer, Y = 1 (CIE 15:2004 Table T.3).
const D65_WHITE_XYZ: [f64; 3] = [0.95047, 1.0, 1.08883];

const fn det3(m: &[[f64; 3]; 3]) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// Inverse of a 3×3 matrix by the adjugate (the callers' matrices are far from singular).
const fn invert3(m: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let d = det3(m);
    let inv_d = 1.0 / d;
    [
        [
            (m[1][1] * m[2][2] - m[1][2] * m[2][1]) * inv_d,
            (m[0][2] * m[2][1] - m[0][1] * m[2][2]) * inv_d,
            (m[0][1] * m[1][2] - m[0][2] * m[1][1]) * inv_d,
        ],
        [
            (m[1][2] * m[2][0] - m[1][0] * m[2][2]) * inv_d,
            (m[0][0] * m[2][2] - m[0][2] * m[2][0]) * inv_d,
            (m[0][2] * m[1][0] - m[0][0] * m[1][2]) * inv_d,
        ],
        [
            (m[1][0] * m[2][1] - m[1][1] * m[2][0]) * inv_d,
            (m[0][1] * m[2][0] - m[0][0] * m[2][1]) * inv_d,
            (m[0][0] * m[1][1] - m[0][1] * m[1][0]) * inv_d,
        ],
    ]
}

const fn mat_vec(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    [
        m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2],
        m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
        m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2],
    ]
}

const fn mat_mul(a: &[[f64; 3]; 3], b: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut out = [[0.0; 3]; 3];
    let mut i = 0;
    while i < 3 {
        let mut j = 0;
        while j < 3 {
            out[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
            j += 1;
        }
        i += 1;
    }
    out
}

/// Columns = XYZ of the R, G, B primaries scaled so that RGB (1, 1, 1) is D65.
const fn rec709_to_xyz_matrix() -> [[f64; 3]; 3] {
    // Unscaled primaries, one per column: (x/y, 1, (1 - x - y)/y).
    let mut p = [[0.0; 3]; 3];
    let mut c = 0;
    while c < 3 {
        let x = REC709_PRIMARIES_XY[c][0];
        let y = REC709_PRIMARIES_XY[c][1];
        p[0][c] = x / y;
        p[1][c] = 1.0;
        p[2][c] = (1.0 - x - y) / y;
        c += 1;
    }
    let s = mat_vec(&invert3(&p), D65_WHITE_XYZ);
    let mut m = [[0.0; 3]; 3];
    let mut r = 0;
    while r < 3 {
        let mut c = 0;
        while c < 3 {
            m[r][c] = p[r][c] * s[c];
            c += 1;
        }
        r += 1;
    }
    m
}

/// Linear Rec.709 RGB → CIE XYZ (row-major, `xyz = M · rgb`).
///
/// Derived from the ITU-R BT.709-6 primaries and the CIE D65 white
/// (0.95047, 1, 1.08883); RGB (1, 1, 1) ↦ D65 with Y = 1.
pub const REC709_TO_XYZ: [[f64; 3]; 3] = rec709_to_xyz_matrix();

/// CIE XYZ → linear Rec.709 RGB (row-major, `rgb = M · xyz`): the exact inverse
/// of [`REC709_TO_XYZ`]. First row ≈ (3.2404542, −1.5371385, −0.4985314)
/// (Lindbloom); agrees with the IEC 61966-2-1 sRGB matrix to < 4·10⁻⁴.
pub const XYZ_TO_REC709: [[f64; 3]; 3] = invert3(&REC709_TO_XYZ);

// ---------------------------------------------------------------------------
// Embedded tables
// ---------------------------------------------------------------------------

const CMF_CSV: &str = include_str!("../data/cie1931_2deg_5nm.csv");
const SOLAR_CSV: &str = include_str!("../data/astm_e490_am0_5nm.csv");

/// Parses an embedded CSV table with `C` value columns after the wavelength
/// column. Panics (programming error: the tables are compiled in) if the table
/// does not match the grid exactly.
fn parse_table<const C: usize>(name: &str, text: &str) -> [Spectrum; C] {
    let fail = |line: usize, why: &str| -> ! { panic!("embedded spectral table `{name}` is malformed (line {line}): {why}") };
    let mut out = [[0.0; SPECTRAL_SAMPLES]; C];
    let mut row = 0;
    let mut seen_header = false;
    for (n, raw) in text.lines().enumerate() {
        let line_no = n + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        if !seen_header {
            if !line.starts_with("wavelength_nm,") {
                fail(line_no, "expected a header line starting with `wavelength_nm,`");
            }
            seen_header = true;
            continue;
        }
        if row >= SPECTRAL_SAMPLES {
            fail(line_no, "more rows than spectral samples");
        }
        let mut fields = line.split(',').map(str::trim);
        let lambda: f64 = match fields.next().map(str::parse) {
            Some(Ok(v)) => v,
            _ => fail(line_no, "unparsable wavelength"),
        };
        if (lambda - WAVELENGTHS[row]).abs() > 1e-9 {
            fail(line_no, "wavelength does not match the 380–780 nm / 5 nm grid");
        }
        for column in out.iter_mut() {
            let v: f64 = match fields.next().map(str::parse) {
                Some(Ok(v)) => v,
                _ => fail(line_no, "missing or unparsable value"),
            };
            if !v.is_finite() || v < 0.0 {
                fail(line_no, "value is not a finite non-negative number");
            }
            column[row] = v;
        }
        if fields.next().is_some() {
            fail(line_no, "too many columns");
        }
        row += 1;
    }
    if row != SPECTRAL_SAMPLES {
        fail(text.lines().count(), "fewer rows than spectral samples");
    }
    out
}

static CMFS: LazyLock<[Spectrum; 3]> = LazyLock::new(|| parse_table::<3>("data/cie1931_2deg_5nm.csv", CMF_CSV));

static SOLAR: LazyLock<Spectrum> = LazyLock::new(|| parse_table::<1>("data/astm_e490_am0_5nm.csv", SOLAR_CSV)[0]);

/// Quantities derived once from the tables.
struct Derived {
    /// Normalisation constant k (see the module docs).
    k: f64,
    /// k·Δλ·cmf_j(λᵢ): `xyz[j] = Σᵢ xyz_weights[j][i]·S[i]`.
    xyz_weights: [Spectrum; 3],
    /// `rec709_to_spectrum(c) = Σ_c basis[c]·c_c`.
    basis: [Spectrum; 3],
    /// max(0, r̄_c(λ)), un-normalised.
    positive_rgb_cmfs: [Spectrum; 3],
    /// Σᵢ positive_rgb_cmfs[c][i] (summed in index order).
    positive_rgb_sums: [f64; 3],
    /// positive_rgb_cmfs / positive_rgb_sums.
    channel_weights: [Spectrum; 3],
}

static DERIVED: LazyLock<Derived> = LazyLock::new(|| {
    let cmfs = &*CMFS;
    let y_integral: f64 = cmfs[1].iter().sum::<f64>() * LAMBDA_STEP_NM;
    let k = (LAMBDA_MAX_NM - LAMBDA_MIN_NM) / y_integral;
    let xyz_weights: [Spectrum; 3] = std::array::from_fn(|j| std::array::from_fn(|i| k * LAMBDA_STEP_NM * cmfs[j][i]));

    // Least-norm upsampling: with A the 3×81 matrix xyz_weights (xyz = A·S),
    // S = Aᵀ (A Aᵀ)⁻¹ REC709_TO_XYZ · c.
    let mut gram = [[0.0; 3]; 3];
    for (a, row) in gram.iter_mut().enumerate() {
        for (b, g) in row.iter_mut().enumerate() {
            *g = xyz_weights[a].iter().zip(&xyz_weights[b]).map(|(p, q)| p * q).sum();
        }
    }
    let coeff = mat_mul(&invert3(&gram), &REC709_TO_XYZ); // 3 (xyz) × 3 (rgb)
    let basis: [Spectrum; 3] = std::array::from_fn(|c| std::array::from_fn(|i| (0..3).map(|j| xyz_weights[j][i] * coeff[j][c]).sum()));

    let positive_rgb_cmfs: [Spectrum; 3] = std::array::from_fn(|c| {
        std::array::from_fn(|i| {
            let rbar = mat_vec(&XYZ_TO_REC709, [cmfs[0][i], cmfs[1][i], cmfs[2][i]])[c];
            rbar.max(0.0)
        })
    });
    let positive_rgb_sums: [f64; 3] = std::array::from_fn(|c| positive_rgb_cmfs[c].iter().sum());
    let channel_weights: [Spectrum; 3] = std::array::from_fn(|c| std::array::from_fn(|i| positive_rgb_cmfs[c][i] / positive_rgb_sums[c]));
    Derived {
        k,
        xyz_weights,
        basis,
        positive_rgb_cmfs,
        positive_rgb_sums,
        channel_weights,
    }
});

/// The CIE 1931 2° colour-matching functions `[x̄, ȳ, z̄]` on the grid
/// (dimensionless; ȳ(555 nm) = 1), from `data/cie1931_2deg_5nm.csv`.
pub fn cie_1931_cmfs() -> &'static [Spectrum; 3] {
    &CMFS
}

/// The normalisation constant k = 400 nm / Σ ȳ(λ)Δλ ≈ 3.7433 used by
/// [`spectrum_to_xyz`] (see the module docs).
pub fn xyz_normalisation() -> f64 {
    DERIVED.k
}

/// The extraterrestrial (top-of-atmosphere, 1 AU) solar spectral irradiance in
/// W·m⁻²·nm⁻¹: ASTM E490-00a AM0, 5 nm box-averaged (see the module docs).
///
/// Integrates (Riemann sum, Δλ = 5 nm) to ≈ 661 W/m² over the grid cells, or
/// ≈ 655 W/m² over exactly 380–780 nm; peak ≈ 2.05 W·m⁻²·nm⁻¹ at 450 nm;
/// chromaticity ≈ (0.3236, 0.3327).
pub fn solar_spectral_irradiance() -> &'static Spectrum {
    &SOLAR
}

// ---------------------------------------------------------------------------
// Colour conversions
// ---------------------------------------------------------------------------

/// CIE 1931 XYZ of a spectrum: `XYZ = k · Σᵢ S(λᵢ)·cmf(λᵢ)·Δλ` (Riemann sum,
/// k from [`xyz_normalisation`]). A flat spectrum of value c gives Y = 400·c;
/// the result has the units of `s` times nm.
pub fn spectrum_to_xyz(s: &Spectrum) -> [f64; 3] {
    let w = &DERIVED.xyz_weights;
    std::array::from_fn(|j| w[j].iter().zip(s).map(|(a, b)| a * b).sum())
}

/// CIE XYZ → linear Rec.709 (sRGB primaries, D65 white) RGB with
/// [`XYZ_TO_REC709`]. No clamping: out-of-gamut colours have negative channels.
pub fn xyz_to_rec709(xyz: [f64; 3]) -> [f64; 3] {
    mat_vec(&XYZ_TO_REC709, xyz)
}

/// Linear Rec.709 RGB → CIE XYZ with [`REC709_TO_XYZ`] (inverse of [`xyz_to_rec709`]).
pub fn rec709_to_xyz(rgb: [f64; 3]) -> [f64; 3] {
    mat_vec(&REC709_TO_XYZ, rgb)
}

/// Linear Rec.709 RGB of a spectrum: `xyz_to_rec709(spectrum_to_xyz(s))`.
pub fn spectrum_to_rec709(s: &Spectrum) -> [f64; 3] {
    xyz_to_rec709(spectrum_to_xyz(s))
}

/// A bound on the error of each linear Rec.709 channel given absolute
/// errors `e` (≥ 0) of X, Y, Z: `|XYZ_TO_REC709|·e`, entry by entry (the
/// matrix has negative entries, so converting `e` itself is no bound).
pub fn xyz_error_to_rec709(e: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|c| (0..3).map(|j| XYZ_TO_REC709[c][j].abs() * e[j]).sum())
}

/// A bound on the error of each linear Rec.709 channel of a spectrum whose
/// samples err by at most `|e|`: [`xyz_error_to_rec709`] of the XYZ of `|e|`
/// (the colour-matching functions are non-negative, so that bounds the XYZ
/// errors; the Rec.709 ones have negative lobes, so `spectrum_to_rec709(|e|)`
/// would not bound the channels).
pub fn spectral_error_to_rec709(e: &Spectrum) -> [f64; 3] {
    xyz_error_to_rec709(spectrum_to_xyz(&e.map(f64::abs)))
}

/// Linear spectral upsampling of a linear Rec.709 colour.
///
/// Returns the minimum-norm spectrum (Euclidean norm over the 81 samples) whose
/// colour is exactly `rgb`: with A the 3×81 matrix of [`spectrum_to_xyz`],
/// `S = Aᵀ (A Aᵀ)⁻¹ · REC709_TO_XYZ · rgb`, so
/// `spectrum_to_rec709(rec709_to_spectrum(c)) == c` up to rounding (~1e-15
/// relative). The map is **linear** in `rgb`, which is what matters here:
/// light colours are upsampled, multiplied per wavelength by medium factors
/// (transmittance, phase-weighted scattering, …) and converted back, and a
/// grey factor f gives back exactly f·c.
///
/// The result is a smooth combination of the colour-matching functions, not a
/// physical spectrum: it is **not flat for white** (RGB (1,1,1) does not give
/// an equal-energy spectrum) and it **can be negative** at some wavelengths,
/// notably for saturated colours. Units: RGB in the units of
/// [`spectrum_to_xyz`]'s output gives a spectrum per nm (e.g. Y = 1 ↦ values
/// of order 1/400).
pub fn rec709_to_spectrum(rgb: [f64; 3]) -> Spectrum {
    let b = &DERIVED.basis;
    std::array::from_fn(|i| b[0][i] * rgb[0] + b[1][i] * rgb[1] + b[2][i] * rgb[2])
}

/// Per-channel spectral averaging weights `[w_r, w_g, w_b]` for turning a
/// spectral transmittance into an RGB one.
///
/// `w_c(λ) = max(0, r̄_c(λ)) / Σ_λ max(0, r̄_c(λ))`, where
/// `r̄_c = (XYZ_TO_REC709 · [x̄, ȳ, z̄])_c` are the Rec.709 colour-matching
/// functions. Each weight is ≥ 0 and each channel sums to 1 over the grid.
pub fn channel_weights() -> &'static [Spectrum; 3] {
    &DERIVED.channel_weights
}

/// Approximate RGB transmittance of a spectral transmittance `t`:
/// `rgb_c = Σ_λ w_c(λ)·t(λ)` with the [`channel_weights`].
///
/// This is an **approximation**: the colour of a spectral product is not the
/// product of the colours, so multiplying an RGB light by this value only
/// matches the spectral result for grey-ish `t` or lights close to the weights'
/// implicit spectra. Guarantees (also in floating point): for `t(λ) ∈ [0, 1]`
/// every channel is in `[0, 1]`, and `t ≡ 1` gives exactly `[1.0, 1.0, 1.0]`.
pub fn spectral_transmittance_to_rgb(t: &Spectrum) -> [f64; 3] {
    let d = &*DERIVED;
    std::array::from_fn(|c| {
        // Same summation order as `positive_rgb_sums`, so t ≡ 1 gives exactly 1
        // and t ≤ 1 gives a numerator ≤ the denominator.
        let num: f64 = d.positive_rgb_cmfs[c].iter().zip(t).map(|(w, x)| w * x).sum();
        num / d.positive_rgb_sums[c]
    })
}

/// `true` if all samples of `s` are equal within the relative tolerance
/// `rel_tol`: `max − min ≤ rel_tol · max|s|`. An all-zero spectrum is grey;
/// a spectrum containing NaN or ±∞ is not. Used to decide that a medium needs
/// no spectral sampling.
pub fn is_grey(s: &Spectrum, rel_tol: f64) -> bool {
    let mut lo = f64::INFINITY;
    let mut hi = f64::NEG_INFINITY;
    for &v in s {
        if !v.is_finite() {
            return false;
        }
        lo = lo.min(v);
        hi = hi.max(v);
    }
    let scale = lo.abs().max(hi.abs());
    hi - lo <= rel_tol * scale
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn grid_index(lambda: f64) -> usize {
        ((lambda - LAMBDA_MIN_NM) / LAMBDA_STEP_NM).round() as usize
    }

    fn trapezoid(s: &Spectrum) -> f64 {
        let sum: f64 = s.iter().sum();
        (sum - 0.5 * (s[0] + s[SPECTRAL_SAMPLES - 1])) * LAMBDA_STEP_NM
    }

    fn chromaticity(xyz: [f64; 3]) -> [f64; 2] {
        let t = xyz[0] + xyz[1] + xyz[2];
        [xyz[0] / t, xyz[1] / t]
    }

    /// `spectral_error_to_rec709(e)` bounds the Rec.709 channels of every
    /// error spectrum within `±|e|`, including the worst sign pattern of
    /// each channel (the sign of its colour-matching function), where
    /// `spectrum_to_rec709(|e|)` falls short.
    #[test]
    fn spectral_error_bound_covers_every_sign_pattern() {
        let mut rnd = crate::test_support::uniform(0x9E37_79B9_7F4A_7C15);
        let mut naive_short = false;
        for _ in 0..200 {
            let e: Spectrum = std::array::from_fn(|_| rnd());
            let bound = spectral_error_to_rec709(&e);
            let naive = spectrum_to_rec709(&e);
            for c in 0..3 {
                // The worst case for channel c: each sample's sign that of the channel's weight.
                let unit = |i: usize| {
                    let mut u = [0.0; SPECTRAL_SAMPLES];
                    u[i] = 1.0;
                    spectrum_to_rec709(&u)[c]
                };
                let worst: f64 = (0..SPECTRAL_SAMPLES).map(|i| e[i] * unit(i).abs()).sum();
                assert!(worst <= bound[c] * (1.0 + 1e-12), "channel {c}: {worst} > {}", bound[c]);
                naive_short |= naive[c].abs() < worst;
            }
            for _ in 0..20 {
                let signed: Spectrum = std::array::from_fn(|i| e[i] * (2.0 * rnd() - 1.0));
                let got = spectrum_to_rec709(&signed);
                for c in 0..3 {
                    assert!(got[c].abs() <= bound[c] * (1.0 + 1e-12));
                }
            }
        }
        assert!(naive_short, "converting |e| directly should fall short somewhere");
    }

    #[test]
    fn grid_is_380_to_780_by_5() {
        let w = wavelengths_nm();
        assert_eq!(w[0], 380.0);
        assert_eq!(w[1], 385.0);
        assert_eq!(w[SPECTRAL_SAMPLES - 1], 780.0);
        assert_eq!(grid_index(555.0), 35);
        assert_eq!(spectrum_from_fn(|l| l)[35], 555.0);
    }

    #[test]
    fn embedded_tables_load_with_known_values() {
        let [x, y, z] = cie_1931_cmfs();
        // CIE 15:2004 Table T.4 spot values.
        assert_eq!(y[grid_index(555.0)], 1.0);
        assert_eq!(y[grid_index(560.0)], 0.995);
        assert_eq!(x[grid_index(600.0)], 1.0622);
        assert_eq!(z[grid_index(450.0)], 1.77211);
        assert_eq!(x[grid_index(380.0)], 0.001368);
        assert_eq!(y[grid_index(380.0)], 0.000039);
        assert_eq!(z[grid_index(380.0)], 0.00645);
        assert_eq!(x[grid_index(780.0)], 0.000042);
        assert_eq!(z[grid_index(700.0)], 0.0);
        let sun = solar_spectral_irradiance();
        assert!(sun.iter().all(|&v| v > 0.5 && v < 2.5));
        // Derived quantities build without panicking.
        assert!(xyz_normalisation() > 3.7 && xyz_normalisation() < 3.8);
    }

    #[test]
    #[should_panic(expected = "is malformed")]
    fn malformed_table_panics_with_clear_message() {
        let _ = parse_table::<1>("bad", "wavelength_nm,v\n380,1\n390,1\n");
    }

    #[test]
    fn cmf_sums_match_published_values() {
        let [x, y, z] = cie_1931_cmfs();
        let sx: f64 = x.iter().sum();
        let sy: f64 = y.iter().sum();
        let sz: f64 = z.iter().sum();
        // CIE 15:2004 Table T.4 column sums (380–780 nm, 5 nm).
        assert!((sx - 21.371524).abs() < 1e-6, "{sx}");
        assert!((sy - 21.371327).abs() < 1e-6, "{sy}");
        assert!((sz - 21.371540).abs() < 1e-6, "{sz}");
        // ∫ȳ dλ = 106.857 nm (1 nm table 360–830 nm: 106.8569).
        assert!((sy * LAMBDA_STEP_NM - 106.857).abs() < 0.01);
        assert!((xyz_normalisation() - 400.0 / 106.856635).abs() < 1e-9);
    }

    #[test]
    fn equal_energy_spectrum() {
        let c = 0.37;
        let xyz = spectrum_to_xyz(&[c; SPECTRAL_SAMPLES]);
        assert!((xyz[1] - 400.0 * c).abs() < 1e-12 * 400.0);
        let [cx, cy] = chromaticity(xyz);
        assert!((cx - 1.0 / 3.0).abs() < 1e-3 && (cy - 1.0 / 3.0).abs() < 1e-3);
    }

    #[test]
    fn rec709_matrix_is_the_standard_one() {
        let rgb = xyz_to_rec709([0.95047, 1.0, 1.08883]);
        for v in rgb {
            assert!((v - 1.0).abs() < 1e-4, "{rgb:?}");
        }
        // B. Lindbloom's XYZ→sRGB matrix (D65 = 0.95047, 1, 1.08883).
        let lindbloom = [
            [3.2404542, -1.5371385, -0.4985314],
            [-0.9692660, 1.8760108, 0.0415560],
            [0.0556434, -0.2040259, 1.0572252],
        ];
        // IEC 61966-2-1:1999 (sRGB), four decimals.
        let iec = [[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]];
        for r in 0..3 {
            for c in 0..3 {
                assert!((XYZ_TO_REC709[r][c] - lindbloom[r][c]).abs() < 1e-6);
                assert!((XYZ_TO_REC709[r][c] - iec[r][c]).abs() < 4e-4);
            }
        }
        // Primaries land on their BT.709 chromaticities; white has Y = 1.
        let expect = [[0.64, 0.33], [0.30, 0.60], [0.15, 0.06]];
        for (c, e) in expect.iter().enumerate() {
            let mut rgb = [0.0; 3];
            rgb[c] = 1.0;
            let xy = chromaticity(rec709_to_xyz(rgb));
            assert!((xy[0] - e[0]).abs() < 1e-12 && (xy[1] - e[1]).abs() < 1e-12);
        }
        assert!((rec709_to_xyz([1.0; 3])[1] - 1.0).abs() < 1e-12);
        let back = xyz_to_rec709(rec709_to_xyz([0.2, -0.3, 0.7]));
        assert!((back[0] - 0.2).abs() < 1e-14 && (back[1] + 0.3).abs() < 1e-14);
    }

    proptest! {
        #[test]
        fn rec709_upsampling_round_trips(
            r in -10.0..10.0f64, g in -10.0..10.0f64, b in -10.0..10.0f64,
        ) {
            let c = [r, g, b];
            let back = spectrum_to_rec709(&rec709_to_spectrum(c));
            let scale = r.abs().max(g.abs()).max(b.abs()).max(1e-300);
            for k in 0..3 {
                prop_assert!((back[k] - c[k]).abs() <= 1e-12 * scale, "{c:?} -> {back:?}");
            }
        }

        #[test]
        fn upsampling_is_linear_and_grey_factors_commute(
            r in 0.0..5.0f64, g in 0.0..5.0f64, b in 0.0..5.0f64, f in 0.0..1.0f64,
        ) {
            let s = rec709_to_spectrum([r, g, b]);
            let scaled: Spectrum = std::array::from_fn(|i| f * s[i]);
            let back = spectrum_to_rec709(&scaled);
            for (k, v) in [r, g, b].into_iter().enumerate() {
                prop_assert!((back[k] - f * v).abs() <= 1e-10 * (1.0 + v));
            }
        }

        #[test]
        fn transmittance_rgb_stays_in_unit_interval(
            t in proptest::array::uniform32(0.0..=1.0f64), shift in 0usize..49,
        ) {
            let mut full = [1.0; SPECTRAL_SAMPLES];
            full[shift..shift + 32].copy_from_slice(&t);
            for v in spectral_transmittance_to_rgb(&full) {
                prop_assert!((0.0..=1.0).contains(&v));
            }
        }
    }

    #[test]
    fn upsampling_is_not_a_physical_spectrum() {
        // A saturated blue needs negative values somewhere; white does not
        // need to be flat. This pins the documented behaviour.
        let blue = rec709_to_spectrum([0.0, 0.0, 1.0]);
        assert!(blue.iter().any(|&v| v < 0.0));
        assert!(!is_grey(&rec709_to_spectrum([1.0; 3]), 1e-3));
    }

    #[test]
    fn channel_weights_are_normalised_and_non_negative() {
        for w in channel_weights() {
            assert!(w.iter().all(|&v| v >= 0.0));
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        assert_eq!(spectral_transmittance_to_rgb(&[1.0; SPECTRAL_SAMPLES]), [1.0; 3]);
        assert_eq!(spectral_transmittance_to_rgb(&[0.0; SPECTRAL_SAMPLES]), [0.0; 3]);
        let half = spectral_transmittance_to_rgb(&[0.5; SPECTRAL_SAMPLES]);
        assert!(half.iter().all(|&v| (v - 0.5).abs() < 1e-15));
        // Red weight lives at long wavelengths, blue at short ones.
        let lam = wavelengths_nm();
        let mean = |w: &Spectrum| w.iter().zip(lam).map(|(a, l)| a * l).sum::<f64>();
        let [r, g, b] = channel_weights();
        assert!(mean(r) > 590.0 && mean(g) > 510.0 && mean(g) < 570.0 && mean(b) < 480.0);
    }

    #[test]
    fn solar_irradiance_integral_and_peak() {
        let sun = solar_spectral_irradiance();
        // Independently from the source table (trapezoid over its 1–2 nm
        // samples, 380–780 nm): 654.95 W/m². ASTM G173-03 ETR: 655.88 W/m².
        let e = trapezoid(sun);
        assert!((e - 654.95).abs() < 0.005 * 654.95, "{e}");
        // ≈ 48 % of the E490 solar constant 1366.1 W/m².
        let frac = e / 1366.1;
        assert!(frac > 0.47 && frac < 0.49, "{frac}");
        let (i_max, &peak) = sun.iter().enumerate().max_by(|a, b| a.1.total_cmp(b.1)).unwrap();
        let lambda_peak = wavelengths_nm()[i_max];
        assert!((450.0..=500.0).contains(&lambda_peak), "{lambda_peak}");
        assert!(peak > 2.0 && peak < 2.1, "{peak}");
        // A few 5 nm averages recomputed by hand from the E490 1 nm rows.
        assert!((sun[grid_index(450.0)] - 2.0524).abs() < 1e-4);
        assert!((sun[grid_index(550.0)] - 1.8661).abs() < 1e-4);
    }

    #[test]
    fn solar_colour() {
        let xyz = spectrum_to_xyz(solar_spectral_irradiance());
        let [x, y] = chromaticity(xyz);
        // Extraterrestrial Sun ≈ 5900 K: slightly bluer than D55, redder than D65.
        assert!((x - 0.3236).abs() < 2e-3 && (y - 0.3327).abs() < 2e-3, "{x} {y}");
        // Luminous solar constant 683 lm/W · ∫ȳE dλ: ≈ 133.3 klx from this
        // table; published values range from 127.5 klx (IES daylighting
        // practice) to ≈ 133–134 klx (estimates from modern AM0 spectra).
        let lux = 683.0 * xyz[1] / xyz_normalisation();
        assert!((127_000.0..135_000.0).contains(&lux), "{lux}");
        assert!((lux - 133_318.0).abs() < 50.0, "{lux}");
        // The Sun is warmer than D65 (x = 0.3127), so its Rec.709 R exceeds B.
        let rgb = spectrum_to_rec709(solar_spectral_irradiance());
        assert!(rgb.iter().all(|&v| v > 0.0) && rgb[0] > rgb[2]);
    }

    #[test]
    fn grey_detection() {
        assert!(is_grey(&[0.0; SPECTRAL_SAMPLES], 0.0));
        assert!(is_grey(&[2.5; SPECTRAL_SAMPLES], 0.0));
        let mut s = [1.0; SPECTRAL_SAMPLES];
        s[40] = 1.0 + 1e-9;
        assert!(is_grey(&s, 1e-6));
        assert!(!is_grey(&s, 1e-12));
        s[40] = f64::NAN;
        assert!(!is_grey(&s, 1.0));
        let rayleigh = spectrum_from_fn(|l| (550.0 / l).powi(4));
        assert!(!is_grey(&rayleigh, 0.1));
        assert!(is_grey(&[-3.0; SPECTRAL_SAMPLES], 1e-12));
    }
}
