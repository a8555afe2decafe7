//! Online self-calibration of the camera: focal length and principal point
//! as filter states with priors around `camera.json`, updated by every
//! accepted fix with what its matches say about them once the pose is
//! eliminated ([`trn_vision::calib::frame_calibration`]).
//!
//! A 0.3% focal error moves a solved position by 0.3% of the range (90 m at
//! 30 km) for any navigator that trusts the nominal camera; relief in view
//! tells the two apart (see `trn_vision::calib`). The state is
//! `x = [focal_rel, du_px, dv_px]` (the true camera is the nominal one with
//! `fx, fy` times `1 + focal_rel` and the principal point moved by
//! `(du, dv)`), with covariance `P`, a random walk between frames (a lens
//! warming up), and per accepted frame an information-form update
//! (one Gauss-Newton step of the frame's cost from the current estimate):
//!
//! ```text
//! P+ = (P^-1 + T H T)^-1,   x+ = x - P+ T g,   T = diag(1 / (1 + focal_rel), 1, 1)
//! ```
//!
//! (`H`, `g`: the frame's information and gradient, relative to the current
//! camera, so `T` maps them onto the state). The frame's evidence is weighed
//! with the larger of the nominal pixel sigma and its inliers' RMS
//! residual, and a frame whose own estimate disagrees with the state beyond
//! [`FRAME_GATE_CHI2`] is not used: relief that the database has wrong
//! shows up as a focal error, and one frame of bad heights must not move it.

use nalgebra::{Matrix3, Vector3};
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
    /// and only the focal length is estimated.
    pub principal_point: bool,
}

