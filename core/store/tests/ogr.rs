//! The database is a GeoPackage that GDAL reads: `ogrinfo` lists the `templates`
//! layer, SQL and spatial filters work, and GDAL's own validator accepts the file.

mod common;

use std::path::Path;
use std::process::Command;

use common::{synthetic_template, write_db, Lcg};
use trn_landmark::{GeoBox, Template};
use trn_store::{BboxQuery, LandmarkDb};

/// Runs a GDAL tool (gdal-bin is installed by scripts/install-deps.sh; a missing
/// tool fails the test rather than skipping it).
fn run(program: &str, args: &[&str]) -> Option<(String, String)> {
    match Command::new(program).args(args).output() {
        Ok(out) => {
            let stdout = String::from_utf8_lossy(&out.stdout).into_owned();
            let stderr = String::from_utf8_lossy(&out.stderr).into_owned();
            assert!(out.status.success(), "{program} {args:?} failed:\n{stdout}\n{stderr}");
            Some((stdout, stderr))
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            panic!("{program} is not installed: run scripts/install-deps.sh (Debian gdal-bin)")
        }
        Err(e) => panic!("{program}: {e}"),
    }
}

/// `ogrinfo` must not complain about the file.
fn assert_quiet(stderr: &str) {
    assert!(!stderr.contains("ERROR") && !stderr.contains("Warning"), "ogrinfo complained:\n{stderr}");
}

/// The value of the SQL result column `n` in ogrinfo output (`  n (Integer) = 12`).
fn sql_n(out: &str) -> &str {
    let line =
        out.lines().find(|l| l.trim_start().starts_with("n (")).unwrap_or_else(|| panic!("no n in:\n{out}"));
    line.split('=').nth(1).unwrap().trim()
}

/// The text after `key` in ogrinfo output.
fn field<'a>(out: &'a str, key: &str) -> &'a str {
    let line = out
        .lines()
        .find(|l| l.trim_start().starts_with(key))
        .unwrap_or_else(|| panic!("no {key} in:\n{out}"));
    line.trim_start()[key.len()..].trim()
}

/// 240 templates on four levels around the Alps; `crossing` adds one footprint across
/// the antimeridian.
fn build(dir: &Path, crossing: bool) -> (std::path::PathBuf, Vec<Template>) {
    let mut rng = Lcg::new(99);
    let mut templates: Vec<Template> = (0..240)
        .map(|i| {
            let level = (i % 4) as u8;
            let lat = 46.0 + rng.uniform(-0.2, 0.2);
            let lon = 7.0 + rng.uniform(-0.3, 0.3);
            synthetic_template(&mut rng, level, lat, lon)
        })
        .collect();
    if crossing {
        templates.push(synthetic_template(&mut rng, 2, 10.0, 179.9999));
        assert!(templates.last().unwrap().footprint.crosses_antimeridian());
    }
    let (path, _) = write_db(dir, "ogr.gpkg", &mut templates);
    (path, templates)
}

#[test]
fn ogrinfo_lists_the_layer_with_count_and_extent() {
    let dir = tempfile::tempdir().unwrap();
    let (path, templates) = build(dir.path(), false);
    let db_arg = path.to_str().unwrap();
    let Some((out, err)) = run("ogrinfo", &["-ro", "-so", db_arg, "templates"]) else { return };
    println!("{out}");
    assert_quiet(&err);
    assert!(out.contains("Layer name: templates"), "{out}");
    assert!(out.contains("Geometry: Polygon"), "{out}");
    assert!(out.contains("Geometry Column NOT NULL = geom"), "{out}");
    assert!(out.contains("FID Column = fid"), "{out}");
    assert_eq!(field(&out, "Feature Count:"), templates.len().to_string());
    let extent = GeoBox::around(templates.iter().flat_map(|t| {
        [
            (t.footprint.min_lon_deg, t.footprint.min_lat_deg),
            (t.footprint.max_lon_deg, t.footprint.max_lat_deg),
        ]
    }))
    .unwrap();
    let expected = format!(
        "({:.6}, {:.6}) - ({:.6}, {:.6})",
        extent.min_lon_deg, extent.min_lat_deg, extent.max_lon_deg, extent.max_lat_deg
    );
    assert_eq!(field(&out, "Extent:"), expected);
    for column in ["level: Integer", "gsd_m: Real", "second_peak_ncc: Real", "pixels: Binary"] {
        assert!(out.contains(column), "no {column} in:\n{out}");
    }

    // The plain listing shows the layer and the level summary, no internal tables.
    let (list, err) = run("ogrinfo", &["-ro", db_arg]).unwrap();
    assert_quiet(&err);
    let layers: Vec<&str> = list.lines().filter(|l| l.starts_with(|c: char| c.is_ascii_digit())).collect();
    assert_eq!(layers, ["1: templates (Polygon)", "2: trn_levels (None)"], "{list}");
}

