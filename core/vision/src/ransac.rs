//! RANSAC over 2D-3D matches with the P3P solver: a robust first pose and the
//! inlier set, to be polished by [`crate::pnp::refine_pose`].

use nalgebra::Vector3;
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::Ecef;

use crate::p3p::{p3p, Pose};

/// RANSAC settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RansacParams {
    /// A match is an inlier when its reprojection error is below this (pixels).
    pub threshold_px: f64,
    /// Wanted probability of drawing at least one all-inlier sample; sets the
    /// adaptive iteration count `log(1 - confidence) / log(1 - w^3)` (w:
    /// inlier ratio of the best pose so far).
    pub confidence: f64,
    /// Upper bound on the number of samples drawn (degenerate ones included).
    pub max_iterations: usize,
    /// Fewer inliers than this (and never fewer than 4) is a failure.
    pub min_inliers: usize,
    /// Seed of the sample generator: equal inputs give equal results.
    pub seed: u64,
}

impl Default for RansacParams {
    fn default() -> Self {
        Self { threshold_px: 2.0, confidence: 0.999, max_iterations: 1000, min_inliers: 6, seed: 0x5eed }
    }
}

/// RANSAC's best pose and its inliers.
#[derive(Clone, Debug, PartialEq)]
pub struct RansacResult {
    pub pose: CameraPose,
    /// One flag per match: reprojection error below `threshold_px`.
    pub inliers: Vec<bool>,
    pub n_inliers: usize,
    /// Samples drawn (including skipped degenerate ones).
    pub iterations: usize,
}

/// Robust pose from 2D-3D matches: `pixels[i]` is where the ECEF point
/// `points_ecef[i]` is seen. Draws 3 distinct matches at a time (seeded, so
/// deterministic), turns their pixels into rays with [`CameraModel::ray`]
/// (undistortion included), solves P3P, and scores every solution by the
/// reprojection error in pixels of all matches through the full camera model
/// (as [`CameraPose::project`]; points behind the camera are outliers). The
/// best pose has the most inliers, ties broken by the lower sum of inlier
/// errors. Samples whose image points or world points are nearly collinear
/// are skipped. `None` with fewer than 3 matches, mismatched lengths, or
/// fewer than `max(min_inliers, 4)` inliers.
pub fn ransac_p3p(
    camera: &CameraModel,
    pixels: &[Pixel],
    points_ecef: &[Vector3<f64>],
    params: &RansacParams,
) -> Option<RansacResult> {
    let n = pixels.len();
    if n < 3 || points_ecef.len() != n {
        return None;
    }
    // Local origin at the centroid keeps ~1e-9 m precision in the solver.
    let origin = Ecef(points_ecef.iter().sum::<Vector3<f64>>() / n as f64);
    let local: Vec<Vector3<f64>> = points_ecef.iter().map(|p| p - origin.0).collect();
    let bearings: Vec<Vector3<f64>> = pixels.iter().map(|&px| camera.ray(px)).collect();
    let threshold2 = params.threshold_px * params.threshold_px;

    let mut rng = Rng::new(params.seed);
    let mut best: Option<(usize, f64, Pose)> = None;
    let mut needed = params.max_iterations;
    let mut iterations = 0;
    while iterations < needed {
        iterations += 1;
        let [i, j, k] = rng.sample3(n);
        let b = [bearings[i], bearings[j], bearings[k]];
        let x = [local[i], local[j], local[k]];
        if nearly_collinear(&b[0], &b[1], &b[2]) || nearly_collinear(&x[0], &x[1], &x[2]) {
            continue;
        }
        for pose in p3p(&b, &x) {
            let (count, error) = score(camera, &pose, pixels, &local, threshold2);
            let better = match &best {
                None => count > 0,
                Some((c, e, _)) => count > *c || (count == *c && error < *e),
            };
            if better {
                best = Some((count, error, pose));
                needed = needed.min(adaptive_iterations(count, n, params.confidence));
            }
        }
    }

    let (n_inliers, _, pose) = best?;
    if n_inliers < params.min_inliers.max(4) {
        return None;
    }
    let inliers: Vec<bool> = local
        .iter()
        .zip(pixels)
        .map(|(x, px)| reprojection_error2(camera, &pose, x, px) < threshold2)
        .collect();
    Some(RansacResult { pose: pose.to_camera_pose(&origin), inliers, n_inliers, iterations })
}

