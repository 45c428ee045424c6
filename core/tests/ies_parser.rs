//! IES LM-63 parser and evaluator: the hand-written corpus in `tests/data/ies/`
//! parses to the expected values, symmetry expansion and type A/B conversion
//! follow Cycles, interpolation reproduces table nodes and matches a literal
//! port of Cycles' kernel lookup, the bounding cone is tight, malformed files
//! are rejected at the right line, and mutated files never panic.

use glam::DVec3;
use proptest::prelude::*;
use std::f64::consts::{FRAC_PI_2, PI};
use std::path::PathBuf;
use tyndall_core::light::ies::{CYCLES_IES_SCALE, HorizontalSymmetry, IesProfile, IesVersion, PhotometricType, Tilt, UnitsType};

fn data_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/ies")
}

fn load(name: &str) -> IesProfile {
    IesProfile::load(&data_dir().join(name)).unwrap_or_else(|e| panic!("{e}"))
}

/// Local direction for Cycles' vertical angle `v` and horizontal angle `h` (degrees):
/// v = 0 is −Z, h = 0 is −Y, h = 90 is −X (Cycles: v = acos(−z), h = atan2(x, y) + π).
fn dir(v: f64, h: f64) -> DVec3 {
    let (v, h) = (v.to_radians(), h.to_radians());
    DVec3::new(-v.sin() * h.sin(), -v.sin() * h.cos(), -v.cos())
}

fn close(a: f64, b: f64, tol: f64) -> bool {
    (a - b).abs() <= tol * (1.0 + a.abs().max(b.abs()))
}

macro_rules! assert_close {
    ($a:expr, $b:expr) => {
        assert_close!($a, $b, 1e-9)
    };
    ($a:expr, $b:expr, $tol:expr) => {{
        let (a, b) = ($a, $b);
        assert!(close(a, b, $tol), "{} = {a} but expected {} = {b}", stringify!($a), stringify!($b));
    }};
}

// ---------------------------------------------------------------------------
// A literal port of Cycles' kernel lookup (src/kernel/util/ies.h, svm/ies.h),
// written independently of the library: linear search, Horner-form cubic,
// half-open ranges. Used to check `cycles_factor` away from range ends.
// ---------------------------------------------------------------------------

fn cubic_interp(a: f64, b: f64, c: f64, d: f64, x: f64) -> f64 {
    0.5 * (((d + 3.0 * (b - c) - a) * x + (2.0 * a - 5.0 * b + 4.0 * c - d)) * x + (c - a)) * x + b
}

fn cycles_reference(p: &IesProfile, d: DVec3) -> f64 {
    let t = p.cycles_table();
    let hs: Vec<f64> = t.horizontal_deg.iter().map(|a| a.to_radians()).collect();
    let vs: Vec<f64> = t.vertical_deg.iter().map(|a| a.to_radians()).collect();
    let val = |h: usize, v: usize| t.candela[h][v] * p.cycles_scale();
    let d = d.normalize();
    let v_angle = (-d.z).acos();
    let h_angle = d.x.atan2(d.y) + PI;
    let (h_num, v_num) = (hs.len(), vs.len());
    if v_angle < vs[0] || v_angle >= vs[v_num - 1] || h_angle < hs[0] || h_angle >= hs[h_num - 1] {
        return 0.0;
    }
    let wrap_h = hs[0] < 1e-7 && hs[h_num - 1] > 2.0 * PI - 1e-7;
    let wrap_vlow = vs[0] < 1e-7;
    let wrap_vhigh = vs[v_num - 1] > PI - 1e-7;
    let mut h_i = 0;
    while hs[h_i + 1] < h_angle {
        h_i += 1;
    }
    let mut v_i = 0;
    while vs[v_i + 1] < v_angle {
        v_i += 1;
    }
    let h_frac = (h_angle - hs[h_i]) / (hs[h_i + 1] - hs[h_i]);
    let v_frac = (v_angle - vs[v_i]) / (vs[v_i + 1] - vs[v_i]);
    let vert = |h: usize| {
        let c = val(h, v_i + 1);
        let b = val(h, v_i);
        let a = if v_i > 0 {
            val(h, v_i - 1)
        } else if wrap_vlow {
            val(h, 1)
        } else {
            b
        };
        let dd = if v_i + 2 < v_num {
            val(h, v_i + 2)
        } else if wrap_vhigh {
            val(h, v_num - 2)
        } else {
            c
        };
        cubic_interp(a, b, c, dd, v_frac)
    };
    let b = vert(h_i);
    let c = vert(h_i + 1);
    let a = if h_i > 0 {
        vert(h_i - 1)
    } else if wrap_h {
        vert(h_num - 2)
    } else {
        b
    };
    let dd = if h_i + 2 < h_num {
        vert(h_i + 2)
    } else if wrap_h {
        vert(1)
    } else {
        b
    };
    cubic_interp(a, b, c, dd, h_frac).max(0.0)
}

