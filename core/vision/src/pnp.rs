//! Levenberg-Marquardt refinement of a camera pose on 2D-3D matches
//! (reprojection error in pixels through the full distortion model), with an
//! optional Huber loss and attitude or full pose prior, and the pose
//! covariance; plus
//! [`solve`], RANSAC followed by refinement.
//!
//! Parameterisation (also the order of the covariance): a perturbation
//! `[dtheta; dp]` of a pose acts as `q_ecef_cam <- exp(dtheta) * q_ecef_cam`
//! (rotation vector `dtheta`, rad, in the ECEF frame) and
//! `position <- position + dp` (ECEF, m). For east/north/up, rotate each 3x3
//! block with `trn_geodesy::LocalFrame::r_ecef_enu()`: `R^T P R`.

use nalgebra::{Matrix2x3, Matrix3, Matrix6, SMatrix, UnitQuaternion, Vector2, Vector3, Vector6};
use trn_camera::{CameraModel, CameraPose, NormalizedPoint, Pixel};
use trn_geodesy::Ecef;

use crate::ransac::{ransac_p3p, RansacParams};

/// Settings of [`refine_pose`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RefineOptions {
    /// Upper bound on Levenberg-Marquardt steps (accepted or not).
    pub max_iterations: usize,
    /// Huber loss on each point's reprojection error (pixels): quadratic below
    /// this, linear above. `None`: plain least squares.
    pub huber_px: Option<f64>,
    /// Attitude prior, e.g. a gyro-propagated attitude that pins tilt where a
    /// narrow-FOV nadir view cannot tell tilt from translation.
    pub prior: Option<AttitudePrior>,
    /// Prior on the whole pose, e.g. an inertial filter's prediction: the
    /// refinement is then the filter's (iterated) measurement update on the
    /// matches themselves. Exclusive with `prior`.
    pub pose_prior: Option<PosePrior>,
    /// Standard deviation of a pixel coordinate (px): pixel residuals are
    /// divided by it, so it weighs them against the prior and scales the
    /// covariance.
    pub pixel_sigma: f64,
}

impl Default for RefineOptions {
    fn default() -> Self {
        Self { max_iterations: 50, huber_px: None, prior: None, pose_prior: None, pixel_sigma: 1.0 }
    }
}

/// A prior on the attitude: adds the residual `W log(q * q_prior^-1)`
/// (rotation vector in ECEF) with `W^T W = covariance^-1`, so a filter can
/// pass on the full attitude covariance of the frames before (tight where
/// they saw it well, loose where they did not).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AttitudePrior {
    pub q_ecef_cam: UnitQuaternion<f64>,
    /// Covariance of the prior's error (rad^2, rotation vector in ECEF).
    pub covariance: Matrix3<f64>,
}

impl AttitudePrior {
    /// The same standard deviation (rad) about every axis.
    pub fn isotropic(q_ecef_cam: UnitQuaternion<f64>, sigma_rad: f64) -> Self {
        Self { q_ecef_cam, covariance: Matrix3::identity() * (sigma_rad * sigma_rad) }
    }

    /// `W` with `W^T W = covariance^-1`; `None` unless the covariance is
    /// finite, symmetric and positive definite.
    pub fn sqrt_information(&self) -> Option<Matrix3<f64>> {
        sqrt_information(&self.covariance)
    }

    /// Squared Mahalanobis distance of `q_ecef_cam` from the prior (chi-square
    /// with 3 degrees of freedom when the prior is right).
    pub fn mahalanobis2(&self, q_ecef_cam: &UnitQuaternion<f64>) -> Option<f64> {
        let w = self.sqrt_information()?;
        Some((w * rotation_vector(&(q_ecef_cam * self.q_ecef_cam.inverse()))).norm_squared())
    }
}

/// A prior on the whole pose: adds the residual `W [log(q * q_prior^-1);
/// c - c_prior]` with `W^T W = covariance^-1` (the module's perturbation
/// order), so the refinement minimises the prior's and the matches' costs
/// together: the maximum a posteriori pose, and its covariance the
/// posterior's.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PosePrior {
    pub pose: CameraPose,
    /// Covariance of `[dtheta (rad, ECEF); dp (m, ECEF)]`.
    pub covariance: Matrix6<f64>,
}

impl PosePrior {
    /// `W` with `W^T W = covariance^-1`; `None` unless the covariance is
    /// finite, symmetric and positive definite.
    pub fn sqrt_information(&self) -> Option<Matrix6<f64>> {
        sqrt_information(&self.covariance)
    }
}

/// `W` with `W^T W = p^-1` (`W = L^-1` of `p = L L^T`); `None` unless `p` is
/// finite, symmetric and positive definite.
fn sqrt_information<const N: usize>(p: &SMatrix<f64, N, N>) -> Option<SMatrix<f64, N, N>> {
    let scale = p.abs().max();
    if !p.iter().all(|x| x.is_finite()) || !(scale > 0.0) || (p - p.transpose()).abs().max() > 1e-9 * scale {
        return None;
    }
    let l = p.cholesky()?.l();
    l.solve_lower_triangular(&SMatrix::<f64, N, N>::identity())
}

/// A refined pose.
#[derive(Clone, Debug, PartialEq)]
pub struct Refined {
    pub pose: CameraPose,
    /// Covariance of `[dtheta (rad, ECEF); dp (m, ECEF)]` (see the module
    /// docs): the inverse of the whitened Gauss-Newton Hessian at the solution,
    /// `(J^T W J / pixel_sigma^2 + prior)^-1` (`W`: Huber weights), i.e.
    /// `(J^T J)^-1 pixel_sigma^2` without prior and loss.
    pub covariance: Matrix6<f64>,
    /// Root mean square of the points' reprojection errors (pixels).
    pub rms_px: f64,
    /// Reprojection error (distance, pixels) of every point at the solution.
    pub residuals_px: Vec<f64>,
    /// Levenberg-Marquardt steps taken (accepted or not).
    pub iterations: usize,
}

impl Refined {
    /// Covariance of the attitude error (rad^2, rotation vector in ECEF).
    pub fn attitude_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(0, 0).into_owned()
    }

    /// Covariance of the position (m^2, ECEF).
    pub fn position_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(3, 3).into_owned()
    }
}

/// Levenberg-Marquardt on the reprojection errors (2 residuals per match, in
/// pixels, through the full distortion model, analytic Jacobian via
/// [`trn_camera::Distortion::jacobian`]), from `initial`. `None` when there
/// are fewer than 3 matches, lengths differ, an option is invalid
/// (`pixel_sigma` or Huber threshold not positive, prior covariance not
/// positive definite), a point is
/// behind the camera at `initial`, or the pose is not determined at the
/// solution (e.g. all points identical).
pub fn refine_pose(
    camera: &CameraModel,
    pixels: &[Pixel],
    points_ecef: &[Vector3<f64>],
    initial: &CameraPose,
    opts: &RefineOptions,
) -> Option<Refined> {
    refine_pose_weighted(camera, pixels, points_ecef, None, initial, opts)
}

