//! The one owner of GDAL in trn: orthoimagery and elevation models read as the
//! builder and the simulator need them, so both see the same pixels and the
//! same terrain.
//!
//! - [`source`]: a raster opened and checked (georeferencing, CRS, bands,
//!   nodata, vertical datum), its luminance bands, warping onto another
//!   grid; GDAL's messages go to the log, errors name the file.
//! - [`ortho`]: level 0 of a luminance pyramid, read in windows with
//!   validity ([`ortho::OrthoReader`]).
//! - [`dem`]: DEMs opened with their conversion to WGS84 ellipsoidal heights
//!   ([`dem::open_dem_specs`], `--dem-vertical`, geoid grids), tile mosaics.
//! - [`terrain`]: heights sampled at longitudes and latitudes
//!   ([`terrain::DemSampler`], [`terrain::DemPatch`] for a whole window).
//! - [`synth`]: synthetic orthos and DEMs with known content (`trn synth`),
//!   written as GeoTIFF.
//!
//! ```
//! use std::path::Path;
//! use trn_raster::{source, RasterError};
//!
//! // A missing file is refused with its name.
//! match source::inspect(Path::new("no-such-dem.tif")) {
//!     Err(e @ RasterError::Open { .. }) => assert!(e.to_string().starts_with("no-such-dem.tif: cannot open raster")),
//!     other => panic!("{:?}", other.map(|(_, info)| info.width)),
//! }
//! ```

pub mod dem;
mod error;
pub mod ortho;
pub mod source;
pub mod synth;
pub mod terrain;

pub use dem::{open_dem_specs, DemInputs, DemVertical, EGM96_GRID};
pub use error::{RasterError, Result};
