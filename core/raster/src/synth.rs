//! Synthetic orthoimages and DEMs with known content, for tests and benchmarks:
//! deterministic from a seed, written as GeoTIFF in strips (memory bounded).

use std::path::Path;

use gdal::raster::{Buffer, RasterCreationOptions};
use gdal::spatial_ref::SpatialRef;
use gdal::DriverManager;

use crate::error::{RasterError, Result};

/// Deterministic value noise with octaves (fBm) on a lattice, in [0, 1].
#[derive(Clone, Copy, Debug)]
pub struct Fbm {
    pub seed: u64,
    pub octaves: u32,
    /// Lattice spacing of the first octave (pixels).
    pub scale: f64,
}

fn hash(seed: u64, x: i64, y: i64) -> f64 {
    let mut h = seed
        ^ (x as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (y as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

impl Fbm {
    pub fn at(&self, x: f64, y: f64) -> f64 {
        let (mut amp, mut sum, mut norm, mut s) = (1.0, 0.0, 0.0, self.scale);
        for o in 0..self.octaves {
            let (fx, fy) = (x / s, y / s);
            let (ix, iy) = (fx.floor() as i64, fy.floor() as i64);
            let (tx, ty) = (fx - ix as f64, fy - iy as f64);
            // Smoothstep keeps the field continuous in its first derivative.
            let (sx, sy) = (tx * tx * (3.0 - 2.0 * tx), ty * ty * (3.0 - 2.0 * ty));
            let seed = self.seed.wrapping_add(o as u64 * 7919);
            let v = (hash(seed, ix, iy) * (1.0 - sx) + hash(seed, ix + 1, iy) * sx) * (1.0 - sy)
                + (hash(seed, ix, iy + 1) * (1.0 - sx) + hash(seed, ix + 1, iy + 1) * sx) * sy;
            sum += amp * v;
            norm += amp;
            amp *= 0.55;
            s *= 0.5;
        }
        sum / norm
    }
}

/// Georeferencing of a synthetic raster.
#[derive(Clone, Debug)]
pub struct SynthGrid {
    pub epsg: u32,
    /// GDAL geotransform.
    pub geo_transform: [f64; 6],
    pub width: usize,
    pub height: usize,
}

/// How a synthetic GeoTIFF is compressed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Compression {
    /// Lossless DEFLATE tiles.
    Deflate,
    /// JPEG in YCbCr, quality 90: how USGS NAIP orthoimagery is distributed.
    Jpeg,
}

/// An ortho: field patchwork with texture and roads, as RGB (or grey) bytes,
/// tiled and compressed like a cloud-optimised USGS product.
pub fn write_ortho(
    path: &Path,
    grid: &SynthGrid,
    bands: usize,
    seed: u64,
    nodata_border: usize,
    compression: Compression,
) -> Result<()> {
    let fields = Fbm { seed, octaves: 2, scale: 180.0 };
    let texture = Fbm { seed: seed + 1, octaves: 5, scale: 24.0 };
    let tint = Fbm { seed: seed + 2, octaves: 2, scale: 400.0 };
    let nodata = (nodata_border > 0).then_some(0.0);
    write_raster::<u8>(path, grid, bands, nodata, compression, |x, y, b| {
        if x < nodata_border
            || y < nodata_border
            || x + nodata_border >= grid.width
            || y + nodata_border >= grid.height
        {
            return 0;
        }
        let (xf, yf) = (x as f64, y as f64);
        // Fields: quantised low-frequency noise; roads: thin lines on a 97/131 px grid.
        let field = (fields.at(xf, yf) * 6.0).floor() / 6.0;
        let road = (x % 131 < 2) || (y % 97 < 2) || ((x + y) % 211 < 2);
        let v = if road { 0.9 } else { 0.25 + 0.45 * field + 0.35 * (texture.at(xf, yf) - 0.5) };
        let t = tint.at(xf, yf);
        let c = match b {
            0 => v * (0.9 + 0.2 * t),
            1 => v,
            _ => v * (1.1 - 0.2 * t),
        };
        (c * 230.0 + 12.0).clamp(1.0, 255.0) as u8
    })
}

/// A DEM: rolling fBm hills, heights in metres, Float32.
/// A synthetic scene as `trn synth` writes it: a `size x size` RGB ortho of
/// `gsd_m` pixels in UTM 13N (EPSG:32613) from (`east_m`, `north_m`), and a
/// DEM of 15 ortho pixels per cell over the same area with a two-cell margin,
/// heights 1500 m plus up to `relief_m` of hills (ellipsoidal).
#[derive(Clone, Copy, Debug)]
pub struct SynthScene {
    pub size: usize,
    pub gsd_m: f64,
    pub east_m: f64,
    pub north_m: f64,
    pub seed: u64,
    pub relief_m: f64,
    /// Nodata pixels around the ortho's edge.
    pub nodata_border: usize,
    pub compression: Compression,
}

impl SynthScene {
    /// Checks the scene, naming the `trn synth` option at fault.
    pub fn check(&self) -> Result<()> {
        let bad = |option, reason: &str| Err(RasterError::Option { option, reason: reason.into() });
        if !(self.relief_m.is_finite() && self.relief_m >= 0.0) {
            return bad("--relief", "must be a number of metres >= 0");
        }
        if !(self.gsd_m.is_finite() && self.gsd_m > 0.0) {
            return bad("--gsd", "must be metres > 0");
        }
        if self.size == 0 {
            return bad("--size", "must be at least 1 pixel");
        }
        Ok(())
    }

    /// Writes the ortho and the DEM (checked first).
    pub fn write(&self, ortho: &Path, dem: &Path) -> Result<()> {
        self.check()?;
        let (e, n, gsd) = (self.east_m, self.north_m, self.gsd_m);
        let grid = SynthGrid {
            epsg: 32613,
            geo_transform: [e, gsd, 0.0, n, 0.0, -gsd],
            width: self.size,
            height: self.size,
        };
        write_ortho(ortho, &grid, 3, self.seed, self.nodata_border, self.compression)?;
        let dem_gsd = gsd * 15.0;
        let cells = (self.size as f64 * gsd / dem_gsd).ceil() as usize + 4;
        let dem_grid = SynthGrid {
            epsg: 32613,
            geo_transform: [e - 2.0 * dem_gsd, dem_gsd, 0.0, n + 2.0 * dem_gsd, 0.0, -dem_gsd],
            width: cells,
            height: cells,
        };
        write_dem(dem, &dem_grid, self.seed + 100, 1500.0, self.relief_m)
    }
}

pub fn write_dem(path: &Path, grid: &SynthGrid, seed: u64, base_m: f64, relief_m: f64) -> Result<()> {
    let hills = Fbm { seed, octaves: 4, scale: 64.0 };
    write_raster::<f32>(path, grid, 1, Some(-9999.0), Compression::Deflate, |x, y, _| {
        (base_m + relief_m * hills.at(x as f64, y as f64)) as f32
    })
}

fn write_raster<T: gdal::raster::GdalType + Copy + Default + Send>(
    path: &Path,
    grid: &SynthGrid,
    bands: usize,
    nodata: Option<f64>,
    compression: Compression,
    value: impl Fn(usize, usize, usize) -> T + Sync,
) -> Result<()> {
    use rayon::prelude::*;
    let err = |e: gdal::errors::GdalError| RasterError::Read { path: path.into(), reason: e.to_string() };
    let driver = DriverManager::get_driver_by_name("GTiff").map_err(err)?;
    let mut opts = RasterCreationOptions::new();
    let mut pairs =
        vec![("TILED", "YES"), ("BLOCKXSIZE", "512"), ("BLOCKYSIZE", "512"), ("BIGTIFF", "IF_SAFER")];
    match compression {
        Compression::Deflate => pairs.extend([("COMPRESS", "DEFLATE"), ("INTERLEAVE", "PIXEL")]),
        Compression::Jpeg if bands == 3 => {
            pairs.extend([("COMPRESS", "JPEG"), ("PHOTOMETRIC", "YCBCR"), ("JPEG_QUALITY", "90")])
        }
        Compression::Jpeg => pairs.extend([("COMPRESS", "JPEG"), ("JPEG_QUALITY", "90")]),
    }
    for (k, v) in pairs {
        opts.set_name_value(k, v).map_err(err)?;
    }
    let mut ds = driver
        .create_with_band_type_with_options::<T, _>(path, grid.width, grid.height, bands, &opts)
        .map_err(err)?;
    ds.set_geo_transform(&grid.geo_transform).map_err(err)?;
    ds.set_spatial_ref(&SpatialRef::from_epsg(grid.epsg).map_err(err)?).map_err(err)?;
    for b in 1..=bands {
        if let (Some(nd), Ok(mut band)) = (nodata, ds.rasterband(b)) {
            band.set_no_data_value(Some(nd)).map_err(err)?;
        }
    }
    // Whole block rows, all bands of a strip together: JPEG tiles are written once.
    let strip = 512;
    let mut y0 = 0;
    while y0 < grid.height {
        let rows = strip.min(grid.height - y0);
        for b in 0..bands {
            let data: Vec<T> = (0..rows * grid.width)
                .into_par_iter()
                .map(|i| value(i % grid.width, y0 + i / grid.width, b))
                .collect();
            let mut buf = Buffer::new((grid.width, rows), data);
            ds.rasterband(b + 1)
                .map_err(err)?
                .write((0, y0 as isize), (grid.width, rows), &mut buf)
                .map_err(err)?;
        }
        y0 += rows;
    }
    ds.close().map_err(err)?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_bad_scene_is_named_and_nothing_is_written() {
        let good = SynthScene {
            size: 64,
            gsd_m: 2.0,
            east_m: 440_000.0,
            north_m: 4_460_000.0,
            seed: 1,
            relief_m: 60.0,
            nodata_border: 0,
            compression: Compression::Deflate,
        };
        assert!(good.check().is_ok());
        let dir = std::env::temp_dir().join(format!("trn-synth-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let (ortho, dem) = (dir.join("o.tif"), dir.join("d.tif"));
        for (bad, option) in [
            (SynthScene { relief_m: -5.0, ..good }, "--relief"),
            (SynthScene { relief_m: f64::NAN, ..good }, "--relief"),
            (SynthScene { gsd_m: 0.0, ..good }, "--gsd"),
            (SynthScene { gsd_m: f64::INFINITY, ..good }, "--gsd"),
            (SynthScene { size: 0, ..good }, "--size"),
        ] {
            let e = bad.write(&ortho, &dem).unwrap_err();
            assert!(e.to_string().contains(option), "{e}");
            assert!(!ortho.exists() && !dem.exists());
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
