//! End to end: `trn build` reads what the issue promises, proven on inputs
//! derived with GDAL's own command-line tools from one `trn synth` pair (UTM 13N,
//! 800 px at 2 m, DEM at 30 m with ellipsoidal heights):
//! mosaics of several orthos (side by side or overlapping) and of several DEMs,
//! 8- and 16-bit, 1 to 4 bands with alpha and nodata masks, orthos and DEMs in
//! other CRSs and resolutions, COG / VRT / JPEG 2000 files, and the DEM's
//! vertical datum taken from its CRS (EGM96 converted with the geoid grid,
//! ellipsoidal heights used as they are).
//!
//! Most checks compare with the build of the original pair ("reference"): a
//! derived input holding the same pixels on the same grid must give the same
//! templates ("twins": same level, centres within a few centimetres).

mod common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::Command;

use gdal::raster::Buffer;
use gdal::spatial_ref::{AxisMappingStrategy, CoordTransform, SpatialRef};
use gdal::{Dataset, DatasetOptions, GdalOpenFlags};
use trn_landmark::Template;
use trn_store::LandmarkDb;

/// Synthetic ortho: SIZE x SIZE pixels of GSD metres, top-left corner at (EAST, NORTH) in UTM 13N.
const SIZE: usize = 800;
const GSD: f64 = 2.0;
const EAST: f64 = 440000.0;
const NORTH: f64 = 4460000.0;
/// `trn synth` writes the DEM at 15x the ortho pixel with 2 pixels of margin.
const DEM_GSD: f64 = 30.0;
const DEM_SIZE: usize = 58;
const SEED: u64 = 11;
/// Template counts of builds from equivalent inputs agree within this fraction.
const COUNT_TOLERANCE: f64 = 0.15;

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Runs a GDAL command-line tool and returns its stdout; fails the test with a
/// clear message when the tool is missing or fails.
fn gdal_tool(tool: &str, args: &[&str]) -> String {
    let o = Command::new(tool).args(args).output().unwrap_or_else(|e| {
        panic!("cannot run {tool} ({e}): these tests need GDAL's tools (apt-get install gdal-bin)")
    });
    assert!(o.status.success(), "{tool} {} failed:\n{}", args.join(" "), String::from_utf8_lossy(&o.stderr));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

fn translate(src: &Path, dst: &Path, args: &[&str]) {
    gdal_tool("gdal_translate", &[&["-q"], args, &[s(src), s(dst)]].concat());
}

fn warp(src: &Path, dst: &Path, args: &[&str]) {
    gdal_tool("gdalwarp", &[&["-q", "-overwrite"], args, &[s(src), s(dst)]].concat());
}

/// The synthetic pair in `dir`.
fn synth(dir: &Path) -> (PathBuf, PathBuf) {
    common::synth(dir, SIZE, GSD, EAST, SEED)
}

/// What a successful build gave.
struct Built {
    name: String,
    templates: Vec<Template>,
    log: String,
    meta: BTreeMap<String, serde_json::Value>,
}

/// `trn build` of `orthos` over `dems` into `dir/NAME.gpkg` with `extra`
/// options; must succeed and add nothing to `dir` but its output.
fn build(dir: &Path, name: &str, orthos: &[&Path], dems: &[&Path], extra: &[&str]) -> Built {
    let out = dir.join(format!("{name}.gpkg"));
    let mut args = vec!["build"];
    for o in orthos {
        args.extend(["--ortho", s(o)]);
    }
    for d in dems {
        args.extend(["--dem", s(d)]);
    }
    args.extend(["--out", s(&out)]);
    // These tests are about reading inputs (CRSs, datums, bands, mosaics), and
    // compare builds template by template: one template size on a sparse grid
    // keeps them fast and their counts stable (the default ladder and density
    // are tested in build_samples.rs and by the benchmarks).
    if !extra.contains(&"--spacing") {
        args.extend(["--min-template-size", "32", "--spacing", "64"]);
    }
    args.extend_from_slice(extra);
    let before: Vec<PathBuf> = std::fs::read_dir(dir).unwrap().map(|e| e.unwrap().path()).collect();
    let o = common::run(&args);
    let log = common::stderr(&o);
    assert!(o.status.success(), "build {name} failed ({args:?}):\n{log}");
    let mut keep: Vec<&Path> = before.iter().map(|p| p.as_path()).collect();
    keep.push(&out);
    let left = common::leftovers(dir, &keep);
    assert!(left.is_empty(), "build {name} left behind (next to its inputs): {left:?}");
    let db = LandmarkDb::open(&out).unwrap();
    let mut templates = Vec::new();
    db.for_each_template(|t| {
        templates.push(t);
        Ok(())
    })
    .unwrap();
    assert!(!templates.is_empty(), "build {name}: no templates");
    let meta = db.all_metadata().unwrap();
    eprintln!("{name}: {} templates", templates.len());
    Built { name: name.into(), templates, log, meta }
}

/// The standard build of the synthetic pair: heights are ellipsoidal.
fn build_ell(dir: &Path, name: &str, orthos: &[&Path], dems: &[&Path], extra: &[&str]) -> Built {
    build(dir, name, orthos, dems, &[extra, &["--dem-vertical", "ellipsoid"]].concat())
}

fn assert_similar_count(b: &Built, reference: &Built) {
    let (n, r) = (b.templates.len() as f64, reference.templates.len() as f64);
    assert!(
        (n - r).abs() <= COUNT_TOLERANCE * r,
        "{}: {n} templates, {}: {r} (more than {:.0}% apart)",
        b.name,
        reference.name,
        COUNT_TOLERANCE * 100.0
    );
}

/// Horizontal distance (m) between two template centres.
fn centre_distance_m(a: &Template, b: &Template) -> f64 {
    let (m_lat, m_lon) = trn_geodesy::metres_per_degree(a.center.lat_deg);
    ((a.center.lat_deg - b.center.lat_deg) * m_lat).hypot((a.center.lon_deg - b.center.lon_deg) * m_lon)
}

/// Pairs (a, b) of templates of one level whose centres lie within 5 cm.
fn twins<'a>(a: &'a [Template], b: &'a [Template]) -> Vec<(&'a Template, &'a Template)> {
    // Buckets of about a metre: a twin is within 5 cm, so in the same or a neighbouring bucket.
    let key = |t: &Template| {
        (t.level, (t.center.lat_deg * 1e5).floor() as i64, (t.center.lon_deg * 1e5).floor() as i64)
    };
    let mut index: std::collections::HashMap<(u8, i64, i64), Vec<&Template>> = Default::default();
    for y in b {
        index.entry(key(y)).or_default().push(y);
    }
    a.iter()
        .filter_map(|x| {
            let (l, la, lo) = key(x);
            (-1..=1)
                .flat_map(|i| (-1..=1).map(move |j| (l, la + i, lo + j)))
                .filter_map(|k| index.get(&k))
                .flatten()
                .find(|y| centre_distance_m(x, y) < 0.05)
                .map(|y| (x, *y))
        })
        .collect()
}

/// Largest absolute difference between two templates' grey levels.
fn max_pixel_diff(a: &Template, b: &Template) -> i32 {
    a.pixels.iter().zip(&b.pixels).map(|(&p, &q)| (p as i32 - q as i32).abs()).max().unwrap_or(0)
}

/// `b` holds the same templates as `reference`: every one of either has a twin
/// in the other, with grey levels within `max_diff` and the same height within
/// `max_dh_m`. For inputs with the same pixels on the same grid.
fn assert_same_templates(b: &Built, reference: &Built, max_diff: i32, max_dh_m: f64) {
    let pairs = twins(&b.templates, &reference.templates);
    let worst_px = pairs.iter().map(|(x, y)| max_pixel_diff(x, y)).max().unwrap_or(0);
    let worst_dh = pairs.iter().map(|(x, y)| (x.center.h_m - y.center.h_m).abs()).fold(0.0, f64::max);
    eprintln!(
        "{} vs {}: {} of {}/{} templates are twins, grey levels within {worst_px}, heights within {worst_dh:.3} m",
        b.name,
        reference.name,
        pairs.len(),
        b.templates.len(),
        reference.templates.len()
    );
    assert_eq!(
        (pairs.len(), b.templates.len()),
        (reference.templates.len(), reference.templates.len()),
        "{} and {} should hold the same templates (twins, {} templates, {} in the reference)",
        b.name,
        reference.name,
        b.templates.len(),
        reference.templates.len()
    );
    assert!(
        worst_px <= max_diff,
        "{}: grey levels differ by up to {worst_px} from {}",
        b.name,
        reference.name
    );
    assert!(
        worst_dh <= max_dh_m,
        "{}: heights differ by up to {worst_dh:.3} m from {}",
        b.name,
        reference.name
    );
}