/// Squared reprojection error (pixels^2) of a local point; infinite behind
/// the camera.
fn reprojection_error2(camera: &CameraModel, pose: &Pose, x: &Vector3<f64>, px: &Pixel) -> f64 {
    match camera.project(&pose.to_camera(x)) {
        Some(p) => {
            let (du, dv) = (p.u - px.u, p.v - px.v);
            let e2 = du * du + dv * dv;
            if e2.is_nan() {
                f64::INFINITY
            } else {
                e2
            }
        }
        None => f64::INFINITY,
    }
}

/// Inlier count and sum of inlier errors (pixels).
fn score(
    camera: &CameraModel,
    pose: &Pose,
    pixels: &[Pixel],
    local: &[Vector3<f64>],
    threshold2: f64,
) -> (usize, f64) {
    let mut count = 0;
    let mut error = 0.0;
    for (x, px) in local.iter().zip(pixels) {
        let e2 = reprojection_error2(camera, pose, x, px);
        if e2 < threshold2 {
            count += 1;
            error += e2.sqrt();
        }
    }
    (count, error)
}

/// Samples needed to draw one all-inlier triple with probability `confidence`.
fn adaptive_iterations(inliers: usize, n: usize, confidence: f64) -> usize {
    let w3 = (inliers as f64 / n as f64).powi(3);
    if w3 >= 1.0 {
        return 1;
    }
    let k = (1.0 - confidence).ln() / (1.0 - w3).ln();
    if k.is_finite() && k >= 0.0 {
        k.ceil().min(usize::MAX as f64) as usize
    } else {
        usize::MAX
    }
}

/// True when three points (or three rays from the origin) lie nearly on a
/// line (a plane through the origin): the triangle's height over its longest
/// side is below 1e-3.
fn nearly_collinear(a: &Vector3<f64>, b: &Vector3<f64>, c: &Vector3<f64>) -> bool {
    let (ab, ac, bc) = (b - a, c - a, c - b);
    let longest2 = ab.norm_squared().max(ac.norm_squared()).max(bc.norm_squared());
    // twice the area = |ab x ac| = longest side * height
    let area2 = ab.cross(&ac).norm();
    !(area2 > 1e-3 * longest2)
}

/// SplitMix64 (Steele, Lea, Flood 2014): a small, fast, seeded generator.
#[derive(Clone, Debug)]
pub(crate) struct Rng(u64);

impl Rng {
    pub(crate) fn new(seed: u64) -> Self {
        Self(seed)
    }

    pub(crate) fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in `0..n` (Lemire's multiply-shift; bias below 2^-40 here).
    pub(crate) fn index(&mut self, n: usize) -> usize {
        ((self.next_u64() as u128 * n as u128) >> 64) as usize
    }

    /// Three distinct indices in `0..n`, `n >= 3`.
    pub(crate) fn sample3(&mut self, n: usize) -> [usize; 3] {
        let i = self.index(n);
        let mut j = self.index(n - 1);
        if j >= i {
            j += 1;
        }
        let (lo, hi) = (i.min(j), i.max(j));
        let mut k = self.index(n - 2);
        if k >= lo {
            k += 1;
        }
        if k >= hi {
            k += 1;
        }
        [i, j, k]
    }

    /// Uniform in `[0, 1)`.
    #[cfg(test)]
    pub(crate) fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    #[cfg(test)]
    pub(crate) fn range(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.uniform()
    }

    /// Standard normal (Box-Muller).
    #[cfg(test)]
    pub(crate) fn gaussian(&mut self) -> f64 {
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    }
}

/// Synthetic scenes shared by the crate's tests.
#[cfg(test)]
pub(crate) mod testutil {
    pub(crate) use super::Rng;
    use nalgebra::{Rotation3, Unit, UnitQuaternion, Vector3};
    use trn_camera::{CameraModel, CameraPose, Pixel};
    use trn_geodesy::{intersect_ellipsoid, Geodetic, LocalFrame};

