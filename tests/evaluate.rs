//! End to end: `trn evaluate` on a small synthetic flight (a curving descent
//! through 26.5-23.6 km with a turning camera). Poses equal to the truth score
//! zero; poses shifted by a known east/north/up offset and rotated by a known
//! angle score exactly that; missing rows count as lost; plots are written;
//! several runs give the per-segment comparison; bad inputs fail clearly.

mod common;

use std::path::{Path, PathBuf};

use serde_json::Value;
use trn_geodesy::{Enu, Geodetic, LocalFrame};

const N: usize = 40;
const RATE_HZ: f64 = 4.0;

type Quat = [f64; 4];

fn qmul(a: Quat, b: Quat) -> Quat {
    [
        a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3],
        a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2],
        a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1],
        a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0],
    ]
}

fn axis_angle(axis: [f64; 3], angle_rad: f64) -> Quat {
    let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
    let (s, c) = (angle_rad / 2.0).sin_cos();
    [c, s * axis[0] / n, s * axis[1] / n, s * axis[2] / n]
}

#[derive(Clone, Copy)]
struct Pose {
    t: f64,
    p: Geodetic,
    q: Quat,
}

fn frame_t(i: usize) -> f64 {
    i as f64 / RATE_HZ
}

/// The true camera pose: a 20 km-radius turn at 1500 m/s, descending 300 m/s.
fn truth(t: f64) -> Pose {
    let origin = Geodetic::new(35.0, -106.0, 26_500.0);
    let (r, w) = (20_000.0, 0.075);
    let e = LocalFrame::at(origin).to_ecef(Enu::new(r * (w * t).sin(), r * (1.0 - (w * t).cos()), 0.0));
    let p = e.to_geodetic().with_height(26_500.0 - 300.0 * t);
    let q = qmul(axis_angle([0.3, 0.5, 0.8], 1.0 + 0.02 * t), axis_angle([1.0, 0.0, 0.0], 0.1 * t.sin()));
    Pose { t, p, q }
}

fn pose_fields(p: &Pose) -> String {
    format!(
        "{:.6},{:.10},{:.10},{:.4},{:.12},{:.12},{:.12},{:.12}",
        p.t, p.p.lat_deg, p.p.lon_deg, p.p.h_m, p.q[0], p.q[1], p.q[2], p.q[3]
    )
}

/// A flight folder: 40 frames at 4 Hz, truth at 8 Hz.
fn make_flight(dir: &Path) -> PathBuf {
    let f = dir.join("flight");
    std::fs::create_dir_all(f.join("images")).unwrap();
    std::fs::write(
        f.join("camera.json"),
        r#"{"width": 1024, "height": 768, "fx": 1785.0, "fy": 1785.0, "cx": 511.5, "cy": 383.5}"#,
    )
    .unwrap();
    let mut frames = String::from("t,image\n");
    for i in 0..N {
        let name = format!("images/{i:06}.png");
        image::GrayImage::new(2, 2).save(f.join(&name)).unwrap();
        frames += &format!("{:.6},{name}\n", frame_t(i));
    }
    std::fs::write(f.join("frames.csv"), frames).unwrap();
    std::fs::write(f.join("imu.csv"), "t,wx,wy,wz\n").unwrap();
    let p0 = truth(0.0);
    std::fs::write(
        f.join("init.json"),
        format!(
            r#"{{"t": 0.0, "lat": {}, "lon": {}, "h": {}, "q_ecef_cam": [{}, {}, {}, {}]}}"#,
            p0.p.lat_deg, p0.p.lon_deg, p0.p.h_m, p0.q[0], p0.q[1], p0.q[2], p0.q[3]
        ),
    )
    .unwrap();
    let mut t = String::from("t,lat,lon,h,qw,qx,qy,qz\n");
    for k in 0..2 * N {
        t += &(pose_fields(&truth(k as f64 / (2.0 * RATE_HZ))) + "\n");
    }
    std::fs::write(f.join("truth.csv"), t).unwrap();
    f
}

