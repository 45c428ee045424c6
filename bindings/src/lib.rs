//! `tyndall._native`: thin PyO3 bindings of the Tyndall core.
//!
//! Extract the arguments, release the interpreter (`py.detach`) for the long
//! work, convert the results: images to numpy arrays, the report to a dict
//! (through its JSON), errors to Python exceptions. No physics here.

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArray2, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Duration;
use tyndall_core::scene::LayerKind;
use tyndall_core::{RenderError, Scene, SceneError};

create_exception!(
    _native,
    SceneFormatError,
    PyValueError,
    "A scene was rejected; `.path` names the field, `.source_name` the file."
);
create_exception!(_native, RenderFailed, PyRuntimeError, "A render or an output file failed.");
create_exception!(
    _native,
    RenderCancelled,
    RenderFailed,
    "The render was stopped by its `cancel` event; nothing was returned or written."
);

fn scene_err(py: Python<'_>, e: SceneError) -> PyErr {
    let err = SceneFormatError::new_err(e.to_string());
    let value = err.value(py);
    let _ = value.setattr("path", e.path.clone());
    let _ = value.setattr("source_name", e.source_name.clone());
    let _ = value.setattr("detail", e.message.clone());
    err
}

fn render_err(py: Python<'_>, e: RenderError) -> PyErr {
    match e {
        RenderError::InvalidScene(path, message) => scene_err(
            py,
            SceneError {
                source_name: "<scene>".into(),
                path,
                message,
            },
        ),
        RenderError::Cancelled => RenderCancelled::new_err("the render was cancelled (its cancel event was set)"),
        other => RenderFailed::new_err(other.to_string()),
    }
}

/// Runs `work` on a helper thread with the interpreter released, and checks
/// for Python signals every 50 ms meanwhile. `py.detach` alone would hold the
/// calling thread inside Rust, so Ctrl-C (or a `signal.alarm` handler) would
/// wait for the whole render. When a handler raises, `cancel` is set, the
/// work winds down (about one ray's time) and the handler's exception
/// (`KeyboardInterrupt`, …) is raised in place of the result.
///
/// `stop`, if given, is any object with an `is_set()` method (a
/// `threading.Event`), polled as often: signals reach only the main thread,
/// so this is how a render on another thread (Blender's background job) is
/// stopped. Once it is set, `cancel` is set and the work's own result
/// (`RenderError::Cancelled`) is returned.
///
/// `poll` runs on the calling thread with the interpreter held, at every
/// check and once after the work ends (to pass on progress, [`ProgressRelay`]);
/// an exception it raises stops the work like a signal's.
fn interruptible<T: Send + 'static>(
    py: Python<'_>,
    stop: Option<&Bound<'_, PyAny>>,
    poll: &mut dyn FnMut(Python<'_>) -> PyResult<()>,
    work: impl FnOnce(&AtomicBool) -> T + Send + 'static,
) -> PyResult<T> {
    /// What the caller and the worker share. Owned by both (an `Arc`, not a
    /// borrow of the caller's stack): a daemon thread calling in is ended by
    /// the interpreter at exit while the worker may still run.
    struct Shared {
        cancel: AtomicBool,
        finished: Mutex<bool>,
        signal: Condvar,
    }
    /// Sets `finished` on the way out, by return or by panic (a panic must
    /// not leave the caller waiting for a flag nobody sets).
    struct Finished(Arc<Shared>);
    impl Drop for Finished {
        fn drop(&mut self) {
            *self.0.finished.lock().unwrap_or_else(|e| e.into_inner()) = true;
            self.0.signal.notify_all();
        }
    }
    let is_set = |event: &Bound<'_, PyAny>| event.call_method0("is_set").and_then(|v| v.is_truthy());
    // Already set: the work starts cancelled (and returns `Cancelled` at once).
    let shared = Arc::new(Shared {
        cancel: AtomicBool::new(match stop {
            Some(event) => is_set(event)?,
            None => false,
        }),
        finished: Mutex::new(false),
        signal: Condvar::new(),
    });
    let worker = {
        let shared = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("tyndall-render".into())
            .spawn(move || {
                let _finished = Finished(Arc::clone(&shared));
                work(&shared.cancel)
            })
            .map_err(|e| RenderFailed::new_err(format!("cannot start the render thread: {e}")))?
    };
    let join = |worker: std::thread::JoinHandle<T>| {
        worker
            .join()
            .map_err(|_| RenderFailed::new_err("the render thread panicked (a bug: please report what was rendered)"))
    };
    loop {
        let done = py.detach(|| {
            let guard = shared.finished.lock().unwrap_or_else(|e| e.into_inner());
            let (guard, _) = shared
                .signal
                .wait_timeout_while(guard, Duration::from_millis(50), |done| !*done)
                .unwrap_or_else(|e| e.into_inner());
            *guard
        });
        if done {
            let result = join(worker)?;
            poll(py)?;
            return Ok(result);
        }
        let stop_asked = stop.map_or(Ok(false), is_set);
        match py.check_signals().and_then(|_| poll(py)).and(stop_asked) {
            Ok(false) => {}
            Ok(true) => {
                shared.cancel.store(true, Ordering::Relaxed);
                return py.detach(|| join(worker));
            }
            Err(raised) => {
                shared.cancel.store(true, Ordering::Relaxed);
                let _ = py.detach(|| join(worker));
                return Err(raised);
            }
        }
    }
}

