//! A DEM that is not the one the camera sees (`trn degrade-dem`): the
//! landmark database of a realistic scenario is built from it, while the
//! simulator renders the original. Real missions map with one elevation
//! model (SRTM, Copernicus, a lidar survey) and fly over the real relief.
//!
//! Two departures, each optional:
//! - **coarser**: block averages of `factor x factor` cells (the factor is the
//!   requested cell size over the input's, rounded; partial blocks at the
//!   right and bottom edges average the cells they have);
//! - **correlated noise**: Gaussian white noise smoothed by a Gaussian of
//!   standard deviation `noise_scale_m`, then scaled so its RMS over the
//!   grid is exactly `noise_rms_m` (a DEM's correlated error: voids filled,
//!   canopy, radar penetration).
//!
//! The output is a Float32 GeoTIFF in the input's CRS (vertical datum
//! included), with its nodata value, written to a temporary file renamed over
//! `out` when complete.

use std::path::PathBuf;

use serde::Serialize;
use trn_raster::source;

use crate::rng::Rng;
use crate::SimError;

/// What to write.
#[derive(Clone, Debug)]
pub struct DemVariantOptions {
    pub dem: PathBuf,
    pub out: PathBuf,
    /// Output cell size (m); `None` keeps the input's grid.
    pub cell_m: Option<f64>,
    /// RMS of the added noise (m); 0 adds none.
    pub noise_rms_m: f64,
    /// Correlation length of the noise: the smoothing Gaussian's sigma (m).
    pub noise_scale_m: f64,
    pub seed: u64,
}

/// What was written.
#[derive(Clone, Debug, Serialize)]
pub struct DemVariantReport {
    pub out: PathBuf,
    pub input_cell_m: f64,
    pub output_cell_m: f64,
    /// Input cells per output cell along each axis.
    pub factor: usize,
    pub width: usize,
    pub height: usize,
    /// RMS of the noise actually added (m).
    pub noise_rms_m: f64,
}

/// A north-up height grid with its missing cells (`NaN`).
#[derive(Clone, Debug, PartialEq)]
pub struct HeightGrid {
    pub width: usize,
    pub height: usize,
    /// Row-major heights (m), `NaN` where unknown.
    pub heights_m: Vec<f64>,
}

impl HeightGrid {
    /// Means of `factor x factor` blocks, ignoring missing cells (`NaN` when a
    /// block has none).
    pub fn block_average(&self, factor: usize) -> HeightGrid {
        let f = factor.max(1);
        let (w, h) = (self.width.div_ceil(f), self.height.div_ceil(f));
        let mut sum = vec![0.0; w * h];
        let mut count = vec![0u32; w * h];
        for r in 0..self.height {
            for c in 0..self.width {
                let v = self.heights_m[r * self.width + c];
                if v.is_finite() {
                    let k = (r / f) * w + c / f;
                    sum[k] += v;
                    count[k] += 1;
                }
            }
        }
        let heights_m =
            sum.iter().zip(&count).map(|(s, &n)| if n > 0 { s / n as f64 } else { f64::NAN }).collect();
        HeightGrid { width: w, height: h, heights_m }
    }
}

/// Gaussian noise on a `width x height` grid, smoothed by a Gaussian of
/// `sigma_cells` (none below 0.3 cells), scaled to an RMS of exactly `rms`.
pub fn correlated_noise(width: usize, height: usize, sigma_cells: f64, rms: f64, seed: u64) -> Vec<f64> {
    let mut rng = Rng::stream(seed, "dem_variant.noise");
    let mut v: Vec<f64> = (0..width * height).map(|_| rng.normal()).collect();
    if sigma_cells >= 0.3 {
        let r = (3.0 * sigma_cells).ceil() as isize;
        let kernel: Vec<f64> = (-r..=r).map(|i| (-0.5 * (i as f64 / sigma_cells).powi(2)).exp()).collect();
        // Separable, edges clamped.
        let pass = |src: &[f64], along_rows: bool| -> Vec<f64> {
            let mut out = vec![0.0; src.len()];
            for y in 0..height {
                for x in 0..width {
                    let mut acc = 0.0;
                    for (k, wk) in kernel.iter().enumerate() {
                        let d = k as isize - r;
                        let (xx, yy) = if along_rows {
                            ((x as isize + d).clamp(0, width as isize - 1) as usize, y)
                        } else {
                            (x, (y as isize + d).clamp(0, height as isize - 1) as usize)
                        };
                        acc += wk * src[yy * width + xx];
                    }
                    out[y * width + x] = acc;
                }
            }
            out
        };
        v = pass(&pass(&v, true), false);
    }
    let mean = v.iter().sum::<f64>() / v.len().max(1) as f64;
    let cur = (v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / v.len().max(1) as f64).sqrt();
    let k = if cur > 0.0 { rms / cur } else { 0.0 };
    v.iter().map(|x| (x - mean) * k).collect()
}

