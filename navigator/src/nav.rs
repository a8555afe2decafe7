//! The per-frame pipeline: pose guess (gyro), footprint, landmark query,
//! prediction, correlation, RANSAC + PnP, acceptance.

use std::collections::HashMap;
use std::time::Instant;

use nalgebra::{
    DMatrix, DVector, Matrix2, Matrix3, Matrix6, SMatrix, UnitQuaternion, Vector2, Vector3, Vector6,
};
use tracing::{debug, info};
use trn_camera::{CameraConfig, CameraModel, CameraPose, Pixel};
use trn_flight::{FixStatus, ImuSample, MatchRecord, NavRecord, PoseCovariance, TimedPose};
use trn_geodesy::Ecef;
use trn_landmark::lighting::SunLight;
use trn_landmark::Template;
use trn_vision::calib::{frame_calibration, perturb_pose, FrameCalibration};
use trn_vision::ncc::{self, ImageView, NccParams};
use trn_vision::pnp::{
    project_with_jacobian, refine_pose, refine_pose_weighted, rotation_vector, AttitudePrior, PosePrior,
    RefineOptions, Refined,
};
use trn_vision::ransac::{ransac_p3p, RansacParams};

use crate::attitude::{AttitudeFilter, FixAttitude, FixRate, GyroErrors};
use crate::calibration::{CalibrationFilter, CalibrationParams, CarriedIntrinsics};
use crate::image::{GreyImage, Pyramid, UndistortLut};
use crate::ins::{
    doubt_factor, JumpTurn, JumpWatch, GYRO_JUMP_MAX_ANGLE_DEG, GYRO_JUMP_MAX_S, HELD_RATE_MAX_DEG_S,
    IMU_GAP_MAX_ANGLE_DEG,
};
use crate::ins::{InsErrors, InsFilter, InsInit, InsState, IntrinsicsSensitivity, FOCAL};
use crate::predict::{predict, Predicted};
use crate::propagate::{
    ends_gap, for_each_segment, propagate_with_bias, turn_over, unmeasured_attitude_variance, WalkStarts,
};
use crate::track::{track_update, TrackAnchor, TrackParams, TrackPoint};
use trn_view::footprint::{footprint, Footprint, FootprintParams};
use trn_view::DbLevel;
use trn_view::LandmarkSource;

/// How the images' landmark matches are fused with the inertial sensors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum FilterMode {
    /// The inertial filter ([`crate::ins`]) updated with the matches
    /// themselves: the refinement of each frame's inliers with the
    /// filter's predicted pose as its prior.
    Tight,
    /// The inertial filter updated with each frame's image-only pose and
    /// its covariance (loosely coupled).
    Loose,
    /// No inertial filter: each frame's PnP pose is the output; the gyro
    /// carries the attitude between frames ([`crate::attitude`]) and the
    /// velocity is the slope of the last fixes. Time no gyro sample
    /// measures doubts the attitude
    /// ([`crate::propagate::unmeasured_attitude_variance`]), a gyro's jump
    /// its angle, a run of misses the pose, as the inertial filter's; the
    /// accelerometer is not read.
    Fixes,
}

/// Navigator settings (the `trn navigate` options).
#[derive(Clone, Debug)]
pub struct NavParams {
    /// Carry the attitude between images with the gyro (off: no inertial
    /// filter either, as [`FilterMode::Fixes`]).
    pub use_gyro: bool,
    pub filter: FilterMode,
    /// Largest angle between a line of sight and the surface normal (deg).
    pub alpha_max_deg: f64,
    /// Corner walking step of the horizon handling (px).
    pub horizon_step_px: f64,
    /// Fewer inliers reject the fix.
    pub min_inliers: usize,
    /// A smaller share of the correlation matches among the inliers rejects
    /// the fix: a chance consensus of wrong matches (measured: 8-12 of 40-90
    /// when the guess is 10 km off; 11 of 26 around a prediction 400 m off
    /// after an accelerometer shock, 537 m from the truth, at the 3 px
    /// RANSAC threshold) rather than the landmarks (15 of 18 to 200 of 210
    /// on the realistic flights). 0.45 (0.3 at the 2 px threshold).
    pub min_inlier_share: f64,
    /// Inliers must spread over the image: over at least this many cells of
    /// `grid`, and with a spread (standard deviation along their narrowest
    /// direction) of at least this share of the image's smaller side. A
    /// line or a cluster of matches pins the pose in some directions only,
    /// and is what a chance consensus of wrong matches on a local pattern
    /// looks like; and landmarks seen through a hole in the cloud leave the
    /// tilt/shift trade of a narrow view to the attitude prior (measured, a
    /// hole of 25% of the sides on the Sierra nadir balloon: fixes 445 m off
    /// at 0.04; none taken at 0.08, the filter coasting instead). (Accepted
    /// fixes on the realistic flights: at least 8 cells and 0.096.)
    pub min_inlier_cells: usize,
    pub min_inlier_spread: f64,
    /// A fix whose height is farther than this from the predicted one (the
    /// last accepted fix carried by the vertical velocity), plus what the
    /// velocity's error allows since then, is rejected (m); see [`HeightGate`].
    pub max_height_jump_m: f64,
    /// Landmarks correlated per frame (spread over the image).
    pub max_landmarks: usize,
    /// Correlation work a frame spends on an acquisition searched in tiles
    /// (the uncertainty wider than one search reaches: a low camera
    /// kilometres off; see `acquisition_tiles`), in G multiply-adds, a
    /// template's prediction counting [`TEMPLATE_WORK`] and
    /// [`PREDICT_WORK_PER_PX`] a pixel of its patch, and each position of
    /// a correlation `NCC_POSITION_WORK` (400) more: tiles are searched
    /// until it is spent (at least one, each at most once a frame), so a lost
    /// frame costs about the same whatever the camera, and tiles without
    /// landmarks cost nothing. One acquisition search correlates at most
    /// `SEARCH_BUDGETS` (4) of it.
    pub acquisition_budget_g: f64,
    /// Image cells (across x down) the landmarks are spread over.
    pub grid: (usize, usize),
    /// RANSAC inlier threshold at full resolution (px).
    pub ransac_threshold_px: f64,
    pub ncc: NccParams,
    /// Largest correlation search radius at one pyramid level (px); wider
    /// searches go to coarser levels first.
    pub max_radius_px: usize,
    /// Position and attitude uncertainty of the initial guess (1 sigma).
    pub init_sigma_m: f64,
    pub init_sigma_deg: f64,
    /// Gyro error model of the attitude filter (1 sigma per axis): the
    /// initial bias uncertainty (deg/s), the angle random walk
    /// (deg/sqrt(s)) and the bias random walk (deg/s/sqrt(s)).
    pub gyro_bias_deg_s: f64,
    pub gyro_arw_deg_sqrt_s: f64,
    pub gyro_bias_walk_deg_s_sqrt_s: f64,
    /// A gyro rate jump from one sample to the next beyond this (deg/s; 0:
    /// none) is doubted by the inertial filter
    /// ([`crate::ins::InsErrors::gyro_max_jump_rad_s`]), or without it
    /// ([`FilterMode::Fixes`]) in the attitude's prediction.
    pub gyro_max_jump_deg_s: f64,
    /// Through a gap in the IMU log (an interval over
    /// [`crate::IMU_GAP_FACTOR`] times the log's median), the doubt on the
    /// rate interpolated between the samples either side, as a random walk
    /// (deg/s/sqrt(s); 0: none): the attitude's sigma grows as
    /// `sigma sqrt(tau^3 / 3)` `tau` seconds into the gap
    /// ([`crate::ins::InsErrors::gap_rate_walk_rad_s_sqrt_s`]), the walk
    /// of the rate the fixes learn (there, and before or after the log).
    /// With [`FilterMode::Fixes`], whose fixes learn no rate, the walk from
    /// the stretch's start ([`crate::propagate::unmeasured_attitude_variance`]).
    pub imu_gap_doubt_deg_s_sqrt_s: f64,
    /// A specific force jump from one accelerometer sample to the next
    /// beyond this (m/s^2; 0: none) is doubted by the inertial filter
    /// ([`crate::ins::InsErrors::accel_max_jump_m_s2`]).
    pub accel_max_jump_m_s2: f64,
    /// The gyro's and the accelerometer's measurement range per axis
    /// (deg/s, m/s^2): a sample beyond either is no measurement and is left
    /// out of the log ([`crate::propagate::within_range`]), reported.
    pub gyro_range_deg_s: f64,
    pub accel_range_m_s2: f64,
    /// Velocity uncertainty between fixes (m/s) in [`FilterMode::Fixes`].
    pub velocity_sigma_m_s: f64,
    /// The inertial filter's initial velocity uncertainty (m/s; the initial
    /// guess has no velocity, its estimate starts at zero).
    pub init_velocity_sigma_m_s: f64,
    /// Accelerometer error model (1 sigma per axis): initial bias
    /// (m/s^2), velocity random walk (m/s/sqrt(s)), bias random walk
    /// (m/s^2/sqrt(s)).
    pub accel_bias_m_s2: f64,
    pub accel_vrw_m_s_sqrt_s: f64,
    pub accel_bias_walk_m_s2_sqrt_s: f64,
    /// Velocity random walk (m/s/sqrt(s)) when the flight has no
    /// accelerometer.
    pub free_accel_m_s2_sqrt_s: f64,
    /// The map offset of the inertial filter ([`crate::ins`]): the 1-sigma
    /// shift (m per axis) the database's errors give the fixes from the
    /// landmarks in view (0: not modelled; `None`: [`MAP_SIGMA_PER_GSD`]
    /// of the inliers' ground sample distance, see [`map_sigmas_for_gsd`]),
    /// and its correlation time (s).
    pub map_sigma_m: Option<f64>,
    pub map_tau_s: f64,
    /// The map offset's attitude part (deg, 1 sigma per axis; 0: not
    /// modelled; `None`: [`MAP_ATT_SIGMA_DEG_PER_GSD_M`] per metre of the
    /// inliers' ground sample distance): the rotation the database's errors
    /// give the pose the images see (a narrow view's tilt for its shift).
    pub map_att_sigma_deg: Option<f64>,
    /// The map offset's view term: each landmark's own error (px per
    /// coordinate, 1 sigma; 0: not modelled), the same in every image that
    /// sees it and independent between landmarks. What it gives the pose of
    /// the view of an accepted fix beyond the offset's isotropic prior
    /// ([`crate::ins::InsFilter::map_view_excess`]: a narrow view's few
    /// landmarks move its pose along the tilt-for-shift trade by hundreds
    /// of metres, a wide view's not at all) joins the map offset, so the
    /// fixes of a narrow view move the offset there and not the pose.
    pub map_view_sigma_px: f64,
    /// Prior 1-sigma of the camera-IMU time offset (s) the inertial filter
    /// estimates (an image stamped `t` exposed at `t + offset`); 0: none.
    pub time_offset_sigma_s: f64,
    /// With the tight filter, a frame without a fix (too few inliers, or
    /// too narrow a spread) still updates the filter with its matches that
    /// agree with the prediction (at least 3; see `Navigator::gated_update`).
    pub prior_gated_update: bool,
    /// With the tight filter, the landmarks found in two consecutive
    /// images update its velocity, gyro bias and time offset through the
    /// motion in between ([`crate::track`]).
    pub track_update: bool,
    /// With the tight filter and a self-calibration of the focal length
    /// alone, the filter carries the focal length as a state, so the motion
    /// the accelerometer measures calibrates it too (a rocket's climb, or a
    /// turning oblique view, against the range the images see), and the
    /// turns the gyro measures through the landmarks tracked between images
    /// (a pendulum's tilts). On by default: on the 24 realistic runs
    /// (8 flights, 3 databases) the sum of the mean errors falls from 1661
    /// to 1208 m against each fix's own evidence alone (README,
    /// self-calibration).
    pub inertial_focal: bool,
    /// With the tight filter and a self-calibration that does not estimate
    /// the principal point itself, the filter carries the principal point as
    /// two states: its error is a tilt fixed in the camera, which a roll
    /// about the boresight or the accelerometer's tilt tells from an
    /// attitude or position error. Off by default (it is then a consider
    /// parameter of each fix's covariance, with its prior): on the realistic
    /// flights it lowers the mean errors of 16 of 24 runs but wanders to the
    /// wrong side on the high rocket, whose worst fix and NEES it raises
    /// (README, self-calibration).
    pub inertial_principal_point: bool,
    /// Carry the principal point in the inertial filter's state but learn
    /// it from the landmark tracks alone (a roll about the boresight
    /// between two images turns the pixels about the true principal
    /// point): the fixes count its uncertainty without moving it, so the
    /// database's tilt in a fix is not taken for the camera's.
    pub principal_point_from_tracks: bool,
    pub track: TrackParams,
    /// A frame whose image-only pose is farther than this from the inertial
    /// filter's prediction (chi-square, 6 degrees of freedom) is rejected as
    /// inconsistent, and the filter's pose and velocity uncertainty doubled
    /// (but see `doubt_min_cells`).
    pub innovation_gate_chi2: f64,
    /// An inconsistent fix doubts the filter (doubles its pose and velocity
    /// sigmas) at once when its inliers cover at least this many cells of
    /// `grid`, or before the first fix, or while the guess is doubted; one
    /// of a narrower view (a hole in the cloud, a patch of texture) only
    /// when it agrees with the inconsistent fix before it since the last
    /// accepted one: both disagree with the filter alike, their
    /// innovations within the gate of each other ([`doubts_filter`],
    /// [`innovations_agree`]). A narrow view's few landmarks trade a tilt
    /// for a shift, its fixes are biased along that trade, and its wrong
    /// solutions scatter: doubling the filter for them let the next biased
    /// fix through the gate, the pose dragged hundreds of metres (measured,
    /// `scripts/bench_narrow.sh`: 9 of 35 runs accepted a fix beyond 250 m
    /// with every inconsistent fix doubting; 1 of 35 with the second
    /// doubting whatever it said, 0 with this; the holes' inconsistent
    /// fixes cover 5-13 cells, those of the shipped realistic flights 32
    /// and 36, but the 640x480 rocket's in its first second, 14). 0: every
    /// inconsistent fix doubts.
    pub doubt_min_cells: usize,
    /// A frame whose matches (as many as a fix needs) do not agree counts
    /// as a miss (`Navigator::count_miss`; after `DOUBT_AFTER_MISSES` in a
    /// row each doubles the pose's doubt) only when they span at least
    /// this many cells of `grid` (`narrow_miss`; the block of cells from
    /// the leftmost match to the rightmost, the top one to the bottom one):
    /// a narrower view's matches (a hole in the cloud) disagree whether the
    /// pose is right or not. Measured (`scripts/bench_faults.sh` on
    /// `scripts/bench_narrow.sh`'s staging, see the README): with 24, the
    /// hole runs that stayed lost after a glitch or a gap, their doubt
    /// doubled into an acquisition that never stood while the pose was
    /// 65 m off, fix again. 0: every such frame counts.
    pub miss_min_cells: usize,
    /// The sun during the flight: picks the database's lighting (its baked
    /// sun nearest to it) when it has several.
    pub sun: Option<SunLight>,
    /// Weight of a template's shading share in the choice of landmarks when
    /// the lighting used is not baked for the flight's sun: the score is
    /// multiplied by `1 - weight * shading_share`.
    pub shading_weight: f64,
    /// Landmarks closer on the ground than this share of a template's
    /// footprint (the larger of the two) are near duplicates: most of their
    /// pixels are the same, so are their matches' errors, and the pose would
    /// count one place's map error several times. In an image cell, a
    /// landmark within this of a better one is taken only after every one
    /// that is not (`Navigator::spread`). 0.5 is the separation the builder
    /// keeps inside one of its cells; across its cells and between levels it
    /// keeps none. Measured on six other renderings of the eight realistic
    /// flights: 293.1 -> 276.9 m (the sum of the means; 0.35: 276.6, 0.7:
    /// 286.6, 1: 291.9). 0: off.
    pub duplicate_separation: f64,
    /// Estimate the camera's focal length and principal point online
    /// ([`crate::calibration`]), with these priors; `None`: trust
    /// `camera.json`.
    pub calibration: Option<CalibrationParams>,
    /// Threads a frame's landmarks are predicted and correlated on (each
    /// landmark's work is its own, so the poses are the same bits for any
    /// count; 0: one per core). 1, the default, keeps the navigator on the
    /// calling thread.
    pub threads: usize,
}

impl Default for NavParams {
    fn default() -> Self {
        Self {
            use_gyro: true,
            filter: FilterMode::Tight,
            alpha_max_deg: 75.0,
            horizon_step_px: 10.0,
            min_inliers: 8,
            min_inlier_share: 0.45,
            min_inlier_cells: 4,
            min_inlier_spread: 0.08,
            max_height_jump_m: 450.0,
            max_landmarks: 600,
            acquisition_budget_g: 30.0,
            grid: (8, 6),
            ransac_threshold_px: 3.0,
            ncc: NccParams { min_peak: 0.5, max_second_ratio: 0.92, min_template_std: 2.0 },
            max_radius_px: 16,
            init_sigma_m: 300.0,
            init_sigma_deg: 2.0,
            // Twice the simulated tactical-grade gyro (10 deg/h, 0.15
            // deg/sqrt(h)); the bias walks 0.01 deg/h per sqrt(s).
            gyro_bias_deg_s: 20.0 / 3600.0,
            gyro_arw_deg_sqrt_s: 0.3 / 60.0,
            gyro_max_jump_deg_s: 10.0,
            imu_gap_doubt_deg_s_sqrt_s: 3.0,
            accel_max_jump_m_s2: 10.0,
            // Beyond any gyro or accelerometer a balloon, rocket or lander
            // flies (their full scales: 2000-4000 deg/s, 16-400 g).
            gyro_range_deg_s: DEFAULT_GYRO_RANGE_DEG_S,
            accel_range_m_s2: DEFAULT_ACCEL_RANGE_M_S2,
            gyro_bias_walk_deg_s_sqrt_s: 0.01 / 3600.0,
            velocity_sigma_m_s: 20.0,
            init_velocity_sigma_m_s: 300.0,
            // Twice the simulated accelerometer (2 mg bias, 0.01 m/s^2 per
            // sample at 200 Hz = 7e-4 m/s/sqrt(s)).
            accel_bias_m_s2: 0.05,
            accel_vrw_m_s_sqrt_s: 0.0015,
            accel_bias_walk_m_s2_sqrt_s: 1e-4,
            free_accel_m_s2_sqrt_s: 3.0,
            // Sized by the landmarks' ground sample distance
            // ([`map_sigmas_for_gsd`]).
            map_sigma_m: None,
            map_tau_s: 10.0,
            map_att_sigma_deg: None,
            map_view_sigma_px: 0.0,
            time_offset_sigma_s: 0.01,
            prior_gated_update: true,
            track_update: true,
            inertial_focal: true,
            inertial_principal_point: false,
            principal_point_from_tracks: false,
            track: TrackParams::default(),
            // 99.9% of chi-square with 6 degrees of freedom.
            innovation_gate_chi2: 22.46,
            // Half of the 8 x 6 grid.
            doubt_min_cells: 24,
            miss_min_cells: 24,
            sun: None,
            shading_weight: 0.5,
            duplicate_separation: 0.5,
            calibration: Some(CalibrationParams::default()),
            threads: 1,
        }
    }
}

/// Result of one processed frame.
pub struct FrameResult {
    pub record: NavRecord,
    pub matches: Vec<MatchRecord>,
    /// Where the pose guess put each match's landmark (full-resolution pixels).
    pub guess_px: Vec<Option<Pixel>>,
    /// The covariance of an accepted fix.
    pub covariance: Option<PoseCovariance>,
    /// Why the frame's solution was not accepted (its pose is then carried).
    pub rejection: Option<Rejection>,
    /// The solution is an acquisition held for the next frame to confirm
    /// (a tile's, [`Rejection::Unconfirmed`], or one refused only for too
    /// narrow a view, [`Rejection::Spread`]).
    pub held: bool,
    /// Matches of a frame without a fix that updated the inertial filter
    /// through its prediction ([`NavParams::prior_gated_update`]; 0: none).
    pub gated_matches: usize,
    /// Landmarks found in this image and the one before that updated the
    /// inertial filter through the motion in between
    /// ([`NavParams::track_update`]; 0: none).
    pub tracked: usize,
}

/// Why a frame's pose solution was rejected.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Rejection {
    /// Fewer RANSAC inliers than `min_inliers`.
    FewInliers { inliers: usize },
    /// Inliers a smaller share of the matches than `min_inlier_share`.
    InlierShare { inliers: usize, matches: usize },
    /// An acquisition (or its confirmation) whose inliers are a smaller
    /// share of the templates it searched for than
    /// [`MIN_ACQUISITION_FOUND_SHARE`]: an alias matches a few of them.
    FoundShare { inliers: usize, searched: usize },
    /// Inliers on a line or in a cluster (`min_inlier_cells`,
    /// `min_inlier_spread`): the cells they cover and their spread (pixels).
    Spread { cells: usize, spread_px: f64 },
    /// The height disagrees with the prediction by more than the gate allows.
    Height { off_m: f64, allowed_m: f64 },
    /// The image-only pose disagrees with the inertial filter's prediction.
    Inconsistent { chi2: f64 },
    /// An acquisition found in a tile away from the guess (east, north;
    /// m): of the many places such a search tries, one may alias, so it is
    /// a fix only once the next frame, searched around it, confirms it.
    Unconfirmed { tile_east_m: f64, tile_north_m: f64 },
}

/// The height check of a fix: where its height should be and how far from it
/// it may be. The reference is the last accepted fix (before the first one,
/// the initial guess, with three of its sigmas added), carried to the frame
/// by the vertical velocity when the fixes give one; the allowance is
/// `max_jump_m` plus three sigmas of the vertical velocity times the time
/// since the reference. It grows while fixes are rejected, so a run of
/// rejections never locks the navigator out, and a climbing rocket is
/// predicted where it climbs to.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeightGate {
    pub predicted_h_m: f64,
    pub allowed_m: f64,
}

/// What a [`HeightGate`] measures from: the last accepted fix (no extra
/// allowance) or the initial guess (three of its sigmas).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeightReference {
    pub t: f64,
    pub h_m: f64,
    pub extra_allowance_m: f64,
}

impl HeightGate {
    /// `v_up_m_s`: the vertical velocity when known; `v_sigma_m_s`: its (or,
    /// unknown, the assumed velocity's) 1-sigma error.
    pub fn new(
        reference: HeightReference,
        t: f64,
        v_up_m_s: Option<f64>,
        v_sigma_m_s: f64,
        max_jump_m: f64,
    ) -> Self {
        let dt = (t - reference.t).max(0.0);
        HeightGate {
            predicted_h_m: reference.h_m + v_up_m_s.unwrap_or(0.0) * dt,
            allowed_m: max_jump_m + reference.extra_allowance_m + 3.0 * v_sigma_m_s * dt,
        }
    }

    /// `None` when `h_m` passes, else the rejection.
    pub fn check(&self, h_m: f64) -> Option<Rejection> {
        let off_m = (h_m - self.predicted_h_m).abs();
        (off_m > self.allowed_m).then_some(Rejection::Height { off_m, allowed_m: self.allowed_m })
    }
}

/// The inertial filter's estimate at one time: the camera pose (map offset
/// not added) and its covariance (`[dtheta; dp]`, ECEF, as `covariance.csv`).
#[derive(Clone, Debug)]
pub struct FilterPose {
    pub t: f64,
    pub pose: CameraPose,
    pub covariance: Matrix6<f64>,
}

/// The least time over which a restart's drift from the filter's
/// prediction is taken as a velocity error (s): a restart after a run of
/// frames without a fix doubts the velocity by that drift over the time
/// since the last fix.
pub const RESTART_MIN_SPAN_S: f64 = 1.0;

/// The default of [`NavParams::gyro_range_deg_s`].
pub const DEFAULT_GYRO_RANGE_DEG_S: f64 = 10_000.0;
/// The default of [`NavParams::accel_range_m_s2`] (about 1000 g).
pub const DEFAULT_ACCEL_RANGE_M_S2: f64 = 10_000.0;

/// Terrain relative navigation over one flight.
pub struct Navigator<'a> {
    source: &'a dyn LandmarkSource,
    /// The camera as estimated now (`camera.json`'s, or self-calibrated).
    camera: CameraModel,
    calibration: Option<CalibrationFilter>,
    /// The camera `lut` was made for.
    lut_camera: CameraModel,
    q_imu_cam: UnitQuaternion<f64>,
    /// The IMU log, less any sample beyond the sensors' range.
    imu: std::borrow::Cow<'a, [ImuSample]>,
    /// The times of the samples left out of `imu`.
    imu_out_of_range: Vec<f64>,
    params: NavParams,
    lut: UndistortLut,
    /// The database's levels.
    levels: Vec<DbLevel>,
    /// The templates' lighting used (`Template::lighting`), and whether it
    /// was baked for the flight's sun.
    lighting: u8,
    lit_for_flight: bool,
    /// Per level: the last (enlarged) query box and its templates; the
    /// footprint moves little between frames.
    cache: std::cell::RefCell<std::collections::HashMap<u8, (trn_landmark::GeoBox, Vec<Template>)>>,
    /// Current estimate and when.
    t: f64,
    pose: CameraPose,
    sigma_m: f64,
    /// Attitude error and gyro bias at `t`: a fix's posterior, carried by
    /// the gyro, is the next frame's attitude prior, so a narrow-FOV nadir
    /// view inherits the tilt the frames before it saw.
    filter: AttitudeFilter,
    last_fix: Option<(f64, CameraPose)>,
    /// The initial guess: the first fix's height reference.
    init_h: HeightReference,
    /// The interval between IMU samples beyond which the log has a gap
    /// (0: fewer than two samples): for [`FilterMode::Fixes`]'s attitude
    /// doubt where no sample measures the rate (the inertial filter has its
    /// own, [`InsErrors::imu_gap_s`]).
    imu_gap_s: f64,
    /// Accepted fix positions of the last [`VELOCITY_WINDOW_S`] (time, ECEF).
    recent_fixes: std::collections::VecDeque<(f64, Vector3<f64>)>,
    /// Velocity (ECEF, m/s) and its 1-sigma error; `None` before the fixes
    /// span [`VELOCITY_MIN_SPAN_S`].
    velocity_sigma: Option<f64>,
    velocity: Vector3<f64>,
    terrain_h_m: f64,
    /// The inertial filter at `t` (`None`: [`FilterMode::Fixes`]).
    ins: Option<InsFilter>,
    /// The last frame's matches and the filter's pose then: the next
    /// frame's track update ([`crate::track`]).
    track: Option<TrackAnchor>,
    /// A frame gave no fix (before the first fix, or after
    /// [`DOUBT_AFTER_MISSES`] misses since it) and the filter's pose uncertainty was
    /// inflated ([`Self::doubt_prediction`]): the next fix restarts the
    /// pose, as an acquisition's does, and until then no match or track
    /// updates the filter.
    guess_doubted: bool,
    /// Fixes after which the map offset was restarted.
    map_doubts: usize,
    /// The largest map offset chi-square an accepted fix found.
    map_chi2_max: f64,
    /// [`FilterMode::Fixes`]: the gyro's jumps doubted ([`Self::doubt_jumps`]).
    own_gyro_jumps: usize,
    /// [`FilterMode::Fixes`]: the gyro's jumps since the last accepted fix,
    /// as turned (the inertial filter keeps its own, [`InsFilter::jump_turn`]).
    own_jump_turn: Option<JumpTurn>,
    /// Fixes found with the gyro's jumps undone ([`Self::jump_undone_prediction`]).
    jumps_undone: usize,
    /// [`FilterMode::Fixes`]: the last accepted fix's attitude, for
    /// [`Self::fix_rate`].
    fix_attitude: Option<FixAttitude>,
    /// [`FilterMode::Fixes`]: the body's rate the last two fixes measured
    /// after the IMU log's end, where no gyro does.
    fix_rate: Option<FixRate>,
    /// Misses since the last accepted fix ([`Self::count_miss`]).
    misses: usize,
    /// Frames whose miss, after a fix, grew the doubt
    /// ([`Self::doubt_prediction`]).
    doubted_frames: usize,
    /// The last inconsistent fix since the last accepted one: its
    /// innovation against the filter's prediction and its covariance
    /// ([`innovations_agree`]).
    last_refused: Option<Innovation>,
    /// Inconsistent fixes of a narrow view that did not doubt the filter.
    narrow_inconsistent: usize,
    /// The threads of [`NavParams::threads`] (`None`: one, the caller's).
    pool: Option<rayon::ThreadPool>,
    /// A fix has sized the map offset's prior ([`map_sigmas_for_gsd`]).
    map_sized: bool,
    /// The last accepted fix's pose sensitivity to the intrinsics the
    /// inertial filter may carry: frames without a fix update the filter
    /// through it too.
    last_sensitivity: IntrinsicsSensitivity,
    /// Per landmark, the accepted fixes in a row (up to the last, since the
    /// filter's pose last restarted) it was an inlier of
    /// ([`inlier_sigmas_px`]).
    landmark_runs: HashMap<i64, u32>,
    /// The next tile of an acquisition searched in tiles
    /// ([`acquisition_tiles`]).
    acquisition_cursor: usize,
    /// The next tile of the narrow layout ([`Navigator::narrow_layout`]).
    narrow_cursor: usize,
    /// The turned headings' layout's cursor (see `Navigator::solve`).
    heading_cursor: usize,
    /// Whether the acquisition's wide layout has been searched once over
    /// since the last fix (all its tiles, or its one search): lost frames
    /// then alternate between it and the narrow layout, narrow first (as
    /// they do once a wide window has been too wide, [`Self::wide_too_wide`]).
    wide_searched: bool,
    /// Frames of that alternation so far.
    alternation: usize,
    /// A wide search's window (the guess's or a wide tile's) has been too
    /// wide since the last fix ([`Navigator::wide_window_too_wide`]): lost
    /// frames then alternate the layouts.
    wide_too_wide: bool,
    /// A tiled acquisition the next frame is to confirm.
    candidate: Option<Candidate>,
    /// Correlation work done (template pixels times search positions, and
    /// each template's prediction) since the tile loop of
    /// [`Self::solve`] last reset it.
    work: std::cell::Cell<u64>,
    /// Search positions a template of the last [`Self::search_from`]'s
    /// first level ([`Self::wide_window_too_wide`]).
    window_positions: std::cell::Cell<u64>,
    /// Set while a tile of an acquisition is searched: the landmarks its
    /// first level searches for ([`ACQUISITION_TILE_LANDMARKS`]).
    tile_landmarks: std::cell::Cell<Option<usize>>,
}

