//! The inertial filter: an error-state extended Kalman filter that carries
//! position, velocity and attitude with the gyro and the accelerometer
//! between images, and learns both sensors' biases from the landmark fixes.
//! Pure math, no I/O.
//!
//! **Mechanization** in ECEF (Groves, *Principles of GNSS, Inertial, and
//! Multisensor Integrated Navigation Systems*, 2nd ed., section 5.3): per IMU
//! interval `dt`, with the gyro's mean rate `w` and the specific force `f`
//! (each less its estimated bias),
//! `q_ecef_imu <- Rz(-we dt) q_ecef_imu exp(w dt)`,
//! `v <- v + (R f + g(r) - 2 we x v) dt`, `r <- r + (v_old + v) dt / 2`, with
//! `g` gravity ([`trn_geodesy::gravity`]: J2 gravitation plus the
//! centrifugal term). Without accelerometer samples the velocity is carried
//! as a random walk of [`InsErrors::free_accel_m_s2_sqrt_s`]. Through a gap
//! in the IMU log ([`InsErrors::imu_gap_s`]) the rate and the specific force
//! are interpolated between the samples either side, and the attitude is
//! doubted as the gap goes on ([`InsErrors::gap_rate_walk_rad_s_sqrt_s`]).
//! There, and before the log's first sample or after its last, the
//! unmeasured rate's error takes the gyro bias's place as a state, learnt
//! from the fixes.
//!
//! **Error state** (the order of [`InsFilter::covariance`]), truth = estimate
//! plus error: `[dtheta (rad, ECEF: q = exp(dtheta) q_est); dr (m); dv (m/s);
//! dbg (rad/s, gyro bias, IMU frame); dba (m/s^2, accelerometer bias, IMU
//! frame); dm (m, map offset); dtau (s, time offset); dm_theta (rad, the
//! map offset's attitude part); dfocal (relative, the camera's focal
//! length); dc (px, the camera's principal point, u and v)]`. Its dynamics (Groves eq. 14.48-14.50):
//! `dtheta' = -[we]x dtheta - R dbg`, `dr' = dv`,
//! `dv' = -[R f]x dtheta + Gamma dr - 2 [we]x dv - R dba`, the biases random
//! walks, and the map offset (both parts) a first-order Gauss-Markov process.
//!
//! **Focal length.** A pose solved with a focal length short by `e` sees the
//! terrain `e` of the range closer (a nadir view cannot tell the two
//! apart). Where the accelerometer measures the motion the images see
//! shortened (a rocket's climb: the range grows by kilometres per second),
//! the two part: the apparent pose is `[...] - S dfocal`, `S` the frame's
//! [`IntrinsicsSensitivity`], and the focal error is a state (a random walk)
//! whenever its prior is not zero.
//!
//! **Principal point.** A principal point off by `dc` pixels turns the pose
//! a frame's matches give, mostly as a tilt of the camera (and, for a
//! narrow view, the tilt as a shift along the ground): the apparent pose is
//! `[...] - S_c dc`, `S_c` the frame's sensitivity to it. The offset is
//! fixed in the camera, so where the camera turns about its boresight (a
//! rocket's roll, a balloon's spin) or the accelerometer pins the tilt, it
//! parts from an attitude or position error; it is a state (a random walk,
//! two pixels) whenever its prior is not zero.
//!
//! **Map offset.** The landmarks are not the world: a database whose heights
//! or orthoimage are off by tens of metres shifts every fix from the same
//! landmarks alike, and consecutive frames see the same landmarks. The
//! filter models that shift as a position offset `m` of what the images see
//! (`apparent = r + m`), correlated over [`InsErrors::map_tau_s`], so a
//! hundred fixes from the same landmarks do not count as a hundred
//! independent ones (`map_sigma_m = 0`: not modelled). Its attitude part
//! turns the pose the images see (`q_apparent = exp(m_theta) q_true`,
//! [`InsErrors::map_att_sigma_rad`]): a narrow view trades a tilt for a
//! shift, and the map's errors move both, so the fixes' tilt wander is not
//! taken for gyro drift. Optionally it has a *view term* besides
//! ([`InsFilter::set_map_view`], [`InsFilter::map_view_excess`]): what each
//! landmark's own error, the same in every image that sees it, gives the
//! pose of the view in hand beyond that isotropic prior. A wide view's is
//! within the prior; a narrow view's few landmarks move its pose along the
//! tilt-for-shift trade by hundreds of metres, and with the term the fixes
//! of such a view move the offset along it, not the pose.
//!
//! **Update** ([`InsFilter::condition_on_pose`]): the image measures the
//! apparent camera pose `[dtheta; dr + dm]`. A refinement of the matches with
//! the filter's predicted pose as its prior (`trn_vision::pnp::PosePrior`)
//! is the iterated Kalman update of that block; the rest of the state follows
//! by Gaussian conditioning, as in [`crate::attitude`]. [`InsFilter::innovation`]
//! tests an image-only pose against the prediction (chi-square, 6 degrees of
//! freedom) before the update. [`InsFilter::linear_update`] takes any
//! whitened linear measurement (with a nuisance), as the landmark tracks
//! between frames give ([`crate::track`]).

use nalgebra::{
    DMatrix, DVector, Matrix2, Matrix3, Matrix6, SMatrix, UnitQuaternion, Vector2, Vector3, Vector6,
};
use trn_camera::CameraPose;
use trn_flight::ImuSample;
use trn_geodesy::gravity::{gravitation_gradient, gravity_ecef};
use trn_geodesy::{Ecef, EARTH_RATE_RAD_S};
use trn_vision::pnp::rotation_vector;

use crate::propagate::{ends_gap, for_each_segment, strapdown_increment};

/// The most the map offset's view term ([`InsFilter::map_view_excess`])
/// adds along any direction, in sigmas of the offset's isotropic prior.
pub const MAP_VIEW_CAP_SIGMAS: f64 = 5.0;

/// Dimension of the error state.
pub const N: usize = 25;
/// Offsets of the error state's blocks.
pub const ATT: usize = 0;
pub const POS: usize = 3;
pub const VEL: usize = 6;
pub const GYRO_BIAS: usize = 9;
pub const ACCEL_BIAS: usize = 12;
pub const MAP: usize = 15;
pub const TIME: usize = 18;
pub const MAP_ATT: usize = 19;
pub const FOCAL: usize = 22;
/// The principal point's error (u, v pixels).
pub const PRINCIPAL: usize = 23;

pub type Covariance = SMatrix<f64, N, N>;

/// Sensor and map error model (1 sigma per axis).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InsErrors {
    /// Gyro angle random walk (rad/sqrt(s)).
    pub gyro_arw_rad_sqrt_s: f64,
    /// Gyro bias random walk (rad/s/sqrt(s)).
    pub gyro_bias_walk_rad_s_sqrt_s: f64,
    /// Accelerometer velocity random walk (m/s/sqrt(s)).
    pub accel_vrw_m_s_sqrt_s: f64,
    /// Accelerometer bias random walk (m/s^2/sqrt(s)).
    pub accel_bias_walk_m_s2_sqrt_s: f64,
    /// Velocity random walk (m/s/sqrt(s)) where no accelerometer sample
    /// covers the interval: the vehicle's own accelerations, unmeasured.
    pub free_accel_m_s2_sqrt_s: f64,
    /// Map offset: its 1-sigma size (m per axis; 0: not modelled) and
    /// correlation time (s).
    pub map_sigma_m: f64,
    pub map_tau_s: f64,
    /// The map offset's attitude part: the 1-sigma rotation (rad per axis;
    /// 0: not modelled) of the pose the images see, with the same
    /// correlation time. A narrow view trades a tilt for a shift; the
    /// database's errors move both.
    pub map_att_sigma_rad: f64,
    /// Random walk of the camera's focal length (relative, per sqrt(s)).
    pub focal_walk_rel_sqrt_s: f64,
    /// Random walk of the camera's principal point (px per sqrt(s)).
    pub principal_walk_px_sqrt_s: f64,
    /// A gyro rate that differs from the sample before by more than this
    /// (rad/s; 0: never) starts a *jump*: until the rate comes back within
    /// it of the rate before (or for [`GYRO_JUMP_MAX_S`]), the angle it
    /// turns beyond that rate is doubted: added to the attitude's sigma
    /// about the jump's axis (see [`InsFilter::propagate`]).
    pub gyro_max_jump_rad_s: f64,
    /// A specific force that differs from the sample before by more than
    /// this (m/s^2; 0: never) starts a jump of the accelerometer: until the
    /// force comes back within it of the force before (or for
    /// [`ACCEL_JUMP_MAX_S`]), the velocity it adds beyond that force is
    /// doubted: added to the velocity's sigma along the jump's axis.
    pub accel_max_jump_m_s2: f64,
    /// An interval between two IMU samples longer than this (s; 0: none)
    /// is a *gap*: samples were lost. Through it the rate and the specific
    /// force are interpolated between the samples on either side, the
    /// velocity walks as without an accelerometer
    /// ([`Self::free_accel_m_s2_sqrt_s`]), and the attitude is doubted by
    /// [`Self::gap_rate_walk_rad_s_sqrt_s`]. Time before the log's first
    /// sample or after its last is crossed likewise, its attitude held
    /// (`0`: neither; the attitude held, undoubted).
    pub imu_gap_s: f64,
    /// The unmeasured rate's departure from that interpolation through a
    /// gap, as a random walk (rad/s/sqrt(s)): `tau` seconds into the gap the
    /// attitude's variance per axis has grown by `sigma^2 tau^3 / 3`, while
    /// its sigma is under [`IMU_GAP_MAX_ANGLE_DEG`]; the rate's error is a
    /// state the fixes learn, walking so up to [`HELD_RATE_MAX_DEG_S`].
    /// Likewise before the log's first sample (at no rate) and after its
    /// last (at the gyro's mean over [`HELD_RATE_WINDOW_S`]).
    pub gap_rate_walk_rad_s_sqrt_s: f64,
}

/// A gap in the IMU log grows the attitude's sigma up to this (deg, per
/// axis): beyond, the frames that then do not fix widen the search (the
/// navigator's doubt after a run of misses), as after a gyro jump. A fix
/// in the gap shrinks it, and the gap grows it again (the rate is still
/// unknown).
pub const IMU_GAP_MAX_ANGLE_DEG: f64 = 10.0;

/// Sub-step of the propagation through a gap (s).
const GAP_STEP_S: f64 = 0.01;

/// Where no sample measures the body's rate, its error is a filter state
/// (see [`InsFilter::propagate`]) that walks by
/// [`InsErrors::gap_rate_walk_rad_s_sqrt_s`] while frames do not fix, up to
/// this sigma (deg/s, per axis): beyond the 20 deg/s spins the method was
/// flown through.
pub const HELD_RATE_MAX_DEG_S: f64 = 30.0;

/// The rate carried on after the IMU log's end is the gyro's mean over this
/// much of the log's end (s).
pub const HELD_RATE_WINDOW_S: f64 = 1.0;

/// How long a gyro jump is doubted at most (s): a rate that stays away from
/// the one before is a turn the platform made.
pub const GYRO_JUMP_MAX_S: f64 = 0.5;

/// The most a gyro jump is doubted (deg, 1 sigma): beyond, a frame that
/// then does not fix is searched again with the jump's turn undone
/// ([`JumpTurn`]), and the frames that still do not fix widen the search
/// (the navigator's doubt after a run of misses). Measured on the 30 km nadir balloon turned 30 deg in 20 ms:
/// doubted in full, 92 of its 121 frames fixed; within 10 deg, 115 (20 deg:
/// 114 and 116).
pub const GYRO_JUMP_MAX_ANGLE_DEG: f64 = 10.0;

/// How long an accelerometer jump is doubted at most (s): a force that
/// stays away from the one before is a thrust the platform felt (an
/// engine's start or cut-off), and the fixes after it find the velocity.
/// Longer than the gyro's: a saturated accelerometer (a shock) reads wrong
/// for as long as the shock lasts.
pub const ACCEL_JUMP_MAX_S: f64 = 2.0;

/// The most an accelerometer jump is doubted (m/s, 1 sigma along its axis).
pub const ACCEL_JUMP_MAX_M_S: f64 = 100.0;

/// A sensor's jumps from one sample to the next (the gyro's rate, the
/// accelerometer's specific force; IMU frame): a value that differs from
/// the sample before by more than a limit starts a jump, which lasts until
/// the values come back within the limit of the one before it, or for a
/// longest time; meanwhile the integral of the values beyond the one before
/// (an angle, a velocity) is what the filter doubts.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub(crate) struct JumpWatch {
    /// The last sample's value.
    last: Option<Vector3<f64>>,
    /// The jump being doubted: the value before it, the integral beyond it
    /// so far (its norm, capped), and its duration so far (s).
    jump: Option<(Vector3<f64>, f64, f64)>,
    /// Jumps seen so far.
    pub(crate) count: usize,
}

impl JumpWatch {
    /// The sample `x` over `dt` of its interval (each sample is visited
    /// once per segment of its interval; the jump is judged once per sample,
    /// when the value changes). Returns the value beyond the one before the
    /// jump (its axis) and the variance to add along it, while a jump lasts.
    pub(crate) fn watch(
        &mut self,
        x: &Vector3<f64>,
        dt: f64,
        limit: f64,
        max_s: f64,
        cap: f64,
    ) -> Option<(Vector3<f64>, f64)> {
        if self.last != Some(*x) {
            if let (None, Some(before)) = (self.jump, self.last) {
                if (x - before).norm() > limit {
                    self.jump = Some((before, 0.0, 0.0));
                    self.count += 1;
                }
            }
            if let Some((before, _, age)) = self.jump {
                if (x - before).norm() <= limit || age >= max_s {
                    self.jump = None;
                }
            }
            self.last = Some(*x);
        }
        let (before, size, age) = self.jump.as_mut()?;
        let beyond = x - *before;
        let grown = (*size + beyond.norm() * dt).min(cap);
        let added = grown * grown - *size * *size;
        *size = grown;
        *age += dt;
        Some((beyond, added))
    }

    /// Forgets the samples before (after a gap in the log).
    pub(crate) fn restart(&mut self, x: Option<Vector3<f64>>) {
        self.jump = None;
        self.last = x;
    }
}

/// The gyro's jumps since the last accepted fix, as turned: the angle
/// beyond the rate before each, for as long as each lasted, uncapped
/// (the doubt is capped at [`GYRO_JUMP_MAX_ANGLE_DEG`]). Were they glitches,
/// the attitude is `exp(-turn_ecef_rad)` times the one carried (a turn
/// about ECEF axes stays one as the body turns on): the navigator's other
/// hypothesis when a frame does not fix after a jump (see
/// `Navigator::jump_undone_prediction`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JumpTurn {
    /// The first jump's time (s): the accelerometer's force has been
    /// turned with the attitude since.
    pub since_t: f64,
    /// The turns added up (rad, ECEF rotation vector).
    pub turn_ecef_rad: Vector3<f64>,
    /// The specific force the inertial filter integrated since the first
    /// jump, as its attitude turned it (ECEF): its integral (m/s), what it
    /// added to the velocity...
    pub force_ecef_m_s: Vector3<f64>,
    /// ...and that integral's own (m), what it added to the position. Zero
    /// where no filter integrates the accelerometer.
    pub force_twice_ecef_m: Vector3<f64>,
    /// The integral of the force's norm (m/s) and its own (m): an
    /// attitude error of `a` rad since the first jump moved the position
    /// by at most `2 sin(a / 2)` times the latter.
    pub force_norm_m_s: f64,
    pub force_norm_twice_m: f64,
    /// The filter's position (m) and velocity (m/s) sigmas at the first
    /// jump (largest axis); infinite where no filter carried them.
    pub position_sigma_m: f64,
    pub velocity_sigma_m_s: f64,
}

impl JumpTurn {
    /// `turn` (rad, ECEF) at `t` added to `record`.
    pub(crate) fn add(record: &mut Option<JumpTurn>, t: f64, turn: Vector3<f64>) {
        match record {
            Some(r) => r.turn_ecef_rad += turn,
            None => {
                *record = Some(JumpTurn {
                    since_t: t,
                    turn_ecef_rad: turn,
                    force_ecef_m_s: Vector3::zeros(),
                    force_twice_ecef_m: Vector3::zeros(),
                    force_norm_m_s: 0.0,
                    force_norm_twice_m: 0.0,
                    position_sigma_m: f64::INFINITY,
                    velocity_sigma_m_s: f64::INFINITY,
                })
            }
        }
    }

    /// How far (1 sigma, m) the position with the jumps undone
    /// ([`Self::undo_shift`]) may be off at `t`: the filter's position and
    /// velocity sigmas at the first jump carried on, and the force since
    /// turned by an attitude error of `attitude_sigma_rad` (what the
    /// filter's own updates since moved it by, besides the jumps).
    /// Infinite where no filter carried them.
    pub fn undone_position_sigma_m(&self, t: f64, attitude_sigma_rad: f64) -> f64 {
        let dt = (t - self.since_t).max(0.0);
        self.position_sigma_m
            + self.velocity_sigma_m_s * dt
            + 2.0 * (0.5 * attitude_sigma_rad).sin().abs() * self.force_norm_twice_m
    }

    /// `f_ecef` (m/s^2) integrated for `dt` s (the mechanization's
    /// trapezoid: the position moves by the velocity's mean over the step).
    fn integrate_force(&mut self, f_ecef: &Vector3<f64>, dt: f64) {
        self.force_twice_ecef_m += self.force_ecef_m_s * dt + f_ecef * (0.5 * dt * dt);
        self.force_ecef_m_s += f_ecef * dt;
        self.force_norm_twice_m += self.force_norm_m_s * dt + f_ecef.norm() * (0.5 * dt * dt);
        self.force_norm_m_s += f_ecef.norm() * dt;
    }

    /// What undoing the turns takes back from the velocity (m/s) and the
    /// position (m), ECEF: the force was integrated turned by them, `R f`
    /// where `f` was meant, so each integral `I` of it gains `(R^T - 1) I`
    /// when turned back (first order in the attitude's other changes since,
    /// which the fixes made; exact for one jump: of several, their sum is
    /// taken back from the first on).
    pub fn undo_shift(&self) -> (Vector3<f64>, Vector3<f64>) {
        let back = UnitQuaternion::from_scaled_axis(-self.turn_ecef_rad);
        (
            back * self.force_ecef_m_s - self.force_ecef_m_s,
            back * self.force_twice_ecef_m - self.force_twice_ecef_m,
        )
    }
}

/// Initial uncertainty (1 sigma per axis).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InsInit {
    pub attitude_rad: f64,
    pub position_m: f64,
    pub velocity_m_s: f64,
    pub gyro_bias_rad_s: f64,
    pub accel_bias_m_s2: f64,
    /// Camera-IMU time offset (s; 0: not estimated).
    pub time_offset_s: f64,
    /// The camera's focal length (relative; 0: not estimated).
    pub focal_rel: f64,
    /// The camera's principal point (px per axis; 0: not estimated).
    pub principal_px: f64,
}

/// The estimated state (the nominal state of the error-state filter).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct InsState {
    pub t: f64,
    pub position: Ecef,
    pub velocity_ecef_m_s: Vector3<f64>,
    pub q_ecef_imu: UnitQuaternion<f64>,
    pub gyro_bias_imu_rad_s: Vector3<f64>,
    pub accel_bias_imu_m_s2: Vector3<f64>,
    /// Apparent minus true position of what the images see (m, ECEF).
    pub map_offset_ecef_m: Vector3<f64>,
    /// Apparent attitude of what the images see relative to the true one
    /// (rad, ECEF rotation vector: `q_apparent = exp(this) q_true`).
    pub map_offset_att_rad: Vector3<f64>,
    /// An image stamped `t` (IMU clock) was exposed at `t + time_offset_s`.
    pub time_offset_s: f64,
    /// The body's rotation rate relative to ECEF (rad/s, ECEF) at `t`, from
    /// the last gyro sample less the bias: with the velocity, how a time
    /// offset moves the pose the image sees (not a filter state).
    pub rate_ecef_rad_s: Vector3<f64>,
}

