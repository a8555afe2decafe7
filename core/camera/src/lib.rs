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
//! and cast ECEF rays; [`IntrinsicsCorrection`] is a focal length and
//! principal point error (the simulator's, or the navigator's estimate).
//!
//! ```
//! use nalgebra::Vector3;
//! use trn_camera::{CameraModel, Pixel};
//!
//! // A 640x480 camera with a 60 deg horizontal field of view: a point on the
//! // boresight lands on the principal point, and a pixel's ray projects back onto it.
//! let cam = CameraModel::from_fov(640, 480, 60.0);
//! let centre = cam.project(&Vector3::new(0.0, 0.0, 10.0)).unwrap();
//! assert_eq!((centre.u, centre.v), (cam.cx, cam.cy));
//! let px = Pixel::new(600.0, 20.0);
//! let ray = cam.pixel_to_normalized(px).to_direction();
//! assert!(cam.project(&(ray * 50.0)).unwrap().distance_px(&px) < 1e-9);
//! // The right edge of the image is 30 deg off the boresight.
//! assert!((cam.hfov_deg() - 60.0).abs() < 1e-9);
//! ```

use nalgebra::{Quaternion, UnitQuaternion, Vector4};

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

/// A correction of a camera's intrinsics: the focal lengths scaled by
/// `1 + focal_rel`, the principal point moved by `(du, dv)` pixels and the
/// first radial distortion coefficient changed by `k1` (a calibration error,
/// or a self-calibration's estimate of one).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct IntrinsicsCorrection {
    /// Relative focal length change: `fx, fy` times `1 + focal_rel`.
    pub focal_rel: f64,
    /// Principal point shift along u and v (pixels).
    pub principal_du_px: f64,
    pub principal_dv_px: f64,
    /// Change of the radial distortion coefficient `k1` (added).
    pub k1: f64,
}

impl IntrinsicsCorrection {
    /// `[focal_rel, du, dv, k1]`.
    pub fn to_vector(self) -> Vector4<f64> {
        Vector4::new(self.focal_rel, self.principal_du_px, self.principal_dv_px, self.k1)
    }

    pub fn from_vector(v: &Vector4<f64>) -> Self {
        Self { focal_rel: v.x, principal_du_px: v.y, principal_dv_px: v.z, k1: v.w }
    }

    /// `camera` with the correction applied.
    pub fn apply(&self, camera: &CameraModel) -> CameraModel {
        let mut m = *camera;
        m.fx *= 1.0 + self.focal_rel;
        m.fy *= 1.0 + self.focal_rel;
        m.cx += self.principal_du_px;
        m.cy += self.principal_dv_px;
        m.distortion.k1 += self.k1;
        m
    }
}
