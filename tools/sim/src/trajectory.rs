//! Vehicle trajectories of the simulator: a balloon gondola descending under a
//! parachute, a rocket ascending (New Shepard-like) and an aircraft in level
//! flight (a low pass over terrain, straight or in a constant turn). Pure
//! math, no I/O.
//!
//! [`Trajectory::state`] gives the position (ECEF, WGS84), the velocity and the
//! acceleration relative to ECEF and the attitude `q_ecef_imu` at any time.
//! Positions are C2 and attitudes C1 in time (closed forms, smooth blends), so
//! the gyro and accelerometer synthesized from them ([`crate::imu`]) are
//! meaningful. The formulas extend smoothly a little beyond `[0, duration]`
//! (the first gyro sample looks back one sample period).
//!
//! Body (IMU) frame of every vehicle, "FRD-like": x a horizontal forward
//! reference, y right, z down when the gondola hangs still, when the rocket
//! flies straight up (rocket z points out of the tail; its roll is about z) or
//! when the aircraft flies level (x along the nose).

use std::f64::consts::PI;
use std::ops::{Add, Mul, Neg, Sub};

use nalgebra::{Matrix3, Quaternion, Unit, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use trn_geodesy::{Ecef, Geodetic, WGS84_A, WGS84_E2};

use crate::rng::Rng;

/// A vehicle's trajectory model (`"kind": "balloon"`, `"rocket"` or `"aircraft"` in JSON).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum TrajectoryParams {
    Balloon(BalloonParams),
    Rocket(RocketParams),
    Aircraft(AircraftParams),
}

impl Default for TrajectoryParams {
    fn default() -> Self {
        TrajectoryParams::Balloon(BalloonParams::default())
    }
}

impl TrajectoryParams {
    /// Checks the parameters; the error names the bad field (e.g. `balloon.burst_s`).
    pub fn validate(&self) -> Result<(), String> {
        match self {
            TrajectoryParams::Balloon(p) => p.validate(),
            TrajectoryParams::Rocket(p) => p.validate(),
            TrajectoryParams::Aircraft(p) => p.validate(),
        }
    }
}

/// Parachute descent of a balloon gondola (like Draper's IBAL flight).
///
/// Descent rate `descent_rate_sl_m_s * sqrt(rho0 / rho(h))` with an exponential
/// atmosphere `rho = rho0 exp(-h / scale_height_m)` (a parachute's terminal
/// speed), integrated in closed form:
/// `h(t) = -2H ln(exp(-h0 / 2H) + v0 t / 2H)`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BalloonParams {
    /// Start height above the WGS84 ellipsoid (m).
    pub start_h_m: f64,
    /// End height above the ellipsoid (m); the duration follows from the descent law.
    pub end_h_m: f64,
    /// Flight duration (s); when given it overrides `end_h_m` (the end height then
    /// follows from the descent law; with `descent_rate_sl_m_s = 0` the gondola hovers).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub duration_s: Option<f64>,
    /// Descent rate at sea-level density (m/s), scaled by sqrt(rho0 / rho(h)).
    pub descent_rate_sl_m_s: f64,
    /// Scale height of the exponential atmosphere (m).
    pub scale_height_m: f64,
    /// Mean horizontal drift toward east (m/s).
    pub drift_east_m_s: f64,
    /// Mean horizontal drift toward north (m/s).
    pub drift_north_m_s: f64,
    /// Amplitude of a slow sinusoidal variation of each drift component (m/s), random phases.
    pub drift_var_m_s: f64,
    /// Period of that variation (s).
    pub drift_var_period_s: f64,
    /// Heading of body x at t = 0 (deg, clockwise from north).
    pub initial_yaw_deg: f64,
    /// Base yaw rate (deg/s, positive clockwise seen from above = about body z down).
    pub yaw_rate_deg_s: f64,
    /// Number of spin bursts, one at a random time in each of as many equal slots of the flight.
    pub spin_bursts: u32,
    /// Total yaw rate at a burst's peak (deg/s, base rate included); sign random per burst.
    pub burst_peak_deg_s: f64,
    /// Duration of a burst (s); raised-cosine rate profile.
    pub burst_s: f64,
    /// Pendulum swing amplitude (deg): the tilt of body z from the local down never exceeds it.
    pub pendulum_deg: f64,
    /// Pendulum period (s).
    pub pendulum_period_s: f64,
}

impl Default for BalloonParams {
    fn default() -> Self {
        Self {
            start_h_m: 30_000.0,
            end_h_m: 24_000.0,
            duration_s: None,
            descent_rate_sl_m_s: 6.0,
            scale_height_m: 7200.0,
            drift_east_m_s: 8.0,
            drift_north_m_s: 3.0,
            drift_var_m_s: 2.0,
            drift_var_period_s: 120.0,
            initial_yaw_deg: 0.0,
            yaw_rate_deg_s: 3.0,
            spin_bursts: 3,
            burst_peak_deg_s: 20.0,
            burst_s: 6.0,
            pendulum_deg: 3.0,
            pendulum_period_s: 9.0,
        }
    }
}

/// Powered ascent of a rocket (New Shepard-like), in the local east/north/up
/// frame of the launch pad.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RocketParams {
    /// Height of the start point above the pad, i.e. above the origin's height (m);
    /// the start is straight above the pad.
    pub start_h_m: f64,
    /// Speed at t = 0 (m/s).
    pub start_speed_m_s: f64,
    /// Acceleration along the path until `max_speed_m_s` (m/s^2).
    pub accel_m_s2: f64,
    /// Final speed, never exceeded (m/s); 244.4 m/s = 880 km/h.
    pub max_speed_m_s: f64,
    /// Width of the smooth (raised-cosine) blend from `accel_m_s2` to zero (s).
    pub accel_blend_s: f64,
    /// Flight duration (s).
    pub duration_s: f64,
    /// Azimuth of the pitch-over direction (deg, clockwise from north).
    pub downrange_azimuth_deg: f64,
    /// Final flight-path angle from the pad's vertical (deg).
    pub pitch_over_deg: f64,
    /// Time the pitch-over starts (s); vertical before.
    pub pitch_start_s: f64,
    /// Duration of the (raised-cosine) pitch-over (s).
    pub pitch_ramp_s: f64,
    /// Roll of body x about the long axis at t = 0 (deg; 0 = body x north while vertical).
    pub initial_roll_deg: f64,
    /// Roll rate about the long axis (body z) (deg/s).
    pub roll_rate_deg_s: f64,
    /// Amplitude of the vibration wobble about each of body x and y (deg).
    pub wobble_deg: f64,
    /// Mean wobble frequency (Hz); each axis draws its own within +-30 %.
    pub wobble_hz: f64,
}

impl Default for RocketParams {
    fn default() -> Self {
        Self {
            start_h_m: 2000.0,
            start_speed_m_s: 120.0,
            accel_m_s2: 12.0,
            max_speed_m_s: 244.4,
            accel_blend_s: 4.0,
            duration_s: 60.0,
            downrange_azimuth_deg: 90.0,
            pitch_over_deg: 8.0,
            pitch_start_s: 5.0,
            pitch_ramp_s: 30.0,
            initial_roll_deg: 0.0,
            roll_rate_deg_s: 1.0,
            wobble_deg: 0.3,
            wobble_hz: 3.0,
        }
    }
}

