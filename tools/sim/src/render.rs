//! Ray-cast camera images: each pixel's ray (distortion included) is marched
//! through the WGS84 terrain, so relief occludes what lies behind it and
//! rays above the horizon see sky. Every step is safe (it cannot pass
//! through terrain): the longest of a max-height pyramid's step over the
//! blocks under the ray (down to the block's maximum or out of the block,
//! or sphere tracing with the block's own slope; [`crate::bounds`]), the
//! exact step within the DEM cell under the ray (its bilinear surface along
//! the ray is a quadratic), and sphere tracing with the terrain's steepest
//! slope; a step that lands below the surface is refined by false position. Ray samples near
//! the hit of a tile's centre ray take their geodetic position from a
//! quadratic expansion around that hit instead of the exact conversion
//! (sub-millimetre either way). The ortho is then sampled with the pixel's
//! ground footprint (trilinear mip, several taps along the long axis of
//! oblique footprints) so a camera coarser than the ortho sees an
//! anti-aliased image. Under another sun ([`crate::sun`]) each terrain pixel
//! is multiplied by the illumination factor at its hit point.

use nalgebra::Vector3;
use rayon::prelude::*;
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::{WGS84_A, WGS84_B};

use crate::bounds::{GridBox, RayMotion};
use crate::scene::{fast_geodetic, NearGeodetic, Scene};
use crate::sun::Illumination;

/// Grey level of sky (before realism effects).
pub const SKY_DN: f32 = 190.0;
/// Grey level where terrain has no ortho or no DEM.
pub const NODATA_DN: f32 = 0.0;

/// One rendered frame: grey levels (0..255) and per-pixel geometry.
#[derive(Clone, Debug, Default)]
pub struct RenderedFrame {
    pub width: usize,
    pub height: usize,
    pub grey: Vec<f32>,
    /// Camera-to-terrain distance along the ray (m); NaN for sky.
    pub range_m: Vec<f32>,
    /// Ellipsoidal height of the terrain hit (m); NaN for sky.
    pub hit_height_m: Vec<f32>,
}

/// Where a pixel's ray meets the terrain.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub range_m: f64,
    pub lat_deg: f64,
    pub lon_deg: f64,
    pub h_m: f64,
    /// False when the ray hit below the DEM's coverage (flat floor).
    pub has_dem: bool,
}

/// Renders one camera over one scene; the per-pixel rays are computed once.
pub struct Renderer<'a> {
    scene: &'a Scene,
    camera: CameraModel,
    /// Unit rays in the camera frame, row-major.
    rays_cam: Vec<Vector3<f64>>,
    /// Per-pixel hits, reused from frame to frame (fresh pages cost more
    /// than the rendering of a nadir frame's first pass).
    hits: std::sync::Mutex<Vec<PixelHit>>,
    /// Geodetic conversion around the scene's centre.
    near: NearGeodetic,
    /// Re-lighting under another sun (factor per terrain-grid node).
    light: Option<Illumination>,
}

/// Side of the square pixel tiles sharing one local geodetic expansion.
const TILE: usize = 16;

/// Stop refining once the ray is this close to the surface (m): far below a
/// pixel's footprint at any useful ground sample distance.
const SURFACE_TOLERANCE_M: f64 = 1e-2;

impl<'a> Renderer<'a> {
    pub fn new(scene: &'a Scene, camera: CameraModel) -> Self {
        let (w, h) = (camera.width as usize, camera.height as usize);
        let rays_cam = (0..w * h)
            .into_par_iter()
            .map(|i| camera.ray(Pixel::new((i % w) as f64, (i / w) as f64)))
            .collect();
        let e = &scene.ortho_extent;
        let near =
            NearGeodetic::new(0.5 * (e.min_lat_deg + e.max_lat_deg), 0.5 * (e.min_lon_deg + e.max_lon_deg));
        Self { scene, camera, rays_cam, hits: std::sync::Mutex::new(Vec::new()), near, light: None }
    }

    /// Multiplies each terrain pixel by `light`'s factor at its hit point
    /// (the grid must be the scene terrain's).
    pub fn with_illumination(mut self, light: Illumination) -> Self {
        let (g, t) = (&light.factor, &self.scene.terrain.heights);
        assert!(
            (g.rows, g.cols, g.north_lat_deg, g.west_lon_deg)
                == (t.rows, t.cols, t.north_lat_deg, t.west_lon_deg),
            "illumination grid differs from the terrain's"
        );
        self.light = Some(light);
        self
    }

    pub fn camera(&self) -> &CameraModel {
        &self.camera
    }

    /// Casts one ECEF ray (unit direction) from `origin` into the terrain.
    pub fn cast(&self, origin: &Vector3<f64>, dir: &Vector3<f64>) -> Option<Hit> {
        let (_, _, cam_h) = fast_geodetic(origin.x, origin.y, origin.z);
        self.cast_from(origin, cam_h, dir, &|s| self.grid_at(origin, dir, s))
    }

