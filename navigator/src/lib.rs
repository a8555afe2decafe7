//! Terrain relative navigation, frame by frame.
//!
//! The main type is [`Navigator`]: for each image it propagates the
//! attitude with the gyro ([`propagate`]), predicts which landmarks are in
//! view from the pose guess ([`trn_view::footprint`]: IBAL's corner projection
//! with horizon handling and angle filter), queries them from a
//! [`LandmarkSource`], warps them into the image ([`predict`]), correlates
//! them (NCC), and solves the pose with P3P RANSAC and PnP refinement
//! (`trn-vision`), then accepts or rejects the fix. With the inertial filter
//! ([`ins`]) an accepted frame updates it tightly, a frame refused as a fix
//! can still update it with the matches that agree with its prediction, the
//! landmarks found in two consecutive images update its velocity, gyro bias
//! and time offset through the motion in between ([`track`]), and the
//! camera's focal length is estimated in flight ([`calibration`]).
//! [`run_flight`] drives it over a flight folder and writes `poses.csv` and
//! `matches.csv`.
//!
//! ```
//! use nalgebra::{UnitQuaternion, Vector3};
//! use trn_flight::ImuSample;
//! use trn_navigator::propagate::propagate;
//!
//! // The gyro carries the attitude between images: 10 deg/s about z for 1 s.
//! let rate = Vector3::new(0.0, 0.0, 10f64.to_radians());
//! let imu: Vec<ImuSample> =
//!     (1..=100).map(|k| ImuSample { t: k as f64 * 0.01, w_imu_rad_s: rate, f_imu_m_s2: None }).collect();
//! let q = propagate(UnitQuaternion::identity(), 0.0, 1.0, &imu);
//! // Apart from the Earth's rotation, which propagate also removes (15 deg/h).
//! assert!((q.angle().to_degrees() - 10.0).abs() < 0.01, "{}", q.angle().to_degrees());
//! ```

pub mod attitude;
pub mod calibration;
pub mod image;
pub mod ins;
pub mod nav;
pub mod picture;
pub mod predict;
pub mod propagate;
pub mod track;

use std::path::{Path, PathBuf};

use ::image::ImageEncoder;

use nalgebra::{Matrix3, Vector3};
use trn_flight::{FixStatus, Flight, MatchRecord, NavRecord, PoseCovariance, TimedPose};

pub use nav::{FilterMode, FilterPose, HeightGate, HeightReference, NavParams, Navigator, Rejection};
pub use trn_view::{DbSource, LandmarkSource, SourceError};