/// Level flight at a constant height above the ellipsoid (a low pass over
/// terrain, a survey line): constant speed, heading turning at a constant
/// rate (0: a straight line), coordinated bank `atan(v omega / g)`, a constant
/// nose-up pitch, and a slow wobble in roll and pitch.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AircraftParams {
    /// Height above the WGS84 ellipsoid, held for the whole flight (m).
    pub h_m: f64,
    /// Ground speed (m/s; exact at the origin's latitude, within ~1e-3 over tens of km).
    pub speed_m_s: f64,
    /// Heading at t = 0 (deg, clockwise from north).
    pub heading_deg: f64,
    /// Rate of turn (deg/s, positive clockwise seen from above); 0 flies straight.
    pub turn_rate_deg_s: f64,
    /// Flight duration (s).
    pub duration_s: f64,
    /// Nose-up pitch of body x above the horizon (deg).
    pub pitch_deg: f64,
    /// Amplitude of the wobble about the roll and pitch axes (deg).
    pub wobble_deg: f64,
    /// Mean wobble frequency (Hz); each axis draws its own within +-30 %.
    pub wobble_hz: f64,
}

impl Default for AircraftParams {
    fn default() -> Self {
        Self {
            h_m: 5000.0,
            speed_m_s: 120.0,
            heading_deg: 90.0,
            turn_rate_deg_s: 0.0,
            duration_s: 60.0,
            pitch_deg: 2.0,
            wobble_deg: 0.5,
            wobble_hz: 0.3,
        }
    }
}

impl AircraftParams {
    /// Checks the parameters; the error names the bad field.
    pub fn validate(&self) -> Result<(), String> {
        if !(-1000.0..=30_000.0).contains(&self.h_m) {
            return Err(format!("aircraft.h_m must be in [-1000, 30000] (got {})", self.h_m));
        }
        if !(self.speed_m_s > 0.0 && self.speed_m_s <= 1000.0) {
            return Err(format!("aircraft.speed_m_s must be in (0, 1000] (got {})", self.speed_m_s));
        }
        finite("aircraft.heading_deg", self.heading_deg)?;
        if !(-10.0..=10.0).contains(&self.turn_rate_deg_s) {
            return Err(format!(
                "aircraft.turn_rate_deg_s must be in [-10, 10] (got {})",
                self.turn_rate_deg_s
            ));
        }
        positive("aircraft.duration_s", self.duration_s)?;
        if !(-30.0..=30.0).contains(&self.pitch_deg) {
            return Err(format!("aircraft.pitch_deg must be in [-30, 30] (got {})", self.pitch_deg));
        }
        if !(0.0..=10.0).contains(&self.wobble_deg) {
            return Err(format!("aircraft.wobble_deg must be in [0, 10] (got {})", self.wobble_deg));
        }
        positive("aircraft.wobble_hz", self.wobble_hz)?;
        Ok(())
    }
}

fn finite(name: &str, v: f64) -> Result<(), String> {
    if v.is_finite() {
        Ok(())
    } else {
        Err(format!("{name} must be a finite number (got {v})"))
    }
}

fn positive(name: &str, v: f64) -> Result<(), String> {
    if v.is_finite() && v > 0.0 {
        Ok(())
    } else {
        Err(format!("{name} must be > 0 (got {v})"))
    }
}

fn non_negative(name: &str, v: f64) -> Result<(), String> {
    if v.is_finite() && v >= 0.0 {
        Ok(())
    } else {
        Err(format!("{name} must be >= 0 (got {v})"))
    }
}

impl BalloonParams {
    /// Checks the parameters; the error names the bad field.
    pub fn validate(&self) -> Result<(), String> {
        finite("balloon.start_h_m", self.start_h_m)?;
        finite("balloon.end_h_m", self.end_h_m)?;
        if !(1000.0..=50_000.0).contains(&self.scale_height_m) {
            return Err(format!(
                "balloon.scale_height_m must be in [1000, 50000] (got {})",
                self.scale_height_m
            ));
        }
        if !(-1000.0..=100_000.0).contains(&self.start_h_m) {
            return Err(format!("balloon.start_h_m must be in [-1000, 100000] (got {})", self.start_h_m));
        }
        match self.duration_s {
            Some(d) => {
                positive("balloon.duration_s", d)?;
                non_negative("balloon.descent_rate_sl_m_s", self.descent_rate_sl_m_s)?;
            }
            None => {
                positive("balloon.descent_rate_sl_m_s", self.descent_rate_sl_m_s)?;
                if self.start_h_m <= self.end_h_m {
                    return Err(format!(
                        "balloon.start_h_m must be above end_h_m (got {} <= {})",
                        self.start_h_m, self.end_h_m
                    ));
                }
            }
        }
        finite("balloon.drift_east_m_s", self.drift_east_m_s)?;
        finite("balloon.drift_north_m_s", self.drift_north_m_s)?;
        non_negative("balloon.drift_var_m_s", self.drift_var_m_s)?;
        positive("balloon.drift_var_period_s", self.drift_var_period_s)?;
        finite("balloon.initial_yaw_deg", self.initial_yaw_deg)?;
        finite("balloon.yaw_rate_deg_s", self.yaw_rate_deg_s)?;
        non_negative("balloon.burst_peak_deg_s", self.burst_peak_deg_s)?;
        positive("balloon.burst_s", self.burst_s)?;
        if !(0.0..60.0).contains(&self.pendulum_deg) {
            return Err(format!("balloon.pendulum_deg must be in [0, 60) (got {})", self.pendulum_deg));
        }
        positive("balloon.pendulum_period_s", self.pendulum_period_s)?;
        Ok(())
    }
}

impl RocketParams {
    /// Checks the parameters; the error names the bad field.
    pub fn validate(&self) -> Result<(), String> {
        non_negative("rocket.start_h_m", self.start_h_m)?;
        non_negative("rocket.start_speed_m_s", self.start_speed_m_s)?;
        finite("rocket.max_speed_m_s", self.max_speed_m_s)?;
        if self.max_speed_m_s < self.start_speed_m_s {
            return Err(format!(
                "rocket.max_speed_m_s must be >= start_speed_m_s (got {} < {})",
                self.max_speed_m_s, self.start_speed_m_s
            ));
        }
        positive("rocket.accel_m_s2", self.accel_m_s2)?;
        positive("rocket.accel_blend_s", self.accel_blend_s)?;
        positive("rocket.duration_s", self.duration_s)?;
        finite("rocket.downrange_azimuth_deg", self.downrange_azimuth_deg)?;
        if !(0.0..90.0).contains(&self.pitch_over_deg) {
            return Err(format!("rocket.pitch_over_deg must be in [0, 90) (got {})", self.pitch_over_deg));
        }
        non_negative("rocket.pitch_start_s", self.pitch_start_s)?;
        positive("rocket.pitch_ramp_s", self.pitch_ramp_s)?;
        finite("rocket.initial_roll_deg", self.initial_roll_deg)?;
        finite("rocket.roll_rate_deg_s", self.roll_rate_deg_s)?;
        if !(0.0..=10.0).contains(&self.wobble_deg) {
            return Err(format!("rocket.wobble_deg must be in [0, 10] (got {})", self.wobble_deg));
        }
        positive("rocket.wobble_hz", self.wobble_hz)?;
        Ok(())
    }
}

