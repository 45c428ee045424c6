//! IES LM-63 photometric files: parser and evaluator matching Blender Cycles.
//!
//! # File layout (LM-63-1986 … LM-63-2019)
//!
//! ```text
//! line 1      version line: IESNA91 | IESNA:LM-63-1995 | IESNA:LM-63-2002 | IES:LM-63-2019
//!             (LM-63-1986 files have no version line: everything before TILT is free text)
//! lines 2..   keyword lines "[KEYWORD] value", "[MORE] continuation" (1991 and later)
//! TILT=NONE | TILT=INCLUDE | TILT=<filename>     (a line of its own)
//! [tilt block, only for TILT=INCLUDE: <lamp-to-luminaire geometry 1|2|3> <N pairs>
//!                                     <N tilt angles, deg> <N multiplying factors>]
//! <number of lamps> <lumens per lamp | -1 = absolute photometry> <candela multiplier>
//!   <number of vertical angles NV> <number of horizontal angles NH>
//!   <photometric type 1=C 2=B 3=A> <units type 1=feet 2=meters> <width> <length> <height>
//! <ballast factor> <ballast-lamp photometric factor (1986/1991), "future use" (1995/2002),
//!   file generation type (2019)> <input watts>
//! <NV vertical angles, deg> <NH horizontal angles, deg>
//! <NH blocks of NV candela values: the block for horizontal angle 1 first>
//! ```
//!
//! After the TILT line the file is a stream of numbers: values may span lines
//! arbitrarily and are separated by white space and/or commas (both occur in
//! real files). CRLF line ends and a UTF-8 byte order mark are accepted.
//!
//! # Sources (Blender Cycles, `github.com/blender/cycles`, read July 2026)
//!
//! * `src/util/ies.cpp` (`IESFile::parse`, `process_type_a/b/c`): Cycles finds the
//!   `TILT=` line, skips a `TILT=INCLUDE` block, reads the numbers in the order
//!   above, multiplies every candela value by *candela multiplier × ballast factor ×
//!   second line-11 field × 0.0706650768394* (it multiplies by the second field
//!   whatever it means in the file's version, even the 2019 "file generation type"),
//!   and turns every photometric type into a type-C-like table covering horizontal
//!   0°..360° and vertical 0°..180°:
//!   - type C: a file whose horizontal angles start at 90° is *shifted* by −90°
//!     (so a 90°–270° file is rotated by 90°, not mirrored about the 90°–270°
//!     plane); a single horizontal angle becomes 0° and 360° (rotational
//!     symmetry); a table ending at 90° is mirrored to 180° (C = 180° − c), one
//!     ending at 180° is mirrored to 360° (C = 360° − c); a table starting at 0°
//!     and ending one regular step short of 360° gets a 360° copy of the 0° plane.
//!   - type B: angles are transposed (the file's vertical angles become the
//!     horizontal ones and vice versa), then each set is mirrored from 0°..90°
//!     to −90°..90° if it starts at 0°, and shifted by +90° to 0°..180°.
//!   - type A: vertical angles shifted by +90°; horizontal angle `a` becomes
//!     `180° − a`; a set starting at 0° is mirrored (`−a` becomes `180° + a`).
//!
//!   The comment there explains the constant: candela are lm/sr; Cycles wants
//!   radiometric units, so it assumes the luminous efficacy of the D65
//!   illuminant, 177.83 lm/W, to get W/sr, and multiplies by 4π because a
//!   Cycles point light of strength P watts has radiant intensity P/(4π) W/sr.
//!   Hence [`CYCLES_IES_SCALE`] = 4π / 177.83 = 0.0706650768394 (W per cd) and a
//!   light of Strength 1 W whose emission is multiplied by the IES node's output
//!   has radiant intensity `candela / 177.83` W/sr: the file's candela, converted
//!   at 177.83 lm/W (not at the 683 lm/W of 555 nm light).
//! * `src/kernel/svm/ies.h` (`svm_node_ies`) and `src/kernel/osl/shaders/node_ies_light.osl`:
//!   the node normalises its vector `d`, takes vertical angle `acos(−d.z)` and
//!   horizontal angle `atan2(d.x, d.y) + π`, and returns Strength × table lookup.
//! * `src/scene/shader_nodes.cpp` / `shader_graph.cpp`: the node's default
//!   vector (`LINK_TEXTURE_INCOMING`) is the geometry "Incoming" vector
//!   transformed from world to object space; `src/kernel/light/sample.h` sets up
//!   the light's shader with incoming = −(direction from shading point to light),
//!   i.e. the direction *from the light towards the lit point*, and with the
//!   light's object, so the lookup direction is the emission direction in the
//!   light's local frame. That is the `dir_local` argument here.
//! * `src/kernel/util/ies.h` (`kernel_ies_interp`, `interpolate_ies_vertical`):
//!   zero outside the table's angle ranges (upper ends excluded); otherwise
//!   cubic Catmull-Rom interpolation (`cubic_interp` in `src/util/math_base.h`),
//!   first along the vertical angle for the four horizontal planes around the
//!   direction, then along the horizontal angle; the result is clamped to ≥ 0.
//!   Missing neighbours: vertically, below the first angle the value at index 1
//!   is used if the table starts at 0° (mirror through the pole), else the first
//!   value is repeated; above the last angle the value at index NV−2 is used if
//!   the table ends at 180°, else the last value is repeated. Horizontally, a
//!   table covering 0°..360° wraps (skipping the duplicated 360° plane);
//!   otherwise the *inner left* plane is repeated on both sides (Cycles falls
//!   back to `b` for the missing last point, not to `c`; reproduced here).
//!
//! # Orientation (light's local frame; Blender lights shine along local −Z)
//!
//! Vertical angle 0° is local −Z (straight down the light's axis), 90° is the
//! local XY plane, 180° is +Z. Horizontal (C-plane) angles: C0 = local −Y,
//! C90 = local −X, C180 = +Y, C270 = +X; viewed from above (from +Z) C increases
//! clockwise. This agrees with glTF `EXT_lights_ies`, which aims +X at C270.
//! Type A and B tables go through Cycles' transposition above, not through the
//! LM-75 type A/B geometry: for type A the photometric axis (0°, 0°) is local +Y,
//! vertical +90° is +Z and horizontal +90° is −X; for type B the axis is −X,
//! horizontal (lateral) +90° is +Z and vertical +90° is +Y. Blender users rotate
//! such lights by hand; we reproduce what Blender renders.
//!
//! # Deviations from Cycles (all on sets of measure zero or in error handling)
//!
//! * Upper ends of the angle ranges are included (Cycles returns 0 exactly at the
//!   last vertical/horizontal angle), directions within 1e-9° outside either end
//!   of a range are clamped onto it (so nodes at range ends survive `acos`/`atan2`
//!   rounding), and on a 0°..360° table the seam direction
//!   `atan2(+0, −y) = π`, which Cycles maps to 360° and so to 0, uses the 0° plane.
//! * Beyond [`IesProfile::bounding_half_angle`] the result is exactly 0 by
//!   construction (Cycles' cubic gives ≤ 0 there before clamping, up to rounding).
//! * Cycles accepts almost anything (missing values read as 0); this parser
//!   rejects malformed files with an [`IesError`] naming the line.
//! * Counts and the photometric type written as `1.0` are accepted (Cycles' `strtol`
//!   would split them into two numbers).
//! * Arithmetic is f64 (Cycles stores f32).
//!
//! # Units
//!
//! Angles in degrees in the public fields; [`IesProfile::bounding_half_angle`] in
//! radians. Intensities in candela (lm/sr). Dimensions in the file's units
//! ([`IesProfile::units`]). `candela` values have the candela multiplier and the
//! ballast factors applied (see [`IesProfile::candela`] for the 2019 exception).

use glam::DVec3;
use std::fmt;
use std::path::Path;

/// Cycles' candela-to-emission scale, `4π / 177.83` (W per cd): 177.83 lm/W is the
/// luminous efficacy Cycles assumes (D65 white), and 4π converts the radiant
/// intensity of a point light to the Strength (W) Cycles expects
/// (`src/util/ies.cpp`).
pub const CYCLES_IES_SCALE: f64 = 0.0706650768394;

/// Luminous efficacy (lm/W) Cycles assumes to turn candela into W/sr (D65).
pub const CYCLES_LUMINOUS_EFFICACY: f64 = 177.83;

/// Largest number of vertical or horizontal angles accepted (real files have < 1000).
pub const MAX_ANGLES: usize = 100_000;

