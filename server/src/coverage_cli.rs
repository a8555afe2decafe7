//! `trn coverage`: the report of a plan over a database file (computed here
//! with [`crate::coverage`]) or from a running server (through
//! [`crate::client`]), written as JSON, GeoJSON and a PNG map.

use std::path::Path;

use trn_landmark::GeoBox;
use trn_view::DbLevel;

use crate::coverage::{
    coverage_query, map_area, to_geojson, CoveragePoint, CoverageReport, CoverageRequest, TemplateBox,
};

/// Where `trn coverage` gets the report and the template footprints.
#[derive(Clone, Copy, Debug)]
pub enum CoverageSource<'a> {
    /// A landmark database file: the report is computed here.
    Db(&'a Path),
    /// A running `trn serve` (its base URL, `http://host:port`): the server
    /// computes the report (`POST /v1/coverage`, one round trip) and lists the
    /// footprints for the map (`GET /v1/templates`).
    Server(&'a str),
}

/// `trn coverage`: the report for the plan in `plan` (a [`CoverageRequest`] as
/// JSON) from `source`, optionally written as GeoJSON and drawn as a PNG map.
/// Both sources give the same report, GeoJSON and map.
pub fn run_cli(
    source: CoverageSource,
    plan: &Path,
    geojson: Option<&Path>,
    png: Option<(&Path, u32)>,
) -> Result<CoverageReport, crate::ServerError> {
    use crate::ServerError;
    let file_err = |path: &Path, reason: String| ServerError::File { path: path.into(), reason };
    let read_plan = || std::fs::read(plan).map_err(|e| file_err(plan, e.to_string()));
    match source {
        CoverageSource::Db(db) => {
            let req: CoverageRequest = serde_json::from_slice(&read_plan()?)
                .map_err(|e| file_err(plan, format!("not a coverage plan: {e}")))?;
            let conn = trn_store::LandmarkDb::open(db)?;
            let levels = DbLevel::of(&conn.levels()?);
            let report = coverage_query(&conn, &levels, &req).map_err(|e| file_err(plan, e.message))?;
            write_outputs(&report, geojson, png, |area| {
                let templates = conn.query_bbox(&trn_store::BboxQuery::new(*area))?;
                Ok(templates.iter().map(TemplateBox::from).collect())
            })?;
            Ok(report)
        }
        CoverageSource::Server(url) => {
            let client = crate::client::Client::new(url)?;
            let report = client.coverage(&read_plan()?)?;
            write_outputs(&report, geojson, png, |area| client.template_boxes(area))?;
            Ok(report)
        }
    }
}

/// Writes the GeoJSON and the map asked for; `templates_in` lists the
/// templates meeting an area (all levels).
fn write_outputs(
    report: &CoverageReport,
    geojson: Option<&Path>,
    png: Option<(&Path, u32)>,
    templates_in: impl FnOnce(&GeoBox) -> Result<Vec<TemplateBox>, crate::ServerError>,
) -> Result<(), crate::ServerError> {
    use crate::ServerError;
    let file_err = |path: &Path, reason: String| ServerError::File { path: path.into(), reason };
    if let Some(path) = geojson {
        let text =
            serde_json::to_string_pretty(&to_geojson(report)).map_err(|e| file_err(path, e.to_string()))?;
        std::fs::write(path, text).map_err(|e| file_err(path, e.to_string()))?;
    }
    if let Some((path, width)) = png {
        let templates = match map_area(report) {
            Some(area) => templates_in(&area)?,
            None => Vec::new(),
        };
        render_map(&templates, report, path, width).map_err(|e| file_err(path, e))?;
    }
    Ok(())
}

/// Draws the trajectory over the landmark footprints (PNG, north up, longitude
/// scaled by cos(latitude)): footprints in grey (darker for finer levels),
/// points green at or above the threshold and red below, joined by a line.
pub fn render_map(
    templates: &[TemplateBox],
    report: &CoverageReport,
    path: &Path,
    width_px: u32,
) -> Result<(), String> {
    let mut boxes: Vec<GeoBox> = report.points.iter().filter_map(|p| p.bbox).collect();
    boxes.extend(report.points.iter().map(|p| GeoBox::new(p.lon_deg, p.lat_deg, p.lon_deg, p.lat_deg)));
    let area = GeoBox::around(
        boxes
            .iter()
            .filter(|b| !b.crosses_antimeridian())
            .flat_map(|b| [(b.min_lon_deg, b.min_lat_deg), (b.max_lon_deg, b.max_lat_deg)]),
    )
    .ok_or("no point to draw")?;
    let (dlon, dlat) =
        ((area.max_lon_deg - area.min_lon_deg).max(1e-6), (area.max_lat_deg - area.min_lat_deg).max(1e-6));
    let margin = 0.05;
    let (lon0, lat1) = (area.min_lon_deg - margin * dlon, area.max_lat_deg + margin * dlat);
    let (span_lon, span_lat) = (dlon * (1.0 + 2.0 * margin), dlat * (1.0 + 2.0 * margin));
    let coslat = (0.5 * (area.min_lat_deg + area.max_lat_deg)).to_radians().cos().max(0.01);
    let w = width_px.max(16);
    let h = ((w as f64 * span_lat / (span_lon * coslat)).round() as u32).clamp(16, 8 * w);
    let mut img = image::RgbImage::from_pixel(w, h, image::Rgb([255, 255, 255]));
    let to_px = |lon: f64, lat: f64| ((lon - lon0) / span_lon * w as f64, (lat1 - lat) / span_lat * h as f64);
    let max_level = templates.iter().map(|t| t.level).max().unwrap_or(0).max(1) as f64;
    let mut sorted: Vec<&TemplateBox> = templates.iter().collect();
    sorted.sort_by_key(|t| std::cmp::Reverse(t.level));
    for t in sorted {
        let f = &t.footprint;
        if f.crosses_antimeridian() {
            continue;
        }
        let (x0, y0) = to_px(f.min_lon_deg, f.max_lat_deg);
        let (x1, y1) = to_px(f.max_lon_deg, f.min_lat_deg);
        let grey = (150.0 + 80.0 * t.level as f64 / max_level) as u8;
        for y in (y0.floor().max(0.0) as u32)..(y1.ceil().min(h as f64) as u32) {
            for x in (x0.floor().max(0.0) as u32)..(x1.ceil().min(w as f64) as u32) {
                let p = img.get_pixel_mut(x, y);
                p.0 = p.0.map(|c| c.min(grey));
            }
        }
    }
    let colour = |p: &CoveragePoint| {
        if p.landmarks >= report.threshold {
            image::Rgb([0, 160, 0])
        } else {
            image::Rgb([220, 0, 0])
        }
    };
    let put = |img: &mut image::RgbImage, x: f64, y: f64, c: image::Rgb<u8>, r: i64| {
        for dy in -r..=r {
            for dx in -r..=r {
                let (px, py) = (x.round() as i64 + dx, y.round() as i64 + dy);
                if px >= 0 && py >= 0 && (px as u32) < w && (py as u32) < h {
                    img.put_pixel(px as u32, py as u32, c);
                }
            }
        }
    };
    for pair in report.points.windows(2) {
        let (a, b) = (to_px(pair[0].lon_deg, pair[0].lat_deg), to_px(pair[1].lon_deg, pair[1].lat_deg));
        let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()).ceil() as usize).clamp(1, 4 * (w + h) as usize);
        for k in 0..=n {
            let f = k as f64 / n as f64;
            put(&mut img, a.0 + f * (b.0 - a.0), a.1 + f * (b.1 - a.1), colour(&pair[1]), 0);
        }
    }
    for p in &report.points {
        let (x, y) = to_px(p.lon_deg, p.lat_deg);
        put(&mut img, x, y, colour(p), 2);
    }
    img.save(path).map_err(|e| format!("{}: {e}", path.display()))
}