/// The vehicle's true state at a time.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BodyState {
    pub t: f64,
    pub position: Ecef,
    /// Velocity relative to ECEF, in ECEF axes (m/s).
    pub velocity_ecef_m_s: Vector3<f64>,
    /// Acceleration relative to ECEF (second derivative of the ECEF position), ECEF axes (m/s^2).
    pub accel_ecef_m_s2: Vector3<f64>,
    /// Rotates IMU-frame vectors into ECEF: `v_ecef = q_ecef_imu * v_imu`.
    pub q_ecef_imu: UnitQuaternion<f64>,
}

/// A trajectory built from [`TrajectoryParams`], an origin and a seed.
#[derive(Clone, Debug)]
pub struct Trajectory {
    model: Model,
    origin: Geodetic,
    duration_s: f64,
}

#[derive(Clone, Debug)]
enum Model {
    Balloon(Balloon),
    Rocket(Rocket),
    Aircraft(Aircraft),
}

impl Trajectory {
    /// `origin`: the ground point (lat, lon, ellipsoidal terrain height) under the
    /// start (balloon) or the launch pad (rocket). The seed draws the random parts
    /// (burst times and signs, pendulum and drift phases, wobble).
    pub fn new(params: &TrajectoryParams, origin: Geodetic, seed: u64) -> Result<Trajectory, String> {
        params.validate()?;
        if !(origin.lat_deg.is_finite() && origin.lon_deg.is_finite() && origin.h_m.is_finite()) {
            return Err(format!("origin must be finite (got {origin:?})"));
        }
        if origin.lat_deg.abs() > 89.5 {
            return Err(format!("origin latitude must be within +-89.5 deg (got {})", origin.lat_deg));
        }
        let (model, duration_s) = match params {
            TrajectoryParams::Balloon(p) => {
                let b = Balloon::new(p, origin, seed)?;
                let d = b.duration_s;
                (Model::Balloon(b), d)
            }
            TrajectoryParams::Rocket(p) => (Model::Rocket(Rocket::new(p, origin, seed)), p.duration_s),
            TrajectoryParams::Aircraft(p) => {
                if p.h_m <= origin.h_m {
                    return Err(format!(
                        "aircraft.h_m ({:.1} m) must be above the terrain height at the origin ({:.1} m)",
                        p.h_m, origin.h_m
                    ));
                }
                (Model::Aircraft(Aircraft::new(p, origin, seed)), p.duration_s)
            }
        };
        Ok(Trajectory { model, origin, duration_s })
    }

    pub fn duration_s(&self) -> f64 {
        self.duration_s
    }

    /// The ground point given to [`Trajectory::new`].
    pub fn origin(&self) -> Geodetic {
        self.origin
    }

    /// The state at `t` (s from the start), meant for `t` in `[0, duration]`;
    /// the formulas extend smoothly a little beyond.
    pub fn state(&self, t: f64) -> BodyState {
        match &self.model {
            Model::Balloon(b) => b.state(t),
            Model::Rocket(r) => r.state(t),
            Model::Aircraft(a) => a.state(t),
        }
    }
}

// ---------------------------------------------------------------------------
// Second-order forward differentiation: value, first and second time derivative.

#[derive(Clone, Copy, Debug)]
struct Jet {
    v: f64,
    d: f64,
    dd: f64,
}

impl Jet {
    fn var(t: f64) -> Jet {
        Jet { v: t, d: 1.0, dd: 0.0 }
    }
    fn cst(c: f64) -> Jet {
        Jet { v: c, d: 0.0, dd: 0.0 }
    }
    /// f(self) given f, f' and f'' at self.v.
    fn chain(self, f: f64, f1: f64, f2: f64) -> Jet {
        Jet { v: f, d: f1 * self.d, dd: f2 * self.d * self.d + f1 * self.dd }
    }
    fn sin(self) -> Jet {
        let (s, c) = self.v.sin_cos();
        self.chain(s, c, -s)
    }
    fn cos(self) -> Jet {
        let (s, c) = self.v.sin_cos();
        self.chain(c, -s, -c)
    }
    fn sqrt(self) -> Jet {
        let r = self.v.sqrt();
        self.chain(r, 0.5 / r, -0.25 / (r * self.v))
    }
    fn ln(self) -> Jet {
        let i = 1.0 / self.v;
        self.chain(self.v.ln(), i, -i * i)
    }
    fn recip(self) -> Jet {
        let i = 1.0 / self.v;
        self.chain(i, -i * i, 2.0 * i * i * i)
    }
}

impl Add for Jet {
    type Output = Jet;
    fn add(self, o: Jet) -> Jet {
        Jet { v: self.v + o.v, d: self.d + o.d, dd: self.dd + o.dd }
    }
}
impl Sub for Jet {
    type Output = Jet;
    fn sub(self, o: Jet) -> Jet {
        Jet { v: self.v - o.v, d: self.d - o.d, dd: self.dd - o.dd }
    }
}
impl Neg for Jet {
    type Output = Jet;
    fn neg(self) -> Jet {
        Jet { v: -self.v, d: -self.d, dd: -self.dd }
    }
}
impl Mul for Jet {
    type Output = Jet;
    fn mul(self, o: Jet) -> Jet {
        Jet {
            v: self.v * o.v,
            d: self.d * o.v + self.v * o.d,
            dd: self.dd * o.v + 2.0 * self.d * o.d + self.v * o.dd,
        }
    }
}
impl Mul<f64> for Jet {
    type Output = Jet;
    fn mul(self, k: f64) -> Jet {
        Jet { v: self.v * k, d: self.d * k, dd: self.dd * k }
    }
}
impl Add<f64> for Jet {
    type Output = Jet;
    fn add(self, k: f64) -> Jet {
        Jet { v: self.v + k, ..self }
    }
}

/// WGS84 geodetic (radians, m) to ECEF with time derivatives.
fn geodetic_to_ecef_jet(lat: Jet, lon: Jet, h: Jet) -> [Jet; 3] {
    let (sl, cl) = (lat.sin(), lat.cos());
    let n = (Jet::cst(1.0) - sl * sl * WGS84_E2).sqrt().recip() * WGS84_A;
    let nh = n + h;
    [nh * cl * lon.cos(), nh * cl * lon.sin(), (n * (1.0 - WGS84_E2) + h) * sl]
}

fn split(j: [Jet; 3]) -> (Vector3<f64>, Vector3<f64>, Vector3<f64>) {
    (
        Vector3::new(j[0].v, j[1].v, j[2].v),
        Vector3::new(j[0].d, j[1].d, j[2].d),
        Vector3::new(j[0].dd, j[1].dd, j[2].dd),
    )
}

