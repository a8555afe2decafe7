//! The world the simulator renders: terrain heights (WGS84 ellipsoidal) on a
//! latitude/longitude grid, the ortho's luminance as a pre-filtered pyramid,
//! and the map from latitude/longitude to ortho pixels. Pure data and
//! sampling; `load.rs` fills it through GDAL.

use crate::bounds::TerrainBounds;
use trn_geodesy::{WGS84_A, WGS84_B, WGS84_E2};

pub use trn_landmark::grid::LatLonGrid;

/// Terrain heights above the WGS84 ellipsoid (m) with the bounds the ray
/// marcher needs.
#[derive(Clone, Debug)]
pub struct Terrain {
    /// Heights at grid nodes; NaN where no DEM covers.
    pub heights: LatLonGrid<f32>,
    pub h_min_m: f64,
    pub h_max_m: f64,
    /// Largest slope (rise over horizontal run) between neighbouring nodes:
    /// the Lipschitz bound of the height field, for safe marching steps.
    pub max_slope: f64,
    /// Node spacing on the ground (m), the smaller of the two directions.
    pub cell_m: f64,
    /// Per-block height maxima and slopes for the marcher (built from
    /// `heights`: rebuild the terrain after changing them).
    pub bounds: TerrainBounds,
}

impl Terrain {
    /// Builds the bounds from the heights.
    pub fn new(heights: LatLonGrid<f32>) -> Option<Self> {
        let valid = || heights.values.iter().filter(|h| h.is_finite()).map(|&h| h as f64);
        let h_min_m = valid().fold(f64::INFINITY, f64::min);
        let h_max_m = valid().fold(f64::NEG_INFINITY, f64::max);
        if !h_min_m.is_finite() {
            return None;
        }
        let mid_lat = heights.north_lat_deg - heights.dlat_deg * (heights.rows as f64 - 1.0) / 2.0;
        let (m_lat, m_lon) = trn_geodesy::metres_per_degree(mid_lat);
        let (dy, dx) = (heights.dlat_deg * m_lat, heights.dlon_deg * m_lon);
        let mut max_slope = 0.0f64;
        let (rows, cols, v) = (heights.rows, heights.cols, &heights.values);
        for r in 0..rows {
            for c in 0..cols {
                let h = v[r * cols + c];
                let mut rise = |o: f32, run: f64| {
                    let s = ((o - h) as f64 / run).abs();
                    if s.is_finite() {
                        max_slope = max_slope.max(s);
                    }
                };
                if c + 1 < cols {
                    rise(v[r * cols + c + 1], dx);
                }
                if r + 1 < rows {
                    rise(v[(r + 1) * cols + c], dy);
                }
            }
        }
        // Diagonal slopes within a bilinear cell are at most sqrt(2) times the edge slopes.
        Some(Self {
            bounds: TerrainBounds::new(&heights, h_min_m),
            heights,
            h_min_m,
            h_max_m,
            max_slope: max_slope * std::f64::consts::SQRT_2,
            cell_m: dx.min(dy),
        })
    }

    /// Height at a point, NaN where there is no DEM.
    #[inline]
    pub fn height_m(&self, lat_deg: f64, lon_deg: f64) -> f64 {
        self.heights.bilinear(lat_deg, lon_deg)
    }

    /// Height at a fractional grid position (row, col), NaN where there is no DEM.
    #[inline(always)]
    pub fn height_at(&self, row: f64, col: f64) -> f64 {
        self.heights.bilinear_at(row, col)
    }

