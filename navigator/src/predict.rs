//! Landmarks predicted into the camera image: each template is warped into
//! image pixels as the pose guess would see it (lens distortion included),
//! so it can be correlated with the image. Over flat terrain the warp is the
//! homography the template's terrain plane induces, each pixel's ray from a
//! per-pixel undistortion table; where the terrain departs from the plane by
//! more than [`RELIEF_SHARE_OF_GSD`] of a template pixel, the template's
//! height grid is drawn into the image instead, as a triangle mesh projected
//! through the lens, with a depth buffer (so relief hides what lies behind
//! it).

use nalgebra::{Matrix3, Vector3};
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::{Ecef, Enu};
use trn_landmark::Template;
use trn_vision::ncc;
use trn_vision::warp::{bilinear, homography_row, homography_sample, GreyTemplate};

use crate::image::{from_level, to_level, UndistortLut};

/// RMS departure of the terrain from the template's plane (in template
/// pixels) above which the warp follows the height grid, not the plane.
pub const RELIEF_SHARE_OF_GSD: f64 = 0.25;

/// Fewest template pixels a prediction must put in the image.
pub const MIN_VALID_PX: f64 = 40.0;

/// A template's terrain as a triangle mesh in the image, for the relief warp.
struct ReliefMesh<'a> {
    grid: &'a trn_landmark::HeightGrid,
    /// Camera centre (ENU, template frame) and rotation ENU -> camera.
    origin: Vector3<f64>,
    r_cam_enu: Matrix3<f64>,
}

/// Largest side of a mesh cell (template pixels): each height-grid cell is
/// cut into cells no wider, four triangles each around the cell's centre.
/// (Two triangles a cell leave the bilinear surface's twist out, a quarter of
/// it at the cell's centre: the low pass's first fixes after an acquisition told
/// from 1.5 and 3 km were 38 and 33 m off where the centre vertex gives 13–14 m;
/// cells of 1 pixel with two triangles cost as much as this.)
const MESH_CELL_PX: f64 = 2.0;

