//! Camera model properties: round trips over the whole image, JSON, field of
//! view, image bounds, fold-over detection.

use nalgebra::Vector3;
use trn_camera::{CameraConfig, CameraModel, Distortion, NormalizedPoint, Pixel};

/// A camera with lens `[k1, k2, p1, p2, k3]` and an off-centre principal point.
fn camera(w: u32, h: u32, f: f64, [k1, k2, p1, p2, k3]: [f64; 5]) -> CameraModel {
    CameraModel {
        width: w,
        height: h,
        fx: f,
        fy: f * 1.003,
        cx: 0.5 * (w as f64 - 1.0) + 3.7,
        cy: 0.5 * (h as f64 - 1.0) - 2.1,
        distortion: Distortion { k1, k2, p1, p2, k3 },
    }
}

/// Realistic lenses, from none to strong barrel / pincushion / tangential
/// (the same as the OpenCV fixture's, plus a fisheye-like barrel).
fn cameras() -> Vec<CameraModel> {
    vec![
        camera(1024, 768, 1785.0, [0.0, 0.0, 0.0, 0.0, 0.0]),
        camera(1280, 960, 900.0, [-0.28, 0.09, 0.0008, -0.0005, -0.012]),
        camera(640, 480, 600.0, [0.15, 0.05, -0.002, 0.003, 0.01]),
        camera(2048, 1536, 2400.0, [-0.05, 0.01, 0.01, -0.008, 0.0]),
        camera(1920, 1080, 1100.0, [-0.30, 0.10, -0.0012, 0.0009, -0.01]),
        camera(1600, 1200, 1000.0, [-0.33, 0.13, 0.0, 0.0, -0.02]),
    ]
}

/// Pixels on a grid over the whole image, corner pixel centres and the
/// image's outer corners included.
fn image_pixels(cam: &CameraModel) -> Vec<Pixel> {
    let (w, h) = (cam.width as f64, cam.height as f64);
    let mut px: Vec<Pixel> = cam.corners().to_vec();
    px.extend([
        Pixel::new(-0.5, -0.5),
        Pixel::new(w - 0.5, -0.5),
        Pixel::new(w - 0.5, h - 0.5),
        Pixel::new(-0.5, h - 0.5),
    ]);
    const N: usize = 40;
    for i in 0..=N {
        for j in 0..=N {
            px.push(Pixel::new(-0.5 + w * i as f64 / N as f64, -0.5 + h * j as f64 / N as f64));
        }
    }
    px
}

#[test]
fn project_of_ray_is_the_pixel_over_the_whole_image() {
    for cam in cameras() {
        cam.validate().unwrap();
        let mut worst_px: f64 = 0.0;
        for px in image_pixels(&cam) {
            let ray = cam.ray(px);
            assert!((ray.norm() - 1.0).abs() < 1e-15 && ray.z > 0.0);
            // At any range along the ray.
            for range_m in [1.0, 3.3e4] {
                let back = cam.project(&(ray * range_m)).unwrap();
                let err_px = back.distance_px(&px);
                assert!(err_px < 1e-9, "{cam:?}: {px:?} -> {back:?}");
                worst_px = worst_px.max(err_px);
            }
            // On the image (off its very edge, where rounding may step outside).
            let (w, h) = (cam.width as f64, cam.height as f64);
            if px.u.abs() < w - 0.5 - 1e-6
                && px.v.abs() < h - 0.5 - 1e-6
                && px.u > -0.5 + 1e-6
                && px.v > -0.5 + 1e-6
            {
                assert_eq!(cam.project_in_image(&ray).map(|b| b.distance_px(&px) < 1e-9), Some(true));
            }
        }
        eprintln!("k1={}: worst project(ray(px)) error {worst_px:.2e} px", cam.distortion.k1);
    }
}

#[test]
fn undistort_converges_to_1e12_over_the_whole_image() {
    for cam in cameras() {
        for px in image_pixels(&cam) {
            let d = cam.pixel_to_distorted(px);
            let u = cam.undistort(d);
            let again = cam.distort(u);
            let err = (again.x - d.x).hypot(again.y - d.y);
            assert!(err < 1e-12, "{cam:?}: {px:?}: residual {err}");
        }
    }
}