    /// How far (m of range) a ray at grid position (row, col) and height
    /// `h` may go without meeting the bilinear surface of the cell under it,
    /// moving `(v_row, v_col)` grid units per metre and descending at most
    /// `descent` m per metre; `approach` bounds how fast it can close in on
    /// the surface anywhere (for the nudge into the next cell). Along the
    /// ray's (linear) track the cell's surface is a quadratic in the range t,
    /// `g0 + g1 t + g2 t^2`, so the height above it is at least
    /// `q(t) = (h - g0) - (descent + g1) t - g2 t^2`: the answer is q's first
    /// root if it comes before the track leaves the cell, else the exit
    /// (plus a nudge the surface cannot rise into). `None` outside the grid,
    /// on no data or when the ray is not above the surface.
    #[inline]
    pub fn cell_step(
        &self,
        (row, col, h): (f64, f64, f64),
        descent: f64,
        (v_row, v_col): (f64, f64),
        approach: f64,
    ) -> Option<f64> {
        let g = &self.heights;
        let (i, u0, w0) = g.cell(row, col)?;
        let v = &g.values;
        let (a, b, c, d) = (v[i] as f64, v[i + 1] as f64, v[i + g.cols] as f64, v[i + g.cols + 1] as f64);
        // Bilinear: a + (c - a) u + (b - a) w + k u w, with u along rows.
        let k = a - b - c + d;
        let g0 = a + (c - a) * u0 + (b - a) * w0 + k * u0 * w0;
        let f0 = h - g0;
        if !(f0 > 0.0) {
            return None;
        }
        let g1 = (c - a + k * w0) * v_row + (b - a + k * u0) * v_col;
        let g2 = k * v_row * v_col;
        // Range to the cell's edge along each axis (infinite when still).
        let exit = |x: f64, vx: f64| {
            if vx > 0.0 {
                (1.0 - x) / vx
            } else if vx < 0.0 {
                -x / vx
            } else {
                f64::INFINITY
            }
        };
        let t_exit = exit(u0, v_row).min(exit(w0, v_col));
        // First positive root of g2 t^2 + B t - f0 (q(0) = f0 > 0), in the
        // form without cancellation; none when q stays positive.
        let bq = descent + g1;
        let disc = bq * bq + 4.0 * g2 * f0;
        if disc >= 0.0 {
            let den = bq + disc.sqrt();
            if den > 0.0 {
                let t_root = 2.0 * f0 / den;
                if t_root < t_exit {
                    return Some(t_root);
                }
            }
        }
        // Past the edge by a thousandth of a cell at most, where the ray
        // cannot reach the surface (whose slope `approach` bounds) yet.
        let q_exit = f0 - bq * t_exit - g2 * t_exit * t_exit;
        let nudge = (1e-3 / v_row.abs().max(v_col.abs())).min(q_exit.max(0.0) / approach);
        Some(t_exit + nudge)
    }
}

/// One level of the luminance pyramid (0..255, NaN = no data).
#[derive(Clone, Debug)]
pub struct Level {
    pub width: usize,
    pub height: usize,
    pub lum: Vec<f32>,
}

impl Level {
    /// Bilinear sample at pixel-centre position (x, y) of this level; NaN
    /// outside or next to no data.
    #[inline]
    pub fn bilinear(&self, x: f64, y: f64) -> f32 {
        if !(x >= 0.0 && y >= 0.0) {
            return f32::NAN;
        }
        let (ix, iy) = (x as usize, y as usize);
        if ix + 1 >= self.width || iy + 1 >= self.height {
            return f32::NAN;
        }
        let (tx, ty) = ((x - ix as f64) as f32, (y - iy as f64) as f32);
        let i = iy * self.width + ix;
        let l = &self.lum;
        (l[i] * (1.0 - tx) + l[i + 1] * tx) * (1.0 - ty)
            + (l[i + self.width] * (1.0 - tx) + l[i + self.width + 1] * tx) * ty
    }