/// Largest number of candela values (`NV × NH`) accepted.
pub const MAX_VALUES: usize = 10_000_000;

/// Largest number of tilt angle/factor pairs accepted.
pub const MAX_TILT_PAIRS: usize = 100_000;

/// Largest IES or tilt file read, bytes: [`MAX_VALUES`] candela values of up
/// to ~25 characters each. A larger file (or an endless one such as
/// `/dev/zero`) is an error, not an unbounded read.
pub const MAX_FILE_BYTES: u64 = 256 << 20;

/// The bytes of `path`, at most [`MAX_FILE_BYTES`] of them.
fn read_capped(path: &Path) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let file = std::fs::File::open(path).map_err(|e| e.to_string())?;
    let mut bytes = Vec::new();
    file.take(MAX_FILE_BYTES + 1).read_to_end(&mut bytes).map_err(|e| e.to_string())?;
    if bytes.len() as u64 > MAX_FILE_BYTES {
        return Err(format!("larger than {} MiB: not an LM-63 photometric file", MAX_FILE_BYTES >> 20));
    }
    Ok(bytes)
}

/// Decodes a file's bytes; UTF-16 (a byte-order mark, or NUL bytes among the
/// first ones) is an error: LM-63 files are ASCII. Invalid UTF-8 (Latin-1
/// keywords) is replaced, not rejected.
fn decode(bytes: &[u8]) -> Result<std::borrow::Cow<'_, str>, String> {
    let head = &bytes[..bytes.len().min(64)];
    if head.starts_with(&[0xFF, 0xFE]) || head.starts_with(&[0xFE, 0xFF]) || head.contains(&0) {
        return Err("the file is UTF-16 (or binary), not text: LM-63 files are ASCII; save it as ASCII or UTF-8".to_string());
    }
    Ok(String::from_utf8_lossy(bytes))
}

/// Tolerance (degrees) Cycles uses to compare angles (`angle_close`).
const ANGLE_TOL: f64 = 1e-4;

/// Directions this close (degrees) outside a table's angle range count as on its
/// end, so that a node at a range end is reproduced despite rounding in
/// `acos`/`atan2` (Cycles returns 0 there; the set is of measure zero).
const END_TOL: f64 = 1e-9;

/// A parse or load failure: where and what.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct IesError {
    /// The file name (or other label) given to [`IesProfile::parse`], or the path for [`IesProfile::load`].
    pub source: String,
    /// 1-based line of the problem; 0 when the file could not be read at all.
    pub line: usize,
    /// What is wrong.
    pub message: String,
}

impl fmt::Display for IesError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}:{}: {}", self.source, self.line, self.message)
    }
}

impl std::error::Error for IesError {}

/// The LM-63 edition a file declares on its first line.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum IesVersion {
    /// LM-63-1986: no version line; the header is free text.
    Lm63_1986,
    /// LM-63-1991: first line `IESNA91`.
    Lm63_1991,
    /// LM-63-1995: first line `IESNA:LM-63-1995`.
    Lm63_1995,
    /// LM-63-2002: first line `IESNA:LM-63-2002`.
    Lm63_2002,
    /// LM-63-2019: first line `IES:LM-63-2019`.
    Lm63_2019,
    /// A first line starting with `IESNA`/`IES:` but naming no known edition; read like 2002.
    Unknown,
}

impl IesVersion {
    /// Short name, e.g. `"LM-63-2002"`.
    pub fn name(self) -> &'static str {
        match self {
            IesVersion::Lm63_1986 => "LM-63-1986",
            IesVersion::Lm63_1991 => "LM-63-1991",
            IesVersion::Lm63_1995 => "LM-63-1995",
            IesVersion::Lm63_2002 => "LM-63-2002",
            IesVersion::Lm63_2019 => "LM-63-2019",
            IesVersion::Unknown => "LM-63-?",
        }
    }
}

/// Photometric type (coordinate system of the angles).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PhotometricType {
    /// Type C (code 1): polar axis vertical; architectural and stage luminaires.
    C,
    /// Type B (code 2): polar axis horizontal; floodlights.
    B,
    /// Type A (code 3): automotive convention.
    A,
}

impl PhotometricType {
    /// The code in the file: 1 = C, 2 = B, 3 = A.
    pub fn code(self) -> u32 {
        match self {
            PhotometricType::C => 1,
            PhotometricType::B => 2,
            PhotometricType::A => 3,
        }
    }
}

/// Units of the luminous opening dimensions.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum UnitsType {
    /// Code 1.
    Feet,
    /// Code 2.
    Meters,
}

/// Lamp tilt data (how output changes when the lamp is tilted). Cycles ignores it;
/// it is kept for reports.
#[derive(Debug, Clone, PartialEq)]
pub struct TiltData {
    /// 1 = vertical base-up/down, 2 = horizontal, stays horizontal when tilted,
    /// 3 = horizontal, tilts in the vertical plane.
    pub lamp_to_luminaire_geometry: u32,
    /// Tilt angles, degrees, strictly increasing.
    pub angles_deg: Vec<f64>,
    /// Output multiplying factors (dimensionless, ≥ 0), one per angle.
    pub factors: Vec<f64>,
}

/// The `TILT=` line and its data.
#[derive(Debug, Clone, PartialEq)]
pub enum Tilt {
    /// `TILT=NONE`.
    None,
    /// `TILT=INCLUDE`: the data follows in the file.
    Include(TiltData),
    /// `TILT=<file>`: the data is in another file (resolved by [`IesProfile::load`]
    /// relative to the IES file's directory).
    File {
        /// The name as written after `TILT=`.
        name: String,
        /// The data read from that file.
        data: TiltData,
    },
}

/// How a type C file's horizontal angles cover the circle (for reports).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HorizontalSymmetry {
    /// One horizontal angle: the same in every C plane.
    Rotational,
    /// 0°..90°: mirrored about the 0–180° and 90–270° planes.
    Quadrant,
    /// 0°..180°: mirrored about the 0–180° plane.
    Bilateral,
    /// 90°..270° (LM-63-1995 style); Cycles shifts it to 0°..180° (a 90° rotation).
    Bilateral90,
    /// 0°..360° (or one step short of 360°): no symmetry.
    None,
    /// Anything else (type A/B files, partial coverage): zero outside the given range.
    Other,
}

/// The table Cycles interpolates, after its symmetry/type conversion (see the module doc).
#[derive(Debug, Clone, PartialEq)]
pub struct CyclesTable {
    /// Horizontal angles, degrees, strictly increasing, within 0..=360.
    pub horizontal_deg: Vec<f64>,
    /// Vertical angles, degrees, strictly increasing, within 0..=180 (0 = local −Z).
    pub vertical_deg: Vec<f64>,
    /// Candela, `[h][v]`, the same scaling as [`IesProfile::candela`].
    pub candela: Vec<Vec<f64>>,
}

/// A parsed IES LM-63 file. The public fields record the file (angles as written,
/// candela scaled); evaluation uses a Cycles-style table built once by
/// [`IesProfile::parse`] (see [`IesProfile::cycles_table`]): editing the fields does
/// not change what [`IesProfile::candela`] returns.
#[derive(Debug, Clone, PartialEq)]
pub struct IesProfile {
    /// The label given to `parse` (file path for `load`).
    pub source: String,
    /// The declared edition.
    pub version: IesVersion,
    /// The first line as written (trimmed); empty for LM-63-1986 files.
    pub version_line: String,
    /// `[KEYWORD] value` pairs in file order, keyword without brackets; `[MORE]`
    /// lines are appended to the previous value after a newline.
    pub keywords: Vec<(String, String)>,
    /// Header lines that are not keywords (LM-63-1986 free text, stray lines).
    pub header_text: Vec<String>,
    /// Tilt information.
    pub tilt: Tilt,
    /// Number of lamps.
    pub number_of_lamps: u32,
    /// Rated lumens per lamp, lm; `None` for absolute photometry (`-1`, LED luminaires).
    pub lumens_per_lamp: Option<f64>,
    /// Candela multiplier as written (already applied to `candela`).
    pub candela_multiplier: f64,
    /// Photometric type.
    pub photometric_type: PhotometricType,
    /// Units of `width`, `length`, `height`.
    pub units: UnitsType,
    /// Luminous opening width (negative: round opening, per LM-63-2002), file units.
    pub width: f64,
    /// Luminous opening length, file units.
    pub length: f64,
    /// Luminous opening height, file units.
    pub height: f64,
    /// Ballast factor as written (already applied to `candela`).
    pub ballast_factor: f64,
    /// Second field of the ballast line as written: ballast-lamp photometric factor
    /// (1986/1991; applied to `candela`), "future use" (1995/2002, normally 1; applied),
    /// or file generation type (2019, e.g. 1.10000; *not* applied to `candela`, but
    /// Cycles multiplies by it, so [`IesProfile::cycles_factor`] does too).
    pub ballast_lamp_factor: f64,
    /// Input watts, W.
    pub input_watts: f64,
    /// Vertical angles as in the file, degrees.
    pub vertical_deg: Vec<f64>,
    /// Horizontal angles as in the file, degrees.
    pub horizontal_deg: Vec<f64>,
    /// Luminous intensity, cd, `[h][v]` as in the file, times candela multiplier,
    /// ballast factor and (except in 2019 files) the ballast-lamp factor.
    pub candela: Vec<Vec<f64>>,
    table: Table,
}