/// Progress from the render's worker threads to a Python callable
/// `progress(stage, done, total)` (`stage` "rendering rows" or "pixel
/// filter"): the workers store the latest state, and the calling thread
/// passes it on when [`interruptible`] polls (every 50 ms, and at the end),
/// so the callable runs on the caller's thread, at most 20 times a second.
#[derive(Clone, Default)]
struct ProgressRelay {
    latest: Arc<Mutex<Option<(tyndall_core::RenderStage, usize, usize)>>>,
}

impl ProgressRelay {
    /// The callback for the core (called from worker threads).
    fn store(&self, stage: tyndall_core::RenderStage, done: usize, total: usize) {
        *self.latest.lock().unwrap_or_else(|e| e.into_inner()) = Some((stage, done, total));
    }

    /// A poll hook that calls `callable` with each new state (nothing without a callable).
    fn poll<'a, 'py>(&'a self, callable: Option<&'a Bound<'py, PyAny>>) -> impl FnMut(Python<'_>) -> PyResult<()> + 'a {
        let mut last = None;
        move |_py| {
            let Some(f) = callable else { return Ok(()) };
            let now = *self.latest.lock().unwrap_or_else(|e| e.into_inner());
            if now.is_some() && now != last {
                last = now;
                if let Some((stage, done, total)) = now {
                    f.call1((stage.label(), done, total))?;
                }
            }
            Ok(())
        }
    }
}

/// A validated scene. Create with `load_scene(path)` or `scene_from_json(text)`.
#[pyclass(name = "Scene", module = "tyndall", frozen)]
#[derive(Clone)]
struct PyScene {
    inner: Scene,
}

#[pymethods]
impl PyScene {
    /// The scene as pretty JSON text.
    fn to_json(&self) -> String {
        self.inner.to_json_string()
    }

    /// Image size `(width, height)` in pixels.
    #[getter]
    fn resolution(&self) -> (u32, u32) {
        match &self.inner.camera {
            tyndall_core::scene::Camera::Perspective(c) => (c.resolution[0], c.resolution[1]),
            tyndall_core::scene::Camera::Equirectangular(c) => (c.resolution[0], c.resolution[1]),
        }
    }

    fn __repr__(&self) -> String {
        let (w, h) = self.resolution();
        format!(
            "<tyndall.Scene {w}x{h}, {} meshes, {} lights, {} media>",
            self.inner.meshes.len(),
            self.inner.lights.len(),
            self.inner.media.len()
        )
    }
}

