//! Sunlight on terrain: the brightness factor a surface takes under a sun,
//! from a grid of heights (pure math; the simulator re-lights its world with
//! it, the builder bakes a mission's sun into its templates).
//!
//! - Shading: Lambertian, from the terrain normal by central differences of
//!   the heights of a [`LatLonGrid`] in metres (each row with its own node
//!   spacing, so a longitude step spans `cos(lat)` of a latitude step's arc).
//! - Cast shadows: one sweep of the grid along the sun's azimuth with the
//!   shadow-height recurrence `S(p) = max(h(p), S(p + step u) - step tan E)`
//!   (`u` the horizontal direction to the sun, `S` linear between the two
//!   nodes of the upwind line); lines are processed from the sun's side, so
//!   the upwind line is always done. A node is in shadow where the shadow
//!   surface passes above it; the edge is a linear ramp centred on the
//!   geometric edge and one sweep step wide (sub-cell, so a bilinear lookup
//!   places the penumbra's middle where the shadow ends).
//! - The factor is `(a + (1 - a) lit max(0, n.s)) / (a + (1 - a) sin E)`
//!   (`a` the diffuse share): 1 on flat, sunlit ground, so an ortho taken
//!   under a high sun keeps its brightness there.
//!
//! The sun has the same azimuth and elevation at every node (a scene tens of
//! kilometres wide spans a few tenths of a degree of the Earth's curvature)
//! and the sweep runs over heights above the ellipsoid without the curvature
//! drop (`L^2 / 2R`: 0.3 m over a 2 km shadow).
//!
//! ```
//! use trn_landmark::grid::LatLonGrid;
//! use trn_landmark::lighting::{illumination, SunLight};
//! // Flat ground: the factor is 1 everywhere.
//! let g = LatLonGrid {
//!     north_lat_deg: 37.5, west_lon_deg: -118.5, dlat_deg: 3e-4, dlon_deg: 3e-4,
//!     rows: 3, cols: 3, values: vec![100f32; 9],
//! };
//! let f = illumination(&g, &SunLight { azimuth_deg: 135.0, elevation_deg: 35.0, ambient: 0.25 });
//! assert!(f.iter().all(|v| (v - 1.0).abs() < 1e-6));
//! ```

use serde::{Deserialize, Serialize};

use crate::grid::{row_spacing_m, LatLonGrid};

/// Depth of the shadow surface under which an upwind point counts as shaded (m).
const SHADOW_EPS_M: f64 = 1e-3;

/// A sun: where it stands, and how much of the light is diffuse.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SunLight {
    /// Direction of the sun, clockwise from north (deg).
    pub azimuth_deg: f64,
    /// Height of the sun above the local horizon (deg, in (0, 90]).
    pub elevation_deg: f64,
    /// Share of the light that is diffuse (sky light), the only light in
    /// shadows and on slopes facing away from the sun (in [0, 1]).
    pub ambient: f64,
}

impl SunLight {
    /// Unit vector toward the sun in the local east-north-up frame.
    pub fn direction_enu(&self) -> [f64; 3] {
        let (az, el) = (self.azimuth_deg.to_radians(), self.elevation_deg.to_radians());
        let (sin_e, cos_e) = el.sin_cos();
        [cos_e * az.sin(), cos_e * az.cos(), sin_e]
    }

    /// Angle between this sun's direction and another's (deg).
    pub fn angle_to_deg(&self, o: &SunLight) -> f64 {
        let (a, b) = (self.direction_enu(), o.direction_enu());
        (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0).acos().to_degrees()
    }

    /// The sun's shading, with its direction and normalisation worked out
    /// once (for many normals).
    pub fn shading(&self) -> Shading {
        let s = self.direction_enu();
        let a = self.ambient.clamp(0.0, 1.0);
        Shading { s, a, flat: a + (1.0 - a) * s[2] }
    }
}

/// A sun's brightness factor as a function of the surface normal.
#[derive(Clone, Copy, Debug)]
pub struct Shading {
    /// Unit vector toward the sun (ENU), diffuse share, flat ground's light.
    s: [f64; 3],
    a: f64,
    flat: f64,
}

impl Shading {
    /// The factor of a surface with upward normal `n_enu` (unit) in the sun
    /// (`lit` = 1) or in cast shadow (`lit` = 0); see the module's formula.
    #[inline]
    pub fn factor(&self, n_enu: [f64; 3], lit: f64) -> f64 {
        let ns = n_enu[0] * self.s[0] + n_enu[1] * self.s[1] + n_enu[2] * self.s[2];
        (self.a + (1.0 - self.a) * ns.max(0.0) * lit) / self.flat
    }
}

