//! Writing and reading back templates and metadata.

mod common;

use common::{synthetic_template, write_db, Lcg};
use rusqlite::{Connection, OpenFlags};
use trn_geodesy::Geodetic;
use trn_landmark::{GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};
use trn_store::{
    gpkg, BboxQuery, DbWriter, LandmarkDb, StoreErrorKind, GPKG_APPLICATION_ID, GPKG_USER_VERSION,
    SCHEMA_VERSION,
};

/// A template whose every field holds a value that a lossy encoding would change.
fn awkward_template() -> Template {
    Template {
        id: 12345, // ignored by the writer
        level: 255,
        gsd_m: 0.1 + 0.2,
        width_px: 3,
        height_px: 2,
        center: Geodetic::new(-33.123_456_789_012_34, 151.987_654_321_098_7, -12.345_678_901_234),
        footprint: GeoBox::new(151.987_6, -33.123_5, 151.987_7, -33.123_4),
        terrain: TerrainPatch {
            plane_normal_enu: [0.1, -0.2, (1.0f64 - 0.05).sqrt()],
            plane_residual_rms_m: 1.0 / 3.0,
            height_grid: HeightGrid {
                n: 2,
                spacing_m: 2.0 / 3.0,
                heights_m: vec![f32::MIN_POSITIVE / 2.0, -1.5e-7, f32::MAX, -0.333_333_34],
            },
        },
        quality: TemplateQuality {
            shi_tomasi: 1.0e-30,
            contrast_std: 1.0 / 3.0,
            second_peak_ncc: -0.1,
            shading_share: 1.0 / 7.0,
        },
        source: u32::MAX,
        lighting: u8::MAX,
        pixels: vec![0, 255, 1, 254, 127, 128],
    }
}

#[test]
fn every_field_round_trips() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg::new(1);
    let crossing = synthetic_template(&mut rng, 2, 10.0, 179.9999);
    assert!(crossing.footprint.crosses_antimeridian());
    let mut originals = vec![awkward_template(), synthetic_template(&mut rng, 0, 46.5, 7.5), crossing];
    let (path, summary) = write_db(dir.path(), "rt.gpkg", &mut originals);
    assert_eq!(summary.template_count, 3);
    assert_eq!(summary.path, path);
    assert!(summary.file_size_bytes > 0);
    assert_eq!(originals.iter().map(|t| t.id).collect::<Vec<_>>(), vec![1, 2, 3]);

    let db = LandmarkDb::open(&path).unwrap();
    assert_eq!(db.count().unwrap(), 3);
    for t in &originals {
        assert_eq!(db.template(t.id).unwrap().as_ref(), Some(t));
    }
    assert_eq!(db.template(4).unwrap(), None);
    assert_eq!(db.template(0).unwrap(), None);

    // Denormalised and GeoPackage columns, read with plain SQL.
    let conn = Connection::open_with_flags(&path, OpenFlags::SQLITE_OPEN_READ_ONLY).unwrap();
    let app_id: i64 = conn.query_row("PRAGMA application_id", [], |r| r.get(0)).unwrap();
    let user_version: i64 = conn.query_row("PRAGMA user_version", [], |r| r.get(0)).unwrap();
    assert_eq!(app_id as u32, GPKG_APPLICATION_ID);
    assert_eq!(user_version as u32, GPKG_USER_VERSION);
    for t in &originals {
        let (x, y, z, geom): (f64, f64, f64, Vec<u8>) = conn
            .query_row(
                "SELECT ecef_x_m, ecef_y_m, ecef_z_m, geom FROM templates WHERE fid = ?1",
                [t.id],
                |r| Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?)),
            )
            .unwrap();
        let ecef = t.center.to_ecef();
        assert_eq!((x, y, z), (ecef.x(), ecef.y(), ecef.z()));
        assert_eq!(geom, gpkg::footprint_polygon_blob(&t.footprint));
        let (min_x, min_y, max_x, max_y) = gpkg::polygon_blob_envelope(&geom).unwrap();
        let (rx0, rx1, ry0, ry1): (f64, f64, f64, f64) = conn
            .query_row("SELECT minx, maxx, miny, maxy FROM rtree_templates_geom WHERE id = ?1", [t.id], |r| {
                Ok((r.get(0)?, r.get(1)?, r.get(2)?, r.get(3)?))
            })
            .unwrap();
        // float32 bounds, rounded outward around the double envelope.
        assert!(rx0 <= min_x && rx1 >= max_x && ry0 <= min_y && ry1 >= max_y);
        assert!(rx1 - rx0 < (max_x - min_x) + 1e-4);
    }
    let pixels_last: String = conn
        .query_row("SELECT name FROM pragma_table_info('templates') ORDER BY cid DESC LIMIT 1", [], |r| {
            r.get(0)
        })
        .unwrap();
    assert_eq!(pixels_last, "pixels");
}

