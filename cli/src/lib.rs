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
        /// Output EXR file.
        #[arg(long)]
        out: PathBuf,
        /// Report file (JSON). Default: OUT with extension .report.json.
        #[arg(long)]
        report: Option<PathBuf>,
        /// Tone-mapped PNG preview of the in-scatter over grey surfaces.
        #[arg(long)]
        preview: Option<PathBuf>,
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
    /// Render the shipped foggy examples into a directory: EXR, PNG previews, reports.
    Demo {
        /// Output directory.
        #[arg(long, default_value = "tyndall-demo")]
        out_dir: PathBuf,
        /// No progress bar.
        #[arg(long)]
        quiet: bool,
    },
    /// Print the JSON Schema of the scene format.
    Schema,
    /// Measure Mpixel/s of the height fog at a given size, with and without a 10k-triangle mesh.
    Bench {
        /// Width, px.
        #[arg(long, default_value_t = 1920)]
        width: u32,
        /// Height, px.
        #[arg(long, default_value_t = 1080)]
        height: u32,
        /// Repetitions (the best and median are reported).
        #[arg(long, default_value_t = 7)]
        repeat: usize,
        /// Worker threads, 0 = all cores.
        #[arg(long, default_value_t = 0)]
        threads: usize,
    },
}

/// Shipped example scenes: (file stem, JSON).
pub const EXAMPLES: [(&str, &str); 2] = [
    ("valley_height_fog", include_str!("../../examples/valley_height_fog.json")),
    ("fog_layer_sunrise", include_str!("../../examples/fog_layer_sunrise.json")),
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
            out,
            report,
            preview,
            tolerance,
            threads,
            quiet,
        } => {
            let mut s = Scene::load(&scene)?;
            if let Some(t) = tolerance {
                s.output.tolerance = t;
            }
            if let Some(n) = threads {
                s.output.threads = n;
            }
            let report_path = report.unwrap_or_else(|| out.with_extension("report.json"));
            let r = render_to_files(&s, &out, Some(&report_path), preview.as_deref(), !quiet)?;
            println!("{}", summary(&r, &out));
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
                println!("{}", summary(&r, &exr));
            }
            Ok(())
        }
        Command::Schema => {
            println!("{}", tyndall_core::scene::json_schema());
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
                let mut scene = tyndall_core::bench_scenes::height_fog(width, height, threads, mesh);
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
                println!(
                    "{label}: {width}x{height}, best {:.1} ms ({:.1} Mpixel/s), median {:.1} ms ({:.1} Mpixel/s), {} threads",
                    times[0] * 1e3,
                    mpix / times[0],
                    times[times.len() / 2] * 1e3,
                    mpix / times[times.len() / 2],
                    if threads == 0 {
                        std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
                    } else {
                        threads
                    }
                );
                println!("  best run: {stages}");
            }
            Ok(())
        }
    }
}

fn summary(r: &Report, out: &Path) -> String {
    let total: f64 = r.timings.iter().map(|t| t.seconds).sum();
    format!(
        "{}: {}x{} in {:.3} s; error estimate max {:.3e} abs, {:.3e} rel; {} items left out",
        out.display(),
        r.resolution[0],
        r.resolution[1],
        total,
        r.error.max_abs,
        r.error.max_rel,
        r.plan.left_out.len()
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
    let bar = if progress { Some(progress_bar()) } else { None };
    let cb = |done: usize, total: usize| {
        if let Some(b) = &bar {
            b.set_length(total as u64);
            b.set_position(done as u64);
        }
    };
    let (images, mut report) = tyndall_core::render(scene, Some(&cb))?;
    if let Some(b) = &bar {
        b.finish_and_clear();
    }
    report.resolution = [images.width, images.height];
    let t = Instant::now();
    if let Some(parent) = out.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent).map_err(|source| CliError::Io {
            path: parent.to_path_buf(),
            source,
        })?;
    }
    io::write_layers_exr(out, images.width, images.height, &images.exr_layers())?;
    let t = report.time("write_exr", t);
    if let Some(p) = preview {
        let rgb = preview_image(&images);
        let stops = io::auto_exposure(&rgb);
        let bad = io::write_png_preview(p, images.width, images.height, &rgb, stops)?;
        if bad > 0 {
            report.warnings.push(format!("{bad} non-finite pixels in the preview"));
        }
        report.time("write_preview", t);
    }
    if let Some(rp) = report_path {
        write_atomic(rp, report.to_json().as_bytes())?;
    }
    Ok(report)
}

/// The preview composite: grey surfaces (radiance 0.05 per channel, where a
/// view ray hits a mesh) seen through the medium, `0.05·T + L`; sky pixels `L`.
pub fn preview_image(images: &Images) -> Vec<[f32; 3]> {
    images
        .inscatter
        .iter()
        .zip(&images.transmittance)
        .zip(&images.depth)
        .map(|((l, t), d)| {
            let s = if *d < tyndall_core::render::DEPTH_NO_HIT { 0.05 } else { 0.0 };
            [s * t[0] + l[0], s * t[1] + l[1], s * t[2] + l[2]]
        })
        .collect()
}

fn progress_bar() -> ProgressBar {
    let b = ProgressBar::new(1);
    b.set_style(
        ProgressStyle::with_template("{spinner} rendering rows {bar:40} {pos}/{len} {elapsed_precise}")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    b
}

/// Writes `bytes` to `path` through a temporary file and a rename.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), CliError> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let tmp = dir.join(format!(
        ".{}.{}.tmp",
        path.file_name().and_then(|n| n.to_str()).unwrap_or("out"),
        std::process::id()
    ));
    std::fs::write(&tmp, bytes).map_err(|source| CliError::Io { path: tmp.clone(), source })?;
    std::fs::rename(&tmp, path).map_err(|source| {
        let _ = std::fs::remove_file(&tmp);
        CliError::Io {
            path: path.to_path_buf(),
            source,
        }
    })
}