// ---------------------------------------------------------------------------
// Rotations.

/// Rotates local east/north/up vectors at (lat, lon) (radians) into ECEF.
fn q_ecef_enu(lat: f64, lon: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), lon + PI / 2.0)
        * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), PI / 2.0 - lat)
}

/// Rotates north/east/down vectors into east/north/up.
fn q_enu_ned() -> UnitQuaternion<f64> {
    let s = std::f64::consts::FRAC_1_SQRT_2;
    UnitQuaternion::new_unchecked(Quaternion::new(0.0, s, s, 0.0))
}

/// Rotation of a rotation vector (rad), accurate for tiny angles.
pub(crate) fn exp_rotvec(v: &Vector3<f64>) -> UnitQuaternion<f64> {
    let th = v.norm();
    let half = 0.5 * th;
    let k = if th > 1e-6 { half.sin() / th } else { 0.5 - th * th / 48.0 };
    UnitQuaternion::new_unchecked(Quaternion::from_parts(half.cos(), v * k))
}

/// Rotation vector (rad, angle in [0, pi]) of a rotation, accurate for tiny angles.
pub(crate) fn log_rotvec(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let (w, v) = if q.w < 0.0 { (-q.w, -q.vector()) } else { (q.w, q.vector().into_owned()) };
    let n = v.norm();
    if n == 0.0 {
        return Vector3::zeros();
    }
    v * (2.0 * n.atan2(w) / n)
}

/// Raised-cosine step 0 -> 1 over x in [0, 1] and its derivative in x.
fn smooth_step(x: f64) -> (f64, f64) {
    if x <= 0.0 {
        (0.0, 0.0)
    } else if x >= 1.0 {
        (1.0, 0.0)
    } else {
        (0.5 * (1.0 - (PI * x).cos()), 0.5 * PI * (PI * x).sin())
    }
}

// ---------------------------------------------------------------------------
// Balloon.

#[derive(Clone, Debug)]
struct Balloon {
    p: BalloonParams,
    lat0: f64,
    lon0: f64,
    /// Metres per radian of latitude / longitude, at the start height.
    r_north: f64,
    r_east: f64,
    /// h(t) = -2H ln(c0 + k t).
    c0: f64,
    k: f64,
    duration_s: f64,
    drift_phase: [f64; 2],
    /// (start time, extra rate amplitude rad/s).
    bursts: Vec<(f64, f64)>,
    /// Swing: amplitudes (rad) about north and east, phases.
    swing_amp: [f64; 2],
    swing_phase: [f64; 2],
}

impl Balloon {
    fn new(p: &BalloonParams, origin: Geodetic, seed: u64) -> Result<Balloon, String> {
        let two_h = 2.0 * p.scale_height_m;
        let c0 = (-p.start_h_m / two_h).exp();
        let k = p.descent_rate_sl_m_s / two_h;
        let (duration_s, end_h) = match p.duration_s {
            Some(d) => (d, -two_h * (c0 + k * d).ln()),
            None => (((-p.end_h_m / two_h).exp() - c0) / k, p.end_h_m),
        };
        if end_h <= origin.h_m {
            return Err(format!(
                "balloon.end_h_m ({end_h:.1} m, at the end of the descent) must be above the terrain height \
                 at the origin ({:.1} m)",
                origin.h_m
            ));
        }
        let g0 = origin.with_height(p.start_h_m);
        let r_north = g0.meridian_radius_m() + p.start_h_m;
        let r_east = (g0.prime_vertical_radius_m() + p.start_h_m) * origin.lat_rad().cos();

        let mut rng = Rng::stream(seed, "balloon_drift");
        let drift_phase = [rng.range(0.0, 2.0 * PI), rng.range(0.0, 2.0 * PI)];

        let mut rng = Rng::stream(seed, "balloon_bursts");
        let n = p.spin_bursts as usize;
        let slot = duration_s / n.max(1) as f64;
        let base = p.yaw_rate_deg_s.to_radians();
        let bursts = (0..n)
            .map(|i| {
                let start = i as f64 * slot + rng.uniform() * (slot - p.burst_s).max(0.0);
                let sign = if rng.uniform() < 0.5 { -1.0 } else { 1.0 };
                (start, sign * p.burst_peak_deg_s.to_radians() - base)
            })
            .collect();

        let mut rng = Rng::stream(seed, "balloon_pendulum");
        // An elliptic swing: the tilt never exceeds the amplitude.
        let beta = rng.range(0.0, 2.0 * PI);
        let a = p.pendulum_deg.to_radians();
        let swing_amp = [a * beta.cos(), a * beta.sin()];
        let swing_phase = [rng.range(0.0, 2.0 * PI), rng.range(0.0, 2.0 * PI)];

        Ok(Balloon {
            p: p.clone(),
            lat0: origin.lat_rad(),
            lon0: origin.lon_rad(),
            r_north,
            r_east,
            c0,
            k,
            duration_s,
            drift_phase,
            bursts,
            swing_amp,
            swing_phase,
        })
    }

    /// Heading (rad, clockwise from north) and its rate (rad/s).
    fn yaw(&self, t: f64) -> (f64, f64) {
        let base = self.p.yaw_rate_deg_s.to_radians();
        let (mut psi, mut rate) = (self.p.initial_yaw_deg.to_radians() + base * t, base);
        let w = self.p.burst_s;
        for &(t0, amp) in &self.bursts {
            let x = (t - t0) / w;
            // Integral of the raised-cosine bump (1 - cos 2 pi x) / 2.
            let (b, db) = if x <= 0.0 {
                (0.0, 0.0)
            } else if x >= 1.0 {
                (0.5, 0.0)
            } else {
                (0.5 * x - (2.0 * PI * x).sin() / (4.0 * PI), 0.5 * (1.0 - (2.0 * PI * x).cos()))
            };
            psi += amp * w * b;
            rate += amp * db;
        }
        (psi, rate)
    }

    /// Pendulum tilt as a rotation vector in north/east/down axes (rad).
    fn swing_ned(&self, t: f64) -> Vector3<f64> {
        let wt = 2.0 * PI * t / self.p.pendulum_period_s;
        Vector3::new(
            self.swing_amp[0] * (wt + self.swing_phase[0]).sin(),
            self.swing_amp[1] * (wt + self.swing_phase[1]).sin(),
            0.0,
        )
    }