#[test]
fn metadata_round_trips_and_schema_version_is_reserved() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("meta.gpkg");
    let mut w = DbWriter::create(&path).unwrap();
    let sources = serde_json::json!([
        {"path": "ortho.tif", "crs": "EPSG:32632", "width_px": 10000, "height_px": 8000},
        {"path": "dem.tif", "crs": "EPSG:4326", "vertical_datum": "EGM2008 -> WGS84 ellipsoid"}
    ]);
    w.set_metadata("sources", &sources).unwrap();
    w.set_metadata("base_gsd_m", &serde_json::json!(0.5)).unwrap();
    w.set_metadata("base_gsd_m", &serde_json::json!(1.0)).unwrap(); // replaces
    let err = w.set_metadata("schema_version", &serde_json::json!(7)).unwrap_err();
    assert!(matches!(err.kind(), StoreErrorKind::InvalidMetadata { .. }));
    assert!(err.to_string().contains("meta.gpkg"), "{err}");
    w.finish().unwrap();

    let db = LandmarkDb::open(&path).unwrap();
    assert_eq!(db.metadata("sources").unwrap(), Some(sources.clone()));
    assert_eq!(db.metadata("base_gsd_m").unwrap(), Some(serde_json::json!(1.0)));
    assert_eq!(db.metadata("nope").unwrap(), None);
    let all = db.all_metadata().unwrap();
    assert_eq!(all.keys().collect::<Vec<_>>(), vec!["base_gsd_m", "schema_version", "sources"]);
    assert_eq!(all["schema_version"], serde_json::json!(SCHEMA_VERSION));
    // An empty database is fine.
    assert_eq!(db.count().unwrap(), 0);
    assert_eq!(db.extent().unwrap(), None);
    assert!(db.levels().unwrap().is_empty());
    let world = BboxQuery::new(GeoBox::new(-180.0, -90.0, 180.0, 90.0));
    assert!(db.query_bbox_ids(&world).unwrap().is_empty());
}

#[test]
fn ids_levels_extent_and_full_scan() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg::new(2);
    let mut templates: Vec<Template> = (0..1200)
        .map(|i| {
            let level = (i % 3) as u8;
            synthetic_template(&mut rng, level, 40.0 + (i as f64) * 1e-3, -105.0 - (i as f64) * 2e-3)
        })
        .collect();
    let (path, summary) = write_db(dir.path(), "ids.gpkg", &mut templates);
    // write_db inserts in batches of 500: ids continue across batches.
    assert!(templates.iter().enumerate().all(|(i, t)| t.id == i as i64 + 1));

    let db = LandmarkDb::open(&path).unwrap();
    assert_eq!(db.count().unwrap(), 1200);
    let levels = db.levels().unwrap();
    assert_eq!(levels, summary.levels);
    assert_eq!(
        levels.iter().map(|l| (l.level, l.count)).collect::<Vec<_>>(),
        vec![(0, 400), (1, 400), (2, 400)]
    );
    for l in &levels {
        assert_eq!(l.gsd_m, 2.0 * f64::from(1u32 << l.level));
        let of_level: Vec<_> = templates.iter().filter(|t| t.level == l.level).collect();
        let hull = GeoBox::around(of_level.iter().flat_map(|t| {
            [
                (t.footprint.min_lon_deg, t.footprint.min_lat_deg),
                (t.footprint.max_lon_deg, t.footprint.max_lat_deg),
            ]
        }))
        .unwrap();
        assert_eq!(l.extent, hull);
    }
    let extent = db.extent().unwrap().unwrap();
    assert_eq!(Some(extent), summary.extent);

    let mut seen = Vec::new();
    db.for_each_template(|t| {
        seen.push(t);
        Ok(())
    })
    .unwrap();
    assert_eq!(seen, templates);

    // The callback's error stops the scan and comes back unchanged.
    let mut calls = 0;
    let err = db
        .for_each_template(|_| {
            calls += 1;
            Err(trn_store::StoreError::new(db.path(), StoreErrorKind::Other("enough".into())))
        })
        .unwrap_err();
    assert_eq!(calls, 1);
    assert!(err.to_string().ends_with("enough"), "{err}");

    // query_bbox gives the full templates in the order of query_bbox_ids.
    let q = BboxQuery::new(GeoBox::new(-105.5, 40.1, -105.2, 40.3)).with_levels(1..=2).with_limit(50);
    let ids = db.query_bbox_ids(&q).unwrap();
    assert_eq!(ids.len(), 50);
    let full = db.query_bbox(&q).unwrap();
    assert_eq!(full.iter().map(|t| t.id).collect::<Vec<_>>(), ids);
    for t in &full {
        assert_eq!(t, &templates[t.id as usize - 1]);
    }
}

