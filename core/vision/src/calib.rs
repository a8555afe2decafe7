//! What one frame's 2D-3D matches say about the camera's intrinsics, with
//! the pose left free: the information and gradient of a small correction
//! `[focal, principal point, k1]` after the pose is eliminated (Schur
//! complement), so a filter can accumulate it over frames (self-calibration).
//!
//! Model: the true camera is the given one with `fx, fy` scaled by
//! `1 + focal_rel`, the principal point moved by `(du, dv)` pixels and the
//! radial coefficient `k1` changed by `dk1`, i.e.
//! `u = fx (1 + focal_rel) x'' + cx + du` with `x''` distorted by `k1 + dk1`
//! (`du/ddk1 = fx x' r^2`, `x'` the undistorted normalized coordinate; see
//! `trn_camera`). For a pose and
//! intrinsics solved together on one frame the normal equations are
//!
//! ```text
//! [ H_pp  H_pc ] [dpose]     [g_p]
//! [ H_cp  H_cc ] [dcal ] = - [g_c]
//! ```
//!
//! (`H = J^T W J / sigma^2`, `g = J^T W r / sigma^2`, pose perturbation as in
//! [`crate::pnp`]); eliminating the pose gives the intrinsics' information
//! `H_cc - H_cp H_pp^-1 H_pc` and gradient `g_c - H_cp H_pp^-1 g_p`, and the
//! pose follows a change `dcal` of the intrinsics by `-H_pp^-1 H_pc dcal`
//! (Triggs et al., *Bundle Adjustment: A Modern Synthesis*, 2000, sec. 6.1).
//!
//! What makes the focal length observable in one frame is relief: landmarks
//! whose ranges differ by a good share of the range (a nadir view of flat
//! ground cannot tell a longer focal length from a lower camera). Tilt over
//! flat ground helps little unless the field of view is wide (the tests:
//! per pixel of noise and 200 matches at 20 km, a flat nadir view gives a
//! focal sigma of ~570%, 2 km of relief 0.6%, a 30-degree tilt of a 30-degree
//! camera ~380%, of a 90-degree camera ~20%). So the estimate leans on the
//! landmarks' heights: relief the database has wrong biases it. The
//! principal point is observable only where a shift of it differs from a
//! rotation of the camera; `k1` wherever matches reach the field's edge
//! (its pixel motion grows with the cube of the distance from the centre,
//! which no pose change mimics).

use nalgebra::{Matrix4, SMatrix, Vector3, Vector4};
pub use trn_camera::IntrinsicsCorrection;
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::Ecef;

use crate::pnp::{huber, invert_normalized, linearize_point};

/// One frame's evidence on a correction of the camera's intrinsics, pose
/// eliminated; vectors and matrices in the order of
/// [`IntrinsicsCorrection::to_vector`].
#[derive(Clone, Debug, PartialEq)]
pub struct FrameCalibration {
    /// Information (inverse covariance) of the correction from this frame.
    pub information: Matrix4<f64>,
    /// Gradient of half the frame's cost with respect to the correction at
    /// zero, with the pose following: `-information^-1 * gradient` is the
    /// frame's own Gauss-Newton estimate of the correction.
    pub gradient: Vector4<f64>,
    /// How the best pose `[dtheta (rad, ECEF); dp (m, ECEF)]` moves per unit
    /// of correction: `-H_pp^-1 H_pc`.
    pub pose_sensitivity: SMatrix<f64, 6, 4>,
}

