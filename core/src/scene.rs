//! The scene description: what Tyndall renders, as serde types (JSON on disk).
//!
//! Conventions (see `docs/scene-format.md` for the full table and
//! `docs/scene.schema.json`, generated from these types):
//! * SI units: metres, seconds, watts, steradians; wavelengths in nm.
//! * World frame as in Blender: right-handed, **+Z up**; heights are Z.
//! * Radiance in W·m⁻²·sr⁻¹ per linear Rec.709 channel (Blender scene linear);
//!   sun irradiance in W·m⁻² (Blender's sun "Strength").
//! * Cameras look along their local −Z with +Y up (Blender, USD).
//!
//! Loading is strict: unknown fields, missing required fields, wrong types,
//! non-finite numbers, negative coefficients, zero-length directions and
//! out-of-range parameters are all rejected with a [`SceneError`] naming the
//! field path (`media[0].scattering[2]`), never a panic.

use crate::medium::phase::PhaseFunction;
pub use crate::render::filter::PixelFilter;
use crate::spectrum::{self, SPECTRAL_SAMPLES, Spectrum};
use glam::{DMat3, DMat4, DQuat, DVec3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::path::Path;

/// Marks a field path carried inside an error message from a tagged object
/// (see [`tagged_inner`]); `Scene::from_json_str` splices it into the path.
const PATH_MARK: char = '\u{1}';

/// Deserialises the payload of a `{"type": ...}`-tagged object as `T`,
/// keeping the path of a failing field (serde's own internally tagged enums
/// lose it: the error would point at the object, not at the field).
fn tagged_inner<T: serde::de::DeserializeOwned, E: serde::de::Error>(v: serde_json::Value) -> Result<T, E> {
    serde_path_to_error::deserialize(v).map_err(|e| {
        let path = e.path().to_string();
        let inner = e.into_inner().to_string();
        E::custom(format!("{PATH_MARK}{path}{PATH_MARK}{inner}"))
    })
}

/// `Deserialize` for an enum tagged by `"type"` whose variants wrap structs.
macro_rules! tagged_enum_deserialize {
    ($enum:ident, $what:literal, { $($tag:literal => $variant:ident($ty:ty)),+ $(,)? }) => {
        impl<'de> Deserialize<'de> for $enum {
            fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
                use serde::de::Error;
                const TAGS: &[&str] = &[$($tag),+];
                let mut map = serde_json::Map::<String, serde_json::Value>::deserialize(d)?;
                let tag = match map.remove("type") {
                    Some(serde_json::Value::String(t)) => t,
                    Some(other) => return Err(D::Error::custom(format!("`type` must be a string naming the {}, one of {}; got {other}", $what, TAGS.join(", ")))),
                    None => return Err(D::Error::custom(format!("missing field `type`: the {} type, one of {}", $what, TAGS.join(", ")))),
                };
                let payload = serde_json::Value::Object(map);
                match tag.as_str() {
                    $($tag => tagged_inner::<$ty, D::Error>(payload).map($enum::$variant),)+
                    other => Err(D::Error::custom(format!("unknown {} type `{other}`, expected one of {}", $what, TAGS.join(", ")))),
                }
            }
        }
    };
}

tagged_enum_deserialize!(Camera, "camera", { "perspective" => Perspective(PerspectiveCamera), "equirectangular" => Equirectangular(EquirectangularCamera) });
tagged_enum_deserialize!(Light, "light", {
    "sun" => Sun(SunLight),
    "ambient" => Ambient(AmbientLight),
    "point" => Point(PointLight),
    "spot" => Spot(SpotLight),
    "window" => Window(WindowLight),
});
tagged_enum_deserialize!(IntensityDistribution, "intensity distribution", {
    "isotropic" => Isotropic(IsotropicDistribution),
    "nishita_spot" => NishitaSpot(NishitaSpotDistribution),
    "usd_shaping" => UsdShaping(UsdShapingDistribution),
    "daisy" => Daisy(DaisyDistribution),
    "polka_dot" => PolkaDot(PolkaDotDistribution),
    "tabulated" => Tabulated(TabulatedDistribution),
});
tagged_enum_deserialize!(Medium, "medium", {
    "homogeneous" => Homogeneous(HomogeneousMedium),
    "height_fog" => HeightFog(HeightFogMedium),
    "fog_layer" => FogLayer(FogLayerMedium),
    "layered_height_field" => LayeredHeightField(LayeredHeightFieldMedium),
    "ellipsoid" => Ellipsoid(EllipsoidMedium),
});

/// The scene format version this build reads and writes.
pub const SCENE_VERSION: u32 = 1;

/// Longest name of a point, spot or window light, bytes: its layer's channel
/// `surface_transmittance.<name>_16.R` must fit OpenEXR's 255 bytes.
pub const MAX_STAGE_LIGHT_NAME_BYTES: usize = 228;

/// Largest distance of a mesh vertex (world space) from the origin, m. A ray's
/// hit on a triangle is found from the vertices relative to the ray's origin,
/// and its distance carries a rounding error of about 1e-16 × their size:
/// ≈ 1e-9 of a hit 8 m away on a triangle 1e7 m across, but the whole distance
/// on one 1e17 m across (measured: wrong depths, in-scatter off by half the
/// image's maximum, with an estimate of 2e-6). 10 000 km holds any ground
/// plane a camera needs; farther vertices are an error, not a silent loss.
pub const MAX_MESH_COORDINATE_M: f64 = 1e7;

/// A rejected scene: where (a field path such as `media[0].phase.g`) and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{source_name}: {path}: {message}")]
pub struct SceneError {
    /// File name or `<string>`.
    pub source_name: String,
    /// Field path inside the scene, e.g. `camera.resolution[0]`; `.` for the root.
    pub path: String,
    /// What is wrong, with the unit and the allowed range where it applies.
    pub message: String,
}

/// A whole scene. JSON root object.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Format version; must be 1.
    pub version: u32,
    /// The camera that the images are rendered for.
    pub camera: Camera,
    /// Triangle meshes: surfaces that end view rays (occluders, set pieces). Default: none.
    #[serde(default)]
    pub meshes: Vec<Mesh>,
    /// Lights. Default: none.
    #[serde(default)]
    pub lights: Vec<Light>,
    /// Participating media (haze, fog). Default: none (vacuum).
    #[serde(default)]
    pub media: Vec<Medium>,
    /// Output settings. Default: see [`Output`].
    #[serde(default)]
    pub output: Output,
}

/// Camera. JSON: `{"type": "perspective", ...}` or `{"type": "equirectangular", ...}`.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Camera {
    /// Blender's perspective camera.
    Perspective(PerspectiveCamera),
    /// Full-sphere latitude–longitude camera, mapped as Blender maps an
    /// equirectangular environment texture.
    Equirectangular(EquirectangularCamera),
}

/// How the sensor is fitted to the image (Blender's "Sensor Fit").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SensorFit {
    /// `sensor_width_mm` spans the larger image dimension (Blender's default).
    #[default]
    Auto,
    /// `sensor_width_mm` spans the image width.
    Horizontal,
    /// `sensor_height_mm` spans the image height.
    Vertical,
}

/// Blender's perspective camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PerspectiveCamera {
    /// Eye position, m. Required.
    pub position: [f64; 3],
    /// Where the camera looks. Required.
    pub orientation: Orientation,
    /// Focal length, mm, > 0. Default 50 (Blender).
    #[serde(default = "default_focal")]
    pub focal_length_mm: f64,
    /// Sensor width, mm, > 0. Default 36 (Blender).
    #[serde(default = "default_sensor_w")]
    pub sensor_width_mm: f64,
    /// Sensor height, mm, > 0; used only with `sensor_fit: vertical`. Default 24.
    #[serde(default = "default_sensor_h")]
    pub sensor_height_mm: f64,
    /// Sensor fit. Default `auto`.
    #[serde(default)]
    pub sensor_fit: SensorFit,
    /// Lens shift X in units of the larger image dimension, as Blender. Default 0.
    #[serde(default)]
    pub shift_x: f64,
    /// Lens shift Y in units of the larger image dimension, as Blender. Default 0.
    #[serde(default)]
    pub shift_y: f64,
    /// Image size `[width, height]` in pixels, each 1..=65536. Required.
    pub resolution: [u32; 2],
    /// Clip start, m, ≥ 0, measured along the view axis as Blender does (a ray
    /// at angle θ to the axis starts at clip_start / cos θ). Default 0.
    #[serde(default)]
    pub clip_start_m: f64,
    /// Distance along each view ray where rendering ends, m, > clip_start;
    /// `null` (default) means infinity.
    #[serde(default)]
    pub clip_end_m: Option<f64>,
}

/// Full-sphere equirectangular camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct EquirectangularCamera {
    /// Eye position, m. Required.
    pub position: [f64; 3],
    /// Image size `[width, height]`, pixels, each 1..=65536. Required.
    pub resolution: [u32; 2],
    /// Distance along each view ray where rendering ends, m; `null` (default) = infinity.
    #[serde(default)]
    pub clip_end_m: Option<f64>,
}

fn default_focal() -> f64 {
    50.0
}
fn default_sensor_w() -> f64 {
    36.0
}
fn default_sensor_h() -> f64 {
    24.0
}

/// Camera orientation. JSON: `{"look_at": {"target": [..], "up": [0,0,1]}}` or
/// `{"quaternion_wxyz": [w, x, y, z]}` (rotation of the camera's local frame,
/// which looks along −Z with +Y up, into the world; need not be normalised).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum Orientation {
    /// Look from the camera position at `target`, with `up` (default +Z) kept upright.
    LookAt {
        /// Point looked at, m.
        target: [f64; 3],
        /// Up hint, any length > 0, not parallel to the view direction. Default [0,0,1].
        #[serde(default = "default_up")]
        up: [f64; 3],
    },
    /// Rotation quaternion `[w, x, y, z]`, any non-zero length (normalised on load).
    QuaternionWxyz([f64; 4]),
}

