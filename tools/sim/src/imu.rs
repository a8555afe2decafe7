//! Gyro and accelerometer synthesis from a [`Trajectory`]. Pure math, no I/O.
//!
//! Gyro: the inertial frame I coincides with ECEF at t = 0 and ECEF turns about
//! its z axis at [`EARTH_RATE_RAD_S`], so `q_I_imu(t) = Rz(w_e t) * q_ecef_imu(t)`.
//! The noise-free sample at `t_k` is the rotation vector of the increment
//! `q_I_imu(t_{k-1})^-1 * q_I_imu(t_k)` divided by the period: the mean rate over
//! the interval ending at `t_k` (a delta angle, coning-free), so integrating the
//! noise-free samples with the exact exponential ([`integrate_exact`]) gives
//! back the true attitude to rounding. Noise: a constant bias per axis and white
//! noise (angle random walk).
//!
//! Accelerometer: specific force in the IMU frame at `t_k`,
//! `f = R_imu_ecef (a_rel + 2 w_e x v + w_e x (w_e x r) - G(r))`, with the
//! gravitation `G` of a point mass plus J2 ([`gravitation_ecef`]; it differs
//! from WGS84 normal gravity by ~1e-4 m/s^2), plus a constant bias per axis
//! and white noise.

use nalgebra::{UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};
use trn_flight::ImuSample;
pub use trn_geodesy::gravity::{gravitation_ecef, GM_M3_S2, J2};
use trn_geodesy::EARTH_RATE_RAD_S;

use crate::rng::Rng;
use crate::trajectory::{exp_rotvec, log_rotvec, BodyState, Trajectory};

/// IMU model (`"imu"` of a scenario).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ImuParams {
    /// Sample rate (Hz), at least 200.
    pub rate_hz: f64,
    /// Gyro bias: each axis' constant bias is drawn from N(0, this) (deg/h).
    pub gyro_bias_deg_h: f64,
    /// Gyro angle random walk (deg/sqrt(h)).
    pub gyro_arw_deg_sqrt_h: f64,
    /// Whether the accelerometer is recorded.
    pub accelerometer: bool,
    /// Accelerometer white noise, standard deviation per sample and axis (m/s^2).
    pub accel_noise_m_s2: f64,
    /// Accelerometer bias: each axis' constant bias is drawn from N(0, this) (m/s^2).
    pub accel_bias_m_s2: f64,
}

impl Default for ImuParams {
    fn default() -> Self {
        Self {
            rate_hz: 200.0,
            gyro_bias_deg_h: 10.0,
            gyro_arw_deg_sqrt_h: 0.15,
            accelerometer: true,
            accel_noise_m_s2: 0.01,
            accel_bias_m_s2: 0.02,
        }
    }
}

impl ImuParams {
    /// Checks the parameters; the error names the bad field.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.rate_hz.is_finite() && self.rate_hz >= 200.0) {
            return Err(format!("imu.rate_hz must be >= 200 (got {})", self.rate_hz));
        }
        for (name, v) in [
            ("imu.gyro_bias_deg_h", self.gyro_bias_deg_h),
            ("imu.gyro_arw_deg_sqrt_h", self.gyro_arw_deg_sqrt_h),
            ("imu.accel_noise_m_s2", self.accel_noise_m_s2),
            ("imu.accel_bias_m_s2", self.accel_bias_m_s2),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be >= 0 (got {v})"));
            }
        }
        Ok(())
    }
}

/// Rotation from ECEF at time `t` to the inertial frame (ECEF at t = 0).
fn q_i_ecef(t: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_axis_angle(&Vector3::z_axis(), EARTH_RATE_RAD_S * t)
}

/// Noise-free specific force in the IMU frame (m/s^2) of a state.
pub fn specific_force_imu(s: &BodyState) -> Vector3<f64> {
    let w = Vector3::new(0.0, 0.0, EARTH_RATE_RAD_S);
    let r = s.position.0;
    let f_ecef = s.accel_ecef_m_s2 + 2.0 * w.cross(&s.velocity_ecef_m_s) + w.cross(&w.cross(&r))
        - gravitation_ecef(&r);
    s.q_ecef_imu.inverse() * f_ecef
}