/// poses.csv rows: (frame index, pose, status).
fn write_poses(path: &Path, rows: &[(usize, Pose, &str)]) {
    let mut s = String::from("t,lat,lon,h,qw,qx,qy,qz,status,inliers,matches,ms\n");
    for (i, p, status) in rows {
        s += &format!("{},{status},{},{},{:.2}\n", pose_fields(p), 20 + i % 7, 30 + i % 5, 10.0 + *i as f64);
    }
    std::fs::write(path, s).unwrap();
}

fn truth_rows() -> Vec<(usize, Pose, &'static str)> {
    (0..N).map(|i| (i, truth(frame_t(i)), "fix")).collect()
}

/// Runs `trn evaluate --flight F ARGS --json J`; returns (stdout, JSON).
fn evaluate_ok(dir: &Path, flight: &Path, args: &[&str]) -> (String, Value) {
    let json = dir.join("report.json");
    let mut full = vec!["evaluate", "--flight", flight.to_str().unwrap(), "--json", json.to_str().unwrap()];
    full.extend_from_slice(args);
    let o = common::run(&full);
    assert!(o.status.success(), "evaluate failed: {}", common::stderr(&o));
    let stdout = String::from_utf8(o.stdout).unwrap();
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    (stdout, v)
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

#[test]
fn poses_equal_to_truth_score_zero() {
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    let poses = dir.path().join("poses.csv");
    write_poses(&poses, &truth_rows());
    let (out, v) = evaluate_ok(dir.path(), &flight, &["--poses", poses.to_str().unwrap()]);
    let run = &v["runs"][0];
    assert_eq!(run["label"], "poses");
    assert_eq!(run["status"]["frames"], N);
    assert_eq!(f(&run["status"]["share_fix"]), 1.0);
    let e = &run["fix_errors"];
    assert_eq!(e["n"], N);
    assert!(f(&e["pos_m"]["mean"]) < 1e-3 && f(&e["pos_m"]["max"]) < 1e-3, "{e}");
    assert!(f(&e["att_deg"]["max"]) < 1e-6, "{e}");
    assert!(out.contains("fix 100.0% (40)"), "{out}");
    assert!(out.contains("3D position (m)"), "{out}");
}

#[test]
fn shifted_and_rotated_poses_report_the_offset() {
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    let dq = axis_angle([0.2, -0.7, 0.4], 0.5f64.to_radians());
    let rows: Vec<(usize, Pose, &str)> = truth_rows()
        .into_iter()
        .map(|(i, p, s)| {
            let shifted = LocalFrame::at(p.p).to_ecef(Enu::new(30.0, -40.0, 12.0)).to_geodetic();
            (i, Pose { t: p.t, p: shifted, q: qmul(p.q, dq) }, s)
        })
        .collect();
    let poses = dir.path().join("shifted.csv");
    write_poses(&poses, &rows);
    let (out, v) = evaluate_ok(dir.path(), &flight, &["--poses", poses.to_str().unwrap()]);
    let e = &v["runs"][0]["fix_errors"];
    let d = (30f64 * 30.0 + 40.0 * 40.0 + 12.0 * 12.0).sqrt(); // 51.420 m
    for k in ["mean", "median", "p95", "max", "rms"] {
        assert!((f(&e["pos_m"][k]) - d).abs() < 0.01, "{k}: {e}");
        assert!((f(&e["att_deg"][k]) - 0.5).abs() < 1e-6, "{k}: {e}");
    }
    for (k, want) in [30.0, -40.0, 12.0].into_iter().enumerate() {
        assert!((f(&e["enu_mean_m"][k]) - want).abs() < 0.01, "{e}");
    }
    assert!((f(&e["east_abs_m"]["max"]) - 30.0).abs() < 0.01);
    assert!(out.contains("51.420"), "{out}");
    // Each band sees the same offset.
    for b in v["runs"][0]["bands"].as_array().unwrap() {
        assert!((f(&b["fix_errors"]["pos_m"]["mean"]) - d).abs() < 0.01, "{b}");
    }
}

#[test]
fn missing_rows_count_as_lost() {
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    let mut rows = truth_rows();
    for i in [30, 17, 5] {
        rows.remove(i);
    }
    // A row at no frame's time is ignored, not scored.
    rows.insert(1, (0, truth(0.125), "fix"));
    let poses = dir.path().join("poses.csv");
    write_poses(&poses, &rows);
    let (out, v) = evaluate_ok(dir.path(), &flight, &["--poses", poses.to_str().unwrap()]);
    let run = &v["runs"][0];
    assert_eq!(run["rows_ignored"], 1);
    let s = &run["status"];
    assert_eq!((s["frames"].as_u64(), s["fix"].as_u64(), s["lost"].as_u64()), (Some(40), Some(37), Some(3)));
    assert_eq!(s["missing"], 3);
    assert!((f(&s["share_fix"]) - 37.0 / 40.0).abs() < 1e-12);
    let frames = run["per_frame"].as_array().unwrap();
    for i in [5, 17, 30] {
        assert_eq!(frames[i]["status"], "lost");
        assert_eq!(frames[i]["missing"], true);
    }
    assert!(out.contains("lost 7.5% (3, 3 without a row)"), "{out}");
}

fn png_size(path: &Path) -> (u32, u32) {
    let img = image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let rgb = img.to_rgb8();
    // Something was drawn: a good share of non-white pixels.
    let inked = rgb.pixels().filter(|p| p.0 != [255, 255, 255]).count();
    assert!(inked > (rgb.width() * rgb.height()) as usize / 50, "{} looks blank", path.display());
    (img.width(), img.height())
}

#[test]
fn plots_are_written_as_pngs() {
    use trn_eval::plots::*;
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    let run_dir = dir.path().join("run");
    std::fs::create_dir(&run_dir).unwrap();
    let mut rows: Vec<(usize, Pose, &str)> = truth_rows()
        .into_iter()
        .map(|(i, p, s)| {
            let d = 5.0 * (i as f64 * 0.7).sin();
            let p2 = LocalFrame::at(p.p).to_ecef(Enu::new(d, -d, 2.0 * d)).to_geodetic();
            (i, Pose { p: p2, ..p }, if i % 9 == 4 { "propagated" } else { s })
        })
        .collect();
    rows[20].2 = "lost";
    rows.remove(33);
    write_poses(&run_dir.join("poses.csv"), &rows);
    let mut m = String::from("t,landmark,u,v,pred_u,pred_v,residual_px,inlier\n");
    for i in 0..N {
        for k in 0..12 {
            let r = 0.1 + 0.05 * ((i * 12 + k) % 17) as f64;
            m += &format!("{:.6},{},100,200,100.5,200.5,{r:.4},{}\n", frame_t(i), k, (k < 9) as u8);
        }
    }
    std::fs::write(run_dir.join("matches.csv"), m).unwrap();
    let plots = dir.path().join("plots/nested");
    let poses = run_dir.join("poses.csv");
    let (_, v) = evaluate_ok(
        dir.path(),
        &flight,
        &["--poses", poses.to_str().unwrap(), "--plot-dir", plots.to_str().unwrap()],
    );
    assert_eq!(v["runs"][0]["inlier_residual_px"]["n"], N * 9);
    for (name, size) in [
        (TRAJECTORY_PNG, TRAJECTORY_SIZE),
        (ERROR_TIME_PNG, ERROR_TIME_SIZE),
        (ERROR_HEIGHT_PNG, ERROR_HEIGHT_SIZE),
        (INLIERS_PNG, INLIERS_SIZE),
        (RESIDUALS_PNG, RESIDUALS_SIZE),
    ] {
        assert_eq!(png_size(&plots.join(name)), size, "{name}");
    }
    let names: Vec<String> = std::fs::read_dir(&plots)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert_eq!(names.len(), 5, "temporary files left: {names:?}");
}

#[test]
fn several_runs_compare_fix_share_per_segment() {
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    // 4 Hz: every 4th frame below 25 km propagated. 2 Hz: even frames only,
    // every 4th frame at 25-26 km lost.
    let h = |i: usize| truth(frame_t(i)).p.h_m;
    let fast: Vec<(usize, Pose, &str)> = truth_rows()
        .into_iter()
        .map(|(i, p, _)| (i, p, if h(i) < 25_000.0 && i % 4 == 0 { "propagated" } else { "fix" }))
        .collect();
    let slow: Vec<(usize, Pose, &str)> = truth_rows()
        .into_iter()
        .filter(|(i, _, _)| i % 2 == 0)
        .map(|(i, p, _)| {
            (i, p, if (25_000.0..26_000.0).contains(&h(i)) && i % 4 == 0 { "lost" } else { "fix" })
        })
        .collect();
    let (pf, ps) = (dir.path().join("fast.csv"), dir.path().join("slow.csv"));
    write_poses(&pf, &fast);
    write_poses(&ps, &slow);
    let args = [
        "--poses",
        pf.to_str().unwrap(),
        "--label",
        "4hz-gyro",
        "--poses",
        ps.to_str().unwrap(),
        "--label",
        "2hz-nogyro",
        "--band-m",
        "1000",
    ];
    let (out, v) = evaluate_ok(dir.path(), &flight, &args);
    // Expected cells, counted here from the truth heights.
    let segs = ["26-27 km", "25-26 km", "24-25 km", "23-24 km"];
    let cell = |rows: &[(usize, Pose, &str)], s: usize| {
        let lo = 26_000.0 - 1000.0 * s as f64;
        let inside: Vec<_> = rows.iter().filter(|(i, _, _)| (lo..lo + 1000.0).contains(&h(*i))).collect();
        (inside.iter().filter(|r| r.2 == "fix").count(), inside.len())
    };
    let c = &v["comparison"];
    assert_eq!(c["runs"], serde_json::json!(["4hz-gyro", "2hz-nogyro"]));
    let segments = c["segments"].as_array().unwrap();
    assert_eq!(segments.len(), 4);
    let header = out.lines().position(|l| l.starts_with("segment")).expect("comparison table");
    assert!(out.lines().nth(header).unwrap().contains("4hz-gyro"));
    for (s, label) in segs.iter().enumerate() {
        assert_eq!(segments[s]["label"], *label);
        let line = out.lines().nth(header + 1 + s).unwrap();
        assert!(line.starts_with(label), "{line}");
        for (r, rows) in [&fast, &slow].into_iter().enumerate() {
            let (fix, n) = cell(rows, s);
            let got = &segments[s]["cells"][r];
            assert_eq!(
                (got["fix"].as_u64(), got["rows"].as_u64()),
                (Some(fix as u64), Some(n as u64)),
                "{label}"
            );
            assert!(line.contains(&format!("({fix}/{n})")), "{line}");
        }
    }
    // The 2 Hz run's unprocessed frames are lost in its own report, not in the table.
    let (fix, n) = cell(&slow, 0);
    assert_eq!(fix, n);
    assert_eq!(v["runs"][1]["status"]["missing"], N / 2);
    // Lost 2 Hz frames exist at 25-26 km, propagated 4 Hz ones below 25 km.
    assert!(cell(&slow, 1).0 < cell(&slow, 1).1 && cell(&fast, 2).0 < cell(&fast, 2).1);
}

#[test]
fn several_runs_plot_into_subfolders() {
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    let (a, b) = (dir.path().join("a.csv"), dir.path().join("b.csv"));
    write_poses(&a, &truth_rows());
    write_poses(&b, &truth_rows()[..20]);
    let plots = dir.path().join("plots");
    evaluate_ok(
        dir.path(),
        &flight,
        &[
            "--poses",
            a.to_str().unwrap(),
            "--poses",
            b.to_str().unwrap(),
            "--plot-dir",
            plots.to_str().unwrap(),
        ],
    );
    for run in ["a", "b"] {
        assert!(plots.join(run).join(trn_eval::plots::TRAJECTORY_PNG).is_file());
        // No matches.csv next to the poses: no residual histogram.
        assert!(!plots.join(run).join(trn_eval::plots::RESIDUALS_PNG).exists());
    }
}

/// Runs evaluate, expects failure with one `error:` line holding every needle.
fn fails(args: &[&str], needles: &[&str]) {
    let mut full = vec!["evaluate"];
    full.extend_from_slice(args);
    let o = common::run(&full);
    assert!(!o.status.success(), "succeeded: {args:?}");
    let err = common::stderr(&o);
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "{err}");
    for n in needles {
        assert!(lines[0].contains(n), "{n:?} not in {}", lines[0]);
    }
}

