//! DEM access: ellipsoidal heights at WGS84 points, read through small GDAL
//! windows, with the geoid correction the DEM's vertical datum needs.

use std::path::Path;
use std::sync::Arc;

use gdal::spatial_ref::CoordTransform;
use gdal::Dataset;
use trn_geodesy::GeoidGrid;
use trn_landmark::GeoBox;

use crate::error::{RasterError, Result};
use crate::source::{self, RasterInfo};

/// Loads a geoid undulation grid (e.g. `/usr/share/proj/egm96_15.gtx`) with GDAL.
pub fn load_geoid(path: &Path) -> Result<GeoidGrid> {
    let err = |reason: String| RasterError::Geoid { path: path.into(), reason };
    if !path.exists() {
        let hint =
            if path == Path::new(crate::EGM96_GRID) { " (Debian's proj-data package ships it)" } else { "" };
        return Err(err(format!("no such file{hint}")));
    }
    let ds = Dataset::open(path).map_err(|e| err(crate::source::gdal_reason(&e, path)))?;
    let gt = ds.geo_transform().map_err(|e| err(format!("no geotransform: {e}")))?;
    let (cols, rows) = ds.raster_size();
    let band = ds.rasterband(1).map_err(|e| err(crate::source::gdal_reason(&e, path)))?;
    let nodata = band.no_data_value();
    let buf = band
        .read_as::<f32>((0, 0), (cols, rows), (cols, rows), None)
        .map_err(|e| err(crate::source::gdal_reason(&e, path)))?;
    let (_, mut values) = buf.into_shape_and_vec();
    if let Some(nd) = nodata {
        for v in values.iter_mut() {
            if (*v as f64 - nd).abs() < 1e-6 {
                *v = f32::NAN;
            }
        }
    }
    if gt[2] != 0.0 || gt[4] != 0.0 || gt[5] >= 0.0 {
        return Err(err("expected a north-up latitude/longitude grid".into()));
    }
    Ok(GeoidGrid {
        name: path.file_name().map(|f| f.to_string_lossy().into_owned()).unwrap_or_default(),
        north_lat_deg: gt[3] + 0.5 * gt[5],
        west_lon_deg: gt[0] + 0.5 * gt[1],
        dlat_deg: -gt[5],
        dlon_deg: gt[1],
        rows,
        cols,
        undulation_m: values,
    })
}

/// One DEM raster as the builder uses it.
#[derive(Clone, Debug)]
pub struct DemSpec {
    pub info: RasterInfo,
    pub nodata: Option<f64>,
    /// Multiplies stored values to metres (feet DEMs).
    pub to_metres: f64,
    /// Geoid added to reach ellipsoidal heights; `None` when already ellipsoidal.
    pub geoid: Option<Arc<GeoidGrid>>,
}

/// Where a template's terrain heights come from.
pub trait Heights {
    /// Ellipsoidal heights (m) at (lon, lat) points; `None` when some point has no DEM.
    fn heights_ellipsoidal(&self, lonlat: &[(f64, f64)]) -> Option<Vec<f64>>;

    /// Ellipsoidal heights (m) at (lon, lat) points, NaN where there is no DEM.
    fn heights_or_nan(&self, lonlat: &[(f64, f64)]) -> Vec<f64> {
        lonlat.iter().map(|p| self.heights_ellipsoidal(&[*p]).map_or(f64::NAN, |h| h[0])).collect()
    }
}

impl Heights for DemSampler {
    /// Ellipsoidal heights (m) at (lon, lat) points, each from the first DEM
    /// (in the order given) with valid data there, so tiles of a DEM mosaic
    /// join; `None` when some point has no DEM.
    fn heights_ellipsoidal(&self, lonlat: &[(f64, f64)]) -> Option<Vec<f64>> {
        self.heights_each(lonlat).into_iter().collect()
    }

    fn heights_or_nan(&self, lonlat: &[(f64, f64)]) -> Vec<f64> {
        self.heights_each(lonlat).into_iter().map(|h| h.unwrap_or(f64::NAN)).collect()
    }
}

impl Heights for DemPatch<'_> {
    /// Points outside the patch's box have no height here.
    fn heights_ellipsoidal(&self, lonlat: &[(f64, f64)]) -> Option<Vec<f64>> {
        lonlat.iter().map(|&(lon, lat)| self.parts.iter().find_map(|p| p.height(lon, lat))).collect()
    }
}

