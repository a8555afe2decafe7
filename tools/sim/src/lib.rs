//! Flight simulator for terrain relative navigation.
//!
//! The main entry is [`simulate`]: from an ortho + DEM and a [`Scenario`]
//! (trajectory, camera, IMU, realism), it writes a flight folder in the
//! project's flight format (`docs/FLIGHT_FORMAT.md`): camera images ray-cast
//! onto the WGS84 terrain ([`render`]), gyro samples whose noise-free
//! integral is the true attitude ([`imu`]), an initial pose guess with a
//! chosen error, and the truth.
//!
//! Parts: [`scene`] (terrain + ortho pyramid, pure; [`bounds`], the
//! terrain's max-height pyramid for the marcher) filled by [`load`]
//! (GDAL), [`trajectory`] and [`imu`] (pure), [`render`] (ray casting),
//! [`effects`] (photometry, haze, noise, vignetting, blur, clouds, cords),
//! [`dem_variant`] (the database's DEM that is not the rendered one),
//! [`sun`] (re-lighting of the terrain, applied by the renderer).
//!
//! ```
//! use trn_geodesy::Geodetic;
//! use trn_sim::trajectory::{BalloonParams, Trajectory, TrajectoryParams};
//!
//! // A balloon's trajectory, deterministic from its seed.
//! let origin = Geodetic::new(37.5, -118.5, 2000.0);
//! let params = TrajectoryParams::Balloon(BalloonParams::default());
//! let a = Trajectory::new(&params, origin, 7).unwrap();
//! let b = Trajectory::new(&params, origin, 7).unwrap();
//! let (sa, sb) = (a.state(10.0), b.state(10.0));
//! assert_eq!(sa.position.0, sb.position.0);
//! assert!(sa.position.to_geodetic().h_m > origin.h_m);
//! ```

pub mod bounds;
pub mod dem_variant;
pub mod effects;
pub mod imu;
pub mod load;
pub mod render;
pub mod rng;
pub mod scenario;
pub mod scene;
pub mod sun;
pub mod trajectory;

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use indicatif::{ProgressBar, ProgressStyle};
use nalgebra::{UnitQuaternion, Vector3};
use rayon::prelude::*;
use serde::Serialize;
use tracing::{info, warn};
use trn_camera::CameraPose;
use trn_flight::{FlightError, Frame, TimedPose};
use trn_geodesy::{Geodetic, LocalFrame};

pub use load::{load_scene, SceneSources};
pub use scenario::Scenario;

use crate::effects::{FrameContext, FrameGeometry};
use crate::rng::Rng;