/// Errors of a navigation run; each names the file at fault.
#[derive(Debug, thiserror::Error)]
pub enum NavError {
    #[error(transparent)]
    Flight(#[from] trn_flight::FlightError),
    #[error("{}: {reason}", path.display())]
    Image { path: PathBuf, reason: String },
    #[error("{0}")]
    Source(#[from] SourceError),
    #[error("{}: {reason}", path.display())]
    Picture { path: PathBuf, reason: String },
    #[error("invalid option {option}: {reason}")]
    Option { option: &'static str, reason: String },
    /// The navigator's pose stopped being a number (a defect: every input
    /// passed its checks); nothing is written.
    #[error("the navigator's pose at t {t:.3} s is not finite (a defect of trn navigate: please report it with the flight); nothing written")]
    NotFinite { t: f64 },
}

/// What `trn navigate` is asked to do.
#[derive(Clone, Debug)]
pub struct RunOptions {
    /// Images per second taken from the flight (`None`: every image).
    pub rate_hz: Option<f64>,
    pub params: NavParams,
    /// Write a match picture per processed frame here ([`picture`]), named
    /// after the frame's image (`.png`).
    pub matches_dir: Option<PathBuf>,
    /// Also output the inertial filter's pose at every IMU sample
    /// ([`RunOutput::imu_rate`]; needs the filter).
    pub imu_rate: bool,
}

impl RunOptions {
    /// Checks every option before any work, naming the `trn navigate` option
    /// at fault (units as the command line gives them).
    pub fn check(&self) -> Result<(), NavError> {
        let bad =
            |option: &'static str, reason: &str| Err(NavError::Option { option, reason: reason.into() });
        let positive = |v: f64| v.is_finite() && v > 0.0;
        let non_negative = |v: f64| v.is_finite() && v >= 0.0;
        let p = &self.params;
        if self.rate_hz.is_some_and(|r| !positive(r)) {
            return bad("--rate", "must be images per second > 0");
        }
        if !(p.alpha_max_deg > 0.0 && p.alpha_max_deg < 90.0) {
            return bad("--alpha-max", "must be an angle in (0, 90) degrees");
        }
        if p.min_inliers < 4 {
            return bad("--min-inliers", "must be at least 4");
        }
        if p.max_landmarks < 4 {
            return bad("--max-landmarks", "must be at least 4");
        }
        if !positive(p.acquisition_budget_g) {
            return bad("--acquisition-budget", "must be G multiply-adds > 0");
        }
        if !positive(p.init_sigma_m) {
            return bad("--init-sigma-m", "must be metres > 0");
        }
        if !(positive(p.init_sigma_deg) && p.init_sigma_deg <= 90.0) {
            return bad("--init-sigma-deg", "must be degrees in (0, 90]");
        }
        if !positive(p.gyro_arw_deg_sqrt_s) {
            return bad("--gyro-arw", "must be deg/sqrt(h) > 0");
        }
        if !positive(p.gyro_bias_deg_s) {
            return bad("--gyro-bias", "must be deg/h > 0");
        }
        if !(p.gyro_max_jump_deg_s.is_finite() && p.gyro_max_jump_deg_s >= 0.0) {
            return bad("--gyro-max-jump", "must be deg/s >= 0 (0: never doubted)");
        }
        if !(p.accel_max_jump_m_s2.is_finite() && p.accel_max_jump_m_s2 >= 0.0) {
            return bad("--accel-max-jump", "must be m/s^2 >= 0 (0: never doubted)");
        }
        if !positive(p.gyro_range_deg_s) {
            return bad("--gyro-range", "must be deg/s > 0");
        }
        if !positive(p.accel_range_m_s2) {
            return bad("--accel-range", "must be m/s^2 > 0");
        }
        if !(p.imu_gap_doubt_deg_s_sqrt_s.is_finite() && p.imu_gap_doubt_deg_s_sqrt_s >= 0.0) {
            return bad("--imu-gap-doubt", "must be deg/s/sqrt(s) >= 0 (0: none)");
        }
        for (option, v) in [
            ("--init-velocity-sigma", p.init_velocity_sigma_m_s),
            ("--accel-bias", p.accel_bias_m_s2),
            ("--map-tau", p.map_tau_s),
            ("--track-sigma", p.track.sigma_px),
            ("--ransac-threshold", p.ransac_threshold_px),
        ] {
            if !positive(v) {
                return bad(option, "must be a number > 0");
            }
        }
        if !non_negative(p.time_offset_sigma_s) {
            return bad("--time-offset-sigma", "must be milliseconds >= 0");
        }
        if !p.map_sigma_m.is_none_or(non_negative) {
            return bad("--map-sigma", "must be metres >= 0");
        }
        if !p.map_att_sigma_deg.is_none_or(|d| non_negative(d) && d <= 10.0) {
            return bad("--map-att-sigma", "must be degrees within 0..10");
        }
        if !non_negative(p.map_view_sigma_px) {
            return bad("--map-view-sigma", "must be pixels >= 0 (0: not modelled)");
        }
        if let Some(c) = &p.calibration {
            for (option, v) in [
                ("--focal-sigma", c.focal_sigma_rel),
                ("--principal-point-sigma", c.principal_sigma_px),
                ("--calibration-frame-sigma", c.max_frame_sigma_rel),
            ] {
                if !positive(v) {
                    return bad(option, "must be a number > 0");
                }
            }
            if !(non_negative(c.k1_sigma) && c.k1_sigma <= 1.0) {
                return bad("--k1-sigma", "must be a number in 0..=1");
            }
            if !non_negative(c.landmark_height_sigma_m) {
                return bad("--landmark-height-sigma", "must be metres >= 0");
            }
        }
        if self.imu_rate && p.filter == FilterMode::Fixes {
            return bad("--imu-rate", "needs the inertial filter (--filter tight or loose)");
        }
        Ok(())
    }
}

/// Summary of a run.
#[derive(Clone, Debug, serde::Serialize)]
pub struct RunReport {
    pub frames: usize,
    pub processed: usize,
    pub fixes: usize,
    /// Solutions rejected, by reason (their frames are `propagated`).
    pub rejected: RejectedCounts,
    pub median_ms: f64,
    /// Frames without a fix whose matches updated the tight filter through
    /// its prediction (`NavParams::prior_gated_update`).
    pub prior_gated_updates: usize,
    /// Frames whose landmarks, found in the image before too, updated the
    /// tight filter through the motion in between (`NavParams::track_update`).
    pub track_updates: usize,
    /// Frames without a fix that doubted the filter's pose, after a fix and
    /// four misses since it (frames whose matches did not agree): its
    /// uncertainty grown, the next fix a restart.
    pub doubted_frames: usize,
    /// Of the fixes rejected as inconsistent, those of a narrow view (inliers
    /// over fewer than `NavParams::doubt_min_cells` cells) that did not
    /// doubt the filter: none before them since the last accepted fix, or
    /// the one before said otherwise.
    pub narrow_inconsistent: usize,
    /// Frames whose image could not be used (their pose carried, status
    /// `propagated`), in time order.
    pub skipped_images: Vec<SkippedImage>,
    /// Stretches of `imu.csv` without samples, longer than
    /// [`IMU_GAP_FACTOR`] times its median interval.
    pub imu_gaps: Vec<propagate::ImuGap>,
    /// The frames' time before `imu.csv`'s first sample or after its last
    /// (none when the log covers them): the attitude held, doubted as in a
    /// gap from the log's edge.
    pub imu_uncovered: Vec<propagate::ImuGap>,
    /// Samples of `imu.csv` beyond the sensors' range (`--gyro-range`,
    /// `--accel-range`), left out (`None`: none).
    pub imu_out_of_range: Option<OutOfRangeReport>,
    /// Gyro rate jumps doubted (`--gyro-max-jump`): by the inertial filter,
    /// or without it (`--filter fixes`) in the attitude's prediction.
    pub gyro_jumps: usize,
    /// Frames that found their landmarks with the gyro's jumps since the
    /// fix before undone, as glitches, after their own search did not
    /// stand: the inertial filter then takes the undo; with `--filter
    /// fixes`, the fix restarts the pose (see `trn navigate`, When the
    /// sensors fail).
    pub gyro_jumps_undone: usize,
    /// Accelerometer jumps the inertial filter doubted (`--accel-max-jump`).
    pub accel_jumps: usize,
    /// Fixes after which the inertial filter's map offset, estimated beyond
    /// its prior, was restarted ([`nav::MAP_DOUBT_CHI2`]).
    pub map_doubts: usize,
    /// The largest chi-square of that map offset in its prior at an
    /// accepted fix (how near [`nav::MAP_DOUBT_CHI2`] the flight came).
    pub map_chi2_max: f64,
    /// The camera's self-calibration at the end (`None`: off).
    pub calibration: Option<CalibrationReport>,
    /// The camera-IMU time offset the inertial filter ends with (`None`:
    /// no inertial filter): an image stamped `t` was exposed at `t + this`.
    pub time_offset: Option<TimeOffsetReport>,
    /// The gyro bias the inertial filter ends with (deg/h, IMU frame).
    pub gyro_bias_imu_deg_h: Option<AxesReport>,
}

/// IMU samples left out as beyond the sensors' range.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct OutOfRangeReport {
    pub samples: usize,
    /// The first and the last of them (s).
    pub first_t: f64,
    pub last_t: f64,
}

/// A vector estimate and its per-axis sigmas (the unit and frame in the
/// field's name).
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct AxesReport {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub sigma_x: f64,
    pub sigma_y: f64,
    pub sigma_z: f64,
}

impl AxesReport {
    /// `value` and its covariance `cov`, both scaled by `scale` (a unit change).
    fn scaled(value: &Vector3<f64>, cov: &Matrix3<f64>, scale: f64) -> Self {
        let v = value * scale;
        let c = cov * (scale * scale);
        let sigma = |i: usize| c[(i, i)].max(0.0).sqrt();
        Self { x: v.x, y: v.y, z: v.z, sigma_x: sigma(0), sigma_y: sigma(1), sigma_z: sigma(2) }
    }
}

/// The inertial filter's camera-IMU time offset (ms).
#[derive(Clone, Debug, serde::Serialize)]
pub struct TimeOffsetReport {
    pub offset_ms: f64,
    pub sigma_ms: f64,
}

/// The self-calibration's estimate at the end of a run.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CalibrationReport {
    /// Relative focal length error of camera.json (true = nominal * (1 + this)).
    pub focal_rel: f64,
    pub focal_sigma_rel: f64,
    /// True minus camera.json's principal point (pixels), and its sigmas.
    pub principal_du_px: f64,
    pub principal_dv_px: f64,
    pub principal_sigma_px: [f64; 2],
    /// True minus camera.json's radial coefficient k1, and its sigma (0 when
    /// not estimated).
    pub k1: f64,
    pub k1_sigma: f64,
    /// Accepted fixes that updated it, were refused by its gate, or were
    /// too weak to use.
    pub frames_used: usize,
    pub frames_refused: usize,
    pub frames_weak: usize,
}

impl CalibrationReport {
    pub fn of(f: &calibration::CalibrationFilter) -> Self {
        let (c, p) = (f.correction(), f.covariance());
        Self {
            focal_rel: c.focal_rel,
            focal_sigma_rel: p[(0, 0)].max(0.0).sqrt(),
            principal_du_px: c.principal_du_px,
            principal_dv_px: c.principal_dv_px,
            principal_sigma_px: [p[(1, 1)].max(0.0).sqrt(), p[(2, 2)].max(0.0).sqrt()],
            k1: c.k1,
            k1_sigma: p[(3, 3)].max(0.0).sqrt(),
            frames_used: f.updates,
            frames_refused: f.refused,
            frames_weak: f.weak,
        }
    }
}

/// Rejected solutions of a run, by [`Rejection`].
#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct RejectedCounts {
    pub few_inliers: usize,
    pub inlier_share: usize,
    /// Acquisitions whose inliers were too small a share of the templates
    /// searched for.
    pub found_share: usize,
    /// Inliers on a line or in a cluster.
    pub spread: usize,
    pub height: usize,
    /// Image-only poses the inertial filter's gate refused.
    pub inconsistent: usize,
    /// Acquisitions found in a tile away from the guess, held until the
    /// next frame confirms them.
    pub unconfirmed: usize,
    /// Acquisitions whose inliers held too narrow a view (not counted in
    /// `spread`), held until the next frame, searched around them, confirms
    /// them.
    pub narrow_held: usize,
}

