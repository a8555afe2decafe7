//! Pure scoring: per-frame pose errors, summary statistics, altitude bands
//! and the per-segment comparison of several runs. No I/O, no plotting.

use std::collections::BTreeMap;

use nalgebra::{UnitQuaternion, Vector3};
use serde::Serialize;
use trn_flight::{FixStatus, NavRecord, TimedCovariance, TimedPose};
use trn_geodesy::LocalFrame;

/// A `poses.csv` row belongs to a frame when their times differ by at most this.
pub const TIME_TOL_S: f64 = 1e-6;

/// Error of an estimated pose against the true one.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PoseError {
    /// ECEF distance (m).
    pub pos_m: f64,
    /// Estimate - truth, east/north/up (m) in the truth's local frame.
    pub enu_m: [f64; 3],
    /// Angle of `q_true^-1 q_est` (deg).
    pub att_deg: f64,
    /// Angle between the true and estimated boresights (camera +z) (deg).
    pub boresight_deg: f64,
}

/// Rotation angle (deg) of `q_a^-1 q_b`, accurate near zero (atan2, not acos).
pub fn rotation_angle_deg(q_a: &UnitQuaternion<f64>, q_b: &UnitQuaternion<f64>) -> f64 {
    let d = q_a.inverse() * q_b;
    (2.0 * d.imag().norm().atan2(d.w.abs())).to_degrees()
}

fn vector_angle_deg(a: &Vector3<f64>, b: &Vector3<f64>) -> f64 {
    a.cross(b).norm().atan2(a.dot(b)).to_degrees()
}

pub fn pose_error(truth: &TimedPose, est: &TimedPose) -> PoseError {
    let (pt, pe) = (truth.position.to_ecef(), est.position.to_ecef());
    let enu = LocalFrame::at(truth.position).vector_to_enu(&(pe.0 - pt.0));
    let z = Vector3::z();
    PoseError {
        pos_m: pt.distance_m(&pe),
        enu_m: [enu.x, enu.y, enu.z],
        att_deg: rotation_angle_deg(&truth.q_ecef_cam, &est.q_ecef_cam),
        boresight_deg: vector_angle_deg(&(truth.q_ecef_cam * z), &(est.q_ecef_cam * z)),
    }
}

/// One frame of `frames.csv` with the navigator's row at its time, if any.
#[derive(Clone, Debug, Serialize)]
pub struct FrameEval {
    pub t: f64,
    /// True height above the ellipsoid (m).
    pub truth_h_m: f64,
    /// `lost` when the frame has no row.
    pub status: FixStatus,
    /// No `poses.csv` row at this frame's time.
    pub missing: bool,
    pub inliers: Option<u32>,
    pub matches: Option<u32>,
    pub ms: Option<f64>,
    /// For `fix` and `propagated` frames.
    pub error: Option<PoseError>,
    #[serde(skip)]
    pub truth: TimedPose,
    #[serde(skip)]
    pub estimate: Option<TimedPose>,
}

impl FrameEval {
    pub fn has_pose(&self) -> bool {
        self.error.is_some()
    }
}

/// Pairs frames (`truths[i]` is the true pose at frame `i`, frames in time
/// order) with rows within [`TIME_TOL_S`]. Returns the per-frame results and
/// the number of rows at no frame's time.
pub fn match_frames(truths: &[TimedPose], rows: &[NavRecord]) -> (Vec<FrameEval>, usize) {
    let mut out: Vec<FrameEval> = truths
        .iter()
        .map(|tp| FrameEval {
            t: tp.t,
            truth_h_m: tp.position.h_m,
            status: FixStatus::Lost,
            missing: true,
            inliers: None,
            matches: None,
            ms: None,
            error: None,
            truth: *tp,
            estimate: None,
        })
        .collect();
    let mut ignored = 0;
    for r in rows {
        let t = r.pose.t;
        let i = truths.partition_point(|f| f.t < t - TIME_TOL_S);
        let Some(f) = out.get_mut(i).filter(|f| (f.t - t).abs() <= TIME_TOL_S && f.missing) else {
            ignored += 1;
            continue;
        };
        f.missing = false;
        f.status = r.status;
        f.inliers = Some(r.inliers);
        f.matches = Some(r.matches);
        f.ms = Some(r.ms);
        if r.status != FixStatus::Lost {
            f.error = Some(pose_error(&f.truth, &r.pose));
            f.estimate = Some(r.pose);
        }
    }
    (out, ignored)
}

