//! Read-only access to a finished landmark database.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use rusqlite::{Connection, ErrorCode, OpenFlags, OptionalExtension};
use trn_landmark::{GeoBox, Template};

use crate::error::{SqlContext, StoreError, StoreErrorKind};
use crate::schema::{template_columns, template_from_row};
use crate::{BboxQuery, LevelInfo, GPKG_APPLICATION_ID, SCHEMA_VERSION, SCHEMA_VERSION_KEY};

/// Memory-mapped reads: the server's many readers share the page cache of the OS.
const MMAP_SIZE_BYTES: i64 = 1 << 30;

/// Coarse candidates from the 3D R*Tree, with what the exact recheck and the ranking need.
/// CROSS JOIN pins the R*Tree as the outer loop.
const CANDIDATES_SQL: &str = "SELECT t.fid,
        t.footprint_min_lon_deg, t.footprint_min_lat_deg, t.footprint_max_lon_deg, t.footprint_max_lat_deg,
        t.second_peak_ncc, t.shi_tomasi
    FROM templates_rtree AS r CROSS JOIN templates AS t ON t.fid = r.id
    WHERE r.max_lon >= ?1 AND r.min_lon <= ?2 AND r.max_lat >= ?3 AND r.min_lat <= ?4
      AND r.max_level >= ?5 AND r.min_level <= ?6 AND (?7 IS NULL OR t.lighting = ?7)";

/// Whole rows of the R*Tree's candidates (same order of columns as [`template_columns`]).
const FULL_SQL: &str = concat!(
    "SELECT ",
    template_columns!(),
    " FROM templates_rtree AS r CROSS JOIN templates AS t ON t.fid = r.id
    WHERE r.max_lon >= ?1 AND r.min_lon <= ?2 AND r.max_lat >= ?3 AND r.min_lat <= ?4
      AND r.max_level >= ?5 AND r.min_level <= ?6 AND (?7 IS NULL OR t.lighting = ?7)"
);

/// What the query order ranks by.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Rank {
    id: i64,
    second_peak_ncc: f32,
    shi_tomasi: f32,
}

impl Rank {
    pub(crate) fn of(t: &Template) -> Self {
        Self { id: t.id, second_peak_ncc: t.quality.second_peak_ncc, shi_tomasi: t.quality.shi_tomasi }
    }
}

/// Sorts best first (see [`LandmarkDb::query_bbox_ids`]), drops duplicates (a
/// template can match both halves of an antimeridian-crossing query; its
/// copies sort next to each other) and keeps the first `limit`.
pub(crate) fn best_first<T>(found: &mut Vec<(Rank, T)>, limit: Option<usize>) {
    found.sort_by(|a, b| {
        a.0.second_peak_ncc
            .total_cmp(&b.0.second_peak_ncc)
            .then(b.0.shi_tomasi.total_cmp(&a.0.shi_tomasi))
            .then(a.0.id.cmp(&b.0.id))
    });
    found.dedup_by_key(|c| c.0.id);
    found.truncate(limit.unwrap_or(usize::MAX));
}

/// A read-only connection to a trn landmark database.
///
/// `Send` but not `Sync`: give each thread its own, via [`LandmarkDb::open`] or
/// [`LandmarkDb::reopen`] (cheap: a file open and a few schema checks). Statements are
/// prepared once per connection and cached.
#[derive(Debug)]
pub struct LandmarkDb {
    conn: Connection,
    path: PathBuf,
}