/// An acquisition found in a tile away from the guess, held for the next
/// frame to confirm ([`Rejection::Unconfirmed`]).
#[derive(Clone, Copy, Debug)]
struct Candidate {
    t: f64,
    pose: CameraPose,
    /// Its position's 1-sigma (m, 3D).
    sigma_m: f64,
}

/// A frame's prediction: the pose guess and how far it may be off.
struct Prediction {
    /// Where the images should see the camera.
    guess: CameraPose,
    /// Covariance of the guess' attitude (rad^2, ECEF): the frame's prior.
    att_cov: Matrix3<f64>,
    /// The guess' position error (m, 1 sigma, 3D).
    sigma_m: f64,
    /// The inertial filter's covariance of the apparent pose (`[dtheta;
    /// dp]`, ECEF): with it the search radius is the largest pixel sigma
    /// it gives in the footprint ([`search_sigma_px`]); without it,
    /// `att_cov` and `sigma_m` added.
    pose_cov: Option<Matrix6<f64>>,
    filter: Carried,
    /// [`FilterMode::Fixes`]: the gyro's jumps doubted since the last
    /// frame ([`Navigator::doubt_jumps`]; the inertial filter counts its own).
    gyro_jumps: usize,
    /// The gyro's jumps since the last accepted fix, as turned.
    jump_turn: Option<JumpTurn>,
}

/// The filter carried to a frame (one per frame, moved by value: the size
/// difference of the variants costs nothing worth a box).
#[allow(clippy::large_enum_variant)]
#[derive(Clone)]
enum Carried {
    /// [`FilterMode::Fixes`]: the attitude filter's covariance.
    Attitude(Matrix6<f64>),
    /// The inertial filter.
    Ins(InsFilter),
}

const PYRAMID_LEVELS: usize = 4;
/// Largest warped template side (px): bigger ones are cut to their centre.
const MAX_PATCH_PX: usize = 63;
/// Fewest landmarks in view for a coarse search level.
const MIN_COARSE_LANDMARKS: usize = 20;
/// Smallest template size at a coarse search level (level pixels).
const MIN_PATCH_PX: f64 = 12.0;
/// Smallest error of the velocity from fixes (m/s, 1 sigma): acceleration
/// since the window's middle.
const VELOCITY_KNOWN_SIGMA_M_S: f64 = 5.0;
/// The velocity is the least-squares slope of the fix positions over this
/// window (s), once they span at least `VELOCITY_MIN_SPAN_S`: two fixes
/// 0.5 s apart whose errors differ by 50 m (a narrow view's tilt/shift
/// trade) would give 100 m/s of error.
const VELOCITY_WINDOW_S: f64 = 8.0;
const VELOCITY_MIN_SPAN_S: f64 = 2.0;
/// Attitude disagreement (deg, 1 sigma per axis) between the image and the
/// gyro prior that the gate below allows on top of the filter's covariance:
/// what the camera's calibration and clock errors move an image's attitude
/// between frames (a 0.3% focal error, a few ms of clock offset during a
/// spin), which the filter does not model. The prior itself stays tight.
const ATTITUDE_GATE_FLOOR_DEG: f64 = 0.05;
/// A refined attitude farther than this (squared Mahalanobis distance, 3
/// degrees of freedom, 99.9%) from the gyro prior means the two disagree:
/// the frame is refined again with the prior loosened.
const PRIOR_GATE_CHI2: f64 = 16.27;
/// One pyramid level's correlation search: the radius (level pixels) and
/// how far outside the image (full-resolution pixels) a landmark's guessed
/// position may be (an acquisition's; 0 otherwise).
#[derive(Clone, Copy, Debug)]
struct Search {
    radius: usize,
    margin_px: f64,
}

/// A first search radius above this share of the focal length is an
/// acquisition (see `solve`).
const ACQUISITION_RADIUS_F: f64 = 0.5;

/// Spacing of the tiles, as a share of what one search reaches (the
/// footprint widened by the image's size): a guess that far off diagonally
/// is still found.
const ACQUISITION_TILE_SPACING: f64 = 0.7;
/// The work of one position of a correlation besides its multiply-adds
/// (the image's sums under the template, the normalisation, the peak and
/// the second peak), in multiply-adds: measured on one core (AVX2,
/// `trn-vision`'s `ncc` over a 320x240 image), 15-20 ns a position at
/// 0.045 ns a multiply-add, as much as a 20x20 template's own. Without it
/// the 23 px templates of an acquisition ([`ACQUISITION_MAX_PATCH_PX`])
/// made lost frames 1.25-1.35x longer than the budget meant.
const NCC_POSITION_WORK: u64 = 400;
/// The work of predicting one template (its warp through the terrain)
/// besides its pixels' ([`PREDICT_WORK_PER_PX`]), in correlation
/// multiply-adds. Measured on one core (AVX2, the 640x480 rocket lost 10 km
/// and 10.8 deg off): a prediction took ~11 us and ~27 ns a pixel of its
/// patch (25 us for an acquisition's 23x23 centre, 113 us for a tracking
/// frame's 61x61 on average), against ~24 ms per G multiply-adds of an
/// acquisition's correlation. (Measured while relief was predicted by a ray
/// march; drawn as a mesh since, a relief patch costs less and is
/// over-counted. Kept, so that a lost frame searches the tiles the
/// acquisition benchmarks were measured with.)
pub const TEMPLATE_WORK: u64 = 450_000;
/// The work of predicting one pixel of a template's patch, in correlation
/// multiply-adds (see [`TEMPLATE_WORK`]).
pub const PREDICT_WORK_PER_PX: u64 = 1_100;
/// The most work one acquisition search correlates, in frame budgets
/// ([`NavParams::acquisition_budget_g`]). One budget cut the oblique
/// balloon's own search (~105 G on its 512x384 level) to a third of its
/// templates, and it no longer acquired 3 km off.
const SEARCH_BUDGETS: f64 = 4.0;
/// Most positions (at the level it starts on) a wide acquisition search may
/// correlate each template over before lost frames alternate with the
/// narrow layout ([`Navigator::narrow_layout`]). Measured (README,
/// acquisition): whole-image searches of 7 500-77 000 positions acquire the
/// rockets, the nadir balloons and the low pass; the oblique balloon's
/// 512x384 level, ~180 000 (radius 233) from a guess 6 km off, matched 32
/// of 300 templates, 5 consistent, at every frame.
const MAX_ACQUISITION_POSITIONS: u64 = 100_000;

/// The least share of the templates an acquisition (or the search that
/// confirms it) searched for at its last level that must be its inliers.
/// Measured (README, acquisition): an alias of the oblique balloon 10 km
/// east, 9 km from the truth, held 9 inliers of 300 templates searched and
/// was confirmed by the next frame with 10 of 300 (and became 18 fixes 9 km
/// off); the aliases of its acquisition benches held 0.027-0.041 of them.
/// True acquisitions held 0.149-1.0 on the benches of every flight, and
/// 0.062 in `tests/navigate.rs`'s climbing rocket 10 km off (a tile's 8 of
/// 130, confirmed with 14 of 115), which a tenth refused.
pub const MIN_ACQUISITION_FOUND_SHARE: f64 = 0.05;
/// Largest change of a template's foreshortening (relative, along the line
/// of sight) between the pose an acquisition's narrow tile warps it from
/// and the truth ([`Navigator::narrow_layout`]).
const ACQUISITION_MAX_FORESHORTENING: f64 = 0.2;
/// Most tiles an acquisition lays out.
const ACQUISITION_MAX_TILES: usize = 400;
/// The landmarks a tile's search looks for on its acquisition level (at most
/// `--max-landmarks`; the guess's own search takes them all). Half the work
/// a tile, twice the tiles a frame. Measured (README, acquisition), against
/// 300: the 640x480 rocket 10 km off from frame 9 / 11 (told / not told)
/// where it took 13 / 25, 10 km and 10.8 deg from 13 / 15 (24 / 25); the low
/// pass 10 km east from 24 / 4 (37 / 5); the oblique balloon 10 km east and
/// west from 8 / 10 (10 / 12, 12 / 12). 100 a tile were too few to stand
/// (the low pass 10 km east from 40 / 27). The found share
/// ([`MIN_ACQUISITION_FOUND_SHARE`]) holds for them as for any acquisition:
/// before it, 180 a tile had let an alias in.
const ACQUISITION_TILE_LANDMARKS: usize = 150;
/// Largest warped template side (level px) on an acquisition's level
/// (any search wider than its footprint): larger ones are cut to their
/// centre (the levels below it take [`MAX_PATCH_PX`]). A template
/// warped as seen from a guess kilometres off is warped wrong the more the
/// farther from its centre, and its correlation costs its pixels at every
/// position of a window as wide as the image (the low pass's tile ~17 G
/// of multiply-adds with 63, ~6 G with 23; ~9.5 G with
/// [`NCC_POSITION_WORK`] counted). Measured (README, acquisition), with
/// [`ACQUISITION_ALONG_SIGHT_STEP`] and against 63: over the 22 runs from
/// 10 km of the benches the latest first fix 24 -> 12, the mean 7.2 -> 6.3;
/// alone, the low pass 10 km east not told fell between its tiles (4 -> 24).
const ACQUISITION_MAX_PATCH_PX: usize = 23;
/// Spacing of an oblique view's acquisition tiles along its line of sight,
/// in ground range over the sine of the boresight's angle from the vertical
/// ([`sight_line`]): the truth is then at most half of it along the line of
/// sight from a tile, where the tile sees the templates ~22% larger or
/// smaller than the truth does. Measured (README, acquisition): the low
/// pass's (50 deg forward, 7.6 km range) wide tiles, 6.3 km apart, failed
/// 2.8-3.7 km from the truth along its line of sight and acquired 1.5-2.4 km
/// from it; across it 3.8 km. 0.55 left the low pass 10 km east, not told,
/// between its tiles until frame 32; 0.45 costs the oblique balloon (19 km
/// tiles) two frames told 10 km off (east, west: 8 -> 10).
const ACQUISITION_ALONG_SIGHT_STEP: f64 = 0.45;

/// Misses since the last fix (frames whose matches, as many as a fix
/// needs, did not agree: [`Navigator::count_miss`]) from which each further
/// one doubts the filter's pose ([`Navigator::doubt_prediction`]): 2 s at
/// the flights' 2 Hz. Frames under cloud, with fewer matches, do not count:
/// a 30 s outage that doubted them all took 2.5-4.5 s to fix again after it
/// (none in the 5 s left after 25-55 s), where it takes none. Measured on
/// the 30 km nadir balloon with its IMU silent for 3 s, or its gyro turned
/// 5 deg in 20 ms with `--gyro-max-jump 0` (the jump's own doubt catches
/// that first): without this doubt the navigator fixed none of the 100
/// frames after (2.2 deg off, its search sized for 0.05 deg), never
/// recovering; with it 115 and 113 of the 121 frames
/// (`scripts/bench_faults.sh`).
const DOUBT_AFTER_MISSES: usize = 4;

/// The least turn (deg) of the gyro's jumps since the last fix for which a
/// frame that does not fix is searched again with them undone
/// ([`Navigator::jump_undone_prediction`]): smaller ones the jump's own
/// doubt covers (1-10 deg glitches fixed every frame of the realistic
/// flights; `scripts/bench_faults.sh`).
const JUMP_UNDO_MIN_DEG: f64 = 1.0;

/// How long after the first of the gyro's jumps since the last fix a frame
/// that does not fix is searched again with them undone (s), where no
/// inertial filter integrates the accelerometer (`--filter fixes`): undone
/// later, the force measured meanwhile, turned by them, has moved the
/// position too far for the search around the guess (a 30 deg glitch on a
/// balloon: 4.9 m/s^2 across, 61 m after 5 s), and the frames then only
/// cost twice their search; the run of misses' doubt
/// ([`DOUBT_AFTER_MISSES`]) goes on from there. The inertial filter takes
/// that force back from the guess ([`JumpTurn::undo_shift`]) and searches
/// it as long as no frame fixes: through holes in the cloud with the
/// glitch 10 s into the hole, four runs of 35 then drifted 358-3016 m,
/// never fixing again (`scripts/bench_faults.sh` on
/// `scripts/bench_narrow.sh`'s staging).
const JUMP_UNDO_WITHIN_S: f64 = 5.0;

/// The largest attitude sigma (deg, any axis) that frames without a first
/// fix grow the guess's doubt to: 2.5 sigmas then span the widest field
/// of view, and more only loosens the gyro's prior on the search.
const DOUBT_MAX_ATTITUDE_DEG: f64 = 20.0;

/// The largest position sigma (m, any axis) that frames without a first
/// fix grow the guess's doubt to: twice the 10 km a guess may be off (#13),
/// and beyond the 400 tiles of a low camera's acquisition (35 km across at
/// 3.5 km above the terrain). (Doubling without a bound reached 10^30 m in
/// 100 frames.)
const DOUBT_MAX_POSITION_M: f64 = 20_000.0;

/// Shortest image side (level pixels) an acquisition searches at. Measured
/// on the realistic flights (README, acquisition): a 640x480 camera's 80x60
/// level (two of its coarse templates across, searched over the whole
/// image) acquired neither the low pass nor the 640x480 rocket 2 km off, its
/// 160x120 level acquires both; the 200x150 rocket acquires 2 km off on its
/// 100x75 level, and at full resolution (16 px templates searched over the
/// whole image) it found aliases up to 491 m off; the 1024x768 balloons
/// acquire 10 km off on their 128x96 level.
const MIN_ACQUISITION_SIDE_PX: usize = 72;

/// Widest angle (rad: the ground size of the level's templates over the
/// range at the image's centre) an acquisition's templates may span: a
/// template is warped into the image as seen from the guess, and the wider
/// the angle it spans the more a guess kilometres off warps it wrong (most
/// in a low oblique view over relief). Coarser levels than that are not
/// searched, down to the first above full resolution. Measured (README,
/// acquisition): the low pass's 160x120 level (1.9 km templates at 7.6 km,
/// 0.25) matched 6 of 76 landmarks a guess 2 km off beside its track, its
/// 320x240 level (0.13) 44 of 177 and fixed, and from 5 and 10 km in tiles
/// at frames 1-4 where the coarse level took ~100; the levels the nadir
/// balloons (0.13) and the 640x480 rocket (0.14) acquire on are kept.
const ACQUISITION_MAX_TEMPLATE_ANGLE: f64 = 0.2;
/// Huber threshold (px) of the self-calibration's residuals, as the
/// full-resolution refinement's.
const HUBER_PX: f64 = 1.0;
/// Smallest pixel sigma a frame's calibration evidence is weighed with.
const CALIBRATION_MIN_SIGMA_PX: f64 = 0.1;
/// Pixel sigma and Huber threshold of a frame's full-resolution
/// refinement (as the last pyramid level's), and so of the inertial
/// filter's update.
const REFINE_SIGMA_PX: f64 = 0.1;
const REFINE_HUBER_PX: f64 = 1.0;
/// Largest correlation-peak sigma a match is given (px): an edge's is
/// infinite along it.
const MAX_PEAK_SIGMA_PX: f64 = 5.0;

/// The map offset's default 1-sigma per axis, in the landmarks' ground
/// sample distance (GSD): where many landmarks agree, a database is off by
/// about one of its pixels (its ortho's registration, the DEM's errors under
/// the templates, another sun moving every correlation peak alike), so a
/// 1 m database is not given a 30 m one's 40 m. Measured on the realistic
/// flights (README; a 30 m Landsat ortho, another DEM): 40 m (4/3 of 30 m)
/// over 10 s, with the landmark tracks, bridges the 30 km nadir balloon's
/// 30 s outage (167 -> 69 m of drift after 15 s of fixes) and leaves no
/// flight's NEES above its 95% band; the 30 km nadir fixes wander by +-50 m.
pub const MAP_SIGMA_PER_GSD: f64 = 4.0 / 3.0;
/// A map offset estimated beyond this chi-square (6 degrees of freedom:
/// 95%) of its prior restarts it ([`InsFilter::map_offset_distance`]). On
/// the eight realistic flights no fix's estimate reaches 4.7 (the high
/// rocket's; the balloons' 1.7 at most: the run report's `map_chi2_max`);
/// the 30 km nadir balloon whose accelerometer read 10 m/s^2 too much for
/// 5 s reached 21.8, one that read 100 m/s^2 too much for 1 s (not doubted
/// as a jump) 65.9 (a build that only logged it, restarting nothing). With
/// 16.81 (99%) the first restart came 200 m off, with this 166 m.
pub const MAP_DOUBT_CHI2: f64 = 12.59;

/// The velocity's sigma (m/s per axis, at least) after a map offset's
/// restart ([`MAP_DOUBT_CHI2`]).
pub const MAP_DOUBT_VELOCITY_M_S: f64 = 10.0;
/// The map offset's attitude part per metre of the landmarks' GSD (deg):
/// 0.1 deg at 30 m, where the realistic 30 km nadir fixes' tilt wanders by
/// 0.03-0.1 deg.
pub const MAP_ATT_SIGMA_DEG_PER_GSD_M: f64 = 0.1 / 30.0;

/// The map offset's 1-sigmas (m, deg per axis) for landmarks of `gsd_m`
/// (the median of a fix's inliers): `--map-sigma` / `--map-att-sigma` where
/// given, else [`MAP_SIGMA_PER_GSD`] and [`MAP_ATT_SIGMA_DEG_PER_GSD_M`].
pub fn map_sigmas_for_gsd(params: &NavParams, gsd_m: f64) -> (f64, f64) {
    (
        params.map_sigma_m.unwrap_or(MAP_SIGMA_PER_GSD * gsd_m),
        params.map_att_sigma_deg.unwrap_or(MAP_ATT_SIGMA_DEG_PER_GSD_M * gsd_m),
    )
}

impl<'a> Navigator<'a> {
    pub fn new(
        source: &'a dyn LandmarkSource,
        camera: &CameraConfig,
        imu: &'a [ImuSample],
        init: &TimedPose,
        params: NavParams,
    ) -> Result<Self, trn_view::SourceError> {
        let pool = match params.threads {
            1 => None,
            n => Some(
                rayon::ThreadPoolBuilder::new()
                    .num_threads(n)
                    .thread_name(|i| format!("trn-navigate-{i}"))
                    .build()
                    .map_err(|e| {
                        trn_view::SourceError(format!(
                            "--threads {n}: cannot start the navigator's threads: {e}"
                        ))
                    })?,
            ),
        };
        let range = crate::propagate::ImuRange {
            gyro_rad_s: params.gyro_range_deg_s.to_radians(),
            accel_m_s2: params.accel_range_m_s2,
        };
        let (imu, imu_out_of_range) = match crate::propagate::within_range(imu, &range) {
            Some((kept, out)) => (std::borrow::Cow::Owned(kept), out),
            None => (std::borrow::Cow::Borrowed(imu), Vec::new()),
        };
        let level_infos = source.levels()?;
        let levels = DbLevel::of(&level_infos);
        if levels.is_empty() {
            return Err(trn_view::SourceError("the landmark database has no templates".into()));
        }
        let near = trn_view::visible::terrain_near(source, &levels, &init.position)?;
        let terrain_h_m = near.height_m;
        let (lighting, lit_for_flight) = choose_lighting(&source.suns()?, params.sun.as_ref());
        // Until a fix says which levels the camera sees: the finest.
        let finest_gsd_m = level_infos.iter().map(|l| l.gsd_m).fold(f64::INFINITY, f64::min);
        let map_start = map_sigmas_for_gsd(&params, finest_gsd_m);
        // The calibration whose focal length the inertial filter carries.
        let focal_prior = params.calibration.filter(|c| {
            params.filter == FilterMode::Tight
                && params.inertial_focal
                && CalibrationFilter::new(camera.model, *c).focal_only()
        });
        // The calibration whose principal point the inertial filter carries.
        let principal_prior = params.calibration.filter(|c| {
            params.filter == FilterMode::Tight
                && (params.inertial_principal_point || params.principal_point_from_tracks)
                && !c.principal_point
        });
        let imu_gap_s = crate::propagate::gap_limit_s(&imu, crate::IMU_GAP_FACTOR).unwrap_or(0.0);
        let ins = (params.filter != FilterMode::Fixes && params.use_gyro).then(|| {
            let q_imu_cam = camera.q_cam_imu().inverse();
            let state = InsState {
                t: init.t,
                position: init.position.to_ecef(),
                velocity_ecef_m_s: Vector3::zeros(),
                q_ecef_imu: init.q_ecef_cam * q_imu_cam.inverse(),
                gyro_bias_imu_rad_s: Vector3::zeros(),
                accel_bias_imu_m_s2: Vector3::zeros(),
                map_offset_ecef_m: Vector3::zeros(),
                map_offset_att_rad: Vector3::zeros(),
                time_offset_s: 0.0,
                rate_ecef_rad_s: Vector3::zeros(),
            };
            let deg_s = |d: f64| d.to_radians();
            let mut f = InsFilter::new(
                state,
                &InsInit {
                    attitude_rad: params.init_sigma_deg.to_radians(),
                    // `init_sigma_m` is the 3D sigma, as the search's.
                    position_m: params.init_sigma_m / 3f64.sqrt(),
                    velocity_m_s: params.init_velocity_sigma_m_s,
                    gyro_bias_rad_s: deg_s(params.gyro_bias_deg_s),
                    accel_bias_m_s2: params.accel_bias_m_s2,
                    time_offset_s: params.time_offset_sigma_s,
                    focal_rel: focal_prior.map_or(0.0, |c| c.focal_sigma_rel),
                    principal_px: principal_prior.map_or(0.0, |c| c.principal_sigma_px),
                },
                InsErrors {
                    gyro_arw_rad_sqrt_s: deg_s(params.gyro_arw_deg_sqrt_s),
                    gyro_bias_walk_rad_s_sqrt_s: deg_s(params.gyro_bias_walk_deg_s_sqrt_s),
                    accel_vrw_m_s_sqrt_s: params.accel_vrw_m_s_sqrt_s,
                    accel_bias_walk_m_s2_sqrt_s: params.accel_bias_walk_m_s2_sqrt_s,
                    free_accel_m_s2_sqrt_s: params.free_accel_m_s2_sqrt_s,
                    map_sigma_m: map_start.0,
                    map_tau_s: params.map_tau_s,
                    map_att_sigma_rad: map_start.1.to_radians(),
                    focal_walk_rel_sqrt_s: focal_prior.map_or(0.0, |c| c.focal_walk_rel_sqrt_s),
                    principal_walk_px_sqrt_s: principal_prior.map_or(0.0, |c| c.principal_walk_px_sqrt_s),
                    gyro_max_jump_rad_s: deg_s(params.gyro_max_jump_deg_s),
                    accel_max_jump_m_s2: params.accel_max_jump_m_s2,
                    imu_gap_s,
                    gap_rate_walk_rad_s_sqrt_s: deg_s(params.imu_gap_doubt_deg_s_sqrt_s),
                },
            );
            f.principal_from_fixes = !params.principal_point_from_tracks;
            f
        });
        let init_h = HeightReference {
            t: init.t,
            h_m: init.position.h_m,
            extra_allowance_m: 3.0 * params.init_sigma_m,
        };
        Ok(Self {
            source,
            camera: camera.model,
            calibration: params.calibration.map(|p| CalibrationFilter::new(camera.model, p)),
            lut_camera: camera.model,
            q_imu_cam: camera.q_cam_imu().inverse(),
            imu,
            imu_out_of_range,
            lut: UndistortLut::new(&camera.model, PYRAMID_LEVELS),
            levels,
            lighting,
            lit_for_flight,
            cache: Default::default(),
            t: init.t,
            pose: CameraPose::new(init.position.to_ecef(), init.q_ecef_cam),
            sigma_m: params.init_sigma_m,
            filter: AttitudeFilter::new(
                params.init_sigma_deg.to_radians(),
                GyroErrors {
                    arw_rad_sqrt_s: params.gyro_arw_deg_sqrt_s.to_radians(),
                    bias_rad_s: params.gyro_bias_deg_s.to_radians(),
                    bias_walk_rad_s_sqrt_s: params.gyro_bias_walk_deg_s_sqrt_s.to_radians(),
                },
            ),
            params,
            last_fix: None,
            init_h,
            imu_gap_s,
            recent_fixes: Default::default(),
            velocity_sigma: None,
            velocity: Vector3::zeros(),
            terrain_h_m,
            ins,
            track: None,
            guess_doubted: false,
            map_doubts: 0,
            map_chi2_max: 0.0,
            own_gyro_jumps: 0,
            own_jump_turn: None,
            jumps_undone: 0,
            fix_attitude: None,
            fix_rate: None,
            misses: 0,
            doubted_frames: 0,
            last_refused: None,
            narrow_inconsistent: 0,
            pool,
            map_sized: false,
            last_sensitivity: IntrinsicsSensitivity::NONE,
            landmark_runs: HashMap::new(),
            acquisition_cursor: 0,
            narrow_cursor: 0,
            heading_cursor: 0,
            wide_searched: false,
            alternation: 0,
            wide_too_wide: false,
            work: Default::default(),
            window_positions: Default::default(),
            tile_landmarks: Default::default(),
            candidate: None,
        })
    }

    /// The pose guess at `t` and its uncertainty: the inertial filter
    /// carried to `t`, or (without it) the attitude through the gyro less
    /// the estimated bias and the position by the velocity of the last fixes.
    fn predict(&self, t: f64) -> Prediction {
        if let Some(ins) = &self.ins {
            let mut f = ins.clone();
            f.propagate(t, &self.imu);
            let (guess, _) = f.apparent_pose(&self.q_imu_cam);
            // The pose's uncertainty as a frame solved with the current
            // camera sees it (the last fix's sensitivity to the intrinsics
            // the filter carries): a lens uncertain by `e` leaves the range
            // uncertain by its share, and the two cancel in the image.
            // Counted apart, they had widened the salt lake's search from
            // 1.6 to 1.7-2.2 px (most frames' radius 7 -> 8 px, 22 -> 29 ms
            // a frame).
            let (_, cov) = f.apparent_pose_with(&self.q_imu_cam, &self.last_sensitivity);
            // What moves the landmarks in the image: the position error
            // across the line of sight, and along it only by the scale it
            // changes (up to the image corner's angle off the boresight).
            let p = cov.fixed_view::<3, 3>(3, 3).into_owned();
            let b = guess.q_ecef_cam * Vector3::z();
            let along2 = b.dot(&(p * b)).max(0.0);
            let across2 = (p.trace() - along2).max(0.0);
            let corner = self.camera.pixel_to_normalized(Pixel::new(0.0, 0.0));
            let tan_corner2 = corner.x * corner.x + corner.y * corner.y;
            return Prediction {
                guess,
                att_cov: cov.fixed_view::<3, 3>(0, 0).into_owned(),
                sigma_m: (across2 + along2 * tan_corner2).sqrt().max(2.0),
                pose_cov: Some(cov),
                jump_turn: f.jump_turn,
                filter: Carried::Ins(f),
                gyro_jumps: 0,
            };
        }
        let dt = t - self.t;
        let position = trn_geodesy::Ecef(self.pose.position.0 + self.velocity * dt);
        // The last fix's position error, plus the velocity's error over the
        // gap (unknown before two fixes).
        let v_sigma = self.velocity_sigma.unwrap_or(self.params.velocity_sigma_m_s);
        let sigma_m = self.sigma_m + v_sigma * dt.max(0.0);
        let mut jump_turn = self.own_jump_turn;
        let (guess, attitude, gyro_jumps) = if self.params.use_gyro {
            let q_ecef_imu = self.pose.q_ecef_cam * self.q_imu_cam.inverse();
            let p = propagate_with_bias(q_ecef_imu, self.t, t, &self.imu, &self.filter.bias_imu_rad_s);
            let mut cov = self.filter.propagated(&p.bias_to_attitude, dt);
            self.doubt_unmeasured(&mut cov, t);
            let jumps = self.doubt_jumps(&mut cov, t, &q_ecef_imu, &mut jump_turn);
            let (turn, turn_var) = self.fix_rate_turn(self.t, t);
            for i in 0..3 {
                cov[(i, i)] += turn_var;
            }
            (CameraPose::new(position, turn * p.q_ecef_imu * self.q_imu_cam), cov, jumps)
        } else {
            // Without the gyro the attitude is only known at fixes.
            let mut cov = self.filter.covariance;
            let grow = (10.0f64.to_radians() * dt.max(0.5)).powi(2);
            for i in 0..3 {
                cov[(i, i)] += grow;
            }
            (CameraPose::new(position, self.pose.q_ecef_cam), cov, 0)
        };
        let att_cov = attitude.fixed_view::<3, 3>(0, 0).into_owned();
        Prediction {
            guess,
            att_cov,
            sigma_m,
            pose_cov: None,
            filter: Carried::Attitude(attitude),
            gyro_jumps,
            jump_turn,
        }
    }

    /// [`FilterMode::Fixes`]: the gyro's jumps between the last frame and
    /// `t` (`--gyro-max-jump`, as the inertial filter watches them,
    /// [`crate::ins::InsErrors::gyro_max_jump_rad_s`]): the angle each
    /// turns beyond the rate before it, for [`GYRO_JUMP_MAX_S`] at most and
    /// up to [`GYRO_JUMP_MAX_ANGLE_DEG`], is added to `cov`'s attitude
    /// variance along its axis (ECEF, through `q_ecef_imu`, the attitude at
    /// the last frame). The watch starts from the sample before the last
    /// frame, and again after a gap. The turns, uncapped, are added to
    /// `turned`. Returns the jumps seen.
    fn doubt_jumps(
        &self,
        cov: &mut Matrix6<f64>,
        t: f64,
        q_ecef_imu: &UnitQuaternion<f64>,
        turned: &mut Option<JumpTurn>,
    ) -> usize {
        let limit = self.params.gyro_max_jump_deg_s.to_radians();
        if !(limit > 0.0) || !(t > self.t) {
            return 0;
        }
        let imu = &self.imu[..];
        let mut watch = JumpWatch::default();
        let mut first = true;
        let cap = GYRO_JUMP_MAX_ANGLE_DEG.to_radians();
        for_each_segment(imu, self.t, t, |a, b, sample| {
            let Some(k) = sample else { return };
            if ends_gap(imu, k, self.imu_gap_s) {
                watch.restart(Some(imu[k].w_imu_rad_s));
                first = false;
                return;
            }
            if first {
                watch.restart(k.checked_sub(1).map(|j| imu[j].w_imu_rad_s));
                first = false;
            }
            if let Some((beyond, added)) =
                watch.watch(&imu[k].w_imu_rad_s, b - a, limit, GYRO_JUMP_MAX_S, cap)
            {
                JumpTurn::add(turned, a, q_ecef_imu * beyond * (b - a));
                if let Some(axis) = (q_ecef_imu * beyond).try_normalize(1e-12) {
                    let mut att = cov.fixed_view_mut::<3, 3>(0, 0);
                    att += axis * axis.transpose() * added;
                }
            }
        });
        watch.count
    }

