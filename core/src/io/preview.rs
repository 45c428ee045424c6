//! 8-bit sRGB PNG previews of linear RGB images.
//!
//! The pipeline of [`write_png_preview`], per pixel, in `f64`:
//!
//! 1. negative components are clamped to 0;
//! 2. exposure: multiply by `2^exposure_stops`;
//! 3. tone mapping with the *luminance-based Reinhard* curve
//!    `c' = c / (1 + Y)`, where `Y = 0.2126 R + 0.7152 G + 0.0722 B` is the
//!    Rec. 709 / sRGB luminance of the exposed pixel. All three components
//!    are divided by the same factor, so hue and saturation are kept and the
//!    output luminance is `Y / (1 + Y)`, which never reaches 1; a very
//!    saturated bright colour can still push one component past 1;
//! 4. clamp each component to `[0, 1]`;
//! 5. sRGB transfer function of IEC 61966-2-1: `12.92 c` for
//!    `c <= 0.0031308`, else `1.055 c^(1/2.4) - 0.055`;
//! 6. quantise to 8 bits with `round(255 v)`.
//!
//! A pixel with a NaN or infinite component becomes magenta `(255, 0, 255)` so
//! that numerical errors are visible, and is counted.
//!
//! The PNG is 8-bit RGB, row 0 the top row, with an `sRGB` chunk (perceptual
//! intent), written atomically like every file of this module.

use std::io::{BufWriter, Write};
use std::path::Path;

use super::{ImageIoError, checked_pixel_count, write_atomically};

/// Rec. 709 / sRGB luminance weights of linear R, G, B.
const LUMINANCE_WEIGHTS: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// Exposure is clamped to this many stops either way; within it every finite
/// `f32` stays finite and non-zero values stay non-zero in `f64`.
const MAX_EXPOSURE_STOPS: f64 = 200.0;

/// Tone-mapped luminance [`auto_exposure`] gives the 99th-percentile pixel.
const AUTO_EXPOSURE_TARGET: f64 = 0.9;

/// The colour of pixels with a NaN or infinite component.
const MAGENTA: [u8; 3] = [255, 0, 255];

/// Writes an 8-bit sRGB PNG preview of the linear RGB image `rgb`
/// (`width * height` pixels, row-major, row 0 the top row), atomically.
///
/// The image is scaled by `2^exposure_stops` (clamped to ±200 stops), tone
/// mapped with the luminance-based Reinhard curve `c / (1 + Y)` and encoded
/// with the sRGB transfer function; see the [module documentation](self) for
/// the exact formulas.
///
/// Returns the number of non-finite pixels (any component NaN or ±infinity),
/// which are drawn magenta. Fails with [`ImageIoError::Invalid`] if the size
/// is zero or too large for PNG, `rgb.len()` is not `width * height`, or
/// `exposure_stops` is not finite.
pub fn write_png_preview(path: &Path, width: usize, height: usize, rgb: &[[f32; 3]], exposure_stops: f32) -> Result<usize, ImageIoError> {
    let pixels = checked_pixel_count(path, width, height)?;
    if rgb.len() != pixels {
        return Err(ImageIoError::Invalid(format!(
            "{}: {} RGB pixels given, a {width}x{height} image needs {pixels}",
            path.display(),
            rgb.len()
        )));
    }
    if !exposure_stops.is_finite() {
        return Err(ImageIoError::Invalid(format!(
            "{}: exposure of {exposure_stops} stops is not finite",
            path.display()
        )));
    }
    // `checked_pixel_count` limits both sides to i32::MAX, which fits in u32.
    let (png_width, png_height) = (width as u32, height as u32);
    let scale = f64::from(exposure_stops).clamp(-MAX_EXPOSURE_STOPS, MAX_EXPOSURE_STOPS).exp2();

    let mut data = Vec::with_capacity(pixels * 3);
    let mut non_finite = 0;
    for pixel in rgb {
        if pixel.iter().all(|c| c.is_finite()) {
            data.extend(display_pixel(*pixel, scale));
        } else {
            non_finite += 1;
            data.extend(MAGENTA);
        }
    }

    write_atomically(path, |file| {
        let png_error = |error: png::EncodingError| match error {
            png::EncodingError::IoError(source) => ImageIoError::io(path, source),
            other => ImageIoError::Png {
                path: path.to_path_buf(),
                message: other.to_string(),
            },
        };
        let mut buffered = BufWriter::new(file);
        let mut encoder = png::Encoder::new(&mut buffered, png_width, png_height);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        encoder.set_source_srgb(png::SrgbRenderingIntent::Perceptual);
        let mut writer = encoder.write_header().map_err(png_error)?;
        writer.write_image_data(&data).map_err(png_error)?;
        writer.finish().map_err(png_error)?;
        buffered.flush().map_err(|e| ImageIoError::io(path, e))
    })?;
    Ok(non_finite)
}

