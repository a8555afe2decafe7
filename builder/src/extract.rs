//! Turns a selected candidate into a [`Template`]: terrain from the DEM, then the
//! template pixels resampled north-up on the local tangent plane.

use nalgebra::{Matrix2, Matrix3, Vector2, Vector3};
use trn_geodesy::Geodetic;
use trn_landmark::{GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};

use crate::select::Candidate;
use crate::source::{PixelToCrs, Wgs84Transform};
use crate::terrain::Heights;
use trn_raster::ortho::Window;

/// Maps a window's pixels to WGS84 for one pyramid level of an ortho.
pub struct WindowGeo<'a> {
    pub to_crs: PixelToCrs,
    /// Native pixels per level pixel (2^p).
    pub scale: f64,
    pub to_wgs: &'a Wgs84Transform,
}

impl WindowGeo<'_> {
    /// (lon, lat) of window pixel centres.
    pub fn lonlat(&self, win: &Window, px: &[(f64, f64)]) -> Option<Vec<(f64, f64)>> {
        let mut xs = Vec::with_capacity(px.len());
        let mut ys = Vec::with_capacity(px.len());
        for &(x, y) in px {
            let (nc, nr) = ((win.x0 as f64 + x + 0.5) * self.scale, (win.y0 as f64 + y + 0.5) * self.scale);
            let (cx, cy) = self.to_crs.apply(nc, nr);
            xs.push(cx);
            ys.push(cy);
        }
        self.to_wgs.apply(&mut xs, &mut ys)?;
        Some(xs.into_iter().zip(ys).collect())
    }
}

#[derive(Clone, Copy, Debug)]
pub struct ExtractParams {
    pub level: u8,
    pub gsd_m: f64,
    pub size_px: u32,
    pub height_grid_n: u32,
    /// Largest RMS distance of the terrain from its plane (m); `None`: relief
    /// is modelled by the height grid, not limited.
    pub max_plane_residual_m: Option<f64>,
    /// Largest view angle from the vertical the database serves, and the
    /// largest share of the height grid its own relief may hide there from
    /// its best side (views come from every azimuth).
    pub max_view_deg: f64,
    pub max_hidden_share: f64,
    pub source: u32,
}

/// Why a candidate did not become a template (counted for the build log).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Reject {
    Transform,
    NoDem,
    Relief,
    /// The template's own relief hides too much of it at the served view
    /// angles, even from its best side.
    Occluded,
    OutsideWindow,
    Nodata,
    /// Relief shading could make more of the template's contrast than
    /// `--max-shading` allows (`TemplateQuality::shading_share`).
    Shading,
}

