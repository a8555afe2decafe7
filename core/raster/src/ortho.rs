//! Level 0 of a luminance pyramid: an ortho (or a VRT mosaic) read through
//! GDAL in windows of luminance with validity, and the GDAL block cache it
//! needs.

use std::cell::RefCell;
use std::path::{Path, PathBuf};

use gdal::Dataset;

use crate::error::{RasterError, Result};
use crate::source::Luminance;

/// A window of luminance (0..255) with validity, row-major.
#[derive(Default)]
pub struct Window {
    /// Top-left pixel of the window in the level's pixel grid (may be negative).
    pub x0: isize,
    pub y0: isize,
    pub width: usize,
    pub height: usize,
    pub lum: Vec<f32>,
    pub valid: Vec<u8>,
}

impl Window {
    /// Places and sizes the window, keeping its buffers (contents unspecified).
    pub fn reset(&mut self, x0: isize, y0: isize, width: usize, height: usize) {
        (self.x0, self.y0, self.width, self.height) = (x0, y0, width, height);
        self.lum.resize(width * height, 0.0);
        self.valid.resize(width * height, 0);
    }
}

/// Level 0: reads an ortho (or a VRT mosaic) through GDAL.
pub struct OrthoReader {
    path: PathBuf,
    ds: Dataset,
    lum: Luminance,
    nodata: Vec<Option<f64>>,
    /// Read the mask band of band 1 (alpha, per-dataset mask).
    use_mask: bool,
    width: usize,
    height: usize,
    scratch: RefCell<Scratch>,
    /// All luminance bands are 8-bit.
    byte_data: bool,
}

impl OrthoReader {
    pub fn open(path: &Path, lum: &Luminance) -> Result<Self> {
        let ds = crate::source::open(path)?;
        let (width, height) = ds.raster_size();
        let rerr = |e: gdal::errors::GdalError| RasterError::Read {
            path: path.into(),
            reason: crate::source::gdal_reason(&e, path),
        };
        let mut nodata = Vec::new();
        for &(b, _) in &lum.bands {
            nodata.push(ds.rasterband(b).map_err(rerr)?.no_data_value());
        }
        let flags = ds.rasterband(lum.bands[0].0).map_err(rerr)?.mask_flags().map_err(rerr)?;
        let use_mask = !flags.is_all_valid() && !flags.is_nodata();
        let mut byte_data = true;
        for &(b, _) in &lum.bands {
            byte_data &= ds.rasterband(b).map_err(rerr)?.band_type() == gdal::raster::GdalDataType::UInt8;
        }
        Ok(Self {
            path: path.into(),
            ds,
            lum: lum.clone(),
            nodata,
            use_mask,
            width,
            height,
            scratch: RefCell::new(Scratch::default()),
            byte_data,
        })
    }

    /// Reads a window; pixels outside the raster are invalid.
    pub fn read(&self, x0: isize, y0: isize, width: usize, height: usize) -> Result<Window> {
        let mut win = Window::default();
        self.read_into(x0, y0, width, height, &mut win)?;
        Ok(win)
    }

