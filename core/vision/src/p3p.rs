//! Minimal absolute pose: Lambda Twist P3P (M. Persson, K. Nordberg, "Lambda
//! Twist: An Accurate Fast Robust Perspective Three Point (P3P) Solver",
//! ECCV 2018). "Line n" below is line n of the paper's Algorithm 1, "(n)" its
//! equation n.
//!
//! Unknowns are the depths `lambda_i` along the unit bearings `y_i`:
//! `lambda_i y_i = R x_i + t`. Rigidity gives three quadratics
//! `|lambda_i y_i - lambda_j y_j|^2 = |x_i - x_j|^2 = a_ij` (2)-(4), i.e.
//! `lambda^T M_ij lambda = a_ij`. Two homogeneous combinations `D1`, `D2`
//! (5)-(6) are combined into a degenerate conic `D0 = D1 + gamma D2` by a
//! root of the cubic `det(D0) = 0` (8)-(10); `D0` factors into two lines
//! through the origin, each line meets the remaining conics in a quadratic
//! (13)-(16). A Gauss-Newton polish of the lambdas (Sec. 3.8) makes the
//! solutions accurate to machine precision.
//!
//! As in the authors' reference code, `b_ij` here is `-2 y_i . y_j` (the
//! paper's is `y_i . y_j`) and gamma has the opposite sign (`D0 = D1 - gamma D2`).

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use trn_camera::CameraPose;
use trn_geodesy::Ecef;

/// Camera pose relative to a world frame: `x_cam = r_cam_world * x_world + t`
/// (camera frame +x right, +y down, +z forward). The camera centre in the
/// world frame is `-r_cam_world^T t`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Pose {
    pub r_cam_world: Rotation3<f64>,
    pub t: Vector3<f64>,
}

impl Pose {
    /// A world point in the camera frame.
    pub fn to_camera(&self, x_world: &Vector3<f64>) -> Vector3<f64> {
        self.r_cam_world * x_world + self.t
    }

    /// Camera centre in world coordinates.
    pub fn centre(&self) -> Vector3<f64> {
        -(self.r_cam_world.inverse() * self.t)
    }

    /// The ECEF [`CameraPose`] when the world frame is ECEF shifted to
    /// `origin` (axes parallel to ECEF): `x_world = x_ecef - origin`.
    pub fn to_camera_pose(&self, origin: &Ecef) -> CameraPose {
        let r_ecef_cam = self.r_cam_world.inverse();
        CameraPose {
            position: Ecef(origin.0 + self.centre()),
            q_ecef_cam: UnitQuaternion::from_rotation_matrix(&r_ecef_cam),
        }
    }

    /// Pose in the world frame shifted to `origin` of a [`CameraPose`] in ECEF
    /// (inverse of [`Pose::to_camera_pose`]).
    pub fn from_camera_pose(pose: &CameraPose, origin: &Ecef) -> Self {
        let r_cam_world = pose.q_ecef_cam.inverse().to_rotation_matrix();
        let centre = pose.position.0 - origin.0;
        Self { r_cam_world, t: -(r_cam_world * centre) }
    }
}

