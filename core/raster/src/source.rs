//! Input rasters: opening and checking them, their footprints on WGS84, how an
//! ortho's bands become luminance, and what vertical datum a DEM uses.

use std::path::{Path, PathBuf};

use gdal::errors::GdalError;
use gdal::raster::GdalDataType;
use gdal::spatial_ref::{AxisMappingStrategy, CoordTransform, SpatialRef};
use gdal::Dataset;
use trn_geodesy::metres_per_degree;
use trn_landmark::GeoBox;

use crate::error::{RasterError, Result};

/// GDAL's affine pixel -> CRS transform; (0, 0) is the top-left corner of the top-left pixel.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PixelToCrs {
    pub gt: [f64; 6],
}

impl PixelToCrs {
    /// CRS coordinates of pixel-grid position (col, row) (corner convention).
    pub fn apply(&self, col: f64, row: f64) -> (f64, f64) {
        let g = &self.gt;
        (g[0] + col * g[1] + row * g[2], g[3] + col * g[4] + row * g[5])
    }

    /// Inverse: CRS coordinates to pixel-grid position (corner convention).
    pub fn invert(&self, x: f64, y: f64) -> (f64, f64) {
        let g = &self.gt;
        let det = g[1] * g[5] - g[2] * g[4];
        let (dx, dy) = (x - g[0], y - g[3]);
        ((dx * g[5] - dy * g[2]) / det, (dy * g[1] - dx * g[4]) / det)
    }
}

/// An opened, checked raster (ortho or DEM).
#[derive(Clone, Debug)]
pub struct RasterInfo {
    pub path: PathBuf,
    pub width: usize,
    pub height: usize,
    pub band_count: usize,
    pub band_type: String,
    pub to_crs: PixelToCrs,
    pub srs_wkt: String,
    /// Footprint on WGS84 (densified edges).
    pub extent: GeoBox,
    /// Pixel size on the ground (m) at the raster's centre, along columns and rows.
    pub pixel_dx_m: f64,
    pub pixel_dy_m: f64,
}

/// A transformation between a raster's CRS and WGS84 longitude/latitude
/// (degrees, in that order), either way. Holds a GDAL transformation: one
/// thread uses it at a time.
pub struct Wgs84Transform(CoordTransform);

impl Wgs84Transform {
    /// From the CRS of the raster at `path` to WGS84.
    pub fn to_wgs84(path: &Path) -> Result<Self> {
        Self::between(path, true)
    }

    /// From WGS84 to the CRS of the raster at `path`.
    pub fn from_wgs84(path: &Path) -> Result<Self> {
        Self::between(path, false)
    }

    fn between(path: &Path, to_wgs84: bool) -> Result<Self> {
        let ds = open(path)?;
        let (crs, wgs) = (srs_of(&ds, path)?, wgs84());
        let (from, to) = if to_wgs84 { (&crs, &wgs) } else { (&wgs, &crs) };
        CoordTransform::new(from, to)
            .map(Self)
            .map_err(|e| RasterError::BadRaster { path: path.into(), reason: gdal_reason(&e, path) })
    }

    /// Transforms the points `(xs, ys)` in place; `None` when one does not
    /// transform.
    pub fn apply(&self, xs: &mut [f64], ys: &mut [f64]) -> Option<()> {
        let mut zs = vec![0.0; xs.len()];
        self.0.transform_coords(xs, ys, &mut zs).ok()
    }
}

/// Band 1 of a raster in full, as f64 with nodata and non-finite values NaN,
/// and the grid it lies on.
pub struct Band1 {
    pub info: RasterInfo,
    /// Row-major, `info.width * info.height`.
    pub values: Vec<f64>,
    pub nodata: Option<f64>,
}

/// Reads band 1 of the raster at `path` in full (see [`Band1`]).
pub fn read_band1(path: &Path) -> Result<Band1> {
    let (ds, info) = inspect(path)?;
    let read = |e: GdalError| RasterError::Read { path: path.into(), reason: gdal_reason(&e, path) };
    let band = ds.rasterband(1).map_err(read)?;
    let nodata = band.no_data_value();
    let buf = band
        .read_as::<f64>((0, 0), (info.width, info.height), (info.width, info.height), None)
        .map_err(read)?;
    let values = buf
        .data()
        .iter()
        .map(|&v| if nodata.is_some_and(|nd| v == nd) || !v.is_finite() { f64::NAN } else { v })
        .collect();
    Ok(Band1 { info, values, nodata })
}

