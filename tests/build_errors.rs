//! End to end: `trn build` on bad inputs and options. Every failure must be a
//! non-zero exit with one clear `error:` line naming the file or option at
//! fault, and must write nothing: no `--out`, no `.trn-build-*` folder, no other
//! file next to it. Also: Ctrl-C cancels cleanly, and a successful build
//! replaces an existing `--out` atomically.

mod common;

use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};
use std::process::{Output, Stdio};
use std::time::{Duration, Instant};

use gdal::raster::{Buffer, GdalType};
use gdal::spatial_ref::SpatialRef;
use gdal::DriverManager;
use trn_store::LandmarkDb;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The one `error:` line of a failed run.
fn error_line(o: &Output) -> String {
    let err = common::stderr(o);
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "expected exactly one `error:` line, stderr:\n{err}");
    // GDAL's own "ERROR 1: ..." chatter must not bury the message.
    let gdal: Vec<&str> = err.lines().filter(|l| l.starts_with("ERROR ")).collect();
    assert!(gdal.is_empty(), "GDAL error output leaked to stderr:\n{err}");
    lines[0].to_string()
}

/// Runs `trn build ARGS` (which must contain `--out`), expects a failure whose
/// error line holds every one of `needles`, and checks that `dir` holds nothing
/// but `keep` afterwards (and no `--out` unless it is in `keep`). Returns the
/// error line.
fn fails(dir: &Path, keep: &[&Path], args: &[&str], needles: &[&str]) -> String {
    let mut full = vec!["build"];
    full.extend_from_slice(args);
    let o = common::run(&full);
    assert!(!o.status.success(), "trn {full:?} succeeded");
    assert!(o.status.code().is_some_and(|c| c != 0), "trn {full:?}: {:?}", o.status);
    let line = error_line(&o);
    for n in needles {
        assert!(line.contains(n), "error line does not mention {n:?}: {line}");
    }
    let out = args.iter().position(|a| *a == "--out").map(|i| PathBuf::from(args[i + 1])).unwrap();
    if !keep.contains(&out.as_path()) {
        assert!(!out.exists(), "{} was written by a failed build", out.display());
    }
    let left = common::leftovers(dir, keep);
    assert!(left.is_empty(), "failed build left behind: {left:?} ({line})");
    line
}

/// A GeoTIFF written with GDAL: `bands` bands of `T`, `value(col, row)` in each;
/// georeferenced in UTM 13N when `gt` is given, otherwise with neither a
/// geotransform nor a CRS.
fn gtiff<T: GdalType + Copy>(
    path: &Path,
    size: usize,
    bands: usize,
    gt: Option<[f64; 6]>,
    nodata: Option<f64>,
    value: impl Fn(usize, usize) -> T,
) {
    let driver = DriverManager::get_driver_by_name("GTiff").unwrap();
    let mut ds = driver.create_with_band_type::<T, _>(path, size, size, bands).unwrap();
    if let Some(gt) = gt {
        ds.set_geo_transform(&gt).unwrap();
        ds.set_spatial_ref(&SpatialRef::from_epsg(32613).unwrap()).unwrap();
    }
    let data: Vec<T> = (0..size * size).map(|i| value(i % size, i / size)).collect();
    for b in 1..=bands {
        let mut band = ds.rasterband(b).unwrap();
        band.set_no_data_value(nodata).unwrap();
        band.write((0, 0), (size, size), &mut Buffer::new((size, size), data.clone())).unwrap();
    }
}

/// Cheap two-octave value noise, 0..=255 (texture for the big ortho).
fn texture(x: usize, y: usize) -> u8 {
    fn hash(x: usize, y: usize) -> f32 {
        let mut h = (x as u32).wrapping_mul(0x9E37_79B1) ^ (y as u32).wrapping_mul(0x85EB_CA77);
        h ^= h >> 15;
        h = h.wrapping_mul(0x2C1B_3C6D);
        h ^= h >> 12;
        (h & 0xff) as f32
    }
    let octave = |cell: usize| {
        let (cx, cy) = (x / cell, y / cell);
        let (fx, fy) = ((x % cell) as f32 / cell as f32, (y % cell) as f32 / cell as f32);
        let top = hash(cx, cy) * (1.0 - fx) + hash(cx + 1, cy) * fx;
        let bottom = hash(cx, cy + 1) * (1.0 - fx) + hash(cx + 1, cy + 1) * fx;
        top * (1.0 - fy) + bottom * fy
    };
    (0.7 * octave(24) + 0.3 * octave(5)) as u8
}