/// Exposure, in stops, for [`write_png_preview`] that brings the image's
/// 99th-percentile luminance to 0.9 after tone mapping.
///
/// The luminance `Y = 0.2126 R + 0.7152 G + 0.0722 B` is taken over the
/// finite pixels (negative components clamped to 0); the percentile is the
/// nearest-rank one (the `ceil(0.99 n)`-th smallest). Since the tone curve
/// maps luminance `Y` to `Y / (1 + Y)`, the exposure is
/// `log2(9 / Y_99)`. A grey pixel of luminance `Y_99` thus shows at linear
/// 0.9; a saturated one may show a little dimmer after clamping.
///
/// Returns 0 for an empty image, one without finite pixels, or one whose
/// 99th-percentile luminance is 0 (e.g. all black).
pub fn auto_exposure(rgb: &[[f32; 3]]) -> f32 {
    let mut luminances: Vec<f64> = rgb
        .iter()
        .filter(|pixel| pixel.iter().all(|c| c.is_finite()))
        .map(|pixel| luminance(pixel.map(|c| f64::from(c).max(0.0))))
        .collect();
    if luminances.is_empty() {
        return 0.0;
    }
    let count = luminances.len();
    // Nearest rank: the smallest value with at least 99 % of the values at or
    // below it. `99 * count` cannot overflow for any slice that fits in memory.
    let rank = (99 * count).div_ceil(100).max(1);
    let (_, &mut percentile, _) = luminances.select_nth_unstable_by(rank - 1, |a, b| a.total_cmp(b));
    if percentile <= 0.0 {
        return 0.0;
    }
    let target_input = AUTO_EXPOSURE_TARGET / (1.0 - AUTO_EXPOSURE_TARGET);
    (target_input / percentile).log2() as f32
}

/// Rec. 709 luminance of linear RGB.
fn luminance(rgb: [f64; 3]) -> f64 {
    rgb.iter().zip(LUMINANCE_WEIGHTS).map(|(c, w)| c * w).sum()
}

/// Exposure, tone curve, clamp, sRGB encoding and quantisation of one finite
/// pixel.
fn display_pixel(pixel: [f32; 3], scale: f64) -> [u8; 3] {
    let exposed = pixel.map(|c| f64::from(c).max(0.0) * scale);
    let factor = 1.0 / (1.0 + luminance(exposed));
    exposed.map(|c| quantize(srgb_encode((c * factor).clamp(0.0, 1.0))))
}

/// The sRGB transfer function (IEC 61966-2-1) of a linear value in `[0, 1]`.
fn srgb_encode(linear: f64) -> f64 {
    if linear <= 0.003_130_8 {
        12.92 * linear
    } else {
        1.055 * linear.powf(1.0 / 2.4) - 0.055
    }
}

