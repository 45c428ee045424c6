//! `render_cancellable`: a flag set by another thread stops the render with
//! `RenderError::Cancelled` (never a partial image), and an unset flag
//! changes nothing.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use tyndall_core::render::RenderError;
use tyndall_core::sky::{
    atmosphere::AtmosphereParams,
    render_world, render_world_cancellable,
    texture::{BuildOptions, TextureSettings},
};
use tyndall_core::{Scene, render, render_cancellable};

fn stage(width: u32, height: u32, tolerance: f64) -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/stage_four_spots.json");
    let mut scene = Scene::load(&path).expect("example loads");
    match &mut scene.camera {
        tyndall_core::scene::Camera::Perspective(c) => c.resolution = [width, height],
        tyndall_core::scene::Camera::Equirectangular(c) => c.resolution = [width, height],
    }
    scene.output.tolerance = tolerance;
    scene
}

#[test]
fn an_unset_flag_changes_nothing() {
    let scene = stage(48, 27, 1e-2);
    let flag = AtomicBool::new(false);
    let (a, _) = render(&scene, None).unwrap();
    let (b, _) = render_cancellable(&scene, None, Some(&flag)).unwrap();
    assert_eq!(a.inscatter, b.inscatter);
    assert_eq!(a.error, b.error);
}

#[test]
fn a_flag_set_before_the_render_cancels_it() {
    let scene = stage(48, 27, 1e-2);
    let flag = AtomicBool::new(true);
    assert!(matches!(render_cancellable(&scene, None, Some(&flag)), Err(RenderError::Cancelled)));
}

#[test]
fn a_flag_set_during_the_render_cancels_it() {
    // 1080p at tolerance 1e-5 runs for tens of seconds on two cores.
    let scene = stage(1920, 1080, 1e-5);
    let flag = AtomicBool::new(false);
    let set_at = std::thread::scope(|s| {
        let setter = s.spawn(|| {
            std::thread::sleep(Duration::from_millis(300));
            flag.store(true, Ordering::Relaxed);
            Instant::now()
        });
        let r = render_cancellable(&scene, None, Some(&flag));
        assert!(matches!(r, Err(RenderError::Cancelled)), "{:?}", r.map(|_| ()));
        let returned = Instant::now();
        let set_at = setter.join().unwrap();
        returned.duration_since(set_at)
    });
    // Not a timing target: a bound far above the ≈ 0.2 s measured, far below the render's own time.
    assert!(set_at < Duration::from_secs(10), "stopped {set_at:?} after the flag was set");
}

#[test]
fn a_flag_set_while_a_sun_disc_table_is_built_cancels_it() {
    // A sun through a Henyey–Greenstein g = 0.9999 lobe at tolerance 1e-8:
    // the disc-averaged phase table runs into its node budget, ≈ 2 s in a
    // release build. The flag is asked inside the table, not only after it.
    let scene = Scene::from_json_str(
        r#"{"version": 1,
            "camera": {"type": "perspective", "position": [0, 0, 0], "focal_length_mm": 2000.0,
                       "orientation": {"look_at": {"target": [0, 0.8, 0.6], "up": [0, 0, 1]}}, "resolution": [5, 3]},
            "lights": [{"type": "sun", "direction_to_sun": [0, 0.8, 0.6], "strength_w_m2": 3.0}],
            "media": [{"type": "homogeneous", "scattering": 0.002,
                       "bounds": {"box": {"min": [-50, -50, -50], "max": [50, 50, 50]}},
                       "phase": {"type": "henyey_greenstein", "g": 0.9999}}],
            "output": {"layers": ["inscatter"], "tolerance": 1e-8, "threads": 1, "pixel_filter": {"type": "none"}}}"#,
        "needle lobe",
    )
    .unwrap();
    let flag = AtomicBool::new(false);
    let (taken, set_at) = std::thread::scope(|s| {
        let setter = s.spawn(|| {
            std::thread::sleep(Duration::from_millis(200));
            flag.store(true, Ordering::Relaxed);
            Instant::now()
        });
        let start = Instant::now();
        let r = render_cancellable(&scene, None, Some(&flag));
        assert!(matches!(r, Err(RenderError::Cancelled)), "{:?}", r.map(|_| ()));
        let returned = Instant::now();
        (returned.duration_since(start), returned.duration_since(setter.join().unwrap()))
    });
    // Asked every 64 averages (≈ 1 ms): a bound far above that, below the table's own time.
    assert!(
        set_at < Duration::from_millis(1000),
        "stopped {set_at:?} after the flag was set ({taken:?} in all)"
    );
}

/// The example stage at 32×18 over a wavy terrain of `2·n²` triangles: preparation
/// (BVH, the lights' shadow casters) is nearly all of its time.
fn stage_over_terrain(n: u32) -> Scene {
    let mut scene = stage(32, 18, 1e-2);
    let side = n + 1;
    let positions = (0..side * side)
        .map(|k| {
            let (x, y) = (
                8.0 * f64::from(k % side) / f64::from(n) - 4.0,
                8.0 * f64::from(k / side) / f64::from(n) - 4.0,
            );
            [x, y, 1.0 + 0.2 * (3.0 * x).sin() * (2.0 * y).cos()]
        })
        .collect();
    let triangles = (0..n * n)
        .flat_map(|k| {
            let (i, j) = (k % n, k / n);
            let a = j * side + i;
            [[a, a + 1, a + side + 1], [a, a + side + 1, a + side]]
        })
        .collect();
    scene.meshes.push(tyndall_core::scene::Mesh {
        name: "terrain".into(),
        positions,
        triangles,
        transform: Default::default(),
        visible_to_camera: true,
        casts_shadows: true,
    });
    scene
}

