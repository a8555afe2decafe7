//! Bulk loading of a new landmark database.

use std::collections::BTreeMap;
use std::fs::OpenOptions;
use std::path::{Path, PathBuf};

use rusqlite::{Connection, OpenFlags};
use trn_landmark::{GeoBox, Template};

use crate::error::{SqlContext, StoreError, StoreErrorKind};
use crate::gpkg::footprint_x_range;
use crate::reader::{extent_of, read_levels};
use crate::rtree::{bulk_load, hilbert_key, Entry};
use crate::schema::{
    bind_template, insert_templates_sql, level_index_lon_range, validate, GPKG_CORE_SQL, GPKG_RTREE_SQL,
    INSERT_LEVEL, TEMPLATES_RTREE_SQL, TEMPLATES_SQL, UPDATE_LAYER_EXTENT,
};
use crate::{DbSummary, LevelInfo, SCHEMA_VERSION, SCHEMA_VERSION_KEY};

/// Durability is traded for speed: the builder writes to a temporary file and renames
/// it only after [`DbWriter::finish`], so a crash leaves no half-written database at
/// the final path. The journal stays (in memory) so that a failed batch rolls back.
/// 16 KiB pages (set before the schema exists) hold nine templates of 32 x 32 pixels
/// where 4 KiB pages hold two: fewer pages to allocate, a 12% smaller file.
const BULK_LOAD_PRAGMAS: &str = "PRAGMA page_size = 16384;
    PRAGMA journal_mode = MEMORY;
    PRAGMA synchronous = OFF;
    PRAGMA locking_mode = EXCLUSIVE;
    PRAGMA temp_store = MEMORY;
    PRAGMA cache_size = -262144;";

/// File growth between two `fdatasync`s while templates come in (see
/// [`DbWriter::pace_sync`]).
const SYNC_EVERY_BYTES: u64 = 16 << 20;

/// Rows per multi-row INSERT: one statement execution, with its fixed costs (the
/// AUTOINCREMENT bookkeeping among them), serves this many templates.
const ROWS_PER_INSERT: usize = 16;

/// Writes a new landmark database. Call [`DbWriter::finish`] at the end: it builds both
/// R*Tree indexes and the summaries that [`crate::LandmarkDb::open`] requires.
pub struct DbWriter {
    conn: Connection,
    path: PathBuf,
    /// Multi-row and single-row INSERT statements (prepared once, cached by `conn`).
    insert_many_sql: String,
    insert_one_sql: String,
    /// Scratch buffer for the height-grid blob.
    heights: Vec<u8>,
    /// What finish needs of every committed template (in id order), so that it need not
    /// read the table back: ~60 bytes a template.
    stored: Vec<Stored>,
    /// The file, for starting its write-back while batches come in.
    file: Option<std::fs::File>,
    /// Its length at the last `fdatasync`.
    synced_len: u64,
}

impl std::fmt::Debug for DbWriter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DbWriter")
            .field("path", &self.path)
            .field("template_count", &self.template_count())
            .finish_non_exhaustive()
    }
}