    /// 2x2 box reduction (odd edges repeat the last pixel), so level k pixel
    /// (i, j) averages level-0 pixels [2^k i, 2^k (i+1)).
    pub fn reduce(&self) -> Level {
        let (w, h) = (self.width.div_ceil(2), self.height.div_ceil(2));
        let mut lum = vec![0f32; w * h];
        for (y, row) in lum.chunks_exact_mut(w).enumerate() {
            let (y0, y1) = (2 * y, (2 * y + 1).min(self.height - 1));
            for (x, out) in row.iter_mut().enumerate() {
                let (x0, x1) = (2 * x, (2 * x + 1).min(self.width - 1));
                let s = self.lum[y0 * self.width + x0]
                    + self.lum[y0 * self.width + x1]
                    + self.lum[y1 * self.width + x0]
                    + self.lum[y1 * self.width + x1];
                *out = 0.25 * s;
            }
        }
        Level { width: w, height: h, lum }
    }
}

/// Side of the square tiles a [`TiledLevel`] stores, apron included.
const TILE_SIDE: usize = 32;
/// Pixels a tile owns per side; its last row and column repeat the next tile's first.
const TILE_STEP: usize = TILE_SIDE - 1;

/// A pyramid level stored as 32 x 32 tiles of 4 KiB (one page) that overlap
/// by one pixel, so every bilinear sample reads one tile: the pixels near a
/// footprint share a few cache lines and pages, where rows of the whole
/// level put each sample on a new page.
#[derive(Clone, Debug)]
pub struct TiledLevel {
    pub width: usize,
    pub height: usize,
    tiles_x: usize,
    data: Vec<f32>,
}

impl TiledLevel {
    /// The tiles of a level (no data past its edges).
    pub fn new(l: &Level) -> Self {
        let tiles_x = l.width.div_ceil(TILE_STEP).max(1);
        let tiles_y = l.height.div_ceil(TILE_STEP).max(1);
        let mut data = vec![f32::NAN; tiles_x * tiles_y * TILE_SIDE * TILE_SIDE];
        for (t, tile) in data.chunks_exact_mut(TILE_SIDE * TILE_SIDE).enumerate() {
            let (x0, y0) = ((t % tiles_x) * TILE_STEP, (t / tiles_x) * TILE_STEP);
            for (iy, row) in tile.chunks_exact_mut(TILE_SIDE).enumerate() {
                let y = y0 + iy;
                if y >= l.height {
                    break;
                }
                let n = TILE_SIDE.min(l.width.saturating_sub(x0));
                row[..n].copy_from_slice(&l.lum[y * l.width + x0..y * l.width + x0 + n]);
            }
        }
        Self { width: l.width, height: l.height, tiles_x, data }
    }

    /// As [`Level::bilinear`] (bit for bit).
    #[inline]
    pub fn bilinear(&self, x: f64, y: f64) -> f32 {
        if !(x >= 0.0 && y >= 0.0) {
            return f32::NAN;
        }
        let (ix, iy) = (x as usize, y as usize);
        if ix + 1 >= self.width || iy + 1 >= self.height {
            return f32::NAN;
        }
        let (tx, ty) = ((x - ix as f64) as f32, (y - iy as f64) as f32);
        let (cx, cy) = (ix / TILE_STEP, iy / TILE_STEP);
        let i = (cy * self.tiles_x + cx) * TILE_SIDE * TILE_SIDE
            + (iy - cy * TILE_STEP) * TILE_SIDE
            + (ix - cx * TILE_STEP);
        let l = &self.data[i..i + TILE_SIDE + 2];
        (l[0] * (1.0 - tx) + l[1] * tx) * (1.0 - ty)
            + (l[TILE_SIDE] * (1.0 - tx) + l[TILE_SIDE + 1] * tx) * ty
    }
}

/// The ortho's luminance as a mip pyramid, sampled with a footprint.
#[derive(Clone, Debug)]
pub struct OrthoPyramid {
    pub levels: Vec<TiledLevel>,
}

impl OrthoPyramid {
    /// Builds the pyramid down to a few pixels.
    pub fn new(level0: Level) -> Self {
        let mut levels = Vec::new();
        let mut last = level0;
        loop {
            levels.push(TiledLevel::new(&last));
            if levels.len() >= 16 || last.width < 8 || last.height < 8 {
                break;
            }
            last = last.reduce();
        }
        Self { levels }
    }