/// State, covariance and error model.
#[derive(Clone, Debug, PartialEq)]
pub struct InsFilter {
    pub state: InsState,
    pub covariance: Covariance,
    pub errors: InsErrors,
    /// The estimated error of the focal length of the camera the images are
    /// solved with (relative: the true focal length is that camera's times
    /// `1 + this`); the owner of the camera takes it with
    /// [`Self::take_focal_error`], which restarts it at zero.
    pub focal_error_rel: f64,
    /// The estimated error of the principal point of that camera (px, u
    /// and v: the true one is that camera's plus this); taken with
    /// [`Self::take_principal_error`].
    pub principal_error_px: Vector2<f64>,
    /// Whether the pose updates ([`Self::condition_on_pose_with`]) move
    /// the principal point (true unless set otherwise). When false they
    /// count its uncertainty without learning it (a Schmidt update: its
    /// gain rows zeroed), so what the database's tilt puts into a fix is
    /// not taken for the camera's; only the landmark tracks' rows
    /// ([`crate::track`]), which the database's errors do not reach, move it.
    pub principal_from_fixes: bool,
    /// The gyro's jumps (rad/s, IMU frame, bias included).
    gyro_watch: JumpWatch,
    /// The accelerometer's jumps (m/s^2, IMU frame, bias included).
    accel_watch: JumpWatch,
    /// The gyro's jumps since the navigator last cleared them (at each
    /// accepted fix): what undoing them as glitches takes back.
    pub jump_turn: Option<JumpTurn>,
    /// Time crossed in gaps of the IMU log so far (s): between two states
    /// whose values differ, the gyro did not measure all of the turn.
    pub gap_crossed_s: f64,
    /// Once the frames outlive the IMU log (and gaps are recognised): the
    /// gyro bias and its covariance at the log's end. From then on the
    /// bias state carries the body's rate instead (its negative, as a
    /// measured rate of zero less the bias), learnt from the fixes (see
    /// [`Self::propagate`]).
    bias_at_log_end: Option<(Vector3<f64>, Matrix3<f64>)>,
    /// In a gap of the log or before its first sample: the gyro bias and
    /// its covariance before (the bias state stands for the unmeasured
    /// rate's error there).
    bias_in_gap: Option<(Vector3<f64>, Matrix3<f64>)>,
    /// The map offset's view term ([`Self::set_map_view`]): the stationary
    /// covariance (`[dm_theta; dm]`, as an apparent pose's) that the
    /// landmarks' own errors give the pose of the view last seen, on top of
    /// the isotropic prior.
    map_view: Matrix6<f64>,
    /// The stationary covariance that term gave the offset as it is now:
    /// grown at once with a view that narrows, decaying with the offset's
    /// correlation time toward the current term when the view widens
    /// (what [`Self::map_offset_distance`] measures the estimate against).
    map_view_prior: Matrix6<f64>,
}

/// The gyro's mean rate (rad/s, IMU frame) over the last `window_s` of the
/// log (each sample the mean over the interval ending at its time): what
/// the body turned there, less a vibration's swings, which the last sample
/// alone carries on (a rocket's 5 deg/s wobble, held for a frame's 0.5 s,
/// put its first frames after the log 2 deg off).
fn mean_rate(imu: &[ImuSample], window_s: f64) -> Vector3<f64> {
    let Some(last) = imu.last() else { return Vector3::zeros() };
    let (mut turned, mut span) = (Vector3::zeros(), 0.0);
    for pair in imu.windows(2).rev() {
        let (a, b) = (pair[0].t.max(last.t - window_s), pair[1].t);
        if !(b > a) {
            break;
        }
        turned += pair[1].w_imu_rad_s * (b - a);
        span += b - a;
    }
    if span > 0.0 {
        turned / span
    } else {
        last.w_imu_rad_s
    }
}

/// The factor a doubt scales a `sigma` by: `factor`, or less where that
/// would take it beyond `max` (never under 1: a doubt only grows, and one
/// already beyond `max` stays).
pub(crate) fn doubt_factor(sigma: f64, max: f64, factor: f64) -> f64 {
    let factor = factor.max(1.0);
    if sigma > 0.0 {
        (max / sigma).clamp(1.0, factor)
    } else {
        factor
    }
}

/// [`IMU_GAP_MAX_ANGLE_DEG`] as a variance (rad^2).
fn gap_cap_variance() -> f64 {
    IMU_GAP_MAX_ANGLE_DEG.to_radians().powi(2)
}

fn block(p: &mut Covariance, at: usize, sigma: f64) {
    for i in at..at + 3 {
        p[(i, i)] = sigma * sigma;
    }
}

/// The covariance is propagated in steps of about this (s): the IMU's own
/// rate (200 Hz and more) would cost an 18x18 product per sample.
pub const COVARIANCE_STEP_S: f64 = 0.05;

/// Error-state dynamics accumulated over IMU samples until the next
/// covariance step.
struct Accumulated {
    /// Integral of the time-varying part of F.
    f_dt: Covariance,
    /// Process noise variances.
    q: SMatrix<f64, N, 1>,
    dt: f64,
    map_decay: f64,
}

impl Default for Accumulated {
    fn default() -> Self {
        Self { f_dt: Covariance::zeros(), q: SMatrix::zeros(), dt: 0.0, map_decay: 1.0 }
    }
}

/// Where the body's rate comes from over one step.
#[derive(Clone, Copy)]
enum Rate {
    /// The gyro's rate (rad/s, IMU frame), bias not yet removed.
    Measured(Vector3<f64>),
    /// No gyro sample (a gap, the log's end): a rate carried on or
    /// interpolated, corrected by the bias state, which stands for the
    /// rate's error there ([`InsFilter::rate_unmeasured`]); `coupled:
    /// false` once the attitude's doubt is at [`IMU_GAP_MAX_ANGLE_DEG`],
    /// where the rate's doubt no longer adds to it.
    Unmeasured { w: Vector3<f64>, coupled: bool },
    /// No rate: the attitude held fixed in inertial space.
    Held,
}

/// Where the velocity comes from over one step.
enum Force {
    /// Specific force (m/s^2, IMU frame), bias not yet removed.
    Measured(Vector3<f64>),
    /// No accelerometer: constant velocity.
    Free,
}

impl InsFilter {
    pub fn new(state: InsState, init: &InsInit, errors: InsErrors) -> Self {
        let mut p = Covariance::zeros();
        block(&mut p, ATT, init.attitude_rad);
        block(&mut p, POS, init.position_m);
        block(&mut p, VEL, init.velocity_m_s);
        block(&mut p, GYRO_BIAS, init.gyro_bias_rad_s);
        block(&mut p, ACCEL_BIAS, init.accel_bias_m_s2);
        block(&mut p, MAP, errors.map_sigma_m);
        block(&mut p, MAP_ATT, errors.map_att_sigma_rad);
        p[(TIME, TIME)] = init.time_offset_s * init.time_offset_s;
        p[(FOCAL, FOCAL)] = init.focal_rel * init.focal_rel;
        for i in PRINCIPAL..PRINCIPAL + 2 {
            p[(i, i)] = init.principal_px * init.principal_px;
        }
        Self {
            state,
            covariance: p,
            errors,
            focal_error_rel: 0.0,
            principal_error_px: Vector2::zeros(),
            principal_from_fixes: true,
            gyro_watch: JumpWatch::default(),
            accel_watch: JumpWatch::default(),
            jump_turn: None,
            gap_crossed_s: 0.0,
            bias_at_log_end: None,
            bias_in_gap: None,
            map_view: Matrix6::zeros(),
            map_view_prior: Matrix6::zeros(),
        }
    }

    /// Carries the state and covariance to `t1` through the IMU samples
    /// (each gyro sample the mean rate over the interval ending at its time,
    /// each accelerometer sample the specific force at its time, linearly
    /// interpolated in between). Time no sample covers (before the log's
    /// first sample, after its last) keeps the velocity as it was, walking
    /// as without an accelerometer, and the attitude fixed in inertial
    /// space; where gaps are recognised, it turns before the log at no
    /// rate and after it at the rate measured last, corrected by a state
    /// the fixes learn (see `outside_log`). An interval
    /// longer than [`InsErrors::imu_gap_s`] is a gap: crossed on
    /// interpolated rates, the attitude doubted. `t1` before the state's
    /// time does nothing.
    pub fn propagate(&mut self, t1: f64, imu: &[ImuSample]) {
        let t0 = self.state.t;
        if !(t1 > t0) {
            return;
        }
        let mut acc = Accumulated::default();
        for_each_segment(imu, t0, t1, |a, b, sample| {
            let Some(k) = sample else {
                if self.errors.imu_gap_s > 0.0 {
                    self.outside_log(a, b, imu, &mut acc);
                } else {
                    self.step(b - a, Rate::Held, Force::Free, &mut acc);
                }
                return;
            };
            let (begin, end) = (if k > 0 { imu[k - 1].t } else { a }, imu[k].t);
            if ends_gap(imu, k, self.errors.imu_gap_s) {
                self.cross_gap(a, b, &imu[k - 1], &imu[k], &mut acc);
                return;
            }
            self.end_gap(&mut acc);
            self.watch_gyro(&imu[k].w_imu_rad_s, a, b - a, &mut acc);
            if let Some(f) = &imu[k].f_imu_m_s2 {
                self.watch_accel(f, b - a, &mut acc);
            }
            let force = match (k.checked_sub(1).and_then(|j| imu[j].f_imu_m_s2), imu[k].f_imu_m_s2) {
                (Some(f0), Some(f1)) if end > begin => {
                    let s = ((0.5 * (a + b) - begin) / (end - begin)).clamp(0.0, 1.0);
                    Force::Measured(f0 + (f1 - f0) * s)
                }
                (_, Some(f1)) => Force::Measured(f1),
                _ => Force::Free,
            };
            self.step(b - a, Rate::Measured(imu[k].w_imu_rad_s), force, &mut acc);
        });
        self.flush(&mut acc);
        self.state.t = t1;
    }

    /// The part `[a, b]` of a gap between the samples `before` and `after`
    /// ([`InsErrors::imu_gap_s`]): in steps of [`GAP_STEP_S`], the rate and
    /// the specific force interpolated linearly between the two samples'
    /// (the sample after a gap is the rate over its own interval, not the
    /// mean over the gap: taken so, a 3 s gap left a balloon's pendulum
    /// 2.2 deg off), the velocity noise of a flight without accelerometer,
    /// and the interpolated rate's error a state that walks
    /// ([`Self::rate_unmeasured`]; the gyro's bias comes back at the gap's
    /// end, [`Self::end_gap`]). The gyro's jump watch restarts at the
    /// sample after.
    fn cross_gap(&mut self, a: f64, b: f64, before: &ImuSample, after: &ImuSample, acc: &mut Accumulated) {
        let (begin, end) = (before.t, after.t);
        self.gyro_watch.restart(Some(after.w_imu_rad_s));
        self.accel_watch.restart(after.f_imu_m_s2);
        self.gap_crossed_s += b - a;
        self.keep_bias_aside(acc);
        let free = self.errors.free_accel_m_s2_sqrt_s.powi(2);
        let steps = ((b - a) / GAP_STEP_S).ceil().max(1.0);
        let dt = (b - a) / steps;
        for i in 0..steps as usize {
            let (s0, s1) = (a + dt * i as f64, a + dt * (i + 1) as f64);
            let s = ((0.5 * (s0 + s1) - begin) / (end - begin)).clamp(0.0, 1.0);
            let w = before.w_imu_rad_s + (after.w_imu_rad_s - before.w_imu_rad_s) * s;
            let force = match (before.f_imu_m_s2, after.f_imu_m_s2) {
                (Some(f0), Some(f1)) => Force::Measured(f0 + (f1 - f0) * s),
                _ => Force::Free,
            };
            for j in 0..3 {
                acc.q[VEL + j] += free * dt;
            }
            self.rate_unmeasured(dt, w, force, acc);
        }
        if b >= end {
            self.end_gap(acc);
        }
    }

    /// The part `[a, b]` of time no sample of the log covers: before its
    /// first sample (from the filter's start) or after its last. Before
    /// the log no rate is known: the attitude turns at none, its error a
    /// state the fixes learn ([`Self::rate_unmeasured`]; the gyro's bias
    /// comes back at the log's first sample, [`Self::end_gap`]). After it,
    /// the gyro's mean over the log's last [`HELD_RATE_WINDOW_S`] is
    /// carried on likewise (the report keeps the gyro's bias as it was at
    /// the log's end). The velocity walks as without an accelerometer;
    /// the jump watches start again with the log.
    fn outside_log(&mut self, a: f64, b: f64, imu: &[ImuSample], acc: &mut Accumulated) {
        let after_log = imu.last().filter(|s| a >= s.t);
        self.gyro_watch.restart(after_log.map(|s| s.w_imu_rad_s));
        self.accel_watch.restart(after_log.and_then(|s| s.f_imu_m_s2));
        self.gap_crossed_s += b - a;
        let w = match after_log {
            Some(_) => {
                if self.bias_at_log_end.is_none() {
                    self.flush(acc);
                    self.bias_at_log_end = Some(self.gyro_bias_with_covariance());
                }
                mean_rate(imu, HELD_RATE_WINDOW_S)
            }
            // Before the log no rate is known: none, its error learnt.
            None => {
                self.keep_bias_aside(acc);
                Vector3::zeros()
            }
        };
        let steps = ((b - a) / GAP_STEP_S).ceil().max(1.0);
        let dt = (b - a) / steps;
        for _ in 0..steps as usize {
            self.rate_unmeasured(dt, w, Force::Free, acc);
        }
    }

    /// One step of `dt` at a rate no sample measured, `w` (interpolated
    /// through a gap, carried on after the log's end, none before it). The
    /// bias state stands for that rate's error meanwhile (the gyro's bias
    /// kept aside: [`Self::keep_bias_aside`], [`Self::end_gap`]),
    /// walking by [`InsErrors::gap_rate_walk_rad_s_sqrt_s`] up to
    /// [`HELD_RATE_MAX_DEG_S`]: `tau` into the stretch the attitude's
    /// variance has grown by `sigma^2 tau^3 / 3` (up to
    /// [`IMU_GAP_MAX_ANGLE_DEG`]), and the fixes there learn the rate, so
    /// the doubt grows from the last fix rather than from the stretch's
    /// start (a frame's search had widened to the cap 3 s into it).
    fn rate_unmeasured(&mut self, dt: f64, w: Vector3<f64>, force: Force, acc: &mut Accumulated) {
        let coupled = self.attitude_variance(acc) < gap_cap_variance();
        let walk = self.errors.gap_rate_walk_rad_s_sqrt_s;
        let cap = HELD_RATE_MAX_DEG_S.to_radians().powi(2);
        for j in GYRO_BIAS..GYRO_BIAS + 3 {
            let now = self.covariance[(j, j)] + acc.q[j];
            acc.q[j] += (walk * walk * dt).min((cap - now).max(0.0));
        }
        self.step(dt, Rate::Unmeasured { w, coupled }, force, acc);
        // The rate's walk reaches the attitude at the next flush: each
        // step's, so the doubt is not a covariance step late.
        self.flush(acc);
    }

    /// At a stretch's start (a gap's, the filter's before the log): the
    /// gyro's bias and its covariance are kept aside while the bias state
    /// stands for the unmeasured rate's error ([`Self::rate_unmeasured`]).
    fn keep_bias_aside(&mut self, acc: &mut Accumulated) {
        if self.bias_in_gap.is_none() {
            self.flush(acc);
            self.bias_in_gap = Some(self.gyro_bias_with_covariance());
        }
    }

    /// At a gap's end (or the log's first sample): the gyro's bias and its
    /// covariance come back from before (its state stood for the unmeasured
    /// rate's error), uncorrelated with the rest.
    fn end_gap(&mut self, acc: &mut Accumulated) {
        let Some((bias, cov)) = self.bias_in_gap.take() else { return };
        self.flush(acc);
        self.state.gyro_bias_imu_rad_s = bias;
        uncorrelate(&mut self.covariance, GYRO_BIAS..GYRO_BIAS + 3);
        self.covariance.fixed_view_mut::<3, 3>(GYRO_BIAS, GYRO_BIAS).copy_from(&cov);
    }

    /// The largest variance of the attitude's axes, with the process noise
    /// accumulated since the last flush (rad^2).
    fn attitude_variance(&self, acc: &Accumulated) -> f64 {
        (0..3).map(|j| self.covariance[(ATT + j, ATT + j)] + acc.q[ATT + j]).fold(0.0, f64::max)
    }

    /// The gyro's plausibility ([`InsErrors::gyro_max_jump_rad_s`]): a rate
    /// that jumps from the sample before may be a glitch (a bit flipped, a
    /// saturated read) or a jerk no platform of ours makes; the filter
    /// integrates it as measured but doubts the angle it turns beyond the
    /// rate before, so the next search widens to where the landmarks are if
    /// it was wrong (an unreported 2-4 deg turn otherwise leaves the search
    /// sized for a small fraction of a degree, and chance matches around the
    /// wrong prediction can then agree).
    /// The turn beyond the rate before is also added up, uncapped, in
    /// [`Self::jump_turn`] (from `t`, the segment's start).
    fn watch_gyro(&mut self, w: &Vector3<f64>, t: f64, dt: f64, acc: &mut Accumulated) {
        let limit = self.errors.gyro_max_jump_rad_s;
        if !(limit > 0.0) {
            return;
        }
        let cap = GYRO_JUMP_MAX_ANGLE_DEG.to_radians();
        if let Some((beyond, added)) = self.gyro_watch.watch(w, dt, limit, GYRO_JUMP_MAX_S, cap) {
            JumpTurn::add(&mut self.jump_turn, t, self.state.q_ecef_imu * beyond * dt);
            if let Some(j) = self.jump_turn.as_mut().filter(|j| j.position_sigma_m.is_infinite()) {
                let largest =
                    |at: usize| (at..at + 3).map(|i| self.covariance[(i, i)]).fold(0.0, f64::max).sqrt();
                (j.position_sigma_m, j.velocity_sigma_m_s) = (largest(POS), largest(VEL));
            }
            self.doubt_along(ATT, &beyond, added, acc);
        }
    }

    /// The accelerometer's plausibility
    /// ([`InsErrors::accel_max_jump_m_s2`]): a specific force that jumps
    /// from the sample before (a shock that saturates it, a glitch) is
    /// integrated as measured, and the velocity it adds beyond the force
    /// before is doubted, so the fixes after it can correct the velocity (a
    /// 1 s glitch of 100 m/s^2 otherwise left the velocity 100 m/s off with
    /// a sigma of centimetres per second: the 30 km nadir balloon's fixes
    /// then drifted 360 m from the truth, 6.5 sigmas, the images' shift
    /// taken for the map's tilt).
    fn watch_accel(&mut self, f: &Vector3<f64>, dt: f64, acc: &mut Accumulated) {
        let limit = self.errors.accel_max_jump_m_s2;
        if !(limit > 0.0) {
            return;
        }
        if let Some((beyond, added)) =
            self.accel_watch.watch(f, dt, limit, ACCEL_JUMP_MAX_S, ACCEL_JUMP_MAX_M_S)
        {
            self.doubt_along(VEL, &beyond, added, acc);
        }
    }

    /// Adds `added` to the variance of the 3-vector state at `at` along
    /// the IMU-frame direction `beyond` (in ECEF, as those errors are).
    fn doubt_along(&mut self, at: usize, beyond: &Vector3<f64>, added: f64, acc: &mut Accumulated) {
        if let Some(axis) = (self.state.q_ecef_imu * beyond).try_normalize(1e-12) {
            self.flush(acc);
            let mut b = self.covariance.fixed_view_mut::<3, 3>(at, at);
            b += axis * axis.transpose() * added;
        }
    }

    /// Gyro jumps doubted so far ([`InsErrors::gyro_max_jump_rad_s`]).
    pub fn gyro_jumps(&self) -> usize {
        self.gyro_watch.count
    }

    /// Accelerometer jumps doubted so far
    /// ([`InsErrors::accel_max_jump_m_s2`]).
    pub fn accel_jumps(&self) -> usize {
        self.accel_watch.count
    }

