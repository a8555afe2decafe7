//! Bulk loading of a new landmark database.

use std::fs::OpenOptions;
use std::path::{Path, PathBuf};

use rusqlite::{Connection, OpenFlags};
use trn_landmark::Template;

use crate::error::{SqlContext, StoreError, StoreErrorKind};
use crate::reader::{extent_of, read_levels};
use crate::schema::{
    insert_template, validate, FINISH_SQL, GPKG_CORE_SQL, GPKG_RTREE_SQL, INSERT_TEMPLATE, TEMPLATES_SQL,
};
use crate::{DbSummary, SCHEMA_VERSION, SCHEMA_VERSION_KEY};

/// Durability is traded for speed: the builder writes to a temporary file and renames
/// it only after [`DbWriter::finish`], so a crash leaves no half-written database at
/// the final path. The journal stays (in memory) so that a failed batch rolls back.
const BULK_LOAD_PRAGMAS: &str = "PRAGMA journal_mode = MEMORY;
    PRAGMA synchronous = OFF;
    PRAGMA locking_mode = EXCLUSIVE;
    PRAGMA temp_store = MEMORY;
    PRAGMA cache_size = -262144;";

/// Writes a new landmark database. Call [`DbWriter::finish`] at the end: it builds the
/// GeoPackage spatial index and the summaries that [`crate::LandmarkDb::open`] requires.
#[derive(Debug)]
pub struct DbWriter {
    conn: Connection,
    path: PathBuf,
    template_count: u64,
}

impl DbWriter {
    /// Creates the file and the schema. Fails, leaving it alone, if `path` already
    /// exists; removes the file again if creating the schema fails.
    pub fn create(path: &Path) -> Result<Self, StoreError> {
        // create_new is the atomic "does not exist yet" check that SQLite lacks.
        match OpenOptions::new().write(true).create_new(true).open(path) {
            Ok(_) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                return Err(StoreError::new(path, StoreErrorKind::AlreadyExists))
            }
            Err(e) => return Err(StoreError::io(path, e)),
        }
        Self::create_schema(path).inspect_err(|_| {
            let _ = std::fs::remove_file(path);
        })
    }

    fn create_schema(path: &Path) -> Result<Self, StoreError> {
        let flags = OpenFlags::SQLITE_OPEN_READ_WRITE | OpenFlags::SQLITE_OPEN_NO_MUTEX;
        let mut conn = Connection::open_with_flags(path, flags).at(path)?;
        conn.execute_batch(BULK_LOAD_PRAGMAS).at(path)?;
        let tx = conn.transaction().at(path)?;
        tx.execute_batch(GPKG_CORE_SQL).at(path)?;
        tx.execute_batch(TEMPLATES_SQL).at(path)?;
        tx.execute(
            "INSERT INTO trn_metadata (key, value) VALUES (?1, ?2)",
            (SCHEMA_VERSION_KEY, SCHEMA_VERSION.to_string()),
        )
        .at(path)?;
        tx.commit().at(path)?;
        Ok(Self { conn, path: path.to_owned(), template_count: 0 })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Templates inserted so far.
    pub fn template_count(&self) -> u64 {
        self.template_count
    }

    /// Stores `value` as JSON under `key`, replacing an earlier value. The key
    /// [`SCHEMA_VERSION_KEY`] is reserved.
    pub fn set_metadata(&mut self, key: &str, value: &serde_json::Value) -> Result<(), StoreError> {
        let invalid = |reason: &str| {
            StoreError::new(
                &self.path,
                StoreErrorKind::InvalidMetadata { key: key.into(), reason: reason.into() },
            )
        };
        if key.is_empty() {
            return Err(invalid("empty key"));
        }
        if key == SCHEMA_VERSION_KEY {
            return Err(invalid("reserved for the store's schema version"));
        }
        let mut stmt = self
            .conn
            .prepare_cached("INSERT OR REPLACE INTO trn_metadata (key, value) VALUES (?1, ?2)")
            .at(&self.path)?;
        stmt.execute((key, value.to_string())).at(&self.path)?;
        Ok(())
    }

    /// Inserts the templates in one transaction and sets their `id`s (any id they had
    /// is ignored; ids count up from 1 over the whole database). All are validated
    /// first: on error nothing is inserted and no id changes.
    pub fn insert_batch(&mut self, templates: &mut [Template]) -> Result<(), StoreError> {
        for (i, t) in templates.iter().enumerate() {
            validate(t).map_err(|why| {
                StoreError::new(
                    &self.path,
                    StoreErrorKind::InvalidTemplate(format!(
                        "batch item {i} (level {}, centre lat {:.7} lon {:.7}): {why}",
                        t.level, t.center.lat_deg, t.center.lon_deg
                    )),
                )
            })?;
        }
        let tx = self.conn.transaction().at(&self.path)?;
        let mut ids = Vec::with_capacity(templates.len());
        {
            let mut stmt = tx.prepare_cached(INSERT_TEMPLATE).at(&self.path)?;
            for t in templates.iter() {
                ids.push(insert_template(&mut stmt, t).at(&self.path)?);
            }
        }
        tx.commit().at(&self.path)?;
        for (t, id) in templates.iter_mut().zip(ids) {
            t.id = id;
        }
        self.template_count += templates.len() as u64;
        Ok(())
    }

    /// Builds the GeoPackage R*Tree index, the level summaries and the layer extent,
    /// checks both R*Trees, runs ANALYZE, closes and syncs the file.
    pub fn finish(self) -> Result<DbSummary, StoreError> {
        let Self { mut conn, path, template_count } = self;
        let tx = conn.transaction().at(&path)?;
        tx.execute_batch(GPKG_RTREE_SQL).at(&path)?;
        tx.execute_batch(FINISH_SQL).at(&path)?;
        tx.commit().at(&path)?;
        check_spatial_indexes(&conn, &path, template_count)?;
        // A bounded ANALYZE: the planner only needs rough row counts.
        conn.execute_batch("PRAGMA analysis_limit = 1000; ANALYZE;").at(&path)?;
        let levels = read_levels(&conn, &path)?;
        let extent = extent_of(&levels);
        conn.close().map_err(|(_, e)| StoreError::sqlite(&path, e))?;
        // synchronous = OFF skipped every fsync; one at the end, before the caller renames.
        std::fs::File::open(&path).and_then(|f| f.sync_all()).map_err(|e| StoreError::io(&path, e))?;
        let file_size_bytes = std::fs::metadata(&path).map_err(|e| StoreError::io(&path, e))?.len();
        Ok(DbSummary { path, template_count, levels, extent, file_size_bytes })
    }
}

/// Both R*Trees must hold exactly one entry per template and pass SQLite's own check.
fn check_spatial_indexes(conn: &Connection, path: &Path, template_count: u64) -> Result<(), StoreError> {
    let corrupt = |msg: String| StoreError::new(path, StoreErrorKind::Corrupt(msg));
    for table in ["templates", "templates_rtree", "rtree_templates_geom"] {
        let n: i64 = conn.query_row(&format!("SELECT count(*) FROM {table}"), [], |r| r.get(0)).at(path)?;
        if n as u64 != template_count {
            return Err(corrupt(format!("{table} has {n} rows, expected {template_count}")));
        }
    }
    for rtree in ["templates_rtree", "rtree_templates_geom"] {
        let report: String = conn.query_row("SELECT rtreecheck(?1)", [rtree], |r| r.get(0)).at(path)?;
        if report != "ok" {
            return Err(corrupt(format!("R*Tree {rtree} check failed: {report}")));
        }
    }
    Ok(())
}