impl LandmarkDb {
    /// Opens `path` read-only and checks that it is a finished trn landmark database of
    /// this [`SCHEMA_VERSION`]; the error says what the file is instead.
    pub fn open(path: &Path) -> Result<Self, StoreError> {
        match std::fs::metadata(path) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                return Err(StoreError::new(path, StoreErrorKind::NotFound))
            }
            Err(e) => return Err(StoreError::io(path, e)),
            Ok(m) if m.is_dir() => {
                return Err(StoreError::new(path, StoreErrorKind::Other("is a directory".into())))
            }
            Ok(_) => {}
        }
        // A finished database is immutable (a new version replaces the file by
        // rename, the open file keeps the old one): `immutable=1` spares every
        // statement SQLite's file locks and journal checks, ~10 us each. The path
        // goes into the URI percent-encoded, so it stays a plain path. No mutex:
        // one thread per connection.
        let flags =
            OpenFlags::SQLITE_OPEN_READ_ONLY | OpenFlags::SQLITE_OPEN_NO_MUTEX | OpenFlags::SQLITE_OPEN_URI;
        let conn = Connection::open_with_flags(immutable_uri(path)?, flags).at(path)?;
        check_trn_database(&conn, path)?;
        conn.pragma_update(None, "mmap_size", MMAP_SIZE_BYTES).at(path)?;
        Ok(Self { conn, path: path.to_owned() })
    }

    /// Another connection to the same file, e.g. for another thread.
    pub fn reopen(&self) -> Result<Self, StoreError> {
        Self::open(&self.path)
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub(crate) fn conn(&self) -> &Connection {
        &self.conn
    }

    /// Number of templates (as summarised by [`crate::DbWriter::finish`]).
    pub fn count(&self) -> Result<u64, StoreError> {
        Ok(self.levels()?.iter().map(|l| l.count).sum())
    }

    /// The pyramid levels present, finest (lowest level) first.
    pub fn levels(&self) -> Result<Vec<LevelInfo>, StoreError> {
        read_levels(&self.conn, &self.path)
    }

    /// Hull of all footprints, `None` for an empty database.
    pub fn extent(&self) -> Result<Option<GeoBox>, StoreError> {
        Ok(extent_of(&self.levels()?))
    }

    pub fn metadata(&self, key: &str) -> Result<Option<serde_json::Value>, StoreError> {
        let mut stmt =
            self.conn.prepare_cached("SELECT value FROM trn_metadata WHERE key = ?1").at(&self.path)?;
        let text: Option<String> = stmt.query_row([key], |r| r.get(0)).optional().at(&self.path)?;
        text.map(|t| parse_metadata(&self.path, key, &t)).transpose()
    }

    pub fn all_metadata(&self) -> Result<BTreeMap<String, serde_json::Value>, StoreError> {
        let mut stmt = self.conn.prepare_cached("SELECT key, value FROM trn_metadata").at(&self.path)?;
        let rows = stmt
            .query_map([], |r| Ok((r.get::<_, String>(0)?, r.get::<_, String>(1)?)))
            .at(&self.path)?
            .collect::<Result<Vec<_>, _>>()
            .at(&self.path)?;
        rows.into_iter().map(|(k, v)| Ok((k.clone(), parse_metadata(&self.path, &k, &v)?))).collect()
    }

    /// The template with this id, pixels included.
    pub fn template(&self, id: i64) -> Result<Option<Template>, StoreError> {
        let mut stmt = self
            .conn
            .prepare_cached(concat!("SELECT ", template_columns!(), " FROM templates WHERE fid = ?1"))
            .at(&self.path)?;
        let mut rows = stmt.query([id]).at(&self.path)?;
        match rows.next().map_err(|e| StoreError::sqlite(&self.path, e).with_template_id(id))? {
            Some(row) => template_from_row(row, &self.path).map(Some),
            None => Ok(None),
        }
    }

    /// The templates matching `query` (see [`BboxQuery`]), pixels included, in the
    /// order of [`LandmarkDb::query_bbox_ids`]. One pass over the R*Tree joined with
    /// the rows (not a lookup per id): the rows of a footprint lie close together.
    pub fn query_bbox(&self, query: &BboxQuery) -> Result<Vec<Template>, StoreError> {
        self.ranked(FULL_SQL, query, |row| {
            let t = template_from_row(row, &self.path)?;
            Ok(query.bbox.intersects(&t.footprint).then(|| (Rank::of(&t), t)))
        })
    }

    /// Ids of the templates matching `query` (see [`BboxQuery`]), best first: ascending
    /// `second_peak_ncc` (most distinctive), then descending `shi_tomasi` (strongest
    /// corners), then ascending id so that the order is total. `limit` keeps the first
    /// results of that order.
    ///
    /// The R*Tree holds float32 bounds rounded outward, so it only proposes candidates;
    /// each is rechecked in double precision with [`GeoBox::intersects`].
    pub fn query_bbox_ids(&self, query: &BboxQuery) -> Result<Vec<i64>, StoreError> {
        self.ranked(CANDIDATES_SQL, query, |row| {
            let footprint = GeoBox {
                min_lon_deg: row.get(1).at(&self.path)?,
                min_lat_deg: row.get(2).at(&self.path)?,
                max_lon_deg: row.get(3).at(&self.path)?,
                max_lat_deg: row.get(4).at(&self.path)?,
            };
            if !query.bbox.intersects(&footprint) {
                return Ok(None);
            }
            let id: i64 = row.get(0).at(&self.path)?;
            let rank = Rank {
                id,
                second_peak_ncc: row.get(5).at(&self.path)?,
                shi_tomasi: row.get(6).at(&self.path)?,
            };
            Ok(Some((rank, id)))
        })
    }

    /// Runs `sql` (an R*Tree query taking the box and level bounds) over each side
    /// of the antimeridian, keeps what `keep` accepts (it rechecks the exact box),
    /// and returns it best first, without duplicates, cut to the limit.
    fn ranked<T>(
        &self,
        sql: &str,
        query: &BboxQuery,
        keep: impl Fn(&rusqlite::Row<'_>) -> Result<Option<(Rank, T)>, StoreError>,
    ) -> Result<Vec<T>, StoreError> {
        let (min_level, max_level) = query.levels.as_ref().map_or((0, u8::MAX), |r| (*r.start(), *r.end()));
        if min_level > max_level || query.limit == Some(0) {
            return Ok(Vec::new());
        }
        let mut stmt = self.conn.prepare_cached(sql).at(&self.path)?;
        let mut found = Vec::new();
        for part in query.bbox.split_antimeridian() {
            let mut rows = stmt
                .query(rusqlite::params![
                    part.min_lon_deg,
                    part.max_lon_deg,
                    part.min_lat_deg,
                    part.max_lat_deg,
                    min_level,
                    max_level,
                    query.lighting
                ])
                .at(&self.path)?;
            while let Some(row) = rows.next().at(&self.path)? {
                found.extend(keep(row)?);
            }
        }
        best_first(&mut found, query.limit);
        Ok(found.into_iter().map(|c| c.1).collect())
    }

    /// Calls `f` with every template, pixels included, in id order; stops at the first error.
    pub fn for_each_template(
        &self,
        mut f: impl FnMut(Template) -> Result<(), StoreError>,
    ) -> Result<(), StoreError> {
        let mut stmt = self
            .conn
            .prepare_cached(concat!("SELECT ", template_columns!(), " FROM templates ORDER BY fid"))
            .at(&self.path)?;
        let mut rows = stmt.query([]).at(&self.path)?;
        while let Some(row) = rows.next().at(&self.path)? {
            f(template_from_row(row, &self.path)?)?;
        }
        Ok(())
    }
}

/// `file:///absolute/path?immutable=1`, every byte of the path but unreserved
/// ones and `/` percent-encoded (RFC 3986, as SQLite's URI parser reads it).
fn immutable_uri(path: &Path) -> Result<String, StoreError> {
    use std::os::unix::ffi::OsStrExt;
    let abs = std::path::absolute(path).map_err(|e| StoreError::io(path, e))?;
    let mut uri = String::from("file://");
    for &b in abs.as_os_str().as_bytes() {
        if b.is_ascii_alphanumeric() || b"-._~/".contains(&b) {
            uri.push(b as char);
        } else {
            uri.push_str(&format!("%{b:02X}"));
        }
    }
    uri.push_str("?immutable=1");
    Ok(uri)
}

/// Tells a trn database apart from other files, most basic check first.
fn check_trn_database(conn: &Connection, path: &Path) -> Result<(), StoreError> {
    let not_trn = |why: String| StoreError::new(path, StoreErrorKind::NotTrnDatabase(why));
    let application_id: i64 = conn.pragma_query_value(None, "application_id", |r| r.get(0)).map_err(|e| {
        match e.sqlite_error_code() {
            Some(ErrorCode::NotADatabase) => StoreError::new(path, StoreErrorKind::NotSqlite),
            _ => StoreError::sqlite(path, e),
        }
    })?;
    if application_id as u32 != GPKG_APPLICATION_ID {
        return Err(not_trn(format!(
            "SQLite application_id is 0x{:08X}, a trn database is a GeoPackage (0x{GPKG_APPLICATION_ID:08X}, 'GPKG')",
            application_id as u32
        )));
    }
    let has_table = |name: &str| -> Result<bool, StoreError> {
        conn.query_row("SELECT count(*) FROM sqlite_master WHERE name = ?1", [name], |r| r.get::<_, i64>(0))
            .map(|n| n > 0)
            .at(path)
    };
    if !has_table("trn_metadata")? {
        return Err(not_trn("a GeoPackage without the trn_metadata table".into()));
    }
    let version: Option<String> = conn
        .query_row("SELECT value FROM trn_metadata WHERE key = ?1", [SCHEMA_VERSION_KEY], |r| r.get(0))
        .optional()
        .at(path)?;
    let version = version.ok_or_else(|| not_trn(format!("trn_metadata has no {SCHEMA_VERSION_KEY:?}")))?;
    let found = parse_metadata(path, SCHEMA_VERSION_KEY, &version)?
        .as_u64()
        .and_then(|v| u32::try_from(v).ok())
        .ok_or_else(|| not_trn(format!("{SCHEMA_VERSION_KEY} {version:?} is not a version number")))?;
    if found != SCHEMA_VERSION {
        return Err(StoreError::new(path, StoreErrorKind::SchemaVersion { found, expected: SCHEMA_VERSION }));
    }
    // Only DbWriter::finish creates the GeoPackage R*Tree: without it the build was cut short.
    if !has_table("rtree_templates_geom")? {
        return Err(StoreError::new(
            path,
            StoreErrorKind::Incomplete("DbWriter::finish never ran (interrupted build?)".into()),
        ));
    }
    Ok(())
}

fn parse_metadata(path: &Path, key: &str, text: &str) -> Result<serde_json::Value, StoreError> {
    serde_json::from_str(text).map_err(|e| {
        StoreError::new(path, StoreErrorKind::Corrupt(format!("metadata {key:?} is not JSON: {e}")))
    })
}

pub(crate) fn read_levels(conn: &Connection, path: &Path) -> Result<Vec<LevelInfo>, StoreError> {
    let mut stmt = conn
        .prepare_cached(
            "SELECT level, gsd_m, template_px, template_count, min_lon_deg, min_lat_deg, max_lon_deg, max_lat_deg
             FROM trn_levels ORDER BY level",
        )
        .at(path)?;
    let rows = stmt
        .query_map([], |r| {
            Ok(LevelInfo {
                level: r.get(0)?,
                gsd_m: r.get(1)?,
                template_px: r.get(2)?,
                count: r.get::<_, i64>(3)? as u64,
                extent: GeoBox::new(r.get(4)?, r.get(5)?, r.get(6)?, r.get(7)?),
            })
        })
        .at(path)?;
    rows.collect::<Result<Vec<_>, _>>().at(path)
}

pub(crate) fn extent_of(levels: &[LevelInfo]) -> Option<GeoBox> {
    levels.iter().map(|l| l.extent).reduce(|a, b| {
        GeoBox::new(
            a.min_lon_deg.min(b.min_lon_deg),
            a.min_lat_deg.min(b.min_lat_deg),
            a.max_lon_deg.max(b.max_lon_deg),
            a.max_lat_deg.max(b.max_lat_deg),
        )
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::DbWriter;

    /// The candidate query must be driven by the 3D R*Tree with all six bounds, level
    /// included, so that a coarse level over a large area does not visit fine templates.
    #[test]
    fn candidate_query_uses_all_rtree_dimensions() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("plan.gpkg");
        DbWriter::create(&path).unwrap().finish().unwrap();
        let db = LandmarkDb::open(&path).unwrap();
        let mut stmt = db.conn.prepare(&format!("EXPLAIN QUERY PLAN {CANDIDATES_SQL}")).unwrap();
        let details: Vec<String> = stmt
            .query_map(rusqlite::params![0.0, 1.0, 0.0, 1.0, 3, 3, Option::<u8>::None], |r| r.get(3))
            .unwrap()
            .collect::<Result<_, _>>()
            .unwrap();
        assert_eq!(details.len(), 2, "{details:?}");
        // R*Tree idxStr: one (operator, column) pair per constraint; B is <=, D is >=;
        // columns 0..5 are min_lon, max_lon, min_lat, max_lat, min_level, max_level.
        let rtree = &details[0];
        assert!(rtree.starts_with("SCAN r VIRTUAL TABLE INDEX 2:"), "{details:?}");
        for pair in ["B0", "D1", "B2", "D3", "B4", "D5"] {
            assert!(rtree.contains(pair), "{pair} missing: {details:?}");
        }
        assert!(details[1].contains("SEARCH t USING INTEGER PRIMARY KEY"), "{details:?}");
    }
}