    /// [`Renderer::cast`] with the origin's ellipsoidal height known and
    /// `geo(s)` the terrain grid position (row, column) and ellipsoidal
    /// height of the ray's point at range `s`.
    fn cast_from(
        &self,
        origin: &Vector3<f64>,
        cam_h: f64,
        dir: &Vector3<f64>,
        geo: &impl Fn(f64) -> (f64, f64, f64),
    ) -> Option<Hit> {
        let t = &self.scene.terrain;
        let margin = 1.0;
        let top = t.h_max_m + margin;
        let floor = t.h_min_m - margin;
        // Start where the ray enters the shell that holds all terrain.
        let s_enter = if cam_h > top {
            let (s0, _) = shell_roots(origin, dir, top)?;
            if s0 < 0.0 {
                return None;
            }
            s0
        } else {
            0.0
        };
        // Stop at the floor, or where a grazing ray leaves the shell again.
        let s_exit = match shell_roots(origin, dir, floor) {
            Some((s0, _)) if s0 >= 0.0 => s0,
            _ => shell_roots(origin, dir, top)?.1,
        };
        let mut s = s_enter;
        let (mut row, mut col, mut h) = geo(s);
        // Vertical and horizontal parts of the direction at the entry point
        // bound how fast the ray can approach the surface: along a straight
        // line the vertical turns towards the line, so the descent rate only
        // falls (by at least d_horiz^2 per radius of curvature, < 6.41e6 m
        // with the height) and the horizontal rate grows by at most the
        // range over the radius (> 6.3e6 m).
        let up = ellipsoid_normal(&(origin + dir * s));
        let d_down = (-dir.dot(&up)).max(0.0);
        let d_horiz = (1.0 - d_down * d_down).max(0.0).sqrt();
        let approach = d_down + t.max_slope * d_horiz;
        let turn = d_horiz * d_horiz / (6.41e6 + t.h_max_m.max(0.0));
        let descent = |s: f64| (d_down - (s - s_enter) * turn).max(0.0);
        let d_horiz_max = (d_horiz + (s_exit - s_enter) / 6.3e6).min(1.0);
        // A floor that keeps rays moving where no exact step is known (next
        // to no data) or where one stalls (tangent to the surface).
        let min_step = 0.05 * t.cell_m / d_horiz.max(0.05);
        // Grid velocity (rows, columns per metre of range) from a short chord.
        let ds = 0.5 * t.cell_m;
        let velocity = |s: f64, row: f64, col: f64| {
            let (r1, c1, _) = geo(s + ds);
            ((r1 - row) / ds, (c1 - col) / ds)
        };
        let motion = |s: f64, row: f64, col: f64| RayMotion::new(velocity(s, row, col), d_down, d_horiz_max);
        let mut ray = Some(motion(s, row, col));
        // Range to cross a cell (at the entry's grid velocity, roughly): a
        // pyramid step longer than that leaves the cell step no chance.
        let cell_crossing = ray.as_ref().map_or(0.0, |m| m.cell_crossing_m());
        let mut mispredicted = 0;
        // A pyramid step taken: the reach it must land in, and where it began.
        let mut landing: Option<(GridBox, f64, (f64, f64, f64))> = None;
        // The last sample (above the surface): range and height above the
        // surface, for the bracket; range and grid position, for the track.
        let mut prev: Option<(f64, f64)> = None;
        let mut last: Option<(f64, f64, f64)> = None;
        let mut stalled = 0;
        loop {
            if let Some((reach, s0, g0)) = landing.take() {
                if !reach.contains(row, col) {
                    // The grid velocity was off: retake the step from a
                    // fresh estimate (twice at most, then without the pyramid).
                    mispredicted += 1;
                    (s, (row, col, h)) = (s0, g0);
                    ray = (mispredicted <= 2).then(|| motion(s, row, col));
                    last = None;
                }
            }
            let ground = t.height_at(row, col);
            let has_dem = ground.is_finite();
            let f = h - if has_dem { ground } else { t.h_min_m };
            if f <= SURFACE_TOLERANCE_M {
                let (s_hit, row, col, h, has_dem) = match prev {
                    Some((sp, fp)) if f < -SURFACE_TOLERANCE_M => self.refine(geo, sp, fp, s, f),
                    _ => (s, row, col, h, has_dem),
                };
                return Some(self.hit(s_hit, row, col, h, has_dem));
            }
            if s >= s_exit {
                return None;
            }
            // Sphere tracing: the surface cannot be nearer than f / approach.
            // Beyond the DEM the floor is flat: its own step lands on it.
            let safe = if has_dem { f / approach.max(1e-9) } else { f / d_down.max(1e-3) };
            let mut step = safe;
            let mut reach = None;
            // Whether the step is the minimum one rather than a safe one.
            let mut guessed = false;
            if has_dem {
                // The pyramid: over the local maxima and slopes, often far longer.
                if let Some((t_p, r)) = ray.as_ref().and_then(|m| t.bounds.step(m, row, col, h, f)) {
                    if t_p > step {
                        (step, reach) = (t_p, Some(r));
                    }
                }
                // Close to the surface: the exact step within the cell,
                // along the track from the last sample when it is near (a
                // chord short against the grid's curvature), else from a
                // fresh chord.
                if reach.is_none() || step < cell_crossing {
                    let v = match last {
                        Some((sl, rl, cl)) if s - sl > 1e-3 && s - sl < 200.0 => {
                            ((row - rl) / (s - sl), (col - cl) / (s - sl))
                        }
                        _ => velocity(s, row, col),
                    };
                    match t.cell_step((row, col, h), descent(s), v, approach.max(1e-9)) {
                        Some(t_c) if t_c > step => (step, reach) = (t_c, None),
                        Some(_) => {}
                        // A cell next to no data: sphere tracing with the
                        // minimum step, as ever.
                        None => guessed = min_step > step,
                    }
                }
                // A ray grazing the surface within a few millimetres above
                // the tolerance may close in ever more slowly.
                stalled = if step < min_step { stalled + 1 } else { 0 };
                if stalled > 16 {
                    guessed = true;
                }
                if guessed {
                    (step, reach) = (min_step, None);
                }
            }
            prev = Some((s, f));
            last = Some((s, row, col));
            let (s0, g0) = (s, (row, col, h));
            s = (s + step).min(s_exit);
            (row, col, h) = geo(s);
            landing = reach.map(|r| (r, s0, g0));
            if guessed && !t.height_at(row, col).is_finite() {
                // The minimum step crossed into no data, where the floor is
                // far below: a crossing just before the DEM's edge would be
                // lost. Retake the safe step instead.
                s = (s0 + safe).min(s_exit);
                (row, col, h) = geo(s);
            }
        }
    }

    /// The hit of a ray steeper than the steepest terrain, searched from a
    /// guess `s0` (a neighbour's range). Along such a ray the height above
    /// the terrain falls strictly (the ray descends faster than any slope can
    /// rise), so there is exactly one crossing and no occluder before it: a
    /// secant search from the guess finds it in two or three evaluations.
    /// `None` when the ray is not steep enough or leaves the DEM.
    fn cast_steep(&self, origin: &Vector3<f64>, dir: &Vector3<f64>, s0: f64) -> Option<Hit> {
        let up = ellipsoid_normal(&(origin + dir * s0));
        self.cast_steep_with(&|s| self.grid_at(origin, dir, s), -dir.dot(&up), s0)
    }

