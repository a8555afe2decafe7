//! End to end: `trn build --sun` bakes a sun's shading and cast shadows into
//! the templates. A wall 300 m high and 200 m thick runs north-south across a
//! synthetic ortho; with the sun 20° above the western horizon it shades the
//! ground east of it for 300 / tan 20° = 824 m, and with the sun in the east,
//! west of it. Every landmark whose footprint lies wholly in a shadow must
//! come out darkened by the shadow factor, every one wholly on open ground
//! away from the wall unchanged, each landmark once per sun.

mod common;

use std::collections::HashMap;
use std::path::Path;

use gdal::raster::Buffer;
use gdal::spatial_ref::{AxisMappingStrategy, CoordTransform, SpatialRef};
use gdal::DriverManager;
use trn_landmark::Template;
use trn_store::{BboxQuery, LandmarkDb};

const GSD: f64 = 8.0;
const SIZE: usize = 512;
const WEST: f64 = 440000.0;
const NORTH: f64 = 4460000.0;
/// The wall: eastings from the ortho's west edge (m).
const WALL: (f64, f64) = (1500.0, 1700.0);
const WALL_H: f64 = 300.0;
const ELEVATION_DEG: f64 = 20.0;
const AMBIENT: f64 = 0.25;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// The DEM: 1500 m ellipsoidal with the wall, 32 m pixels over the ortho.
fn wall_dem(path: &Path) {
    let (n, px) = (128usize, 32.0);
    let driver = DriverManager::get_driver_by_name("GTiff").unwrap();
    let mut ds = driver.create_with_band_type::<f32, _>(path, n, n, 1).unwrap();
    ds.set_geo_transform(&[WEST, px, 0.0, NORTH, 0.0, -px]).unwrap();
    ds.set_spatial_ref(&SpatialRef::from_epsg(32613).unwrap()).unwrap();
    let data: Vec<f32> = (0..n * n)
        .map(|i| {
            let x = ((i % n) as f64 + 0.5) * px;
            if x >= WALL.0 && x < WALL.1 {
                (1500.0 + WALL_H) as f32
            } else {
                1500.0
            }
        })
        .collect();
    ds.rasterband(1).unwrap().write((0, 0), (n, n), &mut Buffer::new((n, n), data)).unwrap();
}

/// `trn build` of `ortho` over `dem` (ellipsoidal heights) into `out`, with `extra` options.
fn build(ortho: &Path, dem: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let mut args = vec!["build", "--ortho", s(ortho), "--dem", s(dem), "--dem-vertical", "ellipsoid"];
    args.extend_from_slice(&["--out", s(out)]);
    args.extend_from_slice(extra);
    let o = common::run(&args);
    assert!(o.status.success(), "trn build failed: {}", common::stderr(&o));
    o
}

/// Easting range (m from the ortho's west edge) of a template's footprint.
fn east_range(t: &Template, to_utm: &CoordTransform) -> (f64, f64) {
    let xs: Vec<f64> = t
        .footprint_corners()
        .iter()
        .map(|g| {
            let (mut x, mut y, mut z) = ([g.lon_deg], [g.lat_deg], [0.0]);
            to_utm.transform_coords(&mut x, &mut y, &mut z).unwrap();
            x[0] - WEST
        })
        .collect();
    (xs.iter().copied().fold(f64::MAX, f64::min), xs.iter().copied().fold(f64::MIN, f64::max))
}

/// Grey-level ratio of a relit template to the unlit one, over pixels bright
/// enough to measure it.
fn ratio(lit: &Template, unlit: &Template) -> f64 {
    let (mut a, mut b) = (0.0, 0.0);
    for (&l, &u) in lit.pixels.iter().zip(&unlit.pixels) {
        if u >= 40 {
            a += l as f64;
            b += u as f64;
        }
    }
    a / b
}

