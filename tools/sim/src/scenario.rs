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
    /// How the real camera differs from `camera.json` (what the navigator is told).
    #[serde(default, skip_serializing_if = "CameraError::is_none")]
    pub camera_error: CameraError,
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

/// Calibration and timing errors: the images are rendered with the *true*
/// camera, `camera.json` carries the nominal one (the scenario's `camera`),
/// so a navigator that trusts `camera.json` sees them as a real flight would.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraError {
    /// Relative focal length error: the true fx and fy are the nominal ones times
    /// `1 + focal_rel` (0.003 = 0.3 %, a lens warming up).
    pub focal_rel: f64,
    /// True principal point minus the nominal one, along u (pixels).
    pub principal_du_px: f64,
    /// True principal point minus the nominal one, along v (pixels).
    pub principal_dv_px: f64,
    /// Added to the nominal radial distortion coefficient k1.
    pub k1: f64,
    /// Added to the nominal radial distortion coefficient k2.
    pub k2: f64,
    /// Camera clock minus IMU clock (s): the image stamped `t` in `frames.csv`
    /// (IMU time; `truth.csv` holds the pose at `t`) was exposed at `t + time_offset_s`.
    pub time_offset_s: f64,
}

impl CameraError {
    pub fn is_none(&self) -> bool {
        *self == Self::default()
    }

    /// The true camera behind a nominal model.
    pub fn apply(&self, nominal: &CameraModel) -> CameraModel {
        let mut m = trn_camera::IntrinsicsCorrection {
            focal_rel: self.focal_rel,
            principal_du_px: self.principal_du_px,
            principal_dv_px: self.principal_dv_px,
            k1: self.k1,
        }
        .apply(nominal);
        m.distortion.k2 += self.k2;
        m
    }

    fn validate(&self, nominal: &CameraModel) -> Result<(), String> {
        let checks = [
            ("focal_rel", self.focal_rel, 0.1),
            ("principal_du_px", self.principal_du_px, 0.25 * nominal.width as f64),
            ("principal_dv_px", self.principal_dv_px, 0.25 * nominal.height as f64),
            ("k1", self.k1, 1.0),
            ("k2", self.k2, 1.0),
            ("time_offset_s", self.time_offset_s, 0.5),
        ];
        for (name, v, max) in checks {
            if !(v.is_finite() && v.abs() <= max) {
                return Err(format!("camera_error.{name} {v} must be within +-{max}"));
            }
        }
        self.apply(nominal).validate().map_err(|e| format!("camera_error: the true camera: {e}"))
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
        self.camera_error.validate(&c.model())?;
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
    fn camera_error_makes_the_true_camera_and_names_bad_fields() {
        let nominal = spec(0.0).model();
        let e = CameraError {
            focal_rel: 0.003,
            principal_du_px: 1.5,
            principal_dv_px: -1.0,
            k1: 0.01,
            k2: -0.002,
            time_offset_s: 0.005,
        };
        let t = e.apply(&nominal);
        assert_eq!(t.fx, nominal.fx * 1.003);
        assert_eq!(t.fy, nominal.fy * 1.003);
        assert_eq!((t.cx - nominal.cx, t.cy - nominal.cy), (1.5, -1.0));
        assert_eq!((t.distortion.k1, t.distortion.k2), (0.01, -0.002));
        assert!(e.validate(&nominal).is_ok());
        for (bad, field) in [
            (CameraError { focal_rel: f64::NAN, ..e.clone() }, "camera_error.focal_rel"),
            (CameraError { principal_du_px: 40.0, ..e.clone() }, "camera_error.principal_du_px"),
            (CameraError { time_offset_s: -0.6, ..e.clone() }, "camera_error.time_offset_s"),
            (CameraError { k2: 2.0, ..e.clone() }, "camera_error.k2"),
        ] {
            let msg = bad.validate(&nominal).unwrap_err();
            assert!(msg.contains(field), "{msg}");
        }
        // Off by default, and then not written to the resolved scenario.
        let s: Scenario = serde_json::from_str(
            r#"{"camera": {"width": 64, "height": 48, "hfov_deg": 30}, "trajectory": {"kind": "balloon"}}"#,
        )
        .unwrap();
        assert!(s.camera_error.is_none());
        assert!(!serde_json::to_string(&s).unwrap().contains("camera_error"));
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