fn default_up() -> [f64; 3] {
    [0.0, 0.0, 1.0]
}

/// An affine transform: `matrix` (row-major 4×4, last row 0 0 0 1), or
/// translation · rotation · scale. Default: identity.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Transform {
    /// Row-major 4×4 matrix (Blender's `matrix_world` rows). Excludes the other fields.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub matrix: Option<[[f64; 4]; 4]>,
    /// Translation, m. Default [0,0,0].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub translation: Option<[f64; 3]>,
    /// Rotation quaternion `[w,x,y,z]`, non-zero. Default identity.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub rotation_wxyz: Option<[f64; 4]>,
    /// Scale per axis, non-zero. Default [1,1,1].
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scale: Option<[f64; 3]>,
}

/// A triangle mesh. Surfaces end view rays; they are not shaded (Tyndall
/// renders what the medium adds: composite `final = surface × T + L`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Mesh {
    /// Name, for reports. Default "".
    #[serde(default)]
    pub name: String,
    /// Vertex positions in object space, m.
    pub positions: Vec<[f64; 3]>,
    /// Vertex index triples, each < `positions.len()`.
    pub triangles: Vec<[u32; 3]>,
    /// Object → world transform. Default identity.
    #[serde(default)]
    pub transform: Transform,
    /// Whether view rays stop at it (Blender's Ray Visibility > Camera). Off,
    /// the camera sees through it, and it may still cast shadows. Default true.
    #[serde(default = "default_true", skip_serializing_if = "is_true")]
    pub visible_to_camera: bool,
    /// Whether it shadows the stage lights' illumination volumes (Blender's
    /// Ray Visibility > Shadow). Off, it still ends the view rays that meet
    /// it. Default true.
    #[serde(default = "default_true", skip_serializing_if = "is_true")]
    pub casts_shadows: bool,
}

/// How a light's colour is given spectrally.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum LightSpectrum {
    /// `color` × strength, upsampled linearly (exact round trip) when the
    /// render is spectral.
    #[default]
    Rgb,
    /// The extraterrestrial solar spectrum, scaled so that its luminance-weighted
    /// RGB has the given strength; `color` multiplies it.
    Solar,
}

/// A mesh's `(index in meshes, positions, triangles)` given apart from the
/// scene's JSON text ([`Scene::from_json_str_with_meshes`]).
pub type MeshArrays = (usize, Vec<[f64; 3]>, Vec<[u32; 3]>);

/// A light. JSON: `{"type": "sun" | "ambient" | "point" | "spot" | "window", ...}`.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Light {
    /// A directional light (Blender's Sun lamp): parallel rays from `direction_to_sun`.
    Sun(SunLight),

    /// Uniform incident radiance from every direction (sky/fill), scattered
    /// isotropically (Ishiyama eq 11).
    Ambient(AmbientLight),

    /// A point light (Blender's Point lamp) with an optional intensity
    /// distribution I(θ, φ) and IES profile (Nishita eqs 7–10, appendix).
    Point(PointLight),

    /// Blender's Spot lamp: a point light masked by Cycles' spot cone
    /// (`spot_size_deg`, `spot_blend`), optionally with an IES profile.
    Spot(SpotLight),

    /// Parallel light through a planar window polygon (Nishita Fig. 3): the
    /// illumination volume is the prism the polygon sweeps along the light.
    Window(WindowLight),
}

fn default_identity_orientation() -> Orientation {
    Orientation::QuaternionWxyz([1.0, 0.0, 0.0, 0.0])
}
fn default_point_name() -> String {
    "point".into()
}
fn default_spot_name() -> String {
    "spot".into()
}
fn default_window_name() -> String {
    "window".into()
}
fn default_light_power() -> f64 {
    1000.0
}
fn default_spot_size() -> f64 {
    45.0
}
fn default_spot_blend() -> f64 {
    0.15
}

/// An IES LM-63 photometric profile attached to a point or spot light, as
/// Blender's IES Texture node plugged into the light's emission strength.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct IesProfileRef {
    /// Path of the `.ies` file; relative paths are relative to the scene
    /// file's folder (the working directory for scenes given as text).
    pub file: String,
    /// Factor on the profile, ≥ 0, as the IES node's Strength input. Default 1.
    #[serde(default = "default_one")]
    pub strength: f64,
}

/// A point light. Radiant intensity towards direction ω (W·sr⁻¹ per channel):
/// `I(ω) = color · power_w · K · D(ω) · IES(ω)`, with Cycles' convention
/// `K = 1/(4π)` W·sr⁻¹ per W (see `docs/cycles-conventions.md`), `D` the
/// relative `distribution` (1 on the axis) and `IES` the profile factor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PointLight {
    /// Name for reports and the `inscatter.<name>` layer. Default "point".
    #[serde(default = "default_point_name")]
    pub name: String,
    /// Position, m.
    pub position: [f64; 3],
    /// Orientation; the illumination axis is the light's local −Z and φ = 0
    /// is its local +X (Blender). Default identity: shining straight down.
    #[serde(default = "default_identity_orientation")]
    pub orientation: Orientation,
    /// Linear Rec.709 colour, each ≥ 0. Default [1,1,1].
    #[serde(default = "default_white")]
    pub color: [f64; 3],
    /// Blender's Power, W, ≥ 0. Default 1000.
    #[serde(default = "default_light_power")]
    pub power_w: f64,
    /// Blender's Radius, m, ≥ 0: view rays passing closer than this to the
    /// light are evaluated as if at this distance (Tyndall treats the light
    /// as a point). Default 0.
    #[serde(default)]
    pub radius_m: f64,
    /// Relative intensity distribution. Default isotropic.
    #[serde(default)]
    pub distribution: IntensityDistribution,
    /// IES profile. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ies: Option<IesProfileRef>,
    /// Whether meshes shadow its light (Blender's Cast Shadow). Off, its
    /// whole illumination volume is lit, and the media do not dim the light
    /// on its way (Cycles traces no shadow ray for it). Default true.
    #[serde(default = "default_true", skip_serializing_if = "is_true")]
    pub casts_shadows: bool,
}

/// Blender's Spot lamp: a point light with Cycles' spot mask
/// `smoothstep((cos θ − cos(size/2)) / (blend·(1 − cos(size/2))))`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SpotLight {
    /// Name for reports and the `inscatter.<name>` layer. Default "spot".
    #[serde(default = "default_spot_name")]
    pub name: String,
    /// Position, m.
    pub position: [f64; 3],
    /// Orientation; the spot shines along its local −Z (Blender). Default identity: straight down.
    #[serde(default = "default_identity_orientation")]
    pub orientation: Orientation,
    /// Linear Rec.709 colour, each ≥ 0. Default [1,1,1].
    #[serde(default = "default_white")]
    pub color: [f64; 3],
    /// Blender's Power, W, ≥ 0. Default 1000.
    #[serde(default = "default_light_power")]
    pub power_w: f64,
    /// Blender's Radius, m, ≥ 0 (see [`PointLight::radius_m`]). Default 0.
    #[serde(default)]
    pub radius_m: f64,
    /// Full cone angle, degrees, 0.1..=180 (Blender's Spot Size, 1°..180°; 0.1° allowed). Default 45.
    #[serde(default = "default_spot_size")]
    pub spot_size_deg: f64,
    /// Softness of the cone edge, 0..=1 (Blender's Blend). Default 0.15.
    #[serde(default = "default_spot_blend")]
    pub spot_blend: f64,
    /// IES profile. Default none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ies: Option<IesProfileRef>,
    /// Whether meshes shadow its light (Blender's Cast Shadow). Off, its
    /// whole illumination volume is lit, and the media do not dim the light
    /// on its way (Cycles traces no shadow ray for it). Default true.
    #[serde(default = "default_true", skip_serializing_if = "is_true")]
    pub casts_shadows: bool,
}

/// Parallel light through a planar convex or concave polygon (a window).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct WindowLight {
    /// Name for reports and the `inscatter.<name>` layer. Default "window".
    #[serde(default = "default_window_name")]
    pub name: String,
    /// Unit-less vector from the scene towards the light source, non-zero.
    pub direction_to_light: [f64; 3],
    /// Linear Rec.709 colour, each ≥ 0. Default [1,1,1].
    #[serde(default = "default_white")]
    pub color: [f64; 3],
    /// Irradiance on a surface facing the light, W·m⁻², ≥ 0. Default 1.
    #[serde(default = "default_one")]
    pub irradiance_w_m2: f64,
    /// The window polygon's corners in order, m; ≥ 3, planar to 1e-6
    /// relative, not parallel to the light direction.
    pub aperture: Vec<[f64; 3]>,
    /// Whether meshes shadow its light (as Blender's Cast Shadow). Off, its
    /// whole prism is lit, undimmed between the window and each point. Default true.
    #[serde(default = "default_true", skip_serializing_if = "is_true")]
    pub casts_shadows: bool,
}

/// Relative luminous intensity distribution of a point light, 1 on the axis
/// (θ = 0) unless the distribution says otherwise. θ is measured from the
/// illumination axis (local −Z), φ around it from local +X towards +Y.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum IntensityDistribution {
    /// 1 in every direction.
    Isotropic(IsotropicDistribution),
    /// Nishita eq 7: `(1−q)(cos θ − cos γ)/(1 − cos γ) + q` inside the beam spread γ, 0 outside.
    NishitaSpot(NishitaSpotDistribution),
    /// UsdLux ShapingAPI: cone angle, softness and focus.
    UsdShaping(UsdShapingDistribution),
    /// Nishita eq 9: eq 7 times the petal function k(φ) of eq 8.
    Daisy(DaisyDistribution),
    /// Nishita eq 10: eq 9 times k(θ) and the checkerboard v.
    PolkaDot(PolkaDotDistribution),
    /// Table of relative intensity over (θ, φ), bilinear interpolation.
    Tabulated(TabulatedDistribution),
}