/// WGS84 (lon, lat) -> UTM 13N.
struct Utm {
    to_utm: CoordTransform,
}

impl Utm {
    fn new() -> Self {
        let mut wgs = SpatialRef::from_epsg(4326).unwrap();
        wgs.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
        let mut utm = SpatialRef::from_epsg(32613).unwrap();
        utm.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
        Self { to_utm: CoordTransform::new(&wgs, &utm).unwrap() }
    }

    fn xy(&self, lon: f64, lat: f64) -> (f64, f64) {
        let (mut x, mut y, mut z) = ([lon], [lat], [0.0]);
        self.to_utm.transform_coords(&mut x, &mut y, &mut z).unwrap();
        (x[0], y[0])
    }

    fn centre(&self, t: &Template) -> (f64, f64) {
        self.xy(t.center.lon_deg, t.center.lat_deg)
    }

    /// The template's footprint corners (the outer edges of its pixels) in UTM.
    fn corners(&self, t: &Template) -> [(f64, f64); 4] {
        t.footprint_corners().map(|g| self.xy(g.lon_deg, g.lat_deg))
    }
}

/// A UTM rectangle (x0 < x1, y0 < y1).
#[derive(Clone, Copy, Debug)]
struct Rect {
    x0: f64,
    x1: f64,
    y0: f64,
    y1: f64,
}

impl Rect {
    /// Pixel columns c0..c1, rows r0..r1 of the synthetic ortho.
    fn ortho_px(c0: usize, c1: usize, r0: usize, r1: usize) -> Self {
        Rect {
            x0: EAST + c0 as f64 * GSD,
            x1: EAST + c1 as f64 * GSD,
            y0: NORTH - r1 as f64 * GSD,
            y1: NORTH - r0 as f64 * GSD,
        }
    }

    fn contains(&self, (x, y): (f64, f64)) -> bool {
        x > self.x0 && x < self.x1 && y > self.y0 && y < self.y1
    }

    /// How far (m) a point lies outside the rectangle (0 inside).
    fn outside_by(&self, (x, y): (f64, f64)) -> f64 {
        let dx = (self.x0 - x).max(x - self.x1).max(0.0);
        let dy = (self.y0 - y).max(y - self.y1).max(0.0);
        dx.hypot(dy)
    }

    /// Whether the convex quadrilateral `q` overlaps this rectangle by more than
    /// `tol` metres (separating axes: the rectangle's two, the quad's four).
    fn overlaps(&self, q: &[(f64, f64); 4], tol: f64) -> bool {
        let r = [(self.x0, self.y0), (self.x1, self.y0), (self.x1, self.y1), (self.x0, self.y1)];
        let mut axes = vec![(1.0, 0.0), (0.0, 1.0)];
        for i in 0..4 {
            let (a, b) = (q[i], q[(i + 1) % 4]);
            let (ex, ey) = (b.0 - a.0, b.1 - a.1);
            let n = ex.hypot(ey);
            axes.push((-ey / n, ex / n));
        }
        axes.iter().all(|&(ax, ay)| {
            let proj = |p: &[(f64, f64)]| {
                let v: Vec<f64> = p.iter().map(|&(x, y)| x * ax + y * ay).collect();
                (v.iter().cloned().fold(f64::MAX, f64::min), v.iter().cloned().fold(f64::MIN, f64::max))
            };
            let ((r0, r1), (q0, q1)) = (proj(&r), proj(q));
            r1.min(q1) - r0.max(q0) > tol
        })
    }
}

/// Where a template's pixels may reach beyond the valid pixels they were
/// resampled from: the lat/lon of its corners carry centimetres of tangent-plane
/// and terrain approximation, and the level GSD is rounded up to three digits
/// (half a pixel of the rounding at each edge).
fn edge_tolerance_m(t: &Template) -> f64 {
    0.1 + 0.01 * t.gsd_m
}

/// A GeoTIFF band rewritten in place with the gdal crate: 0 where `transparent`, else 255.
fn write_alpha(path: &Path, band: usize, transparent: impl Fn(usize, usize) -> bool) {
    let ds = Dataset::open_ex(
        path,
        DatasetOptions {
            open_flags: GdalOpenFlags::GDAL_OF_UPDATE | GdalOpenFlags::GDAL_OF_RASTER,
            ..Default::default()
        },
    )
    .unwrap();
    let (w, h) = ds.raster_size();
    let data: Vec<u8> = (0..w * h).map(|i| if transparent(i % w, i / w) { 0 } else { 255 }).collect();
    let mut b = ds.rasterband(band).unwrap();
    b.write((0, 0), (w, h), &mut Buffer::new((w, h), data)).unwrap();
}

/// Asserts that no template of `b` takes pixels from the masked `region`
/// (neither its centre nor its footprint lies there). Returns how many templates.
fn assert_none_in(b: &Built, region: Rect, utm: &Utm) -> usize {
    for t in &b.templates {
        let c = utm.centre(t);
        assert!(
            !region.contains(c),
            "{}: template {} (level {}) is centred in the masked region",
            b.name,
            t.id,
            t.level
        );
        let q = utm.corners(t);
        assert!(
            !region.overlaps(&q, edge_tolerance_m(t)),
            "{}: template {} (level {}) reaches into the masked region {region:?}: corners {q:?}",
            b.name,
            t.id,
            t.level
        );
    }
    b.templates.len()
}

#[test]
fn ortho_mosaic_side_by_side() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let reference = build_ell(d, "reference", &[&ortho], &[&dem], &[]);
    let half = SIZE / 2;
    let (west, east) = (d.join("west.tif"), d.join("east.tif"));
    translate(&ortho, &west, &["-srcwin", "0", "0", &half.to_string(), &SIZE.to_string()]);
    translate(&ortho, &east, &["-srcwin", &half.to_string(), "0", &half.to_string(), &SIZE.to_string()]);
    let mosaic = build_ell(d, "mosaic", &[&west, &east], &[&dem], &[]);
    assert_similar_count(&mosaic, &reference);

    let utm = Utm::new();
    let seam = EAST + half as f64 * GSD;
    let xs: Vec<f64> = mosaic.templates.iter().map(|t| utm.centre(t).0).collect();
    assert!(xs.iter().any(|&x| x < seam), "no template west of the seam");
    assert!(xs.iter().any(|&x| x > seam), "no template east of the seam");
    // Templates with at least one template pixel column on either side of the
    // seam: read from both files at once, so the files were read as one mosaic.
    let straddle = straddling(&mosaic, seam, &utm);
    eprintln!("{} templates straddle the seam", straddle.len());
    assert!(!straddle.is_empty(), "no template straddles the seam between the two orthos");
    // They are the very templates cut from the single file.
    for t in &straddle {
        let twin = reference
            .templates
            .iter()
            .find(|r| r.level == t.level && centre_distance_m(r, t) < 0.05)
            .unwrap_or_else(|| {
                panic!("template {} (level {}) on the seam is not in the single-file build", t.id, t.level)
            });
        assert_eq!(
            max_pixel_diff(t, twin),
            0,
            "template {} on the seam differs from the single-file one",
            t.id
        );
    }
    assert_same_templates(&mosaic, &reference, 0, 1e-6);
    let sources = mosaic.meta["sources"].as_array().unwrap();
    assert_eq!(sources.len(), 1, "one mosaic expected: {sources:?}");
    assert_eq!(sources[0]["files"].as_array().unwrap().len(), 2, "{sources:?}");
}

#[test]
fn ortho_mosaic_overlapping() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let reference = build_ell(d, "reference", &[&ortho], &[&dem], &[]);
    // Columns 0..500 and 300..800: 200 columns (400 m) in both files.
    let (west, east) = (d.join("west.tif"), d.join("east.tif"));
    translate(&ortho, &west, &["-srcwin", "0", "0", "500", &SIZE.to_string()]);
    translate(&ortho, &east, &["-srcwin", "300", "0", "500", &SIZE.to_string()]);
    let mosaic = build_ell(d, "mosaic", &[&west, &east], &[&dem], &[]);
    assert_similar_count(&mosaic, &reference);
    let utm = Utm::new();
    // Both files' inner edges are crossed by templates (each needs the other file).
    for edge in [EAST + 300.0 * GSD, EAST + 500.0 * GSD] {
        let n = straddling(&mosaic, edge, &utm).len();
        assert!(n > 0, "no template straddles x = {edge}");
    }
    // Processed as one raster: no duplicates in the overlap, and the same
    // selection (grid of cells) as the single file. Per-file processing would
    // give other cells, other centres, and more templates.
    assert_same_templates(&mosaic, &reference, 0, 1e-6);
}