/// [`refine_pose`] with a pixel sigma per match (`sigma_px[i]`, replacing
/// `opts.pixel_sigma`; each must be positive and finite), e.g. the
/// correlation peak's own uncertainty on top of what all matches share.
pub fn refine_pose_weighted(
    camera: &CameraModel,
    pixels: &[Pixel],
    points_ecef: &[Vector3<f64>],
    sigma_px: Option<&[f64]>,
    initial: &CameraPose,
    opts: &RefineOptions,
) -> Option<Refined> {
    let n = pixels.len();
    if n < 3 || points_ecef.len() != n || !(opts.pixel_sigma > 0.0 && opts.pixel_sigma.is_finite()) {
        return None;
    }
    let positive = |s: f64| s > 0.0 && s.is_finite();
    if sigma_px.is_some_and(|s| s.len() != n || !s.iter().all(|&x| positive(x))) {
        return None;
    }
    let inv_sigma2: Vec<f64> = match sigma_px {
        Some(s) => s.iter().map(|x| 1.0 / (x * x)).collect(),
        None => vec![1.0 / (opts.pixel_sigma * opts.pixel_sigma); n],
    };
    if opts.huber_px.is_some_and(|k| !(k > 0.0)) {
        return None;
    }
    // Work relative to the initial position (precision at ECEF magnitudes).
    let origin = initial.position;
    let prior = match (&opts.prior, &opts.pose_prior) {
        (Some(_), Some(_)) => return None,
        (Some(p), None) => Some(PriorTerm::Attitude(p.q_ecef_cam, p.sqrt_information()?)),
        (None, Some(p)) => Some(PriorTerm::Pose {
            q: p.pose.q_ecef_cam,
            c: p.pose.position.0 - origin.0,
            w: Box::new(p.sqrt_information()?),
        }),
        (None, None) => None,
    };
    let problem = Problem {
        camera,
        pixels,
        local: points_ecef.iter().map(|p| p - origin.0).collect(),
        huber_px: opts.huber_px,
        inv_sigma2,
        prior,
    };
    let mut state = State { q: initial.q_ecef_cam, c: Vector3::zeros() };
    let mut lin = problem.linearize(&state)?;
    if !lin.cost.is_finite() {
        return None;
    }
    let depth_scale =
        (problem.local.iter().map(|x| x.norm_squared()).sum::<f64>() / n as f64).sqrt().max(1e-3);

    let mut mu = 1e-4;
    let mut iterations = 0;
    while iterations < opts.max_iterations {
        iterations += 1;
        // Marquardt damping on the diagonal (plus a tiny floor for rank-deficient H).
        let max_diag = lin.h.diagonal().max();
        let mut a = lin.h;
        for i in 0..6 {
            a[(i, i)] += mu * (lin.h[(i, i)] + 1e-12 * max_diag);
        }
        let Some(delta) = a.cholesky().map(|ch| ch.solve(&-lin.g)) else {
            mu *= 10.0;
            continue;
        };
        let candidate = state.apply(&delta);
        let tiny_step =
            delta.fixed_rows::<3>(0).norm() < 1e-13 && delta.fixed_rows::<3>(3).norm() < 1e-13 * depth_scale;
        match problem.linearize(&candidate) {
            Some(next) if next.cost < lin.cost => {
                let decrease = lin.cost - next.cost;
                let old_cost = lin.cost;
                state = candidate;
                lin = next;
                mu = (mu * 0.1).max(1e-12);
                // Converged: tiny step, stalled cost, or (noise-free) RMS below 1e-12 px.
                if tiny_step
                    || decrease <= 1e-14 * old_cost
                    || lin.cost <= 1e-24 * problem.inv_sigma2.iter().sum::<f64>()
                {
                    break;
                }
            }
            _ => {
                mu *= 10.0;
                if tiny_step || mu > 1e12 {
                    break;
                }
            }
        }
    }

    let covariance = invert_normalized(&lin.h)?;
    let pose = CameraPose { position: Ecef(origin.0 + state.c), q_ecef_cam: state.q };
    let residuals_px: Vec<f64> =
        problem.local.iter().zip(pixels).map(|(x, px)| problem.error_px(&state, x, px)).collect();
    let rms_px = (residuals_px.iter().map(|e| e * e).sum::<f64>() / n as f64).sqrt();
    Some(Refined { pose, covariance, rms_px, residuals_px, iterations })
}

/// RANSAC ([`ransac_p3p`]), then [`refine_pose`] on its inliers, then the
/// inliers re-classified with the refined pose (`threshold_px`) and, if they
/// changed, one more refinement on the new set.
#[derive(Clone, Debug, PartialEq)]
pub struct Solution {
    pub pose: CameraPose,
    /// See [`Refined::covariance`].
    pub covariance: Matrix6<f64>,
    /// The matches used in the final refinement.
    pub inliers: Vec<bool>,
    pub n_inliers: usize,
    /// RMS reprojection error (pixels) over the inliers.
    pub rms_px: f64,
    /// Reprojection error (pixels) of every match at the final pose (infinite
    /// behind the camera).
    pub residuals_px: Vec<f64>,
    pub ransac_iterations: usize,
    /// Levenberg-Marquardt steps of all refinement rounds.
    pub refine_iterations: usize,
}

impl Solution {
    pub fn attitude_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(0, 0).into_owned()
    }

    pub fn position_covariance(&self) -> Matrix3<f64> {
        self.covariance.fixed_view::<3, 3>(3, 3).into_owned()
    }
}