/// Ellipsoidal heights (m, NaN where no DEM covers) at the nodes of a
/// latitude/longitude grid: node `(row, col)` at `north - row * dlat`,
/// `west + col * dlon`; sampled 64 rows at a time (one DEM read and one batch
/// of coordinate transforms each, in bounded memory).
pub fn latlon_heights(
    dem: &impl Heights,
    north: f64,
    west: f64,
    dlat: f64,
    dlon: f64,
    rows: usize,
    cols: usize,
) -> trn_landmark::grid::LatLonGrid<f32> {
    let mut values: Vec<f32> = Vec::with_capacity(rows * cols);
    for r0 in (0..rows).step_by(64) {
        let points: Vec<(f64, f64)> = (r0..(r0 + 64).min(rows))
            .flat_map(|r| (0..cols).map(move |c| (west + c as f64 * dlon, north - r as f64 * dlat)))
            .collect();
        values.extend(dem.heights_or_nan(&points).into_iter().map(|h| h as f32));
    }
    trn_landmark::grid::LatLonGrid {
        north_lat_deg: north,
        west_lon_deg: west,
        dlat_deg: dlat,
        dlon_deg: dlon,
        rows,
        cols,
        values,
    }
}

/// Per-thread DEM reader (GDAL handles are not shared across threads).
pub struct DemSampler {
    dems: Vec<(DemSpec, Dataset, CoordTransform)>,
}

impl DemSampler {
    /// Ellipsoidal heights (m) at (lon, lat) points, each from the first DEM
    /// with valid data there; `None` per point without DEM.
    pub fn heights_each(&self, lonlat: &[(f64, f64)]) -> Vec<Option<f64>> {
        let mut out: Vec<Option<f64>> = vec![None; lonlat.len()];
        for (spec, ds, ct) in &self.dems {
            let missing: Vec<usize> = (0..lonlat.len()).filter(|&i| out[i].is_none()).collect();
            if missing.is_empty() {
                break;
            }
            let pts: Vec<(f64, f64)> = missing.iter().map(|&i| lonlat[i]).collect();
            for (k, h) in sample(spec, ds, ct, &pts).into_iter().enumerate() {
                out[missing[k]] = h;
            }
        }
        out
    }
}

impl DemSampler {
    pub fn open(specs: &[DemSpec]) -> Result<Self> {
        let mut dems = Vec::new();
        for s in specs {
            let ds = source::open(&s.info.path)?;
            let srs = source::srs_of(&ds, &s.info.path)?;
            let ct = CoordTransform::new(&source::wgs84(), &srs).map_err(|e| RasterError::BadRaster {
                path: s.info.path.clone(),
                reason: crate::source::gdal_reason(&e, &s.info.path),
            })?;
            dems.push((s.clone(), ds, ct));
        }
        Ok(Self { dems })
    }
}

/// Heights at the points this DEM covers with valid data (bilinear, clamped
/// half a pixel past the edge centres so adjacent tiles meet).
fn sample(spec: &DemSpec, ds: &Dataset, ct: &CoordTransform, lonlat: &[(f64, f64)]) -> Vec<Option<f64>> {
    let none = vec![None; lonlat.len()];
    let mut xs: Vec<f64> = lonlat.iter().map(|p| p.0).collect();
    let mut ys: Vec<f64> = lonlat.iter().map(|p| p.1).collect();
    let mut zs = vec![0.0; xs.len()];
    if ct.transform_coords(&mut xs, &mut ys, &mut zs).is_err() {
        return none;
    }
    let (w, h) = (spec.info.width as f64, spec.info.height as f64);
    // Sample positions in pixel-centre convention; None outside the raster.
    let pos: Vec<Option<(f64, f64)>> = xs
        .iter()
        .zip(&ys)
        .map(|(&x, &y)| {
            let (c, r) = spec.info.to_crs.invert(x, y);
            let (c, r) = (c - 0.5, r - 0.5);
            (c >= -0.5 && r >= -0.5 && c <= w - 0.5 && r <= h - 0.5).then_some((c, r))
        })
        .collect();
    let inside: Vec<(f64, f64)> = pos.iter().flatten().copied().collect();
    if inside.is_empty() {
        return none;
    }
    let (wi, hi) = (spec.info.width as isize, spec.info.height as isize);
    let c0 = inside.iter().map(|p| p.0.floor() as isize).min().unwrap_or(0).clamp(0, wi - 1);
    let c1 = inside.iter().map(|p| p.0.floor() as isize + 1).max().unwrap_or(0).clamp(0, wi - 1);
    let r0 = inside.iter().map(|p| p.1.floor() as isize).min().unwrap_or(0).clamp(0, hi - 1);
    let r1 = inside.iter().map(|p| p.1.floor() as isize + 1).max().unwrap_or(0).clamp(0, hi - 1);
    let (ww, wh) = ((c1 - c0 + 1) as usize, (r1 - r0 + 1) as usize);
    let Ok(band) = ds.rasterband(1) else { return none };
    let Ok(buf) = band.read_as::<f64>((c0, r0), (ww, wh), (ww, wh), None) else { return none };
    let data = buf.data();
    let at = |c: isize, r: isize| -> Option<f64> {
        let (c, r) = (c.clamp(c0, c1), r.clamp(r0, r1));
        valid_height(spec, data[(r - r0) as usize * ww + (c - c0) as usize])
    };
    pos.iter()
        .zip(lonlat)
        .map(|(p, &(lon, lat))| {
            let (c, r) = (*p)?;
            ellipsoidal_height(spec, &at, c, r, lon, lat)
        })
        .collect()
}