const GOOD: &[&str] = &[
    "lm63_1986_rotational.ies",
    "lm63_1991_quadrant_crlf.ies",
    "lm63_1995_bilateral_commas.ies",
    "lm63_2002_full_absolute.ies",
    "lm63_2019_gap360.ies",
    "typec_uplight_90_180.ies",
    "typec_90_270.ies",
    "tilt_include.ies",
    "tilt_file.ies",
    "typeb_flood.ies",
    "typea_auto.ies",
    "downlight_cutoff60.ies",
    "downlight_cutoff_uneven.ies",
];

/// Deterministic pseudo-random unit vectors.
fn directions(n: usize) -> Vec<DVec3> {
    let mut s: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    (0..n)
        .map(|_| {
            let z = 2.0 * next() - 1.0;
            let phi = 2.0 * PI * next();
            let r = (1.0 - z * z).sqrt();
            DVec3::new(r * phi.cos(), r * phi.sin(), z)
        })
        .collect()
}

// ---------------------------------------------------------------------------
// Corpus values
// ---------------------------------------------------------------------------

#[test]
fn every_good_file_parses_and_describes() {
    for name in GOOD {
        let p = load(name);
        let line = p.describe();
        assert!(!line.contains('\n'), "{line}");
        assert!(line.contains("max"), "{line}");
        assert!(p.max_cycles_factor() >= p.max_candela() * p.cycles_scale());
        assert!(p.bounding_half_angle() >= 0.0 && p.bounding_half_angle() <= PI);
    }
}

#[test]
fn lm63_1986_rotational() {
    let p = load("lm63_1986_rotational.ies");
    assert_eq!(p.version, IesVersion::Lm63_1986);
    assert_eq!(p.version_line, "");
    assert!(p.keywords.is_empty());
    assert_eq!(p.header_text.len(), 2);
    assert_eq!(p.tilt, Tilt::None);
    assert_eq!(p.photometric_type, PhotometricType::C);
    assert_eq!(p.units, UnitsType::Feet);
    assert_eq!(p.lumens_per_lamp, Some(1200.0));
    assert_eq!((p.width, p.length, p.height), (0.5, 0.5, 0.3));
    assert_eq!(p.input_watts, 100.0);
    assert_eq!(p.vertical_deg, vec![0.0, 15.0, 30.0, 45.0, 60.0, 75.0, 90.0]);
    assert_eq!(p.horizontal_deg, vec![0.0]);
    assert_eq!(p.candela, vec![vec![1000.0, 950.0, 800.0, 500.0, 200.0, 50.0, 0.0]]);
    assert_eq!(p.symmetry(), HorizontalSymmetry::Rotational);
    assert_eq!(p.cycles_table().horizontal_deg, vec![0.0, 360.0]);
    // The same in every C plane.
    for h in [0.0, 17.0, 90.0, 200.0, 359.0] {
        assert_close!(p.candela(dir(30.0, h)), 800.0);
        assert_close!(p.candela(dir(40.0, h)), p.candela(dir(40.0, 0.0)));
    }
    // Nothing below the horizon (vertical > 90).
    assert_eq!(p.candela(dir(91.0, 10.0)), 0.0);
    assert_close!(p.bounding_half_angle(), PI / 2.0);
    assert_close!(p.max_candela(), 1000.0);
}

#[test]
fn lm63_1991_quadrant_crlf_and_symmetry() {
    let p = load("lm63_1991_quadrant_crlf.ies");
    assert_eq!(p.version, IesVersion::Lm63_1991);
    assert_eq!(p.version_line, "IESNA91");
    assert_eq!(p.keyword("test"), Some("1991 quadrant, CRLF line ends"));
    assert_eq!(p.keyword("MANUFAC"), Some("Tyndall test corpus\nsecond line of manufacturer"));
    assert_eq!(p.units, UnitsType::Meters);
    assert_eq!(p.symmetry(), HorizontalSymmetry::Quadrant);
    assert_eq!(p.candela[1], vec![500.0, 300.0, 80.0, 0.0]);
    let t = p.cycles_table();
    assert_eq!(t.horizontal_deg, vec![0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0, 360.0]);
    assert_eq!(t.candela[3], t.candela[1]);
    assert_eq!(t.candela[4], t.candela[0]);
    assert_eq!(t.candela[6], t.candela[2]);
    // Quadrant symmetry: φ, 180−φ, 180+φ, 360−φ (= −φ) are the same, at any vertical angle.
    for v in [10.0, 30.0, 47.0, 75.0] {
        for phi in [0.0, 12.0, 45.0, 63.0, 90.0] {
            let c = p.candela(dir(v, phi));
            for other in [180.0 - phi, 180.0 + phi, 360.0 - phi, -phi] {
                assert_close!(p.candela(dir(v, other)), c, 1e-9);
            }
        }
    }
    // Nodes.
    for (ih, &h) in p.horizontal_deg.iter().enumerate() {
        for (iv, &v) in p.vertical_deg.iter().enumerate().skip(1).take(2) {
            assert_close!(p.candela(dir(v, h)), p.candela[ih][iv]);
        }
    }
}