#[test]
fn baked_sun_shades_and_shadows_the_templates() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, _) = common::synth(d, SIZE, GSD, WEST, 3);
    let dem = d.join("wall.tif");
    wall_dem(&dem);
    let build_db = |name: &str, extra: &[&str]| -> Vec<Template> {
        let out = d.join(name);
        build(&ortho, &dem, &out, extra);
        let db = LandmarkDb::open(&out).unwrap();
        let suns = db.metadata("suns").unwrap().unwrap();
        assert_eq!(suns.as_array().unwrap().len(), extra.len() / 2, "{suns}");
        db.query_bbox(&BboxQuery::new(trn_landmark::GeoBox::new(-180.0, -90.0, 180.0, 90.0))).unwrap()
    };
    let unlit = build_db("unlit.gpkg", &[]);
    let (west_sun, east_sun) = (format!("270,{ELEVATION_DEG},{AMBIENT}"), format!("90,{ELEVATION_DEG}"));
    let lit = build_db("lit.gpkg", &["--sun", &west_sun, "--sun", &east_sun]);

    // Each landmark once per sun, with the same terrain and scores (the
    // shading share is taken over the build's suns when it has any).
    let key = |t: &Template| (t.level, (t.center.lat_deg * 1e9) as i64, (t.center.lon_deg * 1e9) as i64);
    let by_key: HashMap<_, &Template> = unlit.iter().map(|t| (key(t), t)).collect();
    assert!(unlit.iter().all(|t| t.lighting == 0));
    assert_eq!(lit.len(), 2 * unlit.len());
    for l in [1u8, 2] {
        assert_eq!(lit.iter().filter(|t| t.lighting == l).count(), unlit.len(), "lighting {l}");
    }
    for t in &lit {
        let u = by_key[&key(t)];
        let scores = |t: &Template| (t.quality.shi_tomasi, t.quality.contrast_std, t.quality.second_peak_ncc);
        assert_eq!((&t.terrain, scores(t)), (&u.terrain, scores(u)));
    }
    // Relief gives a shading share; the wall's templates have the largest.
    let max_share = unlit.iter().map(|t| t.quality.shading_share).fold(0.0, f32::max);
    assert!(max_share > 0.5, "largest shading share {max_share}");

    let mut utm = SpatialRef::from_epsg(32613).unwrap();
    utm.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
    let mut wgs = SpatialRef::from_epsg(4326).unwrap();
    wgs.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
    let to_utm = CoordTransform::new(&wgs, &utm).unwrap();
    let dark = AMBIENT / (AMBIENT + (1.0 - AMBIENT) * ELEVATION_DEG.to_radians().sin());
    let shadow_len = WALL_H / ELEVATION_DEG.to_radians().tan();
    // Two DEM cells of slack for the penumbra ramp and the grid convergence.
    let slack = 64.0;
    let mut counts = [[0usize; 2]; 2];
    for t in &lit {
        let u = by_key[&key(t)];
        let (x0, x1) = east_range(t, &to_utm);
        let r = ratio(t, u);
        // Where this lighting's shadow falls, and open ground.
        let shadow = if t.lighting == 1 {
            (WALL.1 + slack, WALL.1 + shadow_len - slack)
        } else {
            (WALL.0 - shadow_len + slack, WALL.0 - slack)
        };
        let open = |a: f64, b: f64| b < WALL.0 - shadow_len - slack || (a > WALL.1 + shadow_len + slack);
        let l = (t.lighting - 1) as usize;
        if x0 >= shadow.0 && x1 <= shadow.1 {
            assert!(
                (r - dark).abs() < 0.03,
                "lighting {} at {x0:.0}..{x1:.0} m: ratio {r:.3}, shadow {dark:.3}",
                t.lighting
            );
            counts[l][0] += 1;
        } else if open(x0, x1) {
            let worst = t.pixels.iter().zip(&u.pixels).map(|(a, b)| a.abs_diff(*b)).max().unwrap();
            assert!(
                worst <= 1,
                "lighting {} at {x0:.0}..{x1:.0} m on open ground: pixels changed by {worst}",
                t.lighting
            );
            counts[l][1] += 1;
        }
    }
    eprintln!("(in shadow, on open ground) per sun: {counts:?}; shadow factor {dark:.3}");
    for c in counts {
        assert!(c[0] >= 10 && c[1] >= 10, "too few landmarks checked: {counts:?}");
    }

    // Coverage counts each landmark once, whatever the number of suns.
    let to_wgs = CoordTransform::new(&utm, &wgs).unwrap();
    let half = SIZE as f64 * GSD / 2.0;
    let (mut x, mut y, mut z) = ([WEST + half], [NORTH - half], [0.0]);
    to_wgs.transform_coords(&mut x, &mut y, &mut z).unwrap();
    let plan = d.join("plan.json");
    std::fs::write(
        &plan,
        format!(
            r#"{{"camera": {{"width": 640, "height": 480, "hfov_deg": 40}},
                "waypoints": [{{"lat_deg": {}, "lon_deg": {}, "h_m": 4500}}],
                "attitude": {{"tilt_deg": 0, "azimuth_deg": 0}}}}"#,
            y[0], x[0]
        ),
    )
    .unwrap();
    let in_view = |db: &str| -> Vec<u64> {
        let o = common::run(&["coverage", "--db", s(&d.join(db)), "--plan", s(&plan)]);
        assert!(o.status.success(), "trn coverage failed: {}", common::stderr(&o));
        let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        v["points"].as_array().unwrap().iter().map(|p| p["landmarks"].as_u64().unwrap()).collect()
    };
    let (one, two) = (in_view("unlit.gpkg"), in_view("lit.gpkg"));
    assert!(one.iter().all(|&n| n > 20), "{one:?}");
    assert_eq!(one, two, "landmarks in view, as imaged and lit for two suns");
}

/// `--max-shading S` keeps no template whose shading share is above `S`
/// (the wall's flanks have the largest), and counts what it passed over.
#[test]
fn max_shading_rejects_shading_dominated_templates() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, _) = common::synth(d, SIZE, GSD, WEST, 3);
    let dem = d.join("wall.tif");
    wall_dem(&dem);
    let out = d.join("limited.gpkg");
    let o = build(&ortho, &dem, &out, &["--max-shading", "0.3"]);
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let passed_over = report["rejected"]["Shading"].as_u64().unwrap_or(0);
    assert!(passed_over > 0, "nothing rejected: {}", report["rejected"]);
    let db = LandmarkDb::open(&out).unwrap();
    let all = db.query_bbox(&BboxQuery::new(trn_landmark::GeoBox::new(-180.0, -90.0, 180.0, 90.0))).unwrap();
    assert!(!all.is_empty());
    let worst = all.iter().map(|t| t.quality.shading_share).fold(0.0, f32::max);
    assert!(worst <= 0.3, "a template with shading share {worst} was kept");
    eprintln!("{} templates kept, {passed_over} candidates passed over", all.len());
}