/// Summary of a sample. `p95` is the nearest-rank percentile (the smallest
/// value with at least 95% of the sample at or below it); `median` averages
/// the two middle values of an even sample.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stats {
    pub n: usize,
    pub mean: f64,
    pub median: f64,
    pub p95: f64,
    pub max: f64,
    pub rms: f64,
}

/// `None` for an empty sample.
pub fn stats(values: &[f64]) -> Option<Stats> {
    if values.is_empty() {
        return None;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    let median = if n % 2 == 1 { v[n / 2] } else { 0.5 * (v[n / 2 - 1] + v[n / 2]) };
    let rank = ((0.95 * n as f64).ceil() as usize).clamp(1, n);
    Some(Stats {
        n,
        mean: v.iter().sum::<f64>() / n as f64,
        median,
        p95: v[rank - 1],
        max: v[n - 1],
        rms: (v.iter().map(|x| x * x).sum::<f64>() / n as f64).sqrt(),
    })
}

/// Error statistics over a set of frames with a pose.
#[derive(Clone, Debug, Serialize)]
pub struct ErrorStats {
    pub n: usize,
    /// 3D position error (m).
    pub pos_m: Stats,
    /// |east|, |north|, |up| (m).
    pub east_abs_m: Stats,
    pub north_abs_m: Stats,
    pub up_abs_m: Stats,
    /// Mean signed east/north/up error (m): the bias.
    pub enu_mean_m: [f64; 3],
    pub att_deg: Stats,
    pub boresight_deg: Stats,
}

pub fn error_stats<'a>(errors: impl IntoIterator<Item = &'a PoseError>) -> Option<ErrorStats> {
    let e: Vec<&PoseError> = errors.into_iter().collect();
    let col = |f: &dyn Fn(&PoseError) -> f64| stats(&e.iter().map(|x| f(x)).collect::<Vec<_>>());
    let n = e.len() as f64;
    let mean = |k: usize| e.iter().map(|x| x.enu_m[k]).sum::<f64>() / n;
    Some(ErrorStats {
        n: e.len(),
        pos_m: col(&|x| x.pos_m)?,
        east_abs_m: col(&|x| x.enu_m[0].abs())?,
        north_abs_m: col(&|x| x.enu_m[1].abs())?,
        up_abs_m: col(&|x| x.enu_m[2].abs())?,
        enu_mean_m: [mean(0), mean(1), mean(2)],
        att_deg: col(&|x| x.att_deg)?,
        boresight_deg: col(&|x| x.boresight_deg)?,
    })
}

/// Frames by status. `lost` includes the `missing` frames (no row).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StatusCounts {
    pub frames: usize,
    pub fix: usize,
    pub propagated: usize,
    pub lost: usize,
    pub missing: usize,
    pub share_fix: f64,
    pub share_propagated: f64,
    pub share_lost: f64,
}

pub fn status_counts<'a>(frames: impl IntoIterator<Item = &'a FrameEval>) -> StatusCounts {
    let mut c = StatusCounts::default();
    for f in frames {
        c.frames += 1;
        match f.status {
            FixStatus::Fix => c.fix += 1,
            FixStatus::Propagated => c.propagated += 1,
            FixStatus::Lost => c.lost += 1,
        }
        c.missing += f.missing as usize;
    }
    let share = |k: usize| if c.frames == 0 { 0.0 } else { k as f64 / c.frames as f64 };
    (c.share_fix, c.share_propagated, c.share_lost) = (share(c.fix), share(c.propagated), share(c.lost));
    c
}

