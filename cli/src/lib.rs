//! The `tyndall` command line, as a library so that the Python package's
//! `tyndall` entry point runs exactly the same code as the cargo binary.
//!
//! ```text
//! tyndall render SCENE.json --out OUT.exr [--report R.json] [--preview P.png] [--tolerance T] [--threads N]
//! tyndall demo [--out-dir ./tyndall-demo]
//! tyndall schema
//! tyndall bench [--width W --height H --repeat N]
//! ```
#![warn(missing_docs)]

use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use std::path::{Path, PathBuf};
use std::time::Instant;
use tyndall_core::io::{self, ImageIoError};
use tyndall_core::{Images, RenderError, Report, Scene, SceneError};

/// Everything that can stop a command.
#[derive(Debug, thiserror::Error)]
pub enum CliError {
    /// The scene file is invalid.
    #[error("{0}")]
    Scene(#[from] SceneError),
    /// The render could not run.
    #[error("{0}")]
    Render(#[from] RenderError),
    /// An output file could not be written.
    #[error("{0}")]
    Image(#[from] ImageIoError),
    /// Another I/O problem (report, directories).
    #[error("{path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// An output path that cannot be written as asked (checked before the render).
    #[error("{path}: {message}")]
    Output {
        /// The path given.
        path: PathBuf,
        /// What is wrong with it.
        message: String,
    },
}

/// Checks the output paths before a render or a sky, so that no work is lost
/// and nothing is half written: the image must end in `.exr`, the preview in
/// `.png` and the report in `.json` (their formats), no path may be a
/// directory, no two may name the same file (a report over the image would
/// replace it), and the folders of all three are created. A scene file
/// given as the report is refused by its extension only if it does not end
/// in `.json`: the CLI also passes the scene to [`check_not_an_input`].
pub fn prepare_outputs(out: &Path, preview: Option<&Path>, report: Option<&Path>) -> Result<(), CliError> {
    let wants = |p: &Path, ext: &str, what: &str| -> Result<(), CliError> {
        let format = if ext == "exr" { "an OpenEXR" } else { "a PNG" };
        let ok = p.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case(ext));
        if ok {
            Ok(())
        } else {
            Err(CliError::Output {
                path: p.to_path_buf(),
                message: format!("the {what} is written as {format} file: give a file name ending in .{ext}"),
            })
        }
    };
    let all = || std::iter::once(out).chain(preview).chain(report);
    if let Some(p) = all().find(|p| p.is_dir()) {
        return Err(CliError::Output {
            path: p.to_path_buf(),
            message: "is a directory: give a file name in it".into(),
        });
    }
    wants(out, "exr", "image")?;
    if let Some(p) = preview {
        wants(p, "png", "preview")?;
    }
    if let Some(p) = report
        && !p
            .extension()
            .and_then(|e| e.to_str())
            .is_some_and(|e| e.eq_ignore_ascii_case("json"))
    {
        return Err(CliError::Output {
            path: p.to_path_buf(),
            message: "the report is written as JSON: give a file name ending in .json".into(),
        });
    }
    let named: Vec<&Path> = all().collect();
    for (i, a) in named.iter().enumerate() {
        if named[..i].iter().any(|b| same_file_name(a, b)) {
            return Err(CliError::Output {
                path: a.to_path_buf(),
                message: "is given for two outputs (image, preview, report): give each its own file".into(),
            });
        }
    }
    for p in all() {
        if let Some(parent) = p.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(parent).map_err(|source| CliError::Io {
                path: parent.to_path_buf(),
                source,
            })?;
        }
    }
    Ok(())
}

/// Whether `a` and `b` name the same file: their folders made absolute with
/// `.` and `..` resolved in the text (a folder that does not exist yet, as in
/// `new/../scene.json`, cannot be resolved on disk), then links resolved
/// where the folder exists; their names compared exactly.
fn same_file_name(a: &Path, b: &Path) -> bool {
    let folder = |p: &Path| -> PathBuf {
        let dir = p.parent().filter(|d| !d.as_os_str().is_empty()).unwrap_or(Path::new("."));
        let absolute = std::path::absolute(dir).unwrap_or_else(|_| dir.to_path_buf());
        let mut plain = PathBuf::new();
        for part in absolute.components() {
            match part {
                std::path::Component::CurDir => {}
                std::path::Component::ParentDir => {
                    plain.pop();
                }
                other => plain.push(other),
            }
        }
        std::fs::canonicalize(&plain).unwrap_or(plain)
    };
    a.file_name() == b.file_name() && folder(a) == folder(b)
}

/// Refuses an output that names an input file (`--report scene.json` would
/// replace the scene).
pub fn check_not_an_input(output: &Path, input: &Path) -> Result<(), CliError> {
    if same_file_name(output, input) {
        return Err(CliError::Output {
            path: output.to_path_buf(),
            message: format!("is the input {}: give another file name", input.display()),
        });
    }
    Ok(())
}

#[derive(Parser, Debug)]
#[command(
    name = "tyndall",
    version,
    about = "Noise-free light in haze and fog: analytic height fog, fog layers, EXR layers and an error report."
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Render a scene (JSON) to a multi-layer EXR (inscatter, transmittance, depth, …) and a report.
    Render {
        /// Scene file (JSON, see docs/scene-format.md).
        scene: PathBuf,
        #[command(flatten)]
        files: OutputFiles,
        /// Relative tolerance for numerically integrated pixels (overrides output.tolerance).
        #[arg(long)]
        tolerance: Option<f64>,
        /// Worker threads, 0 = all cores (overrides output.threads).
        #[arg(long)]
        threads: Option<usize>,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Render the shipped examples (foggy valley, fog layer, a stage with four spots, dry ice) and a sky into a directory: EXR, PNG previews, reports.
    Demo {
        /// Output directory.
        #[arg(long, default_value = "tyndall-demo")]
        out_dir: PathBuf,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Render a sky as an equirectangular world texture (EXR, plain R, G, B) for
    /// Blender's World Environment Texture, with the matching sun lamp in the report.
    Sky {
        /// Sun elevation above the horizon, degrees (−90..=90; down to −6 for twilight).
        #[arg(long, allow_hyphen_values = true)]
        sun_elevation: f64,
        /// Sun direction as Blender's Sky Texture "Sun Rotation", degrees (0: sun towards +Y,
        /// increasing towards +X, clockwise seen from above).
        #[arg(long, default_value_t = 0.0, allow_hyphen_values = true)]
        sun_azimuth: f64,
        /// Sky model.
        #[arg(long, value_enum, default_value_t = SkyModelName::Atmosphere)]
        model: SkyModelName,
        /// Air (Rayleigh) density multiplier, 0..=10 (Blender's Air).
        #[arg(long, default_value_t = 1.0)]
        air: f64,
        /// Aerosol (Mie) density multiplier, 0..=10 (Blender's Dust/Aerosol).
        #[arg(long, default_value_t = 1.0)]
        aerosol: f64,
        /// Ozone density multiplier, 0..=10 (Blender's Ozone).
        #[arg(long, default_value_t = 1.0)]
        ozone: f64,
        /// Observer altitude, m, 0..=100000.
        #[arg(long, default_value_t = 0.0)]
        altitude: f64,
        /// Sun angular diameter, degrees.
        #[arg(long, default_value_t = 0.545)]
        sun_size: f64,
        /// Klassen: meteorological visibility of the haze, m (Koschmieder; 23000 is clear).
        #[arg(long, default_value_t = 23000.0)]
        visibility: f64,
        /// Klassen: top of the haze layer above the ground, m.
        #[arg(long, default_value_t = 1500.0)]
        haze_top: f64,
        /// Texture width, px (height is half).
        #[arg(long, default_value_t = 2048)]
        width: usize,
        /// Relative tolerance of the sky (per channel, relative to luminance).
        #[arg(long, default_value_t = 1e-3)]
        tolerance: f64,
        /// Leave the sun disc out of the texture (use the sun lamp).
        #[arg(long)]
        no_sun_disc: bool,
        /// Sampling: `adaptive` (default; grid with error control) or
        /// `klassen-coherence` (Klassen's baseline: every pixel, a neighbour's value
        /// reused while the first estimates differ by less than the tolerance).
        #[arg(long, value_enum, default_value_t = SkyIntegratorName::Adaptive)]
        integrator: SkyIntegratorName,
        /// Colour path at the evaluated points: `auto` (default; the model's own
        /// Rec.709 path where it has one: the atmosphere's 81-wavelength colour
        /// sums tabulated over its columns), `spectral` (81 samples converted per point).
        #[arg(long, value_enum, default_value_t = SkyColourName::Auto)]
        colour_path: SkyColourName,
        /// Atmosphere only: add the optional, approximate multiple-scattering term
        /// (isotropic second order; off by default).
        #[arg(long)]
        multiple_scattering: bool,
        #[command(flatten)]
        files: OutputFiles,
    },
    /// Print the JSON Schema of the scene format.
    Schema,
    /// Measure Mpixel/s of the height fog at a given size, with and without a 10k-triangle mesh.
    Bench {
        /// Width, px (1–16384).
        #[arg(long, default_value_t = 1920, value_parser = clap::value_parser!(u32).range(1..=16384))]
        width: u32,
        /// Height, px (1–16384).
        #[arg(long, default_value_t = 1080, value_parser = clap::value_parser!(u32).range(1..=16384))]
        height: u32,
        /// Repetitions (the best and median are reported).
        #[arg(long, default_value_t = 7)]
        repeat: usize,
        /// Worker threads, 0 = all cores (at most 1024).
        #[arg(long, default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=1024))]
        threads: u16,
    },
}

/// `println!` that ignores a closed stdout (`tyndall demo | head -1`): a
/// broken pipe is not an error of the render and must not panic.
macro_rules! say {
    ($($arg:tt)*) => {{
        use std::io::Write as _;
        let _ = writeln!(std::io::stdout(), $($arg)*);
    }};
}

/// The files a rendering command writes.
#[derive(clap::Args, Debug)]
struct OutputFiles {
    /// Output EXR file.
    #[arg(long)]
    out: PathBuf,
    /// Report file (JSON). Default: OUT with extension .report.json.
    #[arg(long)]
    report: Option<PathBuf>,
    /// Tone-mapped PNG preview.
    #[arg(long)]
    preview: Option<PathBuf>,
}

impl OutputFiles {
    fn report_path(&self) -> PathBuf {
        self.report.clone().unwrap_or_else(|| self.out.with_extension("report.json"))
    }
}

/// Sampling of the `sky` command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SkyIntegratorName {
    /// Adaptive (θ, Δφ) grid with error control, resampled (default).
    Adaptive,
    /// Klassen 1987 §4: per-pixel integrals with pixel coherence (the baseline).
    KlassenCoherence,
}

/// Colour path of the `sky` command.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum SkyColourName {
    /// The model's own Rec.709 path where it has one, else spectral (default).
    Auto,
    /// Always 81 spectral samples, converted per point.
    Spectral,
}

