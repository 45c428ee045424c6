//! Rendering for a camera: plan, then per pixel the first surface (BVH), then
//! the medium's transmittance `T` and in-scattered radiance `L` along the view
//! ray, so that `final = surface × T + L`.
//!
//! **Plan.** The scene is reduced to what it needs: the colour path (RGB when
//! every medium is wavelength-independent or given per RGB channel; spectral,
//! 81 samples, only when some medium is given spectrally and depends on
//! wavelength), the lights that contribute, the media that are non-zero. Each
//! decision is written into the report's plan, with the reason for what was
//! left out.
//!
//! **Per pixel.** A view ray that crosses no medium evaluates no integral. A
//! ray crossing one medium uses that medium's closed form. A ray crossing
//! several overlapping media is integrated numerically, `L = ∫ Σ_m S_m(s)
//! e^{−Σ_m τ_m(s)} ds` with closed-form optical depths, by adaptive
//! Gauss–Kronrod to the requested relative tolerance, with the estimate
//! reported per pixel (`error` layer) and summarised in the report.
//!
//! Rows are rendered in parallel with rayon; a progress callback is called as
//! rows finish.

pub mod filter;
mod profile;
pub mod smooth;
pub mod stage;
pub mod unlit;

use crate::geometry::bvh::{Bvh, Triangle};
use crate::geometry::camera::CameraRays;
use crate::geometry::world_triangles;
use crate::io::{ChannelSamples, ImageLayer, LayerRef};
use crate::medium;
use crate::medium::ellipsoid::Ellipsoid;
use crate::medium::fog_layer::FogLayer;
use crate::medium::height_field_layer::{HeightFieldLayer, Side, Wave};
use crate::medium::height_fog::HeightFog;
use crate::medium::homogeneous::{Homogeneous, MediumBox};
use crate::medium::phase::PhaseFunction;
use crate::medium::{LightSet, PreparedMedium, RayResult, SunSource, ViewRay};
use crate::numeric::integrate_adaptive;
use crate::report::Report;
use crate::scene::Mesh;
use crate::scene::{
    AmbientLight, Bounds, Coefficient, EllipsoidMedium, FogLayerMedium, HeightFogMedium, HomogeneousMedium, LayerKind,
    LayeredHeightFieldMedium, Light, LightSpectrum, Medium, Scene, SpectralMode, SunLight,
};
use crate::spectrum::{self, SPECTRAL_SAMPLES};
use glam::DVec3;
use rayon::prelude::*;
use std::borrow::Cow;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::Instant;

/// Depth written where a view ray meets no surface (Blender's convention).
pub const DEPTH_NO_HIT: f32 = 1e10;

/// Why a render could not run.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// The scene is invalid (field path and message).
    #[error("invalid scene: {0}: {1}")]
    InvalidScene(String, String),
    /// A layer holds values that are not finite in f32 storage.
    #[error("the {layer} layer has {pixels} pixels that are not finite (NaN or ∞) in 32-bit storage: {hint}")]
    NonFinite {
        /// Layer name.
        layer: String,
        /// Pixels with a non-finite channel.
        pixels: usize,
        /// What is likely the cause.
        hint: String,
    },
    /// Another thread asked the render to stop ([`render_cancellable`]).
    #[error("the render was cancelled")]
    Cancelled,
    /// The thread pool could not be built.
    #[error("cannot start {threads} worker threads: {message}")]
    Threads {
        /// Requested threads.
        threads: usize,
        /// The reason.
        message: String,
    },
}

/// The rendered images, row 0 at the top, `width × height` pixels each.
#[derive(Debug, Clone, Default)]
pub struct Images {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// In-scattered radiance, W·m⁻²·sr⁻¹, linear Rec.709.
    pub inscatter: Vec<[f32; 3]>,
    /// View transmittance, 0..1; empty unless a layer made from it is requested.
    pub transmittance: Vec<[f32; 3]>,
    /// Distance to the first surface, m; [`DEPTH_NO_HIT`] where none; empty
    /// unless the depth layer is requested.
    pub depth: Vec<f32>,
    /// Sunlight transmittance at the surface point (1 without surface).
    pub sun_transmittance: Vec<[f32; 3]>,
    /// Absolute error estimate of `inscatter`.
    pub error: Vec<[f32; 3]>,
    /// The layers requested, in order.
    pub layers: Vec<LayerKind>,
    /// Per stage light (point, spot, window), its in-scatter; empty unless
    /// `inscatter_per_light` was requested.
    pub light_inscatter: Vec<Vec<[f32; 3]>>,
    /// EXR layer names of `light_inscatter` (`inscatter.<light name>`).
    pub light_layer_names: Vec<String>,
    /// Per stage light, the medium transmittance of its direct light via the
    /// visible surface to the camera (see [`LayerKind::SurfaceTransmittancePerLight`]);
    /// empty unless `surface_transmittance_per_light` was requested.
    pub light_surface_transmittance: Vec<Vec<[f32; 3]>>,
    /// EXR layer names of `light_surface_transmittance` (`surface_transmittance.<light name>`).
    pub surface_layer_names: Vec<String>,
}

/// A layer of RGB pixels as three borrowed channels.
fn rgb_layer<'a>(name: &'a str, px: &'a [[f32; 3]]) -> LayerRef<'a> {
    LayerRef {
        name,
        channels: ["R", "G", "B"]
            .into_iter()
            .enumerate()
            .map(|(c, n)| (n, ChannelSamples::Rgb(px, c)))
            .collect(),
    }
}

impl Images {
    /// The requested layers as EXR layers (`inscatter.R`, …, `depth.Z`),
    /// borrowed from the images (what [`crate::io::write_layer_refs_exr`] writes).
    pub fn exr_layer_refs(&self) -> Vec<LayerRef<'_>> {
        let mut out = Vec::new();
        for k in &self.layers {
            if *k == LayerKind::InscatterPerLight {
                for (name, px) in self.light_layer_names.iter().zip(&self.light_inscatter) {
                    out.push(rgb_layer(name, px));
                }
                continue;
            }
            if *k == LayerKind::SurfaceTransmittancePerLight {
                for (name, px) in self.surface_layer_names.iter().zip(&self.light_surface_transmittance) {
                    out.push(rgb_layer(name, px));
                }
                continue;
            }
            out.push(match k {
                LayerKind::Inscatter => rgb_layer("inscatter", &self.inscatter),
                LayerKind::Transmittance => rgb_layer("transmittance", &self.transmittance),
                LayerKind::SunTransmittance => rgb_layer("sun_transmittance", &self.sun_transmittance),
                LayerKind::Error => rgb_layer("error", &self.error),
                LayerKind::Depth => LayerRef {
                    name: "depth",
                    channels: vec![("Z", ChannelSamples::Plane(&self.depth))],
                },
                LayerKind::InscatterPerLight | LayerKind::SurfaceTransmittancePerLight => unreachable!("handled above"),
            });
        }
        out
    }

    /// The requested layers as owned EXR layers (copies of [`Self::exr_layer_refs`]).
    pub fn exr_layers(&self) -> Vec<ImageLayer> {
        self.exr_layer_refs()
            .into_iter()
            .map(|l| ImageLayer {
                name: l.name.to_owned(),
                channels: l
                    .channels
                    .into_iter()
                    .map(|(n, v)| {
                        let samples = match v {
                            ChannelSamples::Plane(p) => p.to_vec(),
                            ChannelSamples::Rgb(px, c) => px.iter().map(|p| p[c]).collect(),
                        };
                        (n.to_owned(), samples)
                    })
                    .collect(),
            })
            .collect()
    }
}

/// What a render reports progress on, in this order.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RenderStage {
    /// The image's rows of centre samples (`done` and `total` count rows).
    Rows,
    /// The pixels integrated against the pixel filter (`done` and `total`
    /// count pixels; they come in tiles, and where the filter is used it is
    /// most of the time: 8.0 of 8.2 s for the demo stage at 640×360, 1e-3, in
    /// the fifteenth session's measurement).
    PixelFilter,
}

impl RenderStage {
    /// A short label: "rendering rows", "pixel filter".
    pub fn label(self) -> &'static str {
        match self {
            RenderStage::Rows => "rendering rows",
            RenderStage::PixelFilter => "pixel filter",
        }
    }
}

/// Progress callback: `(stage, done, total)`; called from worker threads,
/// one call at a time and in order (`done` rises to `total` in each stage).
pub type Progress<'a> = &'a (dyn Fn(RenderStage, usize, usize) + Sync);

/// Renders a validated scene.
pub fn render(scene: &Scene, progress: Option<Progress<'_>>) -> Result<(Images, Report), RenderError> {
    render_cancellable(scene, progress, None)
}

/// [`render`] that stops early once another thread sets `cancel`: every
/// ray not yet started is skipped (a ray already under way finishes, so the
/// delay is about one ray's time, ms for stage lights in haze), and the
/// result is [`RenderError::Cancelled`], never a partial image. The
/// preparation asks too: between chunks of 65 536 triangles while surfaces
/// are grouped by plane, before each split of 16 384 or more in the BVH
/// build, and before each light's shadow casters (720 000 triangles: ≤ 0.04 s
/// after the flag, of ≈ 0.8 s; one light's casters are not split further).
pub fn render_cancellable(
    scene: &Scene,
    progress: Option<Progress<'_>>,
    cancel: Option<&AtomicBool>,
) -> Result<(Images, Report), RenderError> {
    scene.validate().map_err(|(p, m)| RenderError::InvalidScene(p, m))?;
    let cancelled = || cancel.is_some_and(|c| c.load(Ordering::Relaxed));
    check_memory(scene)?;
    let threads = scene.output.threads;
    let run = || {
        let mut report = Report {
            tyndall_version: crate::VERSION.into(),
            ..Default::default()
        };
        let spectral = needs_spectral(scene, &mut report);
        // Per-light slots in every sample only when per-light layers are
        // output: a sample without them is 190 instead of 950 bytes, and the
        // pixel filter's lattice stores and sums tens of thousands of them
        // (96×54 narrow beam, tolerance 0.05: its time 13.6 → 12.4 ms).
        let per_light = [LayerKind::InscatterPerLight, LayerKind::SurfaceTransmittancePerLight]
            .iter()
            .any(|k| scene.output.layers.contains(k));
        const K: usize = stage::MAX_LIGHT_LAYERS;
        let images = match (spectral, per_light) {
            (true, true) => render_channels::<SPECTRAL_SAMPLES, K>(scene, &mut report, progress, cancel),
            (true, false) => render_channels::<SPECTRAL_SAMPLES, 0>(scene, &mut report, progress, cancel),
            (false, true) => render_channels::<3, K>(scene, &mut report, progress, cancel),
            (false, false) => render_channels::<3, 0>(scene, &mut report, progress, cancel),
        }?;
        if cancelled() {
            return Err(RenderError::Cancelled);
        }
        report.stats.threads = rayon::current_num_threads();
        check_finite(&images, &report)?;
        // Spectra outside the Rec.709 gamut convert to negative channels
        // (a scattering coefficient ∝ λ^±20 concentrates the light at one end
        // of the spectrum); they are kept, not clamped, and counted.
        let negative = images.inscatter.iter().filter(|p| p.iter().any(|v| *v < 0.0)).count();
        if negative > 0 {
            report.warnings.push(if spectral {
                format!(
                    "{negative} pixels have a negative in-scatter channel: their spectrum lies outside the Rec.709 gamut (kept as computed, not clamped)"
                )
            } else {
                format!("{negative} pixels have a negative in-scatter channel in the RGB path: this is a bug, please report the scene")
            });
        }
        Ok((images, report))
    };
    if threads == 0 {
        return run();
    }
    worker_pool(threads)?.install(run)
}

/// The worker pool of `threads` threads, built once per process and reused.
/// Building one spawns its threads: reusing the pool cut the time outside
/// the render's stages from ≈ 0.12 to ≈ 0.06 ms on the 2-core machine
/// (96×54 narrow beam, two threads, ≈ 2 % of the render). A few sizes are kept (a
/// pipeline asking for many different counts drops the older pools, whose
/// threads end once no render uses them).
fn worker_pool(threads: usize) -> Result<Arc<rayon::ThreadPool>, RenderError> {
    const KEPT: usize = 4;
    type Pools = Vec<(usize, Arc<rayon::ThreadPool>)>;
    static POOLS: OnceLock<Mutex<Pools>> = OnceLock::new();
    let mut pools = POOLS
        .get_or_init(|| Mutex::new(Vec::new()))
        .lock()
        .unwrap_or_else(|e| e.into_inner());
    if let Some((_, pool)) = pools.iter().find(|(n, _)| *n == threads) {
        return Ok(Arc::clone(pool));
    }
    let pool = Arc::new(
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("tyndall-worker-{i}"))
            .build()
            .map_err(|e| RenderError::Threads {
                threads,
                message: e.to_string(),
            })?,
    );
    if pools.len() >= KEPT {
        pools.remove(0);
    }
    pools.push((threads, Arc::clone(&pool)));
    Ok(pool)
}

/// `work` on every item, results in the items' order; the workers take the
/// items in that order from one queue, each with its own state from `init`.
/// Rayon's splitting of an indexed range does not keep the order, and with
/// a few uneven tiles sorted longest first that order is the schedule. The
/// lattice needs it (box occluder at 192×108, its light's tile first: 9.8 ms
/// as split by rayon, 7.6–8.0 ms from the queue); for the narrow beam's
/// profile tiles at 96×54 (0.33 ms for the largest of eight, 0.89 ms in
/// all) the queue's gain was within the noise.
pub(crate) fn queued<T: Sync, S, R: Send>(items: &[T], init: impl Fn() -> S + Sync, work: impl Fn(&mut S, &T) -> R + Sync) -> Vec<R> {
    let next = std::sync::atomic::AtomicUsize::new(0);
    let workers = rayon::current_num_threads().clamp(1, items.len().max(1));
    let done: Vec<Vec<(usize, R)>> = (0..workers)
        .into_par_iter()
        .map(|_| {
            let mut state = init();
            let mut out = Vec::new();
            loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some(item) = items.get(i) else { break };
                out.push((i, work(&mut state, item)));
            }
            out
        })
        .collect();
    let mut slots: Vec<Option<R>> = std::iter::repeat_with(|| None).take(items.len()).collect();
    for (i, r) in done.into_iter().flatten() {
        slots[i] = Some(r);
    }
    slots.into_iter().flatten().collect()
}

/// Bytes per pixel a render holds at least: the in-scatter, transmittance,
/// sun transmittance and error layers and per stage light two more (RGB f32,
/// 12 bytes each), depth, and the pixel's working data.
fn bytes_per_pixel(scene: &Scene) -> u64 {
    let stage = scene
        .lights
        .iter()
        .filter(|l| matches!(l, Light::Point(_) | Light::Spot(_) | Light::Window(_)))
        .count()
        .min(stage::MAX_LIGHT_LAYERS) as u64;
    12 * (4 + 2 * stage) + 4 + 16
}

/// A frame too large for the machine is an error before any work, not an
/// abort when an image buffer cannot be allocated (65536 × 65536 px is
/// within the resolution's range and needs ≥ 290 GB): the estimate of
/// [`bytes_per_pixel`] is reserved once and released untouched (no page is
/// used; the allocator refuses what the system cannot provide).
/// Whether this process can allocate `bytes` at once now (tried and given
/// back: an allocation that fails later aborts the process instead).
pub fn can_allocate(bytes: u64) -> bool {
    usize::try_from(bytes)
        .ok()
        .is_some_and(|b| Vec::<u8>::new().try_reserve_exact(b).is_ok())
}

fn check_memory(scene: &Scene) -> Result<(), RenderError> {
    let [w, h] = match &scene.camera {
        crate::scene::Camera::Perspective(c) => c.resolution,
        crate::scene::Camera::Equirectangular(c) => c.resolution,
    };
    let pixels = u64::from(w) * u64::from(h);
    let bytes = pixels.saturating_mul(bytes_per_pixel(scene));
    if can_allocate(bytes) {
        Ok(())
    } else {
        Err(RenderError::InvalidScene(
            "camera.resolution".into(),
            format!(
                "{w}×{h} px needs at least {:.1} GB for its layers, more than this machine can allocate",
                bytes as f64 / 1e9
            ),
        ))
    }
}

/// No image leaves with a NaN or ∞: a layer that has one is an error naming
/// it. Values beyond f32's range (3.4e38) come from light strengths or
/// coefficients that large (a spot of 1e45 W); NaN where the f64 samples were
/// finite follows from them (∞ − ∞ in the pixel filter).
fn check_finite(images: &Images, report: &Report) -> Result<(), RenderError> {
    let bad = |px: &[[f32; 3]]| px.iter().filter(|p| p.iter().any(|v| !v.is_finite())).count();
    let mut layers: Vec<(&str, &[[f32; 3]])> = vec![
        ("inscatter", &images.inscatter),
        ("transmittance", &images.transmittance),
        ("sun_transmittance", &images.sun_transmittance),
        ("error", &images.error),
    ];
    for (name, px) in images.light_layer_names.iter().zip(&images.light_inscatter) {
        layers.push((name, px));
    }
    for (name, px) in images.surface_layer_names.iter().zip(&images.light_surface_transmittance) {
        layers.push((name, px));
    }
    for (layer, px) in layers {
        let pixels = bad(px);
        if pixels > 0 {
            let hint = if report.stats.non_finite_pixels == 0 {
                "the values exceed the range of f32 (3.4e38); light strengths or medium coefficients this large overflow it, so scale them down".to_string()
            } else {
                format!(
                    "{} samples were already not finite in f64: light strengths or coefficients within a few orders of f64's limit (1.8e308) overflow, so scale them down; with ordinary values this is a bug, please report the scene",
                    report.stats.non_finite_pixels
                )
            };
            return Err(RenderError::NonFinite {
                layer: layer.to_string(),
                pixels,
                hint,
            });
        }
    }
    if images.depth.iter().any(|v| v.is_nan()) {
        return Err(RenderError::NonFinite {
            layer: "depth".into(),
            pixels: images.depth.iter().filter(|v| v.is_nan()).count(),
            hint: "this is a bug, please report the scene".into(),
        });
    }
    Ok(())
}

fn medium_coefficients(m: &Medium) -> Vec<&Coefficient> {
    match m {
        Medium::Homogeneous(HomogeneousMedium {
            scattering, absorption, ..
        }) => vec![scattering, absorption],
        Medium::HeightFog(HeightFogMedium { rayleigh, mie, .. }) => {
            let mut v = Vec::new();
            if let Some(r) = rayleigh {
                v.push(&r.scattering);
                v.push(&r.absorption);
            }
            if let Some(m) = mie {
                v.push(&m.scattering);
                v.push(&m.absorption);
            }
            v
        }
        Medium::FogLayer(FogLayerMedium {
            extinction,
            air_extinction,
            ..
        }) => vec![extinction, air_extinction],
        Medium::LayeredHeightField(LayeredHeightFieldMedium { lower, upper, .. }) => {
            let mut v = vec![&lower.scattering, &lower.absorption];
            if let Some(u) = upper {
                v.push(&u.scattering);
                v.push(&u.absorption);
            }
            v
        }
        Medium::Ellipsoid(EllipsoidMedium {
            scattering, absorption, ..
        }) => vec![scattering, absorption],
    }
}

fn needs_spectral(scene: &Scene, report: &mut Report) -> bool {
    let spectral_media: Vec<String> = scene
        .media
        .iter()
        .enumerate()
        .filter(|(_, m)| medium_coefficients(m).iter().any(|c| c.is_spectral()))
        .map(|(i, m)| medium_label(i, m))
        .collect();
    let plan = &mut report.plan;
    let spectral = match scene.output.spectral {
        SpectralMode::Always => true,
        SpectralMode::Never => false,
        SpectralMode::Auto => !spectral_media.is_empty(),
    };
    if spectral {
        plan.colour_path = format!("spectral ({SPECTRAL_SAMPLES} samples, 380-780 nm at 5 nm, CIE 1931 2° to linear Rec.709)");
        let why = if spectral_media.is_empty() {
            "output.spectral = always".to_string()
        } else {
            format!("wavelength-dependent spectral coefficients in {}", spectral_media.join(", "))
        };
        plan.computed("colour", format!("spectral path: {why}"));
        if scene.media.iter().any(|m| {
            medium_coefficients(m)
                .iter()
                .any(|c| matches!(c, Coefficient::Rgb(v) if !(v[0] == v[1] && v[1] == v[2])))
        }) {
            report
                .warnings
                .push("RGB coefficients were upsampled to spectra (linear least-norm basis, clamped at 0) for the spectral path".into());
        }
    } else {
        plan.colour_path = "rgb".into();
        let why = if scene.output.spectral == SpectralMode::Never {
            "output.spectral = never".to_string()
        } else if scene.media.is_empty() {
            "no media".to_string()
        } else {
            "all media grey or given per RGB channel".to_string()
        };
        plan.left_out(
            "spectral sampling",
            format!("skipped, {why}: computed in RGB (3 channels instead of {SPECTRAL_SAMPLES})"),
        );
        if !spectral_media.is_empty() {
            report.warnings.push(format!(
                "spectral coefficients of {} reduced to RGB with non-negative channel weights (output.spectral = never)",
                spectral_media.join(", ")
            ));
        }
    }
    spectral
}

fn medium_label(i: usize, m: &Medium) -> String {
    let name = match m {
        Medium::Homogeneous(HomogeneousMedium { name, .. })
        | Medium::HeightFog(HeightFogMedium { name, .. })
        | Medium::FogLayer(FogLayerMedium { name, .. })
        | Medium::LayeredHeightField(LayeredHeightFieldMedium { name, .. })
        | Medium::Ellipsoid(EllipsoidMedium { name, .. }) => name,
    };
    if name.is_empty() {
        format!("media[{i}]")
    } else {
        format!("media[{i}] \"{name}\"")
    }
}

fn light_name(l: &Light) -> &str {
    match l {
        Light::Sun(SunLight { name, .. }) | Light::Ambient(AmbientLight { name, .. }) => name,
        Light::Point(l) => &l.name,
        Light::Spot(l) => &l.name,
        Light::Window(l) => &l.name,
    }
}

fn light_label(i: usize, l: &Light) -> String {
    format!("lights[{i}] \"{}\"", light_name(l))
}

/// Coefficient resolved to `C` channels (RGB or spectral).
fn resolve<const C: usize>(c: &Coefficient) -> [f64; C] {
    let mut out = [0.0; C];
    if C == 3 {
        out.copy_from_slice(&c.rgb());
    } else {
        out.copy_from_slice(&c.spectral());
    }
    out
}

/// An RGB colour as `C` channels: itself, or the linear exact-round-trip spectrum.
fn colour_channels<const C: usize>(rgb: [f64; 3]) -> [f64; C] {
    let mut out = [0.0; C];
    if C == 3 {
        out.copy_from_slice(&rgb);
    } else {
        out.copy_from_slice(&spectrum::rec709_to_spectrum(rgb));
    }
    out
}