impl Default for IntensityDistribution {
    fn default() -> Self {
        IntensityDistribution::Isotropic(IsotropicDistribution {})
    }
}

/// Isotropic: no fields.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct IsotropicDistribution {}

/// Nishita's spotlight, eq 7.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct NishitaSpotDistribution {
    /// Beam spread γ (half-angle of the lit cone), degrees, 0.01..=180.
    pub beam_spread_deg: f64,
    /// Edge sharpness q, 0..=1 (1 very sharp, 0 very soft).
    pub sharpness: f64,
}

/// UsdLux ShapingAPI (`shaping:cone:angle`, `shaping:cone:softness`, `shaping:focus`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct UsdShapingDistribution {
    /// Cone half-angle, degrees, 0.01..=180. Default 90 (USD: 90 = no cone).
    #[serde(default = "default_usd_cone")]
    pub cone_angle_deg: f64,
    /// Cone softness, 0..=1. Default 0.
    #[serde(default)]
    pub cone_softness: f64,
    /// Focus exponent, ≥ 0: the intensity is multiplied by `cos(θ)^focus`. Default 0.
    #[serde(default)]
    pub focus: f64,
}
fn default_usd_cone() -> f64 {
    90.0
}

/// Nishita's daisy, eq 9 = eq 7 × k(φ) of eq 8.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DaisyDistribution {
    /// Beam spread γ, degrees, 0.01..=180.
    pub beam_spread_deg: f64,
    /// Edge sharpness q, 0..=1.
    pub sharpness: f64,
    /// Petal period Δφ, degrees, 0.1..=360.
    pub period_phi_deg: f64,
    /// Ratio p of minimum to maximum intensity, −10..1 (negative: narrower petals).
    pub min_ratio: f64,
}

/// Nishita's polka dots, eq 10.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PolkaDotDistribution {
    /// Beam spread γ, degrees, 0.01..=180.
    pub beam_spread_deg: f64,
    /// Edge sharpness q, 0..=1.
    pub sharpness: f64,
    /// Period Δφ, degrees, 0.1..=360.
    pub period_phi_deg: f64,
    /// Period Δθ, degrees, 0.1..=180.
    pub period_theta_deg: f64,
    /// Ratio p of minimum to maximum intensity, −10..1 (negative: smaller dots).
    pub min_ratio: f64,
}

/// Tabulated relative intensity `values[i_phi][i_theta]`, bilinear in (θ, φ).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TabulatedDistribution {
    /// θ samples, degrees, strictly increasing within 0..=180; beyond the
    /// last sample the intensity is 0.
    pub theta_deg: Vec<f64>,
    /// φ samples, degrees, strictly increasing within 0..360, periodic; one
    /// sample means axisymmetric.
    pub phi_deg: Vec<f64>,
    /// Relative intensities, ≥ 0, one row per φ sample, one column per θ sample.
    pub values: Vec<Vec<f64>>,
}

/// A directional light (Blender's Sun lamp): parallel rays from `direction_to_sun`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct SunLight {
    /// Name for reports and per-light layers. Default "sun".
    #[serde(default = "default_sun_name")]
    pub name: String,
    /// Unit-less vector pointing from the scene towards the sun, non-zero.
    pub direction_to_sun: [f64; 3],
    /// Linear Rec.709 colour, each ≥ 0. Default [1,1,1].
    #[serde(default = "default_white")]
    pub color: [f64; 3],
    /// Irradiance on a surface facing the sun, W·m⁻², ≥ 0 (Blender's Strength). Default 1.
    #[serde(default = "default_one")]
    pub strength_w_m2: f64,
    /// Angular diameter of the disc, degrees, 0..=180. Default 0.526 (Blender).
    #[serde(default = "default_sun_angle")]
    pub angular_diameter_deg: f64,
    /// Spectral shape. Default `rgb`.
    #[serde(default)]
    pub spectrum: LightSpectrum,
}

/// Uniform incident radiance from every direction (sky/fill), scattered
/// isotropically (Ishiyama eq 11).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct AmbientLight {
    /// Name. Default "ambient".
    #[serde(default = "default_ambient_name")]
    pub name: String,
    /// Linear Rec.709 colour, each ≥ 0. Default [1,1,1].
    #[serde(default = "default_white")]
    pub color: [f64; 3],
    /// Radiance, W·m⁻²·sr⁻¹, ≥ 0. Default 1.
    #[serde(default = "default_one")]
    pub radiance: f64,
}

fn default_sun_name() -> String {
    "sun".into()
}
fn default_ambient_name() -> String {
    "ambient".into()
}
fn default_white() -> [f64; 3] {
    [1.0, 1.0, 1.0]
}
fn default_one() -> f64 {
    1.0
}
fn default_sun_angle() -> f64 {
    0.526
}

/// A coefficient in m⁻¹ that may depend on wavelength. JSON forms:
/// * a number: grey (the same at every wavelength);
/// * `[r, g, b]`: per linear Rec.709 channel (rendered in RGB);
/// * `{"spectrum_nm": [[λ, value], ...]}`: sampled spectrum, λ in nm
///   increasing, linearly interpolated, held constant outside the samples;
/// * `{"power_law": {"at_550nm": β, "exponent": 4}}`: β·(550/λ)^exponent
///   (exponent 4 is Rayleigh, ≈1.3 is Ångström's haze).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(untagged)]
pub enum Coefficient {
    /// Grey.
    Grey(f64),
    /// Per Rec.709 channel.
    Rgb([f64; 3]),
    /// Spectral.
    Spectral(SpectralCoefficient),
}

impl Default for Coefficient {
    fn default() -> Self {
        Coefficient::Grey(0.0)
    }
}

/// Spectral forms of a [`Coefficient`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
pub enum SpectralCoefficient {
    /// Samples `[λ nm, value m⁻¹]`, λ strictly increasing, ≥ 1 sample.
    SpectrumNm(Vec<[f64; 2]>),
    /// β·(550 nm/λ)^exponent.
    PowerLaw {
        /// Value at 550 nm, m⁻¹, ≥ 0.
        at_550nm: f64,
        /// Exponent, finite (4 = Rayleigh).
        exponent: f64,
    },
}

/// Where a homogeneous medium is.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case", deny_unknown_fields)]
#[derive(Default)]
pub enum Bounds {
    /// Everywhere (Blender's world volume).
    #[default]
    World,
    /// A box (a volume object such as a haze box around a stage): the
    /// axis-aligned box `min ≤ x ≤ max`, turned by `rotation_wxyz` about its
    /// centre `(min + max)/2`.
    Box {
        /// Minimum corner before the rotation, m.
        min: [f64; 3],
        /// Maximum corner before the rotation, m, each component > `min`.
        max: [f64; 3],
        /// Rotation box → world about the box's centre, as a quaternion
        /// `[w, x, y, z]`, non-zero (normalised on load). Default none
        /// (faces along world X, Y, Z).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        rotation_wxyz: Option<[f64; 4]>,
    },
}

/// Scattering and absorption of one component of the height fog.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FogComponent {
    /// Scattering coefficient at the reference height, m⁻¹, ≥ 0.
    pub scattering: Coefficient,
    /// Absorption coefficient at the reference height, m⁻¹, ≥ 0. Default 0.
    #[serde(default)]
    pub absorption: Coefficient,
}

/// Mie component of the height fog, with its phase function.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MieComponent {
    /// Scattering coefficient at the reference height, m⁻¹, ≥ 0.
    pub scattering: Coefficient,
    /// Absorption coefficient at the reference height, m⁻¹, ≥ 0. Default 0.
    #[serde(default)]
    pub absorption: Coefficient,
    /// Phase function. Default Cornette–Shanks g = 0.76.
    #[serde(default = "default_mie_phase")]
    pub phase: PhaseFunction,
}

fn default_mie_phase() -> PhaseFunction {
    PhaseFunction::CornetteShanks { g: 0.76 }
}

/// Which sun path through the fog layer Klassen's closed form uses.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SunPath {
    /// The exact flat-earth path from the fog top to each scattering point,
    /// (z_top − z)/sin φ, integrated in closed form (default).
    #[default]
    PerPoint,
    /// Klassen's eq 3.11/3.20: the whole fog thickness (z_top − z_ground)/sin φ
    /// for every point (his approximation for an eye near the ground).
    FullLayer,
}

/// A medium. JSON: `{"type": "homogeneous" | "height_fog" | "fog_layer" |
/// "layered_height_field" | "ellipsoid", ...}`.
#[derive(Debug, Clone, PartialEq, Serialize, JsonSchema)]
#[serde(tag = "type", rename_all = "snake_case")]
pub enum Medium {
    /// Constant coefficients, in the world or in a box.
    Homogeneous(HomogeneousMedium),

    /// Ishiyama's exponential height fog: Rayleigh + Mie sharing one scale height.
    HeightFog(HeightFogMedium),

    /// Klassen's sunlit fog layer (flat earth): uniform fog between two heights.
    FogLayer(FogLayerMedium),

    /// Nishita's dense lower layer (dry ice) under a boundary made of sine waves.
    LayeredHeightField(LayeredHeightFieldMedium),

    /// Nishita's smoke: constant coefficients inside an ellipsoid.
    Ellipsoid(EllipsoidMedium),
}