    /// [`FilterMode::Fixes`]: the attitude doubt (`cov`'s attitude block,
    /// rad²) of the time since the last frame no gyro sample measures (a
    /// gap, before the log's first sample or after its last;
    /// [`unmeasured_attitude_variance`], the rate's error walking by
    /// `--imu-gap-doubt` up to [`HELD_RATE_MAX_DEG_S`]), up to
    /// [`IMU_GAP_MAX_ANGLE_DEG`] per axis (a larger doubt, after misses,
    /// stays). Without it, the 30 km oblique balloon with its IMU silent for
    /// 3 s (`scripts/bench_faults.sh`) came out of the gap 2 deg off with a
    /// search sized for a tenth of that, and fixed 24 of 121 frames.
    fn doubt_unmeasured(&self, cov: &mut Matrix6<f64>, t: f64) {
        let starts = WalkStarts {
            before_log_t: self.init_h.t,
            after_log_t: self.fix_rate.map_or(f64::NEG_INFINITY, |r| r.t),
        };
        let v = unmeasured_attitude_variance(
            &self.imu,
            self.t,
            t,
            starts,
            self.imu_gap_s,
            self.params.imu_gap_doubt_deg_s_sqrt_s.to_radians(),
            HELD_RATE_MAX_DEG_S.to_radians(),
        );
        if !(v > 0.0) {
            return;
        }
        let cap = IMU_GAP_MAX_ANGLE_DEG.to_radians().powi(2);
        for i in 0..3 {
            let before = cov[(i, i)];
            cov[(i, i)] = (before + v).min(before.max(cap));
        }
    }

    /// [`FilterMode::Fixes`]: the turn (ECEF, on the left of the attitude)
    /// of the rate the fixes measured after the IMU log ([`FixRate`]) over
    /// the part of `[t0, t1]` after the log's last sample, and the attitude
    /// variance (rad² per axis) its error adds there; none without it.
    fn fix_rate_turn(&self, t0: f64, t1: f64) -> (UnitQuaternion<f64>, f64) {
        let (Some(r), Some(end)) = (self.fix_rate, self.imu.last().map(|x| x.t)) else {
            return (UnitQuaternion::identity(), 0.0);
        };
        let d = t1 - t0.max(end);
        if !(d > 0.0) {
            return (UnitQuaternion::identity(), 0.0);
        }
        r.turn(d)
    }

    /// [`FilterMode::Fixes`]: the rate the fix at `t` (attitude `q_ecef_cam`,
    /// its variance `var` per axis) and the one before measure where the
    /// IMU log has ended ([`FixRate`]; `None` otherwise).
    fn fix_rate_at(&mut self, t: f64, q_ecef_cam: UnitQuaternion<f64>, var: f64) -> Option<FixRate> {
        let later = FixAttitude { t, q_ecef_cam, var_rad2: var };
        let earlier = self.fix_attitude.replace(later)?;
        let end = self.imu.last()?.t;
        if earlier.t < end {
            return None;
        }
        FixRate::between(&earlier, &later, self.fix_rate.as_ref())
    }

    /// The camera for a frame at `t`: the calibration's estimate, with the
    /// undistortion table remade once it moved a corner by a fifth of a pixel.
    fn update_camera(&mut self, t: f64) {
        let Some(cal) = &mut self.calibration else { return };
        cal.propagate(t);
        self.camera = cal.camera();
        let corner = |m: &CameraModel| {
            let n = self.lut_camera.pixel_to_normalized(Pixel::new(0.0, 0.0));
            m.normalized_to_pixel(n)
        };
        if corner(&self.camera).distance_px(&corner(&self.lut_camera)) > 0.2 {
            self.lut = UndistortLut::new(&self.camera, PYRAMID_LEVELS);
            self.lut_camera = self.camera;
        }
    }

    /// A frame's evidence on the camera's intrinsics (`None`: no
    /// self-calibration, or too few inliers).
    fn calibration_frame(&self, sol: &Solution) -> Option<FrameCalibration> {
        let cal = self.calibration.as_ref()?;
        let (px, pts) = inliers_of(sol);
        let sigma_px = inlier_rms_px(sol).max(CALIBRATION_MIN_SIGMA_PX);
        let height_sigma = cal.params().landmark_height_sigma_m;
        frame_calibration(&self.camera, &px, &pts, &sol.pose, sigma_px, height_sigma, Some(HUBER_PX))
    }

    /// What the camera's remaining calibration uncertainty adds to a pose
    /// from `frame` (zero without self-calibration).
    fn calibration_consider(&self, frame: Option<&FrameCalibration>) -> Matrix6<f64> {
        match (&self.calibration, frame) {
            (Some(cal), Some(frame)) => cal.pose_covariance(frame),
            _ => Matrix6::zeros(),
        }
    }

    /// The inertial filter in `filter` when it carries the focal length.
    fn focal_carrier(filter: &mut Carried) -> Option<&mut InsFilter> {
        match filter {
            Carried::Ins(f) if f.estimates_focal() => Some(f),
            _ => None,
        }
    }

    /// Moves the camera (and `pose`, solved with it, by `sensitivity`) by
    /// the focal error the inertial filter has estimated, which restarts
    /// at zero.
    fn take_focal(&mut self, f: &mut InsFilter, pose: Option<(&mut CameraPose, &IntrinsicsSensitivity)>) {
        let Some(cal) = &mut self.calibration else { return };
        let (d, var) = f.take_focal_error();
        cal.shift_focal(d, var);
        self.camera = cal.camera();
        debug!(
            "t {:.3}: focal length {:+.4}% +- {:.4}% (the inertial filter moved it {:+.4}%)",
            f.state.t,
            cal.correction().focal_rel * 100.0,
            var.sqrt() * 100.0,
            d * 100.0
        );
        if let Some((pose, s)) = pose {
            *pose = perturb_pose(pose, &(s.0.column(0) * d));
        }
    }

    /// Moves the camera's principal point by the error the inertial filter
    /// has estimated, which restarts at zero.
    fn take_principal_point(&mut self, f: &mut InsFilter) {
        let Some(cal) = &mut self.calibration else { return };
        let (d, cov) = f.take_principal_error();
        cal.shift_principal(d, cov);
        self.camera = cal.camera();
        let c = cal.correction();
        debug!(
            "t {:.3}: principal point {:+.2} {:+.2} px +- {:.2} {:.2} (the inertial filter moved it {:+.2} {:+.2})",
            f.state.t,
            c.principal_du_px,
            c.principal_dv_px,
            cov[(0, 0)].sqrt(),
            cov[(1, 1)].sqrt(),
            d.x,
            d.y
        );
    }

    /// Moves the camera by whatever intrinsics the inertial filter carries
    /// and has learnt since the last take.
    fn take_intrinsics(&mut self, f: &mut InsFilter) {
        if f.estimates_focal() {
            self.take_focal(f, None);
        }
        if f.estimates_principal_point() {
            self.take_principal_point(f);
        }
    }

    /// The intrinsics the inertial filter in `filter` carries.
    fn carried_intrinsics(filter: &Carried) -> CarriedIntrinsics {
        match filter {
            Carried::Ins(f) => CarriedIntrinsics {
                focal: f.estimates_focal(),
                principal_point: f.estimates_principal_point(),
            },
            _ => CarriedIntrinsics::default(),
        }
    }

    /// [`prior_gated_update`] for a frame without a fix, with the tight
    /// filter ([`NavParams::prior_gated_update`]).
    fn gated_update(&mut self, t: f64, filter: &mut Carried, found: &[Match]) -> usize {
        let Carried::Ins(f) = filter else { return 0 };
        // Before the first fix the prediction is only the initial guess: its
        // chance matches would shrink the doubt that widens the search.
        if self.params.filter != FilterMode::Tight
            || !self.params.prior_gated_update
            || self.last_fix.is_none()
            || self.guess_doubted
        {
            return 0;
        }
        let n = prior_gated_update(&self.camera, &self.q_imu_cam, f, found, &self.last_sensitivity);
        if n > 0 {
            debug!("t {t:.3}: prior-gated update with {n} matches");
            self.take_intrinsics(f);
        }
        n
    }

    /// [`track_update`] with the last frame's matches, with the tight
    /// filter ([`NavParams::track_update`]), after the first fix; returns
    /// the tracks used (0: no update).
    fn track_update(&self, t: f64, filter: &mut Carried, current: &[TrackPoint]) -> usize {
        let (Carried::Ins(f), Some(anchor)) = (filter, &self.track) else { return 0 };
        if self.params.filter != FilterMode::Tight
            || !self.params.track_update
            || self.last_fix.is_none()
            || self.guess_doubted
        {
            return 0;
        }
        let turn = Some(self.offset_turn(f));
        let Some(o) =
            track_update(&self.camera, &self.q_imu_cam, f, anchor, current, turn, &self.params.track)
        else {
            return 0;
        };
        debug!(
            "t {t:.3}: tracks: {} pairs, {} used, chi2 {:.1} (limit {:.1}), rms {:.3} px, focal moved {:.1} sigma",
            o.pairs, o.used, o.chi2, o.limit, o.rms_px, o.focal_move_z
        );
        o.used
    }

    /// The camera's turn (ECEF, on the left) from the filter's time to the
    /// image's (its time offset later), integrated from the gyro.
    fn offset_turn(&self, f: &InsFilter) -> UnitQuaternion<f64> {
        let s = &f.state;
        turn_over(s.q_ecef_imu, s.t, s.time_offset_s, &self.imu, &s.gyro_bias_imu_rad_s)
    }

    /// Updates the calibration with an accepted fix's inliers and moves the
    /// fix with it; returns the pose covariance the calibration's remaining
    /// uncertainty adds (zero without self-calibration; without the focal
    /// length's share where the inertial filter carries it, which then
    /// takes the frame's evidence).
    fn calibrate(
        &mut self,
        t: f64,
        sol: &mut Solution,
        frame: Option<FrameCalibration>,
        filter: &mut Carried,
    ) -> Matrix6<f64> {
        let Some(frame) = frame else { return Matrix6::zeros() };
        let Some(cal) = &mut self.calibration else { return Matrix6::zeros() };
        let rms = inlier_rms_px(sol);
        let (frame_focal, frame_sigma) = cal.frame_focal(&frame);
        debug!(
            "t {t:.3}: calibration evidence: focal {frame_focal:+.5} sigma {frame_sigma:.5} ({} inliers, rms {rms:.2} px)",
            sol.inliers,
        );
        let carried = Self::carried_intrinsics(filter);
        if let Some(f) = Self::focal_carrier(filter) {
            let prior_var = f.covariance[(FOCAL, FOCAL)];
            if let Some((z, var)) = cal.focal_evidence(t, &frame, prior_var) {
                f.focal_measurement(z, var);
                let sensitivity = IntrinsicsSensitivity::of_frame(&frame.pose_sensitivity);
                self.take_focal(f, Some((&mut sol.pose, &sensitivity)));
                debug!("t {t:.3}: calibration: the frame's focal evidence updated the inertial filter");
            }
            let cal = self.calibration.as_ref().expect("checked above");
            return cal.pose_covariance_but(&frame, carried);
        }
        match cal.update(t, &frame) {
            Some(step) => {
                sol.pose = perturb_pose(&sol.pose, &(frame.pose_sensitivity * step.relative));
                let c = cal.correction();
                let p = cal.covariance();
                debug!(
                    "t {t:.3}: calibration focal {:+.4}% +- {:.4}%, principal point {:+.2} {:+.2} px +- {:.2} {:.2} (frame chi2 {:.1}, rms {:.2} px)",
                    c.focal_rel * 100.0,
                    p[(0, 0)].sqrt() * 100.0,
                    c.principal_du_px,
                    c.principal_dv_px,
                    p[(1, 1)].sqrt(),
                    p[(2, 2)].sqrt(),
                    step.chi2,
                    rms
                );
                self.camera = cal.camera();
            }
            None => {
                debug!("t {t:.3}: calibration: frame not used (too weak, or inconsistent with the estimate)")
            }
        }
        cal.pose_covariance_but(&frame, carried)
    }

    /// A frame that gave no fix doubts the prediction. Before the first
    /// fix it says the initial guess may be worse than `--init-sigma-m` /
    /// `--init-sigma-deg` claim; after one, [`DOUBT_AFTER_MISSES`] misses
    /// since it ([`Self::count_miss`]: frames whose matches did not agree)
    /// say the filter's pose may be wrong by more than it claims (an IMU
    /// glitch or gap turned the attitude), and each further miss doubts it
    /// (`missed`: this frame was one). Either way the inertial filter's
    /// pose uncertainty doubles (not the velocity's: the next fix then
    /// restarts the pose and doubts the velocity by how far the prediction
    /// had drifted from it since the last fix, [`RESTART_MIN_SPAN_S`]);
    /// without it ([`FilterMode::Fixes`]) the attitude's and the guess's
    /// position sigmas double ([`Self::inflate_guess_within`]). The search
    /// widens frame by frame up to an
    /// acquisition (a guess 3 km off, told 300 m, is fixed on its third
    /// frame), up to sigmas of [`DOUBT_MAX_ATTITUDE_DEG`] and
    /// [`DOUBT_MAX_POSITION_M`].
    fn doubt_prediction(&mut self, t: f64, filter: &mut Carried, missed: bool) {
        let after_fix = self.last_fix.is_some();
        if after_fix && !(missed && self.misses >= DOUBT_AFTER_MISSES) {
            return;
        }
        let (k_att, k_pos) = match filter {
            Carried::Ins(f) => {
                f.inflate_pose_within(2.0, DOUBT_MAX_ATTITUDE_DEG.to_radians(), DOUBT_MAX_POSITION_M)
            }
            Carried::Attitude(cov) => self.inflate_guess_within(cov, 2.0),
        };
        if !after_fix {
            debug!("t {t:.3}: no fix yet: the guess's uncertainty grows (attitude x{k_att:.2}, position x{k_pos:.2})");
        } else {
            if !self.guess_doubted {
                info!("t {t:.3}: {} frames without a fix: the filter's pose is doubted until an image confirms one", self.misses);
            }
            debug!("t {t:.3}: {} frames without a fix: the pose's uncertainty grows (attitude x{k_att:.2}, position x{k_pos:.2})", self.misses);
            self.doubted_frames += 1;
        }
        self.guess_doubted = true;
    }

    /// After an accepted fix: a map offset estimated beyond
    /// [`MAP_DOUBT_CHI2`] of its prior ([`InsFilter::map_offset_distance`])
    /// restarts it ([`InsFilter::restart_map_offset`]): the images were
    /// being explained by a database error the model does not allow, which
    /// is what a velocity gone wrong (an accelerometer's error the filter
    /// trusted) looks like through a narrow view, whose shift a map tilt
    /// passes for. Returns the fix's new covariance when it did.
    fn doubt_map_offset(&mut self, t: f64, calibration_cov: &Matrix6<f64>) -> Option<Matrix6<f64>> {
        let f = self.ins.as_mut()?;
        let d2 = f.map_offset_distance();
        self.map_chi2_max = self.map_chi2_max.max(d2);
        if !(d2 > MAP_DOUBT_CHI2) {
            return None;
        }
        info!("t {t:.3}: the map offset is {d2:.1} (chi-square) from its prior: restarted, the pose as the images see it, its uncertainty doubled");
        f.restart_map_offset(2.0, MAP_DOUBT_VELOCITY_M_S);
        self.map_doubts += 1;
        let (pose, cov) = f.pose(&self.q_imu_cam);
        self.pose = pose;
        Some(cov + calibration_cov)
    }

    /// The IMU log the navigator uses: the flight's, less any sample
    /// beyond the sensors' range ([`NavParams::gyro_range_deg_s`]).
    pub fn imu(&self) -> &[ImuSample] {
        &self.imu
    }

    /// The times of the IMU samples left out as beyond the sensors' range.
    pub fn imu_out_of_range(&self) -> &[f64] {
        &self.imu_out_of_range
    }

    /// The gyro's jumps doubted (`--gyro-max-jump`): the inertial filter's,
    /// or without it ([`FilterMode::Fixes`]) the navigator's own.
    pub fn gyro_jumps(&self) -> usize {
        self.ins.as_ref().map_or(self.own_gyro_jumps, |f| f.gyro_jumps())
    }

    /// Frames that found their landmarks with the gyro's jumps since the
    /// fix before undone: a frame whose own search did not stand after a
    /// jump beyond its doubt, searched again as if the jump had been a
    /// glitch (the inertial filter then takes the undo; with [`FilterMode::Fixes`], an
    /// accepted fix so found).
    pub fn gyro_jumps_undone(&self) -> usize {
        self.jumps_undone
    }

    /// Fixes after which the map offset was restarted ([`MAP_DOUBT_CHI2`]).
    pub fn map_doubts(&self) -> usize {
        self.map_doubts
    }

    /// The largest chi-square of the map offset in its prior that an
    /// accepted fix found (before any restart; 0 without the inertial
    /// filter or a fix).
    pub fn map_chi2_max(&self) -> f64 {
        self.map_chi2_max
    }

    /// Counts a frame without a fix as a miss when its search found as
    /// many matches as a fix needs (`--min-inliers`) and they did not agree
    /// (no solution, too few inliers or too small a share of them): the
    /// image showed landmarks where the prediction did not put them. A
    /// frame with fewer matches (a cloud, a blank image) says nothing of the
    /// pose and leaves it to the IMU, and nor does one whose matches agreed
    /// but were refused for another reason (inliers in a cluster: a hole in
    /// a cloud). Returns whether it counted.
    fn count_miss(&mut self, matches: usize) -> bool {
        let missed = matches >= self.params.min_inliers;
        self.misses += usize::from(missed);
        missed
    }

    /// Whether a frame whose matches at `px` did not agree is a narrow
    /// view's, not to be counted as a miss ([`NavParams::miss_min_cells`]).
    fn narrow_miss(&self, t: f64, px: impl Iterator<Item = Pixel>) -> bool {
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        let narrow = narrow_miss(px, w, h, self.params.grid, self.params.miss_min_cells);
        if narrow {
            debug!("t {t:.3}: matches that do not agree in a narrow view: not counted as a miss");
        }
        narrow
    }

    /// Frames whose miss, after a fix, doubted the filter's pose (after
    /// four frames whose matches did not agree, each further one doubles its
    /// attitude and position sigmas).
    pub fn doubted_frames(&self) -> usize {
        self.doubted_frames
    }

    /// Inconsistent fixes of a narrow view that did not doubt the filter
    /// ([`NavParams::doubt_min_cells`]: none before them since the last
    /// accepted fix, or the one before said otherwise).
    pub fn narrow_inconsistent(&self) -> usize {
        self.narrow_inconsistent
    }

    /// [`FilterMode::Fixes`]: the pose's doubt after misses
    /// ([`Self::doubt_prediction`]): the attitude sigmas (`cov`, the
    /// attitude filter's carried covariance) and the position's
    /// (`sigma_m`) by `factor`, up to [`DOUBT_MAX_ATTITUDE_DEG`] and
    /// [`DOUBT_MAX_POSITION_M`]; the factors applied.
    fn inflate_guess_within(&mut self, cov: &mut Matrix6<f64>, factor: f64) -> (f64, f64) {
        let worst = (0..3).map(|i| cov[(i, i)]).fold(0.0, f64::max).sqrt();
        let k_att = doubt_factor(worst, DOUBT_MAX_ATTITUDE_DEG.to_radians(), factor);
        for i in 0..6 {
            for j in 0..6 {
                cov[(i, j)] *= if i < 3 { k_att } else { 1.0 } * if j < 3 { k_att } else { 1.0 };
            }
        }
        let k_pos = doubt_factor(self.sigma_m, DOUBT_MAX_POSITION_M, factor);
        self.sigma_m *= k_pos;
        (k_att, k_pos)
    }

    /// The pose to report for a frame without an accepted fix.
    fn carry(&mut self, t: f64, pred: Prediction) {
        match pred.filter {
            Carried::Attitude(attitude) => {
                self.sigma_m += self.params.velocity_sigma_m_s * (t - self.t).max(0.0);
                self.filter.carry(attitude);
                self.pose = pred.guess;
                self.own_jump_turn = pred.jump_turn;
            }
            Carried::Ins(f) => {
                self.pose = f.pose(&self.q_imu_cam).0;
                self.ins = Some(f);
            }
        }
        self.t = t;
    }

    /// The frame's inliers refined at full resolution from its pose, alone
    /// or with a pose prior (the inertial filter's prediction).
    /// Its pixel sigma is the inliers' RMS residual per coordinate: what
    /// the matches scatter by, not what the correlation resolves.
    fn refine_inliers(&self, sol: &Solution, pose_prior: Option<PosePrior>) -> Option<Refined> {
        let (px, pts) = inliers_of(sol);
        let opts = RefineOptions {
            pose_prior,
            huber_px: Some(REFINE_HUBER_PX),
            pixel_sigma: (inlier_rms_px(sol) / 2f64.sqrt()).max(REFINE_SIGMA_PX),
            ..RefineOptions::default()
        };
        let sigmas = inlier_sigmas_px(sol, &self.landmark_runs);
        refine_pose_weighted(&self.camera, &px, &pts, Some(&sigmas), &sol.pose, &opts)
    }

    /// Whether the frame's image-only pose agrees with the inertial filter's
    /// prediction ([`NavParams::innovation_gate_chi2`]): the rejection if
    /// not, and the pose's innovation against the prediction (`[dtheta;
    /// dp]`) with its own covariance, for [`innovations_agree`] (`None`
    /// when its inliers give no pose).
    /// `consider`: the calibration's share of the pose's uncertainty.
    fn consistency(
        &self,
        t: f64,
        f: &InsFilter,
        sol: &Solution,
        consider: &Matrix6<f64>,
    ) -> (Option<Rejection>, Option<Innovation>) {
        let Some(r) = self.refine_inliers(sol, None) else { return (None, None) };
        let (y, chi2) = f.innovation(&self.q_imu_cam, &r.pose, &(r.covariance + consider));
        let chi2 = chi2.unwrap_or(f64::INFINITY);
        debug!("t {t:.3}: innovation chi2 {chi2:.1}");
        let innovation = (y, r.covariance);
        (
            (chi2 > self.params.innovation_gate_chi2).then_some(Rejection::Inconsistent { chi2 }),
            Some(innovation),
        )
    }

    /// Updates the inertial filter with an accepted frame; returns the
    /// covariance of the pose it then estimates. The map offset is first
    /// sized for the frame's landmarks ([`map_sigmas_for_gsd`]).
    fn accept_ins(
        &mut self,
        t: f64,
        mut f: InsFilter,
        sol: &Solution,
        calibration_cov: Matrix6<f64>,
        sensitivity: &IntrinsicsSensitivity,
        since_fix_s: Option<f64>,
    ) -> Matrix6<f64> {
        let q = self.q_imu_cam;
        // The next jumps are measured from this fix.
        f.jump_turn = None;
        if let Some(gsd) = sol.median_gsd_m {
            let (m, deg) = map_sigmas_for_gsd(&self.params, gsd);
            let (was_m, was_rad) = f.map_sigmas();
            if (m - was_m).abs() > 1e-6 * m.max(1.0) || (deg.to_radians() - was_rad).abs() > 1e-12 {
                // The first fix sizes the offset's prior; later ones its
                // process noise only (rescaling a posterior would undo what
                // the fixes said of the pose the images see).
                let prior = !self.map_sized;
                debug!("t {t:.3}: landmarks of {gsd:.1} m: the map offset is {m:.1} m, {deg:.3} deg (prior: {prior})");
                f.resize_map_offset(m, deg.to_radians(), prior);
            }
            self.map_sized = true;
        }
        // A restart counts the landmarks' fixes in a row afresh.
        if sol.acquisition || self.guess_doubted {
            self.landmark_runs.clear();
        }
        match self.params.filter {
            // An acquisition's pose is kilometres from the prediction: as an
            // update, the filter's correlations would turn the jump into
            // kilometres per second of velocity. It restarts the pose.
            // So is a first fix after the guess was doubted: the inflated
            // covariance let it through the gate, and the same
            // correlations would take the jump for velocity. It restarts
            // with the pose's doubt as reported, the calibration's share
            // included: measured (`tests/navigate.rs`, the climbing 640x480
            // rocket 10 km off), a first fix 222 m off with 80 m of sigma
            // (18 inliers) restarted without it, and 6 of its 22 fixes fell
            // outside their 95% bound (mean NEES 4.3 over a band up to 4.1);
            // with it 1 of 22, mean NEES 2.6.
            _ if sol.acquisition || self.guess_doubted => {
                self.guess_doubted = false;
                if let Some(r) = self.refine_inliers(sol, None) {
                    // After fixes were lost, how far the prediction had gone
                    // from what the image sees, over the time since the last
                    // fix, is a velocity error the filter did not allow for
                    // (an accelerometer's error it trusted): its velocity is
                    // doubted as much, so the fixes after find it.
                    let velocity_floor = since_fix_s.map_or(0.0, |dt| {
                        let drift = (r.pose.position.0 - f.pose(&q).0.position.0).norm();
                        drift / dt.max(RESTART_MIN_SPAN_S)
                    });
                    debug!("t {t:.3}: acquired: the filter's pose restarts from the image's (velocity sigma at least {velocity_floor:.1} m/s)");
                    f.reset_pose(&q, &r.pose, &(r.covariance + calibration_cov), velocity_floor, sensitivity);
                    if f.forget_velocity_beyond(self.params.init_velocity_sigma_m_s) {
                        debug!("t {t:.3}: the velocity, doubted beyond the initial guess's, restarts as it");
                    }
                }
            }
            FilterMode::Loose => {
                if let Some(r) = self.refine_inliers(sol, None) {
                    f.update_with_pose(&q, &r.pose, &r.covariance);
                }
            }
            _ => {
                // The map offset as this view's landmarks move its pose.
                if self.params.map_view_sigma_px > 0.0 {
                    let (_, pts) = inliers_of(sol);
                    let sigma = self.params.map_view_sigma_px;
                    if let Some(c) = landmark_error_pose_covariance(&self.camera, &sol.pose, &pts, sigma) {
                        let view = f.map_view_excess(&c);
                        f.set_map_view(&view);
                    }
                }
                // Where the filter carries the focal length or the principal
                // point, the frame's pose moves with their errors (the
                // columns of the others meet zero variances).
                let (pose, covariance) = f.apparent_pose_with(&q, sensitivity);
                if let Some(r) = self.refine_inliers(sol, Some(PosePrior { pose, covariance })) {
                    f.condition_on_pose_with(&q, &r.pose, &r.covariance, sensitivity);
                }
                self.take_intrinsics(&mut f);
            }
        }
        // The fix's inliers, each one more fix in a row.
        let before = std::mem::take(&mut self.landmark_runs);
        self.landmark_runs = sol
            .records
            .iter()
            .filter(|r| r.inlier)
            .map(|r| (r.landmark, 1 + before.get(&r.landmark).copied().unwrap_or(0)))
            .collect();
        let (pose, cov) = f.pose(&q);
        let (v, v_cov) = f.velocity();
        self.velocity = v;
        self.velocity_sigma = Some((v_cov.trace() / 3.0).max(0.0).sqrt());
        self.pose = pose;
        self.t = t;
        self.ins = Some(f);
        cov + calibration_cov
    }

    /// The inertial filter (`None`: [`FilterMode::Fixes`]).
    pub fn inertial(&self) -> Option<&InsFilter> {
        self.ins.as_ref()
    }

    /// The inertial filter's camera pose and covariance carried to every IMU
    /// sample time after its last state and before `t1` (the IMU-rate
    /// output between frames); empty without the filter.
    pub fn poses_until(&self, t1: f64) -> Vec<FilterPose> {
        let Some(ins) = &self.ins else { return Vec::new() };
        let mut f = ins.clone();
        let t0 = f.state.t;
        let from = self.imu.partition_point(|s| s.t <= t0);
        let to = self.imu.partition_point(|s| s.t < t1);
        self.imu[from..to.max(from)]
            .iter()
            .map(|s| {
                f.propagate(s.t, &self.imu);
                let (pose, covariance) = f.pose(&self.q_imu_cam);
                FilterPose { t: s.t, pose, covariance }
            })
            .collect()
    }

    /// The inertial filter's camera pose and covariance at `t` (its last
    /// state carried there when older); `None` without the filter.
    pub fn filter_pose(&self, t: f64) -> Option<FilterPose> {
        let mut f = self.ins.clone()?;
        f.propagate(t, &self.imu);
        let (pose, covariance) = f.pose(&self.q_imu_cam);
        Some(FilterPose { t: f.state.t, pose, covariance })
    }

    /// The camera's self-calibration (`None`: camera.json trusted).
    pub fn calibration(&self) -> Option<&CalibrationFilter> {
        self.calibration.as_ref()
    }

    /// A frame taken at `t` whose image could not be used (unreadable,
    /// missing, or not the camera's size): the pose is carried to `t` by the
    /// gyro or the inertial filter, as a frame under cloud (status
    /// `propagated`; not a miss that doubts the pose, see
    /// [`Self::doubted_frames`]).
    pub fn carry_without_image(&mut self, t: f64) -> NavRecord {
        let start = Instant::now();
        self.update_camera(t);
        let pred = self.predict(t);
        self.own_gyro_jumps += pred.gyro_jumps;
        self.carry(t, pred);
        NavRecord {
            pose: TimedPose {
                t,
                position: self.pose.position.to_geodetic(),
                q_ecef_cam: self.pose.q_ecef_cam,
            },
            status: FixStatus::Propagated,
            inliers: 0,
            matches: 0,
            ms: start.elapsed().as_secs_f64() * 1e3,
        }
    }