/// Cycles-style table plus precomputed facts.
#[derive(Debug, Clone, PartialEq)]
struct Table {
    h: Vec<f64>,
    v: Vec<f64>,
    /// `[h][v]` flattened: `vals[ih * v.len() + iv]`.
    vals: Vec<f64>,
    wrap_h: bool,
    wrap_vlow: bool,
    wrap_vhigh: bool,
    /// Beyond this vertical angle (deg) the result is exactly 0.
    bound_deg: f64,
    /// Upper bound of the interpolated candela over all directions.
    max_interp: f64,
    /// Per cell `[i_h * (n_v − 1) + j_v]`: whether the unclamped interpolant
    /// may change sign inside it (its interval bound straddles 0).
    sign_cells: Vec<bool>,
    /// Largest table value.
    max_value: f64,
    /// Extra factor Cycles applies on top of `candela` (2019 file generation type).
    cycles_extra: f64,
}

// ---------------------------------------------------------------------------
// Tokenising
// ---------------------------------------------------------------------------

#[derive(Clone, Copy)]
struct Token<'a> {
    text: &'a str,
    line: usize,
}

struct Reader<'a> {
    source: &'a str,
    tokens: Vec<Token<'a>>,
    pos: usize,
    eof_line: usize,
}

impl<'a> Reader<'a> {
    fn new(source: &'a str, lines: &[(usize, &'a str)], eof_line: usize) -> Self {
        let mut tokens = Vec::new();
        for &(line, text) in lines {
            for t in text.split(|c: char| c.is_whitespace() || c == ',' || c == '\u{1a}') {
                if !t.is_empty() {
                    tokens.push(Token { text: t, line });
                }
            }
        }
        Reader {
            source,
            tokens,
            pos: 0,
            eof_line,
        }
    }

    fn err(&self, line: usize, message: impl Into<String>) -> IesError {
        IesError {
            source: self.source.to_string(),
            line,
            message: message.into(),
        }
    }

    fn remaining(&self) -> usize {
        self.tokens.len() - self.pos
    }

    fn next(&mut self, what: &str) -> Result<Token<'a>, IesError> {
        match self.tokens.get(self.pos) {
            Some(t) => {
                self.pos += 1;
                Ok(*t)
            }
            None => Err(self.err(self.eof_line, format!("unexpected end of file: expected {what}"))),
        }
    }

    /// A finite number.
    fn number(&mut self, what: &str) -> Result<(f64, usize), IesError> {
        let t = self.next(what)?;
        match t.text.parse::<f64>() {
            Ok(x) if x.is_finite() => Ok((x, t.line)),
            Ok(_) => Err(self.err(t.line, format!("{what}: '{}' is not a finite number", t.text))),
            Err(_) => Err(self.err(t.line, format!("{what}: '{}' is not a number", t.text))),
        }
    }

    /// An integer (also accepted written as `2.0`) within `lo..=hi`.
    fn integer(&mut self, what: &str, lo: i64, hi: i64) -> Result<(i64, usize), IesError> {
        let (x, line) = self.number(what)?;
        if x.fract() != 0.0 {
            return Err(self.err(line, format!("{what}: {x} is not an integer")));
        }
        if x < lo as f64 || x > hi as f64 {
            return Err(self.err(line, format!("{what}: {x} is out of range {lo}..={hi}")));
        }
        Ok((x as i64, line))
    }
}

/// Lines of `text` as (1-based number, content without line end); and the line
/// number used for end-of-file errors.
/// The numbered lines of `text`: a line ends at LF, CR LF or a lone CR (files
/// saved by classic Mac OS tools end their lines with CR only).
fn split_lines(text: &str) -> (Vec<(usize, &str)>, usize) {
    let bytes = text.as_bytes();
    let mut lines: Vec<(usize, &str)> = Vec::new();
    let mut start = 0;
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'\n' => {
                lines.push((lines.len() + 1, &text[start..i]));
                start = i + 1;
            }
            b'\r' => {
                lines.push((lines.len() + 1, &text[start..i]));
                if bytes.get(i + 1) == Some(&b'\n') {
                    i += 1;
                }
                start = i + 1;
            }
            _ => {}
        }
        i += 1;
    }
    // The text after the last line break (empty when the text ends with one),
    // as `str::split` gives it.
    lines.push((lines.len() + 1, &text[start..]));
    let eof_line = if start == bytes.len() { lines.len() - 1 } else { lines.len() }.max(1);
    (lines, eof_line)
}

fn angle_close(a: f64, b: f64) -> bool {
    (a - b).abs() < ANGLE_TOL
}

/// Reads a tilt block (geometry, count, angles, factors) from `r`.
fn read_tilt(r: &mut Reader<'_>) -> Result<TiltData, IesError> {
    let (geometry, _) = r.integer("lamp-to-luminaire geometry (1, 2 or 3)", 1, 3)?;
    let (n, nline) = r.integer("number of tilt angles", 0, i64::MAX)?;
    let n = n as usize;
    if n > MAX_TILT_PAIRS {
        return Err(r.err(nline, format!("number of tilt angles {n} is absurd (limit {MAX_TILT_PAIRS})")));
    }
    let mut angles_deg: Vec<f64> = Vec::with_capacity(n.min(r.remaining()));
    for i in 0..n {
        let (a, line) = r.number(&format!("tilt angle {} of {n}", i + 1))?;
        if let Some(&prev) = angles_deg.last()
            && a <= prev
        {
            return Err(r.err(line, format!("tilt angles must increase: {a} follows {prev}")));
        }
        angles_deg.push(a);
    }
    let mut factors = Vec::with_capacity(n.min(r.remaining()));
    for i in 0..n {
        let (f, line) = r.number(&format!("tilt factor {} of {n}", i + 1))?;
        if f < 0.0 {
            return Err(r.err(line, format!("tilt factor {f} is negative")));
        }
        factors.push(f);
    }
    Ok(TiltData {
        lamp_to_luminaire_geometry: geometry as u32,
        angles_deg,
        factors,
    })
}

// ---------------------------------------------------------------------------
// Parsing
// ---------------------------------------------------------------------------

impl IesProfile {
    /// Parses the text of an IES file; `source` names it in errors. A `TILT=<file>`
    /// reference cannot be resolved here (no directory): it is an error; use
    /// [`IesProfile::load`].
    pub fn parse(text: &str, source: &str) -> Result<IesProfile, IesError> {
        Self::parse_impl(text, source, None)
    }

    /// Reads and parses a file. An unreadable file gives an error at line 0 naming
    /// the path. Invalid UTF-8 (Latin-1 headers) is replaced, not rejected.
    pub fn load(path: &Path) -> Result<IesProfile, IesError> {
        let source = path.display().to_string();
        let bytes = read_capped(path).map_err(|e| IesError {
            source: source.clone(),
            line: 0,
            message: format!("cannot read '{source}': {e}"),
        })?;
        let text = decode(&bytes).map_err(|message| IesError {
            source: source.clone(),
            line: 1,
            message,
        })?;
        let dir = path.parent().unwrap_or(Path::new("."));
        Self::parse_impl(&text, &source, Some(dir))
    }

    fn parse_impl(text: &str, source: &str, dir: Option<&Path>) -> Result<IesProfile, IesError> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let (lines, eof_line) = split_lines(text);
        let err = |line: usize, message: String| IesError {
            source: source.to_string(),
            line,
            message,
        };

        if text.trim().is_empty() {
            return Err(err(1, "empty file".into()));
        }