    /// [`Renderer::cast_steep`] with `geo` as in [`Renderer::cast_from`] and
    /// `d_down` the ray's descent rate (m/m) at `s0`.
    #[inline(always)]
    fn cast_steep_with(&self, geo: &impl Fn(f64) -> (f64, f64, f64), d_down: f64, s0: f64) -> Option<Hit> {
        let t = &self.scene.terrain;
        let d_horiz = (1.0 - d_down * d_down).max(0.0).sqrt();
        // Margin for the vertical turning along the ray and for rounding.
        if d_down <= 1.5 * t.max_slope * d_horiz + 0.02 {
            return None;
        }
        let f_at = |s: f64| -> Option<(f64, f64, f64, f64)> {
            let (row, col, h) = geo(s);
            let ground = t.height_at(row, col);
            ground.is_finite().then_some((h - ground, row, col, h))
        };
        let f0 = f_at(s0)?.0;
        // First step: the ray's own descent rate (flat ground).
        let mut last = (s0, f0);
        let mut s = s0 + f0 / d_down;
        // Nearest points known above (f > 0) and below the surface.
        let mut above: Option<(f64, f64)> = None;
        let mut below: Option<(f64, f64)> = None;
        let mut last_side = 0i8;
        for _ in 0..40 {
            let (f, row, col, h) = f_at(s)?;
            if f.abs() <= SURFACE_TOLERANCE_M {
                return Some(self.hit(s, row, col, h, true));
            }
            let side = if f > 0.0 { 1 } else { -1 };
            // Illinois: a side kept twice in a row has its value halved.
            if side == last_side {
                if let Some(o) = if side > 0 { below.as_mut() } else { above.as_mut() } {
                    o.1 *= 0.5;
                }
            }
            last_side = side;
            if f > 0.0 {
                above = Some((s, f));
            } else {
                below = Some((s, f));
            }
            let (a, b) = match (above, below) {
                (Some(a), Some(b)) => (a, b),
                _ => (last, (s, f)),
            };
            last = (s, f);
            s = if a.1 != b.1 { (a.0 * b.1 - b.0 * a.1) / (b.1 - a.1) } else { s + f / d_down };
        }
        None
    }

    /// False position (Illinois) between `sa` (above, fa > 0) and `sb`
    /// (below, fb < 0).
    fn refine(
        &self,
        geo: &impl Fn(f64) -> (f64, f64, f64),
        mut sa: f64,
        mut fa: f64,
        mut sb: f64,
        mut fb: f64,
    ) -> (f64, f64, f64, f64, bool) {
        let t = &self.scene.terrain;
        let mut side = 0i8;
        let mut best = (sb, 0.0, 0.0, 0.0, false);
        for _ in 0..60 {
            let s = if fa - fb != 0.0 { (sa * fb - sb * fa) / (fb - fa) } else { 0.5 * (sa + sb) };
            let s = if s > sa.min(sb) && s < sa.max(sb) { s } else { 0.5 * (sa + sb) };
            let (row, col, h) = geo(s);
            let ground = t.height_at(row, col);
            let has_dem = ground.is_finite();
            let f = h - if has_dem { ground } else { t.h_min_m };
            best = (s, row, col, h, has_dem);
            if f.abs() <= SURFACE_TOLERANCE_M || (sb - sa).abs() < 1e-4 {
                break;
            }
            if f > 0.0 {
                (sa, fa) = (s, f);
                if side == 1 {
                    fb *= 0.5;
                }
                side = 1;
            } else {
                (sb, fb) = (s, f);
                if side == -1 {
                    fa *= 0.5;
                }
                side = -1;
            }
        }
        best
    }

    /// Terrain grid position (row, column) and ellipsoidal height of an ECEF point.
    #[inline(always)]
    fn grid_of(&self, p: &Vector3<f64>) -> [f64; 3] {
        let (lat, lon, h) = self.near.geodetic(p.x, p.y, p.z);
        let (row, col) = self.scene.terrain.heights.position(lat, lon);
        [row, col, h]
    }

    #[inline(always)]
    fn grid_at(&self, o: &Vector3<f64>, d: &Vector3<f64>, s: f64) -> (f64, f64, f64) {
        let [row, col, h] = self.grid_of(&(o + d * s));
        (row, col, h)
    }

    /// The hit at range `s` and terrain grid position (row, col).
    fn hit(&self, s: f64, row: f64, col: f64, h: f64, has_dem: bool) -> Hit {
        let g = &self.scene.terrain.heights;
        Hit {
            range_m: s,
            lat_deg: g.north_lat_deg - row * g.dlat_deg,
            lon_deg: g.west_lon_deg + col * g.dlon_deg,
            h_m: h,
            has_dem,
        }
    }

    /// Renders the frame seen from `pose` (no realism effects).
    pub fn render(&self, pose: &CameraPose) -> RenderedFrame {
        let mut frame = RenderedFrame::default();
        self.render_into(pose, &mut frame);
        frame
    }