#[test]
fn invalid_batch_inserts_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.gpkg");
    let mut rng = Lcg::new(3);
    let mut w = DbWriter::create(&path).unwrap();
    let mut good = vec![synthetic_template(&mut rng, 0, 1.0, 1.0)];
    w.insert_batch(&mut good).unwrap();
    assert_eq!(good[0].id, 1);

    let mut batch =
        vec![synthetic_template(&mut rng, 0, 1.0, 1.0), synthetic_template(&mut rng, 0, 1.0, 1.0)];
    batch[1].pixels.pop();
    let err = w.insert_batch(&mut batch).unwrap_err();
    let msg = err.to_string();
    assert!(msg.contains("bad.gpkg") && msg.contains("batch item 1") && msg.contains("pixels"), "{msg}");
    assert!(batch.iter().all(|t| t.id == 0));

    batch[1] = synthetic_template(&mut rng, 0, 1.0, 1.0);
    batch[1].quality.second_peak_ncc = f32::NAN;
    let msg = w.insert_batch(&mut batch).unwrap_err().to_string();
    assert!(msg.contains("second_peak_ncc"), "{msg}");

    batch[1] = synthetic_template(&mut rng, 0, 1.0, 1.0);
    batch[1].terrain.height_grid.heights_m.push(0.0);
    let msg = w.insert_batch(&mut batch).unwrap_err().to_string();
    assert!(msg.contains("height grid"), "{msg}");

    assert_eq!(w.template_count(), 1);
    let summary = w.finish().unwrap();
    assert_eq!(summary.template_count, 1);
    assert_eq!(LandmarkDb::open(&path).unwrap().count().unwrap(), 1);
}

#[test]
fn readers_on_many_threads() {
    fn assert_send<T: Send>() {}
    assert_send::<LandmarkDb>();

    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg::new(4);
    let mut templates: Vec<Template> =
        (0..300).map(|i| synthetic_template(&mut rng, 0, 50.0 + i as f64 * 1e-3, 10.0)).collect();
    let (path, _) = write_db(dir.path(), "threads.gpkg", &mut templates);
    let first = LandmarkDb::open(&path).unwrap();
    let q = BboxQuery::new(GeoBox::new(9.0, 49.0, 11.0, 51.0));
    let expected = first.query_bbox_ids(&q).unwrap();
    assert_eq!(expected.len(), 300);
    std::thread::scope(|s| {
        for _ in 0..4 {
            let db = first.reopen().unwrap();
            let (q, expected) = (&q, &expected);
            s.spawn(move || assert_eq!(&db.query_bbox_ids(q).unwrap(), expected));
        }
        let moved = LandmarkDb::open(&path).unwrap();
        s.spawn(move || assert_eq!(moved.count().unwrap(), 300));
    });
}