    pub(crate) fn random_unit(rng: &mut Rng) -> Vector3<f64> {
        loop {
            let v = Vector3::new(rng.gaussian(), rng.gaussian(), rng.gaussian());
            if v.norm() > 1e-6 {
                return v.normalize();
            }
        }
    }

    /// A rotation about a random axis by an angle uniform in `[0, max_angle]`.
    pub(crate) fn random_rotation(rng: &mut Rng, max_angle: f64) -> Rotation3<f64> {
        Rotation3::from_axis_angle(&Unit::new_normalize(random_unit(rng)), rng.range(0.0, max_angle))
    }

    pub(crate) struct Scene {
        pub pose: CameraPose,
        pub pixels: Vec<Pixel>,
        pub points: Vec<Vector3<f64>>,
    }

    /// A camera `altitude_m` above the ellipsoid somewhere over the US,
    /// looking down (north up) and tilted by up to `tilt_deg`; `n` ground
    /// points at heights in `[0, relief_m]` seen at random pixels of the
    /// image; exact (noise-free) pixels.
    pub(crate) fn nadir_scene(
        rng: &mut Rng,
        camera: &CameraModel,
        altitude_m: f64,
        n: usize,
        relief_m: f64,
        tilt_deg: f64,
    ) -> Scene {
        let (mut pose, _) = nadir_pose(rng, altitude_m);
        let tilt = random_rotation(rng, tilt_deg.to_radians());
        pose.q_ecef_cam = UnitQuaternion::from_rotation_matrix(&tilt) * pose.q_ecef_cam;
        scene_from(rng, camera, pose, n, relief_m)
    }

    /// As [`nadir_scene`], tilted by exactly `tilt_deg` about the local east
    /// axis (looking north of nadir).
    pub(crate) fn tilted_scene(
        rng: &mut Rng,
        camera: &CameraModel,
        altitude_m: f64,
        n: usize,
        relief_m: f64,
        tilt_deg: f64,
    ) -> Scene {
        let (mut pose, frame) = nadir_pose(rng, altitude_m);
        let east = frame.vector_to_ecef(&Vector3::x());
        let tilt = UnitQuaternion::from_axis_angle(&Unit::new_normalize(east), tilt_deg.to_radians());
        pose.q_ecef_cam = tilt * pose.q_ecef_cam;
        scene_from(rng, camera, pose, n, relief_m)
    }

    /// A camera `altitude_m` above a random place over the US looking
    /// straight down, north up, and the local frame on the ground below it.
    fn nadir_pose(rng: &mut Rng, altitude_m: f64) -> (CameraPose, LocalFrame) {
        let (lat, lon) = (rng.range(30.0, 48.0), rng.range(-120.0, -80.0));
        let position = Geodetic::new(lat, lon, altitude_m).to_ecef();
        let ground = Geodetic::new(lat, lon, 0.0);
        let frame = LocalFrame::at(ground);
        let north = frame.vector_to_ecef(&Vector3::y());
        (CameraPose::look_at(position, ground.to_ecef(), north), frame)
    }

    fn scene_from(rng: &mut Rng, camera: &CameraModel, pose: CameraPose, n: usize, relief_m: f64) -> Scene {
        let (mut pixels, mut points) = (Vec::with_capacity(n), Vec::with_capacity(n));
        while points.len() < n {
            let px = Pixel::new(
                rng.range(-0.5, camera.width as f64 - 0.5),
                rng.range(-0.5, camera.height as f64 - 0.5),
            );
            let ray = pose.ray(camera, px);
            let Some(p) = intersect_ellipsoid(&ray, rng.range(0.0, relief_m)) else { continue };
            let Some(exact) = pose.project(camera, &p) else { continue };
            pixels.push(exact);
            points.push(p.0);
        }
        Scene { pose, pixels, points }
    }

    pub(crate) fn add_noise(rng: &mut Rng, pixels: &mut [Pixel], sigma_px: f64) {
        for p in pixels {
            p.u += sigma_px * rng.gaussian();
            p.v += sigma_px * rng.gaussian();
        }
    }