    /// Processes one image taken at `t`.
    pub fn process(&mut self, t: f64, image: GreyImage) -> FrameResult {
        let start = Instant::now();
        self.update_camera(t);
        let pred = self.predict(t);
        self.own_gyro_jumps += pred.gyro_jumps;
        // A tiled acquisition of the frame before: this frame searches
        // around it, and a fix there confirms it (an acquisition: the
        // filter restarts from it); else the tiles go on.
        let confirming = self.candidate.take().and_then(|c| self.candidate_prediction(t, &pred, c));
        let was_confirming = confirming.is_some();
        // After a gyro jump, the other hypothesis: it was a glitch.
        let undo = self.jump_undone_prediction(t, &pred).map(|p| (p, image.clone()));
        let outcome = match confirming {
            Some(around) => self.solve(t, &around, image).map(|mut sol| {
                debug!("t {t:.3}: searched around the acquisition of the frame before");
                sol.acquisition = true;
                sol
            }),
            None => self.solve(t, &pred, image),
        };
        // The jumps undone and the guess they gave, when that search stood.
        // (An acquisition in a tile away from the guess would wait for the
        // next frame to confirm it: the jumps undone may explain this one.)
        let held_tile = matches!(&outcome, Ok(sol) if sol.tile.is_some());
        let mut undone_pred = None;
        let (outcome, undone) = match undo {
            Some((other, image)) if !self.stands(&outcome) || held_tile => match self.solve(t, &other, image)
            {
                Ok(mut sol) if self.count_check(&sol).is_none() => {
                    debug!("t {t:.3}: the image fixes with the gyro's jumps since the last fix undone");
                    match other.filter {
                        // The inertial filter takes the undo, and the frame
                        // is judged against it as any other (a narrow
                        // view's fix, refused for its spread, still
                        // updates it through its matches).
                        Carried::Ins(_) => {
                            undone_pred = Some(self.take_jumps_undone(t, other));
                            (Ok(sol), None)
                        }
                        // Its pose restarts the attitude filter's, as an
                        // acquisition's.
                        Carried::Attitude(_) => {
                            sol.acquisition = true;
                            (Ok(sol), other.jump_turn.map(|j| (j, other.guess)))
                        }
                    }
                }
                _ => (outcome, None),
            },
            _ => (outcome, None),
        };
        let found = match &outcome {
            Ok(sol) => matches_of(sol),
            Err(e) => e.found.clone(),
        };
        let current: Vec<TrackPoint> = found
            .iter()
            .map(|m| TrackPoint {
                landmark: m.landmark,
                pixel: m.pixel,
                sigma_px: m.sigma_px,
                point_ecef: m.point_ecef,
            })
            .collect();
        let mut pred = undone_pred.unwrap_or(pred);
        let acquisition = matches!(&outcome, Ok(sol) if sol.acquisition);
        let tracked = if acquisition { 0 } else { self.track_update(t, &mut pred.filter, &current) };
        let mut covariance = None;
        let mut rejected = None;
        let mut was_held = false;
        let mut gated_matches = 0;
        let (status, inliers, n_matches, matches, guess_px) = match outcome {
            Ok(mut sol) => {
                let mut rejection = if let Some(r) = self.count_check(&sol) {
                    Some(r)
                } else if let Some(r) = self.spread_check(&sol) {
                    Some(r)
                } else if matches!(pred.filter, Carried::Attitude(_)) || self.last_fix.is_none() {
                    // With the inertial filter, the height gate checks the
                    // first fix against the initial guess; after it the
                    // filter's innovation test (below) judges every fix.
                    self.height_gate(t).check(sol.pose.position.to_geodetic().h_m)
                } else {
                    None
                };
                if let Some(reported) = held(rejection, sol.tile, sol.acquisition, was_confirming) {
                    debug!("t {t:.3}: acquisition held for the next frame to confirm ({rejection:?})");
                    let sigma_m = sol.position_covariance().trace().sqrt();
                    self.candidate = Some(Candidate { t, pose: sol.pose, sigma_m });
                    rejection = Some(reported);
                    was_held = true;
                }
                let frame = if rejection.is_none() { self.calibration_frame(&sol) } else { None };
                // An acquisition searched the whole prior: nothing to test
                // it against (its pose restarts the filter's, below).
                let mut innovation = None;
                if let (None, Carried::Ins(f), false) = (rejection, &pred.filter, sol.acquisition) {
                    let consider = self.calibration_consider(frame.as_ref());
                    (rejection, innovation) = self.consistency(t, f, &sol, &consider);
                }
                rejected = rejection;
                let accepted = rejection.is_none();
                if accepted {
                    let sensitivity = frame.as_ref().map_or(IntrinsicsSensitivity::NONE, |fr| {
                        IntrinsicsSensitivity::of_frame(&fr.pose_sensitivity)
                    });
                    if frame.is_some() {
                        self.last_sensitivity = sensitivity;
                    }
                    let calibration_cov = self.calibrate(t, &mut sol, frame, &mut pred.filter);
                    let since_fix_s = self.last_fix.map(|(t0, _)| t - t0);
                    self.last_fix = Some((t, sol.pose));
                    self.last_refused = None;
                    self.search_afresh();
                    let ecef = match pred.filter {
                        Carried::Ins(f) => {
                            self.accept_ins(t, f, &sol, calibration_cov, &sensitivity, since_fix_s)
                        }
                        Carried::Attitude(attitude) => {
                            let guess = undone.map_or(pred.guess, |u| u.1);
                            self.accept_fix(t, &guess, &attitude, &sol)
                                + calibration_cov
                                + map_offset_covariance(&self.params, sol.median_gsd_m)
                        }
                    };
                    if let Some((j, _)) = undone {
                        self.jumps_undone += 1;
                        info!(
                            "t {t:.3}: the gyro's jump(s) since {:.3} s ({:.1} deg) taken for a glitch: the image fixes with them undone",
                            j.since_t,
                            j.turn_ecef_rad.norm().to_degrees()
                        );
                    }
                    self.log_fix(t, &ecef);
                    let ecef = self.doubt_map_offset(t, &calibration_cov).unwrap_or(ecef);
                    covariance = Some(PoseCovariance { t, position: self.pose.position.to_geodetic(), ecef });
                } else {
                    debug!("t {t:.3}: fix rejected ({} inliers): {rejection:?}", sol.inliers);
                    let disagreed = matches!(
                        rejection,
                        Some(Rejection::FewInliers { .. } | Rejection::InlierShare { .. })
                    );
                    let px = sol.records.iter().map(|r| Pixel::new(r.u, r.v));
                    let missed = disagreed && !self.narrow_miss(t, px) && self.count_miss(sol.n_matches);
                    if let (Some(Rejection::Inconsistent { .. }), Carried::Ins(f)) =
                        (rejection, &mut pred.filter)
                    {
                        // The image says the filter may be wrong: doubt it,
                        // so the next frames search wider and a run of such
                        // frames gets through the gate; a narrow view's
                        // says less, unless the one before said the same
                        // ([`doubts_filter`]).
                        let agrees = match (&self.last_refused, &innovation) {
                            (Some((y0, r0)), Some((y, r))) => {
                                innovations_agree(y0, r0, y, r, self.params.innovation_gate_chi2)
                            }
                            _ => false,
                        };
                        self.last_refused = innovation;
                        let (cells, _) = self.inlier_cells(&sol);
                        let confirmed = self.last_fix.is_some() && !self.guess_doubted;
                        if doubts_filter(cells, self.params.doubt_min_cells, agrees, confirmed) {
                            f.inflate(2.0);
                        } else {
                            debug!(
                                "t {t:.3}: an inconsistent fix of a narrow view ({cells} cells), not as the one before: the filter is not doubted for it"
                            );
                            self.narrow_inconsistent += 1;
                        }
                        self.guess_doubted |= self.last_fix.is_none();
                    } else {
                        if !sol.acquisition && !matches!(rejection, Some(Rejection::Height { .. })) {
                            gated_matches = self.gated_update(t, &mut pred.filter, &found);
                        }
                        self.doubt_prediction(t, &mut pred.filter, missed);
                    }
                    self.carry(t, pred);
                }
                let status = if accepted { FixStatus::Fix } else { FixStatus::Propagated };
                (status, sol.inliers, sol.n_matches, sol.records, sol.guess_px)
            }
            Err(NoSolution { matches, found }) => {
                let missed = !self.narrow_miss(t, found.iter().map(|m| m.pixel)) && self.count_miss(matches);
                gated_matches = self.gated_update(t, &mut pred.filter, &found);
                self.doubt_prediction(t, &mut pred.filter, missed);
                self.carry(t, pred);
                (FixStatus::Propagated, 0, matches, Vec::new(), Vec::new())
            }
        };
        if let Some(f) = &self.ins {
            self.track = Some(TrackAnchor::of(f, &self.q_imu_cam, current, Some(self.offset_turn(f))));
        }
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let g = self.pose.position.to_geodetic();
        FrameResult {
            record: NavRecord {
                pose: TimedPose { t, position: g, q_ecef_cam: self.pose.q_ecef_cam },
                status,
                inliers: inliers as u32,
                matches: n_matches as u32,
                ms,
            },
            matches: matches
                .into_iter()
                .map(|mut m| {
                    m.t = t;
                    m
                })
                .collect(),
            guess_px,
            covariance,
            rejection: rejected,
            held: was_held,
            gated_matches,
            tracked,
        }
    }

    /// An accepted fix without the inertial filter: the fix is the pose;
    /// the velocity is fitted to the last fixes, the attitude filter updated.
    /// Returns the fix's covariance.
    fn accept_fix(
        &mut self,
        t: f64,
        guess: &CameraPose,
        attitude: &Matrix6<f64>,
        sol: &Solution,
    ) -> Matrix6<f64> {
        // A doubted pose ([`Self::doubt_prediction`]) is confirmed, and
        // with it the attitude after any gyro jump.
        self.guess_doubted = false;
        self.own_jump_turn = None;
        let att_var = sol.attitude_covariance().trace() / 3.0;
        let rate = self.fix_rate_at(t, sol.pose.q_ecef_cam, att_var);
        if let (Some(r), None) = (rate, self.fix_rate) {
            info!(
                "t {t:.3} s: after the IMU log's end, the last two fixes measure the body's rate: \
                 {:.2} deg/s (sigma {:.2} deg/s per axis), carried on where no gyro measures",
                r.w_ecef_rad_s.norm().to_degrees(),
                r.sigma_rad_s.to_degrees()
            );
        }
        self.fix_rate = rate;
        self.recent_fixes.push_back((t, sol.pose.position.0));
        while self.recent_fixes.front().is_some_and(|f| t - f.0 > VELOCITY_WINDOW_S) {
            self.recent_fixes.pop_front();
        }
        if let Some((v, sigma)) = velocity_fit(&self.recent_fixes) {
            self.velocity = v;
            self.velocity_sigma = Some(sigma);
        }
        self.pose = sol.pose;
        self.t = t;
        // The covariance of a fix from few matches is pessimistic;
        // the next search only needs to cover a plausible miss.
        let att_cov = sol.attitude_covariance();
        self.sigma_m = sol.position_covariance().trace().max(0.0).sqrt().clamp(2.0, 200.0);
        if !self.params.use_gyro || sol.prior_loosened {
            self.filter.reset_attitude(attitude, &att_cov);
        } else {
            let dtheta = rotation_vector(&(sol.pose.q_ecef_cam * guess.q_ecef_cam.inverse()));
            self.filter.update(attitude, &dtheta, &att_cov);
        }
        sol.covariance * fit_variance_factor(sol)
    }

    /// The accepted estimate's covariance `cov` (as reported), velocity and
    /// gyro bias, at debug level.
    fn log_fix(&self, t: f64, cov: &Matrix6<f64>) {
        if !tracing::enabled!(tracing::Level::DEBUG) {
            return;
        }
        let bias = match &self.ins {
            Some(f) => f.state.gyro_bias_imu_rad_s,
            None => self.filter.bias_imu_rad_s,
        };
        let r = trn_geodesy::LocalFrame::at(self.pose.position.to_geodetic()).r_ecef_enu();
        let p = r.transpose() * cov.fixed_view::<3, 3>(0, 0) * r;
        let ps = r.transpose() * cov.fixed_view::<3, 3>(3, 3) * r;
        let v = r.transpose() * self.velocity;
        debug!(
            "t {t:.3}: attitude sigma e/n/u {:.4} {:.4} {:.4} deg, position {:.1} {:.1} {:.1} m, velocity e/n/u {:.1} {:.1} {:.1} m/s (sigma {:.2}), gyro bias {:.2} {:.2} {:.2} deg/h",
            p[(0, 0)].sqrt().to_degrees(),
            p[(1, 1)].sqrt().to_degrees(),
            p[(2, 2)].sqrt().to_degrees(),
            ps[(0, 0)].sqrt(),
            ps[(1, 1)].sqrt(),
            ps[(2, 2)].sqrt(),
            v.x,
            v.y,
            v.z,
            self.velocity_sigma.unwrap_or(f64::NAN),
            bias.x.to_degrees() * 3600.0,
            bias.y.to_degrees() * 3600.0,
            bias.z.to_degrees() * 3600.0,
        );
    }

    /// Whether a search's outcome would stand as a fix by its counts
    /// ([`Self::count_check`]).
    fn stands(&self, outcome: &Result<Solution, NoSolution>) -> bool {
        outcome.as_ref().is_ok_and(|sol| self.count_check(sol).is_none())
    }

    /// `Some` when the solution has too few inliers, or too small a share
    /// of its matches ([`count_rejection`]).
    fn count_check(&self, sol: &Solution) -> Option<Rejection> {
        count_rejection(&self.params, sol)
    }

    /// The ground the camera at `pose` sees (horizon walking, angle filter).
    fn footprint_at(&self, pose: &CameraPose) -> Result<Footprint, trn_view::footprint::FootprintError> {
        let params = FootprintParams {
            step_px: self.params.horizon_step_px,
            alpha_max_deg: self.params.alpha_max_deg,
            terrain_h_m: self.terrain_h_m,
        };
        footprint(&self.camera, pose, &params)
    }

    /// [`inlier_spread`] of the solution's inliers over the image.
    fn inlier_cells(&self, sol: &Solution) -> (usize, f64) {
        let px: Vec<Pixel> = sol.records.iter().filter(|r| r.inlier).map(|r| Pixel::new(r.u, r.v)).collect();
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        inlier_spread(&px, w, h, self.params.grid)
    }

    /// `Some` when the solution's inliers lie on a line or in a cluster.
    fn spread_check(&self, sol: &Solution) -> Option<Rejection> {
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        let (cells, spread_px) = self.inlier_cells(sol);
        (cells < self.params.min_inlier_cells || spread_px < self.params.min_inlier_spread * w.min(h))
            .then_some(Rejection::Spread { cells, spread_px })
    }

    /// The height gate at `t` ([`HeightGate`]).
    fn height_gate(&self, t: f64) -> HeightGate {
        let (reference, v_up) = match self.last_fix {
            Some((t_fix, p)) => {
                let g = p.position.to_geodetic();
                let reference = HeightReference { t: t_fix, h_m: g.h_m, extra_allowance_m: 0.0 };
                (reference, self.velocity_sigma.map(|_| self.velocity.dot(&g.up_ecef())))
            }
            None => (self.init_h, None),
        };
        // Before a velocity is known: with the inertial filter, the speed its
        // initial guess allows (the first fix of a rocket climbing 230 m/s,
        // 13 s after a guess 10 km off, is 2.9 km above it: at 20 m/s the
        // gate refused it, and every later one); without it, the fixes'.
        let unknown_v = match self.ins {
            Some(_) => self.params.init_velocity_sigma_m_s,
            None => self.params.velocity_sigma_m_s,
        };
        let v_sigma = self.velocity_sigma.unwrap_or(unknown_v);
        HeightGate::new(reference, t, v_up, v_sigma, self.params.max_height_jump_m)
    }

    /// Templates of `level` meeting `bbox`, through the per-level cache.
    fn query(&self, bbox: &trn_landmark::GeoBox, level: u8) -> Result<Vec<Template>, trn_view::SourceError> {
        let mut cache = self.cache.borrow_mut();
        let hit = cache.get(&level).is_some_and(|(b, _)| b.contains_box(bbox));
        if !hit {
            // Half the box's size again on every side (across the antimeridian too).
            let big = bbox.grown(0.5 * bbox.lon_span_deg(), 0.5 * (bbox.max_lat_deg - bbox.min_lat_deg));
            let ts = match self.lighting {
                0 => self.source.query(&big, level)?,
                k => self.source.query_lit(&big, level, k)?,
            };
            cache.insert(level, (big, ts));
        }
        let (_, ts) = &cache[&level];
        Ok(ts.iter().filter(|t| t.footprint.intersects(bbox)).cloned().collect())
    }

    /// Template level that fits the local resolution `gsd_m` (m per pixel).
    fn level_for(&self, gsd_m: f64) -> DbLevel {
        trn_view::visible::level_for(&self.levels, gsd_m).expect("levels")
    }

    /// Coarse-to-fine pose from one image ([`Self::stage`] per pyramid level).
    fn solve(&mut self, t: f64, pred: &Prediction, image: GreyImage) -> Result<Solution, NoSolution> {
        let guess = &pred.guess;
        let att_cov = pred.att_cov;
        let prior = self
            .params
            .use_gyro
            .then_some(AttitudePrior { q_ecef_cam: guess.q_ecef_cam, covariance: att_cov });
        let pyr = Pyramid::new(image, PYRAMID_LEVELS);
        let f = self.camera.fx.min(self.camera.fy);
        let fp = self.footprint_at(guess).map_err(|e| {
            debug!("t {t:.3}: {e}");
            NoSolution::default()
        })?;
        // The attitude's and the position's sigmas added: without the
        // filter's covariance, the search's sigma; with it, for the log.
        let added_px = f * (att_cov.trace().sqrt() + pred.sigma_m / fp.center_range_m);
        let sigma_px = pred
            .pose_cov
            .as_ref()
            .and_then(|c| search_sigma_px(&self.camera, guess, c, &fp))
            .unwrap_or(added_px);
        debug!("t {t:.3}: search sigma {sigma_px:.1} px (attitude and position added: {added_px:.1} px)");
        // A search wider than half the focal length (a guess kilometres
        // off) is an acquisition: it may reach the whole image, and the
        // landmarks come from the guessed footprint widened by the search,
        // predicted even where the guess puts them outside the image. Short
        // of that the search stops at a quarter of the focal length, and a
        // failed coarse level falls back to bounded finer searches.
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        let wanted = 2.5 * sigma_px + 3.0;
        let acquisition = wanted > f * ACQUISITION_RADIUS_F;
        let mut radius_full = if acquisition { wanted.min(w.max(h)) } else { wanted.min(f * 0.25) };
        let mut margin_px = if acquisition { radius_full } else { 0.0 };
        // An uncertainty wider than one search reaches (a low camera
        // kilometres off) is searched in tiles, as many a frame as its work budget allows.
        let need_m = wanted / f * fp.center_range_m;
        // (An oblique view's tiles lie closer along its line of sight.)
        let offsets = if acquisition {
            acquisition_tiles(margin_px / f * fp.center_range_m, need_m, sight_line(guess, fp.center_range_m))
        } else {
            Vec::new()
        };
        let mut tiles = with_headings(&offsets, &[0.0], need_m, 0.0);
        // Once that wide layout has been searched over, or a wide search's
        // window has been too wide (from the second lost frame on, not after
        // the whole wide layout: the oblique balloon's ~26 G wide tiles, one a
        // frame, had kept its narrow tiles, which acquire it, waiting 4-6
        // frames), every other lost frame searches the narrow one instead,
        // where it differs and a wide search's window has been too wide.
        let narrow = if acquisition && (self.wide_searched || self.wide_too_wide) {
            self.alternation += 1;
            (self.alternation % 2 == 1)
                .then(|| {
                    self.wide_too_wide
                        .then(|| self.narrow_layout(t, guess, &fp, &att_cov, radius_full, need_m))
                        .flatten()
                })
                .flatten()
        } else {
            None
        };
        let is_narrow = narrow.is_some();
        if let Some((narrow_tiles, radius_px)) = narrow {
            tiles = with_headings(&narrow_tiles, &[0.0], need_m, 0.0);
            radius_full = radius_px;
            margin_px = radius_px;
        }
        let budget = self.params.acquisition_budget_g * 1e9;
        let cursor = if is_narrow { self.narrow_cursor } else { self.acquisition_cursor };
        let mut walk = TileWalk::new(cursor, tiles.len(), budget);
        let (mut outcome, covered) = if tiles.is_empty() {
            // One search covers the whole layout (a fix resets the mark).
            self.wide_searched |= acquisition;
            self.work.set(0);
            let found = self.search_from(&pyr, guess, fp.clone(), radius_full, margin_px, prior.as_ref());
            walk.spend(self.work.get() as f64);
            if acquisition && !is_narrow && self.work.get() > 0 {
                self.wide_too_wide |= self.wide_window_too_wide();
            }
            (found, true)
        } else {
            debug!(
                "t {t:.3}: acquisition in {} {} tiles of {:.0} m: {}.. this frame",
                tiles.len(),
                if is_narrow { "narrow" } else { "wide" },
                ACQUISITION_TILE_SPACING * margin_px / f * fp.center_range_m,
                walk.start
            );
            let found = self.walk_tiles(
                t,
                &pyr,
                guess,
                TileLayout {
                    tiles: &tiles,
                    radius_px: radius_full,
                    kind: if is_narrow { LayoutKind::Narrow } else { LayoutKind::Wide },
                },
                prior.as_ref(),
                &mut walk,
            );
            (found, walk.searched == tiles.len())
        };
        // A wide layout searched over within the frame's work budget, in
        // vain: what is left of the budget goes to the narrow layout's next
        // tiles, wherever it differs (measured, README acquisition: the
        // oblique balloon's one search from a guess 6 km south, on its
        // 128x96 level, took 28 ms and failed at every frame).
        if acquisition && !is_narrow && covered && walk.spent < budget && !self.stands(&outcome) {
            if let Some((narrow_tiles, radius_px)) =
                self.narrow_layout(t, guess, &fp, &att_cov, radius_full, need_m)
            {
                let narrow_tiles = with_headings(&narrow_tiles, &[0.0], need_m, 0.0);
                let mut rest = TileWalk::new(self.narrow_cursor, narrow_tiles.len(), budget - walk.spent);
                debug!(
                    "t {t:.3}: the rest of the budget in {} narrow tiles: {}.. this frame",
                    narrow_tiles.len(),
                    rest.start
                );
                let found = self.walk_tiles(
                    t,
                    &pyr,
                    guess,
                    TileLayout { tiles: &narrow_tiles, radius_px, kind: LayoutKind::Narrow },
                    prior.as_ref(),
                    &mut rest,
                );
                if self.stands(&found) || stronger(&found, &outcome) {
                    outcome = found;
                }
            }
        }
        // Headings besides the guess's, where its doubt about the vertical
        // is more than one search stands (a heading not known, or lost in a
        // spin the gyro did not see): the wide layout's tiles (or the
        // guess's one search) turned to each, a layout of their own with
        // its own cursor and a frame's budget of its own, searched when the
        // guess's heading found nothing (so what that heading finds, and
        // when, is as without them).
        if acquisition && !self.stands(&outcome) {
            let up = local_up(&guess.position);
            let heading_sigma_rad = up.dot(&(att_cov * up)).max(0.0).sqrt();
            let headings = heading_hypotheses(heading_sigma_rad);
            if headings.len() > 1 {
                let reach_rad = (2.5 * heading_sigma_rad).min(std::f64::consts::PI);
                let guess_only = [Vector2::zeros()];
                let at: &[Vector2<f64>] = if offsets.is_empty() { &guess_only } else { &offsets };
                let turned = with_headings(at, &headings[1..], need_m, reach_rad);
                // Its nearest two (the guess's own position at +-10 deg)
                // again at every frame, the cursor past them: the count
                // goes on into tiles kilometres out while the doubt grows,
                // and a view that clears (a hole in the cloud ending) is
                // then found near the guess.
                let mut walk = TileWalk::new(self.heading_cursor, turned.len(), budget).with_head(2);
                debug!(
                    "t {t:.3}: {} headings within {:.0} deg: {} tiles, {}.. this frame",
                    headings.len(),
                    reach_rad.to_degrees(),
                    turned.len(),
                    walk.start
                );
                let found = self.walk_tiles(
                    t,
                    &pyr,
                    guess,
                    TileLayout { tiles: &turned, radius_px: radius_full, kind: LayoutKind::Turned },
                    prior.as_ref(),
                    &mut walk,
                );
                // (Its failures are not the frame's: what the frame reports,
                // and the misses it counts, are the guess's heading's.)
                if self.stands(&found) {
                    outcome = found;
                }
            }
        }
        let mut sol = outcome?;
        // The refined terrain height helps the next footprint.
        if let Some(h) = sol.mean_landmark_h {
            self.terrain_h_m = h;
        }
        // Sorted by landmark, with where the guess put each one.
        let mut order: Vec<usize> = (0..sol.records.len()).collect();
        order.sort_by_key(|&i| sol.records[i].landmark);
        sol.guess_px =
            order.iter().map(|&i| guess.project(&self.camera, &trn_geodesy::Ecef(sol.points[i]))).collect();
        sol.records = order.iter().map(|&i| sol.records[i]).collect();
        Ok(sol)
    }

    /// Searches the tiles of `layout` (offsets from `guess`, east and
    /// north) that `walk` reaches this frame, each its radius around, and
    /// moves the layout's cursor (the narrow layout's, or the wide one's)
    /// on: the first tile whose solution stands by its counts
    /// ([`Self::stands`]), else the strongest failure.
    fn walk_tiles(
        &mut self,
        t: f64,
        pyr: &Pyramid,
        guess: &CameraPose,
        layout: TileLayout,
        prior: Option<&AttitudePrior>,
        walk: &mut TileWalk,
    ) -> Result<Solution, NoSolution> {
        let TileLayout { tiles, radius_px: radius_full, kind } = layout;
        let mut outcome = Err(NoSolution::default());
        while let Some(i) = walk.next_tile() {
            match kind {
                LayoutKind::Turned => self.heading_cursor = walk.cursor(),
                LayoutKind::Narrow => self.narrow_cursor = walk.cursor(),
                LayoutKind::Wide => {
                    self.acquisition_cursor = walk.cursor();
                    // The wide layout has been searched over once.
                    self.wide_searched |= walk.cursor() >= tiles.len();
                }
            }
            let tile = tiles[i];
            let offset = &tile.offset_m;
            let at = match offset {
                o if *o == Vector2::zeros() => *guess,
                o => CameraPose { position: shifted_enu(&guess.position, o), ..*guess },
            };
            let at = turned_about_vertical(&at, tile.heading_rad);
            let turned_prior =
                prior.map(|p| AttitudePrior { q_ecef_cam: at.q_ecef_cam, covariance: p.covariance });
            let prior = turned_prior.as_ref();
            let Ok(fp_at) = self.footprint_at(&at) else { continue };
            let clock = std::time::Instant::now();
            self.work.set(0);
            self.tile_landmarks.set(Some(self.params.max_landmarks.min(ACQUISITION_TILE_LANDMARKS)));
            let found = self.search_from(pyr, &at, fp_at, radius_full, radius_full, prior);
            self.tile_landmarks.set(None);
            walk.spend(self.work.get() as f64);
            // (A tile off the map searched nothing.)
            if kind == LayoutKind::Wide && self.work.get() > 0 {
                self.wide_too_wide |= self.wide_window_too_wide();
            }
            debug!(
                "t {t:.3}: tile {:.0} E {:.0} N {:+.0} deg: {:.3} G multiply-adds, {:.0} ms, {}",
                offset.x,
                offset.y,
                tile.heading_rad.to_degrees(),
                self.work.get() as f64 * 1e-9,
                clock.elapsed().as_secs_f64() * 1e3,
                match &found {
                    Ok(s) => format!("{} inliers", s.inliers),
                    Err(e) => format!("{} matches", e.matches),
                }
            );
            // A tile stands when its solution would; else the next tile is
            // searched, and the strongest failure is what the frame reports.
            if self.stands(&found) {
                debug!(
                    "t {t:.3}: acquired in the tile {:.0} m east, {:.0} m north of the guess, turned {:+.0} deg",
                    offset.x,
                    offset.y,
                    tile.heading_rad.to_degrees()
                );
                return found.map(|sol| Solution { tile: Some(*offset), ..sol });
            }
            if stronger(&found, &outcome) {
                outcome = found;
            }
        }
        outcome
    }

    /// Whether the last wide acquisition search ([`Self::search_from`])
    /// correlated over more than [`MAX_ACQUISITION_POSITIONS`] a template at
    /// the level it started on. Once one has (the guess's or any wide
    /// tile's), lost frames alternate the layouts until a fix: measured on
    /// the oblique balloon 10 km east and south, the guess's own search
    /// starts on the 128x96 level (12 000 positions, searched whole) once the
    /// doubt has grown, and fails there as its tiles' 512x384 ones do.
    fn wide_window_too_wide(&self) -> bool {
        self.window_positions.get() > MAX_ACQUISITION_POSITIONS
    }