/// The DEM grid these tests assume `trn synth` writes.
fn check_dem_grid(dem: &Path) {
    let ds = Dataset::open(dem).unwrap();
    assert_eq!(ds.raster_size(), (DEM_SIZE, DEM_SIZE), "synthetic DEM size changed");
    let gt = ds.geo_transform().unwrap();
    let expect = [EAST - 2.0 * DEM_GSD, DEM_GSD, 0.0, NORTH + 2.0 * DEM_GSD, 0.0, -DEM_GSD];
    assert_eq!(gt, expect, "synthetic DEM grid changed");
}

/// Templates of `b` with at least one template pixel column on either side of
/// the UTM line x = `seam`.
fn straddling<'a>(b: &'a Built, seam: f64, utm: &Utm) -> Vec<&'a Template> {
    b.templates
        .iter()
        .filter(|t| {
            let q = utm.corners(t);
            q.iter().any(|p| p.0 < seam - t.gsd_m) && q.iter().any(|p| p.0 > seam + t.gsd_m)
        })
        .collect()
}

#[test]
fn sixteen_bit_ortho_mosaic() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let rgb16 = d.join("rgb16.tif");
    translate(&ortho, &rgb16, &["-ot", "UInt16", "-scale", "0", "255", "0", "60000"]);
    let reference = build_ell(d, "rgb16", &[&rgb16], &[&dem], &[]);
    let half = SIZE / 2;
    let (west, east) = (d.join("west16.tif"), d.join("east16.tif"));
    translate(&rgb16, &west, &["-srcwin", "0", "0", &half.to_string(), &SIZE.to_string()]);
    translate(&rgb16, &east, &["-srcwin", &half.to_string(), "0", &half.to_string(), &SIZE.to_string()]);
    let mosaic = build_ell(d, "mosaic16", &[&west, &east], &[&dem], &[]);
    // As the 8-bit mosaic: one raster, one grey-level stretch, templates across the seam.
    let utm = Utm::new();
    let seam = EAST + half as f64 * GSD;
    let over = straddling(&mosaic, seam, &utm).len();
    let groups = mosaic.meta["sources"].as_array().map(|a| a.len()).unwrap_or(0);
    let dropped = mosaic.log.lines().find(|l| l.contains("dropped")).unwrap_or_default();
    eprintln!("16-bit mosaic: {groups} source group(s), {over} templates over the seam; {dropped}");
    assert!(
        over > 0 && groups == 1,
        "the two halves of a 16-bit ortho are not read as one mosaic: {groups} sources, \
         {over} templates over the seam ({} from the single file)",
        straddling(&reference, seam, &utm).len()
    );
    assert_similar_count(&mosaic, &reference);
}

/// The columns `west_cols` of `ortho` kept in UTM (RGB, or RGBA with
/// `west_alpha`) and `east_cols` warped to lat/lon with an alpha band.
fn cut_west_east(
    d: &Path,
    ortho: &Path,
    name: &str,
    west_cols: (usize, usize),
    east_cols: (usize, usize),
    west_alpha: bool,
) -> (PathBuf, PathBuf) {
    let west = d.join(format!("{name}-west.tif"));
    let east_utm = d.join(format!("{name}-east-utm.tif"));
    let east = d.join(format!("{name}-east-4326.tif"));
    let win =
        |(c0, c1): (usize, usize)| [c0.to_string(), "0".into(), (c1 - c0).to_string(), SIZE.to_string()];
    let w = win(west_cols);
    let alpha: &[&str] =
        if west_alpha { &["-b", "1", "-b", "2", "-b", "3", "-b", "mask", "-co", "ALPHA=YES"] } else { &[] };
    translate(ortho, &west, &[&["-srcwin", &w[0], &w[1], &w[2], &w[3]][..], alpha].concat());
    let e = win(east_cols);
    translate(ortho, &east_utm, &["-srcwin", &e[0], &e[1], &e[2], &e[3]]);
    warp(&east_utm, &east, &["-t_srs", "EPSG:4326", "-r", "bilinear", "-dstalpha"]);
    std::fs::remove_file(&east_utm).unwrap();
    (west, east)
}

#[test]
fn ortho_mosaic_across_crs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let gsd = ["--base-gsd", "2.4"];
    let reference = build_ell(d, "reference", &[&ortho], &[&dem], &gsd);
    let utm = Utm::new();
    // West part in UTM, east part warped to lat/lon: the builder warps one onto
    // the other's grid and reads them as one mosaic. Side by side (seam at
    // column 400), then overlapping (columns 300..500 in both).
    for (name, west_cols, east_cols) in
        [("side-by-side", (0, 400), (400, 800)), ("overlapping", (0, 500), (300, 800))]
    {
        // RGBA like the warped east part: the same bands.
        let (west, east) = cut_west_east(d, &ortho, name, west_cols, east_cols, true);
        let alone_w = build_ell(d, &format!("{name}-west-alone"), &[&west], &[&dem], &gsd);
        let alone_e = build_ell(d, &format!("{name}-east-alone"), &[&east], &[&dem], &gsd);
        let mosaic = build_ell(d, &format!("{name}-mosaic"), &[&west, &east], &[&dem], &gsd);
        // One raster: the coarser file warped onto the finer one's grid.
        let groups = mosaic.meta["sources"].as_array().map(|a| a.len()).unwrap_or(0);
        let warped = mosaic.log.lines().find(|l| l.contains("warped onto the grid of")).unwrap_or_default();
        assert!(groups == 1 && !warped.is_empty(), "{name}: {groups} source groups; log: {}", mosaic.log);
        let host_is_west = warped.contains(&*west.to_string_lossy());
        // The host's edge facing the other file: templates reach across it,
        // as they would in a single file (no band lost along the seam).
        let (x_w, x_e) = (EAST + west_cols.1 as f64 * GSD, EAST + east_cols.0 as f64 * GSD);
        let (seam, host_alone, side) =
            if host_is_west { (x_w, &alone_w, -1.0) } else { (x_e, &alone_e, 1.0) };
        let over = straddling(&mosaic, seam, &utm).len();
        let over_ref = straddling(&reference, seam, &utm).len();
        eprintln!("{name}: {warped}; {over} templates over the seam (single file: {over_ref})");
        assert!(
            over_ref > 0 && over as f64 >= 0.5 * over_ref as f64,
            "{name}: {over} templates over the seam, single file {over_ref}"
        );
        // Per level, the strip within one footprint of the seam holds about
        // what the single file holds there (no gap, no duplicates).
        let levels: std::collections::BTreeSet<u8> = reference.templates.iter().map(|t| t.level).collect();
        for level in levels {
            let strip = |b: &Built| {
                b.templates
                    .iter()
                    .filter(|t| {
                        t.level == level && (utm.centre(t).0 - seam).abs() < t.width_px as f64 * t.gsd_m
                    })
                    .count() as f64
            };
            let (m, r) = (strip(&mosaic), strip(&reference));
            if r >= 6.0 {
                assert!(
                    (0.6..=1.4).contains(&(m / r)),
                    "{name}: level {level}: {m} templates along the seam, single file {r}"
                );
            }
        }
        // Away from the seam, each side holds about what the single file holds
        // there, and what its file alone holds (the cells are the mosaic's, so
        // the templates themselves differ).
        for (alone, sgn) in [(host_alone, side), (if host_is_west { &alone_e } else { &alone_w }, -side)] {
            let far = |b: &Built| {
                b.templates
                    .iter()
                    .filter(|t| sgn * (utm.centre(t).0 - seam) > 2.0 * t.width_px as f64 * t.gsd_m)
                    .count() as f64
            };
            let (m, a, r) = (far(&mosaic), far(alone), far(&reference));
            println!(
                "{name}: side {sgn}: {m} templates away from the seam, {a} alone, {r} in the single file"
            );
            assert!(
                r > 20.0 && (m - r).abs() <= 0.25 * r && (m - a).abs() <= 0.25 * a,
                "{name}: {m} {a} {r}"
            );
        }
        assert_similar_count(&mosaic, &reference);
    }
}

