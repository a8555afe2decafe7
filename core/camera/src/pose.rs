//! A camera placed in ECEF: position of the projection centre and attitude.

use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector3};
use trn_geodesy::{Ecef, Ray};

use crate::model::{CameraModel, Pixel};

/// Camera pose in ECEF: projection centre `position` and attitude
/// `q_ecef_cam`, which rotates camera-frame vectors into ECEF
/// (`v_ecef = R(q_ecef_cam) * v_cam`, as the flight format's quaternions).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CameraPose {
    pub position: Ecef,
    pub q_ecef_cam: UnitQuaternion<f64>,
}

impl CameraPose {
    pub fn new(position: Ecef, q_ecef_cam: UnitQuaternion<f64>) -> Self {
        Self { position, q_ecef_cam }
    }

    /// An ECEF point in the camera frame.
    pub fn to_camera(&self, p: &Ecef) -> Vector3<f64> {
        self.q_ecef_cam.inverse_transform_vector(&(p.0 - self.position.0))
    }

    /// A camera-frame point in ECEF.
    pub fn to_ecef(&self, p_cam: &Vector3<f64>) -> Ecef {
        Ecef(self.position.0 + self.q_ecef_cam * p_cam)
    }

    /// Pixel of an ECEF point, `None` behind the camera (see [`CameraModel::project`]).
    pub fn project(&self, cam: &CameraModel, p: &Ecef) -> Option<Pixel> {
        cam.project(&self.to_camera(p))
    }

    /// ECEF ray from the camera centre through a pixel (unit direction, so
    /// the ray parameter is in metres).
    pub fn ray(&self, cam: &CameraModel, px: Pixel) -> Ray {
        Ray { origin: self.position, direction: self.q_ecef_cam * cam.ray(px) }
    }

    /// Unit ECEF direction of the optical axis (camera +z).
    pub fn boresight_ecef(&self) -> Vector3<f64> {
        self.q_ecef_cam * Vector3::z()
    }

    /// A camera at `position` looking at `target` (camera +z toward it), rolled
    /// so that image "up" (camera -y) points as nearly along `up_hint_ecef` as
    /// possible. For a nadir view, `up_hint_ecef` = local north gives a map-like
    /// image: north up, east to the right. When the hint is (nearly) parallel
    /// to the view direction, the roll is arbitrary but well defined.
    pub fn look_at(position: Ecef, target: Ecef, up_hint_ecef: Vector3<f64>) -> Self {
        let z = (target.0 - position.0).normalize();
        let mut up = up_hint_ecef - z * z.dot(&up_hint_ecef);
        if up.norm().is_nan() || up.norm() <= 1e-9 * up_hint_ecef.norm() {
            // Degenerate hint: take the ECEF axis least aligned with the view.
            let axis = z.iamin();
            let mut e = Vector3::zeros();
            e[axis] = 1.0;
            up = e - z * z.dot(&e);
        }
        let y = -up.normalize(); // image down
        let x = y.cross(&z); // right-handed: x = y × z
        let r_ecef_cam = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        Self { position, q_ecef_cam: UnitQuaternion::from_rotation_matrix(&r_ecef_cam) }
    }
}