/// Writes a one-band f32 GeoTIFF (tiled, DEFLATE) at `out` atomically (a
/// temporary file next to it, renamed on success): `values` row-major, NaN
/// written as `nodata`, on the grid of geotransform `gt` in the CRS `wkt`.
pub fn write_f32_geotiff(
    out: &Path,
    (width, height): (usize, usize),
    values: &[f64],
    gt: [f64; 6],
    wkt: &str,
    nodata: f64,
) -> Result<()> {
    let err = |reason: String| RasterError::Write { path: out.into(), reason };
    let parent = out.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    let tmp = tempfile::Builder::new()
        .prefix(".trn-raster-")
        .suffix(".tif")
        .tempfile_in(parent)
        .map_err(|e| err(e.to_string()))?;
    {
        let driver = gdal::DriverManager::get_driver_by_name("GTiff").map_err(|e| err(e.to_string()))?;
        let mut opts = gdal::raster::RasterCreationOptions::new();
        for (k, v) in [("COMPRESS", "DEFLATE"), ("PREDICTOR", "3"), ("TILED", "YES")] {
            opts.set_name_value(k, v).map_err(|e| err(e.to_string()))?;
        }
        let mut ds = driver
            .create_with_band_type_with_options::<f32, _>(tmp.path(), width, height, 1, &opts)
            .map_err(|e| err(e.to_string()))?;
        ds.set_geo_transform(&gt).map_err(|e| err(e.to_string()))?;
        ds.set_projection(wkt).map_err(|e| err(e.to_string()))?;
        let mut band = ds.rasterband(1).map_err(|e| err(e.to_string()))?;
        band.set_no_data_value(Some(nodata)).map_err(|e| err(e.to_string()))?;
        let data: Vec<f32> =
            values.iter().map(|&v| if v.is_finite() { v as f32 } else { nodata as f32 }).collect();
        let mut buf = gdal::raster::Buffer::new((width, height), data);
        band.write((0, 0), (width, height), &mut buf).map_err(|e| err(e.to_string()))?;
        ds.close().map_err(|e| err(e.to_string()))?;
    }
    tmp.persist(out).map_err(|e| err(e.error.to_string()))?;
    Ok(())
}

/// Writes a VRT at `out` reading the rasters `paths` as one mosaic
/// (`gdalbuildvrt`); an error names `blame` (the user's file) and says
/// `what` was being mosaicked.
pub fn build_vrt(out: &Path, paths: &[PathBuf], blame: &Path, what: &str) -> Result<()> {
    let dss = paths.iter().map(|p| open(p)).collect::<Result<Vec<_>>>()?;
    gdal::programs::raster::build_vrt(Some(out), &dss, None).map(|_| ()).map_err(|e| RasterError::Read {
        path: blame.into(),
        reason: format!("cannot mosaic {what}: {}", gdal_reason(&e, blame)),
    })
}

pub fn wgs84() -> SpatialRef {
    let mut srs = SpatialRef::from_epsg(4326).expect("EPSG:4326 is in every PROJ database");
    srs.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
    srs
}

pub fn open(path: &Path) -> Result<Dataset> {
    if !path.exists() {
        return Err(RasterError::Open { path: path.into(), reason: "no such file".into() });
    }
    quietly(|| Dataset::open(path)).map_err(|e| {
        let reason = match &e {
            // GDAL says nothing when no driver recognises the file.
            GdalError::NullPointer { msg, .. } if msg.is_empty() => {
                "not a raster GDAL can read (unknown format, or a damaged header)".into()
            }
            _ => gdal_reason(&e, path),
        };
        RasterError::Open { path: path.into(), reason }
    })
}

/// GDAL's own message from an error, on one line, without a leading copy of
/// `path` (the errors name it already).
pub fn gdal_reason(e: &GdalError, path: &Path) -> String {
    let msg = match e {
        GdalError::CplError { msg, .. } | GdalError::NullPointer { msg, .. } if !msg.is_empty() => {
            msg.clone()
        }
        other => other.to_string(),
    };
    let msg = msg.split_whitespace().collect::<Vec<_>>().join(" ");
    let p = path.display().to_string();
    match msg.strip_prefix(&p) {
        Some(rest) => rest.trim_start_matches([',', ':', ' ']).to_string(),
        None => msg,
    }
}