    /// Trilinear sample at level-0 pixel-centre position (x, y), averaging a
    /// footprint `footprint_px` level-0 pixels wide (<= 1: plain bilinear).
    #[inline]
    pub fn sample(&self, x: f64, y: f64, footprint_px: f64) -> f32 {
        self.sample_lod(self.lod(footprint_px), x, y)
    }

    /// The levels and blend weight for a footprint `footprint_px` level-0
    /// pixels wide (one logarithm, shared by the taps of one footprint).
    #[inline]
    pub fn lod(&self, footprint_px: f64) -> (usize, f32) {
        let lod = footprint_px.max(1.0).log2().min((self.levels.len() - 1) as f64);
        // Truncation is the floor here (lod >= 0), without a libm call.
        let k = lod as usize;
        (k, (lod - k as f64) as f32)
    }

    /// [`OrthoPyramid::sample`] with the levels from [`OrthoPyramid::lod`].
    #[inline]
    pub fn sample_lod(&self, (k, t): (usize, f32), x: f64, y: f64) -> f32 {
        let a = self.sample_level(k, x, y);
        if t < 1e-3 || k + 1 >= self.levels.len() {
            return a;
        }
        a * (1.0 - t) + self.sample_level(k + 1, x, y) * t
    }

    /// Bilinear sample of level k at level-0 position (x, y): level k's pixel
    /// i is centred on level-0 position 2^k i + (2^k - 1) / 2.
    #[inline]
    pub fn sample_level(&self, k: usize, x: f64, y: f64) -> f32 {
        // A power of two: the product is exactly the quotient.
        let inv = 1.0 / (1u64 << k) as f64;
        self.levels[k].bilinear((x + 0.5) * inv - 0.5, (y + 0.5) * inv - 0.5)
    }
}

/// Everything the renderer needs.
#[derive(Clone, Debug)]
pub struct Scene {
    pub terrain: Terrain,
    pub ortho: OrthoPyramid,
    /// Latitude/longitude -> ortho level-0 pixel-centre position (x = column, y = row).
    pub to_ortho: LatLonGrid<[f64; 2]>,
    /// Ortho pixel size on the ground (m).
    pub ortho_gsd_m: f64,
    /// The ortho's footprint.
    pub ortho_extent: trn_landmark::GeoBox,
}

/// Geodetic latitude, longitude (degrees) and height (m) of an ECEF point by
/// Bowring's formula with one iteration: sub-millimetre from below the
/// ground to beyond 100 km, at a fraction of the iterative conversion's cost
/// (the marcher calls it several times per pixel).
#[inline]
pub fn fast_geodetic(x: f64, y: f64, z: f64) -> (f64, f64, f64) {
    let ep2 = WGS84_E2 / (1.0 - WGS84_E2);
    // Plain square roots: libm's hypot guards against overflow we cannot have.
    let p = (x * x + y * y).sqrt();
    let lon = y.atan2(x);
    // Parametric latitude without trigonometry: (cos, sin) of atan2(a z, b p).
    let (bz, bp) = (WGS84_A * z, WGS84_B * p);
    let r = (bz * bz + bp * bp).sqrt();
    let (sb, cb) = (bz / r, bp / r);
    let num = z + ep2 * WGS84_B * sb * sb * sb;
    let den = p - WGS84_E2 * WGS84_A * cb * cb * cb;
    let rr = (num * num + den * den).sqrt();
    let (sl, cl) = (num / rr, den / rr);
    let h = p * cl + z * sl - WGS84_A * (1.0 - WGS84_E2 * sl * sl).sqrt();
    (num.atan2(den).to_degrees(), lon.to_degrees(), h)
}

