//! Online self-calibration of the camera: focal length, principal point and
//! the first radial distortion coefficient as filter states with priors
//! around `camera.json`, updated by every accepted fix with what its matches
//! say about them once the pose is eliminated
//! ([`trn_vision::calib::frame_calibration`]).
//!
//! A 0.3% focal error moves a solved position by 0.3% of the range (90 m at
//! 30 km) for any navigator that trusts the nominal camera; relief in view
//! tells the two apart (see `trn_vision::calib`). A `k1` error of 0.002 moves
//! a 60-degree camera's corners by 0.7 px, tens of metres at the far edge of
//! an oblique view. The state is `x = [focal_rel, du_px, dv_px, k1]` (the
//! true camera is the nominal one with `fx, fy` times `1 + focal_rel`, the
//! principal point moved by `(du, dv)` and `k1` added), with covariance `P`,
//! a random walk between frames (a lens warming up), and per accepted frame
//! an information-form update of the states estimated (`E`; one Gauss-Newton
//! step of the frame's cost from the current estimate), the others (`M`)
//! eliminated with their priors `L` (consider parameters):
//!
//! ```text
//! H' = H_EE - H_EM (H_MM + L)^-1 H_ME,   g' = g_E - H_EM (H_MM + L)^-1 g_M
//! P_E+ = (P_E^-1 + T H' T)^-1,   x_E+ = x_E - P_E+ T g',   T = diag(1 / (1 + focal_rel), 1, ...)
//! ```
//!
//! (`H`, `g`: the frame's information and gradient, relative to the current
//! camera, so `T` maps them onto the state). The focal length is estimated
//! by default, the principal point and `k1` only on request (a nadir view
//! cannot tell the principal point from a tilt, and on the realistic flights
//! the database's errors pass for both). The frame's evidence is weighed
//! with the larger of the nominal pixel sigma and its inliers' RMS
//! residual, and a frame whose own estimate disagrees with the state beyond
//! the 99.9% chi-square gate is not used: relief that the database has wrong
//! shows up as a focal error, and one frame of bad heights must not move it.

use nalgebra::{DMatrix, DVector, Matrix2, Matrix4, Vector2, Vector4};
use trn_camera::CameraModel;
use trn_camera::IntrinsicsCorrection;
use trn_vision::calib::FrameCalibration;

/// Priors and drift of the calibration states (1 sigma).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibrationParams {
    /// Relative focal length error of `camera.json` (0.005 = 0.5%).
    pub focal_sigma_rel: f64,
    /// Principal point error of `camera.json` (pixels, each axis).
    pub principal_sigma_px: f64,
    /// Radial distortion `k1` error of `camera.json`: `k1` is estimated
    /// with this prior; 0 (the default): trusted. (On the realistic flights
    /// the map's errors pass for distortion: see the README.)
    pub k1_sigma: f64,
    /// Random walk of the focal length (relative, per sqrt(s)).
    pub focal_walk_rel_sqrt_s: f64,
    /// Random walk of the principal point (pixels per sqrt(s)).
    pub principal_walk_px_sqrt_s: f64,
    /// Uncertainty of a landmark's height (m, 1 sigma): the database's DEM
    /// error, which relief-based focal evidence must not take for a lens.
    pub landmark_height_sigma_m: f64,
    /// A frame whose matches alone determine the focal length worse than
    /// this (relative, 1 sigma) is not used: its relief is too small against
    /// the range, and the little it says comes from the landmarks' height
    /// errors as much as from the lens (measured on the realistic flights:
    /// nadir views from 12-30 km give 4% per frame, steadily biased).
    pub max_frame_sigma_rel: f64,
    /// Time (s) over which frames see mostly the same landmarks, so the same
    /// height errors: each frame's evidence counts for `dt / correlation` of
    /// an independent one (at most one).
    pub correlation_s: f64,
    /// Estimate the principal point too; otherwise it stays `camera.json`'s
    /// and only its prior enters (as a consider parameter).
    pub principal_point: bool,
}