/// Sky models the `sky` command offers.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum SkyModelName {
    /// Layered exponential atmosphere: Rayleigh, Mie, ozone, twilight (Blender's parameters).
    Atmosphere,
    /// Klassen 1987: spherical earth, constant-density haze shell, spectral sun and sky.
    Klassen,
}

/// Shipped example scenes: (file stem, JSON).
pub const EXAMPLES: [(&str, &str); 4] = [
    ("valley_height_fog", include_str!("../../examples/valley_height_fog.json")),
    ("fog_layer_sunrise", include_str!("../../examples/fog_layer_sunrise.json")),
    ("stage_four_spots", include_str!("../../examples/stage_four_spots.json")),
    ("dry_ice_stage", include_str!("../../examples/dry_ice_stage.json")),
];

/// Runs the command line; returns the process exit code (0 ok, 1 error, 2 usage).
pub fn run<I, T>(args: I) -> i32
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    let cli = match Cli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => {
            let _ = e.print();
            return if e.use_stderr() { 2 } else { 0 };
        }
    };
    match execute(cli.command) {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("tyndall: error: {e}");
            1
        }
    }
}

fn execute(cmd: Command) -> Result<(), CliError> {
    match cmd {
        Command::Render {
            scene,
            files,
            tolerance,
            threads,
            quiet,
        } => {
            for output in [
                Some(files.out.as_path()),
                files.preview.as_deref(),
                Some(files.report_path().as_path()),
            ]
            .into_iter()
            .flatten()
            {
                check_not_an_input(output, &scene)?;
            }
            let mut s = Scene::load(&scene)?;
            if let Some(t) = tolerance {
                s.output.tolerance = t;
            }
            if let Some(n) = threads {
                s.output.threads = n;
            }
            let r = render_to_files(&s, &files.out, Some(&files.report_path()), files.preview.as_deref(), !quiet)?;
            say!("{}", summary(&r, &files.out));
            for w in &r.warnings {
                eprintln!("tyndall: warning: {w}");
            }
            Ok(())
        }
        Command::Demo { out_dir, quiet } => {
            std::fs::create_dir_all(&out_dir).map_err(|source| CliError::Io {
                path: out_dir.clone(),
                source,
            })?;
            for (stem, json) in EXAMPLES {
                let scene = Scene::from_json_str(json, &format!("examples/{stem}.json"))?;
                let exr = out_dir.join(format!("{stem}.exr"));
                let r = render_to_files(
                    &scene,
                    &exr,
                    Some(&out_dir.join(format!("{stem}.report.json"))),
                    Some(&out_dir.join(format!("{stem}.png"))),
                    !quiet,
                )?;
                say!("{}", summary(&r, &exr));
            }
            // And a sky: the layered atmosphere with a low afternoon sun, as a world texture.
            let sky = SkyChoice::Atmosphere(tyndall_core::sky::atmosphere::AtmosphereParams {
                sun_elevation_rad: 12f64.to_radians(),
                sun_rotation_rad: 200f64.to_radians(),
                ..Default::default()
            });
            let settings = tyndall_core::sky::texture::TextureSettings {
                width: 1024,
                tolerance: 1e-3,
                sun_disc: true,
            };
            let sky_exr = out_dir.join("sky_atmosphere.exr");
            let r = sky_to_files(
                &sky,
                &settings,
                &sky_exr,
                Some(&out_dir.join("sky_atmosphere.report.json")),
                Some(&out_dir.join("sky_atmosphere.png")),
            )?;
            say!(
                "{}: {}x{} sky in {:.3} s; interpolation error {:.2e}; sun lamp strength {:.1} W/m²",
                sky_exr.display(),
                r.resolution[0],
                r.resolution[1],
                r.timings.iter().map(|t| t.seconds).sum::<f64>(),
                r.interpolation_error,
                r.sun_lamp.as_ref().map(|l| l.strength_w_m2).unwrap_or(0.0)
            );
            Ok(())
        }
        Command::Sky {
            sun_elevation,
            sun_azimuth,
            model,
            air,
            aerosol,
            ozone,
            altitude,
            sun_size,
            visibility,
            haze_top,
            width,
            tolerance,
            no_sun_disc,
            integrator,
            colour_path,
            multiple_scattering,
            files,
        } => {
            let max_size_deg = match model {
                SkyModelName::Atmosphere => 90.0,
                SkyModelName::Klassen => KLASSEN_MAX_SUN_SIZE_RAD.to_degrees(),
            };
            check_sky_angles(sun_elevation, sun_azimuth, sun_size, max_size_deg).map_err(|(path, message)| {
                // (The flags' names, not the Python keywords.)
                let flag = match path.as_str() {
                    "sun_elevation_deg" => "--sun-elevation",
                    "sun_rotation_deg" => "--sun-azimuth",
                    "sun_size_deg" => "--sun-size",
                    other => other,
                };
                CliError::Scene(SceneError {
                    source_name: "sky parameters".into(),
                    path: flag.into(),
                    message,
                })
            })?;
            let sky = match model {
                SkyModelName::Atmosphere => SkyChoice::Atmosphere(tyndall_core::sky::atmosphere::AtmosphereParams {
                    air_density: air,
                    aerosol_density: aerosol,
                    ozone_density: ozone,
                    altitude_m: altitude,
                    sun_elevation_rad: sun_elevation.to_radians(),
                    sun_rotation_rad: sun_azimuth.to_radians(),
                    sun_size_rad: sun_size.to_radians(),
                    ..Default::default()
                }),
                SkyModelName::Klassen => SkyChoice::Klassen {
                    params: tyndall_core::sky::klassen::KlassenParams {
                        visibility_m: visibility,
                        haze_top_m: haze_top,
                        observer_altitude_m: altitude,
                        ..Default::default()
                    },
                    sun_elevation_rad: sun_elevation.to_radians(),
                    sun_rotation_rad: sun_azimuth.to_radians(),
                    sun_size_rad: sun_size.to_radians(),
                },
            };
            let settings = tyndall_core::sky::texture::TextureSettings {
                width,
                tolerance,
                sun_disc: !no_sun_disc,
            };
            let options = SkyOptions {
                build: tyndall_core::sky::texture::BuildOptions {
                    colour: match colour_path {
                        SkyColourName::Auto => tyndall_core::sky::texture::ColourPath::Auto,
                        SkyColourName::Spectral => tyndall_core::sky::texture::ColourPath::Spectral,
                    },
                    integrator: match integrator {
                        SkyIntegratorName::Adaptive => tyndall_core::sky::texture::Integrator::Adaptive,
                        SkyIntegratorName::KlassenCoherence => {
                            tyndall_core::sky::texture::Integrator::KlassenCoherence { threshold: tolerance }
                        }
                    },
                },
                multiple_scattering,
            };
            let r = sky_to_files_with(
                &sky,
                &settings,
                &options,
                &files.out,
                Some(&files.report_path()),
                files.preview.as_deref(),
            )?;
            let out = &files.out;
            say!(
                "{}: {}x{} sky in {:.3} s; {} evaluations, interpolation error {:.2e} (tolerance {:.1e}); sun lamp strength {:.3} W/m², colour {:?}",
                out.display(),
                r.resolution[0],
                r.resolution[1],
                r.timings.iter().map(|t| t.seconds).sum::<f64>(),
                r.evaluations,
                r.interpolation_error,
                r.tolerance,
                r.sun_lamp.as_ref().map(|l| l.strength_w_m2).unwrap_or(0.0),
                r.sun_lamp
                    .as_ref()
                    .map(|l| l.color.map(|c| (c * 1000.0).round() / 1000.0))
                    .unwrap_or([0.0; 3])
            );
            Ok(())
        }
        Command::Schema => {
            say!("{}", tyndall_core::scene::json_schema());
            Ok(())
        }
        Command::Bench {
            width,
            height,
            repeat,
            threads,
        } => {
            let cases = [
                ("height fog, no geometry, point samples", false, false),
                ("height fog, no geometry, Blender pixel filter", false, true),
                ("height fog, 10k-triangle mesh, point samples", true, false),
                ("height fog, 10k-triangle mesh, Blender pixel filter", true, true),
            ];
            for (label, mesh, filtered) in cases {
                let mut scene = tyndall_core::bench_scenes::height_fog(width, height, threads.into(), mesh)?;
                if !filtered {
                    scene.output.pixel_filter = tyndall_core::scene::PixelFilter::None;
                }
                let mut times = Vec::new();
                let mut stages = String::new();
                for _ in 0..repeat.max(1) {
                    // Wall time of the whole call: plan, BVH build, render and pixel filter.
                    let t = Instant::now();
                    let (_, rep) = tyndall_core::render(&scene, None)?;
                    let wall = t.elapsed().as_secs_f64();
                    if times.iter().all(|b| wall < *b) {
                        stages = rep
                            .timings
                            .iter()
                            .map(|t| format!("{} {:.1} ms", t.stage, t.seconds * 1e3))
                            .collect::<Vec<_>>()
                            .join(", ");
                    }
                    times.push(wall);
                }
                times.sort_by(f64::total_cmp);
                let mpix = (width as f64 * height as f64) / 1e6;
                say!(
                    "{label}: {width}x{height}, best {:.1} ms ({:.1} Mpixel/s), median {:.1} ms ({:.1} Mpixel/s), {} threads",
                    times[0] * 1e3,
                    mpix / times[0],
                    times[times.len() / 2] * 1e3,
                    mpix / times[times.len() / 2],
                    if threads == 0 {
                        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
                    } else {
                        usize::from(threads)
                    }
                );
                say!("  best run: {stages}");
            }
            Ok(())
        }
    }
}