/// Loads and validates a JSON scene file.
#[pyfunction]
fn load_scene(py: Python<'_>, path: PathBuf) -> PyResult<PyScene> {
    let r = py.detach(|| Scene::load(&path));
    r.map(|inner| PyScene { inner }).map_err(|e| scene_err(py, e))
}

/// `(index in meshes, positions, triangles)` from Python.
type MeshArraysPy<'py> = (usize, PyReadonlyArray2<'py, f64>, PyReadonlyArray2<'py, u32>);

/// Parses and validates a scene from JSON text. `mesh_arrays`: optional
/// `(i, positions, triangles)` for `meshes[i]`, whose arrays are `[]` in the
/// text: C-contiguous `float64 (n, 3)` and `uint32 (m, 3)` numpy arrays
/// (`tyndall.as_scene` checks and converts them).
#[pyfunction]
#[pyo3(signature = (text, source_name = "<string>", mesh_arrays = None))]
fn scene_from_json(py: Python<'_>, text: &str, source_name: &str, mesh_arrays: Option<Vec<MeshArraysPy<'_>>>) -> PyResult<PyScene> {
    let mut arrays = Vec::new();
    for (i, positions, triangles) in mesh_arrays.unwrap_or_default() {
        let rows = |shape: &[usize], what: &str| -> PyResult<()> {
            if shape.len() == 2 && shape[1] == 3 {
                Ok(())
            } else {
                Err(PyValueError::new_err(format!(
                    "meshes[{i}].{what}: expected shape (n, 3), got {shape:?}"
                )))
            }
        };
        rows(positions.shape(), "positions")?;
        rows(triangles.shape(), "triangles")?;
        let p = positions
            .as_slice()
            .map_err(|e| PyValueError::new_err(format!("meshes[{i}].positions: {e}")))?;
        let t = triangles
            .as_slice()
            .map_err(|e| PyValueError::new_err(format!("meshes[{i}].triangles: {e}")))?;
        let p: Vec<[f64; 3]> = p.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        let t: Vec<[u32; 3]> = t.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect();
        arrays.push((i, p, t));
    }
    py.detach(|| Scene::from_json_str_with_meshes(text, source_name, arrays))
        .map(|inner| PyScene { inner })
        .map_err(|e| scene_err(py, e))
}

fn parse_layers(py: Python<'_>, names: Vec<String>) -> PyResult<Vec<LayerKind>> {
    names
        .into_iter()
        .map(|n| {
            serde_json_layer(&n).ok_or_else(|| {
                scene_err(
                    py,
                    SceneError {
                        source_name: "render arguments".into(),
                        path: "layers".into(),
                        message: format!(
                            "unknown layer {n:?}: expected inscatter, transmittance, depth, sun_transmittance, error, inscatter_per_light or surface_transmittance_per_light"
                        ),
                    },
                )
            })
        })
        .collect()
}

fn serde_json_layer(name: &str) -> Option<LayerKind> {
    [
        LayerKind::Inscatter,
        LayerKind::Transmittance,
        LayerKind::Depth,
        LayerKind::SunTransmittance,
        LayerKind::Error,
        LayerKind::InscatterPerLight,
        LayerKind::SurfaceTransmittancePerLight,
    ]
    .into_iter()
    .find(|k| k.to_string() == name)
}

fn with_overrides(
    py: Python<'_>,
    scene: &Scene,
    tolerance: Option<f64>,
    threads: Option<usize>,
    layers: Option<Vec<String>>,
) -> PyResult<Scene> {
    let mut s = scene.clone();
    if let Some(t) = tolerance {
        s.output.tolerance = t;
    }
    if let Some(n) = threads {
        s.output.threads = n;
    }
    if let Some(l) = layers {
        s.output.layers = parse_layers(py, l)?;
    }
    if tolerance.is_some() || threads.is_some() {
        // The overrides are checked as the scene's own fields are (a SceneFormatError naming
        // `output.tolerance`, not a bare ValueError from deep inside the render).
        s.validate().map_err(|(path, message)| {
            scene_err(
                py,
                SceneError {
                    source_name: "render arguments".into(),
                    path,
                    message,
                },
            )
        })?;
    }
    Ok(s)
}