pub fn extract(
    win: &Window,
    geo: &WindowGeo,
    dem: &impl Heights,
    cand: &Candidate,
    p: &ExtractParams,
) -> Result<Template, Reject> {
    // The centre and four points half a template away: a central-difference
    // Jacobian of window pixels -> local metres. Over one template the map from
    // the tangent plane to the ortho's pixels is affine to far below a pixel.
    let (cx, cy) = (cand.x as f64, cand.y as f64);
    let a = (p.size_px as f64 / 2.0).max(1.0);
    let ll = geo
        .lonlat(win, &[(cx, cy), (cx + a, cy), (cx - a, cy), (cx, cy + a), (cx, cy - a)])
        .ok_or(Reject::Transform)?;
    let centre_ll = ll[0];
    let (m_lat, m_lon) = trn_geodesy::metres_per_degree(centre_ll.1);
    let en_per_px = Matrix2::new(
        (ll[1].0 - ll[2].0) * m_lon / (2.0 * a),
        (ll[3].0 - ll[4].0) * m_lon / (2.0 * a),
        (ll[1].1 - ll[2].1) * m_lat / (2.0 * a),
        (ll[3].1 - ll[4].1) * m_lat / (2.0 * a),
    );
    let px_per_en = en_per_px.try_inverse().ok_or(Reject::Transform)?;

    // Terrain: n x n grid over the footprint (row 0 north) plus the centre, in
    // one DEM read. The local linear lat/lon map is within centimetres of exact
    // geodesy over a template, far below a DEM cell.
    let footprint_half_m = p.size_px as f64 / 2.0 * p.gsd_m;
    let n = p.height_grid_n.max(2) as usize;
    let spacing = 2.0 * footprint_half_m / (n as f64 - 1.0);
    let mut grid_en = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            grid_en.push((-footprint_half_m + c as f64 * spacing, footprint_half_m - r as f64 * spacing));
        }
    }
    let mut sample_ll: Vec<(f64, f64)> =
        grid_en.iter().map(|&(e, nn)| (centre_ll.0 + e / m_lon, centre_ll.1 + nn / m_lat)).collect();
    sample_ll.push(centre_ll);
    let hs = dem.heights_ellipsoidal(&sample_ll).ok_or(Reject::NoDem)?;
    let h_centre = hs[n * n];
    let centre = Geodetic::new(centre_ll.1, centre_ll.0, h_centre);
    // Height above the tangent plane: the ellipsoid falls away from it by
    // e^2 / 2N + n^2 / 2M (its principal curvatures), millimetre-exact here.
    let (rn, rm) = (centre.prime_vertical_radius_m() + h_centre, centre.meridian_radius_m() + h_centre);
    let heights: Vec<f64> = grid_en
        .iter()
        .zip(&hs)
        .map(|(&(e, nn), &h)| h - h_centre - e * e / (2.0 * rn) - nn * nn / (2.0 * rm))
        .collect();
    let (normal, rms) = fit_plane(&grid_en, &heights);
    if p.max_plane_residual_m.is_some_and(|max| rms > max) {
        return Err(Reject::Relief);
    }
    let height_grid = HeightGrid {
        n: n as u32,
        spacing_m: spacing,
        heights_m: heights.iter().map(|&h| h as f32).collect(),
    };
    if height_grid.hidden_share_best_side(p.max_view_deg) > p.max_hidden_share {
        return Err(Reject::Occluded);
    }

    // Template pixels: the affine map walks the window in fixed steps. The grid
    // is inside the window when its four corners are (the map is affine).
    let size = p.size_px as usize;
    let c0 = (size as f64 - 1.0) / 2.0;
    let step_col = px_per_en * Vector2::new(p.gsd_m, 0.0);
    let step_row = px_per_en * Vector2::new(0.0, -p.gsd_m);
    let origin = Vector2::new(cx, cy) - step_col * c0 - step_row * c0;
    let last = (size - 1) as f64;
    for corner in
        [origin, origin + step_col * last, origin + step_row * last, origin + (step_col + step_row) * last]
    {
        // A micro-pixel of slack covers the rounding of the stepping below.
        let (xmax, ymax) = ((win.width - 1) as f64 - 1e-6, (win.height - 1) as f64 - 1e-6);
        if !(corner.x >= 0.0 && corner.y >= 0.0 && corner.x < xmax && corner.y < ymax) {
            return Err(Reject::OutsideWindow);
        }
    }
    let mut pixels = vec![0u8; size * size];
    let (lum, valid) = (&win.lum[..], &win.valid[..]);
    if all_valid_and_fetched(
        lum,
        valid,
        win.width,
        &[origin, origin + step_col * last, origin + step_row * last, origin + (step_col + step_row) * last],
    ) {
        // Every neighbour the samples can touch is valid (the usual case): no
        // per-sample nodata test, so the row loop runs branch-free.
        for (row, out) in pixels.chunks_exact_mut(size).enumerate() {
            let q = origin + step_row * row as f64;
            resample_row(lum, win.width, (q.x, q.y), (step_col.x, step_col.y), out);
        }
    } else {
        for (row, out) in pixels.chunks_exact_mut(size).enumerate() {
            let mut q = origin + step_row * row as f64;
            for o in out {
                let v = bilinear_inside(lum, valid, win.width, q.x, q.y).ok_or(Reject::Nodata)?;
                // v is in 0..=255: adding a half and truncating rounds it.
                *o = (v + 0.5) as u8;
                q += step_col;
            }
        }
    }

    let tmp = Template {
        id: 0,
        level: p.level,
        gsd_m: p.gsd_m,
        width_px: p.size_px,
        height_px: p.size_px,
        center: centre,
        footprint: GeoBox::new(0.0, 0.0, 0.0, 0.0),
        terrain: TerrainPatch {
            plane_normal_enu: [normal.x, normal.y, normal.z],
            plane_residual_rms_m: rms,
            height_grid,
        },
        quality: TemplateQuality {
            shi_tomasi: cand.shi_tomasi,
            contrast_std: cand.contrast_std,
            second_peak_ncc: cand.second_peak_ncc,
            shading_share: 0.0,
        },
        source: p.source,
        lighting: 0,
        pixels,
    };
    let corners = tmp.footprint_corners();
    let footprint =
        GeoBox::around(corners.iter().map(|g| (g.lon_deg, g.lat_deg))).ok_or(Reject::Transform)?;
    Ok(Template { footprint, ..tmp })
}

/// Whether every window pixel a bilinear sample inside the parallelogram of
/// `corners` may read (its bounding box plus the right and lower neighbours)
/// is valid. The corners are inside the window. On the way it loads one
/// luminance value per cache line of the box, all independent of each other,
/// so the memory system fetches the template's rows together rather than one
/// after another inside the resampling loop (a window is larger than the L2
/// cache; measured: a third less time in extraction).
fn all_valid_and_fetched(lum: &[f32], valid: &[u8], width: usize, corners: &[Vector2<f64>; 4]) -> bool {
    let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for c in corners {
        (x0, y0, x1, y1) = (x0.min(c.x), y0.min(c.y), x1.max(c.x), y1.max(c.y));
    }
    let (x0, y0) = (x0 as usize, y0 as usize);
    let (x1, y1) = (x1 as usize + 1, y1 as usize + 1);
    let mut touched = 0.0f32;
    for r in y0..=y1 {
        let row = r * width;
        if valid[row + x0..=row + x1].contains(&0) {
            return false;
        }
        touched += lum[row + x0..=row + x1].iter().step_by(16).sum::<f32>() + lum[row + x1];
    }
    std::hint::black_box(touched);
    true
}