fn solar_channels<const C: usize>(strength: f64) -> [f64; C] {
    // The solar spectrum scaled so that its luminance (Y of its Rec.709 RGB) equals `strength`.
    let solar = spectrum::solar_spectral_irradiance();
    let rgb = spectrum::spectrum_to_rec709(solar);
    let y = 0.2126 * rgb[0] + 0.7152 * rgb[1] + 0.0722 * rgb[2];
    let k = strength / y;
    let mut out = [0.0; C];
    if C == 3 {
        out.copy_from_slice(&rgb.map(|v| v * k));
    } else {
        for (o, s) in out.iter_mut().zip(solar.iter()) {
            *o = s * k;
        }
    }
    out
}

fn prepare_lights<const C: usize>(scene: &Scene, report: &mut Report) -> LightSet<C> {
    let mut set = LightSet {
        suns: Vec::new(),
        ambient: [0.0; C],
    };
    for (i, l) in scene.lights.iter().enumerate() {
        let label = light_label(i, l);
        match l {
            Light::Sun(SunLight {
                direction_to_sun,
                color,
                strength_w_m2,
                spectrum: shape,
                ..
            }) => {
                if *strength_w_m2 == 0.0 || color.iter().all(|c| *c == 0.0) {
                    report.plan.left_out(label, "no contribution: zero strength or black colour");
                    continue;
                }
                let irradiance = match shape {
                    LightSpectrum::Rgb => colour_channels::<C>(color.map(|c| c * strength_w_m2)),
                    LightSpectrum::Solar => {
                        let mut s = solar_channels::<C>(*strength_w_m2);
                        let tint = colour_channels::<C>(*color);
                        let white = colour_channels::<C>([1.0; 3]);
                        for c in 0..C {
                            if white[c] != 0.0 {
                                s[c] *= tint[c] / white[c];
                            }
                        }
                        s
                    }
                };
                let to_sun = DVec3::from(*direction_to_sun).normalize();
                report.plan.computed(
                    label.clone(),
                    format!(
                        "directional light, {strength_w_m2} W/m², elevation {:.3}°",
                        to_sun.z.asin().to_degrees()
                    ),
                );
                set.suns.push(SunSource::point(to_sun, irradiance));
            }
            Light::Ambient(AmbientLight { color, radiance, .. }) => {
                if *radiance == 0.0 || color.iter().all(|c| *c == 0.0) {
                    report.plan.left_out(label, "no contribution: zero radiance or black colour");
                    continue;
                }
                let a = colour_channels::<C>(color.map(|c| c * radiance));
                for c in 0..C {
                    set.ambient[c] += a[c];
                }
                report
                    .plan
                    .computed(label, format!("uniform ambient radiance {radiance} W/m²/sr, isotropic in-scatter"));
            }
            // Stage lights are prepared by the `stage` module.
            Light::Point(_) | Light::Spot(_) | Light::Window(_) => {}
        }
    }
    if scene.lights.is_empty() {
        report
            .plan
            .left_out("in-scattered light", "no lights: only transmittance is non-trivial");
    }
    set
}

/// Point, spot and window lights resolved to `C` channels; IES files are
/// loaded here (a missing or malformed file is an error naming the light).
fn prepare_stage_lights<const C: usize>(scene: &Scene, report: &mut Report) -> Result<stage::StageLights<C>, RenderError> {
    let mut out = stage::StageLights::default();
    let load_ies = |i: usize,
                    r: &Option<crate::scene::IesProfileRef>|
     -> Result<Option<(std::sync::Arc<crate::light::ies::IesProfile>, f64)>, RenderError> {
        match r {
            None => Ok(None),
            Some(r) => crate::light::ies::IesProfile::load(std::path::Path::new(&r.file))
                .map(|p| Some((std::sync::Arc::new(p), r.strength)))
                .map_err(|e| RenderError::InvalidScene(format!("lights[{i}].ies.file"), e.to_string())),
        }
    };
    for (i, l) in scene.lights.iter().enumerate() {
        let label = light_label(i, l);
        match l {
            Light::Point(_) | Light::Spot(_) => {
                let (power_w, color, ies_ref, casts_shadows) = match l {
                    Light::Point(p) => (p.power_w, p.color, &p.ies, p.casts_shadows),
                    Light::Spot(p) => (p.power_w, p.color, &p.ies, p.casts_shadows),
                    _ => unreachable!("matched above"),
                };
                // The profile first: a missing or malformed file is an error
                // even where this frame's power is 0 (an animated power would
                // hide a bad path until a later frame).
                let ies = load_ies(i, ies_ref)?;
                if let Some((profile, _)) = &ies
                    && profile.version == crate::light::ies::IesVersion::Lm63_2019
                    && profile.ballast_lamp_factor != 1.0
                {
                    report.warnings.push(format!(
                        "{label}: its LM-63-2019 profile's file generation type {} (the ballast line's second field) multiplies its candela values, as Cycles applies it; LM-63 does not mean it as a factor",
                        profile.ballast_lamp_factor
                    ));
                }
                if power_w == 0.0 || color.iter().all(|c| *c == 0.0) || ies_ref.as_ref().is_some_and(|r| r.strength == 0.0) {
                    report.plan.left_out(
                        label,
                        "no contribution: zero power, black colour or zero IES strength (its inscatter.<light> layer is 0)",
                    );
                    out.dark.push(light_name(l).to_string());
                    continue;
                }
                let src = match l {
                    Light::Point(p) => crate::light::PointSource::from_point(p, colour_channels::<C>(color), ies),
                    Light::Spot(p) => crate::light::PointSource::from_spot(p, colour_channels::<C>(color), ies),
                    _ => unreachable!("matched above"),
                };
                // A profile that is 0 inside the whole of the light's own cone
                // (an uplight's file on a spot pointing down, or an all-zero file).
                if let Some((profile, _)) = &src.ies {
                    let (reach, unlit) = (src.shape.cos_reach().clamp(-1.0, 1.0).acos(), profile.unlit_half_angle());
                    if reach <= unlit || profile.max_candela() == 0.0 {
                        report.plan.left_out(
                            label,
                            format!(
                                "no contribution: its IES profile is 0 below {:.1}° from the axis, and its distribution reaches only {:.1}° (its inscatter.<light> layer is 0)",
                                unlit.to_degrees(),
                                reach.to_degrees()
                            ),
                        );
                        out.dark.push(light_name(l).to_string());
                        continue;
                    }
                }
                report.plan.computed(label, describe_point(&src, power_w));
                out.points.push(stage::PreparedPoint {
                    light: src,
                    shadows: None,
                    casts_shadows,
                });
            }
            Light::Window(wl) => {
                if wl.irradiance_w_m2 == 0.0 || wl.color.iter().all(|c| *c == 0.0) {
                    report.plan.left_out(
                        label,
                        "no contribution: zero irradiance or black colour (its inscatter.<light> layer is 0)",
                    );
                    out.dark.push(wl.name.clone());
                    continue;
                }
                let src = crate::light::window::WindowSource::new(
                    &wl.name,
                    DVec3::from(wl.direction_to_light),
                    colour_channels::<C>(wl.color.map(|c| c * wl.irradiance_w_m2)),
                    &wl.aperture,
                );
                report.plan.computed(
                    label,
                    format!(
                        "parallel light through a {}-corner window, {} W/m²: in-scatter integrated over the prism the window sweeps (Nishita Fig. 3)",
                        wl.aperture.len(),
                        wl.irradiance_w_m2
                    ),
                );
                out.windows.push(stage::PreparedWindow {
                    light: src,
                    shadows: None,
                    casts_shadows: wl.casts_shadows,
                });
            }
            _ => {}
        }
    }
    // The lights beyond the layer cap, named: layers go to the contributing
    // lights first (point and spot lights, then windows), then to those that
    // contribute nothing (their `inscatter.<light>` layers are 0).
    let per_light = scene.output.layers.contains(&LayerKind::InscatterPerLight);
    let surface = scene.output.layers.contains(&LayerKind::SurfaceTransmittancePerLight);
    let names = out.names();
    let mut dropped: Vec<String> = names.iter().skip(stage::MAX_LIGHT_LAYERS).cloned().collect();
    if per_light {
        let room = stage::MAX_LIGHT_LAYERS.saturating_sub(names.len());
        dropped.extend(out.dark.iter().skip(room).cloned());
    }
    if (per_light || surface) && !dropped.is_empty() {
        let total = names.len() + if per_light { out.dark.len() } else { 0 };
        report.warnings.push(format!(
            "{total} stage lights: per-light layers are written for {} of them (the contributing lights first); none for {}; `inscatter` contains all of them",
            stage::MAX_LIGHT_LAYERS,
            dropped.join(", ")
        ));
    }
    Ok(out)
}

fn describe_point<const C: usize>(src: &crate::light::PointSource<C>, power_w: f64) -> String {
    let reach = if let Some((a, b)) = src.ellipse {
        format!(
            "an elliptical cone of half-angles {:.3}° (local X) × {:.3}° (local Y)",
            a.atan().to_degrees(),
            b.atan().to_degrees()
        )
    } else if src.cos_reach <= -1.0 {
        "every direction".to_string()
    } else {
        format!("a cone of half-angle {:.4}°", src.cos_reach.clamp(-1.0, 1.0).acos().to_degrees())
    };
    let ies = src
        .ies
        .as_ref()
        .map(|(p, s)| format!(", IES ×{s}: {}", p.describe()))
        .unwrap_or_default();
    format!(
        "point source, {power_w} W (Cycles: {:.4} W/sr per W on the axis), illumination volume {reach}{ies}; in-scatter by adaptive Gauss-Kronrod in u = atan((t - t_c)/h) over the exact lit segments",
        crate::light::CYCLES_WATTS_TO_INTENSITY
    )
}

/// Shadow casters per stage light: silhouette wedges of the triangles inside its volume.
/// `Err(Cancelled)` once `stop()` is true (asked before each light's).
fn prepare_stage_shadows<const C: usize>(
    meshes: &[Mesh],
    stage_lights: &mut stage::StageLights<C>,
    report: &mut Report,
    stop: &(dyn Fn() -> bool + Sync),
) -> Result<(), RenderError> {
    let names = stage_lights.names();
    let flags = stage_lights
        .points
        .iter()
        .map(|p| p.casts_shadows)
        .chain(stage_lights.windows.iter().map(|w| w.casts_shadows));
    for (name, casts) in names.iter().zip(flags) {
        if !casts {
            report.plan.left_out(
                format!("shadows of \"{name}\""),
                "casts_shadows false (Blender's Cast Shadow off): its whole illumination volume is lit, and undimmed by the media on the light's way (Cycles traces no shadow ray for it)",
            );
        }
    }
    let world: Vec<(Vec<DVec3>, &[[u32; 3]])> = meshes
        .iter()
        .map(|m| {
            let mat = m.transform.to_matrix();
            (
                m.positions.iter().map(|p| mat.transform_point3(DVec3::from(*p))).collect(),
                m.triangles.as_slice(),
            )
        })
        .collect();
    let indexed: Vec<crate::light::shadow::IndexedMesh<'_>> = world
        .iter()
        .map(|(p, t)| crate::light::shadow::IndexedMesh {
            positions: p,
            triangles: t,
        })
        .collect();
    if indexed.iter().all(|m| m.triangles.is_empty()) {
        report.plan.left_out(
            "volumetric shadows",
            "no shadow-casting meshes: every stage light's volume is fully lit",
        );
        return Ok(());
    }
    if !stage_lights.build_shadows_cancellable(&indexed, stop) {
        return Err(RenderError::Cancelled);
    }
    let casters: Vec<Option<&crate::light::shadow::ShadowWedges>> = stage_lights
        .points
        .iter()
        .map(|p| p.shadows.as_ref())
        .chain(stage_lights.windows.iter().map(|w| w.shadows.as_ref()))
        .collect();
    for (name, sw) in names.iter().zip(casters) {
        let Some(sw) = sw else { continue };
        if sw.triangles_used > 0 {
            report.plan.computed(
                format!("shadows of \"{name}\""),
                format!(
                    "exact lit segments: {} silhouette/boundary edges of {} triangles inside the illumination volume, crossings found in a light-space BVH, one shadow ray per piece unless the light's visibility grid decides it",
                    sw.wedge_count(),
                    sw.triangles_used
                ),
            );
        }
        if sw.triangles_left_out > 0 {
            report.plan.left_out(
                format!("{} occluder triangles for \"{name}\"", sw.triangles_left_out),
                "outside the light's illumination volume: they cast no shadow in its light",
            );
        }
    }
    Ok(())
}

fn report_stage<const C: usize>(stage_lights: &stage::StageLights<C>, stats: &RowStats, report: &mut Report) {
    if stats.stage_skipped > 0 {
        report.plan.left_out(
            format!("{} light-ray integrals", stats.stage_skipped),
            "the view ray misses the light's illumination volume inside a medium: no integral evaluated",
        );
    }
    report.plan.computed(
        format!("{} lit segments on {} view rays", stats.stage_segments, stats.stage_rays),
        format!(
            "adaptive Gauss-Kronrod-Patterson per segment to the relative tolerance (K7, extended to P15 before a panel is split); {} shadow rays (where the lights' visibility grids did not decide)",
            stats.stage_shadow_rays
        ),
    );
    if stats.stage_clamped > 0 {
        report.warnings.push(format!(
            "{} view rays pass closer to a point light than its radius (or {} m for radius 0): evaluated at that distance (a ray through a point light has infinite in-scatter)",
            stats.stage_clamped,
            crate::light::MIN_LIGHT_DISTANCE
        ));
    }
    for (k, name) in stage_lights.names().iter().enumerate().take(64) {
        if stats.stage_crossed & (1 << k) == 0 {
            report.plan.left_out(
                format!("light \"{name}\""),
                "its illumination volume meets no view ray inside a medium (outside the view, behind surfaces, or no medium there): nothing computed for it",
            );
        }
    }
    if stats.stage_segments == 0 && !stage_lights.is_empty() {
        report.plan.left_out(
            "stage lights' in-scatter",
            "no view ray crosses an illumination volume inside a medium (lights outside the view or without medium)",
        );
    }
}

/// `<prefix>.<name>` layer names (`inscatter.<name>`, …), unique and without
/// '.' inside the name.
fn per_light_layer_names(prefix: &str, names: &[String]) -> Vec<String> {
    // Layer names are `prefix.name` with the name's dots (EXR's layer
    // separator) and control characters turned into `_`. A light keeps its
    // own name where it can: first the lights whose names need no change
    // (the first of equal ones), then the others in order, each taking its
    // cleaned name or the first `_2`, `_3`, … that is free and is not
    // another light's own name (two lights `key` and one `key_2`: `key`,
    // `key_3`, `key_2`; never `key_2` for the second `key`).
    let bases: Vec<(String, bool)> = names
        .iter()
        .map(|n| {
            let clean: String = n.chars().map(|c| if c == '.' || c.is_control() { '_' } else { c }).collect();
            let exact = !clean.is_empty() && clean == *n;
            (format!("{prefix}.{}", if clean.is_empty() { "light" } else { &clean }), exact)
        })
        .collect();
    let own: std::collections::HashSet<&str> = bases.iter().map(|(b, _)| b.as_str()).collect();
    let mut taken: std::collections::HashSet<String> = std::collections::HashSet::new();
    let mut out: Vec<Option<String>> = vec![None; names.len()];
    for (slot, (base, exact)) in out.iter_mut().zip(&bases) {
        if *exact && taken.insert(base.clone()) {
            *slot = Some(base.clone());
        }
    }
    for (slot, (base, _)) in out.iter_mut().zip(&bases) {
        if slot.is_some() {
            continue;
        }
        let mut name = base.clone();
        let mut k = 2;
        while taken.contains(&name) || (name != *base && own.contains(name.as_str())) {
            name = format!("{base}_{k}");
            k += 1;
        }
        taken.insert(name.clone());
        *slot = Some(name);
    }
    out.into_iter().flatten().collect()
}

fn prepare_media<const C: usize>(scene: &Scene, lights: &LightSet<C>, report: &mut Report) -> Vec<PreparedMedium<C>> {
    let mut out = Vec::new();
    for (i, m) in scene.media.iter().enumerate() {
        let label = medium_label(i, m);
        let add = |a: [f64; C], b: [f64; C]| -> [f64; C] {
            let mut r = a;
            for c in 0..C {
                r[c] += b[c];
            }
            r
        };
        let prepared = match m {
            Medium::Homogeneous(HomogeneousMedium {
                name,
                scattering,
                absorption,
                phase,
                bounds,
            }) => {
                let s = resolve::<C>(scattering);
                let ext = add(s, resolve::<C>(absorption));
                let b = match bounds {
                    Bounds::World => None,
                    Bounds::Box { min, max, rotation_wxyz } => Some(MediumBox::new(
                        DVec3::from(*min),
                        DVec3::from(*max),
                        rotation_wxyz.map(crate::scene::quat_wxyz),
                    )),
                };
                report.plan.computed(
                    label.clone(),
                    format!(
                        "homogeneous, {}, phase {}: closed form (Klassen eq 1.11 with constant coefficients{})",
                        match &b {
                            None => "world",
                            Some(b) if b.is_rotated() => "rotated box",
                            Some(_) => "box",
                        },
                        phase.describe(),
                        if b.is_some() {
                            "; sun attenuated inside the box, piecewise exact"
                        } else {
                            "; sun unattenuated, Ishiyama eq 11"
                        }
                    ),
                );
                PreparedMedium::Homogeneous(Homogeneous {
                    name: name.clone(),
                    scattering: s,
                    extinction: ext,
                    phase: *phase,
                    bounds: b,
                })
            }
            Medium::HeightFog(HeightFogMedium {
                name,
                scale_height_m,
                reference_height_m,
                rayleigh,
                mie,
            }) => {
                let zero = [0.0; C];
                let (rs, ra) = rayleigh
                    .as_ref()
                    .map(|r| (resolve::<C>(&r.scattering), resolve::<C>(&r.absorption)))
                    .unwrap_or((zero, zero));
                let (ms, ma, mp) = mie
                    .as_ref()
                    .map(|m| (resolve::<C>(&m.scattering), resolve::<C>(&m.absorption), m.phase))
                    .unwrap_or((zero, zero, PhaseFunction::Isotropic));
                let ext = add(add(rs, ra), add(ms, ma));
                report.plan.computed(
                    label.clone(),
                    format!(
                        "exponential height fog, H = {scale_height_m} m: closed form (Ishiyama eqs 14, 21-23), sun unattenuated (eq 11)"
                    ),
                );
                PreparedMedium::HeightFog(HeightFog {
                    name: name.clone(),
                    scale_height: *scale_height_m,
                    reference_height: *reference_height_m,
                    rayleigh_scattering: rs,
                    mie_scattering: ms,
                    extinction: ext,
                    mie_phase: mp,
                })
            }
            Medium::FogLayer(FogLayerMedium {
                name,
                ground_height_m,
                top_height_m,
                extinction,
                single_scattering_albedo,
                air_extinction,
                phase,
                sun_path,
                min_sun_elevation_deg,
            }) => {
                let fog = resolve::<C>(extinction);
                let ext = add(fog, resolve::<C>(air_extinction));
                let scat = fog.map(|v| v * single_scattering_albedo);
                let layer = FogLayer {
                    name: name.clone(),
                    ground: *ground_height_m,
                    top: *top_height_m,
                    extinction: ext,
                    scattering: scat,
                    phase: *phase,
                    sun_path: *sun_path,
                    min_sin_elevation: min_sun_elevation_deg.to_radians().sin(),
                };
                let path = match sun_path {
                    crate::scene::SunPath::PerPoint => "sun path per point, exact flat-earth closed form",
                    crate::scene::SunPath::FullLayer => "sun path through the full layer, Klassen eqs 3.11, 3.20",
                };
                report.plan.computed(
                    label.clone(),
                    format!("Klassen fog layer {ground_height_m}..{top_height_m} m: {path}"),
                );
                for (k, sun) in lights.suns.iter().enumerate() {
                    if !layer.sun_is_direct(sun.to_sun) {
                        report.plan.left_out(
                            format!("{label}: direct light of sun {k}"),
                            format!(
                                "sun elevation {:.3}° is below min_sun_elevation_deg = {min_sun_elevation_deg}°: no direct sunlight reaches the fog on a curved earth; the fog colour is the ambient light's (Klassen §3, sun at the horizon)",
                                sun.to_sun.z.asin().to_degrees()
                            ),
                        );
                    }
                }
                PreparedMedium::FogLayer(layer)
            }
            Medium::LayeredHeightField(LayeredHeightFieldMedium {
                name,
                base_height_m,
                waves,
                lower,
                upper,
            }) => {
                let side = |l: &crate::scene::LayerSide| {
                    let s = resolve::<C>(&l.scattering);
                    Side {
                        scattering: s,
                        extinction: add(s, resolve::<C>(&l.absorption)),
                        phase: l.phase,
                    }
                };
                let vacuum = Side {
                    scattering: [0.0; C],
                    extinction: [0.0; C],
                    phase: PhaseFunction::Isotropic,
                };
                let ws: Vec<Wave> = waves
                    .iter()
                    .map(|w| Wave::new(w.amplitude_m, w.wavelength_m, w.direction_deg, w.phase_deg))
                    .collect();
                let layer = HeightFieldLayer::new(
                    name.clone(),
                    *base_height_m,
                    ws,
                    side(lower),
                    upper.as_ref().map(side).unwrap_or(vacuum),
                    scene.output.tolerance,
                );
                report.plan.computed(
                    label.clone(),
                    format!(
                        "layered height field (Nishita et al. 1987 §4), {} sine waves, boundary {:.3}..{:.3} m, lower phase {}, upper {}: boundary crossings found first (Lipschitz/Taylor-bounded interval subdivision + Newton-bisection), optical depths exact per piece; ambient in closed form, sun in-scatter by adaptive Gauss-Kronrod per piece (sun path crossings by the same finder; sun irradiance given at the crest plane)",
                        waves.len(),
                        layer.bottom(),
                        layer.top(),
                        lower.phase.describe(),
                        if layer.upper_is_vacuum() { "vacuum".to_string() } else { "non-zero (segment = whole ray)".to_string() }
                    ),
                );
                PreparedMedium::HeightFieldLayer(layer)
            }
            Medium::Ellipsoid(EllipsoidMedium {
                name,
                center,
                radii,
                rotation_wxyz,
                scattering,
                absorption,
                phase,
            }) => {
                let s = resolve::<C>(scattering);
                let ext = add(s, resolve::<C>(absorption));
                let rot = rotation_wxyz.map(crate::scene::quat_wxyz).unwrap_or(glam::DQuat::IDENTITY);
                report.plan.computed(
                    label.clone(),
                    format!(
                        "smoke ellipsoid (Nishita et al. 1987 §4), radii {radii:?} m, phase {}: chord in the unit-sphere frame (stable quadratic), optical depths exact; ambient in closed form, sun in-scatter (sun path a chord of the ellipsoid) by adaptive Gauss-Kronrod with its error estimate",
                        phase.describe()
                    ),
                );
                PreparedMedium::Ellipsoid(Ellipsoid::new(
                    name.clone(),
                    DVec3::from(*center),
                    DVec3::from(*radii),
                    rot,
                    s,
                    ext,
                    *phase,
                    scene.output.tolerance,
                ))
            }
        };
        let ext_zero = match &prepared {
            PreparedMedium::Homogeneous(h) => h.extinction.iter().all(|v| *v == 0.0),
            PreparedMedium::HeightFog(h) => h.extinction.iter().all(|v| *v == 0.0),
            PreparedMedium::FogLayer(f) => f.extinction.iter().all(|v| *v == 0.0),
            PreparedMedium::HeightFieldLayer(f) => f.lower.extinction.iter().chain(f.upper.extinction.iter()).all(|v| *v == 0.0),
            PreparedMedium::Ellipsoid(e) => e.extinction.iter().all(|v| *v == 0.0),
        };
        if ext_zero {
            report.plan.computed.pop();
            report.plan.left_out(label, "zero extinction and scattering: the medium is vacuum");
            continue;
        }
        out.push(prepared);
    }
    if scene.media.is_empty() {
        report.plan.left_out("scattering integrals", "no media: T = 1 and L = 0 everywhere");
    }
    report.plan.left_out(
        "volumetric shadows of meshes",
        "for sun and ambient light (closed-form fog path) meshes end view rays but do not shadow the medium; point, spot and window lights do get exact mesh shadows",
    );
    out
}

