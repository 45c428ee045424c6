//! `render_cancellable`: a flag set by another thread stops the render with
//! `RenderError::Cancelled` (never a partial image), and an unset flag
//! changes nothing.

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};
use tyndall_core::render::RenderError;
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