/// Errors over `fix` frames.
pub fn fix_errors(frames: &[FrameEval]) -> Option<ErrorStats> {
    error_stats(frames.iter().filter(|f| f.status == FixStatus::Fix).filter_map(|f| f.error.as_ref()))
}

/// Errors over frames with a pose (`fix` and `propagated`).
pub fn pose_errors(frames: &[FrameEval]) -> Option<ErrorStats> {
    error_stats(frames.iter().filter_map(|f| f.error.as_ref()))
}

/// Index of the height band `[k band_m, (k + 1) band_m)` holding `h_m`.
pub fn band_index(h_m: f64, band_m: f64) -> i64 {
    (h_m / band_m).floor() as i64
}

fn km(m: f64) -> String {
    let s = format!("{:.3}", m / 1000.0);
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// "25-30 km" for band 5 of 5000 m.
pub fn band_label(index: i64, band_m: f64) -> String {
    format!("{}-{} km", km(index as f64 * band_m), km((index + 1) as f64 * band_m))
}

/// One truth-height band of a run.
#[derive(Clone, Debug, Serialize)]
pub struct Band {
    pub label: String,
    pub lo_m: f64,
    pub hi_m: f64,
    pub status: StatusCounts,
    pub fix_errors: Option<ErrorStats>,
}

fn group_by_band<'a>(
    frames: impl IntoIterator<Item = &'a FrameEval>,
    band_m: f64,
) -> BTreeMap<i64, Vec<&'a FrameEval>> {
    let mut m: BTreeMap<i64, Vec<&FrameEval>> = BTreeMap::new();
    for f in frames {
        m.entry(band_index(f.truth_h_m, band_m)).or_default().push(f);
    }
    m
}

/// Bands holding at least one frame, highest first (the order of a descent).
pub fn bands(frames: &[FrameEval], band_m: f64) -> Vec<Band> {
    group_by_band(frames, band_m)
        .into_iter()
        .rev()
        .map(|(k, fs)| Band {
            label: band_label(k, band_m),
            lo_m: k as f64 * band_m,
            hi_m: (k + 1) as f64 * band_m,
            status: status_counts(fs.iter().copied()),
            fix_errors: error_stats(
                fs.iter().filter(|f| f.status == FixStatus::Fix).filter_map(|f| f.error.as_ref()),
            ),
        })
        .collect()
}

/// Rows of one run in one altitude segment.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SegmentCell {
    pub rows: usize,
    pub fix: usize,
    pub share_fix: f64,
}

#[derive(Clone, Debug, Serialize)]
pub struct SegmentRow {
    pub label: String,
    pub lo_m: f64,
    pub hi_m: f64,
    /// One per run, in the order of [`Comparison::runs`]; `None`: no rows there.
    pub cells: Vec<Option<SegmentCell>>,
}

/// Share of each run's rows with status `fix`, per altitude segment. Only
/// rows count (frames a run did not process are not held against it), so
/// runs at different image rates compare fairly.
#[derive(Clone, Debug, Serialize)]
pub struct Comparison {
    pub runs: Vec<String>,
    pub segments: Vec<SegmentRow>,
}

pub fn compare(runs: &[(&str, &[FrameEval])], band_m: f64) -> Comparison {
    let per_run: Vec<BTreeMap<i64, Vec<&FrameEval>>> =
        runs.iter().map(|(_, fs)| group_by_band(fs.iter().filter(|f| !f.missing), band_m)).collect();
    let mut keys: Vec<i64> = per_run.iter().flat_map(|m| m.keys().copied()).collect();
    keys.sort_unstable();
    keys.dedup();
    let segments = keys
        .into_iter()
        .rev()
        .map(|k| SegmentRow {
            label: band_label(k, band_m),
            lo_m: k as f64 * band_m,
            hi_m: (k + 1) as f64 * band_m,
            cells: per_run
                .iter()
                .map(|m| {
                    m.get(&k).map(|fs| {
                        let fix = fs.iter().filter(|f| f.status == FixStatus::Fix).count();
                        SegmentCell { rows: fs.len(), fix, share_fix: fix as f64 / fs.len() as f64 }
                    })
                })
                .collect(),
        })
        .collect();
    Comparison { runs: runs.iter().map(|(l, _)| l.to_string()).collect(), segments }
}