        // Version line.
        let first = lines[0].1.trim();
        let upper = first.to_ascii_uppercase();
        let (version, header_start) = if upper.starts_with("IESNA91") || upper.starts_with("IESNA:LM-63-1991") {
            (IesVersion::Lm63_1991, 1)
        } else if upper.starts_with("IESNA:LM-63-1995") {
            (IesVersion::Lm63_1995, 1)
        } else if upper.starts_with("IESNA:LM-63-2002") {
            (IesVersion::Lm63_2002, 1)
        } else if upper.starts_with("IES:LM-63-2019") || upper.starts_with("IESNA:LM-63-2019") {
            (IesVersion::Lm63_2019, 1)
        } else if upper.starts_with("IESNA") || upper.starts_with("IES:") {
            (IesVersion::Unknown, 1)
        } else {
            (IesVersion::Lm63_1986, 0)
        };
        let version_line = if header_start == 1 { first.to_string() } else { String::new() };

        // Header up to the TILT line.
        let mut keywords: Vec<(String, String)> = Vec::new();
        let mut header_text = Vec::new();
        let mut tilt_idx = None;
        for (idx, &(_, l)) in lines.iter().enumerate().skip(header_start) {
            let t = l.trim();
            if is_tilt_line(t) {
                tilt_idx = Some(idx);
                break;
            }
            if version != IesVersion::Lm63_1986
                && let Some(rest) = t.strip_prefix('[')
                && let Some(close) = rest.find(']')
            {
                let key = rest[..close].trim().to_string();
                let value = rest[close + 1..].trim().to_string();
                if key.eq_ignore_ascii_case("MORE")
                    && let Some(last) = keywords.last_mut()
                {
                    last.1.push('\n');
                    last.1.push_str(&value);
                } else {
                    keywords.push((key, value));
                }
                continue;
            }
            if !t.is_empty() {
                header_text.push(t.to_string());
            }
        }
        let Some(tilt_idx) = tilt_idx else {
            // Point at the first line that looks like photometric data, if any.
            let data_line = lines
                .iter()
                .skip(header_start)
                .find(|(_, l)| {
                    l.split([' ', '\t', ','])
                        .find(|s| !s.is_empty())
                        .is_some_and(|s| s.parse::<f64>().is_ok())
                })
                .map(|&(n, _)| n);
            return Err(match data_line {
                Some(n) => err(
                    n,
                    "missing TILT line (TILT=NONE, TILT=INCLUDE or TILT=<file>) before the photometric data".into(),
                ),
                None => err(eof_line, "missing TILT line (TILT=NONE, TILT=INCLUDE or TILT=<file>)".into()),
            });
        };
        let (tilt_line_no, tilt_line) = lines[tilt_idx];
        let tilt_value = tilt_line.trim().split_once('=').map(|(_, v)| v.trim()).unwrap_or("");

        let mut r = Reader::new(source, &lines[tilt_idx + 1..], eof_line);
        let tilt = if tilt_value.eq_ignore_ascii_case("NONE") {
            Tilt::None
        } else if tilt_value.eq_ignore_ascii_case("INCLUDE") {
            Tilt::Include(read_tilt(&mut r)?)
        } else if tilt_value.is_empty() {
            return Err(err(
                tilt_line_no,
                "TILT= names nothing (expected NONE, INCLUDE or a file name)".into(),
            ));
        } else {
            let Some(dir) = dir else {
                return Err(err(
                    tilt_line_no,
                    format!("TILT={tilt_value}: external tilt file cannot be resolved without a directory (use IesProfile::load)"),
                ));
            };
            let path = dir.join(tilt_value);
            let data = read_capped(&path).map_err(|e| {
                err(
                    tilt_line_no,
                    format!("TILT={tilt_value}: cannot read tilt file '{}': {e}", path.display()),
                )
            })?;
            let ttext = decode(&data).map_err(|e| err(tilt_line_no, format!("TILT={tilt_value}: tilt file '{}': {e}", path.display())))?;
            let (tlines, teof) = split_lines(&ttext);
            let tsource = path.display().to_string();
            let mut tr = Reader::new(&tsource, &tlines, teof);
            let data = read_tilt(&mut tr).map_err(|e| err(tilt_line_no, format!("TILT={tilt_value}: {e}")))?;
            Tilt::File {
                name: tilt_value.to_string(),
                data,
            }
        };

        // Line 10.
        let (number_of_lamps, _) = r.integer("number of lamps", 0, u32::MAX as i64)?;
        let (lumens, lline) = r.number("lumens per lamp")?;
        let lumens_per_lamp = if lumens == -1.0 {
            None
        } else if lumens >= 0.0 {
            Some(lumens)
        } else {
            return Err(err(
                lline,
                format!("lumens per lamp {lumens} is negative (only -1, absolute photometry, is allowed)"),
            ));
        };
        let (candela_multiplier, mline) = r.number("candela multiplier")?;
        if candela_multiplier <= 0.0 {
            return Err(err(mline, format!("candela multiplier {candela_multiplier} must be positive")));
        }
        let (nv, nvline) = r.integer("number of vertical angles", 1, i64::MAX)?;
        let (nh, nhline) = r.integer("number of horizontal angles", 1, i64::MAX)?;
        let (nv, nh) = (nv as usize, nh as usize);
        if nv > MAX_ANGLES {
            return Err(err(
                nvline,
                format!("number of vertical angles {nv} is absurd (limit {MAX_ANGLES})"),
            ));
        }
        if nh > MAX_ANGLES {
            return Err(err(
                nhline,
                format!("number of horizontal angles {nh} is absurd (limit {MAX_ANGLES})"),
            ));
        }
        if nv * nh > MAX_VALUES {
            return Err(err(nhline, format!("{nv} × {nh} candela values is absurd (limit {MAX_VALUES})")));
        }
        let ptok = r.next("photometric type")?;
        let photometric_type = match ptok.text.parse::<f64>() {
            Ok(1.0) => PhotometricType::C,
            Ok(2.0) => PhotometricType::B,
            Ok(3.0) => PhotometricType::A,
            _ => {
                return Err(err(
                    ptok.line,
                    format!("unsupported photometric type '{}' (expected 1 = C, 2 = B or 3 = A)", ptok.text),
                ));
            }
        };
        let (units_code, uline) = r.integer("units type", i64::MIN, i64::MAX)?;
        let units = match units_code {
            1 => UnitsType::Feet,
            2 => UnitsType::Meters,
            u => return Err(err(uline, format!("units type {u} is neither 1 (feet) nor 2 (meters)"))),
        };
        let (width, _) = r.number("luminous opening width")?;
        let (length, _) = r.number("luminous opening length")?;
        let (height, _) = r.number("luminous opening height")?;

        // Line 11.
        let (ballast_factor, bline) = r.number("ballast factor")?;
        if ballast_factor <= 0.0 {
            return Err(err(bline, format!("ballast factor {ballast_factor} must be positive")));
        }
        let second_name = if version == IesVersion::Lm63_2019 {
            "file generation type"
        } else {
            "ballast-lamp photometric factor"
        };
        let (ballast_lamp_factor, blline) = r.number(second_name)?;
        if ballast_lamp_factor <= 0.0 {
            return Err(err(blline, format!("{second_name} {ballast_lamp_factor} must be positive")));
        }
        let (input_watts, wline) = r.number("input watts")?;
        if input_watts < 0.0 {
            return Err(err(wline, format!("input watts {input_watts} is negative")));
        }