struct PixelOut<const C: usize> {
    result: RayResult<C>,
    stage: Option<stage::StageShade<C>>,
    depth: f64,
    hit: bool,
    /// Triangle index + 1 of the surface hit, 0 for none.
    surface: u32,
    numeric: Option<bool>,
    in_medium: bool,
    /// The surface point the view ray ends on.
    surface_point: Option<DVec3>,
}

/// Optical depth of the medium between `p` and the `k`-th stage light
/// (per-light layer order: points, then windows): to a point light's
/// position; for a window light, back along the light's direction to the
/// window plane (the prism's light enters there; nothing on the light's side).
fn light_path_depth<const C: usize>(stage_lights: &stage::StageLights<C>, media: &[PreparedMedium<C>], k: usize, p: DVec3) -> [f64; C] {
    // A light without shadows (Cycles traces no shadow ray for it): undimmed.
    let end = if let Some(pt) = stage_lights.points.get(k) {
        if !pt.casts_shadows {
            return [0.0; C];
        }
        pt.light.position
    } else if let Some(wl) = stage_lights.windows.get(k - stage_lights.points.len()) {
        if !wl.casts_shadows {
            return [0.0; C];
        }
        let s = wl.light.distance_to_window(p);
        if s.is_nan() || s <= 0.0 {
            return [0.0; C];
        }
        p + wl.light.to_light * s
    } else {
        return [0.0; C];
    };
    let mut tau = [0.0; C];
    for m in media {
        let d = m.optical_depth_between(p, end);
        for c in 0..C {
            tau[c] += d[c];
        }
    }
    tau
}

#[allow(clippy::too_many_arguments)]
fn shade_pixel<const C: usize>(
    cam: &CameraRays,
    bvh: Option<&Bvh>,
    shadow_bvh: Option<&Bvh>,
    media: &[PreparedMedium<C>],
    lights: &LightSet<C>,
    stage_lights: &stage::StageLights<C>,
    x: f64,
    y: f64,
    tolerance: f64,
    topology: bool,
    per_light: &mut [[f64; 3]],
    to_rgb: &dyn Fn(&[f64; C]) -> [f64; 3],
) -> PixelOut<C> {
    let dir = cam.direction(x, y);
    let start = cam.start_distance(dir);
    let mut end = cam.clip_end;
    let mut hit = false;
    let mut surface = 0;
    if let Some(b) = bvh
        && let Some(h) = b.closest_hit(cam.position, dir, start, end)
    {
        end = h.t;
        hit = true;
        surface = h.triangle + 1;
    }
    let depth = if hit { end } else { f64::INFINITY };
    let ray = ViewRay {
        origin: cam.position + dir * start,
        dir,
        s_max: (end - start).max(0.0),
    };
    let mut active: [usize; 8] = [0; 8];
    let mut n_active = 0;
    let mut extra_active = false;
    for (i, m) in media.iter().enumerate() {
        if m.segment(&ray).is_some() {
            if n_active < active.len() {
                active[n_active] = i;
                n_active += 1;
            } else {
                extra_active = true;
            }
        }
    }
    let mut result = RayResult::vacuum();
    let mut numeric = None;
    if n_active == 1 && !extra_active {
        result = media[active[0]].closed_form(&ray, lights);
    } else if n_active > 1 || extra_active {
        let (r, converged) = integrate_media(&ray, media, lights, tolerance);
        result = r;
        numeric = Some(converged);
    }
    // The sun reaching the surface point crosses every medium on its way,
    // including media the view ray never enters.
    if hit && let Some(sun) = lights.suns.first() {
        let p = ray.origin + ray.dir * ray.s_max;
        let mut ts = [1.0; C];
        for m in media {
            let t = m.sun_transmittance_at(p, sun.to_sun);
            for c in 0..C {
                ts[c] *= t[c];
            }
        }
        result.sun_transmittance = ts;
    }
    if !hit {
        result.sun_transmittance = [1.0; C];
    }
    let stage = if stage_lights.is_empty() || n_active == 0 {
        None
    } else {
        let sh = STAGE_SCRATCH.with(|cell| {
            let mut scratch = cell.borrow_mut();
            scratch.topology = topology;
            stage_lights.shade(&ray, media, shadow_bvh, tolerance, &mut scratch, per_light, to_rgb)
        });
        for c in 0..C {
            result.inscatter[c] += sh.inscatter[c];
            result.error[c] += sh.error[c];
        }
        Some(sh)
    };
    PixelOut {
        stage,
        result,
        depth,
        hit,
        surface,
        numeric,
        in_medium: n_active > 0,
        surface_point: hit.then(|| ray.origin + ray.dir * ray.s_max),
    }
}

thread_local! {
    static STAGE_SCRATCH: std::cell::RefCell<stage::Scratch> = std::cell::RefCell::new(stage::Scratch::default());
}

/// The lights with each sun dimmed at `p` by every medium but `media[own]`
/// (that medium's own attenuation is inside its source and closed form);
/// `None` where nothing would change (no suns, or no other medium).
fn suns_dimmed_by_others<const C: usize>(lights: &LightSet<C>, media: &[PreparedMedium<C>], own: usize, p: DVec3) -> Option<LightSet<C>> {
    if lights.suns.is_empty() || media.len() == 1 {
        return None;
    }
    let mut dimmed = lights.clone();
    for sun in dimmed.suns.iter_mut() {
        for (j, other) in media.iter().enumerate() {
            if j != own {
                let t = other.sun_transmittance_at(p, sun.to_sun);
                for c in 0..C {
                    sun.irradiance[c] *= t[c];
                }
            }
        }
    }
    Some(dimmed)
}

/// An eye inside height fogs opaque at once there (σ_t > 1e20 m⁻¹, far
/// below their reference heights; `opaque` lists them with the channels
/// where they are). In such a channel `L = Σ_i σ_s,i J_i / Σ_i σ_t,i` at the
/// eye and `T = 0`: each height fog's own saturated closed form
/// (`J_i σ_s,i/σ_t,i`) weighted by its share of the extinction there,
/// `σ_t,i / Σ σ_t`, computed from the log extinctions (the densities may
/// overflow f64): the denser fog wins whatever the scene order, and a fog
/// just short of the threshold takes its share too (so nothing jumps where
/// one fog crosses it before another). The other media's extinctions are
/// finite and small against 1e20 m⁻¹ and add nothing. A channel no opaque
/// fog dims (extinction 0 there, so no scattering either) sees the other
/// media alone, as if the fogs were not on the ray. The suns reach the eye
/// dimmed by the other media, as in [`integrate_media`]'s integrand.
fn saturated_at_eye<const C: usize>(
    ray: &ViewRay,
    media: &[PreparedMedium<C>],
    lights: &LightSet<C>,
    tolerance: f64,
    opaque: &[(usize, [bool; C])],
) -> (RayResult<C>, bool) {
    let fogs: Vec<(RayResult<C>, [Option<f64>; C])> = media
        .iter()
        .enumerate()
        .map(|(i, m)| (i, m.height_fog_log_extinction_at(ray.origin)))
        .filter(|(_, l)| l.iter().any(Option::is_some))
        .map(|(i, log_extinction)| {
            let own = match suns_dimmed_by_others(lights, media, i, ray.origin) {
                Some(dimmed) => media[i].closed_form(ray, &dimmed),
                None => media[i].closed_form(ray, lights),
            };
            (own, log_extinction)
        })
        .collect();
    let saturated = |c: usize| opaque.iter().any(|(_, o)| o[c]);
    let others: Vec<PreparedMedium<C>> = media
        .iter()
        .enumerate()
        .filter(|(j, _)| opaque.iter().all(|(i, _)| i != j))
        .map(|(_, m)| m.clone())
        .collect();
    let (mut out, converged) = if (0..C).any(|c| !saturated(c)) && !others.is_empty() {
        integrate_media(ray, &others, lights, tolerance)
    } else {
        (RayResult::vacuum(), true)
    };
    for c in (0..C).filter(|&c| saturated(c)) {
        let densest = fogs.iter().filter_map(|(_, l)| l[c]).fold(f64::NEG_INFINITY, f64::max);
        let (mut inscatter, mut error, mut weights) = (0.0, 0.0, 0.0);
        for (own, log_extinction) in &fogs {
            if let Some(l) = log_extinction[c] {
                // (Equal logs, also both f64::MAX: weight 1, never exp(∞ − ∞).)
                let w = if l == densest { 1.0 } else { (l - densest).exp() };
                inscatter += w * own.inscatter[c];
                error += w * own.error[c];
                weights += w;
            }
        }
        out.inscatter[c] = inscatter / weights;
        out.error[c] = error / weights + medium::rounding_bound(out.inscatter[c], 4.0 * fogs.len() as f64);
        out.transmittance[c] = 0.0;
    }
    for (own, _) in &fogs {
        out.rel_bound = out.rel_bound.max(own.rel_bound);
    }
    (out, converged)
}

/// Cuts for a boundary layer in the piece `[a, b]` of a view ray (`b` may be
/// ∞; then `first_step`, > 0, is the length to try first): where the optical
/// depth of a channel still lit at `a` (τ(a) < 40) rises by more than 64
/// across the piece, the points where the steepest such channel's has risen
/// by 4^k, k = −3 … 3, found by bisection on the closed-form τ (monotone in
/// the distance; each point to 1 % of its distance from `a`). Without them a
/// G7–K15 rule over a piece much longer than the layer (an eye in a fog of
/// σ_t = 10⁴ m⁻¹ with a haze box's face 10 m away, or a ray into a fog whose
/// density grows e-fold in a millimetre) sees e^{−τ}·σ ≈ 0 at every node:
/// both rules agree on 0, and the layer's light is lost with an error
/// estimate of 0. Between the cuts the optical depth changes by a factor of
/// 4 or by at most 48, which the rule resolves; beyond the last that channel
/// is dark (e^{−64}). No cuts in gentler pieces.
fn depth_level_cuts<const C: usize>(total_tau: &impl Fn(f64) -> [f64; C], a: f64, b: f64, first_step: f64) -> Vec<f64> {
    const LEVELS: [f64; 7] = [1.0 / 64.0, 1.0 / 16.0, 0.25, 1.0, 4.0, 16.0, 64.0];
    let base = total_tau(a);
    let lit: Vec<usize> = (0..C).filter(|&c| base[c] < 40.0).collect();
    if lit.is_empty() {
        return Vec::new();
    }
    let rise = |s: f64| {
        let t = total_tau(s);
        lit.iter().map(|&c| t[c] - base[c]).fold(0.0_f64, f64::max)
    };
    let mut hi = b;
    if !b.is_finite() {
        // An upper bracket: first_step·4^k past `a`.
        let mut step = first_step;
        hi = a + step;
        while hi.is_finite() && rise(hi) <= 64.0 && step < 1e300 {
            step *= 4.0;
            hi = a + step;
        }
    }
    if !hi.is_finite() || rise(hi) <= 64.0 {
        return Vec::new();
    }
    // The search runs on the distance d from `a`: by factors of 16 down from
    // the bracket while nothing below is known, geometric while the bracket
    // spans more than a factor of 4, then halving.
    let mut cuts = Vec::with_capacity(LEVELS.len());
    let (span, mut d_lo) = (hi - a, 0.0_f64);
    for level in LEVELS {
        let (mut l, mut h) = (d_lo, span);
        for _ in 0..400 {
            let m = if l == 0.0 {
                h / 16.0
            } else if h > 4.0 * l {
                (l * h).sqrt()
            } else {
                0.5 * (l + h)
            };
            if m <= l || m >= h || h - l <= 0.01 * h {
                break;
            }
            if rise(a + m) < level {
                l = m;
            } else {
                h = m;
            }
        }
        if h > d_lo && h < span {
            cuts.push(a + h);
            d_lo = h;
        }
    }
    cuts
}

/// Several media on one ray: `L = ∫ Σ S_m e^{−Σ τ_m}`, adaptive G7–K15 over
/// each piece between medium boundaries; an infinite ray is mapped to a finite
/// interval by `s = a + σ·u/(1 − u)`.
fn integrate_media<const C: usize>(
    ray: &ViewRay,
    media: &[PreparedMedium<C>],
    lights: &LightSet<C>,
    tolerance: f64,
) -> (RayResult<C>, bool) {
    let opaque: Vec<(usize, [bool; C])> = media
        .iter()
        .map(|m| m.opaque_at(ray.origin))
        .enumerate()
        .filter(|(_, o)| o.contains(&true))
        .collect();
    if !opaque.is_empty() {
        return saturated_at_eye(ray, media, lights, tolerance, &opaque);
    }
    let total_tau = |s: f64| {
        let mut t = [0.0; C];
        for m in media {
            let d = m.optical_depth(ray, s);
            for c in 0..C {
                t[c] += d[c];
            }
        }
        t
    };
    // Each medium's source sees the suns dimmed by every other medium on the
    // sun path too (its own attenuation is inside its `source`).
    let integrand = |s: f64| {
        let tau = total_tau(s);
        let p = ray.origin + ray.dir * s;
        let mut out = [0.0; C];
        for (mi, m) in media.iter().enumerate() {
            let src = match suns_dimmed_by_others(lights, media, mi, p) {
                Some(dimmed) => m.source(ray, s, &dimmed),
                None => m.source(ray, s, lights),
            };
            for c in 0..C {
                out[c] += src[c];
            }
        }
        for c in 0..C {
            // Where the transmittance has underflowed the product is 0, even if a
            // height fog's density has overflowed there (∞·0 would be NaN): its
            // transmittance falls super-exponentially while its density grows
            // exponentially.
            let t = (-tau[c]).exp();
            out[c] = if out[c] == 0.0 || t == 0.0 { 0.0 } else { out[c] * t };
        }
        out
    };
    let mut cuts = vec![0.0];
    for m in media {
        if let Some((a, b)) = m.segment(ray) {
            cuts.push(a);
            if b.is_finite() {
                cuts.push(b);
            }
        }
    }
    if ray.s_max.is_finite() {
        cuts.push(ray.s_max);
    }
    cuts.retain(|c| *c <= ray.s_max);
    cuts.sort_by(f64::total_cmp);
    cuts.dedup();
    // Optically thick pieces get cuts where their steepest channel's optical
    // depth has risen by 4^k, k = −3 … 3 (see `depth_level_cuts`).
    let mut levels = Vec::new();
    for w in cuts.windows(2) {
        levels.extend(depth_level_cuts(&total_tau, w[0], w[1], 0.0));
    }
    let tail = !ray.s_max.is_finite();
    // The tail's own scale is 1/(the fastest rate of extinction at its start),
    // which resolves that channel's fall. Where the channels' rates differ by
    // more than 64× (a dense red-only fog in a thin haze), one scale cannot
    // serve all: the fast channel's fall gets level cuts first, and the tail
    // then starts where that channel is dark, at the rate of the channels
    // still lit.
    // (fastest rate among the lit channels, slowest positive one among them,
    // fastest among all), per m, at `a`.
    let tail_rates = |a: f64| {
        let (tau1, tau0) = (total_tau(a + 1.0), total_tau(a));
        let lit: Vec<f64> = (0..C).filter(|&c| tau0[c] < 40.0).map(|c| tau1[c] - tau0[c]).collect();
        let fastest = lit.iter().copied().fold(0.0_f64, f64::max);
        let slowest = lit.iter().copied().filter(|r| *r > 0.0).fold(f64::INFINITY, f64::min);
        let any = (0..C).map(|c| tau1[c] - tau0[c]).fold(0.0_f64, f64::max);
        (fastest, slowest, any)
    };
    let mut tail_start = None;
    if tail {
        // A height fog seen upwards thins out over H/d_z. Where that is much
        // shorter than the extinction's scale (thin media), the tail's map put
        // its first node beyond the fog's light: a height fog with a haze box at
        // optical depth 1e-5 came out 16 % dark with an estimate of 2e-7. Cuts at
        // 4^k decay lengths, k = 0 … 3, resolve the fog's fall; the tail then
        // starts where its source has fallen by e^-64.
        let a = *cuts.last().unwrap_or(&0.0);
        let decay = media
            .iter()
            .filter_map(|m| m.density_decay_length(ray))
            .fold(f64::INFINITY, f64::min);
        if decay * tail_rates(a).2 < 0.25 && (a + 64.0 * decay).is_finite() {
            cuts.extend((0..4).map(|k| a + decay * 4f64.powi(k)));
        }
        let a = *cuts.last().unwrap_or(&0.0);
        let rates = tail_rates(a);
        if rates.0 > 64.0 * rates.1 {
            levels.extend(depth_level_cuts(&total_tau, a, f64::INFINITY, 1.0 / rates.0));
        }
        tail_start = Some((a, rates));
    }
    cuts.extend(levels);
    cuts.sort_by(f64::total_cmp);
    cuts.dedup();
    let mut value = [0.0; C];
    let mut error = [0.0; C];
    let mut converged = true;
    // The tolerance is relative to the whole integral: a first coarse G7-K15
    // pass over every piece estimates its size, and each piece (the infinite
    // tail counts as one) then gets an equal share of the absolute budget, so a
    // negligible piece is not refined to relative accuracy of its own.
    let (tail_a, tail_scale) = {
        let a = *cuts.last().unwrap_or(&0.0);
        // (The rates at the tail's start unless level cuts moved it.)
        let (fastest, _, any) = match tail_start {
            Some((a0, rates)) if a0 == a => rates,
            _ => tail_rates(a),
        };
        let rate = if fastest > 0.0 { fastest } else { any };
        (a, 1.0 / rate.max(1e-12))
    };
    let tail_integrand = |u: f64| {
        if u >= 1.0 {
            return [0.0; C];
        }
        let s = tail_a + tail_scale * u / (1.0 - u);
        let jac = tail_scale / ((1.0 - u) * (1.0 - u));
        // (0 where the integrand is, also where the Jacobian has overflowed.)
        integrand(s).map(|v| if v == 0.0 { 0.0 } else { v * jac })
    };
    let mut coarse = [0.0f64; C];
    for w in cuts.windows(2) {
        let r = integrate_adaptive(integrand, w[0], w[1], f64::INFINITY, 0.0, 1);
        for c in 0..C {
            coarse[c] += r.value[c].abs();
        }
    }
    if tail {
        let r = integrate_adaptive(tail_integrand, 0.0, 1.0, f64::INFINITY, 0.0, 1);
        for c in 0..C {
            coarse[c] += r.value[c].abs();
        }
    }
    let pieces = (cuts.len().saturating_sub(1) + tail as usize).max(1) as f64;
    let smallest = coarse.iter().copied().filter(|v| *v > 0.0).fold(f64::INFINITY, f64::min);
    let abs_tol = if smallest.is_finite() {
        tolerance * smallest / pieces
    } else {
        1e-300
    };
    for w in cuts.windows(2) {
        let r = integrate_adaptive(integrand, w[0], w[1], abs_tol, tolerance, 400);
        converged &= r.converged;
        for c in 0..C {
            value[c] += r.value[c];
            error[c] += r.error[c];
        }
    }
    if tail {
        let r = integrate_adaptive(tail_integrand, 0.0, 1.0, abs_tol, tolerance, 400);
        converged &= r.converged;
        for c in 0..C {
            value[c] += r.value[c];
            error[c] += r.error[c];
        }
    }
    let tau = total_tau(ray.s_max);
    let transmittance = tau.map(|t| (-t).exp());
    (
        RayResult {
            inscatter: value,
            transmittance,
            sun_transmittance: [1.0; C],
            error,
            rel_bound: 0.0,
        },
        converged,
    )
}

