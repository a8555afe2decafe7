//! Shared helpers for the store's integration tests: a deterministic random generator
//! and synthetic templates.
#![allow(dead_code)]

use std::path::{Path, PathBuf};

use trn_geodesy::{metres_per_degree, Geodetic};
use trn_landmark::{GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};
use trn_store::{DbSummary, DbWriter};

/// Knuth's MMIX linear congruential generator; plenty for test data.
pub struct Lcg(u64);

impl Lcg {
    pub fn new(seed: u64) -> Self {
        Self(seed ^ 0x9E37_79B9_7F4A_7C15)
    }

    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        self.0
    }

    /// Uniform in [0, 1).
    pub fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }

    pub fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }

    pub fn below(&mut self, n: u64) -> u64 {
        (self.next_u64() >> 32) % n
    }

    pub fn chance(&mut self, p: f64) -> bool {
        self.unit() < p
    }
}

/// A template of `width_px` x `height_px` at `level` (GSD 2 m * 2^level) centred at
/// (lat, lon), with every field filled from `rng`.
pub fn synthetic_template(rng: &mut Lcg, level: u8, lat_deg: f64, lon_deg: f64) -> Template {
    let (width_px, height_px) = (16u32, 12u32);
    let gsd_m = 2.0 * f64::from(1u32 << level);
    let (m_per_lat, m_per_lon) = metres_per_degree(lat_deg);
    let half_lon = width_px as f64 * gsd_m / 2.0 / m_per_lon;
    let half_lat = height_px as f64 * gsd_m / 2.0 / m_per_lat;
    let wrap = |lon: f64| {
        if lon > 180.0 {
            lon - 360.0
        } else if lon < -180.0 {
            lon + 360.0
        } else {
            lon
        }
    };
    let footprint = GeoBox::new(
        wrap(lon_deg - half_lon),
        lat_deg - half_lat,
        wrap(lon_deg + half_lon),
        lat_deg + half_lat,
    );
    let n = 3 + rng.below(4) as u32;
    let heights_m = (0..n * n).map(|_| rng.uniform(-50.0, 50.0) as f32).collect();
    let (nx, ny) = (rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3));
    let norm = (nx * nx + ny * ny + 1.0).sqrt();
    Template {
        id: 0,
        level,
        gsd_m,
        width_px,
        height_px,
        center: Geodetic::new(lat_deg, lon_deg, rng.uniform(-100.0, 4000.0)),
        footprint,
        terrain: TerrainPatch {
            plane_normal_enu: [nx / norm, ny / norm, 1.0 / norm],
            plane_residual_rms_m: rng.uniform(0.0, 5.0),
            height_grid: HeightGrid { n, spacing_m: width_px as f64 * gsd_m / (n - 1) as f64, heights_m },
        },
        quality: TemplateQuality {
            shi_tomasi: rng.uniform(0.0, 500.0) as f32,
            contrast_std: rng.uniform(5.0, 60.0) as f32,
            // Few distinct values, so that the shi_tomasi and id tie-breaks matter.
            second_peak_ncc: (rng.below(8) as f32) / 10.0,
            shading_share: (rng.below(5) as f32) / 4.0,
        },
        source: rng.below(3) as u32,
        lighting: rng.below(2) as u8,
        pixels: (0..width_px * height_px).map(|_| rng.below(256) as u8).collect(),
    }
}

/// Writes `templates` (ids assigned in place) into a new database at `dir/name`.
pub fn write_db(dir: &Path, name: &str, templates: &mut [Template]) -> (PathBuf, DbSummary) {
    let path = dir.join(name);
    let mut writer = DbWriter::create(&path).unwrap();
    writer.set_metadata("test", &serde_json::json!({"name": name})).unwrap();
    for batch in templates.chunks_mut(500) {
        writer.insert_batch(batch).unwrap();
    }
    let summary = writer.finish().unwrap();
    (path, summary)
}