#[test]
fn distortion_jacobian_matches_finite_differences() {
    for cam in cameras() {
        let d = cam.distortion;
        for &(x, y) in &[(0.0, 0.0), (0.3, -0.2), (-0.7, 0.5), (0.9, 0.6)] {
            let j = d.jacobian(NormalizedPoint::new(x, y));
            let e = 1e-6;
            let fd = |dx: f64, dy: f64| {
                let p = d.apply(NormalizedPoint::new(x + dx, y + dy));
                let m = d.apply(NormalizedPoint::new(x - dx, y - dy));
                ((p.x - m.x) / (2.0 * e), (p.y - m.y) / (2.0 * e))
            };
            let (dxx, dyx) = fd(e, 0.0);
            let (dxy, dyy) = fd(0.0, e);
            for (a, b) in [(j[(0, 0)], dxx), (j[(1, 0)], dyx), (j[(0, 1)], dxy), (j[(1, 1)], dyy)] {
                assert!((a - b).abs() < 1e-8, "{d:?} at ({x}, {y}): {j} vs fd");
            }
        }
    }
}

#[test]
fn zero_distortion_is_a_pinhole() {
    let cam = CameraModel::from_fov(1024, 768, 32.0);
    let p = Vector3::new(-120.0, 45.0, 900.0);
    let px = cam.project(&p).unwrap();
    assert!((px.u - (cam.fx * p.x / p.z + cam.cx)).abs() < 1e-12);
    assert!((px.v - (cam.fy * p.y / p.z + cam.cy)).abs() < 1e-12);
    assert_eq!(cam.undistort(NormalizedPoint::new(0.3, -0.2)), NormalizedPoint::new(0.3, -0.2));
    // Principal point -> boresight.
    assert!((cam.ray(cam.principal_point()) - Vector3::z()).norm() < 1e-15);
}

#[test]
fn behind_the_camera_is_none() {
    let cam = CameraModel::from_fov(640, 480, 60.0);
    assert!(cam.project(&Vector3::new(1.0, 2.0, 0.0)).is_none());
    assert!(cam.project(&Vector3::new(0.0, 0.0, -5.0)).is_none());
    assert!(cam.project(&Vector3::new(0.0, 0.0, f64::NAN)).is_none());
    assert!(cam.project(&Vector3::new(0.0, 0.0, 1e-300)).is_some());
}