fn render_channels<const C: usize, const K: usize>(
    scene: &Scene,
    report: &mut Report,
    progress: Option<Progress<'_>>,
    cancel: Option<&AtomicBool>,
) -> Result<Images, RenderError> {
    let t0 = Instant::now();
    // The preparation steps (media, BVH, shadow volumes: milliseconds in
    // every scene measured) are not interrupted inside, but none starts once
    // a cancel is seen; the sun disc tables (seconds for a needle lobe at the
    // node budget) stop inside.
    let cancelled = || cancel.is_some_and(|c| c.load(Ordering::Relaxed));
    let cam = CameraRays::new(&scene.camera);
    let mut lights = prepare_lights::<C>(scene, report);
    let mut stage_lights = prepare_stage_lights::<C>(scene, report)?;
    let media = prepare_media::<C>(scene, &lights, report);
    if cancelled() {
        return Err(RenderError::Cancelled);
    }
    report.error.sun_disc_rel = sun_disc_effect(scene, &media, &mut lights, report, &cancelled).ok_or(RenderError::Cancelled)?;
    if cancelled() {
        return Err(RenderError::Cancelled);
    }
    let tolerance = scene.output.tolerance;
    let mut t = report.time("plan", t0);

    // The meshes the camera sees and those that cast shadows (Blender's Ray
    // Visibility > Camera and > Shadow). Each list is the scene's own unless a
    // mesh leaves it (then the rest is copied); when the two lists differ, the
    // shadow rays get a BVH of their own (a second build).
    let split = scene.meshes.iter().any(|m| m.visible_to_camera != m.casts_shadows);
    let pick = |f: fn(&Mesh) -> bool| -> Cow<'_, [Mesh]> {
        if scene.meshes.iter().all(f) {
            Cow::Borrowed(scene.meshes.as_slice())
        } else {
            Cow::Owned(scene.meshes.iter().filter(|m| f(m)).cloned().collect())
        }
    };
    let (camera_meshes, shadow_meshes) = (pick(|m| m.visible_to_camera), pick(|m| m.casts_shadows));
    if scene.meshes.iter().any(|m| !m.visible_to_camera || !m.casts_shadows) {
        let see_through = scene.meshes.iter().filter(|m| !m.visible_to_camera && m.casts_shadows).count();
        let no_shadow = scene.meshes.iter().filter(|m| m.visible_to_camera && !m.casts_shadows).count();
        let neither = scene.meshes.iter().filter(|m| !m.visible_to_camera && !m.casts_shadows).count();
        for (n, what, why) in [
            (
                see_through,
                "meshes in view rays",
                "visible_to_camera false: view rays pass through them (they still cast shadows)",
            ),
            (
                no_shadow,
                "meshes in the lights' shadows",
                "casts_shadows false: they shadow no light (they still end view rays)",
            ),
            (neither, "meshes", "visible_to_camera and casts_shadows false: left out entirely"),
        ] {
            if n > 0 {
                report.plan.left_out(format!("{n} {what}"), why);
            }
        }
    }
    let (tris, owner) = world_triangles(&camera_meshes);
    // The shadow casters' triangles when they are not the camera's.
    let shadow_tris: Option<Vec<Triangle>> = split.then(|| world_triangles(&shadow_meshes).0);
    report.stats.triangles = scene.meshes.iter().map(|m| m.triangles.len() as u64).sum();
    // What the smoothness test of [`smooth`] needs of the scene: the
    // surfaces' planes and each light's volume and shadow casters. Only when
    // the media and the lights' distributions are smooth.
    let smooth_scene: Result<(smooth::Planes, Vec<smooth::Casters>), &str> = {
        let media_smooth = media.iter().all(|m| match m {
            PreparedMedium::Homogeneous(h) => h.bounds.is_none(),
            PreparedMedium::HeightFog(_) => true,
            _ => false,
        });
        let lights_smooth = stage_lights
            .points
            .iter()
            .all(|p| p.light.smooth_between_kinks() && p.light.ellipse.is_none() && p.light.cos_reach > 0.0);
        if !scene.output.interpolate_smooth_pixels && !scene.output.profile_filter {
            Err("not asked for (output.interpolate_smooth_pixels and output.profile_filter false)")
        } else if media.is_empty() || stage_lights.is_empty() {
            Err("no stage light in a medium")
        } else if !media_smooth {
            Err("a medium with a boundary inside the scene (fog layer, dry-ice layer, smoke ellipsoid, bounded box)")
        } else if !lights_smooth {
            Err(
                "a light whose distribution is not smooth (IES, pattern, table, elliptical) or whose cone is not narrower than a hemisphere",
            )
        } else if stage_lights.topology_bits() > 62 {
            Err("too many lights and cones for the 62-bit topology code")
        } else {
            let eye = cam.position;
            let Some(planes) = smooth::Planes::new_cancellable(&camera_meshes, &tris, &cancelled) else {
                return Err(RenderError::Cancelled);
            };
            // The casters' planes: the camera's unless the shadow casters differ.
            let own_shadow_planes = match shadow_tris.as_ref() {
                Some(st) => match smooth::Planes::new_cancellable(&shadow_meshes, st, &cancelled) {
                    Some(p) => Some((p, st)),
                    None => return Err(RenderError::Cancelled),
                },
                None => None,
            };
            let (caster_planes, caster_tris) = match &own_shadow_planes {
                Some((p, st)) => (p, st.as_slice()),
                None => (&planes, tris.as_slice()),
            };
            let points = stage_lights.points.iter().map(|p| {
                if !p.casts_shadows {
                    return smooth::Casters::None;
                }
                let l = &p.light;
                let (apex, axis, cos_reach) = (l.position, l.frame.axis, l.cos_reach);
                smooth::Casters::of(caster_tris, caster_planes, eye, apex, |c, r| {
                    stage::sphere_may_touch_cone(apex, axis, cos_reach, c, r)
                })
            });
            // A window's prism has flat faces and edges: where a ray's entry
            // or exit face changes, the in-scatter has a kink its code does
            // not record. Rays crossing a prism are never interpolated.
            let windows = stage_lights.windows.iter().map(|_| smooth::Casters::Any);
            let casters: Vec<smooth::Casters> = points.chain(windows).collect();
            Ok((planes, casters))
        }
    };
    // Floors that end the view rays beneath the lights' cones, for the unlit
    // tiles ([`unlit::Floor`]): of the planes' triangles, the four largest
    // groups by area that qualify.
    // (Only when the unlit tiles may be used: no layer needs the view rays,
    // or point samples need them only for the layers that the surface hit
    // and closed-form transmittance give: `unlit_with_rays`.)
    let unlit_with_rays = scene.output.pixel_filter.radius() == 0.0 && !scene.output.layers.contains(&LayerKind::SunTransmittance);
    let rays_needed = scene.output.layers.iter().any(|k| {
        matches!(
            k,
            LayerKind::Transmittance | LayerKind::SunTransmittance | LayerKind::SurfaceTransmittancePerLight | LayerKind::Depth
        )
    });
    let floors: Vec<unlit::Floor> =
        if scene.output.skip_unlit_tiles && (!rays_needed || unlit_with_rays) && !tris.is_empty() && !stage_lights.points.is_empty() {
            let own;
            let planes = match &smooth_scene {
                Ok((p, _)) => p,
                Err(_) => {
                    let Some(p) = smooth::Planes::new_cancellable(&scene.meshes, &tris, &cancelled) else {
                        return Err(RenderError::Cancelled);
                    };
                    own = p;
                    &own
                }
            };
            // The four largest plane groups by area (ties: the lower group), then
            // their triangles. (A group per triangle of a curved million-triangle
            // mesh: collecting every group's triangles first took ≈ 0.8 s.)
            let mut area = vec![0.0f64; planes.group_count() + 1];
            for (i, t) in tris.iter().enumerate() {
                let g = planes.group_of(i as u32) as usize;
                if g > 0 {
                    area[g] += 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length();
                }
            }
            let mut largest: Vec<usize> = Vec::with_capacity(5);
            for g in 1..area.len() {
                let at = largest.partition_point(|&h| area[h].total_cmp(&area[g]).then(g.cmp(&h)).is_gt());
                if at < 4 {
                    largest.insert(at, g);
                    largest.truncate(4);
                }
            }
            let mut groups: Vec<(u32, Vec<[DVec3; 3]>)> = largest.iter().map(|&g| (g as u32, Vec::new())).collect();
            for (i, t) in tris.iter().enumerate() {
                let g = planes.group_of(i as u32);
                if let Some(k) = largest.iter().position(|&h| h == g as usize) {
                    groups[k].1.push(t.v);
                }
            }
            groups
                .iter()
                .filter_map(|(g, t)| {
                    let (normal, offset) = planes.plane(*g);
                    unlit::Floor::new(t, normal, offset, cam.position)
                })
                .collect()
        } else {
            Vec::new()
        };
    let bvh = if tris.is_empty() {
        report
            .plan
            .left_out("ray casting", "no meshes the camera sees: every view ray runs to the clip end");
        None
    } else {
        report.plan.computed(
            format!("{} triangles in {} meshes", tris.len(), camera_meshes.len()),
            "binned-SAH BVH, first hit per view ray",
        );
        // (Cancelled while it was built: 720 000 triangles took ≈ 0.3 s.)
        let Some(b) = Bvh::build_cancellable(tris, &cancelled) else {
            return Err(RenderError::Cancelled);
        };
        Some(b)
    };
    // The shadow rays' BVH: the view rays' unless the shadow casters differ.
    let own_shadow_bvh = match shadow_tris {
        Some(st) if !st.is_empty() => {
            report.plan.computed(
                format!("{} shadow-casting triangles in {} meshes", st.len(), shadow_meshes.len()),
                "a BVH of their own for the shadow rays (the camera sees other meshes)",
            );
            let Some(b) = Bvh::build_cancellable(st, &cancelled) else {
                return Err(RenderError::Cancelled);
            };
            Some(b)
        }
        _ => None,
    };
    let shadow_bvh = if split { own_shadow_bvh.as_ref() } else { bvh.as_ref() };
    t = report.time("bvh", t);
    if cancelled() {
        return Err(RenderError::Cancelled);
    }
    if !stage_lights.is_empty() {
        prepare_stage_shadows(&shadow_meshes, &mut stage_lights, report, &cancelled)?;
        if scene.meshes.iter().any(|m| !m.visible_to_camera && m.casts_shadows) {
            let wedges = stage_lights.points.iter_mut().map(|p| &mut p.shadows);
            for sw in wedges.chain(stage_lights.windows.iter_mut().map(|w| &mut w.shadows)).flatten() {
                sw.view_rays_cross_casters = true;
            }
        }
        if media.is_empty() {
            report
                .plan
                .left_out("stage lights' in-scatter", "no media: light is scattered only by a medium");
        }
        t = report.time("shadow_volumes", t);
    }
    let n_stage = stage_lights.len().min(stage::MAX_LIGHT_LAYERS);
    let want_per_light = scene.output.layers.contains(&LayerKind::InscatterPerLight) && n_stage > 0;
    let want_surface_t = scene.output.layers.contains(&LayerKind::SurfaceTransmittancePerLight) && n_stage > 0;
    let to_rgb = |v: &[f64; C]| -> [f64; 3] {
        if C == 3 {
            [v[0], v[1], v[2]]
        } else {
            let mut buf = [0.0; SPECTRAL_SAMPLES];
            buf.copy_from_slice(&v[..SPECTRAL_SAMPLES]);
            spectrum::spectrum_to_rec709(&buf)
        }
    };

    let (w, h) = (cam.width, cam.height);
    let n = w * h;
    let want = |k: LayerKind| scene.output.layers.contains(&k);
    let (want_sun_t, want_error) = (want(LayerKind::SunTransmittance), want(LayerKind::Error));
    // The view transmittance is filtered (and its smoothness tested) only for
    // the layers made from it; otherwise every sample holds it at 1, and
    // neither the classification nor the filter spends rays on it.
    let need_t = want(LayerKind::Transmittance) || want_sun_t || want_surface_t;
    // Whether any requested layer needs the view ray itself, not only its in-scatter.
    let need_ray = need_t || want(LayerKind::Depth);
    let spectral = C != 3;
    let abs_weights = if spectral { Some(abs_rgb_weights()) } else { None };
    // One view ray, reduced to RGB (identity for C = 3), written over `out`
    // (a Sample with 16 per-light slots is ≈ 950 bytes: pass 1 reuses one
    // per row instead of zeroing and returning a new one per pixel, −17 % of
    // its time on a 768×432 frame whose rays all miss the one spot). Only
    // the first `n_stage` per-light slots are ever written, so the rest stay
    // as `Sample::default()` left them.
    // Whether the rays' topology codes are computed for the interpolation
    // ([`smooth`]): the conditions of `smooth_on` below that do not need
    // the unlit grid (which needs the same and more).
    let want_topology = smooth_scene.is_ok()
        && scene.output.interpolate_smooth_pixels
        && !want_sun_t
        && scene.output.skip_unlit_tiles
        && matches!(scene.camera, crate::scene::Camera::Perspective(_))
        && lights.suns.is_empty()
        && lights.ambient.iter().all(|a| *a == 0.0);
    // A transmittance per channel in RGB, as [`Sample`]s hold it.
    let transmittance_rgb = |t: &[f64; C]| -> [f64; 3] {
        if spectral {
            let mut buf = [0.0; SPECTRAL_SAMPLES];
            buf.copy_from_slice(&t[..SPECTRAL_SAMPLES]);
            spectrum::spectral_transmittance_to_rgb(&buf)
        } else {
            [t[0], t[1], t[2]]
        }
    };
    // Per light `k`: T_view · T(surface point `sp` → light), in RGB
    // (`t_view` per channel), unclamped.
    let surface_transmittance = |t_view: &[f64; C], sp: DVec3, k: usize| -> [f64; 3] {
        let tau = light_path_depth(&stage_lights, &media, k, sp);
        let tc: [f64; C] = std::array::from_fn(|c| t_view[c] * (-tau[c]).exp());
        transmittance_rgb(&tc)
    };
    let sample_into = |x: f64, y: f64, out: &mut Sample<K>| {
        // Every pass (point samples, interpolation checks, the pixel filter's
        // lattice) traces through here, so this one test stops them all; the
        // caller discards the images.
        if cancelled() {
            *out = Sample::default();
            return;
        }
        let per_light = &mut out.lights;
        for v in per_light.iter_mut().take(n_stage) {
            *v = [0.0; 3];
        }
        let p = shade_pixel(
            &cam,
            bvh.as_ref(),
            shadow_bvh,
            &media,
            &lights,
            &stage_lights,
            x,
            y,
            tolerance,
            want_topology,
            per_light,
            &to_rgb,
        );
        let (l, t, st, e) = if spectral {
            let mut buf = [0.0; SPECTRAL_SAMPLES];
            buf.copy_from_slice(&p.result.inscatter);
            let l = spectrum::spectrum_to_rec709(&buf);
            buf.copy_from_slice(&p.result.transmittance);
            let t = spectrum::spectral_transmittance_to_rgb(&buf);
            buf.copy_from_slice(&p.result.sun_transmittance);
            let st = spectrum::spectral_transmittance_to_rgb(&buf);
            let mut e = [0.0; 3];
            if let Some(wts) = &abs_weights {
                for c in 0..3 {
                    e[c] = p.result.error.iter().zip(wts[c].iter()).map(|(v, k)| v.abs() * k).sum();
                }
            }
            (l, t, st, e)
        } else {
            let r = &p.result;
            (
                [r.inscatter[0], r.inscatter[1], r.inscatter[2]],
                [r.transmittance[0], r.transmittance[1], r.transmittance[2]],
                [r.sun_transmittance[0], r.sun_transmittance[1], r.sun_transmittance[2]],
                [r.error[0], r.error[1], r.error[2]],
            )
        };
        // Per light: T_view · T(surface → light), weighted by `hit` so that the
        // filter averages over the surface samples only.
        let surface_t = &mut out.surface_t;
        if want_surface_t {
            for v in surface_t.iter_mut().take(n_stage) {
                *v = [0.0; 3];
            }
        }
        if want_surface_t && let Some(sp) = p.surface_point {
            for (k, out) in surface_t.iter_mut().enumerate().take(n_stage) {
                *out = surface_transmittance(&p.result.transmittance, sp, k);
            }
        }
        // Closed forms carry their rounding bound as a relative constant; only
        // numeric pixels need a division.
        let mut rel = p.result.rel_bound;
        let numeric = match (p.numeric, &p.stage) {
            (n, Some(sh)) if sh.segments > 0 => Some(n.unwrap_or(true) && sh.converged),
            (n, _) => n,
        };
        if numeric.is_some() {
            for c in 0..3 {
                if l[c].abs() > 0.0 {
                    rel = rel.max(e[c] / l[c].abs());
                }
            }
        }
        out.l = l;
        out.t = if need_t { t } else { [1.0; 3] };
        out.st = st;
        out.e = e;
        out.rel = rel;
        out.depth = p.depth;
        out.hit = p.hit;
        out.surface = p.surface;
        out.numeric = numeric;
        out.in_medium = p.in_medium;
        out.light_layers = if want_per_light || want_surface_t { n_stage as u8 } else { 0 };
        out.hit_weight = if p.hit { 1.0 } else { 0.0 };
        out.stage_segments = p.stage.map_or(0, |s| s.segments);
        out.stage_skipped = p.stage.map_or(0, |s| s.lights_skipped);
        out.stage_crossed = p.stage.map_or(0, |s| s.lights_crossed);
        out.stage_shadow_rays = p.stage.map_or(0, |s| s.shadow_rays);
        out.stage_clamped = p.stage.is_some_and(|s| s.clamped);
        out.topology = p.stage.map_or(0, |s| s.topology);
    };
    let sample = |x: f64, y: f64| -> Sample<K> {
        let mut s = Sample::<K>::default();
        sample_into(x, y, &mut s);
        s
    };

    let filter = match scene.camera {
        crate::scene::Camera::Perspective(_) => scene.output.pixel_filter,
        crate::scene::Camera::Equirectangular(_) => filter::PixelFilter::None,
    };
    // The ring of centre samples the classification reads around the frame, px.
    let ring = if filter.radius() > 0.0 {
        filter.radius().ceil() as usize
    } else {
        0
    };
    // Tiles whose rays, with every pixel any of their pixels' results read,
    // miss every light's illumination volume ([`unlit`]): in-scatter exactly
    // 0, and when no requested layer needs the ray, not traced. A pixel's
    // result reads centre samples within max(ring, 2) + 1 px (window scale
    // and silhouettes ±ring, Laplacian terms of the 3×3 neighbourhood ±2,
    // step terms ±2, the flags' dilation ±1) and its filter window, within
    // the ring.
    let unlit_grid: Option<(usize, Vec<bool>)> = {
        let cones: Option<Vec<unlit::Volume>> = stage_lights
            .points
            .iter()
            .map(|p| {
                let c = p.light.cos_reach;
                (c > 0.0).then(|| {
                    unlit::Volume::Cone(unlit::Cone {
                        apex: p.light.position,
                        axis: p.light.frame.axis,
                        half_angle: c.min(1.0).acos(),
                    })
                })
            })
            .collect();
        let prisms = stage_lights.windows.iter().map(|w| {
            unlit::Volume::Prism(unlit::Prism {
                corners: w.light.corners(),
                recession: -w.light.to_light,
            })
        });
        let perspective = matches!(scene.camera, crate::scene::Camera::Perspective(_));
        let only_stage_light = lights.suns.is_empty() && lights.ambient.iter().all(|a| *a == 0.0);
        match cones {
            Some(mut volumes) if scene.output.skip_unlit_tiles && (!need_ray || unlit_with_rays) && perspective && only_stage_light => {
                volumes.extend(prisms);
                let read = if ring > 0 { ring.max(2) + 1 } else { 0 };
                Some(unlit::unlit_tiles(&cam, &volumes, &floors, ring, read as f64))
            }
            _ => None,
        }
    };
    let unlit = |x: isize, y: isize| -> bool {
        match &unlit_grid {
            Some((cols, flags)) => {
                let (tx, ty) = (
                    (x + ring as isize) as usize / unlit::TILE,
                    (y + ring as isize) as usize / unlit::TILE,
                );
                flags[ty * cols + tx]
            }
            None => false,
        }
    };
    // Per row, the columns [lo, hi) outside which every pixel is unlit (the
    // whole row without unlit tiles): the passes below skip the rest.
    let row_spans: Vec<(usize, usize)> = (0..h)
        .map(|y| match &unlit_grid {
            None => (0, w),
            Some((cols, flags)) => {
                let ty = (y + ring) / unlit::TILE;
                let tiles = &flags[ty * cols..(ty + 1) * cols];
                match (tiles.iter().position(|f| !f), tiles.iter().rposition(|f| !f)) {
                    (Some(a), Some(b)) => (
                        (a * unlit::TILE).saturating_sub(ring).min(w),
                        ((b + 1) * unlit::TILE).saturating_sub(ring).min(w),
                    ),
                    _ => (0, 0),
                }
            }
        })
        .collect();

    // Images of point lights: there the in-scatter has an integrable 1/r
    // peak, which the filter integrates in polar coordinates about the image
    // (or, where it cannot, with lattice cells down to 1/2048 px).
    // With the image directions of the lines through them along which the
    // in-scatter's peak has features (its cones' silhouettes), for the pixel
    // filter's polar rule; and with each light's beam as geometry in the
    // image (no profile table) and the image direction of its axis: where
    // the beam is narrower than the lattice's cells, the squares it crosses
    // are integrated about the image too.
    let (polar_images, image_beams): (Vec<filter::LightImage>, Vec<Option<ImageBeam>>) = stage_lights
        .points
        .iter()
        .filter_map(|p| {
            let at = cam.project(p.light.position)?;
            let image = filter::LightImage {
                at,
                cuts: light_image_cuts(&cam, &p.light, at),
            };
            let beam = (p.light.cos_reach > 0.0)
                .then(|| profile::BeamLight::new(&p.light, &cam, p.casts_shadows, false, tolerance))
                .flatten()
                .map(|geometry| ImageBeam {
                    geometry,
                    forward: image_direction(&cam, p.light.position, p.light.frame.axis, at),
                });
            Some((image, beam))
        })
        .unzip();
    let light_images: Vec<(f64, f64)> = polar_images.iter().map(|p| p.at).collect();
    // Pixels may be interpolated ([`smooth`]) with unlit tiles on, or when
    // a layer needs every ray anyway (transmittance, depth: then unlit tiles
    // are on with point samples only; under a pixel filter the deferred
    // pixels outside every beam cost a surface hit and cone tests).
    let smooth_on = want_topology && (need_ray || unlit_grid.is_some());
    // The filter across beams from their profiles ([`profile`]): when all
    // in-scatter comes from spot lamps in media without boundaries (the
    // interpolation's conditions) and a perspective camera's pixels are filtered.
    let profile_on = scene.output.profile_filter
        && smooth_scene.is_ok()
        && filter.radius() > 0.0
        && lights.suns.is_empty()
        && lights.ambient.iter().all(|a| *a == 0.0)
        && stage_lights.windows.is_empty()
        && stage_lights.points.iter().all(|p| p.light.is_axial() && p.light.cos_reach > 0.0);
    const ST: usize = smooth::STENCIL;
    // Which interpolation pass, if any, pixel (col, row) is left for: the
    // half-spacing `s` of its level (2, the first: the pixels with even x
    // and y not on the lattice of multiples of 4, interpolated from samples
    // 4 px apart; 1, the second: the others, from samples 2 px apart), or 0
    // when it is traced in
    // pass 1. A pixel is traced when the stencil of its level leaves the
    // frame or reaches near a light's image, or when it is unlit; on rows
    // of its level's lattice it is interpolated along x, on the others
    // along y.
    let near_light_row: Vec<bool> = (0..h)
        .map(|y| {
            light_images
                .iter()
                .any(|&(_, iy)| (iy - (y as f64 + 0.5)).abs() <= 2.0 * smooth::LIGHT_IMAGE_MARGIN)
        })
        .collect();
    let near_light = |x: f64, y: f64, m: f64| -> bool { light_images.iter().any(|&(ix, iy)| (ix - x).abs() <= m && (iy - y).abs() <= m) };
    let level_of = |col: usize, row: usize| -> usize {
        if !smooth_on || (col.is_multiple_of(4) && row.is_multiple_of(4)) || unlit(col as isize, row as isize) {
            return 0;
        }
        let s = if col.is_multiple_of(2) && row.is_multiple_of(2) { 2 } else { 1 };
        let reach = ST * s;
        let stencil_inside = if row.is_multiple_of(2 * s) {
            col >= reach && col + reach < w
        } else {
            row >= reach && row + reach < h
        };
        let m = smooth::LIGHT_IMAGE_MARGIN * s as f64;
        let (x, y) = (col as f64 + 0.5, row as f64 + 0.5);
        if stencil_inside && !(near_light_row[row] && near_light(x, y, m)) {
            s
        } else {
            0
        }
    };
    let deferred = |col: usize, row: usize| -> bool { level_of(col, row) > 0 };
    // A pixel's surface (triangle + 1, 0: none), view ray and the distance
    // to its surface hit (`None`: no hit), as [`shade_pixel`] finds them.
    let view_ray_of = |x: f64, y: f64| -> (u32, ViewRay, Option<f64>) {
        let dir = cam.direction(x, y);
        let start = cam.start_distance(dir);
        let (end, surface, hit) = match bvh.as_ref().and_then(|b| b.closest_hit(cam.position, dir, start, cam.clip_end)) {
            Some(hit) => (hit.t, hit.triangle + 1, Some(hit.t)),
            None => (cam.clip_end, 0, None),
        };
        let ray = ViewRay {
            origin: cam.position + dir * start,
            dir,
            s_max: (end - start).max(0.0),
        };
        (surface, ray, hit)
    };
    // A pixel's surface (triangle + 1, 0: none) and topology code
    // ([`smooth::PRESENT`] set; 0 below it: the ray crosses no light's
    // volume, in-scatter 0), from one surface hit and the cone tests.
    // With it, what the ray-dependent layers need: the view ray and the
    // distance to its surface hit (`None`: no hit).
    let code_of = |x: f64, y: f64, buf: &mut Vec<(f64, f64)>| -> (u32, u64, ViewRay, Option<f64>) {
        let (surface, ray, hit) = view_ray_of(x, y);
        let Ok((_, casters)) = &smooth_scene else { return (0, 0, ray, hit) };
        let end = hit.unwrap_or(cam.clip_end);
        let code = smooth::PRESENT | stage_lights.topology(&ray, buf, &|k| casters[k].may_shadow(cam.position, ray.dir, end));
        (surface, code, ray, hit)
    };
    // The view transmittance of a ray, as [`shade_pixel`] computes it (one
    // medium: its closed form; several: `exp(−Σ τ)`), per channel.
    let view_transmittance = |ray: &ViewRay| -> [f64; C] {
        let mut crossed = media.iter().filter(|m| m.segment(ray).is_some());
        let t: [f64; C] = match (crossed.next(), crossed.next()) {
            (None, _) => [1.0; C],
            (Some(m), None) => m.closed_form(ray, &lights).transmittance,
            _ => {
                let mut tau = [0.0; C];
                for m in &media {
                    let d = m.optical_depth(ray, ray.s_max);
                    for c in 0..C {
                        tau[c] += d[c];
                    }
                }
                tau.map(|v| (-v).exp())
            }
        };
        t
    };
    // The same for a traced sample, from its own surface hit and cone tests.
    let traced_code = |x: f64, y: f64, s: &Sample<K>| -> u64 {
        let Ok((_, casters)) = &smooth_scene else { return 0 };
        let end = if s.hit { s.depth } else { cam.clip_end };
        let dir = cam.direction(x, y);
        let shadowed =
            (0..casters.len()).any(|k| (k >= 64 || s.stage_crossed >> k & 1 == 1) && casters[k].may_shadow(cam.position, dir, end));
        smooth::PRESENT | s.topology | u64::from(shadowed) << 63
    };
    // The plane group + 1 of a surface (triangle + 1; 1: none).
    let group_of = |surface: u32| -> u32 {
        match &smooth_scene {
            Ok((planes, _)) if surface > 0 => planes.group_of(surface - 1) + 1,
            _ => 1,
        }
    };
    let want_depth = want(LayerKind::Depth);
    // What a pixel whose in-scatter is not integrated (interpolated, or
    // outside every light's volume) writes besides it: the ray-dependent
    // layers, exact, from its own ray (`exact_layers`), and the per-light
    // in-scatter. In the interpolation's passes `lights` is a scratch of
    // the fill; the record written back holds where the pixel's per-light
    // values start in a side list (`Lights`).
    #[derive(Clone, Copy)]
    struct Extra<const K: usize> {
        t: [f32; 3],
        depth: f32,
        lights: [[f32; 3]; K],
        surface_t: [[f32; 3]; K],
    }
    let exact_layers = |ray: &ViewRay, hit: Option<f64>, x: &mut Extra<K>| {
        if need_t {
            let t = view_transmittance(ray);
            x.t = transmittance_rgb(&t).map(|v| v.clamp(0.0, 1.0) as f32);
            // Per light: T_view · T(surface → light) at the surface hit
            // (as `sample_into`), T_view without one.
            if want_surface_t {
                for k in 0..n_stage {
                    x.surface_t[k] = if hit.is_some() {
                        let sp = ray.origin + ray.dir * ray.s_max;
                        surface_transmittance(&t, sp, k).map(|v| v.clamp(0.0, 1.0) as f32)
                    } else {
                        x.t
                    };
                }
            }
        }
        if want_depth {
            x.depth = hit.map_or(DEPTH_NO_HIT, |t| t as f32);
        }
    };
    let extra0 = Extra::<K> {
        t: [1.0; 3],
        depth: DEPTH_NO_HIT,
        lights: [[0.0; 3]; K],
        surface_t: [[1.0; 3]; K],
    };
    // Pass 1: the centre of every pixel, rows in parallel, straight into the
    // output buffers (plus the surface id for silhouette detection).
    // Layers not requested get one dummy element per row instead of a full buffer.
    let mut inscatter = vec![[0f32; 3]; n];
    // Layers filled with a constant (T = 1, no depth) are full-size only when
    // requested: a constant buffer is written page by page (1.3 ms for 4 MB
    // at 768×432), a zeroed one costs nothing until touched.
    let mut transmittance = vec![[1f32; 3]; if need_t { n } else { h }];
    let mut depth = vec![DEPTH_NO_HIT; if want_depth { n } else { h }];
    let mut surface = vec![0u32; n];
    let mut sun_t = vec![[1f32; 3]; if want_sun_t { n } else { h }];
    // The interpolation reads the samples' own errors (the largest channel:
    // a quarter of the memory of the error layer, whose pages each touch
    // costs) and their topology codes ([`smooth::PRESENT`]: a code to read;
    // the surface comes from `surface`).
    let mut error = vec![[0f32; 3]; if want_error { n } else { h }];
    let mut own_error = vec![0f32; if smooth_on || profile_on { n } else { h }];
    let mut codes = vec![0u64; if smooth_on { n } else { h }];
    let (sun_chunk, err_chunk) = (if want_sun_t { w } else { 1 }, if want_error { w } else { 1 });
    let max_of = |e: &[f32; 3]| e[0].max(e[1]).max(e[2]);
    let (t_chunk, d_chunk) = (if need_t { w } else { 1 }, if want_depth { w } else { 1 });
    let smooth_chunk = if smooth_on { w } else { 1 };
    // Rows done; the count and the callback under one lock, so that the
    // calls arrive in order and the last reports the total.
    let done = std::sync::Mutex::new(0usize);
    // The per-light layers, written by the rows in place: per row, its slice
    // of every light's image. (Rows of their own, copied after the pass,
    // were 100 MB of temporaries and a serial copy at 1920×1080 with four
    // lights, and `vec![vec![..]; k]` cloned each zeroed image.) A pixel the
    // pass does not write stays 0, as the rows' defaults were.
    let mut light_inscatter: Vec<Vec<[f32; 3]>> = if want_per_light {
        (0..n_stage).map(|_| vec![[0f32; 3]; n]).collect()
    } else {
        Vec::new()
    };
    let mut light_surface_transmittance: Vec<Vec<[f32; 3]>> = if want_surface_t {
        (0..n_stage).map(|_| vec![[0f32; 3]; n]).collect()
    } else {
        Vec::new()
    };
    let light_rows = rows_of_images(&mut light_inscatter, w, h);
    let surface_rows = rows_of_images(&mut light_surface_transmittance, w, h);
    let row_stats: Vec<RowStats> = inscatter
        .par_chunks_mut(w)
        .zip(transmittance.par_chunks_mut(t_chunk))
        .zip(depth.par_chunks_mut(d_chunk))
        .zip(surface.par_chunks_mut(w))
        .zip(sun_t.par_chunks_mut(sun_chunk))
        .zip(error.par_chunks_mut(err_chunk))
        .zip(own_error.par_chunks_mut(if smooth_on || profile_on { w } else { 1 }))
        .zip(codes.par_chunks_mut(smooth_chunk))
        .zip(light_rows.into_par_iter().zip(surface_rows.into_par_iter()))
        .enumerate()
        .map(|(row, (chunks, (mut light_row, mut surface_row)))| {
            let (((((((l_row, t_row), d_row), id_row), s_row), e_row), oe_row), code_row) = chunks;
            let mut st = RowStats::default();
            let mut s = Sample::<K>::default();
            // (A layer that needs the rays: every pixel's, unlit or not.)
            let (lo, hi) = if need_ray { (0, w) } else { row_spans[row] };
            st.unlit += (w - (hi - lo)) as u64;
            let mut extra = extra0;
            for col in lo..hi {
                if unlit(col as isize, row as isize) {
                    // The buffers' defaults: no in-scatter, no error; the
                    // ray-dependent layers from the surface hit alone.
                    st.unlit += 1;
                    if need_ray {
                        let (id, ray, hit) = view_ray_of(col as f64 + 0.5, row as f64 + 0.5);
                        st.hits += u64::from(hit.is_some());
                        exact_layers(&ray, hit, &mut extra);
                        id_row[col] = id;
                        if need_t {
                            t_row[col] = extra.t;
                        }
                        if want_depth {
                            d_row[col] = extra.depth;
                        }
                        if want_surface_t {
                            for k in 0..n_stage {
                                surface_row[k][col] = extra.surface_t[k];
                            }
                        }
                    }
                    continue;
                }
                if deferred(col, row) {
                    continue;
                }
                sample_into(col as f64 + 0.5, row as f64 + 0.5, &mut s);
                if want_per_light {
                    for k in 0..n_stage {
                        light_row[k][col] = s.lights[k].map(|v| v as f32);
                    }
                }
                if want_surface_t {
                    for k in 0..n_stage {
                        surface_row[k][col] = surface_transmittance_of(&s, k);
                    }
                }
                let e = s.e.map(|v| v as f32);
                l_row[col] = s.l.map(|v| v as f32);
                if need_t {
                    t_row[col] = s.t.map(|v| v.clamp(0.0, 1.0) as f32);
                }
                if want_depth {
                    d_row[col] = if s.hit { s.depth as f32 } else { DEPTH_NO_HIT };
                }
                id_row[col] = s.surface;
                if want_sun_t {
                    s_row[col] = s.st.map(|v| v.clamp(0.0, 1.0) as f32);
                }
                if want_error {
                    e_row[col] = e;
                }
                if smooth_on || profile_on {
                    oe_row[col] = max_of(&e);
                }
                if smooth_on {
                    code_row[col] = traced_code(col as f64 + 0.5, row as f64 + 0.5, &s);
                }
                st.add(&s);
            }
            if let Some(cb) = progress {
                let mut d = done.lock().unwrap_or_else(|e| e.into_inner());
                *d += 1;
                cb(RenderStage::Rows, *d, h);
            }
            st
        })
        .collect();
    let mut stats = RowStats::default();
    for r in &row_stats {
        stats.merge(r);
    }
    // Passes 1b and 1c, per level: the deferred pixels, interpolated from
    // six samples 2s px apart where that meets the tolerance
    // ([`smooth::interpolate`]), else traced: first along x on the rows of
    // the level's lattice (in place: a row reads only its own lattice
    // pixels), then along y on the rows between (reading the lattice rows,
    // now complete; written back after).
    if smooth_on {
        #[derive(Clone, Copy)]
        enum Lights {
            None,
            Listed(u32),
        }
        #[derive(Clone, Copy)]
        struct Record {
            i: usize,
            t: [f32; 3],
            depth: f32,
            lights: Lights,
        }
        // Whether a filled pixel lists per-light values (in-scatter, then
        // surface transmittance) for the write-back.
        let listed = want_per_light || want_surface_t;
        // Channels that are exactly 0 on every ray, per light (in per-light
        // layer order: points, then windows) and for the sum: the light's
        // colour is 0 there, and the integrand is a product with it. Their
        // samples' own errors are 0 too, so the interpolation does not fail
        // on `error > tolerance · 0` (the samples store their largest
        // channel's error; a pure red gel was never interpolated, and per-light
        // layers failed for every light with a zero channel). RGB only: a
        // spectral render's conversion mixes the channels.
        let light_zero: Vec<[bool; 3]> = stage_lights
            .points
            .iter()
            .map(|p| p.light.intensity)
            .chain(stage_lights.windows.iter().map(|w| w.light.irradiance))
            .map(|v| std::array::from_fn(|c| C == 3 && v[c] == 0.0))
            .collect();
        // The sum's zero channels at a sample follow from the lights its ray
        // crosses, read from its topology code (a light's bits are all 0
        // when the ray misses its volume): a channel is 0 when every crossed
        // light's colour is 0 there.
        let light_bits = stage_lights.topology_masks();
        let zero_for_code = |code: u64| -> [bool; 3] {
            std::array::from_fn(|c| light_bits.iter().zip(&light_zero).all(|(bits, zero)| code & bits == 0 || zero[c]))
        };
        let mask = |e: [f64; 3], zero: &[bool; 3]| -> [f64; 3] { std::array::from_fn(|c| if zero[c] { 0.0 } else { e[c] }) };
        // One deferred pixel, given its six samples (in-scatter, error,
        // surface, code) and their pixel indices (for the per-light images),
        // and what it adds to the row's statistics.
        #[allow(clippy::too_many_arguments)]
        let fill = |col: usize,
                    row: usize,
                    stencil: &[smooth::StencilSample; 6],
                    at: [usize; 6],
                    light_images: &[Vec<[f32; 3]>],
                    st: &mut RowStats,
                    s: &mut Sample<K>,
                    buf: &mut Vec<(f64, f64)>,
                    extra: &mut Extra<K>| {
            if cancelled() {
                // Skipped: code 0 is "no sample" to the pixels that read it.
                *s = Sample::default();
                return ([0.0f32; 3], [0.0f32; 3], 0.0, s.surface, 0, Lights::None);
            }
            let (x, y) = (col as f64 + 0.5, row as f64 + 0.5);
            // The pixel's own code costs a surface hit and cone tests: only
            // worth it when the six samples agree.
            let common = stencil[0]
                .map(|v| v.2)
                .filter(|g| stencil.iter().all(|v| v.is_some_and(|v| v.2 == *g)));
            // Each light's in-scatter, interpolated from its layer's samples
            // with the samples' own errors of the whole in-scatter (which
            // bound each light's share); every light must meet the tolerance
            // too, else the pixel is traced. The largest estimate, which the
            // pixel's own error then carries for the next level's stencils
            // (so that it bounds every light's error, not only the sum's).
            let per_light = |extra: &mut Extra<K>| -> Option<f32> {
                let errs: [[f64; 3]; 6] = std::array::from_fn(|i| stencil[i].map_or([0.0; 3], |v| v.1.map(f64::from)));
                let mut worst = 0f32;
                for (k, img) in light_images.iter().enumerate() {
                    let vals: [[f64; 3]; 6] = at.map(|i| img[i].map(f64::from));
                    if vals.iter().all(|v| *v == [0.0; 3]) {
                        // A light the samples do not cross (same code: nor does the pixel).
                        extra.lights[k] = [0.0; 3];
                        continue;
                    }
                    let errs = errs.map(|e| mask(e, light_zero.get(k).unwrap_or(&[false; 3])));
                    let (v, e) = smooth::interpolate_values(&vals, &errs, tolerance)?;
                    extra.lights[k] = v.map(|x| x as f32);
                    worst = worst.max(e.iter().fold(0f32, |m, x| m.max(*x as f32)));
                }
                Some(worst)
            };
            // Samples that share a code with the shadow bit (63) set: the
            // pixel is traced, whatever its own code. Otherwise the values
            // are tried first (they need only the samples), and the pixel's
            // own code, a surface hit and cone tests, only when they pass.
            let own = common.filter(|g| g.1 >> 63 == 0).and_then(|g| {
                let values = if g.1 == smooth::PRESENT {
                    None
                } else {
                    Some((smooth::interpolate(stencil, g, tolerance)?, per_light(extra)?))
                };
                let (surface, code, ray, hit) = code_of(x, y, buf);
                ((group_of(surface), code) == g).then_some((surface, code, ray, hit, values))
            });
            match own {
                Some((surface, code, ray, hit, None)) => {
                    // The ray crosses no light's volume (nor do the samples):
                    // in-scatter exactly 0.
                    st.outside += 1;
                    st.hits += u64::from(hit.is_some());
                    exact_layers(&ray, hit, extra);
                    extra.lights = [[0.0; 3]; K];
                    let lights = if listed { Lights::Listed(0) } else { Lights::None };
                    ([0.0f32; 3], [0.0f32; 3], 0.0, surface, code, lights)
                }
                Some((surface, code, ray, hit, Some(((l, e), light_error)))) => {
                    st.add_interpolated(&l, &e);
                    st.hits += u64::from(hit.is_some());
                    exact_layers(&ray, hit, extra);
                    let e = e.map(|v| v as f32);
                    let lights = if listed { Lights::Listed(0) } else { Lights::None };
                    (l.map(|v| v as f32), e, max_of(&e).max(light_error), surface, code, lights)
                }
                _ => {
                    sample_into(x, y, s);
                    st.add(s);
                    let code = traced_code(x, y, s);
                    extra.t = s.t.map(|v| v.clamp(0.0, 1.0) as f32);
                    extra.depth = if s.hit { s.depth as f32 } else { DEPTH_NO_HIT };
                    for k in 0..light_images.len() {
                        extra.lights[k] = s.lights[k].map(|v| v as f32);
                    }
                    if want_surface_t {
                        for k in 0..n_stage {
                            extra.surface_t[k] = surface_transmittance_of(s, k);
                        }
                    }
                    let lights = if listed { Lights::Listed(0) } else { Lights::None };
                    let e = s.e.map(|v| v as f32);
                    (s.l.map(|v| v as f32), e, max_of(&e), s.surface, code, lights)
                }
            }
        };
        let read = |l: &[[f32; 3]], e: &[f32], id: &[u32], code: &[u64], i: usize| -> smooth::StencilSample {
            let zero = zero_for_code(code[i]);
            let own: [f32; 3] = std::array::from_fn(|c| if zero[c] { 0.0 } else { e[i] });
            (code[i] & smooth::PRESENT != 0).then(|| (l[i], own, (group_of(id[i]), code[i])))
        };
        // The ray-dependent layers and per-light in-scatter of the filled
        // pixels, written after each pass (pixel index, extra).
        let write_extra = |records: &[Record],
                           traced: &[[f32; 3]],
                           t_img: &mut [[f32; 3]],
                           d_img: &mut [f32],
                           lights_img: &mut [Vec<[f32; 3]>],
                           surface_img: &mut [Vec<[f32; 3]>]| {
            for r in records {
                if need_t {
                    t_img[r.i] = r.t;
                }
                if want_depth {
                    d_img[r.i] = r.depth;
                }
                if let Lights::Listed(at) = r.lights {
                    for (img, v) in lights_img.iter_mut().chain(surface_img.iter_mut()).zip(&traced[at as usize..]) {
                        img[r.i] = *v;
                    }
                }
            }
        };
        // The record of a filled pixel; a traced pixel's per-light values go to `traced`.
        let record = |i: usize, x: &Extra<K>, lights: Lights, traced: &mut Vec<[f32; 3]>| -> Record {
            let lights = match lights {
                Lights::Listed(_) => {
                    let at = traced.len() as u32;
                    if want_per_light {
                        traced.extend_from_slice(&x.lights[..n_stage]);
                    }
                    if want_surface_t {
                        traced.extend_from_slice(&x.surface_t[..n_stage]);
                    }
                    Lights::Listed(at)
                }
                Lights::None => Lights::None,
            };
            Record {
                i,
                t: x.t,
                depth: x.depth,
                lights,
            }
        };
        let keeps_extra = need_t || want_depth || listed;
        // A pass's records into the images (between passes: the next one reads them).
        macro_rules! write_back {
            ($records:expr, $traced:expr) => {
                write_extra(
                    $records,
                    $traced,
                    &mut transmittance,
                    &mut depth,
                    &mut light_inscatter,
                    &mut light_surface_transmittance,
                )
            };
        }
        // Level by level, coarse to fine: the half-spacing s = 2 fills the
        // lattice of even pixels from the multiples of 4, s = 1 the rest.
        for s in [2usize, 1] {
            let images = &light_inscatter;
            type RowFilled = (RowStats, Vec<Record>, Vec<[f32; 3]>);
            let along_x: Vec<RowFilled> = inscatter
                .par_chunks_mut(w)
                .zip(surface.par_chunks_mut(w))
                .zip(error.par_chunks_mut(err_chunk))
                .zip(own_error.par_chunks_mut(w))
                .zip(codes.par_chunks_mut(w))
                .enumerate()
                .filter(|(row, _)| row.is_multiple_of(2 * s))
                .map(|(row, ((((l_row, id_row), e_row), oe_row), code_row))| {
                    let (mut st, mut smp, mut buf) = (RowStats::default(), Sample::<K>::default(), Vec::new());
                    let (mut records, mut traced) = (Vec::new(), Vec::new());
                    let mut extra = extra0;
                    let (lo, hi) = row_spans[row];
                    // The first column ≡ s (mod 2s) from lo.
                    let first = lo + (3 * s - lo % (2 * s)) % (2 * s);
                    for col in (first.min(hi)..hi).step_by(2 * s) {
                        if level_of(col, row) != s {
                            continue;
                        }
                        let at: [usize; 6] = std::array::from_fn(|k| col + (2 * k + 1) * s - (ST + 1) * s);
                        let stencil: [smooth::StencilSample; 6] = at.map(|c| read(l_row, oe_row, id_row, code_row, c));
                        let (l, e, oe, id, code, lights) = fill(
                            col,
                            row,
                            &stencil,
                            at.map(|c| row * w + c),
                            images,
                            &mut st,
                            &mut smp,
                            &mut buf,
                            &mut extra,
                        );
                        (l_row[col], oe_row[col], id_row[col], code_row[col]) = (l, oe, id, code);
                        if want_error {
                            e_row[col] = e;
                        }
                        if keeps_extra {
                            records.push(record(row * w + col, &extra, lights, &mut traced));
                        }
                    }
                    (st, records, traced)
                })
                .collect();
            for (_, records, traced) in &along_x {
                write_back!(records, traced);
            }
            let images = &light_inscatter;
            type Filled = (Vec<(usize, [f32; 3], [f32; 3], f32, u32, u64)>, Vec<Record>, Vec<[f32; 3]>);
            let along_y: Vec<(Filled, RowStats)> = (0..h.div_ceil(2 * s))
                .into_par_iter()
                .map(|k| {
                    let row = 2 * s * k + s;
                    let (mut st, mut smp, mut buf) = (RowStats::default(), Sample::<K>::default(), Vec::new());
                    let mut extra = extra0;
                    let mut out: Filled = (Vec::new(), Vec::new(), Vec::new());
                    if row >= h {
                        return (out, st);
                    }
                    let (lo, hi) = row_spans[row];
                    for col in (lo.next_multiple_of(s).min(hi)..hi).step_by(s) {
                        if level_of(col, row) != s {
                            continue;
                        }
                        let at: [usize; 6] = std::array::from_fn(|j| (row + (2 * j + 1) * s - (ST + 1) * s) * w + col);
                        let stencil: [smooth::StencilSample; 6] = at.map(|i| read(&inscatter, &own_error, &surface, &codes, i));
                        let (l, e, oe, id, code, lights) = fill(col, row, &stencil, at, images, &mut st, &mut smp, &mut buf, &mut extra);
                        out.0.push((col, l, e, oe, id, code));
                        if keeps_extra {
                            out.1.push(record(row * w + col, &extra, lights, &mut out.2));
                        }
                    }
                    (out, st)
                })
                .collect();
            // Written back: the rows s mod 2s, the second of each chunk.
            inscatter
                .par_chunks_mut(2 * s * w)
                .zip(surface.par_chunks_mut(2 * s * w))
                .zip(error.par_chunks_mut(2 * s * err_chunk))
                .zip(own_error.par_chunks_mut(2 * s * w))
                .zip(codes.par_chunks_mut(2 * s * w))
                .zip(&along_y)
                .for_each(|(((((l_rows, id_rows), e_rows), oe_rows), code_rows), ((out, ..), _))| {
                    for &(col, l, e, oe, id, code) in out {
                        let i = s * w + col;
                        (l_rows[i], id_rows[i], oe_rows[i], code_rows[i]) = (l, id, oe, code);
                        if want_error {
                            e_rows[s * err_chunk + col] = e;
                        }
                    }
                });
            for ((_, records, traced), _) in &along_y {
                write_back!(records, traced);
            }
            for st in along_x.iter().map(|(st, ..)| st).chain(along_y.iter().map(|(_, st)| st)) {
                stats.merge(st);
            }
        }
    }
    drop(codes);
    t = report.time("render", t);
    if cancelled() {
        // The classification of the next pass alone takes 0.2–0.4 s at 1080p.
        return Err(RenderError::Cancelled);
    }

    // Pass 2: Blender's pixel filter where the centre sample is not good enough.
    let mut edge = EdgeStats::default();
    report.stats.light_images = light_images.iter().map(|p| [p.0, p.1]).collect();
    if filter.radius() > 0.0 {
        let reach = filter.radius().ceil() as isize;
        let half_var = 0.5 * filter.variance();
        // Centre samples of the image padded by a ring `reach` pixels wide, so
        // the Laplacian and the silhouette test work on the border pixels too
        // (Cycles' filter reaches outside the frame as well). The ring is traced here.
        let r = reach as usize;
        let (pw, ph) = (w + 2 * r, h + 2 * r);
        // Per row of `padded`, the columns [lo, hi) outside which every
        // pixel, and every pixel within `2r + 2` of it, is unlit. There each
        // pass below would only reproduce its defaults (no in-scatter, no
        // surface, no term, not flagged: each reads within r + 1 px of an
        // unlit pixel, all 0), so nothing is computed. Without unlit tiles:
        // whole rows.
        debug_assert_eq!(r, ring);
        let padded_spans: Vec<(usize, usize)> = match &unlit_grid {
            None => vec![(0, pw); ph],
            Some((cols, flags)) => {
                let tile = unlit::TILE;
                let lit: Vec<Option<(usize, usize)>> = (0..ph)
                    .map(|py| {
                        let row = &flags[(py / tile) * cols..(py / tile + 1) * cols];
                        let lo = row.iter().position(|f| !f)?;
                        let hi = row.iter().rposition(|f| !f)?;
                        Some((lo * tile, ((hi + 1) * tile).min(pw)))
                    })
                    .collect();
                let dilate = 2 * r + 2;
                (0..ph)
                    .map(|py| {
                        lit[py.saturating_sub(dilate)..(py + dilate + 1).min(ph)]
                            .iter()
                            .flatten()
                            .fold(None, |acc: Option<(usize, usize)>, &(lo, hi)| {
                                Some(acc.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))))
                            })
                            .map_or((0, 0), |(lo, hi)| (lo.saturating_sub(dilate), (hi + dilate).min(pw)))
                    })
                    .collect()
            }
        };
        // The same for the frame's rows and columns.
        let frame_spans: Vec<(usize, usize)> = (0..h)
            .map(|y| {
                let (lo, hi) = padded_spans[y + r];
                (lo.saturating_sub(r).min(w), hi.saturating_sub(r).min(w))
            })
            .collect();
        // Which surface a centre sample sees, as one key: the mesh + 1, or 0
        // for none. Triangles of one mesh are one surface (T and L are
        // continuous across its creases).
        let surface_key = |s: u32| if s == 0 { 0 } else { owner[(s - 1) as usize] + 1 };
        // Zeroed (no in-scatter, no surface), and filled only within the
        // spans: elsewhere every pixel is unlit, and when a tile is unlit the
        // transmittance is held at 1 in every sample and not read (`need_t`).
        let mut padded: Vec<CentreSample> = vec![([0.0; 3], [0.0; 3], 0); pw * ph];
        padded
            .par_chunks_mut(pw)
            .zip(&padded_spans)
            .enumerate()
            .for_each(|(py, (prow, &(lo, hi)))| {
                let y = py as isize - reach;
                for (px, out) in prow.iter_mut().enumerate().take(hi).skip(lo) {
                    let x = px as isize - reach;
                    *out = if x >= 0 && y >= 0 && (x as usize) < w && (y as usize) < h {
                        let i = y as usize * w + x as usize;
                        (
                            inscatter[i],
                            if need_t { transmittance[i] } else { [1.0; 3] },
                            surface_key(surface[i]),
                        )
                    } else if unlit(x, y) {
                        ([0.0; 3], [1.0; 3], 0)
                    } else {
                        let s = sample(x as f64 + 0.5, y as f64 + 0.5);
                        (s.l.map(|v| v as f32), s.t.map(|v| v.clamp(0.0, 1.0) as f32), surface_key(s.surface))
                    };
                }
            });
        // Index in `padded` of in-frame pixel (x, y); its neighbours within
        // `reach` are all in `padded`.
        let padded_index = |x: usize, y: usize| (y + r) * pw + x + r;
        // In f32, where the samples are: the maxima are the same values, in
        // half the memory.
        let lmax = |v: &[f32; 3]| v.iter().fold(0.0f32, |m, c| m.max(c.abs()));
        // The scale errors of the filtered image are measured against: the
        // brightest centre sample within the filter's window, which reaches
        // outside the frame (the padded ring: a border pixel whose in-frame
        // samples are all 0 beside a beam just outside had a scale of 0, and
        // its 1e-13 filter error counted as not converged).
        // A dark pixel next to a bright beam is filtered to a tolerance of
        // what its window sees, not of its own (tiny) value — the
        // pixel-filter error is an image-space error, and this is the norm in
        // which it is reported (edge_*).
        // The filter's second-order effect (σ²/2)·∇²L (and on T), from the
        // discrete Laplacian of the centre samples.
        let lap = |x: usize, y: usize| -> ([f64; 3], f64) {
            let j = padded_index(x, y);
            let nb = [padded[j - 1], padded[j + 1], padded[j - pw], padded[j + pw]];
            let me = padded[j];
            let mut el = [0.0; 3];
            let mut et = 0.0f64;
            for c in 0..3 {
                let sl: f64 = nb.iter().map(|n| f64::from(n.0[c])).sum::<f64>() - 4.0 * f64::from(me.0[c]);
                el[c] = half_var * sl.abs();
                if need_t {
                    let st: f64 = nb.iter().map(|n| f64::from(n.1[c])).sum::<f64>() - 4.0 * f64::from(me.1[c]);
                    et = et.max(half_var * st.abs());
                }
            }
            (el, et)
        };
        // A silhouette: a neighbour within reach sees another surface and the
        // centre samples differ by more than the tolerance (a fogged-out
        // horizon needs nothing).
        let silhouette = |x: usize, y: usize| -> bool {
            let j = padded_index(x, y);
            if unlit(x as isize, y as isize) {
                return false;
            }
            let me = padded[j];
            for dy in 0..=2 * r {
                for dx in 0..=2 * r {
                    let other = padded[j + dy * pw + dx - r * pw - r];
                    if me.2 != other.2
                        && (0..3).any(|c| {
                            let (a, b) = (f64::from(me.0[c]), f64::from(other.0[c]));
                            (a - b).abs() > tolerance * a.abs().max(b.abs())
                                || (need_t && f64::from((me.1[c] - other.1[c]).abs()) > tolerance)
                        })
                    {
                        return true;
                    }
                }
            }
            false
        };
        // Where the centre sample stands uncorrected (the frame's border, or a
        // filter wider than the correction allows, see `smooth` below), its
        // filter error is the whole term plus higher orders, which the term
        // alone underestimates at a steep feature (a beam entering at the
        // frame's edge at 768×432: 0.0080 against a term of 0.0067): it is
        // charged twice.
        let uncorrected = |x: usize, y: usize| half_var > 0.25 || x == 0 || x + 1 == w || y == 0 || y + 1 == h;
        let lap_term = |x: usize, y: usize| -> ([f64; 3], f64) {
            let (el, et) = lap(x, y);
            if uncorrected(x, y) {
                (el.map(|e| 2.0 * e), 2.0 * et)
            } else {
                (el, et)
            }
        };
        // Each pixel's terms, then the largest in-scatter term (per channel)
        // of its 3×3 neighbourhood, whose stencils cover the filter's window.
        // That is the filter error charged where the centre sample stands:
        // the pixel's own term is the error only where ∇²L is nearly constant
        // across the window. Next to a beam's edge (narrow beam, 96×54,
        // tolerance 0.1) the own term was up to 8× too small (1.7e-4 against
        // 2.0e-5), and a pixel whose five samples are all 0 claimed no error
        // although its window reaches the beam.
        // A step next to the centre is not in that term. Between the centre
        // and a neighbour, at an unknown offset δ, a step of height Δ leaves
        // the corrected centre sample wrong by up to (½ − σ²/2)·Δ (δ → 0: half
        // the window's weight is across it, and the correction restores
        // σ²/2·Δ), 0.41·Δ for Blender's filter, where the Laplacian term is
        // 0.086·Δ (box occluder, 96×54, tolerance 0.1: the shadow's vertical
        // edge was wrong by up to 6.6e-3 against terms of 2.3e-3). Its
        // signature: both third differences across the centre,
        // L(2) − 3L(1) + 3L(0) − L(−1) and its mirror, are ≥ Δ. A step between
        // ±1 and ±2 px moves only one of them (its error, ≤ 0.006·Δ, is within
        // the neighbours' Laplacian terms), and on a smooth image both are
        // O(h³·L'''). A ramp through the centre (the same shadow's slanted
        // edge further down, which the centre sample catches part-way) has
        // one small third difference; there the rise to the neighbour on each
        // side counts, where that side's third difference is as large
        // (`step_beside_centre`). So each pixel is also charged (½ − σ²/2)
        // times that signature per axis, summed over the two axes (½ where the
        // centre sample stands uncorrected), which bounds a 1-D step at every
        // δ and ramps of any width, and straight slanted steps, ramps and
        // bands ≥ 1 px wide in 2-D (`step_charge_bounds_the_filter_error_of_a_step`,
        // `step_charge_bounds_slanted_ramps_and_bands`). The
        // stencil needs ±2 px: a filter narrower than that (reach 1) has no
        // room for a step beside the centre that its Laplacian does not see.
        let step_factor = (0.5 - half_var).max(0.0);
        let step_term = |x: usize, y: usize| -> [f64; 3] {
            if r < 2 {
                return [0.0; 3];
            }
            let j = padded_index(x, y) as isize;
            let factor = if uncorrected(x, y) { 0.5 } else { step_factor };
            std::array::from_fn(|c| {
                let v = |k: isize| f64::from(padded[(j + k) as usize].0[c]);
                let axis = |d: isize| step_beside_centre([v(-2 * d), v(-d), v(0), v(d), v(2 * d)]);
                factor * (axis(1) + axis(pw as isize))
            })
        };
        let largest = |v: &[f64; 3]| v.iter().fold(0.0f64, |m, c| m.max(*c));
        // A point light's image: the in-scatter has its 1/r peak there, inside
        // a cone whose apex can be narrower than a pixel, so the centre
        // samples around it can all be 0 (box occluder, 96×54, tolerance 0.1:
        // two pixels were 0 with an estimate of 0 against 5.2e-4). Every pixel
        // whose window holds an image gets the filter integral.
        let radius = filter.radius();
        let light_rects: Vec<(std::ops::Range<usize>, std::ops::Range<usize>)> = light_images
            .iter()
            .filter(|p| p.0.is_finite() && p.1.is_finite())
            .map(|&(px, py)| {
                let span = |c: f64, n: usize| -> std::ops::Range<usize> {
                    let lo = (c - radius - 0.5).ceil().max(0.0);
                    let hi = (c + radius - 0.5).floor().min(n as f64 - 1.0);
                    if lo > hi { 0..0 } else { lo as usize..hi as usize + 1 }
                };
                (span(px, w), span(py, h))
            })
            .collect();
        // Classify every pixel: either its centre sample stands (with the
        // nearby Laplacian terms as its filter error) or it needs the filter
        // integral. Per pixel: its Laplacian and step terms (the largest
        // channel's, and the transmittance's); the largest in-scatter term of
        // its 3×3 neighbourhood, whose stencils cover the filter's window, is
        // the filter error charged where the centre sample stands: the
        // pixel's own term is the error only where ∇²L is nearly constant
        // across the window (next to a beam's edge, narrow beam, 96×54,
        // tolerance 0.1, the own term was up to 8× too small, 1.7e-4 against
        // 2.0e-5, and a pixel whose five samples are all 0 claimed no error
        // although its window reaches the beam), or the step term if larger.
        // A pixel is flagged when that exceeds the tolerance of its window's
        // scale, or the transmittance term the tolerance, or at a silhouette;
        // then the flags are dilated by one pixel (8-neighbourhood): the
        // Laplacian stencil sees ±1 px around a centre, the filter window
        // ±1.5 px, so a pixel next to a flagged one may have the feature
        // inside its window although its own stencil is flat (for the
        // in-scatter term the neighbourhood maximum does this already; the
        // dilation still carries silhouettes and the transmittance term).
        // Where the centre sample stands, the in-scatter (and each light's)
        // gets the filter's second-order term (σ²/2)·∇²v from the 5-point
        // Laplacian, O(σ⁴∇⁴v) left while the estimate keeps the whole term:
        // with σ²/2 ≤ ¼ px² a convex combination of the five samples (≥ 0); a
        // wider filter keeps the centre sample, as do the frame's border
        // pixels (the per-light layers have no samples outside it). The
        // transmittance layers keep their centre samples (the per-light
        // surface transmittance is the view transmittance where no surface is
        // seen, and must stay equal to it there). Where all five in-scatter
        // samples are 0 the term is 0 in every layer, and the pixel is skipped.
        //
        // In bands of rows, each with its halo (the terms of 2 rows either
        // side, the flags of 1) in small buffers of its own, over the band's
        // spans only: the same values as whole-image passes, without their
        // ≈ 37 MB of arrays at 768×432, whose page faults and copies cost
        // more than the arithmetic. (Narrow beam, 768×432, tolerance 0.3, one
        // thread: classification 26 → 9.3 ms, with the unlit tiles.)
        const BAND: usize = 16;
        let mut window_scales = vec![0.0f32; n];
        let zero = |j: usize| inscatter[j] == [0.0f32; 3];
        struct BandOut {
            edges: Vec<usize>,
            smooth: Vec<usize>,
            lap_abs: f64,
            lap_rel: f64,
        }
        let bands: Vec<BandOut> = window_scales
            .par_chunks_mut(BAND * w)
            .zip(error.par_chunks_mut(if want_error { BAND * w } else { BAND }))
            .enumerate()
            .map(|(b, (scale_rows, err_rows))| {
                let (y0, y1) = (b * BAND, ((b + 1) * BAND).min(h));
                // The band's final flags; the flagged pixels leave as `edges`.
                let mut flag_rows = vec![false; (y1 - y0) * w];
                // Rows whose terms (ta..tb) and first flags (fa..fb) are needed.
                let (ta, tb) = (y0.saturating_sub(2), (y1 + 2).min(h));
                let (fa, fb) = (y0.saturating_sub(1), (y1 + 1).min(h));
                // The band's buffers hold the columns c0 .. c0 + lw: its
                // spans and one pixel either side.
                let (blo, bhi) = frame_spans[ta..tb]
                    .iter()
                    .fold((w, 0), |(a, b), &(lo, hi)| if lo < hi { (a.min(lo), b.max(hi)) } else { (a, b) });
                let c0 = blo.saturating_sub(1).min(w);
                let lw = (bhi + 1).min(w).saturating_sub(c0);
                let cells = (tb - ta) * lw;
                let at = |x: usize, y: usize| (y - ta) * lw + x - c0;
                // Window scales of the term rows: row maxima of |L| over ±r
                // (padded rows ta .. tb + 2r), then column maxima.
                let mut row_max = vec![0.0f32; (tb - ta + 2 * r) * lw];
                let mut scales = vec![0.0f32; cells];
                if blo < bhi {
                    // Each sample's largest channel once, then the sliding
                    // maxima (max is exact: the same values in any order).
                    let mut largest_of_row = vec![0.0f32; bhi - blo + 2 * r];
                    for (py, out) in (ta..tb + 2 * r).zip(row_max.chunks_mut(lw)) {
                        let prow = &padded[py * pw + blo..py * pw + bhi + 2 * r];
                        for (m, p) in largest_of_row.iter_mut().zip(prow) {
                            *m = lmax(&p.0);
                        }
                        for (o, win) in out[blo - c0..bhi - c0].iter_mut().zip(largest_of_row.windows(2 * r + 1)) {
                            *o = win.iter().fold(0.0f32, |m, v| m.max(*v));
                        }
                    }
                    for (y, out) in (ta..tb).zip(scales.chunks_mut(lw)) {
                        for k in 0..=2 * r {
                            let src = &row_max[(y - ta + k) * lw..(y - ta + k + 1) * lw];
                            for (o, v) in out[blo - c0..bhi - c0].iter_mut().zip(&src[blo - c0..bhi - c0]) {
                                *o = o.max(*v);
                            }
                        }
                    }
                }
                // A pixel whose window holds only zeros (and whose
                // transmittance is not filtered) has no term, no silhouette
                // and is not flagged: every sample its terms and its
                // neighbours' terms read is within ±2 px, inside the window
                // when it reaches 2 px (a narrower filter gets no shortcut).
                let dark = |x: usize, y: usize| !need_t && r >= 2 && scales[at(x, y)] == 0.0;
                let (mut l_t, mut t_t, mut s_t) = (vec![0.0f64; cells], vec![0.0f64; cells], vec![0.0f64; cells]);
                let per_channel = if want_error { cells } else { 0 };
                let (mut c_l, mut c_s) = (vec![[0.0f64; 3]; per_channel], vec![[0.0f64; 3]; per_channel]);
                for y in ta..tb {
                    let (lo, hi) = frame_spans[y];
                    for x in lo..hi {
                        // Every sample an unlit pixel's terms read is 0.
                        if unlit(x as isize, y as isize) || dark(x, y) {
                            continue;
                        }
                        let (el, et) = lap_term(x, y);
                        let st = step_term(x, y);
                        let k = at(x, y);
                        (l_t[k], t_t[k], s_t[k]) = (largest(&el), et, largest(&st));
                        if want_error {
                            (c_l[k], c_s[k]) = (el, st);
                        }
                    }
                }
                // The 3×3 neighbourhood within the frame, as term-buffer indices.
                let around = |x: usize, y: usize| {
                    let (xa, xb) = (x.saturating_sub(1), (x + 2).min(w));
                    (y.saturating_sub(1)..(y + 2).min(h)).flat_map(move |yy| (xa..xb).map(move |xx| at(xx, yy)))
                };
                // The 3×3 maxima of the in-scatter terms, separably: first
                // along x (within the frame) on every term row.
                let mut l_t_x = vec![0.0f64; cells];
                for y in ta..tb {
                    for x in blo..bhi {
                        let (xa, xb) = (x.saturating_sub(1), (x + 2).min(w));
                        l_t_x[at(x, y)] = (xa..xb).fold(0.0f64, |m, xx| m.max(l_t[at(xx, y)]));
                    }
                }
                // Which surfaces each pixel's silhouette test sees: the least
                // and greatest surface key within ±r, separably (a pixel
                // whose window holds one surface has no silhouette).
                let key_rows = fb - fa + 2 * r;
                let (mut key_lo, mut key_hi) = (vec![0u32; key_rows * lw], vec![0u32; key_rows * lw]);
                if blo < bhi {
                    for (k, py) in (fa..fb + 2 * r).enumerate() {
                        let prow = &padded[py * pw + blo..py * pw + bhi + 2 * r];
                        for (x, win) in (blo..bhi).zip(prow.windows(2 * r + 1)) {
                            let (a, b) = win.iter().fold((u32::MAX, 0), |(a, b), p| (a.min(p.2), b.max(p.2)));
                            (key_lo[k * lw + x - c0], key_hi[k * lw + x - c0]) = (a, b);
                        }
                    }
                }
                let one_surface = |x: usize, y: usize| {
                    let col = |k: usize| (key_lo[k * lw + x - c0], key_hi[k * lw + x - c0]);
                    let (a, b) = (y - fa..=y - fa + 2 * r)
                        .map(col)
                        .fold((u32::MAX, 0), |(a, b), (c, d)| (a.min(c), b.max(d)));
                    a == b
                };
                // Rows fa..fb: the nearby terms (kept for the estimate) and the first flags.
                let mut first = vec![false; (fb - fa) * lw];
                let mut near = vec![0.0f64; (fb - fa) * lw];
                let at_first = |x: usize, y: usize| (y - fa) * lw + x - c0;
                for y in fa..fb {
                    let (lo, hi) = frame_spans[y];
                    for x in lo..hi {
                        if dark(x, y) {
                            continue;
                        }
                        let (k, i) = (at_first(x, y), at(x, y));
                        near[k] = (y.saturating_sub(1)..(y + 2).min(h)).fold(s_t[i], |m, yy| m.max(l_t_x[at(x, yy)]));
                        first[k] =
                            t_t[i] > tolerance || near[k] > tolerance * f64::from(scales[i]) || (!one_surface(x, y) && silhouette(x, y));
                    }
                }
                // The first flags dilated along x (within the frame).
                let mut first_x = vec![false; (fb - fa) * lw];
                for y in fa..fb {
                    for x in blo..bhi {
                        let (xa, xb) = (x.saturating_sub(1), (x + 2).min(w));
                        first_x[at_first(x, y)] = (xa..xb).any(|xx| first[at_first(xx, y)]);
                    }
                }
                let mut out = BandOut {
                    edges: Vec::new(),
                    smooth: Vec::new(),
                    lap_abs: 0.0,
                    lap_rel: 0.0,
                };
                for y in y0..y1 {
                    let (lo, hi) = frame_spans[y];
                    let row = (y - y0) * w;
                    for x in lo..hi {
                        flag_rows[row + x] = (y.saturating_sub(1)..(y + 2).min(h)).any(|yy| first_x[at_first(x, yy)]);
                        scale_rows[row + x] = scales[at(x, y)];
                    }
                    // Flags outside the span come only from the lights' images.
                    let (mut xa, mut xb) = (lo, hi);
                    for (xs, ys) in &light_rects {
                        if ys.contains(&y) {
                            flag_rows[row + xs.start..row + xs.end].fill(true);
                            (xa, xb) = if xa < xb {
                                (xa.min(xs.start), xb.max(xs.end))
                            } else {
                                (xs.start, xs.end)
                            };
                        }
                    }
                    for x in xa..xb {
                        let i = y * w + x;
                        if flag_rows[row + x] {
                            out.edges.push(i);
                            continue;
                        }
                        if !(lo..hi).contains(&x) {
                            continue;
                        }
                        // The other pixels' filter error: the nearby terms,
                        // absolute and relative to the window's scale.
                        let (a, m) = (near[at_first(x, y)], f64::from(scale_rows[row + x]));
                        out.lap_abs = out.lap_abs.max(a);
                        out.lap_rel = out.lap_rel.max(if m > 0.0 { a / m } else { 0.0 });
                        if want_error {
                            let e = &mut err_rows[row + x];
                            let step = c_s[at(x, y)];
                            for c in 0..3 {
                                let t = around(x, y).fold(0.0f64, |m, k| m.max(c_l[k][c])).max(step[c]);
                                e[c] += t as f32;
                            }
                        }
                        if !uncorrected(x, y) && ![i, i - 1, i + 1, i - w, i + w].iter().all(|&j| zero(j)) {
                            out.smooth.push(i);
                        }
                    }
                }
                out
            })
            .collect();
        let window_scale = |i: usize| -> f64 { f64::from(window_scales[i]) };
        let mut edges: Vec<usize> = Vec::new();
        let mut smooth: Vec<usize> = Vec::new();
        let (mut lap_abs, mut lap_rel) = (0.0f64, 0.0f64);
        for band in bands {
            edges.extend(band.edges);
            smooth.extend(band.smooth);
            lap_abs = lap_abs.max(band.lap_abs);
            lap_rel = lap_rel.max(band.lap_rel);
        }
        // A beam narrower than the centre samples' spacing can pass between
        // them (a 0.5° spot, any spot near its apex): its pixels' samples are
        // flat, often all 0, and nothing above flags them. Where the profile
        // filter may run, every pixel whose window such a beam crosses is
        // flagged, by the beam's geometry alone.
        let beams: Vec<profile::BeamLight> = if profile_on {
            let casters = smooth_scene.as_ref().map(|(_, c)| c.as_slice()).unwrap_or(&[]);
            stage_lights
                .points
                .iter()
                .enumerate()
                .map(|(k, p)| {
                    let servable = !matches!(casters.get(k), Some(smooth::Casters::Any) | None);
                    profile::BeamLight::new(&p.light, &cam, p.casts_shadows, servable, tolerance)
                })
                .collect::<Option<Vec<_>>>()
                .unwrap_or_default()
        } else {
            Vec::new()
        };
        if !beams.is_empty() {
            let mut flagged = vec![false; n];
            for &i in &edges {
                flagged[i] = true;
            }
            // (Unlit tiles included: a window reaches 1.5 px beyond its tile.)
            let thin = profile::thin_beam_pixels(&beams, filter.radius(), w, h, &flagged);
            if !thin.is_empty() {
                for &i in &thin {
                    flagged[i] = true;
                }
                smooth.retain(|&i| !flagged[i]);
                edges.extend(thin);
                edges.sort_unstable();
            }
        }
        stats.max_abs += lap_abs;
        stats.max_rel += lap_rel;
        t = report.time("pixel_filter_classify", t);
        if cancelled() {
            return Err(RenderError::Cancelled);
        }
        let with_filter_term =
            |img: &[[f32; 3]]| -> Vec<[f32; 3]> { smooth.iter().map(|&i| second_order_filter_term(img, w, i, half_var)).collect() };
        let smooth_inscatter = with_filter_term(&inscatter);
        let smooth_lights: Vec<Vec<[f32; 3]>> = light_inscatter.iter().map(|img| with_filter_term(img)).collect();
        // The stage counts every pixel integrated against the filter: those
        // the beams' profiles served (at once, when the profile ends), then
        // the lattice's, to the report's `edge_pixels`.
        let served_first = std::sync::atomic::AtomicUsize::new(0);
        let filter_progress = |done: usize, total: usize| {
            if let Some(cb) = progress {
                let first = served_first.load(Ordering::Relaxed);
                cb(RenderStage::PixelFilter, first + done, first + total);
            }
        };
        // Only near the light's image: farther out, the pixels a beam
        // narrower than 2 px crosses are the profile filter's (it leaves
        // those within LIGHT_IMAGE_MARGIN of a light's image to the
        // lattice). On the 0.5° beam with its lamp in view (96×54), squares
        // along the whole band took 146 polar squares and made the filter 7×
        // slower; beyond this reach they lay past the beam's end on the
        // floor, where the band goes on but no light does.
        let reach = profile::LIGHT_IMAGE_MARGIN + filter.radius();
        let beam_width = |n: usize, (x, y): (f64, f64)| {
            let (ix, iy) = light_images[n];
            if (x - ix).abs().max((y - iy).abs()) > reach {
                return None;
            }
            let beam = image_beams[n].as_ref()?;
            // The band |sin ψ| < sin(reach) is a double cone; a beam narrower
            // than a hemisphere lies on its axis's side of the image (a
            // half-plane), and a square wholly on the other side holds only
            // the unlit nappe (a 5° beam: 6 of 14 squares, a quarter of
            // their rays).
            if let Some((fx, fy)) = beam.forward {
                let behind = [(-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)]
                    .iter()
                    .all(|&(dx, dy)| (x + dx - ix) * fx + (y + dy - iy) * fy < 0.0);
                if behind {
                    return None;
                }
            }
            beam.geometry.width_in_square([x, y], 0.5)
        };
        let job = filter::AdaptiveFilterJob {
            filter,
            width: w,
            height: h,
            tolerance,
            window_scale: &window_scale,
            light_images: &light_images,
            polar_images: &polar_images,
            beam_width: image_beams
                .iter()
                .any(Option::is_some)
                .then_some(&beam_width as &filter::BeamWidth<'_>),
            cancel,
            progress: &filter_progress,
        };
        // Pixels across a spot's beam, from its profile, without lattice rays.
        let (profiled, edges) = match &smooth_scene {
            Ok((planes, casters)) if profile_on && !edges.is_empty() => {
                let trace = |x: f64, y: f64| -> profile::TracedRay {
                    let s = sample(x, y);
                    profile::TracedRay {
                        inscatter: s.l,
                        error: s.e,
                        surface: s.surface,
                        t_end: if s.hit { s.depth } else { cam.clip_end },
                    }
                };
                let input = profile::ProfileInput {
                    cam: &cam,
                    width: w,
                    height: h,
                    filter,
                    tolerance,
                    inscatter: &inscatter,
                    own_error: &own_error,
                    surface: &surface,
                    planes,
                    casters: &casters[..beams.len()],
                    lights: &beams,
                    media: &media,
                    light_images: &light_images,
                    window_scale: &window_scale,
                    trace: &trace,
                };
                profile::filter_by_profile(&input, &edges)
            }
            _ => (Vec::new(), edges),
        };
        // The profile gives the in-scatter only: where the transmittance is
        // filtered too and is not smooth in the window (its filter term over
        // the tolerance, or a silhouette, within the 3×3 neighbourhood), the
        // lattice also takes the pixel, and the profile's in-scatter is kept.
        let mut edges = edges;
        let mut both = 0u64;
        if need_t && !profiled.is_empty() {
            let t_not_smooth = |i: usize| {
                let (x, y) = (i % w, i / w);
                (y.saturating_sub(1)..(y + 2).min(h))
                    .any(|yy| (x.saturating_sub(1)..(x + 2).min(w)).any(|xx| lap_term(xx, yy).1 > tolerance || silhouette(xx, yy)))
            };
            let extra: Vec<usize> = profiled.iter().map(|p| p.index).filter(|&i| t_not_smooth(i)).collect();
            both = extra.len() as u64;
            edges.extend(extra);
            edges.sort_unstable();
        }
        t = report.time("pixel_filter_profile", t);
        let first = profiled.len() - both as usize;
        if first > 0 {
            served_first.store(first, Ordering::Relaxed);
            filter_progress(0, edges.len());
        }
        let (filtered, lattice) = filter::filter_adaptive(&job, &edges, &sample);
        if cancelled() {
            return Err(RenderError::Cancelled);
        }
        edge.pixels = filtered.len() as u64;
        edge.samples = lattice.samples;
        let scales: Vec<f64> = filtered.iter().map(|f| window_scale(f.index)).collect();
        for (f, &scale) in filtered.iter().zip(&scales) {
            let (i, s, err) = (&f.index, &f.value, &f.error);
            inscatter[*i] = s.l.map(|v| v as f32);
            for (k, img) in light_inscatter.iter_mut().enumerate() {
                img[*i] = s.lights[k].map(|v| v as f32);
            }
            for (k, img) in light_surface_transmittance.iter_mut().enumerate() {
                img[*i] = surface_transmittance_of(s, k);
            }
            if need_t {
                transmittance[*i] = s.t.map(|v| v.clamp(0.0, 1.0) as f32);
            }
            if want_sun_t {
                sun_t[*i] = s.st.map(|v| v.clamp(0.0, 1.0) as f32);
            }
            if want_error {
                error[*i] = err.map(|v| v as f32);
            }
            let m = s.l.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(scale);
            let e_max = err.iter().fold(0.0f64, |a, v| a.max(*v));
            let rel = if m > 0.0 { e_max / m } else { 0.0 };
            edge.max_abs = edge.max_abs.max(e_max);
            edge.max_rel = edge.max_rel.max(rel);
            if rel > tolerance {
                edge.not_converged += 1;
            }
        }
        for p in &profiled {
            let i = p.index;
            inscatter[i] = p.value.map(|v| v as f32);
            match p.light {
                Some(k) => {
                    if let Some(img) = light_inscatter.get_mut(k) {
                        img[i] = p.value.map(|v| v as f32);
                    }
                }
                // No beam reaches the window: 0 in every light's layer.
                None => light_inscatter.iter_mut().for_each(|img| img[i] = [0.0; 3]),
            }
            if want_error {
                error[i] = p.error.map(|v| v as f32);
            }
            let m = p.value.iter().fold(0.0f64, |a, v| a.max(v.abs())).max(window_scale(i));
            let e_max = p.error.iter().fold(0.0f64, |a, v| a.max(*v));
            let rel = if m > 0.0 { e_max / m } else { 0.0 };
            edge.max_abs = edge.max_abs.max(e_max);
            edge.max_rel = edge.max_rel.max(rel);
            // (A beam too thin for the lattice is served over the tolerance.)
            if rel > tolerance {
                edge.not_converged += 1;
            }
        }
        edge.pixels += profiled.len() as u64 - both;
        edge.profile_pixels = profiled.len() as u64;
        if !profiled.is_empty() {
            report.plan.computed(
                format!("pixel filter from the beams' profiles on {} pixels", profiled.len()),
                "the window integral of G·A(ψ): A the light's profile integrated across its cone along the great circle at the ray plane's angle ψ from the axis (a table per light, exact geometry per node), G = L/A from the centre samples (as ρ·G₀, G₀ the in-scatter density at the chord's middle in closed form), Catmull–Rom on ¼ px nodes, trapezoid rule; estimate: |Catmull–Rom − bilinear| and ρ's spread where extended, |¼ px − ½ px rule|, the samples' own errors and the table's; no lattice rays; a window no cone can reach (exact bound on the ray planes) is 0",
            );
            report.plan.left_out(
                format!("lattice rays on {} pixels", profiled.len()),
                "filtered from the beam's profile within the tolerance (render::profile); the rest (surfaces cutting a chord, possible shadows, another light's cone, a light's image, the frame's 3 px border, or an estimate over the tolerance) use the lattice",
            );
        }
        for (k, &i) in smooth.iter().enumerate() {
            inscatter[i] = smooth_inscatter[k];
            for (img, v) in light_inscatter.iter_mut().zip(&smooth_lights) {
                img[i] = v[k];
            }
        }
        report.plan.computed(
            format!("pixel filter integral on {} pixels (silhouettes, sharp medium boundaries)", filtered.len()),
            format!(
                "Blackman-Harris, filter size {:.2} px (Blender's; window ±{:.2} px as Cycles doubles it), bilinear interpolation integrated exactly against the window, on one adaptive lattice shared by all windows: ½ px cells split while not flat to the tolerance, down to 1/32 px (1/2048 px at a point light's image where the polar rule does not apply), until each pixel's estimate settles; {} squares of 1 px at point lights' images (and near them where a beam is narrower than the cells) in polar coordinates about the image (Gauss–Kronrod 5 × 5 rectangles in angle and radius, cut at the light's cone silhouettes, bisected until each pixel is within ¼ of its tolerance; {} of the view rays): {} view rays, {} cells",
                filter.radius(),
                filter.radius(),
                lattice.polar_squares,
                lattice.polar_samples,
                edge.samples,
                lattice.cells
            ),
        );
        report.plan.left_out(
            format!("pixel filter integral on {} smooth pixels", n - filtered.len()),
            "the image is smooth within the filter: the centre sample plus the filter's second-order effect (σ²/2)·∇²L from the 5-point Laplacian of the centre samples (the centre sample alone on the frame's border) is used; the largest such term of the pixel's 3×3 neighbourhood (whose stencils cover the window), or a step or ramp beside the centre's worst case (½ − σ²/2)·Δ from third and first differences, is below the tolerance and is the pixel's filter error estimate (the pixel's own term alone fell short beside a beam's edge)",
        );
        t = report.time("pixel_filter", t);
    } else {
        report.plan.left_out(
            "pixel filter",
            "none requested (or an equirectangular camera): point samples at pixel centres",
        );
    }
    let _ = t;

    let pixels = n as u64;
    report.stats.pixels = pixels;
    report.stats.rays_hit_surface = stats.hits;
    report.stats.rays_without_medium = stats.vacuum;
    report.stats.pixels_unlit = stats.unlit;
    report.stats.pixels_interpolated = stats.interpolated;
    report.stats.pixels_profile_filtered = edge.profile_pixels;
    report.stats.pixels_outside_every_volume = stats.outside;
    if stats.outside > 0 {
        report.plan.left_out(
            format!("scattering integral on {} view rays", stats.outside),
            "outside every light's volume: the ray's surface hit and its cone and prism tests show it crosses none (in-scatter exactly 0, no medium evaluated)",
        );
    }
    match &smooth_scene {
        Ok(_) if smooth_on => report.plan.left_out(
            format!("scattering integral on {} view rays", stats.interpolated),
            format!(
                "interpolated: the 4-point cubic between samples 4 px apart (pixels with even x and y), then 2 px apart (the rest), that end on the same plane and cross the same light cones (blend cones included) and window prisms the same way as the pixel's own ray (its topology, one surface hit and cone tests), unshadowed (outside their casters' shadow pyramids and balls), away from the lights' images; charged {} × (3/256)(|Δ⁴_L| + |Δ⁴_R|) plus the samples' own errors, within the tolerance, and each light's layer within it too (rays that cross no light: exactly 0); transmittance and depth from the pixel's own ray",
                smooth::SAFETY
            ),
        ),
        Err(why) if scene.output.interpolate_smooth_pixels && !stage_lights.is_empty() && !media.is_empty() => {
            report.plan.computed("every lit pixel's view ray", format!("no pixel interpolated: {why}"))
        }
        Ok(_) if scene.output.interpolate_smooth_pixels => report.plan.computed(
            "every lit pixel's view ray",
            "no pixel interpolated: not with the sun_transmittance layer, with unlit tiles off, an equirectangular camera, or sun or ambient light",
        ),
        _ => {}
    }
    if stats.unlit > 0 {
        report.plan.left_out(
            if need_ray {
                format!("scattering integral on the view rays of {} pixels", stats.unlit)
            } else {
                format!("view rays of {} pixels", stats.unlit)
            },
            format!(
                "unlit: in tiles of {0}×{0} px whose rays, padded by every pixel their results read, miss every light's illumination volume (a separating plane through the eye, per light: spot cones, window prisms; or, where all their rays end on a floor, a plane separating their segments from the cone); their in-scatter is exactly 0, and the layers that need the ray (transmittance, depth, surface transmittance; point samples only) take its surface hit and closed-form transmittance alone",
                unlit::TILE
            ),
        );
    } else if unlit_grid.is_none() && !need_ray && scene.output.skip_unlit_tiles && !stage_lights.is_empty() {
        report.plan.computed(
            "every pixel's view ray",
            "no tile is provably unlit: a sun, ambient light or a light whose volume is not a cone narrower than a hemisphere reaches every ray",
        );
    }
    report.stats.non_finite_pixels = stats.non_finite;
    if stats.non_finite > 0 {
        report.warnings.push(format!(
            "{} pixels are not finite (NaN or ∞): this is a bug, please report the scene",
            stats.non_finite
        ));
    }
    if stats.vacuum > 0 && !media.is_empty() {
        report.plan.left_out(
            format!("scattering integral on {} view rays", stats.vacuum),
            "the ray crosses no medium",
        );
    }
    report.error = crate::report::ErrorEstimate {
        sun_disc_rel: report.error.sun_disc_rel,
        tolerance,
        max_abs: stats.max_abs,
        max_rel: stats.max_rel,
        f32_storage_rel: f64::from(f32::EPSILON) / 2.0,
        pixels_closed_form: pixels - stats.numeric - stats.vacuum - stats.unlit - stats.interpolated - stats.outside,
        pixels_numeric: stats.numeric,
        pixels_not_converged: stats.not_converged,
        edge_pixels: edge.pixels,
        edge_max_abs: edge.max_abs,
        edge_max_rel: edge.max_rel,
        edge_pixels_not_converged: edge.not_converged,
        method: format!(
            "{}; where the centre sample stands for the filtered pixel, plus the filter's second-order effect (σ²/2)·∇²L (bounds are added: max over pixels of each part); pixels integrated against the filter are summarised in edge_*",
            if stats.numeric == 0 {
                "closed forms: floating-point rounding bound of the closed form (exact model)"
            } else {
                "closed forms where one medium is on the ray (rounding bound); Gauss-Kronrod G7-K15 error estimate where several media overlap"
            }
        ),
    };
    for k in [
        LayerKind::Inscatter,
        LayerKind::Transmittance,
        LayerKind::Depth,
        LayerKind::SunTransmittance,
        LayerKind::Error,
    ] {
        if !want(k) {
            report.plan.left_out(format!("layer {k}"), "not requested in output.layers");
        }
    }
    if !want_sun_t {
        sun_t = Vec::new();
    }
    if !want_error {
        error = Vec::new();
    }
    if !stage_lights.is_empty() {
        report_stage(&stage_lights, &stats, report);
    }
    if want_surface_t {
        report.plan.computed(
            format!("surface_transmittance.<light> for {n_stage} stage lights"),
            "per pixel with a surface: view transmittance × the medium's transmittance from the surface point to the light (window lights: to the window plane); filtered pixels average over their surface samples",
        );
    } else if scene.output.layers.contains(&LayerKind::SurfaceTransmittancePerLight) && stage_lights.dark.is_empty() {
        report
            .plan
            .left_out("surface_transmittance per light", "the scene has no point, spot or window lights");
    }
    if scene.output.layers.contains(&LayerKind::SurfaceTransmittancePerLight) && !stage_lights.dark.is_empty() {
        report.plan.left_out(
            format!("surface_transmittance.<light> of {}", stage_lights.dark.join(", ")),
            "these lights contribute nothing (zero power, irradiance or IES strength, or black): no surface light to dim",
        );
    }
    let mut light_layer_names = if want_per_light {
        per_light_layer_names("inscatter", &stage_lights.names()[..n_stage])
    } else {
        Vec::new()
    };
    // Lights that contribute nothing keep their in-scatter layer, exactly 0,
    // so that a pipeline finds `inscatter.<light>` for every light it exported
    // (within the per-light layer cap).
    if scene.output.layers.contains(&LayerKind::InscatterPerLight) && !stage_lights.dark.is_empty() {
        let room = stage::MAX_LIGHT_LAYERS.saturating_sub(n_stage);
        let mut all = stage_lights.names()[..n_stage].to_vec();
        all.extend(stage_lights.dark.iter().take(room).cloned());
        let names = per_light_layer_names("inscatter", &all);
        for name in names.into_iter().skip(n_stage) {
            light_layer_names.push(name);
            light_inscatter.push(vec![[0f32; 3]; w * h]);
        }
    }
    // Say which light a layer holds wherever its name is not `inscatter.` +
    // the light's own name (a name taken by another light, or one with dots
    // or control characters).
    {
        let mut all = stage_lights.names()[..n_stage].to_vec();
        all.extend(stage_lights.dark.iter().cloned());
        for (k, layer) in light_layer_names.iter().enumerate() {
            let Some(name) = all.get(k) else { break };
            if *layer != format!("inscatter.{name}") {
                let nth = all[..=k].iter().filter(|n| *n == name).count();
                report.plan.computed(
                    format!("layer {layer}"),
                    format!(
                        "the in-scatter of the stage light named {name:?}{} (point and spot lights first, then windows, each in the scene's order): its own name is another light's or has dots or control characters",
                        if nth > 1 {
                            let suffix = match (nth % 10, nth % 100) {
                                (_, 11..=13) => "th",
                                (2, _) => "nd",
                                (3, _) => "rd",
                                _ => "th",
                            };
                            format!(", the {nth}{suffix} of that name")
                        } else {
                            String::new()
                        }
                    ),
                );
            }
        }
    }
    let surface_layer_names = if want_surface_t {
        per_light_layer_names("surface_transmittance", &stage_lights.names()[..n_stage])
    } else {
        Vec::new()
    };
    Ok(Images {
        width: w,
        height: h,
        inscatter,
        transmittance: if need_t { transmittance } else { Vec::new() },
        depth: if want_depth { depth } else { Vec::new() },
        sun_transmittance: sun_t,
        error,
        layers: scene.output.layers.clone(),
        light_inscatter,
        light_layer_names,
        light_surface_transmittance,
        surface_layer_names,
    })
}