/// One template row of bilinear samples stepping `step` window pixels from
/// `start`, every neighbour known valid and inside (see [`all_valid_and_fetched`]);
/// rounded to bytes. Positions step in 16.16 fixed point (a 32-pixel row
/// drifts by under 1/1000 pixel), weights and sums in f32: a third of the
/// time of the f64 arithmetic of [`bilinear_inside`], the same bytes but for
/// rare ties in the rounding.
#[inline(always)]
fn resample_row(lum: &[f32], width: usize, start: (f64, f64), step: (f64, f64), out: &mut [u8]) {
    const ONE: f64 = 65536.0;
    let (mut x, mut y) = ((start.0 * ONE) as i64, (start.1 * ONE) as i64);
    let (dx, dy) = ((step.0 * ONE).round() as i64, (step.1 * ONE).round() as i64);
    for o in out {
        let (ix, iy) = ((x >> 16) as usize, (y >> 16) as usize);
        let (tx, ty) = ((x & 0xffff) as f32 * (1.0 / 65536.0), (y & 0xffff) as f32 * (1.0 / 65536.0));
        let i = iy * width + ix;
        let (l0, l1) = (&lum[i..i + 2], &lum[i + width..i + width + 2]);
        let top = l0[0] + (l0[1] - l0[0]) * tx;
        let bottom = l1[0] + (l1[1] - l1[0]) * tx;
        *o = (top + (bottom - top) * ty + 0.5) as u8;
        x += dx;
        y += dy;
    }
}

/// Bilinear sample at a position known to lie inside the window (`width`
/// wide, with its right and lower neighbours); `None` on nodata.
#[inline(always)]
fn bilinear_inside(lum: &[f32], valid: &[u8], width: usize, x: f64, y: f64) -> Option<f64> {
    // Truncation is floor for non-negative values (and avoids a libm call);
    // through i32, a cheaper conversion than to usize (windows are far smaller).
    let (ix, iy) = (x as i32 as usize, y as i32 as usize);
    let (tx, ty) = (x - ix as f64, y - iy as f64);
    let i = iy * width + ix;
    let j = i + width;
    // Pairs of neighbours as slices: one bounds check per pair.
    let (v0, v1) = (&valid[i..i + 2], &valid[j..j + 2]);
    if v0[0] & v0[1] & v1[0] & v1[1] == 0 {
        return None;
    }
    let (l0, l1) = (&lum[i..i + 2], &lum[j..j + 2]);
    Some(
        (l0[0] as f64 * (1.0 - tx) + l0[1] as f64 * tx) * (1.0 - ty)
            + (l1[0] as f64 * (1.0 - tx) + l1[1] as f64 * tx) * ty,
    )
}

/// Least-squares plane u = a e + b n + c; returns its unit normal (ENU) and the RMS residual.
pub fn fit_plane(en: &[(f64, f64)], up: &[f64]) -> (Vector3<f64>, f64) {
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    for (&(e, n), &u) in en.iter().zip(up) {
        let row = Vector3::new(e, n, 1.0);
        ata += row * row.transpose();
        atb += row * u;
    }
    let sol = ata.lu().solve(&atb).unwrap_or_else(Vector3::zeros);
    let rms =
        (en.iter().zip(up).map(|(&(e, n), &u)| (u - (sol.x * e + sol.y * n + sol.z)).powi(2)).sum::<f64>()
            / en.len().max(1) as f64)
            .sqrt();
    (Vector3::new(-sol.x, -sol.y, 1.0).normalize(), rms)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_fit_recovers_slope_and_zero_residual() {
        let en: Vec<(f64, f64)> =
            (0..25).map(|i| ((i % 5) as f64 * 10.0 - 20.0, (i / 5) as f64 * 10.0 - 20.0)).collect();
        let up: Vec<f64> = en.iter().map(|&(e, n)| 0.5 * e - 0.25 * n + 3.0).collect();
        let (normal, rms) = fit_plane(&en, &up);
        assert!(rms < 1e-9);
        let expect = Vector3::new(-0.5, 0.25, 1.0).normalize();
        assert!((normal - expect).norm() < 1e-9);
        // A bump gives a residual.
        let mut bumped = up.clone();
        bumped[12] += 10.0;
        assert!(fit_plane(&en, &bumped).1 > 1.0);
    }
}