#[test]
fn lm63_1995_bilateral_commas_spanning_lines() {
    let p = load("lm63_1995_bilateral_commas.ies");
    assert_eq!(p.version, IesVersion::Lm63_1995);
    assert_eq!(p.keyword("LUMINAIRE"), Some("wall washer"));
    assert_eq!(p.input_watts, 30.0);
    assert_eq!(p.vertical_deg, vec![0.0, 45.0, 90.0, 135.0, 180.0]);
    assert_eq!(p.horizontal_deg, vec![0.0, 90.0, 180.0]);
    assert_eq!(p.candela[1], vec![800.0, 750.0, 400.0, 50.0, 0.0]);
    assert_eq!(p.symmetry(), HorizontalSymmetry::Bilateral);
    assert_eq!(p.cycles_table().horizontal_deg, vec![0.0, 90.0, 180.0, 270.0, 360.0]);
    // Mirror about the 0–180 plane: φ and 360−φ.
    for v in [20.0, 45.0, 100.0, 150.0] {
        for phi in [0.0, 30.0, 90.0, 150.0, 180.0] {
            assert_close!(p.candela(dir(v, 360.0 - phi)), p.candela(dir(v, phi)));
        }
    }
    assert_close!(p.candela(dir(90.0, 90.0)), 400.0);
    assert_close!(p.candela(dir(90.0, 270.0)), 400.0);
    assert_close!(p.candela(dir(135.0, 180.0)), 100.0);
    // Light goes above the horizon up to 135°, the cubic reaches to 180°: cone is everything.
    assert_close!(p.bounding_half_angle(), PI);
}

#[test]
fn lm63_2002_full_absolute_multiplier_ballast() {
    let p = load("lm63_2002_full_absolute.ies");
    assert_eq!(p.version, IesVersion::Lm63_2002);
    assert_eq!(p.lumens_per_lamp, None);
    assert_eq!(p.candela_multiplier, 2.0);
    assert_eq!(p.ballast_factor, 0.9);
    assert_eq!(p.ballast_lamp_factor, 1.0);
    assert_eq!(p.symmetry(), HorizontalSymmetry::None);
    let k = 2.0 * 0.9;
    assert_close!(p.candela[1][1], 80.0 * k);
    assert_close!(p.candela[3][2], 40.0 * k);
    assert_close!(p.max_candela(), 100.0 * k);
    assert_eq!(p.cycles_table().horizontal_deg, p.horizontal_deg);
    // Nodes of all planes, and the scale constant.
    for (ih, &h) in p.horizontal_deg.iter().enumerate() {
        for (iv, &v) in p.vertical_deg.iter().enumerate().skip(1) {
            assert_close!(p.candela(dir(v, h)), p.candela[ih][iv]);
            assert_close!(p.cycles_factor(dir(v, h)), p.candela[ih][iv] * CYCLES_IES_SCALE);
        }
    }
    // C90 is local −X, C270 local +X, C0 −Y, C180 +Y (at 60° from −Z).
    let s = 60f64.to_radians();
    assert_close!(p.candela(DVec3::new(-s.sin(), 0.0, -s.cos())), 20.0 * k);
    assert_close!(p.candela(DVec3::new(s.sin(), 0.0, -s.cos())), 40.0 * k);
    assert_close!(p.candela(DVec3::new(0.0, -s.sin(), -s.cos())), 30.0 * k);
    assert_close!(p.candela(DVec3::new(0.0, s.sin(), -s.cos())), 10.0 * k);
    // Not normalised input is normalised; zero / NaN give 0.
    assert_close!(p.candela(DVec3::new(0.0, s.sin(), -s.cos()) * 7.5), 10.0 * k);
    assert_eq!(p.candela(DVec3::ZERO), 0.0);
    assert_eq!(p.candela(DVec3::NAN), 0.0);
    // Straight down.
    assert_close!(p.candela(DVec3::NEG_Z), 100.0 * k);
}