/// Whether the navigator's position covariances fit its errors: the
/// normalised estimation error squared `NEES = eᵀ P⁻¹ e` of each fix with a
/// covariance (e: estimate − truth, ECEF; P: the position block), 3 degrees
/// of freedom. A consistent navigator has a mean NEES of 3, inside `band`
/// (the two-sided 95% interval of the mean of n values, χ²(3n)/n).
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Consistency {
    pub fixes: usize,
    pub mean_nees: f64,
    pub band: [f64; 2],
    /// Share of fixes whose NEES is within χ²(3)'s 95% point (7.81).
    pub share_within_95: f64,
    /// The median ratio of the error to the covariance's 1-sigma size along
    /// it (`sqrt(NEES)` for one dimension): how many times too small the
    /// reported sigma is.
    pub median_sigma_ratio: f64,
    /// The farthest fix from the truth in its own covariance's sigmas (the
    /// largest `sqrt(NEES)`, the Mahalanobis distance), and its time (s):
    /// #13's "no accepted fix more than 5 sigma from the truth". (A
    /// consistent navigator's 3D distance exceeds 5 once in ~70 000 fixes.)
    pub max_sigma_distance: f64,
    pub max_sigma_distance_t: f64,
    /// The same test of the attitude (`None`: no fix with an invertible
    /// attitude block).
    pub attitude: Option<AttitudeConsistency>,
}

/// Whether the navigator's attitude covariances fit its attitude errors:
/// the NEES of the rotation error `log(q_est q_true⁻¹)` (ECEF, the left
/// perturbation of `covariance.csv`'s attitude block), 3 degrees of
/// freedom, over the fixes with an invertible attitude block; the fields
/// as [`Consistency`]'s.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct AttitudeConsistency {
    pub fixes: usize,
    pub mean_nees: f64,
    pub band: [f64; 2],
    pub max_sigma_distance: f64,
    pub max_sigma_distance_t: f64,
}

/// χ²(k) quantile at the standard-normal point `z` (Wilson-Hilferty; within
/// 0.1% for the k >= 3 used here).
pub fn chi2_quantile(k: f64, z: f64) -> f64 {
    let a = 2.0 / (9.0 * k);
    k * (1.0 - a + z * a.sqrt()).powi(3)
}

/// [`Consistency`] of the `fix` frames that have a covariance row at their
/// time (`covariances` in time order).
pub fn consistency(frames: &[FrameEval], covariances: &[TimedCovariance]) -> Option<Consistency> {
    // (NEES, time) of each fix, position and attitude.
    let mut position = Vec::new();
    let mut attitude = Vec::new();
    let nees = |e: Vector3<f64>, p: nalgebra::Matrix3<f64>| {
        p.try_inverse().map(|pi| (e.transpose() * pi * e)[(0, 0)]).filter(|v| v.is_finite() && *v >= 0.0)
    };
    for f in frames.iter().filter(|f| f.status == FixStatus::Fix) {
        let Some(est) = &f.estimate else { continue };
        let i = covariances.partition_point(|c| c.t < f.t - TIME_TOL_S);
        let Some(c) = covariances.get(i).filter(|c| (c.t - f.t).abs() <= TIME_TOL_S) else { continue };
        let e = est.position.to_ecef().0 - f.truth.position.to_ecef().0;
        if let Some(v) = nees(e, c.ecef.fixed_view::<3, 3>(3, 3).into_owned()) {
            position.push((v, f.t));
        }
        let e = (est.q_ecef_cam * f.truth.q_ecef_cam.inverse()).scaled_axis();
        if let Some(v) = nees(e, c.ecef.fixed_view::<3, 3>(0, 0).into_owned()) {
            attitude.push((v, f.t));
        }
    }
    let p = NeesSummary::of(&position)?;
    let mut sorted: Vec<f64> = position.iter().map(|(v, _)| *v).collect();
    sorted.sort_by(f64::total_cmp);
    let n = sorted.len();
    Some(Consistency {
        fixes: n,
        mean_nees: p.mean,
        band: p.band,
        share_within_95: sorted.iter().filter(|&&v| v <= 7.814_727_903_251_178).count() as f64 / n as f64,
        median_sigma_ratio: (sorted[n / 2] / 3.0).sqrt(),
        max_sigma_distance: p.worst.0.sqrt(),
        max_sigma_distance_t: p.worst.1,
        attitude: NeesSummary::of(&attitude).map(|a| AttitudeConsistency {
            fixes: attitude.len(),
            mean_nees: a.mean,
            band: a.band,
            max_sigma_distance: a.worst.0.sqrt(),
            max_sigma_distance_t: a.worst.1,
        }),
    })
}

