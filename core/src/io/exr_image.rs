//! Multi-layer OpenEXR output (and input) with 32-bit float samples.
//!
//! Files written here have exactly this layout, which Blender, Nuke,
//! `exrheader` and every OpenEXR viewer understand:
//!
//! * one part (a single-part, non-deep, scan-line file);
//! * one channel per `(layer, channel)` pair, named `<layer>.<channel>`
//!   (`inscatter.R`, `transmittance.G`, `depth.Z`), or just `<channel>` for a
//!   layer with an empty name; names are stored as UTF-8 bytes, like OpenEXR
//!   itself does;
//! * 32-bit float samples, stored bit-exactly (NaN payloads included);
//! * `ZIP` compression in blocks of 16 scan lines (OpenEXR's
//!   `ZIP_COMPRESSION`, the exr crate's `Compression::ZIP16`; lossless);
//! * increasing-Y line order, data window = display window =
//!   `(0,0)-(width-1,height-1)`, pixel aspect 1;
//! * pixel data row-major, index `y * width + x`, row `y = 0` the **top** row
//!   of the image (OpenEXR's y axis points down).
//!
//! The split of a channel name into layer and channel happens at the **last**
//! dot, so layer names may contain dots themselves: `inscatter.key light.R` is
//! channel `R` of layer `inscatter.key light`.
//!
//! **Encoder.** Files are read with the exr crate but written by
//! [`encode_exr`] here: the same layout, with the 16-line blocks compressed in
//! parallel and deflated at zlib level 1 rather than the exr crate's fixed
//! level 4. On Tyndall's layers (smooth transmittance and depth, mostly-zero
//! per-light in-scatter) that is ≈ 3× less compression work for ≈ 5 % larger
//! files (1920×1080, 22 channels: 25.1 MB instead of 23.8 MB). The block
//! encoding is OpenEXR's (`ImfZip.cpp`): the bytes of the block's scan lines
//! (per line, per channel in name order, little-endian samples) are split
//! into the even- and the odd-indexed half, delta-coded
//! (`d = b − b_prev + 128 mod 256`) and zlib-compressed; a block that would
//! not shrink is stored raw, as OpenEXR does. The channels are read in place
//! ([`ChannelSamples`]): a render's RGB buffers are not split into planes
//! first ([`write_layer_refs_exr`]).

use std::collections::HashSet;
use std::io::{BufWriter, Write};
use std::path::Path;

use exr::prelude::{FlatSamples, ReadChannels, ReadLayers};
use rayon::prelude::*;

use super::{ImageIoError, checked_pixel_count, write_atomically};

/// OpenEXR channel names are limited to 255 bytes (plus the terminating NUL).
const MAX_CHANNEL_NAME_BYTES: usize = 255;

/// Names of 32 bytes or more need the "long names" flag (bit 10 of the
/// version field) in the file header, or OpenEXR 3 refuses the file.
const LONG_NAME_BYTES: usize = 32;

/// One named layer of an image: a group of channels sharing a name prefix.
///
/// Every channel holds `width * height` samples, row-major, row 0 the top row.
#[derive(Debug, Clone, PartialEq)]
pub struct ImageLayer {
    /// Layer name, e.g. `"inscatter"` or `"inscatter.key light"`; the empty
    /// string means plain channels without a prefix (`"R"`, `"G"`, `"B"`).
    pub name: String,
    /// `(channel name, samples)` pairs, e.g. `[("R", ..), ("G", ..),
    /// ("B", ..)]` or `[("Z", ..)]`. Channel names must be non-empty and must
    /// not contain a dot.
    pub channels: Vec<(String, Vec<f32>)>,
}

impl ImageLayer {
    /// The samples of the channel called `channel`, if the layer has one.
    pub fn channel(&self, channel: &str) -> Option<&[f32]> {
        self.channels
            .iter()
            .find(|(name, _)| name == channel)
            .map(|(_, samples)| samples.as_slice())
    }
}

