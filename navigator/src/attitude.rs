//! The attitude filter across frames: attitude error and gyro bias.
//!
//! Looking straight down through a narrow lens, one frame cannot tell a small
//! tilt from a sideways shift; the gyro can, if its bias is known. The filter
//! carries the covariance of `x = [dtheta (rad, rotation vector in ECEF);
//! db (rad/s, gyro bias in the IMU frame)]` (the truth is `q = exp(dtheta)
//! q_est`, `b = b_est + db`) from fix to fix, so each frame's PnP gets the
//! attitude prior the frames before it earned, and the bias is learnt as the
//! camera turns.
//!
//! Propagation over an interval with `S = integral R_ecef_imu dt`:
//! `dtheta' = dtheta - S db`, plus angle random walk on `dtheta` and a slow
//! random walk on `db`. Update: the frame's refinement is run with the
//! propagated attitude block as its prior, so its posterior attitude is the
//! Kalman update of that block; since the image sees only the attitude, the
//! bias follows from it by conditioning (Gaussian: `b | theta`), see
//! [`AttitudeFilter::update`].
//!
//! Where no gyro measures (after the IMU log's end), two fixes measure the
//! body's rate instead ([`FixRate`]).

use nalgebra::{Matrix3, Matrix6, UnitQuaternion, Vector3};
use trn_vision::pnp::rotation_vector;

/// Gyro error model (1 sigma per axis).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GyroErrors {
    /// Angle random walk (rad/sqrt(s)).
    pub arw_rad_sqrt_s: f64,
    /// Initial uncertainty of the bias (rad/s).
    pub bias_rad_s: f64,
    /// Random walk of the bias (rad/s/sqrt(s)).
    pub bias_walk_rad_s_sqrt_s: f64,
}

/// State of the filter at the last accepted fix (or carried frame).
#[derive(Clone, Debug, PartialEq)]
pub struct AttitudeFilter {
    /// Estimated gyro bias (rad/s, IMU frame), taken off the gyro samples.
    pub bias_imu_rad_s: Vector3<f64>,
    /// Covariance of `[dtheta; db]`.
    pub covariance: Matrix6<f64>,
    pub errors: GyroErrors,
}

impl AttitudeFilter {
    pub fn new(attitude_sigma_rad: f64, errors: GyroErrors) -> Self {
        let mut covariance = Matrix6::zeros();
        covariance.fixed_view_mut::<3, 3>(0, 0).fill_diagonal(attitude_sigma_rad.powi(2));
        covariance.fixed_view_mut::<3, 3>(3, 3).fill_diagonal(errors.bias_rad_s.powi(2));
        Self { bias_imu_rad_s: Vector3::zeros(), covariance, errors }
    }

    /// Covariance after an interval of `dt` seconds whose attitude-bias
    /// sensitivity is `bias_to_attitude` (see
    /// [`crate::propagate::Propagated`]).
    pub fn propagated(&self, bias_to_attitude: &Matrix3<f64>, dt: f64) -> Matrix6<f64> {
        let mut phi = Matrix6::identity();
        phi.fixed_view_mut::<3, 3>(0, 3).copy_from(&-bias_to_attitude);
        let mut p = phi * self.covariance * phi.transpose();
        let dt = dt.max(0.0);
        let e = &self.errors;
        for i in 0..3 {
            p[(i, i)] += e.arw_rad_sqrt_s.powi(2) * dt;
            p[(i + 3, i + 3)] += e.bias_walk_rad_s_sqrt_s.powi(2) * dt;
        }
        p
    }

    /// No image: the propagated covariance becomes the state.
    pub fn carry(&mut self, propagated: Matrix6<f64>) {
        self.covariance = propagated;
    }

    /// A fix whose refinement used the attitude block of `propagated` as its
    /// prior, moved the attitude by `dtheta_rad` (ECEF, posterior relative to
    /// the prior) and left it with covariance `posterior_att`.
    ///
    /// With the prior `P = [Ptt Ptb; Pbt Pbb]`, `K = Pbt Ptt^-1`, the bias
    /// conditioned on the attitude gives `db = K dtheta`, `Pbt' = K Ptt'`,
    /// `Pbb' = Pbb - K (Ptt - Ptt') K^T`: the same as a Kalman update with
    /// `H = [I 0]` whatever the image's own attitude information was.
    /// Returns false (and keeps only the attitude part) when `Ptt` cannot be
    /// inverted.
    pub fn update(
        &mut self,
        propagated: &Matrix6<f64>,
        dtheta_rad: &Vector3<f64>,
        posterior_att: &Matrix3<f64>,
    ) -> bool {
        let ptt = propagated.fixed_view::<3, 3>(0, 0).into_owned();
        let pbt = propagated.fixed_view::<3, 3>(3, 0).into_owned();
        let pbb = propagated.fixed_view::<3, 3>(3, 3).into_owned();
        let Some(ptt_inv) = ptt.cholesky().map(|c| c.inverse()) else {
            self.reset_attitude(propagated, posterior_att);
            return false;
        };
        let k = pbt * ptt_inv;
        self.bias_imu_rad_s += k * dtheta_rad;
        let pbt_new = k * posterior_att;
        let mut pbb_new = pbb - k * (ptt - posterior_att) * k.transpose();
        pbb_new = (pbb_new + pbb_new.transpose()) * 0.5;
        let mut p = Matrix6::zeros();
        p.fixed_view_mut::<3, 3>(0, 0).copy_from(&((posterior_att + posterior_att.transpose()) * 0.5));
        p.fixed_view_mut::<3, 3>(3, 0).copy_from(&pbt_new);
        p.fixed_view_mut::<3, 3>(0, 3).copy_from(&pbt_new.transpose());
        p.fixed_view_mut::<3, 3>(3, 3).copy_from(&pbb_new);
        self.covariance = p;
        true
    }

