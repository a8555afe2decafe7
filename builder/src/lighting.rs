//! Baked lighting (`trn build --sun AZ,EL`): the templates' appearance under a
//! mission's sun, rendered from the ortho and the DEM, and every template's
//! shading share (how much of its contrast relief shading could make).
//!
//! The brightness factor of `trn_landmark::lighting` (Lambertian shading and
//! cast shadows) is computed once per sun on a latitude/longitude grid of DEM
//! heights over the orthos and a margin (shadows fall in from terrain
//! outside), at the DEM's spacing; a template's pixel takes the factor at its
//! ground position, bilinear. The ortho's own baked-in shading is kept (its
//! sun is unknown): what is rendered is the ortho as it would look with the
//! new sun's shading and shadows added, the model the simulator re-lights its
//! worlds with.

use trn_geodesy::metres_per_degree;
use trn_landmark::grid::LatLonGrid;
use trn_landmark::lighting::{illumination, SunLight};
use trn_landmark::{GeoBox, HeightGrid, Template};

use crate::terrain::{self, Heights};

/// Most grid nodes along a side of a lighting grid.
pub const MAX_GRID_SIDE: usize = 2048;

/// Reach of the lighting grids past the orthos (m): cast shadows from
/// terrain that far away are rendered (2 km of relief at 20° elevation).
pub const SHADOW_MARGIN_M: f64 = 5_000.0;

/// Suns the shading share is taken over when the build has none: four
/// azimuths at a middle elevation.
pub const SHARE_SUNS: [SunLight; 4] = [
    SunLight { azimuth_deg: 45.0, elevation_deg: 35.0, ambient: 0.25 },
    SunLight { azimuth_deg: 135.0, elevation_deg: 35.0, ambient: 0.25 },
    SunLight { azimuth_deg: 225.0, elevation_deg: 35.0, ambient: 0.25 },
    SunLight { azimuth_deg: 315.0, elevation_deg: 35.0, ambient: 0.25 },
];

/// One sun's brightness factor over a latitude/longitude grid.
#[derive(Clone, Debug)]
pub struct SunGrid {
    pub sun: SunLight,
    pub factor: LatLonGrid<f32>,
}

impl SunGrid {
    /// The factor under each of `suns` over `bbox` (lon/lat, widened by
    /// [`SHADOW_MARGIN_M`]) from `dem`, with nodes `spacing_m` apart (or
    /// wider, to stay within [`MAX_GRID_SIDE`]). Nodes without a height are
    /// lit as flat ground.
    pub fn render(dem: &impl Heights, bbox: &GeoBox, spacing_m: f64, suns: &[SunLight]) -> Vec<SunGrid> {
        let lat_mid = 0.5 * (bbox.min_lat_deg + bbox.max_lat_deg);
        let (m_lat, m_lon) = metres_per_degree(lat_mid);
        let (mx, my) = (SHADOW_MARGIN_M / m_lon, SHADOW_MARGIN_M / m_lat);
        let (west, east) = (bbox.min_lon_deg - mx, bbox.max_lon_deg + mx);
        let (south, north) = ((bbox.min_lat_deg - my).max(-89.9), (bbox.max_lat_deg + my).min(89.9));
        let side = |extent_deg: f64, m_per_deg: f64| {
            let n = (extent_deg * m_per_deg / spacing_m.max(1e-3)).ceil() as usize + 1;
            n.clamp(2, MAX_GRID_SIDE)
        };
        let (cols, rows) = (side(east - west, m_lon), side(north - south, m_lat));
        let (dlon, dlat) = ((east - west) / (cols - 1) as f64, (north - south) / (rows - 1) as f64);
        let heights = terrain::latlon_heights(dem, north, west, dlat, dlon, rows, cols);
        suns.iter()
            .map(|sun| SunGrid { sun: *sun, factor: heights.with_values(illumination(&heights, sun)) })
            .collect()
    }

    /// Nodes (rows, cols) of the grid.
    pub fn shape(&self) -> (usize, usize) {
        (self.factor.rows, self.factor.cols)
    }

    /// The factor at a point, bilinear; 1 off the grid.
    pub fn factor_at(&self, lon_deg: f64, lat_deg: f64) -> f32 {
        self.factor.bilinear_or(lat_deg, lon_deg, 1.0)
    }