    /// One mechanization step of `dt` seconds at the body's `rate` (see
    /// [`Rate`]) and the specific `force`. The error state's
    /// dynamics are accumulated in `acc` and applied to the covariance every
    /// [`COVARIANCE_STEP_S`].
    fn step(&mut self, dt: f64, rate: Rate, force: Force, acc: &mut Accumulated) {
        let decay = self.map_decay(dt);
        let s = &mut self.state;
        let we = Vector3::new(0.0, 0.0, EARTH_RATE_RAD_S);
        let (w, coupled) = match rate {
            Rate::Measured(w) => (w - s.gyro_bias_imu_rad_s, true),
            Rate::Unmeasured { w, coupled } => (w - s.gyro_bias_imu_rad_s, coupled),
            Rate::Held => (Vector3::zeros(), false),
        };
        if !matches!(rate, Rate::Held) {
            s.rate_ecef_rad_s = s.q_ecef_imu * w - we;
        }
        let dq = strapdown_increment(&w, dt);
        // Mid-step attitude for the specific force (second order).
        let r_mid = (s.q_ecef_imu * UnitQuaternion::from_scaled_axis(w * (0.5 * dt))).to_rotation_matrix();
        let r_mid = r_mid.into_inner();
        let measured = match force {
            Force::Measured(f) => Some(r_mid * (f - s.accel_bias_imu_m_s2)),
            Force::Free => None,
        };
        let v0 = s.velocity_ecef_m_s;
        if let Some(f_ecef) = measured {
            let a = f_ecef + gravity_ecef(&s.position) - 2.0 * we.cross(&v0);
            s.velocity_ecef_m_s += a * dt;
            if let Some(j) = &mut self.jump_turn {
                j.integrate_force(&f_ecef, dt);
            }
        }
        s.position.0 += (v0 + s.velocity_ecef_m_s) * (0.5 * dt);
        let earth = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -EARTH_RATE_RAD_S * dt);
        s.q_ecef_imu = earth * s.q_ecef_imu * dq;
        s.map_offset_ecef_m *= decay;
        s.map_offset_att_rad *= decay;

        // The error state's F dt (the constant blocks are added at the flush).
        if coupled {
            let mut b = acc.f_dt.fixed_view_mut::<3, 3>(ATT, GYRO_BIAS);
            b -= r_mid * dt;
        }
        if let Some(f_ecef) = measured {
            let mut b = acc.f_dt.fixed_view_mut::<3, 3>(VEL, ATT);
            b -= f_ecef.cross_matrix() * dt;
            let mut b = acc.f_dt.fixed_view_mut::<3, 3>(VEL, POS);
            b += gravitation_gradient(&s.position) * dt;
            let mut b = acc.f_dt.fixed_view_mut::<3, 3>(VEL, ACCEL_BIAS);
            b -= r_mid * dt;
        }
        let e = &self.errors;
        let vel_noise = if measured.is_some() { e.accel_vrw_m_s_sqrt_s } else { e.free_accel_m_s2_sqrt_s };
        let map_var = e.map_sigma_m.powi(2) * (1.0 - decay * decay);
        let map_att_var = e.map_att_sigma_rad.powi(2) * (1.0 - decay * decay);
        for i in 0..3 {
            acc.q[ATT + i] += e.gyro_arw_rad_sqrt_s.powi(2) * dt;
            acc.q[VEL + i] += vel_noise.powi(2) * dt;
            acc.q[GYRO_BIAS + i] += e.gyro_bias_walk_rad_s_sqrt_s.powi(2) * dt;
            acc.q[ACCEL_BIAS + i] += e.accel_bias_walk_m_s2_sqrt_s.powi(2) * dt;
            acc.q[MAP + i] += map_var;
            acc.q[MAP_ATT + i] += map_att_var;
        }
        if self.covariance[(FOCAL, FOCAL)] > 0.0 {
            acc.q[FOCAL] += e.focal_walk_rel_sqrt_s.powi(2) * dt;
        }
        if self.estimates_principal_point() {
            for i in PRINCIPAL..PRINCIPAL + 2 {
                acc.q[i] += e.principal_walk_px_sqrt_s.powi(2) * dt;
            }
        }
        acc.dt += dt;
        acc.map_decay *= decay;
        if acc.dt >= COVARIANCE_STEP_S {
            self.flush(acc);
        }
    }

    /// Applies the accumulated transition `Phi = I + A + A^2 / 2` (`A` the
    /// integral of F) and process noise to the covariance.
    fn flush(&mut self, acc: &mut Accumulated) {
        if acc.dt <= 0.0 {
            return;
        }
        let wx = Vector3::new(0.0, 0.0, EARTH_RATE_RAD_S).cross_matrix() * acc.dt;
        let mut a = acc.f_dt;
        {
            let mut b = a.fixed_view_mut::<3, 3>(ATT, ATT);
            b -= wx;
        }
        a.fixed_view_mut::<3, 3>(POS, VEL).fill_diagonal(acc.dt);
        {
            let mut b = a.fixed_view_mut::<3, 3>(VEL, VEL);
            b -= wx * 2.0;
        }
        let mut phi = Covariance::identity() + a + a * a * 0.5;
        for i in (MAP..MAP + 3).chain(MAP_ATT..MAP_ATT + 3) {
            for j in 0..N {
                phi[(i, j)] = 0.0;
            }
            phi[(i, i)] = acc.map_decay;
        }
        let p = &mut self.covariance;
        *p = phi * *p * phi.transpose();
        for i in 0..N {
            p[(i, i)] += acc.q[i];
        }
        let fresh = 1.0 - acc.map_decay * acc.map_decay;
        add_map_block(p, &(self.map_view * fresh));
        self.map_view_prior = self.map_view_prior * (1.0 - fresh) + self.map_view * fresh;
        *acc = Accumulated::default();
    }

    fn map_decay(&self, dt: f64) -> f64 {
        if self.errors.map_tau_s > 0.0 {
            (-dt / self.errors.map_tau_s).exp()
        } else {
            0.0
        }
    }

    /// `H` of the apparent camera pose `[dtheta + dm_theta + w dtau; dr + dm
    /// + v dtau]`, solved with a camera whose focal length and principal
    /// point may be off: `- S [dfocal; dc]` added (see [`IntrinsicsSensitivity`]).
    fn pose_rows_with(&self, sensitivity: &IntrinsicsSensitivity) -> SMatrix<f64, 6, N> {
        let mut h = SMatrix::<f64, 6, N>::zeros();
        h.fixed_view_mut::<3, 3>(0, ATT).copy_from(&Matrix3::identity());
        h.fixed_view_mut::<3, 3>(3, POS).copy_from(&Matrix3::identity());
        h.fixed_view_mut::<3, 3>(3, MAP).copy_from(&Matrix3::identity());
        h.fixed_view_mut::<3, 3>(0, MAP_ATT).copy_from(&Matrix3::identity());
        h.fixed_view_mut::<3, 1>(0, TIME).copy_from(&self.state.rate_ecef_rad_s);
        h.fixed_view_mut::<3, 1>(3, TIME).copy_from(&self.state.velocity_ecef_m_s);
        h.fixed_view_mut::<6, 3>(0, FOCAL).copy_from(&-sensitivity.0);
        h
    }

    /// The intrinsics' errors the filter carries: `[dfocal; dc]`.
    fn intrinsics_error(&self) -> Vector3<f64> {
        Vector3::new(self.focal_error_rel, self.principal_error_px.x, self.principal_error_px.y)
    }

    /// How the time offset moves the pose an image sees: `[w tau; v tau]`.
    fn time_shift(&self) -> Vector6<f64> {
        let s = &self.state;
        time_shift(&s.rate_ecef_rad_s, &s.velocity_ecef_m_s, s.time_offset_s)
    }

    /// The camera pose the images should see (the map offset added, carried
    /// over the time offset) and its covariance (`[dtheta; dp]`, as
    /// `trn_vision::pnp`'s).
    pub fn apparent_pose(&self, q_imu_cam: &UnitQuaternion<f64>) -> (CameraPose, Matrix6<f64>) {
        self.apparent_pose_with(q_imu_cam, &IntrinsicsSensitivity::NONE)
    }

    /// [`Self::apparent_pose`] as a frame solved with the current camera
    /// sees it, its focal length and principal point uncertain
    /// ([`IntrinsicsSensitivity`]).
    pub fn apparent_pose_with(
        &self,
        q_imu_cam: &UnitQuaternion<f64>,
        sensitivity: &IntrinsicsSensitivity,
    ) -> (CameraPose, Matrix6<f64>) {
        let h = self.pose_rows_with(sensitivity);
        let s = &self.state;
        let shift = self.time_shift() - sensitivity.0 * self.intrinsics_error();
        let pose = CameraPose::new(
            Ecef(s.position.0 + s.map_offset_ecef_m),
            UnitQuaternion::from_scaled_axis(s.map_offset_att_rad) * s.q_ecef_imu * q_imu_cam,
        );
        (perturb(&pose, &shift), h * self.covariance * h.transpose())
    }

    /// The gyro bias's estimate and covariance (rad/s, IMU frame); after
    /// the IMU log's end, as it was there.
    pub fn gyro_bias_with_covariance(&self) -> (Vector3<f64>, Matrix3<f64>) {
        if let Some(kept) = self.bias_at_log_end.or(self.bias_in_gap) {
            return kept;
        }
        let cov = self.covariance.fixed_view::<3, 3>(GYRO_BIAS, GYRO_BIAS).into_owned();
        (self.state.gyro_bias_imu_rad_s, cov)
    }

    /// The camera-IMU time offset's estimate and sigma (s).
    pub fn time_offset(&self) -> (f64, f64) {
        (self.state.time_offset_s, self.covariance[(TIME, TIME)].max(0.0).sqrt())
    }

    /// The estimated camera pose (the map offset not added) and its covariance.
    pub fn pose(&self, q_imu_cam: &UnitQuaternion<f64>) -> (CameraPose, Matrix6<f64>) {
        let s = &self.state;
        let pose = CameraPose::new(s.position, s.q_ecef_imu * q_imu_cam);
        (pose, self.covariance.fixed_view::<6, 6>(ATT, ATT).into_owned())
    }

    /// Velocity (m/s, ECEF) and its covariance.
    pub fn velocity(&self) -> (Vector3<f64>, Matrix3<f64>) {
        (self.state.velocity_ecef_m_s, self.covariance.fixed_view::<3, 3>(VEL, VEL).into_owned())
    }

    /// The innovation of an apparent camera pose measured with covariance
    /// `r` independently of the filter: the measured minus the predicted
    /// pose (`[dtheta; dp]`, [`pose_difference`]) and its normalized square
    /// (chi-square, 6 degrees of freedom; `None` when the innovation
    /// covariance is singular).
    pub fn innovation(
        &self,
        q_imu_cam: &UnitQuaternion<f64>,
        measured: &CameraPose,
        r: &Matrix6<f64>,
    ) -> (Vector6<f64>, Option<f64>) {
        let (pred, m) = self.apparent_pose(q_imu_cam);
        let y = pose_difference(measured, &pred);
        let nis = (m + r).cholesky().map(|s| y.dot(&s.solve(&y)));
        (y, nis)
    }

    /// Conditions the filter on a posterior of the apparent camera pose
    /// (mean and covariance) that was computed with [`Self::apparent_pose`]
    /// as its prior: the posterior becomes the pose block, and the other
    /// states move with it by their correlation with that block
    /// (`K = P H^T (H P H^T)^-1`, `x += K dm`,
    /// `P -= K (H P H^T - posterior) K^T`). Returns false, changing
    /// nothing, when the prior pose covariance cannot be inverted.
    pub fn condition_on_pose(
        &mut self,
        q_imu_cam: &UnitQuaternion<f64>,
        posterior: &CameraPose,
        posterior_cov: &Matrix6<f64>,
    ) -> bool {
        self.condition_on_pose_with(q_imu_cam, posterior, posterior_cov, &IntrinsicsSensitivity::NONE)
    }

    /// [`Self::condition_on_pose`] with a posterior computed with
    /// [`Self::apparent_pose_with`] as its prior: the focal length's and
    /// the principal point's errors move with the pose by their correlation
    /// with it, which the inertial trajectory builds (a rocket's climb,
    /// measured by the accelerometer, against the range the images see; a
    /// camera's roll about its boresight, against a tilt fixed in it).
    pub fn condition_on_pose_with(
        &mut self,
        q_imu_cam: &UnitQuaternion<f64>,
        posterior: &CameraPose,
        posterior_cov: &Matrix6<f64>,
        sensitivity: &IntrinsicsSensitivity,
    ) -> bool {
        let h = self.pose_rows_with(sensitivity);
        let (pred, m) = self.apparent_pose_with(q_imu_cam, sensitivity);
        let Some(m_inv) = m.cholesky().map(|c| c.inverse()) else { return false };
        let k = self.covariance * h.transpose() * m_inv;
        let a = m - posterior_cov;
        let (gain, p) = if self.principal_from_fixes || !self.estimates_principal_point() {
            (k, self.covariance - k * a * k.transpose())
        } else {
            // Schmidt: the principal point's gain rows zeroed, and the
            // covariance of that (suboptimal) gain, `P - Kz A K' - K A Kz'
            // + Kz A Kz'` (Joseph's form with `H P = M K'` and `K (M + R)
            // K'` written through the posterior, `A = M - posterior`).
            let mut kz = k;
            kz.fixed_rows_mut::<2>(PRINCIPAL).fill(0.0);
            (kz, self.covariance - kz * a * k.transpose() - k * a * kz.transpose() + kz * a * kz.transpose())
        };
        let dx = gain * pose_difference(posterior, &pred);
        self.covariance = (p + p.transpose()) * 0.5;
        self.apply(&dx);
        true
    }

    /// A standard (loosely coupled) Kalman update with an apparent camera
    /// pose measured with covariance `r`; returns its normalized innovation
    /// squared, or `None` (nothing changed) when singular.
    pub fn update_with_pose(
        &mut self,
        q_imu_cam: &UnitQuaternion<f64>,
        measured: &CameraPose,
        r: &Matrix6<f64>,
    ) -> Option<f64> {
        let (pred, m) = self.apparent_pose(q_imu_cam);
        let y = pose_difference(measured, &pred);
        let s_inv = (m + r).cholesky()?.inverse();
        // Posterior of the pose block, then conditioning.
        let post_cov = m - m * s_inv * m;
        let post_cov = (post_cov + post_cov.transpose()) * 0.5;
        let dm = m * s_inv * y;
        let posterior = perturb(&pred, &dm);
        self.condition_on_pose(q_imu_cam, &posterior, &post_cov);
        Some(y.dot(&(s_inv * y)))
    }

    /// A Kalman update from `m` scalar measurements `y = H dx + G n + e`
    /// with unit noise `e` (rows already whitened), `H` over the error state
    /// (`m` x [`N`]) and, optionally, a nuisance `n` (`G`: `m` x `k`) of
    /// zero mean and the given 1-sigma per component, independent of the state,
    /// estimated with it and then dropped. Many rows are first compressed by
    /// a QR factorization of `[H G]` (the same information in at most `N + k`
    /// rows). Nothing is changed: [`Self::apply_update`] applies the result.
    /// `None` when a matrix is singular.
    pub fn linear_update(
        &self,
        h: &DMatrix<f64>,
        nuisance: Option<(&DMatrix<f64>, &[f64])>,
        y: &DVector<f64>,
    ) -> Option<LinearUpdate> {
        let m = h.nrows();
        if h.ncols() != N
            || y.len() != m
            || nuisance.is_some_and(|(g, sd)| g.nrows() != m || g.ncols() != sd.len())
        {
            return None;
        }
        let k = nuisance.map_or(0, |(g, _)| g.ncols());
        let na = N + k;
        let mut a = DMatrix::<f64>::zeros(m, na);
        a.columns_mut(0, N).copy_from(h);
        let mut pa = DMatrix::<f64>::zeros(na, na);
        pa.view_mut((0, 0), (N, N)).copy_from(&self.covariance);
        if let Some((g, sigmas)) = nuisance {
            a.columns_mut(N, k).copy_from(g);
            for (i, s) in sigmas.iter().enumerate() {
                pa[(N + i, N + i)] = s * s;
            }
        }
        // The residual orthogonal to [H G]'s columns is information on
        // nothing but the noise: it enters the chi-square only.
        let (a, y, outside) = if m > na {
            let qr = a.qr();
            let yc = qr.q().transpose() * y;
            let outside = (y.norm_squared() - yc.norm_squared()).max(0.0);
            (qr.r(), yc, outside)
        } else {
            (a, y.clone(), 0.0)
        };
        let mr = a.nrows();
        let pht = &pa * a.transpose();
        let s = &a * &pht + DMatrix::<f64>::identity(mr, mr);
        let chol = s.clone().cholesky()?;
        let gain = chol.solve(&pht.transpose()).transpose();
        let dxa = &gain * &y;
        let chi2 = y.dot(&chol.solve(&y)) + outside;
        let kx = gain.rows(0, N).into_owned();
        let dp = &kx * &s * kx.transpose();
        let mut covariance = self.covariance;
        for i in 0..N {
            for j in 0..N {
                covariance[(i, j)] -= 0.5 * (dp[(i, j)] + dp[(j, i)]);
            }
        }
        Some(LinearUpdate {
            dx: SMatrix::<f64, N, 1>::from_iterator(dxa.rows(0, N).iter().copied()),
            nuisance: dxa.rows(N, k).into_owned(),
            covariance,
            chi2,
            dof: m,
        })
    }

    /// Applies a [`Self::linear_update`] computed from this filter.
    pub fn apply_update(&mut self, u: &LinearUpdate) {
        self.covariance = u.covariance;
        self.apply(&u.dx);
    }

    /// Adds an error-state correction to the nominal state.
    fn apply(&mut self, dx: &SMatrix<f64, N, 1>) {
        let s = &mut self.state;
        let v = |at: usize| Vector3::new(dx[at], dx[at + 1], dx[at + 2]);
        s.q_ecef_imu = UnitQuaternion::from_scaled_axis(v(ATT)) * s.q_ecef_imu;
        s.position.0 += v(POS);
        s.velocity_ecef_m_s += v(VEL);
        s.gyro_bias_imu_rad_s += v(GYRO_BIAS);
        s.accel_bias_imu_m_s2 += v(ACCEL_BIAS);
        s.map_offset_ecef_m += v(MAP);
        s.map_offset_att_rad += v(MAP_ATT);
        s.time_offset_s += dx[TIME];
        self.focal_error_rel += dx[FOCAL];
        self.principal_error_px += Vector2::new(dx[PRINCIPAL], dx[PRINCIPAL + 1]);
    }

    /// A direct measurement of the focal length's error (relative to the
    /// camera in use) with variance `variance`: what a frame's relief says
    /// of the lens once its pose is eliminated
    /// ([`crate::calibration::CalibrationFilter::update`]); the pose moves
    /// with it by their correlation. Returns false, changing nothing, when
    /// the focal length is not estimated or the variance is not positive.
    pub fn focal_measurement(&mut self, measured_rel: f64, variance: f64) -> bool {
        let p = self.covariance[(FOCAL, FOCAL)];
        if !(p > 0.0 && variance > 0.0) {
            return false;
        }
        let k = self.covariance.column(FOCAL) / (p + variance);
        let dx = k * (measured_rel - self.focal_error_rel);
        let p_new = self.covariance - k * self.covariance.row(FOCAL);
        self.covariance = (p_new + p_new.transpose()) * 0.5;
        self.apply(&dx);
        true
    }

    /// Whether the focal length is a state (its prior was not zero).
    pub fn estimates_focal(&self) -> bool {
        self.covariance[(FOCAL, FOCAL)] > 0.0
    }

    /// The focal length's estimated error and its variance (relative); the
    /// error restarts at zero: the caller moves its camera by it.
    pub fn take_focal_error(&mut self) -> (f64, f64) {
        let d = std::mem::take(&mut self.focal_error_rel);
        (d, self.covariance[(FOCAL, FOCAL)])
    }

    /// Whether the principal point is a state (its prior was not zero).
    pub fn estimates_principal_point(&self) -> bool {
        self.covariance[(PRINCIPAL, PRINCIPAL)] > 0.0
    }

    /// The principal point's estimated error and its covariance (px); the
    /// error restarts at zero: the caller moves its camera by it.
    pub fn take_principal_error(&mut self) -> (Vector2<f64>, Matrix2<f64>) {
        let d = std::mem::take(&mut self.principal_error_px);
        (d, self.covariance.fixed_view::<2, 2>(PRINCIPAL, PRINCIPAL).into_owned())
    }

    /// The map offset's 1-sigmas (m per axis, rad per axis).
    pub fn map_sigmas(&self) -> (f64, f64) {
        (self.errors.map_sigma_m, self.errors.map_att_sigma_rad)
    }

    /// How far the map offset's estimate lies in its own prior (the
    /// stationary 1-sigmas of [`InsErrors::map_sigma_m`] and
    /// [`InsErrors::map_att_sigma_rad`]): the sum of its six parts' squares
    /// in those sigmas (chi-square with up to 6 degrees of freedom where the
    /// database's errors are what the model says). Large, the images are
    /// being explained by a map error no database of the model has: the
    /// inertial state is more likely wrong.
    pub fn map_offset_distance(&self) -> f64 {
        let (sm, sa) = self.map_sigmas();
        if self.map_view_prior != Matrix6::zeros() {
            // The prior with the view's term: a full covariance.
            let mut prior = self.map_view_prior;
            for i in 0..3 {
                prior[(i, i)] += sa * sa;
                prior[(i + 3, i + 3)] += sm * sm;
            }
            let x = Vector6::new(
                self.state.map_offset_att_rad.x,
                self.state.map_offset_att_rad.y,
                self.state.map_offset_att_rad.z,
                self.state.map_offset_ecef_m.x,
                self.state.map_offset_ecef_m.y,
                self.state.map_offset_ecef_m.z,
            );
            // A part not modelled (a zero sigma and no view term) has no
            // variance and stays at zero: a unit variance counts it nothing.
            for i in 0..6 {
                if prior[(i, i)] <= 0.0 {
                    prior[(i, i)] = 1.0;
                }
            }
            return prior.cholesky().map_or(f64::INFINITY, |c| x.dot(&c.solve(&x)));
        }
        let part =
            |v: &Vector3<f64>, sigma: f64| if sigma > 0.0 { v.norm_squared() / (sigma * sigma) } else { 0.0 };
        part(&self.state.map_offset_ecef_m, sm) + part(&self.state.map_offset_att_rad, sa)
    }

    /// The map offset's view term for a view whose landmarks' own errors
    /// give its pose the covariance `pose_cov` (`[dtheta; dp]`, rad and m):
    /// the part of it beyond the isotropic prior
    /// ([`InsErrors::map_sigma_m`], [`InsErrors::map_att_sigma_rad`]: a wide
    /// view's own errors lie within it and add nothing), at most
    /// [`MAP_VIEW_CAP_SIGMAS`] of that prior's sigmas along any direction (a
    /// view of a handful of landmarks would otherwise make the offset, and
    /// with it the search and the gate, kilometres wide). Without either
    /// part of the prior (a sigma of 0: not modelled): nothing.
    pub fn map_view_excess(&self, pose_cov: &Matrix6<f64>) -> Matrix6<f64> {
        let (sm, sa) = self.map_sigmas();
        if !(sm > 0.0 && sa > 0.0) {
            return Matrix6::zeros();
        }
        // In the prior's sigmas, the prior is the identity.
        let d = Vector6::new(sa, sa, sa, sm, sm, sm);
        let w = Matrix6::from_fn(|i, j| pose_cov[(i, j)] / (d[i] * d[j]));
        let cap2 = MAP_VIEW_CAP_SIGMAS * MAP_VIEW_CAP_SIGMAS;
        let c = map_eigenvalues(&w, |l| (l - 1.0).clamp(0.0, cap2));
        Matrix6::from_fn(|i, j| c[(i, j)] * d[i] * d[j])
    }

    /// Sets the map offset's view term: `view` (`[dm_theta; dm]`, rad and
    /// m, as an apparent pose's covariance) is the stationary covariance
    /// the landmarks' own errors give the pose of the view now seen, on top
    /// of the isotropic prior ([`InsErrors::map_sigma_m`],
    /// [`InsErrors::map_att_sigma_rad`]). A narrow view trades a tilt for a
    /// shift: the few landmarks' errors, the same from frame to frame, move
    /// the pose it gives along that trade by far more than a wide view's.
    /// What the new term adds to the old is added to the offset's
    /// covariance at once (a view that narrows brings its landmarks' errors
    /// with it); from then on it is the offset's process noise, as the
    /// prior is.
    pub fn set_map_view(&mut self, view: &Matrix6<f64>) {
        let grown = positive_part(&(view - self.map_view_prior));
        add_map_block(&mut self.covariance, &grown);
        self.map_view_prior += grown;
        self.map_view = (view + view.transpose()) * 0.5;
    }

    /// Takes the gyro's jumps since the last fix (`jump`) for a glitch, as
    /// a frame that found its landmarks with them undone says: the attitude
    /// is turned back by them (in ECEF, where a turn made at the jump stays
    /// the same rotation as the body turns on), the velocity and the
    /// position lose what the accelerometer's force, turned by them since
    /// the first, added ([`JumpTurn::undo_shift`]), and the jump record is
    /// cleared.
    ///
    /// The undone state's doubt: the attitude's at most
    /// `attitude_sigma_rad` on any axis (the undone guess's), the force
    /// since the jump turned by that much doubting the velocity and the
    /// position (`2 sin(a / 2)` times the force norm's integral, and its
    /// own); then what frames without a fix since added (the jumps taken
    /// for turns left them unexplained) goes: the position's sigma is at
    /// most the filter's at the jump carried on
    /// ([`JumpTurn::undone_position_sigma_m`]) and the velocity's its sigma
    /// at the jump and that doubt, correlations kept.
    pub fn undo_jumps(&mut self, jump: &JumpTurn, attitude_sigma_rad: f64) {
        let s = &mut self.state;
        s.q_ecef_imu = UnitQuaternion::from_scaled_axis(-jump.turn_ecef_rad) * s.q_ecef_imu;
        let (dv, dp) = jump.undo_shift();
        s.velocity_ecef_m_s += dv;
        s.position.0 += dp;
        let turned = 2.0 * (0.5 * attitude_sigma_rad).sin().abs();
        let (v_doubt, p_doubt) = (turned * jump.force_norm_m_s, turned * jump.force_norm_twice_m);
        for i in 0..3 {
            self.covariance[(VEL + i, VEL + i)] += v_doubt * v_doubt;
            self.covariance[(POS + i, POS + i)] += p_doubt * p_doubt;
        }
        let position_most = jump.undone_position_sigma_m(s.t, attitude_sigma_rad);
        for (at, most) in
            [(POS, position_most), (ATT, attitude_sigma_rad), (VEL, jump.velocity_sigma_m_s + v_doubt)]
        {
            let worst = (at..at + 3).map(|i| self.covariance[(i, i)]).fold(0.0, f64::max).sqrt();
            if worst > most && most > 0.0 {
                self.scale_sigmas(at..at + 3, most / worst);
            }
        }
        self.jump_turn = None;
    }

    /// Restarts the map offset when its estimate is not to be believed
    /// ([`Self::map_offset_distance`]): the pose the images see is kept (the
    /// offset moved into the position and attitude), the offset starts
    /// again at zero with its prior, uncorrelated, the position, velocity
    /// and attitude sigmas are scaled by `factor` (correlations kept), and
    /// the velocity's scaled further until its largest axis reaches
    /// `velocity_sigma_m_s`, so the next fixes correct the state that
    /// drifted.
    pub fn restart_map_offset(&mut self, factor: f64, velocity_sigma_m_s: f64) {
        let s = &mut self.state;
        s.position = Ecef(s.position.0 + s.map_offset_ecef_m);
        s.q_ecef_imu = UnitQuaternion::from_scaled_axis(s.map_offset_att_rad) * s.q_ecef_imu;
        s.map_offset_ecef_m = Vector3::zeros();
        s.map_offset_att_rad = Vector3::zeros();
        let (sm, sa) = self.map_sigmas();
        uncorrelate(&mut self.covariance, MAP..MAP + 3);
        uncorrelate(&mut self.covariance, MAP_ATT..MAP_ATT + 3);
        block(&mut self.covariance, MAP, sm);
        block(&mut self.covariance, MAP_ATT, sa);
        let view = self.map_view_prior;
        add_map_block(&mut self.covariance, &view);
        self.inflate(factor);
        let worst = (VEL..VEL + 3).map(|i| self.covariance[(i, i)]).fold(0.0, f64::max).sqrt();
        if worst < velocity_sigma_m_s && worst > 0.0 {
            self.scale_sigmas(VEL..VEL + 3, velocity_sigma_m_s / worst);
        }
    }

    /// Resizes the map offset to new 1-sigmas: its process noise from now
    /// on and, with `covariance`, its covariance by the same ratio
    /// (correlations kept; a part that was not modelled starts uncorrelated
    /// at its sigma, one set to 0 is dropped). The estimate is kept: it is
    /// evidence.
    pub fn resize_map_offset(&mut self, map_sigma_m: f64, map_att_sigma_rad: f64, covariance: bool) {
        let parts = [
            (MAP, self.errors.map_sigma_m, map_sigma_m),
            (MAP_ATT, self.errors.map_att_sigma_rad, map_att_sigma_rad),
        ];
        if covariance {
            for (at, old, new) in parts {
                if old > 0.0 && new > 0.0 {
                    self.scale_sigmas(at..at + 3, new / old);
                } else if old != new {
                    uncorrelate(&mut self.covariance, at..at + 3);
                    for i in at..at + 3 {
                        self.covariance[(i, i)] = new * new;
                    }
                }
            }
        }
        self.errors.map_sigma_m = map_sigma_m;
        self.errors.map_att_sigma_rad = map_att_sigma_rad;
    }

    /// Scales the uncertainty of position, velocity and attitude by `factor`
    /// (their standard deviations), keeping every correlation: what the
    /// filter does when an image it could not explain says it may be wrong.
    pub fn inflate(&mut self, factor: f64) {
        self.scale_sigmas(ATT..VEL + 3, factor);
    }

    /// Forgets a velocity doubted beyond `sigma_m_s` (on any axis): frames of
    /// doubt before a restart inflate the pose's uncertainty, and the
    /// propagation carries it into the velocity's without bound, and the
    /// estimate with it (the IMU integrated through a wrong attitude). Such a
    /// velocity restarts as the initial guess's: zero, `sigma_m_s` per axis,
    /// uncorrelated. Returns whether it did.
    pub fn forget_velocity_beyond(&mut self, sigma_m_s: f64) -> bool {
        let worst = (VEL..VEL + 3).map(|i| self.covariance[(i, i)]).fold(0.0, f64::max).sqrt();
        if !(sigma_m_s > 0.0 && worst > sigma_m_s) {
            return false;
        }
        self.state.velocity_ecef_m_s = Vector3::zeros();
        uncorrelate(&mut self.covariance, VEL..VEL + 3);
        block(&mut self.covariance, VEL, sigma_m_s);
        true
    }

    /// Scales the uncertainty of attitude and position only by `factor`
    /// (the velocity's is left): what the filter does when the images have
    /// not yet confirmed an initial guess, which says nothing of velocity.
    /// Each of the two by at most what takes its largest sigma (on any axis)
    /// to `max_attitude_rad` / `max_position_m` (never shrinking one already
    /// beyond): a doubt that grows frame by frame stays bounded where a
    /// search no longer gains from it. Returns the factors applied
    /// (attitude, position).
    pub fn inflate_pose_within(
        &mut self,
        factor: f64,
        max_attitude_rad: f64,
        max_position_m: f64,
    ) -> (f64, f64) {
        let worst =
            |s: &Self, at: usize| (at..at + 3).map(|i| s.covariance[(i, i)]).fold(0.0, f64::max).sqrt();
        let k_att = doubt_factor(worst(self, ATT), max_attitude_rad, factor);
        let k_pos = doubt_factor(worst(self, POS), max_position_m, factor);
        let mut d = SMatrix::<f64, N, 1>::repeat(1.0);
        for i in 0..3 {
            d[ATT + i] = k_att;
            d[POS + i] = k_pos;
        }
        self.scale_by(&d);
        (k_att, k_pos)
    }

    /// `P <- D P D` with `D` = `factor` on the states of `range`, 1 elsewhere.
    fn scale_sigmas(&mut self, range: std::ops::Range<usize>, factor: f64) {
        let mut d = SMatrix::<f64, N, 1>::repeat(1.0);
        for i in range {
            d[i] = factor;
        }
        self.scale_by(&d);
    }

    /// `P <- D P D`, `D` the diagonal `d`.
    fn scale_by(&mut self, d: &SMatrix<f64, N, 1>) {
        let scale = Covariance::from_diagonal(d);
        self.covariance = scale * self.covariance * scale;
    }

    /// Restarts the pose from an image-only fix (mean and covariance),
    /// forgetting the pose's prior: what the images see is the true pose
    /// plus the map offset, carried over the time offset (`z = x_pose +
    /// H_o x_o`, [`Self::apparent_pose`]'s rows), so the pose becomes
    /// `z - H_o x_o`: its covariance `R + H_o P_oo H_oᵀ`, its correlation with
    /// the other states `-H_o P_oo`, and the apparent pose's covariance is
    /// the fix's. (Dropping those terms would say the fix measured the true
    /// pose: every later fix's disagreement would go to the map offset, and
    /// the first fix's error would stay for the offset's correlation time.)
    /// The intrinsics the filter carries enter as the other offsets do, by
    /// the fix's `sensitivity` to them.
    /// The velocity's uncertainty is at least `velocity_sigma_m_s`.
    pub fn reset_pose(
        &mut self,
        q_imu_cam: &UnitQuaternion<f64>,
        fix: &CameraPose,
        fix_cov: &Matrix6<f64>,
        velocity_sigma_m_s: f64,
        sensitivity: &IntrinsicsSensitivity,
    ) {
        let shift = self.time_shift() - sensitivity.0 * self.intrinsics_error();
        let at_stamp = perturb(fix, &-shift);
        let s = &mut self.state;
        s.q_ecef_imu = UnitQuaternion::from_scaled_axis(-s.map_offset_att_rad)
            * at_stamp.q_ecef_cam
            * q_imu_cam.inverse();
        s.position = Ecef(at_stamp.position.0 - s.map_offset_ecef_m);
        let mut p = self.covariance;
        uncorrelate(&mut p, ATT..POS + 3);
        for i in VEL..VEL + 3 {
            p[(i, i)] = p[(i, i)].max(velocity_sigma_m_s * velocity_sigma_m_s);
        }
        let mut h_other = self.pose_rows_with(sensitivity);
        h_other.fixed_view_mut::<6, 6>(0, ATT).fill(0.0);
        let cross = -h_other * p;
        let pose_block = fix_cov + h_other * p * h_other.transpose();
        p.fixed_view_mut::<6, N>(ATT, 0).copy_from(&cross);
        p.fixed_view_mut::<N, 6>(0, ATT).copy_from(&cross.transpose());
        p.fixed_view_mut::<6, 6>(ATT, ATT).copy_from(&((pose_block + pose_block.transpose()) * 0.5));
        self.covariance = p;
    }
}