/// UTM 13N geotransform of `common::synth(.., east = 440000, ..)`'s ortho at `gsd`.
fn synth_gt(gsd: f64) -> [f64; 6] {
    [440000.0, gsd, 0.0, 4460000.0, 0.0, -gsd]
}

#[test]
fn missing_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 64, 8.0, 440000.0, 1);
    let out = d.join("db.gpkg");
    let nope = d.join("no-such-ortho.tif");
    let e = fails(
        d,
        &[ortho.as_path(), dem.as_path()],
        &["--ortho", s(&nope), "--dem", s(&dem), "--out", s(&out), "--dem-vertical", "ellipsoid"],
        &[s(&nope), "no such file"],
    );
    eprintln!("{e}");
    let nope = d.join("no-such-dem.tif");
    let e = fails(
        d,
        &[ortho.as_path(), dem.as_path()],
        &["--ortho", s(&ortho), "--dem", s(&nope), "--out", s(&out), "--dem-vertical", "ellipsoid"],
        &[s(&nope), "no such file"],
    );
    eprintln!("{e}");
}

#[test]
fn corrupt_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 64, 8.0, 440000.0, 1);
    let out = d.join("db.gpkg");
    let text = d.join("notes.tif");
    std::fs::write(&text, "this is not a GeoTIFF\n").unwrap();
    // Header and directory intact, pixel data cut off.
    let bytes = std::fs::read(&ortho).unwrap();
    let cut_ortho = d.join("cut-ortho.tif");
    std::fs::write(&cut_ortho, &bytes[..bytes.len() / 3]).unwrap();
    let bytes = std::fs::read(&dem).unwrap();
    let cut_dem = d.join("cut-dem.tif");
    std::fs::write(&cut_dem, &bytes[..bytes.len() / 2]).unwrap();
    let keep = [&ortho, &dem, &text, &cut_ortho, &cut_dem].map(|p| p.as_path());
    for (o, m) in [(&text, &dem), (&cut_ortho, &dem), (&ortho, &text), (&ortho, &cut_dem)] {
        let bad = if o == &ortho { m } else { o };
        let e = fails(
            d,
            &keep,
            &["--ortho", s(o), "--dem", s(m), "--out", s(&out), "--dem-vertical", "ellipsoid"],
            &[s(bad)],
        );
        eprintln!("{e}");
    }
}

#[test]
fn inputs_without_georeferencing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 64, 8.0, 440000.0, 1);
    let out = d.join("db.gpkg");
    let plain_ortho = d.join("plain-ortho.tif");
    gtiff::<u8>(&plain_ortho, 64, 1, None, None, texture);
    let plain_dem = d.join("plain-dem.tif");
    gtiff::<f32>(&plain_dem, 64, 1, None, None, |x, y| 1500.0 + (x + y) as f32);
    let keep = [&ortho, &dem, &plain_ortho, &plain_dem].map(|p| p.as_path());
    for (o, m, bad) in [(&plain_ortho, &dem, &plain_ortho), (&ortho, &plain_dem, &plain_dem)] {
        let e = fails(
            d,
            &keep,
            &["--ortho", s(o), "--dem", s(m), "--out", s(&out), "--dem-vertical", "ellipsoid"],
            &[s(bad), "georeferencing"],
        );
        eprintln!("{e}");
    }
}

#[test]
fn ortho_and_dem_that_do_not_overlap() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho_a, dem_a) = common::synth(d, 64, 8.0, 440000.0, 1);
    let (ortho_b, dem_b) = common::synth(d, 64, 8.0, 600000.0, 2);
    let out = d.join("db.gpkg");
    let e = fails(
        d,
        &[&ortho_a, &dem_a, &ortho_b, &dem_b].map(|p| p.as_path()),
        &["--ortho", s(&ortho_a), "--dem", s(&dem_b), "--out", s(&out), "--dem-vertical", "ellipsoid"],
        &["do not overlap", "--ortho", "--dem"],
    );
    eprintln!("{e}");
}