/// All poses (up to four) of a calibrated camera that sees the world points
/// `points` along the camera-frame rays `bearings` (normalized here; they
/// need not be unit). Only solutions with positive depths are returned.
/// Points should be given relative to a nearby origin (not raw ECEF) for
/// precision. Degenerate input (collinear or coincident points, parallel
/// rays, non-finite values) gives no or meaningless-but-finite solutions,
/// never a panic.
pub fn p3p(bearings: &[Vector3<f64>; 3], points: &[Vector3<f64>; 3]) -> Vec<Pose> {
    let mut poses = Vec::with_capacity(4);
    // Line 3: unit bearings.
    let [y1, y2, y3] = bearings.map(|b| b.normalize());
    let [x1, x2, x3] = *points;
    if !(y1.iter().chain(y2.iter()).chain(y3.iter()).all(|v| v.is_finite())) {
        return poses;
    }

    // Line 4: a_ij = |x_i - x_j|^2, b_ij = -2 y_i.y_j (2)-(3). The a_ij are
    // scaled to at most 1 so that tolerances are scale free.
    let (d12, d13, d23) = (x1 - x2, x1 - x3, x2 - x3);
    let scale2 = d12.norm_squared().max(d13.norm_squared()).max(d23.norm_squared());
    if !(scale2 > 0.0 && scale2.is_finite()) {
        return poses;
    }
    let a12 = d12.norm_squared() / scale2;
    let a13 = d13.norm_squared() / scale2;
    let a23 = d23.norm_squared() / scale2;
    let b12 = -2.0 * y1.dot(&y2);
    let b13 = -2.0 * y1.dot(&y3);
    let b23 = -2.0 * y2.dot(&y3);

    // Lines 5-6: a real root gamma of det(D1 - gamma D2) = a23 * cubic (8)-(10)
    // (coefficients of the reference code; det(D2) != 0 unless degenerate).
    let (c12, c13, c23) = (-0.5 * b12, -0.5 * b13, -0.5 * b23);
    let blob = c12 * c23 * c13 - 1.0;
    let s13_sq = 1.0 - c13 * c13;
    let s23_sq = 1.0 - c23 * c23;
    let s12_sq = 1.0 - c12 * c12;
    let p3 = a13 * (a23 * s13_sq - a13 * s23_sq);
    let p2 = 2.0 * blob * a23 * a13 + a13 * (2.0 * a12 + a13) * s23_sq + a23 * (a23 - a12) * s13_sq;
    let p1 = a23 * (a13 - a23) * s12_sq - a12 * a12 * s23_sq - 2.0 * a12 * (blob * a23 + a13 * s23_sq);
    let p0 = a12 * (a12 * s23_sq - a23 * s12_sq);
    if p3 == 0.0 {
        return poses;
    }
    let g = cubic_root(p2 / p3, p1 / p3, p0 / p3);
    if !g.is_finite() {
        return poses;
    }

    // Line 7: the degenerate conic D0 = D1 - gamma D2 (symmetric, rank 2).
    let d0 = Matrix3::new(
        a23 * (1.0 - g),
        0.5 * a23 * b12,
        -0.5 * a23 * b13 * g,
        0.5 * a23 * b12,
        a23 - a12 + a13 * g,
        0.5 * b23 * (a13 * g - a12),
        -0.5 * a23 * b13 * g,
        0.5 * b23 * (a13 * g - a12),
        g * (a13 - a23) - a12,
    );

    // Line 8: EIG3X3KNOWN0, eigen-decomposition with one eigenvalue known to be 0.
    let Some((e1, v1, e2, v2)) = eig_known_zero(&d0) else { return poses };

    // Lines 9-11: D0 = e1 v1 v1^T + e2 v2 v2^T is the line pair
    // (s v2 - v1)^T lambda = 0, s = +-sqrt(-e2/e1); on each line
    // lambda1 = w0 lambda2 + w1 lambda3 (13), and with tau = lambda3/lambda2
    // the constraint a13 M12 - a12 M13 is a quadratic in tau (14)-(15);
    // lambda2 then follows from the M23 equation (16).
    let v = (-e2 / e1).max(0.0).sqrt();
    let mut lambdas: [Vector3<f64>; 4] = [Vector3::zeros(); 4];
    let mut n = 0;
    for s in [v, -v] {
        let w2 = 1.0 / (s * v2[0] - v1[0]);
        let w0 = (v1[1] - s * v2[1]) * w2;
        let w1 = (v1[2] - s * v2[2]) * w2;
        let qa = 1.0 / ((a13 - a12) * w1 * w1 - a12 * b13 * w1 - a12);
        let qb = (a13 * b12 * w1 - a12 * b13 * w0 - 2.0 * w0 * w1 * (a12 - a13)) * qa;
        let qc = ((a13 - a12) * w0 * w0 + a13 * b12 * w0 + a13) * qa;
        let Some((tau1, tau2)) = quadratic_roots(qb, qc) else { continue };
        for tau in [tau1, tau2] {
            if !(tau > 0.0) {
                continue;
            }
            let d = a23 / (tau * (b23 + tau) + 1.0);
            if !(d > 0.0) {
                continue;
            }
            let l2 = d.sqrt();
            let l3 = tau * l2;
            let l1 = w0 * l2 + w1 * l3;
            if l1 > 0.0 && l1.is_finite() && l2.is_finite() && l3.is_finite() && n < 4 {
                lambdas[n] = Vector3::new(l1, l2, l3);
                n += 1;
            }
        }
    }

    // World-side frame of the triangle, for lines 12-17.
    let scale = scale2.sqrt();
    let Some(frame_world) = triangle_frame(&d12, &d13) else { return poses };
    let x_mean = (x1 + x2 + x3) / 3.0;
    for lambda in lambdas.iter_mut().take(n) {
        // Line 14: Gauss-Newton refinement of the lambdas (Sec. 3.8).
        gauss_newton_refine(lambda, [a12, a13, a23], [b12, b13, b23]);
        let l = *lambda * scale;
        if !(l.min() > 0.0 && l.iter().all(|c| c.is_finite())) {
            continue;
        }
        // Lines 15-17: R maps the world triangle's edges onto the camera-frame
        // edges (paper: R = Y X^-1), here built from orthonormal frames so that
        // R is a rotation even with slightly inexact lambdas; t from centroids.
        let (p1, p2, p3) = (y1 * l[0], y2 * l[1], y3 * l[2]);
        let Some(frame_cam) = triangle_frame(&(p1 - p2), &(p1 - p3)) else { continue };
        let r = frame_cam * frame_world.transpose();
        let t = (p1 + p2 + p3) / 3.0 - r * x_mean;
        if t.iter().all(|c| c.is_finite()) {
            poses.push(Pose { r_cam_world: Rotation3::from_matrix_unchecked(r), t });
        }
    }
    poses
}