/// The samples of one channel, read in place by [`write_layer_refs_exr`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ChannelSamples<'a> {
    /// `width * height` samples, row-major.
    Plane(&'a [f32]),
    /// Component `.1` (0, 1 or 2) of `width * height` RGB pixels, row-major:
    /// the render's own buffers, so that no channel is copied out of them
    /// first (at 1920×1080 with 22 channels, splitting them into new planes
    /// took 0.24–0.31 s, most of it the first touch of 182 MB of fresh pages).
    Rgb(&'a [[f32; 3]], usize),
}

impl ChannelSamples<'_> {
    fn len(&self) -> usize {
        match self {
            ChannelSamples::Plane(v) => v.len(),
            ChannelSamples::Rgb(v, _) => v.len(),
        }
    }

    /// The samples of row `y` of an image `width` wide.
    fn row(&self, y: usize, width: usize) -> impl Iterator<Item = f32> + '_ {
        let (plane, rgb) = match *self {
            ChannelSamples::Plane(v) => (Some(&v[y * width..(y + 1) * width]), None),
            ChannelSamples::Rgb(v, c) => (None, Some((&v[y * width..(y + 1) * width], c))),
        };
        let plane = plane.into_iter().flatten().copied();
        let rgb = rgb.into_iter().flat_map(|(px, c)| px.iter().map(move |p| p[c]));
        plane.chain(rgb)
    }
}

/// A named layer whose channels are borrowed (see [`ImageLayer`] for the
/// names' rules).
#[derive(Debug, Clone, PartialEq)]
pub struct LayerRef<'a> {
    /// Layer name (`""`: plain channels).
    pub name: &'a str,
    /// `(channel name, samples)` pairs.
    pub channels: Vec<(&'a str, ChannelSamples<'a>)>,
}

/// Writes a single-part OpenEXR file holding all `layers`, atomically.
///
/// See the [module documentation](self) for the exact file layout. Fails with
/// [`ImageIoError::Invalid`] (writing nothing) if the size is zero, a channel
/// does not hold `width * height` samples, there is no channel at all, a layer
/// has no channels, two layers share a name, a channel name is empty, contains
/// a dot or repeats within its layer, or a full name `<layer>.<channel>`
/// contains a NUL character or is longer than 255 bytes of UTF-8.
pub fn write_layers_exr(path: &Path, width: usize, height: usize, layers: &[ImageLayer]) -> Result<(), ImageIoError> {
    let refs: Vec<LayerRef<'_>> = layers
        .iter()
        .map(|l| LayerRef {
            name: &l.name,
            channels: l.channels.iter().map(|(n, v)| (n.as_str(), ChannelSamples::Plane(v))).collect(),
        })
        .collect();
    write_layer_refs_exr(path, width, height, &refs)
}

