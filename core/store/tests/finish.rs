//! What `DbWriter::finish` builds without SQL row by row: both R*Trees hold exactly the
//! boxes that their insert triggers give, pass SQLite's `rtreecheck`, and stay
//! consistent under later writes through the triggers; the level summaries and the
//! layer extent equal the SQL aggregates over the templates.

mod common;

use common::{synthetic_template, write_db, Lcg};
use rusqlite::Connection;
use trn_landmark::{GeoBox, Template};
use trn_store::{BboxQuery, DbWriter, LandmarkDb, StoreErrorKind};

/// Templates over much of the globe on five levels, clusters, footprints crossing the
/// antimeridian from both sides, and duplicates.
fn templates(rng: &mut Lcg, n: usize) -> Vec<Template> {
    (0..n)
        .map(|i| {
            let level = rng.below(5) as u8;
            let (lat, lon) = match i % 10 {
                0 => (rng.uniform(-70.0, 70.0), rng.uniform(-180.0, 180.0)),
                1 => (rng.uniform(-10.0, 10.0), if rng.chance(0.5) { 179.9999 } else { -179.9999 }),
                _ => (46.0 + rng.uniform(-0.1, 0.1), 7.0 + rng.uniform(-0.1, 0.1)),
            };
            synthetic_template(rng, level, lat, lon)
        })
        .collect()
}

/// All rows of `sql`, every column as an optional f64 (exact for R*Tree float32s).
fn rows(conn: &Connection, sql: &str) -> Vec<Vec<Option<f64>>> {
    let mut stmt = conn.prepare(sql).unwrap();
    let ncol = stmt.column_count();
    stmt.query_map([], |r| (0..ncol).map(|i| r.get(i)).collect()).unwrap().collect::<Result<_, _>>().unwrap()
}

fn rtreecheck(conn: &Connection, table: &str) {
    let report: String = conn.query_row("SELECT rtreecheck(?1)", [table], |r| r.get(0)).unwrap();
    assert_eq!(report, "ok", "{table}");
}

/// The R*Tree contents that the insert triggers (templates_rtree.sql, gpkg_rtree.sql)
/// give, and the summaries as SQL aggregates.
const REFERENCE_SQL: &str = "
    CREATE VIRTUAL TABLE temp.ref_level USING rtree(id, min_lon, max_lon, min_lat, max_lat, min_level, max_level);
    INSERT INTO temp.ref_level SELECT fid,
        CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
             THEN footprint_min_lon_deg ELSE min(-180.0, footprint_max_lon_deg) END,
        CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
             THEN footprint_max_lon_deg ELSE max(180.0, footprint_min_lon_deg) END,
        footprint_min_lat_deg, footprint_max_lat_deg, level - 0.5, level + 0.5
    FROM templates;
    CREATE VIRTUAL TABLE temp.ref_geom USING rtree(id, minx, maxx, miny, maxy);
    INSERT INTO temp.ref_geom SELECT fid, footprint_min_lon_deg,
        CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
             THEN footprint_max_lon_deg ELSE footprint_max_lon_deg + 360.0 END,
        footprint_min_lat_deg, footprint_max_lat_deg
    FROM templates;";

const LEVELS_SQL: &str = "SELECT level, min(gsd_m), max(max(width_px, height_px)), count(*),
       min(CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
                THEN footprint_min_lon_deg ELSE min(-180.0, footprint_max_lon_deg) END),
       min(footprint_min_lat_deg),
       max(CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
                THEN footprint_max_lon_deg ELSE max(180.0, footprint_min_lon_deg) END),
       max(footprint_max_lat_deg)
    FROM templates GROUP BY level ORDER BY level";

const LAYER_EXTENT_SQL: &str = "SELECT min(footprint_min_lon_deg), min(footprint_min_lat_deg),
       max(CASE WHEN footprint_min_lon_deg <= footprint_max_lon_deg
                THEN footprint_max_lon_deg ELSE footprint_max_lon_deg + 360.0 END),
       max(footprint_max_lat_deg)
    FROM templates";

#[test]
fn spatial_indexes_and_summaries_equal_what_sql_gives() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg::new(11);
    for n in [0usize, 1, 51, 52, 3000] {
        let mut ts = templates(&mut rng, n);
        let (path, summary) = write_db(dir.path(), &format!("finish-{n}.gpkg"), &mut ts);
        assert_eq!(summary.template_count, n as u64);
        let conn = Connection::open(&path).unwrap();
        conn.execute_batch(REFERENCE_SQL).unwrap();
        for (table, reference) in
            [("templates_rtree", "temp.ref_level"), ("rtree_templates_geom", "temp.ref_geom")]
        {
            rtreecheck(&conn, table);
            let ours = rows(&conn, &format!("SELECT * FROM {table} ORDER BY id"));
            assert_eq!(ours.len(), n, "{table}");
            assert_eq!(
                ours,
                rows(&conn, &format!("SELECT * FROM {reference} ORDER BY id")),
                "{table}, n = {n}"
            );
        }
        assert_eq!(
            rows(&conn, "SELECT * FROM trn_levels ORDER BY level"),
            rows(&conn, LEVELS_SQL),
            "n = {n}"
        );
        let layer = "SELECT min_x, min_y, max_x, max_y FROM gpkg_contents WHERE table_name = 'templates'";
        assert_eq!(rows(&conn, layer), rows(&conn, LAYER_EXTENT_SQL), "n = {n}");
        let last_change: String = conn
            .query_row("SELECT last_change FROM gpkg_contents WHERE table_name = 'templates'", [], |r| {
                r.get(0)
            })
            .unwrap();
        assert!(last_change.ends_with('Z') && last_change.len() == 24, "{last_change}");

        // Later deletes go through the triggers into both packed trees.
        conn.execute("DELETE FROM templates WHERE fid % 3 = 0", []).unwrap();
        for table in ["templates_rtree", "rtree_templates_geom"] {
            rtreecheck(&conn, table);
            let left: i64 =
                conn.query_row(&format!("SELECT count(*) FROM {table}"), [], |r| r.get(0)).unwrap();
            assert_eq!(left as usize, n - n / 3, "{table}");
        }
        drop(conn);
        let db = LandmarkDb::open(&path).unwrap();
        let world = BboxQuery::new(GeoBox::new(-180.0, -90.0, 180.0, 90.0));
        let mut found = db.query_bbox_ids(&world).unwrap();
        found.sort_unstable();
        assert_eq!(found, (1..=n as i64).filter(|id| id % 3 != 0).collect::<Vec<_>>());
    }
}

#[test]
fn footprint_crossing_the_antimeridian_more_than_once_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("turn.gpkg");
    let mut w = DbWriter::create(&path).unwrap();
    let mut t = synthetic_template(&mut Lcg::new(12), 0, 0.0, 0.0);
    t.footprint.min_lon_deg = 500.0;
    t.footprint.max_lon_deg = 100.0;
    let err = w.insert_batch(&mut [t]).unwrap_err();
    assert!(matches!(err.kind(), StoreErrorKind::InvalidTemplate(_)), "{err}");
    assert!(err.to_string().contains("antimeridian"), "{err}");
    assert_eq!(w.finish().unwrap().template_count, 0);
}