/// The brightness factor of every node of the heights `g` (m, NaN where
/// there are none) under `sun` (1 where there is no height), row-major like
/// the grid. Elevation is taken in (0, 90]; `rows` and `cols` must be at
/// least 2.
pub fn illumination(g: &LatLonGrid<f32>, sun: &SunLight) -> Vec<f32> {
    let (rows, cols) = (g.rows, g.cols);
    assert!(rows >= 2 && cols >= 2 && g.values.len() == rows * cols, "a grid of at least 2 x 2 nodes");
    let (dx, dy) = row_spacing_m(g);
    let az = sun.azimuth_deg.to_radians();
    let (ue, un) = (az.sin(), az.cos());
    // A sun at the zenith casts no shadow; the cap keeps the ramp finite.
    let tan_e = sun.elevation_deg.to_radians().tan().min(1e4);
    let mut lit = shadow_sweep(g, &dx, &dy, ue, un, tan_e);
    let shading = sun.shading();
    let h = &g.values;
    let at = |r: usize, c: usize| h[r * cols + c];
    for (r, row) in lit.chunks_mut(cols).enumerate() {
        for (c, out) in row.iter_mut().enumerate() {
            let hc = at(r, c);
            if !hc.is_finite() {
                *out = 1.0;
                continue;
            }
            let west = if c > 0 { at(r, c - 1) } else { f32::NAN };
            let east = if c + 1 < cols { at(r, c + 1) } else { f32::NAN };
            let north = if r > 0 { at(r - 1, c) } else { f32::NAN };
            let south = if r + 1 < rows { at(r + 1, c) } else { f32::NAN };
            let gx = slope(west, hc, east, dx[r]);
            let gy = slope(south, hc, north, dy[r]);
            let len = (1.0 + gx * gx + gy * gy).sqrt();
            *out = shading.factor([-gx / len, -gy / len, 1.0 / len], *out as f64) as f32;
        }
    }
    lit
}

/// Rise per metre from `minus` to `plus` across the node `centre`, `step`
/// metres from each: central difference, one-sided next to no data or the
/// edge, flat when both neighbours are missing.
fn slope(minus: f32, centre: f32, plus: f32, step: f64) -> f64 {
    match (minus.is_finite(), plus.is_finite()) {
        (true, true) => (plus - minus) as f64 / (2.0 * step),
        (true, false) => (centre - minus) as f64 / step,
        (false, true) => (plus - centre) as f64 / step,
        (false, false) => 0.0,
    }
}

/// The `lit` share (0 in cast shadow, 1 in light) of every node: one sweep
/// along the sun's azimuth (`ue`, `un`: east and north parts of the
/// horizontal direction to the sun), row-major like the grid; `dx`, `dy`:
/// node spacing (m) per row.
fn shadow_sweep(g: &LatLonGrid<f32>, dx: &[f64], dy: &[f64], ue: f64, un: f64, tan_e: f64) -> Vec<f32> {
    let (rows, cols) = (g.rows, g.cols);
    let mid = rows / 2;
    // Lines across the sweep: columns when the sun is more east/west than
    // north/south in grid steps, rows otherwise. Each step toward the sun
    // moves one line over and `dpos` along the line.
    let by_columns = ue.abs() * dy[mid] >= un.abs() * dx[mid];
    let (n_lines, len) = if by_columns { (cols, rows) } else { (rows, cols) };
    let index = |line: usize, pos: usize| if by_columns { pos * cols + line } else { line * cols + pos };
    // Horizontal length (m) of the step to the next line and the offset along it.
    let step_of = |line: usize, pos: usize| -> (f64, f64) {
        if by_columns {
            let step = dx[pos] / ue.abs();
            (step, -un * step / dy[pos])
        } else {
            let step = dy[line] / un.abs();
            (step, ue * step / dx[line])
        }
    };
    // Line indices grow toward the sun: columns eastward, rows southward.
    let toward_sun_up = if by_columns { ue > 0.0 } else { un < 0.0 };
    let mut lit = vec![1f32; rows * cols];
    // Shadow heights and terrain heights of the upwind line.
    let mut up_s = vec![f64::NAN; len];
    let mut up_h = vec![f64::NAN; len];
    let mut cur_s = vec![f64::NAN; len];
    for k in 0..n_lines {
        let line = if toward_sun_up { n_lines - 1 - k } else { k };
        for pos in 0..len {
            let h = g.values[index(line, pos)] as f64;
            if k == 0 {
                cur_s[pos] = h;
                continue;
            }
            let (step, dpos) = step_of(line, pos);
            // (A sun along the grid leaves a rounding offset: no step off the edge.)
            let q = pos as f64 + if dpos.abs() < 1e-9 { 0.0 } else { dpos };
            let (s_up, h_up) = if q >= 0.0 && q <= (len - 1) as f64 {
                let i = (q as usize).min(len - 2);
                let t = q - i as f64;
                (up_s[i] * (1.0 - t) + up_s[i + 1] * t, up_h[i] * (1.0 - t) + up_h[i + 1] * t)
            } else {
                // Beyond the grid: nothing known to cast a shadow.
                (f64::NAN, f64::NAN)
            };
            let drop = step * tan_e;
            let cand = s_up - drop;
            // f64::max keeps the number where the other is NaN (no data).
            cur_s[pos] = h.max(cand);
            if h.is_nan() || s_up.is_nan() {
                continue;
            }
            // How far the shadow surface passes above the node (m, signed).
            let depth = cand - h;
            // Shadow arrives from upwind, or the terrain between rises too
            // steeply toward the sun: a ramp one step wide, half lit at the
            // geometric edge (on flat ground the depth changes by `drop` per
            // step). Otherwise only the shading's own self-shadow applies.
            let rise = s_up - h_up;
            if rise > SHADOW_EPS_M || rise.is_nan() || depth > 0.0 {
                lit[index(line, pos)] = (0.5 - depth / drop).clamp(0.0, 1.0) as f32;
            }
        }
        std::mem::swap(&mut up_s, &mut cur_s);
        for (pos, v) in up_h.iter_mut().enumerate() {
            *v = g.values[index(line, pos)] as f64;
        }
    }
    lit
}
