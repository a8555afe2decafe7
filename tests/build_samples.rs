//! End to end: `trn build` on the real samples, then every template is found
//! again in the ortho re-read independently of the builder: GDAL's own warper
//! reprojects the ortho to an azimuthal equidistant plane centred on the
//! template (north-up, metric, the template's GSD), and an NCC search must find
//! the template there at the centre (NCC > 0.95, offset < 1 px).

mod common;

use gdal::raster::Buffer;
use gdal::spatial_ref::SpatialRef;
use gdal::{Dataset, DriverManager};
use trn_landmark::Template;
use trn_store::LandmarkDb;

/// Search margin around the template in the re-read image (pixels).
const MARGIN: usize = 4;

struct Sample<'a> {
    ortho: &'a str,
    dem: &'a str,
    /// 1-based bands and weights making luminance (as the builder's documented rule).
    bands: &'a [(usize, f64)],
    extra: &'a [&'a str],
}

/// Reprojects the ortho around a template with GDAL and returns its luminance
/// and validity, (S x S) with S = template + 2 * MARGIN.
fn reread(ortho: &Dataset, t: &Template, bands: &[(usize, f64)]) -> (Vec<f64>, Vec<bool>, usize) {
    let s = t.width_px as usize + 2 * MARGIN;
    let driver = DriverManager::get_driver_by_name("MEM").unwrap();
    let mut dst = driver.create_with_band_type::<f32, _>("", s, s, ortho.raster_count()).unwrap();
    let proj = format!(
        "+proj=aeqd +lat_0={} +lon_0={} +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs",
        t.center.lat_deg, t.center.lon_deg
    );
    dst.set_spatial_ref(&SpatialRef::from_proj4(&proj).unwrap()).unwrap();
    let half = s as f64 / 2.0 * t.gsd_m;
    dst.set_geo_transform(&[-half, t.gsd_m, 0.0, half, 0.0, -t.gsd_m]).unwrap();
    for b in 1..=ortho.raster_count() {
        let mut band = dst.rasterband(b).unwrap();
        band.set_no_data_value(Some(-1.0)).unwrap();
        band.fill(-1.0, None).unwrap();
    }
    gdal::raster::reproject(ortho, &dst).unwrap();
    let mut lum = vec![0f64; s * s];
    let mut ok = vec![true; s * s];
    for &(b, w) in bands {
        let nodata = ortho.rasterband(b).unwrap().no_data_value();
        let buf: Buffer<f32> = dst.rasterband(b).unwrap().read_band_as::<f32>().unwrap();
        for ((l, o), &v) in lum.iter_mut().zip(ok.iter_mut()).zip(buf.data()) {
            if v < 0.0 || Some(v as f64) == nodata {
                *o = false;
            }
            *l += w * v as f64;
        }
    }
    (lum, ok, s)
}

/// NCC of the template against the image window at (dx, dy); `None` where the
/// window holds pixels outside the ortho.
fn ncc(t: &[f64], img: &[f64], ok: &[bool], s: usize, tw: usize, dx: usize, dy: usize) -> Option<f64> {
    let n = (tw * tw) as f64;
    let (mut st, mut si, mut stt, mut sii, mut sti) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for r in 0..tw {
        for c in 0..tw {
            let a = t[r * tw + c];
            if !ok[(r + dy) * s + c + dx] {
                return None;
            }
            let b = img[(r + dy) * s + c + dx];
            st += a;
            si += b;
            stt += a * a;
            sii += b * b;
            sti += a * b;
        }
    }
    let vt = stt - st * st / n;
    let vi = sii - si * si / n;
    Some((sti - st * si / n) / (vt * vi).sqrt().max(1e-12))
}

/// Sub-pixel peak offset from a parabola through three NCC values.
fn parabola(l: f64, c: f64, r: f64) -> f64 {
    let d = l - 2.0 * c + r;
    if d.abs() < 1e-12 {
        0.0
    } else {
        0.5 * (l - r) / d
    }
}