/// Orthonormal frame (columns) with its first axis along `e1` and its third
/// along `e1 x e2`; `None` when the edges are (nearly) parallel.
fn triangle_frame(e1: &Vector3<f64>, e2: &Vector3<f64>) -> Option<Matrix3<f64>> {
    let n = e1.cross(e2);
    let (n1, nn) = (e1.norm(), n.norm());
    if !(nn > 1e-14 * n1 * e2.norm() && nn.is_finite()) {
        return None;
    }
    let f1 = e1 / n1;
    let f3 = n / nn;
    Some(Matrix3::from_columns(&[f1, f3.cross(&f1), f3]))
}

/// One real root of `x^3 + b x^2 + c x + d` by Newton's method from a start
/// that avoids the stationary points (as in the paper's reference code).
fn cubic_root(b: f64, c: f64, d: f64) -> f64 {
    let f = |x: f64| ((x + b) * x + c) * x + d;
    let df = |x: f64| (3.0 * x + 2.0 * b) * x + c;
    let mut x = if b * b >= 3.0 * c {
        // Two stationary points t1 < t2: start beyond the outer one, on a
        // quadratic approximation of the cubic there.
        let v = (b * b - 3.0 * c).sqrt();
        let t1 = (-b - v) / 3.0;
        let k = f(t1);
        if k > 0.0 {
            t1 - (-k / (3.0 * t1 + b)).sqrt()
        } else {
            let t2 = (-b + v) / 3.0;
            t2 + (-f(t2) / (3.0 * t2 + b)).sqrt()
        }
    } else {
        // Monotonic: start at the inflection point.
        let x0 = -b / 3.0;
        if df(x0).abs() < 1e-4 {
            x0 + 1.0
        } else {
            x0
        }
    };
    for _ in 0..50 {
        let fx = f(x);
        let dfx = df(x);
        if fx == 0.0 || dfx == 0.0 || !dfx.is_finite() {
            break;
        }
        let step = fx / dfx;
        x -= step;
        if step.abs() <= 1e-16 * (1.0 + x.abs()) {
            break;
        }
    }
    x
}