/// GDAL messages while a raster is checked go to the debug log, not stderr:
/// what matters reaches the user as the build's one error line.
unsafe extern "C" fn gdal_to_log(
    class: gdal_sys::CPLErr::Type,
    no: std::ffi::c_int,
    msg: *const std::ffi::c_char,
) {
    if !msg.is_null() {
        // SAFETY: GDAL passes a NUL-terminated message, valid during the call.
        let msg = unsafe { std::ffi::CStr::from_ptr(msg) }.to_string_lossy();
        tracing::debug!("GDAL ({class}/{no}): {msg}");
    }
}

/// Runs `f` with this thread's GDAL messages sent to the debug log. GDAL still
/// records the last error, so `gdal` results carry the message.
fn quietly<T>(f: impl FnOnce() -> T) -> T {
    struct Pop;
    impl Drop for Pop {
        fn drop(&mut self) {
            // SAFETY: pops the handler pushed below, on the same thread.
            unsafe { gdal_sys::CPLPopErrorHandler() };
        }
    }
    // SAFETY: GDAL keeps a per-thread stack of handlers; `gdal_to_log` only reads `msg`.
    unsafe { gdal_sys::CPLPushErrorHandler(Some(gdal_to_log)) };
    let _pop = Pop;
    f()
}

pub fn srs_of(ds: &Dataset, path: &Path) -> Result<SpatialRef> {
    let mut srs = ds.spatial_ref().map_err(|_| RasterError::NoGeoreference { path: path.into() })?;
    if srs.to_wkt().map(|w| w.is_empty()).unwrap_or(true) {
        return Err(RasterError::NoGeoreference { path: path.into() });
    }
    srs.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
    Ok(srs)
}

/// Opens a raster and checks georeferencing, computing its WGS84 footprint.
pub fn inspect(path: &Path) -> Result<(Dataset, RasterInfo)> {
    let ds = open(path)?;
    let (width, height) = ds.raster_size();
    if width == 0 || height == 0 || ds.raster_count() == 0 {
        return Err(RasterError::BadRaster {
            path: path.into(),
            reason: "raster has no pixels or no bands".into(),
        });
    }
    let gt = ds.geo_transform().map_err(|_| RasterError::NoGeoreference { path: path.into() })?;
    if gt == [0.0, 1.0, 0.0, 0.0, 0.0, 1.0] {
        return Err(RasterError::NoGeoreference { path: path.into() });
    }
    let srs = srs_of(&ds, path)?;
    let to_wgs = CoordTransform::new(&srs, &wgs84())
        .map_err(|e| RasterError::BadRaster { path: path.into(), reason: format!("CRS not usable: {e}") })?;
    let to_crs = PixelToCrs { gt };
    // Densified outline: UTM edges are curved in lat/lon.
    let n = 32;
    let mut xs = Vec::new();
    let mut ys = Vec::new();
    for i in 0..=n {
        let f = i as f64 / n as f64;
        for (c, r) in [
            (f * width as f64, 0.0),
            (f * width as f64, height as f64),
            (0.0, f * height as f64),
            (width as f64, f * height as f64),
        ] {
            let (x, y) = to_crs.apply(c, r);
            xs.push(x);
            ys.push(y);
        }
    }
    let mut zs = vec![0.0; xs.len()];
    to_wgs.transform_coords(&mut xs, &mut ys, &mut zs).map_err(|e| RasterError::BadRaster {
        path: path.into(),
        reason: format!("cannot transform to WGS84: {e}"),
    })?;
    let extent = GeoBox::around(xs.iter().copied().zip(ys.iter().copied()))
        .ok_or_else(|| RasterError::BadRaster { path: path.into(), reason: "empty outline".into() })?;
    if !(extent.min_lat_deg >= -90.0 && extent.max_lat_deg <= 90.0 && extent.min_lon_deg >= -360.0) {
        return Err(RasterError::BadRaster {
            path: path.into(),
            reason: format!("footprint out of range: {extent:?}"),
        });
    }
    // Ground pixel size at the centre, from the transform of a one-pixel step.
    let (cc, cr) = (width as f64 / 2.0, height as f64 / 2.0);
    let pts = [to_crs.apply(cc, cr), to_crs.apply(cc + 1.0, cr), to_crs.apply(cc, cr + 1.0)];
    let mut px: Vec<f64> = pts.iter().map(|p| p.0).collect();
    let mut py: Vec<f64> = pts.iter().map(|p| p.1).collect();
    let mut pz = vec![0.0; 3];
    to_wgs.transform_coords(&mut px, &mut py, &mut pz).map_err(|e| RasterError::BadRaster {
        path: path.into(),
        reason: format!("cannot transform to WGS84: {e}"),
    })?;
    let (m_lat, m_lon) = metres_per_degree(py[0]);
    let step = |i: usize| ((px[i] - px[0]) * m_lon).hypot((py[i] - py[0]) * m_lat);
    let (pixel_dx_m, pixel_dy_m) = (step(1), step(2));
    let band_type = ds.rasterband(1).map(|b| b.band_type().name()).unwrap_or_default();
    let info = RasterInfo {
        path: path.into(),
        width,
        height,
        band_count: ds.raster_count(),
        band_type,
        to_crs,
        srs_wkt: srs.to_wkt().unwrap_or_default(),
        extent,
        pixel_dx_m,
        pixel_dy_m,
    };
    Ok((ds, info))
}