/// The `surface_transmittance.<light>` value of a (possibly filtered) sample:
/// the mean over its surface samples, or the view transmittance where it has none.
fn surface_transmittance_of<const K: usize>(s: &Sample<K>, k: usize) -> [f32; 3] {
    let v = if s.hit_weight > 1e-12 {
        s.surface_t[k].map(|v| v / s.hit_weight)
    } else {
        s.t
    };
    v.map(|x| x.clamp(0.0, 1.0) as f32)
}

/// `v + (σ²/2)·∇²v` at interior pixel `i` of the `w`-wide image `img` (5-point
/// Laplacian, `half_var` = σ²/2 in px², ≤ ¼ so that this is a convex
/// combination of the five samples): the pixel filter's effect on a smooth
/// image to second order.
fn second_order_filter_term(img: &[[f32; 3]], w: usize, i: usize, half_var: f64) -> [f32; 3] {
    let at = |j: usize, c: usize| f64::from(img[j][c]);
    std::array::from_fn(|c| {
        let lap = at(i - 1, c) + at(i + 1, c) + at(i - w, c) + at(i + w, c) - 4.0 * at(i, c);
        (at(i, c) + half_var * lap) as f32
    })
}

/// A light's beam as the pixel filter's polar rule sees it
/// ([`filter::AdaptiveFilterJob::beam_width`]).
struct ImageBeam {
    geometry: profile::BeamLight,
    /// The unit image direction in which the light's axis leaves its image
    /// (`None` where the axis is seen end-on).
    forward: Option<(f64, f64)>,
}