#[test]
fn ortho_groups_with_other_bands_are_deduplicated() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let gsd = ["--base-gsd", "2.4"];
    let reference = build_ell(d, "reference", &[&ortho], &[&dem], &gsd);
    let utm = Utm::new();
    // West part in UTM (RGB), east part warped to lat/lon (RGBA): other bands,
    // so they are built apart and streamed as one. Side by side (seam at
    // column 400), then overlapping (columns 300..500 in both).
    for (name, west_cols, east_cols) in
        [("side-by-side", (0, 400), (400, 800)), ("overlapping", (0, 500), (300, 800))]
    {
        let (west, east) = cut_west_east(d, &ortho, name, west_cols, east_cols, false);
        let alone_w = build_ell(d, &format!("{name}-west-alone"), &[&west], &[&dem], &gsd);
        let alone_e = build_ell(d, &format!("{name}-east-alone"), &[&east], &[&dem], &gsd);
        let mosaic = build_ell(d, &format!("{name}-mosaic"), &[&west, &east], &[&dem], &gsd);
        let dropped = mosaic.log.lines().find(|l| l.contains("dropped")).unwrap_or_default();
        eprintln!("{name}: {dropped}");
        // Duplicates (the same landmark from both files) are gone.
        for (i, a) in mosaic.templates.iter().enumerate() {
            for b in &mosaic.templates[i + 1..] {
                if a.level == b.level && a.source != b.source {
                    let dist = centre_distance_m(a, b);
                    assert!(
                        dist > 2.0 * a.gsd_m,
                        "{name}: templates {} and {} {dist:.1} m apart",
                        a.id,
                        b.id
                    );
                }
            }
        }
        // Templates far from where the files meet (farther than the half cell
        // within which duplicates are looked for) are all kept.
        let (x_w, x_e) = (EAST + west_cols.1 as f64 * GSD, EAST + east_cols.0 as f64 * GSD);
        let mut lost = Vec::new();
        // (build, side: -1 west / +1 east, where the other file begins)
        for (alone, side, limit) in [(&alone_w, -1.0, x_e.min(x_w)), (&alone_e, 1.0, x_w.max(x_e))] {
            for t in &alone.templates {
                let reach = 0.5 * 64.0 * t.gsd_m;
                if side * (utm.centre(t).0 - limit) > reach
                    && !mosaic.templates.iter().any(|m| m.level == t.level && centre_distance_m(m, t) < 0.05)
                {
                    lost.push((alone.name.clone(), t.level, utm.centre(t)));
                }
            }
        }
        assert!(
            lost.is_empty(),
            "{name}: {} templates of the files alone, far from where they meet, are missing from the mosaic \
             ({} templates; {dropped}): {:?}",
            lost.len(),
            mosaic.templates.len(),
            &lost[..lost.len().min(5)]
        );
        assert_similar_count(&mosaic, &reference);
    }
}

#[test]
fn dem_mosaic_side_by_side() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    check_dem_grid(&dem);
    let reference = build_ell(d, "reference", &[&ortho], &[&dem], &[]);
    let half = DEM_SIZE / 2;
    let (west, east) = (d.join("dem-west.tif"), d.join("dem-east.tif"));
    translate(&dem, &west, &["-srcwin", "0", "0", &half.to_string(), &DEM_SIZE.to_string()]);
    translate(&dem, &east, &["-srcwin", &half.to_string(), "0", &half.to_string(), &DEM_SIZE.to_string()]);
    let mosaic = build_ell(d, "dem-mosaic", &[&ortho], &[&west, &east], &[]);
    assert_similar_count(&mosaic, &reference);
    // The two DEM files together cover every template: terrain under a
    // template crossing their seam comes from both, so no template is lost.
    let utm = Utm::new();
    let seam = EAST - 2.0 * DEM_GSD + half as f64 * DEM_GSD;
    let straddle = |b: &Built| {
        b.templates
            .iter()
            .filter(|t| {
                let q = utm.corners(t);
                q.iter().any(|p| p.0 < seam) && q.iter().any(|p| p.0 > seam)
            })
            .count()
    };
    let (over_seam, over_seam_ref) = (straddle(&mosaic), straddle(&reference));
    eprintln!("templates over the DEM seam: {over_seam} (single DEM: {over_seam_ref})");
    assert!(over_seam_ref > 0, "the test needs templates over the DEM seam (x = {seam})");
    let rejected = mosaic.log.lines().find(|l| l.contains("rejected")).unwrap_or_default();
    assert!(
        over_seam > 0,
        "no template over the seam between the two DEM files ({over_seam_ref} with the single DEM): \
         terrain is not read across DEM files; build log: {rejected}"
    );
    assert_same_templates(&mosaic, &reference, 0, 1e-6);
}

#[test]
fn sixteen_bit_orthos() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let reference = build_ell(d, "rgb8", &[&ortho], &[&dem], &[]);
    let rgb16 = d.join("rgb16.tif");
    translate(&ortho, &rgb16, &["-ot", "UInt16", "-scale", "0", "255", "0", "60000"]);
    let grey16 = d.join("grey16.tif");
    translate(&ortho, &grey16, &["-ot", "UInt16", "-scale", "0", "255", "0", "60000", "-b", "1"]);
    for (name, path, bands) in [("rgb16", &rgb16, 3), ("grey16", &grey16, 1)] {
        let b = build_ell(d, name, &[path], &[&dem], &[]);
        assert_similar_count(&b, &reference);
        let src = &b.meta["sources"][0];
        assert_eq!(src["band_type"], "UInt16", "{name}: {src}");
        assert_eq!(src["luminance_bands"].as_array().unwrap().len(), bands, "{name}: {src}");
        assert!(b.log.contains("UInt16"), "{name}: the log does not name the band type:\n{}", b.log);
        // Stretched to 0..255 from the 16-bit range: the full grey scale is used.
        let (lo, hi) = b
            .templates
            .iter()
            .flat_map(|t| t.pixels.iter())
            .fold((255u8, 0u8), |(lo, hi), &p| (lo.min(p), hi.max(p)));
        assert!(lo < 40 && hi > 215, "{name}: grey levels {lo}..{hi}: not stretched from 16 bits");
        let pairs = twins(&b.templates, &reference.templates).len();
        eprintln!("{name}: {pairs} of {} templates at the 8-bit build's centres", b.templates.len());
    }
}

#[test]
fn grey_and_grey_alpha_orthos() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let utm = Utm::new();
    // One band: the red one alone, 8-bit.
    let grey = d.join("grey.tif");
    translate(&ortho, &grey, &["-b", "1"]);
    // Without the density fill, which gives cells by the transparent half's
    // edge more landmarks (as by a scene's edge), so half the ortho is about
    // half the templates.
    let g = build_ell(d, "grey", &[&grey], &[&dem], &["--fill-share", "0"]);
    assert_eq!(g.meta["sources"][0]["luminance_bands"], serde_json::json!([[1, 1.0]]));
    // Two bands: grey + alpha, transparent over the northern half.
    let grey_alpha = d.join("grey-alpha.tif");
    translate(&ortho, &grey_alpha, &["-b", "1", "-b", "1", "-colorinterp", "gray,alpha"]);
    write_alpha(&grey_alpha, 2, |_, row| row < SIZE / 2);
    let ga = build_ell(d, "grey-alpha", &[&grey_alpha], &[&dem], &["--fill-share", "0"]);
    assert_eq!(ga.meta["sources"][0]["luminance_bands"], serde_json::json!([[1, 1.0]]));
    let n = assert_none_in(&ga, Rect::ortho_px(0, SIZE, 0, SIZE / 2), &utm);
    let full = g.templates.len() as f64;
    assert!(
        (n as f64) > 0.3 * full && (n as f64) < 0.7 * full,
        "grey + alpha over half the ortho: {n} templates, {full} without alpha"
    );
    // The unmasked half gives the same templates as the grey ortho there
    // (cells away from the alpha edge).
    let south = Rect::ortho_px(0, SIZE, SIZE / 2 + 100, SIZE);
    let in_south: Vec<&Template> =
        g.templates.iter().filter(|t| t.level == 0 && south.contains(utm.centre(t))).collect();
    let kept = in_south
        .iter()
        .filter(|t| ga.templates.iter().any(|x| x.level == 0 && centre_distance_m(x, t) < 0.05))
        .count();
    eprintln!("grey-alpha: {kept} of {} level-0 grey templates in the south kept", in_south.len());
    assert_eq!(kept, in_south.len(), "grey + alpha lost templates far from the transparent half");
}

