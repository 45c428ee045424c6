//! Blender's pixel filter, so that edges composite cleanly over a Cycles render.
//!
//! Cycles filters every pixel with a separable Blackman–Harris window whose
//! "Filter Size" is 1.5 px by default. Cycles' film code (`filter_table`)
//! doubles the width for Blackman–Harris before tabulating it, so the window
//! spans `±width` px around the pixel centre:
//! `w(x) = 0.35875 − 0.48829 cos 2πt + 0.14128 cos 4πt − 0.01168 cos 6πt`,
//! `t = x/(2·width) + 1/2`, for `|x| ≤ width`, applied along x and y.
//!
//! Tyndall's images are smooth except where a view ray's surface changes
//! (silhouettes). A pixel is treated as a silhouette when a neighbour within
//! the filter's reach sees another surface and the two centre samples differ
//! by more than the tolerance. There, pixels are integrated against the
//! filter with an `n × n` midpoint rule, `n` doubling from 4 until two
//! successive estimates agree to the tolerance (or `n = 16`); the difference
//! is the error estimate, reported separately (`edge_max_abs`,
//! `edge_pixels_not_converged`): a step inside a pixel converges only as
//! O(1/n), so silhouettes are the one place the tolerance may not be met.
//! Elsewhere the centre sample stands for the filtered value; for a smooth
//! image the filter changes it by `(σ²/2)·∇²L + O(σ⁴)` with `σ²` the filter's
//! per-axis variance, and that term, from the discrete Laplacian of the
//! centre samples, is added to the pixel's error estimate.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// The pixel filter. JSON: `{"type": "blackman_harris", "width_px": 1.5}` or `{"type": "none"}`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, schemars::JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case", deny_unknown_fields)]
pub enum PixelFilter {
    /// Separable Blackman–Harris window (Blender/Cycles default).
    BlackmanHarris {
        /// Full width, px, 0.01..=10. Default 1.5 (Blender's Filter Size).
        #[serde(default = "default_width")]
        width_px: f64,
    },
    /// Point samples at pixel centres.
    None,
}

fn default_width() -> f64 {
    1.5
}

impl Default for PixelFilter {
    fn default() -> Self {
        PixelFilter::BlackmanHarris { width_px: 1.5 }
    }
}

impl PixelFilter {
    /// Window value at offset `x` px from the pixel centre (unnormalised).
    pub fn weight(&self, x: f64) -> f64 {
        match *self {
            PixelFilter::BlackmanHarris { width_px } => {
                if x.abs() > width_px {
                    return 0.0;
                }
                let a = 2.0 * PI * (x / (2.0 * width_px) + 0.5);
                0.35875 - 0.48829 * a.cos() + 0.14128 * (2.0 * a).cos() - 0.01168 * (3.0 * a).cos()
            }
            PixelFilter::None => {
                if x == 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
        }
    }

    /// Half of the support, px (Cycles' doubled Blackman–Harris width: `width_px`).
    pub fn radius(&self) -> f64 {
        match *self {
            PixelFilter::BlackmanHarris { width_px } => width_px,
            PixelFilter::None => 0.0,
        }
    }

    /// `n` midpoint nodes `(offset px, normalised weight)` along one axis.
    pub fn nodes(&self, n: usize) -> Vec<(f64, f64)> {
        let r = self.radius();
        if r == 0.0 || n == 0 {
            return vec![(0.0, 1.0)];
        }
        let h = 2.0 * r / n as f64;
        let raw: Vec<(f64, f64)> = (0..n)
            .map(|i| {
                let x = -r + (i as f64 + 0.5) * h;
                (x, self.weight(x))
            })
            .collect();
        let sum: f64 = raw.iter().map(|p| p.1).sum();
        raw.into_iter().map(|(x, w)| (x, w / sum)).collect()
    }

    /// Per-axis variance of the normalised window, px².
    pub fn variance(&self) -> f64 {
        let nodes = self.nodes(4096);
        nodes.iter().map(|(x, w)| x * x * w).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blackman_harris_window_shape() {
        let f = PixelFilter::default();
        // Peak 1.0 at the centre (0.35875 + 0.48829 + 0.14128 + 0.01168), ~6e-5 at the ends.
        assert!((f.weight(0.0) - 1.0).abs() < 1e-12);
        assert!((f.weight(1.5) - 6e-5).abs() < 1e-5);
        assert_eq!(f.weight(1.51), 0.0);
        let s: f64 = f.nodes(16).iter().map(|p| p.1).sum();
        assert!((s - 1.0).abs() < 1e-12);
        // Variance of the 4-term Blackman–Harris window on [−W/2, W/2], W = 2·1.5 px: computed
        // in closed form, σ² = w²·(1/12 − (1/(2π²))·(a1 − a2/4 + a3/9)/a0) with
        // a = (0.35875, 0.48829, 0.14128, 0.01168).
        let (a0, a1, a2, a3) = (0.35875, 0.48829, 0.14128, 0.01168);
        let w: f64 = 3.0;
        let exact = w * w * (1.0 / 12.0 - (a1 - a2 / 4.0 + a3 / 9.0) / (2.0 * PI * PI * a0));
        assert!((f.variance() - exact).abs() < 1e-6 * exact, "{} vs {exact}", f.variance());
    }
}