/// An interval between IMU samples longer than this many times the log's
/// median is reported as a gap ([`propagate::imu_gaps`]).
pub const IMU_GAP_FACTOR: f64 = 5.0;

/// A frame whose image could not be used.
#[derive(Clone, Debug, serde::Serialize)]
pub struct SkippedImage {
    /// The frame's time (s).
    pub t: f64,
    pub image: PathBuf,
    /// What was wrong with it.
    pub reason: String,
}

/// [`load_grey`], checked against the camera's size.
fn load_frame_image(path: &Path, camera: &trn_camera::CameraModel) -> Result<image::GreyImage, NavError> {
    let img = load_grey(path)?;
    if img.width != camera.width as usize || img.height != camera.height as usize {
        return Err(NavError::Image {
            path: path.into(),
            reason: format!(
                "{}x{} pixels, but camera.json says {}x{}",
                img.width, img.height, camera.width, camera.height
            ),
        });
    }
    Ok(img)
}

/// Reads a flight image as grey levels (RGB by Rec. 601 luma).
pub fn load_grey(path: &Path) -> Result<image::GreyImage, NavError> {
    let img =
        ::image::open(path).map_err(|e| NavError::Image { path: path.into(), reason: e.to_string() })?;
    let g = img.to_luma32f();
    let (w, h) = g.dimensions();
    Ok(image::GreyImage {
        width: w as usize,
        height: h as usize,
        data: g.into_raw().iter().map(|v| v * 255.0).collect(),
    })
}

