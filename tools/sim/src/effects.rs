//! Realism effects applied to each rendered frame, in physical order: clouds
//! (in the scene), haze and sky (atmosphere), motion blur (camera rotation
//! during the exposure), suspension cords (just in front of the lens),
//! vignetting (lens), photometric response and noise (sensor), then a clamp to
//! 0..255. Each effect is off unless its section is present in the scenario's
//! `realism`; `"haze": {}` switches haze on with its defaults. The sun
//! ([`Sun`]) is not applied here but by the renderer, through an illumination
//! grid on the terrain ([`crate::sun`]).
//!
//! Deterministic: randomness comes from [`Rng`] streams of the flight seed
//! (and the frame index where it must change between frames), so runs repeat.
//! Smooth per-pixel fields (ray angles, cloud cover, blur vectors, sky) are
//! evaluated on coarse grids and interpolated bilinearly, for speed.

use nalgebra::{Matrix3, UnitQuaternion, Vector3};
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::{intersect_ellipsoid, Ray, WGS84_A, WGS84_B};

use crate::rng::Rng;

/// Per-pixel geometry of one rendered frame (from the ray caster).
#[derive(Clone, Copy)]
pub struct FrameGeometry<'a> {
    pub camera: &'a CameraModel,
    /// True pose at the frame time.
    pub pose: &'a CameraPose,
    /// Ellipsoidal height of the camera (m).
    pub camera_height_m: f64,
    /// Distance camera -> terrain hit along each pixel's ray (m); NaN where the ray sees sky.
    pub range_m: &'a [f32],
    /// Ellipsoidal height of the terrain hit (m); NaN for sky.
    pub hit_height_m: &'a [f32],
}

/// Timing and motion of one frame.
#[derive(Clone, Copy, Debug)]
pub struct FrameContext {
    pub index: usize,
    pub t: f64,
    /// Angular rate of the camera relative to ECEF, camera frame (rad/s), for motion blur.
    pub w_cam_rad_s: Vector3<f64>,
    pub exposure_s: f64,
}

/// Which realism effects to apply, each with its parameters; `None` = off.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Realism {
    /// Re-lighting of the terrain, applied by the renderer.
    pub sun: Option<Sun>,
    /// The camera's spectral response: its own weights of the ortho's red,
    /// green and blue bands (applied when the scene is loaded, see
    /// [`Spectral`]).
    pub spectral: Option<Spectral>,
    /// A slow multiplicative brightness field fixed on the ground (season,
    /// soil moisture, thin haze), applied before the atmosphere.
    pub brightness_field: Option<BrightnessField>,
    pub photometric: Option<Photometric>,
    pub haze: Option<Haze>,
    pub noise: Option<SensorNoise>,
    pub vignetting: Option<Vignetting>,
    pub motion_blur: Option<MotionBlur>,
    pub clouds: Option<Clouds>,
    pub cords: Option<Cords>,
}

/// A sun other than the one of the ortho's acquisition: Lambertian shading
/// from the DEM normal and cast shadows from the terrain, multiplied on top
/// of the ortho, which stays the albedo with its own baked-in lighting. The
/// factor on a terrain point is `(ambient + (1 - ambient) max(0, n.s) lit) /
/// (ambient + (1 - ambient) sin(elevation))` (`n` the terrain normal, `s`
/// the direction to the sun, `lit` 0 in cast shadow with an edge softened
/// over about one DEM cell), so flat, unshadowed ground keeps its ortho
/// brightness, slopes facing the sun brighten and shadows darken to
/// `ambient / (ambient + (1 - ambient) sin(elevation))`. The sun has the same
/// azimuth and elevation over the whole scene.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Sun {
    /// Direction of the sun, clockwise from north (deg, in [-360, 360]).
    pub azimuth_deg: f64,
    /// Height of the sun above the local horizon (deg, in (0, 90]).
    pub elevation_deg: f64,
    /// Share of the light that is diffuse (sky light), the only light in
    /// shadows and on slopes facing away from the sun (in [0, 1]).
    pub ambient: f64,
}

impl Default for Sun {
    fn default() -> Self {
        Self { azimuth_deg: 135.0, elevation_deg: 35.0, ambient: 0.25 }
    }
}

/// The camera's spectral response differs from the database's luminance
/// (Rec. 601 luma of the ortho's red, green, blue): the camera sees
/// `weights[0] red + weights[1] green + weights[2] blue`, the weights scaled
/// to sum to 1 (e.g. `[0.1, 0.3, 0.6]` for a blue-heavy sensor, `[0.6, 0.3,
/// 0.1]` for a red-heavy one). Needs an ortho whose luminance comes from
/// three bands.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Spectral {
    pub weights: [f64; 3],
}

impl Default for Spectral {
    fn default() -> Self {
        Self { weights: [0.6, 0.3, 0.1] }
    }
}

impl Spectral {
    /// The weights scaled to sum to 1.
    pub fn normalized(&self) -> [f32; 3] {
        let s: f64 = self.weights.iter().sum();
        self.weights.map(|w| (w / s) as f32)
    }
}

/// A slow brightness field on the ground: each terrain pixel is multiplied by
/// `1 + amplitude (2 n - 1)`, `n` in [0, 1] being smooth value noise of the
/// ground point's ECEF position over cells of `scale_m` (fixed on the ground,
/// so consistent between frames; seeded).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct BrightnessField {
    pub amplitude: f64,
    pub scale_m: f64,
}

impl Default for BrightnessField {
    fn default() -> Self {
        Self { amplitude: 0.15, scale_m: 5000.0 }
    }
}

impl BrightnessField {
    /// The factor at a ground point.
    pub fn factor(&self, p_ecef: &Vector3<f64>, seed: u64) -> f64 {
        let n = value_noise3(seed ^ 0x5EA5_0B12_647E_F1E1, &(p_ecef / self.scale_m));
        1.0 + self.amplitude * (2.0 * n - 1.0)
    }
}

/// Sensor response different from the ortho's:
/// `out = 255 S(((gain in + offset) / 255)^gamma)`, where the tone curve `S`
/// is the identity for `contrast = 0` and a logistic S-curve of slope
/// `contrast` around mid-grey otherwise (rescaled to map 0 and 1 onto
/// themselves): a camera's film-like tone curve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Photometric {
    pub gain: f64,
    pub gamma: f64,
    pub offset_dn: f64,
    pub contrast: f64,
}

impl Default for Photometric {
    fn default() -> Self {
        Self { gain: 1.1, gamma: 0.9, offset_dn: 5.0, contrast: 0.0 }
    }
}

impl Photometric {
    /// The response to a grey level (before noise and clamping).
    pub fn response(&self, x: f64) -> f64 {
        let b = (self.gain * x + self.offset_dn).clamp(0.0, 255.0) / 255.0;
        255.0 * tone(b.powf(self.gamma), self.contrast)
    }
}

/// The logistic tone curve on [0, 1].
fn tone(x: f64, contrast: f64) -> f64 {
    if contrast == 0.0 {
        return x;
    }
    let sig = |t: f64| 1.0 / (1.0 + (-contrast * (t - 0.5)).exp());
    let (lo, hi) = (sig(0.0), sig(1.0));
    (sig(x) - lo) / (hi - lo)
}

/// Aerosol haze in an exponential atmosphere: terrain is attenuated along the
/// slant path and veiled by airlight; sky pixels get the airlight of their
/// (Chapman grazing-corrected) path out of the atmosphere.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Haze {
    /// Extinction coefficient at sea level (1/km).
    pub beta_sl_per_km: f64,
    pub scale_height_m: f64,
    /// Brightness of an infinitely thick haze (also the horizon sky).
    pub airlight_dn: f64,
}

impl Default for Haze {
    fn default() -> Self {
        Self { beta_sl_per_km: 0.05, scale_height_m: 8000.0, airlight_dn: 200.0 }
    }
}

/// Gaussian read noise plus signal-dependent shot noise, variance
/// `read_noise_dn^2 + shot_gain * signal_dn`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SensorNoise {
    pub read_noise_dn: f64,
    pub shot_gain: f64,
}

impl Default for SensorNoise {
    fn default() -> Self {
        Self { read_noise_dn: 2.0, shot_gain: 0.05 }
    }
}

/// Lens falloff `cos(theta)^(4 strength)`, theta the ray's angle to the
/// optical axis: strength 1 is the natural cos^4 law; 0.3 leaves the corners
/// of a 76 degree lens at ~0.67.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Vignetting {
    pub strength: f64,
}

impl Default for Vignetting {
    fn default() -> Self {
        Self { strength: 0.3 }
    }
}

/// Blur from the camera's rotation during the exposure (the exposure time
/// comes from the frame). Translation is negligible at flight ranges.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MotionBlur {
    /// Samples along the blur segment; more (one per 0.5 px) for long streaks.
    pub samples: u32,
    pub max_samples: u32,
}

impl Default for MotionBlur {
    fn default() -> Self {
        Self { samples: 5, max_samples: 16 }
    }
}

/// A thin cloud sheet at `height_m` above the ellipsoid, fixed to the Earth
/// (the same clouds in every frame) and drifting with the wind. It should lie
/// above the terrain: terrain that rises above it hides it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Clouds {
    pub height_m: f64,
    /// Share of the sheet's area that is cloud (opacity above half its maximum).
    pub coverage: f64,
    /// Size of the largest cloud features (m).
    pub scale_m: f64,
    /// Width of the soft cloud edges, in units of the [0, 1] noise field.
    pub edge_softness: f64,
    /// Opacity of a cloud's core.
    pub opacity: f64,
    pub brightness_dn: f64,
    pub wind_east_m_s: f64,
    pub wind_north_m_s: f64,
}

impl Default for Clouds {
    fn default() -> Self {
        Self {
            height_m: 3000.0,
            coverage: 0.25,
            scale_m: 2000.0,
            edge_softness: 0.05,
            opacity: 0.9,
            brightness_dn: 235.0,
            wind_east_m_s: 0.0,
            wind_north_m_s: 0.0,
        }
    }
}

/// The balloon's suspension cords hanging across the lens: dark out-of-focus
/// bands entering from the top edge, swaying like pendulums. Their base
/// positions and angles come from the seed and are fixed for the flight.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Cords {
    pub count: u32,
    pub darkness_dn: f64,
    /// Full width at half darkness (px).
    pub width_px: f64,
    /// Width of the soft edges, out of focus (px).
    pub edge_px: f64,
    /// Largest angle of a cord's rest position from the image vertical (deg).
    pub max_base_angle_deg: f64,
    pub sway_deg: f64,
    pub sway_period_s: f64,
}

impl Default for Cords {
    fn default() -> Self {
        Self {
            count: 2,
            darkness_dn: 20.0,
            width_px: 6.0,
            edge_px: 3.0,
            max_base_angle_deg: 15.0,
            sway_deg: 8.0,
            sway_period_s: 4.0,
        }
    }
}

