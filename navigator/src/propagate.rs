//! Attitude propagation with the gyro between images: the second-order
//! strapdown quaternion expansion `dq = [1 - |w|^2 dt^2 / 8, w dt / 2]` per
//! sample, with the Earth's rotation taken out (the gyro measures rates
//! relative to inertial space; the pose lives in ECEF).

use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};
use trn_flight::ImuSample;
use trn_geodesy::EARTH_RATE_RAD_S;

/// Second-order increment for a rate `w` (rad/s) held for `dt` seconds.
#[inline]
pub fn strapdown_increment(w: &Vector3<f64>, dt: f64) -> UnitQuaternion<f64> {
    let half = w * (0.5 * dt);
    UnitQuaternion::from_quaternion(Quaternion::new(
        1.0 - w.norm_squared() * dt * dt / 8.0,
        half.x,
        half.y,
        half.z,
    ))
}

/// `q_ecef_imu` at `t1` from its value at `t0`, through the gyro samples
/// (each the mean rate over the interval ending at its time; the first
/// sample's interval is taken as long as the second's). Parts of
/// `[t0, t1]` no sample covers keep the attitude fixed in inertial space.
pub fn propagate(
    q_ecef_imu: UnitQuaternion<f64>,
    t0: f64,
    t1: f64,
    imu: &[ImuSample],
) -> UnitQuaternion<f64> {
    propagate_with_bias(q_ecef_imu, t0, t1, imu, &Vector3::zeros()).q_ecef_imu
}

/// Walks `[t0, t1]` through the IMU samples: `visit(a, b, Some(k))` for the
/// part `[a, b]` that sample `k`'s interval covers (each sample holds over
/// the interval ending at its time; the first sample's is taken as long as
/// the second's), `visit(a, b, None)` for time no sample covers (before the
/// first sample or after the last), in time order.
pub fn for_each_segment(imu: &[ImuSample], t0: f64, t1: f64, mut visit: impl FnMut(f64, f64, Option<usize>)) {
    if !(t1 > t0) {
        return;
    }
    let start = imu.partition_point(|s| s.t <= t0);
    let mut covered = t0;
    for k in start..imu.len() {
        let end = imu[k].t;
        let begin = if k > 0 { imu[k - 1].t } else { imu.get(1).map_or(end, |n| end - (n.t - end)) };
        let (a, b) = (begin.max(t0), end.min(t1));
        if b > a {
            if a > covered {
                visit(covered, a, None);
            }
            visit(a, b, Some(k));
            covered = b;
        }
        if end >= t1 {
            break;
        }
    }
    if t1 > covered {
        visit(covered, t1, None);
    }
}

/// An attitude carried through the gyro.
#[derive(Clone, Copy, Debug)]
pub struct Propagated {
    pub q_ecef_imu: UnitQuaternion<f64>,
    /// `integral R_ecef_imu dt` over the interval (s): how an error `db` in
    /// the gyro bias (rad/s, IMU frame) turns the attitude, `dtheta_ecef =
    /// -bias_to_attitude * db` (the attitude filter's transition).
    pub bias_to_attitude: Matrix3<f64>,
}