/// One sine wave of a height field:
/// `A·sin(2π (x cos θ + y sin θ)/λ + φ)`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HeightWave {
    /// Amplitude A, m, 0..=1e4. Required.
    pub amplitude_m: f64,
    /// Wavelength λ, m, 1e-3..=1e7. Required.
    pub wavelength_m: f64,
    /// Direction θ of the wave vector in the XY plane, degrees from +X towards
    /// +Y, -360..=360. Default 0.
    #[serde(default)]
    pub direction_deg: f64,
    /// Phase φ, degrees, -360..=360. Default 0.
    #[serde(default)]
    pub phase_deg: f64,
}

/// Coefficients on one side of a height-field boundary.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LayerSide {
    /// Scattering coefficient σ_s, m⁻¹, ≥ 0. Required.
    pub scattering: Coefficient,
    /// Absorption coefficient σ_a, m⁻¹, ≥ 0. Default 0.
    #[serde(default)]
    pub absorption: Coefficient,
    /// Phase function. Default isotropic.
    #[serde(default)]
    pub phase: PhaseFunction,
}

/// Nishita et al. 1987 §4: a dense lower layer (dry ice) whose upper boundary
/// is `z = base + Σ_k A_k sin(2π (x cos θ_k + y sin θ_k)/λ_k + φ_k)`; the
/// `lower` coefficients apply below it, `upper` above.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LayeredHeightFieldMedium {
    /// Name for reports. Default "".
    #[serde(default)]
    pub name: String,
    /// Mean height of the boundary, m, -1e7..=1e7. Required.
    pub base_height_m: f64,
    /// The sine waves, 1..=8. Required.
    pub waves: Vec<HeightWave>,
    /// Below the boundary (the dense layer). Required.
    pub lower: LayerSide,
    /// Above the boundary. Default none (vacuum).
    #[serde(default)]
    pub upper: Option<LayerSide>,
}

/// Nishita et al. 1987 §4: smoke of constant density inside an ellipsoid.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct EllipsoidMedium {
    /// Name for reports. Default "".
    #[serde(default)]
    pub name: String,
    /// Centre, m, each component finite. Required.
    pub center: [f64; 3],
    /// Semi-axes along the local X, Y, Z axes, m, each 1e-6..=1e7. Required.
    pub radii: [f64; 3],
    /// Rotation local → world as a quaternion `[w, x, y, z]`, non-zero
    /// (normalised on load). Default none (axes along world X, Y, Z).
    #[serde(default)]
    pub rotation_wxyz: Option<[f64; 4]>,
    /// Scattering coefficient σ_s, m⁻¹, ≥ 0. Required.
    pub scattering: Coefficient,
    /// Absorption coefficient σ_a, m⁻¹, ≥ 0. Default 0.
    #[serde(default)]
    pub absorption: Coefficient,
    /// Phase function. Default isotropic.
    #[serde(default)]
    pub phase: PhaseFunction,
}

/// Constant coefficients, in the world or in a box.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HomogeneousMedium {
    /// Name for reports. Default "".
    #[serde(default)]
    pub name: String,
    /// Scattering coefficient σ_s, m⁻¹, ≥ 0. Required.
    pub scattering: Coefficient,
    /// Absorption coefficient σ_a, m⁻¹, ≥ 0. Default 0.
    #[serde(default)]
    pub absorption: Coefficient,
    /// Phase function. Default isotropic.
    #[serde(default)]
    pub phase: PhaseFunction,
    /// Extent. Default `"world"`.
    #[serde(default)]
    pub bounds: Bounds,
}

/// Ishiyama's exponential height fog: Rayleigh + Mie sharing one scale height.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct HeightFogMedium {
    /// Name for reports. Default "".
    #[serde(default)]
    pub name: String,
    /// Scale height H, m, 1e-3..=1e7. Required.
    pub scale_height_m: f64,
    /// Height where the coefficients apply, m. Default 0.
    #[serde(default)]
    pub reference_height_m: f64,
    /// Rayleigh component (phase 3/(16π)(1+μ²)). Default none.
    #[serde(default)]
    pub rayleigh: Option<FogComponent>,
    /// Mie component. Default none.
    #[serde(default)]
    pub mie: Option<MieComponent>,
}

/// Klassen's sunlit fog layer (flat earth): uniform fog between two heights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FogLayerMedium {
    /// Name for reports. Default "".
    #[serde(default)]
    pub name: String,
    /// Ground (bottom of the fog), m. Default 0.
    #[serde(default)]
    pub ground_height_m: f64,
    /// Top of the fog, m, > ground. Required.
    pub top_height_m: f64,
    /// Fog extinction β_ex,p, m⁻¹, ≥ 0 (15e-3..40e-3 for fog per Klassen). Required.
    pub extinction: Coefficient,
    /// Fraction of extinction that is scattering, 0..=1. Default 1 (Klassen:
    /// fog in a steady state only scatters).
    #[serde(default = "default_one")]
    pub single_scattering_albedo: f64,
    /// Molecular extinction inside the layer β_ex,m, m⁻¹, ≥ 0. Default 0.
    #[serde(default)]
    pub air_extinction: Coefficient,
    /// Phase function of the droplets. Default Nishita hazy.
    #[serde(default = "default_fog_phase")]
    pub phase: PhaseFunction,
    /// Sun path through the layer. Default `per_point`.
    #[serde(default)]
    pub sun_path: SunPath,
    /// Below this sun elevation, degrees 0..=90, the direct sun term is replaced
    /// by the constant fog colour of the ambient light (Klassen §3: at low sun
    /// no direct light gets through; the flat earth holds to 1 % for fog above
    /// ≈15°). Default 15.
    #[serde(default = "default_min_sun")]
    pub min_sun_elevation_deg: f64,
}

fn default_fog_phase() -> PhaseFunction {
    PhaseFunction::NishitaHazy
}
fn default_min_sun() -> f64 {
    15.0
}

/// Output layers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum LayerKind {
    /// In-scattered radiance L, RGB, W·m⁻²·sr⁻¹.
    Inscatter,
    /// View-ray transmittance T, RGB, 0..1.
    Transmittance,
    /// Distance along the view ray to the first surface, Z, m; 1e10 where none (Blender).
    Depth,
    /// Transmittance of sunlight to the surface point, RGB (1 where no sun or no surface).
    SunTransmittance,
    /// Estimated absolute error of `inscatter`, RGB, W·m⁻²·sr⁻¹.
    Error,
    /// One `inscatter.<light name>` layer per point, spot and window light, RGB, W·m⁻²·sr⁻¹.
    InscatterPerLight,
    /// One `surface_transmittance.<light name>` layer per point, spot and
    /// window light, RGB, 0..1: the medium's transmittance along the whole
    /// path of that light's direct light to the camera via the visible surface,
    /// T(light → surface) · T(surface → camera). Geometry shadows are not in it
    /// (a renderer's light group has them). Where the pixel sees no surface: the
    /// view transmittance. Filtered pixels average over the surface samples only.
    SurfaceTransmittancePerLight,
}

/// Spectral or RGB computation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum SpectralMode {
    /// Spectral only when some medium has a wavelength-dependent spectral
    /// coefficient (default). A solar-spectrum light alone does not need it:
    /// grey or RGB media scale every wavelength of a channel alike.
    #[default]
    Auto,
    /// Always spectral (81 samples, 380–780 nm at 5 nm).
    Always,
    /// Always RGB; spectral coefficients are reduced to RGB first.
    Never,
}

/// Output settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Output {
    /// Layers to write. Default inscatter, transmittance, depth.
    #[serde(default = "default_layers")]
    pub layers: Vec<LayerKind>,
    /// Relative error tolerance of numerically integrated pixels, 1e-12..=0.5. Default 1e-4.
    #[serde(default = "default_tolerance")]
    pub tolerance: f64,
    /// Worker threads, 0 = all cores. Default 0.
    #[serde(default)]
    pub threads: usize,
    /// Spectral or RGB. Default auto.
    #[serde(default)]
    pub spectral: SpectralMode,
    /// Pixel filter of perspective images. Default Blackman–Harris 1.5 px (Blender's).
    #[serde(default)]
    pub pixel_filter: PixelFilter,
    /// Leave out the view rays of image tiles that provably miss every
    /// light's illumination volume: their in-scatter is exactly 0. With
    /// transmittance, depth or surface-transmittance layers (point samples
    /// only) those rays are followed to their surface and nothing is
    /// integrated. Default true; false traces every pixel (for checking;
    /// it also turns `interpolate_smooth_pixels` off, whose machinery it
    /// shares, so the images then differ within their estimates).
    #[serde(default = "default_true")]
    pub skip_unlit_tiles: bool,
    /// Interpolate pixels where the in-scatter is provably smooth (inside a
    /// beam, away from silhouettes, shadows and lights' images), with
    /// `skip_unlit_tiles` on and without the `sun_transmittance` layer: the
    /// view rays of a lattice of pixels (x and y multiples
    /// of 4) are traced, the others are interpolated in two levels when
    /// their error estimate meets the tolerance, else traced (see
    /// `render::smooth`). Default true; false traces every pixel.
    #[serde(default = "default_true")]
    pub interpolate_smooth_pixels: bool,
    /// Filter the pixels across a spot's beam from the beam's angular
    /// profile instead of a lattice of view rays, where that meets the
    /// tolerance (see `render::profile`): when all in-scatter comes from
    /// Blender spot lamps in media without boundaries. Default true; false
    /// sends every such pixel to the lattice (for checking).
    #[serde(default = "default_true")]
    pub profile_filter: bool,
}

impl Default for Output {
    fn default() -> Self {
        Output {
            layers: default_layers(),
            tolerance: default_tolerance(),
            threads: 0,
            spectral: SpectralMode::Auto,
            pixel_filter: PixelFilter::default(),
            skip_unlit_tiles: true,
            interpolate_smooth_pixels: true,
            profile_filter: true,
        }
    }
}