impl Realism {
    /// Every effect off (the same as `Realism::default()`).
    pub fn none() -> Self {
        Self::default()
    }

    /// Every effect on with its defaults (for tests and benchmarks).
    pub fn all_on() -> Self {
        Self {
            sun: Some(Sun::default()),
            spectral: Some(Spectral::default()),
            brightness_field: Some(BrightnessField::default()),
            photometric: Some(Photometric::default()),
            haze: Some(Haze::default()),
            noise: Some(SensorNoise::default()),
            vignetting: Some(Vignetting::default()),
            motion_blur: Some(MotionBlur::default()),
            clouds: Some(Clouds::default()),
            cords: Some(Cords::default()),
        }
    }

    pub fn is_off(&self) -> bool {
        *self == Self::none()
    }

    /// Checks every field of the effects that are on; the error names the field.
    pub fn validate(&self) -> Result<(), String> {
        if let Some(s) = &self.sun {
            within("sun.azimuth_deg", s.azimuth_deg, -360.0, 360.0)?;
            if !(s.elevation_deg > 0.0 && s.elevation_deg <= 90.0) {
                return Err(format!(
                    "realism.sun.elevation_deg must be in (0, 90] (got {})",
                    s.elevation_deg
                ));
            }
            within("sun.ambient", s.ambient, 0.0, 1.0)?;
        }
        if let Some(sp) = &self.spectral {
            for (k, w) in sp.weights.iter().enumerate() {
                within(&format!("spectral.weights[{k}]"), *w, 0.0, 1e3)?;
            }
            positive("spectral.weights (sum)", sp.weights.iter().sum())?;
        }
        if let Some(b) = &self.brightness_field {
            within("brightness_field.amplitude", b.amplitude, 0.0, 0.9)?;
            within("brightness_field.scale_m", b.scale_m, 10.0, 1e7)?;
        }
        if let Some(p) = &self.photometric {
            positive("photometric.gain", p.gain)?;
            positive("photometric.gamma", p.gamma)?;
            within("photometric.offset_dn", p.offset_dn, -255.0, 255.0)?;
            within("photometric.contrast", p.contrast, 0.0, 50.0)?;
        }
        if let Some(h) = &self.haze {
            within("haze.beta_sl_per_km", h.beta_sl_per_km, 0.0, 10.0)?;
            within("haze.scale_height_m", h.scale_height_m, 100.0, 100_000.0)?;
            within("haze.airlight_dn", h.airlight_dn, 0.0, 255.0)?;
        }
        if let Some(n) = &self.noise {
            within("noise.read_noise_dn", n.read_noise_dn, 0.0, 100.0)?;
            within("noise.shot_gain", n.shot_gain, 0.0, 100.0)?;
        }
        if let Some(v) = &self.vignetting {
            within("vignetting.strength", v.strength, 0.0, 2.0)?;
        }
        if let Some(m) = &self.motion_blur {
            within("motion_blur.samples", m.samples as f64, 1.0, 64.0)?;
            within("motion_blur.max_samples", m.max_samples as f64, m.samples as f64, 64.0)?;
        }
        if let Some(c) = &self.clouds {
            within("clouds.height_m", c.height_m, -500.0, 20_000.0)?;
            within("clouds.coverage", c.coverage, 0.0, 1.0)?;
            within("clouds.scale_m", c.scale_m, 10.0, 1e6)?;
            within("clouds.edge_softness", c.edge_softness, 1e-3, 1.0)?;
            within("clouds.opacity", c.opacity, 0.0, 1.0)?;
            within("clouds.brightness_dn", c.brightness_dn, 0.0, 255.0)?;
            within("clouds.wind_east_m_s", c.wind_east_m_s, -200.0, 200.0)?;
            within("clouds.wind_north_m_s", c.wind_north_m_s, -200.0, 200.0)?;
        }
        if let Some(c) = &self.cords {
            within("cords.count", c.count as f64, 0.0, 16.0)?;
            within("cords.darkness_dn", c.darkness_dn, 0.0, 255.0)?;
            within("cords.width_px", c.width_px, 0.1, 1000.0)?;
            within("cords.edge_px", c.edge_px, 0.0, 1000.0)?;
            within("cords.max_base_angle_deg", c.max_base_angle_deg, 0.0, 60.0)?;
            within("cords.sway_deg", c.sway_deg, 0.0, 60.0)?;
            within("cords.sway_period_s", c.sway_period_s, 1e-3, 1e6)?;
        }
        Ok(())
    }
}

fn positive(name: &str, v: f64) -> Result<(), String> {
    if v > 0.0 && v.is_finite() {
        Ok(())
    } else {
        Err(format!("realism.{name} must be positive and finite (got {v})"))
    }
}

fn within(name: &str, v: f64, lo: f64, hi: f64) -> Result<(), String> {
    if (lo..=hi).contains(&v) {
        Ok(())
    } else {
        Err(format!("realism.{name} must be in [{lo}, {hi}] (got {v})"))
    }
}

/// Applies the effects that are on to one frame (`img`: row-major grey DN,
/// `width * height` of `geo.camera`), in physical order, then clamps to
/// 0..255. With every effect off the image is left untouched.
///
/// # Panics
/// When `img`, `geo.range_m` or `geo.hit_height_m` do not have one value per pixel.
pub fn apply(realism: &Realism, img: &mut [f32], geo: &FrameGeometry, frame: &FrameContext, seed: u64) {
    if realism.is_off() {
        return;
    }
    let (w, h) = (geo.camera.width as usize, geo.camera.height as usize);
    assert_eq!(img.len(), w * h, "image size");
    assert_eq!(geo.range_m.len(), w * h, "range_m size");
    assert_eq!(geo.hit_height_m.len(), w * h, "hit_height_m size");

    if let Some(b) = &realism.brightness_field {
        brightness_field(b, img, geo, seed);
    }
    if realism.haze.is_some() || realism.clouds.is_some() {
        atmosphere(realism.haze.as_ref(), realism.clouds.as_ref(), img, geo, frame.t, seed);
    }
    if let Some(mb) = &realism.motion_blur {
        motion_blur(mb, img, geo.camera, &frame.w_cam_rad_s, frame.exposure_s);
    }
    if let Some(c) = &realism.cords {
        cords(c, img, w, h, frame.t, seed);
    }
    sensor(realism, img, geo.camera, frame.index, seed);
}

// ---------------------------------------------------------------------------
// Coarse grids

/// A smooth per-pixel field with `ch` channels sampled on nodes every `step`
/// pixels (node (i, j) at pixel (i step, j step); the last nodes may lie just
/// outside the image), interpolated bilinearly.
struct CoarseGrid {
    step: usize,
    nx: usize,
    ny: usize,
    ch: usize,
    vals: Vec<f32>,
}

impl CoarseGrid {
    fn build(w: usize, h: usize, step: usize, ch: usize, f: impl Fn(Pixel, &mut [f32]) + Sync) -> Self {
        let nx = w.saturating_sub(1).div_ceil(step) + 1;
        let ny = h.saturating_sub(1).div_ceil(step) + 1;
        let mut vals = vec![0f32; nx * ny * ch];
        vals.par_chunks_mut(ch)
            .enumerate()
            .for_each(|(k, out)| f(Pixel::new(((k % nx) * step) as f64, ((k / nx) * step) as f64), out));
        Self { step, nx, ny, ch, vals }
    }

    fn node(&self, i: usize, j: usize) -> &[f32] {
        let k = (j * self.nx + i) * self.ch;
        &self.vals[k..k + self.ch]
    }

    /// Interpolated values of row `v`, `out.len() / CH` pixels wide (`CH` = channels).
    fn row<const CH: usize>(&self, v: usize, out: &mut [f32]) {
        assert_eq!(CH, self.ch);
        let step = self.step;
        let j0 = (v / step).min(self.ny - 1);
        let j1 = (j0 + 1).min(self.ny - 1);
        let ty = (v - j0 * step) as f32 / step as f32;
        let (r0, r1) = (&self.vals[j0 * self.nx * CH..], &self.vals[j1 * self.nx * CH..]);
        let col: Vec<f32> = (0..self.nx * CH).map(|k| r0[k] + (r1[k] - r0[k]) * ty).collect();
        let w = out.len() / CH;
        let inv = 1.0 / step as f32;
        for (i0, cell) in out.chunks_mut(step * CH).enumerate().take(w.div_ceil(step)) {
            let i1 = (i0 + 1).min(self.nx - 1);
            let a: [f32; CH] = std::array::from_fn(|c| col[i0 * CH + c]);
            let d: [f32; CH] = std::array::from_fn(|c| (col[i1 * CH + c] - a[c]) * inv);
            for (s, o) in cell.chunks_exact_mut(CH).enumerate() {
                for c in 0..CH {
                    o[c] = a[c] + d[c] * s as f32;
                }
            }
        }
    }

    fn max_norm(&self) -> f32 {
        self.vals.chunks(self.ch).map(|v| v.iter().map(|x| x * x).sum::<f32>().sqrt()).fold(0.0, f32::max)
    }
}

