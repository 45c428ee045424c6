//! Fuzz target: `IesProfile::parse` on arbitrary bytes never panics; errors name a
//! line within the file; accepted profiles evaluate to finite, non-negative values
//! within `max_cycles_factor` and zero outside `bounding_half_angle`.
//!
//! Run from `core/fuzz`: `cargo +nightly fuzz run ies_parse ../tests/data/ies`
//! (the hand-written corpus seeds it; new inputs go to `corpus/ies_parse`).
#![no_main]

use glam::DVec3;
use libfuzzer_sys::fuzz_target;
use tyndall_core::light::ies::IesProfile;

fuzz_target!(|data: &[u8]| {
    let text = String::from_utf8_lossy(data);
    let lines = text.lines().count();
    match IesProfile::parse(&text, "fuzz") {
        Ok(p) => {
            let bound = p.max_cycles_factor();
            let cone = p.bounding_half_angle();
            assert!(bound.is_finite() && bound >= 0.0);
            assert!((0.0..=std::f64::consts::PI).contains(&cone));
            for i in 0..32 {
                let t = i as f64 / 31.0 * std::f64::consts::PI;
                let d = DVec3::new(t.sin() * (3.0 * t).cos(), t.sin() * (3.0 * t).sin(), -t.cos());
                let f = p.cycles_factor(d);
                assert!(f.is_finite() && f >= 0.0 && f <= bound * (1.0 + 1e-9));
                if t > cone + 1e-12 {
                    assert_eq!(f, 0.0);
                }
            }
            let _ = p.describe();
        }
        Err(e) => assert!(e.line <= lines + 1),
    }
});