impl Default for CalibrationParams {
    fn default() -> Self {
        Self {
            focal_sigma_rel: 0.005,
            principal_sigma_px: 3.0,
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

/// A frame's own estimate farther than this from the state (squared
/// Mahalanobis distance with the state's and the frame's covariances, 3
/// degrees of freedom, 99.9%) is not used.
pub const FRAME_GATE_CHI2: f64 = 16.27;

/// The calibration estimate (see the module docs).
#[derive(Clone, Debug)]
pub struct CalibrationFilter {
    nominal: CameraModel,
    params: CalibrationParams,
    x: Vector3<f64>,
    p: Matrix3<f64>,
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
    /// with (`[focal_rel of that camera, du, dv]`): the pose follows it by
    /// `FrameCalibration::pose_sensitivity * step`.
    pub relative: Vector3<f64>,
    /// The frame's disagreement with the state before the update (chi-square, 3 dof).
    pub chi2: f64,
}

impl CalibrationFilter {
    pub fn new(nominal: CameraModel, params: CalibrationParams) -> Self {
        let pp_var = if params.principal_point { params.principal_sigma_px.powi(2) } else { 0.0 };
        let p = Matrix3::from_diagonal(&Vector3::new(params.focal_sigma_rel.powi(2), pp_var, pp_var));
        Self {
            nominal,
            params,
            x: Vector3::zeros(),
            p,
            t: None,
            last_update_t: None,
            updates: 0,
            refused: 0,
            weak: 0,
        }
    }

    pub fn correction(&self) -> IntrinsicsCorrection {
        IntrinsicsCorrection::from_vector(&self.x)
    }

    /// Covariance of `[focal_rel, du_px, dv_px]`.
    pub fn covariance(&self) -> Matrix3<f64> {
        self.p
    }

    /// The camera as estimated now.
    pub fn camera(&self) -> CameraModel {
        self.correction().apply(&self.nominal)
    }

    /// Adds the random walk up to `t`.
    pub fn propagate(&mut self, t: f64) {
        if let Some(t0) = self.t {
            let dt = (t - t0).max(0.0);
            self.p[(0, 0)] += self.params.focal_walk_rel_sqrt_s.powi(2) * dt;
            if self.params.principal_point {
                self.p[(1, 1)] += self.params.principal_walk_px_sqrt_s.powi(2) * dt;
                self.p[(2, 2)] += self.params.principal_walk_px_sqrt_s.powi(2) * dt;
            }
        }
        self.t = Some(self.t.map_or(t, |t0| t0.max(t)));
    }

    /// `T`: state change per unit of the frame's relative correction, inverted.
    fn to_state(&self) -> Matrix3<f64> {
        Matrix3::from_diagonal(&Vector3::new(1.0 / (1.0 + self.x.x), 1.0, 1.0))
    }

    /// Covariance of the pose `[dtheta; dp]` that the calibration's
    /// uncertainty adds to a frame solved with [`Self::camera`]: the
    /// estimate's, and a principal point not estimated with its prior
    /// (a consider parameter: a nadir view turns its error into a tilt, and
    /// the tilt into a horizontal shift).
    pub fn pose_covariance(&self, frame: &FrameCalibration) -> nalgebra::Matrix6<f64> {
        // A state change dx is the frame's relative correction T dx.
        let s = frame.pose_sensitivity * self.to_state();
        let mut p = self.p;
        if !self.params.principal_point {
            p[(1, 1)] = self.params.principal_sigma_px.powi(2);
            p[(2, 2)] = self.params.principal_sigma_px.powi(2);
        }
        s * p * s.transpose()
    }

    pub fn params(&self) -> &CalibrationParams {
        &self.params
    }

    /// The frame's own focal estimate (relative to the camera it was solved
    /// with) and its sigma; with the principal point not estimated, its
    /// prior uncertainty is marginalised (a consider parameter), so its
    /// error does not pass for a focal one.
    pub fn frame_focal(&self, frame: &FrameCalibration) -> (f64, f64) {
        let (h, g) = self.focal_evidence(frame);
        (-g / h, h.recip().sqrt())
    }

    /// Information and gradient of the relative focal correction alone.
    fn focal_evidence(&self, frame: &FrameCalibration) -> (f64, f64) {
        let h = &frame.information;
        let g = &frame.gradient;
        let mut h_pp = h.fixed_view::<2, 2>(1, 1).into_owned();
        let lambda = self.params.principal_sigma_px.powi(-2);
        h_pp[(0, 0)] += lambda;
        h_pp[(1, 1)] += lambda;
        let h_fp = h.fixed_view::<1, 2>(0, 1).into_owned();
        match h_pp.try_inverse() {
            Some(inv) => (
                h[(0, 0)] - (h_fp * inv * h_fp.transpose())[(0, 0)],
                g.x - (h_fp * inv * g.fixed_rows::<2>(1))[(0, 0)],
            ),
            None => (h[(0, 0)], g.x),
        }
    }

    /// Updates with one frame's evidence at `t`, computed at
    /// [`Self::camera`]. `None` when the frame was too weak or refused
    /// (gate, or a singular system).
    pub fn update(&mut self, t_frame: f64, frame: &FrameCalibration) -> Option<CalibrationStep> {
        let (_, frame_sigma) = self.frame_focal(frame);
        if !(frame_sigma <= self.params.max_frame_sigma_rel) {
            self.weak += 1;
            return None;
        }
        let weight = match self.last_update_t {
            Some(t0) if self.params.correlation_s > 0.0 => {
                ((t_frame - t0) / self.params.correlation_s).clamp(0.0, 1.0)
            }
            _ => 1.0,
        };
        let t = self.to_state();
        let (mut h, mut g) = (t * frame.information * t * weight, t * frame.gradient * weight);
        if !self.params.principal_point {
            let (hf, gf) = self.focal_evidence(frame);
            h = Matrix3::from_diagonal(&Vector3::new(hf * t[(0, 0)].powi(2) * weight, 0.0, 0.0));
            g = Vector3::new(gf * t[(0, 0)] * weight, 0.0, 0.0);
        }
        let (p_new, dx) = if self.params.principal_point {
            let p_new = (self.p.try_inverse()? + h).try_inverse()?;
            let p_new = (p_new + p_new.transpose()) * 0.5;
            (p_new, -p_new * g)
        } else {
            let mut p_new = self.p;
            p_new[(0, 0)] = 1.0 / (1.0 / self.p[(0, 0)] + h[(0, 0)]);
            (p_new, Vector3::new(-p_new[(0, 0)] * g.x, 0.0, 0.0))
        };
        // The frame's innovation: its own estimate `-H^-1 g` against the
        // state, covariance `H^-1 + P`. With `(H^-1 + P)^-1 = H - H P+ H`
        // (Woodbury) the chi-square needs no inverse of a weak `H`:
        // nu^T (H - H P+ H) nu with H nu = -g gives g^T H^-1 g - g^T P+ g,
        // and H^-1 g is solved in the subspace `H` determines.
        let eig = h.symmetric_eigen();
        let max = eig.eigenvalues.max().max(0.0);
        let mut h_inv_g = 0.0;
        for i in 0..3 {
            let l = eig.eigenvalues[i];
            if l > 1e-9 * max && l > 0.0 {
                let c = eig.eigenvectors.column(i).dot(&g);
                h_inv_g += c * c / l;
            }
        }
        let chi2 = (h_inv_g - g.dot(&(p_new * g))).max(0.0);
        if !(chi2 <= FRAME_GATE_CHI2) {
            self.refused += 1;
            return None;
        }
        self.x += dx;
        self.p = p_new;
        self.updates += 1;
        self.last_update_t = Some(t_frame);
        Some(CalibrationStep { relative: t * dx, chi2 })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{SMatrix, UnitQuaternion};
    use trn_camera::{CameraPose, Pixel};
    use trn_geodesy::{intersect_ellipsoid, Geodetic, LocalFrame};
    use trn_vision::calib::frame_calibration;
    use trn_vision::pnp::{refine_pose, RefineOptions};

    fn frame(information: Matrix3<f64>, estimate: Vector3<f64>) -> FrameCalibration {
        FrameCalibration {
            information,
            gradient: -information * estimate,
            pose_sensitivity: SMatrix::<f64, 6, 3>::zeros(),
        }
    }

    fn params() -> CalibrationParams {
        CalibrationParams { correlation_s: 0.0, ..Default::default() }
    }

    #[test]
    fn a_frame_far_from_the_state_is_refused_and_a_weak_one_unused() {
        let mut f = CalibrationFilter::new(CameraModel::from_fov(1024, 768, 30.0), params());
        let info = Matrix3::from_diagonal(&Vector3::new(1.0 / 0.0005f64.powi(2), 1.0, 1.0));
        for k in 0..20 {
            // The frame's estimate is relative to the camera it was solved with.
            let rel = 1.001 / (1.0 + f.correction().focal_rel) - 1.0;
            f.update(k as f64, &frame(info, Vector3::new(rel, 0.0, 0.0))).unwrap();
        }
        assert!((f.correction().focal_rel - 0.001).abs() < 1e-4, "{:?}", f.correction());
        let before = f.correction();
        // 5% of focal in one frame: bad heights, not the lens.
        assert!(f.update(20.0, &frame(info, Vector3::new(0.05, 0.0, 0.0))).is_none());
        // A flat nadir view's 4% sigma says nothing worth using.
        let weak = Matrix3::from_diagonal(&Vector3::new(1.0 / 0.04f64.powi(2), 1.0, 1.0));
        assert!(f.update(21.0, &frame(weak, Vector3::new(0.01, 0.0, 0.0))).is_none());
        assert_eq!(f.correction(), before);
        assert_eq!((f.updates, f.refused, f.weak), (20, 1, 1));
    }

    #[test]
    fn correlated_frames_count_once_per_correlation_time() {
        let info = Matrix3::from_diagonal(&Vector3::new(1.0 / 0.001f64.powi(2), 1.0, 1.0));
        let sigma_after = |correlation_s: f64| {
            let mut f = CalibrationFilter::new(
                CameraModel::from_fov(1024, 768, 30.0),
                CalibrationParams { correlation_s, ..Default::default() },
            );
            // 2 Hz for 30 s.
            for k in 0..60 {
                f.update(k as f64 * 0.5, &frame(info, Vector3::zeros())).unwrap();
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
        let nominal = CameraModel::from_fov(640, 480, 60.0);
        let truth = IntrinsicsCorrection { focal_rel: 0.003, ..Default::default() }.apply(&nominal);
        let mut f =
            CalibrationFilter::new(nominal, CalibrationParams { correlation_s: 1.0, ..Default::default() });
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
        let (est, sigma) = (f.correction().focal_rel, f.covariance()[(0, 0)].sqrt());
        println!(
            "focal {est:.5} +- {sigma:.5} (truth 0.003, {} frames used); mean position error {err_nominal:.1} m \
             nominal, {err_calibrated:.1} m self-calibrated",
            f.updates
        );
        assert!((est - 0.003).abs() < 3.0 * sigma && sigma < 0.0005, "{est} {sigma}");
        assert!(err_calibrated < 0.5 * err_nominal, "{err_calibrated} {err_nominal}");
    }
}