fn summary(r: &Report, out: &Path) -> String {
    let total: f64 = r.timings.iter().map(|t| t.seconds).sum();
    format!(
        "{}: {}x{} in {:.3} s; error estimate max {:.3e} abs, {:.3e} rel ({:.3e} rel at filtered edges); {} pixels not converged; {} items left out{}",
        out.display(),
        r.resolution[0],
        r.resolution[1],
        total,
        r.error.max_abs,
        r.error.max_rel,
        r.error.edge_max_rel,
        r.error.pixels_not_converged + r.error.edge_pixels_not_converged,
        r.plan.left_out.len(),
        if r.warnings.is_empty() {
            String::new()
        } else {
            format!("; {} warnings", r.warnings.len())
        }
    )
}

/// Renders `scene`, writes the EXR (and report, preview), returns the report
/// (with the write times added). Files are written atomically.
pub fn render_to_files(
    scene: &Scene,
    out: &Path,
    report_path: Option<&Path>,
    preview: Option<&Path>,
    progress: bool,
) -> Result<Report, CliError> {
    render_to_files_cancellable(scene, out, report_path, preview, progress, None)
}

/// [`render_to_files`] that stops once another thread sets `cancel` (see
/// [`tyndall_core::render_cancellable`]): nothing is written if it is set
/// before the images are complete; set while writing, the files not yet
/// started are not written (each file is written atomically, so none is torn).
pub fn render_to_files_cancellable(
    scene: &Scene,
    out: &Path,
    report_path: Option<&Path>,
    preview: Option<&Path>,
    progress: bool,
    cancel: Option<&std::sync::atomic::AtomicBool>,
) -> Result<Report, CliError> {
    let bar = progress.then(progress_bar);
    let cb = |stage: tyndall_core::RenderStage, done: usize, total: usize| {
        if let Some(b) = &bar {
            b.set_message(stage.label());
            b.set_length(total as u64);
            b.set_position(done as u64);
        }
    };
    let shown: Option<tyndall_core::render::Progress<'_>> = bar.is_some().then_some(&cb);
    let result = render_to_files_reporting(scene, out, report_path, preview, shown, cancel);
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    result
}