#[test]
fn a_flag_set_while_the_scene_is_prepared_cancels_it() {
    // 720 000 triangles: the BVH and the four spots' shadow casters take most of a
    // second in a release build, the render itself a few ms. The flag is asked inside
    // the BVH build and before each light's casters, not only between the stages.
    let scene = stage_over_terrain(600);
    let (_, report) = render(&scene, None).unwrap();
    let stage_time = |name: &str| report.timings.iter().find(|t| t.stage == name).map_or(0.0, |t| t.seconds);
    let preparation = Duration::from_secs_f64(stage_time("bvh") + stage_time("shadow_volumes"));
    let flag = AtomicBool::new(false);
    let set_at = std::thread::scope(|s| {
        let setter = s.spawn(|| {
            std::thread::sleep(preparation / 10);
            flag.store(true, Ordering::Relaxed);
            Instant::now()
        });
        let r = render_cancellable(&scene, None, Some(&flag));
        assert!(matches!(r, Err(RenderError::Cancelled)), "{:?}", r.map(|_| ()));
        Instant::now().duration_since(setter.join().unwrap())
    });
    // Not a timing target: relative to the same machine's preparation, so that a slow
    // or busy machine scales both (measured: ≈ 0.05 s after the flag, of ≈ 1 s).
    assert!(
        set_at < preparation / 2,
        "stopped {set_at:?} after the flag was set; preparation takes {preparation:?}"
    );
}

/// The atmosphere with the sun 10° up, and a texture `width` px wide at `tolerance`.
fn sky_at_10_degrees(width: usize, tolerance: f64) -> (AtmosphereParams, TextureSettings) {
    let params = AtmosphereParams {
        sun_elevation_rad: 10f64.to_radians(),
        ..Default::default()
    };
    let settings = TextureSettings {
        width,
        tolerance,
        sun_disc: true,
    };
    (params, settings)
}

#[test]
fn a_sky_stops_when_its_flag_is_set() {
    let (params, settings) = sky_at_10_degrees(64, 1e-3);
    let options = BuildOptions::default();
    let set = AtomicBool::new(true);
    assert!(render_world_cancellable(&params, "atmosphere", &settings, &options, Some(&set)).is_none());
    let unset = AtomicBool::new(false);
    let (a, _) = render_world_cancellable(&params, "atmosphere", &settings, &options, Some(&unset)).unwrap();
    let (b, _) = render_world(&params, "atmosphere", &settings);
    assert_eq!(a.rgb, b.rgb);
    // Set while a large sky is built (8192 px at 1e-6: ≈ 3 s in a release build).
    let (_, big) = sky_at_10_degrees(8192, 1e-6);
    let flag = AtomicBool::new(false);
    let set_at = std::thread::scope(|s| {
        let setter = s.spawn(|| {
            std::thread::sleep(Duration::from_millis(200));
            flag.store(true, Ordering::Relaxed);
            Instant::now()
        });
        assert!(render_world_cancellable(&params, "atmosphere", &big, &options, Some(&flag)).is_none());
        Instant::now().duration_since(setter.join().unwrap())
    });
    // Not a timing target: far above the 0.01–0.4 s measured, below the sky's own time.
    assert!(set_at < Duration::from_secs(2), "stopped {set_at:?} after the flag was set");
}

#[test]
fn a_sky_cancelled_and_then_uncancelled_returns_nothing_or_all_of_it() {
    // A flag set and cleared again while a sky is built: once seen, a cancel
    // stays seen, so the result is either none or the whole sky (the review
    // of the cancel found 9 of 200 such builds returning a partial sky).
    let (params, settings) = sky_at_10_degrees(64, 1e-3);
    let (reference, _) = render_world(&params, "atmosphere", &settings);
    let flag = AtomicBool::new(false);
    let running = AtomicBool::new(true);
    let (mut none, mut whole) = (0, 0);
    // Stops the flag's thread however the builds end (a failed assert
    // inside the scope would otherwise wait for it forever).
    struct Stop<'a>(&'a AtomicBool);
    impl Drop for Stop<'_> {
        fn drop(&mut self) {
            self.0.store(false, Ordering::Relaxed);
        }
    }
    std::thread::scope(|s| {
        let _stop = Stop(&running);
        s.spawn(|| {
            while running.load(Ordering::Relaxed) {
                flag.store(true, Ordering::Relaxed);
                std::thread::sleep(Duration::from_micros(300));
                flag.store(false, Ordering::Relaxed);
                std::thread::sleep(Duration::from_micros(700));
            }
        });
        for _ in 0..200 {
            match render_world_cancellable(&params, "atmosphere", &settings, &BuildOptions::default(), Some(&flag)) {
                None => none += 1,
                Some((tex, _)) => {
                    assert_eq!(tex.rgb, reference.rgb, "a partial sky came back");
                    whole += 1;
                }
            }
        }
    });
    assert!(none > 0, "the flag was never seen ({whole} whole)");
}
