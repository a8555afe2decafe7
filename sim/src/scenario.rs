//! A simulation scenario (`scenario.json`): where and how the vehicle flies,
//! the camera and its mounting, the IMU, the initial-guess error and the
//! realism effects. Everything has a default but the camera and trajectory.

use std::path::Path;

use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
use serde::{Deserialize, Serialize};
use trn_camera::{CameraModel, Distortion};

use crate::effects::Realism;
use crate::imu::ImuParams;
use crate::trajectory::TrajectoryParams;
use crate::SimError;

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Scenario {
    #[serde(default)]
    pub name: String,
    /// Seeds every random choice (bursts, noise, initial error, clouds).
    #[serde(default = "default_seed")]
    pub seed: u64,
    /// Ground point under the start (balloon) or the launch pad (rocket);
    /// default: the centre of the ortho.
    #[serde(default)]
    pub origin: Option<Origin>,
    pub camera: CameraSpec,
    /// Images per second.
    #[serde(default = "default_frame_rate")]
    pub frame_rate_hz: f64,
    pub trajectory: TrajectoryParams,
    #[serde(default)]
    pub imu: ImuParams,
    #[serde(default)]
    pub init_error: InitError,
    #[serde(default)]
    pub realism: Realism,
}

fn default_seed() -> u64 {
    1
}

fn default_frame_rate() -> f64 {
    4.0
}

#[derive(Clone, Copy, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Origin {
    pub lat: f64,
    pub lon: f64,
}

/// The camera: image size, field of view, lens distortion, mounting and
/// exposure.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    pub width: u32,
    pub height: u32,
    /// Horizontal field of view of the undistorted pinhole (sets fx = fy; square
    /// pixels, principal point at the centre). With distortion the image
    /// covers a slightly different angle.
    pub hfov_deg: f64,
    #[serde(default)]
    pub distortion: Distortion,
    /// Boresight tilt from the body's +z (down) toward its +x (forward):
    /// 0 looks straight down, 90 at the horizon.
    #[serde(default)]
    pub tilt_deg: f64,
    /// Exposure time, for motion blur.
    #[serde(default = "default_exposure")]
    pub exposure_s: f64,
}

fn default_exposure() -> f64 {
    0.004
}

impl CameraSpec {
    pub fn model(&self) -> CameraModel {
        let mut m = CameraModel::from_fov(self.width, self.height, self.hfov_deg);
        m.distortion = self.distortion;
        m
    }

    /// `q_cam_imu` of the mounting: camera x = body y (right); the boresight
    /// turns from body z toward body x by `tilt_deg`, so image up points
    /// forward for a nadir camera and up for a horizontal one.
    pub fn q_cam_imu(&self) -> UnitQuaternion<f64> {
        let (s, c) = self.tilt_deg.to_radians().sin_cos();
        // Columns: camera axes in body coordinates.
        let x_cam = nalgebra::Vector3::new(0.0, 1.0, 0.0);
        let z_cam = nalgebra::Vector3::new(s, 0.0, c);
        let y_cam = z_cam.cross(&x_cam);
        let r_imu_cam = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x_cam, y_cam, z_cam]));
        UnitQuaternion::from_rotation_matrix(&r_imu_cam).inverse()
    }
}

/// Error of the initial pose guess written to `init.json`: exact magnitudes
/// in random directions (seeded).
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct InitError {
    pub horizontal_m: f64,
    pub vertical_m: f64,
    pub attitude_deg: f64,
}

impl Default for InitError {
    fn default() -> Self {
        Self { horizontal_m: 300.0, vertical_m: 100.0, attitude_deg: 2.0 }
    }
}

impl Scenario {
    /// Reads and checks a scenario file.
    pub fn load(path: &Path) -> Result<Scenario, SimError> {
        let bad = |reason: String| SimError::Input { path: path.into(), reason };
        let text = std::fs::read_to_string(path).map_err(|e| bad(e.to_string()))?;
        let s: Scenario = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
        s.validate().map_err(bad)?;
        Ok(s)
    }

    /// Checks value ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        let c = &self.camera;
        if c.width < 16 || c.height < 16 || c.width > 16384 || c.height > 16384 {
            return Err(format!("camera.width/height {}x{} must be 16..16384 pixels", c.width, c.height));
        }
        if !(c.hfov_deg > 0.5 && c.hfov_deg < 170.0) {
            return Err(format!("camera.hfov_deg {} must be in (0.5, 170)", c.hfov_deg));
        }
        if !(c.tilt_deg.is_finite() && (-180.0..=180.0).contains(&c.tilt_deg)) {
            return Err(format!("camera.tilt_deg {} must be in [-180, 180]", c.tilt_deg));
        }
        if !(c.exposure_s >= 0.0 && c.exposure_s <= 1.0) {
            return Err(format!("camera.exposure_s {} must be in [0, 1]", c.exposure_s));
        }
        c.model().validate().map_err(|e| format!("camera: {e}"))?;
        if !(self.frame_rate_hz > 0.0 && self.frame_rate_hz <= 100.0) {
            return Err(format!("frame_rate_hz {} must be in (0, 100]", self.frame_rate_hz));
        }
        if let Some(o) = &self.origin {
            if !((-90.0..=90.0).contains(&o.lat) && (-360.0..=360.0).contains(&o.lon)) {
                return Err(format!("origin ({}, {}) is not a latitude/longitude in degrees", o.lat, o.lon));
            }
        }
        let e = &self.init_error;
        for (name, v) in
            [("horizontal_m", e.horizontal_m), ("vertical_m", e.vertical_m), ("attitude_deg", e.attitude_deg)]
        {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("init_error.{name} {v} must be a number >= 0"));
            }
        }
        self.trajectory.validate()?;
        self.imu.validate()?;
        self.realism.validate()?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Vector3;

    fn spec(tilt: f64) -> CameraSpec {
        CameraSpec {
            width: 64,
            height: 48,
            hfov_deg: 30.0,
            distortion: Distortion::default(),
            tilt_deg: tilt,
            exposure_s: 0.0,
        }
    }

    #[test]
    fn mounting_points_the_boresight_by_tilt() {
        // v_imu = q_cam_imu^-1 * v_cam: the boresight (camera z) in body axes.
        let q = spec(0.0).q_cam_imu();
        assert!((q.inverse() * Vector3::z() - Vector3::z()).norm() < 1e-12);
        // Image up (-y) is body forward for a nadir camera.
        assert!((q.inverse() * -Vector3::y() - Vector3::x()).norm() < 1e-12);
        let q = spec(90.0).q_cam_imu();
        assert!((q.inverse() * Vector3::z() - Vector3::x()).norm() < 1e-12);
        // Image up is body up (-z) for a horizontal camera.
        assert!((q.inverse() * -Vector3::y() + Vector3::z()).norm() < 1e-12);
        let q = spec(60.0).q_cam_imu();
        let b = q.inverse() * Vector3::z();
        assert!((b.z - 0.5).abs() < 1e-12 && (b.x - 0.75f64.sqrt()).abs() < 1e-12);
    }
}