/// [`propagate`] with `bias_imu_rad_s` taken off every gyro sample, and the
/// attitude's sensitivity to that bias.
pub fn propagate_with_bias(
    q_ecef_imu: UnitQuaternion<f64>,
    t0: f64,
    t1: f64,
    imu: &[ImuSample],
    bias_imu_rad_s: &Vector3<f64>,
) -> Propagated {
    let mut sens = Matrix3::zeros();
    if t1 <= t0 {
        return Propagated { q_ecef_imu, bias_to_attitude: sens };
    }
    // Body increments compose on the right (IMU frame); the ECEF frame turns
    // under the inertial one at the Earth rate, on the left:
    // q_ecef_imu(t1) = Rz(-we (t1 - t0)) q_ecef_imu(t0) dq_1 ... dq_n.
    // The sensitivity ignores the Earth's turn over the interval (< 1e-4 rad).
    let r0 = q_ecef_imu.to_rotation_matrix();
    let mut body = UnitQuaternion::identity();
    for_each_segment(imu, t0, t1, |a, b, sample| match sample {
        Some(k) => {
            let dq = strapdown_increment(&(imu[k].w_imu_rad_s - bias_imu_rad_s), b - a);
            // Mid-interval attitude (second order in the step).
            let mid = body * UnitQuaternion::from_scaled_axis(dq.scaled_axis() * 0.5);
            sens += (r0 * mid.to_rotation_matrix()).into_inner() * (b - a);
            body *= dq;
        }
        // Time no sample covers: the attitude stays fixed in inertial space.
        None => sens += (r0 * body.to_rotation_matrix()).into_inner() * (b - a),
    });
    let earth = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -EARTH_RATE_RAD_S * (t1 - t0));
    Propagated { q_ecef_imu: earth * q_ecef_imu * body, bias_to_attitude: sens }
}

/// The turn (ECEF, on the left) of a body at `q_ecef_imu` at `t` over the
/// next `tau` seconds (before it where negative), integrated from `imu`
/// less `bias_imu_rad_s`: a camera's over its clock offset. The rate at
/// `t` times `tau` leaves half the angular acceleration times `tau`
/// squared, which a wobble turns back and forth with the images.
pub fn turn_over(
    q_ecef_imu: UnitQuaternion<f64>,
    t: f64,
    tau: f64,
    imu: &[ImuSample],
    bias_imu_rad_s: &Vector3<f64>,
) -> UnitQuaternion<f64> {
    let (t0, t1) = if tau >= 0.0 { (t, t + tau) } else { (t + tau, t) };
    let turn = propagate_with_bias(q_ecef_imu, t0, t1, imu, bias_imu_rad_s).q_ecef_imu * q_ecef_imu.inverse();
    if tau >= 0.0 {
        turn
    } else {
        turn.inverse()
    }
}

/// Where the rate's walk of a stretch no gyro sample measures starts
/// ([`unmeasured_attitude_variance`]), besides a gap's (its last sample).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WalkStarts {
    /// Before the log's first sample: the flight's first frame.
    pub before_log_t: f64,
    /// After the log's last sample: that sample, or later where fixes
    /// measured the rate after it (the later of the two counts).
    pub after_log_t: f64,
}

/// The attitude variance (rad², about any axis) that the parts of
/// `[t0, t1]` no gyro sample measures add, for a navigator that carries no
/// rate of its own (`--filter fixes`): through a gap (an interval between
/// samples longer than `gap_s`; 0: none recognised), after the log's last
/// sample, and before its first (the walks' starts in `starts`).
/// The rate carried there ([`propagate_with_bias`]: the sample after a gap,
/// none outside the log; after it, the fixes' own where they measured it)
/// is taken as off by a random walk of
/// `walk_rad_s_sqrt_s` from the stretch's start, up to `rate_cap_rad_s`:
/// over `[a, b]` of a stretch that began at `s`, the angle `∫ w dt` of a
/// rate error `w` walking from zero at `s` has the variance
/// `σ² (a − s)(b − a)² + σ² (b − a)³ / 3` (independent increments), the
/// first term's rate variance capped.
pub fn unmeasured_attitude_variance(
    imu: &[ImuSample],
    t0: f64,
    t1: f64,
    starts: WalkStarts,
    gap_s: f64,
    walk_rad_s_sqrt_s: f64,
    rate_cap_rad_s: f64,
) -> f64 {
    let q = walk_rad_s_sqrt_s * walk_rad_s_sqrt_s;
    if !(q > 0.0) || imu.is_empty() {
        return 0.0;
    }
    let mut var = 0.0;
    let mut add = |a: f64, b: f64, s: f64| {
        let d = b - a;
        let rate_var = (q * (a - s).max(0.0)).min(rate_cap_rad_s * rate_cap_rad_s);
        var += rate_var * d * d + q * d * d * d / 3.0;
    };
    for_each_segment(imu, t0, t1, |a, b, sample| match sample {
        Some(k) if ends_gap(imu, k, gap_s) => add(a, b, imu[k - 1].t),
        Some(_) => {}
        None if a >= imu[imu.len() - 1].t => add(a, b, starts.after_log_t.max(imu[imu.len() - 1].t).min(a)),
        None => add(a, b, starts.before_log_t.min(a)),
    });
    var
}

