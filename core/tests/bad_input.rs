//! Rejected scenes: every rejection names the field path (in `SceneError::path`
//! and in its message), never panics.
//!
//! Paths run through the `type`-tagged enums (`media[i]`, `lights[i]`, `camera`,
//! `phase`) down to the offending field or array element. A *missing* field is
//! reported at the object that lacks it, the field named in the message
//! (`camera: missing field `resolution``), as serde reports it.

// Per-channel loops index several parallel arrays (as in the library).
#![allow(clippy::needless_range_loop)]

use std::panic::{AssertUnwindSafe, catch_unwind};
use tyndall_core::render::RenderError;
use tyndall_core::{Scene, SceneError, render};

const CAMERA: &str =
    r#""camera":{"type":"perspective","position":[0,0,1],"orientation":{"look_at":{"target":[0,1,1]}},"resolution":[4,3]}"#;

/// A valid scene with `extra` appended to the root object.
fn with(extra: &str) -> String {
    format!(r#"{{"version":1,{CAMERA}{extra}}}"#)
}

fn reject(json: &str) -> SceneError {
    match catch_unwind(|| Scene::from_json_str(json, "<test>")) {
        Ok(Ok(_)) => panic!("accepted: {json}"),
        Ok(Err(e)) => e,
        Err(_) => panic!("panicked on: {json}"),
    }
}

/// The error's path is `path` and its display names it.
fn assert_path(json: &str, path: &str) -> SceneError {
    let e = reject(json);
    assert_eq!(e.path, path, "wrong path; message: {e}");
    let shown = e.to_string();
    assert!(shown.contains(path), "display does not name {path}: {shown}");
    assert!(shown.starts_with("<test>: "), "display does not name the source: {shown}");
    e
}

/// serde_json's location suffix: `at line L column C`.
fn assert_line_col(e: &SceneError) {
    let m = &e.message;
    let at = m.rfind(" at line ").unwrap_or_else(|| panic!("no line/column in: {e}"));
    let rest = &m[at + " at line ".len()..];
    let mut it = rest.split(" column ");
    let line: usize = it
        .next()
        .and_then(|l| l.trim().parse().ok())
        .unwrap_or_else(|| panic!("bad line in: {e}"));
    let col: usize = it
        .next()
        .and_then(|c| c.trim().parse().ok())
        .unwrap_or_else(|| panic!("bad column in: {e}"));
    assert!(line >= 1 && col >= 1, "{e}");
}

#[test]
fn unknown_field_at_the_top_level() {
    let e = assert_path(&with(r#","colour":1"#), "colour");
    assert!(e.message.contains("unknown field `colour`"), "{e}");
    assert_line_col(&e);
}

#[test]
fn unknown_field_nested_in_a_medium() {
    let e = assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":0.1,"colour":1}]"#),
        "media[0].colour",
    );
    assert!(e.message.contains("unknown field `colour`"), "{e}");
    assert_line_col(&e);
    // Inside the phase function (a serde-tagged enum) the path stops at the
    // phase object; path + message still name the field: `media[0].phase: unknown field `gg``.
    let e = reject(&with(
        r#","media":[{"type":"homogeneous","scattering":1,"phase":{"type":"henyey_greenstein","gg":0.5}}]"#,
    ));
    assert!(e.path == "media[0].phase" || e.path == "media[0].phase.gg", "{e}");
    assert!(e.message.contains("unknown field `gg`"), "{e}");
    let e = reject(&with(r#","lights":[{"type":"laser"}]"#));
    assert!(e.path == "lights[0]" || e.path == "lights[0].type", "{e}");
    assert!(e.message.contains("`laser`") && e.message.contains("type"), "{e}");
}

#[test]
fn unknown_field_nested_in_a_struct() {
    let e = assert_path(&with(r#","output":{"tolerance":1e-4,"colour":1}"#), "output.colour");
    assert!(e.message.contains("unknown field `colour`"), "{e}");
    let e = reject(&with(
        r#","meshes":[{"positions":[[0,0,0],[1,0,0],[0,1,0]],"triangles":[[0,1,2]],"transform":{"shear":1}}]"#,
    ));
    assert!(e.path.starts_with("meshes[0].transform") && e.message.contains("`shear`"), "{e}");
}

#[test]
fn missing_required_field() {
    let json = format!(r#"{{"version":1,{}}}"#, CAMERA.replace(r#","resolution":[4,3]"#, ""));
    let e = reject(&json);
    let shown = e.to_string();
    assert!(e.path == "camera" || e.path == "camera.resolution", "{shown}");
    assert_line_col(&e);
    assert!(shown.contains("camera") && shown.contains("missing field `resolution`"), "{shown}");
    // Required fields of plain structs and of the root.
    let e = reject(r#"{"version":1}"#);
    assert!(e.message.contains("missing field `camera`"), "{e}");
    let e = reject(&with(r#","meshes":[{"positions":[[0,0,0]]}]"#));
    assert!(
        e.path.starts_with("meshes[0]") && e.message.contains("missing field `triangles`"),
        "{e}"
    );
    let e = reject(&with(r#","media":[{"type":"fog_layer","extinction":0.01}]"#));
    assert!(
        e.path.starts_with("media[0]") && e.message.contains("missing field `top_height_m`"),
        "{e}"
    );
}

#[test]
fn nan_and_infinity_literals_are_rejected_with_line_and_column() {
    for lit in ["NaN", "nan", "Infinity", "-Infinity", "inf"] {
        let e = reject(&with(&format!(r#","media":[{{"type":"homogeneous","scattering":{lit}}}]"#)));
        assert_line_col(&e);
        assert_eq!(e.path, "media[0].scattering", "{lit}: {e}");
        let e = reject(&with(&format!(r#","lights":[{{"type":"sun","direction_to_sun":[0,{lit},1]}}]"#)));
        assert_line_col(&e);
        assert_eq!(e.path, "lights[0].direction_to_sun[1]", "{lit}: {e}");
        let e = reject(&with(&format!(r#","output":{{"tolerance":{lit}}}"#)));
        assert_line_col(&e);
        assert_eq!(e.path, "output.tolerance", "{lit}: {e}");
    }
    // A literal that overflows f64 is not infinity either.
    let e = assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":1e999}]"#),
        "media[0].scattering",
    );
    assert!(e.message.contains("out of range"), "{e}");
    assert_line_col(&e);
}

#[test]
fn negative_density() {
    let e = assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":-0.1}]"#),
        "media[0].scattering",
    );
    assert!(e.message.contains("-0.1"), "{e}");
    assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":[0.1,-1e-9,0.1]}]"#),
        "media[0].scattering[1]",
    );
    assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":0.1,"absorption":-1}]"#),
        "media[0].absorption",
    );
    assert_path(
        &with(
            r#","media":[{"type":"homogeneous","scattering":0.1},{"type":"height_fog","scale_height_m":100,"mie":{"scattering":[1,2,-3]}}]"#,
        ),
        "media[1].mie.scattering[2]",
    );
    assert_path(
        &with(r#","media":[{"type":"height_fog","scale_height_m":100,"rayleigh":{"scattering":1,"absorption":-2}}]"#),
        "media[0].rayleigh.absorption",
    );
    assert_path(
        &with(r#","media":[{"type":"fog_layer","top_height_m":10,"extinction":-0.02}]"#),
        "media[0].extinction",
    );
    assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":{"spectrum_nm":[[400,0.1],[500,-0.1]]}}]"#),
        "media[0].scattering.spectrum_nm[1][1]",
    );
    assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":{"power_law":{"at_550nm":-1,"exponent":4}}}]"#),
        "media[0].scattering.power_law.at_550nm",
    );
}

#[test]
fn wrong_type_coefficient_names_its_field() {
    let e = assert_path(
        &with(r#","media":[{"type":"homogeneous","scattering":"thick"}]"#),
        "media[0].scattering",
    );
    assert!(e.message.contains("coefficient"), "{e}");
    assert_line_col(&e);
}

#[test]
fn zero_length_direction() {
    let e = assert_path(
        &with(r#","lights":[{"type":"sun","direction_to_sun":[0,0,0]}]"#),
        "lights[0].direction_to_sun",
    );
    assert!(e.message.contains("zero-length"), "{e}");
    assert_path(
        &with(r#","lights":[{"type":"ambient"},{"type":"sun","direction_to_sun":[0,-0.0,0]}]"#),
        "lights[1].direction_to_sun",
    );
    assert_path(
        &with(r#","lights":[{"type":"sun","direction_to_sun":[1e-320,0,0]}]"#),
        "lights[0].direction_to_sun",
    );
}

#[test]
fn look_at_target_equal_to_position() {
    let json = format!(r#"{{"version":1,{}}}"#, CAMERA.replace("[0,1,1]", "[0,0,1]"));
    let e = assert_path(&json, "camera.orientation.look_at.target");
    assert!(e.message.contains("coincides"), "{e}");
    // Up parallel to the view direction.
    let json = format!(r#"{{"version":1,{}}}"#, CAMERA.replace(r#"[0,1,1]}"#, r#"[0,0,5],"up":[0,0,-2]}"#));
    assert_path(&json, "camera.orientation.look_at.up");
    // Zero quaternion.
    let json = format!(
        r#"{{"version":1,{}}}"#,
        CAMERA.replace(r#"{"look_at":{"target":[0,1,1]}}"#, r#"{"quaternion_wxyz":[0,0,0,0]}"#)
    );
    assert_path(&json, "camera.orientation.quaternion_wxyz");
}

#[test]
fn phase_asymmetry_out_of_range() {
    for g in ["1.5", "1", "-1", "-1.0000001"] {
        let e = assert_path(
            &with(&format!(
                r#","media":[{{"type":"homogeneous","scattering":1,"phase":{{"type":"henyey_greenstein","g":{g}}}}}]"#
            )),
            "media[0].phase.g",
        );
        assert!(e.message.contains("(-1, 1)"), "{e}");
    }
    assert_path(
        &with(r#","media":[{"type":"height_fog","scale_height_m":1,"mie":{"scattering":1,"phase":{"type":"cornette_shanks","g":2}}}]"#),
        "media[0].mie.phase.g",
    );
    assert_path(
        &with(r#","media":[{"type":"fog_layer","top_height_m":1,"extinction":1,"phase":{"type":"cornette_shanks","g":-3}}]"#),
        "media[0].phase.g",
    );
}

#[test]
fn fog_top_not_above_ground() {
    for (g, t) in [("0", "0"), ("10", "5"), ("-1", "-1")] {
        let e = assert_path(
            &with(&format!(
                r#","media":[{{"type":"fog_layer","ground_height_m":{g},"top_height_m":{t},"extinction":0.01}}]"#
            )),
            "media[0].top_height_m",
        );
        assert!(e.message.contains("ground_height_m"), "{e}");
    }
}

#[test]
fn resolution_zero_or_too_large() {
    for (res, path) in [
        ("[0,3]", "camera.resolution[0]"),
        ("[4,0]", "camera.resolution[1]"),
        ("[70000,3]", "camera.resolution[0]"),
    ] {
        let json = format!(r#"{{"version":1,{}}}"#, CAMERA.replace("[4,3]", res));
        assert_path(&json, path);
    }
}

#[test]
fn negative_resolution_names_its_field() {
    let json = format!(r#"{{"version":1,{}}}"#, CAMERA.replace("[4,3]", "[4,-3]"));
    let e = assert_path(&json, "camera.resolution[1]");
    assert!(e.message.contains("-3"), "{e}");
}

#[test]
fn triangle_index_out_of_range() {
    let e = assert_path(
        &with(r#","meshes":[{"positions":[[0,0,0],[1,0,0],[0,1,0]],"triangles":[[0,1,2],[0,1,3]]}]"#),
        "meshes[0].triangles[1][2]",
    );
    assert!(e.message.contains("3 positions"), "{e}");
    assert_path(
        &with(r#","meshes":[{"positions":[[0,0,0],[1,0,0],[0,1,0]],"triangles":[[0,1,2]]},{"positions":[[0,0,0]],"triangles":[[0,0,1]]}]"#),
        "meshes[1].triangles[0][2]",
    );
    assert_path(
        &with(r#","meshes":[{"positions":[[0,0,0],[1,0,0],[0,1,0]],"triangles":[[0,1,4294967295]]}]"#),
        "meshes[0].triangles[0][2]",
    );
}

#[test]
fn wrong_version() {
    for v in ["0", "2", "4294967295"] {
        let e = assert_path(&format!(r#"{{"version":{v},{CAMERA}}}"#), "version");
        assert!(e.message.contains("version 1"), "{e}");
    }
}

#[test]
fn other_out_of_range_values_name_their_field() {
    for (extra, path) in [
        (r#","media":[{"type":"height_fog","scale_height_m":0}]"#, "media[0].scale_height_m"),
        (
            r#","media":[{"type":"height_fog","scale_height_m":1e8}]"#,
            "media[0].scale_height_m",
        ),
        (
            r#","media":[{"type":"fog_layer","top_height_m":1,"extinction":1,"single_scattering_albedo":1.5}]"#,
            "media[0].single_scattering_albedo",
        ),
        (
            r#","media":[{"type":"homogeneous","scattering":1,"bounds":{"box":{"min":[0,0,0],"max":[1,0,1]}}}]"#,
            "media[0].bounds.box.max[1]",
        ),
        (
            r#","media":[{"type":"homogeneous","scattering":1,"bounds":{"box":{"min":[0,0,0],"max":[1,1,1],"rotation_wxyz":[0,0,0,0]}}}]"#,
            "media[0].bounds.box.rotation_wxyz",
        ),
        (
            r#","media":[{"type":"homogeneous","scattering":1,"bounds":{"box":{"min":[0,0,0],"max":[1,1,1],"rotation_wxyz":[1,0,"x",0]}}}]"#,
            "media[0].bounds.box.rotation_wxyz[2]",
        ),
        (
            r#","lights":[{"type":"sun","direction_to_sun":[0,0,1],"strength_w_m2":-1}]"#,
            "lights[0].strength_w_m2",
        ),
        (r#","lights":[{"type":"ambient","color":[1,-1,1]}]"#, "lights[0].color[1]"),
        (r#","output":{"tolerance":0}"#, "output.tolerance"),
        (
            r#","meshes":[{"positions":[[0,0,0],[1,0,0],[0,1,0]],"triangles":[[0,1,2]],"transform":{"scale":[1,0,1]}}]"#,
            "meshes[0].transform.scale",
        ),
    ] {
        assert_path(&with(extra), path);
    }
}

#[test]
fn malformed_json_is_an_error_not_a_panic() {
    for text in ["", "{", "[]", "null", "1", r#"{"version":1,"#, "\u{feff}{}", r#"{"version":"1"}"#] {
        let e = reject(text);
        assert!(!e.message.is_empty(), "{text:?}: {e}");
    }
}

/// Scenes that never went through `from_json_str` (deserialised without
/// validation, or built in memory) are refused by `render` with the same field
/// path, not rendered or panicked on.
#[test]
fn render_refuses_an_unvalidated_scene() {
    let scene: Scene = serde_json::from_str(&with(r#","media":[{"type":"homogeneous","scattering":[0.1,-1.0,0.1]}]"#)).unwrap();
    match catch_unwind(AssertUnwindSafe(|| render(&scene, None))) {
        Ok(Err(RenderError::InvalidScene(path, msg))) => {
            assert_eq!(path, "media[0].scattering[1]", "{msg}");
        }
        Ok(Err(e)) => panic!("wrong error: {e}"),
        Ok(Ok(_)) => panic!("rendered an invalid scene"),
        Err(_) => panic!("render panicked"),
    }
    let mut scene = Scene::from_json_str(&with(""), "<t>").unwrap();
    scene.version = 7;
    assert!(matches!(render(&scene, None), Err(RenderError::InvalidScene(p, _)) if p == "version"));
    let mut scene = Scene::from_json_str(&with(""), "<t>").unwrap();
    scene.output.tolerance = f64::NAN;
    assert!(matches!(render(&scene, None), Err(RenderError::InvalidScene(p, _)) if p == "output.tolerance"));
}

/// Every number of a valid scene replaced, one at a time, by hostile values:
/// loading never panics, and a scene that loads also renders without panicking
/// (`render` on 4×3 pixels; point-sampled so that the 221 renders take seconds:
/// with Blender's filter this 3-medium scene takes ≈ 0.3 s per render).
#[test]
fn hostile_numbers_never_panic() {
    let base = with(
        r#","meshes":[{"positions":[[-5,-5,0],[5,-5,0],[5,5,0]],"triangles":[[0,1,2]],"transform":{"translation":[0,3,0],"scale":[1,1,1]}}],
            "lights":[{"type":"sun","direction_to_sun":[0.3,0.2,0.9],"strength_w_m2":3},{"type":"ambient","radiance":0.5}],
            "media":[{"type":"height_fog","scale_height_m":100,"reference_height_m":0,"mie":{"scattering":0.001,"phase":{"type":"henyey_greenstein","g":0.5}}},
                     {"type":"fog_layer","ground_height_m":0,"top_height_m":20,"extinction":0.02},
                     {"type":"homogeneous","scattering":[0.001,0.002,0.003],"bounds":{"box":{"min":[-1,-1,-1],"max":[1,2,3]}}}],
            "output":{"pixel_filter":{"type":"none"}}"#,
    );
    // Byte ranges of the numeric literals.
    let bytes = base.as_bytes();
    let mut spans = vec![];
    let mut i = 0;
    while i < bytes.len() {
        let c = bytes[i];
        let starts = (c == b'-' || c.is_ascii_digit()) && i > 0 && matches!(bytes[i - 1], b':' | b',' | b'[');
        if starts {
            let mut j = i + 1;
            while j < bytes.len() && (bytes[j].is_ascii_digit() || matches!(bytes[j], b'.' | b'e' | b'E' | b'-' | b'+')) {
                j += 1;
            }
            spans.push((i, j));
            i = j;
        } else {
            i += 1;
        }
    }
    assert!(spans.len() > 40, "found {} numbers", spans.len());
    let hostile = [
        "-1",
        "0",
        "-0",
        "1e308",
        "-1e308",
        "1e-320",
        "4294967296",
        "1e999",
        "\"x\"",
        "null",
        "[]",
        "{}",
        "true",
    ];
    let (mut loaded, mut rejected) = (0, 0);
    for &(a, b) in &spans {
        for h in hostile {
            let text = format!("{}{}{}", &base[..a], h, &base[b..]);
            let result = catch_unwind(|| Scene::from_json_str(&text, "<hostile>"));
            match result {
                Err(_) => panic!("from_json_str panicked on {h} at byte {a}: {text}"),
                Ok(Err(e)) => {
                    rejected += 1;
                    assert!(!e.path.is_empty() && !e.message.is_empty(), "{e}");
                }
                Ok(Ok(scene)) => {
                    loaded += 1;
                    if catch_unwind(AssertUnwindSafe(|| render(&scene, None))).is_err() {
                        panic!("render panicked on {h} at byte {a}: {text}");
                    }
                }
            }
        }
    }
    eprintln!(
        "hostile numbers: {} variants, {loaded} loaded and rendered, {rejected} rejected",
        spans.len() * hostile.len()
    );
}

#[test]
fn stage_light_names_fit_exr_channel_names() {
    // A 300-byte spot name used to render and then fail writing the EXR
    // (`surface_transmittance.<name>.R` over OpenEXR's 255 bytes).
    let long = "a".repeat(tyndall_core::scene::MAX_STAGE_LIGHT_NAME_BYTES + 1);
    let e = assert_path(
        &with(&format!(r#","lights":[{{"type":"spot","name":"{long}","position":[0,0,3]}}]"#)),
        "lights[0].name",
    );
    assert!(e.message.contains("255-byte"), "{e}");
    let fits = "a".repeat(tyndall_core::scene::MAX_STAGE_LIGHT_NAME_BYTES);
    Scene::from_json_str(
        &with(&format!(r#","lights":[{{"type":"spot","name":"{fits}","position":[0,0,3]}}]"#)),
        "<test>",
    )
    .expect("a name of the largest length is accepted");
}

#[test]
fn vectors_whose_length_overflows_are_named_as_such() {
    // Finite but huge: the messages used to say "up is parallel to the view
    // direction" and "zero-length quaternion".
    let cam = |pos: &str, orient: &str| {
        format!(r#"{{"version":1,"camera":{{"type":"perspective","position":{pos},"orientation":{orient},"resolution":[4,3]}}}}"#)
    };
    let e = assert_path(
        &cam("[1e300,0,2.5]", r#"{"look_at":{"target":[0,0,2.2]}}"#),
        "camera.orientation.look_at.target",
    );
    assert!(e.message.contains("overflows"), "{e}");
    let e = assert_path(
        &cam("[0,-10,2.5]", r#"{"look_at":{"target":[0,0,2.2],"up":[0,0,1e300]}}"#),
        "camera.orientation.look_at.up",
    );
    assert!(e.message.contains("overflows"), "{e}");
    let e = assert_path(
        &cam("[0,-10,2.5]", r#"{"quaternion_wxyz":[1e300,1e300,0,0]}"#),
        "camera.orientation.quaternion_wxyz",
    );
    assert!(e.message.contains("overflows"), "{e}");
}
