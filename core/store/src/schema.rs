//! SQL text and the mapping between [`Template`] and a `templates` row.

use std::path::Path;

use rusqlite::{Row, Statement, ToSql};
use trn_geodesy::Geodetic;
use trn_landmark::{GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};

use crate::error::{SqlContext, StoreError, StoreErrorKind};
use crate::gpkg::footprint_polygon;

pub(crate) const GPKG_CORE_SQL: &str = include_str!("../sql/gpkg_core.sql");
pub(crate) const TEMPLATES_SQL: &str = include_str!("../sql/templates.sql");
pub(crate) const TEMPLATES_RTREE_SQL: &str = include_str!("../sql/templates_rtree.sql");
pub(crate) const GPKG_RTREE_SQL: &str = include_str!("../sql/gpkg_rtree.sql");

/// One row of trn_levels, the summary of a pyramid level (see writer::write_summaries).
pub(crate) const INSERT_LEVEL: &str = "INSERT INTO trn_levels (level, gsd_m, template_px, template_count,
    min_lon_deg, min_lat_deg, max_lon_deg, max_lat_deg) VALUES (?1, ?2, ?3, ?4, ?5, ?6, ?7, ?8)";

/// The templates layer extent for GIS clients, in geometry coordinates.
pub(crate) const UPDATE_LAYER_EXTENT: &str = "UPDATE gpkg_contents
    SET (min_x, min_y, max_x, max_y) = (?1, ?2, ?3, ?4),
        last_change = strftime('%Y-%m-%dT%H:%M:%fZ', 'now')
    WHERE table_name = 'templates'";

/// The longitude range of a footprint in templates_rtree and trn_levels: a footprint
/// crossing the antimeridian spans all longitudes (see templates_rtree.sql).
pub(crate) fn level_index_lon_range(fp: &GeoBox) -> (f64, f64) {
    if fp.crosses_antimeridian() {
        ((-180.0f64).min(fp.max_lon_deg), 180.0f64.max(fp.min_lon_deg))
    } else {
        (fp.min_lon_deg, fp.max_lon_deg)
    }
}

/// Columns written by [`bind_template`], in its order.
const INSERT_COLUMNS: [&str; 30] = [
    "fid",
    "geom",
    "level",
    "gsd_m",
    "width_px",
    "height_px",
    "lat_deg",
    "lon_deg",
    "h_m",
    "ecef_x_m",
    "ecef_y_m",
    "ecef_z_m",
    "footprint_min_lon_deg",
    "footprint_min_lat_deg",
    "footprint_max_lon_deg",
    "footprint_max_lat_deg",
    "plane_normal_e",
    "plane_normal_n",
    "plane_normal_u",
    "plane_residual_rms_m",
    "height_grid_n",
    "height_grid_spacing_m",
    "height_grid_heights_m",
    "shi_tomasi",
    "contrast_std",
    "second_peak_ncc",
    "shading_share",
    "source",
    "lighting",
    "pixels",
];

/// An `INSERT INTO templates` of `rows` rows, each bound by [`bind_template`].
pub(crate) fn insert_templates_sql(rows: usize) -> String {
    let row = format!("({})", ["?"; INSERT_COLUMNS.len()].join(", "));
    format!("INSERT INTO templates ({}) VALUES {}", INSERT_COLUMNS.join(", "), vec![row; rows].join(", "))
}

/// Columns read by [`template_from_row`], in its order; a macro so that `concat!`
/// can build constant SQL for `prepare_cached`.
macro_rules! template_columns {
    () => {
        "fid, level, gsd_m, width_px, height_px, lat_deg, lon_deg, h_m, \
         footprint_min_lon_deg, footprint_min_lat_deg, footprint_max_lon_deg, footprint_max_lat_deg, \
         plane_normal_e, plane_normal_n, plane_normal_u, plane_residual_rms_m, \
         height_grid_n, height_grid_spacing_m, height_grid_heights_m, \
         shi_tomasi, contrast_std, second_peak_ncc, shading_share, source, lighting, pixels"
    };
}
pub(crate) use template_columns;

/// Why a template cannot be stored. SQLite turns NaN into NULL and the R*Tree rejects
/// NaN and inverted boxes, so those are refused up front with the field's name.
pub(crate) fn validate(t: &Template) -> Result<(), String> {
    let expected_px = t.width_px as u64 * t.height_px as u64;
    if t.pixels.len() as u64 != expected_px {
        return Err(format!(
            "pixels has {} bytes, expected width_px x height_px = {} x {} = {expected_px}",
            t.pixels.len(),
            t.width_px,
            t.height_px
        ));
    }
    let g = &t.terrain.height_grid;
    let expected_heights = g.n as u64 * g.n as u64;
    if g.heights_m.len() as u64 != expected_heights {
        return Err(format!(
            "height grid has {} heights, expected n x n = {} x {} = {expected_heights}",
            g.heights_m.len(),
            g.n,
            g.n
        ));
    }
    let fp = &t.footprint;
    let n = &t.terrain.plane_normal_enu;
    let q = &t.quality;
    let reals: [(&str, f64); 18] = [
        ("gsd_m", t.gsd_m),
        ("center.lat_deg", t.center.lat_deg),
        ("center.lon_deg", t.center.lon_deg),
        ("center.h_m", t.center.h_m),
        ("footprint.min_lon_deg", fp.min_lon_deg),
        ("footprint.min_lat_deg", fp.min_lat_deg),
        ("footprint.max_lon_deg", fp.max_lon_deg),
        ("footprint.max_lat_deg", fp.max_lat_deg),
        ("terrain.plane_normal_enu[0]", n[0]),
        ("terrain.plane_normal_enu[1]", n[1]),
        ("terrain.plane_normal_enu[2]", n[2]),
        ("terrain.plane_residual_rms_m", t.terrain.plane_residual_rms_m),
        ("terrain.height_grid.spacing_m", g.spacing_m),
        ("quality.shi_tomasi", q.shi_tomasi as f64),
        ("quality.contrast_std", q.contrast_std as f64),
        ("quality.second_peak_ncc", q.second_peak_ncc as f64),
        ("quality.shading_share", q.shading_share as f64),
        ("source", t.source as f64),
    ];
    if let Some((name, v)) = reals.iter().find(|(_, v)| !v.is_finite()) {
        return Err(format!("{name} is {v}, must be finite"));
    }
    if fp.min_lat_deg > fp.max_lat_deg {
        return Err(format!("footprint min_lat_deg {} > max_lat_deg {}", fp.min_lat_deg, fp.max_lat_deg));
    }
    // Drawn unwrapped, past +180 (gpkg::footprint_x_range); the GeoPackage R*Tree
    // refuses an inverted box.
    if fp.crosses_antimeridian() && fp.max_lon_deg + 360.0 < fp.min_lon_deg {
        return Err(format!(
            "footprint crosses the antimeridian by more than a turn: min_lon_deg {} > max_lon_deg {} + 360",
            fp.min_lon_deg, fp.max_lon_deg
        ));
    }
    Ok(())
}