fn default_layers() -> Vec<LayerKind> {
    vec![LayerKind::Inscatter, LayerKind::Transmittance, LayerKind::Depth]
}
fn default_tolerance() -> f64 {
    1e-4
}
fn is_true(v: &bool) -> bool {
    *v
}

fn default_true() -> bool {
    true
}

// ---------------------------------------------------------------- loading

impl Scene {
    /// Parses and validates a scene from JSON text; `source_name` names it in errors.
    pub fn from_json_str(text: &str, source_name: &str) -> Result<Scene, SceneError> {
        Self::from_json_str_with_meshes(text, source_name, Vec::new())
    }

    /// [`Scene::from_json_str`] whose meshes' vertex and index arrays may come
    /// apart from the text: each `(i, positions, triangles)` replaces the arrays
    /// of `meshes[i]` (given as `[]` in the text) before the scene is validated,
    /// so errors name the same fields. A million-triangle mesh is ≈ 50 MB of
    /// JSON whose printing and parsing took longer than rendering it (the
    /// Python bindings pass numpy arrays this way).
    pub fn from_json_str_with_meshes(text: &str, source_name: &str, arrays: Vec<MeshArrays>) -> Result<Scene, SceneError> {
        // (serde reads a struct from an array too, by field order: a whole scene
        // given as `[1, {camera}, …]` rendered.)
        let first = text.trim_start().chars().next();
        if first.is_some_and(|c| c != '{') {
            return Err(SceneError {
                source_name: source_name.to_string(),
                path: ".".into(),
                message: format!(
                    "a scene is a JSON object {{\"version\": 1, …}}, got text starting with {:?}",
                    first.unwrap_or(' ')
                ),
            });
        }
        let de = &mut serde_json::Deserializer::from_str(text);
        let mut scene: Scene = serde_path_to_error::deserialize(de).map_err(|e| {
            let mut path = e.path().to_string();
            let mut message = e.into_inner().to_string();
            // Paths from inside tagged objects arrive as MARK path MARK message.
            while let Some(rest) = message.strip_prefix(PATH_MARK) {
                let Some((inner, tail)) = rest.split_once(PATH_MARK) else { break };
                if !inner.is_empty() && inner != "." {
                    if path.is_empty() || path == "." {
                        path = inner.to_string();
                    } else if inner.starts_with('[') {
                        path = format!("{path}{inner}");
                    } else {
                        path = format!("{path}.{inner}");
                    }
                }
                message = tail.to_string();
            }
            let message = describe_json_error(&message);
            SceneError {
                source_name: source_name.to_string(),
                path: if path.is_empty() { ".".into() } else { path },
                message,
            }
        })?;
        for (i, positions, triangles) in arrays {
            let n = scene.meshes.len();
            let Some(mesh) = scene.meshes.get_mut(i) else {
                return Err(SceneError {
                    source_name: source_name.to_string(),
                    path: "meshes".into(),
                    message: format!("arrays were given for meshes[{i}], but the scene has {n} meshes"),
                });
            };
            if !mesh.positions.is_empty() || !mesh.triangles.is_empty() {
                return Err(SceneError {
                    source_name: source_name.to_string(),
                    path: format!("meshes[{i}]"),
                    message: "positions and triangles are given both in the text and as arrays".into(),
                });
            }
            mesh.positions = positions;
            mesh.triangles = triangles;
        }
        scene.validate().map_err(|(path, message)| SceneError {
            source_name: source_name.to_string(),
            path,
            message,
        })?;
        Ok(scene)
    }

    /// Reads, parses and validates a JSON scene file.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|e| SceneError {
            source_name: path.display().to_string(),
            path: ".".into(),
            message: format!("cannot read file: {e}"),
        })?;
        let mut scene = Scene::from_json_str(&text, &path.display().to_string())?;
        if let Some(dir) = path.parent() {
            scene.resolve_relative_paths(dir);
        }
        Ok(scene)
    }

    /// Makes relative file references (IES profiles) relative to `dir`.
    pub fn resolve_relative_paths(&mut self, dir: &Path) {
        for l in &mut self.lights {
            let ies = match l {
                Light::Point(p) => p.ies.as_mut(),
                Light::Spot(p) => p.ies.as_mut(),
                _ => None,
            };
            if let Some(r) = ies
                && Path::new(&r.file).is_relative()
            {
                r.file = dir.join(&r.file).display().to_string();
            }
        }
    }

    /// Serialises to pretty JSON.
    pub fn to_json_string(&self) -> String {
        serde_json::to_string_pretty(self).unwrap_or_else(|e| format!("{{\"error\": \"{e}\"}}"))
    }

    /// Checks every value; `Err((field path, message))` for the first problem.
    pub fn validate(&self) -> Result<(), (String, String)> {
        let mut v = Validator::default();
        v.check(self);
        match v.first {
            Some(e) => Err(e),
            None => Ok(()),
        }
    }
}

fn describe_json_error(msg: &str) -> String {
    let msg = msg.to_string();
    // serde_json writes "... at line L column C"; keep it, and explain the
    // untagged-coefficient message, which says nothing useful on its own.
    if msg.contains("untagged enum Coefficient") {
        let loc = msg
            .rsplit_once(" at line ")
            .map(|(_, l)| format!(" at line {l}"))
            .unwrap_or_default();
        return format!(
            "expected a coefficient in m⁻¹: a number, [r, g, b], {{\"spectrum_nm\": [[nm, value], ...]}} or {{\"power_law\": {{\"at_550nm\": b, \"exponent\": e}}}}{loc}"
        );
    }
    msg
}

/// `x` for a message: plain where that is short, else in exponent form
/// (`5e-324`, not 324 digits).
fn number(x: f64) -> String {
    let plain = format!("{x}");
    if plain.len() > 12 && x != 0.0 { format!("{x:e}") } else { plain }
}

/// " m" for a unit, nothing for none.
fn with_unit(unit: &str) -> String {
    if unit.is_empty() { String::new() } else { format!(" {unit}") }
}

#[derive(Default)]
struct Validator {
    path: Vec<String>,
    first: Option<(String, String)>,
}

