//! One opened version of the landmark database: a fixed pool of read-only
//! connections (each with its cached prepared statements), the whole database
//! in memory as a [`Catalogue`] when it fits the cache budget, what `/v1/info`
//! says, and the identity that makes the ETag.
//!
//! All connections are opened up front: the file at the path may be replaced
//! (atomic rename) at any time, and a connection opened later would see the
//! new file while this version's others see the old one.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use serde::Serialize;
use tokio::sync::Semaphore;
use tracing::info;
use trn_landmark::lighting::SunLight;
use trn_landmark::GeoBox;
use trn_landmark::Template;
use trn_store::{BboxQuery, Catalogue, LandmarkDb, LevelInfo, StoreError};
use trn_view::{DbLevel, LandmarkSource, SourceError};
use utoipa::ToSchema;

use crate::error::{ApiError, ServerError};

/// What `GET /v1/info` answers.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct Info {
    /// The database file as given to `trn serve --db`.
    pub path: String,
    /// Identity of this version of the database (the ETag's value).
    pub database_id: String,
    pub template_count: u64,
    /// Per level: GSD, count and extent (footprint hull), finest first.
    #[schema(value_type = Vec<Object>)]
    pub levels: Vec<LevelInfo>,
    /// Hull of all footprints; null for an empty database.
    #[schema(value_type = Option<Object>)]
    pub extent: Option<GeoBox>,
    /// The build metadata (`trn_metadata`): sources, DEMs, parameters, time, version.
    #[schema(value_type = Object)]
    pub metadata: serde_json::Value,
    pub file_size_bytes: u64,
    /// Bytes of the in-memory catalogue (templates served from memory), or 0
    /// when the database is larger than `--cache-mb` and queries read SQLite.
    pub memory_bytes: u64,
}

/// One version of the database, shared by the requests that started on it.
pub struct Database {
    path: PathBuf,
    conns: Mutex<Vec<LandmarkDb>>,
    permits: Arc<Semaphore>,
    catalogue: Option<Catalogue>,
    /// The suns its templates are lit for (metadata `suns`), read once.
    suns: Vec<SunLight>,
    pub info: Info,
    /// (level, GSD) of every level, finest first.
    pub levels: Vec<DbLevel>,
    /// `W/"<database_id>"`.
    pub etag: String,
}