/// Real roots of `x^2 + b x + c` (without cancellation), `None` if complex.
fn quadratic_roots(b: f64, c: f64) -> Option<(f64, f64)> {
    let disc = b * b - 4.0 * c;
    if !(disc >= 0.0) {
        return None;
    }
    let q = -0.5 * (b + b.signum() * disc.sqrt());
    if q == 0.0 {
        return Some((0.0, 0.0));
    }
    Some((q, c / q))
}

/// Non-zero eigenvalues and unit eigenvectors `(e1, v1, e2, v2)` of a
/// symmetric 3x3 matrix with a zero eigenvalue, `|e1| >= |e2|` (EIG3X3KNOWN0:
/// the characteristic polynomial reduces to a quadratic; eigenvectors as
/// cross products of rows of `m - e I`).
fn eig_known_zero(m: &Matrix3<f64>) -> Option<(f64, Vector3<f64>, f64, Vector3<f64>)> {
    let b = -m.trace();
    let c = m[(0, 0)] * m[(1, 1)] + m[(0, 0)] * m[(2, 2)] + m[(1, 1)] * m[(2, 2)]
        - m[(0, 1)] * m[(0, 1)]
        - m[(0, 2)] * m[(0, 2)]
        - m[(1, 2)] * m[(1, 2)];
    // Both roots are real for a symmetric matrix; clamp a rounding-negative
    // discriminant.
    let disc = (b * b - 4.0 * c).max(0.0);
    let q = -0.5 * (b + b.signum() * disc.sqrt());
    let (mut e1, mut e2) = (q, if q != 0.0 { c / q } else { 0.0 });
    if e1.abs() < e2.abs() {
        std::mem::swap(&mut e1, &mut e2);
    }
    if !(e1 != 0.0 && e1.is_finite() && e2.is_finite()) {
        return None;
    }
    let v1 = null_vector(&(m - Matrix3::identity() * e1))?;
    let v2 = null_vector(&(m - Matrix3::identity() * e2))?;
    Some((e1, v1, e2, v2))
}

/// Unit null vector of a rank-2 3x3 matrix: the largest cross product of two
/// of its rows.
fn null_vector(m: &Matrix3<f64>) -> Option<Vector3<f64>> {
    let (r0, r1, r2) = (m.row(0).transpose(), m.row(1).transpose(), m.row(2).transpose());
    let candidates = [r0.cross(&r1), r0.cross(&r2), r1.cross(&r2)];
    let best = candidates.iter().max_by(|a, b| a.norm_squared().total_cmp(&b.norm_squared()))?;
    let n = best.norm();
    (n > 0.0 && n.is_finite()).then(|| best / n)
}