    fn state(&self, t: f64) -> BodyState {
        let p = &self.p;
        let tj = Jet::var(t);
        let h = (Jet::cst(self.c0) + tj * self.k).ln() * (-2.0 * p.scale_height_m);
        let om = 2.0 * PI / p.drift_var_period_s;
        let a = p.drift_var_m_s / om;
        let drift = |v: f64, ph: f64| tj * v + (-((tj * om + ph).cos()) + ph.cos()) * a;
        let east = drift(p.drift_east_m_s, self.drift_phase[0]);
        let north = drift(p.drift_north_m_s, self.drift_phase[1]);
        let lat = north * (1.0 / self.r_north) + self.lat0;
        let lon = east * (1.0 / self.r_east) + self.lon0;
        let (r, v, acc) = split(geodetic_to_ecef_jet(lat, lon, h));

        let (psi, _) = self.yaw(t);
        let q_ned_body =
            exp_rotvec(&self.swing_ned(t)) * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), psi);
        let q = q_ecef_enu(lat.v, lon.v) * q_enu_ned() * q_ned_body;
        BodyState { t, position: Ecef(r), velocity_ecef_m_s: v, accel_ecef_m_s2: acc, q_ecef_imu: q }
    }
}

// ---------------------------------------------------------------------------
// Rocket.

const GL8_X: [f64; 4] =
    [0.183_434_642_495_649_8, 0.525_532_409_916_329, 0.796_666_477_413_626_7, 0.960_289_856_497_536_3];
const GL8_W: [f64; 4] =
    [0.362_683_783_378_362, 0.313_706_645_877_887_3, 0.222_381_034_453_374_5, 0.101_228_536_290_376_3];

#[derive(Clone, Debug)]
struct Rocket {
    p: RocketParams,
    q_ecef_enu: UnitQuaternion<f64>,
    r_ecef_enu: Matrix3<f64>,
    pad_ecef: Vector3<f64>,
    /// Horizontal downrange unit vector and the tilt axis (ENU).
    downrange: Vector3<f64>,
    tilt_axis: Unit<Vector3<f64>>,
    /// Acceleration blend: start time and width (s); none when start = max speed.
    blend: Option<(f64, f64)>,
    /// Wobble about body x and y: angular frequency (rad/s) and phase.
    wobble: [(f64, f64); 2],
    /// Integration nodes (t, ENU position) at every break of smoothness and every second.
    nodes: Vec<(f64, Vector3<f64>)>,
}

impl Rocket {
    fn new(p: &RocketParams, origin: Geodetic, seed: u64) -> Rocket {
        let q = q_ecef_enu(origin.lat_rad(), origin.lon_rad());
        let az = p.downrange_azimuth_deg.to_radians();
        let downrange = Vector3::new(az.sin(), az.cos(), 0.0);
        // Rotating up about (up x downrange) tilts it toward downrange.
        let tilt_axis = Unit::new_normalize(Vector3::z().cross(&downrange));
        let blend = if p.max_speed_m_s > p.start_speed_m_s {
            let tc = (p.max_speed_m_s - p.start_speed_m_s) / p.accel_m_s2;
            let w = p.accel_blend_s.min(2.0 * tc);
            Some((tc - 0.5 * w, w))
        } else {
            None
        };
        let mut rng = Rng::stream(seed, "rocket_wobble");
        let mut wob = || (2.0 * PI * p.wobble_hz * rng.range(0.7, 1.3), rng.range(0.0, 2.0 * PI));
        let wobble = [wob(), wob()];
        let mut r = Rocket {
            p: p.clone(),
            q_ecef_enu: q,
            r_ecef_enu: *q.to_rotation_matrix().matrix(),
            pad_ecef: origin.to_ecef().0,
            downrange,
            tilt_axis,
            blend,
            wobble,
            nodes: Vec::new(),
        };
        let end = p.duration_s + 2.0;
        let mut ts: Vec<f64> = (0..=end.ceil() as usize).map(|i| i as f64).collect();
        if let Some((ta, w)) = blend {
            ts.extend([ta, ta + w]);
        }
        ts.extend([p.pitch_start_s, p.pitch_start_s + p.pitch_ramp_s]);
        ts.retain(|t| (0.0..=end.ceil()).contains(t));
        ts.sort_by(f64::total_cmp);
        ts.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
        let mut pos = Vector3::new(0.0, 0.0, p.start_h_m);
        let mut nodes = vec![(ts[0], pos)];
        for w in ts.windows(2) {
            pos += r.integrate_velocity(w[0], w[1]);
            nodes.push((w[1], pos));
        }
        r.nodes = nodes;
        r
    }

    /// Speed along the path (m/s) and its rate (m/s^2).
    fn speed(&self, t: f64) -> (f64, f64) {
        let p = &self.p;
        let Some((ta, w)) = self.blend else { return (p.start_speed_m_s, 0.0) };
        let a = p.accel_m_s2;
        if t < ta {
            (p.start_speed_m_s + a * t, a)
        } else if t < ta + w {
            let x = (t - ta) / w;
            let v = p.start_speed_m_s + a * ta + a * w * (0.5 * x + (PI * x).sin() / (2.0 * PI));
            (v, 0.5 * a * (1.0 + (PI * x).cos()))
        } else {
            (p.max_speed_m_s, 0.0)
        }
    }

    /// Flight-path angle from the vertical (rad) and its rate.
    fn pitch(&self, t: f64) -> (f64, f64) {
        let (s, ds) = smooth_step((t - self.p.pitch_start_s) / self.p.pitch_ramp_s);
        let th = self.p.pitch_over_deg.to_radians();
        (th * s, th * ds / self.p.pitch_ramp_s)
    }

    /// ENU velocity and acceleration.
    fn velocity_enu(&self, t: f64) -> (Vector3<f64>, Vector3<f64>) {
        let (v, dv) = self.speed(t);
        let (th, dth) = self.pitch(t);
        let (s, c) = th.sin_cos();
        let u = self.downrange * s + Vector3::z() * c;
        let du = self.downrange * c - Vector3::z() * s;
        (u * v, u * dv + du * (v * dth))
    }

    /// Integral of the velocity over [t0, t1], within one smooth piece (Gauss-Legendre, 8 points).
    fn integrate_velocity(&self, t0: f64, t1: f64) -> Vector3<f64> {
        let (m, r) = (0.5 * (t0 + t1), 0.5 * (t1 - t0));
        let mut sum = Vector3::zeros();
        for (x, w) in GL8_X.iter().zip(GL8_W) {
            sum += (self.velocity_enu(m - r * x).0 + self.velocity_enu(m + r * x).0) * w;
        }
        sum * r
    }

    fn position_enu(&self, t: f64) -> Vector3<f64> {
        let i = self.nodes.partition_point(|n| n.0 <= t).saturating_sub(1);
        let (t0, p0) = self.nodes[i];
        p0 + self.integrate_velocity(t0, t)
    }

    fn state(&self, t: f64) -> BodyState {
        let p = &self.p;
        let pos = self.position_enu(t);
        let (v, a) = self.velocity_enu(t);
        let (th, _) = self.pitch(t);
        let roll = (p.initial_roll_deg + p.roll_rate_deg_s * t).to_radians();
        let amp = p.wobble_deg.to_radians();
        let wob = Vector3::new(
            amp * (self.wobble[0].0 * t + self.wobble[0].1).sin(),
            amp * (self.wobble[1].0 * t + self.wobble[1].1).sin(),
            0.0,
        );
        let q_enu_body = UnitQuaternion::from_axis_angle(&self.tilt_axis, th)
            * q_enu_ned()
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), roll)
            * exp_rotvec(&wob);
        BodyState {
            t,
            position: Ecef(self.pad_ecef + self.r_ecef_enu * pos),
            velocity_ecef_m_s: self.r_ecef_enu * v,
            accel_ecef_m_s2: self.r_ecef_enu * a,
            q_ecef_imu: self.q_ecef_enu * q_enu_body,
        }
    }
}