#[test]
fn rgb_and_rgba_orthos() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let utm = Utm::new();
    // Without the density fill, as in `grey_and_grey_alpha_orthos`.
    let rgb = build_ell(d, "rgb", &[&ortho], &[&dem], &["--fill-share", "0"]);
    assert_eq!(rgb.meta["sources"][0]["luminance_bands"].as_array().unwrap().len(), 3);
    // Four bands: RGB + alpha, transparent over the western half.
    let rgba = d.join("rgba.tif");
    translate(
        &ortho,
        &rgba,
        &["-b", "1", "-b", "2", "-b", "3", "-b", "1", "-colorinterp", "red,green,blue,alpha"],
    );
    write_alpha(&rgba, 4, |col, _| col < SIZE / 2);
    let b = build_ell(d, "rgba", &[&rgba], &[&dem], &["--fill-share", "0"]);
    let bands: Vec<u64> = b.meta["sources"][0]["luminance_bands"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x[0].as_u64().unwrap())
        .collect();
    assert_eq!(bands, [1, 2, 3], "RGBA luminance must come from the colour bands");
    let n = assert_none_in(&b, Rect::ortho_px(0, SIZE / 2, 0, SIZE), &utm);
    let full = rgb.templates.len() as f64;
    assert!(
        (n as f64) > 0.3 * full && (n as f64) < 0.7 * full,
        "RGBA with alpha over half the ortho: {n} templates, {full} from RGB"
    );
    // Away from the alpha edge the templates are those of the RGB ortho, pixel for pixel.
    let east = Rect::ortho_px(SIZE / 2 + 100, SIZE, 0, SIZE);
    for t in rgb.templates.iter().filter(|t| t.level == 0 && east.contains(utm.centre(t))) {
        let twin =
            b.templates.iter().find(|x| x.level == 0 && centre_distance_m(x, t) < 0.05).unwrap_or_else(
                || panic!("RGBA build lost RGB template {} far from the transparent half", t.id),
            );
        assert_eq!(max_pixel_diff(t, twin), 0);
    }
    // An RGBA whose alpha is opaque everywhere gives exactly the RGB templates.
    let opaque = d.join("rgba-opaque.tif");
    translate(
        &ortho,
        &opaque,
        &["-b", "1", "-b", "2", "-b", "3", "-b", "1", "-colorinterp", "red,green,blue,alpha"],
    );
    write_alpha(&opaque, 4, |_, _| false);
    let o = build_ell(d, "rgba-opaque", &[&opaque], &[&dem], &["--fill-share", "0"]);
    assert_same_templates(&o, &rgb, 0, 1e-6);
}

#[test]
fn nodata_frame_and_dem_hole() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = (d.join("framed.tif"), d.join("dem.tif"));
    let border = 100;
    let o = common::run(&[
        "synth",
        "--ortho",
        s(&ortho),
        "--dem",
        s(&dem),
        "--size",
        &SIZE.to_string(),
        "--gsd",
        &GSD.to_string(),
        "--east",
        &EAST.to_string(),
        "--seed",
        &SEED.to_string(),
        "--nodata-border",
        &border.to_string(),
    ]);
    assert!(o.status.success(), "synth failed: {}", common::stderr(&o));
    let info = gdal_tool("gdalinfo", &[s(&ortho)]);
    assert!(info.contains("NoData Value=0"), "synth --nodata-border wrote no nodata value:\n{info}");
    check_dem_grid(&dem);
    // A 5 x 5 pixel hole of nodata in the DEM, inside the valid ortho.
    let hole_px = (20usize, 20usize, 5usize);
    {
        let ds = Dataset::open_ex(
            &dem,
            DatasetOptions {
                open_flags: GdalOpenFlags::GDAL_OF_UPDATE | GdalOpenFlags::GDAL_OF_RASTER,
                ..Default::default()
            },
        )
        .unwrap();
        let mut band = ds.rasterband(1).unwrap();
        assert_eq!(band.no_data_value(), Some(-9999.0));
        let n = hole_px.2;
        band.write(
            (hole_px.0 as isize, hole_px.1 as isize),
            (n, n),
            &mut Buffer::new((n, n), vec![-9999f32; n * n]),
        )
        .unwrap();
    }
    let dem_x0 = EAST - 2.0 * DEM_GSD;
    let dem_y0 = NORTH + 2.0 * DEM_GSD;
    let hole = Rect {
        x0: dem_x0 + hole_px.0 as f64 * DEM_GSD,
        x1: dem_x0 + (hole_px.0 + hole_px.2) as f64 * DEM_GSD,
        y0: dem_y0 - (hole_px.1 + hole_px.2) as f64 * DEM_GSD,
        y1: dem_y0 - hole_px.1 as f64 * DEM_GSD,
    };
    let valid = Rect::ortho_px(border, SIZE - border, border, SIZE - border);
    assert!(valid.contains((hole.x0, hole.y0)) && valid.contains((hole.x1, hole.y1)));

    let b = build_ell(d, "framed", &[&ortho], &[&dem], &[]);
    let utm = Utm::new();
    let mut worst = f64::MIN;
    for t in &b.templates {
        let q = utm.corners(t);
        // The footprint stays inside the valid pixels.
        let out = q.iter().map(|&p| valid.outside_by(p)).fold(0.0, f64::max);
        assert!(
            out <= edge_tolerance_m(t),
            "template {} (level {}, GSD {:.2} m) reaches {out:.2} m into the nodata frame: corners {q:?}",
            t.id,
            t.level,
            t.gsd_m
        );
        worst = worst.max(out);
        // No terrain from the DEM hole: the footprint does not overlap it.
        assert!(
            !hole.overlaps(&q, 1.0),
            "template {} (level {}) lies over the DEM's nodata hole {hole:?}: corners {q:?}",
            t.id,
            t.level
        );
    }
    let levels: std::collections::BTreeSet<u8> = b.templates.iter().map(|t| t.level).collect();
    eprintln!(
        "{} templates on levels {levels:?}, worst reach into the frame {worst:.3} m",
        b.templates.len()
    );
    assert!(levels.len() >= 3, "templates on levels {levels:?} only");
}

/// The luminance (Rec. 601, as the builder's documented rule) of the synthetic
/// RGB ortho, row-major, with its geotransform.
struct Reference {
    lum: Vec<f64>,
    gt: [f64; 6],
    width: usize,
    height: usize,
}

impl Reference {
    fn load(path: &Path) -> Self {
        let ds = Dataset::open(path).unwrap();
        let (width, height) = ds.raster_size();
        let mut lum = vec![0f64; width * height];
        for (b, w) in [(1, 0.299), (2, 0.587), (3, 0.114)] {
            let buf = ds.rasterband(b).unwrap().read_band_as::<f64>().unwrap();
            for (l, &v) in lum.iter_mut().zip(buf.data()) {
                *l += w * v;
            }
        }
        Self { lum, gt: ds.geo_transform().unwrap(), width, height }
    }

    /// Half the resolution (2 x 2 means): templates of coarse levels are
    /// compared with an image free of aliasing.
    fn halve(&self) -> Self {
        let (width, height) = (self.width / 2, self.height / 2);
        let v = |c: usize, r: usize| self.lum[r * self.width + c];
        let lum = (0..width * height)
            .map(|i| {
                let (c, r) = (2 * (i % width), 2 * (i / width));
                (v(c, r) + v(c + 1, r) + v(c, r + 1) + v(c + 1, r + 1)) / 4.0
            })
            .collect();
        let g = self.gt;
        Self { lum, gt: [g[0], 2.0 * g[1], g[2], g[3], g[4], 2.0 * g[5]], width, height }
    }

    /// Bilinear luminance at UTM (x, y); `None` outside the pixel centres.
    fn at(&self, x: f64, y: f64) -> Option<f64> {
        let g = &self.gt;
        let (c, r) = ((x - g[0]) / g[1] - 0.5, (y - g[3]) / g[5] - 0.5);
        if !(c >= 0.0 && r >= 0.0 && c < (self.width - 1) as f64 && r < (self.height - 1) as f64) {
            return None;
        }
        let (ic, ir) = (c as usize, r as usize);
        let (tc, tr) = (c - ic as f64, r - ir as f64);
        let v = |c: usize, r: usize| self.lum[r * self.width + c];
        Some(
            (v(ic, ir) * (1.0 - tc) + v(ic + 1, ir) * tc) * (1.0 - tr)
                + (v(ic, ir + 1) * (1.0 - tc) + v(ic + 1, ir + 1) * tc) * tr,
        )
    }