#[test]
fn dem_vertical_datum_unknown_or_its_geoid_missing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ortho = common::sample("rmnp-rgb.tif", d);
    let dem = common::sample("rmnp-dem.tif", d);
    let out = d.join("db.gpkg");
    let keep = [ortho.as_path(), dem.as_path()];
    let base = ["--ortho", s(&ortho), "--dem", s(&dem), "--out", s(&out)];
    let e = fails(d, &keep, &base, &[s(&dem), "--dem-vertical"]);
    eprintln!("{e}");
    let e = fails(d, &keep, &[&base[..], &["--dem-vertical", "geoid"]].concat(), &["--geoid"]);
    eprintln!("{e}");
    let e = fails(
        d,
        &keep,
        &[&base[..], &["--dem-vertical", "geoid", "--geoid", "/nonexistent.gtx"]].concat(),
        &["/nonexistent.gtx", "geoid"],
    );
    eprintln!("{e}");
}

#[test]
fn all_nodata_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 256, 2.0, 440000.0, 1);
    let out = d.join("db.gpkg");
    let empty_ortho = d.join("empty-ortho.tif");
    gtiff::<u8>(&empty_ortho, 256, 1, Some(synth_gt(2.0)), Some(0.0), |_, _| 0);
    let empty_dem = d.join("empty-dem.tif");
    gtiff::<f32>(&empty_dem, 64, 1, Some(synth_gt(30.0)), Some(-9999.0), |_, _| -9999.0);
    let keep = [&ortho, &dem, &empty_ortho, &empty_dem].map(|p| p.as_path());
    for (o, m, bad) in [(&empty_ortho, &dem, &empty_ortho), (&ortho, &empty_dem, &empty_dem)] {
        let e = fails(
            d,
            &keep,
            &["--ortho", s(o), "--dem", s(m), "--out", s(&out), "--dem-vertical", "ellipsoid"],
            &[s(bad), "nodata"],
        );
        eprintln!("{e}");
    }
}

#[test]
fn ortho_bands_needed_or_wrong() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let ortho = common::sample("L7_ETMs.tif", d);
    let dem = common::sample("olinda_dem_utm25s.tif", d);
    let out = d.join("db.gpkg");
    let keep = [ortho.as_path(), dem.as_path()];
    let base = ["--ortho", s(&ortho), "--dem", s(&dem), "--out", s(&out), "--dem-vertical", "egm96"];
    let e = fails(d, &keep, &base, &[s(&ortho), "--ortho-bands", "6 bands"]);
    eprintln!("{e}");
    let e = fails(d, &keep, &[&base[..], &["--ortho-bands", "9"]].concat(), &["--ortho-bands", "9"]);
    eprintln!("{e}");
    let e = fails(d, &keep, &[&base[..], &["--ortho-bands", "1,2"]].concat(), &["--ortho-bands"]);
    eprintln!("{e}");
}

#[test]
fn bad_output_folder_and_numeric_options() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 64, 8.0, 440000.0, 1);
    let keep = [ortho.as_path(), dem.as_path()];
    let out = d.join("no-such-folder").join("db.gpkg");
    let base = ["--ortho", s(&ortho), "--dem", s(&dem), "--dem-vertical", "ellipsoid"];
    let e = fails(d, &keep, &[&base[..], &["--out", s(&out)]].concat(), &["--out", "no-such-folder"]);
    eprintln!("{e}");
    // --out naming a folder.
    let sub = d.join("a-folder");
    std::fs::create_dir(&sub).unwrap();
    let keep_sub = [ortho.as_path(), dem.as_path(), sub.as_path()];
    let e = fails(d, &keep_sub, &[&base[..], &["--out", s(&sub)]].concat(), &["--out"]);
    assert!(std::fs::read_dir(&sub).unwrap().next().is_none(), "wrote into the --out folder");
    eprintln!("{e}");
    let out = d.join("db.gpkg");
    for (option, value) in [
        ("--template-size", "2"),
        ("--template-size", "4096"),
        ("--spacing", "1"),
        ("--per-cell", "0"),
        ("--fill-share", "1.5"),
        ("--fill-share", "nan"),
        ("--levels", "0"),
        ("--levels", "13"),
        ("--base-gsd", "0"),
        // The synthetic ortho has 8 m pixels: a 1 m level 0 would only upsample.
        ("--base-gsd", "1"),
        ("--max-second-peak", "1.5"),
        ("--max-relief", "-1"),
        ("--max-relief", "nan"),
        ("--min-template-size", "4"),
        ("--min-template-size", "64"),
        ("--max-hidden", "-0.1"),
        ("--max-hidden", "1.5"),
        ("--min-contrast", "nan"),
        ("--min-shi-tomasi", "-1"),
        ("--search-radius", "0"),
        ("--threads", "0"),
        ("--sun", "250"),
        ("--sun", "250,0"),
        ("--sun", "250,95"),
        ("--sun", "east,25"),
        ("--sun", "250,25,1.5"),
        ("--sun", "400,25"),
        ("--max-shading", "1.5"),
        ("--max-shading", "-0.1"),
    ] {
        let flag = format!("{option}={value}");
        let args = [&base[..], &["--out", s(&out), &flag]].concat();
        let e = fails(d, &keep_sub, &args, &[option]);
        eprintln!("{e}");
    }
}