impl Validator {
    fn at(&self, field: &str) -> String {
        let mut s = String::new();
        for p in &self.path {
            if p.starts_with('[') || s.is_empty() {
                s.push_str(p);
            } else {
                s.push('.');
                s.push_str(p);
            }
        }
        if field.is_empty() {
            return if s.is_empty() { ".".into() } else { s };
        }
        if field.starts_with('[') || s.is_empty() {
            format!("{s}{field}")
        } else {
            format!("{s}.{field}")
        }
    }
    fn fail(&mut self, field: &str, msg: impl Into<String>) {
        if self.first.is_none() {
            self.first = Some((self.at(field), msg.into()));
        }
    }
    fn push(&mut self, p: impl Into<String>) {
        self.path.push(p.into());
    }
    fn pop(&mut self) {
        self.path.pop();
    }
    fn finite(&mut self, field: &str, x: f64) -> bool {
        if !x.is_finite() {
            self.fail(field, format!("must be a finite number, got {x}"));
            return false;
        }
        true
    }
    fn range(&mut self, field: &str, x: f64, lo: f64, hi: f64, unit: &str) {
        if self.finite(field, x) && !(x >= lo && x <= hi) {
            let (x, lo, hi) = (number(x), number(lo), number(hi));
            self.fail(field, format!("{x}{} is outside the allowed range {lo}..={hi}", with_unit(unit)));
        }
    }
    fn positive(&mut self, field: &str, x: f64, unit: &str) {
        if self.finite(field, x) && x <= 0.0 {
            self.fail(field, format!("must be > 0{}, got {}", with_unit(unit), number(x)));
        }
    }
    fn non_negative(&mut self, field: &str, x: f64, unit: &str) {
        if self.finite(field, x) && x < 0.0 {
            self.fail(field, format!("must be ≥ 0{}, got {}", with_unit(unit), number(x)));
        }
    }
    /// A light's `color × field` (each valid on its own) must not overflow f64.
    fn colour_times(&mut self, field: &str, color: [f64; 3], x: f64) {
        if x.is_finite() && color.iter().all(|c| c.is_finite()) && color.iter().any(|c| !(c * x).is_finite()) {
            self.fail(
                field,
                format!(
                    "color × {field} overflows f64 ({} × {}): scale them down",
                    number(color.iter().copied().fold(0.0, f64::max)),
                    number(x)
                ),
            );
        }
    }
    fn vec3(&mut self, field: &str, v: [f64; 3]) -> bool {
        for (i, x) in v.iter().enumerate() {
            if !self.finite(&format!("{field}[{i}]"), *x) {
                return false;
            }
        }
        true
    }
    fn direction(&mut self, field: &str, v: [f64; 3]) {
        if self.vec3(field, v) {
            // Scale first so that [1e200, 1e200, 0] does not overflow to ∞.
            let m = v.iter().fold(0.0f64, |a, x| a.max(x.abs()));
            let l = if m > 0.0 { m * (DVec3::from(v) / m).length() } else { 0.0 };
            if m == 0.0 || l.is_nan() || l <= 1e-300 {
                self.fail(field, "zero-length direction: give a non-zero vector");
            }
        }
    }
    fn color(&mut self, field: &str, c: [f64; 3]) {
        for (i, x) in c.iter().enumerate() {
            self.non_negative(&format!("{field}[{i}]"), *x, "");
        }
    }
    fn resolution(&mut self, r: [u32; 2]) {
        for (i, x) in r.iter().enumerate() {
            if *x == 0 || *x > 65536 {
                self.fail(&format!("resolution[{i}]"), format!("{x} pixels is outside 1..=65536"));
            }
        }
    }
    fn coefficient(&mut self, field: &str, c: &Coefficient) {
        match c {
            Coefficient::Grey(x) => self.non_negative(field, *x, "m⁻¹"),
            Coefficient::Rgb(v) => {
                for (i, x) in v.iter().enumerate() {
                    self.non_negative(&format!("{field}[{i}]"), *x, "m⁻¹");
                }
            }
            Coefficient::Spectral(SpectralCoefficient::SpectrumNm(samples)) => {
                if samples.is_empty() {
                    self.fail(&format!("{field}.spectrum_nm"), "needs at least one [nm, value] sample");
                }
                let mut last = f64::NEG_INFINITY;
                for (i, [l, x]) in samples.iter().enumerate() {
                    let f = format!("{field}.spectrum_nm[{i}]");
                    if self.finite(&format!("{f}[0]"), *l) && (*l <= last || *l <= 0.0) {
                        self.fail(
                            &format!("{f}[0]"),
                            format!("wavelengths must be > 0 nm and strictly increasing, got {l} after {last}"),
                        );
                    }
                    last = *l;
                    self.non_negative(&format!("{f}[1]"), *x, "m⁻¹");
                }
            }
            Coefficient::Spectral(SpectralCoefficient::PowerLaw { at_550nm, exponent }) => {
                self.non_negative(&format!("{field}.power_law.at_550nm"), *at_550nm, "m⁻¹");
                self.range(&format!("{field}.power_law.exponent"), *exponent, -20.0, 20.0, "");
            }
        }
    }
    fn phase(&mut self, field: &str, p: &PhaseFunction) {
        if let Err(m) = p.validate() {
            self.fail(&format!("{field}.g"), m);
        }
    }
    fn layer_side(&mut self, field: &str, s: &LayerSide) {
        self.coefficient(&format!("{field}.scattering"), &s.scattering);
        self.coefficient(&format!("{field}.absorption"), &s.absorption);
        self.phase(&format!("{field}.phase"), &s.phase);
    }
    fn ies(&mut self, field: &str, r: Option<&IesProfileRef>) {
        if let Some(r) = r {
            if r.file.trim().is_empty() {
                self.fail(&format!("{field}.file"), "empty path: give the .ies file");
            }
            self.non_negative(&format!("{field}.strength"), r.strength, "");
        }
    }
    fn beam(&mut self, spread: f64, q: f64) {
        self.range("beam_spread_deg", spread, 0.01, 180.0, "degrees");
        self.range("sharpness", q, 0.0, 1.0, "");
    }
    fn distribution(&mut self, d: &IntensityDistribution) {
        match d {
            IntensityDistribution::Isotropic(_) => {}
            IntensityDistribution::NishitaSpot(n) => self.beam(n.beam_spread_deg, n.sharpness),
            IntensityDistribution::UsdShaping(u) => {
                self.range("cone_angle_deg", u.cone_angle_deg, 0.01, 180.0, "degrees");
                self.range("cone_softness", u.cone_softness, 0.0, 1.0, "");
                self.range("focus", u.focus, 0.0, 1e6, "");
            }
            IntensityDistribution::Daisy(d) => {
                self.beam(d.beam_spread_deg, d.sharpness);
                self.range("period_phi_deg", d.period_phi_deg, 0.1, 360.0, "degrees");
                self.range("min_ratio", d.min_ratio, -10.0, 1.0, "");
            }
            IntensityDistribution::PolkaDot(d) => {
                self.beam(d.beam_spread_deg, d.sharpness);
                self.range("period_phi_deg", d.period_phi_deg, 0.1, 360.0, "degrees");
                self.range("period_theta_deg", d.period_theta_deg, 0.1, 180.0, "degrees");
                self.range("min_ratio", d.min_ratio, -10.0, 1.0, "");
            }
            IntensityDistribution::Tabulated(t) => {
                if t.theta_deg.is_empty() {
                    self.fail("theta_deg", "needs at least one θ sample");
                }
                if t.phi_deg.is_empty() {
                    self.fail("phi_deg", "needs at least one φ sample");
                }
                self.increasing("theta_deg", &t.theta_deg, 0.0, 180.0);
                self.increasing("phi_deg", &t.phi_deg, 0.0, 360.0);
                if !t.phi_deg.is_empty() && t.phi_deg.last().is_some_and(|l| *l - t.phi_deg[0] >= 360.0) {
                    self.fail("phi_deg", "φ samples must span less than 360° (the table is periodic)");
                }
                if t.values.len() != t.phi_deg.len() {
                    self.fail(
                        "values",
                        format!("has {} rows, expected one per φ sample ({})", t.values.len(), t.phi_deg.len()),
                    );
                }
                for (i, row) in t.values.iter().enumerate() {
                    if row.len() != t.theta_deg.len() {
                        self.fail(
                            &format!("values[{i}]"),
                            format!("has {} values, expected one per θ sample ({})", row.len(), t.theta_deg.len()),
                        );
                    }
                    for (j, x) in row.iter().enumerate() {
                        self.non_negative(&format!("values[{i}][{j}]"), *x, "");
                    }
                }
            }
        }
    }
    fn increasing(&mut self, field: &str, xs: &[f64], lo: f64, hi: f64) {
        let mut last = f64::NEG_INFINITY;
        for (i, x) in xs.iter().enumerate() {
            let f = format!("{field}[{i}]");
            self.range(&f, *x, lo, hi, "degrees");
            if x.is_finite() && *x <= last {
                self.fail(&f, format!("must be strictly increasing, got {x} after {last}"));
            }
            last = *x;
        }
    }
    fn window_aperture(&mut self, w: &WindowLight) {
        if w.aperture.len() < 3 {
            self.fail("aperture", format!("needs at least 3 corners, got {}", w.aperture.len()));
            return;
        }
        for (i, c) in w.aperture.iter().enumerate() {
            if !self.vec3(&format!("aperture[{i}]"), *c) {
                return;
            }
            if c.iter().any(|x| x.abs() > MAX_MESH_COORDINATE_M) {
                // (As for mesh vertices: the aperture's edges cut view rays and shadows.)
                self.fail(
                    &format!("aperture[{i}]"),
                    format!("corner beyond ±{MAX_MESH_COORDINATE_M:e} m, the range of mesh vertices"),
                );
                return;
            }
        }
        let pts: Vec<DVec3> = w.aperture.iter().map(|c| DVec3::from(*c)).collect();
        // Newell's normal: robust for any simple polygon.
        let mut n = DVec3::ZERO;
        for i in 0..pts.len() {
            let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
            n += DVec3::new((a.y - b.y) * (a.z + b.z), (a.z - b.z) * (a.x + b.x), (a.x - b.x) * (a.y + b.y));
        }
        let size = pts.iter().map(|p| (*p - pts[0]).length()).fold(0.0, f64::max);
        if n.length() <= 1e-12 * size * size || size == 0.0 {
            self.fail("aperture", "the corners enclose no area");
            return;
        }
        let n = n.normalize();
        for (i, p) in pts.iter().enumerate() {
            let off = (*p - pts[0]).dot(n).abs();
            if off > 1e-6 * size {
                self.fail(
                    &format!("aperture[{i}]"),
                    format!("corner is {off:.3e} m off the window's plane: the polygon must be planar"),
                );
                return;
            }
        }
        let to_light = DVec3::from(w.direction_to_light);
        if to_light.length() > 0.0 && n.dot(to_light.normalize()).abs() < 1e-9 {
            self.fail("direction_to_light", "is parallel to the window's plane: no light passes");
        }
    }
    fn orientation(&mut self, position: [f64; 3], o: &Orientation) {
        self.push("orientation");
        match o {
            Orientation::LookAt { target, up } => {
                if self.vec3("look_at.target", *target) && self.vec3("look_at.up", *up) {
                    let fwd = DVec3::from(*target) - DVec3::from(position);
                    let upv = DVec3::from(*up);
                    if !fwd.length().is_finite() {
                        self.fail(
                            "look_at.target",
                            "the view direction target − position is too long for f64 (its length overflows): bring the camera and target within ±1e150 m",
                        );
                    } else if !upv.length().is_finite() {
                        self.fail("look_at.up", "the up vector's length overflows f64: give a unit vector");
                    } else if fwd.length() < 1e-12 {
                        self.fail("look_at.target", "target coincides with the position: zero-length direction");
                    } else if upv.length() < 1e-300 {
                        self.fail("look_at.up", "zero-length direction: give a non-zero vector");
                    } else if fwd.normalize().cross(upv.normalize()).length() < 1e-9 {
                        self.fail("look_at.up", "up is parallel to the view direction");
                    }
                }
            }
            Orientation::QuaternionWxyz(q) => self.quaternion("quaternion_wxyz", *q),
        }
        self.pop();
    }
    fn quaternion(&mut self, field: &str, q: [f64; 4]) {
        for (i, x) in q.iter().enumerate() {
            if !self.finite(&format!("{field}[{i}]"), *x) {
                return;
            }
        }
        let n = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if n.is_infinite() {
            self.fail(field, "the quaternion's norm overflows f64: give a unit quaternion");
        } else if n.is_nan() || n <= 1e-12 {
            self.fail(field, "zero-length quaternion");
        }
    }