    /// The narrow layout of an acquisition: tiles whose ground reach a
    /// template's warp stands (and the radius each searches), where that
    /// reach is less than the wide layout's (its radius `radius_px`) and the
    /// uncertainty `need_m`; `None` elsewhere (a near-nadir view).
    ///
    /// A template is warped into the image as seen from the tile's centre.
    /// Seen from a point `d` metres away at the incidence `i`, its
    /// foreshortening along the line of sight changes by about
    /// `tan(i) d / range`; the narrow tiles keep that under
    /// [`ACQUISITION_MAX_FORESHORTENING`], and each searches what its share of
    /// the grid and the attitude's doubt need, at most its reach. Measured (README,
    /// acquisition): the oblique balloon (62° at 40 km) searched from a guess
    /// 6 km off over its whole 512x384 level matched 32 of 300 templates, 5
    /// consistent, at every frame for 96 frames; its narrow tiles (4 km,
    /// searched ~90 px around) acquire it within a few. The low pass's wide
    /// tiles acquire it where its narrow ones (1 km) took 60 frames to reach
    /// 10 km, and alternating with them 37 frames where it took 5: whole
    /// frames go to the narrow layout only where the wide search's window
    /// is too wide ([`Self::wide_window_too_wide`]), elsewhere only what a
    /// frame's budget leaves.
    fn narrow_layout(
        &self,
        t: f64,
        guess: &CameraPose,
        fp: &Footprint,
        att_cov: &Matrix3<f64>,
        radius_px: f64,
        need_m: f64,
    ) -> Option<(Vec<Vector2<f64>>, f64)> {
        let f = self.camera.fx.min(self.camera.fy);
        let range = fp.center_range_m;
        let above_m = guess.position.to_geodetic().h_m - self.terrain_h_m;
        let reach_m = foreshortening_reach_m(range, above_m);
        if !(reach_m < radius_px / f * range && reach_m < need_m) {
            return None;
        }
        let tile_px = ACQUISITION_TILE_SPACING * std::f64::consts::FRAC_1_SQRT_2 * reach_m / range * f;
        let attitude_px = 2.5 * (att_cov.trace() / 3.0).sqrt() * f;
        // (At most the tile's reach, as a wide tile's: a doubt grown to tens of
        // degrees would make it the whole image again.)
        let radius = ((tile_px.powi(2) + attitude_px.powi(2)).sqrt() + 3.0).min(reach_m / range * f);
        debug!("t {t:.3}: narrow layout: {reach_m:.0} m a tile, {radius:.0} px around each");
        Some((acquisition_tiles(reach_m, need_m, None), radius))
    }

    /// The prediction that searches around a tiled acquisition `c`: its pose
    /// carried to `t` by the filter's rotation and velocity since (without
    /// the inertial filter, [`FilterMode::Fixes`]: by the gyro and the
    /// fixes' velocity), its uncertainty the acquisition's plus the
    /// velocity's over the interval. (Without it, `--filter fixes` never
    /// confirmed an acquisition: the 30 km oblique balloon turned 5 deg in
    /// 20 ms found the landmarks every other frame and fixed none of the
    /// 100 frames after.)
    fn candidate_prediction(&self, t: f64, pred: &Prediction, c: Candidate) -> Option<Prediction> {
        let Candidate { t: t0, pose, sigma_m: sigma0_m } = c;
        let dt = (t - t0).max(0.0);
        let (guess, sigma_m) = match &pred.filter {
            Carried::Ins(f) => {
                let before = self.ins.as_ref()?;
                // The filter's own attitude change and velocity (its position is
                // the doubted guess's; its motion is the IMU's).
                let turn = f.state.q_ecef_imu * before.state.q_ecef_imu.inverse();
                let (v, v_cov) = f.velocity();
                let guess =
                    CameraPose::new(trn_geodesy::Ecef(pose.position.0 + v * dt), turn * pose.q_ecef_cam);
                // (Frames of doubt before it may have inflated the filter's velocity
                // uncertainty without bound: at most the initial guess's.)
                let v_var = v_cov.trace().min(3.0 * self.params.init_velocity_sigma_m_s.powi(2));
                (guess, (sigma0_m.powi(2) + v_var * dt * dt).sqrt())
            }
            Carried::Attitude(_) => {
                let q_ecef_cam = if self.params.use_gyro {
                    let q_ecef_imu = pose.q_ecef_cam * self.q_imu_cam.inverse();
                    let p = propagate_with_bias(q_ecef_imu, t0, t, &self.imu, &self.filter.bias_imu_rad_s);
                    self.fix_rate_turn(t0, t).0 * p.q_ecef_imu * self.q_imu_cam
                } else {
                    pose.q_ecef_cam
                };
                let v_sigma = self.velocity_sigma.unwrap_or(self.params.velocity_sigma_m_s);
                let position = trn_geodesy::Ecef(pose.position.0 + self.velocity * dt);
                (CameraPose::new(position, q_ecef_cam), sigma0_m + v_sigma * dt)
            }
        };
        let att_sigma = (pred.att_cov.trace() / 3.0).sqrt().min(1f64.to_radians());
        Some(Prediction {
            guess,
            att_cov: Matrix3::identity() * att_sigma.powi(2),
            sigma_m,
            pose_cov: None,
            filter: pred.filter.clone(),
            gyro_jumps: 0,
            jump_turn: None,
        })
    }

    /// The other hypothesis after the gyro's jumps since the last fix
    /// (`pred.jump_turn`, together at least [`JUMP_UNDO_MIN_DEG`]): they
    /// were glitches, not turns, and the camera looks where it did. Its
    /// guess is `pred`'s turned back by them (in ECEF, where a turn made at
    /// the jump stays the same rotation as the body turns on), its attitude
    /// sigma at most 1 deg. With the inertial filter, its position is
    /// `pred`'s less what the accelerometer's force, turned by them, added
    /// ([`JumpTurn::undo_shift`]), its sigma the filter's at the jump
    /// carried on ([`JumpTurn::undone_position_sigma_m`]) where `pred`'s,
    /// grown by the frames without a fix since, is wider; searched for as
    /// long as no frame fixes (a glitch inside a cloud is undone when the
    /// cloud ends). Without it (`--filter fixes`), `pred`'s position and
    /// sigma, and `None` [`JUMP_UNDO_WITHIN_S`] after the first jump.
    /// Searched when `pred`'s own search does not stand, or stands only in
    /// a tile away from the guess (held for the next frame to confirm)
    /// ([`Self::process`]).
    fn jump_undone_prediction(&self, t: f64, pred: &Prediction) -> Option<Prediction> {
        let jump = pred.jump_turn?;
        // The inertial filter integrated the turned force: it takes it back.
        let filtered = matches!(pred.filter, Carried::Ins(_));
        if !(jump.turn_ecef_rad.norm() >= JUMP_UNDO_MIN_DEG.to_radians())
            || (!filtered && t - jump.since_t > JUMP_UNDO_WITHIN_S)
        {
            return None;
        }
        let back = UnitQuaternion::from_scaled_axis(-jump.turn_ecef_rad);
        let dp = if filtered { jump.undo_shift().1 } else { Vector3::zeros() };
        let guess =
            CameraPose::new(trn_geodesy::Ecef(pred.guess.position.0 + dp), back * pred.guess.q_ecef_cam);
        let att_sigma = (pred.att_cov.trace() / 3.0).sqrt().min(1f64.to_radians());
        let sigma_m = pred.sigma_m.min(jump.undone_position_sigma_m(t, att_sigma));
        Some(Prediction {
            guess,
            att_cov: Matrix3::identity() * att_sigma.powi(2),
            sigma_m,
            pose_cov: None,
            filter: pred.filter.clone(),
            gyro_jumps: 0,
            jump_turn: pred.jump_turn,
        })
    }

    /// A run of misses over, and a later acquisition in tiles starting
    /// from the nearest (one that failed its confirmation goes on from
    /// there): after an accepted fix, or a pose the gyro's jumps undone
    /// explain.
    fn search_afresh(&mut self) {
        self.misses = 0;
        self.acquisition_cursor = 0;
        self.heading_cursor = 0;
        self.narrow_cursor = 0;
        self.wide_searched = false;
        self.alternation = 0;
        self.wide_too_wide = false;
    }

    /// The inertial filter takes the gyro's jumps since the last fix
    /// (`undone.jump_turn`) for a glitch: `undone`
    /// ([`Self::jump_undone_prediction`], whose search stood) with its
    /// filter's attitude turned back by them, its velocity and position
    /// less what the accelerometer's force, turned by them since the
    /// first, added, and its pose's doubt the undone guess's
    /// ([`InsFilter::undo_jumps`]); the run of misses is over (they were
    /// the glitch's). The frame is then judged against it as any other,
    /// and the frames after are predicted from it. Before, such a fix
    /// restarted the filter's pose from the image's, as an acquisition's:
    /// under a hole in the cloud, a narrow view's fix 1059 m off (3.5
    /// sigma) restarted it after a 30 deg glitch, where the undo alone kept
    /// every fix within 73 m (`scripts/bench_faults.sh`).
    fn take_jumps_undone(&mut self, t: f64, mut undone: Prediction) -> Prediction {
        if let (Carried::Ins(f), Some(j)) = (&mut undone.filter, undone.jump_turn) {
            let att_sigma_rad = (undone.att_cov.trace() / 3.0).sqrt();
            f.undo_jumps(&j, att_sigma_rad);
            self.search_afresh();
            self.jumps_undone += 1;
            let (dv, dp) = j.undo_shift();
            info!(
                "t {t:.3}: the gyro's jump(s) since {:.3} s ({:.1} deg) taken for a glitch: the image finds its landmarks with them undone, and the filter takes the undo (the force they turned had moved the position {:.0} m and the velocity {:.1} m/s)",
                j.since_t,
                j.turn_ecef_rad.norm().to_degrees(),
                dp.norm(),
                dv.norm()
            );
        }
        undone.jump_turn = None;
        undone
    }

    /// The footprint `fp` widened by an acquisition's margin of `margin_px`
    /// pixels (at its centre's range); as it is without one.
    fn widened_footprint(&self, fp: Footprint, margin_px: f64) -> Footprint {
        if margin_px > 0.0 {
            let metres = margin_px / self.camera.fx.min(self.camera.fy) * fp.center_range_m;
            Footprint { bbox: fp.bbox.grown_m(metres), ..fp }
        } else {
            fp
        }
    }

    /// The pyramid level a search of `radius_full` pixels around `guess`
    /// starts on (its footprint `fp`, widened by `margin_px` for an acquisition).
    fn first_level(
        &self,
        pyr: &Pyramid,
        guess: &CameraPose,
        fp: &Footprint,
        radius_full: f64,
        margin_px: f64,
    ) -> usize {
        // Coarsest level whose search radius fits, then the finest.
        // (The undistortion table stops one level earlier than the image
        // pyramid on small images: a 320x240 camera's 40x30 level has none.)
        let n_levels = pyr.levels.len().min(self.lut.levels.len());
        let mut k = 0;
        while k + 1 < n_levels && radius_full / (1u32 << k) as f64 > self.params.max_radius_px as f64 {
            k += 1;
        }
        // A coarse level needs enough landmarks in view, large enough to correlate.
        while k > 0 && self.usable_landmarks(fp, guess, k, margin_px) < MIN_COARSE_LANDMARKS {
            k -= 1;
        }
        // An acquisition stands on its coarse level alone: one whose image
        // is a few templates across leaves them no room to slide.
        while margin_px > 0.0
            && k > 0
            && pyr.levels[k].width.min(pyr.levels[k].height) < MIN_ACQUISITION_SIDE_PX
        {
            k -= 1;
        }
        // Nor on one whose templates span too wide an angle of the view to be
        // warped right from a guess kilometres off (above full resolution).
        let template_angle =
            |k: usize| self.level_for(fp.center_gsd_m * (1u32 << k) as f64).footprint_m / fp.center_range_m;
        while margin_px > 0.0 && k > 1 && template_angle(k) > ACQUISITION_MAX_TEMPLATE_ANGLE {
            k -= 1;
        }
        k
    }

    /// The coarse-to-fine search of one image around the pose `guess`
    /// (its footprint `fp`): a search radius of `radius_full` pixels, and
    /// with `margin_px` (an acquisition) the footprint widened by it.
    fn search_from(
        &self,
        pyr: &Pyramid,
        guess: &CameraPose,
        fp: Footprint,
        radius_full: f64,
        margin_px: f64,
        prior: Option<&AttitudePrior>,
    ) -> Result<Solution, NoSolution> {
        let fp = self.widened_footprint(fp, margin_px);
        if margin_px > 0.0 {
            debug!("acquisition: search radius {radius_full:.0} px, footprint widened by {margin_px:.0} px");
        }
        let k = self.first_level(pyr, guess, &fp, radius_full, margin_px);
        let mut pose = *guess;
        let mut radius = ((radius_full / (1u32 << k) as f64).ceil() as usize).max(4);
        self.window_positions.set(window_positions(1, 1, radius, &pyr.levels[k]));
        let mut best: Option<Solution> = None;
        // Coarse to fine: each level starts from the pose of the one above
        // when that one is trustworthy (enough inliers, attitude within the
        // gyro prior's gate); a weak coarse solution is not followed: the
        // next level searches the same ground radius around the guess.
        for level in (0..=k).rev() {
            // Below an accepted coarse level the search is local again.
            let margin = if best.is_some() { 0.0 } else { margin_px };
            match self.stage(pyr, &pose, &fp, level, Search { radius, margin_px: margin }, prior) {
                Ok(sol) if level == 0 || (sol.inliers >= self.params.min_inliers && !sol.prior_loosened) => {
                    pose = sol.pose;
                    best = Some(sol);
                    radius = 5;
                }
                // An acquisition stands on its coarse level, the one search
                // that covered the whole uncertainty: a finer level's bounded
                // search around the guess would find whatever aliases the
                // landmarks there (a repeated pattern: measured on the
                // synthetic map's road grid, fixes 1.1-1.6 km off with 40-95
                // inliers), and nothing tells it from the truth.
                Ok(sol) if margin_px > 0.0 && best.is_none() => {
                    debug!("level {level}: acquisition failed ({} inliers)", sol.inliers);
                    return Err(NoSolution { matches: sol.n_matches, found: Vec::new() });
                }
                Err(e) if margin_px > 0.0 && best.is_none() => {
                    debug!("level {level}: acquisition failed ({} matches)", e.matches);
                    return Err(e);
                }
                Ok(sol) => {
                    debug!("level {level}: weak solution ({} inliers) not followed", sol.inliers);
                    radius = widened(radius, self.params.max_radius_px);
                }
                Err(e) if level == 0 => return Err(e),
                Err(_) => radius = widened(radius, self.params.max_radius_px),
            }
        }
        let mut sol = best.ok_or(NoSolution::default())?;
        sol.acquisition = margin_px > 0.0;
        Ok(sol)
    }

    /// One pyramid level: select, predict and correlate ([`Self::find_matches`]),
    /// then RANSAC and refine ([`Self::solve_level`]).
    fn stage(
        &self,
        pyr: &Pyramid,
        pose: &CameraPose,
        fp: &trn_view::footprint::Footprint,
        level: usize,
        search: Search,
        prior: Option<&AttitudePrior>,
    ) -> Result<Solution, NoSolution> {
        let (matches, searched) = self.find_matches(pyr, pose, fp, level, search)?;
        let sol = self.solve_level(&matches, level, prior)?;
        Ok(Solution { n_searched: searched, ..sol })
    }

    /// `f` of each item, the `None`s left out, in the items' order: on the
    /// navigator's threads when it has several ([`NavParams::threads`]).
    fn filter_map_in_order<T: Sync, R: Send>(
        &self,
        items: &[T],
        f: impl Fn(&T) -> Option<R> + Sync,
    ) -> Vec<R> {
        use rayon::prelude::*;
        match &self.pool {
            Some(pool) => pool.install(|| items.par_iter().filter_map(&f).collect()),
            None => items.iter().filter_map(f).collect(),
        }
    }

    /// The templates the guess puts in view at pyramid level `level`, each
    /// searched for in the image within `search.radius` level pixels: the
    /// matches found, and how many templates were searched for.
    fn find_matches(
        &self,
        pyr: &Pyramid,
        pose: &CameraPose,
        fp: &trn_view::footprint::Footprint,
        level: usize,
        search: Search,
    ) -> Result<(Vec<Match>, usize), NoSolution> {
        let Search { radius, margin_px } = search;
        let scale = (1u32 << level) as f64;
        // Oblique views span many ground resolutions: query the levels around
        // the centre's and keep each template only where its level fits the
        // local resolution (`view::level_fits`, shared with the server).
        let db_level = self.level_for(fp.center_gsd_m * scale).level;
        let span = trn_view::visible::LEVEL_SPAN;
        let (lo, hi) = (db_level.saturating_sub(span), db_level.saturating_add(span));
        let mut templates = Vec::new();
        for l in self.levels.iter().map(|l| l.level).filter(|&l| l >= lo && l <= hi) {
            templates.extend(self.query(&fp.bbox, l).map_err(|e| {
                tracing::warn!("landmark query failed: {e}");
                NoSolution::default()
            })?);
        }
        templates.retain(|t| {
            trn_view::visible::level_fits(
                &self.levels,
                t,
                trn_view::visible::local_gsd_m(&self.camera, pose, t) * scale,
            )
        });
        let chosen = self.spread(&templates, pose, scale, margin_px);
        self.work.set(self.work.get() + chosen.len() as u64 * TEMPLATE_WORK);
        let img = &pyr.levels[level];
        let view = ImageView::new(img.width, img.height, &img.data);
        // An acquisition correlates the centres of the larger templates only.
        let max_patch_px = if margin_px > 0.0 { ACQUISITION_MAX_PATCH_PX } else { MAX_PATCH_PX };
        let (camera, lut, alpha_max_deg) = (&self.camera, &self.lut, self.params.alpha_max_deg);
        let predicted: Vec<Predicted> = self.filter_map_in_order(&chosen, |t| {
            predict(t, pose, camera, lut, level, max_patch_px, alpha_max_deg)
        });
        let predict_px: usize = predicted.iter().map(|p| p.patch.width * p.patch.height).sum();
        self.work.set(self.work.get() + predict_px as u64 * PREDICT_WORK_PER_PX);
        // An acquisition correlates its templates (spread over the image, the
        // best of each cell first) up to [`SEARCH_BUDGETS`] of a frame's work
        // budget: one search of a 1024x768 oblique view over its whole image
        // at full resolution had taken 811 G multiply-adds, 8 s.
        let works: Vec<u64> =
            predicted.iter().map(|p| correlation_work(p.patch.width, p.patch.height, radius, img)).collect();
        let searched = if margin_px > 0.0 {
            within_budget(&works, SEARCH_BUDGETS * self.params.acquisition_budget_g * 1e9)
        } else {
            works.len()
        };
        self.work.set(self.work.get() + works[..searched].iter().sum::<u64>());
        let ncc_params = &self.params.ncc;
        let matches: Vec<Match> = self.filter_map_in_order(&predicted[..searched], |p| {
            let (u0, v0) = (p.patch_center.u, p.patch_center.v);
            let m = ncc::match_template(&view, &p.patch, u0, v0, radius, ncc_params).ok()?;
            Some(Match {
                pixel: p.observed_center(Pixel::new(m.u, m.v)),
                point_ecef: p.center_ecef.0,
                landmark: p.template_id,
                predicted: p.center_px,
                // At full resolution; an edge's (infinite along it) capped.
                sigma_px: (m.sigma_px * scale).min(MAX_PEAK_SIGMA_PX),
                gsd_m: p.gsd_m,
            })
        });
        debug!(
            "level {level}: db levels around {db_level}, {} templates, {} predicted, {} searched, {} matches, radius {radius}",
            templates.len(),
            predicted.len(),
            searched,
            matches.len()
        );
        Ok((matches, searched))
    }

    /// The pose from one pyramid level's matches: P3P RANSAC, then the
    /// refinement with the gyro's attitude prior (loosened when the image
    /// disagrees with it), and every match classified against the result.
    fn solve_level(
        &self,
        matches: &[Match],
        level: usize,
        prior: Option<&AttitudePrior>,
    ) -> Result<Solution, NoSolution> {
        let n = matches.len();
        // Only a failure keeps the matches (the full-resolution level's, for
        // a prior-gated update).
        let fail =
            || NoSolution { matches: n, found: if level == 0 { matches.to_vec() } else { Vec::new() } };
        if n < 4 {
            return Err(fail());
        }
        let scale = (1u32 << level) as f64;
        let pixels: Vec<Pixel> = matches.iter().map(|m| m.pixel).collect();
        let points: Vec<Vector3<f64>> = matches.iter().map(|m| m.point_ecef).collect();
        let rp = RansacParams {
            threshold_px: self.params.ransac_threshold_px * scale,
            min_inliers: 4,
            ..RansacParams::default()
        };
        let r = ransac_p3p(&self.camera, &pixels, &points, &rp).ok_or_else(fail)?;
        let in_px: Vec<Pixel> = pixels.iter().zip(&r.inliers).filter(|x| *x.1).map(|x| *x.0).collect();
        let in_pts: Vec<Vector3<f64>> =
            points.iter().zip(&r.inliers).filter(|x| *x.1).map(|x| *x.0).collect();
        let opts = RefineOptions {
            prior: prior.copied(),
            huber_px: Some(REFINE_HUBER_PX * scale),
            pixel_sigma: REFINE_SIGMA_PX * scale,
            ..RefineOptions::default()
        };
        let mut refined = refine_pose(&self.camera, &in_px, &in_pts, &r.pose, &opts).ok_or_else(fail)?;
        let mut prior_loosened = false;
        if let Some(p) = prior {
            // Gated with the floor: the image may disagree with the gyro by what
            // calibration and clock errors explain without the prior being wrong.
            let gate = AttitudePrior {
                covariance: p.covariance + Matrix3::identity() * ATTITUDE_GATE_FLOOR_DEG.to_radians().powi(2),
                ..*p
            };
            let d2 = gate.mahalanobis2(&refined.pose.q_ecef_cam).unwrap_or(f64::INFINITY);
            if d2 > PRIOR_GATE_CHI2 {
                // The image and the gyro disagree (a bad earlier fix, or more
                // drift than modelled): trust the image.
                debug!("level {level}: attitude {d2:.0} chi2 from the gyro prior, prior loosened");
                let loose = AttitudePrior { covariance: p.covariance * 1e4, ..*p };
                let opts = RefineOptions { prior: Some(loose), ..opts };
                refined =
                    refine_pose(&self.camera, &in_px, &in_pts, &refined.pose, &opts).ok_or_else(fail)?;
                prior_loosened = true;
            }
        }
        // Re-classify every match with the refined pose.
        let thr = self.params.ransac_threshold_px * scale;
        let mut records = Vec::with_capacity(n);
        let mut inliers = 0;
        let mut h_sum = 0.0;
        let mut gsds = Vec::new();
        for m in matches {
            let at = trn_geodesy::Ecef(m.point_ecef);
            let pred = refined.pose.project(&self.camera, &at);
            let res = pred.map_or(f64::INFINITY, |q| q.distance_px(&m.pixel));
            let inl = res <= thr;
            if inl {
                inliers += 1;
                h_sum += at.to_geodetic().h_m;
                if m.gsd_m > 0.0 {
                    gsds.push(m.gsd_m);
                }
            }
            let q = pred.unwrap_or(m.predicted);
            records.push(MatchRecord {
                t: 0.0,
                landmark: m.landmark,
                u: m.pixel.u,
                v: m.pixel.v,
                pred_u: q.u,
                pred_v: q.v,
                residual_px: res.min(1e6),
                inlier: inl,
                landmark_ecef: Some(at),
                sigma_px: Some(m.sigma_px),
            });
        }
        Ok(Solution {
            pose: refined.pose,
            inliers,
            n_matches: n,
            records,
            points,
            guess_px: Vec::new(),
            covariance: refined.covariance,
            prior_loosened,
            mean_landmark_h: (inliers > 0).then(|| h_sum / inliers as f64),
            median_gsd_m: median(&mut gsds),
            acquisition: false,
            tile: None,
            // (At least its matches; [`Self::stage`] counts the templates.)
            n_searched: n,
        })
    }

    /// Landmarks of the level pyramid level `k` would use that land in the
    /// image at least `MIN_PATCH_PX` level pixels wide.
    fn usable_landmarks(
        &self,
        fp: &trn_view::footprint::Footprint,
        pose: &CameraPose,
        k: usize,
        margin_px: f64,
    ) -> usize {
        let scale = (1u32 << k) as f64;
        let db_level = self.level_for(fp.center_gsd_m * scale);
        if db_level.span_px(fp.center_gsd_m * scale) < MIN_PATCH_PX {
            return 0;
        }
        let Ok(ts) = self.query(&fp.bbox, db_level.level) else { return 0 };
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        ts.iter()
            .filter_map(|t| pose.project(&self.camera, &t.center_ecef()))
            .filter(|p| p.u >= -margin_px && p.v >= -margin_px && p.u < w + margin_px && p.v < h + margin_px)
            .count()
    }

    /// Landmarks in view, spread over image cells, best first, capped. A
    /// template's score is its texture (√Shi–Tomasi), its uniqueness, the
    /// image area it covers up to [`trn_view::visible::TARGET_PATCH_PX`]² (a
    /// correlation's precision grows with the pixels it sums: a cell takes
    /// the level that fits the resolution before the one finer, whose
    /// templates are four times as many but half as wide) and, unless the
    /// database was lit for the flight's sun, its stability under another
    /// sun (`1 - shading_weight * shading_share`). In a cell, near
    /// duplicates of a better landmark come last
    /// ([`NavParams::duplicate_separation`], [`duplicates_last`]).
    /// Landmarks up to `margin_px` outside the image count (in its edge
    /// cells): an acquisition's search reaches in from there.
    fn spread<'t>(
        &self,
        templates: &'t [Template],
        pose: &CameraPose,
        scale: f64,
        margin_px: f64,
    ) -> Vec<&'t Template> {
        let (gx, gy) = self.params.grid;
        let (w, h) = (self.camera.width as f64, self.camera.height as f64);
        // Per cell: (score, centre, template).
        let mut cells: Vec<Vec<(f32, Ecef, &Template)>> = vec![Vec::new(); gx * gy];
        for t in templates {
            let at = t.center_ecef();
            let Some(p) = pose.project(&self.camera, &at) else { continue };
            let m = margin_px;
            if !(p.u >= -m && p.v >= -m && p.u < w + m && p.v < h + m) {
                continue;
            }
            // `as usize` saturates: left of the image is cell 0.
            let (cx, cy) = (((p.u / w) * gx as f64) as usize, ((p.v / h) * gy as f64) as usize);
            let q = &t.quality;
            let span_px =
                t.width_px as f64 * t.gsd_m / (trn_view::visible::local_gsd_m(&self.camera, pose, t) * scale);
            let area = (span_px / trn_view::visible::TARGET_PATCH_PX).min(1.0).powi(2) as f32;
            let stable = if self.lit_for_flight {
                1.0
            } else {
                1.0 - self.params.shading_weight as f32 * q.shading_share.clamp(0.0, 1.0)
            };
            let score = q.shi_tomasi.sqrt() * (1.0 - q.second_peak_ncc).max(0.01) * area * stable;
            cells[cy.min(gy - 1) * gx + cx.min(gx - 1)].push((score, at, t));
        }
        // A tile's acquisition level searches fewer ([`ACQUISITION_TILE_LANDMARKS`]).
        let cap = self.tile_landmarks.get().filter(|_| margin_px > 0.0).unwrap_or(self.params.max_landmarks);
        for c in &mut cells {
            c.sort_by(|a, b| b.0.total_cmp(&a.0));
            duplicates_last(c, self.params.duplicate_separation, cap);
        }
        // Round-robin over cells so the cap keeps the spread.
        let mut out = Vec::new();
        let mut round = 0;
        while out.len() < cap {
            let mut any = false;
            for c in &cells {
                if let Some((_, _, t)) = c.get(round) {
                    out.push(*t);
                    any = true;
                    if out.len() == cap {
                        break;
                    }
                }
            }
            if !any {
                break;
            }
            round += 1;
        }
        out
    }
}

/// Reorders a cell's landmarks (best first; each with its centre) so that
/// each one closer on the ground to a better one kept before it than
/// `separation` times the larger of their footprints (`width_px * gsd_m`)
/// comes after every one that is not, each group in its order. Only the
/// first `cap` kept are looked for (no more can be taken from a cell), so
/// the work stays `cap` distances a landmark. `separation` 0: unchanged.
fn duplicates_last(cell: &mut Vec<(f32, Ecef, &Template)>, separation: f64, cap: usize) {
    if separation <= 0.0 || cell.len() < 2 {
        return;
    }
    let radius_m = |t: &Template| separation * t.width_px as f64 * t.gsd_m;
    let (mut kept, mut later) = (Vec::with_capacity(cell.len()), Vec::new());
    for &entry in cell.iter() {
        let (_, at, t) = entry;
        let near = |&(_, q, u): &(f32, Ecef, &Template)| (q.0 - at.0).norm() < radius_m(t).max(radius_m(u));
        if kept.len() >= cap || kept.iter().any(near) {
            later.push(entry);
        } else {
            kept.push(entry);
        }
    }
    kept.extend(later);
    *cell = kept;
}

/// Sun directions closer than this (deg) count as the same lighting.
pub const SAME_SUN_DEG: f64 = 10.0;

/// The lighting (`Template::lighting`) to use from a database baked for
/// `suns` (empty: the ortho as imaged, 0) on a flight under `sun`: the
/// nearest baked sun, or the first without one; and whether it is the
/// flight's (within [`SAME_SUN_DEG`]).
pub fn choose_lighting(suns: &[SunLight], sun: Option<&SunLight>) -> (u8, bool) {
    if suns.is_empty() {
        return (0, false);
    }
    let Some(sun) = sun else {
        tracing::info!(
            "the database is lit for {} sun(s) and no --sun was given: using its first",
            suns.len()
        );
        return (1, false);
    };
    let (k, angle) = suns
        .iter()
        .enumerate()
        .map(|(k, s)| (k, s.angle_to_deg(sun)))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .expect("suns");
    if angle > SAME_SUN_DEG {
        tracing::warn!(
            "the database's nearest sun is {angle:.1} deg from the flight's: its shading will differ"
        );
    } else {
        tracing::info!("using the database's lighting {} ({angle:.1} deg from the flight's sun)", k + 1);
    }
    ((k + 1).min(255) as u8, angle <= SAME_SUN_DEG)
}

/// A pose from one frame before acceptance.
/// A template found in the image.
#[derive(Clone, Copy, Debug, Default)]
struct Match {
    /// Where the correlation put the template's centre (full-resolution pixels).
    pixel: Pixel,
    point_ecef: Vector3<f64>,
    landmark: i64,
    /// Where the frame's guess predicted it.
    predicted: Pixel,
    /// The correlation peak's sigma (full-resolution pixels, capped).
    sigma_px: f64,
    /// The template's ground sample distance (m; 0 when not known).
    gsd_m: f64,
}

/// Why a level or a frame gave no pose: too few matches, or no consensus
/// among them (`matches` found; at the full-resolution level, `found` holds
/// them for a prior-gated update).
#[derive(Clone, Debug, Default)]
struct NoSolution {
    matches: usize,
    found: Vec<Match>,
}

