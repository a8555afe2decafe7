use std::path::PathBuf;

/// Everything that can go wrong reading a raster. Each variant names the file
/// (or the option) at fault.
#[derive(Debug, thiserror::Error)]
pub enum RasterError {
    #[error("{}: cannot open raster: {reason}", path.display())]
    Open { path: PathBuf, reason: String },
    #[error("{}: no georeferencing (the raster has no geotransform or no coordinate reference system)", path.display())]
    NoGeoreference { path: PathBuf },
    #[error("{}: {reason}", path.display())]
    BadRaster { path: PathBuf, reason: String },
    #[error("{}: every pixel is nodata", path.display())]
    AllNodata { path: PathBuf },
    #[error("{}: the DEM has no vertical datum; say which with --dem-vertical (egm96, ellipsoid, or geoid with --geoid GRID)", path.display())]
    UnknownVerticalDatum { path: PathBuf },
    #[error("{}: vertical datum {datum} needs a geoid grid: pass --geoid GRID (e.g. GEOID18 for NAVD88)", path.display())]
    GeoidGridNeeded { path: PathBuf, datum: String },
    #[error("{}: cannot read geoid grid: {reason}", path.display())]
    Geoid { path: PathBuf, reason: String },
    #[error("invalid option {option}: {reason}")]
    Option { option: &'static str, reason: String },
    #[error("{}: cannot read: {reason}", path.display())]
    Read { path: PathBuf, reason: String },
    #[error("{}: {source}", path.display())]
    Io { path: PathBuf, source: std::io::Error },
    #[error("{}: cannot write: {reason}", path.display())]
    Write { path: PathBuf, reason: String },
}

pub type Result<T> = std::result::Result<T, RasterError>;