/// `round(255 v)` of a value in `[0, 1]`.
fn quantize(encoded: f64) -> u8 {
    // The clamp makes the cast exact and lossless.
    (encoded * 255.0).round().clamp(0.0, 255.0) as u8
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use std::fs::File;
    use std::io::BufReader;
    use std::path::PathBuf;

    fn temp_dir(test: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("tyndall-png-test-{}-{test}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// Decodes an 8-bit RGB PNG into (width, height, bytes).
    fn decode(path: &Path) -> (u32, u32, Vec<u8>) {
        let decoder = png::Decoder::new(BufReader::new(File::open(path).unwrap()));
        let mut reader = decoder.read_info().unwrap();
        let mut buf = vec![0; reader.output_buffer_size().unwrap()];
        let info = reader.next_frame(&mut buf).unwrap();
        assert_eq!(info.color_type, png::ColorType::Rgb);
        assert_eq!(info.bit_depth, png::BitDepth::Eight);
        assert!(reader.info().srgb.is_some(), "no sRGB chunk");
        buf.truncate(info.buffer_size());
        (info.width, info.height, buf)
    }

    /// The expected 8-bit value, computed from the documented formulas
    /// independently of the implementation.
    fn expected(linear_rgb: [f64; 3], stops: f64) -> [u8; 3] {
        let s = 2_f64.powf(stops);
        let (r, g, b) = (linear_rgb[0] * s, linear_rgb[1] * s, linear_rgb[2] * s);
        let y = 0.2126 * r + 0.7152 * g + 0.0722 * b;
        [r, g, b].map(|c| {
            let t = (c / (1.0 + y)).clamp(0.0, 1.0);
            let v = if t <= 0.0031308 {
                12.92 * t
            } else {
                1.055 * t.powf(1.0 / 2.4) - 0.055
            };
            (v * 255.0).round() as u8
        })
    }

    #[test]
    fn known_values_and_row_order() {
        let dir = temp_dir("known");
        let path = dir.join("preview.png");
        // 3x2: top row black, grey 1, colour; bottom row NaN, grey 0.5, inf.
        let rgb = [
            [0.0, 0.0, 0.0],
            [1.0, 1.0, 1.0],
            [0.8, 0.3, 0.05],
            [f32::NAN, 0.0, 0.0],
            [0.5, 0.5, 0.5],
            [0.0, f32::INFINITY, 0.0],
        ];
        let bad = write_png_preview(&path, 3, 2, &rgb, 0.0).unwrap();
        assert_eq!(bad, 2);
        let entries: Vec<_> = std::fs::read_dir(&dir).unwrap().collect();
        assert_eq!(entries.len(), 1, "temp file left behind");

        let (w, h, data) = decode(&path);
        assert_eq!((w, h), (3, 2));
        let px = |x: usize, y: usize| -> [u8; 3] {
            let i = 3 * (y * 3 + x);
            [data[i], data[i + 1], data[i + 2]]
        };
        assert_eq!(px(0, 0), [0, 0, 0]);
        // Grey 1.0 -> Y = 1 -> 0.5 linear -> sRGB 0.7354 -> 188.
        assert_eq!(px(1, 0), expected([1.0; 3], 0.0));
        assert_eq!(px(1, 0), [188; 3]);
        assert_eq!(px(2, 0), expected([0.8, 0.3, 0.05], 0.0));
        assert_eq!(px(0, 1), [255, 0, 255]);
        assert_eq!(px(1, 1), expected([0.5; 3], 0.0));
        assert_eq!(px(2, 1), [255, 0, 255]);

        // One stop up: grey 0.5 looks like grey 1.0 did; negatives are black;
        // very bright grey is (nearly) white.
        let rgb = [[0.5, 0.5, 0.5], [-1.0, -2.0, -3.0], [1e30, 1e30, 1e30]];
        assert_eq!(write_png_preview(&path, 1, 3, &rgb, 1.0).unwrap(), 0);
        let (_, _, data) = decode(&path);
        assert_eq!(data, [188, 188, 188, 0, 0, 0, 255, 255, 255]);

        // A small value in the linear segment of the sRGB curve.
        let small = 0.002_f32;
        write_png_preview(&path, 1, 1, &[[small, 0.0, 0.0]], 0.0).unwrap();
        let (_, _, data) = decode(&path);
        assert_eq!(data, expected([f64::from(small), 0.0, 0.0], 0.0));
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn invalid_input_and_io_errors() {
        let dir = temp_dir("invalid");
        let path = dir.join("bad.png");
        for (w, h, n, stops) in [(0, 1, 0, 0.0), (2, 2, 3, 0.0), (1, 1, 1, f32::NAN), (1, 1, 1, f32::INFINITY)] {
            let err = write_png_preview(&path, w, h, &vec![[0.0; 3]; n], stops).unwrap_err();
            assert!(matches!(err, ImageIoError::Invalid(_)), "{err:?}");
            assert!(err.to_string().contains("bad.png"), "{err}");
        }
        let missing = dir.join("nope").join("out.png");
        let err = write_png_preview(&missing, 1, 1, &[[0.0; 3]], 0.0).unwrap_err();
        assert!(matches!(err, ImageIoError::Io { .. }), "{err:?}");
        assert!(err.to_string().contains(&missing.display().to_string()), "{err}");
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn auto_exposure_targets_99th_percentile() {
        assert_eq!(auto_exposure(&[]), 0.0);
        assert_eq!(auto_exposure(&[[0.0; 3]; 10]), 0.0);
        assert_eq!(auto_exposure(&[[f32::NAN; 3]; 3]), 0.0);
        assert_eq!(auto_exposure(&[[-1.0; 3]; 3]), 0.0);

        // Uniform grey 2: 2^s * 2 / (1 + 2^s * 2) = 0.9 -> 2^s = 4.5.
        let s = auto_exposure(&[[2.0; 3]; 7]);
        assert!((s - 4.5_f32.log2()).abs() < 1e-6, "{s}");
        let y = 2.0 * 2_f64.powf(f64::from(s));
        assert!((y / (1.0 + y) - 0.9).abs() < 1e-6);

        // 1000 pixels of grey 1 and 5 hot pixels: the hot pixels (< 1 %) are
        // ignored, as are NaNs.
        let mut rgb = vec![[1.0_f32; 3]; 1000];
        rgb.extend([[1e6; 3]; 5]);
        rgb.extend([[f32::NAN; 3]; 50]);
        let s = auto_exposure(&rgb);
        assert!((s - 9_f32.log2()).abs() < 1e-6, "{s}");

        // 100 distinct luminances: nearest rank 99 is the 99th smallest.
        let rgb: Vec<[f32; 3]> = (1..=100).map(|i| [i as f32; 3]).collect();
        let s = auto_exposure(&rgb);
        assert!((s - (9.0_f32 / 99.0).log2()).abs() < 1e-6, "{s}");
    }

    proptest! {
        #[test]
        fn auto_exposure_is_finite(values in proptest::collection::vec(any::<f32>(), 0..60)) {
            let rgb: Vec<[f32; 3]> = values.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
            let stops = auto_exposure(&rgb);
            prop_assert!(stops.is_finite());
        }

        #[test]
        fn tone_curve_keeps_hue_and_is_monotonic(
            r in 0.0_f32..1e6, g in 0.0_f32..1e6, b in 0.0_f32..1e6, k in 1.0_f32..4.0
        ) {
            // Brighter input never gives a darker output.
            let dim = display_pixel([r, g, b], 1.0);
            let bright = display_pixel([r * k, g * k, b * k], 1.0);
            for c in 0..3 {
                prop_assert!(bright[c] >= dim[c]);
            }
            // Channel order is kept (same hue) unless clamping kicks in.
            let exposed = [r, g, b].map(f64::from);
            let f = 1.0 / (1.0 + luminance(exposed));
            if exposed.iter().all(|c| c * f < 1.0) {
                for (i, j) in [(0, 1), (1, 2), (0, 2)] {
                    if exposed[i] > exposed[j] {
                        prop_assert!(dim[i] >= dim[j]);
                    }
                }
            }
        }
    }
}