    /// Replaces a share of the pixels by random ones (far from the truth);
    /// returns the true inlier flags.
    pub(crate) fn add_outliers(
        rng: &mut Rng,
        camera: &CameraModel,
        pixels: &mut [Pixel],
        share: f64,
    ) -> Vec<bool> {
        let n = pixels.len();
        let n_out = (share * n as f64).round() as usize;
        let mut inlier = vec![true; n];
        let mut k = 0;
        while k < n_out {
            let i = rng.index(n);
            if !inlier[i] {
                continue;
            }
            let px = loop {
                let p = Pixel::new(
                    rng.range(-0.5, camera.width as f64 - 0.5),
                    rng.range(-0.5, camera.height as f64 - 0.5),
                );
                if p.distance_px(&pixels[i]) > 20.0 {
                    break p;
                }
            };
            pixels[i] = px;
            inlier[i] = false;
            k += 1;
        }
        inlier
    }

    /// Angle between two attitudes (accurate near zero).
    pub(crate) fn rotation_error(a: &UnitQuaternion<f64>, b: &UnitQuaternion<f64>) -> f64 {
        crate::pnp::rotation_vector(&(a * b.inverse())).norm()
    }
}

#[cfg(test)]
mod tests {
    use super::testutil::*;
    use super::*;
    use trn_camera::Distortion;

    fn run_case(seed: u64, outlier_share: f64, noise_px: f64, camera: &CameraModel, altitude: f64) {
        let mut rng = Rng::new(seed);
        let mut scene = nadir_scene(&mut rng, camera, altitude, 100, 500.0, 10.0);
        add_noise(&mut rng, &mut scene.pixels, noise_px);
        let truth_inliers = add_outliers(&mut rng, camera, &mut scene.pixels, outlier_share);
        let params = RansacParams { seed, ..RansacParams::default() };
        let r = ransac_p3p(camera, &scene.pixels, &scene.points, &params).expect("a pose");
        let pos_err = r.pose.position.distance_m(&scene.pose.position);
        let rot_err = rotation_error(&r.pose.q_ecef_cam, &scene.pose.q_ecef_cam);
        let false_inliers = (0..100).filter(|&i| r.inliers[i] && !truth_inliers[i]).count();
        let missed = (0..100).filter(|&i| !r.inliers[i] && truth_inliers[i]).count();
        let n_true = truth_inliers.iter().filter(|&&b| b).count();
        println!(
            "ransac outliers {:.0}% noise {noise_px} px: {} iterations, {} inliers ({n_true} true, \
             {false_inliers} false, {missed} missed), position error {pos_err:.2} m, rotation error {:.2e} rad",
            outlier_share * 100.0,
            r.iterations,
            r.n_inliers,
            rot_err
        );
        assert_eq!(r.n_inliers, r.inliers.iter().filter(|&&b| b).count());
        assert_eq!(false_inliers, 0);
        if noise_px == 0.0 {
            assert_eq!(missed, 0);
            assert!(pos_err < 1e-4 && rot_err < 1e-9, "{pos_err} {rot_err}");
        } else {
            // A minimal-sample pose is rough, most in narrow-FOV tilt/translation
            // (solve() refines and re-classifies).
            assert!(missed * 100 <= 15 * n_true, "missed {missed} of {n_true}");
            assert!(pos_err < 0.02 * altitude && rot_err < 2e-2, "{pos_err} {rot_err}");
        }
    }

    #[test]
    fn recovers_pose_and_inliers_noise_free() {
        let camera = CameraModel::from_fov(1024, 768, 60.0);
        for (seed, share) in [(1, 0.3), (2, 0.45), (3, 0.6)] {
            run_case(seed, share, 0.0, &camera, 5000.0);
        }
    }

