//! Landmarks predicted into the camera image: each template is warped into
//! image pixels as the pose guess would see it (distortion included through
//! a per-pixel undistortion table), so it can be correlated with the image.
//! Over flat terrain the warp is the homography the template's terrain plane
//! induces; where the terrain departs from the plane by more than
//! [`RELIEF_SHARE_OF_GSD`] of a template pixel, each image pixel's ray is
//! intersected with the template's height grid instead (first crossing, so
//! relief hides what lies behind it).

use nalgebra::{Matrix3, Vector3};
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::{Ecef, Enu};
use trn_landmark::Template;
use trn_vision::ncc;

use crate::image::{from_level, to_level, UndistortLut};

/// RMS departure of the terrain from the template's plane (in template
/// pixels) above which the warp follows the height grid, not the plane.
pub const RELIEF_SHARE_OF_GSD: f64 = 0.25;

/// Fewest template pixels a prediction must put in the image.
pub const MIN_VALID_PX: f64 = 40.0;

/// A template's terrain for ray intersection, in its tangent frame.
struct Relief<'a> {
    grid: &'a trn_landmark::HeightGrid,
    /// Camera centre (ENU, template frame) and rotation camera -> ENU.
    origin: Vector3<f64>,
    r_enu_cam: Matrix3<f64>,
    h_lo: f64,
    h_hi: f64,
    /// Largest horizontal step of the march (m).
    step_m: f64,
}

impl Relief<'_> {
    /// Tangent-plane (east, north) where the ray through normalized image
    /// point (x, y) first meets the terrain; `None` if it points up or the
    /// march does not close.
    fn hit(&self, x: f64, y: f64) -> Option<(f64, f64)> {
        let d = self.r_enu_cam * Vector3::new(x, y, 1.0);
        if d.z >= -1e-9 {
            return None;
        }
        let o = &self.origin;
        let f = |s: f64| o.z + s * d.z - self.grid.height_at(o.x + s * d.x, o.y + s * d.y);
        // The ray is within the terrain's height band for s in [s0, s1].
        let (s0, s1) = ((self.h_hi - o.z) / d.z, (self.h_lo - o.z) / d.z);
        let horiz = d.x.hypot(d.y);
        let n = if horiz * (s1 - s0) <= self.step_m {
            1
        } else {
            ((horiz * (s1 - s0) / self.step_m).ceil() as usize).min(256)
        };
        let ds = (s1 - s0) / n as f64;
        let (mut a, mut fa) = (s0, f(s0));
        for i in 1..=n {
            let b = s0 + ds * i as f64;
            let fb = f(b);
            if fb <= 0.0 {
                // Bracketed: false position, a few steps (bilinear terrain).
                let (mut lo, mut flo, mut hi, mut fhi) = (a, fa, b, fb);
                for _ in 0..6 {
                    let m =
                        if flo - fhi > 1e-12 { lo + (hi - lo) * flo / (flo - fhi) } else { 0.5 * (lo + hi) };
                    let fm = f(m);
                    if fm > 0.0 {
                        (lo, flo) = (m, fm);
                    } else {
                        (hi, fhi) = (m, fm);
                    }
                }
                let s = if flo - fhi > 1e-12 { lo + (hi - lo) * flo / (flo - fhi) } else { hi };
                return Some((o.x + s * d.x, o.y + s * d.y));
            }
            (a, fa) = (b, fb);
        }
        None
    }
}

/// Side (patch pixels) of the cells [`relief_hits`] interpolates over.
const RELIEF_CELL_PX: usize = 4;
/// A cell is interpolated when the exact hit at its centre is within this
/// share of a template pixel of its corners' bilinear mean.
const RELIEF_INTERPOLATION_TOLERANCE: f64 = 0.25;