    fn check(&mut self, s: &Scene) {
        if s.version != SCENE_VERSION {
            self.fail(
                "version",
                format!("unsupported version {}; this build reads version {SCENE_VERSION}", s.version),
            );
        }
        self.push("camera");
        match &s.camera {
            Camera::Perspective(c) => {
                self.vec3("position", c.position);
                self.orientation(c.position, &c.orientation);
                self.positive("focal_length_mm", c.focal_length_mm, "mm");
                self.positive("sensor_width_mm", c.sensor_width_mm, "mm");
                self.positive("sensor_height_mm", c.sensor_height_mm, "mm");
                self.range("shift_x", c.shift_x, -100.0, 100.0, "");
                self.range("shift_y", c.shift_y, -100.0, 100.0, "");
                self.resolution(c.resolution);
                self.non_negative("clip_start_m", c.clip_start_m, "m");
                if let Some(e) = c.clip_end_m {
                    if !e.is_nan() && e <= c.clip_start_m {
                        self.fail("clip_end_m", format!("must be > clip_start_m ({}), got {e}", c.clip_start_m));
                    } else if e.is_nan() {
                        self.fail("clip_end_m", "must be a number > clip_start_m");
                    }
                }
            }
            Camera::Equirectangular(c) => {
                self.vec3("position", c.position);
                self.resolution(c.resolution);
                if let Some(e) = c.clip_end_m
                    && (e.is_nan() || e <= 0.0)
                {
                    self.fail("clip_end_m", format!("must be > 0 m, got {e}"));
                }
            }
        }
        self.pop();
        for (i, m) in s.meshes.iter().enumerate() {
            self.push(format!("meshes[{i}]"));
            for (j, p) in m.positions.iter().enumerate() {
                if !self.vec3(&format!("positions[{j}]"), *p) {
                    break;
                }
            }
            let n = m.positions.len() as u64;
            for (j, t) in m.triangles.iter().enumerate() {
                for (k, ix) in t.iter().enumerate() {
                    if *ix as u64 >= n {
                        self.fail(
                            &format!("triangles[{j}][{k}]"),
                            format!("vertex index {ix} out of range: the mesh has {n} positions"),
                        );
                    }
                }
            }
            self.transform(&m.transform);
            if self.first.is_none() {
                let mat = m.transform.to_matrix();
                let far = m.positions.iter().enumerate().find_map(|(j, p)| {
                    let w = mat.transform_point3(DVec3::from(*p));
                    (w.is_nan() || w.abs().max_element() > MAX_MESH_COORDINATE_M).then_some((j, w))
                });
                if let Some((j, w)) = far {
                    self.fail(
                        &format!("positions[{j}]"),
                        format!(
                            "in world space ({:e}, {:e}, {:e}) m, beyond ±{MAX_MESH_COORDINATE_M:e} m: a ray's hit on a triangle loses \
                             about 1e-16 × its vertices' distance from the ray's origin, so farther vertices would give wrong \
                             depths and shadows; keep meshes within ±{MAX_MESH_COORDINATE_M:e} m (a ground plane 10 000 km across is plenty)",
                            w.x, w.y, w.z
                        ),
                    );
                }
            }
            self.pop();
        }
        for (i, l) in s.lights.iter().enumerate() {
            self.push(format!("lights[{i}]"));
            if let Light::Point(PointLight { name, .. }) | Light::Spot(SpotLight { name, .. }) | Light::Window(WindowLight { name, .. }) = l
                && name.len() > MAX_STAGE_LIGHT_NAME_BYTES
            {
                self.fail(
                    "name",
                    format!(
                        "{} bytes long; at most {MAX_STAGE_LIGHT_NAME_BYTES}, so that `surface_transmittance.<name>.R` fits OpenEXR's 255-byte channel names",
                        name.len()
                    ),
                );
            }
            match l {
                Light::Sun(SunLight {
                    direction_to_sun,
                    color,
                    strength_w_m2,
                    angular_diameter_deg,
                    ..
                }) => {
                    self.direction("direction_to_sun", *direction_to_sun);
                    self.color("color", *color);
                    self.non_negative("strength_w_m2", *strength_w_m2, "W·m⁻²");
                    self.colour_times("strength_w_m2", *color, *strength_w_m2);
                    self.range("angular_diameter_deg", *angular_diameter_deg, 0.0, 180.0, "degrees");
                }
                Light::Ambient(AmbientLight { color, radiance, .. }) => {
                    self.color("color", *color);
                    self.non_negative("radiance", *radiance, "W·m⁻²·sr⁻¹");
                    self.colour_times("radiance", *color, *radiance);
                }
                Light::Point(p) => {
                    self.vec3("position", p.position);
                    self.orientation(p.position, &p.orientation);
                    self.color("color", p.color);
                    self.non_negative("power_w", p.power_w, "W");
                    self.colour_times("power_w", p.color, p.power_w);
                    self.non_negative("radius_m", p.radius_m, "m");
                    self.push("distribution");
                    self.distribution(&p.distribution);
                    self.pop();
                    self.ies("ies", p.ies.as_ref());
                }
                Light::Spot(p) => {
                    self.vec3("position", p.position);
                    self.orientation(p.position, &p.orientation);
                    self.color("color", p.color);
                    self.non_negative("power_w", p.power_w, "W");
                    self.colour_times("power_w", p.color, p.power_w);
                    self.non_negative("radius_m", p.radius_m, "m");
                    self.range("spot_size_deg", p.spot_size_deg, 0.1, 180.0, "degrees");
                    self.range("spot_blend", p.spot_blend, 0.0, 1.0, "");
                    self.ies("ies", p.ies.as_ref());
                }
                Light::Window(w) => {
                    self.direction("direction_to_light", w.direction_to_light);
                    self.color("color", w.color);
                    self.non_negative("irradiance_w_m2", w.irradiance_w_m2, "W·m⁻²");
                    self.colour_times("irradiance_w_m2", w.color, w.irradiance_w_m2);
                    self.window_aperture(w);
                }
            }
            self.pop();
        }
        for (i, m) in s.media.iter().enumerate() {
            self.push(format!("media[{i}]"));
            match m {
                Medium::Homogeneous(HomogeneousMedium {
                    scattering,
                    absorption,
                    phase,
                    bounds,
                    ..
                }) => {
                    self.coefficient("scattering", scattering);
                    self.coefficient("absorption", absorption);
                    self.phase("phase", phase);
                    if let Bounds::Box {
                        rotation_wxyz: Some(q), ..
                    } = bounds
                    {
                        self.quaternion("bounds.box.rotation_wxyz", *q);
                    }
                    if let Bounds::Box { min, max, .. } = bounds
                        && self.vec3("bounds.box.min", *min)
                        && self.vec3("bounds.box.max", *max)
                    {
                        for k in 0..3 {
                            if max[k] <= min[k] {
                                self.fail(
                                    &format!("bounds.box.max[{k}]"),
                                    format!("must be > min[{k}] = {}, got {}", min[k], max[k]),
                                );
                            }
                        }
                    }
                }
                Medium::HeightFog(HeightFogMedium {
                    scale_height_m,
                    reference_height_m,
                    rayleigh,
                    mie,
                    ..
                }) => {
                    self.range("scale_height_m", *scale_height_m, 1e-3, 1e7, "m");
                    self.range("reference_height_m", *reference_height_m, -1e7, 1e7, "m");
                    if let Some(r) = rayleigh {
                        self.coefficient("rayleigh.scattering", &r.scattering);
                        self.coefficient("rayleigh.absorption", &r.absorption);
                    }
                    if let Some(m) = mie {
                        self.coefficient("mie.scattering", &m.scattering);
                        self.coefficient("mie.absorption", &m.absorption);
                        self.phase("mie.phase", &m.phase);
                    }
                }
                Medium::FogLayer(FogLayerMedium {
                    ground_height_m,
                    top_height_m,
                    extinction,
                    single_scattering_albedo,
                    air_extinction,
                    phase,
                    min_sun_elevation_deg,
                    ..
                }) => {
                    self.range("ground_height_m", *ground_height_m, -1e7, 1e7, "m");
                    if self.finite("top_height_m", *top_height_m) && top_height_m <= ground_height_m {
                        self.fail(
                            "top_height_m",
                            format!("must be > ground_height_m ({ground_height_m}), got {top_height_m}"),
                        );
                    }
                    self.coefficient("extinction", extinction);
                    self.range("single_scattering_albedo", *single_scattering_albedo, 0.0, 1.0, "");
                    self.coefficient("air_extinction", air_extinction);
                    self.phase("phase", phase);
                    self.range("min_sun_elevation_deg", *min_sun_elevation_deg, 0.0, 90.0, "degrees");
                }
                Medium::LayeredHeightField(LayeredHeightFieldMedium {
                    base_height_m,
                    waves,
                    lower,
                    upper,
                    ..
                }) => {
                    self.range("base_height_m", *base_height_m, -1e7, 1e7, "m");
                    if waves.is_empty() || waves.len() > 8 {
                        self.fail("waves", format!("needs 1..=8 sine waves, got {}", waves.len()));
                    }
                    for (k, w) in waves.iter().enumerate() {
                        self.range(&format!("waves[{k}].amplitude_m"), w.amplitude_m, 0.0, 1e4, "m");
                        self.range(&format!("waves[{k}].wavelength_m"), w.wavelength_m, 1e-3, 1e7, "m");
                        self.range(&format!("waves[{k}].direction_deg"), w.direction_deg, -360.0, 360.0, "degrees");
                        self.range(&format!("waves[{k}].phase_deg"), w.phase_deg, -360.0, 360.0, "degrees");
                    }
                    self.layer_side("lower", lower);
                    if let Some(u) = upper {
                        self.layer_side("upper", u);
                    }
                }
                Medium::Ellipsoid(EllipsoidMedium {
                    center,
                    radii,
                    rotation_wxyz,
                    scattering,
                    absorption,
                    phase,
                    ..
                }) => {
                    self.vec3("center", *center);
                    for (k, r) in radii.iter().enumerate() {
                        self.range(&format!("radii[{k}]"), *r, 1e-6, 1e7, "m");
                    }
                    if let Some(q) = rotation_wxyz {
                        self.quaternion("rotation_wxyz", *q);
                    }
                    self.coefficient("scattering", scattering);
                    self.coefficient("absorption", absorption);
                    self.phase("phase", phase);
                }
            }
            self.pop();
        }
        self.push("output");
        self.range("tolerance", s.output.tolerance, 1e-12, 0.5, "");
        if s.output.layers.is_empty() {
            self.fail(
                "layers",
                "at least one layer is needed (inscatter, transmittance, depth, sun_transmittance, error)",
            );
        }
        for (i, l) in s.output.layers.iter().enumerate() {
            if s.output.layers[..i].contains(l) {
                self.fail(&format!("layers[{i}]"), format!("layer {l} is listed twice"));
            }
        }
        if let PixelFilter::BlackmanHarris { width_px } = s.output.pixel_filter {
            self.range("pixel_filter.width_px", width_px, 0.01, 10.0, "px");
        }
        if s.output.threads > 4096 {
            self.fail("threads", format!("{} threads is more than 4096", s.output.threads));
        }
        self.pop();
    }