fn check_sample(s: &Sample) {
    let dir = tempfile::tempdir().unwrap();
    let ortho_path = common::sample(s.ortho, dir.path());
    let dem_path = common::sample(s.dem, dir.path());
    let db_path = dir.path().join("landmarks.gpkg");
    let mut args = vec![
        "build",
        "--ortho",
        ortho_path.to_str().unwrap(),
        "--dem",
        dem_path.to_str().unwrap(),
        "--out",
        db_path.to_str().unwrap(),
    ];
    args.extend_from_slice(s.extra);
    let o = common::run(&args);
    assert!(o.status.success(), "build failed: {}", common::stderr(&o));
    // Every sample's ortho (28.5-167 m) is too coarse for the default
    // envelope's finest cameras: its finest level, whose cells are half a
    // footprint, gets the density fill; the other levels none.
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let fills: Vec<f64> =
        report["levels"].as_array().unwrap().iter().map(|l| l["fill_share"].as_f64().unwrap()).collect();
    assert_eq!(fills[0], 0.7, "{}: the finest level's fill {fills:?}", s.ortho);
    assert!(fills[1..].iter().all(|&f| f == 0.0), "{}: fills {fills:?}", s.ortho);

    let db = LandmarkDb::open(&db_path).unwrap();
    let ortho = Dataset::open(&ortho_path).unwrap();
    let (mut checked, mut worst_ncc, mut worst_off) = (0, 1.0f64, 0.0f64);
    let mut templates = Vec::new();
    db.for_each_template(|t| {
        templates.push(t);
        Ok(())
    })
    .unwrap();
    assert!(templates.len() >= 10, "{}: only {} templates", s.ortho, templates.len());
    // Every level, at most ~300 templates in all (each is re-read through GDAL).
    let step = templates.len().div_ceil(300);
    let levels: std::collections::BTreeSet<u8> = templates.iter().map(|t| t.level).collect();
    let picked: Vec<&Template> = templates
        .iter()
        .enumerate()
        .filter(|(i, t)| i % step == 0 || templates.iter().position(|u| u.level == t.level) == Some(*i))
        .map(|(_, t)| t)
        .collect();
    assert!(levels.iter().all(|l| picked.iter().any(|t| t.level == *l)));
    let finest_gsd = templates.iter().map(|t| t.gsd_m).fold(f64::INFINITY, f64::min);
    for t in picked {
        let (img, ok, size) = reread(&ortho, t, s.bands);
        let tw = t.width_px as usize;
        let tpl: Vec<f64> = t.pixels.iter().map(|&v| v as f64).collect();
        let span = 2 * MARGIN + 1;
        let mut scores = vec![f64::MIN; span * span];
        for dy in 0..span {
            for dx in 0..span {
                scores[dy * span + dx] = ncc(&tpl, &img, &ok, size, tw, dx, dy).unwrap_or(f64::MIN);
            }
        }
        let best = (0..scores.len()).max_by(|&a, &b| scores[a].total_cmp(&scores[b])).unwrap();
        let (bx, by) = (best % span, best / span);
        let peak = scores[best];
        // The true position must be inside the ortho.
        assert!(
            scores[MARGIN * span + MARGIN] > f64::MIN,
            "template {} (level {}) lies on nodata in the re-read ortho",
            t.id,
            t.level
        );
        let sub = |l: Option<f64>, r: Option<f64>| match (l, r) {
            (Some(l), Some(r)) => parabola(l, peak, r),
            _ => 0.0,
        };
        let at = |x: isize, y: isize| {
            (x >= 0 && y >= 0 && (x as usize) < span && (y as usize) < span)
                .then(|| scores[y as usize * span + x as usize])
                .filter(|&v| v > f64::MIN)
        };
        let (bxi, byi) = (bx as isize, by as isize);
        let ox = bx as f64 + sub(at(bxi - 1, byi), at(bxi + 1, byi)) - MARGIN as f64;
        let oy = by as f64 + sub(at(bxi, byi - 1), at(bxi, byi + 1)) - MARGIN as f64;
        let off = ox.hypot(oy);
        // GDAL's reprojection here samples the nearest pixel, the builder a 2x2
        // box pyramid: at 4x and more below the ortho's resolution the two
        // low-pass differently.
        let min_peak = if t.gsd_m >= 3.5 * finest_gsd { 0.9 } else { 0.95 };
        assert!(peak > min_peak, "template {} (level {}, {} m): NCC peak {peak:.3}", t.id, t.level, t.gsd_m);
        assert!(
            off < 1.0,
            "template {} (level {}): found {off:.2} px away ({ox:.2}, {oy:.2})",
            t.id,
            t.level
        );
        worst_ncc = worst_ncc.min(peak);
        worst_off = worst_off.max(off);
        checked += 1;
    }
    check_index(&db, &db_path, &templates);
    eprintln!(
        "{}: {checked} templates re-found, worst NCC {worst_ncc:.3}, worst offset {worst_off:.2} px",
        s.ortho
    );
    // The build must not leave anything but its output.
    let left = common::leftovers(dir.path(), &[&ortho_path, &dem_path, &db_path]);
    assert!(left.is_empty(), "left behind: {left:?}");
}