/// Robust pose from 2D-3D matches, see [`Solution`]. `None` when RANSAC fails,
/// a refinement fails, or fewer than `max(min_inliers, 4)` inliers remain.
pub fn solve(
    camera: &CameraModel,
    pixels: &[Pixel],
    points_ecef: &[Vector3<f64>],
    ransac_params: &RansacParams,
    refine_opts: &RefineOptions,
) -> Option<Solution> {
    let ransac = ransac_p3p(camera, pixels, points_ecef, ransac_params)?;
    let min_inliers = ransac_params.min_inliers.max(4);
    let threshold = ransac_params.threshold_px;
    let refine_on = |inliers: &[bool], initial: &CameraPose| {
        let (px, pts): (Vec<Pixel>, Vec<Vector3<f64>>) =
            (0..pixels.len()).filter(|&i| inliers[i]).map(|i| (pixels[i], points_ecef[i])).unzip();
        refine_pose(camera, &px, &pts, initial, refine_opts)
    };
    let all_errors = |pose: &CameraPose| -> Vec<f64> {
        pixels
            .iter()
            .zip(points_ecef)
            .map(|(px, p)| pose.project(camera, &Ecef(*p)).map_or(f64::INFINITY, |q| q.distance_px(px)))
            .map(|e| if e.is_nan() { f64::INFINITY } else { e })
            .collect()
    };

    let mut inliers = ransac.inliers;
    let mut refined = refine_on(&inliers, &ransac.pose)?;
    let mut iterations = refined.iterations;
    let mut residuals = all_errors(&refined.pose);
    let reclassified: Vec<bool> = residuals.iter().map(|&e| e < threshold).collect();
    if reclassified != inliers {
        inliers = reclassified;
        if inliers.iter().filter(|&&b| b).count() < min_inliers {
            return None;
        }
        refined = refine_on(&inliers, &refined.pose)?;
        iterations += refined.iterations;
        residuals = all_errors(&refined.pose);
    }
    let n_inliers = inliers.iter().filter(|&&b| b).count();
    if n_inliers < min_inliers {
        return None;
    }
    Some(Solution {
        pose: refined.pose,
        covariance: refined.covariance,
        inliers,
        n_inliers,
        rms_px: refined.rms_px,
        residuals_px: residuals,
        ransac_iterations: ransac.iterations,
        refine_iterations: iterations,
    })
}

/// Pose being refined: attitude and camera centre relative to the origin.
#[derive(Clone, Copy, Debug)]
struct State {
    q: UnitQuaternion<f64>,
    c: Vector3<f64>,
}

impl State {
    fn apply(&self, delta: &Vector6<f64>) -> State {
        let dtheta = delta.fixed_rows::<3>(0).into_owned();
        State { q: UnitQuaternion::from_scaled_axis(dtheta) * self.q, c: self.c + delta.fixed_rows::<3>(3) }
    }
}

/// Cost `sum rho(e_i) / sigma^2 + |r_prior|^2`, with gradient `g` and
/// Gauss-Newton Hessian `h` of half of it.
struct Linearization {
    cost: f64,
    h: Matrix6<f64>,
    g: Vector6<f64>,
}

struct Problem<'a> {
    camera: &'a CameraModel,
    pixels: &'a [Pixel],
    local: Vec<Vector3<f64>>,
    huber_px: Option<f64>,
    /// Per match: 1 / sigma^2 (px^-2).
    inv_sigma2: Vec<f64>,
    prior: Option<PriorTerm>,
}

/// A prior's mean and square-root information `W`.
enum PriorTerm {
    Attitude(UnitQuaternion<f64>, Matrix3<f64>),
    /// The position `c` relative to the problem's origin.
    Pose {
        q: UnitQuaternion<f64>,
        c: Vector3<f64>,
        w: Box<Matrix6<f64>>,
    },
}

impl Problem<'_> {
    /// `None` when a point is behind the camera.
    fn linearize(&self, state: &State) -> Option<Linearization> {
        let cam = self.camera;
        let r_cam_ecef = state.q.inverse().to_rotation_matrix().into_inner();
        let mut cost = 0.0;
        let mut h = Matrix6::zeros();
        let mut g = Vector6::zeros();
        for ((x, obs), &inv_sigma2) in self.local.iter().zip(self.pixels).zip(&self.inv_sigma2) {
            let pt = linearize_point(cam, &r_cam_ecef, &(x - state.c), obs)?;
            let (r, j) = (pt.residual_px, pt.j_pose);
            let (rho, w) = huber(r.norm_squared(), self.huber_px);
            cost += rho * inv_sigma2;
            let ws = w * inv_sigma2;
            h += j.transpose() * j * ws;
            g += j.transpose() * r * ws;
        }
        match &self.prior {
            Some(PriorTerm::Attitude(q_prior, w)) => {
                let phi = rotation_vector(&(state.q * q_prior.inverse()));
                let r = w * phi;
                let jp = w * inverse_left_jacobian(&phi);
                cost += r.norm_squared();
                let mut hp = h.fixed_view_mut::<3, 3>(0, 0);
                hp += jp.transpose() * jp;
                let mut gp = g.fixed_rows_mut::<3>(0);
                gp += jp.transpose() * r;
            }
            Some(PriorTerm::Pose { q, c, w }) => {
                let phi = rotation_vector(&(state.q * q.inverse()));
                let mut e = Vector6::zeros();
                e.fixed_rows_mut::<3>(0).copy_from(&phi);
                e.fixed_rows_mut::<3>(3).copy_from(&(state.c - c));
                let mut j = Matrix6::identity();
                j.fixed_view_mut::<3, 3>(0, 0).copy_from(&inverse_left_jacobian(&phi));
                let r = w.as_ref() * e;
                let jp = w.as_ref() * j;
                cost += r.norm_squared();
                h += jp.transpose() * jp;
                g += jp.transpose() * r;
            }
            None => {}
        }
        Some(Linearization { cost, h, g })
    }

    /// Reprojection error (pixels) of one point; infinite behind the camera.
    fn error_px(&self, state: &State, x: &Vector3<f64>, px: &Pixel) -> f64 {
        let p = state.q.inverse_transform_vector(&(x - state.c));
        self.camera.project(&p).map_or(f64::INFINITY, |q| q.distance_px(px))
    }
}

/// One match linearized at a pose (see [`linearize_point`]).
pub(crate) struct PointLinearization {
    /// Predicted minus observed pixel.
    pub residual_px: Vector2<f64>,
    /// d(residual)/d[dtheta; dp] (the module's perturbation).
    pub j_pose: SMatrix<f64, 2, 6>,
    /// The point's distorted normalized coordinates (`u = fx x + cx`).
    pub distorted: NormalizedPoint,
    /// The point's normalized coordinates before distortion (`x/z, y/z`).
    pub normalized: NormalizedPoint,
}