/// Gyro (and accelerometer) samples at `t_k = t_start + k / rate_hz` for all
/// `t_k <= t_end`. `noise_free` drops biases and noise. The seed draws biases
/// and noise from streams of their own, so enabling the accelerometer does not
/// change the gyro.
pub fn synthesize(
    traj: &Trajectory,
    params: &ImuParams,
    t_start: f64,
    t_end: f64,
    seed: u64,
    noise_free: bool,
) -> Vec<ImuSample> {
    synthesize_from(|t| traj.state(t), params, t_start, t_end, seed, noise_free)
}

/// [`synthesize`] for any state function (a vehicle at rest, a test trajectory).
pub fn synthesize_from(
    state: impl Fn(f64) -> BodyState,
    params: &ImuParams,
    t_start: f64,
    t_end: f64,
    seed: u64,
    noise_free: bool,
) -> Vec<ImuSample> {
    assert!(params.rate_hz > 0.0 && params.rate_hz.is_finite(), "imu.rate_hz must be > 0");
    let dt = 1.0 / params.rate_hz;
    if t_end < t_start || t_end.is_nan() || t_start.is_nan() {
        return Vec::new();
    }
    let n = ((t_end - t_start) * params.rate_hz + 1e-9).floor() as usize + 1;

    let deg = std::f64::consts::PI / 180.0;
    let draw3 = |purpose: &str, sigma: f64| {
        let mut r = Rng::stream(seed, purpose);
        Vector3::new(r.normal(), r.normal(), r.normal()) * sigma
    };
    let (gyro_bias, accel_bias) = if noise_free {
        (Vector3::zeros(), Vector3::zeros())
    } else {
        (
            draw3("gyro_bias", params.gyro_bias_deg_h * deg / 3600.0),
            draw3("accel_bias", params.accel_bias_m_s2),
        )
    };
    // ARW (rad/sqrt(s)) over a sample period.
    let gyro_sigma = params.gyro_arw_deg_sqrt_h * deg / 60.0 / dt.sqrt();
    let mut gyro_rng = Rng::stream(seed, "gyro_noise");
    let mut accel_rng = Rng::stream(seed, "accel_noise");

    let mut q_prev = q_i_ecef(t_start - dt) * state(t_start - dt).q_ecef_imu;
    let mut out = Vec::with_capacity(n);
    for k in 0..n {
        let t = t_start + k as f64 * dt;
        let s = state(t);
        let q = q_i_ecef(t) * s.q_ecef_imu;
        let mut w = log_rotvec(&(q_prev.inverse() * q)) / dt;
        q_prev = q;
        let mut f = params.accelerometer.then(|| specific_force_imu(&s));
        if !noise_free {
            let g = Vector3::new(gyro_rng.normal(), gyro_rng.normal(), gyro_rng.normal());
            w += gyro_bias + g * gyro_sigma;
            if let Some(f) = f.as_mut() {
                let a = Vector3::new(accel_rng.normal(), accel_rng.normal(), accel_rng.normal());
                *f += accel_bias + a * params.accel_noise_m_s2;
            }
        }
        out.push(ImuSample { t, w_imu_rad_s: w, f_imu_m_s2: f });
    }
    out
}