    /// Finds template `t` again in the original UTM ortho, resampled here
    /// (PROJ through the gdal crate, own bilinear) north up at the template's GSD
    /// around where the template says it lies, `margin` pixels more each side.
    /// Returns the NCC peak and its distance (template pixels) from the centre.
    fn refind(&self, t: &Template, utm: &Utm, margin: usize) -> (f64, f64) {
        let tw = t.width_px as usize;
        let size = tw + 2 * margin;
        let c0 = (size as f64 - 1.0) / 2.0;
        let (m_lat, m_lon) = trn_geodesy::metres_per_degree(t.center.lat_deg);
        let mut xs = Vec::with_capacity(size * size);
        let mut ys = Vec::with_capacity(size * size);
        for j in 0..size {
            for i in 0..size {
                let (e, n) = ((i as f64 - c0) * t.gsd_m, (c0 - j as f64) * t.gsd_m);
                xs.push(t.center.lon_deg + e / m_lon);
                ys.push(t.center.lat_deg + n / m_lat);
            }
        }
        let mut zs = vec![0.0; xs.len()];
        utm.to_utm.transform_coords(&mut xs, &mut ys, &mut zs).unwrap();
        let img: Vec<f64> = xs.iter().zip(&ys).map(|(&x, &y)| self.at(x, y).unwrap_or(f64::NAN)).collect();
        let tpl: Vec<f64> = t.pixels.iter().map(|&v| v as f64).collect();
        let n = (tw * tw) as f64;
        let span = 2 * margin + 1;
        let mut scores = vec![f64::NAN; span * span];
        for dy in 0..span {
            for dx in 0..span {
                let (mut st, mut si, mut stt, mut sii, mut sti) = (0.0, 0.0, 0.0, 0.0, 0.0);
                for r in 0..tw {
                    for c in 0..tw {
                        let (a, b) = (tpl[r * tw + c], img[(r + dy) * size + c + dx]);
                        st += a;
                        si += b;
                        stt += a * a;
                        sii += b * b;
                        sti += a * b;
                    }
                }
                // NaN where the window leaves the ortho.
                scores[dy * span + dx] =
                    (sti - st * si / n) / ((stt - st * st / n) * (sii - si * si / n)).sqrt().max(1e-12);
            }
        }
        let best = (0..scores.len())
            .filter(|&i| scores[i].is_finite())
            .max_by(|&a, &b| scores[a].total_cmp(&scores[b]))
            .expect("template window outside the original ortho");
        let (bx, by) = (best % span, best / span);
        let peak = scores[best];
        // Sub-pixel peak: a parabola through the neighbours, where they exist.
        let score = |x: isize, y: isize| {
            (x >= 0 && y >= 0 && (x as usize) < span && (y as usize) < span)
                .then(|| scores[y as usize * span + x as usize])
                .filter(|v| v.is_finite())
        };
        let sub = |l: Option<f64>, r: Option<f64>| match (l, r) {
            (Some(l), Some(r)) if (l - 2.0 * peak + r).abs() > 1e-12 => 0.5 * (l - r) / (l - 2.0 * peak + r),
            _ => 0.0,
        };
        let (ix, iy) = (bx as isize, by as isize);
        let ox = bx as f64 + sub(score(ix - 1, iy), score(ix + 1, iy)) - margin as f64;
        let oy = by as f64 + sub(score(ix, iy - 1), score(ix, iy + 1)) - margin as f64;
        (peak, ox.hypot(oy))
    }
}

/// Bilinear height of the synthetic UTM DEM at a template's centre.
fn dem_height(dem: &Dataset, data: &[f64], utm: &Utm, t: &Template) -> f64 {
    let gt = dem.geo_transform().unwrap();
    let (w, _) = dem.raster_size();
    let (x, y) = utm.centre(t);
    let (c, r) = ((x - gt[0]) / gt[1] - 0.5, (y - gt[3]) / gt[5] - 0.5);
    let (ic, ir) = (c.floor() as usize, r.floor() as usize);
    let (tc, tr) = (c - ic as f64, r - ir as f64);
    let at = |c: usize, r: usize| data[r * w + c];
    (at(ic, ir) * (1.0 - tc) + at(ic + 1, ir) * tc) * (1.0 - tr)
        + (at(ic, ir + 1) * (1.0 - tc) + at(ic + 1, ir + 1) * tc) * tr
}

#[test]
fn ortho_and_dem_in_other_crs_and_resolutions() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    // One level-0 GSD for all builds (the default follows the ortho's coarsest
    // pixel, which the warps change), so the template counts compare.
    let gsd = ["--base-gsd", "2.4"];
    let reference = build_ell(d, "reference", &[&ortho], &[&dem], &gsd);
    // Ortho in geographic lat/lon with an alpha band where the warp has no data.
    let ortho_ll = d.join("ortho-4326.tif");
    warp(&ortho, &ortho_ll, &["-t_srs", "EPSG:4326", "-r", "bilinear", "-dstalpha"]);
    // Ortho in Web Mercator (2.6 m map pixels for 2 m on the ground), nodata 0 around.
    let ortho_wm = d.join("ortho-3857.tif");
    warp(&ortho, &ortho_wm, &["-t_srs", "EPSG:3857", "-r", "bilinear", "-dstnodata", "0"]);
    // DEM in lat/lon at about 50 x 55 m (the original: 30 m in UTM).
    let dem_ll = d.join("dem-4326.tif");
    warp(&dem, &dem_ll, &["-t_srs", "EPSG:4326", "-tr", "0.0006", "0.0005", "-r", "bilinear"]);

    let utm = Utm::new();
    let extent = Rect::ortho_px(0, SIZE, 0, SIZE);
    // The original's luminance at 2, 4, 8, ... m: each template is compared
    // with the coarsest one not coarser than its GSD.
    let mut ref_pyramid = vec![Reference::load(&ortho)];
    for _ in 0..5 {
        let next = ref_pyramid.last().unwrap().halve();
        ref_pyramid.push(next);
    }
    let ref_for = |t: &Template| {
        let p = (t.gsd_m / GSD).log2().floor().max(0.0) as usize;
        &ref_pyramid[p.min(ref_pyramid.len() - 1)]
    };
    let dem_ds = Dataset::open(&dem).unwrap();
    let dem_data: Vec<f64> = dem_ds.rasterband(1).unwrap().read_band_as::<f64>().unwrap().data().to_vec();
    let cases: [(&str, &Path, &Path, f64); 3] = [
        // (name, ortho, DEM, largest height error expected from the DEM's resampling)
        // Same DEM: only the builder's per-tile interpolated lon/lat -> DEM map differs (sub-cm).
        ("ortho-4326+dem-utm", &ortho_ll, &dem, 0.01),
        ("ortho-3857+dem-4326", &ortho_wm, &dem_ll, 0.75),
        ("ortho-utm+dem-4326", &ortho, &dem_ll, 0.75),
    ];
    for (name, o, m, dh_tol) in cases {
        let b = build_ell(d, name, &[o], &[m], &gsd);
        assert_similar_count(&b, &reference);
        let (mut worst_ncc, mut worst_off, mut worst_dh, mut sum_off) = (1.0f64, 0.0f64, 0.0f64, 0.0);
        for t in &b.templates {
            // Inside the original ortho.
            let out = utm.corners(t).iter().map(|&p| extent.outside_by(p)).fold(0.0, f64::max);
            assert!(
                out <= edge_tolerance_m(t),
                "{name}: template {} (level {}) reaches {out:.2} m outside the ortho",
                t.id,
                t.level
            );
            // Where it says it is: found there again in the UTM original.
            let (ncc, off) = ref_for(t).refind(t, &utm, 3);
            assert!(
                ncc > 0.75 && off < 0.75,
                "{name}: template {} (level {}) found in the UTM original with NCC {ncc:.3} {off:.2} px away",
                t.id,
                t.level
            );
            // Its height is the original DEM's there.
            let dh = (t.center.h_m - dem_height(&dem_ds, &dem_data, &utm, t)).abs();
            assert!(dh <= dh_tol, "{name}: template {} height {:.2} m off the original DEM", t.id, dh);
            worst_ncc = worst_ncc.min(ncc);
            worst_off = worst_off.max(off);
            worst_dh = worst_dh.max(dh);
            sum_off += off;
        }
        let mean_off = sum_off / b.templates.len() as f64;
        eprintln!(
            "{name}: worst NCC {worst_ncc:.3}, offset {worst_off:.2} px (mean {mean_off:.3}), height error {worst_dh:.3} m"
        );
        assert!(mean_off < 0.15, "{name}: templates lie {mean_off:.3} px off on average");
        // Over the same area as the UTM build's templates (within a level-0 cell).
        let (bb, rb) = (centre_bounds(&b, &utm), centre_bounds(&reference, &utm));
        let cell = 64.0 * 2.4;
        let apart = bb.iter().zip(&rb).map(|(x, y)| (x - y).abs()).fold(0.0, f64::max);
        assert!(apart < cell, "{name}: template centres span {bb:?}, the UTM build's {rb:?}");
    }
}

/// UTM bounds (x0, x1, y0, y1) of a build's template centres.
fn centre_bounds(b: &Built, utm: &Utm) -> [f64; 4] {
    b.templates.iter().map(|t| utm.centre(t)).fold([f64::MAX, f64::MIN, f64::MAX, f64::MIN], |a, (x, y)| {
        [a[0].min(x), a[1].max(x), a[2].min(y), a[3].max(y)]
    })
}