#[test]
fn lm63_2019_gap_and_file_generation_type() {
    let p = load("lm63_2019_gap360.ies");
    assert_eq!(p.version, IesVersion::Lm63_2019);
    assert_eq!(p.keyword("FILEGENINFO"), Some("written by hand"));
    assert_eq!(p.ballast_lamp_factor, 1.1);
    // The 360° plane is added as a copy of 0°.
    let t = p.cycles_table();
    assert_eq!(t.horizontal_deg, vec![0.0, 90.0, 180.0, 270.0, 360.0]);
    assert_eq!(t.candela[4], t.candela[0]);
    // candela excludes the file generation type; Cycles multiplies it in.
    assert_eq!(p.candela[2], vec![300.0, 200.0, 0.0]);
    assert_close!(p.cycles_scale(), CYCLES_IES_SCALE * 1.1);
    assert_close!(p.candela(dir(90.0, 180.0)), 200.0);
    assert_close!(p.cycles_factor(dir(90.0, 180.0)), 200.0 * CYCLES_IES_SCALE * 1.1);
    assert_close!(p.candela(dir(90.0, 359.999_999)), 100.0, 1e-6);
}

#[test]
fn classic_mac_line_ends_utf16_and_endless_files() {
    // A file whose lines end in a lone CR parses as its CR LF original does.
    let crlf = std::fs::read_to_string(data_dir().join("lm63_1991_quadrant_crlf.ies")).unwrap();
    let cr_only = crlf.replace("\r\n", "\r");
    assert!(!cr_only.contains('\n'));
    let a = IesProfile::parse(&cr_only, "cr_only").unwrap();
    let b = load("lm63_1991_quadrant_crlf.ies");
    assert_eq!((a.candela.clone(), a.keyword("MANUFAC")), (b.candela.clone(), b.keyword("MANUFAC")));
    // A bad number on line 12 is reported there with any line ends.
    let lines: Vec<&str> = crlf.split("\r\n").collect();
    let bad = lines
        .iter()
        .enumerate()
        .map(|(i, l)| if i == 11 { "1.0 x" } else { l })
        .collect::<Vec<_>>()
        .join("\r");
    assert_eq!(IesProfile::parse(&bad, "bad").unwrap_err().line, 12);
    // UTF-16 (as Windows' Notepad saves "Unicode") is named, at line 1.
    let tmp = std::env::temp_dir().join(format!("tyndall_ies_{}", std::process::id()));
    std::fs::create_dir_all(&tmp).unwrap();
    let utf16 = tmp.join("utf16.ies");
    let mut bytes = vec![0xFF, 0xFE];
    bytes.extend(crlf.encode_utf16().flat_map(|u| u.to_le_bytes()));
    std::fs::write(&utf16, bytes).unwrap();
    let e = IesProfile::load(&utf16).unwrap_err();
    assert_eq!(e.line, 1);
    assert!(e.message.contains("UTF-16"), "{e}");
    // A tilt file that never ends is cut off at MAX_FILE_BYTES with an error at the TILT line.
    #[cfg(unix)]
    {
        let endless = tmp.join("endless.ies");
        std::fs::write(&endless, crlf.replacen("TILT=NONE", "TILT=/dev/zero", 1)).unwrap();
        let e = IesProfile::load(&endless).unwrap_err();
        assert!(e.message.contains("larger than 256 MiB"), "{e}");
        assert!(e.line > 1, "{e}");
    }
    std::fs::remove_dir_all(&tmp).unwrap();
}

#[test]
fn uplight_90_180() {
    let p = load("typec_uplight_90_180.ies");
    assert_eq!(p.candela(dir(45.0, 0.0)), 0.0);
    assert_eq!(p.candela(DVec3::NEG_Z), 0.0);
    assert_close!(p.candela(dir(120.0, 33.0)), 40.0);
    assert_close!(p.candela(dir(150.0, 200.0)), 80.0);
    // Straight up: the last node (Cycles returns 0 exactly there; we include the end).
    assert_close!(p.candela(DVec3::Z), 100.0);
    assert_close!(p.bounding_half_angle(), PI);
    // Nothing below 90° (a spot pointing down with this file emits nothing).
    assert_close!(p.unlit_half_angle(), FRAC_PI_2, 1e-9);
    for v in [0.0, 30.0, 60.0, 89.9] {
        for h in [0.0, 90.0, 200.0] {
            assert_eq!(p.candela(dir(v, h)), 0.0);
        }
    }
    // A downlight is lit from its axis on.
    assert_eq!(load("downlight_cutoff60.ies").unlit_half_angle(), 0.0);
}

