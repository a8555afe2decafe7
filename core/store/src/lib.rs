//! The landmark database: one SQLite file that is also a GeoPackage 1.3.
//!
//! [`DbWriter`] bulk-loads [`Template`]s into a new file and [`LandmarkDb`] reads it
//! back (read-only, one cheap connection per thread) with bounding-box + pyramid-level
//! queries. The template footprints form the GeoPackage feature layer `templates`
//! (polygons in EPSG:4326 with the GeoPackage R*Tree index), so GDAL (`ogrinfo`) and
//! QGIS open the file directly and show the coverage. Our own queries use a second,
//! 3D R*Tree `templates_rtree` over (longitude, latitude, level), so a coarse level
//! over a large area does not touch the fine levels.
//!
//! This crate is the only owner of SQL in trn; the schema lives in `core/store/sql/*.sql`.
//! Since GeoPackage fixes `PRAGMA user_version`, our [`SCHEMA_VERSION`] is stored in
//! the `trn_metadata` table under the key `schema_version`.
//!
//! ```
//! use trn_landmark::GeoBox;
//! use trn_store::{BboxQuery, DbWriter, LandmarkDb};
//!
//! // An empty database, written and read back (`finish` builds the R*Trees).
//! let dir = std::env::temp_dir().join(format!("trn-store-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! let path = dir.join("empty.gpkg");
//! let summary = DbWriter::create(&path).unwrap().finish().unwrap();
//! assert_eq!(summary.template_count, 0);
//! let db = LandmarkDb::open(&path).unwrap();
//! assert_eq!(db.count().unwrap(), 0);
//! assert!(db.query_bbox(&BboxQuery::new(GeoBox::new(-1.0, -1.0, 1.0, 1.0))).unwrap().is_empty());
//! std::fs::remove_dir_all(&dir).unwrap();
//! ```

mod catalogue;
mod error;
pub mod gpkg;
mod reader;
mod rtree;
mod schema;
mod writer;

use std::ops::RangeInclusive;
use std::path::PathBuf;

use serde::Serialize;

pub use catalogue::Catalogue;
pub use error::{StoreError, StoreErrorKind};
pub use reader::LandmarkDb;
pub use trn_landmark::{GeoBox, Template};
pub use writer::DbWriter;

/// Version of the trn schema (tables and columns below the GeoPackage core). Bump it
/// with every change to `sql/templates.sql` or to the blob encodings.
pub const SCHEMA_VERSION: u32 = 3;

/// `PRAGMA application_id` of a GeoPackage: 'GPKG'.
pub const GPKG_APPLICATION_ID: u32 = 0x4750_4B47;

/// `PRAGMA user_version` of a GeoPackage 1.3.0.
pub const GPKG_USER_VERSION: u32 = 10300;

/// `trn_metadata` key holding [`SCHEMA_VERSION`]; reserved, not settable.
pub const SCHEMA_VERSION_KEY: &str = "schema_version";

/// Summary of one pyramid level.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LevelInfo {
    pub level: u8,
    /// Smallest ground sample distance among the level's templates (they normally share one).
    pub gsd_m: f64,
    /// Largest template side in the level (pixels); `gsd_m * template_px` is
    /// the level's footprint, the scale at which navigators choose levels.
    pub template_px: u32,
    pub count: u64,
    /// Hull of the level's footprints; never crosses the antimeridian (a footprint that
    /// does counts as the whole longitude range).
    pub extent: GeoBox,
}

/// What [`DbWriter::finish`] reports about the finished file.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct DbSummary {
    pub path: PathBuf,
    pub template_count: u64,
    pub levels: Vec<LevelInfo>,
    pub extent: Option<GeoBox>,
    pub file_size_bytes: u64,
}

/// A bounding-box query.
///
/// Matches the templates whose footprint box intersects `bbox`, closed intervals (a
/// shared edge or corner counts), exactly as [`GeoBox::intersects`] decides it; a `bbox`
/// with `min_lon_deg > max_lon_deg` crosses the antimeridian. `levels` restricts the
/// pyramid levels (all when `None`); `limit` keeps only the best results.
#[derive(Clone, Debug, PartialEq)]
pub struct BboxQuery {
    pub bbox: GeoBox,
    pub levels: Option<RangeInclusive<u8>>,
    pub limit: Option<usize>,
    /// Only templates of this lighting (`Template::lighting`); `None`: all.
    pub lighting: Option<u8>,
}

impl BboxQuery {
    /// All levels, no limit.
    pub fn new(bbox: GeoBox) -> Self {
        Self { bbox, levels: None, limit: None, lighting: None }
    }

    pub fn with_levels(mut self, levels: RangeInclusive<u8>) -> Self {
        self.levels = Some(levels);
        self
    }

    pub fn with_limit(mut self, limit: usize) -> Self {
        self.limit = Some(limit);
        self
    }

    pub fn with_lighting(mut self, lighting: u8) -> Self {
        self.lighting = Some(lighting);
        self
    }
}