/// Gauss-Newton on the three rigidity equations
/// `r_ij = l_i^2 + l_j^2 + b_ij l_i l_j - a_ij` (Sec. 3.8); a step is kept
/// only if it lowers the residual.
fn gauss_newton_refine(l: &mut Vector3<f64>, a: [f64; 3], b: [f64; 3]) {
    let [a12, a13, a23] = a;
    let [b12, b13, b23] = b;
    let residual = |l: &Vector3<f64>| {
        Vector3::new(
            l[0] * l[0] + l[1] * l[1] + b12 * l[0] * l[1] - a12,
            l[0] * l[0] + l[2] * l[2] + b13 * l[0] * l[2] - a13,
            l[1] * l[1] + l[2] * l[2] + b23 * l[1] * l[2] - a23,
        )
    };
    let mut r = residual(l);
    for _ in 0..5 {
        let err = r.abs().sum();
        if err < 1e-15 {
            break;
        }
        let j = Matrix3::new(
            2.0 * l[0] + b12 * l[1],
            2.0 * l[1] + b12 * l[0],
            0.0,
            2.0 * l[0] + b13 * l[2],
            0.0,
            2.0 * l[2] + b13 * l[0],
            0.0,
            2.0 * l[1] + b23 * l[2],
            2.0 * l[2] + b23 * l[1],
        );
        let Some(step) = j.lu().solve(&r) else { break };
        let next = *l - step;
        let r_next = residual(&next);
        if !(r_next.abs().sum() < err) {
            break;
        }
        *l = next;
        r = r_next;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ransac::testutil::{nadir_scene, random_rotation, Rng};
    use trn_camera::CameraModel;

    /// Angle between two rotations, accurate near zero (unlike acos of the trace).
    fn angle_between(a: &Rotation3<f64>, b: &Rotation3<f64>) -> f64 {
        let chord = (a.matrix() - b.matrix()).norm() / (2.0 * 2f64.sqrt());
        2.0 * chord.min(1.0).asin()
    }

    /// Smallest (rotation angle, relative translation error) over solutions.
    fn best_match(solutions: &[Pose], truth: &Pose) -> (f64, f64) {
        solutions
            .iter()
            .map(|s| {
                let angle = angle_between(&s.r_cam_world, &truth.r_cam_world);
                let rel_t = (s.t - truth.t).norm() / truth.t.norm().max(1e-300);
                (angle, rel_t)
            })
            .min_by(|a, b| (a.0 + a.1).total_cmp(&(b.0 + b.1)))
            .unwrap_or((f64::INFINITY, f64::INFINITY))
    }

    fn max_reprojection_angle(s: &Pose, bearings: &[Vector3<f64>; 3], points: &[Vector3<f64>; 3]) -> f64 {
        (0..3)
            .map(|i| {
                let p = s.to_camera(&points[i]);
                p.normalize().cross(&bearings[i].normalize()).norm().asin()
                    + if p.dot(&bearings[i]) > 0.0 { 0.0 } else { 10.0 }
            })
            .fold(0.0, f64::max)
    }

    #[test]
    fn random_poses_are_recovered() {
        let mut rng = Rng::new(7);
        let trials = 1000;
        let (mut worst_angle, mut worst_t, mut worst_reproj, mut total_solutions) =
            (0.0f64, 0.0f64, 0.0f64, 0);
        for _ in 0..trials {
            let truth = Pose {
                r_cam_world: random_rotation(&mut rng, std::f64::consts::PI),
                t: Vector3::new(rng.range(-2.0, 2.0), rng.range(-2.0, 2.0), rng.range(2.0, 8.0)),
            };
            let points = [0; 3]
                .map(|_| Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0)));
            let bearings = points.map(|x| truth.to_camera(&x).normalize());
            let solutions = p3p(&bearings, &points);
            assert!(!solutions.is_empty() && solutions.len() <= 4);
            total_solutions += solutions.len();
            let (angle, rel_t) = best_match(&solutions, &truth);
            worst_angle = worst_angle.max(angle);
            worst_t = worst_t.max(rel_t);
            for s in &solutions {
                let m = s.r_cam_world.matrix();
                assert!((m.transpose() * m - Matrix3::identity()).norm() < 1e-12);
                assert!((m.determinant() - 1.0).abs() < 1e-12);
                worst_reproj = worst_reproj.max(max_reprojection_angle(s, &bearings, &points));
            }
        }
        println!(
            "p3p {trials} random poses: worst rotation error {worst_angle:.2e} rad, worst relative t error \
             {worst_t:.2e}, worst reprojection {worst_reproj:.2e} rad, {:.2} solutions/case",
            total_solutions as f64 / trials as f64
        );
        assert!(worst_angle < 1e-9 && worst_t < 1e-9, "{worst_angle:e} {worst_t:e}");
        assert!(worst_reproj < 1e-9, "{worst_reproj:e}");
    }

    #[test]
    fn cubic_and_eigen_helpers() {
        // (x - 1)(x - 2)(x + 3) = x^3 - 7x + 6
        let r = cubic_root(0.0, -7.0, 6.0);
        assert!([1.0, 2.0, -3.0].iter().any(|x| (r - x).abs() < 1e-14), "{r}");
        let m = Matrix3::new(2.0, 1.0, 0.0, 1.0, 2.0, 0.0, 0.0, 0.0, 0.0);
        let (e1, v1, e2, v2) = eig_known_zero(&m).unwrap();
        assert!((e1 - 3.0).abs() < 1e-14 && (e2 - 1.0).abs() < 1e-14);
        assert!((m * v1 - v1 * e1).norm() < 1e-14 && (m * v2 - v2 * e2).norm() < 1e-14);
    }

    #[test]
    fn degenerate_input_does_not_panic() {
        let b = [Vector3::new(0.0, 0.0, 1.0), Vector3::new(0.1, 0.0, 1.0), Vector3::new(0.2, 0.0, 1.0)];
        let collinear =
            [Vector3::new(0.0, 0.0, 5.0), Vector3::new(1.0, 0.0, 5.0), Vector3::new(2.0, 0.0, 5.0)];
        for s in p3p(&b, &collinear) {
            assert!(s.t.iter().all(|c| c.is_finite()));
        }
        let same = [Vector3::new(1.0, 2.0, 3.0); 3];
        assert!(p3p(&b, &same).is_empty());
        let nan = [Vector3::new(f64::NAN, 0.0, 1.0), b[1], b[2]];
        assert!(p3p(&nan, &collinear).is_empty());
        let zero = [Vector3::zeros(), b[1], b[2]];
        let pts = [Vector3::new(0.0, 0.0, 5.0), Vector3::new(1.0, 0.0, 5.0), Vector3::new(0.0, 1.0, 5.0)];
        for s in p3p(&zero, &pts) {
            assert!(s.t.iter().all(|c| c.is_finite()));
        }
        // Nearly collinear points and nearly identical bearings: finite output.
        let mut rng = Rng::new(3);
        for _ in 0..200 {
            let eps = 10f64.powf(rng.range(-14.0, -4.0));
            let pts = [
                Vector3::new(0.0, 0.0, 5.0),
                Vector3::new(1.0, eps, 5.0),
                Vector3::new(2.0, rng.range(-eps, eps), 5.0 + eps),
            ];
            let bearings = pts.map(|p| p.normalize());
            for s in p3p(&bearings, &pts) {
                assert!(s.t.iter().all(|c| c.is_finite()));
            }
        }
    }

    #[test]
    fn trn_geometry_narrow_fov_high_altitude() {
        // 32 deg FOV, camera 30 km above terrain with 1 km relief, points over
        // the whole image (about 17 km across).
        let camera = CameraModel::from_fov(1024, 768, 32.0);
        let mut rng = Rng::new(11);
        let (mut worst_angle, mut worst_pos) = (0.0f64, 0.0f64);
        for _ in 0..300 {
            let scene = nadir_scene(&mut rng, &camera, 30_000.0, 3, 1000.0, 5.0);
            let origin = scene.points[0];
            let points = [0, 1, 2].map(|i| scene.points[i] - origin);
            let bearings = [0, 1, 2].map(|i| camera.ray(scene.pixels[i]));
            let spread = (points[1] - points[0]).norm().max((points[2] - points[0]).norm());
            if spread < 5000.0 {
                continue; // keep the 15-km-spread cases
            }
            let truth = Pose::from_camera_pose(&scene.pose, &trn_geodesy::Ecef(origin));
            let solutions = p3p(&bearings, &points);
            let best = solutions
                .iter()
                .map(|s| {
                    let cp = s.to_camera_pose(&trn_geodesy::Ecef(origin));
                    (
                        angle_between(&s.r_cam_world, &truth.r_cam_world),
                        cp.position.distance_m(&scene.pose.position),
                    )
                })
                .min_by(|a, b| a.0.total_cmp(&b.0))
                .expect("a solution");
            worst_angle = worst_angle.max(best.0);
            worst_pos = worst_pos.max(best.1);
        }
        println!("p3p TRN geometry: worst rotation error {worst_angle:.2e} rad, worst position error {worst_pos:.2e} m");
        assert!(worst_angle < 1e-6, "{worst_angle:e}");
        assert!(worst_pos < 1e-2, "{worst_pos:e}");
    }
}