/// The map offset's six states in an apparent pose's order
/// (`[dm_theta; dm]`, as `[dtheta; dp]`).
const MAP_BLOCK: [usize; 6] = [MAP_ATT, MAP_ATT + 1, MAP_ATT + 2, MAP, MAP + 1, MAP + 2];

/// Adds `c` (in [`MAP_BLOCK`]'s order) to the map offset's block of `p`.
fn add_map_block(p: &mut Covariance, c: &Matrix6<f64>) {
    for (a, &i) in MAP_BLOCK.iter().enumerate() {
        for (b, &j) in MAP_BLOCK.iter().enumerate() {
            p[(i, j)] += c[(a, b)];
        }
    }
}

/// A symmetric `d` (its symmetric part) with `g` applied to its
/// eigenvalues: `U g(L) U^T`.
fn map_eigenvalues(d: &Matrix6<f64>, g: impl Fn(f64) -> f64) -> Matrix6<f64> {
    let e = ((d + d.transpose()) * 0.5).symmetric_eigen();
    let mut out = Matrix6::zeros();
    for (k, &l) in e.eigenvalues.iter().enumerate() {
        let u = e.eigenvectors.column(k);
        out += u * u.transpose() * g(l);
    }
    out
}

/// The part of a symmetric `d` that adds variance: its negative
/// eigenvalues dropped.
fn positive_part(d: &Matrix6<f64>) -> Matrix6<f64> {
    map_eigenvalues(d, |l| l.max(0.0))
}

/// Zeroes the rows and columns of `range` in `p` (their variances too).
fn uncorrelate(p: &mut Covariance, range: std::ops::Range<usize>) {
    for i in range {
        p.row_mut(i).fill(0.0);
        p.column_mut(i).fill(0.0);
    }
}

/// How a pose solved from a frame's matches moves per unit of the camera's
/// relative focal length error and per pixel of its principal point's
/// (`[dtheta (rad, ECEF); dp (m, ECEF)]` per column: focal, u, v; the first
/// three columns of `trn_vision::calib::FrameCalibration::pose_sensitivity`):
/// a pose solved with a camera whose focal length is short by `e` (principal
/// point off by `dc`) is the true pose less `S [e; dc]` (a nadir view's
/// range, shortened by the focal error's share; its attitude, tilted by
/// the principal point's).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IntrinsicsSensitivity(pub SMatrix<f64, 6, 3>);

impl IntrinsicsSensitivity {
    /// No intrinsics' error modelled.
    pub const NONE: Self = Self(SMatrix::<f64, 6, 3>::new(
        0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
    ));

    /// From a frame's `pose_sensitivity` (columns focal, u, v, k1).
    pub fn of_frame(pose_sensitivity: &SMatrix<f64, 6, 4>) -> Self {
        Self(pose_sensitivity.fixed_columns::<3>(0).into_owned())
    }
}

/// The result of [`InsFilter::linear_update`].
#[derive(Clone, Debug, PartialEq)]
pub struct LinearUpdate {
    /// The error-state correction.
    pub dx: SMatrix<f64, N, 1>,
    /// The nuisance's estimate (dropped by the filter).
    pub nuisance: DVector<f64>,
    /// The posterior covariance.
    pub covariance: Covariance,
    /// Normalized innovation squared of the measurements against the
    /// prediction, with `dof` degrees of freedom (the rows).
    pub chi2: f64,
    pub dof: usize,
}

/// How a time offset `tau` (s) moves the pose an image sees, with the body's
/// rotation rate (rad/s) and velocity (m/s), both ECEF: `[w tau; v tau]`.
pub fn time_shift(
    rate_ecef_rad_s: &Vector3<f64>,
    velocity_ecef_m_s: &Vector3<f64>,
    tau: f64,
) -> Vector6<f64> {
    let (w, v) = (rate_ecef_rad_s * tau, velocity_ecef_m_s * tau);
    Vector6::new(w.x, w.y, w.z, v.x, v.y, v.z)
}

/// `[log(q_a q_b^-1); p_a - p_b]`: pose `a` as a perturbation of `b`.
pub fn pose_difference(a: &CameraPose, b: &CameraPose) -> Vector6<f64> {
    let d = rotation_vector(&(a.q_ecef_cam * b.q_ecef_cam.inverse()));
    let p = a.position.0 - b.position.0;
    Vector6::new(d.x, d.y, d.z, p.x, p.y, p.z)
}