/// [`render_to_files_cancellable`] with any progress callback (rows, then the
/// pixel filter's pixels; [`tyndall_core::RenderStage`]) instead of the bar.
pub fn render_to_files_reporting(
    scene: &Scene,
    out: &Path,
    report_path: Option<&Path>,
    preview: Option<&Path>,
    progress: Option<tyndall_core::render::Progress<'_>>,
    cancel: Option<&std::sync::atomic::AtomicBool>,
) -> Result<Report, CliError> {
    prepare_outputs(out, preview, report_path)?;
    let (images, mut report) = tyndall_core::render_cancellable(scene, progress, cancel)?;
    // A cancel that came after the last ray: still nothing is written.
    let cancelled = || cancel.is_some_and(|c| c.load(std::sync::atomic::Ordering::Relaxed));
    if cancelled() {
        return Err(tyndall_core::RenderError::Cancelled.into());
    }
    report.resolution = [images.width, images.height];
    let t = Instant::now();
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| CliError::Io {
            path: parent.to_path_buf(),
            source,
        })?;
    }
    io::write_layer_refs_exr(out, images.width, images.height, &images.exr_layer_refs())?;
    let t = report.time("write_exr", t);
    if let Some(p) = preview {
        if cancelled() {
            return Err(tyndall_core::RenderError::Cancelled.into());
        }
        let rgb = preview_image(&images);
        let stops = io::auto_exposure(&rgb);
        let bad = io::write_png_preview(p, images.width, images.height, &rgb, stops)?;
        if bad > 0 {
            report.warnings.push(format!("{bad} non-finite pixels in the preview"));
        }
        report.time("write_preview", t);
    }
    if let Some(rp) = report_path {
        if cancelled() {
            return Err(tyndall_core::RenderError::Cancelled.into());
        }
        write_atomic(rp, report.to_json().as_bytes())?;
    }
    Ok(report)
}