/// Integrates gyro samples from a known attitude `q_ecef_imu_0` at `t0` with the
/// exact exponential, removing the Earth rotation: `(t, q_ecef_imu(t))` at `t0`
/// (first element) and at every sample time after `t0`. Each sample covers the
/// interval since the previous sample (since `t0` for the first one used).
pub fn integrate_exact(
    q_ecef_imu_0: UnitQuaternion<f64>,
    t0: f64,
    samples: &[ImuSample],
) -> Vec<(f64, UnitQuaternion<f64>)> {
    let mut q = q_i_ecef(t0) * q_ecef_imu_0;
    let mut t_prev = t0;
    let mut out = vec![(t0, q_ecef_imu_0)];
    for s in samples.iter().filter(|s| s.t > t0) {
        q *= exp_rotvec(&(s.w_imu_rad_s * (s.t - t_prev)));
        q.renormalize();
        t_prev = s.t;
        out.push((s.t, q_i_ecef(-s.t) * q));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::trajectory::{BalloonParams, RocketParams, TrajectoryParams};
    use nalgebra::Quaternion;
    use trn_geodesy::Geodetic;

    fn origin() -> Geodetic {
        Geodetic::new(32.9, -106.4, 1250.0)
    }

    fn balloon(seed: u64) -> Trajectory {
        Trajectory::new(&TrajectoryParams::Balloon(BalloonParams::default()), origin(), seed).unwrap()
    }

    fn rocket(seed: u64) -> Trajectory {
        Trajectory::new(&TrajectoryParams::Rocket(RocketParams::default()), origin(), seed).unwrap()
    }

    /// A vehicle at rest at `g`, body axes NED-like with heading 30 deg.
    fn at_rest(g: Geodetic) -> impl Fn(f64) -> BodyState {
        let (lat, lon) = (g.lat_rad(), g.lon_rad());
        let pi = std::f64::consts::PI;
        let s = std::f64::consts::FRAC_1_SQRT_2;
        let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), lon + pi / 2.0)
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), pi / 2.0 - lat)
            * UnitQuaternion::new_unchecked(Quaternion::new(0.0, s, s, 0.0))
            * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 30f64.to_radians());
        let r = g.to_ecef();
        move |t| BodyState {
            t,
            position: r,
            velocity_ecef_m_s: Vector3::zeros(),
            accel_ecef_m_s2: Vector3::zeros(),
            q_ecef_imu: q,
        }
    }

    fn max_error(tr: &Trajectory, est: &[(f64, UnitQuaternion<f64>)]) -> f64 {
        est.iter().map(|(t, q)| q.angle_to(&tr.state(*t).q_ecef_imu)).fold(0.0, f64::max)
    }

    #[test]
    fn noise_free_gyro_integrates_to_truth() {
        let p = ImuParams::default();
        for tr in [balloon(1), rocket(1)] {
            let imu = synthesize(&tr, &p, 0.0, tr.duration_s(), 9, true);
            assert_eq!(imu.len(), (tr.duration_s() * 200.0 + 1e-9).floor() as usize + 1);
            assert!(imu.iter().enumerate().all(|(k, s)| (s.t - k as f64 / 200.0).abs() < 1e-12));
            let est = integrate_exact(tr.state(0.0).q_ecef_imu, 0.0, &imu);
            assert_eq!(est.len(), imu.len());
            let e = max_error(&tr, &est);
            assert!(e < 1e-9, "exact integration error {e}");
            // The first sample looks back one period: integrating it from t0 - dt works too.
            let est = integrate_exact(tr.state(-0.005).q_ecef_imu, -0.005, &imu);
            assert!(max_error(&tr, &est) < 1e-9);
            // Started later, at a sample time.
            let est = integrate_exact(tr.state(imu[1000].t).q_ecef_imu, imu[1000].t, &imu);
            assert!(max_error(&tr, &est) < 1e-9);
            // The flights do rotate.
            let peak = imu.iter().map(|s| s.w_imu_rad_s.norm()).fold(0.0, f64::max);
            assert!(peak > 0.05, "{peak}");
        }
    }

    #[test]
    fn second_order_strapdown_tracks_truth() {
        let p = ImuParams::default();
        for tr in [balloon(2), rocket(2)] {
            let imu = synthesize(&tr, &p, 0.0, tr.duration_s(), 9, true);
            let dt = 1.0 / p.rate_hz;
            let mut q = tr.state(0.0).q_ecef_imu;
            let mut worst: f64 = 0.0;
            for s in &imu[1..] {
                let w = s.w_imu_rad_s;
                let d = Quaternion::from_parts(1.0 - w.norm_squared() * dt * dt / 8.0, w * (dt / 2.0));
                let e = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -EARTH_RATE_RAD_S * dt);
                q = e * UnitQuaternion::from_quaternion(q.into_inner() * d);
                worst = worst.max(q.angle_to(&tr.state(s.t).q_ecef_imu));
            }
            assert!(worst < 1e-5, "second-order strapdown error {worst}");
        }
    }

    #[test]
    fn stationary_gyro_reads_earth_rate() {
        let imu = synthesize_from(at_rest(origin()), &ImuParams::default(), 10.0, 20.0, 0, true);
        let q = at_rest(origin())(0.0).q_ecef_imu;
        for s in &imu {
            assert!((s.w_imu_rad_s.norm() / 7.292115e-5 - 1.0).abs() < 1e-9, "{}", s.w_imu_rad_s.norm());
            let w_ecef = q * s.w_imu_rad_s;
            assert!(w_ecef.angle(&Vector3::z()) < 1e-8, "{w_ecef:?}");
        }
        // A hovering balloon (degenerate parameters) reads it as well.
        let p = BalloonParams {
            duration_s: Some(30.0),
            descent_rate_sl_m_s: 0.0,
            drift_east_m_s: 0.0,
            drift_north_m_s: 0.0,
            drift_var_m_s: 0.0,
            yaw_rate_deg_s: 0.0,
            spin_bursts: 0,
            pendulum_deg: 0.0,
            ..Default::default()
        };
        let tr = Trajectory::new(&TrajectoryParams::Balloon(p), origin(), 3).unwrap();
        for s in synthesize(&tr, &ImuParams::default(), 0.0, 30.0, 0, true) {
            let w_ecef = tr.state(s.t).q_ecef_imu * s.w_imu_rad_s;
            assert!((w_ecef - Vector3::new(0.0, 0.0, EARTH_RATE_RAD_S)).norm() < 2e-12, "{w_ecef:?}");
        }
    }

    use trn_geodesy::gravity::normal_gravity_m_s2 as normal_gravity;

    #[test]
    fn accelerometer_at_rest_reads_normal_gravity_upward() {
        for g in [origin(), Geodetic::new(0.0, 10.0, 0.0), Geodetic::new(-67.0, 120.0, 3000.0)] {
            let state = at_rest(g);
            let q = state(0.0).q_ecef_imu;
            let imu = synthesize_from(state, &ImuParams::default(), 0.0, 1.0, 0, true);
            for s in &imu {
                let f = q * s.f_imu_m_s2.unwrap();
                let gamma = normal_gravity(&g);
                assert!((f.norm() - gamma).abs() < 5e-4, "{g:?}: |f| {} vs {gamma}", f.norm());
                assert!(f.angle(&g.up_ecef()) < 2e-5, "{g:?}: {}", f.angle(&g.up_ecef()));
            }
        }
        // With noise: bias and noise of the set size.
        let p = ImuParams::default();
        let state = at_rest(origin());
        let clean = synthesize_from(&state, &p, 0.0, 100.0, 4, true);
        let noisy = synthesize_from(&state, &p, 0.0, 100.0, 4, false);
        let d: Vec<Vector3<f64>> =
            clean.iter().zip(&noisy).map(|(a, b)| b.f_imu_m_s2.unwrap() - a.f_imu_m_s2.unwrap()).collect();
        let mean = d.iter().sum::<Vector3<f64>>() / d.len() as f64;
        let var = d.iter().map(|x| (x - mean).norm_squared()).sum::<f64>() / (3 * d.len()) as f64;
        assert!((var.sqrt() / p.accel_noise_m_s2 - 1.0).abs() < 0.05, "{}", var.sqrt());
        assert!(mean.norm() > 1e-4 && mean.norm() < 5.0 * p.accel_bias_m_s2, "{mean:?}");
        // Without the accelerometer, no specific force and the same gyro.
        let q = ImuParams { accelerometer: false, ..p };
        let nof = synthesize_from(&state, &q, 0.0, 100.0, 4, false);
        assert!(nof
            .iter()
            .zip(&noisy)
            .all(|(a, b)| a.f_imu_m_s2.is_none() && a.w_imu_rad_s == b.w_imu_rad_s));
    }

    #[test]
    fn accelerometer_in_flight_matches_kinematics() {
        // Rocket at constant speed on a fixed path: specific force = -gravity (+ Coriolis), i.e. ~g up.
        let tr = rocket(5);
        let imu = synthesize(&tr, &ImuParams::default(), 50.0, 60.0, 0, true);
        for s in &imu {
            let st = tr.state(s.t);
            let f = st.q_ecef_imu * s.f_imu_m_s2.unwrap();
            let g = st.position.to_geodetic();
            let up = g.up_ecef();
            assert!(
                (f.dot(&up) - normal_gravity(&g)).abs() < 0.01 && (f - up * f.dot(&up)).norm() < 0.05,
                "{f:?}"
            );
        }
        // While accelerating along a vertical path: g + a along the long axis (-z body).
        let imu = synthesize(&tr, &ImuParams::default(), 0.0, 4.0, 0, true);
        for s in &imu {
            let f = s.f_imu_m_s2.unwrap();
            let st = tr.state(s.t);
            let g = st.position.to_geodetic();
            assert!((-f.z - (normal_gravity(&g) + 12.0)).abs() < 0.01, "{f:?}");
            // In ECEF: gravity reaction plus the acceleration, Coriolis aside.
            let f_ecef = st.q_ecef_imu * f;
            let expect = g.up_ecef() * normal_gravity(&g) + st.accel_ecef_m_s2;
            assert!((f_ecef - expect).norm() < 0.05, "{f_ecef:?} vs {expect:?}");
        }
    }

    fn mean_square_error(params: &ImuParams, t_end: f64, seeds: u64) -> f64 {
        let state = at_rest(origin());
        let q0 = state(0.0).q_ecef_imu;
        let mut sum = 0.0;
        for seed in 0..seeds {
            let imu = synthesize_from(&state, params, 0.0, t_end, seed, false);
            let (_, q) = *integrate_exact(q0, 0.0, &imu).last().unwrap();
            sum += q.angle_to(&q0).powi(2);
        }
        sum / seeds as f64
    }

    #[test]
    fn noise_grows_as_random_walk_and_bias() {
        let deg = std::f64::consts::PI / 180.0;
        let t = 200.0;
        // Angle random walk only: E|err|^2 = 3 arw^2 t.
        let p = ImuParams { gyro_bias_deg_h: 0.0, gyro_arw_deg_sqrt_h: 0.5, ..Default::default() };
        let ratio = mean_square_error(&p, t, 32) / (3.0 * (0.5 * deg / 60.0).powi(2) * t);
        assert!((0.6..1.5).contains(&ratio), "ARW ratio {ratio}");
        // Bias only: E|err|^2 = 3 (sigma_b t)^2.
        let p = ImuParams { gyro_bias_deg_h: 10.0, gyro_arw_deg_sqrt_h: 0.0, ..Default::default() };
        let ratio = mean_square_error(&p, t, 32) / (3.0 * (10.0 * deg / 3600.0 * t).powi(2));
        assert!((0.6..1.5).contains(&ratio), "bias ratio {ratio}");
        // Default noise over a spinning balloon flight: of the expected size, growing in time.
        let tr = balloon(8);
        let p = ImuParams::default();
        let d = tr.duration_s();
        let (mut early, mut late) = (0.0, 0.0);
        for seed in 0..8 {
            let imu = synthesize(&tr, &p, 0.0, d, seed, false);
            let est = integrate_exact(tr.state(0.0).q_ecef_imu, 0.0, &imu);
            let err = |i: usize| est[i].1.angle_to(&tr.state(est[i].0).q_ecef_imu).powi(2);
            early += err(est.len() / 4);
            late += err(est.len() - 1);
        }
        let bound = |t: f64| (0.15 * deg / 60.0 * t.sqrt() + 10.0 * deg / 3600.0 * t) * 3f64.sqrt();
        let rms_late = (late / 8.0).sqrt();
        assert!(rms_late > 0.2 * bound(d) && rms_late < 1.5 * bound(d), "{rms_late} vs {}", bound(d));
        assert!(late > 2.0 * early, "error does not grow: {early} {late}");
    }

    #[test]
    fn seeds_are_deterministic() {
        let tr = rocket(1);
        let p = ImuParams::default();
        let a = synthesize(&tr, &p, 0.0, 5.0, 42, false);
        let b = synthesize(&tr, &p, 0.0, 5.0, 42, false);
        let c = synthesize(&tr, &p, 0.0, 5.0, 43, false);
        assert_eq!(a, b);
        assert_ne!(a[10].w_imu_rad_s, c[10].w_imu_rad_s);
        assert_ne!(a[10].f_imu_m_s2, c[10].f_imu_m_s2);
        let clean = synthesize(&tr, &p, 0.0, 5.0, 42, true);
        assert_eq!(clean, synthesize(&tr, &p, 0.0, 5.0, 43, true));
    }

    #[test]
    fn validate_names_the_field() {
        assert!(ImuParams::default().validate().is_ok());
        let e = ImuParams { rate_hz: 100.0, ..Default::default() }.validate().unwrap_err();
        assert!(e.contains("imu.rate_hz"), "{e}");
        let e = ImuParams { gyro_arw_deg_sqrt_h: -1.0, ..Default::default() }.validate().unwrap_err();
        assert!(e.contains("imu.gyro_arw_deg_sqrt_h"), "{e}");
        let p: ImuParams = serde_json::from_str(r#"{"rate_hz": 400}"#).unwrap();
        assert_eq!(p, ImuParams { rate_hz: 400.0, ..Default::default() });
        assert!(serde_json::from_str::<ImuParams>(r#"{"rate": 400}"#).is_err());
    }
}
