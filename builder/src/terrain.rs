//! DEM access: ellipsoidal heights at WGS84 points, read through small GDAL
//! windows, with the geoid correction the DEM's vertical datum needs.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use gdal::spatial_ref::CoordTransform;
use gdal::Dataset;
use trn_geodesy::GeoidGrid;

use crate::error::{BuildError, Result};
use crate::source::{self, PixelToCrs, RasterInfo};

/// Loads a geoid undulation grid (e.g. `/usr/share/proj/egm96_15.gtx`) with GDAL.
pub fn load_geoid(path: &Path) -> Result<GeoidGrid> {
    let err = |reason: String| BuildError::Geoid { path: path.into(), reason };
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

/// Per-thread DEM reader (GDAL handles are not shared across threads).
pub struct DemSampler {
    dems: Vec<(DemSpec, Dataset, CoordTransform)>,
}

impl DemSampler {
    pub fn open(specs: &[DemSpec]) -> Result<Self> {
        let mut dems = Vec::new();
        for s in specs {
            let ds = source::open(&s.info.path)?;
            let srs = source::srs_of(&ds, &s.info.path)?;
            let ct = CoordTransform::new(&source::wgs84(), &srs).map_err(|e| BuildError::BadRaster {
                path: s.info.path.clone(),
                reason: crate::source::gdal_reason(&e, &s.info.path),
            })?;
            dems.push((s.clone(), ds, ct));
        }
        Ok(Self { dems })
    }

    /// Ellipsoidal heights (m) at (lon, lat) points, all from the first DEM that
    /// covers every point with valid data; `None` when none does.
    pub fn heights_ellipsoidal(&self, lonlat: &[(f64, f64)]) -> Option<Vec<f64>> {
        self.dems.iter().find_map(|(spec, ds, ct)| sample(spec, ds, ct, lonlat))
    }

    pub fn paths(&self) -> Vec<PathBuf> {
        self.dems.iter().map(|d| d.0.info.path.clone()).collect()
    }
}

fn sample(spec: &DemSpec, ds: &Dataset, ct: &CoordTransform, lonlat: &[(f64, f64)]) -> Option<Vec<f64>> {
    let mut xs: Vec<f64> = lonlat.iter().map(|p| p.0).collect();
    let mut ys: Vec<f64> = lonlat.iter().map(|p| p.1).collect();
    let mut zs = vec![0.0; xs.len()];
    ct.transform_coords(&mut xs, &mut ys, &mut zs).ok()?;
    let to_crs: PixelToCrs = spec.info.to_crs;
    // Sample positions in pixel-centre convention.
    let pos: Vec<(f64, f64)> = xs
        .iter()
        .zip(&ys)
        .map(|(&x, &y)| {
            let (c, r) = to_crs.invert(x, y);
            (c - 0.5, r - 0.5)
        })
        .collect();
    let (w, h) = (spec.info.width as isize, spec.info.height as isize);
    let c0 = pos.iter().map(|p| p.0.floor() as isize).min()?;
    let c1 = pos.iter().map(|p| p.0.floor() as isize + 1).max()?;
    let r0 = pos.iter().map(|p| p.1.floor() as isize).min()?;
    let r1 = pos.iter().map(|p| p.1.floor() as isize + 1).max()?;
    // Edge pixels are clamped (half a pixel of extrapolation at the border).
    let (c0c, r0c, c1c, r1c) = (c0.max(0), r0.max(0), c1.min(w - 1), r1.min(h - 1));
    if pos.iter().any(|p| p.0 < -0.5 || p.1 < -0.5 || p.0 > w as f64 - 0.5 || p.1 > h as f64 - 0.5)
        || c1c < c0c
        || r1c < r0c
    {
        return None;
    }
    let (ww, wh) = ((c1c - c0c + 1) as usize, (r1c - r0c + 1) as usize);
    let band = ds.rasterband(1).ok()?;
    let buf = band.read_as::<f64>((c0c, r0c), (ww, wh), (ww, wh), None).ok()?;
    let data = buf.data();
    let at = |c: isize, r: isize| -> Option<f64> {
        let (c, r) = (c.clamp(c0c, c1c), r.clamp(r0c, r1c));
        let v = data[(r - r0c) as usize * ww + (c - c0c) as usize];
        match spec.nodata {
            Some(nd) if v == nd || (nd.is_nan() && v.is_nan()) => None,
            _ if !v.is_finite() => None,
            _ => Some(v),
        }
    };
    let mut out = Vec::with_capacity(pos.len());
    for (i, &(c, r)) in pos.iter().enumerate() {
        let (fc, fr) = (c.floor(), r.floor());
        let (tc, tr) = (c - fc, r - fr);
        let (ic, ir) = (fc as isize, fr as isize);
        let v = (at(ic, ir)? * (1.0 - tc) + at(ic + 1, ir)? * tc) * (1.0 - tr)
            + (at(ic, ir + 1)? * (1.0 - tc) + at(ic + 1, ir + 1)? * tc) * tr;
        let mut hgt = v * spec.to_metres;
        if let Some(g) = &spec.geoid {
            hgt += g.undulation_at(lonlat[i].1, lonlat[i].0)?;
        }
        out.push(hgt);
    }
    Some(out)
}