    /// `t`'s pixels as they look under this sun: each grey level times the
    /// factor at the pixel's ground position (on the template's tangent
    /// plane), rounded; a template that would saturate is scaled down whole
    /// to peak at 255 instead (correlation ignores a template's gain, not
    /// its clipped texture on slopes facing the sun).
    pub fn relight(&self, t: &Template) -> Vec<u8> {
        let (m_lat, m_lon) = metres_per_degree(t.center.lat_deg);
        let (w, h) = (t.width_px as usize, t.height_px as usize);
        let mut lit = Vec::with_capacity(t.pixels.len());
        for row in 0..h {
            for col in 0..w {
                let en = t.pixel_offset_enu(col as f64, row as f64);
                let f = self.factor_at(t.center.lon_deg + en.0.x / m_lon, t.center.lat_deg + en.0.y / m_lat);
                lit.push(t.pixels[row * w + col] as f32 * f);
            }
        }
        let gain = 255.0 / lit.iter().copied().fold(255.0, f32::max);
        lit.into_iter().map(|v| (v * gain + 0.5).clamp(0.0, 255.0) as u8).collect()
    }
}

/// How much of a template's contrast relief shading could make: for each
/// sun, the standard deviation of the Lambertian factor over the interior
/// nodes of its height grid (normals by central differences), times its
/// mean grey level, over its grey-level standard deviation; the largest over
/// `suns`, at most 1 (0 for a grid too small to have an interior or a flat
/// template).
pub fn shading_share(grid: &HeightGrid, mean_grey: f64, contrast_std: f64, suns: &[SunLight]) -> f32 {
    let n = grid.n as usize;
    if n < 3 || contrast_std <= 0.0 || grid.heights_m.len() != n * n {
        return 0.0;
    }
    let h = |r: usize, c: usize| grid.heights_m[r * n + c] as f64;
    let d = 2.0 * grid.spacing_m;
    let normals: Vec<[f64; 3]> = (1..n - 1)
        .flat_map(|r| (1..n - 1).map(move |c| (r, c)))
        .map(|(r, c)| {
            // Row 0 is north: the north neighbour is r - 1.
            let (gx, gy) = ((h(r, c + 1) - h(r, c - 1)) / d, (h(r - 1, c) - h(r + 1, c)) / d);
            let len = (1.0 + gx * gx + gy * gy).sqrt();
            [-gx / len, -gy / len, 1.0 / len]
        })
        .collect();
    let spread = |sun: &SunLight| {
        let shading = sun.shading();
        let (mut sum, mut sum2) = (0.0, 0.0);
        for nv in &normals {
            let f = shading.factor(*nv, 1.0);
            sum += f;
            sum2 += f * f;
        }
        let k = normals.len() as f64;
        (sum2 / k - (sum / k).powi(2)).max(0.0).sqrt()
    };
    let worst = suns.iter().map(spread).fold(0.0, f64::max);
    (worst * mean_grey / contrast_std).clamp(0.0, 1.0) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::Geodetic;
    use trn_landmark::{TemplateQuality, TerrainPatch};

    /// Heights from a function of (lon, lat).
    struct FnDem<F: Fn(f64, f64) -> f64>(F);

    impl<F: Fn(f64, f64) -> f64> Heights for FnDem<F> {
        fn heights_ellipsoidal(&self, pts: &[(f64, f64)]) -> Option<Vec<f64>> {
            Some(pts.iter().map(|&(lon, lat)| (self.0)(lon, lat)).collect())
        }
    }

    const LAT: f64 = 37.5;
    const LON: f64 = -118.5;

    fn template(side: u32, gsd_m: f64, grey: u8) -> Template {
        Template {
            id: 0,
            level: 0,
            gsd_m,
            width_px: side,
            height_px: side,
            center: Geodetic::new(LAT, LON, 1500.0),
            footprint: GeoBox::new(0.0, 0.0, 0.0, 0.0),
            terrain: TerrainPatch {
                plane_normal_enu: [0.0, 0.0, 1.0],
                plane_residual_rms_m: 0.0,
                height_grid: HeightGrid { n: 2, spacing_m: 1.0, heights_m: vec![0.0; 4] },
            },
            quality: TemplateQuality {
                shi_tomasi: 1.0,
                contrast_std: 1.0,
                second_peak_ncc: 0.0,
                shading_share: 0.0,
            },
            source: 0,
            lighting: 0,
            pixels: vec![grey; (side * side) as usize],
        }
    }

    #[test]
    fn flat_ground_keeps_the_pixels() {
        let dem = FnDem(|_, _| 1500.0);
        let bbox = GeoBox::new(LON - 0.05, LAT - 0.05, LON + 0.05, LAT + 0.05);
        let sun = SunLight { azimuth_deg: 250.0, elevation_deg: 25.0, ambient: 0.25 };
        let g = &SunGrid::render(&dem, &bbox, 100.0, &[sun])[0];
        let t = template(16, 30.0, 120);
        assert_eq!(g.relight(&t), t.pixels);
    }

    #[test]
    fn a_wall_shades_and_shadows_where_the_sun_says() {
        // A north-south wall 300 m high, 200 m wide, its west foot at LON; sun
        // from the west at 20 degrees: its west face is bright, and east of it
        // a shadow 300 / tan 20 = 824 m long falls on the flat ground.
        let (m_lat, m_lon) = metres_per_degree(LAT);
        let east_m = move |lon: f64| (lon - LON) * m_lon;
        let dem = FnDem(move |lon, _| if (0.0..200.0).contains(&east_m(lon)) { 1800.0 } else { 1500.0 });
        let bbox = GeoBox::new(LON - 0.05, LAT - 0.05, LON + 0.05, LAT + 0.05);
        let sun = SunLight { azimuth_deg: 270.0, elevation_deg: 20.0, ambient: 0.25 };
        let g = &SunGrid::render(&dem, &bbox, 20.0, &[sun])[0];
        let at = |e: f64| g.factor_at(LON + e / m_lon, LAT);
        let dark = 0.25 / (0.25 + 0.75 * 20f64.to_radians().sin());
        for e in [300.0, 500.0, 900.0] {
            assert!((at(e) as f64 - dark).abs() < 1e-3, "{e} m east of the wall: {} vs {dark}", at(e));
        }
        for e in [1200.0, 2000.0, -500.0, 100.0] {
            assert!((at(e) - 1.0).abs() < 1e-3, "{e} m: {} lit", at(e));
        }
        assert!(at(-10.0) > 1.5, "the west face faces the sun: {}", at(-10.0));
        // A template centred in the shadow darkens by the factor.
        let mut t = template(8, 10.0, 200);
        t.center = Geodetic::new(LAT, LON + 600.0 / m_lon, 1500.0);
        let lit = g.relight(&t);
        let want = (200.0 * dark + 0.5) as u8;
        assert!(lit.iter().all(|&v| v.abs_diff(want) <= 1), "{lit:?} vs {want}");
        let _ = m_lat;
    }

    #[test]
    fn shading_share_grows_with_relief_and_falls_with_texture() {
        // A ridge across the template, `amp_m` high: slopes on both sides.
        let grid = |amp_m: f64| HeightGrid {
            n: 9,
            spacing_m: 60.0,
            heights_m: (0..81)
                .map(|i| ((i % 9) as f64 * std::f64::consts::PI / 8.0).sin() * amp_m)
                .map(|h| h as f32)
                .collect(),
        };
        let flat = shading_share(&grid(0.0), 120.0, 30.0, &SHARE_SUNS);
        let gentle = shading_share(&grid(10.0), 120.0, 30.0, &SHARE_SUNS);
        let steep = shading_share(&grid(300.0), 120.0, 30.0, &SHARE_SUNS);
        assert_eq!(flat, 0.0);
        assert!(gentle > 0.0 && gentle < steep, "{gentle} {steep}");
        // The same relief under a contrasty texture: a smaller share.
        assert!(shading_share(&grid(10.0), 120.0, 60.0, &SHARE_SUNS) < gentle);
        assert!(steep == 1.0, "{steep}");
        // A plane shades uniformly: no share.
        let plane =
            HeightGrid { n: 9, spacing_m: 60.0, heights_m: (0..81).map(|i| (i % 9) as f32 * 20.0).collect() };
        assert!(shading_share(&plane, 120.0, 30.0, &SHARE_SUNS) < 1e-6);
    }
}
