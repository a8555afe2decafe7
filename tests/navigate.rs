//! End to end: build a landmark database from a synthetic map, simulate a
//! short flight over it, navigate it with the real `trn` binary and score it
//! with `trn evaluate`.

mod common;

use std::path::Path;

use common::{nav_fixture, run, stderr, NavFixture};

fn navigate(s: &NavFixture, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec![
        "navigate",
        "--db",
        s.db.to_str().unwrap(),
        "--flight",
        s.flight.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    args.extend_from_slice(extra);
    run(&args)
}

fn evaluate(s: &NavFixture, poses: &Path) -> serde_json::Value {
    let json = s.root().join("eval.json");
    let o = run(&[
        "evaluate",
        "--flight",
        s.flight.to_str().unwrap(),
        "--poses",
        poses.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "evaluate failed: {}", stderr(&o));
    serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap()
}

#[test]
fn navigates_a_simulated_flight_to_metres() {
    let s = nav_fixture();
    let poses = s.root().join("poses.csv");
    let o = navigate(&s, &poses, &[]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let report = evaluate(&s, &poses);
    let run = &report["runs"][0];
    let share = run["status"]["share_fix"].as_f64().unwrap();
    let mean = run["fix_errors"]["pos_m"]["mean"].as_f64().unwrap();
    let att = run["fix_errors"]["att_deg"]["mean"].as_f64().unwrap();
    println!("fix share {share:.2}, mean 3D error {mean:.2} m, attitude {att:.4} deg");
    // 13 frames from a 100 m / 1 deg initial error, 4 m ortho, ~7 m camera pixels.
    assert!(share >= 0.9, "fix share {share}");
    assert!(mean < 10.0, "mean error {mean} m");
    assert!(att < 0.1, "attitude error {att} deg");
    // matches.csv sits next to poses.csv, one row per correlation match,
    // with the landmark's ECEF position: the truth pose projects an inlier's
    // landmark where it was found.
    let text = std::fs::read_to_string(s.root().join("matches.csv")).unwrap();
    assert!(text.starts_with("t,landmark,u,v,pred_u,pred_v,residual_px,inlier,x_m,y_m,z_m\n"));
    let matches = trn_flight::read_match_records(&s.root().join("matches.csv")).unwrap();
    assert!(matches.len() > 13 * 8);
    let flight = trn_flight::Flight::open(&s.flight).unwrap();
    let mut off: Vec<f64> = matches
        .iter()
        .filter(|m| m.inlier)
        .map(|m| {
            let truth = flight.truth_at(m.t).unwrap();
            let pose = trn_camera::CameraPose::new(truth.position.to_ecef(), truth.q_ecef_cam);
            let px = pose.project(&flight.camera.model, &m.landmark_ecef.expect("landmark ECEF")).unwrap();
            ((px.u - m.u).powi(2) + (px.v - m.v).powi(2)).sqrt()
        })
        .collect();
    off.sort_by(f64::total_cmp);
    let (median, worst) = (off[off.len() / 2], off[off.len() - 1]);
    println!("inliers against the truth projection: median {median:.2} px, worst {worst:.2} px");
    // Inliers are within 2 px of the solved pose, which is itself off by a little.
    assert!(median < 0.5 && worst < 4.0, "{median} {worst} px");
    // covariance.csv: one row per fix, positive standard deviations that
    // are about the size of the errors.
    let cov = std::fs::read_to_string(s.root().join("covariance.csv")).unwrap();
    let mut lines = cov.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header.len(), 7 + 21);
    assert_eq!(header[1], "sd_east_m");
    let rows: Vec<Vec<f64>> = lines.map(|l| l.split(',').map(|x| x.parse().unwrap()).collect()).collect();
    let fixes = std::fs::read_to_string(&poses).unwrap().lines().filter(|l| l.contains(",fix,")).count();
    assert_eq!(rows.len(), fixes);
    let sd_mean =
        rows.iter().map(|r| (r[1] * r[1] + r[2] * r[2] + r[3] * r[3]).sqrt()).sum::<f64>() / fixes as f64;
    println!("mean predicted 3D sd {sd_mean:.2} m against mean error {mean:.2} m");
    assert!(rows.iter().all(|r| r[1..7].iter().all(|&x| x > 0.0 && x.is_finite())));
    assert!(sd_mean > 0.1 * mean && sd_mean < 10.0 * mean, "{sd_mean} {mean}");

    // At 2 images per second only every other frame is processed while fixes
    // are accepted.
    // With --matches-dir, one picture per processed frame, named after its image.
    let half = s.root().join("half.csv");
    let pics = s.root().join("pictures/of/matches");
    let o = navigate(&s, &half, &["--rate", "2", "--no-gyro", "--matches-dir", pics.to_str().unwrap()]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let csv = std::fs::read_to_string(&half).unwrap();
    let rows = csv.lines().count() - 1;
    assert!((7..13).contains(&rows), "{rows} rows at 2 Hz");
    let mut names: Vec<String> =
        std::fs::read_dir(&pics).unwrap().map(|e| e.unwrap().file_name().into_string().unwrap()).collect();
    names.sort();
    assert_eq!(names.len(), rows, "{names:?}");
    let frames = std::fs::read_to_string(s.flight.join("frames.csv")).unwrap();
    for name in &names {
        let stem = name.strip_suffix(".png").expect("png");
        assert!(frames.contains(&format!("{stem}.")), "{name} is no frame's image");
        let pic = image::open(pics.join(name)).unwrap().to_rgb8();
        assert_eq!(pic.dimensions(), (320, 240));
        // Inliers are drawn green.
        assert!(pic.pixels().any(|p| p.0 == [40, 220, 60]), "{name} has no inlier mark");
    }
}

#[test]
fn bad_inputs_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("poses.csv");
    let missing = dir.path().join("nope");
    let o = run(&[
        "navigate",
        "--db",
        missing.join("x.gpkg").to_str().unwrap(),
        "--flight",
        missing.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains("nope"), "{e}");
    assert!(!out.exists());
    // --matches-dir naming an existing file cannot be a folder.
    std::fs::write(dir.path().join("file"), b"").unwrap();
    let file = dir.path().join("file");
    for (opt, value) in [
        ("--rate", "0"),
        ("--alpha-max", "90"),
        ("--min-inliers", "3"),
        ("--max-landmarks", "2"),
        ("--gyro-arw", "0"),
        ("--gyro-bias", "nan"),
        ("--matches-dir", file.to_str().unwrap()),
        ("--shading-weight", "1.5"),
        ("--sun", "250"),
        ("--sun", "250,95"),
    ] {
        let o = run(&["navigate", "--db", "x", "--flight", "y", "--out", "z", opt, value]);
        assert!(!o.status.success(), "{opt} {value} accepted");
        let e = stderr(&o);
        assert!(e.lines().any(|l| l.starts_with("error:") && l.contains(opt)), "{opt}: {e}");
    }
    // trn synth checks its relief too, before writing anything.
    let (ortho, dem) = (dir.path().join("o.tif"), dir.path().join("d.tif"));
    let o = run(&[
        "synth",
        "--ortho",
        ortho.to_str().unwrap(),
        "--dem",
        dem.to_str().unwrap(),
        "--size",
        "64",
        "--relief=-5",
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--relief"), "{}", stderr(&o));
    assert!(!ortho.exists() && !dem.exists());
}
