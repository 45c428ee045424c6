//! # Tyndall core
//!
//! Noise-free single scattering of light in haze and fog, in Rust, free of
//! Python, USD and Blender. A [`scene::Scene`] (JSON) goes in; [`render::render`]
//! returns the images (`inscatter`, `transmittance`, `depth`, …) and a
//! [`report::Report`] with timings, an error estimate and the plan.
//!
//! Modules: [`medium`] (phase functions, homogeneous media, Ishiyama's height
//! fog, Klassen's fog layer), [`spectrum`] (CIE 1931 colour, solar spectrum),
//! [`geometry`] (Blender cameras, BVH), [`render`], [`io`] (EXR, PNG),
//! [`numeric`] (stable forms, adaptive quadrature).
#![warn(missing_docs)]
// Per-channel loops index several parallel arrays (σ_s, σ_t, E, …) by channel;
// iterator chains over four zipped arrays read worse than `for c in 0..C`.
#![allow(clippy::needless_range_loop)]

pub mod bench_scenes;
pub mod geometry;
pub mod io;
pub mod light;
pub mod medium;
pub mod numeric;
pub mod render;
pub mod report;
pub mod scene;
pub mod sky;
pub mod spectrum;

pub use render::{Images, RenderError, RenderStage, render, render_cancellable};
pub use report::Report;
pub use scene::{Scene, SceneError};

/// The crate version.
pub const VERSION: &str = env!("CARGO_PKG_VERSION");

/// Helpers shared by the unit tests.
#[cfg(test)]
pub(crate) mod test_support {
    /// Uniform numbers in [0, 1) from a xorshift64 generator seeded with
    /// `seed` (≠ 0): reproducible random inputs without a dependency.
    pub fn uniform(seed: u64) -> impl FnMut() -> f64 {
        let mut state = seed;
        move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        }
    }
}
