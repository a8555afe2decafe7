//! The store's one error type.

use std::fmt;
use std::path::{Path, PathBuf};

/// An error from the landmark store. Its message always starts with the database
/// path, and names the template where one is concerned, e.g.
/// `landmarks.gpkg: template 42: corrupt record: ...`.
#[derive(Debug, thiserror::Error)]
#[error("{}{}: {kind}", path.display(), TemplateRef(*template_id))]
pub struct StoreError {
    path: PathBuf,
    template_id: Option<i64>,
    kind: StoreErrorKind,
}

/// What went wrong. Messages are complete in `Display` (the underlying SQLite or I/O
/// error text included), so the error is not chained further.
#[derive(Debug, thiserror::Error)]
pub enum StoreErrorKind {
    #[error("no such file")]
    NotFound,
    #[error("file already exists; refusing to overwrite it")]
    AlreadyExists,
    #[error("not a SQLite database (so not a trn landmark database)")]
    NotSqlite,
    #[error("not a trn landmark database: {0}")]
    NotTrnDatabase(String),
    #[error("incomplete trn landmark database: {0}")]
    Incomplete(String),
    #[error(
        "trn landmark database schema version {found}, but this trn reads version {expected}; \
         rebuild the database with this trn"
    )]
    SchemaVersion { found: u32, expected: u32 },
    #[error("invalid template: {0}")]
    InvalidTemplate(String),
    #[error("invalid metadata key {key:?}: {reason}")]
    InvalidMetadata { key: String, reason: String },
    #[error("corrupt record: {0}")]
    Corrupt(String),
    #[error("SQLite: {0}")]
    Sqlite(rusqlite::Error),
    #[error("I/O: {0}")]
    Io(std::io::Error),
    /// For callers' own failures inside callbacks such as `for_each_template`.
    #[error("{0}")]
    Other(String),
}

impl StoreError {
    pub fn new(path: impl Into<PathBuf>, kind: StoreErrorKind) -> Self {
        Self { path: path.into(), template_id: None, kind }
    }

    pub fn with_template_id(mut self, id: i64) -> Self {
        self.template_id = Some(id);
        self
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn template_id(&self) -> Option<i64> {
        self.template_id
    }

    pub fn kind(&self) -> &StoreErrorKind {
        &self.kind
    }

    pub(crate) fn sqlite(path: &Path, e: rusqlite::Error) -> Self {
        Self::new(path, StoreErrorKind::Sqlite(e))
    }

    pub(crate) fn io(path: &Path, e: std::io::Error) -> Self {
        Self::new(path, StoreErrorKind::Io(e))
    }
}

struct TemplateRef(Option<i64>);

impl fmt::Display for TemplateRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.0 {
            Some(id) => write!(f, ": template {id}"),
            None => Ok(()),
        }
    }
}

/// Attaches the database path to SQLite results.
pub(crate) trait SqlContext<T> {
    fn at(self, path: &Path) -> Result<T, StoreError>;
}

impl<T> SqlContext<T> for rusqlite::Result<T> {
    fn at(self, path: &Path) -> Result<T, StoreError> {
        self.map_err(|e| StoreError::sqlite(path, e))
    }
}