#[test]
fn horizontal_90_270_is_rotated_like_cycles() {
    let p = load("typec_90_270.ies");
    assert_eq!(p.symmetry(), HorizontalSymmetry::Bilateral90);
    assert_eq!(p.cycles_table().horizontal_deg, vec![0.0, 90.0, 180.0, 270.0, 360.0]);
    // Cycles shifts the table by −90°: the file's C90 plane lands on C0 (local −Y).
    assert_close!(p.candela(dir(45.0, 0.0)), 100.0);
    assert_close!(p.candela(dir(45.0, 90.0)), 150.0);
    assert_close!(p.candela(dir(45.0, 180.0)), 60.0);
    assert_close!(p.candela(dir(45.0, 270.0)), 150.0);
}

#[test]
fn tilt_include_and_file() {
    let p = load("tilt_include.ies");
    match &p.tilt {
        Tilt::Include(t) => {
            assert_eq!(t.lamp_to_luminaire_geometry, 1);
            assert_eq!(t.angles_deg, vec![0.0, 45.0, 90.0]);
            assert_eq!(t.factors, vec![1.0, 0.9, 0.7]);
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(p.candela, vec![vec![500.0, 250.0, 0.0]]);

    let p = load("tilt_file.ies");
    match &p.tilt {
        Tilt::File { name, data } => {
            assert_eq!(name, "tilt_file.tlt");
            assert_eq!(data.lamp_to_luminaire_geometry, 2);
            assert_eq!(data.angles_deg, vec![0.0, 90.0]);
            assert_eq!(data.factors, vec![1.0, 0.5]);
        }
        other => panic!("{other:?}"),
    }
    // Without a directory the reference cannot be resolved.
    let text = std::fs::read_to_string(data_dir().join("tilt_file.ies")).unwrap();
    let e = IesProfile::parse(&text, "mem").unwrap_err();
    assert_eq!(e.line, 3, "{e}");
    assert!(e.message.contains("tilt_file.tlt"), "{e}");
}

#[test]
fn type_b_follows_cycles_transposition() {
    let p = load("typeb_flood.ies");
    assert_eq!(p.photometric_type, PhotometricType::B);
    assert_eq!(p.symmetry(), HorizontalSymmetry::Other);
    let t = p.cycles_table();
    // File vertical 0,45,90 mirrored to −90..90 and shifted: Cycles' horizontal.
    assert_eq!(t.horizontal_deg, vec![0.0, 45.0, 90.0, 135.0, 180.0]);
    // File horizontal −90, 0, 90 shifted by 90: Cycles' vertical.
    assert_eq!(t.vertical_deg, vec![0.0, 90.0, 180.0]);
    // candela[H][V]: at Cycles (v = H + 90, h = 90 ± V).
    let (x, y) = (DVec3::X, DVec3::Y);
    let r = 0.5f64.sqrt();
    // Photometric axis (H = 0, V = 0) is local −X.
    assert_close!(p.candela(-x), 10.0);
    // V = +45: h = 135 → (−sin 135°, −cos 135°, 0); V = −45 mirrored: h = 45.
    assert_close!(p.candela(DVec3::new(-r, r, 0.0)), 20.0);
    assert_close!(p.candela(DVec3::new(-r, -r, 0.0)), 20.0);
    // V = ±90 → ±Y.
    assert_close!(p.candela(y), 30.0);
    assert_close!(p.candela(DVec3::new(-0.0, -1.0, 0.0)), 30.0);
    // The +X half space is outside Cycles' 0–180° horizontal range.
    assert_eq!(p.candela(DVec3::new(1.0, 0.2, 0.1)), 0.0);
    // H = +90 is +Z side, H = −90 the −Z side: at 45° from the axis towards −Z, h = 90.
    let toward_down = DVec3::new(-r, 0.0, -r);
    let toward_up = DVec3::new(-r, 0.0, r);
    let (dn, up) = (p.candela(toward_down), p.candela(toward_up));
    assert!(dn > 1.0 && dn < 10.0 && up > 4.0 && up < 10.0, "{dn} {up}");
}

#[test]
fn type_a_follows_cycles_conversion() {
    let p = load("typea_auto.ies");
    assert_eq!(p.photometric_type, PhotometricType::A);
    let t = p.cycles_table();
    assert_eq!(t.vertical_deg, vec![0.0, 90.0, 180.0]);
    assert_eq!(t.horizontal_deg, vec![90.0, 135.0, 180.0, 225.0, 270.0]);
    let r = 0.5f64.sqrt();
    // Axis (0, 0) is local +Y.
    assert_close!(p.candela(DVec3::Y), 50.0);
    // H = +45 at h = 135: (−r, r, 0); H = −45 (mirrored) at h = 225: (r, r, 0).
    assert_close!(p.candela(DVec3::new(-r, r, 0.0)), 40.0);
    assert_close!(p.candela(DVec3::new(r, r, 0.0)), 40.0);
    // H = +90 → −X, H = −90 → +X (the range end, included here).
    assert_close!(p.candela(DVec3::NEG_X), 30.0);
    assert_close!(p.candela(DVec3::X), 30.0);
    // −Y is outside the 90–270 range.
    assert_eq!(p.candela(DVec3::new(0.1, -1.0, 0.0)), 0.0);
    // Vertical: V = −90 is −Z side, +90 the +Z side.
    let dn = p.candela(DVec3::new(0.0, r, -r));
    let up = p.candela(DVec3::new(0.0, r, r));
    assert!(dn > 5.0 && dn < 50.0 && up > 7.0 && up < 50.0, "{dn} {up}");
}

// ---------------------------------------------------------------------------
// Interpolation against the Cycles port; nodes; bounds
// ---------------------------------------------------------------------------

#[test]
fn cycles_factor_matches_cycles_kernel_port() {
    let dirs = directions(4000);
    for name in GOOD {
        let p = load(name);
        let mut nonzero = 0;
        for &d in &dirs {
            let ours = p.cycles_factor(d);
            let theirs = cycles_reference(&p, d);
            assert!(
                (ours - theirs).abs() <= 1e-9 * (1.0 + p.max_cycles_factor()),
                "{name}: {d:?}: ours {ours}, Cycles port {theirs}"
            );
            assert!(
                ours >= 0.0 && ours <= p.max_cycles_factor() * (1.0 + 1e-12),
                "{name}: {ours} > bound {}",
                p.max_cycles_factor()
            );
            assert_close!(ours, p.candela(d) * p.cycles_scale(), 1e-12);
            nonzero += usize::from(ours > 0.0);
        }
        assert!(nonzero > 100, "{name}: only {nonzero} lit directions");
    }
}

#[test]
fn interpolation_reproduces_every_node() {
    for name in GOOD {
        let p = load(name);
        let t = p.cycles_table();
        for (ih, &h) in t.horizontal_deg.iter().enumerate() {
            for (iv, &v) in t.vertical_deg.iter().enumerate() {
                // Skip the poles (all planes meet there) and nodes beyond the cone.
                if !(1e-9..=180.0 - 1e-9).contains(&v) || v.to_radians() > p.bounding_half_angle() {
                    continue;
                }
                let got = p.candela(dir(v, h));
                assert!(
                    close(got, t.candela[ih][iv], 1e-9),
                    "{name}: node h={h} v={v}: {got} vs {}",
                    t.candela[ih][iv]
                );
            }
        }
    }
}

#[test]
fn max_cycles_factor_bounds_a_dense_scan() {
    for name in GOOD {
        let p = load(name);
        let mut best: f64 = 0.0;
        for iv in 0..=360 {
            for ih in 0..=720 {
                best = best.max(p.cycles_factor(dir(iv as f64 * 0.5, ih as f64 * 0.5)));
            }
        }
        let bound = p.max_cycles_factor();
        assert!(best <= bound * (1.0 + 1e-12), "{name}: {best} > {bound}");
        // Not absurdly loose: within the 1.28 worst case of Catmull-Rom overshoot.
        assert!(bound <= 1.29 * p.max_candela() * p.cycles_scale(), "{name}");
    }
}

#[test]
fn downlight_cone_is_60_degrees() {
    let p = load("downlight_cutoff60.ies");
    assert_close!(p.bounding_half_angle().to_degrees(), 60.0, 1e-12);
    for v in [60.000_001, 60.001, 65.0, 70.0, 89.0, 90.0, 120.0, 180.0] {
        for h in (0..360).step_by(7) {
            assert_eq!(p.candela(dir(v, h as f64)), 0.0, "v={v} h={h}");
        }
    }
    assert!(p.candela(dir(59.9, 10.0)) > 0.0);
}

#[test]
fn uneven_last_row_leaks_and_the_cone_says_so() {
    let p = load("downlight_cutoff_uneven.ies");
    // Row 50° is 0, 0, 100 across C0, C45, C90: the horizontal cubic dips below 0
    // between C0 and C45, so the 60–70° band gets light from the vertical cubic.
    assert_close!(p.bounding_half_angle().to_degrees(), 70.0, 1e-12);
    let mut lit = false;
    for h in 0..360 {
        lit |= p.candela(dir(65.0, h as f64)) > 0.0;
        assert_eq!(p.candela(dir(70.5, h as f64)), 0.0);
    }
    assert!(lit, "expected light between 60 and 70 degrees");
}

#[test]
fn all_zero_table_has_zero_cone() {
    let text = "IESNA:LM-63-2002\nTILT=NONE\n1 -1 1 3 1 1 2 0 0 0\n1 1 0\n0 45 90\n0\n0 0 0\n";
    let p = IesProfile::parse(text, "zero").unwrap();
    assert_eq!(p.bounding_half_angle(), 0.0);
    assert_eq!(p.max_cycles_factor(), 0.0);
    assert_eq!(p.candela(DVec3::NEG_Z), 0.0);
}

// ---------------------------------------------------------------------------
// Malformed files
// ---------------------------------------------------------------------------

#[test]
fn malformed_files_name_the_line() {
    let cases: &[(&str, usize, &str)] = &[
        ("bad_missing_tilt.ies", 3, "TILT"),
        ("bad_number.ies", 6, "'6O' is not a number"),
        ("bad_number_crlf.ies", 6, "'9x0' is not a number"),
        ("bad_too_few.ies", 8, "end of file"),
        ("bad_extra_values.ies", 9, "extra value"),
        ("bad_nonincreasing.ies", 6, "must increase"),
        ("bad_negative_candela.ies", 8, "negative"),
        ("bad_nan_candela.ies", 8, "not a finite number"),
        ("bad_photometric_type.ies", 4, "unsupported photometric type"),
        ("bad_absurd_count.ies", 4, "absurd"),
        ("bad_tilt_file_missing.ies", 3, "missing_tilt.tlt"),
        ("bad_tilt_truncated.ies", 7, "end of file"),
        ("bad_horizontal_range.ies", 7, "outside"),
        ("bad_units.ies", 4, "units type"),
        ("bad_lumens.ies", 4, "lumens"),
        ("bad_multiplier.ies", 4, "multiplier"),
        ("bad_empty.ies", 1, "empty"),
        ("bad_count_mismatch.ies", 7, "must increase"),
        ("bad_single_vertical.ies", 6, "at least 2 vertical"),
        // Found by `mutated_corpus_never_panics`: an infinite intensity bound.
        ("bad_generation_type_overflow.ies", 9, "file generation type 1e308 overflows"),
    ];
    for &(name, line, needle) in cases {
        let path = data_dir().join(name);
        let e = IesProfile::load(&path).expect_err(name);
        assert_eq!(e.line, line, "{name}: {e}");
        assert!(e.message.contains(needle), "{name}: {e}");
        assert_eq!(e.to_string(), format!("{}:{}: {}", path.display(), line, e.message));
        // Same through parse.
        let text = String::from_utf8_lossy(&std::fs::read(&path).unwrap()).into_owned();
        let e2 = IesProfile::parse(&text, name).expect_err(name);
        assert_eq!(e2.line, line, "{name}: {e2}");
        assert_eq!(e2.source, name);
    }
}

#[test]
fn unreadable_file_is_line_zero_naming_the_path() {
    let path = data_dir().join("no_such_file.ies");
    let e = IesProfile::load(&path).unwrap_err();
    assert_eq!(e.line, 0);
    assert!(e.to_string().contains("no_such_file.ies"), "{e}");
    let boxed: Box<dyn std::error::Error> = Box::new(e);
    assert!(boxed.to_string().contains(":0: "));
}

#[test]
fn huge_counts_do_not_allocate() {
    // 10^5 × 10^5 is over the value limit; 10^9 over the angle limit; a plausible
    // 90000 × 100 with no data fails at end of file without reserving for it.
    for (nv, nh, needle) in [
        ("100000", "100000", "absurd"),
        ("1000000000", "1", "absurd"),
        ("90000", "100", "end of file"),
    ] {
        let text = format!("IESNA:LM-63-2002\nTILT=NONE\n1 -1 1 {nv} {nh} 1 2 0 0 0\n1 1 0\n0 1 2\n");
        let e = IesProfile::parse(&text, "huge").unwrap_err();
        assert!(e.message.contains(needle), "{e}");
    }
}

#[test]
fn counts_written_as_reals_and_bom_accepted() {
    let text = "\u{feff}IESNA:LM-63-2002\r\nTILT = NONE\r\n1.0 -1 1 3.0 1. 1.0 2 0 0 0\r\n1 1 0\r\n0 45 90\r\n0\r\n10 5 0\r\n\u{1a}";
    let p = IesProfile::parse(text, "reals").unwrap();
    assert_eq!(p.vertical_deg.len(), 3);
    assert_close!(p.candela(DVec3::NEG_Z), 10.0);
    let e = IesProfile::parse(&text.replace("3.0 1.", "3.5 1."), "reals").unwrap_err();
    assert_eq!(e.line, 3);
}

// ---------------------------------------------------------------------------
// Fuzz: mutated corpus files never panic
// ---------------------------------------------------------------------------

fn corpus_texts() -> Vec<Vec<u8>> {
    let mut names: Vec<PathBuf> = std::fs::read_dir(data_dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "ies"))
        .collect();
    names.sort();
    names.into_iter().map(|p| std::fs::read(p).unwrap()).collect()
}

const INTERESTING: &[&str] = &[
    "-1",
    "0",
    "1",
    "-0",
    "1e308",
    "-1e308",
    "1e-320",
    "1000000000",
    "4294967296",
    "nan",
    "inf",
    "90",
    "180",
    "360",
    "180.00001",
    "89.99999",
    "3",
    "2",
    "",
    ",",
    "1.5",
    "TILT=INCLUDE",
    "\n",
    "\r\n",
    "9999999999999999999999",
];

#[derive(Debug, Clone)]
enum Mutation {
    Flip { at: usize, byte: u8 },
    Truncate { at: usize },
    SwapNumber { nth: usize, with: usize },
    DeleteLine { nth: usize },
    DuplicateLine { nth: usize },
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        (
            any::<usize>(),
            prop::sample::select(b"0123456789-+.,eE \n\r\tN=[]TILxAa\x00\xff".to_vec())
        )
            .prop_map(|(at, byte)| Mutation::Flip { at, byte }),
        any::<usize>().prop_map(|at| Mutation::Truncate { at }),
        (any::<usize>(), 0..INTERESTING.len()).prop_map(|(nth, with)| Mutation::SwapNumber { nth, with }),
        any::<usize>().prop_map(|nth| Mutation::DeleteLine { nth }),
        any::<usize>().prop_map(|nth| Mutation::DuplicateLine { nth }),
    ]
}