/// [`FrameCalibration`] of `camera` at `pose` from matched pixels and their
/// landmarks (ECEF), each pixel with standard deviation `pixel_sigma` and an
/// optional Huber threshold (px), as [`crate::pnp::refine_pose`] weighs them,
/// and each landmark's height uncertain by `height_sigma_m` (the database's
/// DEM): a match's pixel covariance is `pixel_sigma^2 I + height_sigma^2 a
/// a^T`, `a` the pixel's motion per metre of its landmark's height. Relief
/// is what tells the focal length from the range, so heights the database
/// has wrong would otherwise pass for a focal error.
/// `None` when the inputs disagree in length or are fewer than 4, a point is
/// behind the camera, or the pose is not determined by the matches.
pub fn frame_calibration(
    camera: &CameraModel,
    pixels: &[Pixel],
    points_ecef: &[Vector3<f64>],
    pose: &CameraPose,
    pixel_sigma: f64,
    height_sigma_m: f64,
    huber_px: Option<f64>,
) -> Option<FrameCalibration> {
    if pixels.len() < 4
        || pixels.len() != points_ecef.len()
        || !(pixel_sigma > 0.0)
        || !(height_sigma_m >= 0.0)
    {
        return None;
    }
    let r_cam_ecef = pose.q_ecef_cam.inverse().to_rotation_matrix().into_inner();
    let sigma2 = pixel_sigma * pixel_sigma;
    let mut h = SMatrix::<f64, 10, 10>::zeros();
    let mut g = SMatrix::<f64, 10, 1>::zeros();
    for (x, obs) in points_ecef.iter().zip(pixels) {
        let pt = linearize_point(camera, &r_cam_ecef, &(Ecef(*x).0 - pose.position.0), obs)?;
        let mut j = SMatrix::<f64, 2, 10>::zeros();
        j.fixed_view_mut::<2, 6>(0, 0).copy_from(&pt.j_pose);
        // u = fx (1 + f) x'' + cx + du, v = fy (1 + f) y'' + cy + dv.
        j[(0, 6)] = camera.fx * pt.distorted.x;
        j[(1, 6)] = camera.fy * pt.distorted.y;
        j[(0, 7)] = 1.0;
        j[(1, 8)] = 1.0;
        let n = pt.normalized;
        let r2 = n.x * n.x + n.y * n.y;
        j[(0, 9)] = camera.fx * n.x * r2;
        j[(1, 9)] = camera.fy * n.y * r2;
        // The pixel moves by -J_position * up per metre of the landmark's
        // height (up: the geocentric direction, close enough for a sigma).
        let up = x.normalize();
        let a = -pt.j_pose.fixed_view::<2, 3>(0, 3) * up;
        let cov = nalgebra::Matrix2::identity() * sigma2 + a * a.transpose() * height_sigma_m.powi(2);
        let info = cov.try_inverse()?;
        // Huber on the whitened error, in pixel-sigma units of the threshold.
        let e2 = pt.residual_px.dot(&(info * pt.residual_px)) * sigma2;
        let (_, w) = huber(e2, huber_px);
        h += j.transpose() * info * j * w;
        g += j.transpose() * info * pt.residual_px * w;
    }
    let h_pp = h.fixed_view::<6, 6>(0, 0).into_owned();
    let h_pc = h.fixed_view::<6, 4>(0, 6).into_owned();
    let h_cc = h.fixed_view::<4, 4>(6, 6).into_owned();
    let pose_sensitivity = -invert_normalized(&h_pp)? * h_pc;
    let information = h_cc + h_pc.transpose() * pose_sensitivity;
    let g_p = g.fixed_rows::<6>(0).into_owned();
    let gradient = g.fixed_rows::<4>(6).into_owned() + pose_sensitivity.transpose() * g_p;
    Some(FrameCalibration {
        information: (information + information.transpose()) * 0.5,
        gradient,
        pose_sensitivity,
    })
}