/// The unit image direction, from `at` (the image of `origin`), in which
/// the line from `origin` along `dir` leaves it: a point a little way along
/// it (or back along it, reversed, where that one is behind the camera).
fn image_direction(cam: &CameraRays, origin: glam::DVec3, dir: glam::DVec3, at: (f64, f64)) -> Option<(f64, f64)> {
    let step = 1e-3 * (cam.position - origin).length();
    for sign in [1.0, -1.0] {
        if let Some((x, y)) = cam.project(origin + sign * step * dir) {
            let (dx, dy) = (sign * (x - at.0), sign * (y - at.1));
            let len = dx.hypot(dy);
            return (len > 1e-9 && len.is_finite()).then(|| (dx / len, dy / len));
        }
    }
    None
}

/// Image angles (radians, from +x towards +y, which points down) of the
/// lines through a point light's image `at` along which its in-scatter's
/// peak has features: the silhouettes of the cones where its distribution
/// has kinks ([`crate::light::PointSource::kinks`]), seen from the camera.
/// A cone's silhouette generators are lines through the light, so their
/// images are lines through `at`; the half along the lit nappe is listed.
fn light_image_cuts<const C: usize>(cam: &CameraRays, light: &crate::light::PointSource<C>, at: (f64, f64)) -> Vec<f64> {
    let mut cuts = Vec::new();
    let reach = (cam.position - light.position).length();
    for &cos_half in light.kinks().as_slice() {
        let Some(generators) = filter::cone_silhouette_generators(light.position, light.frame.axis, cos_half, cam.position) else {
            continue;
        };
        for g in generators {
            // The image of a line is a line: any point of it in front of the
            // camera gives its direction.
            for sign in [1.0, -1.0] {
                if let Some((x, y)) = cam.project(light.position + sign * 1e-3 * reach * g) {
                    let angle = (y - at.1).atan2(x - at.0);
                    if angle.is_finite() {
                        cuts.push(if sign > 0.0 { angle } else { angle + std::f64::consts::PI });
                    }
                    break;
                }
            }
        }
    }
    cuts
}