/// The terrain hit `(east, north)` of every pixel of a `side`-square patch
/// (row-major), `hit(i, j)` being the exact one (a ray march). The march is
/// the cost of a relief prediction (80% of an oblique frame's time), and
/// over smooth terrain the hits vary smoothly: they are marched exactly on a
/// lattice every [`RELIEF_CELL_PX`] pixels and at each cell's centre, and a
/// cell whose four corners hit and whose centre agrees with their mean
/// within `tolerance_m` is filled bilinearly; any other cell (an occlusion
/// edge, the sky, the image border) is marched pixel by pixel.
fn relief_hits(
    side: usize,
    tolerance_m: f64,
    hit: impl Fn(usize, usize) -> Option<(f64, f64)>,
) -> Vec<Option<(f64, f64)>> {
    let k = RELIEF_CELL_PX;
    let cells = side.div_ceil(k);
    let nl = cells + 1;
    let lattice: Vec<Option<(f64, f64)>> = (0..nl * nl).map(|q| hit((q % nl) * k, (q / nl) * k)).collect();
    let mut out = vec![None; side * side];
    for cj in 0..cells {
        for ci in 0..cells {
            let corners = [
                lattice[cj * nl + ci],
                lattice[cj * nl + ci + 1],
                lattice[(cj + 1) * nl + ci],
                lattice[(cj + 1) * nl + ci + 1],
            ];
            let smooth = match corners {
                [Some(a), Some(b), Some(c), Some(d)] => hit(ci * k + k / 2, cj * k + k / 2)
                    .is_some_and(|m| {
                        let mean = (0.25 * (a.0 + b.0 + c.0 + d.0), 0.25 * (a.1 + b.1 + c.1 + d.1));
                        (m.0 - mean.0).hypot(m.1 - mean.1) <= tolerance_m
                    })
                    .then_some([a, b, c, d]),
                _ => None,
            };
            for j in cj * k..((cj + 1) * k).min(side) {
                for i in ci * k..((ci + 1) * k).min(side) {
                    out[j * side + i] = match smooth {
                        Some([a, b, c, d]) => {
                            let (fx, fy) = ((i - ci * k) as f64 / k as f64, (j - cj * k) as f64 / k as f64);
                            let lerp = |p: f64, q: f64, r: f64, s: f64| {
                                (p * (1.0 - fx) + q * fx) * (1.0 - fy) + (r * (1.0 - fx) + s * fx) * fy
                            };
                            Some((lerp(a.0, b.0, c.0, d.0), lerp(a.1, b.1, c.1, d.1)))
                        }
                        None => hit(i, j),
                    };
                }
            }
        }
    }
    out
}

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
    /// The template's ground sample distance (m).
    pub gsd_m: f64,
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
    let grid = &t.terrain.height_grid;
    let relief = (t.terrain.plane_residual_rms_m > RELIEF_SHARE_OF_GSD * t.gsd_m
        && grid.n >= 2
        && grid.heights_m.len() == (grid.n * grid.n) as usize)
        .then(|| {
            let r_enu_ecef = frame.r_ecef_enu().transpose();
            let (h_lo, h_hi) = grid
                .heights_m
                .iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| (l.min(v as f64), h.max(v as f64)));
            Relief {
                grid,
                origin: frame.to_enu(&pose.position).0,
                r_enu_cam: r_enu_ecef * pose.q_ecef_cam.to_rotation_matrix().matrix(),
                h_lo: h_lo - 0.01,
                h_hi: h_hi + 0.01,
                step_m: 0.5 * grid.spacing_m.min(t.gsd_m * 2.0),
            }
        });
    // Patch size: the template's extent in level pixels (its outline at the
    // grid's heights when relief is modelled).
    let (tw, th) = (t.width_px as f64, t.height_px as f64);
    let mut outline = vec![(-0.5, -0.5), (tw - 0.5, -0.5), (tw - 0.5, th - 0.5), (-0.5, th - 0.5)];
    if relief.is_some() {
        outline.extend([(tw / 2.0, -0.5), (tw / 2.0, th - 0.5), (-0.5, th / 2.0), (tw - 0.5, th / 2.0)]);
    }
    let to_cam_relief = |c: f64, r: f64| -> Vector3<f64> {
        let e = (c - (tw - 1.0) / 2.0) * t.gsd_m;
        let n = ((th - 1.0) / 2.0 - r) * t.gsd_m;
        pose.to_camera(&frame.to_ecef(Enu::new(e, n, grid.height_at(e, n))))
    };
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    let mut ring = Vec::with_capacity(outline.len());
    for (c, r) in outline {
        let x = if relief.is_some() { to_cam_relief(c, r) } else { to_cam(c, r) };
        let p = camera.project(&x)?;
        let p = to_level(p, level);
        lo = [lo[0].min(p.u), lo[1].min(p.v)];
        hi = [hi[0].max(p.u), hi[1].max(p.v)];
        ring.push(p);
    }
    // Projected area of the template (shoelace over its four corners), level pixels².
    let area_px = 0.5
        * (0..4)
            .map(|i| {
                let (a, b) = (ring[i], ring[(i + 1) % 4]);
                a.u * b.v - b.u * a.v
            })
            .sum::<f64>()
            .abs();
    let side = ((hi[0] - lo[0]).max(hi[1] - lo[1]).ceil() as usize).clamp(9, max_side) | 1;
    let c = to_level(center_px, level);
    let half = (side / 2) as isize;
    let (x0, y0) = (c.u.round() as isize - half, c.v.round() as isize - half);
    let (lw, lh, _) = &lut.levels[level];
    // A centre outside the image (a search from a guess far off, whose
    // window reaches into the image) gets its whole patch, the rays of the
    // pixels beyond the image from the camera model; one inside keeps only
    // the part in the image.
    let (w, h) = (camera.width as f64, camera.height as f64);
    let centre_outside = !(center_px.u >= 0.0 && center_px.v >= 0.0 && center_px.u < w && center_px.v < h);
    // The ray (normalized image point) of a patch pixel: the undistortion
    // table's inside the image, the camera model's beyond it when the centre
    // is outside; `None` where the patch keeps no pixel.
    let ray = |x: isize, y: isize| -> Option<[f32; 2]> {
        if x >= 0 && y >= 0 && x < *lw as isize && y < *lh as isize {
            Some(lut.at(level, x as usize, y as usize))
        } else if centre_outside {
            let q =
                camera.pixel_to_normalized(crate::image::from_level(Pixel::new(x as f64, y as f64), level));
            Some([q.x as f32, q.y as f32])
        } else {
            None
        }
    };
    let mut data = vec![0f32; side * side];
    let mut mask = vec![false; side * side];
    let tw_i = t.width_px as usize;
    // Patch pixel `k` shows the template at pixel (column, row) `(tc, tr)`.
    let mut sample = |k: usize, tc: f64, tr: f64| {
        if !(tc >= 0.0 && tr >= 0.0 && tc <= tw - 1.0 && tr <= th - 1.0) {
            return;
        }
        let (ic, ir) = ((tc as usize).min(tw_i - 2), (tr as usize).min(t.height_px as usize - 2));
        let (fc, fr) = ((tc - ic as f64) as f32, (tr - ir as f64) as f32);
        let px = |cc: usize, rr: usize| t.pixels[rr * tw_i + cc] as f32;
        data[k] = (px(ic, ir) * (1.0 - fc) + px(ic + 1, ir) * fc) * (1.0 - fr)
            + (px(ic, ir + 1) * (1.0 - fc) + px(ic + 1, ir + 1) * fc) * fr;
        mask[k] = true;
    };
    match &relief {
        // Through the relief: each pixel's terrain hit (see `relief_hits`).
        Some(rl) => {
            let hits = relief_hits(side, RELIEF_INTERPOLATION_TOLERANCE * t.gsd_m, |i, j| {
                let n = ray(x0 + i as isize, y0 + j as isize)?;
                rl.hit(n[0] as f64, n[1] as f64)
            });
            for (k, hit) in hits.into_iter().enumerate() {
                if let Some((e, nn)) = hit {
                    sample(k, e / t.gsd_m + (tw - 1.0) / 2.0, (th - 1.0) / 2.0 - nn / t.gsd_m);
                }
            }
        }
        // Through the plane's homography.
        None => {
            for k in 0..side * side {
                let Some(n) = ray(x0 + (k % side) as isize, y0 + (k / side) as isize) else { continue };
                let m = a_inv * Vector3::new(n[0] as f64, n[1] as f64, 1.0);
                if m.z > 0.0 {
                    sample(k, m.x / m.z, m.y / m.z);
                }
            }
        }
    }
    // Enough of the template must land in the image: a third of its
    // projected area (a foreshortened template fills little of its square
    // patch), and at least MIN_VALID_PX pixels.
    let valid = mask.iter().filter(|&&m| m).count();
    if (valid as f64) < (area_px / 3.0).min((side * side) as f64 / 3.0).max(MIN_VALID_PX) {
        return None;
    }
    Some(Predicted {
        template_id: t.id,
        center_ecef: center,
        center_px,
        patch: ncc::Template { width: side, height: side, data, mask: Some(mask) },
        patch_center: Pixel::new((x0 + half) as f64, (y0 + half) as f64),
        level,
        gsd_m: t.gsd_m,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::Geodetic;
    use trn_landmark::{GeoBox, HeightGrid, TemplateQuality, TerrainPatch};

    /// A 32-px template at 30 m over a ridge running north-south (height
    /// `ridge_m` at the centre line), with a smooth texture.
    fn ridge_template(ridge_m: f64) -> Template {
        let (n, size, gsd) = (17u32, 32u32, 30.0);
        let half = (size as f64) / 2.0 * gsd;
        let spacing = 2.0 * half / (n as f64 - 1.0);
        let h = |e: f64| ridge_m * (1.0 - (e.abs() / 300.0)).max(0.0);
        let heights_m: Vec<f32> = (0..n * n).map(|i| h(-half + (i % n) as f64 * spacing) as f32).collect();
        let en: Vec<(f64, f64)> =
            (0..n * n).map(|i| (-half + (i % n) as f64 * spacing, half - (i / n) as f64 * spacing)).collect();
        let up: Vec<f64> = heights_m.iter().map(|&v| v as f64).collect();
        // The plane a builder would fit (least squares, as trn-builder does).
        let (mut s, mut su) = (0.0, 0.0);
        for &u in &up {
            s += 1.0;
            su += u;
        }
        let mean = su / s;
        let rms = (up.iter().map(|u| (u - mean).powi(2)).sum::<f64>() / s).sqrt();
        let _ = en;
        let pixels = (0..size * size)
            .map(|i| {
                let (c, r) = ((i % size) as f64, (i / size) as f64);
                (128.0 + 60.0 * (c * 0.35).sin() * (r * 0.27).cos() + 40.0 * (c * 0.11 + r * 0.19).sin())
                    as u8
            })
            .collect();
        Template {
            id: 1,
            level: 0,
            gsd_m: gsd,
            width_px: size,
            height_px: size,
            center: Geodetic::new(37.0, -118.5, 2000.0),
            footprint: GeoBox::new(0.0, 0.0, 0.0, 0.0),
            terrain: TerrainPatch {
                plane_normal_enu: [0.0, 0.0, 1.0],
                plane_residual_rms_m: rms,
                height_grid: HeightGrid { n, spacing_m: spacing, heights_m },
            },
            quality: TemplateQuality {
                shi_tomasi: 10.0,
                contrast_std: 30.0,
                second_peak_ncc: 0.2,
                shading_share: 0.0,
            },
            source: 0,
            lighting: 0,
            pixels,
        }
    }

    /// Mean absolute difference between the patch and the template's own
    /// pixels projected forward through the true terrain (pixel centres away
    /// from the template's border, seen and not hidden).
    fn forward_error(t: &Template, pose: &CameraPose, camera: &CameraModel) -> f64 {
        let lut = UndistortLut::new(camera, 1);
        let p = predict(t, pose, camera, &lut, 0, 255, 85.0).expect("predicted");
        let frame = t.local_frame();
        let g = &t.terrain.height_grid;
        let (mut sum, mut n) = (0.0, 0);
        for r in 4..t.height_px - 4 {
            for c in 4..t.width_px - 4 {
                let e = (c as f64 - 15.5) * t.gsd_m;
                let nn = (15.5 - r as f64) * t.gsd_m;
                let u = g.height_at(e, nn);
                // Brute force visibility: the segment to the camera stays above the terrain.
                let eye = frame.to_enu(&pose.position).0;
                let hidden = (1..2000).any(|i| {
                    let s = i as f64 / 2000.0 * 0.2;
                    let q = Vector3::new(e, nn, u) + (eye - Vector3::new(e, nn, u)) * s;
                    q.z < g.height_at(q.x, q.y) - 0.01
                });
                if hidden {
                    continue;
                }
                let x = pose.to_camera(&frame.to_ecef(Enu::new(e, nn, u)));
                let q = camera.project(&x).unwrap();
                let (pu, pv) = (
                    q.u - p.patch_center.u + (p.patch.width / 2) as f64,
                    q.v - p.patch_center.v + (p.patch.height / 2) as f64,
                );
                let (iu, iv) = (pu.round() as usize, pv.round() as usize);
                if iu >= p.patch.width || iv >= p.patch.height {
                    continue;
                }
                let k = iv * p.patch.width + iu;
                if !p.patch.mask.as_ref().unwrap()[k] {
                    continue;
                }
                sum += (p.patch.data[k] as f64 - t.pixels[(r * t.width_px + c) as usize] as f64).abs();
                n += 1;
            }
        }
        assert!(n > 300, "{n} samples");
        sum / n as f64
    }

    #[test]
    fn relief_is_predicted_through_the_height_grid() {
        let camera = CameraModel::from_fov(1024, 768, 30.0);
        let t = ridge_template(250.0);
        let centre = t.center_ecef();
        // 6 km east of the ridge and 8 km up: its top leans ~190 m (6 template
        // pixels) against its foot in the view.
        let frame = t.local_frame();
        let eye = frame.to_ecef(Enu::new(6000.0, 0.0, 8000.0));
        let pose = CameraPose::look_at(eye, centre, t.center.up_ecef());
        let with_relief = forward_error(&t, &pose, &camera);
        // The same template with its relief hidden from the predictor: the plane.
        let mut flat = t.clone();
        flat.terrain.plane_residual_rms_m = 0.0;
        let planar = forward_error(&flat, &pose, &camera);
        eprintln!("forward error: relief-aware {with_relief:.2}, planar {planar:.2} grey levels");
        assert!(with_relief < 6.0, "relief-aware prediction off by {with_relief:.1} grey levels");
        assert!(planar > 2.0 * with_relief, "plane {planar:.1} vs relief {with_relief:.1}");
    }

    /// A centre the guess puts outside the image (an acquisition's search
    /// reaches in from there) gets its whole patch, the same as the one an
    /// inside view of it gives; one inside keeps only what the image holds.
    #[test]
    fn a_centre_outside_the_image_gets_its_whole_patch() {
        let camera = CameraModel::from_fov(640, 480, 40.0);
        let lut = UndistortLut::new(&camera, 1);
        let t = ridge_template(0.0);
        let centre = t.center_ecef();
        let frame = t.local_frame();
        let eye = frame.to_ecef(Enu::new(0.0, 0.0, 6000.0));
        let north = frame.to_ecef(Enu::new(0.0, 1.0, 0.0)).0 - centre.0;
        let inside = CameraPose::look_at(eye, centre, north);
        // Turned 25 degrees about the camera's y axis: the centre leaves the
        // image on the left (half the field of view is 20 degrees).
        let turn =
            nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::y_axis(), 25f64.to_radians());
        let outside = CameraPose { q_ecef_cam: inside.q_ecef_cam * turn, ..inside };
        let p_in = predict(&t, &inside, &camera, &lut, 0, 63, 85.0).expect("inside");
        let p_out = predict(&t, &outside, &camera, &lut, 0, 63, 85.0).expect("outside");
        assert!(p_out.center_px.u < 0.0, "{:?}", p_out.center_px);
        let valid = |p: &Predicted| {
            p.patch.mask.as_ref().map_or(p.patch.data.len(), |m| m.iter().filter(|&&b| b).count())
        };
        assert_eq!(p_out.patch.width, p_in.patch.width);
        assert!(valid(&p_out) as f64 >= 0.9 * valid(&p_in) as f64, "{} of {}", valid(&p_out), valid(&p_in));
        // Straddling the left edge: only the inside part.
        let edge =
            nalgebra::UnitQuaternion::from_axis_angle(&nalgebra::Vector3::y_axis(), 19.5f64.to_radians());
        let p_edge = predict(
            &t,
            &CameraPose { q_ecef_cam: inside.q_ecef_cam * edge, ..inside },
            &camera,
            &lut,
            0,
            63,
            85.0,
        )
        .expect("edge");
        assert!(p_edge.center_px.u >= 0.0 && p_edge.center_px.u < 10.0, "{:?}", p_edge.center_px);
        assert!(
            (valid(&p_edge) as f64) < 0.8 * valid(&p_in) as f64,
            "{} of {}",
            valid(&p_edge),
            valid(&p_in)
        );
    }

    /// The lattice's shortcut is exact where the hits are affine, marches
    /// every pixel of a cell an occlusion edge crosses, and leaves the sky out.
    #[test]
    fn relief_hits_interpolate_smooth_cells_and_march_the_rest() {
        let side = 23;
        let calls = std::cell::Cell::new(0usize);
        // Affine: every cell interpolated, equal to the exact hits.
        let affine = |i: usize, j: usize| {
            calls.set(calls.get() + 1);
            Some((3.0 * i as f64 - 1.0 * j as f64, 0.5 * i as f64 + 2.0 * j as f64))
        };
        let out = relief_hits(side, 0.1, affine);
        for j in 0..side {
            for i in 0..side {
                let (e, n) = out[j * side + i].unwrap();
                let (ee, nn) = (3.0 * i as f64 - 1.0 * j as f64, 0.5 * i as f64 + 2.0 * j as f64);
                assert!((e - ee).abs() < 1e-9 && (n - nn).abs() < 1e-9, "{i} {j}");
            }
        }
        let marched = calls.get();
        assert!(marched < side * side / 4, "{marched} marches for {} pixels", side * side);
        // An occlusion edge at column 10 (the far slope jumps 500 m away) and
        // sky below row 17: those cells are marched, so every pixel is exact.
        let exact =
            |i: usize, j: usize| (j < 17).then_some((i as f64 + if i >= 10 { 500.0 } else { 0.0 }, j as f64));
        let out = relief_hits(side, 0.1, exact);
        for j in 0..side {
            for i in 0..side {
                assert_eq!(out[j * side + i], exact(i, j), "{i} {j}");
            }
        }
    }
}
