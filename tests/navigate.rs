//! End to end: build a landmark database from a synthetic map, simulate a
//! short flight over it, navigate it with the real `trn` binary and score it
//! with `trn evaluate`.

mod common;

use std::path::{Path, PathBuf};

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
    evaluate_flight(&s.flight, poses, &s.root().join("eval.json"))
}

/// `trn evaluate` of `poses` on `flight`, its JSON report written to `json`.
fn evaluate_flight(flight: &Path, poses: &Path, json: &Path) -> serde_json::Value {
    let o = run(&[
        "evaluate",
        "--flight",
        flight.to_str().unwrap(),
        "--poses",
        poses.to_str().unwrap(),
        "--json",
        json.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "evaluate failed: {}", stderr(&o));
    serde_json::from_str(&std::fs::read_to_string(json).unwrap()).unwrap()
}

/// `--inertial-principal-point`: the tight filter carries the principal
/// point. The synthetic camera's is exact, and the balloon yaws 6 deg/s about
/// its boresight: over its 3 s the filter learns it a little (2.8 px from
/// its 3 px prior; 2.1 px before the landmark tracks' rows carried its
/// columns, which say that a steady roll's turn of a principal point error
/// is the shift a tilt gyro bias gives), around zero, and navigates as
/// well. (The filter's own convergence is `trn-navigator`'s unit test on a
/// 60 s turn.)
#[test]
fn the_principal_point_carried_by_the_filter_stays_at_an_exact_camera() {
    let s = nav_fixture();
    let poses = s.root().join("poses-pp.csv");
    let o = navigate(&s, &poses, &["--inertial-principal-point"]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let nav_report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let cal = &nav_report["calibration"];
    let est = [cal["principal_du_px"].as_f64().unwrap(), cal["principal_dv_px"].as_f64().unwrap()];
    let sigma: Vec<f64> =
        cal["principal_sigma_px"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
    println!("principal point {est:?} px +- {sigma:?}");
    assert!(sigma.iter().all(|&s| s > 0.0 && s < 2.95), "{cal}");
    assert!(est.iter().zip(&sigma).all(|(e, s)| e.abs() < 3.0 * s), "{cal}");
    let run = &evaluate(&s, &poses)["runs"][0];
    let mean = run["fix_errors"]["pos_m"]["mean"].as_f64().unwrap();
    assert!(run["status"]["share_fix"].as_f64().unwrap() >= 0.9 && mean < 10.0, "mean error {mean} m");
    // Both ways of estimating it at once is a usage error that names them.
    let o = navigate(&s, &poses, &["--inertial-principal-point", "--estimate-principal-point"]);
    assert!(!o.status.success());
    let err = stderr(&o);
    assert!(
        err.contains("--inertial-principal-point") && err.contains("--estimate-principal-point"),
        "{err}"
    );
}

#[test]
fn navigates_a_simulated_flight_to_metres() {
    let s = nav_fixture();
    let poses = s.root().join("poses.csv");
    let o = navigate(&s, &poses, &[]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    // The run report accounts for every fix in the self-calibration.
    let nav_report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let cal = &nav_report["calibration"];
    let counted: u64 =
        ["frames_used", "frames_weak", "frames_refused"].iter().map(|k| cal[k].as_u64().unwrap()).sum();
    assert_eq!(counted, nav_report["fixes"].as_u64().unwrap(), "{nav_report}");
    let focal_sigma = cal["focal_sigma_rel"].as_f64().unwrap();
    assert!(focal_sigma > 0.0 && focal_sigma < 0.0051, "{cal}");
    // After the first fix, the landmarks found in the image before update
    // the tight filter through the motion in between.
    let tracked = nav_report["track_updates"].as_u64().unwrap();
    assert!(tracked >= 6 && tracked < nav_report["processed"].as_u64().unwrap(), "{nav_report}");
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
    assert!(text.starts_with("t,landmark,u,v,pred_u,pred_v,residual_px,inlier,x_m,y_m,z_m,sigma_px\n"));
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
    // The defaults allow for a 40 m map offset and camera.json's 0.5% / 3 px,
    // which this perfect synthetic world does not have: sigmas well above
    // the errors.
    assert!(sd_mean > 0.1 * mean && sd_mean < 30.0 * mean, "{sd_mean} {mean}");
    // trn evaluate reads covariance.csv next to poses.csv: one NEES per fix.
    let c = &run["consistency"];
    assert_eq!(c["fixes"].as_u64().unwrap() as usize, fixes, "{c}");
    let (nees, band) = (c["mean_nees"].as_f64().unwrap(), c["band"].as_array().unwrap());
    println!("mean NEES {nees:.2}, consistent {band:?}");
    assert!(nees.is_finite() && nees > 0.0 && band[0].as_f64().unwrap() < 3.0);

    // With the focal length not carried by the inertial filter (each fix's
    // own evidence calibrates it), the same flight navigates as well, and
    // every fix is still accounted for in the self-calibration.
    let carried = s.root().join("no-inertial-focal.csv");
    let o = navigate(&s, &carried, &["--no-inertial-focal"]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let nav_report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let cal = &nav_report["calibration"];
    let counted: u64 =
        ["frames_used", "frames_weak", "frames_refused"].iter().map(|k| cal[k].as_u64().unwrap()).sum();
    assert_eq!(counted, nav_report["fixes"].as_u64().unwrap(), "{nav_report}");
    let focal_sigma = cal["focal_sigma_rel"].as_f64().unwrap();
    assert!(focal_sigma > 0.0 && focal_sigma < 0.0051, "{cal}");
    let run = evaluate_flight(&s.flight, &carried, &s.root().join("no-inertial-focal.json"));
    let (share, mean) = (
        run["runs"][0]["status"]["share_fix"].as_f64().unwrap(),
        run["runs"][0]["fix_errors"]["pos_m"]["mean"].as_f64().unwrap(),
    );
    println!("--no-inertial-focal: fix share {share:.2}, mean 3D error {mean:.2} m");
    assert!(share >= 0.9 && mean < 10.0, "{share} {mean}");

    // At 2 images per second only every other frame is processed while fixes
    // are accepted.
    // With --matches-dir, one picture per processed frame, named after its image.
    let half = s.root().join("half.csv");
    let pics = s.root().join("pictures/of/matches");
    let o = navigate(
        &s,
        &half,
        &["--rate", "2", "--no-gyro", "--no-self-calibration", "--matches-dir", pics.to_str().unwrap()],
    );
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let nav_report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert!(nav_report["calibration"].is_null(), "{nav_report}");
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
fn imu_rate_poses_fill_the_gaps_between_frames() {
    let s = nav_fixture();
    let poses = s.root().join("imu-run.csv");
    let o = navigate(&s, &poses, &["--imu-rate"]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let frames = trn_flight::read_nav_records(&poses).unwrap();
    let rows = trn_flight::read_nav_records(&s.root().join("poses-imu.csv")).unwrap();
    let flight = trn_flight::Flight::open(&s.flight).unwrap();
    // Every IMU sample between the first and the last frame, and every frame
    // (a sample at a frame's time is that frame's row).
    let (t0, t1) = (frames[0].pose.t, frames[frames.len() - 1].pose.t);
    let at_frame = |t: f64| frames.iter().any(|f| (f.pose.t - t).abs() < 1e-9);
    let samples = flight.imu.iter().filter(|x| x.t > t0 && x.t < t1 && !at_frame(x.t)).count();
    assert!(samples > 20 * frames.len(), "{samples} IMU samples for {} frames", frames.len());
    assert_eq!(rows.len(), samples + frames.len());
    assert!(rows.windows(2).all(|w| w[1].pose.t > w[0].pose.t), "IMU-rate rows out of order");
    for f in &frames {
        let r = rows.iter().find(|r| (r.pose.t - f.pose.t).abs() < 1e-9).expect("a row at each frame");
        assert_eq!(r.status, f.status, "t {}", f.pose.t);
    }
    // Between frames the poses follow the truth (interpolated between its
    // frame-time rows) as closely as at the frames.
    let err = |r: &trn_flight::NavRecord| {
        let truth = flight.truth_at(r.pose.t).unwrap();
        (r.pose.position.to_ecef().0 - truth.position.to_ecef().0).norm()
    };
    let mean = |v: &[f64]| v.iter().sum::<f64>() / v.len() as f64;
    let between: Vec<f64> =
        rows.iter().filter(|r| r.status == trn_flight::FixStatus::Propagated).map(err).collect();
    let at_frames: Vec<f64> =
        rows.iter().filter(|r| r.status == trn_flight::FixStatus::Fix).map(err).collect();
    println!(
        "IMU rate: mean error {:.2} m between frames, {:.2} m at fixes",
        mean(&between),
        mean(&at_frames)
    );
    assert!(mean(&between) < 2.0 * mean(&at_frames) + 1.0, "{} {}", mean(&between), mean(&at_frames));
    // covariance-imu.csv: a row per pose; a fix shrinks the sigma.
    let cov = std::fs::read_to_string(s.root().join("covariance-imu.csv")).unwrap();
    let sd: Vec<(f64, f64)> = cov
        .lines()
        .skip(1)
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
            (v[0], (v[1] * v[1] + v[2] * v[2] + v[3] * v[3]).sqrt())
        })
        .collect();
    assert_eq!(sd.len(), rows.len());
    assert!(sd.iter().all(|s| s.1.is_finite() && s.1 > 0.0));
    let mut shrunk = 0;
    for (k, r) in rows.iter().enumerate().skip(1) {
        if r.status == trn_flight::FixStatus::Fix && rows[k - 1].status == trn_flight::FixStatus::Propagated {
            shrunk += usize::from(sd[k].1 < sd[k - 1].1);
        }
    }
    assert!(shrunk >= frames.len() / 2, "{shrunk} fixes shrank the sigma");
    // Only the inertial filter has poses between frames.
    let o = navigate(&s, &s.root().join("fixes.csv"), &["--imu-rate", "--filter", "fixes"]);
    assert!(!o.status.success() && stderr(&o).contains("--imu-rate"), "{}", stderr(&o));
}

/// A realistic scenario of `data-samples/scenarios/realistic/` (Sierra SRTM
/// under Landsat, another sun, calibration and clock errors) with its guess
/// `horizontal_m` off, simulated for `duration_s` into `d`, and a default
/// database of the same sample: (database, flight).
fn realistic_flight(d: &Path, scenario: &str, horizontal_m: f64, duration_s: &str) -> (PathBuf, PathBuf) {
    (realistic_db(d), realistic_sim(d, scenario, horizontal_m, duration_s, "flight"))
}

/// The Sierra world's database, built in `d` (where its samples are
/// copied) as `trn build` with the realistic options builds it.
fn realistic_db(d: &Path) -> PathBuf {
    let ortho = common::sample("sierra-ortho-draped.tif", d);
    let dem = common::sample("sierra-dem.tif", d);
    let db = d.join("sierra.gpkg");
    let o = run(&[
        &["build", "--ortho", ortho.to_str().unwrap(), "--dem", dem.to_str().unwrap()][..],
        &REALISTIC[..],
        &["--out", db.to_str().unwrap()][..],
    ]
    .concat());
    assert!(o.status.success(), "build failed: {}", stderr(&o));
    db
}

/// The Sierra world's options (Landsat bands, EGM96 heights).
const REALISTIC: [&str; 4] = ["--ortho-bands", "3,2,1", "--dem-vertical", "egm96"];

/// A realistic scenario rendered over the Sierra world (its samples in `d`,
/// as [`realistic_flight`] copies them) into `d/name`, with its initial
/// guess `horizontal_m` off.
fn realistic_sim(d: &Path, scenario: &str, horizontal_m: f64, duration_s: &str, name: &str) -> PathBuf {
    realistic_sim_with(d, scenario, duration_s, name, |s| {
        s["init_error"]["horizontal_m"] = serde_json::json!(horizontal_m);
    })
}

/// [`realistic_sim`] of the scenario as `edit` changes it.
fn realistic_sim_with(
    d: &Path,
    scenario: &str,
    duration_s: &str,
    name: &str,
    edit: impl FnOnce(&mut serde_json::Value),
) -> PathBuf {
    let (ortho, dem) = (d.join("sierra-ortho-draped.tif"), d.join("sierra-dem.tif"));
    let real = REALISTIC;
    let src = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join(format!("data-samples/scenarios/realistic/{scenario}.json"));
    let mut scenario: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(src).unwrap()).unwrap();
    edit(&mut scenario);
    let scenario_path = d.join(format!("{name}.json"));
    std::fs::write(&scenario_path, scenario.to_string()).unwrap();
    let flight = d.join(name);
    let o = run(&[
        &["simulate", "--ortho", ortho.to_str().unwrap(), "--dem", dem.to_str().unwrap()][..],
        &real[..],
        &[
            "--scenario",
            scenario_path.to_str().unwrap(),
            "--out",
            flight.to_str().unwrap(),
            "--duration",
            duration_s,
        ][..],
    ]
    .concat());
    assert!(o.status.success(), "simulate failed: {}", stderr(&o));
    flight
}

/// Navigates `s` into `poses` with `args`; returns the first fixed frame,
/// the fix share and the worst accepted fix's error (m; `None` when none).
fn acquisition(s: &NavFixture, poses: &Path, args: &[&str]) -> (Option<usize>, f64, Option<f64>) {
    let (first, share, worst, _) = acquisition_consistency(s, poses, args);
    (first, share, worst)
}

/// [`acquisition`], and `trn evaluate`'s consistency of the fixes: the share
/// within their covariance's 95% bound, and whether their mean NEES is
/// under the top of its 95% band.
fn acquisition_consistency(
    s: &NavFixture,
    poses: &Path,
    args: &[&str],
) -> (Option<usize>, f64, Option<f64>, (f64, bool)) {
    let o = navigate(s, poses, args);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let r = rows(poses);
    println!("{args:?}: {r:?}");
    let first = r.iter().position(|x| x.1 == "fix");
    let report = evaluate(s, poses);
    let run = &report["runs"][0];
    let (share, worst) =
        (run["status"]["share_fix"].as_f64().unwrap(), run["fix_errors"]["pos_m"]["max"].as_f64());
    println!("{args:?}: first fix at {first:?}; fix share {share:.2}, worst fix {worst:?} m");
    println!("{args:?}: consistency {}", run["consistency"]);
    let c = &run["consistency"];
    let nees_under_band = c["mean_nees"].as_f64().zip(c["band"][1].as_f64()).is_some_and(|(n, top)| n <= top);
    (first, share, worst, (c["share_within_95"].as_f64().unwrap_or(0.0), nees_under_band))
}

/// [`acquisition`] with its checks: a first fix no later than frame
/// `by_frame`, at least `min_share` of the frames fixed, and no accepted fix
/// a navigator should not trust (250 m).
fn acquires(s: &NavFixture, poses: &Path, args: &[&str], by_frame: usize, min_share: f64) {
    let (first, share, worst) = acquisition(s, poses, args);
    assert!(first.is_some_and(|f| f <= by_frame), "{args:?}: first fix at frame {first:?}");
    assert!(
        share >= min_share && worst.is_some_and(|w| w < 250.0),
        "{args:?}: fix share {share}, worst fix {worst:?} m"
    );
}

/// Issue #13's acquisition from 5 km, on real relief and a world that is not
/// the map: the realistic lost-balloon scenario with its guess 5 km off,
/// navigated with that uncertainty told (`--init-sigma-m 5000`).
#[test]
fn acquires_from_5_km_on_real_relief() {
    let dir = tempfile::tempdir().unwrap();
    let (db, flight) = realistic_flight(dir.path(), "sierra-balloon-nadir-lost", 5000.0, "5");
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db, flight };
    // Within 10 processed frames, and no fix a navigator should not trust.
    acquires(&s, &s.root().join("poses.csv"), &["--init-sigma-m", "5000"], 9, 0.8);
    // Not told (the default 300 m): the inertial filter's velocity doubt
    // widens the search until it acquires.
    acquires(&s, &s.root().join("poses-untold.csv"), &[], 9, 0.0);
    // A high oblique view (the balloon at 20 km, 62 deg of incidence at the
    // image's centre, 40 km away) 6 km off, told. Searched over its whole
    // 512x384 level from so far, 32 of 300 templates matched and 5 agreed, at
    // every frame (the first fix came at frame 96); its narrow tiles, as far
    // apart as a template's warp stands, searched every other frame from the
    // second, acquire it (its first fix at frame 2 here; at frame 5 when the
    // alternation looked at the guess's own search of each frame only).
    let oblique = realistic_sim(dir.path(), "sierra-balloon-oblique", 300.0, "5", "oblique-6km");
    move_guess(&oblique, 0.0, 6000.0);
    let s = NavFixture { flight: oblique, ..s };
    acquires(&s, &s.root().join("poses-oblique.csv"), &["--init-sigma-m", "6000"], 3, 0.6);
    // The same 6 km south (the truth farther along the line of sight): its
    // one search starts on the 128x96 level, takes ~30 ms and fails at
    // every frame (first fix at frame 74), too cheap to alternate with the
    // narrow layout; the rest of its frame's work budget goes to the narrow
    // tiles, and the first frame acquires it (the second confirms it).
    move_guess(&s.flight, 0.0, -6000.0);
    acquires(&s, &s.root().join("poses-oblique-south.csv"), &["--init-sigma-m", "6000"], 2, 0.6);
}

/// The lens learnt in flight on real relief: the realistic 30 km nadir
/// balloon, whose camera's focal length is 0.3% longer than `camera.json`
/// says. A nadir view cannot tell it from the range, so each fix's own
/// evidence leaves it at its prior (`--no-inertial-focal`); the inertial
/// filter, which carries it by default, learns it from the pendulum's
/// tilts through the landmarks tracked between images, and the fixes'
/// error falls with it.
#[test]
fn the_filter_learns_the_lens_a_nadir_view_cannot_see() {
    let dir = tempfile::tempdir().unwrap();
    let (db, flight) = realistic_flight(dir.path(), "sierra-balloon-nadir", 300.0, "20");
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db, flight };
    // (focal estimate, its sigma, mean fix error m)
    let run = |name: &str, extra: &[&str]| {
        let poses = s.root().join(format!("{name}.csv"));
        let o = navigate(&s, &poses, extra);
        assert!(o.status.success(), "{name}: navigate failed: {}", stderr(&o));
        let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let cal = &report["calibration"];
        let e = evaluate_flight(&s.flight, &poses, &s.root().join(format!("{name}.json")));
        let run = &e["runs"][0];
        assert!(run["status"]["share_fix"].as_f64().unwrap() >= 0.95, "{name}: {run}");
        let got = (
            cal["focal_rel"].as_f64().unwrap(),
            cal["focal_sigma_rel"].as_f64().unwrap(),
            run["fix_errors"]["pos_m"]["mean"].as_f64().unwrap(),
        );
        println!("{name}: focal {:+.3}% +- {:.3}%, mean error {:.1} m", got.0 * 100.0, got.1 * 100.0, got.2);
        got
    };
    let (focal, sigma, carried_m) = run("carried", &[]);
    let (alone, alone_sigma, alone_m) = run("alone", &["--no-inertial-focal"]);
    // Each fix alone: nothing learnt (the prior's 0.5%).
    assert!(alone.abs() < 0.0005 && alone_sigma > 0.0045, "{alone} +- {alone_sigma}");
    // Carried: within 3 sigmas of the truth, the sigma at most 0.3%, and on
    // the right side of zero.
    assert!((focal - 0.003).abs() < 3.0 * sigma && sigma < 0.003 && focal > 0.0, "{focal} +- {sigma}");
    assert!(carried_m < 0.8 * alone_m, "carried {carried_m:.1} m, alone {alone_m:.1} m");
}

/// A low camera's acquisition: the realistic 640x480 rocket (40 deg, 3.5 km
/// above the pad) with its guess 1.5 km off (about 23 deg of view at that
/// height), told. Its acquisition searches the 160x120 level: on the 80x60
/// one (two coarse templates across) it never fixed, whichever way the
/// guess was off (README, acquisition). Then 5 km off (twice what one
/// search reaches at that height): the acquisition searches in tiles,
/// nearest first, as many a frame as its work budget allows, and the next
/// frame confirms it. Then a low oblique view 2 km off across its line of
/// sight, and a small camera 10 km off.
#[test]
fn a_low_camera_acquires_from_1_5_and_5_km() {
    let dir = tempfile::tempdir().unwrap();
    let (db, flight) = realistic_flight(dir.path(), "sierra-rocket-640x480", 1500.0, "3");
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db, flight };
    acquires(&s, &s.root().join("poses.csv"), &["--init-sigma-m", "1500"], 2, 0.6);
    // Without the inertial filter (`--filter fixes`, the navigator before
    // it, kept for comparison) its fixes, 12-20 landmarks at 5 km, are
    // 30-150 m off, and one 400 m (the image disagreed with the gyro and
    // was trusted: open, README). Their covariance now counts the
    // residuals' own scatter and the map's offset, which the filter
    // carries as states: that fix lies 5.1 sigmas off, where it lay 9.6
    // with the map's offset alone (solved at 0.1 px, their sigmas were
    // 12-17 m).
    let fixes = ["--init-sigma-m", "1500", "--filter", "fixes"];
    let (_, share, _, _) = acquisition_consistency(&s, &s.root().join("poses-fixes.csv"), &fixes);
    let e = evaluate(&s, &s.root().join("poses-fixes.csv"));
    let farthest = e["runs"][0]["consistency"]["max_sigma_distance"].as_f64().unwrap();
    assert!(share >= 0.6, "--filter fixes: fix share {share}");
    assert!(farthest < 6.0, "--filter fixes: a fix {farthest:.1} sigmas from the truth");
    let far = realistic_sim(dir.path(), "sierra-rocket-640x480", 5000.0, "3", "flight-5km");
    let s = NavFixture { flight: far, ..s };
    acquires(&s, &s.root().join("poses-5km.csv"), &["--init-sigma-m", "5000"], 5, 0.5);
    // The low pass (640x480, 60 deg, 50 deg forward, flying east) with its
    // guess 2 km north, across its line of sight: its 160x120 level's
    // templates span 0.25 rad, warped wrong from so far off (6 matches, 5
    // inliers), and the acquisition searches its 320x240 level. (On the
    // coarse level it fixed only after ~100 frames, when a tile caught it.)
    let low = realistic_sim(dir.path(), "sierra-low-pass", 300.0, "2", "low-pass");
    move_guess(&low, 0.0, 2000.0);
    let s = NavFixture { flight: low, ..s };
    acquires(&s, &s.root().join("poses-low.csv"), &["--init-sigma-m", "2000"], 1, 0.6);
    // The 200x150 rocket 10 km off, told: ~100 of its 1.7 km tiles lie
    // nearer the guess than the truth. Four a frame never reached it in the
    // flight; a frame's work budget (`--acquisition-budget`) searched ~15
    // while a template's prediction counted 10^7 multiply-adds, and ~40 at
    // what a prediction costs (its first fix at frame 2, where it was 4).
    // With the lower texture thresholds of stop 51 (14 089 templates where
    // 8344) its finer levels hold enough landmarks for tiles of 852 m
    // where they were 1.7 km: ~60 a frame, four times as many to cover, and
    // it is found at frame 5 (8 km off) and confirmed at frame 6. #13 asks
    // for 10.
    let small = realistic_sim(dir.path(), "sierra-rocket-200x150", 10000.0, "5", "small-10km");
    let s = NavFixture { flight: small, ..s };
    acquires(&s, &s.root().join("poses-small.csv"), &["--init-sigma-m", "10000"], 6, 0.25);
    // The 640x480 rocket 10 km off, not told, climbing 230 m/s: its first
    // fix comes from a tile, kilometres above the guess. The first fix's
    // height gate, at the 20 m/s of a navigator without the inertial filter,
    // refused it and every later one; at the filter's initial velocity doubt
    // it stands. Found at frame 6 (its first fix 119 m off, 17 inliers, 65 m
    // of sigma east, while relief was ray-marched; the rocket's first frames
    // see ~20 landmarks);
    // at frame 9 while a template's prediction counted 10^7 multiply-adds of
    // the frame's budget, at frame 10 with whole templates on the tiles'
    // level, at frame 26 with 300 landmarks a tile. Its fixes are
    // consistent: their mean NEES under the top of its 95% band, 90% of them
    // inside their 95% bound (a consistent navigator leaves 5% outside: 25
    // of 25 here; 21 of 25 when each fix counted its landmarks' own errors
    // anew, the same landmarks seen again keeping a 120 m tilt/shift error
    // for 4 s; 16 of 22 when the filter restarted from the fix's covariance
    // without the calibration's), and none beyond #13's 250 m.
    let climbing = realistic_sim(dir.path(), "sierra-rocket-640x480", 10000.0, "15", "climbing-10km");
    let s = NavFixture { flight: climbing, ..s };
    let (first, share, worst, (within, nees_ok)) =
        acquisition_consistency(&s, &s.root().join("poses-climbing.csv"), &[]);
    assert!(first.is_some_and(|f| f <= 8) && share >= 0.05, "first fix at {first:?}, fix share {share}");
    assert!(
        nees_ok && within >= 0.9 && worst.is_some_and(|w| w < 250.0),
        "worst fix {worst:?} m, {within} within 95%, mean NEES under its band: {nees_ok}"
    );
}

/// Moves `flight`'s initial guess to `east_m`, `north_m` from its first true
/// position (its height and attitude kept).
fn move_guess(flight: &Path, east_m: f64, north_m: f64) {
    let truth = std::fs::read_to_string(flight.join("truth.csv")).unwrap();
    let first: Vec<f64> =
        truth.lines().nth(1).unwrap().split(',').take(3).map(|x| x.parse().unwrap()).collect();
    let (lat, lon) = (first[1], first[2]);
    // Metres on a local sphere: accurate to metres over 2 km.
    let r = 6_371_000.0;
    edit_init(flight, |init| {
        init["lat"] = serde_json::json!(lat + (north_m / r).to_degrees());
        init["lon"] = serde_json::json!(lon + (east_m / (r * lat.to_radians().cos())).to_degrees());
    });
}

/// `flight`'s `init.json` changed in place by `edit`.
fn edit_init(flight: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let init_path = flight.join("init.json");
    let mut init: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&init_path).unwrap()).unwrap();
    edit(&mut init);
    std::fs::write(&init_path, init.to_string()).unwrap();
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
        ("--acquisition-budget", "0"),
        ("--init-sigma-m", "0"),
        ("--min-inlier-share", "1.5"),
        ("--init-sigma-deg", "inf"),
        ("--gyro-arw", "0"),
        ("--gyro-bias", "nan"),
        ("--gyro-max-jump", "nan"),
        ("--imu-gap-doubt", "nan"),
        ("--accel-max-jump", "inf"),
        ("--gyro-range", "0"),
        ("--accel-range", "nan"),
        ("--matches-dir", file.to_str().unwrap()),
        ("--shading-weight", "1.5"),
        ("--duplicate-separation", "1.5"),
        ("--duplicate-separation", "nan"),
        ("--duplicate-separation", "-0.5"),
        ("--sun", "250"),
        ("--sun", "250,95"),
        ("--focal-sigma", "0"),
        ("--principal-point-sigma", "0"),
        ("--calibration-frame-sigma", "nan"),
        ("--landmark-height-sigma", "inf"),
        ("--filter", "kalman"),
        ("--init-velocity-sigma", "0"),
        ("--accel-bias", "nan"),
        ("--map-sigma", "inf"),
        ("--map-att-sigma", "11"),
        ("--map-att-sigma", "nan"),
        ("--map-tau", "0"),
        ("--map-view-sigma", "nan"),
        ("--map-view-sigma", "inf"),
        ("--doubt-min-cells", "many"),
        ("--doubt-min-cells", "2.5"),
        ("--miss-min-cells", "many"),
        ("--miss-min-cells", "2.5"),
        // A negative number is the option's value (refused, the option
        // named), not an unknown flag.
        ("--miss-min-cells", "-1"),
        ("--max-landmarks", "-5"),
        ("--gyro-arw", "-1"),
        ("--time-offset-sigma", "nan"),
        ("--track-sigma", "0"),
        ("--track-sigma", "nan"),
        ("--ransac-threshold", "0"),
        ("--ransac-threshold", "nan"),
    ] {
        let o = run(&["navigate", "--db", "x", "--flight", "y", "--out", "z", opt, value]);
        assert!(!o.status.success(), "{opt} {value} accepted");
        let e = stderr(&o);
        assert!(e.lines().any(|l| l.starts_with("error:") && l.contains(opt)), "{opt}: {e}");
    }
    // The principal point learnt two ways at once is a usage error that
    // names both.
    let o = run(&[
        "navigate",
        "--db",
        "x",
        "--flight",
        "y",
        "--out",
        "z",
        "--principal-point-from-tracks",
        "--inertial-principal-point",
    ]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains("--principal-point-from-tracks") && e.contains("--inertial-principal-point"), "{e}");
    // trn synth checks its relief too, before writing anything, with the
    // negative value given either way.
    let (ortho, dem) = (dir.path().join("o.tif"), dir.path().join("d.tif"));
    let files = ["--ortho", ortho.to_str().unwrap(), "--dem", dem.to_str().unwrap(), "--size", "64"];
    for relief in [&["--relief=-5"][..], &["--relief", "-5"]] {
        let o = run(&[&["synth"][..], &files, relief].concat());
        assert!(!o.status.success());
        assert!(stderr(&o).contains("--relief"), "{relief:?}: {}", stderr(&o));
    }
    assert!(!ortho.exists() && !dem.exists());
}

