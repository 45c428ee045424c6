//! Image output: multi-layer OpenEXR files and tone-mapped PNG previews.
//!
//! * [`exr_image`]: lossless 32-bit float OpenEXR files with named layers
//!   (`inscatter.R`, `transmittance.G`, `depth.Z`, ...), readable by Blender,
//!   Nuke and every other OpenEXR viewer, and read back bit-exactly.
//! * [`preview`]: 8-bit sRGB PNG previews of a linear RGB image, with exposure
//!   control and a hue-preserving tone curve.
//!
//! All images are row-major with row 0 the **top** row, as image viewers show
//! them. Every file is written atomically: the data goes to a temporary file
//! in the target's directory, which is then renamed over the target, so a
//! failure never leaves a half-written file behind. Bad input is reported as an
//! [`ImageIoError`], never a panic.

use std::fs::{self, File, OpenOptions};
use std::io::ErrorKind;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

pub mod exr_image;
pub mod preview;

pub use exr_image::{ChannelSamples, ImageLayer, LayerRef, read_layers_exr, write_layer_refs_exr, write_layers_exr, write_rgb_exr};
pub use preview::{auto_exposure, write_png_preview};

/// Errors of image reading and writing.
#[derive(Debug, thiserror::Error)]
pub enum ImageIoError {
    /// The operating system failed to create, write, rename or read a file.
    #[error("I/O error on {}: {source}", path.display())]
    Io {
        /// The image file being written or read (the target, not the
        /// temporary file used for the atomic write).
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The OpenEXR encoder or decoder reported an error (for example a corrupt
    /// or unsupported file).
    #[error("OpenEXR error in {}: {message}", path.display())]
    Exr {
        /// The image file being written or read.
        path: PathBuf,
        /// The message of the `exr` crate.
        message: String,
    },
    /// The PNG encoder reported an error.
    #[error("PNG error in {}: {message}", path.display())]
    Png {
        /// The image file being written.
        path: PathBuf,
        /// The message of the `png` crate.
        message: String,
    },
    /// The caller's data is unusable: a zero or too large size, a channel whose
    /// length is not `width * height`, an empty, duplicate or unencodable
    /// name, a non-finite exposure, a path without a file name...
    /// The message names the file.
    #[error("invalid image data: {0}")]
    Invalid(String),
}

impl ImageIoError {
    /// Shorthand for an [`ImageIoError::Io`] about `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }
}

/// Checks an image size: both sides at least 1 and at most `i32::MAX` (the
/// limit of both OpenEXR and PNG), and `width * height` representable.
/// Returns the pixel count.
pub(crate) fn checked_pixel_count(path: &Path, width: usize, height: usize) -> Result<usize, ImageIoError> {
    const MAX_SIDE: usize = i32::MAX as usize;
    if width == 0 || height == 0 {
        return Err(ImageIoError::Invalid(format!(
            "{}: image size {width}x{height} is empty (both sides must be at least 1)",
            path.display()
        )));
    }
    if width > MAX_SIDE || height > MAX_SIDE {
        return Err(ImageIoError::Invalid(format!(
            "{}: image size {width}x{height} exceeds the format limit of {MAX_SIDE} per side",
            path.display()
        )));
    }
    width
        .checked_mul(height)
        .ok_or_else(|| ImageIoError::Invalid(format!("{}: image size {width}x{height} overflows the pixel count", path.display())))
}

/// Distinguishes the temporary files of concurrent writes within one process.
static TEMP_COUNTER: AtomicU64 = AtomicU64::new(0);

/// Writes `path` atomically.
///
/// `write` fills a fresh temporary file (opened for reading and writing) in
/// the directory of `path`. If it succeeds, the file is flushed to disk and
/// renamed over `path`; if anything fails, the temporary file is removed and
/// `path` is left untouched.
pub fn write_atomically<F>(path: &Path, write: F) -> Result<(), ImageIoError>
where
    F: FnOnce(&mut File) -> Result<(), ImageIoError>,
{
    let file_name = path
        .file_name()
        .ok_or_else(|| ImageIoError::Invalid(format!("{}: path has no file name", path.display())))?;
    let dir = match path.parent() {
        Some(parent) if !parent.as_os_str().is_empty() => parent,
        _ => Path::new("."),
    };
    // Keep the temporary name short enough for any file system even when the
    // target's name is near the length limit.
    let stem: String = file_name.to_string_lossy().chars().take(48).collect();

    let (mut file, temp_path) = {
        let mut attempt = 0;
        loop {
            let n = TEMP_COUNTER.fetch_add(1, Ordering::Relaxed);
            let temp_path = dir.join(format!(".{stem}.{}-{n}.tmp", std::process::id()));
            match OpenOptions::new().read(true).write(true).create_new(true).open(&temp_path) {
                Ok(file) => break (file, temp_path),
                Err(e) if e.kind() == ErrorKind::AlreadyExists && attempt < 100 => attempt += 1,
                Err(e) => return Err(ImageIoError::io(path, e)),
            }
        }
    };

    let result = write(&mut file).and_then(|()| file.sync_all().map_err(|e| ImageIoError::io(path, e)));
    drop(file);
    let result = result.and_then(|()| fs::rename(&temp_path, path).map_err(|e| ImageIoError::io(path, e)));
    if result.is_err() {
        // Best effort: the original error is what matters to the caller.
        let _ = fs::remove_file(&temp_path);
    }
    result
}