#[test]
fn cog_vrt_and_jp2_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let reference = build_ell(d, "reference", &[&ortho], &[&dem], &[]);
    let (ortho_cog, dem_cog) = (d.join("ortho-cog.tif"), d.join("dem-cog.tif"));
    translate(&ortho, &ortho_cog, &["-of", "COG", "-co", "COMPRESS=DEFLATE"]);
    translate(&dem, &dem_cog, &["-of", "COG", "-co", "COMPRESS=DEFLATE"]);
    let cog = build_ell(d, "cog", &[&ortho_cog], &[&dem_cog], &[]);
    assert_similar_count(&cog, &reference);
    assert_same_templates(&cog, &reference, 0, 1e-6);

    let (ortho_vrt, dem_vrt) = (d.join("ortho.vrt"), d.join("dem.vrt"));
    gdal_tool("gdalbuildvrt", &["-q", s(&ortho_vrt), s(&ortho)]);
    gdal_tool("gdalbuildvrt", &["-q", s(&dem_vrt), s(&dem)]);
    let vrt = build_ell(d, "vrt", &[&ortho_vrt], &[&dem_vrt], &[]);
    assert_similar_count(&vrt, &reference);
    assert_same_templates(&vrt, &reference, 0, 1e-6);

    let formats = gdal_tool("gdalinfo", &["--formats"]);
    if !formats.lines().any(|l| l.trim_start().starts_with("JP2OpenJPEG")) {
        eprintln!("JPEG 2000 skipped: GDAL has no JP2OpenJPEG driver (gdalinfo --formats)");
        return;
    }
    // Lossless (reversible) JPEG 2000: the same pixels.
    let ortho_jp2 = d.join("ortho.jp2");
    translate(&ortho, &ortho_jp2, &["-of", "JP2OpenJPEG", "-co", "QUALITY=100", "-co", "REVERSIBLE=YES"]);
    let jp2 = build_ell(d, "jp2", &[&ortho_jp2], &[&dem], &[]);
    assert_similar_count(&jp2, &reference);
    assert_same_templates(&jp2, &reference, 0, 1e-6);
    // Lossy JPEG 2000 still builds, with a similar number of templates.
    let ortho_lossy = d.join("ortho-lossy.jp2");
    translate(&ortho, &ortho_lossy, &["-of", "JP2OpenJPEG", "-co", "QUALITY=25"]);
    let lossy = build_ell(d, "jp2-lossy", &[&ortho_lossy], &[&dem], &[]);
    assert_similar_count(&lossy, &reference);
}

/// EGM96 undulation at each (lon, lat) computed by PROJ through `gdaltransform`
/// (independent of the builder's own reading of the grid): the ellipsoidal
/// height of a point at EGM96 height 0.
fn egm96_undulation(points: &[(f64, f64)], horizontal: &str) -> Vec<f64> {
    use std::io::Write;
    use std::process::Stdio;
    let input: String = points.iter().map(|(x, y)| format!("{x} {y} 0\n")).collect();
    let mut child = Command::new("gdaltransform")
        .args(["-s_srs", &format!("{horizontal}+5773"), "-t_srs", "EPSG:4979"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("cannot run gdaltransform ({e}): install gdal-bin"));
    // Written from a thread: gdaltransform answers as it reads, and a full
    // stdout pipe would otherwise block both sides.
    let mut stdin = child.stdin.take().unwrap();
    let writer = std::thread::spawn(move || stdin.write_all(input.as_bytes()));
    let o = child.wait_with_output().unwrap();
    writer.join().unwrap().unwrap();
    assert!(o.status.success(), "gdaltransform failed: {}", String::from_utf8_lossy(&o.stderr));
    let text = String::from_utf8_lossy(&o.stdout);
    let n: Vec<f64> = text
        .lines()
        .map(|l| l.split_whitespace().nth(2).and_then(|z| z.parse().ok()).unwrap_or(f64::NAN))
        .collect();
    assert_eq!(n.len(), points.len(), "gdaltransform said:\n{text}{}", String::from_utf8_lossy(&o.stderr));
    assert!(n.iter().all(|v| v.is_finite()), "gdaltransform said:\n{text}");
    n
}

/// The line of the build log about `dem`.
fn dem_log_line<'a>(b: &'a Built, dem: &Path) -> &'a str {
    b.log
        .lines()
        .find(|l| l.contains(s(dem)) && l.contains("DEM"))
        .unwrap_or_else(|| panic!("{}: no log line about DEM {}:\n{}", b.name, dem.display(), b.log))
}

#[test]
fn dem_vertical_datum_egm96_from_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let ell = build_ell(d, "ellipsoid", &[&ortho], &[&dem], &[]);
    // The same heights declared as EGM96 in a compound CRS (UTM 13N + EGM96 height).
    let dem_egm = d.join("dem-egm96.tif");
    translate(&dem, &dem_egm, &["-a_srs", "EPSG:32613+5773"]);
    let egm = build(d, "egm96-from-file", &[&ortho], &[&dem_egm], &[]);
    let line = dem_log_line(&egm, &dem_egm).to_lowercase();
    eprintln!("log: {line}");
    assert!(
        line.contains("egm96") && line.contains("convert") && line.contains("file"),
        "the log does not say that EGM96 heights from the file's CRS were converted: {line}"
    );
    let conv = egm.meta["dems"][0]["vertical_conversion"].as_str().unwrap_or_default().to_string();
    assert!(conv.contains("egm96"), "metadata vertical_conversion: {conv:?}");

    // Same templates, heights shifted by the geoid undulation that PROJ computes there.
    let pairs = twins(&egm.templates, &ell.templates);
    assert_eq!(pairs.len(), ell.templates.len(), "the EGM96 build selected other templates");
    let pts: Vec<(f64, f64)> = pairs.iter().map(|(_, e)| (e.center.lon_deg, e.center.lat_deg)).collect();
    let undulation = egm96_undulation(&pts, "EPSG:4326");
    let diffs: Vec<f64> = pairs.iter().map(|(g, e)| g.center.h_m - e.center.h_m).collect();
    let (lo, hi) = diffs.iter().fold((f64::MAX, f64::MIN), |(lo, hi), &v| (lo.min(v), hi.max(v)));
    let worst = diffs.iter().zip(&undulation).map(|(dh, n)| (dh - n).abs()).fold(0.0, f64::max);
    eprintln!(
        "EGM96 - ellipsoid build heights: {lo:.3}..{hi:.3} m; PROJ's undulation {:.3}..{:.3} m; worst difference {worst:.4} m",
        undulation.iter().cloned().fold(f64::MAX, f64::min),
        undulation.iter().cloned().fold(f64::MIN, f64::max)
    );
    assert!(hi - lo < 0.5, "height shifts {lo:.3}..{hi:.3} m vary too much over 1.6 km");
    assert!(lo > -25.0 && hi < -5.0, "height shifts {lo:.3}..{hi:.3} m are not the EGM96 undulation here");
    assert!(worst < 0.05, "heights differ from PROJ's EGM96 conversion by up to {worst:.3} m");

    // --dem-vertical overrides the file (and says so).
    let over = build(d, "override", &[&ortho], &[&dem_egm], &["--dem-vertical", "ellipsoid"]);
    assert!(
        over.log.lines().any(|l| l.contains("WARN") && l.contains(s(&dem_egm)) && l.contains("overrides")),
        "no warning that --dem-vertical overrides the file's datum:\n{}",
        over.log
    );
    assert_same_templates(&over, &ell, 0, 1e-6);
}

#[test]
fn dem_vertical_datum_geographic_egm96_and_ellipsoidal_from_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    // The DEM in lat/lon (EPSG:4326, no vertical CRS) needs the flag...
    let dem_ll = d.join("dem-4326.tif");
    warp(&dem, &dem_ll, &["-t_srs", "EPSG:4326", "-tr", "0.0003", "0.0003", "-r", "bilinear"]);
    let ell = build_ell(d, "ellipsoid-flag", &[&ortho], &[&dem_ll], &[]);
    // ... a geographic 3D CRS (EPSG:4979: ellipsoidal heights) needs none.
    let dem_3d = d.join("dem-4979.tif");
    translate(&dem_ll, &dem_3d, &["-a_srs", "EPSG:4979"]);
    let e3d = build(d, "ellipsoid-4979", &[&ortho], &[&dem_3d], &[]);
    let line = dem_log_line(&e3d, &dem_3d).to_lowercase();
    assert!(line.contains("ellipsoidal") && line.contains("file"), "log: {line}");
    assert!(!line.contains("egm96"), "log: {line}");
    assert_same_templates(&e3d, &ell, 0, 1e-6);
    // ... the issue's example, EPSG:4326+5773 (EGM96 heights), is converted.
    let dem_egm = d.join("dem-4326-egm96.tif");
    translate(&dem_ll, &dem_egm, &["-a_srs", "EPSG:4326+5773"]);
    let egm = build(d, "egm96-4326", &[&ortho], &[&dem_egm], &[]);
    let line = dem_log_line(&egm, &dem_egm).to_lowercase();
    assert!(line.contains("egm96") && line.contains("convert"), "log: {line}");
    let pairs = twins(&egm.templates, &ell.templates);
    assert_eq!(pairs.len(), ell.templates.len(), "the EGM96 build selected other templates");
    let pts: Vec<(f64, f64)> = pairs.iter().map(|(_, e)| (e.center.lon_deg, e.center.lat_deg)).collect();
    let undulation = egm96_undulation(&pts, "EPSG:4326");
    let worst = pairs
        .iter()
        .zip(&undulation)
        .map(|((g, e), n)| (g.center.h_m - e.center.h_m - n).abs())
        .fold(0.0, f64::max);
    eprintln!("EPSG:4326+5773: heights within {worst:.4} m of PROJ's EGM96 conversion");
    assert!(worst < 0.05, "heights differ from PROJ's EGM96 conversion by up to {worst:.3} m");
}