/// Pose `b` perturbed by `[dtheta; dp]` (the inverse of [`pose_difference`]).
pub fn perturb(b: &CameraPose, d: &Vector6<f64>) -> CameraPose {
    CameraPose::new(
        Ecef(b.position.0 + Vector3::new(d[3], d[4], d[5])),
        UnitQuaternion::from_scaled_axis(Vector3::new(d[0], d[1], d[2])) * b.q_ecef_cam,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::{Geodetic, LocalFrame};

    /// SplitMix64 with Box-Muller normals: seeded noise for the tests.
    struct Rng(u64);

    impl Rng {
        fn new(seed: u64) -> Self {
            Rng(seed)
        }

        fn uniform(&mut self) -> f64 {
            self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }

        fn normal(&mut self) -> f64 {
            let (u1, u2) = (1.0 - self.uniform(), self.uniform());
            (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
        }
    }

    /// A constant turn: a circle of radius `r` flown at `omega` rad/s in the
    /// plane tangent to the ellipsoid at 30 km, the body's x axis along the
    /// velocity and z down. Exact position, velocity, acceleration and
    /// attitude at any time.
    struct Turn {
        centre: Vector3<f64>,
        e: Matrix3<f64>,
        r: f64,
        omega: f64,
        /// A roll wobble of this amplitude (rad) over a 4 s period (a
        /// balloon's pendulum; 0: none).
        wobble_rad: f64,
    }

    struct Truth {
        p: Vector3<f64>,
        v: Vector3<f64>,
        a: Vector3<f64>,
        q: UnitQuaternion<f64>,
    }

    impl Turn {
        fn new() -> Self {
            let frame = LocalFrame::at(Geodetic::new(36.6, -118.3, 30_000.0));
            Turn {
                centre: frame.origin_ecef().0,
                e: frame.r_ecef_enu(),
                r: 2000.0,
                omega: 0.1,
                wobble_rad: 0.0,
            }
        }

        fn at(&self, t: f64) -> Truth {
            let (s, c) = (self.omega * t).sin_cos();
            let (e1, e2, e3) = (self.e.column(0), self.e.column(1), self.e.column(2));
            let p = self.centre + (e1 * c + e2 * s) * self.r;
            let v = (-e1 * s + e2 * c) * (self.r * self.omega);
            let a = -(e1 * c + e2 * s) * (self.r * self.omega * self.omega);
            let x = v.normalize();
            let z = -e3.into_owned();
            let y = z.cross(&x);
            let m = Matrix3::from_columns(&[x, y, z]);
            let q = UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(m))
                * UnitQuaternion::from_axis_angle(
                    &Vector3::x_axis(),
                    self.wobble_rad * (std::f64::consts::TAU * t / 4.0).sin(),
                );
            Truth { p, v, a, q }
        }

        /// Gyro (mean inertial rate over the interval ending at each time)
        /// and accelerometer (specific force at each time) samples, with
        /// constant biases and white noise of the given sigmas per sample.
        fn imu(
            &self,
            rate_hz: f64,
            t_end: f64,
            noise: Option<(&InsErrors, &InsInit, u64)>,
        ) -> (Vec<ImuSample>, Vector3<f64>, Vector3<f64>) {
            let dt = 1.0 / rate_hz;
            let we = Vector3::new(0.0, 0.0, EARTH_RATE_RAD_S);
            let inertial = |t: f64| {
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), EARTH_RATE_RAD_S * t) * self.at(t).q
            };
            let mut rng = Rng::new(noise.map_or(0, |n| n.2));
            let mut draw = |sigma: f64| Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
            let (bg, ba) = match noise {
                Some((_, init, _)) => (draw(init.gyro_bias_rad_s), draw(init.accel_bias_m_s2)),
                None => (Vector3::zeros(), Vector3::zeros()),
            };
            let n = (t_end * rate_hz).round() as usize;
            let mut out = Vec::with_capacity(n + 1);
            for k in 0..=n {
                let t = k as f64 * dt;
                let truth = self.at(t);
                let mut w = rotation_vector(&(inertial(t - dt).inverse() * inertial(t))) / dt;
                let f_ecef = truth.a + 2.0 * we.cross(&truth.v) - gravity_ecef(&Ecef(truth.p));
                let mut f = truth.q.inverse() * f_ecef;
                if let Some((e, _, _)) = noise {
                    w += bg + draw(e.gyro_arw_rad_sqrt_s / dt.sqrt());
                    f += ba + draw(e.accel_vrw_m_s_sqrt_s / dt.sqrt());
                }
                out.push(ImuSample { t, w_imu_rad_s: w, f_imu_m_s2: Some(f) });
            }
            (out, bg, ba)
        }

        fn state(&self, t: f64) -> InsState {
            let truth = self.at(t);
            InsState {
                t,
                position: Ecef(truth.p),
                velocity_ecef_m_s: truth.v,
                q_ecef_imu: truth.q,
                gyro_bias_imu_rad_s: Vector3::zeros(),
                accel_bias_imu_m_s2: Vector3::zeros(),
                map_offset_ecef_m: Vector3::zeros(),
                map_offset_att_rad: Vector3::zeros(),
                time_offset_s: 0.0,
                rate_ecef_rad_s: Vector3::zeros(),
            }
        }
    }

    fn errors() -> InsErrors {
        InsErrors {
            gyro_arw_rad_sqrt_s: 0.15f64.to_radians() / 60.0,
            gyro_bias_walk_rad_s_sqrt_s: 0.0,
            accel_vrw_m_s_sqrt_s: 0.001,
            accel_bias_walk_m_s2_sqrt_s: 0.0,
            free_accel_m_s2_sqrt_s: 3.0,
            map_sigma_m: 0.0,
            map_tau_s: 0.0,
            map_att_sigma_rad: 0.0,
            focal_walk_rel_sqrt_s: 0.0,
            gyro_max_jump_rad_s: 0.0,
            accel_max_jump_m_s2: 0.0,
            imu_gap_s: 0.0,
            gap_rate_walk_rad_s_sqrt_s: 0.0,
            principal_walk_px_sqrt_s: 0.0,
        }
    }

    fn init() -> InsInit {
        InsInit {
            attitude_rad: 0.05f64.to_radians(),
            position_m: 20.0,
            velocity_m_s: 1.0,
            gyro_bias_rad_s: 10f64.to_radians() / 3600.0,
            accel_bias_m_s2: 0.02,
            time_offset_s: 0.0,
            focal_rel: 0.0,
            principal_px: 0.0,
        }
    }

    /// Error `[dtheta; dr; dv]` of a state against the truth.
    fn error9(s: &InsState, truth: &Truth) -> SMatrix<f64, 9, 1> {
        let mut e = SMatrix::<f64, 9, 1>::zeros();
        e.fixed_rows_mut::<3>(0).copy_from(&rotation_vector(&(truth.q * s.q_ecef_imu.inverse())));
        e.fixed_rows_mut::<3>(3).copy_from(&(truth.p - s.position.0));
        e.fixed_rows_mut::<3>(6).copy_from(&(truth.v - s.velocity_ecef_m_s));
        e
    }

    #[test]
    fn a_constant_turn_is_flown_on_the_imu_alone() {
        // 60 s of a 2 km turn at 200 m/s (2 g of centripetal acceleration
        // sideways, the body turning at 5.7 deg/s), exact samples at 200 Hz.
        let turn = Turn::new();
        let (imu, _, _) = turn.imu(200.0, 61.0, None);
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors());
        for t in [0.5, 17.25, 33.3, 60.0] {
            f.propagate(t, &imu);
            let e = error9(&f.state, &turn.at(t));
            let (att, pos, vel) =
                (e.fixed_rows::<3>(0).norm(), e.fixed_rows::<3>(3).norm(), e.fixed_rows::<3>(6).norm());
            assert!(att < 1e-6 && pos < 0.5 && vel < 0.02, "t {t}: {att:.2e} rad, {pos:.3} m, {vel:.4} m/s");
        }
        // Without the accelerometer the velocity is held: after 10 s the
        // turn's 2 g are missing.
        let bare: Vec<ImuSample> = imu.iter().map(|s| ImuSample { f_imu_m_s2: None, ..*s }).collect();
        let mut g = InsFilter::new(turn.state(0.0), &init(), errors());
        g.propagate(10.0, &bare);
        let pos = (g.state.position.0 - turn.at(10.0).p).norm();
        assert!(pos > 500.0, "{pos}");
        assert!(g.covariance[(POS, POS)].sqrt() > 10.0, "the free velocity walk grows the position sigma");
    }

    #[test]
    fn a_gyro_jump_is_doubted_about_its_axis() {
        // The 2 km turn (5.7 deg/s, noise-free samples at 200 Hz) with four
        // samples 150 deg/s off about the IMU's x axis from 10 s: 3 deg
        // turned in 20 ms that the body did not turn.
        let turn = Turn::new();
        let (clean, _, _) = turn.imu(200.0, 21.0, None);
        let mut imu = clean.clone();
        let glitch = 150f64.to_radians();
        for s in imu.iter_mut().filter(|s| s.t > 10.0 && s.t < 10.021) {
            s.w_imu_rad_s.x += glitch;
        }
        let watching = InsErrors { gyro_max_jump_rad_s: 10f64.to_radians(), ..errors() };
        let run = |errors: InsErrors, imu: &[ImuSample], t: f64| {
            let mut f = InsFilter::new(turn.state(0.0), &init(), errors);
            f.propagate(t, imu);
            f
        };
        // The turn's own rate changes (1e-4 deg/s a sample) are no jump.
        let smooth = run(watching, &imu, 9.9);
        assert_eq!(smooth.gyro_jumps(), 0);
        let f = run(watching, &imu, 12.0);
        assert_eq!(f.gyro_jumps(), 1);
        let err = error9(&f.state, &turn.at(12.0)).fixed_rows::<3>(0).into_owned();
        assert!((err.norm().to_degrees() - 3.0).abs() < 0.05, "{err}");
        // Doubted by the angle turned beyond the rate before, about the
        // jump's axis (the IMU's x in ECEF then, 10 s: the error stays fixed
        // in ECEF as the body turns on): 3 deg there, nothing across.
        let axis = turn.at(10.01).q * Vector3::x();
        let p = f.covariance.fixed_view::<3, 3>(ATT, ATT);
        let along = (axis.transpose() * p * axis)[0].sqrt().to_degrees();
        let across = (p.trace() - along.to_radians().powi(2)).max(0.0).sqrt().to_degrees();
        assert!((along - 3.0).abs() < 0.1, "along {along} deg");
        assert!(across < 0.1, "across {across} deg");
        assert!(err.norm() < 1.5 * along.to_radians(), "the error within its doubt");
        // The turn is kept, uncapped, in ECEF: undone, the attitude is the
        // truth's again (to the turn's own dynamics over 20 ms).
        let undone_error = |f: &InsFilter| {
            let j = f.jump_turn.expect("a jump's turn");
            assert!((j.since_t - 10.0).abs() < 0.01, "{j:?}");
            let state = InsState {
                q_ecef_imu: UnitQuaternion::from_scaled_axis(-j.turn_ecef_rad) * f.state.q_ecef_imu,
                ..f.state
            };
            (
                j.turn_ecef_rad.norm().to_degrees(),
                error9(&state, &turn.at(12.0)).fixed_rows::<3>(0).norm().to_degrees(),
            )
        };
        let (turned, left) = undone_error(&f);
        assert!((turned - 3.0).abs() < 0.01 && left < 0.01, "turned {turned} deg, left {left} deg");
        assert_eq!(smooth.jump_turn, None);
        // Off (0), the same glitch leaves the attitude's sigma as without it
        // (but for the jump's own turn of the dynamics).
        let off = run(errors(), &imu, 12.0);
        let quiet = run(errors(), &clean, 12.0);
        assert_eq!(off.gyro_jumps(), 0);
        let att_var = |f: &InsFilter| f.covariance.fixed_view::<3, 3>(ATT, ATT).trace();
        assert!(
            (att_var(&off) / att_var(&quiet) - 1.0).abs() < 0.01,
            "{} {}",
            att_var(&off),
            att_var(&quiet)
        );
        // A jump of 40 deg is doubted by GYRO_JUMP_MAX_ANGLE_DEG at most.
        for s in imu.iter_mut().filter(|s| s.t > 10.0 && s.t < 10.021) {
            s.w_imu_rad_s.x += 2000f64.to_radians() - glitch;
        }
        let f = run(watching, &imu, 12.0);
        let p = f.covariance.fixed_view::<3, 3>(ATT, ATT);
        let along = (axis.transpose() * p * axis)[0].sqrt().to_degrees();
        assert!((along - GYRO_JUMP_MAX_ANGLE_DEG).abs() < 0.2, "{along}");
        // Its turn is kept whole (undone to within the turn's own dynamics
        // over the 20 ms, 0.1 deg).
        let (turned, left) = undone_error(&f);
        assert!((turned - 40.0).abs() < 0.1 && left < 0.1, "turned {turned} deg, left {left} deg");
    }

    #[test]
    fn an_accelerometer_jump_is_doubted_along_its_axis() {
        // The 2 km turn (2 g sideways, noise-free samples at 200 Hz) with
        // its accelerometer 100 m/s^2 off along the IMU's x axis for 1 s
        // from 10 s (a shock that saturated it): 100 m/s of velocity the
        // body did not gain.
        let turn = Turn::new();
        let (clean, _, _) = turn.imu(200.0, 21.0, None);
        let mut imu = clean.clone();
        let glitch = 100.0;
        for s in imu.iter_mut().filter(|s| s.t > 10.0 && s.t < 11.0 + 1e-9) {
            s.f_imu_m_s2 = s.f_imu_m_s2.map(|f| f + Vector3::x() * glitch);
        }
        let watching = InsErrors { accel_max_jump_m_s2: 10.0, ..errors() };
        let run = |errors: InsErrors, imu: &[ImuSample], t: f64| {
            let mut f = InsFilter::new(turn.state(0.0), &init(), errors);
            f.propagate(t, imu);
            f
        };
        // The turn's own force (constant in the body) is no jump.
        assert_eq!(run(watching, &clean, 21.0).accel_jumps(), 0);
        let f = run(watching, &imu, 12.0);
        assert_eq!(f.accel_jumps(), 1);
        let err = error9(&f.state, &turn.at(12.0)).fixed_rows::<3>(6).into_owned();
        assert!((err.norm() - glitch).abs() < 3.0, "{err}");
        // Doubted by the velocity it added beyond the force before, along
        // its axis (the IMU's x in ECEF, which turns 5.7 deg in that second).
        let p = f.covariance.fixed_view::<3, 3>(VEL, VEL).into_owned();
        let dir = err.normalize();
        let along = (dir.transpose() * p * dir)[0].sqrt();
        assert!(along > 0.9 * glitch && along < 1.1 * glitch, "along {along} m/s");
        assert!(p.trace() - along * along < 25.0, "across {} m/s", (p.trace() - along * along).sqrt());
        // Off (0), the velocity is as sure as without the glitch, 100 m/s
        // off: tens of its sigmas.
        let off = run(errors(), &imu, 12.0);
        let quiet = run(errors(), &clean, 12.0);
        assert_eq!(off.accel_jumps(), 0);
        let vel_var = |f: &InsFilter| f.covariance.fixed_view::<3, 3>(VEL, VEL).trace();
        assert!(
            (vel_var(&off) / vel_var(&quiet) - 1.0).abs() < 0.05,
            "{} {}",
            vel_var(&off),
            vel_var(&quiet)
        );
        assert!(vel_var(&off).sqrt() < glitch / 20.0, "{}", vel_var(&off).sqrt());
        // 500 m/s^2 for 1 s is doubted by ACCEL_JUMP_MAX_M_S at most.
        for s in imu.iter_mut().filter(|s| s.t > 10.0 && s.t < 11.0 + 1e-9) {
            s.f_imu_m_s2 = s.f_imu_m_s2.map(|f| f + Vector3::x() * 400.0);
        }
        let f = run(watching, &imu, 12.0);
        let p = f.covariance.fixed_view::<3, 3>(VEL, VEL);
        let doubt = p.symmetric_eigenvalues().max().sqrt();
        assert!((doubt - ACCEL_JUMP_MAX_M_S).abs() < 1.0, "{doubt}");
    }

    #[test]
    fn a_gap_in_the_imu_log_is_crossed_on_interpolated_rates_and_doubted() {
        // A body spun up about its z axis, w(t) = w0 + alpha t (0.1 rad/s,
        // 0.2 rad/s^2), gyro samples at 100 Hz (each the mean rate over its
        // interval) but none between 1 and 3 s; no accelerometer.
        let (w0, alpha, dt) = (0.1, 0.2, 0.01);
        let imu: Vec<ImuSample> = (0..=500)
            .map(|k| k as f64 * dt)
            .filter(|t| !(*t > 1.0 + 1e-9 && *t < 3.0 - 1e-9))
            .map(|t| ImuSample {
                t,
                w_imu_rad_s: Vector3::z() * (w0 + alpha * (t - 0.5 * dt)),
                f_imu_m_s2: None,
            })
            .collect();
        let start = Turn::new().state(0.0);
        let expected = |t: f64| {
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -EARTH_RATE_RAD_S * t)
                * start.q_ecef_imu
                * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), w0 * t + 0.5 * alpha * t * t)
        };
        let sigma = 3f64.to_radians();
        let gapped = InsErrors {
            imu_gap_s: 5.0 * dt,
            gap_rate_walk_rad_s_sqrt_s: sigma,
            gyro_max_jump_rad_s: 10f64.to_radians(),
            ..errors()
        };
        let run = |errors: InsErrors, times: &[f64]| {
            let mut f = InsFilter::new(start, &init(), errors);
            for &t in times {
                f.propagate(t, &imu);
            }
            f
        };
        let att_err =
            |f: &InsFilter, t: f64| rotation_vector(&(expected(t) * f.state.q_ecef_imu.inverse())).norm();
        // The variance about the spin axis (the rate's error, a walk in the
        // body, turns with it about the others).
        let spin_axis = start.q_ecef_imu * Vector3::z();
        let att_var = |f: &InsFilter| {
            (spin_axis.transpose() * f.covariance.fixed_view::<3, 3>(ATT, ATT) * spin_axis)[(0, 0)]
        };
        // Interpolated, the spin-up is followed through the gap but for the
        // samples' half-interval lag (alpha dt / 2 over 2 s: 2e-3 rad); the
        // sample after the gap taken as the mean rate through it, in one
        // step (the gap not recognised), leaves it 2 alpha = 0.4 rad off and
        // more (the second-order increment over 1.4 rad adds 0.1), and its
        // 23 deg/s step from the sample before reads as a gyro jump.
        let crossed = run(gapped, &[4.0]);
        assert!(att_err(&crossed, 4.0) < 2.5e-3, "{}", att_err(&crossed, 4.0));
        // Through the gap the bias state stood for the interpolated rate's
        // error; after it, the gyro's bias is back as it was.
        let mid_gap = run(gapped, &[2.0]);
        assert!(mid_gap.covariance[(GYRO_BIAS, GYRO_BIAS)] > 0.5 * sigma * sigma);
        assert_eq!(crossed.state.gyro_bias_imu_rad_s, start.gyro_bias_imu_rad_s);
        let bias_var = |f: &InsFilter| f.covariance.fixed_view::<3, 3>(GYRO_BIAS, GYRO_BIAS).into_owned();
        assert_eq!(bias_var(&crossed), bias_var(&run(gapped, &[1.0])));
        assert_eq!(mid_gap.gyro_bias_with_covariance().1, bias_var(&run(gapped, &[1.0])));
        assert_eq!(crossed.gyro_jumps(), 0);
        let blind = run(InsErrors { imu_gap_s: 0.0, ..gapped }, &[4.0]);
        assert!(att_err(&blind, 4.0) > 2.0 * alpha, "{}", att_err(&blind, 4.0));
        assert_eq!(blind.gyro_jumps(), 1);
        // The attitude's variance per axis grows by sigma^2 tau^3 / 3, tau
        // into the gap, whether the gap is crossed in one call or in frames.
        let quiet = run(InsErrors { gap_rate_walk_rad_s_sqrt_s: 0.0, ..gapped }, &[1.8, 2.6, 4.0]);
        for times in [&[1.8, 2.6, 4.0][..], &[4.0][..]] {
            let f = run(gapped, times);
            let added = att_var(&f) - att_var(&quiet);
            let model = sigma * sigma * 8.0 / 3.0;
            assert!((added / model - 1.0).abs() < 0.01, "{times:?}: {added} against {model}");
            assert!((att_err(&f, 4.0) - att_err(&crossed, 4.0)).abs() < 1e-9);
        }
        let mid = run(gapped, &[2.0]);
        let added =
            att_var(&mid) - att_var(&run(InsErrors { gap_rate_walk_rad_s_sqrt_s: 0.0, ..gapped }, &[2.0]));
        // (A flush per 10 ms step of the gap: the rate's walk reaches the
        // attitude one step late, 1.5% of 100 steps.)
        assert!((added / (sigma * sigma / 3.0) - 1.0).abs() < 0.02, "{added}");
        // Up to IMU_GAP_MAX_ANGLE_DEG per axis; a fix in the gap shrinks
        // it, and the gap grows it again.
        // (The largest axis's: the rate's doubt stops adding to the
        // attitude's at the step that reaches the cap, 0.3 deg at most at
        // 30 deg/s.)
        let wild = InsErrors { gap_rate_walk_rad_s_sqrt_s: 1.0, ..gapped };
        let sigma_deg = |f: &InsFilter| {
            (0..3).map(|j| f.covariance[(ATT + j, ATT + j)]).fold(0.0, f64::max).sqrt().to_degrees()
        };
        let at_cap = |f: &InsFilter| (0.0..0.35).contains(&(sigma_deg(f) - IMU_GAP_MAX_ANGLE_DEG));
        assert!(at_cap(&run(wild, &[4.0])), "{}", sigma_deg(&run(wild, &[4.0])));
        let mut f = run(wild, &[2.0]);
        assert!(at_cap(&f), "{}", sigma_deg(&f));
        let q_imu_cam = UnitQuaternion::identity();
        let fix = CameraPose::new(f.state.position, expected(2.0));
        let r = Matrix6::from_diagonal(&Vector6::new(1e-8, 1e-8, 1e-8, 25.0, 25.0, 25.0));
        f.update_with_pose(&q_imu_cam, &fix, &r).unwrap();
        assert!(sigma_deg(&f) < 0.01, "{}", sigma_deg(&f));
        f.propagate(2.5, &imu);
        assert!(at_cap(&f), "{}", sigma_deg(&f));
    }

    #[test]
    fn time_outside_the_imu_log_is_doubted_as_a_gap_from_its_edge_or_turned_at_the_last_rate() {
        // Gyro samples at 100 Hz from 1 to 3 s only (a log that starts late
        // and ends early); no accelerometer.
        let dt = 0.01;
        let imu: Vec<ImuSample> = (100..=300)
            .map(|k| ImuSample { t: k as f64 * dt, w_imu_rad_s: Vector3::z() * 0.1, f_imu_m_s2: None })
            .collect();
        let sigma = 3f64.to_radians();
        let gapped = InsErrors { imu_gap_s: 5.0 * dt, gap_rate_walk_rad_s_sqrt_s: sigma, ..errors() };
        let quiet_errors = InsErrors { gap_rate_walk_rad_s_sqrt_s: 0.0, ..gapped };
        let att_var = |f: &InsFilter| f.covariance.fixed_view::<3, 3>(ATT, ATT).trace() / 3.0;
        let run = |errors: InsErrors, times: &[f64]| {
            let mut f = InsFilter::new(Turn::new().state(0.0), &init(), errors);
            for &t in times {
                f.propagate(t, &imu);
            }
            f
        };
        // Before the first sample (its interval reaches back to 0.99 s):
        // no rate, its error walking from the filter's start, sigma^2 tau^3
        // / 3, in one call or in frames (within the 1.5% the walk reaches
        // the attitude a 10 ms step late). At the log's first sample the
        // gyro's bias comes back.
        for times in [&[0.99][..], &[0.5, 0.99][..]] {
            let f = run(gapped, times);
            let added = att_var(&f) - att_var(&run(quiet_errors, times));
            let model = sigma * sigma * 0.99f64.powi(3) / 3.0;
            assert!((added / model - 1.0).abs() < 0.02, "{times:?}: {added} against {model}");
            let held = run(InsErrors { imu_gap_s: 0.0, ..gapped }, times).state.q_ecef_imu;
            assert!(f.state.q_ecef_imu.angle_to(&held) < 1e-9);
        }
        let in_log = run(gapped, &[2.0]);
        assert_eq!(in_log.gyro_bias_with_covariance(), run(gapped, &[0.0]).gyro_bias_with_covariance());
        assert!(in_log.covariance[(GYRO_BIAS, GYRO_BIAS)] < 1e-6 * sigma * sigma);
        // Inside the log, nothing more. After its last sample the attitude
        // turns on at the last rate measured, and the rate's walk adds
        // sigma^2 tau^3 / 3 from there.
        let inside = att_var(&run(gapped, &[3.0])) - att_var(&run(quiet_errors, &[3.0]));
        let after = att_var(&run(gapped, &[3.0, 4.0])) - att_var(&run(quiet_errors, &[3.0, 4.0]));
        assert!(((after - inside) / (sigma * sigma / 3.0) - 1.0).abs() < 0.03, "{inside} {after}");
        let (at_end, later) = (run(gapped, &[3.0]), run(gapped, &[3.0, 4.0]));
        let earth = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -EARTH_RATE_RAD_S);
        let want = earth * at_end.state.q_ecef_imu * UnitQuaternion::from_scaled_axis(Vector3::z() * 0.1);
        assert!(want.angle_to(&later.state.q_ecef_imu) < 1e-7, "{}", want.angle_to(&later.state.q_ecef_imu));
        // The report's gyro bias is the one at the log's end.
        assert_eq!(later.gyro_bias_with_covariance(), at_end.gyro_bias_with_covariance());
        // Two states across it are no track pair (the turn is not measured).
        let f = run(gapped, &[3.0, 4.0]);
        assert!((f.gap_crossed_s - (0.99 + 1.0)).abs() < 1e-9, "{}", f.gap_crossed_s);
        // Up to IMU_GAP_MAX_ANGLE_DEG on the largest axis (and one 10 ms
        // step's growth), however long.
        let f = run(InsErrors { gap_rate_walk_rad_s_sqrt_s: 1.0, ..gapped }, &[3.0, 30.0]);
        let largest =
            (0..3).map(|j| f.covariance[(ATT + j, ATT + j)]).fold(0.0, f64::max).sqrt().to_degrees();
        assert!((0.0..0.35).contains(&(largest - IMU_GAP_MAX_ANGLE_DEG)), "{largest}");
    }

    #[test]
    fn the_rate_carried_on_is_the_logs_mean_over_its_last_second() {
        // 0.1 rad/s about z with a 3 Hz vibration of 0.5 rad/s about x, at
        // 400 Hz until 5.05 s (the last sample at the vibration's peak).
        let imu: Vec<ImuSample> = (0..=2020)
            .map(|k| k as f64 / 400.0)
            .map(|t| ImuSample {
                t,
                w_imu_rad_s: Vector3::new(
                    0.5 * (std::f64::consts::TAU * 3.0 * (t - 0.05) + 1.5).sin(),
                    0.0,
                    0.1,
                ),
                f_imu_m_s2: None,
            })
            .collect();
        let mean = mean_rate(&imu, 1.0);
        assert!((mean - Vector3::z() * 0.1).norm() < 0.01, "{mean}");
        assert!(imu.last().unwrap().w_imu_rad_s.x > 0.45);
        // A window longer than the log: its whole span; one sample: itself.
        assert!((mean_rate(&imu[..401], 10.0) - Vector3::z() * 0.1).norm() < 0.01);
        assert_eq!(mean_rate(&imu[..1], 1.0), imu[0].w_imu_rad_s);
        assert_eq!(mean_rate(&[], 1.0), Vector3::zeros());
    }

    #[test]
    fn after_the_imu_log_the_rate_is_learnt_from_the_fixes() {
        // The constant turn (0.1 rad/s) with a 2-degree pendulum (its rate
        // swings by 3.1 deg/s); the log ends at 10 s, and a fix of the
        // attitude (0.006 deg) and the position (5 m) comes every 0.5 s
        // until 20 s. Without a rate the attitude held between frames is
        // about 2.9 deg off at each (the turn); with the rate a state, the
        // prediction stays within a third of that and within its own
        // sigmas, and the rate is learnt.
        let turn = Turn { wobble_rad: 2f64.to_radians(), ..Turn::new() };
        let (imu, _, _) = turn.imu(100.0, 10.0, None);
        let errors = InsErrors { imu_gap_s: 0.05, gap_rate_walk_rad_s_sqrt_s: 3f64.to_radians(), ..errors() };
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors);
        let q_imu_cam = UnitQuaternion::identity();
        let r = Matrix6::from_diagonal(&Vector6::new(1e-8, 1e-8, 1e-8, 25.0, 25.0, 25.0));
        let mut rng = Rng::new(5);
        let mut draw = |sigma: f64| Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
        let mut worst_deg: f64 = 0.0;
        for k in 1..=40 {
            let t = k as f64 * 0.5;
            f.propagate(t, &imu);
            let truth = turn.at(t);
            let err = rotation_vector(&(truth.q * f.state.q_ecef_imu.inverse()));
            let p = f.covariance.fixed_view::<3, 3>(ATT, ATT).into_owned();
            let nees = (err.transpose() * p.try_inverse().unwrap() * err)[(0, 0)];
            if t > 11.0 {
                // Two fixes after the log's end have found the rate.
                worst_deg = worst_deg.max(err.norm().to_degrees());
                assert!(
                    nees < 3.0 * 16.0,
                    "t {t}: attitude {:.3} deg off, NEES {nees:.1}",
                    err.norm().to_degrees()
                );
            }
            let mut d = Vector6::zeros();
            d.fixed_rows_mut::<3>(0).copy_from(&draw(1e-4));
            d.fixed_rows_mut::<3>(3).copy_from(&draw(5.0));
            let fix = perturb(&CameraPose::new(Ecef(truth.p), truth.q * q_imu_cam), &d);
            f.update_with_pose(&q_imu_cam, &fix, &r).unwrap();
        }
        // The pendulum's swing between two frames is left (up to ~1 deg),
        // where holding the attitude misses by the whole turn.
        let held_deg = (23..=40)
            .map(|k| k as f64 * 0.5)
            .map(|t| turn.at(t).q.angle_to(&turn.at(t - 0.5).q).to_degrees())
            .fold(f64::INFINITY, f64::min);
        assert!(worst_deg < 1.1 && worst_deg < held_deg / 2.5, "{worst_deg} against {held_deg}");
        // The rate is the truth's to a fraction of its swing.
        let inertial =
            |t: f64| UnitQuaternion::from_axis_angle(&Vector3::z_axis(), EARTH_RATE_RAD_S * t) * turn.at(t).q;
        let true_rate = rotation_vector(&(inertial(19.99).inverse() * inertial(20.01))) / 0.02;
        f.propagate(20.001, &imu); // the state's rate is its last step's
        let rate = f.state.q_ecef_imu.inverse() * (f.state.rate_ecef_rad_s + Vector3::z() * EARTH_RATE_RAD_S);
        let off = (rate - true_rate).norm().to_degrees();
        assert!(off < 1.0, "rate {off} deg/s off");
    }

    #[test]
    fn the_covariance_follows_the_errors_through_propagation_and_updates() {
        // Monte Carlo over noisy IMUs with random biases and a wrong start
        // drawn from the initial covariance: a pose fix each second (noise
        // drawn from its covariance) updates the filter. The NEES of
        // [attitude; position; velocity] (9 dof) averaged over runs and
        // epochs is near 9, and the biases are learnt as the body turns.
        let turn = Turn::new();
        let (e, i) = (errors(), init());
        let runs = 12;
        let (mut nees, mut count) = (0.0, 0);
        let mut bias_err = 0.0;
        let q_imu_cam = UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3);
        for run in 0..runs {
            let (imu, bg, ba) = turn.imu(100.0, 31.0, Some((&e, &i, run + 1)));
            let mut rng = Rng::new(1000 + run);
            let mut draw = |sigma: f64| Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
            let mut start = turn.state(0.0);
            start.q_ecef_imu = UnitQuaternion::from_scaled_axis(draw(i.attitude_rad)) * start.q_ecef_imu;
            start.position.0 += draw(i.position_m);
            start.velocity_ecef_m_s += draw(i.velocity_m_s);
            let mut f = InsFilter::new(start, &i, e);
            let r = Matrix6::from_diagonal(&Vector6::new(1e-8, 1e-8, 1e-8, 25.0, 25.0, 25.0));
            for k in 1..=30 {
                let t = k as f64;
                f.propagate(t, &imu);
                let truth = turn.at(t);
                let err = error9(&f.state, &truth);
                let p9 = f.covariance.fixed_view::<9, 9>(0, 0).into_owned();
                nees += (err.transpose() * p9.try_inverse().unwrap() * err)[(0, 0)];
                count += 1;
                let true_cam = CameraPose::new(Ecef(truth.p), truth.q * q_imu_cam);
                let mut d = Vector6::zeros();
                d.fixed_rows_mut::<3>(0).copy_from(&draw(1e-4));
                d.fixed_rows_mut::<3>(3).copy_from(&draw(5.0));
                let chi2 = f.update_with_pose(&q_imu_cam, &perturb(&true_cam, &d), &r).unwrap();
                assert!(chi2 < 40.0, "run {run} t {t}: chi2 {chi2}");
            }
            bias_err += (f.state.gyro_bias_imu_rad_s - bg).norm() / bg.norm().max(1e-9);
            let _ = ba;
        }
        let nees = nees / count as f64;
        println!(
            "INS constant turn, {runs} runs: mean NEES {nees:.2} (9 dof), gyro bias error {:.0}% of the bias",
            100.0 * bias_err / runs as f64
        );
        assert!((5.0..14.0).contains(&nees), "{nees}");
        assert!(bias_err / (runs as f64) < 0.5, "{}", bias_err / runs as f64);
    }

    #[test]
    fn the_time_offset_converges_on_a_known_offset() {
        // Images exposed 5 ms after their stamp during the turn (200 m/s)
        // with a 5-degree pendulum (up to 7.9 deg/s): each noisy fix (0.006
        // deg, 5 m) is the pose 5 ms later. (In a steady turn the offset's
        // constant rotation would pass for an attitude error.)
        let turn = Turn { wobble_rad: 5f64.to_radians(), ..Turn::new() };
        let (e, mut i) = (errors(), init());
        i.time_offset_s = 0.01;
        let (imu, _, _) = turn.imu(100.0, 31.0, Some((&e, &i, 7)));
        let mut f = InsFilter::new(turn.state(0.0), &i, e);
        let q_imu_cam = UnitQuaternion::identity();
        let mut rng = Rng::new(8);
        let mut draw = |sigma: f64| Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
        let r = Matrix6::from_diagonal(&Vector6::new(1e-8, 1e-8, 1e-8, 25.0, 25.0, 25.0));
        let tau = 0.005;
        for k in 1..=60 {
            let t = 0.5 * k as f64;
            f.propagate(t, &imu);
            let truth = turn.at(t + tau);
            let mut d = Vector6::zeros();
            d.fixed_rows_mut::<3>(0).copy_from(&draw(1e-4));
            d.fixed_rows_mut::<3>(3).copy_from(&draw(5.0));
            let seen = perturb(&CameraPose::new(Ecef(truth.p), truth.q), &d);
            f.update_with_pose(&q_imu_cam, &seen, &r).unwrap();
        }
        let (est, sigma) = f.time_offset();
        println!("time offset {:.2} ms +- {:.2} ms (truth 5 ms)", est * 1e3, sigma * 1e3);
        assert!(sigma < 1e-3, "{sigma}");
        assert!((est - tau).abs() < 3.0 * sigma, "{est} {sigma}");
        // The reported pose is the one at the stamp.
        let err = (f.state.position.0 - turn.at(30.0).p).norm();
        assert!(err < 10.0, "{err} m");
    }

    /// Conditions `f` on a pose `seen` with covariance `r`: the Kalman
    /// posterior of the apparent pose, as the tight navigator's refinement
    /// with the prediction as its prior, through `sensitivity`.
    fn condition_on_seen(
        f: &mut InsFilter,
        q_imu_cam: &UnitQuaternion<f64>,
        seen: &CameraPose,
        r: &Matrix6<f64>,
        sensitivity: &IntrinsicsSensitivity,
    ) {
        let (pred, m) = f.apparent_pose_with(q_imu_cam, sensitivity);
        let s_inv = (m + r).try_inverse().unwrap();
        let posterior = perturb(&pred, &(m * s_inv * pose_difference(seen, &pred)));
        let post_cov = m - m * s_inv * m;
        assert!(f.condition_on_pose_with(
            q_imu_cam,
            &posterior,
            &((post_cov + post_cov.transpose()) * 0.5),
            sensitivity
        ));
    }

    #[test]
    fn the_focal_length_is_learnt_where_the_boresight_turns_and_a_nadir_view_needs_relief() {
        // Images solved with a focal length 0.3% short see the terrain 0.3%
        // of the range closer, along the boresight `b`: the pose that
        // corrects the focal length moves by `S = [0; -b R]` per unit. On
        // the 2 km turn (2 g sideways, exact IMU but for noise and biases)
        // a camera 30 degrees off nadir turns its boresight with the body:
        // the apparent position circles with it, which the accelerometer
        // tells from a position error. A nadir camera's offset stays
        // vertical: a position error as good as a focal one, until the
        // relief says which (a direct measurement of the focal length),
        // and then the position follows it by their correlation.
        let turn = Turn::new();
        let (e, mut i) = (errors(), init());
        i.focal_rel = 0.005;
        // Where the vehicle is, the images alone say.
        i.position_m = 1000.0;
        let (imu, _, _) = turn.imu(100.0, 61.0, Some((&e, &i, 11)));
        let focal_true = 0.003;
        let run = |tilt_deg: f64| -> InsFilter {
            let q_imu_cam = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), tilt_deg.to_radians());
            let range = 30_000.0 / tilt_deg.to_radians().cos();
            let mut f = InsFilter::new(turn.state(0.0), &i, e);
            let mut rng = Rng::new(12);
            let mut draw = |sigma: f64| Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
            let r = Matrix6::from_diagonal(&Vector6::new(1e-8, 1e-8, 1e-8, 25.0, 25.0, 25.0));
            for k in 1..=60 {
                let t = k as f64;
                f.propagate(t, &imu);
                let truth = turn.at(t);
                let cam = CameraPose::new(Ecef(truth.p), truth.q * q_imu_cam);
                let b = cam.q_ecef_cam * Vector3::z();
                let mut s = SMatrix::<f64, 6, 3>::zeros();
                s.set_column(0, &(Vector6::new(0.0, 0.0, 0.0, -b.x, -b.y, -b.z) * range));
                let sensitivity = IntrinsicsSensitivity(s);
                let mut d = Vector6::zeros();
                d.fixed_rows_mut::<3>(0).copy_from(&draw(1e-4));
                d.fixed_rows_mut::<3>(3).copy_from(&(draw(5.0) + b * (range * focal_true)));
                let seen = perturb(&cam, &d);
                condition_on_seen(&mut f, &q_imu_cam, &seen, &r, &sensitivity);
            }
            f
        };
        let mut oblique = run(30.0);
        let (est, var) = oblique.take_focal_error();
        println!(
            "focal error, 30 deg off nadir: {:+.4}% +- {:.4}% (truth +0.3%)",
            est * 100.0,
            var.sqrt() * 100.0
        );
        assert!(var.sqrt() < 0.0005 && (est - focal_true).abs() < 3.0 * var.sqrt(), "{est} {}", var.sqrt());
        assert_eq!(oblique.focal_error_rel, 0.0, "taken");
        let pos_err = (oblique.state.position.0 - turn.at(60.0).p).norm();
        assert!(pos_err < 15.0, "{pos_err} m");

        let mut nadir = run(0.0);
        let sigma = nadir.covariance[(FOCAL, FOCAL)].sqrt();
        let pos_err = |f: &InsFilter| (f.state.position.0 - turn.at(60.0).p).norm();
        let before = pos_err(&nadir);
        println!(
            "focal error, nadir: {:+.4}% +- {:.4}%, position {before:.1} m off",
            nadir.focal_error_rel * 100.0,
            sigma * 100.0
        );
        assert!(sigma > 0.004, "a nadir view on a level turn says nothing of the focal length: {sigma}");
        // The relief's say: the focal length to 0.01%.
        assert!(nadir.focal_measurement(focal_true, 1e-8));
        let after = pos_err(&nadir);
        println!("after a direct focal measurement: {after:.1} m off");
        assert!(before > 40.0 && after < 15.0, "{before} -> {after} m");
        assert!(!InsFilter::new(turn.state(0.0), &init(), e).focal_measurement(0.003, 1e-8), "not a state");
    }

    #[test]
    fn the_principal_point_is_learnt_where_the_camera_turns_about_its_boresight() {
        // A principal point off by `dc` pixels makes every frame solved with
        // the nominal camera look tilted by `(dv, -du) / f` about the
        // camera's own x and y axes: apparent = true - S dc with
        // `S = [R_ecef_cam [0, -1/f; 1/f, 0; 0, 0]; 0]`. On the
        // constant turn a nadir camera turns about its boresight, 344
        // degrees in 60 s: the tilt turns with it in ECEF, which an attitude
        // error (carried by the gyro) does not. The attitude is known to 2
        // degrees only, so the first frames cannot tell the tilt from it.
        let turn = Turn::new();
        let (e, mut i) = (errors(), init());
        i.attitude_rad = 2f64.to_radians();
        i.position_m = 1000.0;
        let (imu, _, _) = turn.imu(100.0, 61.0, Some((&e, &i, 13)));
        let (f_px, dc_true) = (1000.0, Vector2::new(1.5, -1.0));
        let run = |principal_px: f64| -> (InsFilter, f64, f64) {
            let mut f = InsFilter::new(turn.state(0.0), &InsInit { principal_px, ..i }, e);
            let mut rng = Rng::new(14);
            let mut draw = |sigma: f64| Vector3::new(rng.normal(), rng.normal(), rng.normal()) * sigma;
            let r = Matrix6::from_diagonal(&Vector6::new(1e-8, 1e-8, 1e-8, 25.0, 25.0, 25.0));
            let mut sigma_after_2 = 0.0;
            for k in 1..=60 {
                let t = k as f64;
                f.propagate(t, &imu);
                let truth = turn.at(t);
                let cam = CameraPose::new(Ecef(truth.p), truth.q);
                let r_ecef_cam = cam.q_ecef_cam.to_rotation_matrix().into_inner();
                let mut s = SMatrix::<f64, 6, 3>::zeros();
                s.fixed_view_mut::<3, 1>(0, 1).copy_from(&(r_ecef_cam * Vector3::new(0.0, 1.0 / f_px, 0.0)));
                s.fixed_view_mut::<3, 1>(0, 2).copy_from(&(r_ecef_cam * Vector3::new(-1.0 / f_px, 0.0, 0.0)));
                let sensitivity = IntrinsicsSensitivity(s);
                let mut d = Vector6::zeros();
                let tilt = r_ecef_cam * Vector3::new(dc_true.y / f_px, -dc_true.x / f_px, 0.0);
                d.fixed_rows_mut::<3>(0).copy_from(&(draw(1e-4) + tilt));
                d.fixed_rows_mut::<3>(3).copy_from(&draw(5.0));
                // apparent - true = -S dc
                assert!((tilt + s.fixed_view::<3, 2>(0, 1) * dc_true).norm() < 1e-15);
                let seen = perturb(&cam, &d);
                condition_on_seen(&mut f, &UnitQuaternion::identity(), &seen, &r, &sensitivity);
                if k == 2 {
                    sigma_after_2 = f.covariance[(PRINCIPAL, PRINCIPAL)].sqrt();
                }
            }
            let att_err = rotation_vector(&(turn.at(60.0).q * f.state.q_ecef_imu.inverse())).norm();
            (f, att_err, sigma_after_2)
        };
        let (mut with, att_with, sigma_2) = run(3.0);
        assert!(with.estimates_principal_point());
        let (est, cov) = with.take_principal_error();
        let sigma = Vector2::new(cov[(0, 0)].sqrt(), cov[(1, 1)].sqrt());
        println!(
            "principal point: {:+.3} {:+.3} px +- {:.3} {:.3} (truth +1.5 -1.0; +- {sigma_2:.2} after 2 frames), attitude {:.3} mrad off",
            est.x,
            est.y,
            sigma.x,
            sigma.y,
            att_with * 1e3
        );
        let (without, att_without, _) = run(0.0);
        assert!(!without.estimates_principal_point());
        println!("attitude without the state: {:.3} mrad off", att_without * 1e3);
        assert!(sigma_2 > 1.0, "two frames cannot tell the tilt from the attitude: {sigma_2}");
        // From 3 px to under 0.6 (the gyro's 10 deg/h bias, fixed in the
        // body, also turns with it: the rest of the ambiguity).
        assert!(sigma.max() < 0.6, "{sigma}");
        assert!(((est - dc_true).component_div(&sigma)).abs().max() < 3.0, "{est} {sigma}");
        assert_eq!(with.principal_error_px, Vector2::zeros(), "taken");
        // Without the state the attitude follows the tilt (1.8 mrad).
        assert!(att_with < 0.5 * att_without && att_without > 1.5e-3, "{att_with} {att_without}");
    }

    /// Each state's scale for [`random_covariance`] (rad, m, m/s, rad/s,
    /// m/s^2, m, s, then 1e-3 for the rest).
    fn test_sigma(i: usize) -> f64 {
        match i {
            TIME => 0.01,
            MAP_ATT.. => 1e-3,
            _ => [1e-3, 10.0, 1.0, 1e-5, 0.01, 10.0][i / 3],
        }
    }

    /// A random covariance (a seeded Wishart-like draw plus the identity)
    /// scaled by `sigma(i)` per state.
    fn random_covariance(seed: u64, sigma: impl Fn(usize) -> f64) -> Covariance {
        let mut rng = Rng::new(seed);
        let a = Covariance::from_fn(|_, _| rng.normal());
        let scale = Covariance::from_diagonal(&SMatrix::<f64, N, 1>::from_fn(|i, _| sigma(i)));
        scale * (a * a.transpose() / N as f64 + Covariance::identity()) * scale
    }

    #[test]
    fn conditioning_on_a_pose_posterior_is_the_kalman_update() {
        // update_with_pose goes through condition_on_pose; check it against
        // the textbook update with H = [I6 0 ...] (map offset on), P random.
        let turn = Turn::new();
        let mut e = errors();
        e.map_sigma_m = 15.0;
        e.map_tau_s = 20.0;
        e.map_att_sigma_rad = 1e-3;
        let mut f = InsFilter::new(turn.state(0.0), &init(), e);
        f.covariance = random_covariance(3, test_sigma);
        f.state.rate_ecef_rad_s = Vector3::new(0.1, -0.05, 0.2);
        f.state.time_offset_s = 0.003;
        let q_imu_cam = UnitQuaternion::identity();
        let (pred, _) = f.apparent_pose(&q_imu_cam);
        let y = Vector6::new(2e-4, -1e-4, 3e-4, 12.0, -7.0, 4.0);
        let r = Matrix6::from_diagonal(&Vector6::new(1e-7, 1e-7, 1e-7, 30.0, 30.0, 30.0));
        let h = f.pose_rows_with(&IntrinsicsSensitivity::NONE);
        let p = f.covariance;
        let s = h * p * h.transpose() + r;
        let k = p * h.transpose() * s.try_inverse().unwrap();
        let want_p = (Covariance::identity() - k * h) * p;
        let want_dx = k * y;
        let before = f.state;
        let mut g = f.clone();
        g.update_with_pose(&q_imu_cam, &perturb(&pred, &y), &r).unwrap();
        assert!((g.covariance - want_p).norm() < 1e-9 * want_p.norm(), "covariance");
        let dv = g.state.velocity_ecef_m_s - before.velocity_ecef_m_s;
        let want_dv = want_dx.fixed_rows::<3>(VEL).into_owned();
        assert!((dv - want_dv).norm() < 1e-6 * want_dv.norm().max(1e-9), "{dv} {want_dv}");
        let dm = g.state.map_offset_ecef_m - before.map_offset_ecef_m;
        assert!((dm - want_dx.fixed_rows::<3>(MAP)).norm() < 1e-6 * dm.norm().max(1e-9));
        let dma = g.state.map_offset_att_rad - before.map_offset_att_rad;
        assert!((dma - want_dx.fixed_rows::<3>(MAP_ATT)).norm() < 1e-6 * dma.norm().max(1e-12));
        let dbg = g.state.gyro_bias_imu_rad_s - before.gyro_bias_imu_rad_s;
        assert!((dbg - want_dx.fixed_rows::<3>(GYRO_BIAS)).norm() < 1e-6 * dbg.norm().max(1e-12));
    }

    #[test]
    fn a_pose_update_that_does_not_learn_the_principal_point_is_schmidts() {
        // With `principal_from_fixes` off, conditioning on a pose is the
        // textbook update with the principal point's gain rows zeroed and
        // the covariance of that gain (Joseph's form): the principal point
        // and its variance stay, the rest move by the gain that counts its
        // uncertainty.
        let turn = Turn::new();
        let mut i = init();
        i.focal_rel = 0.005;
        i.principal_px = 3.0;
        let mut f = InsFilter::new(turn.state(0.0), &i, errors());
        f.covariance = random_covariance(5, |i| match i {
            FOCAL => 0.005,
            PRINCIPAL.. => 3.0,
            _ => test_sigma(i),
        });
        f.principal_from_fixes = false;
        let sens = IntrinsicsSensitivity(SMatrix::<f64, 6, 3>::from_fn(|r, c| {
            let v = ((r * 3 + c) as f64 * 1.3).sin();
            if r < 3 {
                v * 1e-4
            } else {
                v * 10.0
            }
        }));
        let q_imu_cam = UnitQuaternion::identity();
        let (pred, m) = f.apparent_pose_with(&q_imu_cam, &sens);
        let y = Vector6::new(2e-4, -1e-4, 3e-4, 12.0, -7.0, 4.0);
        let r = Matrix6::from_diagonal(&Vector6::new(1e-7, 1e-7, 1e-7, 30.0, 30.0, 30.0));
        let s_inv = (m + r).try_inverse().unwrap();
        let post_cov = m - m * s_inv * m;
        let posterior = perturb(&pred, &(m * s_inv * y));
        let h = f.pose_rows_with(&sens);
        let p = f.covariance;
        let mut k = p * h.transpose() * s_inv;
        k.fixed_rows_mut::<2>(PRINCIPAL).fill(0.0);
        let i_kh = Covariance::identity() - k * h;
        let want_p = i_kh * p * i_kh.transpose() + k * r * k.transpose();
        let want_dx = k * y;
        let before = f.clone();
        assert!(f.condition_on_pose_with(&q_imu_cam, &posterior, &post_cov, &sens));
        assert!((f.covariance - want_p).norm() < 1e-9 * want_p.norm(), "covariance");
        let pp = |g: &InsFilter| g.covariance.fixed_view::<2, 2>(PRINCIPAL, PRINCIPAL).into_owned();
        assert!((pp(&f) - pp(&before)).norm() < 1e-9 * pp(&before).norm());
        assert_eq!(f.principal_error_px, before.principal_error_px);
        let dv = f.state.velocity_ecef_m_s - before.state.velocity_ecef_m_s;
        let want_dv = want_dx.fixed_rows::<3>(VEL).into_owned();
        assert!((dv - want_dv).norm() < 1e-6 * want_dv.norm(), "{dv} {want_dv}");
        assert!((f.focal_error_rel - want_dx[FOCAL]).abs() < 1e-6 * want_dx[FOCAL].abs().max(1e-12));
        // Learnt from fixes (the default), the same update moves it.
        let mut g = before.clone();
        g.principal_from_fixes = true;
        assert!(g.condition_on_pose_with(&q_imu_cam, &posterior, &post_cov, &sens));
        assert!(g.principal_error_px.norm() > 0.0 && pp(&g).trace() < pp(&before).trace());
    }

    #[test]
    fn a_velocity_doubted_without_bound_restarts_as_the_guess() {
        let turn = Turn::new();
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors());
        let (imu, _, _) = turn.imu(100.0, 10.0, None);
        // Frames of doubt: the pose's sigmas doubled 20 times, carried by
        // the propagation into the velocity's.
        for k in 1..=20 {
            f.inflate_pose_within(2.0, f64::INFINITY, f64::INFINITY);
            f.propagate(0.5 * k as f64, &imu);
        }
        let worst = (VEL..VEL + 3).map(|i| f.covariance[(i, i)].sqrt()).fold(0.0, f64::max);
        assert!(worst > 1e4, "{worst} m/s");
        // Within the bound: nothing changes.
        let mut g = f.clone();
        assert!(!g.forget_velocity_beyond(2.0 * worst));
        assert_eq!(g, f);
        let before = f.covariance;
        assert!(f.forget_velocity_beyond(300.0));
        assert_eq!(f.state.velocity_ecef_m_s, Vector3::zeros());
        for i in 0..N {
            for j in VEL..VEL + 3 {
                let want = if i == j { 300.0 * 300.0 } else { 0.0 };
                assert_eq!(f.covariance[(i, j)], want, "{i} {j}");
            }
        }
        assert_eq!(f.covariance.fixed_view::<6, 6>(ATT, ATT), before.fixed_view::<6, 6>(ATT, ATT));
    }

    #[test]
    fn a_doubt_grown_frame_by_frame_stops_at_its_bound() {
        let turn = Turn::new();
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors());
        let (imu, _, _) = turn.imu(100.0, 60.0, None);
        let sigma =
            |f: &InsFilter, at: usize| (at..at + 3).map(|i| f.covariance[(i, i)].sqrt()).fold(0.0, f64::max);
        let (max_att, max_pos) = (20f64.to_radians(), 20_000.0);
        let (att0, pos0) = (sigma(&f, ATT), sigma(&f, POS));
        // The first frame doubles both.
        let (ka, kp) = f.inflate_pose_within(2.0, max_att, max_pos);
        assert_eq!((ka, kp), (2.0, 2.0));
        assert!((sigma(&f, ATT) - 2.0 * att0).abs() < 1e-12 && (sigma(&f, POS) - 2.0 * pos0).abs() < 1e-9);
        // 100 frames of doubt: bounded where doubling alone gave 2^100.
        for k in 1..=100 {
            f.inflate_pose_within(2.0, max_att, max_pos);
            f.propagate(0.5 * k as f64, &imu);
        }
        let (att, pos, vel) = (sigma(&f, ATT), sigma(&f, POS), sigma(&f, VEL));
        assert!(att <= 1.2 * max_att && att >= max_att, "attitude sigma {} deg", att.to_degrees());
        // The position's own growth (the velocity's uncertainty over 50 s)
        // goes on; the doubling stops at its bound.
        assert!(pos >= max_pos && pos < 1e6, "position sigma {pos} m");
        assert!(vel.is_finite() && vel < 1e4, "velocity sigma {vel} m/s");
        // Beyond the bound, nothing is scaled (and nothing shrinks).
        let mut g = f.clone();
        let (ka, kp) = g.inflate_pose_within(2.0, 0.1 * max_att, 0.1 * max_pos);
        assert_eq!((ka, kp), (1.0, 1.0));
        assert_eq!(g, f);
    }

    #[test]
    fn inflating_keeps_correlations_and_a_reset_takes_the_fix() {
        let turn = Turn::new();
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors());
        let (imu, _, _) = turn.imu(100.0, 3.0, None);
        f.propagate(2.0, &imu);
        let before = f.covariance;
        f.inflate(2.0);
        assert!((f.covariance[(POS, POS)] - 4.0 * before[(POS, POS)]).abs() < 1e-9 * before[(POS, POS)]);
        assert!(
            (f.covariance[(POS, VEL)] - 4.0 * before[(POS, VEL)]).abs() <= 1e-9 * before[(POS, VEL)].abs()
        );
        assert_eq!(f.covariance[(GYRO_BIAS, GYRO_BIAS)], before[(GYRO_BIAS, GYRO_BIAS)]);
        // The pose alone: the velocity's block stays, its correlations with
        // the pose scale once.
        let mut g = f.clone();
        let inflated = f.covariance;
        g.inflate_pose_within(3.0, f64::INFINITY, f64::INFINITY);
        assert!(
            (g.covariance[(ATT + 1, ATT + 1)] - 9.0 * inflated[(ATT + 1, ATT + 1)]).abs()
                < 1e-9 * inflated[(ATT + 1, ATT + 1)]
        );
        assert!(
            (g.covariance[(POS, POS + 2)] - 9.0 * inflated[(POS, POS + 2)]).abs()
                <= 1e-9 * inflated[(POS, POS + 2)].abs()
        );
        assert!(
            (g.covariance[(POS, VEL)] - 3.0 * inflated[(POS, VEL)]).abs()
                <= 1e-9 * inflated[(POS, VEL)].abs()
        );
        assert_eq!(g.covariance.fixed_view::<3, 3>(VEL, VEL), inflated.fixed_view::<3, 3>(VEL, VEL));
        assert!(inflated[(POS, VEL)].abs() > 0.0);
        // (The map offset is off: its block is zero.)
        assert!(f.covariance.fixed_view::<15, 15>(0, 0).into_owned().cholesky().is_some());
        let fix = CameraPose::new(Ecef(turn.at(2.0).p + Vector3::new(300.0, 0.0, 0.0)), turn.at(2.0).q);
        let cov = Matrix6::identity() * 100.0;
        f.reset_pose(&UnitQuaternion::identity(), &fix, &cov, 50.0, &IntrinsicsSensitivity::NONE);
        assert_eq!(f.state.position, fix.position);
        assert_eq!(f.covariance.fixed_view::<6, 6>(0, 0).into_owned(), cov);
        assert_eq!(f.covariance[(POS, VEL)], 0.0);
        assert!(f.covariance[(VEL, VEL)] >= 2500.0);
        // (The map offset is off: its block is zero.)
        assert!(f.covariance.fixed_view::<15, 15>(0, 0).into_owned().cholesky().is_some());
    }

    #[test]
    fn a_linear_update_is_the_dense_kalman_update_with_its_nuisance() {
        // Random covariance, rows and nuisance; the compressed update (many
        // rows) and the direct one (few rows) both match the Kalman update
        // of the state augmented with the nuisance, written out densely.
        let mut rng = Rng::new(7);
        let mut f = InsFilter::new(Turn::new().state(0.0), &init(), errors());
        let a = DMatrix::<f64>::from_fn(N, N, |_, _| rng.normal());
        f.covariance = Covariance::from_iterator((&a * a.transpose() / N as f64).iter().copied())
            + Covariance::identity() * 0.1;
        for m in [40, 6] {
            let h = DMatrix::<f64>::from_fn(m, N, |_, _| rng.normal());
            let g = DMatrix::<f64>::from_fn(m, 3, |_, _| rng.normal());
            let y = DVector::<f64>::from_fn(m, |_, _| 3.0 * rng.normal());
            let sigmas = [0.5, 1.0, 2.0];
            let u = f.linear_update(&h, Some((&g, &sigmas)), &y).expect("regular");
            // Dense: x_a = [x; n], P_a = diag(P, sigmas^2), R = I.
            let na = N + 3;
            let mut ha = DMatrix::<f64>::zeros(m, na);
            ha.columns_mut(0, N).copy_from(&h);
            ha.columns_mut(N, 3).copy_from(&g);
            let mut pa = DMatrix::<f64>::zeros(na, na);
            pa.view_mut((0, 0), (N, N)).copy_from(&f.covariance);
            for (i, s) in sigmas.iter().enumerate() {
                pa[(N + i, N + i)] = s * s;
            }
            let s_mat = &ha * &pa * ha.transpose() + DMatrix::<f64>::identity(m, m);
            let s_inv = s_mat.clone().try_inverse().unwrap();
            let k = &pa * ha.transpose() * &s_inv;
            let dx = &k * &y;
            let post = &pa - &k * &s_mat * k.transpose();
            let chi2 = y.dot(&(&s_inv * &y));
            for i in 0..N {
                assert!((u.dx[i] - dx[i]).abs() < 1e-9 * (1.0 + dx[i].abs()), "m {m} dx {i}");
                for j in 0..N {
                    assert!((u.covariance[(i, j)] - post[(i, j)]).abs() < 1e-9, "m {m} P {i} {j}");
                }
            }
            for i in 0..3 {
                assert!((u.nuisance[i] - dx[N + i]).abs() < 1e-9 * (1.0 + dx[N + i].abs()));
            }
            assert!((u.chi2 - chi2).abs() < 1e-8 * chi2, "m {m}: {} against {chi2}", u.chi2);
            assert_eq!(u.dof, m);
        }
        // Rows that do not fit the state are refused.
        let y = DVector::<f64>::zeros(4);
        assert!(f.linear_update(&DMatrix::zeros(4, N - 1), None, &y).is_none());
        assert!(f.linear_update(&DMatrix::zeros(4, N), Some((&DMatrix::zeros(4, 2), &[1.0])), &y).is_none());
    }

    #[test]
    fn the_map_offset_turns_the_pose_the_images_see() {
        // With an attitude map offset, the apparent pose is the true one
        // turned by it, the innovation's rows see it, and a reset to a fix
        // puts the apparent pose on the fix.
        let turn = Turn::new();
        let mut e = errors();
        e.map_att_sigma_rad = 0.1f64.to_radians();
        e.map_tau_s = 10.0;
        let mut f = InsFilter::new(turn.state(0.0), &init(), e);
        let m = Vector3::new(1e-3, -2e-3, 5e-4);
        f.state.map_offset_att_rad = m;
        let q = UnitQuaternion::identity();
        let (apparent, cov) = f.apparent_pose(&q);
        let (truth_pose, _) = f.pose(&q);
        let d = pose_difference(&apparent, &truth_pose);
        assert!((d.fixed_rows::<3>(0) - m).norm() < 1e-12, "{d}");
        // Its variance is in the apparent attitude's.
        let want = init().attitude_rad.powi(2) + e.map_att_sigma_rad.powi(2);
        assert!((cov[(0, 0)] - want).abs() < 1e-12 * want);
        // It decays over its correlation time, its variance stays.
        let (imu, _, _) = turn.imu(100.0, 11.0, None);
        f.propagate(10.0, &imu);
        let decayed = f.state.map_offset_att_rad;
        assert!((decayed - m * (-1.0f64).exp()).norm() < 1e-9, "{decayed} {}", m * (-1.0f64).exp());
        let v = f.covariance[(MAP_ATT, MAP_ATT)];
        assert!((v - e.map_att_sigma_rad.powi(2)).abs() < 0.01 * v, "{v}");
        let fix = CameraPose::new(Ecef(turn.at(10.0).p + Vector3::new(30.0, 0.0, 0.0)), turn.at(10.0).q);
        f.reset_pose(&q, &fix, &(Matrix6::identity() * 100.0), 10.0, &IntrinsicsSensitivity::NONE);
        let (apparent, _) = f.apparent_pose(&q);
        assert!(pose_difference(&apparent, &fix).norm() < 1e-9);
    }

    /// [`errors`] with the navigator's map offset: 40 m, 0.1 deg, 10 s.
    fn errors_with_map_offset() -> InsErrors {
        InsErrors { map_sigma_m: 40.0, map_att_sigma_rad: 0.1f64.to_radians(), map_tau_s: 10.0, ..errors() }
    }

    #[test]
    fn a_map_offset_beyond_its_prior_restarts_with_the_pose_the_images_see() {
        let turn = Turn::new();
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors_with_map_offset());
        let q = UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3);
        // 120 m and 0.3 deg: (120/40)^2 + (0.3/0.1)^2 = 18 in its prior's
        // sigmas.
        f.state.map_offset_ecef_m = Vector3::new(120.0, 0.0, 0.0);
        f.state.map_offset_att_rad = Vector3::new(0.0, 0.0, 0.3f64.to_radians());
        assert!((f.map_offset_distance() - 18.0).abs() < 1e-9, "{}", f.map_offset_distance());
        let (seen, _) = f.apparent_pose(&q);
        let (p_before, v_before) = (f.covariance[(POS, POS)], f.covariance[(VEL, VEL)]);
        f.restart_map_offset(2.0, 10.0);
        // The images' pose is kept; the offset is zero, at its prior.
        let (after, _) = f.apparent_pose(&q);
        assert!((after.position.0 - seen.position.0).norm() < 1e-6);
        assert!(rotation_vector(&(after.q_ecef_cam * seen.q_ecef_cam.inverse())).norm() < 1e-12);
        assert_eq!(f.map_offset_distance(), 0.0);
        let (pose, _) = f.pose(&q);
        assert!((pose.position.0 - seen.position.0).norm() < 1e-6, "the filter's pose is the images'");
        for i in 0..3 {
            assert!((f.covariance[(MAP + i, MAP + i)].sqrt() - 40.0).abs() < 1e-9);
            assert!((f.covariance[(MAP_ATT + i, MAP_ATT + i)].sqrt() - 0.1f64.to_radians()).abs() < 1e-12);
            assert_eq!(f.covariance[(MAP + i, POS + i)], 0.0);
        }
        // Position doubled; velocity raised to 10 m/s (it was 1).
        assert!((f.covariance[(POS, POS)] / p_before - 4.0).abs() < 1e-9);
        assert!(v_before < 1.01 && (f.covariance[(VEL, VEL)].sqrt() - 10.0).abs() < 1e-6);
    }

    #[test]
    fn a_restart_forgets_the_guess_and_keeps_the_map_offset_out_of_the_next_fix() {
        // A restart says the images see the fix (the apparent pose's
        // covariance is the fix's), so the true pose is the fix less the
        // map offset: its uncertainty holds the offset's, anti-correlated.
        // A second fix at the same time then averages with the first in the
        // pose and leaves the map offset alone; before, with the pose's
        // block set to the fix's alone, it went almost wholly to the offset.
        let turn = Turn::new();
        let mut i = init();
        i.time_offset_s = 0.005;
        let mut f = InsFilter::new(turn.state(0.0), &i, errors_with_map_offset());
        let q = UnitQuaternion::identity();
        let truth = turn.at(0.0);
        let fix = CameraPose::new(Ecef(truth.p + Vector3::new(300.0, -200.0, 100.0)), truth.q);
        let mut r = Matrix6::zeros();
        for k in 0..3 {
            r[(k, k)] = 1e-10;
            r[(k + 3, k + 3)] = 4.0;
        }
        f.reset_pose(&q, &fix, &r, 0.0, &IntrinsicsSensitivity::NONE);
        let (apparent, apparent_cov) = f.apparent_pose(&q);
        assert!(pose_difference(&apparent, &fix).norm() < 1e-9);
        for a in 0..6 {
            for b in 0..6 {
                assert!((apparent_cov[(a, b)] - r[(a, b)]).abs() < 1e-9 * (1.0 + r[(a, b)].abs()), "{a} {b}");
            }
        }
        let p = &f.covariance;
        for k in 0..3 {
            // Position: the fix's 4 m^2, the map offset's 1600 and the time
            // offset's (200 m/s x 5 ms)^2.
            assert!(p[(POS + k, POS + k)] > 4.0 + 1600.0 - 1e-6, "{}", p[(POS + k, POS + k)]);
            assert!((p[(POS + k, MAP + k)] + p[(MAP + k, MAP + k)]).abs() < 1e-9);
            assert!((p[(ATT + k, MAP_ATT + k)] + p[(MAP_ATT + k, MAP_ATT + k)]).abs() < 1e-15);
        }
        // (The focal length's error is not modelled: its row is zero.)
        assert!(p.fixed_view::<22, 22>(0, 0).into_owned().cholesky().is_some(), "positive definite");
        let (pose0, _) = f.pose(&q);
        let map0 = f.state.map_offset_ecef_m;
        let second = CameraPose::new(Ecef(fix.position.0 + Vector3::new(10.0, 0.0, 0.0)), fix.q_ecef_cam);
        f.update_with_pose(&q, &second, &r).expect("regular");
        let (pose1, _) = f.pose(&q);
        let moved = pose1.position.0 - pose0.position.0;
        let map_moved = f.state.map_offset_ecef_m - map0;
        assert!((moved - Vector3::new(5.0, 0.0, 0.0)).norm() < 0.05, "pose moved {moved}");
        assert!(map_moved.norm() < 0.05, "map offset moved {map_moved}");
    }

    #[test]
    fn the_map_offset_resizes_its_prior_or_only_its_process_noise() {
        let turn = Turn::new();
        let q = UnitQuaternion::identity();
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors_with_map_offset());
        // A fix correlates the offset with the pose.
        let fix = CameraPose::new(Ecef(turn.at(0.0).p + Vector3::new(30.0, 0.0, 0.0)), turn.at(0.0).q);
        f.update_with_pose(&q, &fix, &(Matrix6::identity() * 4.0)).expect("regular");
        let before = f.covariance;
        assert!(before[(POS, MAP)].abs() > 1.0);
        // The prior: rows and columns of the offset scaled by the ratio.
        let mut g = f.clone();
        g.resize_map_offset(20.0, 0.05f64.to_radians(), true);
        assert_eq!(g.map_sigmas(), (20.0, 0.05f64.to_radians()));
        for (i, j) in [(MAP, MAP), (MAP + 1, MAP + 2), (MAP_ATT, MAP_ATT)] {
            assert!(
                (g.covariance[(i, j)] - 0.25 * before[(i, j)]).abs()
                    <= 1e-12 * before[(i, j)].abs().max(1e-30)
            );
        }
        assert!(
            (g.covariance[(POS, MAP)] - 0.5 * before[(POS, MAP)]).abs() <= 1e-12 * before[(POS, MAP)].abs()
        );
        assert_eq!(g.covariance[(POS, POS)], before[(POS, POS)]);
        assert_eq!(g.state.map_offset_ecef_m, f.state.map_offset_ecef_m);
        // The process noise only: the covariance stays, then settles at the
        // new sigma over a few correlation times.
        let mut h = f.clone();
        h.resize_map_offset(20.0, 0.05f64.to_radians(), false);
        assert_eq!(h.covariance, before);
        let (imu, _, _) = turn.imu(100.0, 61.0, None);
        h.propagate(60.0, &imu);
        let v = h.covariance[(MAP, MAP)];
        assert!((v - 400.0).abs() < 0.02 * 400.0, "{v}");
        let a = h.covariance[(MAP_ATT, MAP_ATT)];
        let want = 0.05f64.to_radians().powi(2);
        assert!((a - want).abs() < 0.02 * want, "{a} against {want}");
        // A part that was not modelled starts at its sigma, uncorrelated.
        let mut k = InsFilter::new(turn.state(0.0), &init(), errors());
        k.update_with_pose(&q, &fix, &(Matrix6::identity() * 4.0)).expect("regular");
        k.resize_map_offset(20.0, 0.0, true);
        assert_eq!(k.covariance[(MAP, MAP)], 400.0);
        assert_eq!(k.covariance[(POS, MAP)], 0.0);
        assert_eq!(k.covariance[(MAP_ATT, MAP_ATT)], 0.0);
    }

    #[test]
    fn undoing_the_gyros_jumps_turns_the_attitude_back_and_doubts_by_the_turned_force() {
        let turn = Turn::new();
        let mut f = InsFilter::new(turn.state(3.0), &init(), errors());
        let before = f.clone();
        // Turned 0.5 rad about an ECEF axis since 1 s, no force integrated
        // (nothing to take back), 10 m/s of force norm and 20 m of its own
        // integral since.
        let jump = JumpTurn {
            since_t: 1.0,
            turn_ecef_rad: Vector3::new(0.0, 0.3, 0.4),
            force_ecef_m_s: Vector3::zeros(),
            force_twice_ecef_m: Vector3::zeros(),
            force_norm_m_s: 10.0,
            force_norm_twice_m: 20.0,
            position_sigma_m: f64::INFINITY,
            velocity_sigma_m_s: f64::INFINITY,
        };
        f.jump_turn = Some(jump);
        f.undo_jumps(&jump, 0.1);
        assert_eq!(f.jump_turn, None);
        let turned = f.state.q_ecef_imu.angle_to(&before.state.q_ecef_imu);
        assert!((turned - 0.5).abs() < 1e-12, "{turned}");
        let again = UnitQuaternion::from_scaled_axis(jump.turn_ecef_rad) * f.state.q_ecef_imu;
        assert!(again.angle_to(&before.state.q_ecef_imu) < 1e-12);
        // The force turned by 0.1 rad, the attitude's doubt (above the
        // filter's own 0.05 deg: no cap): 2 sin(0.05) of 10 m/s per velocity
        // axis, of 20 m per position axis; nothing else moves.
        let chord = 2.0 * 0.05f64.sin();
        for i in 0..N {
            for j in 0..N {
                let added = f.covariance[(i, j)] - before.covariance[(i, j)];
                let want = match (i == j, i) {
                    (true, i) if (VEL..VEL + 3).contains(&i) => (chord * 10.0).powi(2),
                    (true, i) if (POS..POS + 3).contains(&i) => (chord * 20.0).powi(2),
                    _ => 0.0,
                };
                assert!((added - want).abs() < 1e-9, "({i}, {j}): {added}");
            }
        }
        assert_eq!(f.state.position, before.state.position);
        assert_eq!(f.state.velocity_ecef_m_s, before.state.velocity_ecef_m_s);
        // The doubt frames without a fix added goes: a pose inflated 100
        // times is capped at the filter's sigmas at the jump carried on (20
        // m, 1 m/s over the 2 s since, and 20 m of the force's own integral
        // turned by 0.01 rad: 22.2 m), the attitude at the undone guess's,
        // the velocity at its sigma at the jump and the turned force's
        // doubt; correlations kept.
        let mut g = InsFilter::new(turn.state(3.0), &init(), errors());
        g.covariance[(POS, POS + 1)] = 100.0;
        g.covariance[(POS + 1, POS)] = 100.0;
        g.inflate(100.0);
        let inflated = g.clone();
        let jump = JumpTurn { position_sigma_m: 20.0, velocity_sigma_m_s: 1.0, ..jump };
        g.undo_jumps(&jump, 0.01);
        let worst =
            |g: &InsFilter, at: usize| (at..at + 3).map(|i| g.covariance[(i, i)]).fold(0.0, f64::max).sqrt();
        let p_most = 20.0 + 2.0 + 2.0 * 0.005f64.sin() * 20.0;
        assert!((jump.undone_position_sigma_m(3.0, 0.01) - p_most).abs() < 1e-12);
        assert!((worst(&g, POS) - p_most).abs() < 1e-9, "{}", worst(&g, POS));
        assert!((worst(&g, ATT) - 0.01).abs() < 1e-12, "{}", worst(&g, ATT));
        let v_most = 1.0 + 2.0 * 0.005f64.sin() * 10.0;
        assert!((worst(&g, VEL) - v_most).abs() < 1e-9, "{}", worst(&g, VEL));
        let corr = |g: &InsFilter| {
            g.covariance[(POS, POS + 1)]
                / (g.covariance[(POS, POS)] * g.covariance[(POS + 1, POS + 1)]).sqrt()
        };
        assert!((corr(&g) - corr(&inflated)).abs() < 1e-6, "{} {}", corr(&g), corr(&inflated));
    }

    #[test]
    fn undoing_a_glitch_takes_back_what_its_turned_force_added() {
        // The 2 km turn (2 g sideways, noise-free samples at 200 Hz) with a
        // 30 deg glitch about the IMU's x axis at 10 s (four samples of 1500
        // deg/s), propagated to 25 s: the force integrated turned by 30 deg
        // for 15 s has moved the position by kilometres.
        let turn = Turn::new();
        let (clean, _, _) = turn.imu(200.0, 26.0, None);
        let mut imu = clean.clone();
        for s in imu.iter_mut().filter(|s| s.t > 10.0 && s.t < 10.021) {
            s.w_imu_rad_s.x += 1500f64.to_radians();
        }
        let watching = InsErrors { gyro_max_jump_rad_s: 10f64.to_radians(), ..errors() };
        let run = |imu: &[ImuSample]| {
            let mut f = InsFilter::new(turn.state(0.0), &init(), watching);
            f.propagate(25.0, imu);
            f
        };
        let (mut f, quiet) = (run(&imu), run(&clean));
        let j = f.jump_turn.expect("a jump's turn");
        let off = |f: &InsFilter| error9(&f.state, &turn.at(25.0));
        let (e, e_quiet) = (off(&f), off(&quiet));
        assert!(e.fixed_rows::<3>(3).norm() > 1000.0, "{e}");
        // At the jump the filter's sigmas were its own (the initial ones,
        // propagated 10 s), and they are kept for the undone guess's doubt.
        assert!(j.position_sigma_m > 20.0 && j.position_sigma_m < 40.0, "{j:?}");
        assert!(j.velocity_sigma_m_s > 1.0 && j.velocity_sigma_m_s < 2.0, "{j:?}");
        // The force's norm: 2.2 g for 15 s.
        let g_turn = (9.80 * 9.80 + (2000.0 * 0.01f64).powi(2)).sqrt();
        assert!((j.force_norm_m_s / (15.0 * g_turn) - 1.0).abs() < 0.01, "{j:?}");
        assert!((j.force_norm_twice_m / (0.5 * 225.0 * g_turn) - 1.0).abs() < 0.01, "{j:?}");
        f.undo_jumps(&j, 0.001);
        // Undone, the state is the unglitched filter's, to the turn's own
        // dynamics over the glitch's 20 ms (0.03 deg, 1 m, 0.08 m/s).
        let e = off(&f);
        let d = e - e_quiet;
        assert!(d.fixed_rows::<3>(0).norm().to_degrees() < 0.05, "{d}");
        assert!(d.fixed_rows::<3>(3).norm() < 2.0, "position {d}");
        assert!(d.fixed_rows::<3>(6).norm() < 0.2, "velocity {d}");
        // The undone position's doubt: its sigma at the jump, the velocity's
        // over the 15 s since, and the force turned by the attitude's doubt.
        let sigma = j.undone_position_sigma_m(25.0, 0.001);
        let want = j.position_sigma_m + 15.0 * j.velocity_sigma_m_s + 0.001 * j.force_norm_twice_m;
        assert!((sigma - want).abs() < 1e-3 * want, "{sigma} {want}");
    }

    #[test]
    fn a_narrow_views_term_joins_the_map_offset_beyond_its_prior() {
        let turn = Turn::new();
        let mut f = InsFilter::new(turn.state(0.0), &init(), errors_with_map_offset());
        let (sm, sa) = f.map_sigmas();
        let prior =
            Matrix6::from_diagonal(&Vector6::new(sa * sa, sa * sa, sa * sa, sm * sm, sm * sm, sm * sm));
        // A wide view's own errors lie within the prior: nothing to add.
        assert_eq!(f.map_view_excess(&(prior * 0.5)), Matrix6::zeros());
        // Twice the prior's sigmas everywhere: three priors more.
        let twice = f.map_view_excess(&(prior * 4.0));
        assert!((twice - prior * 3.0).norm() <= 1e-9 * prior.norm(), "{twice}");
        // A narrow view: a tilt about east traded for a shift north at 30
        // km, 0.5 deg and 262 m along it (6.5 of the prior's sigmas in both
        // parts), well fixed across it.
        let mut u = Vector6::new(0.5f64.to_radians(), 0.0, 0.0, 0.0, 30e3 * 0.5f64.to_radians(), 0.0);
        let narrow = u * u.transpose() + prior * 0.25;
        let term = f.map_view_excess(&narrow);
        // Along the trade, capped at MAP_VIEW_CAP_SIGMAS of the prior's
        // (normalized: the direction has (6.5, 6.5) sigmas, 9.2 in all).
        let d = Vector6::new(sa, sa, sa, sm, sm, sm);
        let un = u.component_div(&d).normalize();
        let along = Matrix6::from_fn(|i, j| term[(i, j)] / (d[i] * d[j]));
        let along_var = un.dot(&(along * un));
        assert!((along_var - MAP_VIEW_CAP_SIGMAS.powi(2)).abs() < 1e-6, "{along_var}");
        // Nothing across it.
        let across = Vector6::new(0.0, 0.0, 0.0, 1.0, 0.0, 0.0);
        assert!(across.dot(&(along * across)).abs() < 1e-9);
        // Set: the offset's covariance grows by the term at once...
        let before = f.covariance;
        f.set_map_view(&term);
        let grown = Matrix6::from_fn(|a, b| {
            f.covariance[(MAP_BLOCK[a], MAP_BLOCK[b])] - before[(MAP_BLOCK[a], MAP_BLOCK[b])]
        });
        assert!((grown - term).norm() <= 1e-9 * term.norm(), "{grown}");
        // ... once: the same view again adds nothing.
        let once = f.covariance;
        f.set_map_view(&term);
        assert!((f.covariance - once).norm() <= 1e-9 * once.norm());
        // ... and an offset along the trade at the term's size is within
        // the prior the distance measures (it would be 27 sigmas^2 beyond
        // the isotropic prior alone).
        u = u * (MAP_VIEW_CAP_SIGMAS / u.component_div(&d).norm());
        f.state.map_offset_att_rad = Vector3::new(u[0], u[1], u[2]);
        f.state.map_offset_ecef_m = Vector3::new(u[3], u[4], u[5]);
        let d2 = f.map_offset_distance();
        assert!(d2 < 1.05 && d2 > 0.9, "{d2}");
        // Without updates the offset settles at prior + term (its process
        // noise), even after the view widens: the term then decays with the
        // offset's correlation time, as the distance's prior does.
        let (imu, _, _) = turn.imu(100.0, 61.0, None);
        let mut g = f.clone();
        g.propagate(60.0, &imu);
        let settled = Matrix6::from_fn(|a, b| g.covariance[(MAP_BLOCK[a], MAP_BLOCK[b])]);
        assert!((settled - (prior + term)).norm() < 0.02 * (prior + term).norm(), "{settled}");
        f.set_map_view(&Matrix6::zeros());
        assert_eq!(f.map_offset_distance(), d2);
        f.propagate(60.0, &imu);
        let settled = Matrix6::from_fn(|a, b| f.covariance[(MAP_BLOCK[a], MAP_BLOCK[b])]);
        assert!((settled - prior).norm() < 0.02 * prior.norm(), "{settled}");
    }
}