struct Solution {
    pose: CameraPose,
    inliers: usize,
    n_matches: usize,
    /// Templates searched for at its level (found or not).
    n_searched: usize,
    records: Vec<MatchRecord>,
    /// Landmark (ECEF) of each record.
    points: Vec<Vector3<f64>>,
    /// Where the frame's pose guess put each record's landmark (after sorting).
    guess_px: Vec<Option<Pixel>>,
    /// Of `[dtheta; dp]` (see `trn_vision::pnp`), the prior included.
    covariance: Matrix6<f64>,
    /// The image disagreed with the gyro prior; it was refined again with the prior loosened.
    prior_loosened: bool,
    /// The pose came from an acquisition (a search over the whole
    /// uncertainty of a guess kilometres off).
    acquisition: bool,
    /// The acquisition's tile (east, north offset of the guess, m) when it
    /// searched in tiles ([`acquisition_tiles`]).
    tile: Option<Vector2<f64>>,
    mean_landmark_h: Option<f64>,
    /// The inliers' median ground sample distance (m).
    median_gsd_m: Option<f64>,
}

impl Solution {
    fn attitude_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(0, 0).into_owned()
    }

    fn position_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(3, 3).into_owned()
    }
}

/// How pixels spread over a `w` x `h` image: the cells of a `grid` (across,
/// down) they cover, and their standard deviation along their narrowest
/// direction (the square root of their covariance's smaller eigenvalue;
/// pixels).
pub fn inlier_spread(px: &[Pixel], w: f64, h: f64, grid: (usize, usize)) -> (usize, f64) {
    if px.is_empty() {
        return (0, 0.0);
    }
    let n = px.len() as f64;
    let (mu, mv) = (px.iter().map(|p| p.u).sum::<f64>() / n, px.iter().map(|p| p.v).sum::<f64>() / n);
    let (mut a, mut b, mut c) = (0.0, 0.0, 0.0);
    for p in px {
        let (du, dv) = (p.u - mu, p.v - mv);
        a += du * du / n;
        b += dv * dv / n;
        c += du * dv / n;
    }
    let minor = 0.5 * (a + b) - (0.25 * (a - b) * (a - b) + c * c).sqrt();
    let (gx, gy) = grid;
    let mut seen = vec![false; gx * gy];
    for p in px {
        let (cx, cy) = grid_cell(p, w, h, grid);
        seen[cy * gx + cx] = true;
    }
    (seen.iter().filter(|&&s| s).count(), minor.max(0.0).sqrt())
}

/// Whether an inconsistent fix (refused by the innovation gate) doubts
/// the inertial filter: always before the filter's pose is `confirmed` by
/// a fix (an initial or doubted guess), and when its inliers cover at
/// least `min_cells` cells (a view that pins the pose whole); a narrower
/// view's only when it `agrees_with_last` inconsistent fix since the last
/// accepted one ([`innovations_agree`]): two images that say the filter is
/// off by the same are evidence, a narrow view's scattered solutions are
/// not. See [`NavParams::doubt_min_cells`].
pub fn doubts_filter(cells: usize, min_cells: usize, agrees_with_last: bool, confirmed: bool) -> bool {
    !confirmed || cells >= min_cells || agrees_with_last
}

/// Whether matches at `px` (a frame's, which did not agree) span fewer
/// than `min_cells` cells of a `grid` over a `width x height` image
/// ([`spanned_cells`]), and so are a narrow view's, not counted as a miss
/// ([`NavParams::miss_min_cells`]; 0: never; no match: not one). The
/// span, not the cells the matches fall in: a wide view's few scattered
/// matches fall in few cells but span most of the image.
fn narrow_miss(
    px: impl IntoIterator<Item = Pixel>,
    width: f64,
    height: f64,
    grid: (usize, usize),
    min_cells: usize,
) -> bool {
    min_cells > 0 && (1..min_cells).contains(&spanned_cells(px, width, height, grid))
}

/// Cells of a `grid` over a `w x h` image in the smallest block of cells
/// that holds every pixel of `px` (from the leftmost match's column to the
/// rightmost's, the top one's row to the bottom one's); 0 without pixels.
fn spanned_cells(px: impl IntoIterator<Item = Pixel>, w: f64, h: f64, grid: (usize, usize)) -> usize {
    px.into_iter()
        .map(|p| grid_cell(&p, w, h, grid))
        .fold(None, |span, (c, r)| {
            Some(span.map_or((c, c, r, r), |(c0, c1, r0, r1): (usize, usize, usize, usize)| {
                (c0.min(c), c1.max(c), r0.min(r), r1.max(r))
            }))
        })
        .map_or(0, |(c0, c1, r0, r1)| (c1 - c0 + 1) * (r1 - r0 + 1))
}

/// The cell `(column, row)` of a `grid` over a `w x h` image that pixel
/// `p` falls in; a pixel outside the image counts in the nearest cell
/// (`as usize` saturates: left of or above the image is cell 0).
fn grid_cell(p: &Pixel, w: f64, h: f64, grid: (usize, usize)) -> (usize, usize) {
    let (gx, gy) = grid;
    ((((p.u / w) * gx as f64) as usize).min(gx - 1), (((p.v / h) * gy as f64) as usize).min(gy - 1))
}

/// A fix's innovation against the inertial filter's prediction (`[dtheta;
/// dp]`, [`pose_difference`](crate::ins::pose_difference) of the fix's pose and the predicted one) and
/// the fix's own covariance.
type Innovation = (Vector6<f64>, Matrix6<f64>);

/// Whether two fixes' innovations against the filter's predictions
/// (`[dtheta; dp]`, [`pose_difference`](crate::ins::pose_difference) of the fix's pose and the
/// predicted one; `y0` with covariance `r0`, `y1` with `r1`, each the
/// fix's own) say the same: their difference within `chi2_limit`
/// (chi-square, 6 degrees of freedom) of the sum of their covariances. A
/// filter gone wrong is off by nearly the same at two frames half a second
/// apart; a narrow view's wrong solutions are not.
pub fn innovations_agree(
    y0: &Vector6<f64>,
    r0: &Matrix6<f64>,
    y1: &Vector6<f64>,
    r1: &Matrix6<f64>,
    chi2_limit: f64,
) -> bool {
    let d = y1 - y0;
    (r0 + r1).cholesky().is_some_and(|c| d.dot(&c.solve(&d)) <= chi2_limit)
}

/// The tight filter's update from a frame without a fix (too few
/// inliers, or spread too narrow to stand alone): each match is gated by
/// its innovation against the filter's predicted pixel (chi-square, 2
/// degrees of freedom), the survivors are refined with the prediction
/// as the prior, the worst is dropped while one lies more than the gate
/// from the result, and the whole set must pass the joint innovation
/// test (99.9%) before the filter is conditioned on it. Returns
/// the matches used (0: no update). The intrinsics the filter carries
/// enter by `sensitivity` (the last fix's), as in a fix's update.
fn prior_gated_update(
    camera: &CameraModel,
    q_imu_cam: &UnitQuaternion<f64>,
    f: &mut InsFilter,
    found: &[Match],
    sensitivity: &IntrinsicsSensitivity,
) -> usize {
    if found.len() < 3 {
        return 0;
    }
    let q = *q_imu_cam;
    let (pred, m) = f.apparent_pose_with(&q, sensitivity);
    let mut used: Vec<Gated> = found
        .iter()
        .filter_map(|mt| {
            // Its predicted pixel and Jacobian in the pose [dtheta; dp].
            let (p0, j) = project_with_jacobian(camera, &pred, &mt.point_ecef)?;
            let sigma = (mt.sigma_px.powi(2) + GATED_SIGMA_FLOOR_PX.powi(2)).sqrt();
            let r = Vector2::new(mt.pixel.u - p0.u, mt.pixel.v - p0.v);
            let predicted = j * m * j.transpose();
            // A prediction this uncertain gates nothing: any texture near
            // it would pass.
            if predicted.symmetric_eigenvalues().max() > GATED_MAX_PREDICTED_SIGMA_PX.powi(2) {
                return None;
            }
            let s = predicted + Matrix2::identity() * sigma * sigma;
            let d2 = r.dot(&(s.try_inverse()? * r));
            (d2 <= GATE_CHI2_2DOF).then_some(Gated {
                found: *mt,
                jacobian: j,
                innovation_px: r,
                sigma_px: sigma,
            })
        })
        .collect();
    loop {
        if used.len() < 3 {
            return 0;
        }
        let px: Vec<Pixel> = used.iter().map(|u| u.found.pixel).collect();
        let pts: Vec<Vector3<f64>> = used.iter().map(|u| u.found.point_ecef).collect();
        let sig: Vec<f64> = used.iter().map(|u| u.sigma_px).collect();
        let opts = RefineOptions {
            pose_prior: Some(PosePrior { pose: pred, covariance: m }),
            ..RefineOptions::default()
        };
        let Some(r) = refine_pose_weighted(camera, &px, &pts, Some(&sig), &pred, &opts) else { return 0 };
        let worst = r
            .residuals_px
            .iter()
            .zip(&sig)
            .map(|(e, s)| (e / s).powi(2))
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .expect("three or more");
        if worst.1 > GATE_CHI2_2DOF {
            used.swap_remove(worst.0);
            continue;
        }
        // The joint innovation: every residual against the prediction,
        // with the pose uncertainty they share.
        let n = used.len();
        let mut s = DMatrix::<f64>::zeros(2 * n, 2 * n);
        let mut y = DVector::<f64>::zeros(2 * n);
        for (a, ua) in used.iter().enumerate() {
            y[2 * a] = ua.innovation_px.x;
            y[2 * a + 1] = ua.innovation_px.y;
            for (b, ub) in used.iter().enumerate() {
                let c = ua.jacobian * m * ub.jacobian.transpose();
                for i in 0..2 {
                    for k in 0..2 {
                        s[(2 * a + i, 2 * b + k)] = c[(i, k)];
                    }
                }
            }
            s[(2 * a, 2 * a)] += ua.sigma_px * ua.sigma_px;
            s[(2 * a + 1, 2 * a + 1)] += ua.sigma_px * ua.sigma_px;
        }
        let Some(chol) = s.cholesky() else { return 0 };
        let chi2 = y.dot(&chol.solve(&y));
        let limit = chi2_quantile(2 * n, JOINT_GATE_P_Z);
        if chi2 > limit {
            debug!("prior-gated update refused: {n} matches, joint chi2 {chi2:.1} > {limit:.1}");
            return 0;
        }
        return if f.condition_on_pose_with(&q, &r.pose, &r.covariance, sensitivity) { n } else { 0 };
    }
}

/// A match that passed its innovation gate in [`prior_gated_update`].
struct Gated {
    found: Match,
    /// Its pixel's Jacobian in the pose `[dtheta; dp]` at the prediction.
    jacobian: SMatrix<f64, 2, 6>,
    /// Found minus predicted pixel (u, v).
    innovation_px: Vector2<f64>,
    /// Its pixel sigma (per coordinate).
    sigma_px: f64,
}

/// The median of `v` (sorted in place); `None` when empty.
fn median(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    Some(if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) })
}

/// Whether a frame's solution is held for the next frame to confirm (the
/// next frame searches around it, and a fix there is the acquisition), and
/// what the frame then reports:
/// - an acquisition found in a tile away from the guess that passed every
///   test: of the many places tiles try, one may alias (`Unconfirmed`);
/// - an acquisition refused only for too narrow a view (`Spread`, kept): a
///   guess ahead of an oblique camera predicts the landmarks of a part of its
///   image only, and around the acquisition every landmark in view is
///   predicted. Not when that search was itself around a held one: a frame
///   spent confirming is not spent on tiles.
fn held(
    rejection: Option<Rejection>,
    tile: Option<Vector2<f64>>,
    acquisition: bool,
    was_confirming: bool,
) -> Option<Rejection> {
    match (rejection, tile) {
        (None, Some(t)) => Some(Rejection::Unconfirmed { tile_east_m: t.x, tile_north_m: t.y }),
        (Some(r @ Rejection::Spread { .. }), _) if acquisition && !was_confirming => Some(r),
        _ => None,
    }
}

/// Where an acquisition searches (east, north offsets of the guess, m,
/// nearest first, the guess itself first) when one search reaches `reach_m`
/// around the guess and the uncertainty `need_m`: a grid of
/// `ACQUISITION_TILE_SPACING * reach_m` over the disc of `need_m` (at most
/// [`ACQUISITION_MAX_TILES`]), its rows along an oblique view's line of
/// `sight` no farther apart than its step; none when one search around the
/// guess covers it (the reach across the line of sight, and along it its
/// step over `ACQUISITION_TILE_SPACING`, as the grid's own reach).
fn acquisition_tiles(reach_m: f64, need_m: f64, sight: Option<SightLine>) -> Vec<Vector2<f64>> {
    let step_across = ACQUISITION_TILE_SPACING * reach_m;
    let (along, step_along) = match sight {
        Some(s) => (s.dir_en, s.step_m.min(step_across)),
        None => (Vector2::new(1.0, 0.0), step_across),
    };
    if !(reach_m > 0.0 && need_m > reach_m.min(step_along / ACQUISITION_TILE_SPACING)) {
        return Vec::new();
    }
    let across = Vector2::new(-along.y, along.x);
    // Rings enough for the most tiles, however wide the uncertainty.
    let most_rings = (ACQUISITION_MAX_TILES as f64).sqrt().ceil() as i64;
    let n_along = ((need_m / step_along).ceil() as i64).min(most_rings);
    let n_across = ((need_m / step_across).ceil() as i64).min(most_rings);
    let mut tiles: Vec<Vector2<f64>> = (-n_along..=n_along)
        .flat_map(|i| {
            (-n_across..=n_across)
                .map(move |j| along * (i as f64 * step_along) + across * (j as f64 * step_across))
        })
        .filter(|o| o.norm() <= need_m + 0.5 * step_across)
        .collect();
    tiles.sort_by(|a, b| a.norm().total_cmp(&b.norm()).then(a.x.total_cmp(&b.x)).then(a.y.total_cmp(&b.y)));
    tiles.truncate(ACQUISITION_MAX_TILES);
    tiles
}

/// An oblique view's line of sight on the ground, which acquisition tiles
/// are laid out along ([`acquisition_tiles`]).
#[derive(Clone, Copy, Debug)]
struct SightLine {
    /// The boresight's horizontal direction (unit; east, north).
    dir_en: Vector2<f64>,
    /// The tiles' spacing along it (m).
    step_m: f64,
}

/// The line of sight of a view from `guess` whose image centre is
/// `range_m` from the ground it sees, with the tile spacing along it of
/// [`ACQUISITION_ALONG_SIGHT_STEP`]: a tile `d` metres nearer the ground
/// along the line of sight than the truth (or farther) sees it `d sin(i)`
/// nearer, its templates `d sin(i) / range` larger (first order; `i` the
/// boresight's angle from the vertical); `None` looking within 6 degrees of
/// straight down.
fn sight_line(guess: &CameraPose, range_m: f64) -> Option<SightLine> {
    let b_enu =
        trn_geodesy::LocalFrame::at(guess.position.to_geodetic()).vector_to_enu(&guess.boresight_ecef());
    let sin_i = b_enu.x.hypot(b_enu.y);
    (sin_i > 0.1).then(|| SightLine {
        dir_en: Vector2::new(b_enu.x, b_enu.y) / sin_i,
        step_m: ACQUISITION_ALONG_SIGHT_STEP * range_m / sin_i,
    })
}

/// How far (m) a viewpoint `range_m` from the ground it looks at, `above_m`
/// above it, may move across its line of sight before a template's
/// foreshortening there changes by [`ACQUISITION_MAX_FORESHORTENING`]: the
/// incidence `i` (cos i = `above_m` / `range_m`) turns by `d / range_m`, the
/// foreshortening `cos i` by `tan(i) d / range_m` (first order). Unbounded
/// looking straight down.
fn foreshortening_reach_m(range_m: f64, above_m: f64) -> f64 {
    let cos_i = (above_m / range_m).clamp(1e-3, 1.0);
    let tan_i = (1.0 - cos_i * cos_i).sqrt() / cos_i;
    if tan_i > 0.0 {
        ACQUISITION_MAX_FORESHORTENING * range_m / tan_i
    } else {
        f64::INFINITY
    }
}

/// The work of one template's correlation (`width` x `height` pixels,
/// searched within `radius` px of its prediction in `image`), in
/// multiply-adds: its pixels and [`NCC_POSITION_WORK`] at each position of
/// its window ([`window_positions`]).
fn correlation_work(width: usize, height: usize, radius: usize, image: &GreyImage) -> u64 {
    ((width * height) as u64 + NCC_POSITION_WORK) * window_positions(width, height, radius, image)
}

/// The positions of a `width` x `height` template's window of `radius` px
/// inside `image` (those of a window cut by the image's border, at most).
fn window_positions(width: usize, height: usize, radius: usize, image: &GreyImage) -> u64 {
    let side = 2 * radius as u64 + 1;
    let nx = side.min((image.width + 1).saturating_sub(width) as u64);
    let ny = side.min((image.height + 1).saturating_sub(height) as u64);
    nx * ny
}

/// The tiles of one acquisition layout, and how each is searched.
#[derive(Clone, Copy, Debug)]
struct TileLayout<'a> {
    /// Where each tile searches from, nearest first.
    tiles: &'a [Tile],
    /// Radius (full-resolution pixels) each tile searches, and widens its
    /// footprint by.
    radius_px: f64,
    /// Which layout (each walked with its own cursor).
    kind: LayoutKind,
}

/// An acquisition's layouts of tiles ([`Navigator::walk_tiles`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum LayoutKind {
    /// The wide layout, at the guess's heading.
    Wide,
    /// The narrow layout ([`Navigator::narrow_layout`]).
    Narrow,
    /// The wide layout's tiles at the other headings ([`heading_hypotheses`]).
    Turned,
}

/// Where an acquisition's tile searches from: the guess moved east and
/// north, and turned about the local vertical.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Tile {
    /// East, north offset of the guess (m).
    offset_m: Vector2<f64>,
    /// Turn about the local vertical at the guess (rad, counter-clockwise
    /// seen from above: a heading error of the guess's attitude).
    heading_rad: f64,
}

/// The largest heading error (deg) a search around a guess stands: its
/// templates, warped as the guess sees them, turn by that in the image
/// (the edge of a 32-pixel template moves 1.4 px at 5 deg). Beyond,
/// an acquisition searches headings [`HEADING_STEP_DEG`] apart.
const HEADING_TOLERANCE_DEG: f64 = 5.0;

/// The step (deg) between the headings an acquisition searches, twice
/// what one search stands ([`HEADING_TOLERANCE_DEG`]).
const HEADING_STEP_DEG: f64 = 2.0 * HEADING_TOLERANCE_DEG;

/// The headings (rad, about the local vertical) an acquisition searches
/// for a heading sigma of `sigma_rad`: 0 alone where 2.5 sigmas are within
/// [`HEADING_TOLERANCE_DEG`]; else 0, then +-[`HEADING_STEP_DEG`],
/// +-2 steps, ... out to 2.5 sigmas (at most the whole turn; a sigma that
/// is not a number: 0 alone).
fn heading_hypotheses(sigma_rad: f64) -> Vec<f64> {
    let mut headings = vec![0.0];
    let reach = (2.5 * sigma_rad).min(std::f64::consts::PI);
    if sigma_rad.is_nan() || reach <= HEADING_TOLERANCE_DEG.to_radians() {
        return headings;
    }
    let step = HEADING_STEP_DEG.to_radians();
    let n = ((reach - HEADING_TOLERANCE_DEG.to_radians()) / step).ceil() as i32;
    for k in 1..=n {
        let h = k as f64 * step;
        if h > std::f64::consts::PI + 1e-9 {
            break;
        }
        headings.push(h);
        if h < std::f64::consts::PI - 1e-9 {
            headings.push(-h);
        }
    }
    headings
}

/// An acquisition's tiles: each of `offsets` (east, north, m) at each of
/// `headings` (rad), nearest first by the sum of the offset's square over
/// `need_m`'s and the heading's over `heading_reach_rad`'s (the guess
/// itself first); at one heading, the offsets in their own order (an
/// oblique view's layout is not ordered by distance alone).
fn with_headings(
    offsets: &[Vector2<f64>],
    headings: &[f64],
    need_m: f64,
    heading_reach_rad: f64,
) -> Vec<Tile> {
    if headings.len() <= 1 {
        let h = headings.first().copied().unwrap_or(0.0);
        return offsets.iter().map(|o| Tile { offset_m: *o, heading_rad: h }).collect();
    }
    let mut tiles: Vec<(f64, usize, Tile)> = Vec::with_capacity(offsets.len() * headings.len());
    for o in offsets {
        for &h in headings {
            let d = (o.norm() / need_m.max(1.0)).powi(2) + (h / heading_reach_rad.max(1e-9)).powi(2);
            tiles.push((d, tiles.len(), Tile { offset_m: *o, heading_rad: h }));
        }
    }
    tiles.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    tiles.into_iter().map(|(_, _, t)| t).collect()
}

/// The local vertical (ECEF unit vector, up) at `p`.
fn local_up(p: &trn_geodesy::Ecef) -> Vector3<f64> {
    trn_geodesy::LocalFrame::at(p.to_geodetic()).r_ecef_enu().column(2).into_owned()
}

/// `pose` turned by `heading_rad` about the local vertical at its position.
fn turned_about_vertical(pose: &CameraPose, heading_rad: f64) -> CameraPose {
    if heading_rad == 0.0 {
        return *pose;
    }
    let turn = UnitQuaternion::from_scaled_axis(local_up(&pose.position) * heading_rad);
    CameraPose::new(pose.position, turn * pose.q_ecef_cam)
}

/// The tiles one frame searches: from the cursor on (wrapping), until
/// `budget` work is spent; at least one tile, none twice.
#[derive(Clone, Copy, Debug)]
struct TileWalk {
    /// The first tile's index.
    start: usize,
    len: usize,
    searched: usize,
    spent: f64,
    budget: f64,
    /// The first tiles searched again at every frame before the cursor's
    /// (when the cursor is past them), and how many of them this frame has.
    head: usize,
    revisited: usize,
}

impl TileWalk {
    fn new(cursor: usize, len: usize, budget: f64) -> TileWalk {
        TileWalk {
            start: if len == 0 { 0 } else { cursor % len },
            len,
            searched: 0,
            spent: 0.0,
            budget,
            head: 0,
            revisited: 0,
        }
    }

    /// The walk with the first `head` tiles searched first at every frame
    /// (where the cursor is past them).
    fn with_head(self, head: usize) -> TileWalk {
        TileWalk { head: if self.start >= head { head } else { 0 }, ..self }
    }

    /// The index of the next tile to search, if the frame has work left.
    fn next_tile(&mut self) -> Option<usize> {
        if self.revisited < self.head {
            self.revisited += 1;
            return Some(self.revisited - 1);
        }
        // At least one tile from the cursor on, whatever the head spent.
        loop {
            if self.searched == self.len || (self.searched > 0 && self.spent >= self.budget) {
                return None;
            }
            let i = (self.start + self.searched) % self.len;
            self.searched += 1;
            // (A head tile wrapped to is not searched twice in a frame.)
            if i >= self.revisited {
                return Some(i);
            }
        }
    }

    /// The next frame's cursor: the tiles searched so far, counted on from
    /// this frame's first (not wrapped: while the doubt grows, the grid
    /// grows around the same nearest tiles, and the count goes on into it).
    fn cursor(&self) -> usize {
        self.start + self.searched
    }

    /// Counts the work the last tile's search took.
    fn spend(&mut self, work: f64) {
        self.spent += work;
    }
}

/// `Some` when the solution has fewer inliers than `min_inliers`, a smaller
/// share of its matches than `min_inlier_share`, or, an acquisition (or its
/// confirmation), a smaller share of the templates it searched for than
/// [`MIN_ACQUISITION_FOUND_SHARE`].
fn count_rejection(params: &NavParams, sol: &Solution) -> Option<Rejection> {
    if sol.inliers < params.min_inliers {
        Some(Rejection::FewInliers { inliers: sol.inliers })
    } else if (sol.inliers as f64) < params.min_inlier_share * sol.n_matches as f64 {
        Some(Rejection::InlierShare { inliers: sol.inliers, matches: sol.n_matches })
    } else if sol.acquisition && (sol.inliers as f64) < MIN_ACQUISITION_FOUND_SHARE * sol.n_searched as f64 {
        Some(Rejection::FoundShare { inliers: sol.inliers, searched: sol.n_searched })
    } else {
        None
    }
}

/// Whether the search outcome `a` is stronger than `b`: more inliers, or
/// (neither solved) more matches.
fn stronger(a: &Result<Solution, NoSolution>, b: &Result<Solution, NoSolution>) -> bool {
    match (a, b) {
        (Ok(a), Ok(b)) => a.inliers > b.inliers,
        (Ok(_), Err(_)) => true,
        (Err(a), Err(b)) => a.matches > b.matches,
        (Err(_), Ok(_)) => false,
    }
}

/// How many of the leading `works` fit within `budget` (at least one when
/// there is one).
fn within_budget(works: &[u64], budget: f64) -> usize {
    let mut total = 0.0;
    let fit = works
        .iter()
        .take_while(|&&w| {
            total += w as f64;
            total <= budget
        })
        .count();
    fit.max(works.len().min(1))
}

/// `p` moved by `offset` (east, north; m) in its local level frame.
fn shifted_enu(p: &trn_geodesy::Ecef, offset: &Vector2<f64>) -> trn_geodesy::Ecef {
    let g = p.to_geodetic();
    let moved =
        trn_geodesy::LocalFrame::at(g).to_ecef(trn_geodesy::Enu::new(offset.x, offset.y, 0.0)).to_geodetic();
    trn_geodesy::Geodetic::new(moved.lat_deg, moved.lon_deg, g.h_m).to_ecef()
}

/// Every match of a solution (inliers or not) as found.
fn matches_of(sol: &Solution) -> Vec<Match> {
    sol.records
        .iter()
        .filter_map(|r| {
            Some(Match {
                pixel: Pixel::new(r.u, r.v),
                point_ecef: r.landmark_ecef?.0,
                landmark: r.landmark,
                predicted: Pixel::new(r.pred_u, r.pred_v),
                sigma_px: r.sigma_px.unwrap_or(0.0),
                gsd_m: 0.0,
            })
        })
        .collect()
}

/// 99% of chi-square with 2 degrees of freedom: a match's innovation gate.
const GATE_CHI2_2DOF: f64 = 9.21;
/// What every match of a prior-gated update shares on top of its peak's
/// sigma (px): the inliers' residuals on the realistic flights are 0.2-0.6 px
/// RMS, from the map and the warp.
const GATED_SIGMA_FLOOR_PX: f64 = 0.4;
/// A match whose predicted pixel is more uncertain than this (px, 1 sigma
/// along its worst direction) takes no part in a prior-gated update.
const GATED_MAX_PREDICTED_SIGMA_PX: f64 = 4.0;
/// The prior-gated update's joint test at 99.9% (the normal quantile).
const JOINT_GATE_P_Z: f64 = 3.09;

/// Chi-square quantile with `k` degrees of freedom at the normal quantile
/// `z` (Wilson-Hilferty: within 1% for k >= 3 at 99.9%).
pub(crate) fn chi2_quantile(k: usize, z: f64) -> f64 {
    let k = k as f64;
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + z * a.sqrt()).powi(3)
}

/// The covariance (`[dtheta; dp]`, rad and m, ECEF) that errors of
/// `sigma_px` per landmark and coordinate, independent between landmarks,
/// give the pose `pose` solved from `landmarks` by least squares:
/// `sigma^2 (J^T J)^-1`, `J` the landmarks' pixels' Jacobian in the pose
/// (`trn_vision::pnp::project_with_jacobian`). `None` when a landmark is
/// behind the camera or the landmarks do not fix the pose.
fn landmark_error_pose_covariance(
    camera: &CameraModel,
    pose: &CameraPose,
    landmarks: &[Vector3<f64>],
    sigma_px: f64,
) -> Option<Matrix6<f64>> {
    let mut jtj = Matrix6::zeros();
    for x in landmarks {
        let (_, j) = project_with_jacobian(camera, pose, x)?;
        jtj += j.transpose() * j;
    }
    let inv = jtj.try_inverse()?;
    Some((inv + inv.transpose()) * (0.5 * sigma_px * sigma_px))
}

/// The inliers' pixels and landmarks (ECEF).
fn inliers_of(sol: &Solution) -> (Vec<Pixel>, Vec<Vector3<f64>>) {
    sol.records
        .iter()
        .filter(|r| r.inlier)
        .filter_map(|r| Some((Pixel::new(r.u, r.v), r.landmark_ecef?.0)))
        .unzip()
}