/// An H×W×3 array that takes over the layer's buffer (no copy: a
/// `Vec<[f32; 3]>` is a `Vec<f32>` three times as long, `bytemuck` checks
/// the layout).
fn rgb_array<'py>(py: Python<'py>, px: Vec<[f32; 3]>, w: usize, h: usize) -> PyResult<Bound<'py, PyAny>> {
    let flat: Vec<f32> =
        bytemuck::allocation::try_cast_vec(px).unwrap_or_else(|(_, px)| px.iter().flat_map(|p| p.iter().copied()).collect());
    Ok(PyArray1::from_vec(py, flat).reshape([h, w, 3])?.into_any())
}

/// Renders a scene. Returns `(layers, report)`: a dict of float32 numpy
/// arrays (`inscatter`, `transmittance`, `sun_transmittance`, `error` and
/// `inscatter.<light name>` and `surface_transmittance.<light name>` per stage light: H×W×3; `depth`: H×W), row 0 at the top, and the report as a JSON string.
/// The interpreter is released while rendering.
#[pyfunction]
#[pyo3(signature = (scene, tolerance = None, threads = None, layers = None, cancel = None, progress = None))]
#[allow(clippy::too_many_arguments)]
fn render<'py>(
    py: Python<'py>,
    scene: &PyScene,
    tolerance: Option<f64>,
    threads: Option<usize>,
    layers: Option<Vec<String>>,
    cancel: Option<Bound<'py, PyAny>>,
    progress: Option<Bound<'py, PyAny>>,
) -> PyResult<(Bound<'py, PyDict>, String)> {
    let s = with_overrides(py, &scene.inner, tolerance, threads, layers)?;
    let relay = ProgressRelay::default();
    let to_relay = relay.clone();
    let (mut images, mut report) = interruptible(py, cancel.as_ref(), &mut relay.poll(progress.as_ref()), move |flag| {
        let cb = |stage, done, total| to_relay.store(stage, done, total);
        tyndall_core::render_cancellable(&s, Some(&cb), Some(flag))
    })?
    .map_err(|e| render_err(py, e))?;
    report.resolution = [images.width, images.height];
    let (w, h) = (images.width, images.height);
    let out = PyDict::new(py);
    let layers = std::mem::take(&mut images.layers);
    let mut done: Vec<&LayerKind> = Vec::new();
    for k in &layers {
        // Each buffer is handed over once (a layer named twice is one key).
        if done.contains(&k) {
            continue;
        }
        done.push(k);
        let arr = match k {
            LayerKind::Inscatter => rgb_array(py, std::mem::take(&mut images.inscatter), w, h)?,
            LayerKind::Transmittance => rgb_array(py, std::mem::take(&mut images.transmittance), w, h)?,
            LayerKind::SunTransmittance => rgb_array(py, std::mem::take(&mut images.sun_transmittance), w, h)?,
            LayerKind::Error => rgb_array(py, std::mem::take(&mut images.error), w, h)?,
            LayerKind::Depth => PyArray1::from_vec(py, std::mem::take(&mut images.depth))
                .reshape([h, w])?
                .into_any(),
            LayerKind::InscatterPerLight => {
                for (name, px) in images.light_layer_names.iter().zip(std::mem::take(&mut images.light_inscatter)) {
                    out.set_item(name, rgb_array(py, px, w, h)?)?;
                }
                continue;
            }
            LayerKind::SurfaceTransmittancePerLight => {
                for (name, px) in images
                    .surface_layer_names
                    .iter()
                    .zip(std::mem::take(&mut images.light_surface_transmittance))
                {
                    out.set_item(name, rgb_array(py, px, w, h)?)?;
                }
                continue;
            }
        };
        out.set_item(k.to_string(), arr)?;
    }
    Ok((out, report.to_json()))
}