/// `pose` moved by `delta = [dtheta (rad, ECEF); dp (m, ECEF)]` (the
/// perturbation of [`crate::pnp`]).
pub fn perturb_pose(pose: &CameraPose, delta: &nalgebra::Vector6<f64>) -> CameraPose {
    let dtheta: Vector3<f64> = delta.fixed_rows::<3>(0).into_owned();
    CameraPose {
        position: Ecef(pose.position.0 + delta.fixed_rows::<3>(3)),
        q_ecef_cam: nalgebra::UnitQuaternion::from_scaled_axis(dtheta) * pose.q_ecef_cam,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pnp::{refine_pose, RefineOptions};
    use crate::ransac::testutil::*;

    fn truth_error() -> IntrinsicsCorrection {
        IntrinsicsCorrection { focal_rel: 0.003, principal_du_px: 1.5, principal_dv_px: -1.0, k1: 0.002 }
    }

    /// Gauss-Newton on pose and intrinsics together, alternating: the pose
    /// refined with the current intrinsics, then the intrinsics stepped by
    /// the frame's own estimate (the pose following it).
    fn alternate(
        nominal: &CameraModel,
        scene: &Scene,
        rounds: usize,
    ) -> (IntrinsicsCorrection, CameraPose, FrameCalibration) {
        let mut corr = Vector4::zeros();
        let mut pose = scene.pose;
        let opts = RefineOptions::default();
        for _ in 0..rounds {
            let cam = IntrinsicsCorrection::from_vector(&corr).apply(nominal);
            pose = refine_pose(&cam, &scene.pixels, &scene.points, &pose, &opts).expect("refined").pose;
            let fc = frame_calibration(&cam, &scene.pixels, &scene.points, &pose, 1.0, 0.0, None).unwrap();
            let step = -fc.information.cholesky().unwrap().solve(&fc.gradient);
            pose = perturb_pose(&pose, &(fc.pose_sensitivity * step));
            // The step is relative to `cam`: compose the focal scales.
            corr = Vector4::new(
                (1.0 + corr.x) * (1.0 + step.x) - 1.0,
                corr.y + step.y,
                corr.z + step.z,
                corr.w + step.w,
            );
        }
        let cam = IntrinsicsCorrection::from_vector(&corr).apply(nominal);
        let fc = frame_calibration(&cam, &scene.pixels, &scene.points, &pose, 1.0, 0.0, None).unwrap();
        (IntrinsicsCorrection::from_vector(&corr), pose, fc)
    }

    #[test]
    fn oblique_view_recovers_focal_principal_point_and_k1() {
        let nominal = CameraModel::from_fov(1024, 768, 60.0);
        let truth = truth_error().apply(&nominal);
        let mut rng = Rng::new(7);
        let scene = tilted_scene(&mut rng, &truth, 5000.0, 200, 800.0, 45.0);
        // Trusting the nominal camera costs tens of metres.
        let naive =
            refine_pose(&nominal, &scene.pixels, &scene.points, &scene.pose, &RefineOptions::default())
                .unwrap();
        let naive_m = naive.pose.position.distance_m(&scene.pose.position);
        let (est, pose, _) = alternate(&nominal, &scene, 6);
        let pos_m = pose.position.distance_m(&scene.pose.position);
        println!("oblique: {est:?}, position {pos_m:.2e} m (nominal camera: {naive_m:.1} m)");
        assert!(naive_m > 5.0, "{naive_m}");
        assert!((est.focal_rel - 0.003).abs() < 1e-7, "{est:?}");
        assert!(
            (est.principal_du_px - 1.5).abs() < 1e-4 && (est.principal_dv_px + 1.0).abs() < 1e-4,
            "{est:?}"
        );
        assert!((est.k1 - 0.002).abs() < 1e-7, "{est:?}");
        assert!(pos_m < 1e-3, "{pos_m}");
    }

    #[test]
    fn nadir_over_flat_ground_cannot_tell_focal_from_height() {
        let nominal = CameraModel::from_fov(1024, 768, 30.0);
        let mut rng = Rng::new(3);
        let info = |relief_m: f64, tilt_deg: f64, rng: &mut Rng| {
            let scene = tilted_scene(rng, &nominal, 20_000.0, 200, relief_m, tilt_deg);
            let fc = frame_calibration(&nominal, &scene.pixels, &scene.points, &scene.pose, 1.0, 0.0, None)
                .unwrap();
            // Focal-rel sigma from this frame (1 px pixels), k1 known.
            fc.information.fixed_view::<3, 3>(0, 0).into_owned().try_inverse().unwrap()[(0, 0)].sqrt()
        };
        let flat = info(0.0, 0.0, &mut rng);
        let relief = info(2000.0, 0.0, &mut rng);
        let oblique = info(0.0, 30.0, &mut rng);
        let wide = {
            let camera = CameraModel::from_fov(1024, 768, 90.0);
            let scene = tilted_scene(&mut rng, &camera, 20_000.0, 200, 0.0, 30.0);
            let fc = frame_calibration(&camera, &scene.pixels, &scene.points, &scene.pose, 1.0, 0.0, None)
                .unwrap();
            fc.information.fixed_view::<3, 3>(0, 0).into_owned().try_inverse().unwrap()[(0, 0)].sqrt()
        };
        println!(
            "focal sigma per 1 px: flat nadir {flat:.2e}, 2 km relief {relief:.2e}, 30 deg oblique {oblique:.2e}, \
             90 deg FOV oblique {wide:.2e}"
        );
        // Only the ellipsoid's curvature separates them over flat ground.
        assert!(flat > 0.05, "{flat}");
        // Relief is what tells them apart; tilt over flat ground helps little.
        assert!(relief < 0.01 * flat, "{relief}");
        assert!(wide < 0.1 * flat && oblique > 0.3 * flat, "{wide} {oblique}");
    }

    #[test]
    fn information_predicts_the_scatter_of_single_frame_estimates() {
        let nominal = CameraModel::from_fov(1024, 768, 60.0);
        let truth = truth_error().apply(&nominal);
        let mut rng = Rng::new(11);
        let clean = tilted_scene(&mut rng, &truth, 5000.0, 100, 500.0, 40.0);
        let sigma_px = 0.5;
        let mut estimates = Vec::new();
        let mut predicted = 0.0;
        for _ in 0..200 {
            let mut scene =
                Scene { pose: clean.pose, pixels: clean.pixels.clone(), points: clean.points.clone() };
            add_noise(&mut rng, &mut scene.pixels, sigma_px);
            let (est, _, fc) = alternate(&nominal, &scene, 4);
            estimates.push(est.focal_rel);
            predicted = fc.information.try_inverse().unwrap()[(0, 0)].sqrt() * sigma_px;
        }
        let n = estimates.len() as f64;
        let mean = estimates.iter().sum::<f64>() / n;
        let std = (estimates.iter().map(|e| (e - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
        println!("focal_rel: mean {mean:.5} (truth 0.003), std {std:.2e}, predicted {predicted:.2e}");
        assert!((mean - 0.003).abs() < 3.0 * std / n.sqrt() + 1e-6, "{mean}");
        assert!((std / predicted - 1.0).abs() < 0.2, "{std} {predicted}");
    }
}