/// Writes `out`: a GDAL warped VRT of `srcs` (rasters in one CRS) on the
/// pixel grid of `onto`: its CRS, pixel size and grid lines, over the
/// sources' outline in that CRS snapped outward to the grid, bilinear. Alpha
/// bands and nodata values carry over; a source with neither gets nodata 0
/// outside its footprint. Nothing is read until the VRT is.
pub fn warp_onto_grid(srcs: &[RasterInfo], onto: &RasterInfo, out: &Path) -> Result<()> {
    let g = onto.to_crs.gt;
    let first = &srcs[0].path;
    let bad = |reason: String| RasterError::Read { path: first.clone(), reason };
    // Geotransforms are in x = easting/longitude order whatever the CRS's axes.
    let gis = |wkt: &str, path: &Path| {
        let mut srs =
            SpatialRef::from_wkt(wkt).map_err(|e| bad(format!("CRS of {}: {e}", path.display())))?;
        srs.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
        Ok::<_, RasterError>(srs)
    };
    let to = gis(&onto.srs_wkt, &onto.path)?;
    let (mut xmin, mut ymin, mut xmax, mut ymax) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
    for s in srcs {
        let from = gis(&s.srs_wkt, &s.path)?;
        let t = CoordTransform::new(&from, &to).map_err(|e| bad(format!("cannot reproject: {e}")))?;
        let (x0, y0) = s.to_crs.apply(0.0, 0.0);
        let (x1, y1) = s.to_crs.apply(s.width as f64, s.height as f64);
        let b = t
            .transform_bounds(&[x0.min(x1), y0.min(y1), x0.max(x1), y0.max(y1)], 21)
            .map_err(|e| bad(format!("cannot reproject the outline: {e}")))?;
        (xmin, ymin, xmax, ymax) = (xmin.min(b[0]), ymin.min(b[1]), xmax.max(b[2]), ymax.max(b[3]));
    }
    // Snapped outward to `onto`'s grid lines (no rotation: checked by the caller).
    let (c0, c1) = (((xmin - g[0]) / g[1]).floor(), ((xmax - g[0]) / g[1]).ceil());
    let (r0, r1) = if g[5] < 0.0 {
        (((ymax - g[3]) / g[5]).floor(), ((ymin - g[3]) / g[5]).ceil())
    } else {
        (((ymin - g[3]) / g[5]).floor(), ((ymax - g[3]) / g[5]).ceil())
    };
    let (ex0, ex1) = (g[0] + c0 * g[1], g[0] + c1 * g[1]);
    let (ey0, ey1) = (g[3] + r0 * g[5], g[3] + r1 * g[5]);
    let dss = srcs.iter().map(|s| open(&s.path)).collect::<Result<Vec<_>>>()?;
    let band = dss[0].rasterband(1).map_err(|e| bad(gdal_reason(&e, first)))?;
    let masked = band.no_data_value().is_some()
        || (1..=dss[0].raster_count()).any(|b| {
            dss[0]
                .rasterband(b)
                .is_ok_and(|x| x.color_interpretation() == gdal::raster::ColorInterpretation::AlphaBand)
        });
    let mut args: Vec<String> = vec!["-of".into(), "VRT".into(), "-t_srs".into(), onto.srs_wkt.clone()];
    args.push("-te".into());
    args.extend([ex0.min(ex1), ey0.min(ey1), ex0.max(ex1), ey0.max(ey1)].map(|v| format!("{v:.9}")));
    args.push("-tr".into());
    args.extend([g[1].abs(), g[5].abs()].map(|v| format!("{v:.12}")));
    args.extend(["-r", "bilinear"].map(String::from));
    if !masked {
        args.extend(["-dstnodata", "0"].map(String::from));
    }
    let c_args: Vec<std::ffi::CString> = args
        .iter()
        .map(|a| std::ffi::CString::new(a.as_str()).map_err(|_| bad("a CRS with a NUL byte".into())))
        .collect::<Result<_>>()?;
    let mut argv: Vec<*mut std::ffi::c_char> = c_args.iter().map(|a| a.as_ptr() as *mut _).collect();
    argv.push(std::ptr::null_mut());
    let dest = std::ffi::CString::new(out.to_string_lossy().as_bytes())
        .map_err(|_| bad("a path with a NUL byte".into()))?;
    let mut handles: Vec<gdal_sys::GDALDatasetH> = dss.iter().map(|d| d.c_dataset()).collect();
    // SAFETY: argv is a NULL-terminated list of C strings that outlive the
    // call (GDAL copies them); the handles are open datasets kept alive by
    // `dss`; the returned dataset is closed here and its options freed.
    let ok = quietly(|| unsafe {
        let opts = gdal_sys::GDALWarpAppOptionsNew(argv.as_mut_ptr(), std::ptr::null_mut());
        if opts.is_null() {
            return false;
        }
        let mut usage = 0;
        let ds = gdal_sys::GDALWarp(
            dest.as_ptr(),
            std::ptr::null_mut(),
            handles.len() as std::ffi::c_int,
            handles.as_mut_ptr(),
            opts,
            &mut usage,
        );
        gdal_sys::GDALWarpAppOptionsFree(opts);
        if ds.is_null() {
            return false;
        }
        gdal_sys::GDALClose(ds);
        true
    });
    if !ok {
        // SAFETY: reads this thread's last GDAL error message.
        let msg = unsafe { std::ffi::CStr::from_ptr(gdal_sys::CPLGetLastErrorMsg()) }
            .to_string_lossy()
            .into_owned();
        return Err(bad(format!("cannot reproject onto {}: {msg}", onto.path.display())));
    }
    Ok(())
}