/// Writes a picture as PNG (temp file, then rename).
fn write_picture(path: &Path, pic: &::image::RgbImage) -> Result<(), NavError> {
    let err = |reason: String| NavError::Picture { path: path.into(), reason };
    let mut png = Vec::new();
    ::image::codecs::png::PngEncoder::new_with_quality(
        &mut png,
        ::image::codecs::png::CompressionType::Fast,
        ::image::codecs::png::FilterType::Sub,
    )
    .write_image(pic.as_raw(), pic.width(), pic.height(), ::image::ExtendedColorType::Rgb8)
    .map_err(|e| err(e.to_string()))?;
    trn_flight::write_atomic(path, |w| w.write_all(&png)).map_err(|e| err(e.to_string()))
}

/// Whether every number of a pose is finite.
fn finite_pose(p: &TimedPose) -> bool {
    let g = &p.position;
    [g.lat_deg, g.lon_deg, g.h_m].iter().chain(p.q_ecef_cam.coords.iter()).all(|v| v.is_finite())
}

/// What a run produced: the rows of `poses.csv`, `matches.csv` and
/// `covariance.csv`.
pub struct RunOutput {
    pub records: Vec<NavRecord>,
    pub matches: Vec<MatchRecord>,
    pub covariances: Vec<PoseCovariance>,
    /// With [`RunOptions::imu_rate`]: the filter's pose and covariance at
    /// every IMU sample between the first and the last processed frame
    /// (status `propagated`) and at each processed frame (its status).
    pub imu_rate: Vec<(NavRecord, PoseCovariance)>,
    pub report: RunReport,
}

