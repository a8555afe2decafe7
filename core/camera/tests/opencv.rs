//! Projection and undistortion against OpenCV (`cv2.projectPoints`,
//! `cv2.undistortPointsIter`). Fixture: `scripts/fixtures/camera_opencv.py`.

use std::path::PathBuf;

use nalgebra::Vector3;
use trn_camera::{CameraModel, Distortion, NormalizedPoint, Pixel};

struct Row {
    camera: String,
    kind: String,
    model: CameraModel,
    input: [f64; 3],
    output: [f64; 2],
}

fn rows() -> Vec<Row> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/opencv_project.csv");
    let mut reader = csv::Reader::from_path(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let rows: Vec<Row> = reader
        .records()
        .map(|r| {
            let r = r.unwrap();
            let f = |i: usize| r[i].parse::<f64>().unwrap();
            Row {
                camera: r[0].to_string(),
                kind: r[1].to_string(),
                model: CameraModel {
                    width: r[2].parse().unwrap(),
                    height: r[3].parse().unwrap(),
                    fx: f(4),
                    fy: f(5),
                    cx: f(6),
                    cy: f(7),
                    distortion: Distortion { k1: f(8), k2: f(9), p1: f(10), p2: f(11), k3: f(12) },
                },
                input: [f(13), f(14), f(15)],
                output: [f(16), f(17)],
            }
        })
        .collect();
    assert!(rows.len() >= 200, "only {} fixture rows", rows.len());
    rows
}

#[test]
fn fixture_cameras_are_valid() {
    let mut seen = std::collections::BTreeMap::new();
    for r in rows() {
        seen.entry(r.camera.clone()).or_insert(r.model);
    }
    assert!(seen.len() >= 5);
    for (name, model) in &seen {
        model.validate().unwrap_or_else(|e| panic!("{name}: {e}"));
    }
}

#[test]
fn project_matches_opencv() {
    let mut n = 0;
    let mut worst_px: f64 = 0.0;
    for r in rows().iter().filter(|r| r.kind == "project") {
        let p_cam = Vector3::new(r.input[0], r.input[1], r.input[2]);
        let got = r.model.project(&p_cam).expect("z > 0");
        let want = Pixel::new(r.output[0], r.output[1]);
        let err_px = got.distance_px(&want);
        assert!(err_px < 1e-6, "{}: {p_cam:?} -> {got:?}, OpenCV {want:?}", r.camera);
        worst_px = worst_px.max(err_px);
        n += 1;
    }
    assert!(n >= 100);
    eprintln!("projection: {n} points, worst error vs OpenCV {worst_px:.2e} px");
}

#[test]
fn undistort_matches_opencv() {
    let mut n = 0;
    let mut worst: f64 = 0.0;
    for r in rows().iter().filter(|r| r.kind == "undistort") {
        let px = Pixel::new(r.input[0], r.input[1]);
        let got = r.model.pixel_to_normalized(px);
        let want = NormalizedPoint::new(r.output[0], r.output[1]);
        let err = (got.x - want.x).hypot(got.y - want.y);
        assert!(err < 1e-6, "{}: {px:?} -> {got:?}, OpenCV {want:?}", r.camera);
        // Same through the explicit two steps.
        let two_step = r.model.undistort(r.model.pixel_to_distorted(px));
        assert_eq!(two_step, got);
        worst = worst.max(err);
        n += 1;
    }
    assert!(n >= 100);
    eprintln!("undistortion: {n} pixels, worst error vs OpenCV {worst:.2e} (normalized)");
}
