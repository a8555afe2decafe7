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
//! - [`warp`]: a template resampled through a plane's homography (the inner
//!   loop of predicting a landmark in the image).
//!
//! ```
//! use nalgebra::{Rotation3, Vector3};
//! use trn_vision::p3p::p3p;
//!
//! // A camera 10 m from three points sees them along three rays (camera
//! // frame): P3P finds its centre among its (up to four) solutions.
//! let points = [Vector3::new(1.0, 0.13, 0.05), Vector3::new(0.0, 1.0, -0.2), Vector3::new(-0.7, -1.1, 0.6)];
//! let (r_cam_world, centre) = (Rotation3::from_euler_angles(0.3, 0.06, 0.0), Vector3::new(0.0, 0.0, -10.0));
//! let bearings = points.map(|p| r_cam_world * (p - centre));
//! let poses = p3p(&bearings, &points);
//! assert!(poses.iter().any(|pose| (pose.centre() - centre).norm() < 1e-9));
//! ```

pub mod calib;
pub mod ncc;
pub mod p3p;
pub mod pnp;
pub mod ransac;
pub mod warp;