fn smoothstep(e0: f64, e1: f64, x: f64) -> f64 {
    let t = ((x - e0) / (e1 - e0)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

// ---------------------------------------------------------------------------
// Haze and sky

impl Haze {
    fn beta_per_m(&self) -> f64 {
        self.beta_sl_per_km * 1e-3
    }

    /// Optical depth of the straight path between heights `h1_m` and `h2_m`
    /// of length `range_m`: `beta H (e^(-lo/H) - e^(-hi/H)) / cos(zenith)`,
    /// written to stay exact for (nearly) horizontal paths.
    pub fn optical_depth(&self, h1_m: f64, h2_m: f64, range_m: f64) -> f64 {
        HazeFrom::new(self, h1_m).tau(h2_m, range_m)
    }

    /// Brightness of clear sky along a ray of elevation `sin_elev` (sine)
    /// from height `h_m`: the airlight of its path out of the atmosphere,
    /// with the Chapman grazing air mass (bright horizon and limb, dark
    /// zenith, darker with altitude).
    pub fn sky_dn(&self, h_m: f64, sin_elev: f64) -> f64 {
        let hs = self.scale_height_m;
        let r = WGS84_A + h_m.max(0.0);
        let inv_chapman = (2.0 * hs / (std::f64::consts::PI * r)).sqrt();
        let up = |h: f64, s: f64| self.beta_per_m() * hs * (-h / hs).exp() / (s + inv_chapman);
        let tau = if sin_elev >= 0.0 {
            up(h_m, sin_elev)
        } else {
            // Down to the tangent point and out again, less the part behind the camera.
            let h_t = (r * (1.0 - sin_elev * sin_elev).sqrt() - WGS84_A).max(0.0);
            2.0 * up(h_t, 0.0) - up(h_m, -sin_elev)
        };
        self.airlight_dn * (1.0 - (-tau).exp())
    }

    fn veil(&self, v: f32, tau: f32) -> f32 {
        let t = fast_exp(-tau);
        v * t + self.airlight_dn as f32 * (1.0 - t)
    }
}

/// Paths from one camera height, `e^(-h_cam/H)` computed once (one exp per pixel).
struct HazeFrom {
    beta: f64,
    hs: f64,
    h_cam: f64,
    e_cam: f64,
    /// The same in f32, for the per-pixel pass.
    px: [f32; 4],
}

impl HazeFrom {
    fn new(haze: &Haze, h_cam: f64) -> Self {
        let (beta, hs, e_cam) =
            (haze.beta_per_m(), haze.scale_height_m, (-h_cam / haze.scale_height_m).exp());
        Self { beta, hs, h_cam, e_cam, px: [beta as f32, hs as f32, h_cam as f32, e_cam as f32] }
    }

    fn tau(&self, h: f64, range: f64) -> f64 {
        let dh = self.h_cam - h;
        if dh.abs() > 1e-3 * self.hs {
            self.beta * self.hs * ((-h / self.hs).exp() - self.e_cam) / dh * range
        } else {
            // Nearly level: the mean density, (1 - e^-x) / x times the lower one, to O(x^2).
            let x = dh.abs() / self.hs;
            self.beta * range * (-self.h_cam.min(h) / self.hs).exp() * (1.0 - 0.5 * x)
        }
    }

    /// [`HazeFrom::tau`] in f32 (relative error < 1e-4), both forms computed
    /// and one selected, so that the pixel loop has no branch and vectorizes.
    #[inline(always)]
    fn tau_px(&self, h: f32, range: f32) -> f32 {
        let [beta, hs, h_cam, e_cam] = self.px;
        let dh = h_cam - h;
        let e_h = fast_exp(-h / hs);
        let slant = beta * hs * (e_h - e_cam) / dh;
        let level = beta * (if dh > 0.0 { e_h } else { e_cam }) * (1.0 - 0.5 * dh.abs() / hs);
        range * if dh.abs() > 1e-3 * hs { slant } else { level }
    }
}

/// `e^x` in f32, relative error < 3e-7; inlined and branch-free, so that
/// the haze pass (two per pixel) vectorizes.
#[inline(always)]
fn fast_exp(x: f32) -> f32 {
    let x = x.clamp(-87.0, 88.0);
    // Round to nearest by the 1.5 * 2^23 trick: k also sits in the low mantissa bits.
    let t = x * std::f32::consts::LOG2_E + 12_582_912.0;
    let k = t - 12_582_912.0;
    let ki = (t.to_bits() as i32).wrapping_sub(0x4B40_0000);
    let r = x - k * 0.693_145_75 - k * 1.428_606_8e-6;
    // Taylor to r^6 (|r| <= ln 2 / 2), in Estrin's form for a short dependency chain.
    let r2 = r * r;
    let p = (1.0 + r)
        + r2 * (0.5 + r * (1.0 / 6.0))
        + r2 * r2 * ((1.0 / 24.0 + r * (1.0 / 120.0)) + r2 * (1.0 / 720.0));
    p * f32::from_bits(((ki + 127) << 23) as u32)
}

/// `floor` without a libm call (the baseline target has no SSE4.1 round).
#[inline]
fn fast_floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x {
        t - 1.0
    } else {
        t
    }
}

// ---------------------------------------------------------------------------
// Clouds

// The smallest features (scale / 8) match the 4 px grid at typical ranges.
const CLOUD_OCTAVES: usize = 4;

/// Cloud cover on the Earth: 3D value-noise fBm of the ECEF position (no map
/// projection, so no seams or shear anywhere on the globe), each octave on
/// its own randomly rotated lattice so that no slice of it is axis-aligned.
struct CloudField {
    seed: u64,
    rot: [Matrix3<f64>; CLOUD_OCTAVES],
    offset: [Vector3<f64>; CLOUD_OCTAVES],
    inv_scale: f64,
    lo: f64,
    hi: f64,
    opacity: f64,
    wind: (f64, f64),
}

impl CloudField {
    fn new(c: &Clouds, seed: u64) -> Self {
        let mut rng = Rng::stream(seed, "effects.clouds");
        let noise_seed = rng.next_u64();
        let rot = std::array::from_fn(|_| {
            let q = nalgebra::Quaternion::new(rng.normal(), rng.normal(), rng.normal(), rng.normal());
            *UnitQuaternion::from_quaternion(q).to_rotation_matrix().matrix()
        });
        let offset = std::array::from_fn(|_| Vector3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1e3);
        let mut field = Self {
            seed: noise_seed,
            rot,
            offset,
            inv_scale: 1.0 / c.scale_m,
            lo: 0.0,
            hi: 0.0,
            opacity: c.opacity,
            wind: (c.wind_east_m_s, c.wind_north_m_s),
        };
        let threshold = field.threshold(c.coverage, &mut rng);
        (field.lo, field.hi) = (threshold - 0.5 * c.edge_softness, threshold + 0.5 * c.edge_softness);
        field
    }

    /// The (1 - coverage) quantile of the field, estimated on scattered
    /// points (far apart, so independent); cached, as frames share it.
    fn threshold(&self, coverage: f64, rng: &mut Rng) -> f64 {
        // The field lies in [0, 1]: thresholds outside it give no or full cover.
        if coverage <= 0.0 {
            return 2.0;
        } else if coverage >= 1.0 {
            return -1.0;
        }
        type Cache = std::sync::Mutex<Vec<((u64, u64, u64), f64)>>;
        static CACHE: std::sync::OnceLock<Cache> = std::sync::OnceLock::new();
        let key = (self.seed, coverage.to_bits(), self.inv_scale.to_bits());
        let cache = CACHE.get_or_init(Default::default);
        if let Some(&(_, t)) = cache.lock().unwrap().iter().find(|(k, _)| *k == key) {
            return t;
        }
        const N: usize = 4096;
        let mut vals: Vec<f64> = (0..N)
            .map(|_| {
                let p = Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0));
                self.fbm(&(p * 7e6))
            })
            .collect();
        vals.sort_by(f64::total_cmp);
        let t = vals[(((1.0 - coverage) * N as f64) as usize).min(N - 1)];
        let mut cache = cache.lock().unwrap();
        if cache.len() >= 64 {
            cache.remove(0);
        }
        cache.push((key, t));
        t
    }

    fn fbm(&self, p: &Vector3<f64>) -> f64 {
        self.fbm_clipped(p, f64::NEG_INFINITY, f64::INFINITY)
    }

    /// The fBm, exact within `[lo, hi]`; outside, it may stop at the octave
    /// from which it cannot come back and return a value on that side (saves
    /// most octaves where the cover is surely clear or surely cloud).
    fn fbm_clipped(&self, p: &Vector3<f64>, lo: f64, hi: f64) -> f64 {
        const NORM: f64 = 2.0 - 1.0 / (1 << (CLOUD_OCTAVES - 1)) as f64; // 1 + 1/2 + ...
        let (mut sum, mut amp, mut freq) = (0.0, 1.0, self.inv_scale);
        for o in 0..CLOUD_OCTAVES {
            let q = self.rot[o] * p * freq + self.offset[o];
            sum += amp * value_noise3(self.seed.wrapping_add(o as u64 * 7919), &q);
            // Octaves left can add at most their amplitudes (values in [0, 1)).
            let rest = 2.0 * amp - 2.0 / (1 << (CLOUD_OCTAVES - 1)) as f64;
            if (sum + rest) / NORM < lo || sum / NORM > hi {
                return if sum / NORM > hi { sum / NORM } else { (sum + rest) / NORM };
            }
            amp *= 0.5;
            freq *= 2.0;
        }
        sum / NORM
    }

    /// Opacity of the sheet at ECEF point `p` at time `t`.
    fn alpha(&self, p: &Vector3<f64>, t: f64) -> f64 {
        let mut q = *p;
        if t != 0.0 && self.wind != (0.0, 0.0) {
            // The field drifts with the wind: sample it where this air was at t = 0.
            let east = Vector3::new(-p.y, p.x, 0.0).normalize();
            let b2 = (WGS84_B / WGS84_A).powi(2);
            let up = Vector3::new(p.x * b2, p.y * b2, p.z).normalize(); // ellipsoid normal
            let north = up.cross(&east);
            q -= (east * self.wind.0 + north * self.wind.1) * t;
        }
        self.opacity * smoothstep(self.lo, self.hi, self.fbm_clipped(&q, self.lo, self.hi))
    }
}

fn hash3(seed: u64, x: i64, y: i64, z: i64) -> f64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ (z as u64).wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^= h >> 32;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

/// Value noise in [0, 1] on the unit lattice, smoothstep-interpolated.
fn value_noise3(seed: u64, p: &Vector3<f64>) -> f64 {
    let (fx, fy, fz) = (fast_floor(p.x), fast_floor(p.y), fast_floor(p.z));
    let (ix, iy, iz) = (fx as i64, fy as i64, fz as i64);
    let s = |t: f64| t * t * (3.0 - 2.0 * t);
    let (sx, sy, sz) = (s(p.x - fx), s(p.y - fy), s(p.z - fz));
    let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
    let plane = |z: i64| {
        lerp(
            lerp(hash3(seed, ix, iy, z), hash3(seed, ix + 1, iy, z), sx),
            lerp(hash3(seed, ix, iy + 1, z), hash3(seed, ix + 1, iy + 1, z), sx),
            sy,
        )
    };
    lerp(plane(iz), plane(iz + 1), sz)
}

/// The ground brightness field, evaluated every 8 px at the ground point the
/// node's pixel sees (factor 1 where it sees sky), interpolated, applied to
/// terrain pixels.
fn brightness_field(b: &BrightnessField, img: &mut [f32], geo: &FrameGeometry, seed: u64) {
    let (w, h) = (geo.camera.width as usize, geo.camera.height as usize);
    let origin = geo.pose.position.0;
    let grid = CoarseGrid::build(w, h, 8, 1, |px, out| {
        let (u, v) = ((px.u as usize).min(w - 1), (px.v as usize).min(h - 1));
        let range = geo.range_m[v * w + u] as f64;
        out[0] = if range.is_finite() {
            let dir = geo.pose.q_ecef_cam * geo.camera.ray(Pixel::new(u as f64, v as f64));
            b.factor(&(origin + dir * range), seed) as f32
        } else {
            1.0
        };
    });
    img.par_chunks_mut(w).zip(geo.range_m.par_chunks(w)).enumerate().for_each(|(v, (row, range))| {
        let mut f = vec![0f32; w];
        grid.row::<1>(v, &mut f);
        for ((px, f), r) in row.iter_mut().zip(&f).zip(range) {
            if r.is_finite() {
                *px *= f;
            }
        }
    });
}