/// [`write_layers_exr`] for borrowed layers: the same file, the same checks
/// (and an RGB component other than 0, 1, 2 is invalid).
pub fn write_layer_refs_exr(path: &Path, width: usize, height: usize, layers: &[LayerRef<'_>]) -> Result<(), ImageIoError> {
    let pixels = checked_pixel_count(path, width, height)?;
    let invalid = |message: String| ImageIoError::Invalid(format!("{}: {message}", path.display()));

    if layers.is_empty() {
        return Err(invalid("an EXR image needs at least one layer".into()));
    }
    let mut layer_names = HashSet::new();
    let mut full_names = HashSet::new();
    let mut list: Vec<(String, ChannelSamples<'_>)> = Vec::new();
    let mut long_names = false;
    for layer in layers {
        if !layer_names.insert(layer.name) {
            return Err(invalid(format!("duplicate layer name {:?}", layer.name)));
        }
        if layer.channels.is_empty() {
            return Err(invalid(format!("layer {:?} has no channels", layer.name)));
        }
        for (channel, samples) in &layer.channels {
            if channel.is_empty() {
                return Err(invalid(format!("layer {:?} has a channel with an empty name", layer.name)));
            }
            if channel.contains('.') {
                return Err(invalid(format!(
                    "channel name {channel:?} of layer {:?} contains a dot \
                     (dots separate layers from channels)",
                    layer.name
                )));
            }
            let full = full_channel_name(layer.name, channel);
            if full.contains('\0') {
                return Err(invalid(format!("channel name {full:?} contains a NUL")));
            }
            if full.len() > MAX_CHANNEL_NAME_BYTES {
                return Err(invalid(format!(
                    "channel name {full:?} is {} bytes long, OpenEXR allows at most \
                     {MAX_CHANNEL_NAME_BYTES}",
                    full.len()
                )));
            }
            if let ChannelSamples::Rgb(_, c) = samples
                && *c > 2
            {
                return Err(invalid(format!("channel {full:?} reads RGB component {c}, there are 3")));
            }
            if samples.len() != pixels {
                return Err(invalid(format!(
                    "channel {full:?} has {} samples, a {width}x{height} image needs {pixels}",
                    samples.len()
                )));
            }
            long_names |= full.len() >= LONG_NAME_BYTES;
            if !full_names.insert(full.clone()) {
                return Err(invalid(format!("duplicate channel {:?} in layer {:?}", channel, layer.name)));
            }
            list.push((full, *samples));
        }
    }
    write_atomically(path, |file| {
        encode_exr(file, width, height, list, long_names).map_err(|e| ImageIoError::io(path, e))
    })
}

/// Reads an OpenEXR file written by [`write_layers_exr`] (or any other
/// single-part, non-deep OpenEXR file) and returns `(width, height, layers)`.
///
/// Channel names are split into layer and channel at the last dot (see the
/// [module documentation](self)). Layers come sorted by name (byte order, the
/// plain layer `""` first); within a layer the channels come in the order
/// `R`, `G`, `B`, `A`, then all others sorted by name. Samples are row-major,
/// row 0 the top row of the data window. Half-float samples are widened to
/// `f32` exactly, unsigned-integer samples converted with `as f32`. Only the
/// largest resolution level of a mip-mapped file is read. Multi-part files are
/// refused with [`ImageIoError::Exr`].
pub fn read_layers_exr(path: &Path) -> Result<(usize, usize, Vec<ImageLayer>), ImageIoError> {
    let image = exr::prelude::read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .all_layers()
        .all_attributes()
        .from_file(path)
        .map_err(|e| exr_error(path, e))?;

    let part = match image.layer_data.as_slice() {
        [part] => part,
        parts => {
            return Err(ImageIoError::Exr {
                path: path.to_path_buf(),
                message: format!("expected a single-part file, found {} parts", parts.len()),
            });
        }
    };
    let (width, height) = (part.size.x(), part.size.y());

    let mut layers: Vec<ImageLayer> = Vec::new();
    for channel in &part.channel_data.list {
        let full = String::from_utf8_lossy(channel.name.bytes());
        let (layer_name, channel_name) = split_channel_name(&full);
        let samples: Vec<f32> = match &channel.sample_data {
            FlatSamples::F32(values) => values.clone(),
            FlatSamples::F16(values) => values.iter().map(|v| v.to_f32()).collect(),
            #[allow(clippy::cast_precision_loss)]
            FlatSamples::U32(values) => values.iter().map(|&v| v as f32).collect(),
        };
        let entry = (channel_name.to_owned(), samples);
        match layers.iter_mut().find(|layer| layer.name == layer_name) {
            Some(layer) => layer.channels.push(entry),
            None => layers.push(ImageLayer {
                name: layer_name.to_owned(),
                channels: vec![entry],
            }),
        }
    }
    layers.sort_by(|a, b| a.name.cmp(&b.name));
    for layer in &mut layers {
        layer
            .channels
            .sort_by(|(a, _), (b, _)| channel_rank(a).cmp(&channel_rank(b)).then_with(|| a.cmp(b)));
    }
    Ok((width, height, layers))
}

/// Writes a plain RGB OpenEXR file (channels `R`, `G`, `B`, no layer prefix),
/// atomically, e.g. for world textures.
///
/// `rgb` holds `width * height` pixels, row-major, row 0 the top row. The file
/// layout is otherwise the one described in the
/// [module documentation](self). Fails with [`ImageIoError::Invalid`] if the
/// size is zero or does not match `rgb.len()`.
pub fn write_rgb_exr(path: &Path, width: usize, height: usize, rgb: &[[f32; 3]]) -> Result<(), ImageIoError> {
    let pixels = checked_pixel_count(path, width, height)?;
    if rgb.len() != pixels {
        return Err(ImageIoError::Invalid(format!(
            "{}: {} RGB pixels given, a {width}x{height} image needs {pixels}",
            path.display(),
            rgb.len()
        )));
    }
    let list = ["R", "G", "B"]
        .iter()
        .enumerate()
        .map(|(c, n)| ((*n).to_owned(), ChannelSamples::Rgb(rgb, c)))
        .collect();
    write_atomically(path, |file| {
        encode_exr(file, width, height, list, false).map_err(|e| ImageIoError::io(path, e))
    })
}

/// Scan lines per block of OpenEXR's `ZIP_COMPRESSION`.
const ZIP_BLOCK_LINES: usize = 16;

/// zlib level of the blocks (1: the fastest; see the module documentation).
const DEFLATE_LEVEL: u8 = 1;

/// Writes a single-part scan-line OpenEXR file: `channels` as `(full name,
/// samples)` (read in place) with 32-bit float samples, ZIP compression in 16-line blocks,
/// increasing Y, data and display window `(0,0)–(width−1,height−1)`.
/// Names must be valid (checked by the callers); they are sorted here, as
/// OpenEXR requires.
fn encode_exr(
    file: &mut std::fs::File,
    width: usize,
    height: usize,
    mut channels: Vec<(String, ChannelSamples<'_>)>,
    long_names: bool,
) -> std::io::Result<()> {
    channels.sort_by(|a, b| a.0.as_bytes().cmp(b.0.as_bytes()));
    let attribute = |out: &mut Vec<u8>, name: &str, kind: &str, value: &[u8]| {
        for text in [name, kind] {
            out.extend_from_slice(text.as_bytes());
            out.push(0);
        }
        out.extend_from_slice(&(value.len() as i32).to_le_bytes());
        out.extend_from_slice(value);
    };
    let mut header = Vec::new();
    header.extend_from_slice(&20000630_i32.to_le_bytes());
    // Version 2, single-part scan lines; bit 10 for names of 32 bytes or more.
    header.extend_from_slice(&(2_u32 | if long_names { 1 << 10 } else { 0 }).to_le_bytes());
    let mut chlist = Vec::new();
    for (name, _) in &channels {
        chlist.extend_from_slice(name.as_bytes());
        chlist.push(0);
        chlist.extend_from_slice(&2_i32.to_le_bytes()); // FLOAT
        chlist.extend_from_slice(&[0, 0, 0, 0]); // pLinear, reserved
        chlist.extend_from_slice(&1_i32.to_le_bytes()); // x sampling
        chlist.extend_from_slice(&1_i32.to_le_bytes()); // y sampling
    }
    chlist.push(0);
    let window: Vec<u8> = [0, 0, width as i32 - 1, height as i32 - 1]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    attribute(&mut header, "channels", "chlist", &chlist);
    attribute(&mut header, "compression", "compression", &[3]); // ZIP_COMPRESSION
    attribute(&mut header, "dataWindow", "box2i", &window);
    attribute(&mut header, "displayWindow", "box2i", &window);
    attribute(&mut header, "lineOrder", "lineOrder", &[0]); // INCREASING_Y
    attribute(&mut header, "pixelAspectRatio", "float", &1.0_f32.to_le_bytes());
    attribute(&mut header, "screenWindowCenter", "v2f", &[0; 8]);
    attribute(&mut header, "screenWindowWidth", "float", &1.0_f32.to_le_bytes());
    header.push(0);

    // Per worker, reused: the block's bytes split into halves, and their deltas.
    let blocks: Vec<Vec<u8>> = (0..height.div_ceil(ZIP_BLOCK_LINES))
        .into_par_iter()
        .map_init(
            || (Vec::new(), Vec::new()),
            |(split, delta): &mut (Vec<u8>, Vec<u8>), b| {
                let lines = b * ZIP_BLOCK_LINES..((b + 1) * ZIP_BLOCK_LINES).min(height);
                let rows = || lines.clone().flat_map(|y| channels.iter().map(move |(_, v)| v.row(y, width)));
                let n = lines.len() * channels.len() * width * 4;
                // Byte k of the raw block goes to position k/2 of the even
                // (k even) or the odd half: sample i's little-endian bytes
                // b0 b1 b2 b3 give even[2i], even[2i+1] = b0, b2 and
                // odd[2i], odd[2i+1] = b1, b3.
                split.resize(n, 0);
                let (even, odd) = split.split_at_mut(n / 2);
                let (mut e, mut o) = (even.chunks_exact_mut(2), odd.chunks_exact_mut(2));
                for row in rows() {
                    for (v, (ev, od)) in row.zip(e.by_ref().zip(o.by_ref())) {
                        let [b0, b1, b2, b3] = v.to_le_bytes();
                        ev.copy_from_slice(&[b0, b2]);
                        od.copy_from_slice(&[b1, b3]);
                    }
                }
                delta.resize(n, 0);
                delta[0] = split[0];
                for (d, pair) in delta[1..].iter_mut().zip(split.windows(2)) {
                    *d = pair[1].wrapping_sub(pair[0]).wrapping_add(128);
                }
                let packed = miniz_oxide::deflate::compress_to_vec_zlib(delta, DEFLATE_LEVEL);
                if packed.len() < n {
                    packed
                } else {
                    rows().flat_map(|row| row.flat_map(|v| v.to_le_bytes())).collect()
                }
            },
        )
        .collect();

    let mut out = BufWriter::with_capacity(1 << 20, file);
    out.write_all(&header)?;
    let mut offset = (header.len() + 8 * blocks.len()) as u64;
    for block in &blocks {
        out.write_all(&offset.to_le_bytes())?;
        offset += 8 + block.len() as u64;
    }
    for (b, block) in blocks.iter().enumerate() {
        let size = i32::try_from(block.len()).map_err(|_| std::io::Error::other("an OpenEXR block of 16 scan lines exceeds 2 GiB"))?;
        out.write_all(&((b * ZIP_BLOCK_LINES) as i32).to_le_bytes())?;
        out.write_all(&size.to_le_bytes())?;
        out.write_all(block)?;
    }
    out.flush()
}

/// `<layer>.<channel>`, or `<channel>` for the plain layer `""`.
fn full_channel_name(layer: &str, channel: &str) -> String {
    if layer.is_empty() {
        channel.to_owned()
    } else {
        format!("{layer}.{channel}")
    }
}

/// Splits a full channel name at its last dot into `(layer, channel)`; a name
/// without a dot, or ending in one, is a plain channel of layer `""`.
fn split_channel_name(full: &str) -> (&str, &str) {
    match full.rsplit_once('.') {
        Some((layer, channel)) if !channel.is_empty() => (layer, channel),
        _ => ("", full),
    }
}

/// Sort key putting the colour channels first, in their usual order.
fn channel_rank(name: &str) -> u8 {
    match name {
        "R" => 0,
        "G" => 1,
        "B" => 2,
        "A" => 3,
        _ => 4,
    }
}

/// Converts an error of the exr crate, keeping I/O errors as such.
fn exr_error(path: &Path, error: exr::error::Error) -> ImageIoError {
    match error {
        exr::error::Error::Io(source) => ImageIoError::io(path, source),
        other => ImageIoError::Exr {
            path: path.to_path_buf(),
            message: other.to_string(),
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use exr::prelude::{Compression, LineOrder, Vec2};
    use std::path::PathBuf;

    /// A fresh, empty directory for one test.
    fn temp_dir(test: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("tyndall-exr-test-{}-{test}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    /// Names of the files in `dir`.
    fn dir_entries(dir: &Path) -> Vec<String> {
        let mut names: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|entry| entry.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        names.sort();
        names
    }

    /// A distinct value for every (layer, channel, x, y), exactly
    /// representable, plus a few special bit patterns.
    fn value(layer: usize, channel: usize, x: usize, y: usize) -> f32 {
        match (layer, channel, x, y) {
            (0, 0, 1, 1) => f32::NAN,
            (0, 1, 2, 1) => f32::from_bits(0x7fc0_1234), // NaN with payload
            (0, 2, 3, 1) => -0.0,
            (1, 0, 4, 1) => f32::INFINITY,
            (1, 1, 5, 1) => f32::from_bits(1), // smallest subnormal
            _ => (1000 * layer + 100 * channel + 10 * y + x) as f32 + 0.25,
        }
    }

    fn test_layers(width: usize, height: usize) -> Vec<ImageLayer> {
        let layer_spec: [(&str, &[&str]); 3] = [
            ("inscatter", &["R", "G", "B"]),
            ("transmittance", &["R", "G", "B"]),
            ("depth", &["Z"]),
        ];
        layer_spec
            .iter()
            .enumerate()
            .map(|(l, (name, channels))| ImageLayer {
                name: (*name).to_owned(),
                channels: channels
                    .iter()
                    .enumerate()
                    .map(|(c, channel)| {
                        let samples = (0..height).flat_map(|y| (0..width).map(move |x| value(l, c, x, y))).collect();
                        ((*channel).to_owned(), samples)
                    })
                    .collect(),
            })
            .collect()
    }

    #[test]
    fn three_layers_round_trip_bit_exact() {
        let dir = temp_dir("round-trip");
        let path = dir.join("beauty.exr");
        let (width, height) = (7, 5);
        let layers = test_layers(width, height);
        write_layers_exr(&path, width, height, &layers).unwrap();
        assert_eq!(dir_entries(&dir), ["beauty.exr"], "temp file left behind");

        let (w, h, read) = read_layers_exr(&path).unwrap();
        assert_eq!((w, h), (width, height));
        let names: Vec<&str> = read.iter().map(|layer| layer.name.as_str()).collect();
        assert_eq!(names, ["depth", "inscatter", "transmittance"]);

        for (l, original) in layers.iter().enumerate() {
            let back = read.iter().find(|layer| layer.name == original.name).unwrap();
            let channel_names: Vec<&str> = back.channels.iter().map(|(name, _)| name.as_str()).collect();
            let expected: Vec<&str> = original.channels.iter().map(|(name, _)| name.as_str()).collect();
            assert_eq!(channel_names, expected, "layer {}", original.name);
            for (c, (channel, _)) in original.channels.iter().enumerate() {
                let samples = back.channel(channel).unwrap();
                assert_eq!(samples.len(), width * height);
                for y in 0..height {
                    for x in 0..width {
                        assert_eq!(
                            samples[y * width + x].to_bits(),
                            value(l, c, x, y).to_bits(),
                            "{}.{channel} at ({x},{y})",
                            original.name
                        );
                    }
                }
            }
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    /// Row order and channel names as the exr crate itself sees them: the
    /// first sample of the file's first (top) scan line is pixel (0,0).
    #[test]
    fn file_layout_as_seen_by_exr_crate() {
        let dir = temp_dir("layout");
        let path = dir.join("layout.exr");
        let (width, height) = (7, 5);
        write_layers_exr(&path, width, height, &test_layers(width, height)).unwrap();

        let meta = exr::meta::MetaData::read_from_file(&path, false).unwrap();
        assert_eq!(meta.headers.len(), 1);
        let header = &meta.headers[0];
        assert_eq!(header.compression, Compression::ZIP16);
        assert_eq!(header.line_order, LineOrder::Increasing);
        assert_eq!(header.blocks, exr::meta::BlockDescription::ScanLines);
        assert_eq!(header.layer_size, Vec2(width, height));
        assert_eq!(header.own_attributes.layer_position, Vec2(0, 0));
        assert_eq!(
            header.shared_attributes.display_window,
            exr::prelude::IntegerBounds::new((0, 0), (width, height))
        );
        let names: Vec<String> = header.channels.list.iter().map(|channel| channel.name.to_string()).collect();
        assert_eq!(
            names,
            [
                "depth.Z",
                "inscatter.B",
                "inscatter.G",
                "inscatter.R",
                "transmittance.B",
                "transmittance.G",
                "transmittance.R"
            ]
        );
        assert!(
            header
                .channels
                .list
                .iter()
                .all(|channel| channel.sample_type == exr::prelude::SampleType::F32)
        );

        // Read the depth channel line by line, in file order.
        let image = exr::prelude::read()
            .no_deep_data()
            .largest_resolution_level()
            .all_channels()
            .first_valid_layer()
            .all_attributes()
            .from_file(&path)
            .unwrap();
        let depth = &image.layer_data.channel_data.list[0];
        assert_eq!(depth.name.to_string(), "depth.Z");
        let FlatSamples::F32(z) = &depth.sample_data else {
            panic!("depth is not f32")
        };
        // value(2, 0, x, y) = 2000 + 10 y + x + 0.25: the first row is y = 0.
        let first_row: Vec<f32> = z[..width].to_vec();
        let expected: Vec<f32> = (0..width).map(|x| 2000.25 + x as f32).collect();
        assert_eq!(first_row, expected);
        assert_eq!(z[width], 2010.25, "second row starts with (0,1)");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn rgb_exr_has_plain_channel_names() {
        let dir = temp_dir("rgb");
        let path = dir.join("world.exr");
        let (width, height) = (3, 2);
        let rgb: Vec<[f32; 3]> = (0..width * height)
            .map(|i| [i as f32, i as f32 + 0.5, -(i as f32) - 0.125])
            .collect();
        write_rgb_exr(&path, width, height, &rgb).unwrap();
        assert_eq!(dir_entries(&dir), ["world.exr"]);

        let (w, h, layers) = read_layers_exr(&path).unwrap();
        assert_eq!((w, h), (width, height));
        assert_eq!(layers.len(), 1);
        assert_eq!(layers[0].name, "");
        let names: Vec<&str> = layers[0].channels.iter().map(|(n, _)| n.as_str()).collect();
        assert_eq!(names, ["R", "G", "B"]);
        for (c, (_, samples)) in layers[0].channels.iter().enumerate() {
            let expected: Vec<f32> = rgb.iter().map(|pixel| pixel[c]).collect();
            assert_eq!(samples, &expected);
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn borrowed_rgb_channels_write_the_same_file_as_planes() {
        // Two 16-line blocks and a short third, with NaN payloads and −0.
        let dir = temp_dir("borrowed");
        let (width, height) = (5, 37);
        let px: Vec<[f32; 3]> = (0..width * height)
            .map(|i| [i as f32 * 0.37, f32::from_bits(0x7fc0_1234 + i as u32 % 3), -0.0 - (i % 7) as f32])
            .collect();
        let depth: Vec<f32> = (0..width * height).map(|i| 1.0 / (1.0 + i as f32)).collect();
        let refs = [
            LayerRef {
                name: "inscatter.key light",
                channels: ["R", "G", "B"]
                    .into_iter()
                    .enumerate()
                    .map(|(c, n)| (n, ChannelSamples::Rgb(&px, c)))
                    .collect(),
            },
            LayerRef {
                name: "depth",
                channels: vec![("Z", ChannelSamples::Plane(&depth))],
            },
        ];
        let owned = [
            ImageLayer {
                name: "inscatter.key light".into(),
                channels: ["R", "G", "B"]
                    .into_iter()
                    .enumerate()
                    .map(|(c, n)| (n.to_owned(), px.iter().map(|p| p[c]).collect()))
                    .collect(),
            },
            ImageLayer {
                name: "depth".into(),
                channels: vec![("Z".into(), depth.clone())],
            },
        ];
        let (a, b) = (dir.join("refs.exr"), dir.join("owned.exr"));
        write_layer_refs_exr(&a, width, height, &refs).unwrap();
        write_layers_exr(&b, width, height, &owned).unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
        let (_, _, back) = read_layers_exr(&a).unwrap();
        let key = back.iter().find(|l| l.name == "inscatter.key light").unwrap();
        for (c, n) in ["R", "G", "B"].into_iter().enumerate() {
            let want: Vec<u32> = px.iter().map(|p| p[c].to_bits()).collect();
            let got: Vec<u32> = key.channel(n).unwrap().iter().map(|v| v.to_bits()).collect();
            assert_eq!(got, want, "{n}");
        }
        // A component past B is refused, naming the channel; nothing is written.
        let bad = [LayerRef {
            name: "x",
            channels: vec![("A", ChannelSamples::Rgb(&px, 3))],
        }];
        let c = dir.join("bad.exr");
        let err = write_layer_refs_exr(&c, width, height, &bad).unwrap_err().to_string();
        assert!(err.contains("\"x.A\"") && err.contains("component 3"), "{err}");
        assert!(!c.exists());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn dotted_and_long_layer_names_round_trip() {
        let dir = temp_dir("dotted");
        let path = dir.join("lights.exr");
        let long = "inscatter.a rather long light name über 32 bytes";
        let layers = vec![
            ImageLayer {
                name: "inscatter.key light".into(),
                channels: vec![("R".into(), vec![1.0; 2]), ("G".into(), vec![2.0; 2])],
            },
            ImageLayer {
                name: long.into(),
                channels: vec![("B".into(), vec![3.0; 2])],
            },
            ImageLayer {
                name: String::new(),
                channels: vec![("alpha".into(), vec![4.0; 2])],
            },
        ];
        write_layers_exr(&path, 2, 1, &layers).unwrap();

        // OpenEXR requires the long-names flag for a channel name >= 32 bytes.
        let bytes = std::fs::read(&path).unwrap();
        let version = u32::from_le_bytes(bytes[4..8].try_into().unwrap());
        assert_eq!(version & 0xff, 2);
        assert_ne!(version & (1 << 10), 0, "long-names flag not set");

        let (_, _, read) = read_layers_exr(&path).unwrap();
        let names: Vec<&str> = read.iter().map(|layer| layer.name.as_str()).collect();
        assert_eq!(
            names,
            ["", "inscatter.a rather long light name über 32 bytes", "inscatter.key light"]
        );
        assert_eq!(read[0].channel("alpha").unwrap(), [4.0, 4.0]);
        assert_eq!(read[1].channel("B").unwrap(), [3.0, 3.0]);
        assert_eq!(read[2].channel("G").unwrap(), [2.0, 2.0]);

        // Short names: no flag.
        write_rgb_exr(&path, 1, 1, &[[0.0; 3]]).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        assert_eq!(u32::from_le_bytes(bytes[4..8].try_into().unwrap()), 2);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn missing_directory_is_an_error_naming_the_path() {
        let dir = temp_dir("missing-dir");
        let path = dir.join("no such dir").join("out.exr");
        let err = write_layers_exr(&path, 7, 5, &test_layers(7, 5)).unwrap_err();
        assert!(matches!(err, ImageIoError::Io { .. }), "{err:?}");
        assert!(err.to_string().contains(&path.display().to_string()), "{err}");
        let err = write_rgb_exr(&path, 1, 1, &[[0.0; 3]]).unwrap_err();
        assert!(err.to_string().contains(&path.display().to_string()), "{err}");
        assert!(dir_entries(&dir).is_empty());

        let err = read_layers_exr(&dir.join("absent.exr")).unwrap_err();
        assert!(matches!(err, ImageIoError::Io { .. }), "{err:?}");
        assert!(err.to_string().contains("absent.exr"), "{err}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn failed_write_keeps_the_old_file() {
        let dir = temp_dir("keep-old");
        let path = dir.join("image.exr");
        write_rgb_exr(&path, 1, 1, &[[1.0, 2.0, 3.0]]).unwrap();
        let before = std::fs::read(&path).unwrap();
        assert!(write_rgb_exr(&path, 2, 2, &[[0.0; 3]]).is_err());
        assert_eq!(std::fs::read(&path).unwrap(), before);
        assert_eq!(dir_entries(&dir), ["image.exr"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn corrupt_file_is_an_exr_error() {
        let dir = temp_dir("corrupt");
        let path = dir.join("junk.exr");
        std::fs::write(&path, b"not an exr file at all").unwrap();
        let err = read_layers_exr(&path).unwrap_err();
        assert!(err.to_string().contains("junk.exr"), "{err}");

        // A valid file cut short.
        write_layers_exr(&path, 7, 5, &test_layers(7, 5)).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
        assert!(read_layers_exr(&path).is_err());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn invalid_input_is_rejected() {
        let dir = temp_dir("invalid");
        let path = dir.join("bad.exr");
        let layer = |name: &str, channels: &[(&str, usize)]| ImageLayer {
            name: name.into(),
            channels: channels.iter().map(|&(c, n)| (c.to_owned(), vec![0.0; n])).collect(),
        };
        let cases: Vec<(usize, usize, Vec<ImageLayer>)> = vec![
            (0, 5, vec![layer("a", &[("R", 0)])]),
            (7, 0, vec![layer("a", &[("R", 0)])]),
            (7, 5, vec![]),
            (7, 5, vec![layer("a", &[("R", 35), ("G", 34)])]),
            (7, 5, vec![layer("a", &[("R", 36)])]),
            (7, 5, vec![layer("a", &[])]),
            (7, 5, vec![layer("a", &[("", 35)])]),
            (7, 5, vec![layer("a", &[("x.R", 35)])]),
            (7, 5, vec![layer("a", &[("R", 35), ("R", 35)])]),
            (7, 5, vec![layer("a", &[("R", 35)]), layer("a", &[("G", 35)])]),
            (7, 5, vec![layer("a\0b", &[("R", 35)])]),
            (7, 5, vec![layer(&"x".repeat(254), &[("R", 35)])]),
        ];
        for (width, height, layers) in cases {
            let err = write_layers_exr(&path, width, height, &layers).unwrap_err();
            assert!(matches!(err, ImageIoError::Invalid(_)), "{err:?}");
            assert!(err.to_string().contains("bad.exr"), "{err}");
        }
        // 253 + ".R" = 255 bytes is still fine.
        write_layers_exr(&path, 7, 5, &[layer(&"x".repeat(253), &[("R", 35)])]).unwrap();

        let err = write_rgb_exr(&path, 2, 2, &[[0.0; 3]; 3]).unwrap_err();
        assert!(matches!(err, ImageIoError::Invalid(_)), "{err:?}");
        let err = write_rgb_exr(&path, 0, 2, &[]).unwrap_err();
        assert!(matches!(err, ImageIoError::Invalid(_)), "{err:?}");
        let err = write_rgb_exr(&dir, 1, 1, &[[0.0; 3]]).unwrap_err();
        assert!(err.to_string().contains(&dir.display().to_string()), "{err}");
        assert_eq!(dir_entries(&dir), ["bad.exr"]);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