/// Navigates a whole flight.
pub fn run_flight(
    flight: &Flight,
    source: &dyn LandmarkSource,
    opts: &RunOptions,
    mut progress: impl FnMut(usize),
) -> Result<RunOutput, NavError> {
    opts.check()?;
    let mut nav = Navigator::new(source, &flight.camera, &flight.imu, &flight.init, opts.params.clone())?;
    let mut records = Vec::new();
    let mut matches = Vec::new();
    let mut covariances = Vec::new();
    let mut imu_rate = Vec::new();
    let mut gated = 0;
    let mut tracked = 0;
    let row = |p: FilterPose, status: FixStatus| {
        let position = p.pose.position.to_geodetic();
        let record = NavRecord {
            pose: TimedPose { t: p.t, position, q_ecef_cam: p.pose.q_ecef_cam },
            status,
            inliers: 0,
            matches: 0,
            ms: 0.0,
        };
        (record, PoseCovariance { t: p.t, position, ecef: p.covariance })
    };
    let mut next_due = f64::NEG_INFINITY;
    let mut rejected = RejectedCounts::default();
    let imu_out_of_range = match nav.imu_out_of_range() {
        [] => None,
        out => Some(OutOfRangeReport { samples: out.len(), first_t: out[0], last_t: out[out.len() - 1] }),
    };
    if let Some(o) = &imu_out_of_range {
        tracing::warn!(
            "imu.csv: {} sample(s) beyond the sensors' range (--gyro-range {} deg/s, --accel-range {} m/s^2), from t {:.4} to {:.4} s: no measurements, left out",
            o.samples,
            opts.params.gyro_range_deg_s,
            opts.params.accel_range_m_s2,
            o.first_t,
            o.last_t
        );
    }
    let imu_gaps = propagate::imu_gaps(nav.imu(), IMU_GAP_FACTOR);
    let imu_uncovered = match (flight.frames.first(), flight.frames.last()) {
        (Some(first), Some(last)) => propagate::uncovered(nav.imu(), first.t, last.t),
        _ => Vec::new(),
    };
    for u in &imu_uncovered {
        tracing::warn!(
            "imu.csv has no sample from t {:.3} to {:.3} s, where the flight has frames: the attitude turns there at no rate (before the log) or at the gyro's mean over its last second (after it), the fixes learning the rate's error (--imu-gap-doubt)",
            u.from_t,
            u.to_t
        );
    }
    if let Some(longest) = imu_gaps.iter().max_by(|a, b| (a.to_t - a.from_t).total_cmp(&(b.to_t - b.from_t)))
    {
        tracing::warn!(
            "imu.csv: {} gap(s) without samples, the longest {:.3} s from t {:.3} s: crossed on rates interpolated between the samples either side, the attitude doubted (--imu-gap-doubt)",
            imu_gaps.len(),
            longest.to_t - longest.from_t,
            longest.from_t
        );
    }
    let mut skipped = Vec::new();
    let mut first_error = None;
    let mut images_read = 0;
    for (i, frame) in flight.frames.iter().enumerate() {
        progress(i);
        // Rate downsampling, except right after a rejected fix.
        if frame.t + 1e-6 < next_due {
            continue;
        }
        let path = flight.image_path(frame);
        let img = match load_frame_image(&path, &flight.camera.model) {
            Ok(img) => img,
            Err(e) => {
                // One bad image is a frame without a picture; a flight
                // without one readable image is an error (below).
                if skipped.len() < 5 {
                    tracing::warn!("{e}: frame t {:.3} s carried without it", frame.t);
                } else {
                    tracing::debug!("{e}: frame t {:.3} s carried without it", frame.t);
                }
                if let NavError::Image { path, reason } = &e {
                    skipped.push(SkippedImage { t: frame.t, image: path.clone(), reason: reason.clone() });
                }
                first_error.get_or_insert(e);
                if opts.imu_rate && !records.is_empty() {
                    imu_rate
                        .extend(nav.poses_until(frame.t).into_iter().map(|p| row(p, FixStatus::Propagated)));
                }
                let record = nav.carry_without_image(frame.t);
                if opts.imu_rate {
                    imu_rate.extend(nav.filter_pose(frame.t).map(|p| row(p, FixStatus::Propagated)));
                }
                if !finite_pose(&record.pose) {
                    return Err(NavError::NotFinite { t: frame.t });
                }
                records.push(record);
                next_due = f64::NEG_INFINITY;
                continue;
            }
        };
        images_read += 1;
        let picture_of = opts.matches_dir.as_ref().map(|dir| (dir, img.clone()));
        if opts.imu_rate && !records.is_empty() {
            imu_rate.extend(nav.poses_until(frame.t).into_iter().map(|p| row(p, FixStatus::Propagated)));
        }
        let r = nav.process(frame.t, img);
        if opts.imu_rate {
            imu_rate.extend(nav.filter_pose(frame.t).map(|p| row(p, r.record.status)));
        }
        if let Some((dir, img)) = picture_of {
            let name =
                frame.image.file_stem().map(|s| s.to_os_string()).unwrap_or_else(|| format!("{i:06}").into());
            let path = dir.join(name).with_extension("png");
            write_picture(&path, &picture::draw_matches(&img, &r.matches, &r.guess_px))?;
        }
        next_due = match (r.record.status, opts.rate_hz) {
            (FixStatus::Fix, Some(rate)) => frame.t + 1.0 / rate,
            _ => f64::NEG_INFINITY,
        };
        match r.rejection {
            Some(Rejection::FewInliers { .. }) => rejected.few_inliers += 1,
            Some(Rejection::InlierShare { .. }) => rejected.inlier_share += 1,
            Some(Rejection::FoundShare { .. }) => rejected.found_share += 1,
            Some(Rejection::Spread { .. }) if r.held => rejected.narrow_held += 1,
            Some(Rejection::Spread { .. }) => rejected.spread += 1,
            Some(Rejection::Height { .. }) => rejected.height += 1,
            Some(Rejection::Inconsistent { .. }) => rejected.inconsistent += 1,
            Some(Rejection::Unconfirmed { .. }) => rejected.unconfirmed += 1,
            None => {}
        }
        gated += usize::from(r.gated_matches > 0);
        tracked += usize::from(r.tracked > 0);
        if !finite_pose(&r.record.pose) {
            return Err(NavError::NotFinite { t: frame.t });
        }
        records.push(r.record);
        matches.extend(r.matches);
        covariances.extend(r.covariance);
    }
    if images_read == 0 {
        if let Some(e) = first_error {
            return Err(e);
        }
    }
    let mut ms: Vec<f64> = records.iter().map(|r| r.ms).collect();
    ms.sort_by(f64::total_cmp);
    let report = RunReport {
        frames: flight.frames.len(),
        processed: records.len(),
        fixes: records.iter().filter(|r| r.status == FixStatus::Fix).count(),
        rejected,
        median_ms: ms.get(ms.len() / 2).copied().unwrap_or(0.0),
        prior_gated_updates: gated,
        track_updates: tracked,
        doubted_frames: nav.doubted_frames(),
        narrow_inconsistent: nav.narrow_inconsistent(),
        skipped_images: skipped,
        imu_gaps,
        imu_uncovered,
        imu_out_of_range,
        gyro_jumps: nav.gyro_jumps(),
        gyro_jumps_undone: nav.gyro_jumps_undone(),
        accel_jumps: nav.inertial().map_or(0, |f| f.accel_jumps()),
        map_doubts: nav.map_doubts(),
        map_chi2_max: nav.map_chi2_max(),
        calibration: nav.calibration().map(CalibrationReport::of),
        time_offset: nav.inertial().map(|f| {
            let (offset, sigma) = f.time_offset();
            TimeOffsetReport { offset_ms: offset * 1e3, sigma_ms: sigma * 1e3 }
        }),
        gyro_bias_imu_deg_h: nav.inertial().map(|f| {
            let (b, cov) = f.gyro_bias_with_covariance();
            AxesReport::scaled(&b, &cov, 1f64.to_degrees() * 3600.0)
        }),
    };
    Ok(RunOutput { records, matches, covariances, imu_rate, report })
}

