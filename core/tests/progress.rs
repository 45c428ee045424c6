//! The progress callback: rows first, then the pixels integrated against the
//! pixel filter, each stage counting up to its total.

use std::path::Path;
use std::sync::Mutex;
use tyndall_core::{RenderStage, Scene, render};

#[test]
fn progress_counts_rows_then_filtered_pixels() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../examples/stage_four_spots.json");
    let mut scene = Scene::load(&path).expect("example loads");
    if let tyndall_core::scene::Camera::Perspective(c) = &mut scene.camera {
        c.resolution = [64, 36];
    }
    scene.output.tolerance = 1e-2;
    let calls = Mutex::new(Vec::new());
    let cb = |stage: RenderStage, done: usize, total: usize| calls.lock().unwrap().push((stage, done, total));
    let (_, report) = render(&scene, Some(&cb)).unwrap();
    let calls = calls.into_inner().unwrap();
    let rows: Vec<_> = calls.iter().filter(|c| c.0 == RenderStage::Rows).collect();
    let filter: Vec<_> = calls.iter().filter(|c| c.0 == RenderStage::PixelFilter).collect();
    // One call per row, in order (calls come one at a time, counted under a lock).
    assert_eq!(rows.iter().map(|c| c.1).collect::<Vec<_>>(), (1..=36).collect::<Vec<_>>());
    assert!(rows.iter().all(|c| c.2 == 36));
    // Then the filtered pixels, in tiles, rising to the count the report gives.
    let edge = report.error.edge_pixels as usize;
    assert!(edge > 0, "the stage has filtered pixels");
    assert!(!filter.is_empty() && filter.iter().all(|c| c.2 == edge));
    assert!(filter.windows(2).all(|w| w[0].1 < w[1].1), "the filter's count went down");
    assert_eq!(filter.last().map(|c| c.1), Some(edge));
    let first_filter = calls.iter().position(|c| c.0 == RenderStage::PixelFilter).unwrap();
    assert!(
        calls[first_filter..].iter().all(|c| c.0 == RenderStage::PixelFilter),
        "rows after the filter began"
    );
}
