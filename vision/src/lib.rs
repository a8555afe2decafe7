//! Vision math for terrain relative navigation, free of I/O.
//!
//! - [`p3p`]: the minimal 3-point absolute pose solver (all solutions).
//! - [`ransac`]: outlier rejection with the P3P solver.
//! - [`pnp`]: Levenberg-Marquardt refinement of a pose on all inliers
//!   (reprojection error through the camera's distortion), with an optional
//!   attitude prior, and the pose covariance.
//! - [`calib`]: what one frame's matches say about the camera's focal
//!   length and principal point with the pose left free (self-calibration).
//! - [`ncc`]: normalized cross-correlation of a template over a search
//!   window with sub-pixel peaks and an ambiguity measure.

// `!(x > y)` is how these crates reject NaN along with out-of-range values.
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod calib;
pub mod ncc;
pub mod p3p;
pub mod pnp;
pub mod ransac;
