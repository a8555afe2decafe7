//! Helpers for the end-to-end tests: run the real `trn` binary, find the samples.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub fn trn() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_trn"));
    c.env("TRN_LOG", "info");
    c
}

pub fn run(args: &[&str]) -> Output {
    trn().args(args).output().expect("run trn")
}

pub fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A real sample fetched by data-samples/fetch.sh, copied into `dir` so no test
/// ever writes next to the shared files.
pub fn sample(name: &str, dir: &Path) -> PathBuf {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("data-samples/real").join(name);
    assert!(
        src.exists(),
        "{} is missing: run data-samples/fetch.sh first (the test script does)",
        src.display()
    );
    let dst = dir.join(name);
    std::fs::copy(&src, &dst).expect("copy sample");
    dst
}

/// Files in `dir` other than the ones listed: what a failed build must not leave.
pub fn leftovers(dir: &Path, inputs: &[&Path]) -> Vec<PathBuf> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| !inputs.iter().any(|i| i == p))
        .collect()
}

/// Synthetic ortho + DEM (UTM 13N, ellipsoidal heights) via `trn synth`.
pub fn synth(dir: &Path, size: usize, gsd: f64, east: f64, seed: u64) -> (PathBuf, PathBuf) {
    let ortho = dir.join(format!("synth-ortho-{seed}.tif"));
    let dem = dir.join(format!("synth-dem-{seed}.tif"));
    let o = run(&[
        "synth",
        "--ortho",
        ortho.to_str().unwrap(),
        "--dem",
        dem.to_str().unwrap(),
        "--size",
        &size.to_string(),
        "--gsd",
        &gsd.to_string(),
        "--east",
        &east.to_string(),
        "--seed",
        &seed.to_string(),
    ]);
    assert!(o.status.success(), "synth failed: {}", stderr(&o));
    (ortho, dem)
}

/// `trn simulate` over an ortho + ellipsoidal DEM (two threads unless `extra` says).
pub fn simulate(ortho: &Path, dem: &Path, scenario: &Path, out: &Path, extra: &[&str]) -> Output {
    let mut args = vec![
        "simulate",
        "--ortho",
        ortho.to_str().unwrap(),
        "--dem",
        dem.to_str().unwrap(),
        "--dem-vertical",
        "ellipsoid",
        "--scenario",
        scenario.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    if !extra.contains(&"--threads") {
        args.extend_from_slice(&["--threads", "2"]);
    }
    args.extend_from_slice(extra);
    run(&args)
}

/// A synthetic map, its landmark database (`--spacing 32`) and a 3 s nadir
/// flight 3 km above the terrain, in a temp dir.
pub struct NavFixture {
    pub dir: tempfile::TempDir,
    pub db: PathBuf,
    pub flight: PathBuf,
}

impl NavFixture {
    pub fn root(&self) -> &Path {
        self.dir.path()
    }
}

pub fn nav_fixture() -> NavFixture {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().to_path_buf();
    let (ortho, dem) = synth(&root, 1500, 4.0, 440000.0, 21);
    let db = root.join("map.gpkg");
    let o = run(&[
        "build",
        "--ortho",
        ortho.to_str().unwrap(),
        "--dem",
        dem.to_str().unwrap(),
        "--dem-vertical",
        "ellipsoid",
        "--spacing",
        "32",
        "--out",
        db.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "build failed: {}", stderr(&o));
    let scenario = root.join("scenario.json");
    std::fs::write(
        &scenario,
        r#"{"name": "test", "seed": 5,
            "camera": {"width": 320, "height": 240, "hfov_deg": 40},
            "frame_rate_hz": 4,
            "trajectory": {"kind": "balloon", "start_h_m": 4600, "end_h_m": 4000, "descent_rate_sl_m_s": 5,
                           "yaw_rate_deg_s": 6, "spin_bursts": 0, "pendulum_deg": 2},
            "init_error": {"horizontal_m": 100, "vertical_m": 30, "attitude_deg": 1},
            "realism": {"noise": {}, "photometric": {}}}"#,
    )
    .unwrap();
    let flight = root.join("flight");
    let o = simulate(&ortho, &dem, &scenario, &flight, &["--duration", "3"]);
    assert!(o.status.success(), "simulate failed: {}", stderr(&o));
    NavFixture { dir, db, flight }
}

/// A flight-format `camera.json`: 640 x 480 px, fx = fy = 800 px (43.6 deg).
pub const CAMERA_640_JSON: &str = r#"{"width": 640, "height": 480, "fx": 800.0, "fy": 800.0, "cx": 319.5, "cy": 239.5,
  "distortion": {"k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "k3": 0.0}, "q_cam_imu": [1.0, 0.0, 0.0, 0.0]}"#;
