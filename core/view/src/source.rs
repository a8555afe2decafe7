//! Where landmarks come from: the SQLite database directly (no server
//! needed, [`DbSource`]) or a landmark server (`trn_client::HttpSource`);
//! their users see only the [`LandmarkSource`] trait.

use std::path::Path;

use trn_landmark::lighting::SunLight;
use trn_landmark::{GeoBox, Template};
use trn_store::{BboxQuery, LandmarkDb, LevelInfo};

/// An error from a landmark source, with its location (file or URL).
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct SourceError(pub String);

pub trait LandmarkSource {
    /// The database's levels (GSD doubles per level).
    fn levels(&self) -> Result<Vec<LevelInfo>, SourceError>;
    /// Templates of one level whose footprint meets `bbox`.
    fn query(&self, bbox: &GeoBox, level: u8) -> Result<Vec<Template>, SourceError>;
    /// Suns the database's templates are lit for (`Template::lighting` k is
    /// the k-th, from 1); empty: the ortho as imaged.
    fn suns(&self) -> Result<Vec<SunLight>, SourceError> {
        Ok(Vec::new())
    }
    /// [`LandmarkSource::query`] for the templates of one lighting only (a
    /// source that can filters before sending them).
    fn query_lit(&self, bbox: &GeoBox, level: u8, lighting: u8) -> Result<Vec<Template>, SourceError> {
        let mut ts = self.query(bbox, level)?;
        ts.retain(|t| t.lighting == lighting);
        Ok(ts)
    }
}

/// The `suns` entry of a database's build metadata (none: empty).
pub fn suns_of_metadata(value: Option<&serde_json::Value>, at: &str) -> Result<Vec<SunLight>, SourceError> {
    match value {
        None | Some(serde_json::Value::Null) => Ok(Vec::new()),
        Some(v) => serde_json::from_value(v.clone())
            .map_err(|e| SourceError(format!("{at}: metadata \"suns\" is not a list of suns: {e}"))),
    }
}

/// A landmark database used directly: also one borrowed connection (the
/// server's).
impl LandmarkSource for LandmarkDb {
    fn levels(&self) -> Result<Vec<LevelInfo>, SourceError> {
        LandmarkDb::levels(self).map_err(|e| SourceError(e.to_string()))
    }

    fn query(&self, bbox: &GeoBox, level: u8) -> Result<Vec<Template>, SourceError> {
        self.query_bbox(&BboxQuery::new(*bbox).with_levels(level..=level))
            .map_err(|e| SourceError(e.to_string()))
    }

    fn suns(&self) -> Result<Vec<SunLight>, SourceError> {
        let m = self.metadata("suns").map_err(|e| SourceError(e.to_string()))?;
        suns_of_metadata(m.as_ref(), &self.path().display().to_string())
    }

    fn query_lit(&self, bbox: &GeoBox, level: u8, lighting: u8) -> Result<Vec<Template>, SourceError> {
        self.query_bbox(&BboxQuery::new(*bbox).with_levels(level..=level).with_lighting(lighting))
            .map_err(|e| SourceError(e.to_string()))
    }
}

/// A landmark database opened directly.
pub struct DbSource {
    db: LandmarkDb,
}

impl DbSource {
    pub fn open(path: &Path) -> Result<Self, SourceError> {
        Ok(Self { db: LandmarkDb::open(path).map_err(|e| SourceError(e.to_string()))? })
    }
}

impl LandmarkSource for DbSource {
    fn levels(&self) -> Result<Vec<LevelInfo>, SourceError> {
        LandmarkSource::levels(&self.db)
    }

    fn query(&self, bbox: &GeoBox, level: u8) -> Result<Vec<Template>, SourceError> {
        LandmarkSource::query(&self.db, bbox, level)
    }

    fn suns(&self) -> Result<Vec<SunLight>, SourceError> {
        LandmarkSource::suns(&self.db)
    }

    fn query_lit(&self, bbox: &GeoBox, level: u8, lighting: u8) -> Result<Vec<Template>, SourceError> {
        LandmarkSource::query_lit(&self.db, bbox, level, lighting)
    }
}
