//! DEM access: ellipsoidal heights at WGS84 points, read through small GDAL
//! windows, with the geoid correction the DEM's vertical datum needs.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use gdal::spatial_ref::CoordTransform;
use gdal::Dataset;
use trn_geodesy::GeoidGrid;

use crate::error::{BuildError, Result};
use crate::source::{self, RasterInfo};

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

    /// Ellipsoidal heights (m) at (lon, lat) points, each from the first DEM
    /// (in the order given) with valid data there, so tiles of a DEM mosaic
    /// join; `None` when some point has no DEM.
    pub fn heights_ellipsoidal(&self, lonlat: &[(f64, f64)]) -> Option<Vec<f64>> {
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
        out.into_iter().collect()
    }

    pub fn paths(&self) -> Vec<PathBuf> {
        self.dems.iter().map(|d| d.0.info.path.clone()).collect()
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
        let v = data[(r - r0) as usize * ww + (c - c0) as usize];
        match spec.nodata {
            Some(nd) if v == nd || (nd.is_nan() && v.is_nan()) => None,
            _ if !v.is_finite() => None,
            _ => Some(v),
        }
    };
    pos.iter()
        .zip(lonlat)
        .map(|(p, &(lon, lat))| {
            let (c, r) = (*p)?;
            let (fc, fr) = (c.floor(), r.floor());
            let (tc, tr) = (c - fc, r - fr);
            let (ic, ir) = (fc as isize, fr as isize);
            let v = (at(ic, ir)? * (1.0 - tc) + at(ic + 1, ir)? * tc) * (1.0 - tr)
                + (at(ic, ir + 1)? * (1.0 - tc) + at(ic + 1, ir + 1)? * tc) * tr;
            let mut hgt = v * spec.to_metres;
            if let Some(g) = &spec.geoid {
                hgt += g.undulation_at(lat, lon)?;
            }
            Some(hgt)
        })
        .collect()
}