/// Per inlier, the pixel sigma (per coordinate): the correlation peak's own
/// (`sigma_px`) on top of a sigma `s0` that every match shares (the map, the
/// DEM, the warp), with `s0` such that the residuals are as large as the
/// sigmas say: `sum r^2 / (2 (s0^2 + s_i^2)) = n`. Where the peaks alone
/// explain more than the residuals show, the peaks' sigmas are scaled down
/// to fit. At least [`REFINE_SIGMA_PX`]. Without peak sigmas: the inliers'
/// RMS per coordinate for all.
///
/// The shared part is the landmark's own error (its database position and
/// height, its warp from about the same view): it repeats in every fix the
/// landmark is an inlier of, where the peak's is new each image. A landmark
/// that `runs` says was an inlier of the last `k - 1` accepted fixes in a
/// row is given `k s0^2` (a random constant's `k` looks then weigh as one),
/// so the filter no longer averages a landmark's error down by seeing it
/// again. Measured (README, inertial filter): the 640x480 rocket's fixes
/// kept a 120 m tilt/shift error for 4 s after its acquisition while their
/// sigma shrank (4 of 25 fixes outside their 95% bound; none with it).
fn inlier_sigmas_px(sol: &Solution, runs: &HashMap<i64, u32>) -> Vec<f64> {
    let inliers: Vec<&MatchRecord> =
        sol.records.iter().filter(|r| r.inlier && r.landmark_ecef.is_some()).collect();
    let (r2, s2): (Vec<f64>, Vec<f64>) =
        inliers.iter().map(|r| (r.residual_px.powi(2), r.sigma_px.unwrap_or(0.0).powi(2))).unzip();
    let looks = |r: &MatchRecord| 1.0 + runs.get(&r.landmark).copied().unwrap_or(0) as f64;
    let n = r2.len() as f64;
    let excess =
        |s0_2: f64| r2.iter().zip(&s2).map(|(r, s)| r / (2.0 * (s0_2 + s).max(1e-12))).sum::<f64>() - n;
    let var: Vec<f64> = if excess(0.0) <= 0.0 {
        // The peaks' sigmas alone are too large: scale them to the residuals.
        let k2 = (excess(0.0) + n) / n.max(1.0);
        s2.iter().map(|s| s * k2).collect()
    } else {
        // excess() falls as s0 grows; bisect on s0^2 up to the RMS's.
        let (mut lo, mut hi) = (0.0, r2.iter().sum::<f64>() / (2.0 * n.max(1.0)) + 1e-12);
        for _ in 0..50 {
            let mid = 0.5 * (lo + hi);
            if excess(mid) > 0.0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        s2.iter().zip(&inliers).map(|(s, r)| s + looks(r) * hi).collect()
    };
    var.iter().map(|v| v.sqrt().max(REFINE_SIGMA_PX)).collect()
}

/// [`FilterMode::Fixes`]: what the map's offset adds to a fix's pose
/// covariance (`[dtheta; dp]`, as `trn_vision::pnp`'s), for landmarks of
/// `gsd_m` (none unknown). A fix is the pose the images see; the landmarks
/// it matched may all be off alike (the ortho's registration, the DEM
/// under them, another sun), and the true pose by as much: the inertial
/// filter's map offset prior ([`map_sigmas_for_gsd`]), which the filter
/// carries as a state and this mode cannot learn.
fn map_offset_covariance(params: &NavParams, gsd_m: Option<f64>) -> Matrix6<f64> {
    let Some(gsd) = gsd_m else { return Matrix6::zeros() };
    let (m, deg) = map_sigmas_for_gsd(params, gsd);
    let mut cov = Matrix6::zeros();
    for i in 0..3 {
        cov[(i, i)] = deg.to_radians().powi(2);
        cov[(i + 3, i + 3)] = m * m;
    }
    cov
}

/// How much larger than the refinement assumed ([`REFINE_SIGMA_PX`]) a
/// fix's inliers say its pixel errors are: `(rms / sqrt 2)^2 / sigma^2`
/// (the per-axis sigma of their residuals' distances), at least 1. Without
/// the inertial filter (`--filter fixes`) a fix's covariance, solved at
/// 0.1 px, is scaled by it (the filter's updates weigh the matches at the
/// same sigma, `accept_ins`).
fn fit_variance_factor(sol: &Solution) -> f64 {
    ((inlier_rms_px(sol) / 2f64.sqrt()).max(REFINE_SIGMA_PX) / REFINE_SIGMA_PX).powi(2)
}

/// Root mean square of the inliers' reprojection errors (pixels, distance).
fn inlier_rms_px(sol: &Solution) -> f64 {
    let (n, sum) = sol
        .records
        .iter()
        .filter(|r| r.inlier)
        .fold((0, 0.0), |(n, s), r| (n + 1, s + r.residual_px.powi(2)));
    (sum / n.max(1) as f64).sqrt()
}

/// The largest pixel sigma (1 sigma along the worst direction, full-resolution
/// pixels) that the apparent pose's covariance `cov` (`[dtheta; dp]`, ECEF)
/// gives a ground point of the footprint `fp` seen from `guess`: at its four
/// corners and their centroid, `J cov J^T` with `J` the pixel's Jacobian in
/// the pose. Unlike a sum of the attitude's and the position's sigmas, it
/// keeps their correlation: after a fix a tilt and the shift it trades
/// with move the landmarks together, and the two cancel in the image.
/// `None` when no sample projects.
fn search_sigma_px(
    camera: &CameraModel,
    guess: &CameraPose,
    cov: &Matrix6<f64>,
    fp: &Footprint,
) -> Option<f64> {
    let corners: Vec<Vector3<f64>> = fp.corners.iter().map(|g| g.to_ecef().0).collect();
    let centre = corners.iter().sum::<Vector3<f64>>() / corners.len() as f64;
    corners
        .iter()
        .chain(std::iter::once(&centre))
        .filter_map(|x| {
            let (_, j) = project_with_jacobian(camera, guess, x)?;
            Some((j * cov * j.transpose()).symmetric_eigenvalues().max().max(0.0).sqrt())
        })
        .reduce(f64::max)
}

/// The search radius at the next finer pyramid level after a coarse level
/// gave no trustworthy pose: the same ground radius (twice the pixels), but
/// at most twice `max_radius_px`. Beyond that the coarser level has searched
/// the ground already, and a full-resolution search of hundreds of pixels
/// per landmark costs seconds per frame while lost (5.8 s per 1024x768
/// frame measured before this bound), for a match the coarse level missed.
fn widened(radius: usize, max_radius_px: usize) -> usize {
    (radius * 2).min(2 * max_radius_px)
}

/// Least-squares velocity (m/s) of timed positions, with its 1-sigma error
/// (from the fit's residuals, at least [`VELOCITY_KNOWN_SIGMA_M_S`]); `None`
/// when they span less than [`VELOCITY_MIN_SPAN_S`] or number fewer than 3.
fn velocity_fit(fixes: &std::collections::VecDeque<(f64, Vector3<f64>)>) -> Option<(Vector3<f64>, f64)> {
    let n = fixes.len();
    let (t0, t1) = (fixes.front()?.0, fixes.back()?.0);
    if n < 3 || t1 - t0 < VELOCITY_MIN_SPAN_S {
        return None;
    }
    let tm = fixes.iter().map(|f| f.0).sum::<f64>() / n as f64;
    let pm = fixes.iter().map(|f| f.1).sum::<Vector3<f64>>() / n as f64;
    let stt = fixes.iter().map(|f| (f.0 - tm).powi(2)).sum::<f64>();
    let v = fixes.iter().map(|f| (f.1 - pm) * (f.0 - tm)).sum::<Vector3<f64>>() / stt;
    // Residual scatter per axis, and the slope's error sigma / sqrt(Stt).
    let ss: f64 = fixes.iter().map(|f| (f.1 - pm - v * (f.0 - tm)).norm_squared()).sum::<f64>();
    let sigma_pos = (ss / (3.0 * (n as f64 - 2.0).max(1.0))).sqrt();
    Some((v, (sigma_pos / stt.sqrt()).max(VELOCITY_KNOWN_SIGMA_M_S)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ins;
    use trn_geodesy::{Ecef, Enu, Geodetic, LocalFrame};

    /// A camera `height_m` above `frame`'s origin looking straight down,
    /// its image's up to the north.
    fn nadir_pose(frame: &LocalFrame, height_m: f64) -> CameraPose {
        CameraPose::look_at(
            frame.to_ecef(Enu::new(0.0, 0.0, height_m)),
            frame.to_ecef(Enu::new(0.0, 0.0, 0.0)),
            frame.r_ecef_enu().column(1).into_owned(),
        )
    }

    /// A nadir camera 5 km above the ground, the inertial filter's estimate
    /// 30 m east of it, and ground landmarks seen in a small central box.
    fn gated_scene() -> (CameraModel, InsFilter, LocalFrame, CameraPose, Vec<Vector3<f64>>) {
        let camera = CameraModel::from_fov(640, 480, 40.0);
        let frame = LocalFrame::at(Geodetic::new(37.0, -118.0, 0.0));
        let truth = nadir_pose(&frame, 5000.0);
        let state = InsState {
            t: 0.0,
            position: frame.to_ecef(Enu::new(30.0, 0.0, 5000.0)),
            velocity_ecef_m_s: Vector3::zeros(),
            q_ecef_imu: truth.q_ecef_cam,
            gyro_bias_imu_rad_s: Vector3::zeros(),
            accel_bias_imu_m_s2: Vector3::zeros(),
            map_offset_ecef_m: Vector3::zeros(),
            map_offset_att_rad: Vector3::zeros(),
            time_offset_s: 0.0,
            rate_ecef_rad_s: Vector3::zeros(),
        };
        let init = InsInit {
            attitude_rad: 0.02f64.to_radians(),
            // 3.5 px at 5 km: the prediction gates (see GATED_MAX_PREDICTED_SIGMA_PX).
            position_m: 20.0,
            velocity_m_s: 1.0,
            gyro_bias_rad_s: 1e-5,
            accel_bias_m_s2: 0.01,
            time_offset_s: 0.0,
            focal_rel: 0.0,
            principal_px: 0.0,
        };
        let errors = InsErrors {
            gyro_arw_rad_sqrt_s: 1e-5,
            gyro_bias_walk_rad_s_sqrt_s: 0.0,
            accel_vrw_m_s_sqrt_s: 1e-3,
            accel_bias_walk_m_s2_sqrt_s: 0.0,
            free_accel_m_s2_sqrt_s: 1.0,
            map_sigma_m: 0.0,
            map_tau_s: 10.0,
            map_att_sigma_rad: 0.0,
            focal_walk_rel_sqrt_s: 0.0,
            gyro_max_jump_rad_s: 0.0,
            accel_max_jump_m_s2: 0.0,
            imu_gap_s: 0.0,
            gap_rate_walk_rad_s_sqrt_s: 0.0,
            principal_walk_px_sqrt_s: 0.0,
        };
        // Within +-300 m of the nadir point: +-38 px of a 640 x 480 image.
        let points = [(-250.0, -200.0), (240.0, -180.0), (0.0, 260.0), (-120.0, 90.0), (200.0, 150.0)]
            .iter()
            .map(|&(e, n)| frame.to_ecef(Enu::new(e, n, 0.0)).0)
            .collect();
        (camera, InsFilter::new(state, &init, errors), frame, truth, points)
    }

    /// What independent errors of a landmark's pixel give the pose solved
    /// from a view's landmarks, against a Monte Carlo of the least-squares
    /// solve itself (`refine_pose` on noisy pixels): the same covariance,
    /// and a narrow view's far larger along the tilt-for-shift trade.
    #[test]
    fn landmark_errors_give_the_pose_the_covariance_a_monte_carlo_of_the_solve_gives() {
        let camera = CameraModel::from_fov(1024, 768, 32.0);
        let frame = LocalFrame::at(Geodetic::new(37.4, -118.5, 2000.0));
        let truth = nadir_pose(&frame, 30e3);
        // An 8 x 8 grid over `share` of the image's sides, with relief.
        let half_width_m = 30e3 * 16f64.to_radians().tan();
        let landmarks = |share: f64| -> Vec<Vector3<f64>> {
            (0..64)
                .map(|k| {
                    let (i, j) = ((k % 8) as f64 / 7.0 - 0.5, (k / 8) as f64 / 7.0 - 0.5);
                    let (e, n) = (i * share * 2.0 * half_width_m, j * share * 1.5 * half_width_m);
                    let h = 300.0 * (e / 2100.0).sin() * (n / 1700.0).cos();
                    frame.to_ecef(Enu::new(e, n, h)).0
                })
                .collect()
        };
        // xorshift64* and Box-Muller: the test's own normal numbers.
        let mut seed = 0x9e37_79b9_7f4a_7c15u64;
        let mut normal = move || {
            let mut uniform = || {
                seed ^= seed >> 12;
                seed ^= seed << 25;
                seed ^= seed >> 27;
                ((seed.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            let (a, b) = (uniform(), uniform());
            (-2.0 * a.ln()).sqrt() * (std::f64::consts::TAU * b).cos()
        };
        let sigma = 0.5;
        let mut largest = Vec::new();
        for share in [0.35, 1.0] {
            let pts = landmarks(share);
            let c = landmark_error_pose_covariance(&camera, &truth, &pts, sigma).expect("fixed");
            let pixels: Vec<Pixel> =
                pts.iter().map(|p| truth.project(&camera, &Ecef(*p)).expect("in view")).collect();
            let trials = 400;
            let mut sample = Matrix6::zeros();
            for _ in 0..trials {
                let noisy: Vec<Pixel> = pixels
                    .iter()
                    .map(|p| Pixel::new(p.u + sigma * normal(), p.v + sigma * normal()))
                    .collect();
                let opts = RefineOptions { pixel_sigma: sigma, ..RefineOptions::default() };
                let r = refine_pose(&camera, &noisy, &pts, &truth, &opts).expect("solved");
                let d = ins::pose_difference(&r.pose, &truth);
                sample += d * d.transpose() / trials as f64;
            }
            // In the analytic covariance's own sigmas, the sample's is the
            // identity within the sampling error (400 draws: ~7% per
            // variance; the extreme eigenvalues of six spread further).
            let e = c.symmetric_eigen();
            let w = e.eigenvectors.transpose() * sample * e.eigenvectors;
            let w = Matrix6::from_fn(|i, j| w[(i, j)] / (e.eigenvalues[i] * e.eigenvalues[j]).sqrt());
            let ev = w.symmetric_eigenvalues();
            assert!(ev.min() > 0.75 && ev.max() < 1.3, "share {share}: {ev}");
            largest.push(e.eigenvalues.max().sqrt());
        }
        // The narrow view (0.35 of the sides): the largest direction, a
        // tilt for a shift, 6 times the wide view's (200 against 33 m).
        assert!(largest[0] > 4.0 * largest[1], "{largest:?}");
    }

    fn seen(camera: &CameraModel, truth: &CameraPose, points: &[Vector3<f64>]) -> Vec<Match> {
        points
            .iter()
            .enumerate()
            .map(|(i, p)| Match {
                pixel: truth.project(camera, &Ecef(*p)).expect("in view"),
                point_ecef: *p,
                landmark: i as i64,
                sigma_px: 0.1,
                ..Match::default()
            })
            .collect()
    }

    #[test]
    fn a_frame_without_a_fix_updates_the_principal_point_the_filter_carries() {
        // The filter at the true pose, known to 10 urad and 0.5 m, and the
        // principal point a state known to 3 px; the true camera's is 2 px
        // right and 1 px up. Through the frame's sensitivity the gated
        // matches measure it; without it they are 2.2 px from a prediction
        // known to a tenth of a pixel, and every gate refuses them.
        let (camera, mut f, _, truth, points) = gated_scene();
        f.state.position = truth.position;
        for i in 0..6 {
            f.covariance[(i, i)] = if i < 3 { 1e-10 } else { 0.25 };
        }
        for i in ins::PRINCIPAL..ins::PRINCIPAL + 2 {
            f.covariance[(i, i)] = 9.0;
        }
        assert!(f.estimates_principal_point());
        let mut true_camera = camera;
        (true_camera.cx, true_camera.cy) = (camera.cx + 2.0, camera.cy - 1.0);
        let found = seen(&true_camera, &truth, &points);
        let px: Vec<Pixel> = found.iter().map(|m| m.pixel).collect();
        let fc = frame_calibration(&camera, &px, &points, &truth, 0.1, 0.0, None).expect("five points");
        let sensitivity = IntrinsicsSensitivity::of_frame(&fc.pose_sensitivity);
        let q = UnitQuaternion::identity();
        let mut without = f.clone();
        assert_eq!(prior_gated_update(&camera, &q, &mut without, &found, &IntrinsicsSensitivity::NONE), 0);
        assert_eq!(prior_gated_update(&camera, &q, &mut f, &found, &sensitivity), 5);
        let (est, cov) = f.take_principal_error();
        println!(
            "principal point {:+.3} {:+.3} px +- {:.3} {:.3}",
            est.x,
            est.y,
            cov[(0, 0)].sqrt(),
            cov[(1, 1)].sqrt()
        );
        assert!((est - nalgebra::Vector2::new(2.0, -1.0)).norm() < 0.2, "{est}");
        assert!(cov[(0, 0)].sqrt() < 0.5 && cov[(1, 1)].sqrt() < 0.5, "{cov}");
    }

    #[test]
    fn a_few_matches_update_the_tight_filter_and_a_wrong_one_is_dropped() {
        let (camera, mut f, frame, truth, points) = gated_scene();
        let east = |f: &InsFilter| frame.to_enu(&f.state.position).0.x;
        let mut found = seen(&camera, &truth, &points);
        // One match 12 px off (a repeated texture).
        found[2].pixel.u += 12.0;
        let q = UnitQuaternion::identity();
        let n = prior_gated_update(&camera, &q, &mut f, &found, &IntrinsicsSensitivity::NONE);
        assert_eq!(n, 4, "the wrong match is dropped");
        assert!(east(&f).abs() < 3.0, "30 m east before, {:.1} m after", east(&f));
        assert!(f.covariance[(ins::POS, ins::POS)] < 30.0f64.powi(2));
        // Two matches say too little, and a prediction as uncertain as 100 m
        // gates nothing: nothing changes.
        let (_, mut g, _, _, _) = gated_scene();
        let before = g.clone();
        assert_eq!(prior_gated_update(&camera, &q, &mut g, &found[..2], &IntrinsicsSensitivity::NONE), 0);
        assert_eq!(g, before);
        for i in 3..6 {
            g.covariance[(i, i)] = 100.0f64.powi(2);
        }
        let before = g.clone();
        assert_eq!(
            prior_gated_update(
                &camera,
                &q,
                &mut g,
                &seen(&camera, &truth, &points),
                &IntrinsicsSensitivity::NONE
            ),
            0
        );
        assert_eq!(g, before);
        // Matches that all disagree with the prediction (a guess far off
        // its covariance): refused as a whole.
        let (_, mut h, _, _, _) = gated_scene();
        let far = CameraPose { position: frame.to_ecef(Enu::new(400.0, 0.0, 5000.0)), ..truth };
        assert_eq!(
            prior_gated_update(
                &camera,
                &q,
                &mut h,
                &seen(&camera, &far, &points),
                &IntrinsicsSensitivity::NONE
            ),
            0
        );
    }

    /// An acquisition whose inliers are few of the templates it searched
    /// for is an alias (the oblique balloon's 9 of 300, 9 km off), whatever
    /// their share of its matches (9 of 17); a true one holds more (the
    /// 640x480 rocket's tiles, 15 of 101 and 8 of 130). A tracking fix is
    /// not held to it.
    #[test]
    fn an_acquisition_must_find_a_share_of_what_it_searched_for() {
        let params = NavParams::default();
        let with = |inliers: usize, n_matches: usize, n_searched: usize, acquisition: bool| Solution {
            inliers,
            n_matches,
            n_searched,
            acquisition,
            ..solution_of(&[])
        };
        assert_eq!(
            count_rejection(&params, &with(9, 17, 300, true)),
            Some(Rejection::FoundShare { inliers: 9, searched: 300 })
        );
        assert_eq!(count_rejection(&params, &with(15, 20, 101, true)), None);
        assert_eq!(count_rejection(&params, &with(8, 10, 130, true)), None);
        assert_eq!(count_rejection(&params, &with(9, 17, 300, false)), None);
        // About the bound (15 of 300): 16 stands, 14 does not (of 30
        // matches, above the inlier share).
        assert_eq!(count_rejection(&params, &with(16, 30, 300, true)), None);
        assert!(matches!(
            count_rejection(&params, &with(14, 30, 300, true)),
            Some(Rejection::FoundShare { .. })
        ));
        // The other counts come first.
        assert_eq!(
            count_rejection(&params, &with(9, 40, 300, true)),
            Some(Rejection::InlierShare { inliers: 9, matches: 40 })
        );
    }

    fn solution_of(matches: &[(f64, Option<f64>, bool)]) -> Solution {
        let records = matches
            .iter()
            .enumerate()
            .map(|(i, &(residual_px, sigma_px, inlier))| MatchRecord {
                t: 0.0,
                landmark: i as i64,
                u: 0.0,
                v: 0.0,
                pred_u: 0.0,
                pred_v: 0.0,
                residual_px,
                inlier,
                landmark_ecef: Some(trn_geodesy::Ecef::new(1.0, 2.0, 3.0)),
                sigma_px,
            })
            .collect();
        Solution {
            pose: CameraPose::new(trn_geodesy::Ecef::new(0.0, 0.0, 0.0), UnitQuaternion::identity()),
            inliers: 0,
            n_matches: matches.len(),
            records,
            points: Vec::new(),
            guess_px: Vec::new(),
            covariance: Matrix6::identity(),
            prior_loosened: false,
            acquisition: false,
            tile: None,
            n_searched: 0,
            mean_landmark_h: None,
            median_gsd_m: None,
        }
    }

    #[test]
    fn a_fix_covariance_is_scaled_by_its_residuals() {
        // Inliers 0.8 px off (0.57 px per axis) where the refinement
        // assumed 0.1 px: 32 times the variance; the outlier counts not.
        let mut m: Vec<(f64, Option<f64>, bool)> = (0..12).map(|_| (0.8, None, true)).collect();
        m.push((30.0, None, false));
        let k = fit_variance_factor(&solution_of(&m));
        assert!((k - 32.0).abs() < 1e-9, "{k}");
        // Residuals under the assumed sigma never shrink it.
        assert_eq!(fit_variance_factor(&solution_of(&[(0.05, None, true); 6])), 1.0);
    }

    #[test]
    fn per_match_sigmas_add_a_shared_sigma_that_fits_the_residuals() {
        // Residuals of 1 px; peaks of 0.05 px and one weak one of 2 px.
        let mut m: Vec<(f64, Option<f64>, bool)> = (0..20).map(|_| (1.0, Some(0.05), true)).collect();
        m.push((1.0, Some(2.0), true));
        m.push((30.0, Some(0.01), false));
        let sol = solution_of(&m);
        let s = inlier_sigmas_px(&sol, &HashMap::new());
        assert_eq!(s.len(), 21);
        // sum r^2 / (2 sigma^2) = n over the inliers.
        let fit: f64 = s.iter().map(|x| 1.0 / (2.0 * x * x)).sum();
        assert!((fit - 21.0).abs() < 1e-6, "{fit}");
        let s0 = (s[0] * s[0] - 0.05f64.powi(2)).sqrt();
        assert!((s[20] * s[20] - s0 * s0 - 4.0).abs() < 1e-9, "{s:?}");
        assert!(s[20] > 2.0 && s[0] < 0.71 && s[0] > 0.5, "{s:?}");
        // Without peak sigmas: the inliers' RMS per coordinate, for all.
        let sol = solution_of(
            &(0..10).map(|i| (if i % 2 == 0 { 1.0 } else { 3.0 }, None, true)).collect::<Vec<_>>(),
        );
        let s = inlier_sigmas_px(&sol, &HashMap::new());
        let rms = (inlier_rms_px(&sol) / 2f64.sqrt()).max(REFINE_SIGMA_PX);
        assert!(s.iter().all(|x| (x - rms).abs() < 1e-6 * rms), "{s:?} {rms}");
        // Peaks wider than the scatter: scaled down to it, their ratios kept.
        let sol = solution_of(&[(0.5, Some(2.0), true), (0.5, Some(4.0), true), (0.5, Some(2.0), true)]);
        let s = inlier_sigmas_px(&sol, &HashMap::new());
        assert!((s[1] / s[0] - 2.0).abs() < 1e-9 && s[0] < 2.0, "{s:?}");
    }

    #[test]
    fn a_landmark_seen_again_weighs_its_shared_sigma_once() {
        // 20 inliers, residuals of 1 px, peaks of 0.1 px; landmarks 0-4 were
        // inliers of the last 3 fixes, 5 of the last one.
        let m: Vec<(f64, Option<f64>, bool)> = (0..20).map(|_| (1.0, Some(0.1), true)).collect();
        let sol = solution_of(&m);
        let fresh = inlier_sigmas_px(&sol, &HashMap::new());
        let runs: HashMap<i64, u32> = (0..5).map(|l| (l, 3)).chain([(5, 1), (99, 7)]).collect();
        let seen = inlier_sigmas_px(&sol, &runs);
        // The shared sigma is the frame's whatever was seen before.
        let s0_2 = fresh[0].powi(2) - 0.01;
        for (l, (a, b)) in fresh.iter().zip(&seen).enumerate() {
            let looks = match l {
                0..=4 => 4.0,
                5 => 2.0,
                _ => 1.0,
            };
            // (Four looks at 4 s0^2 carry the information of one at s0^2.)
            assert!((b.powi(2) - (0.01 + looks * s0_2)).abs() < 1e-9, "landmark {l}: {b} (fresh {a})");
        }
    }

    /// A 32-pixel template at `gsd_m` whose centre is `east_m` east of a
    /// fixed point (brute-force distances below are along the east axis).
    fn template_east(id: i64, east_m: f64, gsd_m: f64) -> Template {
        use trn_landmark::{HeightGrid, TerrainPatch};
        let origin = Geodetic::new(37.0, -118.5, 2000.0);
        let frame = LocalFrame::at(origin);
        let center = frame.to_ecef(Enu::new(east_m, 0.0, 0.0)).to_geodetic();
        let terrain = TerrainPatch {
            plane_normal_enu: [0.0, 0.0, 1.0],
            plane_residual_rms_m: 0.0,
            height_grid: HeightGrid { n: 2, spacing_m: 32.0 * gsd_m, heights_m: vec![0.0; 4] },
        };
        crate::test_fixtures::template(id, center, gsd_m, 32, terrain, vec![128; 32 * 32])
    }

    #[test]
    fn near_duplicates_go_after_the_others_in_their_order() {
        // Footprints 32 m (gsd 1 m) and 64 m (gsd 2 m); separation 0.5: 16 m,
        // or 32 m next to the coarser one.
        let ts = [
            template_east(1, 0.0, 1.0),
            template_east(2, 10.0, 1.0),  // 10 m from 1: a duplicate
            template_east(3, 40.0, 1.0),  // 40 m from 1: kept
            template_east(4, 54.0, 1.0),  // 14 m from 3: a duplicate
            template_east(5, 80.0, 2.0),  // 40 m from 3, beyond 32 m: kept
            template_east(6, 100.0, 1.0), // 20 m from 5, within its 32 m: a duplicate
            template_east(7, 130.0, 1.0), // 50 m from 5: kept
        ];
        let order = |separation: f64, cap: usize| {
            let mut c: Vec<_> =
                ts.iter().enumerate().map(|(i, t)| (-(i as f32), t.center_ecef(), t)).collect();
            duplicates_last(&mut c, separation, cap);
            c.iter().map(|(_, _, t)| t.id).collect::<Vec<_>>()
        };
        assert_eq!(order(0.5, 450), [1, 3, 5, 7, 2, 4, 6]);
        // Off: unchanged.
        assert_eq!(order(0.0, 450), [1, 2, 3, 4, 5, 6, 7]);
        // A wider separation (64 m; 128 m for 5) leaves fewer apart: 5 is
        // 80 m from 1, within its own 128 m; 6, 100 m from 1, is the first
        // beyond 64 m; 7 is 30 m from 6.
        assert_eq!(order(2.0, 450), [1, 6, 2, 3, 4, 5, 7]);
        // No more than the cap are looked for: the rest keep their order.
        assert_eq!(order(0.5, 2), [1, 3, 2, 4, 5, 6, 7]);
    }

    #[test]
    fn inliers_on_a_line_or_in_a_cluster_do_not_spread() {
        let (w, h) = (640.0, 480.0);
        // A 10 x 8 lattice over the whole image: every cell, a spread of
        // about a third of the side (uniform: side / sqrt(12) = 0.29).
        let lattice: Vec<Pixel> = (0..80)
            .map(|i| Pixel::new(32.0 + 64.0 * (i % 10) as f64, 30.0 + 60.0 * (i / 10) as f64))
            .collect();
        let (cells, spread) = inlier_spread(&lattice, w, h, (8, 6));
        assert_eq!(cells, 48);
        assert!((spread - 60.0 * (63.0f64 / 12.0).sqrt()).abs() < 1e-6, "{spread}");
        // A diagonal line crosses many cells but has no width.
        let line: Vec<Pixel> = (0..50).map(|i| Pixel::new(12.0 * i as f64, 9.0 * i as f64)).collect();
        let (cells, spread) = inlier_spread(&line, w, h, (8, 6));
        assert!(cells >= 6 && spread < 1e-6, "{cells} {spread}");
        // A cluster in one corner: one cell.
        let cluster: Vec<Pixel> =
            (0..30).map(|i| Pixel::new(5.0 + (i % 6) as f64 * 8.0, 5.0 + (i / 6) as f64 * 8.0)).collect();
        let (cells, spread) = inlier_spread(&cluster, w, h, (8, 6));
        assert_eq!(cells, 1);
        assert!(spread < 0.04 * h, "{spread}");
        assert_eq!(inlier_spread(&[], w, h, (8, 6)), (0, 0.0));
        // A hole in the cloud: landmarks over a centred box of a quarter of
        // the image's sides cover enough cells but are refused by the default
        // spread; a box of 35% of the sides is taken.
        let p = NavParams::default();
        let hole = |share: f64| centred_box(w, h, share, 10, 10);
        let (cells, spread) = inlier_spread(&hole(0.25), w, h, p.grid);
        assert!(cells >= p.min_inlier_cells && spread < p.min_inlier_spread * h, "{cells} {spread}");
        let (cells, spread) = inlier_spread(&hole(0.35), w, h, p.grid);
        assert!(cells >= p.min_inlier_cells && spread >= p.min_inlier_spread * h, "{cells} {spread}");
    }

    #[test]
    fn a_narrow_views_inconsistent_fix_doubts_the_filter_only_when_another_agrees() {
        let p = NavParams::default();
        let (w, h) = (1024.0, 768.0);
        let box_of = |share: f64| inlier_spread(&centred_box(w, h, share, 20, 20), w, h, p.grid).0;
        // The holes of scripts/bench_narrow.sh (0.3-0.5 of the sides) are
        // narrow: an inconsistent fix of one leaves the filter as it is
        // unless it agrees with the one before.
        for share in [0.3, 0.4, 0.5] {
            let cells = box_of(share);
            assert!(!doubts_filter(cells, p.doubt_min_cells, false, true), "{share}: {cells} cells");
            assert!(doubts_filter(cells, p.doubt_min_cells, true, true), "{share}: {cells} cells");
            // Before the pose is confirmed, every one doubts it.
            assert!(doubts_filter(cells, p.doubt_min_cells, false, false), "{share}: {cells} cells");
        }
        // Three quarters of the image, or all of it, pin the pose whole.
        for share in [0.75, 1.0] {
            let cells = box_of(share);
            assert!(doubts_filter(cells, p.doubt_min_cells, false, true), "{share}: {cells} cells");
        }
        // 0: every inconsistent fix doubts, as before the option.
        assert!(doubts_filter(box_of(0.3), 0, false, true));
    }

    /// A `cols x rows` lattice over a centred box of `share` of a `w x h`
    /// image's sides (a hole in the cloud), corners included.
    fn centred_box(w: f64, h: f64, share: f64, cols: usize, rows: usize) -> Vec<Pixel> {
        let (bw, bh) = (share * w, share * h);
        (0..cols * rows)
            .map(|i| {
                Pixel::new(
                    0.5 * (w - bw) + bw * (i % cols) as f64 / (cols - 1) as f64,
                    0.5 * (h - bh) + bh * (i / cols) as f64 / (rows - 1) as f64,
                )
            })
            .collect()
    }

    #[test]
    fn a_narrow_views_disagreeing_matches_are_no_miss() {
        let p = NavParams::default();
        let (w, h) = (1024.0, 768.0);
        let box_px = |share: f64| centred_box(w, h, share, 10, 6);
        assert_eq!(p.miss_min_cells, 24);
        // Off (0): every disagreeing frame is a miss.
        assert!(!narrow_miss(box_px(0.3), w, h, p.grid, 0));
        // With the default, 24 cells: the holes of scripts/bench_narrow.sh
        // (0.3-0.5 of the sides) are narrow, three quarters of the image or all of it
        // not, and a frame without matches is no narrow view.
        for share in [0.3, 0.4, 0.5] {
            assert!(narrow_miss(box_px(share), w, h, p.grid, p.miss_min_cells), "{share}");
        }
        for share in [0.75, 1.0] {
            assert!(!narrow_miss(box_px(share), w, h, p.grid, p.miss_min_cells), "{share}");
        }
        assert!(!narrow_miss([], w, h, p.grid, p.miss_min_cells));
        // A wide view's few scattered matches (a turned attitude's wrong
        // ones) fall in 5 cells but span the image: no narrow view.
        let scattered = [(100.0, 80.0), (900.0, 120.0), (500.0, 400.0), (150.0, 700.0), (950.0, 690.0)]
            .map(|(u, v)| Pixel::new(u, v));
        assert_eq!(inlier_spread(&scattered, w, h, p.grid).0, 5);
        assert_eq!(spanned_cells(scattered, w, h, p.grid), 48);
        assert!(!narrow_miss(scattered, w, h, p.grid, p.miss_min_cells));
        // Three of them on one row of cells: a strip 8 cells long.
        let strip = [(100.0, 80.0), (900.0, 120.0), (500.0, 60.0)].map(|(u, v)| Pixel::new(u, v));
        assert_eq!(spanned_cells(strip, w, h, p.grid), 8);
    }

    /// A `[dtheta; dp]` covariance of `att_deg` about and `pos_m` along
    /// each axis (1 sigma), uncorrelated.
    fn pose_variances(att_deg: f64, pos_m: f64) -> Matrix6<f64> {
        let a = att_deg.to_radians().powi(2);
        let p = pos_m * pos_m;
        Matrix6::from_diagonal(&Vector6::new(a, a, a, p, p, p))
    }

    #[test]
    fn two_refused_fixes_agree_when_the_filter_is_off_by_the_same() {
        // A fix's covariance: 0.05 deg and 20 m (1 sigma per axis).
        let r = pose_variances(0.05, 20.0);
        let gate = NavParams::default().innovation_gate_chi2;
        // The filter 150 m east and 0.3 deg off: two fixes see it alike,
        // within their own noise (1 sigma apart on two axes).
        let off = Vector6::new(0.3f64.to_radians(), 0.0, 0.0, 150.0, 0.0, 0.0);
        let noise = Vector6::new(0.0, 0.05f64.to_radians(), 0.0, 0.0, 20.0, 0.0);
        assert!(innovations_agree(&off, &r, &(off + noise), &r, gate));
        // A narrow view's two wrong solutions, each as far from the filter:
        // one 150 m east, the other 150 m north.
        let north = Vector6::new(0.0, 0.3f64.to_radians(), 0.0, 0.0, 150.0, 0.0);
        assert!(!innovations_agree(&off, &r, &north, &r, gate));
        // The test is the gate's: at its edge along one axis, and past it.
        let edge = (gate * 2.0 * 400.0).sqrt();
        let along = |m: f64| Vector6::new(0.0, 0.0, 0.0, 0.0, 0.0, m);
        assert!(innovations_agree(&off, &r, &(off + along(0.99 * edge)), &r, gate));
        assert!(!innovations_agree(&off, &r, &(off + along(1.01 * edge)), &r, gate));
        // A covariance that cannot be inverted agrees with nothing.
        assert!(!innovations_agree(&off, &Matrix6::zeros(), &off, &Matrix6::zeros(), gate));
    }

    #[test]
    fn lighting_is_the_nearest_baked_sun() {
        let sun = |azimuth_deg, elevation_deg| SunLight { azimuth_deg, elevation_deg, ambient: 0.25 };
        let baked = [sun(250.0, 25.0), sun(240.0, 12.0), sun(90.0, 40.0)];
        // As imaged: lighting 0, whatever the flight's sun.
        assert_eq!(choose_lighting(&[], Some(&sun(250.0, 25.0))), (0, false));
        assert_eq!(choose_lighting(&[], None), (0, false));
        // No sun given: the first, not known to be the flight's.
        assert_eq!(choose_lighting(&baked, None), (1, false));
        assert_eq!(choose_lighting(&baked, Some(&sun(252.0, 24.0))), (1, true));
        assert_eq!(choose_lighting(&baked, Some(&sun(238.0, 10.0))), (2, true));
        // -270 is 90: the same direction.
        assert_eq!(choose_lighting(&baked, Some(&sun(-270.0, 41.0))), (3, true));
        // The nearest is too far to count as the flight's.
        assert_eq!(choose_lighting(&baked, Some(&sun(180.0, 60.0))), (3, false));
    }

    /// `search_sigma_px` against brute force: poses drawn from the
    /// covariance, the footprint's ground points projected, the largest
    /// per-point pixel sigma measured. A covariance whose tilt and shift
    /// trade (what a fix leaves: 0.1 deg of tilt against 8.7 m of shift at
    /// 5 km) moves the landmarks far less than the two sigmas added.
    #[test]
    fn the_search_sigma_is_the_pose_covariance_seen_in_the_image() {
        let camera = CameraModel::from_fov(640, 480, 40.0);
        let frame = LocalFrame::at(Geodetic::new(37.0, -118.0, 0.0));
        let pose = nadir_pose(&frame, 5000.0);
        let fp = footprint(&camera, &pose, &FootprintParams::default()).unwrap();
        let (east, north) =
            (frame.r_ecef_enu().column(0).into_owned(), frame.r_ecef_enu().column(1).into_owned());
        // Tilt about north (rad) with the eastward shift it trades with, plus
        // small independent parts.
        let tilt = 0.1f64.to_radians();
        let mut l = Matrix6::<f64>::zeros();
        l.fixed_view_mut::<3, 1>(0, 0).copy_from(&(north * tilt));
        l.fixed_view_mut::<3, 1>(3, 0).copy_from(&(east * tilt * 5000.0));
        for i in 1..6 {
            l[(i, i)] = if i < 3 { 0.005f64.to_radians() } else { 2.0 };
        }
        let cov = l * l.transpose();
        let got = search_sigma_px(&camera, &pose, &cov, &fp).unwrap();
        // Brute force: draws d = L z, z ~ N(0, I).
        let mut rng = 0x2545_f491_4f6c_dd1du64;
        let mut normal = move || {
            let mut u = || {
                rng ^= rng << 13;
                rng ^= rng >> 7;
                rng ^= rng << 17;
                (rng >> 11) as f64 / (1u64 << 53) as f64
            };
            let (u1, u2) = (1.0 - u(), u());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        };
        let corners: Vec<Vector3<f64>> = fp.corners.iter().map(|g| g.to_ecef().0).collect();
        let centre = corners.iter().sum::<Vector3<f64>>() / 4.0;
        let points: Vec<Vector3<f64>> = corners.iter().copied().chain([centre]).collect();
        let n = 4000;
        let mut sums = vec![Matrix2::<f64>::zeros(); points.len()];
        for _ in 0..n {
            let z = nalgebra::Vector6::from_fn(|_, _| normal());
            let p = perturb_pose(&pose, &(l * z));
            for (k, x) in points.iter().enumerate() {
                let (a, b) =
                    (pose.project(&camera, &Ecef(*x)).unwrap(), p.project(&camera, &Ecef(*x)).unwrap());
                let d = Vector2::new(b.u - a.u, b.v - a.v);
                sums[k] += d * d.transpose();
            }
        }
        let brute =
            sums.iter().map(|s| (s / n as f64).symmetric_eigenvalues().max().sqrt()).fold(0.0, f64::max);
        assert!((got - brute).abs() < 0.05 * brute, "search sigma {got:.3} px, brute force {brute:.3} px");
        // The attitude's and the position's sigmas added, as without the
        // filter's covariance: several times wider.
        let att = cov.fixed_view::<3, 3>(0, 0).trace().sqrt();
        let pos = cov.fixed_view::<3, 3>(3, 3).trace().sqrt();
        let added = camera.fx * (att + pos / fp.center_range_m);
        assert!(added > 4.0 * got, "added {added:.2} px, covariance {got:.2} px");
    }

    #[test]
    fn a_failed_coarse_level_widens_the_next_search_within_a_bound() {
        assert_eq!(widened(5, 16), 10);
        assert_eq!(widened(16, 16), 32);
        assert_eq!(widened(32, 16), 32);
        // A first search wider than the bound (the coarsest level's) is not carried down.
        assert_eq!(widened(56, 16), 32);
    }

    #[test]
    fn the_height_gate_widens_while_fixes_are_rejected() {
        // A fix 100 m off the last one, with a 30 m limit and no velocity yet
        // (20 m/s assumed): rejected at first, accepted once 70 m of
        // 3-sigma drift have accumulated (70 / 60 m/s = 1.17 s): no lockout.
        let fix = HeightReference { t: 10.0, h_m: 1000.0, extra_allowance_m: 0.0 };
        let gate = |t| HeightGate::new(fix, t, None, 20.0, 30.0);
        assert!(matches!(gate(10.5).check(1100.0), Some(Rejection::Height { .. })));
        assert!(gate(11.0).check(1100.0).is_some());
        assert_eq!(gate(11.2).check(1100.0), None);
        // Before the first fix the initial guess is the reference, with three
        // of its sigmas: 300 m x 3 + 30 m.
        let guess = HeightReference { t: 0.0, h_m: 5000.0, extra_allowance_m: 900.0 };
        let first = HeightGate::new(guess, 0.0, None, 20.0, 30.0);
        assert_eq!(first.check(5929.0), None);
        assert!(first.check(5931.0).is_some() && first.check(4069.0).is_some());
    }

    #[test]
    fn the_height_gate_follows_a_climb() {
        // A rocket climbing 240 m/s, velocity known to 5 m/s: two seconds after
        // the last fix it is predicted 480 m higher; the old gate (450 m from
        // the last fix, whatever the time) would refuse it for good.
        let fix = HeightReference { t: 3.0, h_m: 2000.0, extra_allowance_m: 0.0 };
        let g = HeightGate::new(fix, 5.0, Some(240.0), 5.0, 30.0);
        assert!((g.predicted_h_m - 2480.0).abs() < 1e-9 && (g.allowed_m - 60.0).abs() < 1e-9);
        assert_eq!(g.check(2470.0), None);
        assert!(g.check(2000.0).is_some());
    }

    #[test]
    fn velocity_is_the_least_squares_slope_of_the_fixes() {
        let v = Vector3::new(8.0, 3.0, -6.0);
        let p0 = Vector3::new(-2.4e6, -4.6e6, 3.8e6);
        // Fixes every 0.5 s with +-40 m of alternating error: pairwise differences
        // would be off by 160 m/s.
        let fixes: std::collections::VecDeque<(f64, Vector3<f64>)> = (0..13)
            .map(|i| {
                let t = i as f64 * 0.5;
                let e = if i % 2 == 0 { 40.0 } else { -40.0 };
                (t, p0 + v * t + Vector3::new(e, -e, e))
            })
            .collect();
        let (got, sigma) = velocity_fit(&fixes).unwrap();
        assert!((got - v).norm() < 10.0, "{got:?}");
        // The reported error covers the actual one, and exceeds the floor here.
        assert!(sigma >= (got - v).norm() / 3.0 && sigma > VELOCITY_KNOWN_SIGMA_M_S, "{sigma}");
        // Exact positions: the exact velocity, the floor as its error.
        let exact: std::collections::VecDeque<_> = fixes.iter().map(|&(t, _)| (t, p0 + v * t)).collect();
        let (got, sigma) = velocity_fit(&exact).unwrap();
        assert!((got - v).norm() < 1e-6);
        assert_eq!(sigma, VELOCITY_KNOWN_SIGMA_M_S);
        // Too short a span, or too few fixes: no velocity.
        let short: std::collections::VecDeque<_> = exact.iter().take(4).copied().collect();
        assert!(velocity_fit(&short).is_none());
        let two: std::collections::VecDeque<_> = [exact[0], exact[12]].into_iter().collect();
        assert!(velocity_fit(&two).is_none());
    }

    #[test]
    fn a_frame_searches_tiles_until_its_budget_is_spent() {
        // Each tile's work; tiles 2 and 3 are off the map (no work).
        let work = [4.0, 7.0, 0.0, 0.0, 5.0, 30.0, 1.0];
        let frame = |cursor: usize, budget: f64| {
            let mut walk = TileWalk::new(cursor, work.len(), budget);
            let mut seen = Vec::new();
            while let Some(i) = walk.next_tile() {
                seen.push(i);
                walk.spend(work[i]);
            }
            (seen, walk.cursor())
        };
        // The tile that crosses the budget is finished; empty tiles are free.
        assert_eq!(frame(0, 10.0), (vec![0, 1], 2));
        assert_eq!(frame(2, 10.0), (vec![2, 3, 4, 5], 6));
        // At least one tile, however small the budget.
        assert_eq!(frame(5, 1e-9), (vec![5], 6));
        // Wrapping from the cursor, never a tile twice in a frame.
        assert_eq!(frame(6, 8.0), (vec![6, 0, 1], 9));
        assert_eq!(frame(3, 1e9), (vec![3, 4, 5, 6, 0, 1, 2], 10));
        // A cursor past the end wraps; no tiles, no search.
        assert_eq!(frame(9, 10.0).0, vec![2, 3, 4, 5]);
        assert_eq!(TileWalk::new(4, 0, 10.0).next_tile(), None);
        // With a head of 2: those first, then from the cursor (at least
        // one, whatever the head spent), never a head tile twice.
        let headed = |cursor: usize, budget: f64| {
            let mut walk = TileWalk::new(cursor, work.len(), budget).with_head(2);
            let mut seen = Vec::new();
            while let Some(i) = walk.next_tile() {
                seen.push(i);
                walk.spend(work[i]);
            }
            (seen, walk.cursor())
        };
        assert_eq!(headed(4, 10.0), (vec![0, 1, 4], 5));
        assert_eq!(headed(5, 1e9), (vec![0, 1, 5, 6, 2, 3, 4], 12));
        // A cursor not past the head yet: the walk as without it.
        assert_eq!(headed(1, 10.0), frame(1, 10.0));
    }

    #[test]
    fn headings_cover_the_doubt_about_the_vertical() {
        let deg = |v: Vec<f64>| v.iter().map(|h| (h.to_degrees() * 1e6).round() / 1e6).collect::<Vec<_>>();
        // Within what one search stands: the guess's heading alone.
        assert_eq!(deg(heading_hypotheses(1f64.to_radians())), vec![0.0]);
        assert_eq!(deg(heading_hypotheses(2f64.to_radians())), vec![0.0]);
        assert_eq!(deg(heading_hypotheses(0.0)), vec![0.0]);
        assert_eq!(deg(heading_hypotheses(f64::NAN)), vec![0.0]);
        assert_eq!(deg(heading_hypotheses(4f64.to_radians())), vec![0.0, 10.0, -10.0]);
        assert_eq!(
            deg(heading_hypotheses(14.1f64.to_radians())),
            vec![0.0, 10.0, -10.0, 20.0, -20.0, 30.0, -30.0, 40.0, -40.0]
        );
        // A heading not known at all: the whole turn, 180 once.
        let all = heading_hypotheses(100f64.to_radians());
        assert_eq!(all.len(), 36);
        assert_eq!(all.iter().filter(|h| (h.abs() - std::f64::consts::PI).abs() < 1e-9).count(), 1);
        // Every heading error within 2.5 sigmas is within one search of a
        // hypothesis (brute force, every 0.1 deg).
        for sigma_deg in [3.0, 7.5, 14.1, 20.0, 45.0, 100.0] {
            let hs = heading_hypotheses(f64::to_radians(sigma_deg));
            let reach = (2.5 * sigma_deg).min(180.0);
            let mut a = -reach;
            while a <= reach {
                let near = hs
                    .iter()
                    .map(|h| {
                        let d = (a - h.to_degrees()).rem_euclid(360.0);
                        d.min(360.0 - d)
                    })
                    .fold(f64::INFINITY, f64::min);
                assert!(
                    near <= HEADING_TOLERANCE_DEG + 1e-9,
                    "sigma {sigma_deg}: {a:.1} deg is {near:.2} from {hs:?}"
                );
                a += 0.1;
            }
        }
    }

    #[test]
    fn tiles_at_headings_go_nearest_first() {
        let ten = 10f64.to_radians();
        let offsets = [Vector2::zeros(), Vector2::new(1000.0, 0.0)];
        let tiles = with_headings(&offsets, &[0.0, ten, -ten], 2000.0, 2.0 * ten);
        let got: Vec<(f64, f64)> = tiles.iter().map(|t| (t.offset_m.x, t.heading_rad)).collect();
        assert_eq!(
            got,
            vec![(0.0, 0.0), (0.0, ten), (0.0, -ten), (1000.0, 0.0), (1000.0, ten), (1000.0, -ten)]
        );
        // One heading: the offsets in their own order, not re-sorted.
        let layout = [Vector2::new(1000.0, 0.0), Vector2::zeros()];
        let plain = with_headings(&layout, &[0.0], 2000.0, 0.0);
        assert_eq!(plain.iter().map(|t| t.offset_m).collect::<Vec<_>>(), layout.to_vec());
        assert!(plain.iter().all(|t| t.heading_rad == 0.0));
        assert!(with_headings(&[], &[0.0, ten], 2000.0, ten).is_empty());
    }

    #[test]
    fn a_guess_turns_about_the_local_vertical() {
        let frame = LocalFrame::at(Geodetic::new(37.0, -118.0, 0.0));
        let guess = nadir_pose(&frame, 30_000.0);
        let turned = turned_about_vertical(&guess, 30f64.to_radians());
        assert_eq!(turned.position, guess.position);
        // A nadir camera's boresight stays; its image x axis turns 30 deg
        // counter-clockwise seen from above (east toward north).
        assert!(turned.boresight_ecef().angle(&guess.boresight_ecef()) < 1e-9);
        let x_enu = |p: &CameraPose| frame.vector_to_enu(&(p.q_ecef_cam * Vector3::x()));
        let (a, b) = (x_enu(&guess), x_enu(&turned));
        assert!((a.angle(&b).to_degrees() - 30.0).abs() < 1e-6, "{}", a.angle(&b).to_degrees());
        assert!(a.cross(&b).z > 0.0);
        assert_eq!(turned_about_vertical(&guess, 0.0), guess);
    }

    #[test]
    fn an_acquisition_correlates_what_fits_its_budget() {
        assert_eq!(within_budget(&[4, 5, 6, 7], 15.0), 3);
        assert_eq!(within_budget(&[4, 5, 6, 7], 14.9), 2);
        assert_eq!(within_budget(&[4, 5, 6, 7], 1e9), 4);
        // The first template at least, however dear.
        assert_eq!(within_budget(&[40, 5], 10.0), 1);
        assert_eq!(within_budget(&[], 10.0), 0);
    }

    #[test]
    fn a_narrow_tile_bounds_the_change_of_foreshortening() {
        // Brute force in the plane of incidence: the ground point at the
        // origin, the camera `range` away at the incidence `i`, moved by the
        // reach across its line of sight; a ground segment's foreshortening
        // is the cosine of the angle it is seen at.
        let range = 40_000.0;
        for i_deg in [45.0_f64, 62.6, 75.0] {
            let i = i_deg.to_radians();
            let reach = foreshortening_reach_m(range, range * i.cos());
            let camera = Vector2::new(-range * i.sin(), range * i.cos());
            for sign in [-1.0, 1.0] {
                let moved = camera + sign * reach * Vector2::new(i.cos(), i.sin());
                let cos_moved = moved.y / moved.norm();
                let change = (cos_moved / i.cos() - 1.0).abs();
                assert!(
                    (change - ACQUISITION_MAX_FORESHORTENING).abs() < 0.25 * ACQUISITION_MAX_FORESHORTENING,
                    "incidence {i_deg} deg, reach {reach:.0} m: foreshortening changed by {change:.3}"
                );
            }
        }
        // The oblique balloon's view (62.6 deg at 40 km): about 4 km.
        let oblique = foreshortening_reach_m(range, range * 62.6f64.to_radians().cos());
        assert!((3_900.0..4_300.0).contains(&oblique), "{oblique}");
        // Looking straight down a position error warps nothing.
        assert!(foreshortening_reach_m(30_000.0, 30_000.0).is_infinite());
        assert!(foreshortening_reach_m(30_000.0, 29_990.0) > 5.0 * 30_000.0);
    }

    #[test]
    fn correlation_work_counts_the_positions_inside_the_image() {
        let image = GreyImage { width: 200, height: 150, data: vec![0.0; 200 * 150] };
        // Brute force: template pixels and the work of a position, times the
        // placements within the radius (around the image centre) that keep
        // it inside the image.
        let brute = |w: usize, h: usize, r: usize| {
            let (cx, cy) = ((200 - w) as i64 / 2, (150 - h) as i64 / 2);
            let r = r as i64;
            let inside = |c: i64, side: usize, len: usize| {
                (c - r..=c + r).filter(|&x| x >= 0 && x as usize + side <= len).count()
            };
            ((w * h) as u64 + NCC_POSITION_WORK) * (inside(cx, w, 200) * inside(cy, h, 150)) as u64
        };
        for (w, h, r) in [(21, 21, 5), (21, 21, 60), (21, 21, 500), (63, 40, 90), (200, 150, 3)] {
            assert_eq!(correlation_work(w, h, r, &image), brute(w, h, r), "{w}x{h} r {r}");
        }
        // A template larger than the image has no position.
        assert_eq!(correlation_work(201, 10, 4, &image), 0);
    }

    #[test]
    fn a_tiles_acquisition_and_a_narrow_one_are_held_once() {
        let tile = Some(Vector2::new(1734.0, 0.0));
        let narrow = Some(Rejection::Spread { cells: 11, spread_px: 27.5 });
        // A tile's acquisition that passed every test: held, unconfirmed.
        assert_eq!(
            held(None, tile, true, false),
            Some(Rejection::Unconfirmed { tile_east_m: 1734.0, tile_north_m: 0.0 })
        );
        // One refused for another reason is not held.
        let few = Some(Rejection::FewInliers { inliers: 5 });
        assert_eq!(held(few, tile, true, false), None);
        // An acquisition (tiled or not) refused only for too narrow a view:
        // held, its refusal reported; not a frame's local search, and not
        // the search around a held one.
        assert_eq!(held(narrow, None, true, false), narrow);
        assert_eq!(held(narrow, tile, true, false), narrow);
        assert_eq!(held(narrow, None, false, false), None);
        assert_eq!(held(narrow, None, true, true), None);
        // A fix searched around the guess is no candidate.
        assert_eq!(held(None, None, true, false), None);
    }

    #[test]
    fn an_acquisition_wider_than_its_reach_is_laid_out_in_tiles_nearest_first() {
        // One search around the guess covers it: no tiles.
        assert!(acquisition_tiles(2000.0, 1500.0, None).is_empty());
        assert!(acquisition_tiles(0.0, 1500.0, None).is_empty());
        // 5 km with a 2 km reach: every point of the disc is within half a
        // reach of a tile (brute force on a fine grid), the guess first,
        // nearest first.
        let (reach, need) = (2000.0, 5000.0);
        let tiles = acquisition_tiles(reach, need, None);
        assert_eq!(tiles[0], Vector2::zeros());
        assert!(tiles.windows(2).all(|w| w[0].norm() <= w[1].norm()));
        let step = ACQUISITION_TILE_SPACING * reach;
        assert!(tiles.iter().all(|t| t.norm() <= need + 0.5 * step));
        let mut worst: f64 = 0.0;
        for i in -50..=50 {
            for j in -50..=50 {
                let p = Vector2::new(i as f64, j as f64) * (need / 50.0);
                if p.norm() <= need {
                    let d = tiles.iter().map(|t| (t - p).norm()).fold(f64::INFINITY, f64::min);
                    worst = worst.max(d);
                }
            }
        }
        assert!(worst <= 0.5 * reach && worst > 0.4 * reach, "farthest point from a tile {worst} m");
        // However wide the doubt, at most ACQUISITION_MAX_TILES.
        for need in [1e5, 1e9, f64::INFINITY] {
            let t = acquisition_tiles(reach, need, None);
            assert_eq!(t.len(), ACQUISITION_MAX_TILES, "{need}");
            assert_eq!(t[0], Vector2::zeros());
        }
    }

    #[test]
    fn an_oblique_views_tiles_lie_closer_along_its_line_of_sight() {
        // A low view looking north-east: tiles 1.5 km apart along its line of
        // sight, 4.2 km across it (a 6 km reach).
        let along = Vector2::new(1.0, 1.0).normalize();
        let across = Vector2::new(-along.y, along.x);
        let (reach, need, step) = (6000.0, 10_000.0, 1500.0);
        let sight = SightLine { dir_en: along, step_m: step };
        let tiles = acquisition_tiles(reach, need, Some(sight));
        assert_eq!(tiles[0], Vector2::zeros());
        assert!(tiles.windows(2).all(|w| w[0].norm() <= w[1].norm()));
        // Every point of the disc within half a step along the line of sight
        // of a tile, and half the other step across it (brute force).
        let step_across = ACQUISITION_TILE_SPACING * reach;
        for i in -40..=40 {
            for j in -40..=40 {
                let p = Vector2::new(i as f64, j as f64) * (need / 40.0);
                if p.norm() <= need {
                    assert!(
                        tiles.iter().any(|t| {
                            let d = p - t;
                            d.dot(&along).abs() <= 0.5 * step + 1e-6
                                && d.dot(&across).abs() <= 0.5 * step_across + 1e-6
                        }),
                        "{p:?} is farther from every tile"
                    );
                }
            }
        }
        // One search reaches 6 km across but only 1.05 km along: a 4 km doubt
        // is tiled along the line of sight; within 1.05 km it is not.
        let near = acquisition_tiles(reach, 4000.0, Some(sight));
        assert!(near.len() > 1 && near.iter().any(|t| (t.dot(&along) - step).abs() < 1e-6));
        assert!(acquisition_tiles(reach, 1000.0, Some(sight)).is_empty());
        // A line of sight whose step is the grid's own changes nothing but
        // the grid's axes: as many tiles, at the same distances.
        let wide = SightLine { dir_en: along, step_m: 1e6 };
        let (a, b) = (acquisition_tiles(reach, need, Some(wide)), acquisition_tiles(reach, need, None));
        assert_eq!(a.len(), b.len());
        assert!(a.iter().zip(&b).all(|(x, y)| (x.norm() - y.norm()).abs() < 1e-6));
    }

    #[test]
    fn the_line_of_sight_of_an_oblique_view_and_none_straight_down() {
        let frame = LocalFrame::at(Geodetic::new(37.0, -118.0, 0.0));
        let up = frame.r_ecef_enu().column(2).into_owned();
        let at = frame.to_ecef(Enu::new(0.0, 0.0, 4000.0));
        let nadir = CameraPose::look_at(at, frame.to_ecef(Enu::new(0.0, 0.0, 0.0)), up);
        assert!(sight_line(&nadir, 4000.0).is_none());
        // 50 deg from the vertical, toward the east: range 4000 / cos 50.
        let ground_e = 4000.0 * 50f64.to_radians().tan();
        let oblique = CameraPose::look_at(at, frame.to_ecef(Enu::new(ground_e, 0.0, 0.0)), up);
        let range = 4000.0 / 50f64.to_radians().cos();
        let s = sight_line(&oblique, range).expect("an oblique view");
        assert!((s.dir_en - Vector2::new(1.0, 0.0)).norm() < 1e-6, "{:?}", s.dir_en);
        let want = ACQUISITION_ALONG_SIGHT_STEP * range / 50f64.to_radians().sin();
        assert!((s.step_m - want).abs() < 1e-6 * want, "{} m, want {want} m", s.step_m);
    }

    #[test]
    fn the_map_offset_is_sized_by_the_landmarks_ground_sample_distance() {
        // The realistic flights' 30 m landmarks keep the figures measured on
        // them; a finer database is given less; options win.
        let mut p = NavParams::default();
        let (m, deg) = map_sigmas_for_gsd(&p, 30.0);
        assert!((m - 40.0).abs() < 1e-9 && (deg - 0.1).abs() < 1e-12, "{m} {deg}");
        let (m, deg) = map_sigmas_for_gsd(&p, 1.0);
        assert!(m < 1.5 && deg < 0.004, "{m} {deg}");
        p.map_sigma_m = Some(20.0);
        p.map_att_sigma_deg = Some(0.0);
        assert_eq!(map_sigmas_for_gsd(&p, 30.0), (20.0, 0.0));
        // Without the filter a fix's covariance takes the offset's prior:
        // 0.1 deg about each axis, 40 m along each, for 30 m landmarks.
        let p = NavParams::default();
        let c = map_offset_covariance(&p, Some(30.0));
        let want = pose_variances(0.1, 40.0);
        assert!((c - want).abs().max() < 1e-9, "{c}");
        assert_eq!(map_offset_covariance(&p, None), Matrix6::zeros());
        let mut v = vec![32.0, 16.0, 16.0, 64.0];
        assert_eq!(median(&mut v), Some(24.0));
        assert_eq!(median(&mut [8.0, 64.0, 16.0]), Some(16.0));
        assert_eq!(median(&mut []), None);
    }
}
