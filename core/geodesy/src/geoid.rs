//! Geoid undulation grids (e.g. EGM96): N such that h_ellipsoid = H_orthometric + N.

/// A regular latitude/longitude grid of geoid undulations (m), row-major.
/// Row 0 is the northernmost row, rows go south by `dlat_deg`; column 0 is
/// the westernmost column, columns go east by `dlon_deg`. Grid values sit on
/// the nodes (row/column centres); between nodes the undulation is bilinear.
///
/// A grid whose columns span 360 degrees is *global*: longitudes wrap, and it
/// may or may not repeat its first column at the end (both forms work). Any
/// other grid is *regional* and may straddle the antimeridian.
#[derive(Clone, Debug, PartialEq)]
pub struct GeoidGrid {
    pub name: String,
    /// Latitude of row 0's centre (degrees, northernmost).
    pub north_lat_deg: f64,
    /// Longitude of column 0's centre (degrees).
    pub west_lon_deg: f64,
    /// Row and column spacing (degrees, positive).
    pub dlat_deg: f64,
    pub dlon_deg: f64,
    pub rows: usize,
    pub cols: usize,
    /// `rows * cols` values, row-major; NaN marks no-data nodes.
    pub undulation_m: Vec<f32>,
}

/// Slack (in grid cells) for points on the outer edge of a regional grid.
const EDGE_TOLERANCE_CELLS: f64 = 1e-9;

impl GeoidGrid {
    /// True when the columns span the whole globe, so longitudes wrap.
    pub fn wraps(&self) -> bool {
        (self.cols as f64 * self.dlon_deg) >= 359.999
    }

    /// Bilinear geoid undulation (m) at a point, `None` outside a regional grid,
    /// on a cell with a no-data (NaN) corner, or for a malformed grid.
    ///
    /// A global grid covers every longitude, and latitudes between its outer
    /// rows and the poles take the outer row's value (clamped), as the grid
    /// gives no information beyond it.
    pub fn undulation_at(&self, lat_deg: f64, lon_deg: f64) -> Option<f64> {
        if self.rows == 0
            || self.cols == 0
            || self.undulation_m.len() != self.rows * self.cols
            || !(self.dlat_deg > 0.0 && self.dlon_deg > 0.0)
            || !lat_deg.is_finite()
            || !lon_deg.is_finite()
        {
            return None;
        }
        let last_row = (self.rows - 1) as f64;
        let mut row = (self.north_lat_deg - lat_deg) / self.dlat_deg;
        if self.wraps() && lat_deg.abs() <= 90.0 {
            row = row.clamp(0.0, last_row);
        } else if row < -EDGE_TOLERANCE_CELLS || row > last_row + EDGE_TOLERANCE_CELLS {
            return None;
        }
        let row = row.clamp(0.0, last_row);

        // Longitude east of column 0, in [0, 360): handles any input longitude
        // convention and regional grids across the antimeridian alike.
        let mut east_deg = (lon_deg - self.west_lon_deg).rem_euclid(360.0);
        let (c0, c1, fc) = if self.wraps() {
            // Columns per turn; a trailing copy of column 0 (if any) is never read.
            let period = ((360.0 / self.dlon_deg).round() as usize).clamp(1, self.cols);
            let col = east_deg / self.dlon_deg;
            let c0 = col.floor() as usize % period;
            (c0, (c0 + 1) % period, col - col.floor())
        } else {
            // A point a hair west of column 0 wrapped to ~360: bring it back.
            if east_deg > 360.0 - EDGE_TOLERANCE_CELLS * self.dlon_deg {
                east_deg -= 360.0;
            }
            let last_col = (self.cols - 1) as f64;
            let col = east_deg / self.dlon_deg;
            if col < -EDGE_TOLERANCE_CELLS || col > last_col + EDGE_TOLERANCE_CELLS {
                return None;
            }
            let col = col.clamp(0.0, last_col);
            let c0 = col.floor() as usize;
            (c0, (c0 + 1).min(self.cols - 1), col - col.floor())
        };

        let r0 = row.floor() as usize;
        let r1 = (r0 + 1).min(self.rows - 1);
        let fr = row - row.floor();
        let v = |r: usize, c: usize| self.undulation_m.get(r * self.cols + c).map(|&n| n as f64);
        let n = (v(r0, c0)? * (1.0 - fc) + v(r0, c1)? * fc) * (1.0 - fr)
            + (v(r1, c0)? * (1.0 - fc) + v(r1, c1)? * fc) * fr;
        n.is_finite().then_some(n)
    }
}
