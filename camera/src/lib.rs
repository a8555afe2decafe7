//! Camera geometry for terrain relative navigation. Pure math, no I/O.
//!
//! The main type is [`CameraModel`]: a pinhole camera with OpenCV's
//! five-coefficient Brown-Conrady distortion ([`Distortion`]), mapping
//! camera-frame points to [`Pixel`]s and pixels back to unit rays, in the
//! conventions of the flight format (`FLIGHT_FORMAT.md`):
//!
//! - camera frame: +x right (increasing column), +y down (increasing row),
//!   +z forward along the boresight;
//! - pixel `(u, v)` = (column, row), `(0, 0)` the *centre* of the top-left
//!   pixel, so the image spans `[-0.5, w - 0.5] x [-0.5, h - 0.5]`; this is
//!   also OpenCV's convention for `cx`, `cy` (no half-pixel shifts anywhere);
//! - attitude: Hamilton unit quaternion, scalar first `[w, x, y, z]`, with
//!   `v_ecef = R(q_ecef_cam) * v_cam`.
//!
//! [`CameraConfig`] is the flight's `camera.json` (a model plus the IMU
//! mounting); [`CameraPose`] places a camera in ECEF, to project ECEF points
//! and cast ECEF rays.

use nalgebra::{Quaternion, UnitQuaternion};

mod model;
mod pose;

pub use model::{CameraConfig, CameraModel, Distortion, InvalidCamera, NormalizedPoint, Pixel};
pub use pose::CameraPose;

/// A unit quaternion from `[w, x, y, z]` (Hamilton, scalar first, as in the
/// flight format), normalized so that rounded file values are accepted.
pub fn quat_from_wxyz(q: [f64; 4]) -> UnitQuaternion<f64> {
    UnitQuaternion::from_quaternion(Quaternion::new(q[0], q[1], q[2], q[3]))
}

/// `[w, x, y, z]` of a unit quaternion (Hamilton, scalar first). The sign is
/// kept as is (`q` and `-q` are the same rotation).
pub fn quat_to_wxyz(q: &UnitQuaternion<f64>) -> [f64; 4] {
    [q.w, q.i, q.j, q.k]
}