// ---------------------------------------------------------------------------
// Aircraft.

#[derive(Clone, Debug)]
struct Aircraft {
    p: AircraftParams,
    lat0: f64,
    lon0: f64,
    /// Metres per radian of latitude / longitude, at the flight height.
    r_north: f64,
    r_east: f64,
    /// Wobble about body x (roll) and y (pitch): angular frequency (rad/s) and phase.
    wobble: [(f64, f64); 2],
}

/// Standard gravity for the coordinated bank angle (m/s^2).
const G0: f64 = 9.80665;

impl Aircraft {
    fn new(p: &AircraftParams, origin: Geodetic, seed: u64) -> Aircraft {
        let g0 = origin.with_height(p.h_m);
        let r_north = g0.meridian_radius_m() + p.h_m;
        let r_east = (g0.prime_vertical_radius_m() + p.h_m) * origin.lat_rad().cos();
        let mut rng = Rng::stream(seed, "aircraft_wobble");
        let mut wob = || (2.0 * PI * p.wobble_hz * rng.range(0.7, 1.3), rng.range(0.0, 2.0 * PI));
        let wobble = [wob(), wob()];
        Aircraft { p: p.clone(), lat0: origin.lat_rad(), lon0: origin.lon_rad(), r_north, r_east, wobble }
    }