/// A centre sample as stored in the images: (L, T, surface id).
type CentreSample = ([f32; 3], [f32; 3], u32);

/// The signature of a step between the centre `v[2]` and a neighbour, from
/// five samples at −2..=2 px along one axis, on the scale of the step's
/// height. With the two third differences across the centre,
/// T₊ = L(2) − 3L(1) + 3L(0) − L(−1) and its mirror T₋, and the first
/// differences D± = L(±1) − L(0), it is the larger of min(|T₊|, |T₋|) and
/// min(|T₊|, |D₊|) + min(|T₋|, |D₋|).
///
/// - A step Δ beside the centre makes both third differences ≥ Δ; one
///   between ±1 and ±2 px moves only one; on a smooth image both are
///   O(h³·L''').
/// - A ramp through the centre (a volumetric shadow's edge seen at a slant,
///   or a step whose rise the centre sample catches half-way) has one small
///   third difference: for a ramp 0.1 px wide through the centre the first
///   term alone was 0.04 and the Laplacian terms 0.06 where the error is
///   0.15 (1-D, a rise of 1), and it left the box
///   occluder's shadow edge at 96×54, tolerance 0.3, wrong by 3.3e-3 against
///   an estimate of 2.3e-3. The second term charges each side the rise
///   between the centre and its neighbour, where the third difference on
///   that side says it is not smooth (`step_charge_bounds_the_filter_error_of_a_step`
///   and `step_charge_bounds_slanted_ramps_and_bands` check both).
fn step_beside_centre(v: [f64; 5]) -> f64 {
    let right = v[4] - 3.0 * v[3] + 3.0 * v[2] - v[1];
    let left = v[3] - 3.0 * v[2] + 3.0 * v[1] - v[0];
    let (rise_right, rise_left) = (v[3] - v[2], v[1] - v[2]);
    let either = right.abs().min(left.abs());
    let each = right.abs().min(rise_right.abs()) + left.abs().min(rise_left.abs());
    either.max(each)
}