/// [`fast_geodetic`] near a reference point: latitude and longitude as
/// small-angle series around the reference instead of two `atan2` calls
/// (exact to 1e-15 rad within 0.05 rad of it; farther points fall back).
#[derive(Clone, Copy, Debug)]
pub struct NearGeodetic {
    lat0_rad: f64,
    lon0_rad: f64,
    sin_lat0: f64,
    cos_lat0: f64,
    sin_lon0: f64,
    cos_lon0: f64,
}

impl NearGeodetic {
    pub fn new(lat_deg: f64, lon_deg: f64) -> Self {
        let (lat0_rad, lon0_rad) = (lat_deg.to_radians(), lon_deg.to_radians());
        let ((sin_lat0, cos_lat0), (sin_lon0, cos_lon0)) = (lat0_rad.sin_cos(), lon0_rad.sin_cos());
        Self { lat0_rad, lon0_rad, sin_lat0, cos_lat0, sin_lon0, cos_lon0 }
    }

    /// Latitude, longitude (degrees) and ellipsoidal height (m).
    #[inline(always)]
    pub fn geodetic(&self, x: f64, y: f64, z: f64) -> (f64, f64, f64) {
        let ep2 = WGS84_E2 / (1.0 - WGS84_E2);
        let p = (x * x + y * y).sqrt();
        let (bz, bp) = (WGS84_A * z, WGS84_B * p);
        let inv_r = 1.0 / (bz * bz + bp * bp).sqrt();
        let (sb, cb) = (bz * inv_r, bp * inv_r);
        let num = z + ep2 * WGS84_B * sb * sb * sb;
        let den = p - WGS84_E2 * WGS84_A * cb * cb * cb;
        let inv_rr = 1.0 / (num * num + den * den).sqrt();
        let (sl, cl) = (num * inv_rr, den * inv_rr);
        let h = p * cl + z * sl - WGS84_A * (1.0 - WGS84_E2 * sl * sl).sqrt();
        // Angle differences from the reference: atan of their tangents.
        let lat_den = cl * self.cos_lat0 + sl * self.sin_lat0;
        let lon_den = x * self.cos_lon0 + y * self.sin_lon0;
        let inv = 1.0 / (lat_den * lon_den);
        let t_lat = (sl * self.cos_lat0 - cl * self.sin_lat0) * lon_den * inv;
        let t_lon = (y * self.cos_lon0 - x * self.sin_lon0) * lat_den * inv;
        if t_lat.abs() > 0.05 || t_lon.abs() > 0.05 || !(lat_den > 0.0 && lon_den > 0.0) {
            return fast_geodetic(x, y, z);
        }
        let lat = self.lat0_rad + small_atan(t_lat);
        let lon = self.lon0_rad + small_atan(t_lon);
        (lat.to_degrees(), lon.to_degrees(), h)
    }
}