    /// A fix whose attitude did not come from this filter's prior (the image
    /// disagreed with it): keep the bias and its uncertainty, drop the
    /// attitude-bias correlation.
    pub fn reset_attitude(&mut self, propagated: &Matrix6<f64>, posterior_att: &Matrix3<f64>) {
        let mut p = Matrix6::zeros();
        p.fixed_view_mut::<3, 3>(0, 0).copy_from(posterior_att);
        p.fixed_view_mut::<3, 3>(3, 3).copy_from(&propagated.fixed_view::<3, 3>(3, 3));
        self.covariance = p;
    }
}

/// `--filter fixes` after the IMU log's last sample: the body's rate
/// from the turn between the last two accepted fixes (both after it, at
/// most [`FIX_RATE_MAX_SPAN_S`] apart), carried on as the inertial filter
/// carries the rate it learns there.
#[derive(Clone, Copy, Debug)]
pub struct FixRate {
    /// The later fix's time (s): the rate's error walks from there.
    pub t: f64,
    /// The rate (rad/s, ECEF rotation vector per second) beyond the
    /// Earth's turn, which the propagation applies itself: zero for a body
    /// fixed in inertial space.
    pub w_ecef_rad_s: Vector3<f64>,
    /// Its error (rad/s, 1 sigma per axis): the two fixes' attitude
    /// sigmas over the time between them.
    pub sigma_rad_s: f64,
}

/// An accepted fix's attitude, for [`FixRate`].
#[derive(Clone, Copy, Debug)]
pub struct FixAttitude {
    /// Its time (s).
    pub t: f64,
    pub q_ecef_cam: UnitQuaternion<f64>,
    /// Its attitude variance (rad², per axis).
    pub var_rad2: f64,
}

impl FixRate {
    /// The rate that turned `earlier`'s attitude into `later`'s (`None`
    /// unless they are `(0, FIX_RATE_MAX_SPAN_S]` apart), its error the two
    /// attitudes' over the time between them. A body that wobbles (a
    /// rocket's roll, a balloon's swing) changes its rate from one pair
    /// of fixes to the next: the change since the estimate `before` is
    /// doubted as much again.
    pub fn between(earlier: &FixAttitude, later: &FixAttitude, before: Option<&FixRate>) -> Option<Self> {
        let dt = later.t - earlier.t;
        if !(dt > 0.0 && dt <= FIX_RATE_MAX_SPAN_S) {
            return None;
        }
        let seen = rotation_vector(&(later.q_ecef_cam * earlier.q_ecef_cam.inverse())) / dt;
        let w_ecef_rad_s = seen + Vector3::new(0.0, 0.0, trn_geodesy::EARTH_RATE_RAD_S);
        let change = before.map_or(0.0, |r| (w_ecef_rad_s - r.w_ecef_rad_s).norm_squared() / 3.0);
        let measured = (earlier.var_rad2 + later.var_rad2).max(0.0) / (dt * dt);
        Some(FixRate { t: later.t, w_ecef_rad_s, sigma_rad_s: (measured + change).sqrt() })
    }

    /// The turn (ECEF, on the left of an attitude) of this rate over `d`
    /// seconds, and the attitude variance (rad² per axis) its error adds.
    pub fn turn(&self, d: f64) -> (UnitQuaternion<f64>, f64) {
        (UnitQuaternion::from_scaled_axis(self.w_ecef_rad_s * d), (self.sigma_rad_s * d).powi(2))
    }
}