/// Renders and writes the EXR (and optionally report JSON and PNG preview)
/// atomically; returns the report as a JSON string.
#[pyfunction]
#[pyo3(signature = (scene, out, report = None, preview = None, tolerance = None, threads = None, cancel = None, progress = None))]
// The Python signature's keywords, one argument each (as `sky`).
#[allow(clippy::too_many_arguments)]
fn render_to_files(
    py: Python<'_>,
    scene: &PyScene,
    out: PathBuf,
    report: Option<PathBuf>,
    preview: Option<PathBuf>,
    tolerance: Option<f64>,
    threads: Option<usize>,
    cancel: Option<Bound<'_, PyAny>>,
    progress: Option<Bound<'_, PyAny>>,
) -> PyResult<String> {
    let s = with_overrides(py, &scene.inner, tolerance, threads, None)?;
    let relay = ProgressRelay::default();
    let to_relay = relay.clone();
    let r = interruptible(py, cancel.as_ref(), &mut relay.poll(progress.as_ref()), move |flag| {
        let cb = |stage, done, total| to_relay.store(stage, done, total);
        tyndall_cli::render_to_files_reporting(&s, &out, report.as_deref(), preview.as_deref(), Some(&cb), Some(flag))
    })?;
    match r {
        Ok(rep) => Ok(rep.to_json()),
        Err(tyndall_cli::CliError::Scene(e)) => Err(scene_err(py, e)),
        Err(tyndall_cli::CliError::Render(e)) => Err(render_err(py, e)),
        Err(e) => Err(RenderFailed::new_err(e.to_string())),
    }
}