impl Default for CalibrationParams {
    fn default() -> Self {
        Self {
            focal_sigma_rel: 0.005,
            principal_sigma_px: 3.0,
            k1_sigma: 0.0,
            // 0.06% per hour: a lens through a stratospheric day.
            focal_walk_rel_sqrt_s: 1e-5,
            principal_walk_px_sqrt_s: 1e-3,
            landmark_height_sigma_m: 20.0,
            max_frame_sigma_rel: 0.005,
            correlation_s: 3.0,
            principal_point: false,
        }
    }
}

/// 99.9% of chi-square with 1 to 4 degrees of freedom: a frame's own
/// estimate farther than this from the state (squared Mahalanobis distance
/// with the state's and the frame's covariances) is not used.
pub const FRAME_GATE_CHI2: [f64; 4] = [10.83, 13.82, 16.27, 18.47];

/// The intrinsics another filter carries (see
/// [`CalibrationFilter::pose_covariance_but`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CarriedIntrinsics {
    pub focal: bool,
    pub principal_point: bool,
}

/// Index of each intrinsic in the state.
const FOCAL: usize = 0;
const K1: usize = 3;

/// The calibration estimate (see the module docs).
#[derive(Clone, Debug)]
pub struct CalibrationFilter {
    nominal: CameraModel,
    params: CalibrationParams,
    x: Vector4<f64>,
    p: Matrix4<f64>,
    t: Option<f64>,
    /// When the last frame's evidence was used.
    last_update_t: Option<f64>,
    /// Frames used, refused by the gate, and too weak to use.
    pub updates: usize,
    pub refused: usize,
    pub weak: usize,
}

/// What one update did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CalibrationStep {
    /// Change of the correction relative to the camera the frame was solved
    /// with (`[focal_rel of that camera, du, dv, k1]`): the pose follows it by
    /// `FrameCalibration::pose_sensitivity * step`.
    pub relative: Vector4<f64>,
    /// The frame's disagreement with the state before the update (chi-square,
    /// as many degrees of freedom as states estimated).
    pub chi2: f64,
}

impl CalibrationFilter {
    pub fn new(nominal: CameraModel, params: CalibrationParams) -> Self {
        let mut f = Self {
            nominal,
            params,
            x: Vector4::zeros(),
            p: Matrix4::zeros(),
            t: None,
            last_update_t: None,
            updates: 0,
            refused: 0,
            weak: 0,
        };
        for i in 0..4 {
            if f.estimated(i) {
                f.p[(i, i)] = f.prior_var(i);
            }
        }
        f
    }

    /// The prior variance of intrinsic `i` (camera.json's error).
    fn prior_var(&self, i: usize) -> f64 {
        let c = &self.params;
        match i {
            FOCAL => c.focal_sigma_rel.powi(2),
            K1 => c.k1_sigma.powi(2),
            _ => c.principal_sigma_px.powi(2),
        }
    }

    /// Whether intrinsic `i` is a state (else a consider parameter, or
    /// trusted when its prior is 0).
    fn estimated(&self, i: usize) -> bool {
        match i {
            FOCAL => true,
            K1 => self.params.k1_sigma > 0.0,
            _ => self.params.principal_point,
        }
    }

    /// The current correction of `camera.json`.
    pub fn correction(&self) -> IntrinsicsCorrection {
        IntrinsicsCorrection::from_vector(&self.x)
    }

    /// Covariance of the correction (zero rows for what is not estimated).
    pub fn covariance(&self) -> Matrix4<f64> {
        self.p
    }

    /// The camera as estimated now.
    pub fn camera(&self) -> CameraModel {
        self.correction().apply(&self.nominal)
    }