/// Rasters up to this many pixels have band 1 read in full by
/// [`check_not_all_nodata`]; larger ones are read decimated (from overviews
/// when the file has them).
const FULL_CHECK_PIXELS: usize = 64 << 20;

/// Reads band 1 (in full up to `FULL_CHECK_PIXELS`, decimated beyond) and
/// fails when a block cannot be read (a truncated or damaged file) or when no
/// pixel is valid (nodata, NaN, or masked out by an alpha/dataset mask).
pub fn check_not_all_nodata(ds: &Dataset, path: &Path) -> Result<()> {
    let read_err = |e: GdalError| RasterError::Read {
        path: path.into(),
        reason: format!("damaged or truncated pixel data ({})", gdal_reason(&e, path)),
    };
    let band = ds.rasterband(1).map_err(read_err)?;
    let nodata = band.no_data_value();
    let flags = band.mask_flags().map_err(read_err)?;
    let mask = if flags.is_all_valid() || flags.is_nodata() {
        None
    } else {
        Some(band.open_mask_band().map_err(read_err)?)
    };
    let (w, h) = ds.raster_size();
    let is_valid = |v: f64, m: Option<u8>| !v.is_nan() && nodata.is_none_or(|nd| v != nd) && m != Some(0);
    // First a sample of up to 64 whole blocks spread over the raster, the last
    // one included (where truncation shows): cheap, and enough almost always.
    let (bw, bh) = band.block_size();
    let (bw, bh) = (bw.max(1), bh.max(1));
    let (nbx, nby) = (w.div_ceil(bw), h.div_ceil(bh));
    let blocks = nbx * nby;
    let picks: Vec<usize> =
        if blocks <= 64 { (0..blocks).collect() } else { (0..64).map(|k| k * (blocks - 1) / 63).collect() };
    let sampled_valid = quietly(|| {
        for &i in &picks {
            let (x0, y0) = ((i % nbx) * bw, (i / nbx) * bh);
            let size = (bw.min(w - x0), bh.min(h - y0));
            let win = (x0 as isize, y0 as isize);
            let values = band.read_as::<f64>(win, size, size, None).map_err(read_err)?;
            let masked = match &mask {
                Some(m) => Some(m.read_as::<u8>(win, size, size, None).map_err(read_err)?),
                None => None,
            };
            let any = values
                .data()
                .iter()
                .enumerate()
                .any(|(k, &v)| is_valid(v, masked.as_ref().map(|m| m.data()[k])));
            if any {
                return Ok::<bool, RasterError>(true);
            }
        }
        Ok(false)
    })?;
    if sampled_valid {
        return Ok(());
    }
    // Nothing valid in the sample: look at everything (decimated) before saying so.
    // Decimation factor and the decimated size.
    let f = ((w as f64 * h as f64 / FULL_CHECK_PIXELS as f64).sqrt().ceil() as usize).max(1);
    let (ow, oh) = (w.div_ceil(f), h.div_ceil(f));
    let rows_per_read = ((1usize << 22) / ow).max(1);
    let mut any_valid = false;
    quietly(|| {
        let mut oy = 0;
        while oy < oh {
            let n = rows_per_read.min(oh - oy);
            let (y0, y1) = (oy * f, ((oy + n) * f).min(h));
            let win = ((0, y0 as isize), (w, y1 - y0), (ow, n));
            let values = band.read_as::<f64>(win.0, win.1, win.2, None).map_err(read_err)?;
            let masked = match &mask {
                Some(m) => Some(m.read_as::<u8>(win.0, win.1, win.2, None).map_err(read_err)?),
                None => None,
            };
            if !any_valid {
                any_valid = values
                    .data()
                    .iter()
                    .enumerate()
                    .any(|(i, &v)| is_valid(v, masked.as_ref().map(|m| m.data()[i])));
            }
            oy += n;
        }
        Ok::<(), RasterError>(())
    })?;
    if any_valid {
        Ok(())
    } else {
        Err(RasterError::AllNodata { path: path.into() })
    }
}

