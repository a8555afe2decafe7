//! Values on a regular latitude/longitude grid (terrain heights, a sun's
//! brightness factor, a map to ortho pixels), with bilinear sampling. Pure.

/// Values on a regular latitude/longitude grid: node `(row, col)` lies at
/// `lat = north_lat_deg - row * dlat_deg`, `lon = west_lon_deg + col * dlon_deg`.
#[derive(Clone, Debug)]
pub struct LatLonGrid<T> {
    pub north_lat_deg: f64,
    pub west_lon_deg: f64,
    pub dlat_deg: f64,
    pub dlon_deg: f64,
    pub rows: usize,
    pub cols: usize,
    pub values: Vec<T>,
}

impl<T> LatLonGrid<T> {
    /// A grid on the same nodes holding `values` (row-major, `rows * cols`).
    pub fn with_values<U>(&self, values: Vec<U>) -> LatLonGrid<U> {
        assert_eq!(values.len(), self.rows * self.cols, "one value per node");
        LatLonGrid {
            north_lat_deg: self.north_lat_deg,
            west_lon_deg: self.west_lon_deg,
            dlat_deg: self.dlat_deg,
            dlon_deg: self.dlon_deg,
            rows: self.rows,
            cols: self.cols,
            values,
        }
    }
}

impl<T: Copy> LatLonGrid<T> {
    /// Fractional (row, col) of a point; may lie outside the grid.
    #[inline]
    pub fn position(&self, lat_deg: f64, lon_deg: f64) -> (f64, f64) {
        ((self.north_lat_deg - lat_deg) / self.dlat_deg, (lon_deg - self.west_lon_deg) / self.dlon_deg)
    }

    /// The index of the north-west node of the cell holding (row, col) and
    /// the weights within it (row, col), or `None` outside the grid.
    #[inline]
    pub fn cell(&self, r: f64, c: f64) -> Option<(usize, f64, f64)> {
        if !(r >= 0.0 && c >= 0.0) {
            return None;
        }
        // Truncation is the floor here (non-negative), without a libm call.
        let (ir, ic) = (r as usize, c as usize);
        let (fr, fc) = (ir as f64, ic as f64);
        if ir + 1 >= self.rows || ic + 1 >= self.cols {
            // The last row/column belongs to the grid too.
            if (r == (self.rows - 1) as f64 || ir + 1 < self.rows)
                && (c == (self.cols - 1) as f64 || ic + 1 < self.cols)
            {
                let ir = ir.min(self.rows - 2);
                let ic = ic.min(self.cols - 2);
                return Some((ir * self.cols + ic, r - ir as f64, c - ic as f64));
            }
            return None;
        }
        Some((ir * self.cols + ic, r - fr, c - fc))
    }
}

impl LatLonGrid<f32> {
    /// Bilinear value; NaN outside the grid or next to a NaN node.
    #[inline(always)]
    pub fn bilinear(&self, lat_deg: f64, lon_deg: f64) -> f64 {
        let (r, c) = self.position(lat_deg, lon_deg);
        self.bilinear_at(r, c)
    }

    /// Bilinear value at a fractional grid position (row, col).
    #[inline(always)]
    pub fn bilinear_at(&self, r: f64, c: f64) -> f64 {
        let Some((i, tr, tc)) = self.cell(r, c) else { return f64::NAN };
        let v = &self.values;
        let (a, b, cc, d) =
            (v[i] as f64, v[i + 1] as f64, v[i + self.cols] as f64, v[i + self.cols + 1] as f64);
        (a * (1.0 - tc) + b * tc) * (1.0 - tr) + (cc * (1.0 - tc) + d * tc) * tr
    }

    /// [`Self::bilinear_at`], or `default` where that is NaN (off the grid,
    /// next to a NaN node).
    #[inline(always)]
    pub fn bilinear_at_or(&self, r: f64, c: f64, default: f32) -> f32 {
        let v = self.bilinear_at(r, c);
        if v.is_nan() {
            default
        } else {
            v as f32
        }
    }

    /// [`Self::bilinear`], or `default` where that is NaN.
    #[inline(always)]
    pub fn bilinear_or(&self, lat_deg: f64, lon_deg: f64, default: f32) -> f32 {
        let (r, c) = self.position(lat_deg, lon_deg);
        self.bilinear_at_or(r, c, default)
    }
}

impl LatLonGrid<[f64; 2]> {
    /// Bilinear interpolation of a 2-vector field; `None` outside.
    #[inline]
    pub fn bilinear2(&self, lat_deg: f64, lon_deg: f64) -> Option<[f64; 2]> {
        let (r, c) = self.position(lat_deg, lon_deg);
        let (i, tr, tc) = self.cell(r, c)?;
        let v = &self.values;
        let (a, b, cc, d) = (v[i], v[i + 1], v[i + self.cols], v[i + self.cols + 1]);
        let f =
            |k: usize| (a[k] * (1.0 - tc) + b[k] * tc) * (1.0 - tr) + (cc[k] * (1.0 - tc) + d[k] * tc) * tr;
        Some([f(0), f(1)])
    }
}

/// Node spacing (m) east and north along each row of `g` (a longitude step
/// spans `cos(lat)` of a latitude step's arc).
pub fn row_spacing_m<T>(g: &LatLonGrid<T>) -> (Vec<f64>, Vec<f64>) {
    (0..g.rows)
        .map(|r| {
            let (m_lat, m_lon) = trn_geodesy::metres_per_degree(g.north_lat_deg - r as f64 * g.dlat_deg);
            (g.dlon_deg * m_lon, g.dlat_deg * m_lat)
        })
        .unzip()
}