/// Residual and pose Jacobian of one match; `v` is the point minus the
/// camera centre (ECEF), `r_cam_ecef` the camera's rotation ECEF -> camera.
/// `None` behind the camera.
pub(crate) fn linearize_point(
    cam: &CameraModel,
    r_cam_ecef: &Matrix3<f64>,
    v: &Vector3<f64>,
    obs: &Pixel,
) -> Option<PointLinearization> {
    let p = r_cam_ecef * v;
    if !(p.z > 0.0) {
        return None;
    }
    let inv_z = 1.0 / p.z;
    let n = NormalizedPoint::new(p.x * inv_z, p.y * inv_z);
    let d = cam.distortion.apply(n);
    let r = Vector2::new(cam.fx * d.x + cam.cx - obs.u, cam.fy * d.y + cam.cy - obs.v);
    // d(pixel)/d(p_cam) = diag(fx, fy) * D(distortion) * d(x/z, y/z)/dp
    let jd = cam.distortion.jacobian(n);
    let jn = Matrix2x3::new(inv_z, 0.0, -n.x * inv_z, 0.0, inv_z, -n.y * inv_z);
    let mut a = jd * jn;
    a.row_mut(0).scale_mut(cam.fx);
    a.row_mut(1).scale_mut(cam.fy);
    // p = R^T (x - c): dp/dtheta = R^T [v]x, dp/dc = -R^T.
    let b = a * r_cam_ecef;
    let j_theta = b * v.cross_matrix();
    let mut j = SMatrix::<f64, 2, 6>::zeros();
    j.fixed_view_mut::<2, 3>(0, 0).copy_from(&j_theta);
    j.fixed_view_mut::<2, 3>(0, 3).copy_from(&-b);
    Some(PointLinearization { residual_px: r, j_pose: j, distorted: d, normalized: n })
}

/// Huber loss `rho(e)` of a squared error `e2` with threshold `k` (none:
/// plain squares) and the IRLS weight `rho'(e) / (2 e)`.
pub(crate) fn huber(e2: f64, k: Option<f64>) -> (f64, f64) {
    match k {
        Some(k) if e2 > k * k => {
            let e = e2.sqrt();
            (2.0 * k * e - k * k, k / e)
        }
        _ => (e2, 1.0),
    }
}

/// The pixel where `pose` sees `point_ecef` and its Jacobian in the pose
/// perturbation `[dtheta (rad, ECEF); dp (m, ECEF)]` of this module
/// (`q = exp(dtheta) q`, `c = c + dp`), through the full distortion model;
/// `None` behind the camera. What a filter needs to carry a pose covariance
/// into the image.
pub fn project_with_jacobian(
    camera: &CameraModel,
    pose: &CameraPose,
    point_ecef: &Vector3<f64>,
) -> Option<(Pixel, SMatrix<f64, 2, 6>)> {
    let r_cam_ecef = pose.q_ecef_cam.inverse().to_rotation_matrix().into_inner();
    // The residual against pixel (0, 0) is the predicted pixel itself.
    let pt = linearize_point(camera, &r_cam_ecef, &(point_ecef - pose.position.0), &Pixel::new(0.0, 0.0))?;
    Some((Pixel::new(pt.residual_px.x, pt.residual_px.y), pt.j_pose))
}

/// Rotation vector (axis * angle, angle in `[0, pi]`) of a unit quaternion,
/// accurate for small angles (nalgebra's `scaled_axis` goes through `acos`).
pub fn rotation_vector(q: &UnitQuaternion<f64>) -> Vector3<f64> {
    let (w, v) = if q.w < 0.0 { (-q.w, -q.imag()) } else { (q.w, q.imag()) };
    let s = v.norm();
    if s < 1e-300 {
        return v * 2.0;
    }
    v * (2.0 * s.atan2(w) / s)
}

/// `J_l^-1(phi)` of SO(3): `log(exp(d) exp(phi)) = phi + J_l^-1(phi) d + O(d^2)`.
fn inverse_left_jacobian(phi: &Vector3<f64>) -> Matrix3<f64> {
    let theta2 = phi.norm_squared();
    let k = phi.cross_matrix();
    let coeff = if theta2 < 1e-8 {
        1.0 / 12.0 + theta2 / 720.0
    } else {
        let theta = theta2.sqrt();
        1.0 / theta2 - (1.0 + theta.cos()) / (2.0 * theta * theta.sin())
    };
    Matrix3::identity() - k * 0.5 + k * k * coeff
}