/// The indexed fields of a committed template.
#[derive(Clone, Copy, Debug)]
struct Stored {
    id: i64,
    level: u8,
    gsd_m: f64,
    template_px: u32,
    footprint: GeoBox,
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
        Ok(Self {
            conn,
            path: path.to_owned(),
            insert_many_sql: insert_templates_sql(ROWS_PER_INSERT),
            insert_one_sql: insert_templates_sql(1),
            heights: Vec::new(),
            stored: Vec::new(),
            file: std::fs::File::open(path).ok(),
            synced_len: 0,
        })
    }

    /// Starts writing the file's dirty pages to disk without waiting
    /// (Linux `sync_file_range`), so that the fsync of [`DbWriter::finish`]
    /// finds little left to write. Advisory: errors are ignored (the fsync
    /// reports them).
    fn start_writeback(&self) {
        #[cfg(target_os = "linux")]
        if let Some(f) = &self.file {
            use std::os::fd::AsRawFd;
            // SAFETY: a valid open descriptor; offset 0 and length 0 mean the whole file.
            unsafe { libc::sync_file_range(f.as_raw_fd(), 0, 0, libc::SYNC_FILE_RANGE_WRITE) };
        }
    }

    /// Makes the file durable every [`SYNC_EVERY_BYTES`] of growth, from the
    /// writer's thread while the builder's threads compute: the one fsync of
    /// [`DbWriter::finish`] then commits only the tail. An fsync of a fresh
    /// file costs about a millisecond per MB after its data is written
    /// (measured on ext4: 120 ms for 120 MB at the end, 8 ms in 16 MB steps),
    /// mostly the journal's record of the new blocks. Advisory: errors are
    /// ignored (the final fsync reports them).
    fn pace_sync(&mut self) {
        let Some(f) = &self.file else { return };
        let Ok(len) = f.metadata().map(|m| m.len()) else { return };
        if len >= self.synced_len + SYNC_EVERY_BYTES {
            let _ = f.sync_data();
            self.synced_len = len;
        }
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Templates inserted so far.
    pub fn template_count(&self) -> u64 {
        self.stored.len() as u64
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
    ///
    /// The spatial indexes are built by [`DbWriter::finish`], not here.
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
        // Ids are given explicitly, counting on from the templates already stored (this
        // writer created the file and is its only writer), so that one statement can
        // insert many rows.
        let first_id = self.stored.len() as i64 + 1;
        let tx = self.conn.transaction().at(&self.path)?;
        {
            let mut ids = first_id..;
            let chunks = templates.chunks_exact(ROWS_PER_INSERT);
            let rest = chunks.remainder();
            let mut many = tx.prepare_cached(&self.insert_many_sql).at(&self.path)?;
            for chunk in chunks {
                for (row, (t, id)) in chunk.iter().zip(&mut ids).enumerate() {
                    bind_template(&mut many, row, id, t, &mut self.heights).at(&self.path)?;
                }
                many.raw_execute().at(&self.path)?;
            }
            let mut one = tx.prepare_cached(&self.insert_one_sql).at(&self.path)?;
            for (t, id) in rest.iter().zip(&mut ids) {
                bind_template(&mut one, 0, id, t, &mut self.heights).at(&self.path)?;
                one.raw_execute().at(&self.path)?;
            }
        }
        tx.commit().at(&self.path)?;
        self.start_writeback();
        self.pace_sync();
        for (t, id) in templates.iter_mut().zip(first_id..) {
            t.id = id;
            self.stored.push(Stored {
                id,
                level: t.level,
                gsd_m: t.gsd_m,
                template_px: t.width_px.max(t.height_px),
                footprint: t.footprint,
            });
        }
        Ok(())
    }

    /// Creates and fills both R*Tree indexes (with the triggers that keep them current
    /// for later writers), writes the level summaries and the layer extent, checks the
    /// R*Trees, runs ANALYZE, closes and syncs the file.
    pub fn finish(self) -> Result<DbSummary, StoreError> {
        let Self { mut conn, path, stored, .. } = self;
        let template_count = stored.len() as u64;
        let tx = conn.transaction().at(&path)?;
        tx.execute_batch(TEMPLATES_RTREE_SQL).at(&path)?;
        tx.execute_batch(GPKG_RTREE_SQL).at(&path)?;
        fill_spatial_indexes(&tx, &path, &stored)?;
        write_summaries(&tx, &path, &stored)?;
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

/// Fills both new, empty R*Trees in one pass (see rtree.rs): packed in the order of a
/// Hilbert curve over the footprint centres, templates_rtree by level first. The boxes
/// are exactly those of the insert triggers in templates_rtree.sql and gpkg_rtree.sql.
fn fill_spatial_indexes(conn: &Connection, path: &Path, stored: &[Stored]) -> Result<(), StoreError> {
    // Geometry (x, y) of the footprint centres, and their extent.
    let centre = |fp: &GeoBox| {
        let (x0, x1) = footprint_x_range(fp);
        (0.5 * (x0 + x1), 0.5 * (fp.min_lat_deg + fp.max_lat_deg))
    };
    let (mut lo, mut hi) = ((f64::MAX, f64::MAX), (f64::MIN, f64::MIN));
    for s in stored {
        let (x, y) = centre(&s.footprint);
        (lo.0, lo.1, hi.0, hi.1) = (lo.0.min(x), lo.1.min(y), hi.0.max(x), hi.1.max(y));
    }
    let unit = |v: f64, lo: f64, hi: f64| if hi > lo { (v - lo) / (hi - lo) } else { 0.0 };
    let inverted = |id: i64, table: &str, dim: usize| {
        StoreError::new(
            path,
            StoreErrorKind::InvalidTemplate(format!(
                "footprint gives {table} an inverted box in dimension {dim}"
            )),
        )
        .with_template_id(id)
    };
    let mut by_level: Vec<Entry<6>> = Vec::with_capacity(stored.len());
    let mut geom: Vec<Entry<4>> = Vec::with_capacity(stored.len());
    for &Stored { id, level, footprint: ref fp, .. } in stored {
        let (x, y) = centre(fp);
        let key = hilbert_key(unit(x, lo.0, hi.0), unit(y, lo.1, hi.1));
        let (lon0, lon1) = level_index_lon_range(fp);
        let l = f64::from(level);
        let bounds = [lon0, lon1, fp.min_lat_deg, fp.max_lat_deg, l - 0.5, l + 0.5];
        by_level.push(
            Entry::new(id, u64::from(level) << 32 | key, bounds)
                .map_err(|d| inverted(id, "templates_rtree", d))?,
        );
        let (x0, x1) = footprint_x_range(fp);
        let bounds = [x0, x1, fp.min_lat_deg, fp.max_lat_deg];
        geom.push(Entry::new(id, key, bounds).map_err(|d| inverted(id, "rtree_templates_geom", d))?);
    }
    bulk_load(conn, path, "templates_rtree", &mut by_level)?;
    bulk_load(conn, path, "rtree_templates_geom", &mut geom)
}

/// Fills trn_levels and the layer extent in gpkg_contents. Per level: the smallest GSD,
/// the count and the hull of the footprints as templates_rtree enters them (a footprint
/// crossing the antimeridian spans all longitudes). The layer extent is in geometry
/// coordinates (gpkg::footprint_x_range); NULL for an empty layer.
fn write_summaries(conn: &Connection, path: &Path, stored: &[Stored]) -> Result<(), StoreError> {
    let mut levels: BTreeMap<u8, LevelInfo> = BTreeMap::new();
    let mut layer: Option<(f64, f64, f64, f64)> = None;
    for s in stored {
        let fp = &s.footprint;
        let (lon0, lon1) = level_index_lon_range(fp);
        let l = levels.entry(s.level).or_insert(LevelInfo {
            level: s.level,
            gsd_m: s.gsd_m,
            template_px: s.template_px,
            count: 0,
            extent: GeoBox::new(lon0, fp.min_lat_deg, lon1, fp.max_lat_deg),
        });
        l.gsd_m = l.gsd_m.min(s.gsd_m);
        l.template_px = l.template_px.max(s.template_px);
        l.count += 1;
        let e = &mut l.extent;
        e.min_lon_deg = e.min_lon_deg.min(lon0);
        e.min_lat_deg = e.min_lat_deg.min(fp.min_lat_deg);
        e.max_lon_deg = e.max_lon_deg.max(lon1);
        e.max_lat_deg = e.max_lat_deg.max(fp.max_lat_deg);
        let (_, x1) = footprint_x_range(fp);
        let (x0, y0, y1) = (fp.min_lon_deg, fp.min_lat_deg, fp.max_lat_deg);
        layer = Some(match layer {
            None => (x0, y0, x1, y1),
            Some((a, b, c, d)) => (a.min(x0), b.min(y0), c.max(x1), d.max(y1)),
        });
    }
    conn.execute("DELETE FROM trn_levels", []).at(path)?;
    let mut insert = conn.prepare(INSERT_LEVEL).at(path)?;
    for l in levels.values() {
        let e = &l.extent;
        insert
            .execute((
                l.level,
                l.gsd_m,
                l.template_px,
                l.count as i64,
                e.min_lon_deg,
                e.min_lat_deg,
                e.max_lon_deg,
                e.max_lat_deg,
            ))
            .at(path)?;
    }
    let (x0, y0, x1, y1) =
        layer.map_or((None, None, None, None), |(a, b, c, d)| (Some(a), Some(b), Some(c), Some(d)));
    conn.execute(UPDATE_LAYER_EXTENT, (x0, y0, x1, y1)).at(path)?;
    Ok(())
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
    // SQLite's full structural check of the packed trees: in debug builds
    // (every test), not in release ones, where it took 50 ms of a 100 MP
    // build's 1.7 s. The packer is tested against it on random templates
    // (tests/finish.rs, rtree.rs) and its queries against brute force.
    if cfg!(debug_assertions) {
        for rtree in ["templates_rtree", "rtree_templates_geom"] {
            let report: String = conn.query_row("SELECT rtreecheck(?1)", [rtree], |r| r.get(0)).at(path)?;
            if report != "ok" {
                return Err(corrupt(format!("R*Tree {rtree} check failed: {report}")));
            }
        }
    }
    Ok(())
}