    /// The random walk up to `t` (s).
    pub fn propagate(&mut self, t: f64) {
        if let Some(t0) = self.t {
            let dt = (t - t0).max(0.0);
            self.p[(FOCAL, FOCAL)] += self.params.focal_walk_rel_sqrt_s.powi(2) * dt;
            if self.params.principal_point {
                self.p[(1, 1)] += self.params.principal_walk_px_sqrt_s.powi(2) * dt;
                self.p[(2, 2)] += self.params.principal_walk_px_sqrt_s.powi(2) * dt;
            }
        }
        self.t = Some(self.t.map_or(t, |t0| t0.max(t)));
    }

    /// Maps a frame's relative correction onto the state (see the module docs).
    fn to_state(&self) -> Matrix4<f64> {
        Matrix4::from_diagonal(&Vector4::new(1.0 / (1.0 + self.x[FOCAL]), 1.0, 1.0, 1.0))
    }

    /// Covariance of the pose `[dtheta; dp]` that the calibration's
    /// uncertainty adds to a frame solved with [`Self::camera`]: the
    /// estimate's, and what is not estimated with its prior (a consider
    /// parameter: a nadir view turns a principal point error into a tilt,
    /// and the tilt into a horizontal shift).
    pub fn pose_covariance(&self, frame: &FrameCalibration) -> nalgebra::Matrix6<f64> {
        self.pose_covariance_but(frame, CarriedIntrinsics::default())
    }

    /// [`Self::pose_covariance`] without the shares of the intrinsics that
    /// another filter carries (the inertial one: [`Self::focal_evidence`],
    /// [`Self::shift_principal`]): what the others add.
    pub fn pose_covariance_but(
        &self,
        frame: &FrameCalibration,
        carried: CarriedIntrinsics,
    ) -> nalgebra::Matrix6<f64> {
        // A state change dx is the frame's relative correction T dx.
        let s = frame.pose_sensitivity * self.to_state();
        let mut p = self.p;
        for i in 0..4 {
            if !self.estimated(i) {
                p[(i, i)] = self.prior_var(i);
            }
        }
        let elsewhere = |i: usize| match i {
            FOCAL => carried.focal,
            K1 => false,
            _ => carried.principal_point,
        };
        for i in (0..4).filter(|&i| elsewhere(i)) {
            for j in 0..4 {
                p[(i, j)] = 0.0;
                p[(j, i)] = 0.0;
            }
        }
        s * p * s.transpose()
    }

    pub fn params(&self) -> &CalibrationParams {
        &self.params
    }

    /// The frame's own estimate of the focal correction (relative to the
    /// camera it was solved with) and its sigma, every other intrinsic
    /// eliminated with its prior.
    pub fn frame_focal(&self, frame: &FrameCalibration) -> (f64, f64) {
        let (h, g) = self.eliminated(frame, &[FOCAL], |i| i != FOCAL);
        let (h, g) = (h[(0, 0)], g[0]);
        (-g / h, h.recip().sqrt())
    }

    /// The frame's information and gradient on the intrinsics `keep`, with
    /// those for which `marginal` holds eliminated through their prior
    /// (Schur complement); the rest ignored (trusted).
    fn eliminated(
        &self,
        frame: &FrameCalibration,
        keep: &[usize],
        marginal: impl Fn(usize) -> bool,
    ) -> (DMatrix<f64>, DVector<f64>) {
        let h = &frame.information;
        let g = &frame.gradient;
        let m: Vec<usize> =
            (0..4).filter(|&i| !keep.contains(&i) && marginal(i) && self.prior_var(i) > 0.0).collect();
        let sub = |rows: &[usize], cols: &[usize]| {
            DMatrix::from_fn(rows.len(), cols.len(), |a, b| h[(rows[a], cols[b])])
        };
        let h_ee = sub(keep, keep);
        let g_e = DVector::from_fn(keep.len(), |a, _| g[keep[a]]);
        if m.is_empty() {
            return (h_ee, g_e);
        }
        let mut h_mm = sub(&m, &m);
        for (a, &i) in m.iter().enumerate() {
            h_mm[(a, a)] += 1.0 / self.prior_var(i);
        }
        let h_em = sub(keep, &m);
        let g_m = DVector::from_fn(m.len(), |a, _| g[m[a]]);
        match h_mm.try_inverse() {
            Some(inv) => (&h_ee - &h_em * &inv * h_em.transpose(), &g_e - &h_em * inv * g_m),
            None => (h_ee, g_e),
        }
    }