        // Angles.
        let (vrange, hrange) = match photometric_type {
            PhotometricType::C => ((0.0, 180.0), (0.0, 360.0)),
            PhotometricType::A | PhotometricType::B => ((-90.0, 90.0), (-90.0, 90.0)),
        };
        let read_angles = |r: &mut Reader<'_>, n: usize, kind: &str, (lo, hi): (f64, f64)| -> Result<(Vec<f64>, usize), IesError> {
            let mut out: Vec<f64> = Vec::with_capacity(n.min(r.remaining()));
            let mut first_line = 0;
            for i in 0..n {
                let (a, line) = r.number(&format!("{kind} angle {} of {n}", i + 1))?;
                if i == 0 {
                    first_line = line;
                }
                if a < lo - ANGLE_TOL || a > hi + ANGLE_TOL {
                    return Err(r.err(
                        line,
                        format!("{kind} angle {a} is outside {lo}..{hi} degrees for photometric type {photometric_type:?}"),
                    ));
                }
                if let Some(&prev) = out.last()
                    && a <= prev
                {
                    return Err(r.err(line, format!("{kind} angles must increase: {a} follows {prev}")));
                }
                out.push(a);
            }
            Ok((out, first_line))
        };
        let (vertical_deg, vline) = read_angles(&mut r, nv, "vertical", vrange)?;
        let (horizontal_deg, hline) = read_angles(&mut r, nh, "horizontal", hrange)?;

        // Candela.
        let file_factor = candela_multiplier
            * ballast_factor
            * if version == IesVersion::Lm63_2019 {
                1.0
            } else {
                ballast_lamp_factor
            };
        let cycles_extra = if version == IesVersion::Lm63_2019 {
            ballast_lamp_factor
        } else {
            1.0
        };
        let mut candela: Vec<Vec<f64>> = Vec::with_capacity(nh.min(r.remaining() / nv + 1));
        for ih in 0..nh {
            let mut row = Vec::with_capacity(nv.min(r.remaining()));
            for iv in 0..nv {
                let what = format!(
                    "candela value {} of {} (horizontal angle {} of {nh}, vertical {} of {nv})",
                    ih * nv + iv + 1,
                    nh * nv,
                    ih + 1,
                    iv + 1
                );
                let (c, line) = r.number(&what)?;
                if c < 0.0 {
                    return Err(err(line, format!("{what} is negative: {c}")));
                }
                let scaled = c * file_factor;
                if !scaled.is_finite() {
                    return Err(err(line, format!("{what} overflows after scaling: {c} × {file_factor}")));
                }
                row.push(scaled);
            }
            candela.push(row);
        }
        if let Some(t) = r.tokens.get(r.pos) {
            return Err(err(
                t.line,
                format!(
                    "unexpected extra value '{}' after the {} candela values ({} extra values: do the angle counts {nv} × {nh} match the data?)",
                    t.text,
                    nv * nh,
                    r.remaining()
                ),
            ));
        }

        let (h, v, rows) = to_cycles_layout(photometric_type, &vertical_deg, &horizontal_deg, &candela);
        let check = |a: &[f64], kind: &str, line: usize, hi: f64| -> Result<(), IesError> {
            if a.len() < 2 {
                return Err(err(
                    line,
                    format!(
                        "{kind} angles: a table needs at least 2 {kind} angles after symmetry expansion, got {}",
                        a.len()
                    ),
                ));
            }
            if a.windows(2).any(|w| w[1] <= w[0]) || a[0] < -ANGLE_TOL || a[a.len() - 1] > hi + ANGLE_TOL {
                return Err(err(
                    line,
                    format!("{kind} angles {a:?} do not form an increasing table within 0..{hi} after symmetry expansion"),
                ));
            }
            Ok(())
        };
        // Type B transposes: Cycles' horizontal angles come from the vertical ones.
        let (hl, vl) = if photometric_type == PhotometricType::B {
            (vline, hline)
        } else {
            (hline, vline)
        };
        check(&h, "horizontal", hl, 360.0)?;
        check(&v, "vertical", vl, 180.0)?;
        let table = Table::new(h, v, rows, cycles_extra);
        // A 2019 file's generation type multiplies the intensity as Cycles
        // reads it (after the candela values were checked): it must not
        // overflow it (the fuzzer found 1e308 there giving an infinite bound).
        if !(table.max_interp * CYCLES_IES_SCALE * cycles_extra).is_finite() {
            return Err(err(
                blline,
                format!(
                    "{second_name} {ballast_lamp_factor:e} overflows the intensity (Cycles multiplies by it): {:e} cd × {ballast_lamp_factor:e}",
                    table.max_interp
                ),
            ));
        }

        Ok(IesProfile {
            source: source.to_string(),
            version,
            version_line,
            keywords,
            header_text,
            tilt,
            number_of_lamps: number_of_lamps as u32,
            lumens_per_lamp,
            candela_multiplier,
            photometric_type,
            units,
            width,
            length,
            height,
            ballast_factor,
            ballast_lamp_factor,
            input_watts,
            vertical_deg,
            horizontal_deg,
            candela,
            table,
        })
    }
}

fn is_tilt_line(t: &str) -> bool {
    t.get(..4).is_some_and(|k| k.eq_ignore_ascii_case("TILT")) && t[4..].trim_start().starts_with('=')
}

/// Cycles' `process_type_a/b/c`: returns (horizontal, vertical, values[h][v]).
fn to_cycles_layout(ty: PhotometricType, v_in: &[f64], h_in: &[f64], cand: &[Vec<f64>]) -> (Vec<f64>, Vec<f64>, Vec<Vec<f64>>) {
    let mut h = h_in.to_vec();
    let mut v = v_in.to_vec();
    let mut rows = cand.to_vec();
    match ty {
        PhotometricType::C => {
            if angle_close(h[0], 90.0) {
                h.iter_mut().for_each(|a| *a -= 90.0);
            }
            if h.len() == 1 {
                h = vec![0.0, 360.0];
                rows.push(rows[0].clone());
            }
            if angle_close(h[h.len() - 1], 90.0) {
                for i in (0..h.len() - 1).rev() {
                    h.push(180.0 - h[i]);
                    rows.push(rows[i].clone());
                }
            }
            if angle_close(h[h.len() - 1], 180.0) {
                for i in (0..h.len() - 1).rev() {
                    h.push(360.0 - h[i]);
                    rows.push(rows[i].clone());
                }
            }
            let n = h.len();
            if angle_close(h[0], 0.0) && !angle_close(h[n - 1], 360.0) {
                let last_step = h[n - 1] - h[n - 2];
                let first_step = h[1] - h[0];
                let gap = 360.0 - h[n - 1];
                if angle_close(last_step, gap) || angle_close(first_step, gap) {
                    h.push(360.0);
                    rows.push(rows[0].clone());
                }
            }
        }
        PhotometricType::B => {
            // Transpose: the file's vertical angles become horizontal.
            let mut t = vec![Vec::with_capacity(h.len()); v.len()];
            for row in &rows {
                for (iv, &x) in row.iter().enumerate() {
                    t[iv].push(x);
                }
            }
            rows = t;
            std::mem::swap(&mut h, &mut v);
            if angle_close(h[0], 0.0) {
                let n = h.len();
                let mut nh = Vec::with_capacity(2 * n - 1);
                let mut nr = Vec::with_capacity(2 * n - 1);
                for i in (1..n).rev() {
                    nh.push(90.0 - h[i]);
                    nr.push(rows[i].clone());
                }
                for i in 0..n {
                    nh.push(90.0 + h[i]);
                    nr.push(rows[i].clone());
                }
                h = nh;
                rows = nr;
            } else {
                h.iter_mut().for_each(|a| *a += 90.0);
            }
            if angle_close(v[0], 0.0) {
                let n = v.len();
                let mut nv: Vec<f64> = (1..n).rev().map(|i| 90.0 - v[i]).collect();
                nv.extend(v.iter().map(|a| 90.0 + a));
                for row in &mut rows {
                    let mut r: Vec<f64> = (1..n).rev().map(|j| row[j]).collect();
                    r.extend_from_slice(row);
                    *row = r;
                }
                v = nv;
            } else {
                v.iter_mut().for_each(|a| *a += 90.0);
            }
        }
        PhotometricType::A => {
            v.iter_mut().for_each(|a| *a += 90.0);
            let n = h.len();
            let mut nh: Vec<f64> = (0..n).rev().map(|i| 180.0 - h[i]).collect();
            let mut nr: Vec<Vec<f64>> = (0..n).rev().map(|i| rows[i].clone()).collect();
            if angle_close(h[0], 0.0) {
                for i in 1..n {
                    nh.push(180.0 + h[i]);
                    nr.push(rows[i].clone());
                }
            }
            h = nh;
            rows = nr;
        }
    }
    (h, v, rows)
}

// ---------------------------------------------------------------------------
// Interpolation
// ---------------------------------------------------------------------------

/// Catmull-Rom weights for the points a, b, c, d at fraction `x` in [0, 1] between b and c
/// (the polynomial of Cycles' `cubic_interp`). `wa`, `wd` ≤ 0 and `wb`, `wc` ≥ 0 on [0, 1].
fn cr_weights(x: f64) -> [f64; 4] {
    let y = 1.0 - x;
    [
        -0.5 * x * y * y,
        1.0 - x * x * (2.5 - 1.5 * x),
        x * (0.5 + x * (2.0 - 1.5 * x)),
        -0.5 * x * x * y,
    ]
}

fn cr(w: &[f64; 4], p: [f64; 4]) -> f64 {
    w[0] * p[0] + w[1] * p[1] + w[2] * p[2] + w[3] * p[3]
}

