//! The pixel filter across beams from their angular profiles (`render::profile`)
//! against the lattice filter of exact view rays at a tight tolerance: the
//! filtered values agree, and every profile-filtered pixel's error is within
//! its estimate, on the stiff cases the model meets — a 0.5° beam narrower
//! than a pixel, a 60° cone in dense haze, two crossing coloured spots, a
//! forward-scattering lobe, a light whose medium is not dimmed (Cast Shadow
//! off), and a beam cut by the floor.

use tyndall_core::{Scene, render};

/// Renders `json` (a scene without `output`) with the profile filter at
/// `tolerance`, with the lattice alone at the same tolerance (the pixels
/// that differ are the profile's), and with the lattice alone at 1e-6;
/// returns the pixels the profile served, the worst ratio of true error to
/// estimate among the profile's pixels, and the relative RMSE of the image.
fn compare(name: &str, mut json: serde_json::Value, tolerance: f64) -> (u64, f64, f64) {
    json["output"] = serde_json::json!({"layers": ["inscatter", "error"], "tolerance": tolerance, "spectral": "never"});
    let scene = Scene::from_json_str(&json.to_string(), "<t>").unwrap();
    let (img, report) = render(&scene, None).unwrap();
    // The same tolerance with the lattice alone: the pixels that differ are the profile's.
    let mut lattice = scene.clone();
    lattice.output.profile_filter = false;
    let (plain, _) = render(&lattice, None).unwrap();
    let mut reference = scene.clone();
    reference.output.tolerance = 1e-6;
    reference.output.profile_filter = false;
    let (exact, exact_report) = render(&reference, None).unwrap();
    assert_eq!(exact_report.stats.pixels_profile_filtered, 0);
    let served = report.stats.pixels_profile_filtered;
    let w = 64usize;
    let (mut worst, mut over, mut sq, mut norm, mut lattice_over) = (0.0f64, 0usize, 0.0f64, 0.0f64, 0usize);
    for (i, ((got, want), (e, e_ref))) in img
        .inscatter
        .iter()
        .zip(&exact.inscatter)
        .zip(img.error.iter().zip(&exact.error))
        .enumerate()
    {
        let profiled = got != &plain.inscatter[i];
        for c in 0..3 {
            let (g, x) = (f64::from(got[c]), f64::from(want[c]));
            assert!(g.is_finite() && f64::from(e[c]).is_finite(), "{name}: pixel {i} not finite");
            let true_err = (g - x).abs() - f64::from(e_ref[c]) - 1e-6 * x.abs();
            let ratio = true_err / f64::from(e[c]).max(1e-300);
            if true_err > 0.0 && !profiled {
                lattice_over += usize::from(ratio > 1.0);
            } else if true_err > 0.0 {
                worst = worst.max(ratio);
                if ratio > 1.0 {
                    over += 1;
                    println!(
                        "{name}: pixel ({}, {}) channel {c}: {g:e} against {x:e}, estimate {:e}",
                        i % w,
                        i / w,
                        e[c]
                    );
                }
            }
            sq += (g - x) * (g - x);
            norm += x * x;
        }
    }
    let rmse = (sq / norm).sqrt();
    println!(
        "{name}: {served} of {} filtered pixels from the profile, relative RMSE {rmse:.3e}, worst error/estimate {worst:.2}, {over} channels over; elsewhere {lattice_over} channels over",
        report.error.edge_pixels
    );
    // The profile's estimates are honest in every pixel it served.
    assert_eq!(over, 0, "{name}: {over} profile-filtered pixel channels over their estimate");
    (served, worst, rmse)
}

fn spot(name: &str, position: [f64; 3], target: [f64; 3], size_deg: f64, colour: [f64; 3]) -> serde_json::Value {
    serde_json::json!({"type": "spot", "name": name, "position": position, "power_w": 2000.0, "color": colour,
                       "orientation": {"look_at": {"target": target, "up": [0, 0, 1]}},
                       "spot_size_deg": size_deg, "spot_blend": 0.1})
}

fn stage(lights: Vec<serde_json::Value>, scattering: f64, phase: serde_json::Value, floor: bool) -> serde_json::Value {
    let meshes = if floor {
        serde_json::json!([{"name": "floor", "positions": [[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]],
                            "triangles": [[0, 1, 2], [0, 2, 3]]}])
    } else {
        serde_json::json!([])
    };
    serde_json::json!({
        "version": 1,
        "camera": {"type": "perspective", "position": [0, -9, 2], "resolution": [64, 36],
                   "orientation": {"look_at": {"target": [0, 0, 2], "up": [0, 0, 1]}}},
        "meshes": meshes,
        "lights": lights,
        "media": [{"type": "homogeneous", "name": "haze", "scattering": scattering, "phase": phase}]
    })
}

#[test]
fn a_narrow_beam_is_filtered_from_its_profile_within_its_estimate() {
    let iso = serde_json::json!({"type": "isotropic"});
    // The benchmark's 5° beam, entering the frame and hitting the floor.
    let five = stage(
        vec![spot("beam", [-9.0, 2.0, 6.0], [3.0, 0.0, 0.0], 5.0, [1.0, 1.0, 1.0])],
        0.02,
        iso.clone(),
        true,
    );
    let (served, _, rmse) = compare("5° beam", five.clone(), 0.1);
    assert!(served > 50, "the profile filtered only {served} pixels");
    assert!(rmse < 0.02, "relative RMSE {rmse}");
    // The same, looser: the profile still serves, and stays within its estimates.
    compare("5° beam, tolerance 0.5", five, 0.5);
    // A 0.5° beam: about a pixel wide across the frame.
    let thin = stage(
        vec![spot("thin", [-6.0, 3.0, 5.0], [6.0, 3.0, 0.5], 0.5, [1.0, 1.0, 1.0])],
        0.05,
        iso.clone(),
        false,
    );
    compare("0.5° beam", thin, 0.1);
    // A 60° cone in dense haze, seen from outside it.
    let wide = stage(
        vec![spot("wide", [0.0, 6.0, 9.0], [0.0, 6.5, 0.0], 60.0, [1.0, 1.0, 1.0])],
        1.0,
        iso.clone(),
        false,
    );
    compare("60° cone, σ = 1", wide, 0.1);
    // Two coloured spots whose beams cross (pixels near the crossing go to the lattice).
    let two = stage(
        vec![
            spot("red", [-6.0, 4.0, 6.0], [4.0, 4.0, 0.0], 6.0, [1.0, 0.1, 0.1]),
            spot("blue", [6.0, 4.0, 6.0], [-4.0, 4.0, 0.0], 6.0, [0.1, 0.2, 1.0]),
        ],
        0.05,
        iso,
        true,
    );
    let (served, _, _) = compare("two crossing spots", two, 0.1);
    assert!(served > 20, "the profile filtered only {served} pixels");
    // A forward-scattering lobe, looking almost into the beam.
    let hg = serde_json::json!({"type": "henyey_greenstein", "g": 0.9});
    let mut into = stage(
        vec![spot("into", [-2.0, 12.0, 2.5], [3.0, -9.0, 1.0], 4.0, [1.0, 1.0, 1.0])],
        0.05,
        hg,
        false,
    );
    compare("HG 0.9, looking along the beam", into.clone(), 0.1);
    // Cast Shadow off: no extinction on the light path.
    into["lights"][0]["casts_shadows"] = serde_json::json!(false);
    into["media"][0]["phase"] = serde_json::json!({"type": "rayleigh"});
    into["media"][0]["absorption"] = serde_json::json!(0.2);
    compare("light path not dimmed", into, 0.1);
}