/// How an ortho's bands are combined into one luminance channel scaled to 0..255.
#[derive(Clone, Debug, PartialEq)]
pub struct Luminance {
    /// (1-based band index, weight).
    pub bands: Vec<(usize, f32)>,
    /// lum = (sum(w_i * band_i) - offset) * scale
    pub offset: f32,
    pub scale: f32,
    /// Band used for the validity mask when it is an alpha band.
    pub alpha_band: Option<usize>,
}

/// Rec. 601 luma weights.
const LUMA_RGB: [f32; 3] = [0.299, 0.587, 0.114];

/// Decides the band combination: 1 band grey, 2 grey + alpha, 3 RGB, 4 RGB + alpha
/// (or RGB + another band); more bands need `--ortho-bands`.
pub fn luminance_for(ds: &Dataset, info: &RasterInfo, bands_opt: Option<&[usize]>) -> Result<Luminance> {
    use gdal::raster::ColorInterpretation as CI;
    let path = &info.path;
    let n = info.band_count;
    let interp: Vec<CI> = (1..=n)
        .map(|b| ds.rasterband(b).map(|x| x.color_interpretation()).unwrap_or(CI::Undefined))
        .collect();
    let alpha_band = interp.iter().position(|c| *c == CI::AlphaBand).map(|i| i + 1);
    let chosen: Vec<usize> = match bands_opt {
        Some(b) => {
            if let Some(&bad) = b.iter().find(|&&i| i == 0 || i > n) {
                return Err(RasterError::Option {
                    option: "--ortho-bands",
                    reason: format!("band {bad} does not exist in {} ({n} bands)", path.display()),
                });
            }
            if b.len() != 1 && b.len() != 3 {
                return Err(RasterError::Option { option: "--ortho-bands", reason: "give 1 band (grey) or 3 (red,green,blue)".into() });
            }
            b.to_vec()
        }
        None => match (n, alpha_band) {
            (1, _) => vec![1],
            (2, Some(2)) | (2, None) => vec![1],
            (3, _) => vec![1, 2, 3],
            (4, _) => {
                let find = |c: CI| interp.iter().position(|x| *x == c).map(|i| i + 1);
                match (find(CI::RedBand), find(CI::GreenBand), find(CI::BlueBand)) {
                    (Some(r), Some(g), Some(b)) => vec![r, g, b],
                    _ => vec![1, 2, 3],
                }
            }
            _ => {
                return Err(RasterError::BadRaster {
                    path: path.clone(),
                    reason: format!(
                        "{n} bands: say which make the luminance with --ortho-bands (one grey band, or red,green,blue, e.g. 3,2,1)"
                    ),
                })
            }
        },
    };
    let weights: Vec<(usize, f32)> = if chosen.len() == 1 {
        vec![(chosen[0], 1.0)]
    } else {
        chosen.iter().zip(LUMA_RGB).map(|(&b, w)| (b, w)).collect()
    };
    // 8-bit data is used as it is; wider types are stretched from their range.
    let (offset, scale) = if info.band_type == GdalDataType::UInt8.name() {
        (0.0, 1.0)
    } else {
        let mut lo = 0f64;
        let mut hi = 0f64;
        for &(b, w) in &weights {
            let band = ds
                .rasterband(b)
                .map_err(|e| RasterError::Read { path: path.clone(), reason: gdal_reason(&e, path) })?;
            let mm = band
                .compute_raster_min_max(true)
                .map_err(|_| RasterError::AllNodata { path: path.clone() })?;
            lo += w as f64 * mm.min;
            hi += w as f64 * mm.max;
        }
        if hi <= lo {
            return Err(RasterError::BadRaster {
                path: path.clone(),
                reason: "constant image: no texture".into(),
            });
        }
        (lo as f32, (255.0 / (hi - lo)) as f32)
    };
    Ok(Luminance { bands: weights, offset, scale, alpha_band })
}