/// A stored DEM value, or `None` for nodata.
fn valid_height(spec: &DemSpec, v: f64) -> Option<f64> {
    match spec.nodata {
        Some(nd) if v == nd || (nd.is_nan() && v.is_nan()) => None,
        _ if !v.is_finite() => None,
        _ => Some(v),
    }
}

/// Bilinear DEM height at pixel-centre position (c, r) from the stored values
/// `at(col, row)`, in metres, made ellipsoidal with the DEM's geoid.
fn ellipsoidal_height(
    spec: &DemSpec,
    at: &dyn Fn(isize, isize) -> Option<f64>,
    c: f64,
    r: f64,
    lon: f64,
    lat: f64,
) -> Option<f64> {
    let (fc, fr) = (c.floor(), r.floor());
    let (ic, ir) = (fc as isize, fr as isize);
    let corners = [at(ic, ir)?, at(ic + 1, ir)?, at(ic, ir + 1)?, at(ic + 1, ir + 1)?];
    metres_above_ellipsoid(spec, corners, (c - fc, r - fr), lon, lat)
}

/// Bilinear blend of a cell's four stored values (top-left, top-right,
/// bottom-left, bottom-right) at fractions `(tc, tr)`, in metres, made
/// ellipsoidal with the DEM's geoid.
fn metres_above_ellipsoid(
    spec: &DemSpec,
    v: [f64; 4],
    (tc, tr): (f64, f64),
    lon: f64,
    lat: f64,
) -> Option<f64> {
    let blend = (v[0] * (1.0 - tc) + v[1] * tc) * (1.0 - tr) + (v[2] * (1.0 - tc) + v[3] * tc) * tr;
    let mut hgt = blend * spec.to_metres;
    if let Some(g) = &spec.geoid {
        hgt += g.undulation_at(lat, lon)?;
    }
    Some(hgt)
}

/// The DEMs under one tile, read once: per DEM a window of heights and a
/// lon/lat -> DEM pixel map interpolated from a grid of exact transformations
/// (centimetre-accurate over a tile, far below a DEM cell), so templates sample
/// heights without a GDAL read or a PROJ call each.
pub struct DemPatch<'a> {
    parts: Vec<PatchPart<'a>>,
}

struct PatchPart<'a> {
    spec: &'a DemSpec,
    /// Window origin (DEM pixels) and size.
    c0: isize,
    r0: isize,
    w: usize,
    h: usize,
    heights: Vec<f64>,
    /// Grid nodes: (lon, lat) -> (col, row) in pixel-centre convention.
    grid: TransformGrid,
}

/// Bilinear interpolation of a smooth map on an n x n grid over a lon/lat box.
struct TransformGrid {
    lon0: f64,
    lat0: f64,
    /// Grid nodes per degree of longitude and of latitude.
    per_dlon: f64,
    per_dlat: f64,
    n: usize,
    cols: Vec<f64>,
    rows: Vec<f64>,
}

impl TransformGrid {
    fn at(&self, lon: f64, lat: f64) -> Option<(f64, f64)> {
        let fx = (lon - self.lon0) * self.per_dlon;
        let fy = (lat - self.lat0) * self.per_dlat;
        let last = (self.n - 1) as f64;
        if !(fx >= -1e-9 && fy >= -1e-9 && fx <= last + 1e-9 && fy <= last + 1e-9) {
            return None;
        }
        let (ix, iy) = ((fx as usize).min(self.n - 2), (fy as usize).min(self.n - 2));
        let (tx, ty) = (fx - ix as f64, fy - iy as f64);
        let i = iy * self.n + ix;
        let lerp = |v: &[f64]| {
            (v[i] * (1.0 - tx) + v[i + 1] * tx) * (1.0 - ty)
                + (v[i + self.n] * (1.0 - tx) + v[i + self.n + 1] * tx) * ty
        };
        Some((lerp(&self.cols), lerp(&self.rows)))
    }
}