/// The most time between two fixes whose turn measures the body's rate
/// after the IMU log ([`FixRate`]): a balloon's pendulum swings with a
/// period of seconds.
pub const FIX_RATE_MAX_SPAN_S: f64 = 1.5;

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{SMatrix, UnitQuaternion, Vector6};

    fn errors() -> GyroErrors {
        GyroErrors {
            arw_rad_sqrt_s: 0.005f64.to_radians(),
            bias_rad_s: 0.01f64.to_radians(),
            bias_walk_rad_s_sqrt_s: 5e-8,
        }
    }

    /// A random symmetric positive definite matrix.
    fn spd<const N: usize>(seed: u64, scale: f64) -> SMatrix<f64, N, N> {
        let mut s = seed;
        let a = SMatrix::<f64, N, N>::from_fn(|_, _| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        });
        (a * a.transpose() + SMatrix::<f64, N, N>::identity() * 0.1) * scale
    }

    #[test]
    fn update_equals_the_full_kalman_update() {
        // Independent reference: the textbook 6-state Kalman update with
        // H = [I 0], measurement z of the attitude with covariance R.
        for seed in 1..20 {
            let p = spd::<6>(seed, 1e-6);
            let r = spd::<3>(seed + 100, 1e-6);
            let z = Vector3::new(1e-3, -2e-3, 5e-4) * seed as f64;
            let mut h = SMatrix::<f64, 3, 6>::zeros();
            h.fixed_view_mut::<3, 3>(0, 0).fill_diagonal(1.0);
            let s = h * p * h.transpose() + r;
            let k = p * h.transpose() * s.try_inverse().unwrap();
            let x_ref: Vector6<f64> = k * z;
            let p_ref = (Matrix6::identity() - k * h) * p;
            // What the refinement returns: the attitude block's update.
            let ptt = p.fixed_view::<3, 3>(0, 0).into_owned();
            let post_att = (ptt.try_inverse().unwrap() + r.try_inverse().unwrap()).try_inverse().unwrap();
            let dtheta = post_att * r.try_inverse().unwrap() * z;
            let mut f = AttitudeFilter::new(0.0, errors());
            assert!(f.update(&p, &dtheta, &post_att));
            let scale = p.abs().max();
            assert!(
                (f.covariance - p_ref).abs().max() < 1e-9 * scale,
                "seed {seed}\n{}\n{p_ref}",
                f.covariance
            );
            let db_ref = x_ref.fixed_rows::<3>(3).into_owned();
            assert!((f.bias_imu_rad_s - db_ref).norm() < 1e-9 * db_ref.norm().max(1e-12), "seed {seed}");
        }
    }

    #[test]
    fn learns_a_constant_bias_as_the_body_turns() {
        // Truth: the body spins about its z axis at 3 deg/s, tilted; the gyro
        // has a constant bias. Attitude measurements every 0.25 s are good
        // about the spin axis' tilt only in one direction (like a nadir view:
        // 0.02 deg about ECEF x, 0.002 deg about y and z).
        let dt = 0.25;
        let bias_true = Vector3::new(10.0, -7.0, 4.0) * (1.0f64 / 3600.0).to_radians(); // deg/h
        let spin = 3f64.to_radians();
        let q_tilt = UnitQuaternion::from_euler_angles(0.4, -0.2, 0.1);
        let r_meas =
            Matrix3::from_diagonal(&Vector3::new(0.02f64, 0.002, 0.002).map(|d| d.to_radians().powi(2)));
        let mut f = AttitudeFilter::new(2f64.to_radians(), errors());
        // Estimated attitude error (truth = exp(err) * estimate), simulated linearly.
        let mut err = Vector3::new(0.01, -0.02, 0.005);
        let mut rng = 12345u64;
        let mut gauss = || {
            // Box-Muller from an LCG: deterministic.
            let mut u = || {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((rng >> 11) as f64 + 0.5) / (1u64 << 53) as f64
            };
            (-2.0 * u().ln()).sqrt() * (2.0 * std::f64::consts::PI * u()).cos()
        };
        let mut late_err = 0.0;
        let mut n_late = 0;
        for k in 0..2400 {
            let t = k as f64 * dt;
            // S = integral of R_ecef_imu over the step (midpoint).
            let r_mid = (q_tilt * UnitQuaternion::from_axis_angle(&Vector3::z_axis(), spin * (t + dt / 2.0)))
                .to_rotation_matrix()
                .into_inner();
            let s = r_mid * dt;
            // The estimate integrates gyro - bias_est: its error grows by -S (b_true - b_est).
            err -= s * (bias_true - f.bias_imu_rad_s);
            let prop = f.propagated(&s, dt);
            // The measurement of the attitude error, and the posterior of the attitude block.
            let noise = Vector3::new(gauss(), gauss(), gauss());
            let z = err + r_meas.map(f64::sqrt).diagonal().component_mul(&noise);
            let ptt = prop.fixed_view::<3, 3>(0, 0).into_owned();
            let post = (ptt.try_inverse().unwrap() + r_meas.try_inverse().unwrap()).try_inverse().unwrap();
            let dtheta = post * r_meas.try_inverse().unwrap() * z;
            assert!(f.update(&prop, &dtheta, &post));
            err -= dtheta;
            if k >= 1800 {
                late_err += (bias_true - f.bias_imu_rad_s).norm();
                n_late += 1;
            }
        }
        let late = late_err / n_late as f64;
        let sd = f.covariance.fixed_view::<3, 3>(3, 3).trace().sqrt();
        println!(
            "bias error after 450-600 s: {:.3} deg/h (filter sigma {:.3} deg/h, bias {:.1} deg/h)",
            late.to_degrees() * 3600.0,
            sd.to_degrees() * 3600.0,
            bias_true.norm().to_degrees() * 3600.0
        );
        assert!(late < 0.2 * bias_true.norm(), "{}", late.to_degrees() * 3600.0);
        assert!(late < 3.0 * sd);
    }

    #[test]
    fn propagation_grows_the_attitude_through_the_bias() {
        let f = AttitudeFilter::new(0.0, errors());
        let s = Matrix3::identity() * 0.5;
        let p = f.propagated(&s, 0.5);
        let e = errors();
        let want = 0.25 * e.bias_rad_s.powi(2) + e.arw_rad_sqrt_s.powi(2) * 0.5;
        assert!((p[(0, 0)] - want).abs() < 1e-12 * want);
        assert!((p[(0, 3)] + 0.5 * e.bias_rad_s.powi(2)).abs() < 1e-20);
    }

    /// [`FixRate::between`] on synthetic attitudes: a steady 2 deg/s turn
    /// is measured and carried on to within the fixes' doubt; fixes too far
    /// apart measure nothing; a rate that changed since the last estimate
    /// (a wobble) is doubted by the change.
    #[test]
    fn two_fixes_measure_the_rate_after_the_log() {
        let q0 = UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1);
        let w = Vector3::new(0.5, -1.0, 1.5).normalize() * 2f64.to_radians();
        // In ECEF the body turns at its rate less the Earth's.
        let earth = Vector3::new(0.0, 0.0, trn_geodesy::EARTH_RATE_RAD_S);
        let at = |t: f64, w: &Vector3<f64>| FixAttitude {
            t,
            q_ecef_cam: UnitQuaternion::from_scaled_axis((w - earth) * t) * q0,
            var_rad2: 0.01f64.to_radians().powi(2),
        };
        // Fixed in inertial space: no rate of its own.
        let still = FixRate::between(&at(0.0, &Vector3::zeros()), &at(1.0, &Vector3::zeros()), None).unwrap();
        assert!(still.w_ecef_rad_s.norm() < 1e-15, "{:?}", still.w_ecef_rad_s);
        let r = FixRate::between(&at(0.0, &w), &at(0.5, &w), None).unwrap();
        assert!((r.w_ecef_rad_s - w).norm() < 1e-12, "{:?}", r.w_ecef_rad_s);
        assert_eq!(r.t, 0.5);
        // Two fixes' 0.01 deg over 0.5 s.
        assert!((r.sigma_rad_s.to_degrees() - 0.01 * 2f64.sqrt() / 0.5).abs() < 1e-9, "{}", r.sigma_rad_s);
        // Carried on 1 s with the Earth's turn (as the propagation does):
        // the attitude there (to the two turns' product's second order,
        // |w x earth| / 2, 1.3e-6 rad).
        let (turn, var) = r.turn(1.0);
        let predicted = turn * UnitQuaternion::from_scaled_axis(-earth) * at(0.5, &w).q_ecef_cam;
        let off = predicted.angle_to(&at(1.5, &w).q_ecef_cam);
        assert!(off < 2e-6, "{off}");
        assert!((var.sqrt() - r.sigma_rad_s).abs() < 1e-15);
        // Too far apart, or out of order: nothing.
        assert!(FixRate::between(&at(0.0, &w), &at(2.0, &w), None).is_none());
        assert!(FixRate::between(&at(0.5, &w), &at(0.0, &w), None).is_none());
        // The rate changed by 3 deg/s since the last estimate: doubted by
        // that change, 3/sqrt(3) deg/s per axis, on top of the fixes'.
        let w2 = w + Vector3::new(3f64.to_radians(), 0.0, 0.0);
        let r2 = FixRate::between(&at(0.0, &w2), &at(0.5, &w2), Some(&r)).unwrap();
        assert!((r2.w_ecef_rad_s - w2).norm() < 1e-12);
        let expect = (r.sigma_rad_s.powi(2) + 3f64.to_radians().powi(2) / 3.0).sqrt();
        assert!((r2.sigma_rad_s - expect).abs() < 1e-12, "{} vs {expect}", r2.sigma_rad_s);
    }
}