/// A sky model with its parameters, as the `sky` command builds it.
#[derive(Debug, Clone)]
pub enum SkyChoice {
    /// The layered atmosphere (its parameters include the sun).
    Atmosphere(tyndall_core::sky::atmosphere::AtmosphereParams),
    /// Klassen's model and the sun.
    Klassen {
        /// Model parameters.
        params: tyndall_core::sky::klassen::KlassenParams,
        /// Sun elevation, rad.
        sun_elevation_rad: f64,
        /// Blender's Sun Rotation, rad.
        sun_rotation_rad: f64,
        /// Sun angular diameter, rad.
        sun_size_rad: f64,
    },
}

/// The largest sun disc Klassen's model takes, rad (5.73°).
pub const KLASSEN_MAX_SUN_SIZE_RAD: f64 = 0.1;

/// The sun's angles as the user gives them, in degrees (`sun_elevation_deg`,
/// `sun_rotation_deg`, `sun_size_deg`, the Python keywords; the CLI's
/// `--sun-elevation`, `--sun-azimuth`, `--sun-size`): `Err((keyword, message))`
/// in those terms, before they become the models' radians.
pub fn check_sky_angles(elevation_deg: f64, rotation_deg: f64, size_deg: f64, max_size_deg: f64) -> Result<(), (String, String)> {
    for (name, v, lo, hi) in [
        ("sun_elevation_deg", elevation_deg, -90.0, 90.0),
        ("sun_rotation_deg", rotation_deg, -1e4, 1e4),
        ("sun_size_deg", size_deg, 0.0, max_size_deg),
    ] {
        if !v.is_finite() || v < lo || v > hi {
            let hi = if hi.fract() == 0.0 { format!("{hi}") } else { format!("{hi:.4}") };
            return Err((name.into(), format!("must be within {lo}..={hi} degrees, got {v}")));
        }
    }
    Ok(())
}