/// Whether sample `k` of `imu` ends a gap: its interval is longer than
/// `gap_s` ([`gap_limit_s`]; 0: no gap recognised).
pub fn ends_gap(imu: &[ImuSample], k: usize, gap_s: f64) -> bool {
    k > 0 && gap_s > 0.0 && imu[k].t - imu[k - 1].t > gap_s
}

/// A stretch of the IMU log without samples.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct ImuGap {
    /// The last sample before it and the first after (s).
    pub from_t: f64,
    pub to_t: f64,
}

/// The interval between samples beyond which the log has a gap: `factor`
/// times its median interval (`None` with fewer than two samples).
pub fn gap_limit_s(imu: &[ImuSample], factor: f64) -> Option<f64> {
    let mut dts: Vec<f64> = imu.windows(2).map(|w| w[1].t - w[0].t).collect();
    if dts.is_empty() {
        return None;
    }
    let mid = dts.len() / 2;
    let (_, median, _) = dts.select_nth_unstable_by(mid, f64::total_cmp);
    Some(factor * *median)
}

/// The stretches between consecutive samples longer than `factor` times the
/// log's median interval ([`gap_limit_s`]): the inertial filter crosses them
/// on rates interpolated between the samples either side, its attitude
/// doubted as it goes (`InsFilter::propagate`).
pub fn imu_gaps(imu: &[ImuSample], factor: f64) -> Vec<ImuGap> {
    let Some(limit) = gap_limit_s(imu, factor) else { return Vec::new() };
    imu.windows(2)
        .filter(|w| w[1].t - w[0].t > limit)
        .map(|w| ImuGap { from_t: w[0].t, to_t: w[1].t })
        .collect()
}

/// The parts of `[t0, t1]` (a flight's first and last frame) before the
/// log's first sample or after its last (the first sample's interval taken
/// as long as the second's, as [`for_each_segment`] does): all of it for an
/// empty log.
pub fn uncovered(imu: &[ImuSample], t0: f64, t1: f64) -> Vec<ImuGap> {
    let (Some(first), Some(last)) = (imu.first(), imu.last()) else {
        return if t1 >= t0 { vec![ImuGap { from_t: t0, to_t: t1 }] } else { Vec::new() };
    };
    let start = imu.get(1).map_or(first.t, |n| first.t - (n.t - first.t));
    let mut out = Vec::new();
    if t0 < start {
        out.push(ImuGap { from_t: t0, to_t: start.min(t1) });
    }
    if t1 > last.t {
        out.push(ImuGap { from_t: last.t.max(t0), to_t: t1 });
    }
    out
}

/// The measurement range of an IMU's sensors, per axis: a sample beyond it
/// is no measurement (a corrupt record: a flipped bit in an exponent, a
/// value from another unit), since a sensor at its limit reads the limit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ImuRange {
    pub gyro_rad_s: f64,
    pub accel_m_s2: f64,
}

impl ImuRange {
    /// Whether every axis of `s` is within the range (an accelerometer
    /// that recorded nothing is).
    pub fn holds(&self, s: &ImuSample) -> bool {
        let within = |v: &Vector3<f64>, limit: f64| v.iter().all(|x| x.abs() <= limit);
        within(&s.w_imu_rad_s, self.gyro_rad_s) && s.f_imu_m_s2.is_none_or(|f| within(&f, self.accel_m_s2))
    }
}