impl ReliefMesh<'_> {
    /// Template pixel `(column, row)` of every patch pixel (row-major,
    /// `side`-square, patch pixel `(i, j)` at level pixel `(x0 + i, y0 + j)`)
    /// where the template's terrain is what the camera sees there: the height
    /// grid's surface is cut into triangles (vertices on the bilinear surface:
    /// the corners of cells at most [`MESH_CELL_PX`] template pixels wide and
    /// their centres), each projected through the camera (lens included)
    /// and filled in the image by its barycentric weights; the nearest
    /// surface wins (a depth buffer), and triangles that face away from the
    /// camera are left out, so relief hides what lies behind it. `keep(i, j)`
    /// says which patch pixels may hold data.
    fn rasterize(
        &self,
        t: &Template,
        camera: &CameraModel,
        level: usize,
        side: usize,
        (x0, y0): (isize, isize),
        keep: impl Fn(usize, usize) -> bool,
    ) -> Vec<Option<(f64, f64)>> {
        let g = self.grid;
        let n = g.n as usize;
        let sub = ((g.spacing_m / (MESH_CELL_PX * t.gsd_m)).ceil() as usize).max(1);
        let m = (n - 1) * sub + 1;
        let step = g.spacing_m / sub as f64;
        let half = (n as f64 - 1.0) / 2.0 * g.spacing_m;
        let (tw, th) = (t.width_px as f64, t.height_px as f64);
        // Vertices: ENU, patch-local pixel, depth (camera z) and template
        // pixel, or `None` behind the camera.
        struct Vertex {
            enu: Vector3<f64>,
            px: [f64; 2],
            depth: f64,
            at: [f64; 2],
        }
        let vertex = |e: f64, nn: f64| {
            let enu = Vector3::new(e, nn, g.height_at(e, nn));
            let x = self.r_cam_enu * (enu - self.origin);
            let p = to_level(camera.project(&x)?, level);
            let at = [e / t.gsd_m + (tw - 1.0) / 2.0, (th - 1.0) / 2.0 - nn / t.gsd_m];
            Some(Vertex { enu, px: [p.u - x0 as f64, p.v - y0 as f64], depth: x.z, at })
        };
        // The cells' corners, then their centres.
        let vertices: Vec<Option<Vertex>> = (0..m * m)
            .map(|q| vertex(-half + (q % m) as f64 * step, half - (q / m) as f64 * step))
            .chain((0..(m - 1) * (m - 1)).map(|q| {
                let (ci, cj) = (q % (m - 1), q / (m - 1));
                vertex(-half + (ci as f64 + 0.5) * step, half - (cj as f64 + 0.5) * step)
            }))
            .collect();
        let mut depth = vec![f64::INFINITY; side * side];
        let mut out = vec![None; side * side];
        let lim = side as f64 - 1.0;
        // The first whole pixel at or after a non-negative `x` (no libm call).
        let ceil = |x: f64| {
            let i = x as usize;
            if (i as f64) < x {
                i + 1
            } else {
                i
            }
        };
        for cj in 0..m - 1 {
            for ci in 0..m - 1 {
                let q = cj * m + ci;
                let centre = m * m + cj * (m - 1) + ci;
                for tri in [
                    [q, q + 1, centre],
                    [q + 1, q + m + 1, centre],
                    [q + m + 1, q + m, centre],
                    [q + m, q, centre],
                ] {
                    let (Some(a), Some(b), Some(c)) =
                        (&vertices[tri[0]], &vertices[tri[1]], &vertices[tri[2]])
                    else {
                        continue;
                    };
                    let (lo_u, hi_u) = (a.px[0].min(b.px[0]).min(c.px[0]), a.px[0].max(b.px[0]).max(c.px[0]));
                    let (lo_v, hi_v) = (a.px[1].min(b.px[1]).min(c.px[1]), a.px[1].max(b.px[1]).max(c.px[1]));
                    if hi_u < 0.0 || hi_v < 0.0 || lo_u > lim || lo_v > lim {
                        continue;
                    }
                    let (i0, i1) = (ceil(lo_u.max(0.0)), hi_u.min(lim) as usize);
                    let (j0, j1) = (ceil(lo_v.max(0.0)), hi_v.min(lim) as usize);
                    if i0 > i1 || j0 > j1 {
                        continue;
                    }
                    // Facing the camera: its upward normal toward the eye.
                    let normal = (b.enu - a.enu).cross(&(c.enu - a.enu));
                    let normal = if normal.z < 0.0 { -normal } else { normal };
                    if normal.dot(&(self.origin - a.enu)) <= 0.0 {
                        continue;
                    }
                    let area =
                        (b.px[0] - a.px[0]) * (c.px[1] - a.px[1]) - (b.px[1] - a.px[1]) * (c.px[0] - a.px[0]);
                    if area.abs() < 1e-12 {
                        continue;
                    }
                    // Barycentric weights of a and b as affine functions of
                    // the pixel (i, j); c's is the rest.
                    let weight = |p: &Vertex, q: &Vertex| {
                        let (du, dv) = ((q.px[0] - p.px[0]) / area, (q.px[1] - p.px[1]) / area);
                        [-dv, du, dv * p.px[0] - du * p.px[1]]
                    };
                    let (wa, wb) = (weight(b, c), weight(c, a));
                    for j in j0..=j1 {
                        let v = j as f64;
                        for i in i0..=i1 {
                            let u = i as f64;
                            let ka = wa[0] * u + wa[1] * v + wa[2];
                            let kb = wb[0] * u + wb[1] * v + wb[2];
                            let kc = 1.0 - ka - kb;
                            if ka < -1e-9 || kb < -1e-9 || kc < -1e-9 {
                                continue;
                            }
                            let k = j * side + i;
                            let z = ka * a.depth + kb * b.depth + kc * c.depth;
                            if z >= depth[k] || !keep(i, j) {
                                continue;
                            }
                            depth[k] = z;
                            out[k] = Some((
                                ka * a.at[0] + kb * b.at[0] + kc * c.at[0],
                                ka * a.at[1] + kb * b.at[1] + kc * c.at[1],
                            ));
                        }
                    }
                }
            }
        }
        out
    }
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
        .then(|| ReliefMesh {
            grid,
            origin: frame.to_enu(&pose.position).0,
            r_cam_enu: (frame.r_ecef_enu().transpose() * pose.q_ecef_cam.to_rotation_matrix().matrix())
                .transpose(),
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
    let mut data = vec![0f32; side * side];
    let mut mask = vec![false; side * side];
    let grey = GreyTemplate { width: t.width_px as usize, height: t.height_px as usize, pixels: &t.pixels };
    match &relief {
        // Through the relief: the template's terrain mesh (see `ReliefMesh`).
        Some(mesh) => {
            let keep = |i: usize, j: usize| {
                let (x, y) = (x0 + i as isize, y0 + j as isize);
                centre_outside || (x >= 0 && y >= 0 && x < *lw as isize && y < *lh as isize)
            };
            let at = mesh.rasterize(t, camera, level, side, (x0, y0), keep);
            for (k, at) in at.into_iter().enumerate() {
                if let Some((tc, tr)) = at {
                    if let Some(v) = bilinear(&grey, tc, tr) {
                        (data[k], mask[k]) = (v, true);
                    }
                }
            }
        }
        // Through the plane's homography, a row of patch pixels at a time:
        // inside the image each pixel's ray is the undistortion table's
        // (the row's part in the image only, unless the centre is outside),
        // beyond it the camera model's.
        None => {
            let [r0, r1, r2] = [a_inv.row(0), a_inv.row(1), a_inv.row(2)];
            let (lw, lh) = (*lw as isize, *lh as isize);
            let homography = [r0[0], r0[1], r0[2], r1[0], r1[1], r1[2], r2[0], r2[1], r2[2]];
            for j in 0..side {
                let y = y0 + j as isize;
                let row_in = y >= 0 && y < lh;
                // The patch columns whose pixels lie in the image on this row.
                let (i_lo, i_hi) = if row_in {
                    ((-x0).clamp(0, side as isize) as usize, (lw - x0).clamp(0, side as isize) as usize)
                } else {
                    (0, 0)
                };
                if centre_outside {
                    for i in (0..i_lo).chain(i_hi.max(i_lo)..side) {
                        let p = from_level(Pixel::new((x0 + i as isize) as f64, y as f64), level);
                        let q = camera.pixel_to_normalized(p);
                        let k = j * side + i;
                        if let Some(v) = homography_sample(&grey, &homography, [q.x as f32, q.y as f32]) {
                            (data[k], mask[k]) = (v, true);
                        }
                    }
                }
                if i_hi > i_lo {
                    let rays = lut.row(level, y as usize, (x0 + i_lo as isize) as usize, i_hi - i_lo);
                    let row = j * side + i_lo;
                    homography_row(&grey, &homography, rays, &mut data[row..], &mut mask[row..]);
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
    use trn_landmark::{HeightGrid, TerrainPatch};

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
        crate::test_fixtures::template(
            1,
            Geodetic::new(37.0, -118.5, 2000.0),
            gsd,
            size,
            TerrainPatch {
                plane_normal_enu: [0.0, 0.0, 1.0],
                plane_residual_rms_m: rms,
                height_grid: HeightGrid { n, spacing_m: spacing, heights_m },
            },
            pixels,
        )
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

    /// The mesh against a brute-force ray cast: over rough terrain (a 9 x 9
    /// grid of pseudo-random heights, 250 m of relief under a 32-pixel, 30 m
    /// template) seen 40 degrees off the vertical, every patch pixel's
    /// template position is where the pixel's ray first meets the bilinear
    /// surface, found in 0.5 m steps. (Two triangles a cell, without the
    /// centre, put 2% of the pixels farther than a quarter pixel off.)
    #[test]
    fn the_mesh_matches_a_brute_force_ray_cast() {
        let camera = CameraModel::from_fov(640, 480, 30.0);
        let mut t = ridge_template(0.0);
        let n = 9u32;
        let half = 16.0 * t.gsd_m;
        let mut seed = 7u64;
        let heights_m = (0..n * n)
            .map(|_| {
                seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((seed >> 33) as f64 / (1u64 << 31) as f64 * 250.0) as f32
            })
            .collect();
        t.terrain.height_grid = HeightGrid { n, spacing_m: 2.0 * half / (n - 1) as f64, heights_m };
        let g = &t.terrain.height_grid;
        let frame = t.local_frame();
        let eye_enu = Vector3::new(3500.0, 2000.0, 4900.0);
        let pose = CameraPose::look_at(frame.to_ecef(Enu(eye_enu)), t.center_ecef(), t.center.up_ecef());
        let r_enu_cam = frame.r_ecef_enu().transpose() * pose.q_ecef_cam.to_rotation_matrix().matrix();
        let mesh = ReliefMesh { grid: g, origin: eye_enu, r_cam_enu: r_enu_cam.transpose() };
        let c = pose.project(&camera, &t.center_ecef()).unwrap();
        let side = 61;
        let origin_px = (c.u.round() as isize - 30, c.v.round() as isize - 30);
        let at = mesh.rasterize(&t, &camera, 0, side, origin_px, |_, _| true);
        let edge = 15.5 * t.gsd_m;
        let (mut compared, mut close, mut missed) = (0, 0, 0);
        for j in 0..side {
            for i in 0..side {
                let px = Pixel::new((origin_px.0 + i as isize) as f64, (origin_px.1 + j as isize) as f64);
                let q = camera.pixel_to_normalized(px);
                let d = (r_enu_cam * Vector3::new(q.x, q.y, 1.0)).normalize();
                // March from where the ray enters the relief's height band.
                let mut s = (250.5 - eye_enu.z) / d.z;
                let hit = loop {
                    let p = eye_enu + d * s;
                    if p.z < -0.5 {
                        break None;
                    }
                    if p.z <= g.height_at(p.x, p.y) {
                        break Some(p);
                    }
                    s += 0.5;
                };
                // Only hits inside the template, away from its border.
                let Some(p) =
                    hit.filter(|p| p.x.abs() < edge - 2.0 * t.gsd_m && p.y.abs() < edge - 2.0 * t.gsd_m)
                else {
                    continue;
                };
                let (tc, tr) = (p.x / t.gsd_m + 15.5, 15.5 - p.y / t.gsd_m);
                compared += 1;
                match at[j * side + i] {
                    Some((mc, mr)) if (mc - tc).hypot(mr - tr) < 0.25 => close += 1,
                    Some(_) => {}
                    None => missed += 1,
                }
            }
        }
        eprintln!("{compared} pixels compared, {close} within 0.25 template px, {missed} not drawn");
        assert!(compared > 1000, "{compared}");
        assert!(close as f64 >= 0.995 * compared as f64, "{close} of {compared} within 0.25 px");
        assert!(missed as f64 <= 0.01 * compared as f64, "{missed} of {compared} not drawn");
    }

    /// A slope that faces away from the camera, or lies behind a ridge, is
    /// hidden: seen low from the east, none of the ridge's west flank (bright
    /// in the template) shows, and its east flank (dark) fills the patch; seen
    /// from the west, the other way round.
    #[test]
    fn relief_hides_the_far_flank_of_a_ridge() {
        let camera = CameraModel::from_fov(1024, 768, 30.0);
        let lut = UndistortLut::new(&camera, 1);
        let mut t = ridge_template(300.0);
        // West of the ridge line (column 15.5) bright, east of it dark.
        for r in 0..32usize {
            for c in 0..32usize {
                t.pixels[r * 32 + c] = if c < 15 {
                    220
                } else if c > 16 {
                    30
                } else {
                    125
                };
            }
        }
        let frame = t.local_frame();
        let centre = t.center_ecef();
        // The flanks slope at 45 degrees; the camera 6 km away, 3 km up
        // (27 degrees above the horizon) sees only the near flank.
        for (east, near, far) in [(6000.0, 30.0, 220.0), (-6000.0, 220.0, 30.0)] {
            let eye = frame.to_ecef(Enu::new(east, 0.0, 3000.0));
            let pose = CameraPose::look_at(eye, centre, t.center.up_ecef());
            let p = predict(&t, &pose, &camera, &lut, 0, 255, 89.0).expect("predicted");
            let mask = p.patch.mask.as_ref().unwrap();
            let seen: Vec<f32> = p.patch.data.iter().zip(mask).filter(|x| *x.1).map(|x| *x.0).collect();
            let count = |v: f64| seen.iter().filter(|&&x| (x as f64 - v).abs() < 1.0).count();
            assert!(count(near) > 100, "{} near-flank pixels of {}", count(near), seen.len());
            assert_eq!(count(far), 0, "far flank seen ({} of {})", count(far), seen.len());
        }
    }
}