/// The Python keyword (and CLI flag) for a field of the atmosphere's parameters.
pub fn sky_keyword(field: &str) -> String {
    match field {
        "air_density" => "air",
        "aerosol_density" => "aerosol",
        "ozone_density" => "ozone",
        other => other,
    }
    .into()
}

/// Memory for a sky texture `width` px wide (RGB f32, height width/2): `Err`
/// (naming `width`) where the machine cannot allocate it, before any work
/// (65536 px wide needs 25.8 GB and aborted the process).
pub fn check_sky_memory(width: usize) -> Result<(), (String, String)> {
    let bytes = (width as u64) * (width as u64 / 2).max(1) * 12;
    if tyndall_core::render::can_allocate(bytes) {
        Ok(())
    } else {
        Err((
            "width".into(),
            format!(
                "a {width} px wide sky needs {:.1} GB for its pixels, more than this machine can allocate",
                bytes as f64 / 1e9
            ),
        ))
    }
}

/// Renders a sky world texture and writes the EXR (plain R, G, B), the report
/// and optionally a preview; returns the report. Invalid parameters are an error
/// naming the field.
pub fn sky_to_files(
    sky: &SkyChoice,
    settings: &tyndall_core::sky::texture::TextureSettings,
    out: &Path,
    report_path: Option<&Path>,
    preview: Option<&Path>,
) -> Result<tyndall_core::sky::SkyReport, CliError> {
    sky_to_files_with(sky, settings, &SkyOptions::default(), out, report_path, preview)
}

