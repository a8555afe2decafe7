//! Which landmarks a camera pose can use, without an image: the catalogue's
//! visibility selection, apart from the estimator that uses it (as NASA
//! GIANT keeps catalogue, visibility and estimator apart).
//!
//! - [`LandmarkSource`]: where landmarks come from (a database file through
//!   [`DbSource`] or a borrowed [`trn_store::LandmarkDb`]; a landmark server
//!   through `trn_client::HttpSource`). The navigator, the server's footprint
//!   and coverage queries and `trn coverage` see only this trait.
//! - [`footprint`]: the image corners projected onto the ellipsoid raised to
//!   the terrain, with IBAL's horizon walking and angle filter.
//! - [`visible`]: the levels that fit the local ground resolution and the
//!   templates that project into the image ([`landmarks_in_view`]).
//!
//! Pure geometry over a source: no HTTP, no GDAL; the only I/O is the
//! source's.
//!
//! ```
//! use trn_camera::{CameraModel, CameraPose};
//! use trn_geodesy::Geodetic;
//! use trn_view::footprint::{footprint, FootprintParams};
//!
//! // A 640x480 camera with a 40 deg field of view, 10 km above the ellipsoid,
//! // looking straight down with north up.
//! let camera = CameraModel::from_fov(640, 480, 40.0);
//! let at = Geodetic::new(40.0, -111.0, 10_000.0);
//! let ground = Geodetic::new(40.0, -111.0, 0.0);
//! let north = Geodetic::new(40.001, -111.0, 10_000.0).to_ecef().0 - at.to_ecef().0;
//! let pose = CameraPose::look_at(at.to_ecef(), ground.to_ecef(), north);
//! let fp = footprint(&camera, &pose, &FootprintParams::default()).unwrap();
//! // The view is 2 * 10 km * tan(20 deg) = 7.3 km wide: 11.4 m per pixel.
//! assert!((fp.center_gsd_m - 7279.0 / 640.0).abs() < 0.2, "{}", fp.center_gsd_m);
//! assert!(!fp.horizon_in_view && fp.bbox.contains(-111.0, 40.0));
//! ```

pub mod footprint;
pub mod source;
pub mod visible;

pub use footprint::{Footprint, FootprintError, FootprintParams};
pub use source::{suns_of_metadata, DbSource, LandmarkSource, SourceError};
pub use visible::{landmarks_in_view, terrain_near, DbLevel, View, ViewError};