/// Cloud opacity and distance (m; infinite where the ray misses the sheet)
/// on a grid every 4 px.
fn cloud_grid(c: &Clouds, geo: &FrameGeometry, t: f64, seed: u64) -> CoarseGrid {
    let field = CloudField::new(c, seed);
    let (w, h) = (geo.camera.width as usize, geo.camera.height as usize);
    let origin = geo.pose.position;
    let up = geo.pose.position.to_geodetic().up_ecef();
    let below = geo.camera_height_m < c.height_m;
    CoarseGrid::build(w, h, 4, 2, |px, out| {
        let dir = geo.pose.q_ecef_cam * geo.camera.ray(px);
        // From below the sheet only rising rays meet it (the other exit is beyond the Earth).
        let hit = if below && dir.dot(&up) <= 0.0 {
            None
        } else {
            intersect_ellipsoid(&Ray { origin, direction: dir }, c.height_m)
        };
        match hit {
            Some(p) => {
                out[0] = field.alpha(&p.0, t) as f32;
                out[1] = (p.0 - origin.0).norm() as f32;
            }
            None => {
                out[0] = 0.0;
                out[1] = f32::INFINITY;
            }
        }
    })
}

/// Clouds and haze in one pass: the terrain (or sky) is veiled by the haze
/// along its full path, the cloud by the haze in front of it, and the cloud
/// is composited over wherever it lies in front of the terrain.
fn atmosphere(
    haze: Option<&Haze>,
    clouds: Option<&Clouds>,
    img: &mut [f32],
    geo: &FrameGeometry,
    t: f64,
    seed: u64,
) {
    let (w, h) = (geo.camera.width as usize, geo.camera.height as usize);
    let h_cam = geo.camera_height_m;
    let cloud = clouds.map(|c| (c, cloud_grid(c, geo, t, seed)));
    let sky = haze.filter(|_| geo.range_m.iter().any(|r| r.is_nan())).map(|hz| {
        let up = geo.pose.position.to_geodetic().up_ecef();
        CoarseGrid::build(w, h, 8, 1, |px, out| {
            let s = (geo.pose.q_ecef_cam * geo.camera.ray(px)).dot(&up);
            out[0] = hz.sky_dn(h_cam, s) as f32;
        })
    });
    let path = HazeFrom::new(haze.unwrap_or(&Haze::default()), h_cam);
    img.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
        let mut sky_row = vec![0f32; if sky.is_some() { w } else { 0 }];
        if let Some(g) = &sky {
            g.row::<1>(v, &mut sky_row);
        }
        let mut cloud_row = vec![0f32; if cloud.is_some() { 2 * w } else { 0 }];
        if let Some((_, g)) = &cloud {
            g.row::<2>(v, &mut cloud_row);
        }
        let ranges = &geo.range_m[v * w..(v + 1) * w];
        if let Some(hz) = haze {
            let heights = &geo.hit_height_m[v * w..(v + 1) * w];
            let air = hz.airlight_dn as f32;
            #[inline(always)]
            fn veiled(path: &HazeFrom, air: f32, px: f32, h: f32, r: f32) -> f32 {
                let t = fast_exp(-path.tau_px(h, r));
                px * t + air * (1.0 - t)
            }
            if sky_row.is_empty() {
                for ((px, &r), &h) in row.iter_mut().zip(ranges).zip(heights) {
                    *px = veiled(&path, air, *px, h, r);
                }
            } else {
                for (((px, &r), &h), &s) in row.iter_mut().zip(ranges).zip(heights).zip(&sky_row) {
                    let p = veiled(&path, air, *px, h, r);
                    *px = if r.is_nan() { s } else { p };
                }
            }
        }
        let Some((c, g)) = &cloud else { return };
        for (u, px) in row.iter_mut().enumerate() {
            let alpha = cloud_row[2 * u];
            if alpha <= 0.0 {
                continue;
            }
            let mut dist = cloud_row[2 * u + 1];
            if !dist.is_finite() {
                dist = nearest_finite_distance(g, u, v);
            }
            if ranges[u] < dist {
                continue; // terrain in front of the cloud (false for sky)
            }
            let mut col = c.brightness_dn as f32;
            if let Some(hz) = haze {
                col = hz.veil(col, path.tau_px(c.height_m as f32, dist));
            }
            *px += (col - *px) * alpha;
        }
    });
}

/// Near the sheet's visible edge some nodes miss it: take the nearest hit.
fn nearest_finite_distance(g: &CoarseGrid, u: usize, v: usize) -> f32 {
    let (i0, j0) = ((u / g.step).min(g.nx - 1), (v / g.step).min(g.ny - 1));
    let mut best = f32::INFINITY;
    for (i, j) in [(i0, j0), (i0 + 1, j0), (i0, j0 + 1), (i0 + 1, j0 + 1)] {
        if i < g.nx && j < g.ny {
            best = best.min(g.node(i, j)[1]);
        }
    }
    best
}

// ---------------------------------------------------------------------------
// Motion blur

/// Image-plane displacement (px) over the exposure of the scene point seen at
/// each grid node: the ray rotated by -/+ half the exposure's rotation, projected.
fn blur_grid(camera: &CameraModel, w_cam: &Vector3<f64>, exposure_s: f64) -> CoarseGrid {
    let half = UnitQuaternion::from_scaled_axis(w_cam * (0.5 * exposure_s));
    let inv = half.inverse();
    let (w, h) = (camera.width as usize, camera.height as usize);
    CoarseGrid::build(w, h, 16, 2, |px, out| {
        let ray = camera.ray(px);
        let (a, b) = (camera.project(&(half * ray)), camera.project(&(inv * ray)));
        (out[0], out[1]) = match (a, b) {
            (Some(a), Some(b)) => ((a.u - b.u) as f32, (a.v - b.v) as f32),
            _ => (0.0, 0.0),
        };
    })
}

fn bilinear(src: &[f32], w: usize, h: usize, x: f32, y: f32) -> f32 {
    let x = x.clamp(0.0, (w - 1) as f32);
    let y = y.clamp(0.0, (h - 1) as f32);
    let (x0, y0) = ((x as usize).min(w.saturating_sub(2)), (y as usize).min(h.saturating_sub(2)));
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    let (tx, ty) = (x - x0 as f32, y - y0 as f32);
    let top = src[y0 * w + x0] + (src[y0 * w + x1] - src[y0 * w + x0]) * tx;
    let bottom = src[y1 * w + x0] + (src[y1 * w + x1] - src[y1 * w + x0]) * tx;
    top + (bottom - top) * ty
}

/// Each pixel averages the input along its blur segment, centred on it:
/// `n` bilinear samples at the middles of `n` equal parts of the segment.
fn motion_blur(
    mb: &MotionBlur,
    img: &mut [f32],
    camera: &CameraModel,
    w_cam: &Vector3<f64>,
    exposure_s: f64,
) {
    if exposure_s.is_nan() || exposure_s <= 0.0 || *w_cam == Vector3::zeros() {
        return;
    }
    let grid = blur_grid(camera, w_cam, exposure_s);
    if grid.max_norm() < 0.25 {
        return;
    }
    let (w, h) = (camera.width as usize, camera.height as usize);
    let src = img.to_vec();
    let (min_n, max_n) = (mb.samples.max(1) as usize, mb.max_samples.max(mb.samples).max(1) as usize);
    // The displacement barely changes over a grid cell (a 16 px block): one
    // kernel per block, its samples' bilinear weights merged per source pixel.
    let b = grid.step;
    let nbx = w.div_ceil(b);
    let kernels: Vec<BlurKernel> = (0..nbx * h.div_ceil(b))
        .into_par_iter()
        .map(|k| {
            let (i, j) = (k % nbx, k / nbx);
            let centre = |n0: usize, len: usize| (n0 * b + b / 2).min(len - 1);
            let (cu, cv) = (centre(i, w), centre(j, h));
            let (d0, d1) = (grid.node(i, j), grid.node((i + 1).min(grid.nx - 1), (j + 1).min(grid.ny - 1)));
            // Block centres lie midway between nodes (or on the last ones).
            let t = |c: usize, n0: usize| (c - n0 * b) as f32 / b as f32;
            let (tx, ty) = (t(cu, i), t(cv, j));
            let (d01, d10) = (grid.node(i, (j + 1).min(grid.ny - 1)), grid.node((i + 1).min(grid.nx - 1), j));
            let lerp2 = |c: usize| {
                let top = d0[c] + (d10[c] - d0[c]) * tx;
                top + (d01[c] + (d1[c] - d01[c]) * tx - top) * ty
            };
            BlurKernel::new(lerp2(0), lerp2(1), min_n, max_n, w)
        })
        .collect();
    img.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
        for (bi, u0) in (0..w).step_by(b).enumerate() {
            let kernel = &kernels[(v / b) * nbx + bi];
            let u1 = (u0 + b).min(w);
            let reach = kernel.reach;
            let rows_ok = v as isize + reach.2 >= 0 && v as isize + reach.3 < h as isize;
            let interior =
                |u: usize| rows_ok && u as isize + reach.0 >= 0 && (u as isize + reach.1) < w as isize;
            let i0 = v * w + u0;
            if interior(u0) && interior(u1 - 1) {
                // Tap by tap over the block's contiguous pixels (vectorizes).
                let out = &mut row[u0..u1];
                out.fill(0.0);
                for &(o, wt) in &kernel.taps {
                    let s0 = (i0 as isize + o) as usize;
                    out.iter_mut().zip(&src[s0..s0 + (u1 - u0)]).for_each(|(p, s)| *p += s * wt);
                }
                continue;
            }
            for (u, px) in row.iter_mut().enumerate().take(u1).skip(u0) {
                let i = (v * w + u) as isize;
                *px = if interior(u) {
                    kernel.taps.iter().map(|&(o, wt)| src[(i + o) as usize] * wt).sum()
                } else {
                    let (x, y) = (u as f32, v as f32);
                    let n = kernel.offsets.len() as f32;
                    kernel.offsets.iter().map(|&(ox, oy)| bilinear(&src, w, h, x + ox, y + oy)).sum::<f32>()
                        / n
                };
            }
        }
    });
}

/// The blur of one block: sample offsets (px) along the segment `(dx, dy)`,
/// and their bilinear weights merged as `(index offset, weight)` in rows `w`
/// wide, with their reach: min/max column, min/max row offset.
struct BlurKernel {
    offsets: Vec<(f32, f32)>,
    taps: Vec<(isize, f32)>,
    reach: (isize, isize, isize, isize),
}