    fn transform(&mut self, t: &Transform) {
        self.push("transform");
        if let Some(m) = t.matrix {
            if t.translation.is_some() || t.rotation_wxyz.is_some() || t.scale.is_some() {
                self.fail("matrix", "give either matrix or translation/rotation_wxyz/scale, not both");
            }
            for (r, row) in m.iter().enumerate() {
                for (c, x) in row.iter().enumerate() {
                    self.finite(&format!("matrix[{r}][{c}]"), *x);
                }
            }
            if m[3] != [0.0, 0.0, 0.0, 1.0] {
                self.fail("matrix[3]", "the last row of an affine transform must be [0, 0, 0, 1]");
            }
            let m3 = DMat3::from_cols_array_2d(&[
                [m[0][0], m[1][0], m[2][0]],
                [m[0][1], m[1][1], m[2][1]],
                [m[0][2], m[1][2], m[2][2]],
            ]);
            if m3.determinant().abs() < 1e-300 {
                self.fail("matrix", "singular matrix (zero scale)");
            }
        }
        if let Some(v) = t.translation {
            self.vec3("translation", v);
        }
        if let Some(q) = t.rotation_wxyz {
            self.quaternion("rotation_wxyz", q);
        }
        if let Some(s) = t.scale
            && self.vec3("scale", s)
            && s.contains(&0.0)
        {
            self.fail("scale", "scale components must be non-zero");
        }
        self.pop();
    }
}

// ---------------------------------------------------------------- helpers for the renderer

impl Transform {
    /// The object → world matrix.
    pub fn to_matrix(&self) -> DMat4 {
        if let Some(m) = self.matrix {
            // Row-major in JSON, column-major in glam.
            return DMat4::from_cols_array_2d(&m).transpose();
        }
        let t = DVec3::from(self.translation.unwrap_or([0.0; 3]));
        let r = self.rotation_wxyz.map(quat_wxyz).unwrap_or(DQuat::IDENTITY);
        let s = DVec3::from(self.scale.unwrap_or([1.0; 3]));
        DMat4::from_scale_rotation_translation(s, r, t)
    }
}

/// `[w, x, y, z]` → normalised quaternion.
pub fn quat_wxyz(q: [f64; 4]) -> DQuat {
    DQuat::from_xyzw(q[1], q[2], q[3], q[0]).normalize()
}

impl Coefficient {
    /// Value at wavelength `lambda_nm`, m⁻¹; RGB coefficients have no spectrum
    /// and return `None`.
    pub fn at_wavelength(&self, lambda_nm: f64) -> Option<f64> {
        match self {
            Coefficient::Grey(x) => Some(*x),
            Coefficient::Rgb(_) => None,
            Coefficient::Spectral(SpectralCoefficient::PowerLaw { at_550nm, exponent }) => {
                Some(at_550nm * (550.0 / lambda_nm).powf(*exponent))
            }
            Coefficient::Spectral(SpectralCoefficient::SpectrumNm(s)) => {
                let first = s.first()?;
                let last = s.last()?;
                if lambda_nm <= first[0] {
                    return Some(first[1]);
                }
                if lambda_nm >= last[0] {
                    return Some(last[1]);
                }
                let i = s.partition_point(|p| p[0] <= lambda_nm);
                let (a, b) = (s[i - 1], s[i]);
                let t = (lambda_nm - a[0]) / (b[0] - a[0]);
                Some(a[1] + t * (b[1] - a[1]))
            }
        }
    }

    /// Whether the value depends on wavelength (grey and equal-RGB do not).
    pub fn is_wavelength_dependent(&self) -> bool {
        match self {
            Coefficient::Grey(_) => false,
            Coefficient::Rgb(v) => !(v[0] == v[1] && v[1] == v[2]),
            Coefficient::Spectral(_) => match self.sampled() {
                Some(s) => !spectrum::is_grey(&s, 1e-12),
                None => true,
            },
        }
    }

    /// Whether the coefficient is given spectrally (needs the spectral path to be exact).
    pub fn is_spectral(&self) -> bool {
        matches!(self, Coefficient::Spectral(_)) && self.is_wavelength_dependent()
    }

    /// Sampled on the spectral grid; `None` for RGB coefficients.
    pub fn sampled(&self) -> Option<Spectrum> {
        let wl = spectrum::wavelengths_nm();
        let mut out = [0.0; SPECTRAL_SAMPLES];
        for (o, l) in out.iter_mut().zip(wl.iter()) {
            *o = self.at_wavelength(*l)?;
        }
        Some(out)
    }

    /// Per Rec.709 channel. Spectral coefficients are reduced with the
    /// non-negative channel weights of [`spectrum::channel_weights`] (an
    /// approximation, reported when used).
    pub fn rgb(&self) -> [f64; 3] {
        match self {
            Coefficient::Grey(x) => [*x; 3],
            Coefficient::Rgb(v) => *v,
            Coefficient::Spectral(_) => {
                let s = self.sampled().unwrap_or([0.0; SPECTRAL_SAMPLES]);
                let w = spectrum::channel_weights();
                let mut out = [0.0; 3];
                for c in 0..3 {
                    out[c] = s.iter().zip(w[c].iter()).map(|(a, b)| a * b).sum();
                }
                out
            }
        }
    }

    /// Per spectral sample. RGB coefficients are upsampled with the linear
    /// [`spectrum::rec709_to_spectrum`] and clamped at 0 (reported when used).
    pub fn spectral(&self) -> Spectrum {
        match self.sampled() {
            Some(s) => s,
            None => {
                let mut s = spectrum::rec709_to_spectrum(self.rgb());
                for x in s.iter_mut() {
                    *x = x.max(0.0);
                }
                s
            }
        }
    }
}

impl fmt::Display for LayerKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let s = match self {
            LayerKind::Inscatter => "inscatter",
            LayerKind::Transmittance => "transmittance",
            LayerKind::Depth => "depth",
            LayerKind::SunTransmittance => "sun_transmittance",
            LayerKind::Error => "error",
            LayerKind::InscatterPerLight => "inscatter_per_light",
            LayerKind::SurfaceTransmittancePerLight => "surface_transmittance_per_light",
        };
        f.write_str(s)
    }
}

/// JSON Schema of the scene format (draft 2020-12), generated from these types.
pub fn json_schema() -> String {
    let schema = schemars::schema_for!(Scene);
    serde_json::to_string_pretty(&schema).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn committed_schema_matches_the_types() {
        let committed = include_str!("../../docs/scene.schema.json");
        assert_eq!(
            committed.trim(),
            json_schema().trim(),
            "docs/scene.schema.json is stale: regenerate it with `tyndall schema > docs/scene.schema.json`"
        );
    }

    #[test]
    fn every_example_scene_loads() {
        for (name, text) in [
            ("valley_height_fog", include_str!("../../examples/valley_height_fog.json")),
            ("fog_layer_sunrise", include_str!("../../examples/fog_layer_sunrise.json")),
            ("dry_ice_stage", include_str!("../../examples/dry_ice_stage.json")),
        ] {
            Scene::from_json_str(text, name).unwrap_or_else(|e| panic!("{e}"));
        }
    }

    #[test]
    fn mesh_arrays_apart_from_the_text_load_as_the_text_would() {
        let scene = |meshes: &str| {
            format!(
                r#"{{"version": 1, "camera": {{"type": "perspective", "position": [0, -5, 1], "orientation": {{"look_at": {{"target": [0, 0, 1]}}}}, "resolution": [8, 4]}},
                "meshes": {meshes}, "lights": [{{"type": "point", "position": [0, 0, 3], "power_w": 10}}],
                "media": [{{"type": "homogeneous", "scattering": 0.1}}]}}"#
            )
        };
        let positions = vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let text = scene(r#"[{"name": "tri", "positions": [[0, 0, 0], [1, 0, 0], [0, 1, 0]], "triangles": [[0, 1, 2]]}]"#);
        let whole = Scene::from_json_str(&text, "text").unwrap();
        let apart = scene(r#"[{"name": "tri", "positions": [], "triangles": []}]"#);
        let arrays = |t: [u32; 3]| vec![(0, positions.clone(), vec![t])];
        assert_eq!(
            Scene::from_json_str_with_meshes(&apart, "arrays", arrays([0, 1, 2])).unwrap(),
            whole
        );
        // The arrays are validated with the scene: the same field is named.
        let e = Scene::from_json_str_with_meshes(&apart, "arrays", arrays([0, 1, 3])).unwrap_err();
        assert_eq!(e.path, "meshes[0].triangles[0][2]", "{e}");
        // Arrays for a mesh that is not there, or given twice.
        let e = Scene::from_json_str_with_meshes(&apart, "arrays", vec![(1, positions.clone(), vec![[0, 1, 2]])]).unwrap_err();
        assert!(e.path == "meshes" && e.message.contains("meshes[1]"), "{e}");
        let e = Scene::from_json_str_with_meshes(&text, "arrays", arrays([0, 1, 2])).unwrap_err();
        assert!(e.path == "meshes[0]" && e.message.contains("both"), "{e}");
    }
}