#[test]
fn bad_inputs_fail_naming_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    let fl = flight.to_str().unwrap();
    let poses = dir.path().join("poses.csv");
    write_poses(&poses, &truth_rows());
    let p = poses.to_str().unwrap();

    let garbage = dir.path().join("garbage.csv");
    std::fs::write(
        &garbage,
        "t,lat,lon,h,qw,qx,qy,qz,status,inliers,matches,ms\n0.0,35,-106,abc,1,0,0,0,fix,1,2,3\n",
    )
    .unwrap();
    fails(&["--flight", fl, "--poses", garbage.to_str().unwrap()], &["garbage.csv", "line 2", "\"h\""]);
    std::fs::write(&garbage, "not,a,poses,file\n1,2,3,4\n").unwrap();
    fails(&["--flight", fl, "--poses", garbage.to_str().unwrap()], &["garbage.csv", "missing column"]);
    std::fs::write(
        &garbage,
        "t,lat,lon,h,qw,qx,qy,qz,status,inliers,matches,ms\n0,35,-106,1,1,0,0,0,fixed,1,2,3\n",
    )
    .unwrap();
    fails(&["--flight", fl, "--poses", garbage.to_str().unwrap()], &["garbage.csv", "status \"fixed\""]);
    fails(
        &["--flight", fl, "--poses", dir.path().join("nope.csv").to_str().unwrap()],
        &["nope.csv", "no such file"],
    );
    let bad_matches = dir.path().join("m.csv");
    std::fs::write(&bad_matches, "t,landmark\n").unwrap();
    fails(
        &["--flight", fl, "--poses", p, "--matches", bad_matches.to_str().unwrap()],
        &["m.csv", "missing column"],
    );
    fails(&["--flight", fl, "--poses", p, "--poses", p], &["label", "\"poses\"", "two runs"]);
    fails(&["--flight", fl, "--poses", p, "--poses", p, "--label", "x"], &["--label", "--poses"]);
    fails(&["--flight", fl, "--poses", p, "--band-m", "0"], &["band"]);

    std::fs::remove_file(flight.join("truth.csv")).unwrap();
    fails(&["--flight", fl, "--poses", p], &["truth.csv", "no such file"]);
    fails(
        &["--flight", dir.path().join("none").to_str().unwrap(), "--poses", p],
        &["none", "not a flight folder"],
    );
}