/// FNV-1a, 64 bits: stable across builds and machines (unlike `DefaultHasher`),
/// so every replica gives the same file the same ETag.
fn fnv1a(bytes: &[u8], mut h: u64) -> u64 {
    for b in bytes {
        h ^= *b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

impl Database {
    /// Opens `connections` connections to `path` (at least one), and reads the
    /// whole database into memory if it takes at most `cache_bytes`.
    pub fn open(path: &Path, connections: usize, cache_bytes: u64) -> Result<Self, ServerError> {
        let first = LandmarkDb::open(path)?;
        let levels_info = first.levels()?;
        let metadata = first.all_metadata()?;
        let extent = first.extent()?;
        let file_size_bytes = std::fs::metadata(path)
            .map_err(|e| ServerError::File { path: path.into(), reason: e.to_string() })?
            .len();
        // The SQLite header (change counter, page count) + build metadata + levels.
        let mut header = [0u8; 100];
        {
            use std::io::Read;
            let mut f = std::fs::File::open(path)
                .map_err(|e| ServerError::File { path: path.into(), reason: e.to_string() })?;
            f.read_exact(&mut header)
                .map_err(|e| ServerError::File { path: path.into(), reason: e.to_string() })?;
        }
        let metadata = serde_json::to_value(&metadata).map_err(|e| ServerError::Other(e.to_string()))?;
        let mut h = fnv1a(&header, 0xcbf2_9ce4_8422_2325);
        h = fnv1a(metadata.to_string().as_bytes(), h);
        h = fnv1a(serde_json::to_string(&levels_info).unwrap_or_default().as_bytes(), h);
        h = fnv1a(&file_size_bytes.to_le_bytes(), h);
        let database_id = format!("{h:016x}");
        let catalogue = if cache_bytes == 0 {
            None
        } else {
            let need = first.catalogue_bytes()?;
            if need <= cache_bytes {
                let t0 = Instant::now();
                let c = first.load_catalogue()?;
                info!(
                    "{}: {} templates in memory, {:.0} MB, read in {:.2} s",
                    path.display(),
                    c.len(),
                    c.memory_bytes() as f64 / 1e6,
                    t0.elapsed().as_secs_f64()
                );
                Some(c)
            } else {
                info!(
                    "{}: needs {:.0} MB in memory, more than the cache's {:.0} MB: queries read SQLite",
                    path.display(),
                    need as f64 / 1e6,
                    cache_bytes as f64 / 1e6
                );
                None
            }
        };
        let suns = LandmarkSource::suns(&first).map_err(|e| ServerError::Other(e.0))?;
        let mut conns = Vec::with_capacity(connections.max(1));
        for _ in 1..connections.max(1) {
            conns.push(first.reopen()?);
        }
        conns.push(first);
        let info = Info {
            path: path.display().to_string(),
            database_id: database_id.clone(),
            template_count: levels_info.iter().map(|l| l.count).sum(),
            extent,
            levels: levels_info.clone(),
            metadata,
            file_size_bytes,
            memory_bytes: catalogue.as_ref().map_or(0, |c| c.memory_bytes()),
        };
        Ok(Self {
            path: path.to_owned(),
            permits: Arc::new(Semaphore::new(conns.len())),
            conns: Mutex::new(conns),
            catalogue,
            suns,
            levels: DbLevel::of(&levels_info),
            etag: format!("W/\"{database_id}\""),
            info,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    /// The whole database in memory, when it fits the cache.
    pub fn catalogue(&self) -> Option<&Catalogue> {
        self.catalogue.as_ref()
    }

    /// Runs `f` with this version's [`Store`] on the blocking thread pool;
    /// waits while all connections are busy.
    pub async fn run<T, F>(self: &Arc<Self>, f: F) -> Result<T, ApiError>
    where
        T: Send + 'static,
        F: FnOnce(Store<'_>) -> Result<T, ApiError> + Send + 'static,
    {
        let permit =
            self.permits.clone().acquire_owned().await.map_err(|_| ApiError::internal("database closed"))?;
        let me = self.clone();
        tokio::task::spawn_blocking(move || {
            let _permit = permit;
            let conn =
                Checkout::take(&me).ok_or_else(|| ApiError::internal("no free database connection"))?;
            f(Store { conn: conn.db(), catalogue: me.catalogue.as_ref(), suns: &me.suns })
        })
        .await
        .map_err(|e| ApiError::internal(format!("database task failed: {e}")))?
    }
}

/// What a request reads: a connection, and the catalogue when the database is in memory.
#[derive(Clone, Copy)]
pub struct Store<'a> {
    pub conn: &'a LandmarkDb,
    pub catalogue: Option<&'a Catalogue>,
    pub suns: &'a [SunLight],
}

impl Store<'_> {
    /// The templates matching `query`, best first, from memory if there.
    pub fn query_bbox(&self, query: &BboxQuery) -> Result<Vec<Template>, StoreError> {
        match self.catalogue {
            Some(c) => c.query_templates(query),
            None => self.conn.query_bbox(query),
        }
    }
}

/// What the footprint and coverage queries see: the same templates either way.
impl LandmarkSource for Store<'_> {
    fn levels(&self) -> Result<Vec<LevelInfo>, SourceError> {
        match self.catalogue {
            Some(c) => Ok(c.levels().to_vec()),
            None => LandmarkSource::levels(self.conn),
        }
    }

    fn query(&self, bbox: &GeoBox, level: u8) -> Result<Vec<Template>, SourceError> {
        self.query_bbox(&BboxQuery::new(*bbox).with_levels(level..=level))
            .map_err(|e| SourceError(e.to_string()))
    }

    fn suns(&self) -> Result<Vec<SunLight>, SourceError> {
        Ok(self.suns.to_vec())
    }

    fn query_lit(&self, bbox: &GeoBox, level: u8, lighting: u8) -> Result<Vec<Template>, SourceError> {
        self.query_bbox(&BboxQuery::new(*bbox).with_levels(level..=level).with_lighting(lighting))
            .map_err(|e| SourceError(e.to_string()))
    }
}

/// A connection taken from the pool, put back when dropped (also on a panic).
struct Checkout<'a> {
    pool: &'a Database,
    db: Option<LandmarkDb>,
}

impl<'a> Checkout<'a> {
    fn take(pool: &'a Database) -> Option<Self> {
        let db = pool.conns.lock().unwrap_or_else(|p| p.into_inner()).pop()?;
        Some(Self { pool, db: Some(db) })
    }

    fn db(&self) -> &LandmarkDb {
        self.db.as_ref().expect("present until dropped")
    }
}

impl Drop for Checkout<'_> {
    fn drop(&mut self) {
        if let Some(db) = self.db.take() {
            self.pool.conns.lock().unwrap_or_else(|p| p.into_inner()).push(db);
        }
    }
}

/// A store failure as an answer (503: the request itself was fine).
pub fn store_error(e: StoreError) -> ApiError {
    ApiError::internal(e.to_string())
}