fn apply(mut bytes: Vec<u8>, m: &Mutation) -> Vec<u8> {
    match *m {
        Mutation::Flip { at, byte } => {
            if !bytes.is_empty() {
                let i = at % bytes.len();
                bytes[i] = byte;
            }
            bytes
        }
        Mutation::Truncate { at } => {
            bytes.truncate(at % (bytes.len() + 1));
            bytes
        }
        Mutation::SwapNumber { nth, with } => {
            let text = String::from_utf8_lossy(&bytes).into_owned();
            let spans: Vec<(usize, usize)> = {
                let mut v = Vec::new();
                let mut start = None;
                for (i, c) in text.char_indices() {
                    let num = c.is_ascii_digit() || c == '.' || c == '-';
                    match (num, start) {
                        (true, None) => start = Some(i),
                        (false, Some(s)) => {
                            v.push((s, i));
                            start = None;
                        }
                        _ => {}
                    }
                }
                if let Some(s) = start {
                    v.push((s, text.len()));
                }
                v
            };
            if spans.is_empty() {
                return bytes;
            }
            let (s, e) = spans[nth % spans.len()];
            format!("{}{}{}", &text[..s], INTERESTING[with], &text[e..]).into_bytes()
        }
        Mutation::DeleteLine { nth } | Mutation::DuplicateLine { nth } => {
            let text = String::from_utf8_lossy(&bytes).into_owned();
            let mut lines: Vec<&str> = text.split('\n').collect();
            let i = nth % lines.len();
            if matches!(m, Mutation::DeleteLine { .. }) {
                lines.remove(i);
            } else {
                lines.insert(i, lines[i]);
            }
            lines.join("\n").into_bytes()
        }
    }
}