/// Templates for the unit tests of several modules.
#[cfg(test)]
pub(crate) mod test_fixtures {
    use trn_geodesy::Geodetic;
    use trn_landmark::{GeoBox, Template, TemplateQuality, TerrainPatch};

    /// A square template of `size` pixels at `gsd_m` centred at `center`,
    /// over `terrain`, with a texture that passes every quality test.
    pub fn template(
        id: i64,
        center: Geodetic,
        gsd_m: f64,
        size: u32,
        terrain: TerrainPatch,
        pixels: Vec<u8>,
    ) -> Template {
        Template {
            id,
            level: 0,
            gsd_m,
            width_px: size,
            height_px: size,
            center,
            footprint: GeoBox::new(0.0, 0.0, 0.0, 0.0),
            terrain,
            quality: TemplateQuality {
                shi_tomasi: 10.0,
                contrast_std: 30.0,
                second_peak_ncc: 0.2,
                shading_share: 0.0,
            },
            source: 0,
            lighting: 0,
            pixels,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn defaults() -> RunOptions {
        RunOptions { rate_hz: None, params: NavParams::default(), matches_dir: None, imu_rate: false }
    }

    fn refused(o: &RunOptions) -> &'static str {
        match o.check() {
            Err(NavError::Option { option, .. }) => option,
            other => panic!("accepted: {other:?}"),
        }
    }

    #[test]
    fn options_are_checked_and_named() {
        assert!(defaults().check().is_ok());
        let mut o = defaults();
        o.rate_hz = Some(0.0);
        assert_eq!(refused(&o), "--rate");
        let mut o = defaults();
        o.params.gyro_bias_deg_s = f64::NAN;
        assert_eq!(refused(&o), "--gyro-bias");
        let mut o = defaults();
        o.params.calibration.as_mut().expect("self-calibration is on by default").focal_sigma_rel = 0.0;
        assert_eq!(refused(&o), "--focal-sigma");
        let mut o = defaults();
        o.params.calibration.as_mut().expect("self-calibration is on by default").k1_sigma = -0.001;
        assert_eq!(refused(&o), "--k1-sigma");
        let mut o = defaults();
        (o.imu_rate, o.params.filter) = (true, FilterMode::Fixes);
        assert_eq!(refused(&o), "--imu-rate");
        o.params.filter = FilterMode::Loose;
        assert!(o.check().is_ok());
    }
}