/// The mission (`--camera`, `--altitude`) and the coverage plan are checked
/// before any work: a bad one names its file or option and leaves nothing.
#[test]
fn bad_mission_and_coverage_plan() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 64, 8.0, 440000.0, 1);
    let out = d.join("db.gpkg");
    let camera = d.join("camera.json");
    std::fs::write(&camera, common::CAMERA_640_JSON).unwrap();
    let bad_plan = d.join("plan.json");
    std::fs::write(&bad_plan, "{\"camera\": {\"width\": 640}}").unwrap();
    let not_json = d.join("not-a-camera.json");
    std::fs::write(&not_json, "width: 640").unwrap();
    let keep = [ortho.as_path(), dem.as_path(), camera.as_path(), bad_plan.as_path(), not_json.as_path()];
    let base = ["--ortho", s(&ortho), "--dem", s(&dem), "--dem-vertical", "ellipsoid", "--out", s(&out)];
    let cases: [(Vec<&str>, Vec<&str>); 6] = [
        (vec!["--camera", s(&camera), "--altitude", "9000..3000"], vec!["--altitude"]),
        (vec!["--camera", s(&camera), "--altitude", "3 km"], vec!["--altitude"]),
        (vec!["--camera", s(&camera), "--altitude", "0..3000"], vec!["--altitude"]),
        (vec!["--camera", "no-such-camera.json", "--altitude", "1000..3000"], vec!["no-such-camera.json"]),
        (vec!["--camera", s(&not_json), "--altitude", "1000..3000"], vec!["not-a-camera.json"]),
        (vec!["--coverage-plan", s(&bad_plan)], vec!["plan.json"]),
    ];
    for (extra, needles) in cases {
        let e = fails(d, &keep, &[&base[..], &extra[..]].concat(), &needles);
        eprintln!("{e}");
    }
    // A mission without --camera, or --max-off-nadir out of range.
    let e = fails(d, &keep, &[&base[..], &["--altitude", "1000..3000"]].concat(), &["--camera"]);
    eprintln!("{e}");
    let e = fails(
        d,
        &keep,
        &[&base[..], &["--camera", s(&camera), "--altitude", "1000..3000", "--max-off-nadir", "95"]].concat(),
        &["--max-off-nadir"],
    );
    eprintln!("{e}");
}

#[test]
fn failed_build_leaves_existing_output_untouched() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 256, 2.0, 440000.0, 1);
    let out = d.join("db.gpkg");
    let before = b"an earlier landmark database: must survive failed builds".to_vec();
    std::fs::write(&out, &before).unwrap();
    let keep = [ortho.as_path(), dem.as_path(), out.as_path()];
    // Fails while checking the inputs, before any work.
    let nope = d.join("no-such-dem.tif");
    let e = fails(
        d,
        &keep,
        &["--ortho", s(&ortho), "--dem", s(&nope), "--out", s(&out), "--dem-vertical", "ellipsoid"],
        &[s(&nope)],
    );
    eprintln!("{e}");
    assert_eq!(std::fs::read(&out).unwrap(), before, "{} changed", out.display());
    // Fails at the end, after the whole pyramid was processed in the work folder.
    let e = fails(
        d,
        &keep,
        &[
            "--ortho",
            s(&ortho),
            "--dem",
            s(&dem),
            "--out",
            s(&out),
            "--dem-vertical",
            "ellipsoid",
            "--min-contrast",
            "1000",
        ],
        &["no landmark"],
    );
    eprintln!("{e}");
    assert_eq!(std::fs::read(&out).unwrap(), before, "{} changed", out.display());
}