/// Everything that can stop a simulation; each names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    #[error("{}: {reason}", path.display())]
    Input { path: PathBuf, reason: String },
    #[error("invalid option {option}: {reason}")]
    Option { option: &'static str, reason: String },
    #[error(transparent)]
    Raster(#[from] trn_raster::RasterError),
    #[error(transparent)]
    Flight(#[from] FlightError),
    #[error("{}: {reason}", path.display())]
    Output { path: PathBuf, reason: String },
    #[error("simulation cancelled")]
    Cancelled,
}

/// What `trn simulate` is asked to do.
#[derive(Clone, Debug)]
pub struct SimOptions {
    pub sources: SceneSources,
    pub scenario: PathBuf,
    pub out: PathBuf,
    /// Cut the flight after this many seconds.
    pub max_duration_s: Option<f64>,
}

/// Summary printed after a simulation.
#[derive(Clone, Debug, Serialize)]
pub struct SimReport {
    pub out: PathBuf,
    pub scenario: String,
    pub frames: usize,
    pub duration_s: f64,
    pub imu_samples: usize,
    pub height_start_m: f64,
    pub height_end_m: f64,
    /// Smallest share of a frame's terrain pixels that the ortho covers.
    pub min_coverage: f64,
    /// Smallest share of a frame's pixels that see terrain (not sky).
    pub min_ground: f64,
    /// Mean time to render one frame with its effects (ms).
    pub render_ms_mean: f64,
    pub seconds: f64,
}

impl SimOptions {
    /// Checks the options before any file is read, naming the `trn simulate`
    /// option at fault.
    pub fn check(&self) -> Result<(), SimError> {
        if self.max_duration_s.is_some_and(|d| !(d.is_finite() && d >= 0.0)) {
            return Err(SimError::Option {
                option: "--duration",
                reason: "must be a number of seconds >= 0".into(),
            });
        }
        Ok(())
    }
}

/// Simulates a flight and writes its folder (atomically: a temporary folder
/// next to `out`, renamed over it at the end).
pub fn simulate(opts: &SimOptions, cancel: &AtomicBool) -> Result<SimReport, SimError> {
    let t_start = Instant::now();
    opts.check()?;
    let scenario = Scenario::load(&opts.scenario)?;
    check_out(&opts.out)?;
    let scene = load_scene(&opts.sources, scenario.realism.spectral.as_ref().map(|s| s.normalized()))?;
    let e = &scene.ortho_extent;
    let (lat, lon) = match scenario.origin {
        Some(o) => (o.lat, o.lon),
        None => (0.5 * (e.min_lat_deg + e.max_lat_deg), 0.5 * (e.min_lon_deg + e.max_lon_deg)),
    };
    let ground = scene.terrain.height_m(lat, lon);
    if !ground.is_finite() {
        return Err(SimError::Input {
            path: opts.scenario.clone(),
            reason: format!("origin ({lat:.6}, {lon:.6}) has no DEM height"),
        });
    }
    let origin = Geodetic::new(lat, lon, ground);
    let traj = trajectory::Trajectory::new(&scenario.trajectory, origin, scenario.seed)
        .map_err(|reason| SimError::Input { path: opts.scenario.clone(), reason })?;
    let duration = opts.max_duration_s.map_or(traj.duration_s(), |d| d.min(traj.duration_s()));
    let n_frames = (duration * scenario.frame_rate_hz + 1e-9).floor() as usize + 1;
    // camera.json gets the nominal camera; the images are rendered with the
    // true one, exposed `time_offset_s` after their IMU-clock stamp.
    let camera = scenario.camera.model();
    let true_camera = scenario.camera_error.apply(&camera);
    let exposure_offset_s = scenario.camera_error.time_offset_s;
    let q_imu_cam = scenario.camera.q_cam_imu().inverse();
    let pose_at = |t: f64| {
        let s = traj.state(t);
        TimedPose { t, position: s.position.to_geodetic(), q_ecef_cam: s.q_ecef_imu * q_imu_cam }
    };
    let truth: Vec<TimedPose> = (0..n_frames).map(|k| pose_at(k as f64 / scenario.frame_rate_hz)).collect();
    let imu = imu::synthesize(&traj, &scenario.imu, 0.0, duration, scenario.seed, false);
    let init = perturb(&truth[0], &scenario.init_error, scenario.seed);

    let parent = opts.out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let out_err = |e: std::io::Error| SimError::Output { path: opts.out.clone(), reason: e.to_string() };
    let tmp = tempfile::Builder::new().prefix(".trn-sim-").tempdir_in(parent).map_err(out_err)?;
    let dir = tmp.path();
    std::fs::create_dir(dir.join("images")).map_err(out_err)?;
    let cfg =
        trn_camera::CameraConfig { model: camera, q_cam_imu: trn_camera::quat_to_wxyz(&q_imu_cam.inverse()) };
    trn_flight::write_camera(&dir.join(trn_flight::CAMERA_FILE), &cfg)?;
    trn_flight::write_imu(&dir.join(trn_flight::IMU_FILE), &imu)?;
    trn_flight::write_truth(&dir.join(trn_flight::TRUTH_FILE), &truth)?;
    trn_flight::write_init(&dir.join(trn_flight::INIT_FILE), &init)?;
    let resolved = serde_json::to_string_pretty(&scenario).expect("a scenario serializes");
    std::fs::write(dir.join("scenario.json"), resolved + "\n").map_err(out_err)?;

    let mut renderer = render::Renderer::new(&scene, true_camera);
    if let Some(sun) = &scenario.realism.sun {
        let t0 = Instant::now();
        renderer = renderer.with_illumination(sun::Illumination::new(&scene.terrain, sun));
        info!(
            "sun at azimuth {:.1} deg, elevation {:.1} deg: illumination of {} x {} terrain nodes in {:.0} ms",
            sun.azimuth_deg,
            sun.elevation_deg,
            scene.terrain.heights.rows,
            scene.terrain.heights.cols,
            1e3 * t0.elapsed().as_secs_f64()
        );
    }
    let bar = ProgressBar::new(n_frames as u64);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:40}] {pos}/{len} frames, {elapsed_precise} (eta {eta})")
            .unwrap_or_else(|_| ProgressStyle::default_bar()),
    );
    bar.set_message(scenario.name.clone());
    let (tx, rx) = std::sync::mpsc::sync_channel::<(PathBuf, Vec<u8>)>(4);
    let (w, h) = (camera.width, camera.height);
    // PNG encoding overlaps the next frame's rendering.
    let writer = std::thread::spawn(move || -> Result<(), (PathBuf, String)> {
        for (path, pixels) in rx {
            write_png(&path, w, h, &pixels).map_err(|e| (path.clone(), e))?;
        }
        Ok(())
    });
    let mut frames = Vec::with_capacity(n_frames);
    let (mut min_cov, mut min_ground, mut render_s) = (1.0f64, 1.0f64, 0.0);
    // One frame's buffers, reused.
    let mut img = render::RenderedFrame::default();
    for (k, pose) in truth.iter().enumerate() {
        if cancel.load(Ordering::Relaxed) {
            drop(tx);
            let _ = writer.join();
            return Err(SimError::Cancelled);
        }
        let t0 = Instant::now();
        let exposed = if exposure_offset_s == 0.0 { *pose } else { pose_at(pose.t + exposure_offset_s) };
        let cam_pose = CameraPose::new(exposed.position.to_ecef(), exposed.q_ecef_cam);
        renderer.render_into(&cam_pose, &mut img);
        let geo = FrameGeometry {
            camera: &true_camera,
            pose: &cam_pose,
            camera_height_m: exposed.position.h_m,
            range_m: &img.range_m,
            hit_height_m: &img.hit_height_m,
        };
        let ctx = FrameContext {
            index: k,
            t: pose.t,
            w_cam_rad_s: camera_rate(&pose_at, exposed.t, duration + exposure_offset_s.max(0.0)),
            exposure_s: scenario.camera.exposure_s,
        };
        // Coverage before the effects change the grey levels.
        let (ground_px, covered) = img
            .grey
            .par_iter()
            .zip(&img.range_m)
            .filter(|(_, r)| !r.is_nan())
            .map(|(g, _)| (1usize, (*g != render::NODATA_DN) as usize))
            .reduce(|| (0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
        let t_fx = Instant::now();
        effects::apply(&scenario.realism, &mut img.grey, &geo, &ctx, scenario.seed);
        tracing::debug!("effects {:.1} ms", 1e3 * t_fx.elapsed().as_secs_f64());
        min_ground = min_ground.min(ground_px as f64 / img.grey.len() as f64);
        if ground_px > 0 {
            min_cov = min_cov.min(covered as f64 / ground_px as f64);
        }
        let pixels: Vec<u8> = img.grey.par_iter().map(|v| v.round().clamp(0.0, 255.0) as u8).collect();
        render_s += t0.elapsed().as_secs_f64();
        let name = format!("images/{k:06}.png");
        if tx.send((dir.join(&name), pixels)).is_err() {
            break;
        }
        frames.push(Frame { t: pose.t, image: PathBuf::from(name) });
        bar.inc(1);
    }
    drop(tx);
    bar.finish_and_clear();
    writer
        .join()
        .map_err(|_| SimError::Output { path: opts.out.clone(), reason: "image writer panicked".into() })?
        .map_err(|(path, reason)| SimError::Output { path, reason })?;
    trn_flight::write_frames(&dir.join(trn_flight::FRAMES_FILE), &frames)?;
    if min_cov < 0.9 {
        warn!(
            "some frames see terrain outside the ortho: only {:.0}% covered in the worst frame",
            100.0 * min_cov
        );
    }
    replace_dir(tmp, &opts.out)?;
    let report = SimReport {
        out: opts.out.clone(),
        scenario: scenario.name.clone(),
        frames: frames.len(),
        duration_s: duration,
        imu_samples: imu.len(),
        height_start_m: truth[0].position.h_m,
        height_end_m: truth[truth.len() - 1].position.h_m,
        min_coverage: min_cov,
        min_ground,
        render_ms_mean: 1e3 * render_s / frames.len().max(1) as f64,
        seconds: t_start.elapsed().as_secs_f64(),
    };
    info!(
        "wrote {} frames ({:.1} s, {:.0} m to {:.0} m) to {} in {:.1} s ({:.0} ms per frame)",
        report.frames,
        duration,
        report.height_start_m,
        report.height_end_m,
        opts.out.display(),
        report.seconds,
        report.render_ms_mean
    );
    Ok(report)
}

/// Camera angular rate relative to ECEF, camera frame (rad/s), by central
/// differences of the true attitude.
fn camera_rate(pose_at: &dyn Fn(f64) -> TimedPose, t: f64, duration: f64) -> Vector3<f64> {
    let dt = 1e-3;
    let (t0, t1) = ((t - dt).max(0.0), (t + dt).min(duration));
    if t1 <= t0 {
        return Vector3::zeros();
    }
    let dq = pose_at(t0).q_ecef_cam.inverse() * pose_at(t1).q_ecef_cam;
    dq.scaled_axis() / (t1 - t0)
}

/// The initial guess: the truth moved by exactly the configured errors in
/// seeded random directions.
pub fn perturb(truth: &TimedPose, err: &scenario::InitError, seed: u64) -> TimedPose {
    let mut rng = Rng::stream(seed, "init");
    let az = rng.range(0.0, std::f64::consts::TAU);
    let up = if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
    let frame = LocalFrame::at(truth.position);
    let offset =
        trn_geodesy::Enu::new(err.horizontal_m * az.sin(), err.horizontal_m * az.cos(), up * err.vertical_m);
    let position = frame.to_ecef(offset).to_geodetic();
    // Uniform axis on the sphere.
    let z = rng.range(-1.0, 1.0);
    let phi = rng.range(0.0, std::f64::consts::TAU);
    let r = (1.0 - z * z).sqrt();
    let axis = Vector3::new(r * phi.cos(), r * phi.sin(), z);
    let dq = UnitQuaternion::from_scaled_axis(axis * err.attitude_deg.to_radians());
    TimedPose { t: truth.t, position, q_ecef_cam: dq * truth.q_ecef_cam }
}

fn write_png(path: &Path, w: u32, h: u32, pixels: &[u8]) -> Result<(), String> {
    use image::codecs::png::{CompressionType, FilterType, PngEncoder};
    use image::ImageEncoder;
    let file = std::fs::File::create(path).map_err(|e| e.to_string())?;
    let enc =
        PngEncoder::new_with_quality(std::io::BufWriter::new(file), CompressionType::Fast, FilterType::Sub);
    enc.write_image(pixels, w, h, image::ExtendedColorType::L8).map_err(|e| e.to_string())
}

/// `out` may be replaced only when it is missing, empty, or a flight folder.
fn check_out(out: &Path) -> Result<(), SimError> {
    if !out.exists() {
        return Ok(());
    }
    let bad = |reason: &str| SimError::Output { path: out.into(), reason: reason.into() };
    if !out.is_dir() {
        return Err(bad("exists and is not a folder; refusing to replace it"));
    }
    let empty = std::fs::read_dir(out).map_err(|e| bad(&e.to_string()))?.next().is_none();
    if !empty && !out.join(trn_flight::FRAMES_FILE).exists() {
        return Err(bad("exists and is not a flight folder (no frames.csv); refusing to replace it"));
    }
    Ok(())
}

fn replace_dir(tmp: tempfile::TempDir, out: &Path) -> Result<(), SimError> {
    let err = |e: std::io::Error| SimError::Output { path: out.into(), reason: e.to_string() };
    if out.exists() {
        let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        let old = tempfile::Builder::new().prefix(".trn-old-").tempdir_in(parent).map_err(err)?;
        let old_path = old.path().join("flight");
        std::fs::rename(out, &old_path).map_err(err)?;
        std::fs::rename(tmp.keep(), out).map_err(err)?;
        drop(old);
    } else {
        std::fs::rename(tmp.keep(), out).map_err(err)?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bad_duration_is_named_before_any_file_is_read() {
        let opts = |d: f64| SimOptions {
            sources: SceneSources {
                ortho: "no-such-ortho.tif".into(),
                ortho_bands: None,
                dem: trn_raster::DemInputs::new(vec!["no-such-dem.tif".into()]),
            },
            scenario: "no-such-scenario.json".into(),
            out: "out".into(),
            max_duration_s: Some(d),
        };
        for d in [-1.0, f64::NAN, f64::INFINITY] {
            let e = simulate(&opts(d), &AtomicBool::new(false)).unwrap_err();
            assert!(e.to_string().contains("--duration"), "{e}");
        }
        // A good one gets as far as the files.
        let e = simulate(&opts(10.0), &AtomicBool::new(false)).unwrap_err();
        assert!(e.to_string().contains("no-such-scenario.json"), "{e}");
    }
}