impl BlurKernel {
    fn new(dx: f32, dy: f32, min_n: usize, max_n: usize, w: usize) -> Self {
        let n = ((2.0 * (dx * dx + dy * dy).sqrt()).ceil() as usize + 1).clamp(min_n, max_n);
        let offsets: Vec<(f32, f32)> = (0..n)
            .map(|k| {
                let s = (k as f32 + 0.5) / n as f32 - 0.5;
                (s * dx, s * dy)
            })
            .collect();
        let mut taps: Vec<(isize, f32)> = Vec::new();
        let mut reach = (0isize, 0isize, 0isize, 0isize);
        let scale = 1.0 / n as f32;
        for &(x, y) in &offsets {
            let (fx, fy) = (x.floor(), y.floor());
            let (tx, ty) = (x - fx, y - fy);
            let (ix, iy) = (fx as isize, fy as isize);
            reach = (reach.0.min(ix), reach.1.max(ix + 1), reach.2.min(iy), reach.3.max(iy + 1));
            for (ox, oy, wt) in [
                (0, 0, (1.0 - tx) * (1.0 - ty)),
                (1, 0, tx * (1.0 - ty)),
                (0, 1, (1.0 - tx) * ty),
                (1, 1, tx * ty),
            ] {
                if wt == 0.0 {
                    continue;
                }
                let off = (iy + oy) * w as isize + ix + ox;
                match taps.iter_mut().find(|t| t.0 == off) {
                    Some(t) => t.1 += wt * scale,
                    None => taps.push((off, wt * scale)),
                }
            }
        }
        Self { offsets, taps, reach }
    }
}

// ---------------------------------------------------------------------------
// Cords

/// One cord: a line through a pivot above the image, at `angle` from the
/// image vertical (+v), positive toward +u.
#[derive(Clone, Copy, Debug)]
struct CordLine {
    pivot_u: f64,
    pivot_v: f64,
    angle: f64,
}

impl CordLine {
    /// Column where the cord's centre line crosses row `v`.
    fn u_at(&self, v: f64) -> f64 {
        self.pivot_u + (v - self.pivot_v) * self.angle.tan()
    }
}

fn cord_lines(c: &Cords, w: usize, h: usize, t: f64, seed: u64) -> Vec<CordLine> {
    let mut rng = Rng::stream(seed, "effects.cords");
    // The pivot lies one image height above the top edge, so the sway moves
    // the whole cord, the bottom twice as much as the top.
    let lever = h as f64;
    (0..c.count)
        .map(|i| {
            let slot = (i as f64 + 0.5 + rng.range(-0.3, 0.3)) / c.count as f64;
            let entry_u = slot * w as f64;
            let base = rng.range(-1.0, 1.0) * c.max_base_angle_deg.to_radians();
            let phase = rng.range(0.0, std::f64::consts::TAU);
            let angle =
                base + c.sway_deg.to_radians() * (std::f64::consts::TAU * t / c.sway_period_s + phase).sin();
            CordLine { pivot_u: entry_u - lever * base.tan(), pivot_v: -0.5 - lever, angle }
        })
        .collect()
}

fn cords(c: &Cords, img: &mut [f32], w: usize, h: usize, t: f64, seed: u64) {
    let lines = cord_lines(c, w, h, t, seed);
    let (half, edge) = (0.5 * c.width_px, c.edge_px.max(1e-3));
    let reach = half + 0.5 * edge;
    let dark = c.darkness_dn as f32;
    img.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
        for line in &lines {
            let (uc, cos) = (line.u_at(v as f64), line.angle.cos());
            let span = reach / cos;
            let lo = (uc - span).ceil().max(0.0) as usize;
            let hi = ((uc + span).floor().min(w as f64 - 1.0)).max(-1.0);
            if hi < lo as f64 {
                continue;
            }
            for (u, px) in row.iter_mut().enumerate().take(hi as usize + 1).skip(lo) {
                let d = ((u as f64 - uc) * cos).abs();
                let alpha = 1.0 - smoothstep(half - 0.5 * edge, half + 0.5 * edge, d);
                *px += (dark - *px) * alpha as f32;
            }
        }
    });
}

// ---------------------------------------------------------------------------
// Lens and sensor

/// The photometric response, tabulated above 4 DN (interpolation error
/// < 0.01 DN for gamma >= 0.5): the power is the costliest per-pixel step.
struct Response {
    gain: f32,
    offset: f32,
    gamma: f32,
    contrast: f64,
    table: Vec<f32>,
}

impl Response {
    const N: usize = 1024;
    const EXACT_BELOW: f32 = 4.0;

    fn new(p: &Photometric) -> Self {
        let curve = |b: f64| 255.0 * tone((b / 255.0).powf(p.gamma), p.contrast);
        let table = (0..=Self::N).map(|k| curve(k as f64 * 255.0 / Self::N as f64) as f32).collect();
        Self {
            gain: p.gain as f32,
            offset: p.offset_dn as f32,
            gamma: p.gamma as f32,
            contrast: p.contrast,
            table,
        }
    }

    fn eval(&self, x: f32) -> f32 {
        let b = (self.gain * x + self.offset).clamp(0.0, 255.0);
        if b < Self::EXACT_BELOW {
            return 255.0 * tone((b / 255.0).powf(self.gamma) as f64, self.contrast) as f32;
        }
        let f = b * (Self::N as f32 / 255.0);
        let k = (f as usize).min(Self::N - 1);
        let (a, c) = (self.table[k], self.table[k + 1]);
        a + (c - a) * (f - k as f32)
    }
}

/// Standard normal deviates from 16 random bits: the inverse normal CDF
/// tabulated at 4096 equal-probability steps, interpolated (4 deviates per
/// `u64`, several times faster than Box-Muller; tails end at 3.7 sigma,
/// which loses 0.2 % of the variance).
struct NormalTable {
    quantiles: Vec<f32>,
}

impl NormalTable {
    const BITS: u32 = 12;

    fn new() -> Self {
        // CDF by the trapezoid rule on a fine grid, then inverted.
        let (lo, dx, steps) = (-8.0f64, 1e-3, 16_000);
        let pdf = |x: f64| (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt();
        let mut cdf = Vec::with_capacity(steps + 1);
        let mut acc = 0.0;
        cdf.push(0.0);
        for i in 0..steps {
            let x = lo + i as f64 * dx;
            acc += 0.5 * (pdf(x) + pdf(x + dx)) * dx;
            cdf.push(acc);
        }
        let n = 1usize << Self::BITS;
        let mut j = 0;
        let quantiles = (0..=n)
            .map(|k| {
                // Bin edges shifted half a step in, so both tails are symmetric.
                let p = (k as f64 + 0.5) / (n as f64 + 1.0);
                while cdf[j + 1] < p {
                    j += 1;
                }
                let t = (p - cdf[j]) / (cdf[j + 1] - cdf[j]);
                (lo + (j as f64 + t) * dx) as f32
            })
            .collect();
        Self { quantiles }
    }

    fn sample(&self, bits: u16) -> f32 {
        let k = (bits >> (16 - Self::BITS)) as usize;
        let t = (bits & ((1 << (16 - Self::BITS)) - 1)) as f32 / (1 << (16 - Self::BITS)) as f32;
        let (a, b) = (self.quantiles[k], self.quantiles[k + 1]);
        a + (b - a) * t
    }
}

fn normal_table() -> &'static NormalTable {
    static TABLE: std::sync::OnceLock<NormalTable> = std::sync::OnceLock::new();
    TABLE.get_or_init(NormalTable::new)
}