    /// [`Renderer::render`] into the buffers of an earlier frame (fresh
    /// pages for each frame would cost several milliseconds).
    pub fn render_into(&self, pose: &CameraPose, frame: &mut RenderedFrame) {
        let (w, h) = (self.camera.width as usize, self.camera.height as usize);
        let r = pose.q_ecef_cam.to_rotation_matrix();
        let o = pose.position.0;
        let (_, _, cam_h) = fast_geodetic(o.x, o.y, o.z);
        let t0 = std::time::Instant::now();
        // Pass 0: per tile, an expansion of the terrain grid position and
        // height around the exact hit of the tile's centre ray (tiles whose
        // centre sees sky convert exactly).
        let (tw, th) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let tiles: Vec<Option<LocalExpansion>> = (0..tw * th)
            .into_par_iter()
            .map(|i| {
                let (u, v) = ((i % tw) * TILE + TILE / 2, (i / tw) * TILE + TILE / 2);
                let d = r * self.rays_cam[v.min(h - 1) * w + u.min(w - 1)];
                let hit = self.cast_from(&o, cam_h, &d, &|s| self.grid_at(&o, &d, s))?;
                Some(LocalExpansion::new(|p| self.grid_of(&p), o + d * hit.range_m, &o))
            })
            .collect();
        // Pass 1: hits, their ortho positions and their illumination (held
        // in the grey buffer until pass 2 multiplies the ortho into it).
        let mut guard = self.hits.lock().unwrap_or_else(|e| e.into_inner());
        let hits = &mut *guard;
        hits.resize(w * h, PixelHit::SKY);
        frame.width = w;
        frame.height = h;
        for buf in [&mut frame.grey, &mut frame.range_m, &mut frame.hit_height_m] {
            buf.resize(w * h, 0.0);
        }
        let rows = hits.par_chunks_mut(w).zip(frame.grey.par_chunks_mut(w));
        rows.enumerate().for_each(|(v, (row, light_row))| {
            // The left neighbour's hit starts steep rays next to the surface.
            let mut prev: Option<f64> = None;
            for (u, (out, light)) in row.iter_mut().zip(light_row.iter_mut()).enumerate() {
                let d = r * self.rays_cam[v * w + u];
                let hit = match &tiles[(v / TILE) * tw + u / TILE] {
                    Some(tile) => {
                        let ray = tile.along(&d);
                        let geo = |s: f64| ray.at(s).unwrap_or_else(|| self.grid_at(&o, &d, s));
                        let steep = |s0: f64| {
                            let d_down = match ray.at(s0) {
                                Some(_) => ray.descent(s0),
                                None => -d.dot(&ellipsoid_normal(&(o + d * s0))),
                            };
                            self.cast_steep_with(&geo, d_down, s0)
                        };
                        match prev.and_then(steep) {
                            Some(h) => Some(h),
                            None => self.cast_from(&o, cam_h, &d, &geo),
                        }
                    }
                    None => match prev.and_then(|s0| self.cast_steep(&o, &d, s0)) {
                        Some(h) => Some(h),
                        None => self.cast_from(&o, cam_h, &d, &|s| self.grid_at(&o, &d, s)),
                    },
                };
                prev = hit.filter(|h| h.has_dem).map(|h| h.range_m);
                *light = match (&self.light, hit) {
                    (Some(l), Some(hit)) if hit.has_dem => l.at_latlon(hit.lat_deg, hit.lon_deg),
                    _ => 1.0,
                };
                *out = match hit {
                    None => PixelHit::SKY,
                    Some(hit) => {
                        let xy = if hit.has_dem {
                            self.scene.to_ortho.bilinear2(hit.lat_deg, hit.lon_deg)
                        } else {
                            None
                        };
                        PixelHit {
                            range_m: hit.range_m as f32,
                            h_m: hit.h_m as f32,
                            x: xy.map_or(f64::NAN, |p| p[0]),
                            y: xy.map_or(f64::NAN, |p| p[1]),
                        }
                    }
                };
            }
        });
        let t1 = std::time::Instant::now();
        // Pass 2: sample the ortho over each pixel's footprint.
        let pixel_angle = 1.0 / self.camera.fx.min(self.camera.fy);
        let rows = frame.grey.par_chunks_mut(w).zip(frame.range_m.par_chunks_mut(w));
        rows.zip(frame.hit_height_m.par_chunks_mut(w)).enumerate().for_each(|(v, ((row, range), hit_h))| {
            for (u, out) in row.iter_mut().enumerate() {
                let p = &hits[v * w + u];
                range[u] = p.range_m;
                hit_h[u] = p.h_m;
                *out = if p.range_m.is_nan() {
                    SKY_DN
                } else if p.x.is_nan() {
                    NODATA_DN
                } else {
                    let iso = p.range_m as f64 * pixel_angle / self.scene.ortho_gsd_m;
                    let du = derivative(hits, w, h, u, v, true);
                    let dv = derivative(hits, w, h, u, v, false);
                    let lum =
                        self.sample_footprint(p.x, p.y, du.unwrap_or([iso, 0.0]), dv.unwrap_or([0.0, iso]));
                    if lum.is_nan() {
                        NODATA_DN
                    } else {
                        lum * *out
                    }
                };
            }
        });
        tracing::debug!(
            "render: rays {:.1} ms, ortho sampling {:.1} ms",
            1e3 * (t1 - t0).as_secs_f64(),
            1e3 * t1.elapsed().as_secs_f64()
        );
    }

    /// Averages the ortho over the parallelogram spanned by the pixel's
    /// footprint axes `a`, `b` (ortho pixels per image pixel): mip level from
    /// the short axis, taps spread along the long one.
    fn sample_footprint(&self, x: f64, y: f64, a: [f64; 2], b: [f64; 2]) -> f32 {
        let (la, lb) = ((a[0] * a[0] + a[1] * a[1]).sqrt(), (b[0] * b[0] + b[1] * b[1]).sqrt());
        let (long, short, axis) = if la >= lb { (la, lb, a) } else { (lb, la, b) };
        let short = short.max(1e-9);
        // One tap per short-axis length along the long axis (nearly round
        // footprints take one).
        // (Adding a half then truncating rounds a positive ratio without a libm call.)
        let taps = ((long / short + 0.5) as usize).clamp(1, 8);
        if taps == 1 {
            return self.scene.ortho.sample(x, y, long);
        }
        let lod = self.scene.ortho.lod(short.max(long / taps as f64));
        let mut sum = 0f32;
        for k in 0..taps {
            let f = (k as f64 + 0.5) / taps as f64 - 0.5;
            sum += self.scene.ortho.sample_lod(lod, x + axis[0] * f, y + axis[1] * f);
        }
        sum / taps as f32
    }
}

/// Terrain grid position and height (or any smooth map of ECEF points) as
/// a second-order Taylor expansion in the offset from a point near the
/// terrain: a few multiply-adds instead of square roots and divisions per
/// ray sample. The third-order remainder grows as |offset|^3 / R^2, so the
/// expansion serves only within [`EXPANSION_RADIUS_M`] of its point (under
/// 0.4 mm there). Held for rays from one origin.
#[derive(Clone, Copy, Debug)]
struct LocalExpansion {
    /// Origin minus expansion point.
    a: Vector3<f64>,
    /// Value at the origin (of the expansion polynomial).
    c0: [f64; 3],
    /// Gradient at the origin.
    lin: [Vector3<f64>; 3],
    /// Half the Hessian: xx, yy, zz, 2 xy, 2 xz, 2 yz.
    quad: [[f64; 6]; 3],
}

/// Largest offset from the expansion point where [`LocalExpansion`] is used.
const EXPANSION_RADIUS_M: f64 = 3000.0;