/// GDAL opens the file as a GeoPackage with one footprint per template, and the
/// R*Tree bounding-box query returns exactly what a brute-force scan finds.
fn check_index(db: &LandmarkDb, path: &std::path::Path, templates: &[Template]) {
    let o = std::process::Command::new("ogrinfo")
        .args(["-ro", "-so", path.to_str().unwrap(), "templates"])
        .output()
        .expect("ogrinfo (gdal-bin) must be installed");
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "ogrinfo failed: {}", String::from_utf8_lossy(&o.stderr));
    assert!(text.contains(&format!("Feature Count: {}", templates.len())), "ogrinfo says: {text}");

    let ext = db.extent().unwrap().expect("extent");
    let (w, h) = (ext.max_lon_deg - ext.min_lon_deg, ext.max_lat_deg - ext.min_lat_deg);
    let mut seed = 12345u64;
    let mut rnd = || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    for _ in 0..300 {
        let (x, y) =
            (ext.min_lon_deg - 0.1 * w + 1.2 * w * rnd(), ext.min_lat_deg - 0.1 * h + 1.2 * h * rnd());
        let (bw, bh) = (0.3 * w * rnd(), 0.3 * h * rnd());
        let bbox = trn_landmark::GeoBox::new(x, y, x + bw, y + bh);
        let mut got = db.query_bbox_ids(&trn_store::BboxQuery::new(bbox)).unwrap();
        got.sort();
        let mut want: Vec<i64> =
            templates.iter().filter(|t| t.footprint.intersects(&bbox)).map(|t| t.id).collect();
        want.sort();
        assert_eq!(got, want, "bbox {bbox:?}");
    }
}

#[test]
fn rmnp_templates_are_found_in_the_ortho() {
    check_sample(&Sample {
        ortho: "rmnp-rgb.tif",
        dem: "rmnp-dem.tif",
        bands: &[(1, 0.299), (2, 0.587), (3, 0.114)],
        extra: &["--dem-vertical", "egm96"],
    });
}

#[test]
fn olinda_landsat_templates_are_found_in_the_ortho() {
    check_sample(&Sample {
        ortho: "L7_ETMs.tif",
        dem: "olinda_dem_utm25s.tif",
        bands: &[(3, 0.299), (2, 0.587), (1, 0.114)],
        extra: &["--ortho-bands", "3,2,1", "--dem-vertical", "egm96"],
    });
}

/// The realistic worlds (issue #11's fetch): default builds succeed and
/// their templates are where they say.
#[test]
fn sierra_draped_landsat_templates_are_found_in_the_ortho() {
    check_sample(&Sample {
        ortho: "sierra-ortho-draped.tif",
        dem: "sierra-dem.tif",
        bands: &[(3, 0.299), (2, 0.587), (1, 0.114)],
        extra: &["--ortho-bands", "3,2,1", "--dem-vertical", "egm96"],
    });
}

#[test]
fn great_salt_lake_landsat_templates_are_found_in_the_ortho() {
    check_sample(&Sample {
        ortho: "gsl-landsat7.tif",
        dem: "gsl-dem-draped.tif",
        bands: &[(3, 0.299), (2, 0.587), (1, 0.114)],
        extra: &["--ortho-bands", "3,2,1", "--dem-vertical", "egm96"],
    });
}