/// The mean of 3-degree-of-freedom NEES values (with their times), its 95%
/// band (χ²(3n)/n) and the largest value with its time.
struct NeesSummary {
    mean: f64,
    band: [f64; 2],
    worst: (f64, f64),
}

impl NeesSummary {
    fn of(nees: &[(f64, f64)]) -> Option<Self> {
        let n = nees.len();
        if n == 0 {
            return None;
        }
        let k = 3.0 * n as f64;
        let z = 1.959_963_984_540_054;
        Some(Self {
            mean: nees.iter().map(|(v, _)| v).sum::<f64>() / n as f64,
            band: [chi2_quantile(k, -z) / n as f64, chi2_quantile(k, z) / n as f64],
            worst: nees
                .iter()
                .copied()
                .fold((f64::NEG_INFINITY, f64::NAN), |w, x| if x.0 > w.0 { x } else { w }),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::{Enu, Geodetic};

    fn truth(t: f64, h: f64) -> TimedPose {
        TimedPose {
            t,
            position: Geodetic::new(35.0, -106.0 + t * 1e-3, h),
            q_ecef_cam: UnitQuaternion::from_euler_angles(0.3, -0.2, 1.0 + t * 0.01),
        }
    }

    fn row(pose: TimedPose, status: FixStatus) -> NavRecord {
        NavRecord { pose, status, inliers: 10, matches: 12, ms: 5.0 }
    }

    /// `n` true poses half a second apart and their fixes, each the truth
    /// moved by `estimate` with a standard normal 3-vector (Box-Muller on a
    /// fixed LCG seeded with `seed`).
    fn drawn_fixes(
        n: usize,
        seed: u64,
        mut estimate: impl FnMut(&TimedPose, Vector3<f64>) -> TimedPose,
    ) -> (Vec<TimedPose>, Vec<FrameEval>) {
        let mut seed = seed;
        let mut uniform = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((seed >> 11) as f64 + 0.5) / (1u64 << 53) as f64
        };
        let mut gauss = || {
            let (u, v) = (uniform(), uniform());
            (-2.0 * u.ln()).sqrt() * (2.0 * std::f64::consts::PI * v).cos()
        };
        let truths: Vec<TimedPose> = (0..n).map(|i| truth(i as f64 * 0.5, 25_000.0)).collect();
        let rows: Vec<NavRecord> = truths
            .iter()
            .map(|t| row(estimate(t, Vector3::new(gauss(), gauss(), gauss())), FixStatus::Fix))
            .collect();
        let (frames, _) = match_frames(&truths, &rows);
        (truths, frames)
    }

    /// A covariance row at each truth's time: `block` at rows and columns
    /// `at..at + 3`, the rest of the diagonal `other`.
    fn block_covariances(
        truths: &[TimedPose],
        at: usize,
        block: nalgebra::Matrix3<f64>,
        other: f64,
    ) -> Vec<TimedCovariance> {
        let mut ecef = nalgebra::Matrix6::identity() * other;
        ecef.fixed_view_mut::<3, 3>(at, at).copy_from(&block);
        truths.iter().map(|t| TimedCovariance { t: t.t, ecef }).collect()
    }

    #[test]
    fn chi2_quantiles_match_tables() {
        // chi2(30): 16.791 and 46.979 (2.5% and 97.5%); chi2(300): 253.9, 349.9.
        for (k, z, want) in
            [(30.0, -1.96, 16.791), (30.0, 1.96, 46.979), (300.0, -1.96, 253.9), (300.0, 1.96, 349.9)]
        {
            let got = chi2_quantile(k, z);
            assert!((got / want - 1.0).abs() < 0.003, "k {k} z {z}: {got} vs {want}");
        }
    }

    #[test]
    fn errors_drawn_from_the_covariance_are_consistent_and_a_tenth_of_it_is_not() {
        // A correlated ECEF position covariance, errors drawn from it (Box-Muller
        // on a fixed LCG), one fix per frame.
        let l = nalgebra::Matrix3::new(30.0, 0.0, 0.0, 12.0, 20.0, 0.0, -5.0, 8.0, 10.0);
        let n = 400;
        let (truths, frames) = drawn_fixes(n, 7, |t, e| {
            let est = trn_geodesy::Ecef(t.position.to_ecef().0 + l * e).to_geodetic();
            TimedPose { position: est, ..*t }
        });
        let cov = |scale: f64| block_covariances(&truths, 3, l * l.transpose() * scale, 1e-8);
        let c = consistency(&frames, &cov(1.0)).unwrap();
        assert_eq!(c.fixes, n);
        assert!(c.band[0] < 3.0 && 3.0 < c.band[1], "{c:?}");
        assert!(c.mean_nees > c.band[0] && c.mean_nees < c.band[1], "{c:?}");
        assert!((c.share_within_95 - 0.95).abs() < 0.04, "{c:?}");
        assert!((c.median_sigma_ratio - 0.88).abs() < 0.15, "{c:?}");
        // The farthest of 400 consistent fixes: sqrt of chi2(3)'s largest of
        // 400 draws, about 4 (5 once in ~70 000); and it is a fix's own time.
        assert!(c.max_sigma_distance > 3.0 && c.max_sigma_distance < 5.0, "{c:?}");
        assert!(truths.iter().any(|t| t.t == c.max_sigma_distance_t), "{c:?}");
        // Reported sigmas ten times too small: NEES ~ 300, far outside.
        let bad = consistency(&frames, &cov(0.01)).unwrap();
        assert!(bad.mean_nees > 10.0 * bad.band[1], "{bad:?}");
        assert!(bad.median_sigma_ratio > 7.0, "{bad:?}");
        assert!(bad.max_sigma_distance > 30.0, "{bad:?}");
        // Frames without a covariance row, or not fixes, are left out.
        assert!(consistency(&frames, &[]).is_none());
        // Exact attitudes: an attitude NEES of zero (to rounding).
        assert!(c.attitude.unwrap().mean_nees < 1e-12, "{c:?}");
    }

    #[test]
    fn attitude_errors_drawn_from_the_covariance_are_consistent_and_a_tenth_of_it_is_not() {
        // A correlated ECEF attitude covariance (rad), rotations drawn from
        // it (Box-Muller on a fixed LCG) and applied on the left of the true
        // attitude, as the navigator's covariance.csv perturbs it.
        let l = nalgebra::Matrix3::new(2e-3, 0.0, 0.0, 1e-3, 1.5e-3, 0.0, -5e-4, 4e-4, 1e-3);
        let n = 400;
        let (truths, frames) = drawn_fixes(n, 11, |t, e| TimedPose {
            q_ecef_cam: UnitQuaternion::from_scaled_axis(l * e) * t.q_ecef_cam,
            ..*t
        });
        let cov = |scale: f64| block_covariances(&truths, 0, l * l.transpose() * scale, 100.0);
        let a = consistency(&frames, &cov(1.0)).unwrap().attitude.unwrap();
        assert_eq!(a.fixes, n);
        assert!(a.mean_nees > a.band[0] && a.mean_nees < a.band[1], "{a:?}");
        assert!(a.max_sigma_distance > 3.0 && a.max_sigma_distance < 5.0, "{a:?}");
        assert!(truths.iter().any(|t| t.t == a.max_sigma_distance_t), "{a:?}");
        // The positions are exact: their NEES is zero whatever the attitude.
        assert!(consistency(&frames, &cov(1.0)).unwrap().mean_nees < 1e-12);
        // Reported attitude sigmas ten times too small.
        let bad = consistency(&frames, &cov(0.01)).unwrap().attitude.unwrap();
        assert!(bad.mean_nees > 10.0 * bad.band[1], "{bad:?}");
        assert!(bad.max_sigma_distance > 30.0, "{bad:?}");
    }

    #[test]
    fn stats_match_hand_computed_values() {
        let s = stats(&[4.0, 1.0, 3.0, 2.0]).unwrap();
        assert_eq!(s.n, 4);
        assert!((s.mean - 2.5).abs() < 1e-12);
        assert!((s.median - 2.5).abs() < 1e-12);
        assert_eq!(s.max, 4.0);
        // ceil(0.95 * 4) = 4th smallest
        assert_eq!(s.p95, 4.0);
        assert!((s.rms - (30.0f64 / 4.0).sqrt()).abs() < 1e-12);
        // 1..=20: rank ceil(19) = 19th value; odd n median is the middle value
        let v: Vec<f64> = (1..=20).map(f64::from).collect();
        assert_eq!(stats(&v).unwrap().p95, 19.0);
        assert_eq!(stats(&[5.0, 1.0, 9.0]).unwrap().median, 5.0);
        assert_eq!(stats(&[7.0]).unwrap().p95, 7.0);
        assert!(stats(&[]).is_none());
    }

    #[test]
    fn attitude_error_of_a_known_rotation() {
        let t = truth(0.0, 25_000.0);
        let delta = UnitQuaternion::from_axis_angle(&Vector3::x_axis(), 0.5f64.to_radians());
        let est = TimedPose { q_ecef_cam: t.q_ecef_cam * delta, ..t };
        let e = pose_error(&t, &est);
        assert!((e.att_deg - 0.5).abs() < 1e-9, "{}", e.att_deg);
        // A rotation about the camera x axis tilts the boresight by the same angle.
        assert!((e.boresight_deg - 0.5).abs() < 1e-9, "{}", e.boresight_deg);
        // About the boresight itself: attitude error, no pointing error.
        let roll = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 2f64.to_radians());
        let e = pose_error(&t, &TimedPose { q_ecef_cam: t.q_ecef_cam * roll, ..t });
        assert!((e.att_deg - 2.0).abs() < 1e-9 && e.boresight_deg < 1e-9);
        assert_eq!(pose_error(&t, &t).att_deg, 0.0);
        assert!(rotation_angle_deg(&t.q_ecef_cam, &t.q_ecef_cam) < 1e-12);
    }

    #[test]
    fn position_error_in_the_truth_local_frame() {
        let t = truth(1.0, 25_000.0);
        let f = LocalFrame::at(t.position);
        let p = f.to_ecef(Enu::new(30.0, -40.0, 12.0)).to_geodetic();
        let e = pose_error(&t, &TimedPose { position: p, ..t });
        // sqrt(30^2 + 40^2 + 12^2)
        assert!((e.pos_m - 2644f64.sqrt()).abs() < 1e-6, "{}", e.pos_m);
        for (a, b) in e.enu_m.iter().zip([30.0, -40.0, 12.0]) {
            assert!((a - b).abs() < 1e-6, "{:?}", e.enu_m);
        }
    }

    #[test]
    fn missing_frames_count_as_lost_and_stray_rows_are_ignored() {
        let truths: Vec<TimedPose> = (0..6).map(|i| truth(i as f64 * 0.5, 25_000.0)).collect();
        let mut rows: Vec<NavRecord> = truths.iter().map(|p| row(*p, FixStatus::Fix)).collect();
        rows[4].status = FixStatus::Propagated;
        rows.remove(2);
        rows.remove(0);
        // Half a frame period off: matches no frame.
        let stray = NavRecord { pose: truth(1.25, 25_000.0), ..rows[0] };
        rows.insert(1, stray);
        let (frames, ignored) = match_frames(&truths, &rows);
        assert_eq!(ignored, 1);
        assert!(frames[0].missing && frames[2].missing && !frames[1].missing);
        let c = status_counts(&frames);
        assert_eq!((c.frames, c.fix, c.propagated, c.lost, c.missing), (6, 3, 1, 2, 2));
        assert!((c.share_fix - 0.5).abs() < 1e-12 && (c.share_lost - 2.0 / 6.0).abs() < 1e-12);
        assert_eq!(fix_errors(&frames).unwrap().n, 3);
        assert_eq!(pose_errors(&frames).unwrap().n, 4);
        // A row a few hundred ns off still matches.
        let near = NavRecord { pose: TimedPose { t: 0.5 + 4e-7, ..truths[1] }, ..rows[0] };
        let (frames, ignored) = match_frames(&truths, &[near]);
        assert_eq!(ignored, 0);
        assert!(!frames[1].missing);
    }

    #[test]
    fn bands_group_by_truth_height_highest_first() {
        assert_eq!(band_index(24_999.0, 5000.0), 4);
        assert_eq!(band_index(25_000.0, 5000.0), 5);
        assert_eq!(band_label(5, 5000.0), "25-30 km");
        assert_eq!(band_label(3, 500.0), "1.5-2 km");
        let hs = [26_000.0, 25_500.0, 24_800.0, 24_100.0, 19_000.0];
        let truths: Vec<TimedPose> = hs.iter().enumerate().map(|(i, h)| truth(i as f64, *h)).collect();
        let mut rows: Vec<NavRecord> = truths.iter().map(|p| row(*p, FixStatus::Fix)).collect();
        rows[2].status = FixStatus::Lost;
        rows.remove(3);
        let (frames, _) = match_frames(&truths, &rows);
        let b = bands(&frames, 5000.0);
        let labels: Vec<&str> = b.iter().map(|b| b.label.as_str()).collect();
        assert_eq!(labels, ["25-30 km", "20-25 km", "15-20 km"]);
        assert_eq!((b[0].status.frames, b[0].status.fix), (2, 2));
        assert_eq!(
            (b[1].status.frames, b[1].status.fix, b[1].status.lost, b[1].status.missing),
            (2, 0, 2, 1)
        );
        assert!(b[1].fix_errors.is_none());
        // The comparison counts rows only: the missing frame is not in it.
        let c = compare(&[("a", &frames)], 5000.0);
        let cell = c.segments[1].cells[0].unwrap();
        assert_eq!((cell.rows, cell.fix), (1, 0));
        assert_eq!(c.segments[0].cells[0].unwrap().share_fix, 1.0);
    }

    #[test]
    fn comparison_aligns_segments_across_runs() {
        let hs = [26_500.0, 25_500.0, 24_500.0, 23_500.0];
        let truths: Vec<TimedPose> = hs.iter().enumerate().map(|(i, h)| truth(i as f64, *h)).collect();
        let all: Vec<NavRecord> = truths.iter().map(|p| row(*p, FixStatus::Fix)).collect();
        let (fa, _) = match_frames(&truths, &all);
        // Run b: every other frame, the low one propagated.
        let mut half = vec![all[0], all[2]];
        half[1].status = FixStatus::Propagated;
        let (fb, _) = match_frames(&truths, &half);
        let c = compare(&[("a", &fa), ("b", &fb)], 1000.0);
        assert_eq!(c.runs, ["a", "b"]);
        assert_eq!(c.segments.len(), 4);
        assert_eq!(c.segments[0].label, "26-27 km");
        assert_eq!(c.segments[0].cells[1].unwrap().share_fix, 1.0);
        assert!(c.segments[1].cells[1].is_none());
        assert_eq!(c.segments[2].cells[1].unwrap().share_fix, 0.0);
        assert_eq!(c.segments[3].cells[0].unwrap().rows, 1);
    }
}