#[test]
fn ogrinfo_sql_and_spatial_filter_agree_with_the_store() {
    let dir = tempfile::tempdir().unwrap();
    let (path, templates) = build(dir.path(), false);
    let db_arg = path.to_str().unwrap();
    let db = LandmarkDb::open(&path).unwrap();

    // Attribute SQL (OGR SQL dialect of the GeoPackage driver, i.e. SQLite).
    let sql = "SELECT COUNT(*) AS n FROM templates WHERE level = 2 AND second_peak_ncc < 0.5";
    let Some((out, err)) = run("ogrinfo", &["-ro", db_arg, "-sql", sql]) else { return };
    assert_quiet(&err);
    let expected = templates.iter().filter(|t| t.level == 2 && t.quality.second_peak_ncc < 0.5).count();
    assert_eq!(sql_n(&out), expected.to_string(), "{out}");

    // GeoPackage spatial SQL through the R*Tree index extension.
    let bbox = GeoBox::new(6.9, 45.95, 7.1, 46.05);
    let sql = format!(
        "SELECT COUNT(*) AS n FROM templates WHERE fid IN (SELECT id FROM rtree_templates_geom \
         WHERE maxx >= {} AND minx <= {} AND maxy >= {} AND miny <= {}) AND ST_EnvIntersects(geom, {}, {}, {}, {})",
        bbox.min_lon_deg,
        bbox.max_lon_deg,
        bbox.min_lat_deg,
        bbox.max_lat_deg,
        bbox.min_lon_deg,
        bbox.min_lat_deg,
        bbox.max_lon_deg,
        bbox.max_lat_deg
    );
    let (out, err) = run("ogrinfo", &["-ro", db_arg, "-sql", &sql]).unwrap();
    assert_quiet(&err);
    let ours = db.query_bbox_ids(&BboxQuery::new(bbox)).unwrap();
    assert!(!ours.is_empty() && ours.len() < templates.len());
    assert_eq!(sql_n(&out), ours.len().to_string(), "{out}");

    // OGR's spatial filter on the layer, for the box and for level 3 only.
    let spat =
        [bbox.min_lon_deg, bbox.min_lat_deg, bbox.max_lon_deg, bbox.max_lat_deg].map(|v| v.to_string());
    let mut args = vec!["-ro", "-so", db_arg, "templates", "-spat"];
    args.extend(spat.iter().map(String::as_str));
    let (out, err) = run("ogrinfo", &args).unwrap();
    assert_quiet(&err);
    assert_eq!(field(&out, "Feature Count:"), ours.len().to_string(), "{out}");
    args.extend(["-where", "level = 3"]);
    let (out, _) = run("ogrinfo", &args).unwrap();
    let level3 = db.query_bbox_ids(&BboxQuery::new(bbox).with_levels(3..=3)).unwrap();
    assert_eq!(field(&out, "Feature Count:"), level3.len().to_string(), "{out}");
}

#[test]
fn gdal_geopackage_validator_accepts_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let (path, _) = build(dir.path(), true);
    let db_arg = path.to_str().unwrap();
    // GDAL's Python bindings belong to the system interpreter, which may not be first on PATH.
    let python = ["python3", "/usr/bin/python3"].into_iter().find(|p| {
        Command::new(p)
            .args(["-c", "import osgeo_utils.samples.validate_gpkg"])
            .output()
            .is_ok_and(|o| o.status.success())
    });
    let python =
        python.expect("GDAL's Python validate_gpkg is missing: Debian python3-gdal (a gdal-bin dependency)");
    // Strict: keep going to list every problem, extra content checks, warnings fail.
    let out = Command::new(python)
        .args(["-m", "osgeo_utils.samples.validate_gpkg", "-k", "--extra", "--warning-as-error", db_arg])
        .output()
        .unwrap();
    let text = format!("{}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    println!("{text}");
    assert!(out.status.success() && text.trim().is_empty(), "validate_gpkg:\n{text}");
}
