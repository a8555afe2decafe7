//! Fills a [`Scene`] from an ortho and DEMs through GDAL, with the builder's
//! own code for luminance and for ellipsoidal heights (so the simulator and
//! the landmark database see the same terrain).

use std::path::{Path, PathBuf};

use tracing::info;
use trn_raster::ortho::OrthoReader;
use trn_raster::source::{self, luminance_for};
use trn_raster::terrain::DemSampler;
use trn_raster::DemInputs;

use crate::scene::{LatLonGrid, Level, OrthoPyramid, Scene, Terrain};
use crate::SimError;

/// Where the scene comes from.
#[derive(Clone, Debug)]
pub struct SceneSources {
    pub ortho: PathBuf,
    /// Bands making the luminance (as `trn build --ortho-bands`).
    pub ortho_bands: Option<Vec<usize>>,
    pub dem: DemInputs,
}

/// Nodes of the latitude/longitude -> ortho pixel grid per side: exact PROJ
/// transforms at the nodes, bilinear between (millimetres over ~100 m cells).
const TRANSFORM_NODES: usize = 257;
/// Largest terrain grid side (nodes).
const MAX_TERRAIN_NODES: usize = 6000;

/// Loads the scene; `spectral_weights`: the camera's own weights of the
/// luminance's red, green and blue bands (scenario `realism.spectral`)
/// instead of the builder's Rec. 601 luma.
pub fn load_scene(src: &SceneSources, spectral_weights: Option<[f32; 3]>) -> Result<Scene, SimError> {
    let t0 = std::time::Instant::now();
    let (ds, info) = source::inspect(&src.ortho)?;
    source::check_not_all_nodata(&ds, &src.ortho)?;
    let mut lum = luminance_for(&ds, &info, src.ortho_bands.as_deref())?;
    if let Some(weights) = spectral_weights {
        if lum.bands.len() != 3 {
            return Err(SimError::Input {
                path: src.ortho.clone(),
                reason: format!(
                    "realism.spectral needs a luminance made of three bands (red, green, blue; see \
                     --ortho-bands), this one uses {}",
                    lum.bands.len()
                ),
            });
        }
        for (band, w) in lum.bands.iter_mut().zip(weights) {
            band.1 = w;
        }
    }
    let reader = OrthoReader::open(&src.ortho, &lum)?;
    let (w, h) = (info.width, info.height);
    if w.checked_mul(h).is_none_or(|n| n > 1_500_000_000) {
        return Err(SimError::Input {
            path: src.ortho.clone(),
            reason: format!("{w} x {h} pixels is too large to hold in memory; crop it"),
        });
    }
    let mut level0 = vec![f32::NAN; w * h];
    for (k, strip) in level0.chunks_mut(w * 512).enumerate() {
        let rows = strip.len() / w;
        let win = reader.read(0, (k * 512) as isize, w, rows)?;
        for ((d, &l), &ok) in strip.iter_mut().zip(&win.lum).zip(&win.valid) {
            *d = if ok != 0 { l } else { f32::NAN };
        }
    }
    let ortho = OrthoPyramid::new(Level { width: w, height: h, lum: level0 });
    let to_ortho = ortho_transform(&info, &src.ortho)?;
    let ortho_gsd_m = (info.pixel_dx_m * info.pixel_dy_m).sqrt();
    let terrain = load_terrain(src, &info)?;
    info!(
        "scene: ortho {} ({w} x {h} px, {:.2} m), terrain {} x {} nodes at {:.1} m, heights {:.0}..{:.0} m, \
         max slope {:.2}, loaded in {:.2} s",
        src.ortho.display(),
        ortho_gsd_m,
        terrain.heights.cols,
        terrain.heights.rows,
        terrain.cell_m,
        terrain.h_min_m,
        terrain.h_max_m,
        terrain.max_slope,
        t0.elapsed().as_secs_f64()
    );
    Ok(Scene { terrain, ortho, to_ortho, ortho_gsd_m, ortho_extent: info.extent })
}

/// Latitude/longitude -> ortho pixel-centre position on a grid over the
/// ortho's footprint.
fn ortho_transform(info: &source::RasterInfo, path: &Path) -> Result<LatLonGrid<[f64; 2]>, SimError> {
    let ct = source::Wgs84Transform::from_wgs84(path)?;
    let e = &info.extent;
    let n = TRANSFORM_NODES;
    let dlat = (e.max_lat_deg - e.min_lat_deg) / (n - 1) as f64;
    let dlon = (e.max_lon_deg - e.min_lon_deg) / (n - 1) as f64;
    let mut xs = Vec::with_capacity(n * n);
    let mut ys = Vec::with_capacity(n * n);
    for r in 0..n {
        for c in 0..n {
            xs.push(e.min_lon_deg + c as f64 * dlon);
            ys.push(e.max_lat_deg - r as f64 * dlat);
        }
    }
    ct.apply(&mut xs, &mut ys).ok_or_else(|| SimError::Input {
        path: path.into(),
        reason: "the ortho's footprint does not transform from WGS84 to its CRS".into(),
    })?;
    let values = xs
        .iter()
        .zip(&ys)
        .map(|(&x, &y)| {
            let (c, r) = info.to_crs.invert(x, y);
            // GDAL's pixel grid has (0, 0) at the corner; ours at the centre.
            [c - 0.5, r - 0.5]
        })
        .collect();
    Ok(LatLonGrid {
        north_lat_deg: e.max_lat_deg,
        west_lon_deg: e.min_lon_deg,
        dlat_deg: dlat,
        dlon_deg: dlon,
        rows: n,
        cols: n,
        values,
    })
}

/// Ellipsoidal heights on a latitude/longitude grid over the ortho's
/// footprint (plus a margin), at half the finest DEM spacing.
fn load_terrain(src: &SceneSources, ortho: &source::RasterInfo) -> Result<Terrain, SimError> {
    let specs = src.dem.open()?;
    let sampler = DemSampler::open(&specs)?;
    let dem_m = specs.iter().map(|s| s.info.pixel_dx_m.min(s.info.pixel_dy_m)).fold(f64::INFINITY, f64::min);
    let e = &ortho.extent;
    let mid_lat = 0.5 * (e.min_lat_deg + e.max_lat_deg);
    let (m_lat, m_lon) = trn_geodesy::metres_per_degree(mid_lat);
    let (span_lat, span_lon) = (e.max_lat_deg - e.min_lat_deg, e.max_lon_deg - e.min_lon_deg);
    let (margin_lat, margin_lon) = (0.05 * span_lat, 0.05 * span_lon);
    let cell_m = (0.5 * dem_m).max(
        ((span_lat + 2.0 * margin_lat) * m_lat).max((span_lon + 2.0 * margin_lon) * m_lon)
            / (MAX_TERRAIN_NODES - 1) as f64,
    );
    let (dlat, dlon) = (cell_m / m_lat, cell_m / m_lon);
    let rows = ((span_lat + 2.0 * margin_lat) / dlat).ceil() as usize + 1;
    let cols = ((span_lon + 2.0 * margin_lon) / dlon).ceil() as usize + 1;
    let (north, west) = (e.max_lat_deg + margin_lat, e.min_lon_deg - margin_lon);
    let heights = trn_raster::terrain::latlon_heights(&sampler, north, west, dlat, dlon, rows, cols);
    Terrain::new(heights).ok_or_else(|| SimError::Input {
        path: src.dem.files[0].clone(),
        reason: format!("the DEM does not cover the ortho ({})", src.ortho.display()),
    })
}