/// Reads `opts.dem`, degrades it and writes `opts.out` (atomically).
pub fn degrade_dem(opts: &DemVariantOptions) -> Result<DemVariantReport, SimError> {
    let bad = |what: &str| SimError::Input { path: opts.dem.clone(), reason: what.to_string() };
    let check = |option: &'static str, v: f64, ok: bool, want: &str| {
        if v.is_finite() && ok {
            Ok(())
        } else {
            Err(SimError::Option { option, reason: format!("must be {want} (got {v})") })
        }
    };
    if let Some(c) = opts.cell_m {
        check("--cell-m", c, c > 0.0, "> 0")?;
    }
    check("--noise-m", opts.noise_rms_m, opts.noise_rms_m >= 0.0, ">= 0")?;
    check("--noise-scale-m", opts.noise_scale_m, opts.noise_scale_m >= 0.0, ">= 0")?;
    let source::Band1 { info, values: heights_m, nodata } = source::read_band1(&opts.dem)?;
    let grid = HeightGrid { width: info.width, height: info.height, heights_m };
    if grid.heights_m.iter().all(|v| v.is_nan()) {
        return Err(bad("every height is nodata"));
    }
    let input_cell_m = (info.pixel_dx_m * info.pixel_dy_m).sqrt();
    let factor = opts.cell_m.map_or(1, |c| (c / input_cell_m).round().max(1.0) as usize);
    let mut out = grid.block_average(factor);
    let output_cell_m = input_cell_m * factor as f64;
    let noise = correlated_noise(
        out.width,
        out.height,
        opts.noise_scale_m / output_cell_m,
        opts.noise_rms_m,
        opts.seed,
    );
    for (h, n) in out.heights_m.iter_mut().zip(&noise) {
        *h += n;
    }
    let noise_rms_m = (noise.iter().map(|n| n * n).sum::<f64>() / noise.len().max(1) as f64).sqrt();

    let mut gt = info.to_crs.gt;
    for k in [1, 2, 4, 5] {
        gt[k] *= factor as f64;
    }
    let nd_out = nodata.unwrap_or(-32768.0);
    source::write_f32_geotiff(&opts.out, (out.width, out.height), &out.heights_m, gt, &info.srs_wkt, nd_out)?;
    Ok(DemVariantReport {
        out: opts.out.clone(),
        input_cell_m,
        output_cell_m,
        factor,
        width: out.width,
        height: out.height,
        noise_rms_m,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn block_average_of_a_plane_is_the_plane_at_block_centres() {
        let (w, h) = (10, 7);
        let plane = |x: f64, y: f64| 100.0 + 2.0 * x - 3.0 * y;
        let heights_m = (0..w * h).map(|k| plane((k % w) as f64, (k / w) as f64)).collect();
        let g = HeightGrid { width: w, height: h, heights_m };
        let a = g.block_average(3);
        assert_eq!((a.width, a.height), (4, 3));
        // Full blocks: the plane at the block's centre cell (1 + 3i, 1 + 3j).
        for j in 0..2 {
            for i in 0..3 {
                let want = plane(1.0 + 3.0 * i as f64, 1.0 + 3.0 * j as f64);
                assert!((a.heights_m[j * 4 + i] - want).abs() < 1e-9);
            }
        }
        // The last column's blocks hold one input column (x = 9).
        assert!((a.heights_m[3] - plane(9.0, 1.0)).abs() < 1e-9);
        // Missing cells are skipped; an all-missing block stays missing.
        let mut g2 = g.clone();
        g2.heights_m[0] = f64::NAN;
        let a2 = g2.block_average(3);
        let want = (1..9).map(|k| plane((k % 3) as f64, (k / 3) as f64)).sum::<f64>() / 8.0;
        assert!((a2.heights_m[0] - want).abs() < 1e-9);
        let g3 = HeightGrid { width: 2, height: 2, heights_m: vec![f64::NAN; 4] };
        assert!(g3.block_average(2).heights_m[0].is_nan());
        assert_eq!(g.block_average(1), g);
    }

    #[test]
    fn noise_has_the_stated_rms_and_correlation_length() {
        let (w, h) = (200, 160);
        let n = correlated_noise(w, h, 4.0, 3.0, 7);
        let rms = (n.iter().map(|x| x * x).sum::<f64>() / n.len() as f64).sqrt();
        assert!((rms - 3.0).abs() < 1e-9, "{rms}");
        // Autocorrelation along rows: a Gaussian-smoothed white field has
        // rho(d) = exp(-d^2 / (4 sigma^2)): 0.94 at 1 cell, 0.21 at 10 cells.
        let rho = |d: usize| {
            let mut s = 0.0;
            let mut c = 0;
            for y in 0..h {
                for x in 0..w - d {
                    s += n[y * w + x] * n[y * w + x + d];
                    c += 1;
                }
            }
            s / c as f64 / 9.0
        };
        assert!((rho(1) - (-1.0f64 / 64.0).exp()).abs() < 0.03, "rho(1) {}", rho(1));
        assert!((rho(10) - (-100.0f64 / 64.0).exp()).abs() < 0.1, "rho(10) {}", rho(10));
        // White when the scale is below a cell; seeded.
        let white = correlated_noise(w, h, 0.0, 1.0, 7);
        let r1: f64 = (0..w * h - 1).map(|k| white[k] * white[k + 1]).sum::<f64>() / (w * h) as f64;
        assert!(r1.abs() < 0.02, "{r1}");
        assert_eq!(correlated_noise(20, 10, 2.0, 1.0, 3), correlated_noise(20, 10, 2.0, 1.0, 3));
        assert_ne!(correlated_noise(20, 10, 2.0, 1.0, 3), correlated_noise(20, 10, 2.0, 1.0, 4));
        assert!(correlated_noise(20, 10, 2.0, 0.0, 3).iter().all(|v| *v == 0.0));
    }
}
