use std::path::PathBuf;

/// Everything that can stop a build. Each variant names the file or option at
/// fault; reading the inputs fails with a [`trn_raster::RasterError`].
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    #[error("the orthoimagery (--ortho: {ortho}) and the DEM (--dem: {dem}) do not overlap")]
    NoOverlap { ortho: String, dem: String },
    #[error("invalid option {option}: {reason}")]
    Option { option: &'static str, reason: String },
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error(transparent)]
    Raster(#[from] trn_raster::RasterError),
    #[error(transparent)]
    Store(#[from] trn_store::StoreError),
    #[error(
        "no landmark passed the selection tests (texture, uniqueness, relief, DEM coverage); see the log"
    )]
    NoTemplates,
    #[error("the database writer stopped")]
    WriterStopped,
    #[error("build cancelled")]
    Cancelled,
}

pub type Result<T> = std::result::Result<T, BuildError>;