/// Inverse of a symmetric positive definite 6x6 matrix, after scaling it to
/// unit diagonal; `None` when its condition (so scaled) exceeds 1e12.
pub(crate) fn invert_normalized(h: &Matrix6<f64>) -> Option<Matrix6<f64>> {
    let diag = h.diagonal();
    if !diag.iter().all(|&d| d > 0.0 && d.is_finite()) {
        return None;
    }
    let s = diag.map(|d| 1.0 / d.sqrt());
    let hn = Matrix6::from_fn(|i, j| h[(i, j)] * s[i] * s[j]);
    let eig = hn.symmetric_eigen();
    let (min, max) = (eig.eigenvalues.min(), eig.eigenvalues.max());
    if !(min > 1e-12 * max) {
        return None;
    }
    let inv = hn.cholesky()?.inverse();
    Some(Matrix6::from_fn(|i, j| inv[(i, j)] * s[i] * s[j]))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ransac::testutil::*;
    use crate::ransac::Rng;
    use trn_camera::Distortion;

    fn perturbed(rng: &mut Rng, pose: &CameraPose, metres: f64, deg: f64) -> CameraPose {
        let dq = UnitQuaternion::from_scaled_axis(random_unit(rng) * deg.to_radians());
        CameraPose {
            position: Ecef(pose.position.0 + random_unit(rng) * metres),
            q_ecef_cam: dq * pose.q_ecef_cam,
        }
    }

    /// Error vector `[dtheta; dp]` of an estimate (the covariance's order).
    fn error(est: &CameraPose, truth: &CameraPose) -> Vector6<f64> {
        let dtheta = rotation_vector(&(est.q_ecef_cam * truth.q_ecef_cam.inverse()));
        let dp = est.position.0 - truth.position.0;
        Vector6::new(dtheta.x, dtheta.y, dtheta.z, dp.x, dp.y, dp.z)
    }

    fn exact_case(camera: &CameraModel, altitude: f64, seed: u64, label: &str) {
        let mut rng = Rng::new(seed);
        let (mut worst_pos, mut worst_rot, mut worst_it) = (0.0f64, 0.0f64, 0);
        for _ in 0..20 {
            let scene = nadir_scene(&mut rng, camera, altitude, 40, 500.0, 10.0);
            let start = perturbed(&mut rng, &scene.pose, 100.0, 1.0);
            let r = refine_pose(camera, &scene.pixels, &scene.points, &start, &RefineOptions::default())
                .expect("refined");
            worst_pos = worst_pos.max(r.pose.position.distance_m(&scene.pose.position));
            worst_rot = worst_rot.max(rotation_error(&r.pose.q_ecef_cam, &scene.pose.q_ecef_cam));
            worst_it = worst_it.max(r.iterations);
            assert!(r.rms_px < 1e-6, "{}", r.rms_px);
        }
        println!(
            "refine noise-free {label}: worst position error {worst_pos:.2e} m, rotation {worst_rot:.2e} rad, \
             {worst_it} iterations"
        );
        assert!(worst_pos < 1e-6 && worst_rot < 1e-9, "{worst_pos:e} {worst_rot:e}");
    }

    #[test]
    fn noise_free_is_exact_from_perturbed_start() {
        exact_case(&CameraModel::from_fov(1024, 768, 60.0), 5000.0, 1, "60 deg 5 km");
        exact_case(&CameraModel::from_fov(1024, 768, 32.0), 30_000.0, 2, "32 deg 30 km");
    }

    #[test]
    fn noise_free_with_distortion_is_exact() {
        let mut camera = CameraModel::from_fov(1024, 768, 60.0);
        camera.distortion = Distortion { k1: -0.2, k2: 0.05, p1: 0.001, p2: -0.0005, k3: 0.0 };
        camera.validate().unwrap();
        exact_case(&camera, 5000.0, 3, "60 deg 5 km distorted");
    }

    #[test]
    fn projection_jacobian_matches_the_pose_perturbation() {
        let mut camera = CameraModel::from_fov(640, 480, 70.0);
        camera.distortion = Distortion { k1: -0.2, k2: 0.05, p1: 0.001, p2: -0.0005, k3: 0.01 };
        let mut rng = Rng::new(9);
        let scene = nadir_scene(&mut rng, &camera, 3000.0, 5, 300.0, 10.0);
        for x in &scene.points {
            let (px, j) = project_with_jacobian(&camera, &scene.pose, x).unwrap();
            assert!(px.distance_px(&scene.pose.project(&camera, &Ecef(*x)).unwrap()) < 1e-9);
            for k in 0..6 {
                let h = if k < 3 { 1e-7 } else { 1e-3 };
                let mut d = nalgebra::Vector6::zeros();
                d[k] = h;
                let plus = crate::calib::perturb_pose(&scene.pose, &d).project(&camera, &Ecef(*x)).unwrap();
                let minus = crate::calib::perturb_pose(&scene.pose, &-d).project(&camera, &Ecef(*x)).unwrap();
                let numeric = ((plus.u - minus.u) / (2.0 * h), (plus.v - minus.v) / (2.0 * h));
                let scale = j.column(k).norm().max(1.0);
                assert!((j[(0, k)] - numeric.0).abs() < 1e-5 * scale, "{k}: {} {}", j[(0, k)], numeric.0);
                assert!((j[(1, k)] - numeric.1).abs() < 1e-5 * scale, "{k}: {} {}", j[(1, k)], numeric.1);
            }
        }
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let mut camera = CameraModel::from_fov(640, 480, 70.0);
        camera.distortion = Distortion { k1: -0.2, k2: 0.05, p1: 0.001, p2: -0.0005, k3: 0.01 };
        let mut rng = Rng::new(4);
        let scene = nadir_scene(&mut rng, &camera, 3000.0, 10, 300.0, 10.0);
        let origin = scene.pose.position;
        let q_prior = UnitQuaternion::from_scaled_axis(Vector3::new(0.1, -0.2, 0.05)) * scene.pose.q_ecef_cam;
        let pose_prior = PosePrior {
            pose: CameraPose {
                position: Ecef(scene.pose.position.0 + Vector3::new(40.0, -25.0, 10.0)),
                q_ecef_cam: q_prior,
            },
            covariance: Matrix6::from_fn(|i, j| {
                let d = if i < 3 { 1e-4 } else { 400.0 };
                if i == j {
                    d
                } else if i / 3 == j / 3 {
                    0.3 * d
                } else {
                    0.0
                }
            }),
        };
        for prior in [
            PriorTerm::Attitude(q_prior, AttitudePrior::isotropic(q_prior, 0.01).sqrt_information().unwrap()),
            PriorTerm::Pose {
                q: q_prior,
                c: pose_prior.pose.position.0 - origin.0,
                w: Box::new(pose_prior.sqrt_information().unwrap()),
            },
        ] {
            let problem = Problem {
                camera: &camera,
                pixels: &scene.pixels,
                local: scene.points.iter().map(|p| p - origin.0).collect(),
                huber_px: None,
                inv_sigma2: vec![1.0; scene.pixels.len()],
                prior: Some(prior),
            };
            let start = perturbed(&mut rng, &scene.pose, 30.0, 0.5);
            let state = State { q: start.q_ecef_cam, c: start.position.0 - origin.0 };
            let lin = problem.linearize(&state).unwrap();
            // The gradient of half the cost by central differences.
            for i in 0..6 {
                let h = if i < 3 { 1e-7 } else { 1e-4 };
                let mut d = Vector6::zeros();
                d[i] = h;
                let plus = problem.linearize(&state.apply(&d)).unwrap().cost;
                let minus = problem.linearize(&state.apply(&-d)).unwrap().cost;
                let numeric = 0.25 * (plus - minus) / h;
                assert!((numeric - lin.g[i]).abs() < 1e-5 * lin.g.abs().max(), "{i}: {numeric} {}", lin.g[i]);
            }
        }
    }

    #[test]
    fn a_pose_prior_gives_the_kalman_update() {
        // Linear-Gaussian check: the refinement with a pose prior is the
        // information-weighted combination of the prior and the image-only
        // solution, with covariance (P^-1 + C^-1)^-1; and an attitude
        // prior and a pose prior cannot both be given.
        let camera = CameraModel::from_fov(640, 480, 40.0);
        let mut rng = Rng::new(21);
        for _ in 0..5 {
            let mut scene = nadir_scene(&mut rng, &camera, 10_000.0, 30, 500.0, 5.0);
            add_noise(&mut rng, &mut scene.pixels, 0.5);
            let opts = RefineOptions { pixel_sigma: 0.5, ..RefineOptions::default() };
            let start = perturbed(&mut rng, &scene.pose, 50.0, 0.3);
            let image = refine_pose(&camera, &scene.pixels, &scene.points, &start, &opts).unwrap();
            // A prior 20 m / 0.05 deg off the truth, correlated between axes.
            let a = Matrix6::from_fn(|_, _| rng.gaussian());
            let scale = Matrix6::from_diagonal(&Vector6::new(1e-3, 1e-3, 1e-3, 30.0, 30.0, 30.0));
            let p = scale * (a * a.transpose() + Matrix6::identity()) * scale / 6.0;
            let prior_pose = perturbed(&mut rng, &scene.pose, 20.0, 0.05);
            let prior = PosePrior { pose: prior_pose, covariance: p };
            let both = RefineOptions { pose_prior: Some(prior), ..opts };
            let fused = refine_pose(&camera, &scene.pixels, &scene.points, &start, &both).unwrap();
            // Everything in the tangent space at the truth.
            let (zi, zp, zf) = (
                error(&image.pose, &scene.pose),
                error(&prior_pose, &scene.pose),
                error(&fused.pose, &scene.pose),
            );
            let (pi, ci) = (p.try_inverse().unwrap(), image.covariance.try_inverse().unwrap());
            let want_cov = (pi + ci).try_inverse().unwrap();
            let want = want_cov * (pi * zp + ci * zi);
            let d = fused.covariance.try_inverse().unwrap();
            let miss = ((zf - want).transpose() * d * (zf - want))[(0, 0)];
            assert!(miss < 1e-2, "posterior mean {miss} (Mahalanobis^2) from the Kalman update");
            let rel = (fused.covariance - want_cov).norm() / want_cov.norm();
            // The Jacobians are taken at different poses (10 km range, metres apart).
            assert!(rel < 1e-2, "posterior covariance off by {rel}");
            let bad =
                RefineOptions { prior: Some(AttitudePrior::isotropic(prior_pose.q_ecef_cam, 1e-3)), ..both };
            assert!(refine_pose(&camera, &scene.pixels, &scene.points, &start, &bad).is_none());
        }
    }

    /// Mean normalised estimation error squared over trials, per dimension.
    fn nees_case(opts: &RefineOptions, noise: f64, trials: usize, seed: u64) -> f64 {
        let camera = CameraModel::from_fov(1024, 768, 45.0);
        let mut rng = Rng::new(seed);
        let mut sum = 0.0;
        for _ in 0..trials {
            let mut scene = nadir_scene(&mut rng, &camera, 8000.0, 50, 800.0, 10.0);
            add_noise(&mut rng, &mut scene.pixels, noise);
            let start = perturbed(&mut rng, &scene.pose, 50.0, 0.5);
            let r = refine_pose(&camera, &scene.pixels, &scene.points, &start, opts).unwrap();
            let e = error(&r.pose, &scene.pose);
            let inv = r.covariance.try_inverse().unwrap();
            sum += (e.transpose() * inv * e)[(0, 0)] / 6.0;
        }
        sum / trials as f64
    }

    #[test]
    fn covariance_matches_errors_with_noise() {
        let opts = RefineOptions { pixel_sigma: 0.5, ..RefineOptions::default() };
        let nees = nees_case(&opts, 0.5, 300, 5);
        let huber = RefineOptions { huber_px: Some(1.5), ..opts };
        let nees_huber = nees_case(&huber, 0.5, 100, 6);
        println!("refine 0.5 px noise: mean NEES/6 = {nees:.3} (plain), {nees_huber:.3} (Huber 1.5 px)");
        assert!((0.5..2.0).contains(&nees), "{nees}");
        assert!((0.5..2.0).contains(&nees_huber), "{nees_huber}");
        // A prior consistent with its sigma keeps the covariance honest.
        let mut rng = Rng::new(7);
        let camera = CameraModel::from_fov(1024, 768, 32.0);
        let mut sum = 0.0;
        let trials = 200;
        for _ in 0..trials {
            let mut scene = nadir_scene(&mut rng, &camera, 30_000.0, 60, 500.0, 3.0);
            add_noise(&mut rng, &mut scene.pixels, 1.0);
            let sigma = 0.01f64.to_radians();
            let noise = Vector3::new(rng.gaussian(), rng.gaussian(), rng.gaussian()) * sigma;
            let prior = UnitQuaternion::from_scaled_axis(noise) * scene.pose.q_ecef_cam;
            let opts = RefineOptions {
                prior: Some(AttitudePrior::isotropic(prior, sigma)),
                ..RefineOptions::default()
            };
            let start = perturbed(&mut rng, &scene.pose, 100.0, 1.0);
            let r = refine_pose(&camera, &scene.pixels, &scene.points, &start, &opts).unwrap();
            let e = error(&r.pose, &scene.pose);
            sum += (e.transpose() * r.covariance.try_inverse().unwrap() * e)[(0, 0)] / 6.0;
        }
        let nees_prior = sum / trials as f64;
        println!("refine 1 px noise, 32 deg 30 km, 0.01 deg prior: mean NEES/6 = {nees_prior:.3}");
        assert!((0.5..2.0).contains(&nees_prior), "{nees_prior}");
    }

    #[test]
    fn anisotropic_prior_is_weighed_by_its_covariance() {
        // A prior tight about one random axis and loose about the others: the
        // estimate's error about that axis follows the prior, and the
        // covariance stays honest (NEES about 1).
        let camera = CameraModel::from_fov(1024, 768, 32.0);
        let mut rng = Rng::new(21);
        let trials = 200;
        let (mut nees, mut tight_err2, mut loose_err2) = (0.0, 0.0, 0.0);
        for _ in 0..trials {
            let mut scene = nadir_scene(&mut rng, &camera, 30_000.0, 60, 500.0, 3.0);
            add_noise(&mut rng, &mut scene.pixels, 1.0);
            let axes = UnitQuaternion::from_scaled_axis(random_unit(&mut rng) * 2.0).to_rotation_matrix();
            let sd = Vector3::new(0.001f64.to_radians(), 0.05f64.to_radians(), 0.05f64.to_radians());
            let cov =
                axes.matrix() * Matrix3::from_diagonal(&sd.component_mul(&sd)) * axes.matrix().transpose();
            let noise =
                axes * Vector3::new(rng.gaussian() * sd.x, rng.gaussian() * sd.y, rng.gaussian() * sd.z);
            let prior = AttitudePrior {
                q_ecef_cam: UnitQuaternion::from_scaled_axis(noise) * scene.pose.q_ecef_cam,
                covariance: cov,
            };
            let w = prior.sqrt_information().unwrap();
            assert!((w.transpose() * w * cov - Matrix3::identity()).abs().max() < 1e-6);
            let opts = RefineOptions { prior: Some(prior), ..RefineOptions::default() };
            let start = perturbed(&mut rng, &scene.pose, 100.0, 1.0);
            let r = refine_pose(&camera, &scene.pixels, &scene.points, &start, &opts).unwrap();
            let e = error(&r.pose, &scene.pose);
            nees += (e.transpose() * r.covariance.try_inverse().unwrap() * e)[(0, 0)] / 6.0;
            let de = axes.inverse() * e.fixed_rows::<3>(0);
            tight_err2 += de.x * de.x;
            loose_err2 += de.y * de.y;
        }
        let nees = nees / trials as f64;
        let (tight, loose) = ((tight_err2 / trials as f64).sqrt(), (loose_err2 / trials as f64).sqrt());
        println!(
            "anisotropic prior (0.001/0.05/0.05 deg): mean NEES/6 = {nees:.3}, RMS error {:.4} deg about \
             the tight axis, {:.4} deg about a loose one",
            tight.to_degrees(),
            loose.to_degrees()
        );
        assert!((0.5..2.0).contains(&nees), "{nees}");
        assert!(tight < 0.0015f64.to_radians(), "{}", tight.to_degrees());
        assert!(loose > 3.0 * tight);
    }

    #[test]
    fn prior_covariance_must_be_positive_definite() {
        let camera = CameraModel::from_fov(1024, 768, 45.0);
        let mut rng = Rng::new(22);
        let scene = nadir_scene(&mut rng, &camera, 8000.0, 20, 800.0, 10.0);
        let q = scene.pose.q_ecef_cam;
        let bad = [
            Matrix3::zeros(),
            Matrix3::from_diagonal(&Vector3::new(1e-6, -1e-6, 1e-6)),
            Matrix3::new(1e-6, 5e-7, 0.0, 0.0, 1e-6, 0.0, 0.0, 0.0, 1e-6),
            Matrix3::identity() * f64::NAN,
        ];
        for cov in bad {
            let opts = RefineOptions {
                prior: Some(AttitudePrior { q_ecef_cam: q, covariance: cov }),
                ..RefineOptions::default()
            };
            assert!(
                refine_pose(&camera, &scene.pixels, &scene.points, &scene.pose, &opts).is_none(),
                "{cov}"
            );
        }
        let good = AttitudePrior::isotropic(q, 1e-3);
        assert!(good.mahalanobis2(&q).unwrap() < 1e-20);
        let off = UnitQuaternion::from_scaled_axis(Vector3::new(3e-3, 0.0, 0.0)) * q;
        assert!((good.mahalanobis2(&off).unwrap() - 9.0).abs() < 1e-6);
    }

    #[test]
    fn attitude_prior_fixes_narrow_fov_tilt_translation_ambiguity() {
        let camera = CameraModel::from_fov(1024, 768, 32.0);
        let mut rng = Rng::new(8);
        let sigma = 0.01f64.to_radians();
        let trials = 100;
        let (mut err_free, mut err_prior, mut sd_free, mut sd_prior) = (0.0, 0.0, 0.0, 0.0);
        for _ in 0..trials {
            let mut scene = nadir_scene(&mut rng, &camera, 30_000.0, 60, 300.0, 2.0);
            add_noise(&mut rng, &mut scene.pixels, 1.0);
            let start = perturbed(&mut rng, &scene.pose, 100.0, 1.0);
            let free = refine_pose(&camera, &scene.pixels, &scene.points, &start, &RefineOptions::default())
                .expect("refined without prior");
            let noise = Vector3::new(rng.gaussian(), rng.gaussian(), rng.gaussian()) * sigma;
            let prior = UnitQuaternion::from_scaled_axis(noise) * scene.pose.q_ecef_cam;
            let opts = RefineOptions {
                prior: Some(AttitudePrior::isotropic(prior, sigma)),
                ..RefineOptions::default()
            };
            let with = refine_pose(&camera, &scene.pixels, &scene.points, &start, &opts).expect("refined");
            err_free += free.pose.position.distance_m(&scene.pose.position).powi(2);
            err_prior += with.pose.position.distance_m(&scene.pose.position).powi(2);
            sd_free += free.position_covariance().trace();
            sd_prior += with.position_covariance().trace();
        }
        let rms = |s: f64| (s / trials as f64).sqrt();
        println!(
            "narrow FOV nadir, 30 km, 60 points, 1 px: position RMS error {:.1} m without prior \
             (predicted {:.1} m), {:.1} m with 0.01 deg prior (predicted {:.1} m)",
            rms(err_free),
            rms(sd_free),
            rms(err_prior),
            rms(sd_prior)
        );
        assert!(rms(err_prior) < 0.5 * rms(err_free));
        assert!(rms(sd_prior) < 0.5 * rms(sd_free));
    }

    #[test]
    fn huber_resists_outliers() {
        let camera = CameraModel::from_fov(1024, 768, 60.0);
        let mut rng = Rng::new(9);
        let mut scene = nadir_scene(&mut rng, &camera, 5000.0, 80, 500.0, 10.0);
        add_noise(&mut rng, &mut scene.pixels, 0.5);
        for p in scene.pixels.iter_mut().take(6) {
            p.u += 15.0;
            p.v -= 10.0;
        }
        let start = perturbed(&mut rng, &scene.pose, 20.0, 0.2);
        let plain =
            refine_pose(&camera, &scene.pixels, &scene.points, &start, &RefineOptions::default()).unwrap();
        let opts = RefineOptions { huber_px: Some(1.0), ..RefineOptions::default() };
        let robust = refine_pose(&camera, &scene.pixels, &scene.points, &start, &opts).unwrap();
        let (e_plain, e_robust) = (
            plain.pose.position.distance_m(&scene.pose.position),
            robust.pose.position.distance_m(&scene.pose.position),
        );
        println!("6/80 gross outliers: position error {e_plain:.2} m plain, {e_robust:.2} m Huber 1 px");
        assert!(e_robust < 0.5 * e_plain);
        assert!(robust.residuals_px[..6].iter().all(|&e| e > 8.0));
    }

    #[test]
    fn degenerate_input_gives_none() {
        let camera = CameraModel::from_fov(1024, 768, 60.0);
        let mut rng = Rng::new(10);
        let scene = nadir_scene(&mut rng, &camera, 5000.0, 10, 500.0, 10.0);
        let opts = RefineOptions::default();
        let pose = scene.pose;
        assert!(refine_pose(&camera, &scene.pixels[..2], &scene.points[..2], &pose, &opts).is_none());
        assert!(refine_pose(&camera, &[], &[], &pose, &opts).is_none());
        assert!(refine_pose(&camera, &scene.pixels[..4], &scene.points[..3], &pose, &opts).is_none());
        let same = vec![scene.points[0]; 10];
        assert!(refine_pose(&camera, &scene.pixels, &same, &pose, &opts).is_none());
        let same_px = vec![scene.pixels[0]; 10];
        assert!(refine_pose(&camera, &same_px, &same, &pose, &opts).is_none());
        // Camera looking away from the points.
        let away = CameraPose {
            q_ecef_cam: UnitQuaternion::from_scaled_axis(Vector3::x() * 3.0) * pose.q_ecef_cam,
            ..pose
        };
        assert!(refine_pose(&camera, &scene.pixels, &scene.points, &away, &opts).is_none());
        let bad = RefineOptions { pixel_sigma: 0.0, ..opts };
        assert!(refine_pose(&camera, &scene.pixels, &scene.points, &pose, &bad).is_none());
        let mut nan_px = scene.pixels.clone();
        nan_px[0].u = f64::NAN;
        assert!(refine_pose(&camera, &nan_px, &scene.points, &pose, &opts).is_none());
        // Three exact points do determine the pose (locally).
        let r = refine_pose(&camera, &scene.pixels[..3], &scene.points[..3], &pose, &opts);
        assert!(r.is_some());
    }

    #[test]
    fn per_match_sigmas_weigh_the_matches() {
        let camera = CameraModel::from_fov(1024, 768, 60.0);
        let mut rng = Rng::new(12);
        let mut scene = nadir_scene(&mut rng, &camera, 5000.0, 40, 500.0, 10.0);
        add_noise(&mut rng, &mut scene.pixels, 0.3);
        // One match 40 px off: with a huge sigma it counts for nothing.
        scene.pixels[7].u += 40.0;
        let opts = RefineOptions { pixel_sigma: 0.3, ..RefineOptions::default() };
        let start = scene.pose;
        let plain = refine_pose(&camera, &scene.pixels, &scene.points, &start, &opts).unwrap();
        // Equal sigmas are the uniform refinement.
        let equal = vec![0.3; scene.pixels.len()];
        let same =
            refine_pose_weighted(&camera, &scene.pixels, &scene.points, Some(&equal), &start, &opts).unwrap();
        assert!((same.pose.position.0 - plain.pose.position.0).norm() < 1e-6);
        assert!((same.covariance - plain.covariance).norm() < 1e-9 * plain.covariance.norm());
        let mut sig = equal.clone();
        sig[7] = 1e4;
        let w =
            refine_pose_weighted(&camera, &scene.pixels, &scene.points, Some(&sig), &start, &opts).unwrap();
        let keep: Vec<usize> = (0..scene.pixels.len()).filter(|&i| i != 7).collect();
        let px: Vec<Pixel> = keep.iter().map(|&i| scene.pixels[i]).collect();
        let pts: Vec<Vector3<f64>> = keep.iter().map(|&i| scene.points[i]).collect();
        let without = refine_pose(&camera, &px, &pts, &start, &opts).unwrap();
        let d = (w.pose.position.0 - without.pose.position.0).norm();
        let d_plain = (plain.pose.position.0 - without.pose.position.0).norm();
        println!("weighted vs dropped: {d:.4} m; uniform vs dropped: {d_plain:.2} m");
        assert!(d < 0.01 * d_plain && d < 0.05, "{d} {d_plain}");
        // Bad sigmas are refused.
        for bad in [
            vec![0.3; 3],
            {
                let mut b = equal.clone();
                b[0] = 0.0;
                b
            },
            {
                let mut b = equal;
                b[1] = f64::NAN;
                b
            },
        ] {
            assert!(refine_pose_weighted(&camera, &scene.pixels, &scene.points, Some(&bad), &start, &opts)
                .is_none());
        }
    }

    fn solve_case(seed: u64, share: f64, camera: &CameraModel, altitude: f64) {
        let mut rng = Rng::new(seed);
        let mut scene = nadir_scene(&mut rng, camera, altitude, 120, 500.0, 10.0);
        add_noise(&mut rng, &mut scene.pixels, 0.5);
        let truth = add_outliers(&mut rng, camera, &mut scene.pixels, share);
        let params = RansacParams { seed, ..RansacParams::default() };
        let opts = RefineOptions { pixel_sigma: 0.5, ..RefineOptions::default() };
        let s = solve(camera, &scene.pixels, &scene.points, &params, &opts).expect("solution");
        let e = error(&s.pose, &scene.pose);
        let nees = (e.transpose() * s.covariance.try_inverse().unwrap() * e)[(0, 0)];
        let wrong = (0..truth.len()).filter(|&i| truth[i] != s.inliers[i]).count();
        println!(
            "solve {:.0}% outliers: {} inliers ({wrong} misclassified), position error {:.2} m \
             (sigma {:.2} m), rotation {:.2e} rad, NEES {nees:.1}, rms {:.2} px, {} + {} iterations",
            share * 100.0,
            s.n_inliers,
            e.fixed_rows::<3>(3).norm(),
            s.position_covariance().trace().sqrt(),
            e.fixed_rows::<3>(0).norm(),
            s.rms_px,
            s.ransac_iterations,
            s.refine_iterations
        );
        assert!(wrong <= 1, "{wrong} misclassified");
        assert!(nees < 25.0, "{nees}"); // chi2(6) 99.98% quantile
        assert_eq!(s.residuals_px.len(), truth.len());
        assert!((s.rms_px - 0.5 * 2f64.sqrt()).abs() < 0.2, "{}", s.rms_px);
    }

    #[test]
    fn solve_end_to_end() {
        let mut camera = CameraModel::from_fov(1024, 768, 60.0);
        camera.distortion = Distortion { k1: -0.2, k2: 0.05, p1: 0.001, p2: -0.0005, k3: 0.0 };
        for (seed, share) in [(11, 0.3), (12, 0.5)] {
            solve_case(seed, share, &camera, 5000.0);
        }
        let narrow = CameraModel::from_fov(1024, 768, 32.0);
        for (seed, share) in [(13, 0.3), (14, 0.6)] {
            solve_case(seed, share, &narrow, 30_000.0);
        }
        assert!(solve(&narrow, &[], &[], &RansacParams::default(), &RefineOptions::default()).is_none());
    }

    /// `cargo test -p trn-vision --release -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn timing_solve_and_refine() {
        let camera = CameraModel::from_fov(1024, 768, 32.0);
        let mut rng = Rng::new(15);
        for n in [50, 100, 200] {
            let cases: Vec<_> = (0..50)
                .map(|_| {
                    let mut scene = nadir_scene(&mut rng, &camera, 30_000.0, n, 500.0, 5.0);
                    add_noise(&mut rng, &mut scene.pixels, 0.5);
                    add_outliers(&mut rng, &camera, &mut scene.pixels, 0.3);
                    scene
                })
                .collect();
            let (params, opts) = (RansacParams::default(), RefineOptions::default());
            let reps = 10;
            let start = std::time::Instant::now();
            for _ in 0..reps {
                for s in &cases {
                    let r = ransac_p3p(&camera, &s.pixels, &s.points, &params).unwrap();
                    std::hint::black_box(r);
                }
            }
            let ransac_ms = start.elapsed().as_secs_f64() * 1e3 / (reps * cases.len()) as f64;
            let start = std::time::Instant::now();
            for _ in 0..reps {
                for s in &cases {
                    let r = solve(&camera, &s.pixels, &s.points, &params, &opts).unwrap();
                    std::hint::black_box(r);
                }
            }
            let solve_ms = start.elapsed().as_secs_f64() * 1e3 / (reps * cases.len()) as f64;
            println!(
                "{n} matches, 30% outliers: ransac_p3p {ransac_ms:.3} ms, solve {solve_ms:.3} ms per call"
            );
        }
    }
}