impl LocalExpansion {
    /// The expansion of `f` at `p0` for rays from `origin`. Derivatives by
    /// central differences (a step of 50 m keeps rounding and truncation
    /// errors far below a millimetre over the expansion's radius).
    fn new(f: impl Fn(Vector3<f64>) -> [f64; 3], p0: Vector3<f64>, origin: &Vector3<f64>) -> Self {
        let step = 50.0;
        let e = |i: usize| Vector3::ith(i, step);
        let val = f(p0);
        let mut grad = [Vector3::zeros(); 3];
        let mut hess = [nalgebra::Matrix3::zeros(); 3];
        for i in 0..3 {
            let (fp, fm) = (f(p0 + e(i)), f(p0 - e(i)));
            for k in 0..3 {
                grad[k][i] = (fp[k] - fm[k]) / (2.0 * step);
                hess[k][(i, i)] = (fp[k] - 2.0 * val[k] + fm[k]) / (step * step);
            }
            for j in 0..i {
                let (pp, pm) = (f(p0 + e(i) + e(j)), f(p0 + e(i) - e(j)));
                let (mp, mm) = (f(p0 - e(i) + e(j)), f(p0 - e(i) - e(j)));
                for k in 0..3 {
                    let v = (pp[k] - pm[k] - mp[k] + mm[k]) / (4.0 * step * step);
                    hess[k][(i, j)] = v;
                    hess[k][(j, i)] = v;
                }
            }
        }
        let a = origin - p0;
        let (mut c0, mut lin, mut quad) = ([0.0; 3], [Vector3::zeros(); 3], [[0.0; 6]; 3]);
        for k in 0..3 {
            let (g, hm) = (&grad[k], &hess[k]);
            let ha = hm * a;
            c0[k] = val[k] + g.dot(&a) + 0.5 * a.dot(&ha);
            lin[k] = g + ha;
            quad[k] =
                [0.5 * hm[(0, 0)], 0.5 * hm[(1, 1)], 0.5 * hm[(2, 2)], hm[(0, 1)], hm[(0, 2)], hm[(1, 2)]];
        }
        Self { a, c0, lin, quad }
    }

    /// The expansion along the ray from the origin in direction `d`: a
    /// quadratic in the range `s` per output.
    #[inline]
    fn along(&self, d: &Vector3<f64>) -> RayExpansion {
        let dd = [d.x * d.x, d.y * d.y, d.z * d.z, d.x * d.y, d.x * d.z, d.y * d.z];
        let c = std::array::from_fn(|k| {
            let q = &self.quad[k];
            let c2 = q[0] * dd[0] + q[1] * dd[1] + q[2] * dd[2] + q[3] * dd[3] + q[4] * dd[4] + q[5] * dd[5];
            [self.c0[k], self.lin[k].dot(d), c2]
        });
        let r2 = EXPANSION_RADIUS_M * EXPANSION_RADIUS_M;
        RayExpansion { c, a2: self.a.norm_squared() - r2, b: 2.0 * self.a.dot(d) }
    }
}

/// [`LocalExpansion`] along one ray.
struct RayExpansion {
    /// Constant, linear and quadratic coefficients of each output.
    c: [[f64; 3]; 3],
    /// |offset from the expansion point|^2 - radius^2 = a2 + s (b + s).
    a2: f64,
    b: f64,
}

impl RayExpansion {
    /// The outputs at range `s`; `None` beyond the expansion's radius.
    #[inline(always)]
    fn at(&self, s: f64) -> Option<(f64, f64, f64)> {
        if self.a2 + s * (self.b + s) > 0.0 {
            return None;
        }
        let q = |c: &[f64; 3]| c[0] + s * (c[1] + s * c[2]);
        Some((q(&self.c[0]), q(&self.c[1]), q(&self.c[2])))
    }

    /// Rate of descent (-dh/ds) at range `s`.
    #[inline]
    fn descent(&self, s: f64) -> f64 {
        -(self.c[2][1] + 2.0 * s * self.c[2][2])
    }
}

/// A pixel's hit during rendering.
#[derive(Clone, Copy)]
struct PixelHit {
    range_m: f32,
    h_m: f32,
    /// Ortho level-0 position; NaN outside the ortho or the DEM.
    x: f64,
    y: f64,
}

impl PixelHit {
    const SKY: PixelHit = PixelHit { range_m: f32::NAN, h_m: f32::NAN, x: f64::NAN, y: f64::NAN };
}

/// Ortho-position change per image pixel along u (or v): the smaller of the
/// one-sided differences, so occlusion edges do not blow the footprint up.
fn derivative(hits: &[PixelHit], w: usize, h: usize, u: usize, v: usize, along_u: bool) -> Option<[f64; 2]> {
    let here = &hits[v * w + u];
    let diff = |o: &PixelHit, sign: f64| -> Option<[f64; 2]> {
        (!o.x.is_nan()).then_some([sign * (o.x - here.x), sign * (o.y - here.y)])
    };
    let (fwd, back) = if along_u {
        (
            (u + 1 < w).then(|| diff(&hits[v * w + u + 1], 1.0)).flatten(),
            (u > 0).then(|| diff(&hits[v * w + u - 1], -1.0)).flatten(),
        )
    } else {
        (
            (v + 1 < h).then(|| diff(&hits[(v + 1) * w + u], 1.0)).flatten(),
            (v > 0).then(|| diff(&hits[(v - 1) * w + u], -1.0)).flatten(),
        )
    };
    match (fwd, back) {
        (Some(f), Some(b)) => {
            Some(if f[0] * f[0] + f[1] * f[1] <= b[0] * b[0] + b[1] * b[1] { f } else { b })
        }
        (f, b) => f.or(b),
    }
}

/// Outward normal of the ellipsoid through `p`'s latitude (the local up, to
/// the accuracy the step bound needs).
#[inline]
fn ellipsoid_normal(p: &Vector3<f64>) -> Vector3<f64> {
    Vector3::new(p.x / (WGS84_A * WGS84_A), p.y / (WGS84_A * WGS84_A), p.z / (WGS84_B * WGS84_B)).normalize()
}