/// Copies a flight folder (files and images) so a test can change it.
fn copy_flight(from: &Path, to: &Path) {
    std::fs::create_dir_all(to.join("images")).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        if e.file_type().unwrap().is_file() {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
    for e in std::fs::read_dir(from.join("images")).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join("images").join(e.file_name())).unwrap();
    }
}

/// A copy of the fixture's flight under `name` with its `init.json` changed
/// by `edit`; returns the copy's folder and its flight folder.
fn with_init(
    s: &NavFixture,
    name: &str,
    edit: impl FnOnce(&mut serde_json::Value),
) -> (std::path::PathBuf, std::path::PathBuf) {
    let dir = s.root().join(name);
    let flight = dir.join("flight");
    copy_flight(&s.flight, &flight);
    edit_init(&flight, edit);
    (dir, flight)
}

/// (t, status, inliers) of each poses.csv row.
fn rows(poses: &Path) -> Vec<(f64, String, u32)> {
    std::fs::read_to_string(poses)
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let f: Vec<&str> = l.split(',').collect();
            (f[0].parse().unwrap(), f[8].to_string(), f[9].parse().unwrap())
        })
        .collect()
}

#[test]
fn rejected_solutions_are_counted_and_the_next_image_is_processed_at_once() {
    let s = nav_fixture();
    let dir = s.root().join("reject");
    std::fs::create_dir_all(&dir).unwrap();
    // No solution can have 10 000 inliers: every one is rejected, so at 2 Hz
    // every image is processed anyway (the reject-and-reprocess path).
    let poses = dir.join("poses.csv");
    let o = navigate(&s, &poses, &["--rate", "2", "--min-inliers", "10000"]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let r = rows(&poses);
    let frames = std::fs::read_to_string(s.flight.join("frames.csv")).unwrap().lines().count() - 1;
    assert_eq!(r.len(), frames, "every frame processed after a rejection");
    assert!(r.iter().all(|(_, st, _)| st == "propagated"));
    // The rejected solutions' inliers are reported, and counted by reason.
    // (Before a first fix every refused frame doubles the inertial filter's
    // pose doubt (the guess may be worse than told), so the searches soon
    // are acquisitions that this small image's repeated road grid defeats:
    // the later frames have no solution at all.)
    let with_solution = r.iter().filter(|(_, _, n)| *n > 0).count();
    assert!(with_solution >= 2, "{r:?}");
    assert!(r[..2].iter().all(|(_, _, n)| *n > 0), "{r:?}");
    assert_eq!(report["rejected"]["few_inliers"].as_u64().unwrap() as usize, with_solution);
    assert_eq!(report["rejected"]["inconsistent"].as_u64().unwrap(), 0);
    assert_eq!(report["narrow_inconsistent"].as_u64().unwrap(), 0);
    assert_eq!(report["rejected"]["height"].as_u64().unwrap(), 0);
    assert_eq!(report["fixes"].as_u64().unwrap(), 0);
}

#[test]
fn the_first_fix_is_checked_and_the_height_gate_never_locks_out() {
    let s = nav_fixture();
    // The initial guess 400 m too high (370 m above the truth with the
    // scenario's own 30 m error), said to be good to 100 m: the first
    // solutions (at the true height, 70-77 inliers) are farther from it than
    // the 30 m limit plus three sigmas (330 m); the gate then widens by 3 x
    // 20 m/s per second (a slow vehicle: the inertial filter's initial
    // velocity doubt, which the first fix's gate allows, set to 20 m/s)
    // until they pass, after about 0.7 s.
    let (dir, flight) = with_init(&s, "high-init", |init| {
        let h = init["h"].as_f64().unwrap();
        init["h"] = serde_json::json!(h + 400.0);
    });
    let poses = dir.join("poses.csv");
    let s2 = NavFixture { dir: tempfile::tempdir().unwrap(), db: s.db.clone(), flight: flight.clone() };
    // (The map offset is sized by the landmarks' GSD: at a fixed 40 m the
    // first fix's update left a third of this 4-sigma guess error in it,
    // and this 3 s flight ended 98 m off; README, inertial filter.)
    let o = navigate(
        &s2,
        &poses,
        &["--max-height-jump", "30", "--init-sigma-m", "100", "--init-velocity-sigma", "20"],
    );
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let r = rows(&poses);
    println!("{r:?}\n{report}");
    // Solutions with enough inliers were refused for their height while the
    // gate was narrow (the first one checked against the initial guess), and
    // the first frames carry the guess.
    assert!(report["rejected"]["height"].as_u64().unwrap() >= 1, "{report}");
    assert_eq!(r[0].1, "propagated");
    assert!(r[0].2 > 0, "{r:?}");
    // Nothing is accepted before the widening gate can admit the true height
    // (a solution that far off is refused), and the last frames all fix.
    let first_fix = r.iter().position(|(_, st, _)| st == "fix").expect("a fix after the rejections");
    assert!(r[first_fix].0 > 0.5, "first fix at {} s", r[first_fix].0);
    assert!(r[r.len() - 3..].iter().all(|(_, st, _)| st == "fix"), "{r:?}");
    // Against the truth, the fixes are at the true height (the guess was not).
    let report = evaluate(&s2, &poses);
    let mean = report["runs"][0]["fix_errors"]["pos_m"]["mean"].as_f64().unwrap();
    assert!(mean < 50.0, "mean fix error {mean} m");
}

/// A guess far off on a repeated pattern: the synthetic map's road grid
/// repeats every 131 x 97 pixels (524 x 388 m), and a guess 1.5 km off (a
/// third of a radian at 4.6 km, a ~380 px search on this 320 px image, as
/// 10 km at 30 km) lands near an alias of it. Before an acquisition had to
/// stand on its coarse level, the bounded finer searches around the guess
/// fixed every frame 1.1-1.6 km off with 40-95 inliers; now the navigator
/// doubts them and carries the guess. (Acquisition itself is measured on the
/// realistic Sierra flight, `scripts/bench_acquisition.sh`: 10 km and 14
/// degrees off, the first frame fixed with 181 inliers.)
#[test]
fn a_guess_kilometres_off_on_a_repeated_pattern_gives_no_wrong_fix() {
    let s = nav_fixture();
    let (dir, flight) = with_init(&s, "far-init", |init| {
        let (lat, lon) = (init["lat"].as_f64().unwrap(), init["lon"].as_f64().unwrap());
        // 1060 m north and 1060 m east.
        init["lat"] = serde_json::json!(lat + 1060.0 / 111_000.0);
        init["lon"] = serde_json::json!(lon + 1060.0 / (111_000.0 * lat.to_radians().cos()));
    });
    let poses = dir.join("poses.csv");
    let s2 = NavFixture { dir: tempfile::tempdir().unwrap(), db: s.db.clone(), flight: flight.clone() };
    let o = navigate(&s2, &poses, &["--init-sigma-m", "1500"]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let r = rows(&poses);
    println!("{r:?}");
    assert_eq!(r.len(), 13, "{r:?}");
    let report = evaluate(&s2, &poses);
    let run = &report["runs"][0];
    if run["status"]["share_fix"].as_f64().unwrap() > 0.0 {
        let worst = run["fix_errors"]["pos_m"]["max"].as_f64().unwrap();
        assert!(worst < 50.0, "a fix {worst} m off was accepted: {r:?}");
    }
}

#[test]
fn frames_seen_through_a_hole_in_the_cloud_still_update_the_tight_filter() {
    let s = nav_fixture();
    let dir = s.root().join("hole");
    let flight = dir.join("flight");
    copy_flight(&s.flight, &flight);
    // From 1 s on, each image is grey but for a centred box of 0.3 of its
    // sides: too narrow a spread for a fix, a few matches for the filter.
    let frames = std::fs::read_to_string(flight.join("frames.csv")).unwrap();
    let hole = grey_but_a_box(&flight, 1.0..f64::INFINITY, 0.3);
    let run_with = |name: &str, extra: &[&str]| {
        let poses = dir.join(name);
        let mut args = vec!["navigate", "--db", s.db.to_str().unwrap(), "--flight", flight.to_str().unwrap()];
        args.extend_from_slice(&["--out", poses.to_str().unwrap()]);
        args.extend_from_slice(extra);
        let o = run(&args);
        assert!(o.status.success(), "navigate failed: {}", stderr(&o));
        let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let e = evaluate_flight(&flight, &poses, &dir.join(format!("{name}.json")));
        let worst = e["runs"][0]["per_frame"]
            .as_array()
            .unwrap()
            .iter()
            .map(|f| f["error"]["pos_m"].as_f64().unwrap())
            .fold(0.0, f64::max);
        (report["fixes"].as_u64().unwrap(), report["prior_gated_updates"].as_u64().unwrap(), worst)
    };
    let (fixes, gated, worst) = run_with("gated.csv", &[]);
    let total = frames.lines().count() as u64 - 1;
    assert!(fixes <= total - hole, "{fixes} fixes: the box gives none");
    assert!(gated * 2 >= hole, "{gated} of {hole} frames through the hole updated the filter");
    assert!(worst < 10.0, "worst error {worst:.1} m");
    let (_, none, _) = run_with("plain.csv", &["--no-prior-gated-update"]);
    assert_eq!(none, 0);
}

/// Greys every image of `flight` taken in `times` but for a centred box of
/// `share` of its sides (a hole in the cloud; 0: a cloud); the images so
/// changed.
fn grey_but_a_box(flight: &Path, times: std::ops::Range<f64>, share: f64) -> u64 {
    let frames = std::fs::read_to_string(flight.join("frames.csv")).unwrap();
    let mut changed = 0;
    for line in frames.lines().skip(1) {
        let (t, image) = line.split_once(',').unwrap();
        if !times.contains(&t.parse::<f64>().unwrap()) {
            continue;
        }
        let path = flight.join(image);
        let mut img = image::open(&path).unwrap().to_luma8();
        let (w, h) = img.dimensions();
        let margin = (1.0 - share) / 2.0;
        let (x0, y0) = ((w as f64 * margin) as u32, (h as f64 * margin) as u32);
        for (x, y, p) in img.enumerate_pixels_mut() {
            if x < x0 || x >= w - x0 || y < y0 || y >= h - y0 {
                p.0 = [128];
            }
        }
        img.save(&path).unwrap();
        changed += 1;
    }
    changed
}

/// `--threads`: a frame's landmarks predicted and correlated on two threads
/// give every frame's pose, status and inliers, every match (in order) and
/// every covariance as on one, from a good guess and from one 1.5 km off
/// (the acquisition's searches).
#[test]
fn threads_change_no_pose() {
    let s = nav_fixture();
    let (dir, flight) = with_init(&s, "threads-far", |_| {});
    move_guess(&flight, 1060.0, 1060.0);
    let far = NavFixture { dir: tempfile::tempdir().unwrap(), db: s.db.clone(), flight };
    // poses.csv without its last column (ms), then matches.csv and covariance.csv.
    let outputs = |poses: &Path| -> Vec<String> {
        let read = |name: &str| std::fs::read_to_string(poses.with_file_name(name)).unwrap();
        let mut lines: Vec<String> =
            read("poses.csv").lines().map(|l| l.rsplit_once(',').unwrap().0.to_string()).collect();
        lines.extend(read("matches.csv").lines().map(str::to_string));
        lines.extend(read("covariance.csv").lines().map(str::to_string));
        lines
    };
    for (k, (fixture, extra)) in
        [(&s, &[][..]), (&far, &["--init-sigma-m", "1500"][..])].into_iter().enumerate()
    {
        let mut out = Vec::new();
        for threads in ["1", "2"] {
            let run_dir = dir.join(format!("run-{k}-{threads}"));
            std::fs::create_dir_all(&run_dir).unwrap();
            let poses = run_dir.join("poses.csv");
            let mut args = extra.to_vec();
            args.extend(["--threads", threads]);
            let o = navigate(fixture, &poses, &args);
            assert!(o.status.success(), "navigate --threads {threads} failed: {}", stderr(&o));
            out.push(outputs(&poses));
        }
        assert!(out[0].len() > 100, "{:?}", out[0]);
        assert_eq!(out[0], out[1], "one thread and two differ ({extra:?})");
    }
    // Zero threads is a usage error that names the option.
    let o = navigate(&s, &dir.join("zero.csv"), &["--threads", "0"]);
    assert!(!o.status.success() && stderr(&o).contains("--threads"), "{}", stderr(&o));
}

/// Rewrites `imu.csv` of `flight` by `edit` on its rows (`t, wx, ..., az`
/// as numbers; rows it returns `false` for are dropped).
fn edit_imu(flight: &Path, mut edit: impl FnMut(&mut [f64]) -> bool) {
    let path = flight.join("imu.csv");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut lines = text.lines();
    let mut out = format!("{}\n", lines.next().unwrap());
    for line in lines {
        let mut v: Vec<f64> = line.split(',').map(|x| x.parse().unwrap()).collect();
        if edit(&mut v) {
            let fields: Vec<String> = v.iter().map(|x| format!("{x:e}")).collect();
            out.push_str(&fields.join(","));
            out.push('\n');
        }
    }
    std::fs::write(&path, out).unwrap();
}

/// #13's "doubt it, report it, recover" where the sensors fail: the
/// realistic 30 km nadir balloon (10 s) with its gyro turned 3 deg in
/// 20 ms (four samples of 150 deg/s more about the IMU's x axis, at 2 s),
/// with its accelerometer shocked (watched, and not: a velocity 300 m/s
/// off; and 9 m/s^2 off for 19 s of a 20 s flight, which the map offset's
/// restart catches), with its IMU silent for 2 s (from 2 s), with a log
/// that ends at 5 s, with samples no sensor measures, and with unreadable
/// images; the glitch (watched, and not), the gap and the short log also
/// with `--filter fixes`; a 30 deg glitch, undone, with both.
/// Before the navigator doubted a gyro's jumps and a run of frames whose
/// matches did not agree, such a turn left it searching 3 deg from the
/// landmarks for the rest of the flight (the full 60 s flight turned 5 deg:
/// 21 of 121 frames fixed, all before it; `scripts/bench_faults.sh`).
#[test]
fn recovers_from_sensor_faults_and_bad_images() {
    let dir = tempfile::tempdir().unwrap();
    let (db, flight) = realistic_flight(dir.path(), "sierra-balloon-nadir", 300.0, "10");
    // Navigates a copy of the flight `from` changed by `change`: (report,
    // rows, worst fix m, log, evaluation).
    let run_changed_from = |from: &Path, name: &str, change: &dyn Fn(&Path), extra: &[&str]| {
        let copy = dir.path().join(name);
        copy_flight(from, &copy);
        change(&copy);
        let s = NavFixture { dir: tempfile::tempdir().unwrap(), db: db.clone(), flight: copy };
        let poses = s.root().join("poses.csv");
        let o = navigate(&s, &poses, extra);
        assert!(o.status.success(), "{name}: navigate failed: {}", stderr(&o));
        let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let e = evaluate(&s, &poses);
        let worst = e["runs"][0]["fix_errors"]["pos_m"]["max"].as_f64().unwrap();
        let r = rows(&poses);
        println!("{name}: {r:?}, worst fix {worst:.1} m, doubted {}", report["doubted_frames"]);
        (report, r, worst, stderr(&o), e)
    };
    let run_changed = |name: &str, change: &dyn Fn(&Path), extra: &[&str]| {
        let (report, r, worst, log, _) = run_changed_from(&flight, name, change, extra);
        (report, r, worst, log)
    };
    let fixed_after = |r: &[(f64, String, u32)], t: f64| r.iter().filter(|x| x.0 > t && x.1 == "fix").count();

    let glitch = |f: &Path| {
        edit_imu(f, |v| {
            if v[0] > 2.0 && v[0] <= 2.02 + 1e-9 {
                v[1] += 3f64.to_radians() / 0.02;
            }
            true
        })
    };
    // The jump from one gyro sample to the next is doubted at once: the
    // next frame searches wide enough, and every frame fixes.
    let (report, r, worst, _) = run_changed("glitch", &glitch, &[]);
    assert_eq!(report["gyro_jumps"], 1, "{report}");
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");
    // Not watched for (`--gyro-max-jump 0`): the frames whose matches do not
    // agree doubt the pose.
    let (report, r, worst, _) = run_changed("glitch-unwatched", &glitch, &["--gyro-max-jump", "0"]);
    assert_eq!(report["gyro_jumps"], 0, "{report}");
    let missed = r.iter().filter(|x| x.0 > 2.0 && x.1 != "fix").count();
    assert!(missed >= 4, "the turn costs frames: {r:?}");
    assert!(report["doubted_frames"].as_u64().unwrap() >= 1, "{report}");
    assert!(r.iter().rev().take(4).all(|x| x.1 == "fix"), "fixed again by the end: {r:?}");
    assert!(worst < 250.0, "no fix a navigator should not trust: {worst:.1} m");
    // Without the inertial filter (`--filter fixes`, the navigator before
    // it), the jump is doubted as well, and every frame fixes; not watched
    // for, the run of misses doubts the pose, and an acquisition found away
    // from it is confirmed around its own pose (before, neither: every
    // frame after the turn was lost).
    let (report, r, worst, _) = run_changed("glitch-fixes", &glitch, &["--filter", "fixes"]);
    assert_eq!(report["gyro_jumps"], 1, "{report}");
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");
    let (report, r, worst, _) =
        run_changed("glitch-fixes-unwatched", &glitch, &["--filter", "fixes", "--gyro-max-jump", "0"]);
    assert!(report["doubted_frames"].as_u64().unwrap() >= 1, "{report}");
    assert!(r.iter().rev().take(4).all(|x| x.1 == "fix"), "fixed again by the end: {r:?}");
    assert!(worst < 250.0, "{worst:.1} m");
    // A 30 deg glitch, beyond the jump's 10 deg doubt: the frame after it
    // does not fix around the turned prediction, and is searched again with
    // the jump undone, where the camera still looks; that fix restarts the
    // pose. Before, the 60 s oblique balloon so turned fixed 21 of 121
    // frames, none after it, with either filter (`scripts/bench_faults.sh`).
    let glitch30 = |f: &Path| {
        edit_imu(f, |v| {
            if v[0] > 2.0 && v[0] <= 2.02 + 1e-9 {
                v[1] += 30f64.to_radians() / 0.02;
            }
            true
        })
    };
    for (name, extra) in [("glitch30", &[][..]), ("glitch30-fixes", &["--filter", "fixes"][..])] {
        let (report, r, worst, log) = run_changed(name, &glitch30, extra);
        assert_eq!(report["gyro_jumps"], 1, "{name}: {report}");
        assert_eq!(report["gyro_jumps_undone"], 1, "{name}: {report}");
        assert!(log.contains("taken for a glitch"), "{name}: {log}");
        assert!(r.iter().all(|x| x.1 == "fix"), "{name}: {r:?}");
        assert!(worst < 250.0, "{name}: {worst:.1} m");
    }

    // The accelerometer 100 m/s^2 off for 1 s (a shock that saturated it):
    // the velocity it adds is doubted, so the fixes after correct it.
    let shock = |f: &Path| {
        edit_imu(f, |v| {
            if v[0] > 2.0 && v[0] <= 3.0 + 1e-9 {
                v[4] += 100.0;
            }
            true
        })
    };
    let (report, r, worst, log) = run_changed("shock", &shock, &[]);
    assert_eq!(report["accel_jumps"], 1, "{report}");
    assert!(log.contains("1 accelerometer jump(s)"), "{log}");
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    // Its worst fix as without the shock (58.3 m when written); not
    // doubted (`--accel-max-jump 0`), the velocity 100 m/s off is trusted
    // and the fixes drift (204.9 m).
    assert!(worst < 110.0, "{worst:.1} m");
    let (report, _, worst_off, _) = run_changed("shock-unwatched", &shock, &["--accel-max-jump", "0"]);
    assert_eq!(report["accel_jumps"], 0, "{report}");
    assert!(worst_off > worst + 20.0, "{worst_off:.1} m not doubted, {worst:.1} m doubted");
    // Unwatched, 300 m/s^2 for 1 s leaves the velocity 300 m/s off and sure
    // of itself: the fixes are lost, and the restart after the run of misses
    // doubts the velocity by how far the prediction had drifted, so the
    // fixes after it find the velocity.
    let big = |f: &Path| {
        edit_imu(f, |v| {
            if v[0] > 2.0 && v[0] <= 3.0 + 1e-9 {
                v[4] += 300.0;
            }
            true
        })
    };
    // Seen with the focal length not carried by the filter
    // (`--no-inertial-focal`), whose run of misses has always come: with
    // it carried, whether one comes depends on how the shock's velocity
    // shares itself with the lens (15 of 21 fixed and 3 frames doubted
    // when written; 20 of 21 and none when the search counted the lens's
    // share of the range apart), and the recovery is checked alone.
    let (report, r, worst, _) =
        run_changed("big-shock-unwatched", &big, &["--accel-max-jump", "0", "--no-inertial-focal"]);
    assert!(report["doubted_frames"].as_u64().unwrap() >= 1, "{report}");
    // Before, the restart kept the velocity as sure as it was: two fixes,
    // then lost again to the end (6.5 and 7 s of 10).
    assert!(r.iter().rev().take(6).all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");
    let (_, r, worst, _) = run_changed("big-shock-unwatched-focal", &big, &["--accel-max-jump", "0"]);
    assert!(r.iter().rev().take(6).all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");

    // An accelerometer 9 m/s^2 off from 1 s to the end of a 20 s flight,
    // a step under the jump limit (10 m/s^2): trusted, the velocity goes
    // wrong, and through a narrow nadir view the fixes' shift is taken for
    // the map's offset. Once that offset is beyond its prior, it is
    // restarted (the pose the images see kept, the velocity doubted), and
    // the fixes after it find the velocity. When written: restarted at
    // 15.5 s, worst fix 172 m, 140 m at the end; never restarted (the
    // threshold infinite, rebuilt), the fixes drifted to 317 m by the end.
    let flight20 = realistic_sim(dir.path(), "sierra-balloon-nadir", 300.0, "20", "flight20");
    let biased = |f: &Path| {
        edit_imu(f, |v| {
            if v[0] > 1.0 {
                v[4] += 9.0;
            }
            true
        })
    };
    let (report, r, worst, log, e) = run_changed_from(&flight20, "accel-biased", &biased, &[]);
    assert_eq!(report["accel_jumps"], 0, "{report}");
    assert!(report["map_doubts"].as_u64().unwrap() >= 1, "{report}");
    assert!(log.contains("found the map offset beyond its prior"), "{log}");
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");
    let last =
        e["runs"][0]["per_frame"].as_array().unwrap().last().unwrap()["error"]["pos_m"].as_f64().unwrap();
    assert!(last < 220.0, "the fixes drift on: {last:.1} m at the end");

    let gap = |f: &Path| edit_imu(f, |v| !(v[0] > 2.0 && v[0] < 4.0));
    let (report, r, worst, log) = run_changed("gap", &gap, &[]);
    let gaps = report["imu_gaps"].as_array().unwrap();
    assert_eq!(gaps.len(), 1, "{report}");
    let (from, to) = (gaps[0]["from_t"].as_f64().unwrap(), gaps[0]["to_t"].as_f64().unwrap());
    assert!((from - 2.0).abs() < 1e-6 && (to - 4.0).abs() < 1e-6, "{gaps:?}");
    assert!(log.contains("imu.csv: 1 gap"), "{log}");
    // Crossed on rates interpolated between the samples either side, their
    // error a state that walks and the fixes learn: the frames in the gap
    // search wide enough and fix (the sample after it taken as the mean rate through it lost
    // them, until the misses doubted the pose).
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert_eq!(report["doubted_frames"], 0, "{report}");
    assert!(fixed_after(&r, 4.0) >= 8, "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");
    // Without the inertial filter, the attitude is doubted through the gap
    // as a rate walking from its start (before, the frames after the gap
    // searched a degree from the landmarks, and one accepted fix was 3 km
    // off).
    let (_, r, worst, _) = run_changed("gap-fixes", &gap, &["--filter", "fixes"]);
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");

    // A log that ends before the images (a recorder full): after its last
    // sample the gyro's mean over its last second is carried on, its error
    // learnt from the fixes (before the last stop, every frame after it was
    // lost).
    let short = |f: &Path| edit_imu(f, |v| v[0] <= 5.0);
    let (report, r, worst, log) = run_changed("short-log", &short, &[]);
    let uncovered = report["imu_uncovered"].as_array().unwrap();
    assert_eq!(uncovered.len(), 1, "{report}");
    assert!((uncovered[0]["from_t"].as_f64().unwrap() - 5.0).abs() < 1e-6, "{uncovered:?}");
    assert!(log.contains("imu.csv has no sample from t 5.000 to 10.000 s"), "{log}");
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");
    // Likewise without the inertial filter, the attitude doubted from the
    // log's end (before, every frame after it was lost), the body's rate
    // measured there by the fixes (before, the full 60 s flight with a log
    // that ended at 5 s lost 49 frames from 25 s on;
    // `scripts/bench_faults.sh`).
    let (_, r, worst, log) = run_changed("short-log-fixes", &short, &["--filter", "fixes"]);
    assert!(log.contains("after the IMU log's end, the last two fixes measure the body's rate"), "{log}");
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");

    // Samples no sensor measures (a flipped bit in an exponent): left out
    // of the log, reported; the flight navigates as without them. Trusted,
    // one such sample turns the filter's state to NaN.
    let corrupt = |f: &Path| {
        let mut k = 0;
        edit_imu(f, |v| {
            k += 1;
            match k {
                400 => v[2] = 1e300,
                401 => v[5] = -1e300,
                900 => v[6] = 3e4,
                _ => {}
            }
            true
        })
    };
    let (report, r, worst, log) = run_changed("corrupt", &corrupt, &[]);
    assert_eq!(report["imu_out_of_range"]["samples"], 3, "{report}");
    assert!(log.contains("imu.csv: 3 sample(s) beyond the sensors' range"), "{log}");
    assert!(r.iter().all(|x| x.1 == "fix"), "{r:?}");
    assert_eq!(
        (report["gyro_jumps"].as_u64(), report["accel_jumps"].as_u64()),
        (Some(0), Some(0)),
        "{report}"
    );
    assert!(worst < 250.0, "{worst:.1} m");
    // Let through (the ranges opened), they turn the state to NaN: an error
    // that says when, and nothing written.
    let copy = dir.path().join("corrupt-trusted");
    copy_flight(&flight, &copy);
    corrupt(&copy);
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db: db.clone(), flight: copy };
    let out = s.root().join("poses.csv");
    let o = navigate(&s, &out, &["--gyro-range", "1e308", "--accel-range", "1e308"]);
    assert!(!o.status.success(), "NaN poses written");
    let e = stderr(&o);
    assert!(e.lines().any(|l| l.starts_with("error:") && l.contains("is not finite")), "{e}");
    assert!(!out.exists() && !out.with_file_name("covariance.csv").exists());

    // One image truncated, one of another size: their frames are carried
    // (propagated, no match), reported, and the others navigate as before.
    let bad_images = |f: &Path| {
        let frames = std::fs::read_to_string(f.join("frames.csv")).unwrap();
        let images: Vec<&str> = frames.lines().skip(1).map(|l| l.split_once(',').unwrap().1).collect();
        let first = f.join(images[3]);
        let bytes = std::fs::read(&first).unwrap();
        std::fs::write(&first, &bytes[..bytes.len() / 3]).unwrap();
        image::GrayImage::new(64, 48).save(f.join(images[7])).unwrap();
    };
    let (report, r, worst, log) = run_changed("bad-images", &bad_images, &[]);
    let skipped = report["skipped_images"].as_array().unwrap();
    assert_eq!(skipped.len(), 2, "{report}");
    assert!(skipped[0]["image"].as_str().unwrap().ends_with("000003.png"), "{skipped:?}");
    assert!(skipped[1]["reason"].as_str().unwrap().contains("64x48 pixels"), "{skipped:?}");
    assert!(log.contains("000003.png") && log.contains("2 of 21 frames had no usable image"), "{log}");
    for k in [3, 7] {
        assert_eq!((r[k].1.as_str(), r[k].2), ("propagated", 0), "{r:?}");
    }
    assert!(r.iter().filter(|x| x.1 == "fix").count() >= 17, "{r:?}");
    assert!(worst < 250.0, "{worst:.1} m");

    // No readable image at all: an error that names the first, nothing written.
    let copy = dir.path().join("no-images");
    copy_flight(&flight, &copy);
    for e in std::fs::read_dir(copy.join("images")).unwrap() {
        std::fs::write(e.unwrap().path(), b"not a png").unwrap();
    }
    let out = dir.path().join("none.csv");
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db: db.clone(), flight: copy };
    let o = navigate(&s, &out, &[]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.lines().any(|l| l.starts_with("error:") && l.contains("000000.png")), "{e}");
    assert!(!out.exists() && !out.with_file_name("matches.csv").exists());
}

/// A 30 deg gyro glitch while the camera sees through a hole in the cloud
/// (a centred box of 0.4 of the image's sides, from 1 s of the realistic
/// 30 km nadir balloon): the frame after it finds its landmarks with the
/// jump undone, and the inertial filter takes the undo. Before, that fix
/// restarted the filter's pose from the narrow view's own, as an
/// acquisition's: here 351.5 m off; on the 60 s flight with the glitch at
/// 25 s, 1059 m off (3.5 sigmas; `scripts/bench_faults.sh` on
/// `scripts/bench_narrow.sh`'s staging).
#[test]
fn a_glitch_under_a_hole_in_the_cloud_is_undone_in_the_filter() {
    let dir = tempfile::tempdir().unwrap();
    let (db, flight) = realistic_flight(dir.path(), "sierra-balloon-nadir", 100.0, "8");
    grey_but_a_box(&flight, 1.0..f64::INFINITY, 0.4);
    let (s, poses) = a_glitch_undone(db, flight, 3.0);
    let e = evaluate(&s, &poses);
    let per_frame = e["runs"][0]["per_frame"].as_array().unwrap();
    let worst = per_frame.iter().map(|f| f["error"]["pos_m"].as_f64().unwrap()).fold(0.0, f64::max);
    println!("{:?}, worst {worst:.1} m", rows(&poses));
    assert!(worst < 150.0, "worst error {worst:.1} m");
}

/// `flight` with its gyro turned 30 deg about the IMU's x axis in 20 ms
/// from `at_s`, navigated on `db`: the run succeeds, the report counts one
/// jump undone and the log says the filter took it. Its fixture and poses.
fn a_glitch_undone(db: PathBuf, flight: PathBuf, at_s: f64) -> (NavFixture, PathBuf) {
    edit_imu(&flight, |v| {
        if v[0] > at_s && v[0] <= at_s + 0.02 + 1e-9 {
            v[1] += 30f64.to_radians() / 0.02;
        }
        true
    });
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db, flight };
    let poses = s.root().join("poses.csv");
    let o = navigate(&s, &poses, &[]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let log = stderr(&o);
    assert_eq!(report["gyro_jumps_undone"], 1, "{report}");
    assert!(log.contains("the filter takes the undo"), "{log}");
    (s, poses)
}

/// A glitch undone only after a cloud: the 30 km nadir balloon's images
/// grey from 1 s to 13 s, its gyro turned 30 deg in 20 ms at 2 s. The
/// first frame after the cloud finds its landmarks with the jump undone,
/// the guess moved back by what the force, turned by it for 11 s, had
/// added to the position (310 m), and the filter takes the undo: fixes
/// from 13 s, within 47 m. Before, the jump was undone only within 5 s of
/// it (the turned force had by then moved the guess beyond its search):
/// here the first two frames after the cloud did not fix, 249 and 240 m
/// off, the next fixes 94-103 m; on `scripts/bench_narrow.sh`'s holes
/// with the glitch 10 s into the hole four runs of 35 never fixed again,
/// drifting to 358-3016 m.
#[test]
fn a_glitch_in_a_cloud_is_undone_when_the_cloud_ends() {
    let dir = tempfile::tempdir().unwrap();
    let (db, flight) = realistic_flight(dir.path(), "sierra-balloon-nadir", 100.0, "18");
    assert_eq!(grey_but_a_box(&flight, 1.0..13.0, 0.0), 24);
    let (s, poses) = a_glitch_undone(db, flight, 2.0);
    let r = rows(&poses);
    println!("{r:?}");
    let after: Vec<_> = r.iter().filter(|x| x.0 >= 13.0).collect();
    assert_eq!(after.first().map(|x| x.1.as_str()), Some("fix"), "{r:?}");
    let fixes = after.iter().filter(|x| x.1 == "fix").count();
    assert!(fixes * 10 >= after.len() * 8, "{fixes} fixes of {} frames after the cloud", after.len());
    let e = evaluate(&s, &poses);
    let per_frame = e["runs"][0]["per_frame"].as_array().unwrap();
    let worst_after = per_frame
        .iter()
        .filter(|f| f["t"].as_f64().unwrap() >= 13.0)
        .map(|f| f["error"]["pos_m"].as_f64().unwrap())
        .fold(0.0, f64::max);
    assert!(worst_after < 100.0, "worst error from 13 s: {worst_after:.1} m");
}

/// A long hole in the cloud (#13, recovery): the 30 km nadir balloon
/// rendered with seed 103, its images grey from 1 s to 24 s but for a
/// centred box of 0.3 of their sides. Through the hole the box's few
/// matches disagree frame after frame. Counted as misses (`--miss-min-cells
/// 0`, the rule before stop 57), each after the fourth doubled the pose's
/// doubt until its search was a wide acquisition that did not stand when
/// the hole ended: no fix from 24 s to the flight's end at 32 s, the pose
/// 121-182 m off and drifting, 34 frames doubted (stop 58; since stop 59
/// takes near-duplicate landmarks last, 25 frames doubted and 9 of the 17
/// frames after the hole fixed, 235 m off at worst). A narrow view's
/// disagreeing matches are no miss by default: no frame is doubted, and
/// every frame after the hole fixes, within 86 m (the release build, stop
/// 60; 98 m in stop 59's, 141 m in stop 58's, the default database's
/// finest level filled; 109 m before). Since stop 60 correlates 600
/// landmarks a frame, the box's matches agree and neither rule doubts the
/// pose; the old rule's run keeps 450 a frame (`--max-landmarks 450`),
/// where they disagree.
#[test]
fn a_long_hole_in_the_cloud_does_not_doubt_the_pose_out_of_its_search() {
    let dir = tempfile::tempdir().unwrap();
    let db = realistic_db(dir.path());
    let flight = realistic_sim_with(dir.path(), "sierra-balloon-nadir", "32", "flight", |s| {
        s["init_error"]["horizontal_m"] = serde_json::json!(100.0);
        s["seed"] = serde_json::json!(103);
    });
    assert_eq!(grey_but_a_box(&flight, 1.0..24.0, 0.3), 46);
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db, flight };
    let after_hole = |name: &str, extra: &[&str]| {
        let poses = s.root().join(name);
        let o = navigate(&s, &poses, extra);
        assert!(o.status.success(), "navigate failed: {}", stderr(&o));
        let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        let fixes = rows(&poses).iter().filter(|x| x.0 >= 24.0 && x.1 == "fix").count();
        let e = evaluate(&s, &poses);
        let worst = e["runs"][0]["per_frame"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|f| f["t"].as_f64().unwrap() >= 24.0)
            .map(|f| f["error"]["pos_m"].as_f64().unwrap())
            .fold(0.0, f64::max);
        (report["doubted_frames"].as_u64().unwrap(), fixes, worst)
    };
    // 17 frames from 24 s to 32 s.
    let (doubted, fixes, worst) = after_hole("poses.csv", &[]);
    assert_eq!((doubted, fixes), (0, 17), "worst {worst:.1} m");
    assert!(worst < 150.0, "worst error after the hole: {worst:.1} m");
    let (doubted_old, fixes_old, worst_old) =
        after_hole("every-miss.csv", &["--miss-min-cells", "0", "--max-landmarks", "450"]);
    println!("--miss-min-cells 0 --max-landmarks 450: {doubted_old} doubted, {fixes_old} fixes after the hole, worst {worst_old:.1} m; default: worst {worst:.1} m");
    // The old rule doubts the pose and loses frames after the hole.
    assert!(
        doubted_old > 0 && fixes_old <= 12 && worst_old > worst,
        "{doubted_old} frames doubted, {fixes_old} fixes after the hole, worst {worst_old:.1} m \
         (by default {worst:.1} m)"
    );
}

/// A guess whose heading is 30 deg off (turned about the local vertical),
/// told (`--init-sigma-deg 21`): the acquisition searches each tile at
/// headings 10 deg apart out to 2.5 sigmas, and fixes within the first
/// frames. Before, a heading error beyond what one search stands (5 deg)
/// was never acquired: the 60 s realistic nadir balloon so turned fixed 0
/// of 121 frames, 3.2 km off at worst (15 deg likewise).
#[test]
fn a_guess_whose_heading_is_off_is_acquired() {
    let dir = tempfile::tempdir().unwrap();
    let (db, flight) = realistic_flight(dir.path(), "sierra-balloon-nadir", 300.0, "6");
    edit_init(&flight, |init| {
        let (lat, lon) =
            (init["lat"].as_f64().unwrap().to_radians(), init["lon"].as_f64().unwrap().to_radians());
        let up = [lat.cos() * lon.cos(), lat.cos() * lon.sin(), lat.sin()];
        let h = 30f64.to_radians() / 2.0;
        let r = [h.cos(), h.sin() * up[0], h.sin() * up[1], h.sin() * up[2]];
        let q: Vec<f64> =
            init["q_ecef_cam"].as_array().unwrap().iter().map(|v| v.as_f64().unwrap()).collect();
        // r * q (w, x, y, z): turned about the vertical, in ECEF.
        let turned = [
            r[0] * q[0] - r[1] * q[1] - r[2] * q[2] - r[3] * q[3],
            r[0] * q[1] + r[1] * q[0] + r[2] * q[3] - r[3] * q[2],
            r[0] * q[2] - r[1] * q[3] + r[2] * q[0] + r[3] * q[1],
            r[0] * q[3] + r[1] * q[2] - r[2] * q[1] + r[3] * q[0],
        ];
        init["q_ecef_cam"] = serde_json::json!(turned);
    });
    let s = NavFixture { dir: tempfile::tempdir().unwrap(), db, flight };
    let poses = s.root().join("poses.csv");
    let o = navigate(&s, &poses, &["--init-sigma-deg", "21"]);
    assert!(o.status.success(), "navigate failed: {}", stderr(&o));
    let r = rows(&poses);
    println!("{r:?}");
    let first = r.iter().position(|x| x.1 == "fix");
    assert!(first.is_some_and(|i| i <= 3), "first fix at frame {first:?}: {r:?}");
    assert!(r.iter().filter(|x| x.1 == "fix").count() * 10 >= r.len() * 7, "{r:?}");
    let e = evaluate(&s, &poses);
    let worst = e["runs"][0]["fix_errors"]["pos_m"]["max"].as_f64().unwrap();
    assert!(worst < 150.0, "worst fix {worst:.1} m");
}