/// Per-row counts and error maxima of pass 1.
#[derive(Debug, Default, Clone, Copy)]
struct RowStats {
    stage_crossed: u64,
    stage_segments: u64,
    stage_skipped: u64,
    stage_shadow_rays: u64,
    stage_clamped: u64,
    stage_rays: u64,
    hits: u64,
    vacuum: u64,
    unlit: u64,
    interpolated: u64,
    outside: u64,
    numeric: u64,
    not_converged: u64,
    non_finite: u64,
    max_abs: f64,
    max_rel: f64,
}

/// `max` that keeps a NaN (f64::max drops it, which would hide a bad pixel).
fn nan_max(a: f64, b: f64) -> f64 {
    if a.is_nan() || b.is_nan() { f64::NAN } else { a.max(b) }
}

impl RowStats {
    /// An interpolated pixel: in-scatter `l` with the error estimate `e`.
    fn add_interpolated(&mut self, l: &[f64; 3], e: &[f64; 3]) {
        self.interpolated += 1;
        let finite = l.iter().chain(e).all(|v| v.is_finite());
        self.non_finite += (!finite) as u64;
        self.max_abs = nan_max(self.max_abs, e.iter().fold(0.0f64, |m, v| nan_max(m, *v)));
        for c in 0..3 {
            if l[c].abs() > 0.0 {
                self.max_rel = nan_max(self.max_rel, e[c] / l[c].abs());
            }
        }
    }

    fn add<const K: usize>(&mut self, s: &Sample<K>) {
        self.stage_crossed |= s.stage_crossed;
        self.stage_segments += u64::from(s.stage_segments);
        self.stage_skipped += u64::from(s.stage_skipped);
        self.stage_shadow_rays += u64::from(s.stage_shadow_rays);
        self.stage_clamped += s.stage_clamped as u64;
        self.stage_rays += (s.stage_segments > 0) as u64;
        self.hits += s.hit as u64;
        self.vacuum += (!s.in_medium) as u64;
        if let Some(conv) = s.numeric {
            self.numeric += 1;
            self.not_converged += (!conv) as u64;
        }
        let finite = s.l.iter().chain(&s.t).chain(&s.st).chain(&s.e).all(|v| v.is_finite()) && s.rel.is_finite();
        self.non_finite += (!finite) as u64;
        self.max_abs = nan_max(self.max_abs, s.e.iter().fold(0.0f64, |m, v| nan_max(m, *v)));
        self.max_rel = nan_max(self.max_rel, s.rel);
    }
    fn merge(&mut self, o: &RowStats) {
        self.stage_crossed |= o.stage_crossed;
        self.stage_segments += o.stage_segments;
        self.stage_skipped += o.stage_skipped;
        self.stage_shadow_rays += o.stage_shadow_rays;
        self.stage_clamped += o.stage_clamped;
        self.stage_rays += o.stage_rays;
        self.hits += o.hits;
        self.vacuum += o.vacuum;
        self.unlit += o.unlit;
        self.interpolated += o.interpolated;
        self.outside += o.outside;
        self.numeric += o.numeric;
        self.not_converged += o.not_converged;
        self.non_finite += o.non_finite;
        self.max_abs = nan_max(self.max_abs, o.max_abs);
        self.max_rel = nan_max(self.max_rel, o.max_rel);
    }
}

/// One view-ray sample reduced to RGB, with `K` per-light slots
/// ([`stage::MAX_LIGHT_LAYERS`] when per-light layers are output, else 0).
#[derive(Debug, Clone, Copy)]
struct Sample<const K: usize> {
    /// Per stage light in-scatter, RGB (first `K` lights).
    lights: [[f64; 3]; K],
    /// Per stage light T_view · T(surface → light) times `hit_weight` (0 without surface).
    surface_t: [[f64; 3]; K],
    /// How many entries of `lights` and `surface_t` are output (the rest are
    /// not accumulated by the pixel filter).
    light_layers: u8,
    /// 1 where the ray ends on a surface, 0 otherwise; in a filtered sum the
    /// filter weight of the surface samples.
    hit_weight: f64,
    stage_segments: u32,
    stage_skipped: u32,
    stage_crossed: u64,
    stage_shadow_rays: u32,
    stage_clamped: bool,
    /// Topology code of the ray without its shadow bit ([`stage::StageShade::topology`]).
    topology: u64,
    l: [f64; 3],
    t: [f64; 3],
    st: [f64; 3],
    e: [f64; 3],
    rel: f64,
    depth: f64,
    hit: bool,
    surface: u32,
    numeric: Option<bool>,
    in_medium: bool,
}

impl<const K: usize> Default for Sample<K> {
    fn default() -> Self {
        Self {
            lights: [[0.0; 3]; K],
            surface_t: [[0.0; 3]; K],
            light_layers: 0,
            hit_weight: 0.0,
            stage_segments: 0,
            stage_skipped: 0,
            stage_crossed: 0,
            stage_shadow_rays: 0,
            stage_clamped: false,
            topology: 0,
            l: [0.0; 3],
            t: [0.0; 3],
            st: [0.0; 3],
            e: [0.0; 3],
            rel: 0.0,
            depth: 0.0,
            hit: false,
            surface: 0,
            numeric: None,
            in_medium: false,
        }
    }
}

#[derive(Debug, Default)]
struct EdgeStats {
    pixels: u64,
    /// Of `pixels`, those filtered from the beam's profile ([`profile`]).
    profile_pixels: u64,
    samples: u64,
    max_abs: f64,
    max_rel: f64,
    not_converged: u64,
}

/// Per row `y` of images `w` wide and `h` high, its slice of each image.
fn rows_of_images(images: &mut [Vec<[f32; 3]>], w: usize, h: usize) -> Vec<Vec<&mut [[f32; 3]]>> {
    let mut rows: Vec<Vec<&mut [[f32; 3]]>> = (0..h).map(|_| Vec::with_capacity(images.len())).collect();
    for img in images.iter_mut() {
        for (row, chunk) in rows.iter_mut().zip(img.chunks_mut(w)) {
            row.push(chunk);
        }
    }
    rows
}

/// `acc += wgt · s` for the filtered quantities of a sample.
fn accumulate<const K: usize>(acc: &mut Sample<K>, s: &Sample<K>, wgt: f64) {
    for c in 0..3 {
        acc.l[c] += wgt * s.l[c];
        acc.t[c] += wgt * s.t[c];
        acc.st[c] += wgt * s.st[c];
        acc.e[c] += wgt * s.e[c];
    }
    let n = usize::from(s.light_layers);
    acc.light_layers = acc.light_layers.max(s.light_layers);
    for (a, v) in acc.lights[..n].iter_mut().zip(&s.lights[..n]) {
        for c in 0..3 {
            a[c] += wgt * v[c];
        }
    }
    for (a, v) in acc.surface_t[..n].iter_mut().zip(&s.surface_t[..n]) {
        for c in 0..3 {
            a[c] += wgt * v[c];
        }
    }
    acc.hit_weight += wgt * s.hit_weight;
    acc.numeric = match (acc.numeric, s.numeric) {
        (Some(a), Some(b)) => Some(a && b),
        (a, b) => a.or(b),
    };
    acc.in_medium |= s.in_medium;
    acc.rel = acc.rel.max(s.rel);
}

impl<const K: usize> filter::FilterSample for Sample<K> {
    fn radiance(&self) -> [f64; 3] {
        self.l
    }
    fn transmittance(&self) -> [f64; 3] {
        self.t
    }
    fn own_error(&self) -> [f64; 3] {
        self.e
    }
    fn add_weighted(&mut self, other: &Self, weight: f64) {
        accumulate(self, other, weight);
    }
}

/// Each sun is one direction unless that is not good enough: for every
/// phase function in the scene, the largest relative change of the sun's
/// in-scatter from averaging over the disc is measured; where it exceeds the
/// tolerance the disc-averaged phase function is tabulated (to a quarter of
/// the tolerance) and used instead. Returns the remaining relative error, or
/// `None` when `stop()` turned true while a table was built.
fn sun_disc_effect<const C: usize>(
    scene: &Scene,
    media: &[PreparedMedium<C>],
    lights: &mut LightSet<C>,
    report: &mut Report,
    stop: &dyn Fn() -> bool,
) -> Option<f64> {
    let mut phases: Vec<PhaseFunction> = Vec::new();
    for m in media {
        let ps = match m {
            PreparedMedium::Homogeneous(h) => vec![h.phase],
            PreparedMedium::HeightFog(h) => vec![PhaseFunction::Rayleigh, h.mie_phase],
            PreparedMedium::FogLayer(f) => vec![f.phase],
            PreparedMedium::HeightFieldLayer(f) => {
                if f.upper_is_vacuum() {
                    vec![f.lower.phase]
                } else {
                    vec![f.lower.phase, f.upper.phase]
                }
            }
            PreparedMedium::Ellipsoid(e) => vec![e.phase],
        };
        for p in ps {
            if !phases.contains(&p) {
                phases.push(p);
            }
        }
    }
    let tol = scene.output.tolerance;
    let mut worst = 0.0f64;
    let mut k = 0;
    for (i, l) in scene.lights.iter().enumerate() {
        let Light::Sun(SunLight {
            angular_diameter_deg,
            strength_w_m2,
            color,
            ..
        }) = l
        else {
            continue;
        };
        if *strength_w_m2 == 0.0 || color.iter().all(|c| *c == 0.0) {
            continue;
        }
        let sun_index = k;
        k += 1;
        if phases.is_empty() {
            continue;
        }
        let diameter = angular_diameter_deg.to_radians();
        let mut tables = Vec::new();
        // The largest effect among the phase functions left as a point, and
        // the largest error of the tables built.
        let (mut residual, mut at, mut which) = (0.0f64, 0.0, String::new());
        let mut table_residual = 0.0f64;
        for p in &phases {
            let (r, theta) = p.point_sun_error(diameter);
            if r > tol {
                let t = medium::phase::DiscPhase::build_unless(*p, 0.5 * diameter, 0.25 * tol, stop)?;
                report.plan.computed(
                    format!("{}: sun disc ({angular_diameter_deg}° wide) for {}", light_label(i, l), p.describe()),
                    format!(
                        "as a point the sun's in-scatter would be off by up to {r:.2e} ({:.3}° from the sun), above the tolerance: the phase function averaged over the disc is tabulated at {} angles to {:.1e} relative",
                        theta.to_degrees(),
                        t.len(),
                        t.table_error()
                    ),
                );
                table_residual = table_residual.max(t.table_error());
                tables.push(t);
            } else if r >= residual {
                (residual, at, which) = (r, theta, p.describe());
            }
        }
        if tables.len() < phases.len() {
            report.plan.left_out(
                format!("{}: sun disc ({angular_diameter_deg}° wide){}", light_label(i, l), if tables.is_empty() { "" } else { " for the other phase functions" }),
                format!(
                    "treated as one direction: averaging over the disc would change the sun's in-scatter by at most {residual:.2e} relative ({which}, {:.3}° from the sun), within the tolerance",
                    at.to_degrees()
                ),
            );
        }
        if !tables.is_empty() {
            lights.suns[sun_index].disc = std::sync::Arc::new(tables);
        }
        worst = worst.max(residual).max(table_residual);
    }
    Some(worst)
}

/// |r̄_c(λ)|·k·Δλ: bounds how a per-wavelength error maps into each RGB channel.
fn abs_rgb_weights() -> [[f64; SPECTRAL_SAMPLES]; 3] {
    let mut out = [[0.0; SPECTRAL_SAMPLES]; 3];
    for i in 0..SPECTRAL_SAMPLES {
        let mut unit = [0.0; SPECTRAL_SAMPLES];
        unit[i] = 1.0;
        let rgb = spectrum::spectrum_to_rec709(&unit);
        for c in 0..3 {
            out[c][i] = rgb[c].abs();
        }
    }
    out
}

#[cfg(test)]
mod tests {
    #[test]
    fn per_light_layer_names_keep_own_names_first() {
        let names = |v: &[&str]| super::per_light_layer_names("inscatter", &v.iter().map(|s| s.to_string()).collect::<Vec<_>>());
        assert_eq!(
            names(&["key", "key", "key_2"]),
            ["inscatter.key", "inscatter.key_3", "inscatter.key_2"]
        );
        assert_eq!(names(&["a.b", "a_b"]), ["inscatter.a_b_2", "inscatter.a_b"]);
        assert_eq!(names(&["", "light"]), ["inscatter.light_2", "inscatter.light"]);
        assert_eq!(names(&["x", "x", "x"]), ["inscatter.x", "inscatter.x_2", "inscatter.x_3"]);
    }

    use super::*;

    /// For a 1-D image `l`: the corrected centre sample's distance from the
    /// window's integral (midpoint `nodes`), and the charge where the centre
    /// sample stands (the larger of the neighbours' Laplacian terms and
    /// `(½ − σ²/2)·step_beside_centre`).
    fn error_and_charge(l: &dyn Fn(f64) -> f64, nodes: &[(f64, f64)], half_var: f64) -> (f64, f64) {
        let window: f64 = nodes.iter().map(|(x, wgt)| wgt * l(*x)).sum();
        let corrected = l(0.0) + half_var * (l(1.0) + l(-1.0) - 2.0 * l(0.0));
        let lap = |c: f64| half_var * (l(c + 1.0) + l(c - 1.0) - 2.0 * l(c)).abs();
        let near = lap(-1.0).max(lap(0.0)).max(lap(1.0));
        let step = (0.5 - half_var) * step_beside_centre([l(-2.0), l(-1.0), l(0.0), l(1.0), l(2.0)]);
        ((corrected - window).abs(), near.max(step))
    }

    /// The charge where a centre sample stands, on a 1-D step of height 1 at
    /// every offset δ in ±2.6 px (5 201 offsets), for Blender's filter and two
    /// others: the corrected centre sample L(0) + σ²/2·(L(1) + L(−1) − 2L(0))
    /// differs from the window's integral by at most the larger of the
    /// neighbours' Laplacian terms and (½ − σ²/2)·step_beside_centre.
    #[test]
    fn step_charge_bounds_the_filter_error_of_a_step() {
        for width_px in [1.5, 1.2, 2.0] {
            let filter = filter::PixelFilter::BlackmanHarris { width_px };
            let nodes = filter.nodes(20_000);
            let half_var = 0.5 * filter.variance();
            for k in 0..=5200 {
                let delta = -2.6 + k as f64 * 1e-3;
                let (error, charge) = error_and_charge(&|x: f64| if x > delta { 1.0 } else { 0.0 }, &nodes, half_var);
                // 2e-4: the midpoint rule's own error on the window's integral at a step.
                assert!(error <= charge + 2e-4, "width {width_px}, δ = {delta}: error {error} > {charge}");
            }
            // Ramps from 0 to 1 over `rise` px, starting at every offset in
            // ±2.6 px (0.01 apart): the centre sample may catch the rise
            // half-way, where one third difference is small (with the first
            // term of `step_beside_centre` alone, a ramp 0.05 px wide was off
            // by 0.23 against a charge of 0.17).
            let nodes = filter.nodes(4_000);
            for rise in [0.05, 0.1, 0.3, 0.7, 1.0, 1.6, 2.4] {
                for k in 0..=520 {
                    let start = -2.6 + k as f64 * 1e-2;
                    let (error, charge) = error_and_charge(&|x: f64| ((x - start) / rise).clamp(0.0, 1.0), &nodes, half_var);
                    assert!(
                        error <= charge + 2e-4,
                        "width {width_px}, ramp {rise} px from {start}: error {error} > {charge}"
                    );
                }
            }
        }
    }

    /// The same charge in two dimensions, as the classification applies it
    /// (the largest Laplacian term of the 3×3 neighbourhood, or the step
    /// terms of the two axes summed), for Blender's filter on straight edges
    /// at 17 angles and 25 offsets: a step, ramps 0.1 and 0.6 px wide
    /// (a volumetric shadow's edge seen at a slant), and bands 1.2 and 2 px
    /// wide (narrower bands can fall between the samples, which no centre
    /// sample sees: those are left to the cone and caster tests that flag
    /// pixels). The window's integral is a 500 × 500 midpoint rule, whose own
    /// error at a step is below 4e-3. The first term of `step_beside_centre`
    /// alone failed 21 of these 2 125 edges, by up to 2.8×.
    #[test]
    fn step_charge_bounds_slanted_ramps_and_bands() {
        let filter = filter::PixelFilter::BlackmanHarris { width_px: 1.5 };
        let nodes = filter.nodes(500);
        let half_var = 0.5 * filter.variance();
        let ramp = |s: f64, rise: f64| {
            if rise > 0.0 {
                (0.5 - s / rise).clamp(0.0, 1.0)
            } else if s < 0.0 {
                1.0
            } else {
                0.0
            }
        };
        let mut worst = 0.0f64;
        for k in 0..17 {
            let angle = k as f64 * std::f64::consts::PI / 17.0 + 0.013;
            let (nx, ny) = (angle.cos(), angle.sin());
            for j in 0..25 {
                let offset = -2.4 + 0.2 * j as f64 + 0.0071;
                for (rise, band) in [(0.0, None), (0.1, None), (0.6, None), (0.0, Some(1.2)), (0.3, Some(2.0))] {
                    let l = |x: f64, y: f64| {
                        let s = x * nx + y * ny - offset;
                        ramp(s, rise) * band.map_or(1.0, |b| ramp(-s - b, rise))
                    };
                    let window: f64 = nodes
                        .iter()
                        .map(|(y, wy)| wy * nodes.iter().map(|(x, wx)| wx * l(*x, *y)).sum::<f64>())
                        .sum();
                    let lap = |x: f64, y: f64| half_var * (l(x + 1.0, y) + l(x - 1.0, y) + l(x, y + 1.0) + l(x, y - 1.0) - 4.0 * l(x, y));
                    let corrected = l(0.0, 0.0) + lap(0.0, 0.0);
                    let error = (corrected - window).abs();
                    let mut near = 0.0f64;
                    for dy in [-1.0, 0.0, 1.0] {
                        for dx in [-1.0, 0.0, 1.0] {
                            near = near.max(lap(dx, dy).abs());
                        }
                    }
                    let along = |ax: f64, ay: f64| {
                        step_beside_centre(std::array::from_fn(|i| {
                            let d = i as f64 - 2.0;
                            l(d * ax, d * ay)
                        }))
                    };
                    let step = (0.5 - half_var) * (along(1.0, 0.0) + along(0.0, 1.0));
                    let charge = near.max(step);
                    assert!(
                        error <= charge + 4e-3,
                        "angle {angle}, offset {offset}, rise {rise}, band {band:?}: error {error} > {charge}"
                    );
                    worst = worst.max(error / charge.max(1e-300));
                }
            }
        }
        println!("worst error / charge {worst:.3}");
    }
}