/// Both ray parameters where the ray meets the ellipsoid raised by `h`
/// (semi-axes a + h, b + h), nearest first; `None` when it misses.
#[inline]
fn shell_roots(o: &Vector3<f64>, d: &Vector3<f64>, h: f64) -> Option<(f64, f64)> {
    let (ia, ib) = (1.0 / (WGS84_A + h), 1.0 / (WGS84_B + h));
    let (ox, oy, oz) = (o.x * ia, o.y * ia, o.z * ib);
    let (dx, dy, dz) = (d.x * ia, d.y * ia, d.z * ib);
    let qa = dx * dx + dy * dy + dz * dz;
    let qb = 2.0 * (ox * dx + oy * dy + oz * dz);
    let qc = ox * ox + oy * oy + oz * oz - 1.0;
    let disc = qb * qb - 4.0 * qa * qc;
    if disc < 0.0 {
        return None;
    }
    let q = -0.5 * (qb + qb.signum() * disc.sqrt());
    let (r0, r1) = (q / qa, if q != 0.0 { qc / q } else { q / qa });
    Some((r0.min(r1), r0.max(r1)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{LatLonGrid, Level, OrthoPyramid, Terrain};
    use trn_geodesy::{Ecef, Geodetic};

    /// A scene on a lat/lon grid: heights from `f(lat, lon)`, ortho = the grid itself.
    fn scene(f: impl Fn(f64, f64) -> f64) -> Scene {
        let (n, lat0, lon0, d) = (401, 40.2, -105.7, 0.0005);
        let mut values = Vec::new();
        for r in 0..n {
            for c in 0..n {
                values.push(f(lat0 - r as f64 * d, lon0 + c as f64 * d) as f32);
            }
        }
        let heights = LatLonGrid {
            north_lat_deg: lat0,
            west_lon_deg: lon0,
            dlat_deg: d,
            dlon_deg: d,
            rows: n,
            cols: n,
            values,
        };
        let terrain = Terrain::new(heights).unwrap();
        let lum = (0..n * n).map(|i| ((i * 37) % 251) as f32).collect();
        let to_ortho = LatLonGrid {
            north_lat_deg: lat0,
            west_lon_deg: lon0,
            dlat_deg: d * (n - 1) as f64,
            dlon_deg: d * (n - 1) as f64,
            rows: 2,
            cols: 2,
            values: vec![
                [0.0, 0.0],
                [(n - 1) as f64, 0.0],
                [0.0, (n - 1) as f64],
                [(n - 1) as f64, (n - 1) as f64],
            ],
        };
        Scene {
            terrain,
            ortho: OrthoPyramid::new(Level { width: n, height: n, lum }),
            to_ortho,
            ortho_gsd_m: 45.0,
            ortho_extent: trn_landmark::GeoBox::new(
                lon0,
                lat0 - d * (n - 1) as f64,
                lon0 + d * (n - 1) as f64,
                lat0,
            ),
        }
    }

    /// The crossing of `f` from above to below zero in `[a, b]`, by `n` halvings.
    fn bisect(f: &impl Fn(f64) -> f64, mut a: f64, mut b: f64, n: usize) -> f64 {
        for _ in 0..n {
            let m = 0.5 * (a + b);
            if f(m) > 0.0 {
                a = m
            } else {
                b = m
            }
        }
        0.5 * (a + b)
    }

    /// Brute force: tiny fixed steps along the ray with the exact geodetic
    /// conversion, then bisection.
    fn brute_force(sc: &Scene, o: &Vector3<f64>, d: &Vector3<f64>, s_max: f64) -> Option<f64> {
        let f = |s: f64| {
            let g = Ecef(o + d * s).to_geodetic();
            g.h_m - sc.terrain.height_m(g.lat_deg, g.lon_deg)
        };
        let step = 2.0;
        let mut s = 0.0;
        while s < s_max {
            if f(s + step) < 0.0 {
                return Some(bisect(&f, s, s + step, 60));
            }
            s += step;
        }
        None
    }

    #[test]
    fn rays_hit_where_brute_force_finds_the_surface_with_occlusion() {
        // A ridge running north-south: oblique rays from the west hit its
        // western face, and some rays pass over shoulders before hitting.
        let sc = scene(|_, lon| 1500.0 + 400.0 * (-((lon + 105.6) / 0.01).powi(2)).exp());
        let cam = CameraModel::from_fov(64, 48, 60.0);
        let r = Renderer::new(&sc, cam);
        let pos = Geodetic::new(40.1, -105.68, 3500.0).to_ecef();
        let target = Geodetic::new(40.1, -105.6, 1500.0).to_ecef();
        let pose = CameraPose::look_at(pos, target, Geodetic::new(40.1, -105.68, 0.0).up_ecef());
        let mut n = 0;
        for v in (0..48).step_by(5) {
            for u in (0..64).step_by(5) {
                let d = pose.q_ecef_cam * cam.ray(Pixel::new(u as f64, v as f64));
                let got = r.cast(&pos.0, &d);
                let want = brute_force(&sc, &pos.0, &d, 60_000.0);
                match (got, want) {
                    (Some(g), Some(w)) => {
                        assert!((g.range_m - w).abs() < 0.05, "pixel ({u},{v}): {} vs {w}", g.range_m);
                        n += 1;
                    }
                    // Past the DEM the ray meets a flat floor the brute force does not know.
                    (None, None) | (Some(Hit { has_dem: false, .. }), None) => {}
                    (g, w) => panic!("pixel ({u},{v}): renderer {g:?}, brute force {w:?}"),
                }
            }
        }
        assert!(n > 50);
    }

    #[test]
    fn marcher_never_misses_an_occluder_on_spiky_terrain() {
        // Rough ground with one-node spikes 700 m high (slopes to 16), a
        // 350 m cliff and thin ridges: rays from all around, grazing to
        // steep, against a fine march (0.5 m steps near the terrain).
        let spike = |lat: f64, lon: f64| {
            let (r, c) = (((40.2 - lat) / 0.0005).round() as i64, ((lon + 105.7) / 0.0005).round() as i64);
            ((r * 7919 + c * 104_729) % 61 == 0) as i32 as f64 * 700.0
        };
        let sc = scene(|lat, lon| {
            1500.0
                + 80.0 * ((lat * 2100.0).sin() * (lon * 1700.0).cos())
                + spike(lat, lon)
                + if lon > -105.62 { 350.0 } else { 0.0 }
                + if ((lat - 40.05) * 4000.0).rem_euclid(37.0) < 1.0 { 250.0 } else { 0.0 }
        });
        let t = &sc.terrain;
        assert!(t.max_slope > 10.0, "{}", t.max_slope);
        let r = Renderer::new(&sc, CameraModel::from_fov(8, 8, 40.0));
        let fine = |o: &Vector3<f64>, d: &Vector3<f64>| -> Option<f64> {
            let f = |s: f64| {
                let g = Ecef(o + d * s).to_geodetic();
                let ground = sc.terrain.height_m(g.lat_deg, g.lon_deg);
                g.h_m - if ground.is_finite() { ground } else { t.h_min_m }
            };
            let mut s = 0.0;
            let mut fs = f(s);
            while s < 400_000.0 {
                // Far above the terrain the global slope bounds the step.
                let step = (0.5 * fs / (1.0 + t.max_slope)).max(0.5);
                let fn_ = f(s + step);
                if fn_ < 0.0 {
                    return Some(bisect(&f, s, s + step, 50));
                }
                (s, fs) = (s + step, fn_);
            }
            None
        };
        let mut rng = crate::rng::Rng::stream(11, "occluders");
        let spikes: Vec<(f64, f64)> = (40..360)
            .flat_map(|r| (40..360).map(move |c| (40.2 - r as f64 * 0.0005, -105.7 + c as f64 * 0.0005)))
            .filter(|&(lat, lon)| spike(lat, lon) > 0.0)
            .collect();
        let (mut grazing, mut steep, mut tips) = (0, 0, 0);
        for k in 0..600 {
            let (lat, lon) = (rng.range(40.06, 40.14), rng.range(-105.68, -105.52));
            // Grazing rays from low over the ground towards the grid's
            // middle, steep ones from higher up, and rays aimed a few metres
            // below a spike's tip from all sides.
            let (o, d) = if k % 3 == 2 {
                let (plat, plon) = spikes[(rng.uniform() * spikes.len() as f64) as usize];
                let peak = t.height_m(plat, plon);
                let tip = Geodetic::new(plat, plon, peak - rng.range(3.0, 40.0)).to_ecef().0;
                let (glat, glon) = (plat + rng.range(-0.03, 0.03), plon + rng.range(-0.03, 0.03));
                let run = (Geodetic::new(glat, glon, peak).to_ecef().0 - tip).norm();
                let dip = rng.range(1.0, 40.0).to_radians();
                let o = Geodetic::new(glat, glon, peak + run * dip.tan()).to_ecef().0;
                (o, (tip - o).normalize())
            } else {
                let (h, az) = if k % 3 == 0 {
                    let to_mid = (-105.6 - lon).atan2(40.1 - lat);
                    (t.height_m(lat, lon) + rng.range(30.0, 900.0), to_mid + rng.range(-1.2, 1.2))
                } else {
                    (rng.range(2600.0, 7000.0), rng.range(0.0, std::f64::consts::TAU))
                };
                let g = Geodetic::new(lat, lon, h);
                let up = g.up_ecef();
                let east = Vector3::new(0.0, 0.0, 1.0).cross(&up).normalize();
                let north = up.cross(&east);
                let dip = if k % 3 == 0 { rng.range(2.0, 12.0) } else { rng.range(12.0, 89.0) }.to_radians();
                (
                    g.to_ecef().0,
                    (-up * dip.sin() + (north * az.cos() + east * az.sin()) * dip.cos()).normalize(),
                )
            };
            let dip = (-d.dot(&Ecef(o).to_geodetic().up_ecef())).asin();
            let got = r.cast(&o, &d);
            let want = fine(&o, &d);
            match (got, want) {
                (Some(h), Some(w)) if h.has_dem => {
                    // Within the 1 cm tolerance (at grazing incidence, more
                    // range), or before: on a crest the ray passes within
                    // the tolerance, between two of the fine march's steps.
                    let near = (h.range_m - w).abs() < 0.01 / dip.sin() + 0.05;
                    let g = Ecef(o + d * h.range_m).to_geodetic();
                    let on_crest = h.range_m < w && (g.h_m - t.height_m(g.lat_deg, g.lon_deg)).abs() < 0.011;
                    assert!(near || on_crest, "ray {k}: {} vs {w}", h.range_m);
                    match k % 3 {
                        0 => grazing += 1,
                        1 => steep += 1,
                        _ => tips += 1,
                    }
                }
                // Past the DEM both meet the floor (far away on grazing rays,
                // where the vertical has turned).
                (Some(h), Some(w)) => {
                    let p = Ecef(o + d * w).to_geodetic();
                    assert!(
                        t.height_m(p.lat_deg, p.lon_deg).is_nan(),
                        "ray {k}: {} vs {w} on the DEM",
                        h.range_m
                    );
                    assert!((h.range_m - w).abs() < 2.0, "ray {k}: {} vs {w}", h.range_m);
                }
                (None, None) => {}
                (g, w) => panic!("ray {k}: marcher {g:?}, fine march {w:?}"),
            }
        }
        println!("{grazing} grazing, {steep} steep, {tips} below spike tips");
        assert!(grazing > 120 && steep > 120 && tips > 150, "{grazing} grazing, {steep} steep, {tips} tips");
    }

    #[test]
    fn steep_rays_from_a_neighbours_range_find_the_same_hit() {
        let sc = scene(|lat, lon| 1500.0 + 120.0 * ((lat * 900.0).sin() * (lon * 700.0).cos()));
        let cam = CameraModel::from_fov(64, 48, 50.0);
        let r = Renderer::new(&sc, cam);
        let pos = Geodetic::new(40.1, -105.6, 6000.0).to_ecef();
        let target = Geodetic::new(40.11, -105.6, 1500.0).to_ecef();
        let pose = CameraPose::look_at(pos, target, Geodetic::new(40.1, -105.6, 0.0).up_ecef());
        let mut n = 0;
        for v in (0..48).step_by(4) {
            for u in (0..64).step_by(4) {
                let d = pose.q_ecef_cam * cam.ray(Pixel::new(u as f64, v as f64));
                let full = r.cast(&pos.0, &d).unwrap();
                for guess in [-300.0, -20.0, 0.5, 40.0, 250.0] {
                    if let Some(fast) = r.cast_steep(&pos.0, &d, full.range_m + guess) {
                        assert!((fast.range_m - full.range_m).abs() < 0.05, "({u},{v}) {guess}");
                        n += 1;
                    }
                }
            }
        }
        assert!(n > 500, "{n} steep casts");
    }

    #[test]
    fn local_expansion_is_within_half_a_millimetre() {
        let near = NearGeodetic::new(40.0, -105.5);
        let mut rng = crate::rng::Rng::stream(1, "expansion");
        let mut worst: f64 = 0.0;
        for (lat, lon, h) in [(40.0, -105.5, 1600.0), (40.3, -105.1, 0.0), (39.7, -105.9, 8800.0)] {
            let p0 = Geodetic::new(lat, lon, h).to_ecef().0;
            for _ in 0..2000 {
                let d = Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0))
                    .normalize();
                let o = p0 + d * rng.range(100.0, 40_000.0);
                let ex = LocalExpansion::new(
                    |p| {
                        let (lat, lon, h) = near.geodetic(p.x, p.y, p.z);
                        [lat, lon, h]
                    },
                    p0,
                    &o,
                );
                let dir = Vector3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), rng.range(-1.0, 1.0))
                    .normalize();
                let ray = ex.along(&dir);
                // The ray's closest approach to p0, then samples along it.
                let s_mid = -(o - p0).dot(&dir);
                for k in -20..=20 {
                    let s = s_mid + k as f64 * 0.05 * EXPANSION_RADIUS_M;
                    let Some((la, lo, hh)) = ray.at(s) else { continue };
                    let p = o + dir * s;
                    let (la0, lo0, h0) = near.geodetic(p.x, p.y, p.z);
                    let e = ((la - la0) * 111e3).abs().max(((lo - lo0) * 85e3).abs()).max((hh - h0).abs());
                    worst = worst.max(e);
                }
            }
        }
        assert!(worst < 5e-4, "worst {worst} m");
    }

    #[test]
    fn sun_darkens_the_pixels_in_a_ridge_shadow_by_the_ambient_share() {
        // A north-south wall 200 m high (4 columns from -105.6), sun from the
        // east at 20 degrees: its shadow reaches 200 / tan 20 = 549 m west of
        // the wall's top edge. Same frame with and without the sun.
        let (top_lon, wall_w) = (-105.6, 3.0 * 0.0005);
        let on_wall = |lon: f64| lon >= top_lon - 1e-9 && lon <= top_lon + wall_w + 1e-9;
        let sc = scene(|_, lon| if on_wall(lon) { 1700.0 } else { 1500.0 });
        let sun = crate::sun::Sun { azimuth_deg: 90.0, elevation_deg: 20.0, ambient: 0.25 };
        let cam = CameraModel::from_fov(160, 120, 60.0);
        let (lat, lon) = (40.1, top_lon - 0.003);
        let g = Geodetic::new(lat, lon, 4000.0);
        let north =
            Geodetic::new(lat + 0.01, lon, 1500.0).to_ecef().0 - Geodetic::new(lat, lon, 1500.0).to_ecef().0;
        let pose = CameraPose::look_at(g.to_ecef(), g.with_height(1500.0).to_ecef(), north.normalize());
        let plain = Renderer::new(&sc, cam).render(&pose);
        let lit =
            Renderer::new(&sc, cam).with_illumination(Illumination::new(&sc.terrain, &sun)).render(&pose);
        let len = 200.0 / 20f64.to_radians().tan();
        let dark = 0.25 / (0.25 + 0.75 * 20f64.to_radians().sin());
        let (m_lon, cell) =
            (trn_geodesy::metres_per_degree(lat).1, 0.0005 * trn_geodesy::metres_per_degree(lat).1);
        let (mut shadowed, mut sunny, mut on_face) = (0, 0, 0);
        for v in 0..120 {
            for u in 0..160 {
                let i = v * 160 + u;
                let (a, b) = (plain.grey[i], lit.grey[i]);
                if plain.range_m[i].is_nan() || a < 1.0 {
                    assert_eq!(a.to_bits(), b.to_bits(), "sky and no data untouched");
                    continue;
                }
                let d = pose.q_ecef_cam * cam.ray(Pixel::new(u as f64, v as f64));
                let p = Ecef(pose.position.0 + d * plain.range_m[i] as f64).to_geodetic();
                // Distance west of the wall's top edge, east of its far edge.
                let west = (top_lon - p.lon_deg) * m_lon;
                let east = (p.lon_deg - top_lon - wall_w) * m_lon;
                let ratio = (b / a) as f64;
                if west > cell && west < len - 1.5 * cell {
                    assert!(
                        (ratio - dark).abs() < 1e-4,
                        "pixel ({u}, {v}) {west:.0} m west: {ratio} vs {dark}"
                    );
                    shadowed += 1;
                } else if west > len + 1.5 * cell || east > 2.0 * cell {
                    // (The node next to the wall has the face in its normal.)
                    assert!((ratio - 1.0).abs() < 1e-4, "pixel ({u}, {v}) {west:.0} m west: {ratio}");
                    sunny += 1;
                } else if east > 0.0 && east < cell {
                    // The wall's east face looks at the sun.
                    assert!(ratio > 1.5, "pixel ({u}, {v}) on the sunny face: {ratio}");
                    on_face += 1;
                }
            }
        }
        assert!(shadowed > 1000 && sunny > 5000 && on_face > 0, "{shadowed} {sunny} {on_face}");
    }

    /// `cargo test --release -p trn-sim --lib render::tests::timing_sun -- --ignored --nocapture`
    #[test]
    #[ignore]
    fn timing_sun_1024x768() {
        let sc = scene(|lat, lon| 1500.0 + 150.0 * ((lat * 900.0).sin() * (lon * 700.0).cos()));
        let sun = crate::sun::Sun { azimuth_deg: 135.0, elevation_deg: 15.0, ambient: 0.25 };
        let t0 = std::time::Instant::now();
        let light = Illumination::new(&sc.terrain, &sun);
        println!(
            "illumination of {} nodes: {:.1} ms",
            sc.terrain.heights.values.len(),
            1e3 * t0.elapsed().as_secs_f64()
        );
        let cam = CameraModel::from_fov(1024, 768, 32.0);
        let g = Geodetic::new(40.1, -105.6, 12_000.0);
        let north = Geodetic::new(40.11, -105.6, 0.0).to_ecef().0 - g.with_height(0.0).to_ecef().0;
        let pose = CameraPose::look_at(g.to_ecef(), g.with_height(0.0).to_ecef(), north.normalize());
        let plain = Renderer::new(&sc, cam);
        let lit = Renderer::new(&sc, cam).with_illumination(light);
        let mut frame = RenderedFrame::default();
        let (mut best_off, mut best_on) = (f64::INFINITY, f64::INFINITY);
        // Interleaved, best of several: the machine may be shared.
        for _ in 0..15 {
            for (r, best) in [(&plain, &mut best_off), (&lit, &mut best_on)] {
                let t0 = std::time::Instant::now();
                r.render_into(&pose, &mut frame);
                *best = best.min(1e3 * t0.elapsed().as_secs_f64());
            }
        }
        println!("render 1024x768: {best_off:.1} ms without the sun, {best_on:.1} ms with");
    }

    #[test]
    fn rays_above_the_horizon_see_sky() {
        let sc = scene(|_, _| 1500.0);
        let cam = CameraModel::from_fov(32, 24, 40.0);
        let r = Renderer::new(&sc, cam);
        let g = Geodetic::new(40.1, -105.6, 20_000.0);
        let up = g.up_ecef();
        let d = (up * 0.2 + Geodetic::new(40.1, -105.6, 0.0).to_ecef().0.cross(&up).normalize()).normalize();
        assert!(r.cast(&g.to_ecef().0, &d).is_none());
        let pose = CameraPose::look_at(
            g.to_ecef(),
            Ecef(g.to_ecef().0 + d * 1000.0),
            Geodetic::new(40.1, -105.6, 0.0).up_ecef(),
        );
        let f = r.render(&pose);
        assert!(f.grey.iter().all(|&v| v == SKY_DN));
        assert!(f.range_m.iter().all(|v| v.is_nan()));
    }
}
