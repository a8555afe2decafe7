//! Landmarks predicted into the camera image: each template is warped into
//! image pixels through the homography its terrain plane and the pose guess
//! induce (distortion included through a per-pixel undistortion table), so
//! it can be correlated with the image as the camera would see it.

use nalgebra::{Matrix3, Vector3};
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::{Ecef, Enu};
use trn_landmark::Template;
use trn_vision::ncc;

use crate::image::{from_level, to_level, UndistortLut};

/// A template warped into pyramid level `level` of the image.
pub struct Predicted {
    pub template_id: i64,
    /// Where the template's centre is in ECEF (its 3D landmark).
    pub center_ecef: Ecef,
    /// Where the pose guess puts the centre (full-resolution pixels).
    pub center_px: Pixel,
    /// The warped template, with a mask where it has no data.
    pub patch: ncc::Template,
    /// Level-`level` position of the patch's centre pixel.
    pub patch_center: Pixel,
    pub level: usize,
}

impl Predicted {
    /// The template centre's full-resolution pixel when the patch centre is
    /// found at `found` (level pixels).
    pub fn observed_center(&self, found: Pixel) -> Pixel {
        let c = to_level(self.center_px, self.level);
        from_level(
            Pixel::new(found.u + c.u - self.patch_center.u, found.v + c.v - self.patch_center.v),
            self.level,
        )
    }
}

/// Warps `t` into level `level` of the image seen from `pose`; `None` when
/// the centre is not in view, the plane faces away, or the view is steeper
/// than `max_incidence_deg`.
pub fn predict(
    t: &Template,
    pose: &CameraPose,
    camera: &CameraModel,
    lut: &UndistortLut,
    level: usize,
    max_side: usize,
    max_incidence_deg: f64,
) -> Option<Predicted> {
    let frame = t.local_frame();
    let center = t.center_ecef();
    let center_px = pose.project(camera, &center)?;
    // Plane through the centre with the fitted normal: height as a function of (e, n).
    let nrm = t.plane_normal_enu();
    if nrm.z <= 0.1 {
        return None;
    }
    let to_cam = |c: f64, r: f64| -> Vector3<f64> {
        let e = (c - (t.width_px as f64 - 1.0) / 2.0) * t.gsd_m;
        let n = ((t.height_px as f64 - 1.0) / 2.0 - r) * t.gsd_m;
        let u = -(nrm.x * e + nrm.y * n) / nrm.z;
        pose.to_camera(&frame.to_ecef(Enu::new(e, n, u)))
    };
    // Line of sight against the plane normal.
    let view = (pose.position.0 - center.0).normalize();
    let n_ecef = frame.r_ecef_enu() * nrm;
    let cos_inc = view.dot(&n_ecef);
    if cos_inc <= (max_incidence_deg.to_radians()).cos() {
        return None;
    }
    // Camera-frame point as an affine function of the template pixel:
    // X(c, r) = X00 + c Xc + r Xr, so normalized image points follow a homography.
    let x00 = to_cam(0.0, 0.0);
    let a = Matrix3::from_columns(&[to_cam(1.0, 0.0) - x00, to_cam(0.0, 1.0) - x00, x00]);
    let a_inv = a.try_inverse()?;
    // Patch size: the template's extent in level pixels.
    let (tw, th) = (t.width_px as f64, t.height_px as f64);
    let corners = [(-0.5, -0.5), (tw - 0.5, -0.5), (tw - 0.5, th - 0.5), (-0.5, th - 0.5)];
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for (c, r) in corners {
        let p = camera.project(&to_cam(c, r))?;
        let p = to_level(p, level);
        lo = [lo[0].min(p.u), lo[1].min(p.v)];
        hi = [hi[0].max(p.u), hi[1].max(p.v)];
    }
    let side = ((hi[0] - lo[0]).max(hi[1] - lo[1]).ceil() as usize).clamp(9, max_side) | 1;
    let c = to_level(center_px, level);
    let half = (side / 2) as isize;
    let (x0, y0) = (c.u.round() as isize - half, c.v.round() as isize - half);
    let (lw, lh, _) = &lut.levels[level];
    let mut data = vec![0f32; side * side];
    let mut mask = vec![false; side * side];
    let tw_i = t.width_px as usize;
    for j in 0..side {
        let y = y0 + j as isize;
        if y < 0 || y >= *lh as isize {
            continue;
        }
        for i in 0..side {
            let x = x0 + i as isize;
            if x < 0 || x >= *lw as isize {
                continue;
            }
            let n = lut.at(level, x as usize, y as usize);
            let m = a_inv * Vector3::new(n[0] as f64, n[1] as f64, 1.0);
            if m.z <= 0.0 {
                continue;
            }
            let (tc, tr) = (m.x / m.z, m.y / m.z);
            if !(tc >= 0.0 && tr >= 0.0 && tc <= tw - 1.0 && tr <= th - 1.0) {
                continue;
            }
            let (ic, ir) = ((tc as usize).min(tw_i - 2), (tr as usize).min(t.height_px as usize - 2));
            let (fc, fr) = ((tc - ic as f64) as f32, (tr - ir as f64) as f32);
            let px = |cc: usize, rr: usize| t.pixels[rr * tw_i + cc] as f32;
            data[j * side + i] = (px(ic, ir) * (1.0 - fc) + px(ic + 1, ir) * fc) * (1.0 - fr)
                + (px(ic, ir + 1) * (1.0 - fc) + px(ic + 1, ir + 1) * fc) * fr;
            mask[j * side + i] = true;
        }
    }
    let valid = mask.iter().filter(|&&m| m).count();
    if valid < side * side / 3 {
        return None;
    }
    Some(Predicted {
        template_id: t.id,
        center_ecef: center,
        center_px,
        patch: ncc::Template { width: side, height: side, data, mask: Some(mask) },
        patch_center: Pixel::new((x0 + half) as f64, (y0 + half) as f64),
        level,
    })
}