#[test]
fn successful_build_replaces_existing_output_atomically() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 512, 2.0, 440000.0, 3);
    let out = d.join("db.gpkg");
    let before = b"an earlier landmark database".to_vec();
    std::fs::write(&out, &before).unwrap();
    // A reader that has the old database open keeps seeing it whole: the new
    // one is renamed over it, never written into it.
    let mut old = std::fs::File::open(&out).unwrap();
    let o = common::run(&[
        "build",
        "--ortho",
        s(&ortho),
        "--dem",
        s(&dem),
        "--out",
        s(&out),
        "--dem-vertical",
        "ellipsoid",
    ]);
    assert!(o.status.success(), "build failed: {}", common::stderr(&o));
    let mut seen = Vec::new();
    old.seek(SeekFrom::Start(0)).unwrap();
    old.read_to_end(&mut seen).unwrap();
    assert_eq!(seen, before, "the old output was modified in place");
    let left = common::leftovers(d, &[&ortho, &dem, &out]);
    assert!(left.is_empty(), "left behind: {left:?}");
    let db = LandmarkDb::open(&out).unwrap();
    let n = db.count().unwrap();
    assert!(n > 0, "no templates in the new database");
    eprintln!("replaced {} with {n} templates", out.display());
}

#[test]
fn ctrl_c_cancels_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    // A big ortho (written directly: cheap) over a small synthetic DEM of the same area.
    const SIZE: usize = 6000;
    let t0 = Instant::now();
    let (small, dem) = common::synth(d, 200, SIZE as f64 / 200.0, 440000.0, 7);
    std::fs::remove_file(&small).unwrap();
    let ortho = d.join("big-ortho.tif");
    gtiff::<u8>(&ortho, SIZE, 1, Some(synth_gt(1.0)), None, texture);
    eprintln!("inputs written in {:.1} s", t0.elapsed().as_secs_f64());
    let out = d.join("db.gpkg");

    let started = Instant::now();
    let mut child = common::trn()
        .args(["build", "--ortho", s(&ortho), "--dem", s(&dem), "--out", s(&out)])
        .args(["--dem-vertical", "ellipsoid"])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start trn build");
    let mut pipe = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        pipe.read_to_string(&mut s).ok();
        s
    });
    let work_dir = || {
        std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .any(|n| n.starts_with(".trn-build-"))
    };
    // The work folder appears once the inputs are checked and tiling starts.
    while !work_dir() {
        assert!(child.try_wait().unwrap().is_none(), "build ended before its work folder appeared");
        assert!(started.elapsed() < Duration::from_secs(30), "no .trn-build-* folder after 30 s");
        std::thread::sleep(Duration::from_millis(10));
    }
    std::thread::sleep(Duration::from_millis(500));
    assert!(
        child.try_wait().unwrap().is_none(),
        "build finished in {:.1} s, before it could be interrupted: make the ortho bigger",
        started.elapsed().as_secs_f64()
    );
    let at = started.elapsed();
    let sent = Instant::now();
    let kill = std::process::Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(kill.success());
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if sent.elapsed() > Duration::from_secs(20) {
            child.kill().ok();
            child.wait().ok();
            panic!("still running 20 s after SIGINT; stderr:\n{}", reader.join().unwrap_or_default());
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let stopped = sent.elapsed();
    let err = reader.join().unwrap();
    eprintln!(
        "SIGINT after {:.2} s, stopped {:.2} s later with {status:?}",
        at.as_secs_f64(),
        stopped.as_secs_f64()
    );
    // Exited by itself (the handler ran), not killed by the signal.
    assert!(status.code().is_some_and(|c| c != 0), "{status:?}, stderr:\n{err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "stderr:\n{err}");
    assert!(lines[0].contains("cancelled"), "{}", lines[0]);
    assert!(!out.exists(), "{} written by a cancelled build", out.display());
    let left = common::leftovers(d, &[&ortho, &dem]);
    assert!(left.is_empty(), "cancelled build left behind: {left:?}");
}