/// Bounds of Catmull-Rom over x in [0, 1] when the points lie in the given intervals:
/// `wb + wc = 1 + s`, `wa + wd = −s`, `s = x(1−x)/2 ≤ 1/8`.
fn cr_range(p: [(f64, f64); 4]) -> (f64, f64) {
    let hi_bc = p[1].1.max(p[2].1);
    let lo_ad = p[0].0.min(p[3].0);
    let lo_bc = p[1].0.min(p[2].0);
    let hi_ad = p[0].1.max(p[3].1);
    (lo_bc - 0.125 * (hi_ad - lo_bc).max(0.0), hi_bc + 0.125 * (hi_bc - lo_ad).max(0.0))
}

impl Table {
    fn new(h: Vec<f64>, v: Vec<f64>, rows: Vec<Vec<f64>>, cycles_extra: f64) -> Table {
        let vals: Vec<f64> = rows.into_iter().flatten().collect();
        let max_value = vals.iter().copied().fold(0.0, f64::max);
        let rad = |d: f64| d.to_radians();
        let wrap_h = rad(h[0]) < 1e-7 && rad(h[h.len() - 1]) > std::f64::consts::TAU - 1e-7;
        let wrap_vlow = rad(v[0]) < 1e-7;
        let wrap_vhigh = rad(v[v.len() - 1]) > std::f64::consts::PI - 1e-7;
        let mut t = Table {
            h,
            v,
            vals,
            wrap_h,
            wrap_vlow,
            wrap_vhigh,
            bound_deg: 0.0,
            max_interp: 0.0,
            sign_cells: Vec::new(),
            max_value,
            cycles_extra,
        };
        t.bound_deg = t.compute_bound();
        t.max_interp = t.compute_max();
        t.sign_cells = t.compute_sign_cells();
        t
    }

    fn at(&self, ih: usize, iv: usize) -> f64 {
        self.vals[ih * self.v.len() + iv]
    }

    /// Rows (vertical indices) a, b, c, d used for the vertical segment `j`.
    fn v_idx(&self, j: usize) -> [usize; 4] {
        let n = self.v.len();
        let a = if j > 0 {
            j - 1
        } else if self.wrap_vlow {
            1
        } else {
            j
        };
        let d = if j + 2 < n {
            j + 2
        } else if self.wrap_vhigh {
            n - 2
        } else {
            j + 1
        };
        [a, j, j + 1, d]
    }

    /// Columns (horizontal indices) a, b, c, d for the horizontal segment `i`
    /// (Cycles: missing a or d falls back to b).
    fn h_idx(&self, i: usize) -> [usize; 4] {
        let n = self.h.len();
        let a = if i > 0 {
            i - 1
        } else if self.wrap_h {
            n - 2
        } else {
            i
        };
        let d = if i + 2 < n {
            i + 2
        } else if self.wrap_h {
            1
        } else {
            i
        };
        [a, i, i + 1, d]
    }

    /// Segment index and fraction of `x` in the increasing array `a` (x within range).
    fn locate(a: &[f64], x: f64) -> (usize, f64) {
        let k = a[1..].partition_point(|&t| t < x).min(a.len() - 2);
        (k, (x - a[k]) / (a[k + 1] - a[k]))
    }

    /// Interpolated candela at Cycles angles (degrees).
    fn eval(&self, v_deg: f64, h_deg: f64) -> f64 {
        self.eval_unclamped(v_deg, h_deg).max(0.0)
    }

    /// [`Table::eval`] before Cycles' final clamp at 0 (0 outside the ranges).
    fn eval_unclamped(&self, v_deg: f64, h_deg: f64) -> f64 {
        let (v0, v1) = (self.v[0], self.v[self.v.len() - 1]);
        if !(v_deg >= v0 - END_TOL && v_deg <= v1 + END_TOL) || v_deg > self.bound_deg {
            return 0.0;
        }
        let v_deg = v_deg.clamp(v0, v1);
        let (h0, h1) = (self.h[0], self.h[self.h.len() - 1]);
        let mut h_deg = h_deg;
        if self.wrap_h && h_deg >= h1 {
            h_deg = h0;
        }
        if !(h_deg >= h0 - END_TOL && h_deg <= h1 + END_TOL) {
            return 0.0;
        }
        let h_deg = h_deg.clamp(h0, h1);
        let (j, xv) = Self::locate(&self.v, v_deg);
        let (i, xh) = Self::locate(&self.h, h_deg);
        let wv = cr_weights(xv);
        let wh = cr_weights(xh);
        let vi = self.v_idx(j);
        let col = |k: usize| cr(&wv, vi.map(|r| self.at(k, r)));
        let hi = self.h_idx(i);
        cr(&wh, hi.map(col))
    }

    fn row_nonzero(&self, iv: usize) -> bool {
        (0..self.h.len()).any(|ih| self.at(ih, iv) != 0.0)
    }

    /// Whether the horizontal Catmull-Rom (with Cycles' fallbacks) of row `iv` is ≥ 0 everywhere.
    fn row_interp_nonneg(&self, iv: usize) -> bool {
        (0..self.h.len() - 1).all(|i| {
            let [a, b, c, d] = self.h_idx(i).map(|k| self.at(k, iv));
            // p(x) = b + ((c−a) + ((2a−5b+4c−d) + (d+3(b−c)−a) x) x) x / 2
            let (k1, k2, k3) = (c - a, 2.0 * a - 5.0 * b + 4.0 * c - d, d + 3.0 * (b - c) - a);
            let p = |x: f64| b + 0.5 * x * (k1 + x * (k2 + x * k3));
            // p'(x) ∝ 3 k3 x² + 2 k2 x + k1
            let mut xs = vec![0.0, 1.0];
            if k3.abs() > 1e-300 {
                let disc = k2 * k2 - 3.0 * k3 * k1;
                if disc >= 0.0 {
                    let s = disc.sqrt();
                    xs.push((-k2 + s) / (3.0 * k3));
                    xs.push((-k2 - s) / (3.0 * k3));
                }
            } else if k2.abs() > 1e-300 {
                xs.push(-k1 / (2.0 * k2));
            }
            // Also sample densely, a guard against rounding in the critical points.
            xs.extend((1..64).map(|m| m as f64 / 64.0));
            xs.into_iter().filter(|x| (0.0..=1.0).contains(x)).all(|x| p(x) >= 0.0)
        })
    }

    /// Smallest vertical angle (deg) beyond which the interpolated value is 0.
    fn compute_bound(&self) -> f64 {
        let nv = self.v.len();
        let nonzero: Vec<bool> = (0..nv).map(|iv| self.row_nonzero(iv)).collect();
        let mut bound = 0.0;
        for j in 0..nv - 1 {
            let [a, b, c, d] = self.v_idx(j);
            let live = nonzero[b] || nonzero[c] || nonzero[d] || (nonzero[a] && !self.row_interp_nonneg(a));
            if live {
                bound = self.v[j + 1];
            }
        }
        bound
    }

    /// Whether the cell of horizontal segment `i` and vertical segment `j` may
    /// be non-zero. On a cell the value is `max(0, Σ_k Σ_r w_k w_r T[k][r])`
    /// over the four columns k and rows r the cell reads; the inner weights
    /// (b, c) of Catmull-Rom are ≥ 0 and the outer ones (a, d) ≤ 0 (an index
    /// read twice, at the table's ends, gets both signs), and T ≥ 0 (the
    /// parser rejects negative candela). So a product `w_k w_r` can be
    /// positive only for inner×inner or outer×outer pairs, and if T is 0 on
    /// all of those the cell is exactly 0 after the clamp.
    fn cell_may_be_lit(&self, i: usize, j: usize) -> bool {
        let split = |idx: [usize; 4]| ([idx[1], idx[2]], [idx[0], idx[3]]);
        let (h_in, h_out) = split(self.h_idx(i));
        let (v_in, v_out) = split(self.v_idx(j));
        let any = |ks: [usize; 2], rs: [usize; 2]| ks.iter().any(|&k| rs.iter().any(|&r| self.at(k, r) != 0.0));
        any(h_in, v_in) || any(h_out, v_out)
    }

    /// Vertical angle (deg) beyond which the interpolated value is 0 for every
    /// horizontal angle in segment `i` (`h[i]..h[i+1]`): the end of its last
    /// cell that [`Table::cell_may_be_lit`].
    fn segment_bound(&self, i: usize) -> f64 {
        let bound = (0..self.v.len() - 1)
            .rev()
            .find(|&j| self.cell_may_be_lit(i, j))
            .map_or(0.0, |j| self.v[j + 1]);
        bound.min(self.bound_deg)
    }