/// Vignetting, photometric response, noise and the final clamp, in one pass.
fn sensor(realism: &Realism, img: &mut [f32], camera: &CameraModel, index: usize, seed: u64) {
    let w = camera.width as usize;
    let vig = realism.vignetting.as_ref().map(|vg| {
        let e = (4.0 * vg.strength) as f32;
        CoarseGrid::build(w, camera.height as usize, 8, 1, |px, out| {
            out[0] = (camera.ray(px).z as f32).max(0.0).powf(e);
        })
    });
    let photo = realism.photometric.as_ref().map(Response::new);
    let noise =
        realism.noise.as_ref().map(|n| ((n.read_noise_dn * n.read_noise_dn) as f32, n.shot_gain as f32));
    // Per frame: frames differ, runs repeat; per row: independent of threads.
    let frame_key =
        Rng::stream(seed ^ (index as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93), "effects.noise").next_u64();
    img.par_chunks_mut(w).enumerate().for_each(|(v, row)| {
        if let Some(g) = &vig {
            let mut f = vec![0f32; w];
            g.row::<1>(v, &mut f);
            row.iter_mut().zip(&f).for_each(|(px, f)| *px *= f);
        }
        if let Some(resp) = &photo {
            row.iter_mut().for_each(|px| *px = resp.eval(*px));
        }
        if let Some((read2, shot)) = noise {
            let table = normal_table();
            let mut rng = Rng::stream(frame_key.wrapping_add(v as u64), "effects.noise.row");
            for quad in row.chunks_mut(4) {
                let bits = rng.next_u64();
                for (k, px) in quad.iter_mut().enumerate() {
                    let z = table.sample((bits >> (16 * k)) as u16);
                    *px += z * (read2 + shot * px.max(0.0)).sqrt();
                }
            }
        }
        for px in row.iter_mut() {
            *px = px.clamp(0.0, 255.0);
        }
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::{Ecef, Geodetic, LocalFrame};

    /// A frame over flat terrain at `ground_m`, ray-cast onto the raised ellipsoid.
    struct Scene {
        cam: CameraModel,
        pose: CameraPose,
        h_cam: f64,
        range: Vec<f32>,
        hit_h: Vec<f32>,
    }

    impl Scene {
        fn new(cam: CameraModel, pose: CameraPose, ground_m: f64) -> Self {
            let (w, h) = (cam.width as usize, cam.height as usize);
            let h_cam = pose.position.to_geodetic().h_m;
            let (mut range, mut hit_h) = (vec![f32::NAN; w * h], vec![f32::NAN; w * h]);
            for v in 0..h {
                for u in 0..w {
                    let ray = pose.ray(&cam, Pixel::new(u as f64, v as f64));
                    if let Some(p) = intersect_ellipsoid(&ray, ground_m).filter(|_| h_cam > ground_m) {
                        range[v * w + u] = p.distance_m(&pose.position) as f32;
                        hit_h[v * w + u] = ground_m as f32;
                    }
                }
            }
            Self { cam, pose, h_cam, range, hit_h }
        }

        fn geo(&self) -> FrameGeometry<'_> {
            FrameGeometry {
                camera: &self.cam,
                pose: &self.pose,
                camera_height_m: self.h_cam,
                range_m: &self.range,
                hit_height_m: &self.hit_h,
            }
        }

        fn n(&self) -> usize {
            self.range.len()
        }

        fn run(&self, r: &Realism, value: f32, frame: &FrameContext, seed: u64) -> Vec<f32> {
            let mut img = vec![value; self.n()];
            apply(r, &mut img, &self.geo(), frame, seed);
            img
        }
    }

    fn north(lat: f64, lon: f64) -> Vector3<f64> {
        LocalFrame::at(Geodetic::new(lat, lon, 0.0)).vector_to_ecef(&Vector3::y())
    }

    /// Looking straight down, north up, east right.
    fn nadir(lat: f64, lon: f64, h: f64) -> CameraPose {
        let g = Geodetic::new(lat, lon, h);
        CameraPose::look_at(g.to_ecef(), g.with_height(0.0).to_ecef(), north(lat, lon))
    }

    fn frame(t: f64) -> FrameContext {
        FrameContext { index: 0, t, w_cam_rad_s: Vector3::zeros(), exposure_s: 0.005 }
    }

    fn only(f: impl FnOnce(&mut Realism)) -> Realism {
        let mut r = Realism::none();
        f(&mut r);
        r
    }

    fn small_scene() -> Scene {
        Scene::new(CameraModel::from_fov(64, 48, 60.0), nadir(35.0, -106.0, 3000.0), 1500.0)
    }

    #[test]
    fn off_is_identity() {
        let s = small_scene();
        let mut rng = Rng::new(3);
        let orig: Vec<f32> = (0..s.n()).map(|_| rng.range(-20.0, 300.0) as f32).collect();
        let mut img = orig.clone();
        let ctx = FrameContext { w_cam_rad_s: Vector3::new(1.0, 2.0, 3.0), ..frame(1.0) };
        apply(&Realism::none(), &mut img, &s.geo(), &ctx, 9);
        assert!(img.iter().zip(&orig).all(|(a, b)| a.to_bits() == b.to_bits()));
        assert_eq!(Realism::default(), Realism::none());
        assert!(Realism::none().is_off() && !Realism::all_on().is_off());
    }

    #[test]
    fn photometric_formula() {
        let s = small_scene();
        let r = only(|r| r.photometric = Some(Photometric::default()));
        // 255 ((1.1 in + 5) / 255)^0.9, clamped.
        for (input, want) in [(0.0, 7.4089), (100.0, 124.531), (250.0, 255.0), (50.0, 69.341)] {
            let out = s.run(&r, input, &frame(0.0), 1);
            assert!((out[7] - want).abs() < 2e-3, "{input}: {} vs {want}", out[7]);
        }
    }

    #[test]
    fn tone_curve_is_a_monotone_s_curve() {
        let s = small_scene();
        let p = Photometric { gain: 1.0, gamma: 1.0, offset_dn: 0.0, contrast: 8.0 };
        let r = only(|r| r.photometric = Some(p.clone()));
        // Fixed points 0, mid-grey and 255; darker below, brighter above; the
        // closed form 255 (sig(x) - sig(0)) / (sig(1) - sig(0)).
        let sig = |t: f64| 1.0 / (1.0 + (-8.0 * (t - 0.5)).exp());
        let mut last = -1.0;
        for input in [0.0, 2.0, 30.0, 64.0, 127.5, 190.0, 250.0, 255.0] {
            let out = s.run(&r, input as f32, &frame(0.0), 1)[7] as f64;
            let want = 255.0 * (sig(input / 255.0) - sig(0.0)) / (sig(1.0) - sig(0.0));
            assert!((out - want).abs() < 0.02, "{input}: {out} vs {want}");
            assert!((out - p.response(input)).abs() < 0.02);
            assert!(out > last, "monotone at {input}");
            last = out;
            if input > 10.0 && input < 120.0 {
                assert!(out < input - 5.0, "{input} -> {out}: shadows darker");
            }
            if input > 135.0 && input < 245.0 {
                assert!(out > input + 5.0, "{input} -> {out}: highlights brighter");
            }
        }
        assert!((p.response(127.5) - 127.5).abs() < 1e-9 && p.response(255.0) == 255.0);
    }

    #[test]
    fn brightness_field_is_slow_bounded_and_fixed_on_the_ground() {
        let b = BrightnessField { amplitude: 0.2, scale_m: 4000.0 };
        let p0 = Geodetic::new(35.0, -106.0, 1500.0).to_ecef().0;
        let f = LocalFrame::at(Geodetic::new(35.0, -106.0, 1500.0));
        let east = f.vector_to_ecef(&Vector3::x());
        // Bounded by the amplitude, varying over km, nearly constant over 10 m.
        let vals: Vec<f64> = (0..400).map(|k| b.factor(&(p0 + east * (k as f64 * 100.0)), 5)).collect();
        let (lo, hi) = vals.iter().fold((f64::MAX, f64::MIN), |(l, h), v| (l.min(*v), h.max(*v)));
        assert!(lo >= 0.8 - 1e-12 && hi <= 1.2 + 1e-12, "{lo} {hi}");
        assert!(hi - lo > 0.1, "the field varies over 40 km: {lo}..{hi}");
        let step = vals.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
        assert!(step < 0.05, "slow: {step} per 100 m");
        assert!((b.factor(&(p0 + east * 10.0), 5) - b.factor(&p0, 5)).abs() < 2e-3);
        assert_ne!(b.factor(&p0, 5), b.factor(&p0, 6), "seeded");
        // Through apply: terrain pixels scaled by the factor of the ground point
        // they see, sky untouched; two poses seeing the same ground agree.
        let mut s = small_scene();
        s.range[3] = f32::NAN;
        let r = only(|r| r.brightness_field = Some(b.clone()));
        let out = s.run(&r, 100.0, &frame(0.0), 5);
        assert_eq!(out[3], 100.0);
        let (w, centre) = (64, 24 * 64 + 32);
        let ray = s.pose.ray(&s.cam, Pixel::new(32.0, 24.0));
        let ground = ray.origin.0 + ray.direction * s.range[centre] as f64;
        assert!((out[centre] as f64 - 100.0 * b.factor(&ground, 5)).abs() < 0.05, "{}", out[centre]);
        let moved = Scene::new(CameraModel::from_fov(64, 48, 60.0), nadir(35.0, -106.0, 2600.0), 1500.0);
        let out2 = moved.run(&r, 100.0, &frame(0.0), 5);
        assert!((out2[centre] - out[centre]).abs() < 0.05, "{} vs {}", out2[centre], out[centre]);
        assert!(out.iter().skip(w).any(|v| (v - 100.0).abs() > 1e-3));
    }

    #[test]
    fn haze_grows_with_range_and_height() {
        let hz = Haze::default();
        // Oblique paths from 10 km to the ground: longer is thicker.
        assert!(hz.optical_depth(10_000.0, 0.0, 20_000.0) > hz.optical_depth(10_000.0, 0.0, 10_000.0));
        // Nadir from higher: thicker, saturating at beta H.
        let nadir_tau = |h: f64| hz.optical_depth(h, 0.0, h);
        assert!(nadir_tau(1000.0) < nadir_tau(5000.0) && nadir_tau(5000.0) < nadir_tau(30_000.0));
        assert!((nadir_tau(1e6) - 0.05e-3 * 8000.0).abs() < 1e-9);
        // Horizontal paths: beta(h) * range, continuous with slightly slanted ones.
        let flat = hz.optical_depth(2000.0, 2000.0, 10_000.0);
        assert!((flat - 0.05e-3 * (-0.25f64).exp() * 10_000.0).abs() < 1e-12);
        assert!((hz.optical_depth(2000.0, 2000.001, 10_000.0) / flat - 1.0).abs() < 1e-6);
        assert!((hz.optical_depth(2000.0, 2010.0, 10_000.0) / flat - 1.0).abs() < 1e-3);
        assert_eq!(hz.optical_depth(5000.0, 0.0, 0.0), 0.0);

        // Through apply: range 0 unchanged, far pixels pulled toward the airlight.
        let mut s = small_scene();
        s.range[5] = 0.0;
        s.hit_h[5] = s.h_cam as f32;
        let out = s.run(&only(|r| r.haze = Some(Haze::default())), 80.0, &frame(0.0), 1);
        assert_eq!(out[5], 80.0);
        let centre = 24 * 64 + 32;
        let tau = hz.optical_depth(s.h_cam, 1500.0, s.range[centre] as f64);
        let want = 80.0 * (-tau).exp() + 200.0 * (1.0 - (-tau).exp());
        assert!((out[centre] as f64 - want).abs() < 1e-3 && out[centre] > 80.5, "{}", out[centre]);
        // Higher camera, same ground: hazier.
        let high = Scene::new(CameraModel::from_fov(64, 48, 60.0), nadir(35.0, -106.0, 30_000.0), 1500.0);
        let out_high = high.run(&only(|r| r.haze = Some(Haze::default())), 80.0, &frame(0.0), 1);
        assert!(out_high[centre] > out[centre] + 5.0, "{} {}", out_high[centre], out[centre]);
    }

    #[test]
    fn sky_is_bright_near_horizon() {
        // Camera at 1 km looking 30 degrees above the horizon, northward.
        let g = Geodetic::new(35.0, -106.0, 1000.0);
        let f = LocalFrame::at(g);
        let (e30, up) = (30f64.to_radians(), f.vector_to_ecef(&Vector3::z()));
        let dir = f.vector_to_ecef(&Vector3::new(0.0, e30.cos(), e30.sin()));
        let pose = CameraPose::look_at(g.to_ecef(), Ecef(g.to_ecef().0 + dir), up);
        let s = Scene::new(CameraModel::from_fov(64, 48, 60.0), pose, 0.0);
        let out = s.run(&only(|r| r.haze = Some(Haze::default())), 100.0, &frame(0.0), 1);
        assert!(s.range[32].is_nan() && s.range[47 * 64 + 32].is_nan(), "all sky");
        let (top, bottom) = (out[32], out[47 * 64 + 32]);
        assert!(bottom > top + 20.0 && top > 30.0 && bottom < 200.0, "top {top} bottom {bottom}");
        // Higher up, the zenith sky darkens while the limb stays bright.
        let hz = Haze::default();
        assert!(hz.sky_dn(30_000.0, 1.0) < 0.1 * hz.sky_dn(0.0, 1.0));
        assert!(hz.sky_dn(30_000.0, -0.09) > 150.0);
        assert!((hz.sky_dn(30_000.0, 1e-9) - hz.sky_dn(30_000.0, -1e-9)).abs() < 1e-3, "continuous");
    }

    #[test]
    fn noise_statistics_and_seeding() {
        let s = Scene::new(CameraModel::from_fov(400, 300, 60.0), nadir(35.0, -106.0, 3000.0), 0.0);
        let r = only(|r| r.noise = Some(SensorNoise::default()));
        let a = s.run(&r, 100.0, &frame(0.0), 5);
        let n = a.len() as f64;
        let mean = a.iter().map(|&x| x as f64).sum::<f64>() / n;
        let std = (a.iter().map(|&x| (x as f64 - mean).powi(2)).sum::<f64>() / n).sqrt();
        let want = (2.0f64 * 2.0 + 100.0 * 0.05).sqrt();
        assert!((std / want - 1.0).abs() < 0.05 && (mean - 100.0).abs() < 0.05, "std {std} mean {mean}");
        assert_eq!(a, s.run(&r, 100.0, &frame(0.0), 5));
        let next = FrameContext { index: 1, ..frame(0.0) };
        let b = s.run(&r, 100.0, &next, 5);
        let c = s.run(&r, 100.0, &frame(0.0), 6);
        let diff = |x: &[f32], y: &[f32]| x.iter().zip(y).filter(|(p, q)| p != q).count();
        assert!(diff(&a, &b) > a.len() * 9 / 10 && diff(&a, &c) > a.len() * 9 / 10);
    }

    #[test]
    fn fast_math_matches_std() {
        for k in 0..=20_000 {
            let x = -87.0 + k as f32 * (87.0 + 20.0) / 20_000.0;
            let (a, b) = (fast_exp(x), x.exp());
            assert!(((a - b) / b).abs() < 3e-7, "exp({x}): {a} vs {b}");
        }
        for x in [-3.5, -3.0, -0.2, 0.0, 0.7, 2.0, -1e9 - 0.5, 123456.9] {
            assert_eq!(fast_floor(x), x.floor(), "{x}");
        }
    }

    #[test]
    fn normal_table_is_standard_normal() {
        let t = normal_table();
        assert!(t.quantiles[2048].abs() < 1e-3, "median {}", t.quantiles[2048]);
        assert!((t.quantiles[0] + t.quantiles[4096]).abs() < 1e-3 && t.quantiles[0] < -3.5);
        let mut rng = Rng::new(2);
        let n = 400_000;
        let zs: Vec<f64> = (0..n).map(|_| t.sample(rng.next_u64() as u16) as f64).collect();
        let mean = zs.iter().sum::<f64>() / n as f64;
        let var = zs.iter().map(|z| (z - mean).powi(2)).sum::<f64>() / n as f64;
        let within1 = zs.iter().filter(|z| z.abs() < 1.0).count() as f64 / n as f64;
        assert!(mean.abs() < 0.01 && (var - 1.0).abs() < 0.01, "mean {mean} var {var}");
        assert!((within1 - 0.6827).abs() < 0.005, "{within1}");
    }

    #[test]
    fn vignetting_darkens_corners_by_the_ray_angle() {
        let s = Scene::new(CameraModel::from_fov(1024, 768, 76.0), nadir(35.0, -106.0, 3000.0), 0.0);
        let out = s.run(&only(|r| r.vignetting = Some(Vignetting::default())), 100.0, &frame(0.0), 1);
        let centre = out[384 * 1024 + 512];
        assert!((centre - 100.0).abs() < 0.01, "{centre}");
        let want = 100.0 * s.cam.ray(Pixel::new(1023.0, 767.0)).z.powf(1.2);
        let corner = out[1024 * 768 - 1] as f64;
        assert!((corner - want).abs() < 0.05 && (62.0..72.0).contains(&corner), "{corner} vs {want}");
        assert!(out[384 * 1024 + 1023] > out[1024 * 768 - 1], "edge middle brighter than corner");
    }

    #[test]
    fn motion_blur_streaks_along_the_rotation() {
        let cam = CameraModel::from_fov(200, 150, 60.0);
        let s = Scene::new(cam, nadir(35.0, -106.0, 3000.0), 0.0);
        let r = only(|r| r.motion_blur = Some(MotionBlur::default()));
        let (u0, v0) = (100usize, 75usize);
        let mut dot = vec![0f32; s.n()];
        dot[v0 * 200 + u0] = 255.0;
        let ctx = FrameContext { w_cam_rad_s: Vector3::new(0.0, 6.0, 0.0), ..frame(0.0) };
        let mut img = dot.clone();
        apply(&r, &mut img, &s.geo(), &ctx, 1);
        // Expected: the ray of the dot rotated by -/+ half the exposure's rotation.
        let ray = cam.ray(Pixel::new(u0 as f64, v0 as f64));
        let half = UnitQuaternion::from_scaled_axis(ctx.w_cam_rad_s * 0.5 * ctx.exposure_s);
        let a = cam.project(&(half * ray)).unwrap();
        let b = cam.project(&(half.inverse() * ray)).unwrap();
        let len = a.distance_px(&b);
        assert!(len > 4.0 && (a.v - b.v).abs() < 0.1, "horizontal, {len} px");
        let lit: Vec<usize> = (0..200).filter(|&u| img[v0 * 200 + u] > 0.5).collect();
        let extent = (lit[lit.len() - 1] - lit[0]) as f64;
        assert!((extent - len).abs() <= 2.0, "streak {extent} px, expected {len}");
        assert_eq!(lit.len(), lit[lit.len() - 1] - lit[0] + 1, "continuous");
        let total: f32 = img.iter().sum();
        let row: f32 = img[v0 * 200..(v0 + 1) * 200].iter().sum();
        assert!((total / 255.0 - 1.0).abs() < 0.1 && row > 0.9 * total, "{total} {row}");
        // No rotation, or too little to see: untouched.
        for w in [Vector3::zeros(), Vector3::new(0.0, 0.05, 0.0)] {
            let mut img = dot.clone();
            apply(&r, &mut img, &s.geo(), &FrameContext { w_cam_rad_s: w, ..ctx }, 1);
            assert_eq!(img, dot);
        }
    }

    /// Opacity image of the clouds alone (input black, brightness 255).
    fn cloud_alpha(s: &Scene, c: &Clouds, t: f64, seed: u64) -> Vec<f32> {
        let c = Clouds { brightness_dn: 255.0, ..c.clone() };
        let out = s.run(&only(|r| r.clouds = Some(c)), 0.0, &frame(t), seed);
        out.iter().map(|v| v / 255.0).collect()
    }

    #[test]
    fn cloud_fraction_matches_coverage() {
        // About 110 x 85 km of the sheet at ~110 m per pixel.
        let cam = CameraModel::from_fov(1024, 768, 90.0);
        let s = Scene::new(cam, nadir(35.0, -106.0, 60_000.0), 0.0);
        for (coverage, seed) in [(0.25, 1), (0.25, 2), (0.6, 3)] {
            let c = Clouds { coverage, ..Clouds::default() };
            let alpha = cloud_alpha(&s, &c, 0.0, seed);
            let frac = alpha.iter().filter(|&&a| a > 0.45).count() as f64 / alpha.len() as f64;
            assert!((frac - coverage).abs() < 0.05, "seed {seed}: {frac} vs {coverage}");
        }
    }

    #[test]
    fn clouds_are_fixed_to_the_earth() {
        let (lat, lon) = (35.0, -106.0);
        let cam = CameraModel::from_fov(320, 240, 60.0);
        let f = LocalFrame::at(Geodetic::new(lat, lon, 0.0));
        let a = Scene::new(cam, nadir(lat, lon, 20_000.0), 0.0);
        // 6 km east, looking obliquely at the same spot.
        let from = f.to_ecef(trn_geodesy::Enu::new(6000.0, 0.0, 20_000.0));
        let b = Scene::new(cam, CameraPose::look_at(from, f.origin_ecef(), north(lat, lon)), 0.0);
        let c = Clouds { coverage: 0.5, ..Clouds::default() };
        let (alpha_a, alpha_b) = (cloud_alpha(&a, &c, 0.0, 7), cloud_alpha(&b, &c, 0.0, 7));
        let at = |s: &Scene, img: &[f32], p: &Ecef| {
            let px = s.pose.project(&s.cam, p).filter(|px| s.cam.contains(*px))?;
            Some(img[px.v.round() as usize * 320 + px.u.round() as usize])
        };
        let (mut pairs, mut clear, mut cloudy) = (Vec::new(), 0, 0);
        for i in -20..=20 {
            for j in -20..=20 {
                let p = f.to_ecef(trn_geodesy::Enu::new(i as f64 * 150.0, j as f64 * 150.0, 3000.0));
                if let (Some(x), Some(y)) = (at(&a, &alpha_a, &p), at(&b, &alpha_b, &p)) {
                    pairs.push((x, y));
                    clear += (x < 0.1) as usize;
                    cloudy += (x > 0.8) as usize;
                }
            }
        }
        let mad = pairs.iter().map(|(x, y)| (x - y).abs()).sum::<f32>() / pairs.len() as f32;
        assert!(pairs.len() > 1000 && clear > 100 && cloudy > 100, "{} {clear} {cloudy}", pairs.len());
        assert!(mad < 0.03, "mean |difference| {mad}");
        // Another seed, other clouds.
        let other = cloud_alpha(&a, &c, 0.0, 8);
        let d = alpha_a.iter().zip(&other).map(|(x, y)| (x - y).abs()).sum::<f32>() / other.len() as f32;
        assert!(d > 0.2, "{d}");
    }

    #[test]
    fn clipped_fbm_gives_the_same_cover() {
        let field = CloudField::new(&Clouds::default(), 3);
        let f = LocalFrame::at(Geodetic::new(35.0, -106.0, 3000.0));
        let mut early = 0;
        for i in 0..4000 {
            let p = f.to_ecef(trn_geodesy::Enu::new((i % 63) as f64 * 211.0, (i / 63) as f64 * 173.0, 0.0)).0;
            let exact = field.fbm(&p);
            let clipped = field.fbm_clipped(&p, field.lo, field.hi);
            let s = |x: f64| smoothstep(field.lo, field.hi, x);
            assert_eq!(s(exact), s(clipped), "{exact} {clipped}");
            early += (exact != clipped) as usize;
        }
        assert!(early > 1000, "{early}");
    }

    #[test]
    fn clouds_drift_with_the_wind() {
        let c = Clouds { wind_east_m_s: 12.0, wind_north_m_s: -5.0, ..Clouds::default() };
        let field = CloudField::new(&c, 4);
        let f = LocalFrame::at(Geodetic::new(35.0, -106.0, 3000.0));
        let mut moving = 0;
        for i in 0..50 {
            let p = f.to_ecef(trn_geodesy::Enu::new(i as f64 * 97.0, i as f64 * 31.0, 0.0));
            let local = LocalFrame::at(p.to_geodetic());
            let later = p.0 + local.vector_to_ecef(&Vector3::new(12.0, -5.0, 0.0)) * 100.0;
            let p = p.0;
            let (a, b) = (field.alpha(&p, 0.0), field.alpha(&later, 100.0));
            assert!((a - b).abs() < 0.01, "{a} {b}");
            moving += ((field.alpha(&p, 0.0) - field.alpha(&p, 100.0)).abs() > 0.05) as usize;
        }
        assert!(moving > 5);
    }

    #[test]
    fn clouds_hidden_behind_terrain_and_from_below() {
        let c = Clouds { coverage: 1.0, ..Clouds::default() };
        let high = Scene::new(CameraModel::from_fov(64, 48, 60.0), nadir(35.0, -106.0, 10_000.0), 0.0);
        assert!(cloud_alpha(&high, &c, 0.0, 1).iter().all(|&a| a > 0.85));
        // Terrain reaching above the sheet.
        let peak = Scene::new(CameraModel::from_fov(64, 48, 60.0), nadir(35.0, -106.0, 10_000.0), 4000.0);
        assert!(cloud_alpha(&peak, &c, 0.0, 1).iter().all(|&a| a == 0.0));
        // Below the sheet looking down: no clouds (nor the far side of the Earth).
        let low = Scene::new(CameraModel::from_fov(64, 48, 60.0), nadir(35.0, -106.0, 2000.0), 0.0);
        assert!(cloud_alpha(&low, &c, 0.0, 1).iter().all(|&a| a == 0.0));
    }

    #[test]
    fn cords_cross_the_image_and_sway_smoothly() {
        let s = Scene::new(CameraModel::from_fov(320, 240, 60.0), nadir(35.0, -106.0, 3000.0), 0.0);
        let cords = Cords::default();
        let r = only(|r| r.cords = Some(cords.clone()));
        let img = s.run(&r, 200.0, &frame(0.0), 11);
        let dark = |x: f32| x < 110.0;
        assert!(img.iter().any(|&x| x <= 21.0), "cord core at its darkness");
        let mut max_runs = 0;
        for v in (0..240).step_by(10) {
            let row = &img[v * 320..(v + 1) * 320];
            let mut runs = Vec::new();
            let mut start = None;
            for (u, &x) in row.iter().enumerate() {
                match (dark(x), start) {
                    (true, None) => start = Some(u),
                    (false, Some(s0)) => {
                        runs.push(u - s0);
                        start = None;
                    }
                    _ => {}
                }
            }
            max_runs = max_runs.max(runs.len());
            for w in runs {
                // Horizontal width = width / cos(angle), angle < 23 degrees.
                assert!((5..=8).contains(&w), "row {v}: run of {w} px");
            }
        }
        assert_eq!(max_runs, cords.count as usize);
        // Smooth sway: close times barely move, seconds apart moves a lot.
        // At the bottom, 480 px below the pivot, 8 degrees at 2 pi / 4 s: at most ~1.1 px per 10 ms.
        let u_at = |t: f64| cord_lines(&cords, 320, 240, t, 11)[0].u_at(239.0);
        let us: Vec<f64> = (0..=400).map(|k| u_at(k as f64 * 0.01)).collect();
        assert!(us.windows(2).all(|p| (p[1] - p[0]).abs() < 1.2));
        let (lo, hi) = us.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &u| (lo.min(u), hi.max(u)));
        assert!(hi - lo > 100.0, "{lo}..{hi}");
        // Same time, same cords, whatever the frame.
        let again = s.run(&r, 200.0, &FrameContext { index: 9, ..frame(0.0) }, 11);
        assert_eq!(img, again);
    }

    #[test]
    fn validate_names_the_bad_field() {
        assert!(Realism::none().validate().is_ok());
        assert!(Realism::all_on().validate().is_ok());
        let cases: Vec<(Realism, &str)> = vec![
            (
                only(|r| r.clouds = Some(Clouds { coverage: 1.5, ..Default::default() })),
                "realism.clouds.coverage",
            ),
            (
                only(|r| r.photometric = Some(Photometric { gamma: 0.0, ..Default::default() })),
                "photometric.gamma",
            ),
            (
                only(|r| r.haze = Some(Haze { beta_sl_per_km: f64::NAN, ..Default::default() })),
                "haze.beta_sl",
            ),
            (
                only(|r| r.noise = Some(SensorNoise { read_noise_dn: -1.0, ..Default::default() })),
                "read_noise",
            ),
            (only(|r| r.vignetting = Some(Vignetting { strength: -0.1 })), "vignetting.strength"),
            (
                only(|r| r.photometric = Some(Photometric { contrast: -2.0, ..Default::default() })),
                "realism.photometric.contrast",
            ),
            (
                only(|r| r.spectral = Some(Spectral { weights: [0.5, -0.1, 0.2] })),
                "realism.spectral.weights[1]",
            ),
            (only(|r| r.spectral = Some(Spectral { weights: [0.0; 3] })), "realism.spectral.weights (sum)"),
            (
                only(|r| r.brightness_field = Some(BrightnessField { amplitude: 1.5, ..Default::default() })),
                "realism.brightness_field.amplitude",
            ),
            (
                only(|r| {
                    r.brightness_field = Some(BrightnessField { scale_m: f64::NAN, ..Default::default() })
                }),
                "realism.brightness_field.scale_m",
            ),
            (only(|r| r.motion_blur = Some(MotionBlur { samples: 0, ..Default::default() })), "blur.samples"),
            (
                only(|r| r.cords = Some(Cords { sway_period_s: 0.0, ..Default::default() })),
                "cords.sway_period_s",
            ),
        ];
        for (r, name) in cases {
            let err = r.validate().unwrap_err();
            assert!(err.contains(name), "{err}");
        }
    }

    #[test]
    fn validate_refuses_a_bad_sun() {
        let sun = |azimuth_deg: f64, elevation_deg: f64, ambient: f64| {
            only(|r| r.sun = Some(Sun { azimuth_deg, elevation_deg, ambient })).validate()
        };
        for (a, e, amb) in [(135.0, 35.0, 0.25), (-90.0, 90.0, 0.0), (360.0, 0.5, 1.0)] {
            assert!(sun(a, e, amb).is_ok(), "{a} {e} {amb}");
        }
        let cases = [
            ((135.0, 0.0, 0.25), "realism.sun.elevation_deg"),
            ((135.0, -10.0, 0.25), "realism.sun.elevation_deg"),
            ((135.0, 90.5, 0.25), "realism.sun.elevation_deg"),
            ((135.0, f64::NAN, 0.25), "realism.sun.elevation_deg"),
            ((f64::NAN, 35.0, 0.25), "realism.sun.azimuth_deg"),
            ((f64::INFINITY, 35.0, 0.25), "realism.sun.azimuth_deg"),
            ((135.0, 35.0, -0.1), "realism.sun.ambient"),
            ((135.0, 35.0, 1.5), "realism.sun.ambient"),
        ];
        for ((a, e, amb), name) in cases {
            let err = sun(a, e, amb).unwrap_err();
            assert!(err.contains(name), "{a} {e} {amb}: {err}");
        }
        // Defaults from an empty section; unknown fields refused.
        let r: Realism = serde_json::from_str(r#"{"sun": {"elevation_deg": 10}}"#).unwrap();
        assert_eq!(r.sun, Some(Sun { elevation_deg: 10.0, ..Sun::default() }));
        assert!(serde_json::from_str::<Realism>(r#"{"sun": {"zenith_deg": 10}}"#).is_err());
    }

    #[test]
    fn serde_sections_switch_effects_on() {
        let r: Realism =
            serde_json::from_str(r#"{"haze": {}, "clouds": {"coverage": 0.4}, "noise": null}"#).unwrap();
        assert_eq!(r.haze, Some(Haze::default()));
        assert_eq!(r.clouds.as_ref().unwrap().coverage, 0.4);
        assert_eq!(r.clouds.as_ref().unwrap().height_m, 3000.0);
        assert!(r.noise.is_none() && r.photometric.is_none());
        assert_eq!(serde_json::from_str::<Realism>("{}").unwrap(), Realism::none());
        assert!(serde_json::from_str::<Realism>(r#"{"hazy": {}}"#).is_err());
        assert!(serde_json::from_str::<Realism>(r#"{"haze": {"beta": 1}}"#).is_err());
        let back: Realism =
            serde_json::from_str(&serde_json::to_string(&Realism::all_on()).unwrap()).unwrap();
        assert_eq!(back, Realism::all_on());
    }

    /// `cargo test --release -p trn-sim --lib effects::tests::timing -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn timing_all_effects_1024x768() {
        // Oblique from 30 km with the limb and some sky in view.
        let g = Geodetic::new(35.0, -106.0, 30_000.0);
        let f = LocalFrame::at(g);
        let dir = f.vector_to_ecef(&Vector3::new(0.0, 1.0, -0.2));
        let pose =
            CameraPose::look_at(g.to_ecef(), Ecef(g.to_ecef().0 + dir), f.vector_to_ecef(&Vector3::z()));
        let s = Scene::new(CameraModel::from_fov(1024, 768, 76.0), pose, 1500.0);
        let sky = s.range.iter().filter(|r| r.is_nan()).count();
        let mut rng = Rng::new(1);
        let base: Vec<f32> = (0..s.n()).map(|_| rng.range(20.0, 200.0) as f32).collect();
        let ctx = FrameContext { w_cam_rad_s: Vector3::new(0.1, 0.3, 0.05), ..frame(2.0) };
        // Best of several runs: the machine may be shared.
        let pool = rayon::ThreadPoolBuilder::new().num_threads(1).build().unwrap();
        let only_name = std::env::var("EFFECTS_ONLY").ok();
        let sub = |name: &str, r: Realism| {
            if only_name.as_ref().is_some_and(|o| o != name) {
                return;
            }
            let mut best = f64::INFINITY;
            // EFFECTS_REPS=0 vs N under `perf stat` gives cycles per frame on a busy machine.
            let reps = std::env::var("EFFECTS_REPS").ok().and_then(|r| r.parse().ok()).unwrap_or(15);
            for _ in 0..reps {
                let mut img = base.clone();
                let t0 = std::time::Instant::now();
                pool.install(|| apply(&r, &mut img, &s.geo(), &ctx, 3));
                best = best.min(t0.elapsed().as_secs_f64() * 1e3);
            }
            println!("{name:>12}: {best:6.1} ms (1 thread, {sky} sky px)");
        };
        sub("all", Realism::all_on());
        sub("photometric", only(|r| r.photometric = Some(Default::default())));
        sub("haze", only(|r| r.haze = Some(Default::default())));
        sub("noise", only(|r| r.noise = Some(Default::default())));
        sub("vignetting", only(|r| r.vignetting = Some(Default::default())));
        sub("motion_blur", only(|r| r.motion_blur = Some(Default::default())));
        sub("clouds", only(|r| r.clouds = Some(Default::default())));
        sub("cords", only(|r| r.cords = Some(Default::default())));
    }
}