    /// [`Self::read`] into a window whose buffers are reused (no allocation, no
    /// fresh pages per tile).
    pub fn read_into(
        &self,
        x0: isize,
        y0: isize,
        width: usize,
        height: usize,
        win: &mut Window,
    ) -> Result<()> {
        win.reset(x0, y0, width, height);
        let (rx0, ry0) = (x0.max(0), y0.max(0));
        let rx1 = (x0 + width as isize).min(self.width as isize);
        let ry1 = (y0 + height as isize).min(self.height as isize);
        if rx1 <= rx0 || ry1 <= ry0 {
            win.lum.fill(0.0);
            win.valid.fill(0);
            return Ok(());
        }
        let (rw, rh) = ((rx1 - rx0) as usize, (ry1 - ry0) as usize);
        if rw != width || rh != height {
            // Part of the window is outside the raster: invalid there.
            win.lum.fill(0.0);
            win.valid.fill(0);
        }
        let rerr = |e: gdal::errors::GdalError| RasterError::Read {
            path: self.path.clone(),
            reason: crate::source::gdal_reason(&e, &self.path),
        };
        // Scratch buffers live with the reader: no allocation and no zeroing per tile.
        let mut scratch = self.scratch.borrow_mut();
        let Scratch { acc, ok, band_buf, byte_bufs, mask_buf } = &mut *scratch;
        let n = rw * rh;
        if self.use_mask {
            let band = self.ds.rasterband(self.lum.bands[0].0).map_err(rerr)?;
            let mask = band.open_mask_band().map_err(rerr)?;
            mask_buf.resize(n, 0);
            mask.read_into_slice::<u8>((rx0, ry0), (rw, rh), (rw, rh), mask_buf, None).map_err(rerr)?;
        }
        let (off, sc) = (self.lum.offset, self.lum.scale);
        let to_lum = |v: f32| ((v - off) * sc).clamp(0.0, 255.0);
        let dst0 = (ry0 - y0) as usize * width + (rx0 - x0) as usize;
        let nb = self.lum.bands.len();
        if self.byte_data && (nb == 1 || nb == 3) {
            // 8-bit bands are read as bytes (a quarter of GDAL's copying) and
            // turned into luminance and validity in one pass, straight into the
            // window. The arithmetic is the general path's, in its order.
            byte_bufs.resize_with(nb, Vec::new);
            for (buf, &(b, _)) in byte_bufs.iter_mut().zip(&self.lum.bands) {
                let band = self.ds.rasterband(b).map_err(rerr)?;
                buf.resize(n, 0);
                band.read_into_slice::<u8>((rx0, ry0), (rw, rh), (rw, rh), buf, None).map_err(rerr)?;
            }
            // No nodata: NAN, which no byte equals.
            let nd: Vec<f32> = self.nodata.iter().map(|v| v.map(|v| v as f32).unwrap_or(f32::NAN)).collect();
            let wg: Vec<f32> = self.lum.bands.iter().map(|b| b.1).collect();
            for r in 0..rh {
                let d = dst0 + r * width;
                let (lrow, vrow) = (&mut win.lum[d..d + rw], &mut win.valid[d..d + rw]);
                let src = r * rw..(r + 1) * rw;
                if nb == 1 {
                    let b0 = &byte_bufs[0][src];
                    for ((l, o), &v0) in lrow.iter_mut().zip(vrow.iter_mut()).zip(b0) {
                        let v0 = v0 as f32;
                        *l = to_lum(wg[0] * v0);
                        *o = u8::from(v0 != nd[0]);
                    }
                } else {
                    let (b0, b1, b2) =
                        (&byte_bufs[0][src.clone()], &byte_bufs[1][src.clone()], &byte_bufs[2][src]);
                    let (w0, w1, w2) = (wg[0], wg[1], wg[2]);
                    let (n0, n1, n2) = (nd[0], nd[1], nd[2]);
                    for ((l, o), ((&v0, &v1), &v2)) in
                        lrow.iter_mut().zip(vrow.iter_mut()).zip(b0.iter().zip(b1).zip(b2))
                    {
                        let (v0, v1, v2) = (v0 as f32, v1 as f32, v2 as f32);
                        let mut a = w0 * v0;
                        a += w1 * v1;
                        a += w2 * v2;
                        *l = to_lum(a);
                        *o = u8::from(v0 != n0) & u8::from(v1 != n1) & u8::from(v2 != n2);
                    }
                }
                if self.use_mask {
                    for (o, &m) in vrow.iter_mut().zip(&mask_buf[r * rw..(r + 1) * rw]) {
                        if m == 0 {
                            *o = 0;
                        }
                    }
                }
            }
            return Ok(());
        }
        for v in [&mut *acc, &mut *band_buf] {
            v.resize(n, 0.0);
        }
        ok.resize(n, 0);
        for (k, &(b, wgt)) in self.lum.bands.iter().enumerate() {
            let band = self.ds.rasterband(b).map_err(rerr)?;
            if self.byte_data {
                byte_bufs.resize_with(1, Vec::new);
                let byte_buf = &mut byte_bufs[0];
                byte_buf.resize(n, 0);
                band.read_into_slice::<u8>((rx0, ry0), (rw, rh), (rw, rh), byte_buf, None).map_err(rerr)?;
                for (d, &v) in band_buf.iter_mut().zip(byte_buf.iter()) {
                    *d = v as f32;
                }
            } else {
                band.read_into_slice::<f32>((rx0, ry0), (rw, rh), (rw, rh), band_buf, None).map_err(rerr)?;
            }
            let nd = self.nodata[k].map(|v| v as f32);
            if k == 0 {
                for ((a, o), &v) in acc.iter_mut().zip(ok.iter_mut()).zip(band_buf.iter()) {
                    *a = wgt * v;
                    *o = u8::from(!(Some(v) == nd || v.is_nan()));
                }
            } else {
                for ((a, o), &v) in acc.iter_mut().zip(ok.iter_mut()).zip(band_buf.iter()) {
                    *a += wgt * v;
                    if Some(v) == nd || v.is_nan() {
                        *o = 0;
                    }
                }
            }
        }
        if self.use_mask {
            for (o, &v) in ok.iter_mut().zip(mask_buf.iter()) {
                if v == 0 {
                    *o = 0;
                }
            }
        }
        for r in 0..rh {
            let d = dst0 + r * width;
            for (l, &v) in win.lum[d..d + rw].iter_mut().zip(&acc[r * rw..(r + 1) * rw]) {
                *l = to_lum(v);
            }
            win.valid[d..d + rw].copy_from_slice(&ok[r * rw..(r + 1) * rw]);
        }
        Ok(())
    }
}