    /// Smallest vertical angle (deg) below which the interpolated value is 0
    /// for every horizontal angle: the start of the first row of cells any of
    /// which [`Table::cell_may_be_lit`]; 180 when the table is 0 everywhere.
    fn lowest_lit_deg(&self) -> f64 {
        (0..self.v.len() - 1)
            .take_while(|&j| self.v[j] < self.bound_deg)
            .find(|&j| (0..self.h.len() - 1).any(|i| self.cell_may_be_lit(i, j)))
            .map_or(180.0, |j| self.v[j])
    }

    /// For every cell, whether the interval Catmull-Rom bound of the unclamped
    /// interpolant contains both signs (else it is > 0 or ≤ 0 throughout).
    fn compute_sign_cells(&self) -> Vec<bool> {
        let (nh, nv) = (self.h.len(), self.v.len());
        let mut out = vec![true; nh.saturating_sub(1) * nv.saturating_sub(1)];
        for j in 0..nv.saturating_sub(1) {
            let vi = self.v_idx(j);
            let cols: Vec<(f64, f64)> = (0..nh)
                .map(|k| {
                    cr_range(vi.map(|r| {
                        let x = self.at(k, r);
                        (x, x)
                    }))
                })
                .collect();
            for i in 0..nh.saturating_sub(1) {
                let (lo, hi) = cr_range(self.h_idx(i).map(|k| cols[k]));
                out[i * (nv - 1) + j] = lo <= 0.0 && hi > 0.0;
            }
        }
        out
    }

    /// Whether the unclamped interpolant may change sign in the cell holding
    /// Cycles angles (v, h) in degrees (true where unsure or out of range).
    fn may_change_sign(&self, v_deg: f64, h_deg: f64) -> bool {
        let (nh, nv) = (self.h.len(), self.v.len());
        if nh < 2 || nv < 2 {
            return true;
        }
        let (v0, v1, h0, h1) = (self.v[0], self.v[nv - 1], self.h[0], self.h[nh - 1]);
        if !(v_deg >= v0 && v_deg <= v1 && h_deg >= h0 && h_deg <= h1) {
            return true;
        }
        let (j, _) = Self::locate(&self.v, v_deg);
        let (i, _) = Self::locate(&self.h, h_deg);
        self.sign_cells.get(i * (nv - 1) + j).copied().unwrap_or(true)
    }

    /// Guaranteed upper bound of `eval` (cell-wise interval Catmull-Rom).
    fn compute_max(&self) -> f64 {
        let (nh, nv) = (self.h.len(), self.v.len());
        let mut best = 0.0f64;
        for j in 0..nv - 1 {
            if self.v[j] >= self.bound_deg {
                break;
            }
            let vi = self.v_idx(j);
            let cols: Vec<(f64, f64)> = (0..nh)
                .map(|k| {
                    let p = vi.map(|r| {
                        let x = self.at(k, r);
                        (x, x)
                    });
                    cr_range(p)
                })
                .collect();
            for i in 0..nh - 1 {
                let (_, hi) = cr_range(self.h_idx(i).map(|k| cols[k]));
                best = best.max(hi);
            }
        }
        best.max(self.max_value)
    }
}

// ---------------------------------------------------------------------------
// Evaluation API
// ---------------------------------------------------------------------------

/// Cycles' (vertical, horizontal) angles in degrees for a local direction, or
/// `None` for a zero or non-finite vector.
fn cycles_angles(dir: DVec3) -> Option<(f64, f64)> {
    let len = dir.length();
    if !len.is_finite() || len <= 0.0 {
        return None;
    }
    let d = dir / len;
    let v = (-d.z).clamp(-1.0, 1.0).acos().to_degrees();
    let h = d.x.atan2(d.y).to_degrees() + 180.0;
    Some((v, h))
}

impl IesProfile {
    /// Luminous intensity, cd, towards `dir_local`: the emission direction in the
    /// light's local frame (normalised here; zero/NaN vectors give 0). Local −Z is
    /// vertical angle 0, C0 is local −Y, C90 local −X (see the module doc). Uses
    /// Cycles' table, symmetry expansion and Catmull-Rom interpolation, so
    /// `cycles_factor = candela × CYCLES_IES_SCALE` (× the file generation type
    /// for LM-63-2019 files, which Cycles multiplies in).
    pub fn candela(&self, dir_local: DVec3) -> f64 {
        match cycles_angles(dir_local) {
            Some((v, h)) => self.table.eval(v, h),
            None => 0.0,
        }
    }

    /// The interpolated candela towards `dir_local` before Cycles clamps it
    /// at 0: negative where the Catmull-Rom interpolation undershoots (thin
    /// dark gaps and islands of light near a cutoff start where it changes
    /// sign, which is where the in-scatter integral cuts its windows).
    pub fn candela_unclamped(&self, dir_local: DVec3) -> f64 {
        match cycles_angles(dir_local) {
            Some((v, h)) => self.table.eval_unclamped(v, h),
            None => 0.0,
        }
    }

    /// Whether [`IesProfile::candela_unclamped`] may change sign in the table
    /// cell holding `dir_local` (from an interval bound of the cell's
    /// Catmull-Rom; true where unsure). Cells that are positive or ≤ 0
    /// throughout need no search for sign changes.
    pub fn may_change_sign(&self, dir_local: DVec3) -> bool {
        match cycles_angles(dir_local) {
            Some((v, h)) => self.table.may_change_sign(v, h),
            None => true,
        }
    }

    /// What Cycles' IES Texture node outputs for this direction with Strength 1
    /// (default vector input): the factor multiplying the light's emission.
    pub fn cycles_factor(&self, dir_local: DVec3) -> f64 {
        self.candela(dir_local) * self.cycles_scale()
    }

    /// `CYCLES_IES_SCALE` times the extra factor Cycles applies (the 2019 file
    /// generation type; 1 for other versions): `cycles_factor / candela`.
    pub fn cycles_scale(&self) -> f64 {
        CYCLES_IES_SCALE * self.table.cycles_extra
    }

    /// An upper bound of [`IesProfile::cycles_factor`] over all directions (the
    /// cubic interpolation may overshoot the largest table value by up to ~28 %;
    /// the bound is computed per table cell and is usually within a few % of the max).
    pub fn max_cycles_factor(&self) -> f64 {
        self.table.max_interp * self.cycles_scale()
    }

    /// An upper bound of [`IesProfile::candela`] over all directions, cd.
    pub fn max_candela_bound(&self) -> f64 {
        self.table.max_interp
    }

    /// Largest candela value in the table, cd.
    pub fn max_candela(&self) -> f64 {
        self.table.max_value
    }

    /// Smallest half-angle (radians) about local −Z outside which the intensity
    /// is exactly 0; π when light can go straight up, 0 when the table is all zero.
    pub fn bounding_half_angle(&self) -> f64 {
        self.table.bound_deg.min(180.0).to_radians()
    }

    /// Largest half-angle (radians) about local −Z inside which the intensity
    /// is exactly 0 (an uplight's profile: π/2); π when the table is all zero.
    pub fn unlit_half_angle(&self) -> f64 {
        // Less the tolerance within which an angle just below the table's
        // first node is read as that node.
        (self.table.lowest_lit_deg().min(180.0) - END_TOL).max(0.0).to_radians()
    }

    /// The vertical and horizontal angles of Cycles' table, rad (where its
    /// interpolation changes cell).
    pub fn cell_angles(&self) -> (Vec<f64>, Vec<f64>) {
        let rad = |xs: &[f64]| xs.iter().map(|x| x.to_radians()).collect::<Vec<_>>();
        (rad(&self.table.v), rad(&self.table.h))
    }

    /// A tighter, elliptical illumination volume for a non-axisymmetric
    /// profile: `(a, b)` with `(tan θ cos φ / a)² + (tan θ sin φ / b)² ≤ 1` for
    /// every direction with a non-zero intensity (θ from local −Z, φ from local
    /// +X towards +Y), when that ellipse has less than 0.9 of the area of the
    /// circular cone of [`IesProfile::bounding_half_angle`]; `None` otherwise
    /// (axisymmetric or nearly so, or lit beyond 80°). Each horizontal segment
    /// `h[i]..h[i+1]` of Cycles' table gets its own vertical bound (the four
    /// columns its interpolation reads), and a direction at Cycles angles
    /// (v, h) lies at `tan v · (−sin h, −cos h)` in the gnomonic plane, so the
    /// segment is the circular sector φ ∈ [−90° − h[i+1], −90° − h[i]].
    pub fn bounding_ellipse(&self) -> Option<(f64, f64)> {
        let t = &self.table;
        let sectors: Vec<(f64, f64, f64)> = (0..t.h.len().saturating_sub(1))
            .map(|i| {
                let (p0, p1) = ((-90.0 - t.h[i + 1]).to_radians(), (-90.0 - t.h[i]).to_radians());
                (p0, p1, t.segment_bound(i).to_radians())
            })
            .collect();
        super::bounding_ellipse_of_sectors(&sectors, self.bounding_half_angle())
    }

