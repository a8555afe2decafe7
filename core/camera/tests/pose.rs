//! Camera poses in ECEF: quaternion convention, look_at, projection and rays.

use nalgebra::{UnitQuaternion, Vector3};
use trn_camera::{quat_from_wxyz, quat_to_wxyz, CameraModel, CameraPose, Pixel};
use trn_geodesy::{intersect_ellipsoid, Geodetic, LocalFrame};

#[test]
fn quaternion_is_hamilton_scalar_first_camera_to_ecef() {
    // 90 degrees about z: [cos 45, 0, 0, sin 45].
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let q = quat_from_wxyz([h, 0.0, 0.0, h]);
    assert!((q * Vector3::x() - Vector3::y()).norm() < 1e-15);
    assert!((q * Vector3::y() + Vector3::x()).norm() < 1e-15);
    // A pose with it maps the camera's x axis to ECEF y.
    let pose = CameraPose::new(trn_geodesy::Ecef::new(0.0, 0.0, 0.0), q);
    assert!((pose.to_ecef(&Vector3::x()).0 - Vector3::y()).norm() < 1e-15);
    // Round trip, and normalization of rounded file values.
    let w = quat_to_wxyz(&q);
    assert!((w[0] - h).abs() < 1e-15 && w[1] == 0.0 && w[2] == 0.0 && (w[3] - h).abs() < 1e-15);
    let q = quat_from_wxyz([0.5, 0.5, -0.5, 0.5001]);
    assert!((q.quaternion().norm() - 1.0).abs() < 1e-15);
    // Composition order: q_ecef_imu = q_ecef_cam * q_cam_imu.
    let q_cam_imu = quat_from_wxyz([h, h, 0.0, 0.0]); // 90 deg about x
    let q_ecef_cam = quat_from_wxyz([h, 0.0, 0.0, h]);
    let v_imu = Vector3::new(0.1, 0.2, 0.3);
    assert!(((q_ecef_cam * q_cam_imu) * v_imu - q_ecef_cam * (q_cam_imu * v_imu)).norm() < 1e-15);
}

#[test]
fn look_at_nadir_is_map_like() {
    let g = Geodetic::new(35.1, -106.6, 30_000.0);
    let frame = LocalFrame::at(g);
    let north = frame.vector_to_ecef(&Vector3::y());
    let pose = CameraPose::look_at(g.to_ecef(), g.with_height(0.0).to_ecef(), north);
    let r = pose.q_ecef_cam.to_rotation_matrix();
    // +z down, +x (image right) east, +y (image down) south.
    assert!((frame.vector_to_enu(&pose.boresight_ecef()) - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-12);
    assert!((frame.vector_to_enu(&(r * Vector3::x())) - Vector3::new(1.0, 0.0, 0.0)).norm() < 1e-12);
    assert!((frame.vector_to_enu(&(r * Vector3::y())) - Vector3::new(0.0, -1.0, 0.0)).norm() < 1e-12);
    // The target projects onto the principal point.
    let cam = CameraModel::from_fov(1024, 768, 30.0);
    let px = pose.project(&cam, &g.with_height(0.0).to_ecef()).unwrap();
    assert!(px.distance_px(&cam.principal_point()) < 1e-9);
    // A point north of the target is in the upper half of the image, east is right.
    let ne = frame.to_ecef(trn_geodesy::Enu::new(1_000.0, 2_000.0, -30_000.0));
    let px = pose.project(&cam, &ne).unwrap();
    assert!(px.u > cam.cx && px.v < cam.cy, "{px:?}");
}

#[test]
fn look_at_oblique_and_degenerate_hint() {
    let from = Geodetic::new(-20.0, 150.0, 12_000.0);
    let target = Geodetic::new(-19.8, 150.1, 300.0).to_ecef();
    let up = from.up_ecef();
    let pose = CameraPose::look_at(from.to_ecef(), target, up);
    let r = pose.q_ecef_cam.to_rotation_matrix();
    let z = (target.0 - from.to_ecef().0).normalize();
    assert!((pose.boresight_ecef() - z).norm() < 1e-12);
    // Image down is as opposite to the hint as possible: -y is the hint's
    // component perpendicular to the view, and x is level (perpendicular to up).
    let up_perp = (up - z * z.dot(&up)).normalize();
    assert!(((r * -Vector3::y()) - up_perp).norm() < 1e-12);
    assert!((r * Vector3::x()).dot(&up).abs() < 1e-12);
    assert!((r.matrix().determinant() - 1.0).abs() < 1e-12);
    // Hint along the view: still a proper rotation with the right boresight.
    let pose = CameraPose::look_at(from.to_ecef(), target, z * 3.0);
    assert!((pose.boresight_ecef() - z).norm() < 1e-12);
    assert!((pose.q_ecef_cam.to_rotation_matrix().matrix().determinant() - 1.0).abs() < 1e-12);
}

#[test]
fn pose_ray_and_project_agree_and_hit_the_ground() {
    let g = Geodetic::new(35.1, -106.6, 30_000.0);
    let north = LocalFrame::at(g).vector_to_ecef(&Vector3::y());
    // Tilted 20 degrees from nadir.
    let target = LocalFrame::at(g).to_ecef(trn_geodesy::Enu::new(6_000.0, 9_000.0, -30_000.0));
    let pose = CameraPose::look_at(g.to_ecef(), target, north);
    let mut cam = CameraModel::from_fov(1024, 768, 40.0);
    cam.distortion.k1 = -0.12;
    cam.distortion.p2 = 0.001;
    for px in cam.corners().into_iter().chain([Pixel::new(100.25, 700.5), cam.principal_point()]) {
        let ray = pose.ray(&cam, px);
        assert_eq!(ray.origin, pose.position);
        assert!((ray.direction.norm() - 1.0).abs() < 1e-15);
        let ground = intersect_ellipsoid(&ray, 1_500.0).expect("looking at the ground");
        assert!((ground.to_geodetic().h_m - 1_500.0).abs() < 0.01);
        let back = pose.project(&cam, &ground).unwrap();
        assert!(back.distance_px(&px) < 1e-6, "{px:?} -> {back:?}");
    }
    // Behind the camera.
    let behind = pose.to_ecef(&Vector3::new(0.0, 0.0, -100.0));
    assert!(pose.project(&cam, &behind).is_none());
    assert!(
        (pose.to_camera(&pose.to_ecef(&Vector3::new(1.0, -2.0, 3.0))) - Vector3::new(1.0, -2.0, 3.0)).norm()
            < 1e-8
    );
    let _: UnitQuaternion<f64> = pose.q_ecef_cam;
}