impl DemSampler {
    /// Reads what every DEM holds under `bbox` (lon/lat degrees).
    pub fn patch(&self, bbox: &GeoBox) -> DemPatch<'_> {
        const N: usize = 9;
        let mut parts = Vec::new();
        for (spec, ds, ct) in &self.dems {
            if bbox.intersection(&spec.info.extent).is_none() {
                continue;
            }
            let (dlon, dlat) = (
                (bbox.max_lon_deg - bbox.min_lon_deg) / (N - 1) as f64,
                (bbox.max_lat_deg - bbox.min_lat_deg) / (N - 1) as f64,
            );
            let mut xs = Vec::with_capacity(N * N);
            let mut ys = Vec::with_capacity(N * N);
            for j in 0..N {
                for i in 0..N {
                    xs.push(bbox.min_lon_deg + i as f64 * dlon);
                    ys.push(bbox.min_lat_deg + j as f64 * dlat);
                }
            }
            let mut zs = vec![0.0; xs.len()];
            if ct.transform_coords(&mut xs, &mut ys, &mut zs).is_err() {
                continue;
            }
            let (cols, rows): (Vec<f64>, Vec<f64>) = xs
                .iter()
                .zip(&ys)
                .map(|(&x, &y)| {
                    let (c, r) = spec.info.to_crs.invert(x, y);
                    (c - 0.5, r - 0.5)
                })
                .unzip();
            let (wi, hi) = (spec.info.width as isize, spec.info.height as isize);
            let lo = |v: &[f64]| v.iter().fold(f64::MAX, |a, &b| a.min(b)).floor() as isize - 1;
            let hi_ = |v: &[f64]| v.iter().fold(f64::MIN, |a, &b| a.max(b)).floor() as isize + 2;
            let (c0, c1) = (lo(&cols).clamp(0, wi - 1), hi_(&cols).clamp(0, wi - 1));
            let (r0, r1) = (lo(&rows).clamp(0, hi - 1), hi_(&rows).clamp(0, hi - 1));
            let (w, h) = ((c1 - c0 + 1) as usize, (r1 - r0 + 1) as usize);
            let Ok(band) = ds.rasterband(1) else { continue };
            let Ok(buf) = band.read_as::<f64>((c0, r0), (w, h), (w, h), None) else { continue };
            let grid = TransformGrid {
                lon0: bbox.min_lon_deg,
                lat0: bbox.min_lat_deg,
                per_dlon: 1.0 / dlon,
                per_dlat: 1.0 / dlat,
                n: N,
                cols,
                rows,
            };
            parts.push(PatchPart { spec, c0, r0, w, h, heights: buf.into_shape_and_vec().1, grid });
        }
        DemPatch { parts }
    }
}

impl PatchPart<'_> {
    fn height(&self, lon: f64, lat: f64) -> Option<f64> {
        let (c, r) = self.grid.at(lon, lat)?;
        let spec = self.spec;
        // The usual case: all four neighbours inside the window (so inside the
        // raster, no clamping) and valid. The same arithmetic as below.
        // Truncation is floor here (non-negative), without a libm call.
        let (fc, fr) = ((c.max(0.0) as i64) as f64, (r.max(0.0) as i64) as f64);
        let (ic, ir) = (fc as isize - self.c0, fr as isize - self.r0);
        if c >= 0.0
            && r >= 0.0
            && ic >= 0
            && ir >= 0
            && ((ic + 1) as usize) < self.w
            && ((ir + 1) as usize) < self.h
        {
            let i = ir as usize * self.w + ic as usize;
            let (a, b) = (&self.heights[i..i + 2], &self.heights[i + self.w..i + self.w + 2]);
            if let (Some(a0), Some(a1), Some(b0), Some(b1)) = (
                valid_height(spec, a[0]),
                valid_height(spec, a[1]),
                valid_height(spec, b[0]),
                valid_height(spec, b[1]),
            ) {
                return metres_above_ellipsoid(spec, [a0, a1, b0, b1], (c - fc, r - fr), lon, lat);
            }
        }
        let (w, h) = (spec.info.width as f64, spec.info.height as f64);
        if !(c >= -0.5 && r >= -0.5 && c <= w - 0.5 && r <= h - 0.5) {
            return None;
        }
        let (c1, r1) = (self.c0 + self.w as isize - 1, self.r0 + self.h as isize - 1);
        let at = |cc: isize, rr: isize| -> Option<f64> {
            // Clamped to the raster's edge pixels (half a pixel past the centres);
            // a point beyond the window is not in this patch.
            let (cc, rr) =
                (cc.clamp(0, spec.info.width as isize - 1), rr.clamp(0, spec.info.height as isize - 1));
            if cc < self.c0 || rr < self.r0 || cc > c1 || rr > r1 {
                return None;
            }
            valid_height(spec, self.heights[(rr - self.r0) as usize * self.w + (cc - self.c0) as usize])
        };
        ellipsoidal_height(spec, &at, c, r, lon, lat)
    }
}