/// GDAL block cache that level 0 needs so that no ortho block is decoded twice:
/// per worker (each has its own dataset), the block rows under one row of
/// tile windows of `window_h` rows plus the next, across the full width, for
/// every band (a pixel-interleaved file caches all bands when one is read).
/// `None` when the file cannot be opened (reading reports that later).
pub fn ortho_cache_bytes(path: &Path, window_h: usize, workers: usize) -> Option<usize> {
    let ds = crate::source::open(path).ok()?;
    let (width, _) = ds.raster_size();
    let mut bytes_per_px = 0usize;
    let mut block_h = 1usize;
    for b in 1..=ds.raster_count() {
        let band = ds.rasterband(b).ok()?;
        bytes_per_px += band.band_type().bytes() as usize;
        block_h = block_h.max(band.block_size().1);
    }
    let rows = (window_h.div_ceil(block_h) + 2) * block_h;
    Some(workers.max(1) * rows * width * bytes_per_px)
}

/// Lowers GDAL's block cache for the life of the guard (and restores it), unless
/// the user set `GDAL_CACHEMAX`. GDAL's default (5% of memory) would keep every
/// decoded block of an ortho: hundreds of megabytes of fresh pages, each
/// faulted in and zeroed by the kernel, where a few block rows are ever reused.
pub struct CacheLimit(Option<i64>);

impl CacheLimit {
    pub fn new(bytes: usize) -> Self {
        let user_set = gdal::config::get_config_option("GDAL_CACHEMAX", "").map(|v| !v.is_empty());
        if user_set.unwrap_or(true) {
            return Self(None);
        }
        // At least 32 MB: the DEM and small rasters share the cache.
        let want = bytes.max(32 << 20) as i64;
        // SAFETY: plain getters/setters of GDAL's global cache size.
        let before = unsafe { gdal_sys::GDALGetCacheMax64() };
        if want >= before {
            return Self(None);
        }
        unsafe { gdal_sys::GDALSetCacheMax64(want) };
        Self(Some(before))
    }
}

impl Drop for CacheLimit {
    fn drop(&mut self) {
        if let Some(before) = self.0 {
            // SAFETY: as above.
            unsafe { gdal_sys::GDALSetCacheMax64(before) };
        }
    }
}

/// Reusable buffers of one reader.
#[derive(Default)]
struct Scratch {
    acc: Vec<f32>,
    ok: Vec<u8>,
    band_buf: Vec<f32>,
    /// One per band on the fused 8-bit path.
    byte_bufs: Vec<Vec<u8>>,
    mask_buf: Vec<u8>,
}