    /// Whether the focal length is the only intrinsic estimated: another
    /// filter (the inertial one) can then carry it, with
    /// [`Self::focal_evidence`] and [`Self::shift_focal`].
    pub fn focal_only(&self) -> bool {
        (1..4).all(|i| !self.estimated(i))
    }

    /// Share of an independent frame a frame at `t_frame` counts for.
    fn weight(&self, t_frame: f64) -> f64 {
        match self.last_update_t {
            Some(t0) if self.params.correlation_s > 0.0 => {
                ((t_frame - t0) / self.params.correlation_s).clamp(0.0, 1.0)
            }
            _ => 1.0,
        }
    }

    /// A frame's evidence on the focal length for a filter that carries it
    /// with variance `prior_var` (relative to the camera the frame was
    /// solved with; [`Self::focal_only`]): the frame's own estimate of the
    /// focal error and its variance, weighed as [`Self::update`] weighs it
    /// and through the same gates; `None` when the frame is too weak, counts
    /// for nothing yet, or disagrees with the prior. The estimate stays
    /// where it is until [`Self::shift_focal`].
    pub fn focal_evidence(
        &mut self,
        t_frame: f64,
        frame: &FrameCalibration,
        prior_var: f64,
    ) -> Option<(f64, f64)> {
        let (z, sigma) = self.frame_focal(frame);
        if !(sigma <= self.params.max_frame_sigma_rel) {
            self.weak += 1;
            return None;
        }
        let weight = self.weight(t_frame);
        if !(weight > 0.0) {
            return None;
        }
        let variance = sigma * sigma / weight;
        // The chi-square of [`Self::update`] with one state: z^2 / (1/h + p).
        if !(z * z / (variance + prior_var) <= FRAME_GATE_CHI2[0]) {
            self.refused += 1;
            return None;
        }
        self.updates += 1;
        self.last_update_t = Some(t_frame);
        Some((z, variance))
    }

    /// Moves the principal point by `d_px` and sets its covariance (px):
    /// what a filter that carries it (the inertial one) learnt. It stays a
    /// consider parameter of this filter's own updates, with its prior.
    pub fn shift_principal(&mut self, d_px: Vector2<f64>, covariance_px: Matrix2<f64>) {
        self.x[1] += d_px.x;
        self.x[2] += d_px.y;
        self.p.fixed_view_mut::<2, 2>(1, 1).copy_from(&((covariance_px + covariance_px.transpose()) * 0.5));
    }

    /// Moves the focal length by `relative` of the current camera's and
    /// sets its variance (`variance_rel`, relative to the current camera):
    /// what a filter that carries it ([`Self::focal_evidence`]) learnt.
    pub fn shift_focal(&mut self, relative: f64, variance_rel: f64) {
        let scale = 1.0 + self.x[FOCAL];
        self.x[FOCAL] += relative * scale;
        self.p[(FOCAL, FOCAL)] = variance_rel.max(0.0) * scale * scale;
    }