/// Vertical datum of DEM heights.
#[derive(Clone, Debug, PartialEq)]
pub enum VerticalDatum {
    Ellipsoid,
    /// EGM96 geoid heights (EPSG:5773).
    Egm96,
    /// Heights above a geoid given by a grid file (NAVD88 with GEOID18, EGM2008, ...).
    Geoid {
        name: String,
    },
}

/// The vertical CRS a raster's compound CRS names, as (name, EPSG code).
pub fn vertical_crs_of(wkt: &str) -> Option<(String, Option<u32>)> {
    let start = wkt.find("VERT_CS[").or_else(|| wkt.find("VERTCRS["))?;
    let rest = &wkt[start..];
    let name = rest.split('"').nth(1).unwrap_or("").to_string();
    // The vertical CRS's own AUTHORITY is its last one before the block closes.
    let mut depth = 0i32;
    let mut end = rest.len();
    for (i, ch) in rest.char_indices() {
        match ch {
            '[' => depth += 1,
            ']' => {
                depth -= 1;
                if depth == 0 {
                    end = i;
                    break;
                }
            }
            _ => {}
        }
    }
    let block = &rest[..end];
    let code = block
        .rfind("AUTHORITY[\"EPSG\",\"")
        .map(|i| &block[i + 18..])
        .or_else(|| block.rfind("ID[\"EPSG\",").map(|i| &block[i + 10..]))
        .and_then(|s| {
            s.trim_matches('"').split(|c: char| !c.is_ascii_digit()).next().and_then(|d| d.parse().ok())
        });
    Some((name, code))
}

/// The datum the DEM declares in its CRS, if any.
pub fn declared_vertical(wkt: &str) -> Option<VerticalDatum> {
    let (name, code) = vertical_crs_of(wkt)?;
    let lname = name.to_lowercase();
    Some(match code {
        Some(5773) => VerticalDatum::Egm96,
        _ if lname.contains("egm96") => VerticalDatum::Egm96,
        _ if lname.contains("ellipsoid") => VerticalDatum::Ellipsoid,
        _ => VerticalDatum::Geoid { name: code.map(|c| format!("EPSG:{c} ({name})")).unwrap_or(name) },
    })
}

/// Geographic 3D CRSs (EPSG:4979 style) carry ellipsoidal heights.
pub fn is_ellipsoidal_3d(srs_wkt: &str) -> bool {
    srs_wkt.contains("GEOGCRS") && srs_wkt.contains("ellipsoidal height")
        || srs_wkt.contains("\"EPSG\",\"4979\"")
}