/// A reader that closed its end of the pipe (`trn evaluate ... | head`):
/// the command ends on SIGPIPE, quietly, as other command-line tools do.
/// Before, Rust's ignored SIGPIPE made the first print fail and the
/// process panic ("failed printing to stdout: Broken pipe", exit 101).
#[cfg(unix)]
#[test]
fn a_closed_pipe_ends_the_output_quietly() {
    use std::os::fd::FromRawFd;
    use std::os::unix::process::ExitStatusExt;
    let dir = tempfile::tempdir().unwrap();
    let flight = make_flight(dir.path());
    let poses = dir.path().join("poses.csv");
    write_poses(&poses, &truth_rows());
    // A pipe whose read end is closed before trn starts: its first print
    // meets no reader.
    let mut fds = [0; 2];
    // SAFETY: pipe writes two new descriptors into `fds`.
    assert_eq!(unsafe { libc::pipe(fds.as_mut_ptr()) }, 0);
    // SAFETY: both descriptors are new and owned here alone.
    let (read, write) =
        unsafe { (std::os::fd::OwnedFd::from_raw_fd(fds[0]), std::os::fd::OwnedFd::from_raw_fd(fds[1])) };
    drop(read);
    let o = common::trn()
        .args(["evaluate", "--flight", flight.to_str().unwrap(), "--poses", poses.to_str().unwrap()])
        .stdout(std::process::Stdio::from(write))
        .output()
        .expect("run trn");
    let err = common::stderr(&o);
    assert!(!err.contains("panicked"), "{err}");
    assert_eq!(o.status.signal(), Some(libc::SIGPIPE), "{:?}: {err}", o.status);
}