/// atan(t) for |t| <= 0.05: Taylor series to t^13 (truncation < 1e-19).
#[inline]
fn small_atan(t: f64) -> f64 {
    let t2 = t * t;
    t * (1.0
        - t2 * (1.0 / 3.0
            - t2 * (1.0 / 5.0 - t2 * (1.0 / 7.0 - t2 * (1.0 / 9.0 - t2 * (1.0 / 11.0 - t2 / 13.0))))))
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::Geodetic;

    #[test]
    fn fast_geodetic_matches_iterative_below_a_millimetre() {
        let mut worst: f64 = 0.0;
        for lat in (-89..=89).step_by(7) {
            for h in [-500.0, 0.0, 1500.0, 9000.0, 35_000.0, 120_000.0] {
                let g = Geodetic::new(lat as f64 + 0.37, 12.3 * lat as f64 / 7.0, h);
                let e = g.to_ecef();
                let (la, lo, hh) = fast_geodetic(e.x(), e.y(), e.z());
                let back = Geodetic::new(la, lo, hh).to_ecef();
                worst = worst.max(back.distance_m(&e));
            }
        }
        assert!(worst < 1e-3, "worst {worst} m");
    }

    #[test]
    fn near_geodetic_matches_fast_geodetic() {
        let near = NearGeodetic::new(40.3, -105.6);
        let mut worst: f64 = 0.0;
        for dlat in [-3.0, -0.5, 0.0, 0.01, 1.2, 2.8] {
            for dlon in [-3.5, -1.0, 0.0, 0.3, 2.9] {
                for h in [0.0, 2500.0, 30_000.0] {
                    let e = Geodetic::new(40.3 + dlat, -105.6 + dlon, h).to_ecef();
                    let (a, b) = (near.geodetic(e.x(), e.y(), e.z()), fast_geodetic(e.x(), e.y(), e.z()));
                    worst = worst.max((a.0 - b.0).abs()).max((a.1 - b.1).abs());
                    assert!((a.2 - b.2).abs() < 1e-9);
                }
            }
        }
        assert!(worst < 1e-12, "worst {worst} deg");
    }

    #[test]
    fn pyramid_levels_keep_the_pixel_centre_convention() {
        // A linear ramp stays a ramp under box filtering: every level must
        // return the level-0 value at the same level-0 position.
        let (w, h) = (64, 48);
        let lum: Vec<f32> = (0..w * h).map(|i| ((i % w) as f32) * 2.0 + ((i / w) as f32) * 0.5).collect();
        let p = OrthoPyramid::new(Level { width: w, height: h, lum });
        for k in 0..3 {
            for (x, y) in [(20.3, 17.8), (31.0, 9.25), (12.5, 22.0)] {
                let want = (x * 2.0 + y * 0.5) as f32;
                let got = p.sample_level(k, x, y);
                assert!((got - want).abs() < 1e-3, "level {k} at ({x}, {y}): {got} vs {want}");
            }
        }
    }

    #[test]
    fn tiled_level_samples_as_the_plain_level() {
        let (w, h) = (101, 70);
        let mut lum: Vec<f32> = (0..w * h).map(|i| ((i * 7919) % 255) as f32 * 0.5).collect();
        lum[40 * w + 62] = f32::NAN;
        let level = Level { width: w, height: h, lum };
        let tiled = TiledLevel::new(&level);
        let mut rng = crate::rng::Rng::stream(3, "tiles");
        for _ in 0..20_000 {
            let (x, y) = (rng.range(-2.0, w as f64 + 1.0), rng.range(-2.0, h as f64 + 1.0));
            let (a, b) = (level.bilinear(x, y), tiled.bilinear(x, y));
            assert!(a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()), "({x}, {y}): {a} vs {b}");
        }
        for (x, y) in [(30.0, 30.5), (31.0, 61.99), (99.0, 68.0), (99.5, 30.0), (0.0, 0.0)] {
            assert_eq!(level.bilinear(x, y).to_bits(), tiled.bilinear(x, y).to_bits(), "({x}, {y})");
        }
    }

    #[test]
    fn grid_bilinear_interpolates_and_refuses_outside() {
        let g = LatLonGrid {
            north_lat_deg: 41.0,
            west_lon_deg: -106.0,
            dlat_deg: 0.5,
            dlon_deg: 0.5,
            rows: 3,
            cols: 3,
            values: vec![0f32, 1.0, 2.0, 10.0, 11.0, 12.0, 20.0, 21.0, 22.0],
        };
        assert!((g.bilinear(40.75, -105.75) - 5.5).abs() < 1e-9);
        assert!((g.bilinear(40.0, -105.0) - 22.0).abs() < 1e-9);
        assert!(g.bilinear(41.1, -105.5).is_nan());
        assert!(g.bilinear(40.5, -104.9).is_nan());
        let t = Terrain::new(g).unwrap();
        assert_eq!((t.h_min_m, t.h_max_m), (0.0, 22.0));
    }
}