    fn state(&self, t: f64) -> BodyState {
        let p = &self.p;
        let tj = Jet::var(t);
        let (v, om, psi0) = (p.speed_m_s, p.turn_rate_deg_s.to_radians(), p.heading_deg.to_radians());
        let psi = tj * om + psi0;
        // Ground track: east = int v sin(psi), north = int v cos(psi).
        let (east, north) = if om.abs() < 1e-12 {
            (tj * (v * psi0.sin()), tj * (v * psi0.cos()))
        } else {
            let k = v / om;
            ((-psi.cos() + psi0.cos()) * k, (psi.sin() + (-psi0.sin())) * k)
        };
        let lat = north * (1.0 / self.r_north) + self.lat0;
        let lon = east * (1.0 / self.r_east) + self.lon0;
        let (r, vel, acc) = split(geodetic_to_ecef_jet(lat, lon, Jet::cst(p.h_m)));
        let amp = p.wobble_deg.to_radians();
        let wob = |i: usize| amp * (self.wobble[i].0 * t + self.wobble[i].1).sin();
        let roll = (v * om / G0).atan() + wob(0);
        let pitch = p.pitch_deg.to_radians() + wob(1);
        let q_ned_body = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), psi.v)
            * UnitQuaternion::from_axis_angle(&Vector3::y_axis(), pitch)
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), roll);
        let q = q_ecef_enu(lat.v, lon.v) * q_enu_ned() * q_ned_body;
        BodyState { t, position: Ecef(r), velocity_ecef_m_s: vel, accel_ecef_m_s2: acc, q_ecef_imu: q }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::LocalFrame;

    fn origin() -> Geodetic {
        Geodetic::new(32.9, -106.4, 1250.0)
    }

    fn balloon(seed: u64) -> Trajectory {
        Trajectory::new(&TrajectoryParams::Balloon(BalloonParams::default()), origin(), seed).unwrap()
    }

    fn rocket(seed: u64) -> Trajectory {
        Trajectory::new(&TrajectoryParams::Rocket(RocketParams::default()), origin(), seed).unwrap()
    }

    fn local_down(s: &BodyState) -> Vector3<f64> {
        -s.position.to_geodetic().up_ecef()
    }

    #[test]
    fn balloon_heights_and_descent_rate() {
        let p = BalloonParams::default();
        let tr = balloon(1);
        let d = tr.duration_s();
        // Duration against a fine numerical integral of dt = dh / rate.
        let n = 200_000;
        let dh = (p.start_h_m - p.end_h_m) / n as f64;
        let rate = |h: f64| p.descent_rate_sl_m_s * (h / (2.0 * p.scale_height_m)).exp();
        let num: f64 = (0..n).map(|i| dh / rate(p.end_h_m + (i as f64 + 0.5) * dh)).sum();
        assert!((num - d).abs() < 1e-3, "duration {d} vs numerical {num}");

        let h0 = tr.state(0.0).position.to_geodetic().h_m;
        let h1 = tr.state(d).position.to_geodetic().h_m;
        assert!((h0 - p.start_h_m).abs() < 1e-3 && (h1 - p.end_h_m).abs() < 1e-3, "{h0} {h1}");
        let mut last = f64::INFINITY;
        for i in 0..=200 {
            let h = tr.state(d * i as f64 / 200.0).position.to_geodetic().h_m;
            assert!(h < last, "height not decreasing at step {i}");
            last = h;
        }
        let s0 = tr.state(0.0);
        let up_rate = s0.velocity_ecef_m_s.dot(&-local_down(&s0));
        let expect = -rate(p.start_h_m);
        assert!((up_rate / expect - 1.0).abs() < 1e-3, "{up_rate} vs {expect}");
        // Horizontal speed close to the drift.
        let f = LocalFrame::at(s0.position.to_geodetic());
        let v = f.vector_to_enu(&s0.velocity_ecef_m_s);
        assert!((v.x - 8.0).abs() <= 2.01 && (v.y - 3.0).abs() <= 2.01, "{v:?}");
    }

    fn heading(s: &BodyState) -> f64 {
        let f = LocalFrame::at(s.position.to_geodetic());
        let x = f.vector_to_enu(&(s.q_ecef_imu * Vector3::x()));
        x.x.atan2(x.y)
    }

    fn wrap(a: f64) -> f64 {
        (a + PI).rem_euclid(2.0 * PI) - PI
    }

    #[test]
    fn balloon_bursts_reach_peak_rate() {
        let p = BalloonParams::default();
        let tr = balloon(3);
        let Model::Balloon(b) = &tr.model else { panic!() };
        assert_eq!(b.bursts.len(), 3);
        let dt = 0.02;
        for &(t0, amp) in &b.bursts {
            let mut peak: f64 = 0.0;
            let mut t = t0;
            while t < t0 + p.burst_s {
                let r = wrap(heading(&tr.state(t + dt)) - heading(&tr.state(t))) / dt;
                if r.abs() > peak.abs() {
                    peak = r;
                }
                t += dt;
            }
            let peak_deg = peak.to_degrees();
            assert!(
                (peak_deg.abs() / p.burst_peak_deg_s - 1.0).abs() < 0.1,
                "burst at {t0}: peak {peak_deg}"
            );
            assert_eq!(peak.signum(), (amp + p.yaw_rate_deg_s.to_radians()).signum());
        }
        // Away from the bursts the rate is the base rate (pendulum aside).
        let quiet = (0..200)
            .map(|i| tr.duration_s() * i as f64 / 200.0)
            .find(|t| b.bursts.iter().all(|&(t0, _)| *t < t0 - 1.0 || *t > t0 + p.burst_s + 1.0))
            .unwrap();
        let r = wrap(heading(&tr.state(quiet + dt)) - heading(&tr.state(quiet))) / dt;
        assert!((r.to_degrees() - p.yaw_rate_deg_s).abs() < 0.5, "quiet rate {}", r.to_degrees());
    }

    #[test]
    fn balloon_tilt_within_pendulum_amplitude() {
        let p = BalloonParams::default();
        let tr = balloon(4);
        let mut max_tilt: f64 = 0.0;
        for i in 0..=2000 {
            let s = tr.state(tr.duration_s() * i as f64 / 2000.0);
            let z = s.q_ecef_imu * Vector3::z();
            max_tilt = max_tilt.max(z.angle(&local_down(&s)).to_degrees());
        }
        assert!(max_tilt <= p.pendulum_deg * 1.001 && max_tilt > 0.5 * p.pendulum_deg, "{max_tilt}");
        // Without swing, body z is the local down exactly.
        let q = BalloonParams { pendulum_deg: 0.0, ..p };
        let tr = Trajectory::new(&TrajectoryParams::Balloon(q), origin(), 4).unwrap();
        let s = tr.state(77.0);
        assert!((s.q_ecef_imu * Vector3::z()).angle(&local_down(&s)) < 1e-12);
    }

    #[test]
    fn rocket_speed_and_attitude() {
        let p = RocketParams::default();
        let tr = rocket(5);
        let mut vmax: f64 = 0.0;
        for i in 0..=6000 {
            let t = tr.duration_s() * i as f64 / 6000.0;
            let s = tr.state(t);
            let v = s.velocity_ecef_m_s.norm();
            vmax = vmax.max(v);
            // Body z along the tail (within the wobble), body x horizontal at the start.
            let z = s.q_ecef_imu * Vector3::z();
            let tilt = z.angle(&-s.velocity_ecef_m_s).to_degrees();
            assert!(tilt <= p.wobble_deg * 2f64.sqrt() * 1.001, "t {t}: tail vs velocity {tilt}");
        }
        assert!(vmax >= 0.999 * p.max_speed_m_s && vmax <= 1.01 * p.max_speed_m_s, "{vmax}");
        let s0 = tr.state(0.0);
        assert!((s0.velocity_ecef_m_s.norm() - p.start_speed_m_s).abs() < 1e-9);
        let g0 = s0.position.to_geodetic();
        assert!((g0.h_m - origin().h_m - p.start_h_m).abs() < 1e-6, "{g0:?}");
        assert!(
            (s0.q_ecef_imu * Vector3::z()).angle(&local_down(&s0)) < 2f64.sqrt() * p.wobble_deg.to_radians()
        );
        // Final flight path angle.
        let s1 = tr.state(tr.duration_s());
        let up = origin().up_ecef();
        let fpa = s1.velocity_ecef_m_s.angle(&up).to_degrees();
        assert!((fpa - p.pitch_over_deg).abs() < 1e-9, "{fpa}");
        let f = LocalFrame::at(origin());
        let v = f.vector_to_enu(&s1.velocity_ecef_m_s);
        assert!(v.x > 0.0 && v.y.abs() < 1e-9 * v.x, "downrange east: {v:?}");
    }

    #[test]
    fn aircraft_level_turn_and_attitude() {
        // A constant turn: constant height, speed, the circle's radius v / omega, the
        // heading along the velocity and the coordinated bank atan(v omega / g).
        let p = AircraftParams {
            h_m: 6000.0,
            speed_m_s: 150.0,
            turn_rate_deg_s: 3.0,
            wobble_deg: 0.0,
            pitch_deg: 0.0,
            ..Default::default()
        };
        let tr = Trajectory::new(&TrajectoryParams::Aircraft(p.clone()), origin(), 3).unwrap();
        let om = p.turn_rate_deg_s.to_radians();
        let radius = p.speed_m_s / om;
        let f = LocalFrame::at(origin().with_height(p.h_m));
        // Centre of the turn: right of the initial heading (east) = south of the start.
        let centre = Vector3::new(0.0, -radius, 0.0);
        let bank = (p.speed_m_s * om / G0).atan();
        for i in 0..=60 {
            let t = i as f64;
            let s = tr.state(t);
            let g = s.position.to_geodetic();
            assert!((g.h_m - p.h_m).abs() < 1e-6, "t {t}: h {}", g.h_m);
            // Longitude is scaled at the origin's latitude: the speed drifts by ~1e-3 over km.
            assert!((s.velocity_ecef_m_s.norm() - p.speed_m_s).abs() < 2e-3 * p.speed_m_s, "t {t}");
            let e = f.to_enu(&s.position).0;
            // The ellipsoid curves away from the tangent plane by d^2 / 2R over the circle.
            let r = (Vector3::new(e.x, e.y, 0.0) - centre).norm();
            assert!((r - radius).abs() < 2.0, "t {t}: radius {r} vs {radius}");
            let nose = s.q_ecef_imu * Vector3::x();
            assert!(nose.angle(&s.velocity_ecef_m_s) < 1e-3, "t {t}: nose off the velocity");
            let right = s.q_ecef_imu * Vector3::y();
            let up = g.up_ecef();
            let roll = (-right.dot(&up)).asin();
            assert!((roll - bank).abs() < 1e-3, "t {t}: roll {roll} vs bank {bank}");
        }
        check_derivatives(&tr);
        let straight = AircraftParams { turn_rate_deg_s: 0.0, ..Default::default() };
        let tr = Trajectory::new(&TrajectoryParams::Aircraft(straight.clone()), origin(), 3).unwrap();
        check_derivatives(&tr);
        let d = f.to_enu(&tr.state(straight.duration_s).position).0;
        let dist = straight.speed_m_s * straight.duration_s;
        // Heading east follows the parallel, d^2 tan(lat) / 2R (2.6 m here) north of the tangent.
        let parallel = dist * dist * origin().lat_rad().tan() / (2.0 * WGS84_A);
        assert!((d.x - dist).abs() < 1.0 && (d.y - parallel).abs() < 0.1, "straight east: {d:?}");
        let e = Trajectory::new(
            &TrajectoryParams::Aircraft(AircraftParams { h_m: 1000.0, ..Default::default() }),
            origin(),
            0,
        )
        .unwrap_err();
        assert!(e.contains("aircraft.h_m") && e.contains("terrain"), "{e}");
        for (bad, field) in [
            (AircraftParams { speed_m_s: 0.0, ..Default::default() }, "aircraft.speed_m_s"),
            (AircraftParams { heading_deg: f64::NAN, ..Default::default() }, "aircraft.heading_deg"),
            (AircraftParams { turn_rate_deg_s: 20.0, ..Default::default() }, "aircraft.turn_rate_deg_s"),
            (AircraftParams { duration_s: 0.0, ..Default::default() }, "aircraft.duration_s"),
            (AircraftParams { pitch_deg: 45.0, ..Default::default() }, "aircraft.pitch_deg"),
            (AircraftParams { wobble_deg: -1.0, ..Default::default() }, "aircraft.wobble_deg"),
            (AircraftParams { wobble_hz: 0.0, ..Default::default() }, "aircraft.wobble_hz"),
            (AircraftParams { h_m: 40_000.0, ..Default::default() }, "aircraft.h_m"),
        ] {
            let e = bad.validate().unwrap_err();
            assert!(e.contains(field), "{e}");
        }
    }

    fn check_derivatives(tr: &Trajectory) {
        let h = 1e-3;
        let n = 600;
        for i in 0..=n {
            let t = tr.duration_s() * i as f64 / n as f64;
            let (a, s, b) = (tr.state(t - h), tr.state(t), tr.state(t + h));
            let v_fd = (b.position.0 - a.position.0) / (2.0 * h);
            let a_fd = (b.velocity_ecef_m_s - a.velocity_ecef_m_s) / (2.0 * h);
            assert!(
                (v_fd - s.velocity_ecef_m_s).norm() < 1e-4,
                "t {t}: v {v_fd:?} vs {:?}",
                s.velocity_ecef_m_s
            );
            assert!((a_fd - s.accel_ecef_m_s2).norm() < 1e-4, "t {t}: a {a_fd:?} vs {:?}", s.accel_ecef_m_s2);
            let h2 = 0.02;
            let (a2, b2) = (tr.state(t - h2), tr.state(t + h2));
            let acc2 = (b2.position.0 - 2.0 * s.position.0 + a2.position.0) / (h2 * h2);
            assert!((acc2 - s.accel_ecef_m_s2).norm() < 2e-3, "t {t}: {acc2:?} vs {:?}", s.accel_ecef_m_s2);
        }
    }

    #[test]
    fn position_velocity_acceleration_consistent() {
        check_derivatives(&balloon(6));
        check_derivatives(&rocket(6));
        // Long drift: curvature handled (height above the ellipsoid, not above a plane).
        let p = BalloonParams { duration_s: Some(3000.0), descent_rate_sl_m_s: 0.0, ..Default::default() };
        let tr = Trajectory::new(&TrajectoryParams::Balloon(p), origin(), 6).unwrap();
        check_derivatives(&tr);
        let g = tr.state(3000.0).position.to_geodetic();
        assert!((g.h_m - 30_000.0).abs() < 1e-6, "{g:?}");
    }

    #[test]
    fn rocket_acceleration_is_continuous() {
        let tr = rocket(7);
        let mut prev = tr.state(0.0).accel_ecef_m_s2;
        for i in 1..=60_000 {
            let a = tr.state(i as f64 * 1e-3).accel_ecef_m_s2;
            assert!((a - prev).norm() < 0.02, "jump at {}", i as f64 * 1e-3);
            prev = a;
        }
    }

    #[test]
    fn seeds_are_deterministic() {
        let (a, b, c) = (balloon(11), balloon(11), balloon(12));
        for t in [0.0, 10.0, 77.7, a.duration_s()] {
            assert_eq!(a.state(t), b.state(t));
        }
        let (Model::Balloon(ba), Model::Balloon(bc)) = (&a.model, &c.model) else { panic!() };
        assert_ne!(ba.bursts, bc.bursts);
        assert_ne!(a.state(50.0).q_ecef_imu, c.state(50.0).q_ecef_imu);
        let (r1, r2, r3) = (rocket(1), rocket(1), rocket(2));
        assert_eq!(r1.state(33.3), r2.state(33.3));
        assert_ne!(r1.state(33.3).q_ecef_imu, r3.state(33.3).q_ecef_imu);
    }

    #[test]
    fn validate_names_the_field() {
        let err = |p: TrajectoryParams| Trajectory::new(&p, origin(), 0).unwrap_err();
        let b = BalloonParams::default;
        let r = RocketParams::default;
        let e = err(TrajectoryParams::Balloon(BalloonParams { end_h_m: 31_000.0, ..b() }));
        assert!(e.contains("balloon.start_h_m must be above end_h_m"), "{e}");
        let e = err(TrajectoryParams::Balloon(BalloonParams { burst_s: 0.0, ..b() }));
        assert!(e.contains("balloon.burst_s"), "{e}");
        let e = err(TrajectoryParams::Balloon(BalloonParams { pendulum_period_s: f64::NAN, ..b() }));
        assert!(e.contains("balloon.pendulum_period_s"), "{e}");
        let e = err(TrajectoryParams::Balloon(BalloonParams { descent_rate_sl_m_s: 0.0, ..b() }));
        assert!(e.contains("balloon.descent_rate_sl_m_s"), "{e}");
        let e = err(TrajectoryParams::Balloon(BalloonParams { end_h_m: 1000.0, ..b() }));
        assert!(e.contains("balloon.end_h_m") && e.contains("terrain"), "{e}");
        let e = err(TrajectoryParams::Rocket(RocketParams { max_speed_m_s: 100.0, ..r() }));
        assert!(e.contains("rocket.max_speed_m_s"), "{e}");
        let e = err(TrajectoryParams::Rocket(RocketParams { pitch_over_deg: 95.0, ..r() }));
        assert!(e.contains("rocket.pitch_over_deg"), "{e}");
        let e = err(TrajectoryParams::Rocket(RocketParams { duration_s: -1.0, ..r() }));
        assert!(e.contains("rocket.duration_s"), "{e}");
        assert!(TrajectoryParams::default().validate().is_ok());
        assert!(TrajectoryParams::Rocket(r()).validate().is_ok());
    }

    #[test]
    fn json_defaults_and_unknown_fields() {
        let p: TrajectoryParams = serde_json::from_str(r#"{"kind": "balloon", "start_h_m": 33000}"#).unwrap();
        assert_eq!(p, TrajectoryParams::Balloon(BalloonParams { start_h_m: 33000.0, ..Default::default() }));
        let p: TrajectoryParams = serde_json::from_str(r#"{"kind": "rocket", "duration_s": 90}"#).unwrap();
        assert_eq!(p, TrajectoryParams::Rocket(RocketParams { duration_s: 90.0, ..Default::default() }));
        let e = serde_json::from_str::<TrajectoryParams>(r#"{"kind": "rocket", "speed": 3}"#).unwrap_err();
        assert!(e.to_string().contains("speed"), "{e}");
        let back: TrajectoryParams = serde_json::from_str(&serde_json::to_string(&p).unwrap()).unwrap();
        assert_eq!(back, p);
    }

    #[test]
    fn rotvec_helpers_round_trip() {
        for v in
            [Vector3::new(1e-12, -3e-13, 2e-12), Vector3::new(0.3, -1.2, 0.7), Vector3::new(0.0, 0.0, 3.1)]
        {
            let q = exp_rotvec(&v);
            assert!((log_rotvec(&q) - v).norm() < 1e-15 * (1.0 + v.norm()) * 10.0);
            assert!(q.angle_to(&UnitQuaternion::from_scaled_axis(v)) < 1e-15);
        }
    }
}
