//! Elevation models as the builder and the simulator read them: each DEM
//! opened and checked, its vertical datum decided (the file's CRS, or the
//! user's `--dem-vertical` with a geoid grid) and its units converted, and
//! tiles of one grid read as one VRT mosaic.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Serialize;
use tracing::{info, warn};

use crate::error::{RasterError, Result};
use crate::source::{self, VerticalDatum};
use crate::terrain::{self, DemSpec};

/// Where EGM96 lives on Debian (package proj-data).
pub const EGM96_GRID: &str = "/usr/share/proj/egm96_15.gtx";

/// Vertical datum of the DEM as the user states it (overrides the file's).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum DemVertical {
    Egm96,
    Ellipsoid,
    /// Heights above the geoid of `--geoid GRID`.
    Geoid,
}

/// The elevation models of a build or a simulation, as the user gives them
/// (`--dem`, `--dem-vertical`, `--geoid`; serialized under those names).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct DemInputs {
    /// Elevation model files, any GDAL raster in any CRS (tiles of one grid
    /// are read as one mosaic).
    #[serde(rename = "dems")]
    pub files: Vec<PathBuf>,
    /// The heights' vertical datum where the files do not say (or to override them).
    #[serde(rename = "dem_vertical")]
    pub vertical: Option<DemVertical>,
    /// Geoid grid for [`DemVertical::Geoid`] (for EGM96, default [`EGM96_GRID`]).
    pub geoid: Option<PathBuf>,
}

impl DemInputs {
    pub fn new(files: Vec<PathBuf>) -> Self {
        Self { files, ..Self::default() }
    }

    /// Opens and checks every file ([`open_dem_specs`]).
    pub fn open(&self) -> Result<Vec<DemSpec>> {
        open_dem_specs(&self.files, self.vertical, self.geoid.as_deref())
    }
}

/// Opens and checks DEMs and decides each one's conversion to ellipsoidal
/// heights (from the file's CRS, or `vertical` with `geoid`), as `trn build`
/// does; the simulator uses the same path so both see the same terrain.
pub fn open_dem_specs(
    dems: &[PathBuf],
    dem_vertical: Option<DemVertical>,
    geoid: Option<&Path>,
) -> Result<Vec<DemSpec>> {
    if dem_vertical == Some(DemVertical::Geoid) && geoid.is_none() {
        return Err(RasterError::Option {
            option: "--dem-vertical",
            reason: "geoid needs --geoid GRID".into(),
        });
    }
    let mut geoids: HashMap<PathBuf, Arc<trn_geodesy::GeoidGrid>> = HashMap::new();
    let mut load = |p: &Path| -> Result<Arc<trn_geodesy::GeoidGrid>> {
        if let Some(g) = geoids.get(p) {
            return Ok(g.clone());
        }
        let g = Arc::new(terrain::load_geoid(p)?);
        geoids.insert(p.into(), g.clone());
        Ok(g)
    };
    let mut out = Vec::new();
    for p in dems {
        let (ds, info) = source::inspect(p)?;
        source::check_not_all_nodata(&ds, p)?;
        let band = ds
            .rasterband(1)
            .map_err(|e| RasterError::Read { path: p.clone(), reason: source::gdal_reason(&e, p) })?;
        let unit = band.unit().to_lowercase();
        let to_metres = match unit.as_str() {
            "ft" | "foot" | "feet" => 0.3048,
            "us-ft" | "us survey foot" | "ftus" => 1200.0 / 3937.0,
            _ => 1.0,
        };
        let declared = source::declared_vertical(&info.srs_wkt)
            .or_else(|| source::is_ellipsoidal_3d(&info.srs_wkt).then_some(VerticalDatum::Ellipsoid));
        let datum = match (dem_vertical, &declared) {
            (Some(DemVertical::Egm96), _) => VerticalDatum::Egm96,
            (Some(DemVertical::Ellipsoid), _) => VerticalDatum::Ellipsoid,
            (Some(DemVertical::Geoid), _) => VerticalDatum::Geoid { name: "--geoid".into() },
            (None, Some(d)) => d.clone(),
            (None, None) => return Err(RasterError::UnknownVerticalDatum { path: p.clone() }),
        };
        if let (Some(flag), Some(d)) = (dem_vertical, &declared) {
            warn!("{}: file declares {d:?}, --dem-vertical {flag:?} overrides it", p.display());
        }
        let source_of_datum = if dem_vertical.is_some() { "--dem-vertical" } else { "the file's CRS" };
        let geoid = match &datum {
            VerticalDatum::Ellipsoid => None,
            VerticalDatum::Egm96 => Some(load(geoid.unwrap_or(Path::new(EGM96_GRID)))?),
            VerticalDatum::Geoid { name } => match geoid {
                Some(g) => Some(load(g)?),
                None => return Err(RasterError::GeoidGridNeeded { path: p.clone(), datum: name.clone() }),
            },
        };
        match &geoid {
            None => info!("DEM {}: heights are ellipsoidal (from {source_of_datum}); no conversion", p.display()),
            Some(g) => info!(
                "DEM {}: heights {datum:?} (from {source_of_datum}) converted to WGS84 ellipsoidal with geoid grid {}",
                p.display(),
                g.name
            ),
        }
        out.push(DemSpec { info, nodata: band.no_data_value(), to_metres, geoid });
    }
    Ok(out)
}

/// DEM tiles with one CRS, pixel size, datum and nodata are read as one VRT,
/// so heights interpolate across tile seams; others are sampled in turn. The
/// VRTs are written in `work`.
pub fn mosaic_dems(dems: Vec<DemSpec>, work: &Path) -> Result<Vec<DemSpec>> {
    let mut buckets: Vec<Vec<DemSpec>> = Vec::new();
    for d in dems {
        let same = |o: &DemSpec| {
            o.info.srs_wkt == d.info.srs_wkt
                && o.info.to_crs.gt[1] == d.info.to_crs.gt[1]
                && o.info.to_crs.gt[5] == d.info.to_crs.gt[5]
                && o.info.to_crs.gt[2] == 0.0
                && d.info.to_crs.gt[2] == 0.0
                && o.info.band_type == d.info.band_type
                && o.nodata.map(f64::to_bits) == d.nodata.map(f64::to_bits)
                && o.to_metres == d.to_metres
                && o.geoid.as_ref().map(|g| &g.name) == d.geoid.as_ref().map(|g| &g.name)
        };
        match buckets.iter_mut().find(|b| same(&b[0])) {
            Some(b) => b.push(d),
            None => buckets.push(vec![d]),
        }
    }
    let mut out = Vec::new();
    for (i, b) in buckets.into_iter().enumerate() {
        if b.len() == 1 {
            out.extend(b);
            continue;
        }
        let vrt = work.join(format!("dem-mosaic-{i}.vrt"));
        let paths: Vec<PathBuf> = b.iter().map(|d| d.info.path.clone()).collect();
        source::build_vrt(&vrt, &paths, &paths[0], "DEMs")?;
        let (_, info) = source::inspect(&vrt)?;
        info!("mosaic of {} DEMs: {}x{} px", b.len(), info.width, info.height);
        out.push(DemSpec { info, ..b[0].clone() });
    }
    Ok(out)
}