    #[test]
    fn recovers_pose_and_inliers_with_noise_and_distortion() {
        let mut camera = CameraModel::from_fov(1024, 768, 60.0);
        camera.distortion = Distortion { k1: -0.2, k2: 0.05, p1: 0.001, p2: -0.0005, k3: 0.0 };
        camera.validate().unwrap();
        for (seed, share) in [(4, 0.3), (5, 0.45), (6, 0.6)] {
            run_case(seed, share, 0.5, &camera, 5000.0);
        }
        let narrow = CameraModel::from_fov(1024, 768, 32.0);
        for (seed, share) in [(7, 0.3), (8, 0.6)] {
            run_case(seed, share, 0.5, &narrow, 30_000.0);
        }
    }

    #[test]
    fn too_few_matches_or_bad_input() {
        let camera = CameraModel::from_fov(1024, 768, 60.0);
        let mut rng = Rng::new(9);
        let scene = nadir_scene(&mut rng, &camera, 5000.0, 10, 500.0, 5.0);
        let params = RansacParams::default();
        assert!(ransac_p3p(&camera, &scene.pixels[..2], &scene.points[..2], &params).is_none());
        assert!(ransac_p3p(&camera, &[], &[], &params).is_none());
        assert!(ransac_p3p(&camera, &scene.pixels[..5], &scene.points[..4], &params).is_none());
        // Three exact matches are fewer than min_inliers.
        assert!(ransac_p3p(&camera, &scene.pixels[..3], &scene.points[..3], &params).is_none());
        // All points identical: no pose, no panic.
        let same = vec![scene.points[0]; 10];
        assert!(ransac_p3p(&camera, &scene.pixels, &same, &params).is_none());
        // Exact matches with a lenient min_inliers.
        let lenient = RansacParams { min_inliers: 4, ..params };
        let r = ransac_p3p(&camera, &scene.pixels[..5], &scene.points[..5], &lenient).unwrap();
        assert_eq!(r.n_inliers, 5);
    }

    #[test]
    fn deterministic_for_a_seed() {
        let camera = CameraModel::from_fov(1024, 768, 60.0);
        let mut rng = Rng::new(10);
        let mut scene = nadir_scene(&mut rng, &camera, 5000.0, 60, 500.0, 5.0);
        add_noise(&mut rng, &mut scene.pixels, 0.5);
        add_outliers(&mut rng, &camera, &mut scene.pixels, 0.4);
        let params = RansacParams::default();
        let a = ransac_p3p(&camera, &scene.pixels, &scene.points, &params).unwrap();
        let b = ransac_p3p(&camera, &scene.pixels, &scene.points, &params).unwrap();
        assert_eq!(a, b);
    }

    #[test]
    fn sampler_gives_distinct_indices() {
        let mut rng = Rng::new(1);
        let mut counts = [0usize; 5];
        for _ in 0..30_000 {
            let [i, j, k] = rng.sample3(5);
            assert!(i != j && j != k && i != k && i < 5 && j < 5 && k < 5);
            for x in [i, j, k] {
                counts[x] += 1;
            }
        }
        // Each index in 3/5 of the samples.
        assert!(counts.iter().all(|&c| (c as f64 - 18_000.0).abs() < 600.0), "{counts:?}");
    }

    /// `cargo test -p trn-vision --release -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn timing_ransac_100_matches_30_percent_outliers() {
        let camera = CameraModel::from_fov(1024, 768, 32.0);
        let mut rng = Rng::new(12);
        let cases: Vec<_> = (0..50)
            .map(|_| {
                let mut scene = nadir_scene(&mut rng, &camera, 30_000.0, 100, 500.0, 5.0);
                add_noise(&mut rng, &mut scene.pixels, 0.5);
                add_outliers(&mut rng, &camera, &mut scene.pixels, 0.3);
                scene
            })
            .collect();
        let params = RansacParams::default();
        let reps = 20;
        let start = std::time::Instant::now();
        let mut iterations = 0;
        for _ in 0..reps {
            for s in &cases {
                let r = ransac_p3p(&camera, &s.pixels, &s.points, &params).unwrap();
                iterations += r.iterations;
            }
        }
        let calls = (reps * cases.len()) as f64;
        let per_call = start.elapsed().as_secs_f64() / calls;
        println!(
            "ransac_p3p, 100 matches, 30% outliers: {:.3} ms per call, {:.1} samples per call",
            per_call * 1e3,
            iterations as f64 / calls
        );
    }
}