/// Options of [`sky_to_files_with`] beyond the texture settings.
#[derive(Debug, Clone, Copy, Default)]
pub struct SkyOptions {
    /// Colour path and sampling (defaults: auto, adaptive).
    pub build: tyndall_core::sky::texture::BuildOptions,
    /// Atmosphere only: add the approximate multiple-scattering term (default off;
    /// an error for Klassen's model, which has none).
    pub multiple_scattering: bool,
}

/// [`sky_to_files`] with [`SkyOptions`].
pub fn sky_to_files_with(
    sky: &SkyChoice,
    settings: &tyndall_core::sky::texture::TextureSettings,
    options: &SkyOptions,
    out: &Path,
    report_path: Option<&Path>,
    preview: Option<&Path>,
) -> Result<tyndall_core::sky::SkyReport, CliError> {
    let bad = |path: String, message: String| {
        CliError::Scene(SceneError {
            source_name: "sky parameters".into(),
            path,
            message,
        })
    };
    let klassen_world;
    let with_ms;
    let (model, name): (&dyn tyndall_core::sky::texture::SkyModel, &str) = match sky {
        SkyChoice::Atmosphere(p) => {
            p.validate().map_err(|(path, message)| bad(sky_keyword(&path), message))?;
            if options.multiple_scattering {
                with_ms = tyndall_core::sky::atmosphere::AtmosphereWithMultipleScattering::new(*p, 1e-3);
                (&with_ms, "atmosphere")
            } else {
                (p, "atmosphere")
            }
        }
        SkyChoice::Klassen {
            params,
            sun_elevation_rad,
            sun_rotation_rad,
            sun_size_rad,
        } => {
            for (field, v, lo, hi) in [
                (
                    "sun_elevation_rad",
                    *sun_elevation_rad,
                    -std::f64::consts::FRAC_PI_2,
                    std::f64::consts::FRAC_PI_2,
                ),
                ("sun_rotation_rad", *sun_rotation_rad, -1e3, 1e3),
                ("sun_size_rad", *sun_size_rad, 0.0, KLASSEN_MAX_SUN_SIZE_RAD),
            ] {
                if !(v.is_finite() && (lo..=hi).contains(&v)) {
                    return Err(bad(field.into(), format!("{v} is outside {lo}..={hi}")));
                }
            }
            let k = tyndall_core::sky::klassen::KlassenSky::new(*params).map_err(|(path, message)| bad(path.into(), message))?;
            klassen_world = tyndall_core::sky::klassen::KlassenWorld {
                sky: k,
                sun: tyndall_core::sky::blender_sun_direction(*sun_elevation_rad, *sun_rotation_rad),
                sun_diameter_rad: *sun_size_rad,
            };
            if options.multiple_scattering {
                return Err(bad(
                    "multiple_scattering".into(),
                    "the multiple-scattering approximation exists for the atmosphere model only".into(),
                ));
            }
            (&klassen_world, "klassen")
        }
    };
    if !(1e-6..=0.5).contains(&settings.tolerance) || settings.width < 2 || settings.width > 65536 {
        return Err(CliError::Scene(SceneError {
            source_name: "sky parameters".into(),
            path: if settings.width < 2 || settings.width > 65536 {
                "width".into()
            } else {
                "tolerance".into()
            },
            message: format!(
                "width must be 2..=65536 and tolerance 1e-6..=0.5, got {} and {}",
                settings.width, settings.tolerance
            ),
        }));
    }
    check_sky_memory(settings.width).map_err(|(path, message)| bad(path, message))?;
    prepare_outputs(out, preview, report_path)?;
    let (tex, mut report) = tyndall_core::sky::render_world_with(model, name, settings, &options.build);
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| CliError::Io {
            path: parent.to_path_buf(),
            source,
        })?;
    }
    let t = Instant::now();
    io::write_rgb_exr(out, tex.width, tex.height, &tex.rgb)?;
    report.timings.push(tyndall_core::report::Timing {
        stage: "write_exr".into(),
        seconds: t.elapsed().as_secs_f64(),
    });
    if let Some(p) = preview {
        let stops = io::auto_exposure(&tex.rgb);
        io::write_png_preview(p, tex.width, tex.height, &tex.rgb, stops)?;
    }
    if let Some(rp) = report_path {
        write_atomic(rp, tyndall_core::report::to_json_string(&report).as_bytes())?;
    }
    Ok(report)
}