/// The samples of `imu` within `range`, and the times of those left out;
/// `None` when every sample is within it. The samples left out make a
/// longer interval between those either side, crossed like any (a gap where
/// it is one: [`imu_gaps`]).
pub fn within_range(imu: &[ImuSample], range: &ImuRange) -> Option<(Vec<ImuSample>, Vec<f64>)> {
    if imu.iter().all(|s| range.holds(s)) {
        return None;
    }
    let (mut kept, mut out) = (Vec::with_capacity(imu.len()), Vec::new());
    for s in imu {
        if range.holds(s) {
            kept.push(*s);
        } else {
            out.push(s.t);
        }
    }
    Some((kept, out))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Samples of a rate function, each its value mid-interval (the mean
    /// rate to second order).
    fn samples(rate_hz: f64, t_end: f64, w: impl Fn(f64) -> Vector3<f64>) -> Vec<ImuSample> {
        let n = (t_end * rate_hz).round() as usize;
        (0..=n)
            .map(|k| {
                let t = k as f64 / rate_hz;
                ImuSample { t, w_imu_rad_s: w(t - 0.5 / rate_hz), f_imu_m_s2: None }
            })
            .collect()
    }

    #[test]
    fn gaps_are_the_intervals_beyond_the_median() {
        let mut imu = samples(200.0, 10.0, |_| Vector3::zeros());
        assert!(imu_gaps(&imu, 5.0).is_empty());
        // One sample dropped is twice the interval: not a gap at 5x.
        imu.remove(100);
        assert!(imu_gaps(&imu, 5.0).is_empty());
        // 3 s without samples from t = 4 s, and 30 ms from t = 8 s (five
        // samples dropped: 6x the interval).
        let dropped = |t: f64| (t > 4.0 && t < 7.0) || (t > 8.0 && t < 8.03);
        imu.retain(|s| !dropped(s.t));
        let gaps = imu_gaps(&imu, 5.0);
        assert_eq!(gaps.len(), 2, "{gaps:?}");
        assert!((gaps[0].from_t - 4.0).abs() < 1e-9 && (gaps[0].to_t - 7.0).abs() < 1e-9, "{gaps:?}");
        assert!((gaps[1].to_t - gaps[1].from_t - 0.03).abs() < 1e-6, "{gaps:?}");
        assert!(imu_gaps(&imu[..1], 5.0).is_empty());
    }

    #[test]
    fn the_frames_time_outside_the_log_is_found() {
        let imu = samples(100.0, 10.0, |_| Vector3::zeros());
        // Covered: the first sample's interval reaches 10 ms before it.
        assert!(uncovered(&imu, 0.0, 10.0).is_empty());
        assert!(uncovered(&imu, -0.01, 10.0).is_empty());
        let late: Vec<ImuSample> =
            imu.iter().filter(|s| s.t >= 2.0 - 1e-9 && s.t <= 8.0 + 1e-9).copied().collect();
        let u = uncovered(&late, 0.0, 10.0);
        assert_eq!(u.len(), 2, "{u:?}");
        assert!((u[0].from_t - 0.0).abs() < 1e-12 && (u[0].to_t - 1.99).abs() < 1e-9, "{u:?}");
        assert!((u[1].from_t - 8.0).abs() < 1e-9 && (u[1].to_t - 10.0).abs() < 1e-12, "{u:?}");
        assert_eq!(uncovered(&[], 1.0, 3.0), vec![ImuGap { from_t: 1.0, to_t: 3.0 }]);
    }

    /// The angle variance of a rate error walking from zero at `s`, over
    /// `[a, b]`, by simulation (a fixed-seed Gaussian walk in 1 ms steps).
    fn walked_angle_variance(s: f64, a: f64, b: f64, sigma: f64, paths: usize) -> f64 {
        let mut seed = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            ((seed >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let dt = 1e-3;
        let steps = ((b - s) / dt).round() as usize;
        let first = ((a - s) / dt).round() as usize;
        let mut sum2 = 0.0;
        for _ in 0..paths {
            let (mut w, mut angle) = (0.0, 0.0);
            for k in 0..steps {
                let g = (-2.0 * uniform().ln()).sqrt() * (std::f64::consts::TAU * uniform()).cos();
                // The rate over the step is its mean: half the step's walk.
                let dw = sigma * dt.sqrt() * g;
                if k >= first {
                    angle += (w + 0.5 * dw) * dt;
                }
                w += dw;
            }
            sum2 += angle * angle;
        }
        sum2 / paths as f64
    }

    #[test]
    fn time_no_sample_measures_doubts_the_attitude_as_a_walking_rate() {
        let sigma = 3f64.to_radians();
        let q = sigma * sigma;
        let cap = 30f64.to_radians();
        let near = |got: f64, want: f64| (got - want).abs() <= 1e-9 * want.max(1e-12);
        // 100 Hz from 2 s to 10 s, silent from 4 to 6 s (a gap at 5x).
        let mut imu = samples(100.0, 10.0, |_| Vector3::zeros());
        imu.retain(|x| x.t >= 2.0 - 1e-9 && !(x.t > 4.0 + 1e-9 && x.t < 6.0 - 1e-9));
        let gap = gap_limit_s(&imu, 5.0).unwrap();
        let starts = WalkStarts { before_log_t: 0.0, after_log_t: f64::NEG_INFINITY };
        let var = |t0: f64, t1: f64| unmeasured_attitude_variance(&imu, t0, t1, starts, gap, sigma, cap);
        // Measured throughout: nothing.
        assert_eq!(var(6.5, 9.5), 0.0);
        // In the gap, 0.5 s after its start, for 1 s: the rate's walk so
        // far over the second, and its walk within it.
        assert!(near(var(4.5, 5.5), q * 0.5 + q / 3.0), "{}", var(4.5, 5.5));
        // Across the gap's end, only the gap's part counts.
        assert!(near(var(5.5, 7.0), q * 1.5 * 0.25 + q * 0.125 / 3.0), "{}", var(5.5, 7.0));
        // After the log's end (10 s), from its end.
        assert!(near(var(9.5, 11.0), q / 3.0), "{}", var(9.5, 11.0));
        assert!(near(var(12.0, 12.5), q * 2.0 * 0.25 + q * 0.125 / 3.0), "{}", var(12.0, 12.5));
        // Where fixes measured the rate after it (at 11.5 s), from there.
        let later = WalkStarts { after_log_t: 11.5, ..starts };
        let v = unmeasured_attitude_variance(&imu, 12.0, 12.5, later, gap, sigma, cap);
        assert!(near(v, q * 0.5 * 0.25 + q * 0.125 / 3.0), "{v}");
        // Before its first sample (its interval from 1.99 s), from the
        // flight's first frame (0 s).
        assert!(near(var(1.0, 1.5), q * 0.25 + q * 0.125 / 3.0), "{}", var(1.0, 1.5));
        // The rate's variance is capped: 30 deg/s, 100 s after the log.
        let late = var(110.0, 110.5);
        assert!(near(late, cap * cap * 0.25 + q * 0.125 / 3.0), "{late}");
        // Not recognised (no gap limit), a gap is crossed as measured.
        assert_eq!(unmeasured_attitude_variance(&imu, 4.5, 5.5, starts, 0.0, sigma, cap), 0.0);
        assert_eq!(unmeasured_attitude_variance(&imu, 9.5, 11.0, starts, gap, 0.0, cap), 0.0);
        // The formula against a simulated walk (2000 paths: 3% at 1 sigma).
        for (s, a, b) in [(0.0, 0.5, 1.0), (0.0, 0.0, 0.8)] {
            let sim = walked_angle_variance(s, a, b, sigma, 2000);
            let d = b - a;
            let model = q * (a - s) * d * d + q * d * d * d / 3.0;
            assert!((sim / model - 1.0).abs() < 0.1, "{s} {a} {b}: simulated {sim:.3e}, model {model:.3e}");
        }
    }

    #[test]
    fn samples_beyond_the_sensors_range_are_left_out() {
        let range = ImuRange { gyro_rad_s: 10.0, accel_m_s2: 100.0 };
        let mut imu = samples(100.0, 1.0, |_| Vector3::new(0.1, -0.2, 0.3));
        for s in &mut imu {
            s.f_imu_m_s2 = Some(Vector3::new(0.0, 0.0, -9.8));
        }
        assert!(within_range(&imu, &range).is_none());
        // At the limit a sensor reads the limit: kept. Beyond it, on any
        // axis of either sensor: left out, the neighbours kept.
        imu[10].w_imu_rad_s.y = -10.0;
        imu[20].w_imu_rad_s.z = 10.5;
        imu[30].f_imu_m_s2 = Some(Vector3::new(1e300, 0.0, -9.8));
        imu[31].f_imu_m_s2 = None;
        let (kept, out) = within_range(&imu, &range).expect("two out of range");
        assert_eq!(out, vec![imu[20].t, imu[30].t]);
        assert_eq!(kept.len(), imu.len() - 2);
        assert!(kept.iter().all(|s| range.holds(s)));
        assert!(kept.iter().any(|s| s.t == imu[10].t) && kept.iter().any(|s| s.t == imu[31].t));
        // Two neighbours left out make an interval of three: no gap at 5x.
        assert!(imu_gaps(&kept, 5.0).is_empty());
    }

    #[test]
    fn constant_rate_matches_the_analytic_rotation() {
        // A constant body rate w for T seconds is exp(w T) in the body frame,
        // with the Earth turning underneath.
        let w = Vector3::new(0.2, -0.35, 0.1); // ~23 deg/s
        let imu = samples(200.0, 10.0, |_| w);
        let q0 = UnitQuaternion::from_euler_angles(0.3, -1.1, 2.0);
        let (t0, t1) = (1.0, 7.5);
        let got = propagate(q0, t0, t1, &imu);
        let want = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -EARTH_RATE_RAD_S * (t1 - t0))
            * q0
            * UnitQuaternion::from_scaled_axis(w * (t1 - t0));
        // Each normalized step turns by theta + theta^3 / 24 instead of theta.
        let theta = w.norm() / 200.0;
        let expected = 1300.0 * theta.powi(3) / 24.0;
        let err = got.angle_to(&want);
        assert!((err - expected).abs() < 0.05 * expected, "{err} rad, expected {expected}");
    }

    #[test]
    fn partial_intervals_and_earth_rate() {
        // A stationary gyro reads the Earth rate: the attitude stays fixed in ECEF.
        let we = Vector3::new(0.0, 0.0, EARTH_RATE_RAD_S);
        let q0 = UnitQuaternion::from_euler_angles(0.1, 0.2, 0.3);
        // In the IMU frame the Earth rate is q0^-1 * we.
        let imu = samples(200.0, 100.0, |_| q0.inverse() * we);
        let q = propagate(q0, 0.0012, 93.4567, &imu);
        assert!(q.angle_to(&q0) < 1e-12, "{}", q.angle_to(&q0));
        // Frame times between samples: a rate step mid-interval counts by overlap.
        let imu = samples(10.0, 2.0, |t| if t <= 1.0 { Vector3::zeros() } else { Vector3::x() });
        let q = propagate(UnitQuaternion::identity(), 0.95, 1.25, &imu);
        let want = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), -EARTH_RATE_RAD_S * 0.3)
            * UnitQuaternion::from_scaled_axis(Vector3::x() * 0.25);
        assert!(q.angle_to(&want) < 1e-4, "{}", q.angle_to(&want));
    }

    #[test]
    fn second_order_error_is_third_order_in_the_step() {
        // A coning motion: the axis turns, so the increments do not commute.
        let w = |t: f64| Vector3::new(0.3 * (2.0 * t).cos(), 0.3 * (2.0 * t).sin(), 0.5);
        for (rate, bound) in [(200.0, 1e-5), (400.0, 2e-6)] {
            let imu = samples(rate, 20.0, w);
            let fine = samples(20_000.0, 20.0, w);
            let coarse = propagate(UnitQuaternion::identity(), 0.0, 20.0, &imu);
            let reference = propagate(UnitQuaternion::identity(), 0.0, 20.0, &fine);
            assert!(coarse.angle_to(&reference) < bound, "{rate} Hz: {}", coarse.angle_to(&reference));
        }
    }

    #[test]
    fn the_turn_over_a_clock_offset_is_the_gyros() {
        // A wobble: 0.2 deg at 3 Hz about x (71 deg/s^2 at its peak),
        // sampled at 400 Hz.
        let (amp, omega) = (0.2f64.to_radians(), std::f64::consts::TAU * 3.0);
        let w = |t: f64| Vector3::new(amp * omega * (omega * t).cos(), 0.0, 0.0);
        let angle = |t: f64| amp * (omega * t).sin();
        let imu = samples(400.0, 2.0, w);
        let q0 = UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0);
        let tau = 0.005;
        let about_x = |a: f64| q0 * UnitQuaternion::from_scaled_axis(Vector3::x() * a) * q0.inverse();
        for t in [0.5, 0.58, 0.6, 1.0] {
            // The body turns by the wobble's change of angle about its x
            // axis (the Earth's turn over 5 ms, 4e-7 rad, aside).
            let got = turn_over(q0, t, tau, &imu, &Vector3::zeros());
            let want = about_x(angle(t + tau) - angle(t));
            assert!(got.angle_to(&want) < 2e-6, "{t}: {}", got.angle_to(&want));
            // Backwards: from t - tau to t, inverted.
            let back = turn_over(q0, t, -tau, &imu, &Vector3::zeros());
            let want = about_x(angle(t - tau) - angle(t));
            assert!(back.angle_to(&want) < 2e-6, "{t}: {}", back.angle_to(&want));
        }
        // Where the angular acceleration peaks (1.24 rad/s^2, as at 0.58 s
        // above), the rate times the offset misses by half of it times the
        // offset squared, 1.5e-5 rad: eight times the tolerance above.
        let t = 0.25 / 3.0;
        let first_order = amp * omega * (omega * t).cos() * tau;
        let exact = angle(t + tau) - angle(t);
        assert!((first_order - exact).abs() > 0.8 * 0.5 * amp * omega * omega * tau * tau);
    }

    #[test]
    fn bias_sensitivity_matches_finite_differences() {
        let w = |t: f64| Vector3::new(0.3 * (2.0 * t).cos(), 0.3 * (2.0 * t).sin(), 0.5);
        let imu = samples(200.0, 5.0, w);
        let q0 = UnitQuaternion::from_euler_angles(0.3, -1.1, 2.0);
        let b = Vector3::new(1e-4, -2e-4, 5e-5);
        let (t0, t1) = (0.4012, 1.3333);
        let base = propagate_with_bias(q0, t0, t1, &imu, &b);
        let h = 1e-6;
        for i in 0..3 {
            let mut db = Vector3::zeros();
            db[i] = h;
            let plus = propagate_with_bias(q0, t0, t1, &imu, &(b + db)).q_ecef_imu;
            let minus = propagate_with_bias(q0, t0, t1, &imu, &(b - db)).q_ecef_imu;
            // Left (ECEF) error: q(b + db) = exp(dtheta) q(b).
            let numeric = ((plus * minus.inverse()).scaled_axis()) / (2.0 * h);
            let analytic = -base.bias_to_attitude.column(i);
            // The sensitivity leaves out the Earth's turn (7e-5 rad over the interval).
            assert!((numeric - analytic).norm() < 2e-4 * analytic.norm(), "{i}: {numeric} {analytic}");
        }
        // Without rotation it is the interval times the attitude.
        let still = samples(200.0, 5.0, |_| Vector3::zeros());
        let p = propagate_with_bias(q0, 1.0, 1.5, &still, &Vector3::zeros());
        assert!((p.bias_to_attitude - q0.to_rotation_matrix().into_inner() * 0.5).norm() < 1e-12);
    }
}