#[test]
fn from_fov_and_hfov() {
    for &(w, h, fov) in &[(1024, 768, 32.0), (640, 480, 90.0), (4000, 3000, 5.5), (101, 99, 120.0)] {
        let cam = CameraModel::from_fov(w, h, fov);
        assert!((cam.hfov_deg() - fov).abs() < 1e-12, "{w}x{h} {fov}: {}", cam.hfov_deg());
        assert_eq!((cam.fx, cam.cx, cam.cy), (cam.fy, (w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0));
        // Square pixels: vertical fov from the same focal length.
        let vfov = 2.0 * (0.5 * h as f64 / cam.fy).atan().to_degrees();
        assert!((cam.vfov_deg() - vfov).abs() < 1e-12);
        // The edge-of-image rays make half the fov with the boresight.
        let edge = cam.ray(Pixel::new(-0.5, cam.cy));
        assert!((edge.z.acos().to_degrees() - fov / 2.0).abs() < 1e-9);
    }
    // Barrel distortion widens the field of view of the same focal length.
    let mut cam = CameraModel::from_fov(1280, 960, 70.0);
    cam.distortion.k1 = -0.2;
    assert!(cam.hfov_deg() > 70.5);
}

#[test]
fn contains_and_corners() {
    let cam = CameraModel::from_fov(1024, 768, 30.0);
    let c = cam.corners();
    assert_eq!(
        c,
        [Pixel::new(0.0, 0.0), Pixel::new(1023.0, 0.0), Pixel::new(1023.0, 767.0), Pixel::new(0.0, 767.0)]
    );
    for px in c {
        assert!(cam.contains(px));
    }
    for px in [Pixel::new(-0.5, -0.5), Pixel::new(1023.5, 767.5), Pixel::new(511.5, 383.5)] {
        assert!(cam.contains(px), "{px:?}");
    }
    for px in
        [Pixel::new(-0.51, 0.0), Pixel::new(1023.51, 0.0), Pixel::new(0.0, -0.6), Pixel::new(0.0, 767.6)]
    {
        assert!(!cam.contains(px), "{px:?}");
    }
    assert!(!cam.contains(Pixel::new(f64::NAN, 0.0)));
}

#[test]
fn fold_back_is_rejected() {
    // Barrel: the distorted radius r (1 - 0.1 r^2) peaks at r = 1.83 and
    // folds back, so a point far outside the view (r = 3 -> 0.3) lands inside
    // the image (corners at distorted radius 0.82).
    let mut cam = CameraModel::from_fov(1000, 1000, 60.0);
    cam.distortion.k1 = -0.1;
    cam.validate().unwrap();
    let far_out = Vector3::new(3.0, 0.0, 1.0);
    let px = cam.project(&far_out).unwrap();
    assert!(cam.contains(px), "{px:?}");
    assert!(cam.project_in_image(&far_out).is_none());
    assert!(cam.project_in_image(&Vector3::new(0.2, 0.1, 1.0)).is_some());
    // A lens that folds over inside its own image fails validation.
    let mut wide = cam;
    wide.fx = 300.0;
    wide.fy = 300.0;
    assert!(wide.validate().is_err());
    assert!(CameraModel { fx: -1.0, ..cam }.validate().is_err());
    assert!(CameraModel { width: 0, ..cam }.validate().is_err());
}

#[test]
fn camera_json_of_the_flight_format() {
    // The example of FLIGHT_FORMAT.md.
    let text = r#"{
      "width": 1024, "height": 768,
      "fx": 1785.0, "fy": 1785.0, "cx": 511.5, "cy": 383.5,
      "distortion": {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0},
      "q_cam_imu": [1.0, 0.0, 0.0, 0.0]
    }"#;
    let cfg: CameraConfig = serde_json::from_str(text).unwrap();
    let m = cfg.model;
    assert_eq!((m.width, m.height, m.fx, m.fy, m.cx, m.cy), (1024, 768, 1785.0, 1785.0, 511.5, 383.5));
    assert_eq!(m.distortion, Distortion::default());
    assert_eq!(cfg.q_cam_imu(), nalgebra::UnitQuaternion::identity());
    let back: CameraConfig = serde_json::from_str(&serde_json::to_string(&cfg).unwrap()).unwrap();
    assert_eq!(back, cfg);

    // Distortion omitted -> zeros; integers where floats are expected; a
    // partial distortion object; mounting normalized on use.
    let text = r#"{"width": 640, "height": 480, "fx": 500, "fy": 500, "cx": 319.5, "cy": 239.5,
                   "q_cam_imu": [0.0, 0.0, 0.0, 2.0]}"#;
    let cfg: CameraConfig = serde_json::from_str(text).unwrap();
    assert_eq!(cfg.model.distortion, Distortion::default());
    assert!((cfg.q_cam_imu() * Vector3::x() - (-Vector3::x())).norm() < 1e-15);
    let cfg: CameraConfig =
        serde_json::from_str(r#"{"width": 8, "height": 8, "fx": 5, "fy": 5, "cx": 3.5, "cy": 3.5, "distortion": {"k1": -0.1}, "q_cam_imu": [1, 0, 0, 0]}"#)
            .unwrap();
    assert_eq!(cfg.model.distortion, Distortion { k1: -0.1, ..Default::default() });

    // A model alone round-trips too, and always writes its distortion.
    let json = serde_json::to_value(cfg.model).unwrap();
    assert_eq!(json["distortion"]["k1"], -0.1);
    assert!(serde_json::from_str::<CameraConfig>(r#"{"width": 8}"#).is_err());
}