/// The preview composite: grey surfaces (radiance 0.05 per channel, where a
/// view ray hits a mesh) seen through the medium, `0.05·T + L`; sky pixels `L`.
/// Without the depth layer there are no surfaces to show (`L` alone); without
/// the transmittance layer, `T = 1`.
pub fn preview_image(images: &Images) -> Vec<[f32; 3]> {
    let n = images.inscatter.len();
    let full_t = images.transmittance.len() == n;
    let full_d = images.depth.len() == n;
    images
        .inscatter
        .iter()
        .enumerate()
        .map(|(i, l)| {
            let t = if full_t { images.transmittance[i] } else { [1.0; 3] };
            let d = if full_d {
                images.depth[i]
            } else {
                tyndall_core::render::DEPTH_NO_HIT
            };
            let s = if d < tyndall_core::render::DEPTH_NO_HIT { 0.05 } else { 0.0 };
            [s * t[0] + l[0], s * t[1] + l[1], s * t[2] + l[2]]
        })
        .collect()
}

fn progress_bar() -> ProgressBar {
    let b = ProgressBar::new(1);
    b.set_style(
        ProgressStyle::with_template("{spinner} {msg:14} {bar:40} {pos}/{len} {elapsed_precise}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    b
}

/// Writes `bytes` to `path` through a temporary file and a rename (the
/// image writer's: a short temporary name however long `path`'s is).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), CliError> {
    use std::io::Write;
    io::write_atomically(path, |file| file.write_all(bytes).map_err(|e| ImageIoError::io(path, e)))?;
    Ok(())
}