    /// One frame's update (see the module docs); `None` when the frame is
    /// too weak or refused by the gate (nothing changes).
    pub fn update(&mut self, t_frame: f64, frame: &FrameCalibration) -> Option<CalibrationStep> {
        let (_, frame_sigma) = self.frame_focal(frame);
        if !(frame_sigma <= self.params.max_frame_sigma_rel) {
            self.weak += 1;
            return None;
        }
        let weight = self.weight(t_frame);
        let e: Vec<usize> = (0..4).filter(|&i| self.estimated(i)).collect();
        let n = e.len();
        let (h_rel, g_rel) = self.eliminated(frame, &e, |i| !self.estimated(i));
        // Onto the state: T (diagonal) on the estimated rows and columns.
        let t = self.to_state();
        let td = DVector::from_fn(n, |a, _| t[(e[a], e[a])]);
        let h = DMatrix::from_fn(n, n, |a, b| h_rel[(a, b)] * td[a] * td[b] * weight);
        let g = DVector::from_fn(n, |a, _| g_rel[a] * td[a] * weight);
        let p_e = DMatrix::from_fn(n, n, |a, b| self.p[(e[a], e[b])]);
        let p_new = (p_e.clone().try_inverse()? + &h).try_inverse()?;
        let p_new = (&p_new + p_new.transpose()) * 0.5;
        let dx = -&p_new * &g;
        // The frame's disagreement with the state: its own minimum (a
        // pseudo-inverse where it says nothing) against the posterior's.
        let eig = h.clone().symmetric_eigen();
        let max = eig.eigenvalues.max().max(0.0);
        let mut h_inv_g = 0.0;
        for i in 0..n {
            let l = eig.eigenvalues[i];
            if l > 1e-9 * max && l > 0.0 {
                let c = eig.eigenvectors.column(i).dot(&g);
                h_inv_g += c * c / l;
            }
        }
        let chi2 = (h_inv_g - g.dot(&(&p_new * &g))).max(0.0);
        if !(chi2 <= FRAME_GATE_CHI2[n - 1]) {
            self.refused += 1;
            return None;
        }
        let mut dx4 = Vector4::zeros();
        for (a, &i) in e.iter().enumerate() {
            dx4[i] = dx[a];
            for (b, &j) in e.iter().enumerate() {
                self.p[(i, j)] = p_new[(a, b)];
            }
        }
        self.x += dx4;
        self.updates += 1;
        self.last_update_t = Some(t_frame);
        Some(CalibrationStep { relative: t * dx4, chi2 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{SMatrix, UnitQuaternion, Vector3};
    use trn_camera::{CameraPose, Pixel};
    use trn_geodesy::{intersect_ellipsoid, Geodetic, LocalFrame};
    use trn_vision::calib::frame_calibration;
    use trn_vision::pnp::{refine_pose, RefineOptions};

    fn frame(information: Matrix4<f64>, estimate: Vector4<f64>) -> FrameCalibration {
        FrameCalibration {
            information,
            gradient: -information * estimate,
            pose_sensitivity: SMatrix::<f64, 6, 4>::zeros(),
        }
    }

    fn params() -> CalibrationParams {
        CalibrationParams { correlation_s: 0.0, ..Default::default() }
    }

    #[test]
    fn a_frame_far_from_the_state_is_refused_and_a_weak_one_unused() {
        let mut f = CalibrationFilter::new(CameraModel::from_fov(1024, 768, 30.0), params());
        let info = Matrix4::from_diagonal(&Vector4::new(1.0 / 0.0005f64.powi(2), 1.0, 1.0, 1e6));
        for k in 0..20 {
            // The frame's estimate is relative to the camera it was solved with.
            let rel = 1.001 / (1.0 + f.correction().focal_rel) - 1.0;
            f.update(k as f64, &frame(info, Vector4::new(rel, 0.0, 0.0, 0.0))).unwrap();
        }
        assert!((f.correction().focal_rel - 0.001).abs() < 1e-4, "{:?}", f.correction());
        let before = f.correction();
        // 5% of focal in one frame: bad heights, not the lens.
        assert!(f.update(20.0, &frame(info, Vector4::new(0.05, 0.0, 0.0, 0.0))).is_none());
        // A flat nadir view's 4% sigma says nothing worth using.
        let weak = Matrix4::from_diagonal(&Vector4::new(1.0 / 0.04f64.powi(2), 1.0, 1.0, 1e6));
        assert!(f.update(21.0, &frame(weak, Vector4::new(0.01, 0.0, 0.0, 0.0))).is_none());
        assert_eq!(f.correction(), before);
        assert_eq!((f.updates, f.refused, f.weak), (20, 1, 1));
    }

    #[test]
    fn a_principal_point_carried_elsewhere_leaves_the_pose_covariance_and_moves_the_camera() {
        // The consider share of each intrinsic in a frame's pose covariance
        // is S_i var_i S_i^T (independent priors): carried by the inertial
        // filter, the principal point's share leaves it, the focal
        // length's stays; a carried focal length takes its share too.
        let camera = CameraModel::from_fov(640, 480, 40.0);
        let f = CalibrationFilter::new(camera, params());
        let mut fr = frame(Matrix4::identity(), Vector4::zeros());
        fr.pose_sensitivity = SMatrix::<f64, 6, 4>::from_fn(|r, c| ((r * 4 + c) as f64 * 0.7).sin() * 0.01);
        let share = |i: usize, var: f64| {
            let col = fr.pose_sensitivity.column(i);
            col * col.transpose() * var
        };
        let (pp_var, focal_var) = (params().principal_sigma_px.powi(2), params().focal_sigma_rel.powi(2));
        let all = f.pose_covariance(&fr);
        assert!((all - share(0, focal_var) - share(1, pp_var) - share(2, pp_var)).norm() < 1e-15);
        let but_pp = f.pose_covariance_but(&fr, CarriedIntrinsics { focal: false, principal_point: true });
        assert!((all - but_pp - share(1, pp_var) - share(2, pp_var)).norm() < 1e-15);
        let but_both = f.pose_covariance_but(&fr, CarriedIntrinsics { focal: true, principal_point: true });
        assert!(but_both.norm() < 1e-15, "k1 is trusted (prior 0): nothing is left");

        let mut g = f.clone();
        g.shift_principal(Vector2::new(1.5, -1.0), Matrix2::new(0.25, 0.01, 0.01, 0.16));
        let (c, p) = (g.correction(), g.covariance());
        assert_eq!((c.principal_du_px, c.principal_dv_px), (1.5, -1.0));
        assert_eq!((p[(1, 1)], p[(2, 2)], p[(1, 2)]), (0.25, 0.16, 0.01));
        let moved = g.camera();
        assert!((moved.cx - camera.cx - 1.5).abs() < 1e-12 && (moved.cy - camera.cy + 1.0).abs() < 1e-12);
    }

    #[test]
    fn focal_evidence_carried_elsewhere_is_the_update_and_passes_the_same_gates() {
        // A filter that carries the focal length (the inertial one) takes
        // each frame's evidence as a scalar measurement and hands its
        // estimate back with `shift_focal`: the same estimate and variance
        // as `update`, frame after frame, with correlated frames weighed
        // alike; and the same frames refused or too weak.
        let p = CalibrationParams { correlation_s: 1.5, ..Default::default() };
        let camera = CameraModel::from_fov(1024, 768, 30.0);
        let (mut own, mut carried) = (CalibrationFilter::new(camera, p), CalibrationFilter::new(camera, p));
        let mut carrier_var = p.focal_sigma_rel.powi(2);
        let info = Matrix4::from_diagonal(&Vector4::new(1.0 / 0.001f64.powi(2), 1.0, 1.0, 1e6));
        for k in 0..12 {
            let t = 0.5 * k as f64;
            let truth = if k == 7 { 0.04 } else { 0.002 };
            let rel = |f: &CalibrationFilter| (1.0 + truth) / (1.0 + f.correction().focal_rel) - 1.0;
            let used = own.update(t, &frame(info, Vector4::new(rel(&own), 0.0, 0.0, 0.0))).is_some();
            let evidence = carried.focal_evidence(
                t,
                &frame(info, Vector4::new(rel(&carried), 0.0, 0.0, 0.0)),
                carrier_var,
            );
            assert_eq!(used, evidence.is_some(), "frame {k}");
            if let Some((z, var)) = evidence {
                let gain = carrier_var / (carrier_var + var);
                carrier_var *= 1.0 - gain;
                carried.shift_focal(gain * z, carrier_var);
            }
            let (a, b) = (own.correction().focal_rel, carried.correction().focal_rel);
            assert!((a - b).abs() < 1e-3 * a.abs().max(1e-3), "frame {k}: {a} {b}");
            let (pa, pb) = (own.covariance()[(0, 0)], carried.covariance()[(0, 0)]);
            assert!((pa - pb).abs() < 1e-2 * pa, "frame {k}: {pa} {pb}");
        }
        assert_eq!((own.updates, own.refused), (carried.updates, carried.refused));
        assert!(own.refused == 1 && (own.correction().focal_rel - 0.002).abs() < 3e-4, "{own:?}");
        assert!(
            carried.focal_only()
                && !CalibrationFilter::new(camera, CalibrationParams { principal_point: true, ..p })
                    .focal_only()
        );
    }

    #[test]
    fn correlated_frames_count_once_per_correlation_time() {
        let info = Matrix4::from_diagonal(&Vector4::new(1.0 / 0.001f64.powi(2), 1.0, 1.0, 1e6));
        let sigma_after = |correlation_s: f64| {
            let mut f = CalibrationFilter::new(
                CameraModel::from_fov(1024, 768, 30.0),
                CalibrationParams { correlation_s, ..Default::default() },
            );
            // 2 Hz for 30 s.
            for k in 0..60 {
                f.update(k as f64 * 0.5, &frame(info, Vector4::zeros())).unwrap();
            }
            f.covariance()[(0, 0)].sqrt()
        };
        let (independent, correlated) = (sigma_after(0.0), sigma_after(5.0));
        println!(
            "focal sigma after 60 frames: {independent:.6} independent, {correlated:.6} with 5 s correlation"
        );
        // ~60 independent frames against ~7 (the first counts fully).
        assert!(
            (correlated / independent - (60.0f64 / 6.9).sqrt()).abs() < 0.3,
            "{independent} {correlated}"
        );
    }

    /// Frames of an oblique camera crossing relief, rendered with a focal
    /// length 0.3% longer than the nominal one: the filter finds it and the
    /// positions solved with its camera beat the nominal camera's.
    #[test]
    fn converges_on_a_known_focal_error_over_relief() {
        let error = IntrinsicsCorrection { focal_rel: 0.003, ..Default::default() };
        let (f, err_nominal, err_calibrated) =
            fly_over_relief(error, CalibrationParams { correlation_s: 1.0, ..Default::default() });
        let (est, sigma) = (f.correction().focal_rel, f.covariance()[(0, 0)].sqrt());
        println!(
            "focal {est:.5} +- {sigma:.5} (truth 0.003, {} frames used); mean position error {err_nominal:.1} m \
             nominal, {err_calibrated:.1} m self-calibrated",
            f.updates
        );
        assert!((est - 0.003).abs() < 3.0 * sigma && sigma < 0.0005, "{est} {sigma}");
        assert!(err_calibrated < 0.5 * err_nominal, "{err_calibrated} {err_nominal}");
    }

    #[test]
    fn converges_on_a_known_k1_error_with_the_focal_length() {
        let error = IntrinsicsCorrection { focal_rel: 0.003, k1: 0.002, ..Default::default() };
        let params = CalibrationParams { correlation_s: 1.0, k1_sigma: 0.005, ..Default::default() };
        let (f, err_nominal, err_calibrated) = fly_over_relief(error, params);
        let (c, p) = (f.correction(), f.covariance());
        let (k1_sigma, focal_sigma) = (p[(3, 3)].sqrt(), p[(0, 0)].sqrt());
        println!(
            "k1 {:.5} +- {k1_sigma:.5} (truth 0.002), focal {:.5} +- {focal_sigma:.5}; position error \
             {err_nominal:.1} m nominal, {err_calibrated:.1} m self-calibrated",
            c.k1, c.focal_rel
        );
        assert!((c.k1 - 0.002).abs() < 3.0 * k1_sigma && k1_sigma < 0.0005, "{c:?} {k1_sigma}");
        assert!((c.focal_rel - 0.003).abs() < 3.0 * focal_sigma, "{c:?} {focal_sigma}");
        assert!(err_calibrated < 0.5 * err_nominal, "{err_calibrated} {err_nominal}");
        // Not estimated, k1 stays camera.json's.
        let (g, _, _) =
            fly_over_relief(error, CalibrationParams { correlation_s: 1.0, ..Default::default() });
        assert_eq!((g.correction().k1, g.covariance()[(3, 3)]), (0.0, 0.0));
    }

    /// 60 frames of an oblique camera with the `error` crossing relief, the
    /// filter fed with each; returns it and the mean position error of the
    /// frames solved with the nominal camera and with the filter's.
    fn fly_over_relief(
        error: IntrinsicsCorrection,
        params: CalibrationParams,
    ) -> (CalibrationFilter, f64, f64) {
        let nominal = CameraModel::from_fov(640, 480, 60.0);
        let truth = error.apply(&nominal);
        let mut f = CalibrationFilter::new(nominal, params);
        let mut seed = 5u64;
        let mut uniform = move || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let (mut err_nominal, mut err_calibrated) = (0.0, 0.0);
        let frames = 60;
        for k in 0..frames {
            let t = k as f64 * 0.5;
            // 6 km up, 40 degrees forward, moving east at 120 m/s.
            let here = Geodetic::new(37.3, -118.5 + k as f64 * 60.0 / 88_600.0, 6000.0);
            let local = LocalFrame::at(Geodetic::new(here.lat_deg, here.lon_deg, 0.0));
            let below = Geodetic::new(here.lat_deg, here.lon_deg, 0.0).to_ecef();
            let north = local.vector_to_ecef(&Vector3::y());
            let east = local.vector_to_ecef(&Vector3::x());
            let mut pose = CameraPose::look_at(here.to_ecef(), below, north);
            let tilt =
                UnitQuaternion::from_axis_angle(&nalgebra::Unit::new_normalize(east), 40f64.to_radians());
            pose.q_ecef_cam = tilt * pose.q_ecef_cam;
            let (mut pixels, mut points) = (Vec::new(), Vec::new());
            while points.len() < 150 {
                let px = Pixel::new(uniform() * 639.0, uniform() * 479.0);
                // Relief of 0-2500 m under the view.
                let Some(p) = intersect_ellipsoid(&pose.ray(&truth, px), uniform() * 2500.0) else {
                    continue;
                };
                let Some(exact) = pose.project(&truth, &p) else { continue };
                let (du, dv) = ((uniform() - 0.5) * 0.6, (uniform() - 0.5) * 0.6);
                pixels.push(Pixel::new(exact.u + du, exact.v + dv));
                points.push(p.0);
            }
            let opts = RefineOptions::default();
            let solve =
                |camera: &CameraModel| refine_pose(camera, &pixels, &points, &pose, &opts).unwrap().pose;
            err_nominal += solve(&nominal).position.distance_m(&pose.position) / frames as f64;
            f.propagate(t);
            let camera = f.camera();
            let solved = solve(&camera);
            err_calibrated += solved.position.distance_m(&pose.position) / frames as f64;
            let fc = frame_calibration(&camera, &pixels, &points, &solved, 0.17, 20.0, None).unwrap();
            f.update(t, &fc);
        }
        (f, err_nominal, err_calibrated)
    }
}