    /// The table Cycles interpolates (angles in degrees, after symmetry/type conversion).
    pub fn cycles_table(&self) -> CyclesTable {
        let nv = self.table.v.len();
        CyclesTable {
            horizontal_deg: self.table.h.clone(),
            vertical_deg: self.table.v.clone(),
            candela: self.table.vals.chunks(nv).map(|c| c.to_vec()).collect(),
        }
    }

    /// The value of keyword `name` (case-insensitive, without brackets), if present.
    pub fn keyword(&self, name: &str) -> Option<&str> {
        self.keywords
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    /// How the horizontal angles of the file cover the circle.
    pub fn symmetry(&self) -> HorizontalSymmetry {
        let h = &self.horizontal_deg;
        if self.photometric_type != PhotometricType::C {
            return HorizontalSymmetry::Other;
        }
        let (first, last) = (h[0], h[h.len() - 1]);
        if h.len() == 1 {
            HorizontalSymmetry::Rotational
        } else if angle_close(first, 0.0) && angle_close(last, 90.0) {
            HorizontalSymmetry::Quadrant
        } else if angle_close(first, 0.0) && angle_close(last, 180.0) {
            HorizontalSymmetry::Bilateral
        } else if angle_close(first, 90.0) && angle_close(last, 270.0) {
            HorizontalSymmetry::Bilateral90
        } else if angle_close(first, 0.0) && self.table.wrap_h {
            HorizontalSymmetry::None
        } else {
            HorizontalSymmetry::Other
        }
    }

    /// One line for reports: edition, type, symmetry, angle ranges, max candela, cone.
    pub fn describe(&self) -> String {
        let range = |a: &[f64]| format!("{}–{}° ({})", a[0], a[a.len() - 1], a.len());
        let sym = match self.symmetry() {
            HorizontalSymmetry::Rotational => "rotationally symmetric",
            HorizontalSymmetry::Quadrant => "quadrant symmetric",
            HorizontalSymmetry::Bilateral => "bilateral (0–180°)",
            HorizontalSymmetry::Bilateral90 => "bilateral (90–270°, rotated 90° as in Cycles)",
            HorizontalSymmetry::None => "no symmetry",
            HorizontalSymmetry::Other => "partial/other",
        };
        let lumens = match self.lumens_per_lamp {
            Some(l) => format!("{} × {l} lm", self.number_of_lamps),
            None => "absolute photometry".to_string(),
        };
        let tilt = match &self.tilt {
            Tilt::None => "NONE".to_string(),
            Tilt::Include(_) => "INCLUDE".to_string(),
            Tilt::File { name, .. } => name.clone(),
        };
        format!(
            "IES {} type {:?}, {sym}, vertical {}, horizontal {}, max {:.6} cd, cone {:.2}°, {lumens}, TILT={tilt}",
            self.version.name(),
            self.photometric_type,
            range(&self.vertical_deg),
            range(&self.horizontal_deg),
            self.max_candela(),
            self.bounding_half_angle().to_degrees(),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DOWN: &str = "IESNA:LM-63-2002\n[TEST] t\nTILT=NONE\n1 1000 1 4 1 1 2 0 0 0\n1 1 10\n0 30 60 90\n0\n100 80 0 0\n";

    /// Random sparse tables (0–360° with wrap, and 0–90° without): wherever
    /// a cell is marked one-signed, the unclamped interpolant sampled densely
    /// inside it has one sign; and the per-segment vertical bounds hold every
    /// lit sample.
    #[test]
    fn sign_cells_and_segment_bounds_hold_on_random_tables() {
        let mut seed = 11u64;
        let mut next = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64) / ((1u64 << 53) as f64)
        };
        let mut one_signed = 0;
        for case in 0..40 {
            let h: Vec<f64> = if case % 2 == 0 {
                (0..=12).map(|k| 30.0 * k as f64).collect()
            } else {
                (0..=6).map(|k| 15.0 * k as f64).collect()
            };
            let v: Vec<f64> = (0..=18).map(|k| 5.0 * k as f64).collect();
            let mut rows: Vec<Vec<f64>> = h
                .iter()
                .map(|_| v.iter().map(|_| if next() < 0.4 { 0.0 } else { 1000.0 * next() }).collect())
                .collect();
            if case % 2 == 0 {
                // 0° and 360° are the same plane.
                let first = rows[0].clone();
                *rows.last_mut().unwrap() = first;
            }
            let t = Table::new(h.clone(), v.clone(), rows, 1.0);
            let nv = v.len();
            for i in 0..h.len() - 1 {
                let bound = t.segment_bound(i);
                for j in 0..nv - 1 {
                    let marked = t.sign_cells[i * (nv - 1) + j];
                    let (mut pos, mut neg) = (false, false);
                    for a in 1..16 {
                        for b in 1..16 {
                            let vd = v[j] + (v[j + 1] - v[j]) * a as f64 / 16.0;
                            let hd = h[i] + (h[i + 1] - h[i]) * b as f64 / 16.0;
                            let u = t.eval_unclamped(vd, hd);
                            pos |= u > 0.0;
                            neg |= u <= 0.0;
                            if u > 0.0 {
                                assert!(vd <= bound + 1e-9, "case {case}: lit at v={vd} beyond the segment bound {bound}");
                            }
                        }
                    }
                    if !marked {
                        one_signed += 1;
                        assert!(!(pos && neg), "case {case}: cell ({i}, {j}) marked one-signed but changes sign");
                    }
                }
            }
        }
        assert!(one_signed > 100, "{one_signed} one-signed cells");
    }

    #[test]
    fn weights_are_catmull_rom() {
        for &x in &[0.0, 0.1, 0.37, 0.5, 0.9, 1.0] {
            let (a, b, c, d) = (0.3, 1.7, -0.4, 2.2);
            // Cycles' Horner form.
            let horner = 0.5 * (((d + 3.0 * (b - c) - a) * x + (2.0 * a - 5.0 * b + 4.0 * c - d)) * x + (c - a)) * x + b;
            let w = cr_weights(x);
            assert!((cr(&w, [a, b, c, d]) - horner).abs() < 1e-12);
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        assert_eq!(cr_weights(0.0), [0.0, 1.0, 0.0, 0.0]);
        let w1 = cr_weights(1.0);
        assert_eq!((w1[1], w1[2]), (0.0, 1.0));
    }

    #[test]
    fn cr_range_bounds_samples() {
        let p = [0.0, 10.0, 10.0, 0.0];
        let (lo, hi) = cr_range(p.map(|x| (x, x)));
        for m in 0..=100 {
            let y = cr(&cr_weights(m as f64 / 100.0), p);
            assert!(y <= hi + 1e-12 && y >= lo - 1e-12);
        }
        assert!((hi - 11.25).abs() < 1e-12);
    }

    #[test]
    fn downlight_nodes_and_cone() {
        let p = IesProfile::parse(DOWN, "t").unwrap();
        assert_eq!(p.cycles_table().horizontal_deg, vec![0.0, 360.0]);
        let dir = |v: f64| DVec3::new(0.3 * v.to_radians().sin(), 0.0, 0.0) + DVec3::new(0.0, 0.0, -v.to_radians().cos()) * 0.3;
        assert!((p.candela(dir(0.0)) - 100.0).abs() < 1e-9);
        assert!((p.candela(dir(30.0)) - 80.0).abs() < 1e-9);
        // Row at 30° is uniform ≥ 0, so beyond 60° the clamp gives exactly 0.
        assert!((p.bounding_half_angle().to_degrees() - 60.0).abs() < 1e-12);
        assert_eq!(p.candela(dir(61.0)), 0.0);
        assert!(p.max_candela_bound() >= 100.0);
    }

    #[test]
    fn errors_never_panic_on_tiny_inputs() {
        for s in [
            "",
            "\n",
            "TILT=NONE",
            "TILT=NONE\n1",
            "IESNA91\nTILT=INCLUDE\n",
            "x\nTILT=NONE\n1 -1 1 2 1 1 1 0 0 0 1 1 0 0 90 0 5 5 5",
        ] {
            let _ = IesProfile::parse(s, "s");
        }
    }
}