fn check_robust(bytes: &[u8]) {
    let text = String::from_utf8_lossy(bytes);
    // Lines end at LF, CR LF or a lone CR, as the parser counts them.
    let n_lines = text.replace("\r\n", "\n").replace('\r', "\n").lines().count();
    match IesProfile::parse(&text, "fuzz") {
        Ok(p) => {
            let bound = p.max_cycles_factor();
            assert!(bound.is_finite() && bound >= 0.0);
            let cone = p.bounding_half_angle();
            assert!((0.0..=PI).contains(&cone));
            for d in directions(64) {
                let f = p.cycles_factor(d);
                assert!(f.is_finite() && f >= 0.0 && f <= bound * (1.0 + 1e-9), "{f} vs {bound}");
                let v = (-d.z).acos();
                if v > cone + 1e-12 {
                    assert_eq!(f, 0.0);
                }
            }
            let _ = p.describe();
        }
        Err(e) => {
            assert!(e.line <= n_lines + 1, "line {} of {n_lines}: {e}", e.line);
            assert!(!e.message.is_empty());
        }
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 2000, ..ProptestConfig::default() })]

    #[test]
    fn mutated_corpus_never_panics(file in any::<prop::sample::Index>(), muts in prop::collection::vec(mutation(), 1..6)) {
        let corpus = corpus_texts();
        let mut bytes = corpus[file.index(corpus.len())].clone();
        for m in &muts {
            bytes = apply(bytes, m);
        }
        check_robust(&bytes);
    }

    #[test]
    fn arbitrary_text_never_panics(s in "(TILT=NONE|TILT=INCLUDE|IESNA91|[0-9 .,eE+\\-\n\r]{0,20}){0,30}") {
        check_robust(s.as_bytes());
    }
}