/// Renders a sky world texture (layered atmosphere, Blender's Sky Texture
/// parameters). Returns `(rgb, report_json)`: an H×W×3 float32 array (row 0
/// the zenith, the centre column towards +X, as Blender's Environment Texture
/// maps it) and the report with the matching sun lamp. With `out`, also writes
/// the EXR (plain R, G, B) and the report next to it. `multiple_scattering`
/// (default false) adds the approximate isotropic second-order term.
/// Interruptible like `render` (Ctrl-C, or `cancel`, an object with
/// `is_set()`, which raises `RenderCancelled`); nothing is written then.
#[pyfunction]
#[pyo3(signature = (sun_elevation_deg, sun_rotation_deg = 0.0, *, air = 1.0, aerosol = 1.0, ozone = 1.0, altitude_m = 0.0, sun_size_deg = 0.545, width = 1024, tolerance = 1e-3, sun_disc = true, multiple_scattering = false, out = None, cancel = None))]
#[allow(clippy::too_many_arguments)]
fn sky<'py>(
    py: Python<'py>,
    sun_elevation_deg: f64,
    sun_rotation_deg: f64,
    air: f64,
    aerosol: f64,
    ozone: f64,
    altitude_m: f64,
    sun_size_deg: f64,
    width: i64,
    tolerance: f64,
    sun_disc: bool,
    multiple_scattering: bool,
    out: Option<PathBuf>,
    cancel: Option<Bound<'py, PyAny>>,
) -> PyResult<(Bound<'py, PyAny>, String)> {
    let sky_error = |py: Python<'_>, (path, message): (String, String)| {
        scene_err(
            py,
            SceneError {
                source_name: "sky parameters".into(),
                path,
                message,
            },
        )
    };
    tyndall_cli::check_sky_angles(sun_elevation_deg, sun_rotation_deg, sun_size_deg, 90.0).map_err(|e| sky_error(py, e))?;
    if !(2..=65536).contains(&width) {
        return Err(sky_error(py, ("width".into(), format!("must be within 2..=65536 px, got {width}"))));
    }
    if !(1e-6..=0.5).contains(&tolerance) {
        return Err(sky_error(
            py,
            ("tolerance".into(), format!("must be within 1e-6..=0.5, got {tolerance}")),
        ));
    }
    let width = width as usize;
    tyndall_cli::check_sky_memory(width).map_err(|e| sky_error(py, e))?;
    if let Some(path) = &out {
        let report_path = path.with_extension("report.json");
        tyndall_cli::prepare_outputs(path, None, Some(&report_path)).map_err(|e| RenderFailed::new_err(e.to_string()))?;
    }
    let params = tyndall_core::sky::atmosphere::AtmosphereParams {
        air_density: air,
        aerosol_density: aerosol,
        ozone_density: ozone,
        altitude_m,
        sun_elevation_rad: sun_elevation_deg.to_radians(),
        sun_rotation_rad: sun_rotation_deg.to_radians(),
        sun_size_rad: sun_size_deg.to_radians(),
        ..Default::default()
    };
    params
        .validate()
        .map_err(|(path, message)| sky_error(py, (tyndall_cli::sky_keyword(&path), message)))?;
    let settings = tyndall_core::sky::texture::TextureSettings {
        width,
        tolerance,
        sun_disc,
    };
    let rendered = interruptible(py, cancel.as_ref(), &mut |_| Ok(()), move |flag| {
        let options = tyndall_core::sky::texture::BuildOptions::default();
        let render = |model: &dyn tyndall_core::sky::texture::SkyModel| {
            tyndall_core::sky::render_world_cancellable(model, "atmosphere", &settings, &options, Some(flag))
        };
        if multiple_scattering {
            render(&tyndall_core::sky::atmosphere::AtmosphereWithMultipleScattering::new(params, 1e-3))
        } else {
            render(&params)
        }
    })?;
    let cancelled = || RenderCancelled::new_err("the sky was cancelled (its cancel event was set)");
    let (tex, report) = rendered.ok_or_else(cancelled)?;
    // An event set after the build's last check: still nothing is returned or written.
    if let Some(event) = &cancel
        && event.call_method0("is_set")?.is_truthy()?
    {
        return Err(cancelled());
    }
    if let Some(path) = out {
        let written = py.detach(|| {
            tyndall_core::io::write_rgb_exr(&path, tex.width, tex.height, &tex.rgb).map_err(|e| e.to_string())?;
            let rp = path.with_extension("report.json");
            tyndall_cli::write_atomic(&rp, serde_json_report(&report).as_bytes()).map_err(|e| e.to_string())
        });
        written.map_err(RenderFailed::new_err)?;
    }
    let (tw, th) = (tex.width, tex.height);
    let arr = rgb_array(py, tex.rgb, tw, th)?;
    Ok((arr, serde_json_report(&report)))
}

fn serde_json_report(r: &tyndall_core::sky::SkyReport) -> String {
    tyndall_core::report::to_json_string(r)
}

/// The JSON Schema of the scene format.
#[pyfunction]
fn scene_schema() -> String {
    tyndall_core::scene::json_schema()
}

/// Runs the `tyndall` command line with `argv` (including the program name);
/// returns the exit code. The interpreter is released while it runs.
#[pyfunction]
fn cli_main(py: Python<'_>, argv: Bound<'_, PyList>) -> PyResult<i32> {
    let args: Vec<String> = argv.extract()?;
    Ok(py.detach(|| tyndall_cli::run(args)))
}

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyScene>()?;
    m.add_function(wrap_pyfunction!(load_scene, m)?)?;
    m.add_function(wrap_pyfunction!(scene_from_json, m)?)?;
    m.add_function(wrap_pyfunction!(render, m)?)?;
    m.add_function(wrap_pyfunction!(render_to_files, m)?)?;
    m.add_function(wrap_pyfunction!(scene_schema, m)?)?;
    m.add_function(wrap_pyfunction!(sky, m)?)?;
    m.add_function(wrap_pyfunction!(cli_main, m)?)?;
    m.add("SceneFormatError", m.py().get_type::<SceneFormatError>())?;
    m.add("RenderFailed", m.py().get_type::<RenderFailed>())?;
    m.add("RenderCancelled", m.py().get_type::<RenderCancelled>())?;
    m.add("__version__", tyndall_core::VERSION)?;
    Ok(())
}