/// Binds one (validated) template with the given id as row `row` (from 0) of a
/// statement from [`insert_templates_sql`]. `heights` is a scratch buffer (SQLite
/// copies what is bound).
pub(crate) fn bind_template(
    stmt: &mut Statement<'_>,
    row: usize,
    id: i64,
    t: &Template,
    heights: &mut Vec<u8>,
) -> rusqlite::Result<()> {
    let ecef = t.center.to_ecef();
    let fp = &t.footprint;
    let n = &t.terrain.plane_normal_enu;
    let g = &t.terrain.height_grid;
    heights.clear();
    heights.extend(g.heights_m.iter().flat_map(|h| h.to_le_bytes()));
    let geom = footprint_polygon(fp);
    let values: [&dyn ToSql; INSERT_COLUMNS.len()] = [
        &id,
        &geom,
        &t.level,
        &t.gsd_m,
        &t.width_px,
        &t.height_px,
        &t.center.lat_deg,
        &t.center.lon_deg,
        &t.center.h_m,
        &ecef.x(),
        &ecef.y(),
        &ecef.z(),
        &fp.min_lon_deg,
        &fp.min_lat_deg,
        &fp.max_lon_deg,
        &fp.max_lat_deg,
        &n[0],
        &n[1],
        &n[2],
        &t.terrain.plane_residual_rms_m,
        &g.n,
        &g.spacing_m,
        &*heights,
        &t.quality.shi_tomasi,
        &t.quality.contrast_std,
        &t.quality.second_peak_ncc,
        &t.quality.shading_share,
        &t.source,
        &t.lighting,
        &t.pixels,
    ];
    let first = row * INSERT_COLUMNS.len() + 1;
    for (i, v) in values.into_iter().enumerate() {
        stmt.raw_bind_parameter(first + i, v)?;
    }
    Ok(())
}

/// Decodes a row selected with [`TEMPLATE_COLUMNS`].
pub(crate) fn template_from_row(row: &Row<'_>, path: &Path) -> Result<Template, StoreError> {
    let id: i64 = row.get(0).at(path)?;
    let corrupt = |msg: String| StoreError::new(path, StoreErrorKind::Corrupt(msg)).with_template_id(id);
    let mut heights_len_bytes = 0;
    let t = (|| -> rusqlite::Result<Template> {
        let heights_blob: Vec<u8> = row.get(18)?;
        heights_len_bytes = heights_blob.len();
        Ok(Template {
            id,
            level: row.get(1)?,
            gsd_m: row.get(2)?,
            width_px: row.get(3)?,
            height_px: row.get(4)?,
            center: Geodetic { lat_deg: row.get(5)?, lon_deg: row.get(6)?, h_m: row.get(7)? },
            footprint: GeoBox {
                min_lon_deg: row.get(8)?,
                min_lat_deg: row.get(9)?,
                max_lon_deg: row.get(10)?,
                max_lat_deg: row.get(11)?,
            },
            terrain: TerrainPatch {
                plane_normal_enu: [row.get(12)?, row.get(13)?, row.get(14)?],
                plane_residual_rms_m: row.get(15)?,
                height_grid: HeightGrid {
                    n: row.get(16)?,
                    spacing_m: row.get(17)?,
                    heights_m: heights_blob
                        .chunks_exact(4)
                        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                        .collect(),
                },
            },
            quality: TemplateQuality {
                shi_tomasi: row.get(19)?,
                contrast_std: row.get(20)?,
                second_peak_ncc: row.get(21)?,
                shading_share: row.get(22)?,
            },
            source: row.get(23)?,
            lighting: row.get(24)?,
            pixels: row.get(25)?,
        })
    })()
    .map_err(|e| corrupt(e.to_string()))?;
    // The CHECK constraints guard these for our writer; a foreign writer may not have.
    let g = &t.terrain.height_grid;
    if heights_len_bytes as u64 != 4 * g.n as u64 * g.n as u64 {
        return Err(corrupt(format!("height grid blob has {heights_len_bytes} bytes for n = {}", g.n)));
    }
    if t.pixels.len() as u64 != t.width_px as u64 * t.height_px as u64 {
        return Err(corrupt(format!("{} pixels for {} x {}", t.pixels.len(), t.width_px, t.height_px)));
    }
    Ok(t)
}