#[test]
fn dem_compound_crs_with_ellipsoidal_height_needs_no_flag() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let ell = build_ell(d, "ellipsoid-flag", &[&ortho], &[&dem], &[]);
    // UTM 13N + a vertical CRS of ellipsoidal heights (WKT1 vertical datum type
    // 2002). PROJ reads it as a 3D projected CRS; GeoTIFF cannot hold it, a VRT
    // keeps the WKT.
    let wkt = concat!(
        r#"COMPD_CS["WGS 84 / UTM zone 13N + WGS 84 ellipsoidal height","#,
        r#"PROJCS["WGS 84 / UTM zone 13N",GEOGCS["WGS 84",DATUM["WGS_1984","#,
        r#"SPHEROID["WGS 84",6378137,298.257223563]],PRIMEM["Greenwich",0],"#,
        r#"UNIT["degree",0.0174532925199433]],PROJECTION["Transverse_Mercator"],"#,
        r#"PARAMETER["latitude_of_origin",0],PARAMETER["central_meridian",-105],"#,
        r#"PARAMETER["scale_factor",0.9996],PARAMETER["false_easting",500000],"#,
        r#"PARAMETER["false_northing",0],UNIT["metre",1]],"#,
        r#"VERT_CS["WGS 84 ellipsoidal height",VERT_DATUM["Ellipsoid",2002],UNIT["metre",1],AXIS["Up",UP]]]"#
    );
    let dem_vrt = d.join("dem-ellipsoidal.vrt");
    translate(&dem, &dem_vrt, &["-of", "VRT", "-a_srs", wkt]);
    let info = gdal_tool("gdalinfo", &[s(&dem_vrt)]);
    assert!(info.contains("ellipsoidal height"), "GDAL does not see the ellipsoidal height axis:\n{info}");
    let b = build(d, "ellipsoid-from-file", &[&ortho], &[&dem_vrt], &[]);
    let line = dem_log_line(&b, &dem_vrt).to_lowercase();
    assert!(line.contains("ellipsoidal") && line.contains("file"), "log: {line}");
    assert_same_templates(&b, &ell, 0, 1e-6);
}

/// `--camera/--altitude` sizes the ladder for the mission (every altitude of
/// it sees a level whose templates span 12-48 px), and `--coverage-plan` puts
/// in the report exactly what `trn coverage` says of the new database.
#[test]
fn mission_sizing_and_coverage_in_the_report() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = synth(d);
    let camera = d.join("camera.json");
    std::fs::write(&camera, common::CAMERA_640_JSON).unwrap();
    // Across the 1.6 km map, 1.45 km above its terrain (1520-1560 m), looking down.
    let plan = d.join("plan.json");
    std::fs::write(
        &plan,
        format!(
            r#"{{"camera": {}, "waypoints": [{{"lat_deg": 40.2815, "lon_deg": -105.7045, "h_m": 3000}},
                {{"lat_deg": 40.2815, "lon_deg": -105.6905, "h_m": 3000}}], "step_m": 200, "threshold": 20}}"#,
            common::CAMERA_640_JSON
        ),
    )
    .unwrap();
    let out = d.join("mission.gpkg");
    let o = common::run(&[
        "build",
        "--ortho",
        s(&ortho),
        "--dem",
        s(&dem),
        "--dem-vertical",
        "ellipsoid",
        "--camera",
        s(&camera),
        "--altitude",
        "500..3000",
        "--coverage-plan",
        s(&plan),
        "--out",
        s(&out),
    ]);
    assert!(o.status.success(), "{}", common::stderr(&o));
    let r: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    // The mission's resolutions: 500 m / 800 px straight down, 3000 m at the corner ray.
    let sized = &r["sized_for_gsd_m"];
    assert!((sized["finest_m"].as_f64().unwrap() - 0.625).abs() < 1e-9, "{sized}");
    let corner = (400f64 / 800.0).atan().cos();
    assert!((sized["coarsest_m"].as_f64().unwrap() - 3000.0 / 800.0 / corner.powf(1.5)).abs() < 1e-9);
    // Brute force over the mission's resolutions: the level a navigator picks
    // (closest to 32 px) spans 12..48 px wherever the 2 m ortho allows.
    let levels = r["levels"].as_array().unwrap();
    let footprints: Vec<f64> = levels.iter().map(|l| l["footprint_m"].as_f64().unwrap()).collect();
    let serves = &r["serves_gsd_m"];
    let (lo, hi) = (serves["finest_m"].as_f64().unwrap(), serves["coarsest_m"].as_f64().unwrap());
    assert!(hi >= sized["coarsest_m"].as_f64().unwrap(), "{serves}");
    for i in 0..=200 {
        let g = 0.625 * (sized["coarsest_m"].as_f64().unwrap() / 0.625).powf(i as f64 / 200.0);
        let best = footprints
            .iter()
            .map(|f| f / g)
            .min_by(|a, b| (a / 32.0).ln().abs().total_cmp(&(b / 32.0).ln().abs()))
            .unwrap();
        if g >= lo {
            assert!((12.0..=48.0).contains(&best), "at {g} m/px the chosen level spans {best} px");
        }
    }
    // Landmarks per km² and rejections reported per level.
    for l in levels {
        assert!(l["per_km2"].as_f64().unwrap() >= 0.0 && l["empty_cells"].is_object(), "{l}");
    }
    // The coverage in the report is trn coverage's.
    let cov = common::run(&["coverage", "--db", s(&out), "--plan", s(&plan)]);
    assert!(cov.status.success(), "{}", common::stderr(&cov));
    let want: serde_json::Value = serde_json::from_slice(&cov.stdout).unwrap();
    assert_eq!(r["coverage"]["report"], want);
    let points = want["points"].as_array().unwrap();
    assert!(points.len() >= 5 && points.iter().all(|p| p["landmarks"].as_u64().unwrap() > 0), "{want}");
}

/// The database does not depend on how many threads built it, nor on which
/// thread finished first: a build with the default ladder of a 3000 × 3000
/// ortho (two dozen tiles over its pyramid levels) on 1, 2 and 3 threads gives the same
/// templates under the same ids, and so does a second 2-thread build. (Before
/// the tiles' templates were handed on in tile order, the ids followed the
/// threads' finishing order and differed from run to run.)
#[test]
fn the_same_inputs_give_the_same_ids_on_any_number_of_threads() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 3000, GSD, EAST, SEED);
    let key = |b: &Built| -> Vec<(i64, u8, i64, i64, usize)> {
        // Centres to the micro-degree and the pixels' sum: the same template.
        b.templates
            .iter()
            .map(|t| {
                let px: usize = t.pixels.iter().map(|&p| p as usize).sum();
                (
                    t.id,
                    t.level,
                    (t.center.lat_deg * 1e6).round() as i64,
                    (t.center.lon_deg * 1e6).round() as i64,
                    px,
                )
            })
            .collect()
    };
    // The default ladder (every template size), one landmark per 32 pixels.
    let default_ladder = ["--spacing", "32", "--dem-vertical", "ellipsoid"];
    let runs: Vec<Built> = [("t1", "1"), ("t2", "2"), ("t2-again", "2"), ("t3", "3")]
        .iter()
        .map(|(name, n)| {
            build(d, name, &[&ortho], &[&dem], &[&default_ladder[..], &["--threads", n]].concat())
        })
        .collect();
    let reference = key(&runs[0]);
    assert!(reference.len() > 500, "too few templates to tell an order: {}", reference.len());
    let mut ids: Vec<i64> = reference.iter().map(|k| k.0).collect();
    ids.sort_unstable();
    assert_eq!(ids, (1..=reference.len() as i64).collect::<Vec<_>>(), "ids are not 1..=n");
    for b in &runs[1..] {
        let k = key(b);
        assert_eq!(k.len(), reference.len(), "{}: another template count", b.name);
        let first = k.iter().zip(&reference).position(|(a, r)| a != r);
        assert!(
            first.is_none(),
            "{}: template {:?} where the 1-thread build has {:?}",
            b.name,
            k[first.unwrap()],
            reference[first.unwrap()]
        );
    }
}
