//! What the template listing (`GET /v1/templates` as JSON) answers, and its
//! paging limits: shared by the API, the footprint answer, and the client of
//! `trn coverage --server`.

use serde::Serialize;
use trn_landmark::{GeoBox, Template};
use utoipa::ToSchema;

/// Templates per `/v1/templates` answer unless `limit` says otherwise, and at most.
pub const DEFAULT_LIMIT: usize = 1000;
pub const MAX_LIMIT: usize = 10_000;
/// Largest `offset` (paging deeper than this is a scan, not a navigator query).
pub const MAX_OFFSET: usize = 1_000_000;
/// GeoJSON media type (`Accept` of `/v1/coverage`).
pub const GEOJSON: &str = "application/geo+json";

/// A template without pixels and height grid (the JSON listing).
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct TemplateSummary {
    pub id: i64,
    /// Centre: WGS84 latitude and longitude (deg), ellipsoidal height (m).
    pub lat: f64,
    pub lon: f64,
    pub h: f64,
    pub level: u8,
    pub gsd_m: f64,
    pub width_px: u32,
    pub height_px: u32,
    /// Footprint box (deg); `min_lon_deg > max_lon_deg` crosses the antimeridian.
    #[schema(value_type = Object)]
    pub footprint: GeoBox,
    /// Terrain plane normal in the template's ENU frame, and the RMS residual (m).
    pub plane_normal_enu: [f64; 3],
    pub plane_residual_rms_m: f64,
    pub shi_tomasi: f32,
    pub contrast_std: f32,
    pub second_peak_ncc: f32,
    /// Share of the contrast relief shading could make (0 albedo .. 1 shading).
    pub shading_share: f32,
    /// 0: the ortho as imaged; k: rendered under the k-th of the database's `suns`.
    pub lighting: u8,
}

impl From<&Template> for TemplateSummary {
    fn from(t: &Template) -> Self {
        Self {
            id: t.id,
            lat: t.center.lat_deg,
            lon: t.center.lon_deg,
            h: t.center.h_m,
            level: t.level,
            gsd_m: t.gsd_m,
            width_px: t.width_px,
            height_px: t.height_px,
            footprint: t.footprint,
            plane_normal_enu: t.terrain.plane_normal_enu,
            plane_residual_rms_m: t.terrain.plane_residual_rms_m,
            shi_tomasi: t.quality.shi_tomasi,
            contrast_std: t.quality.contrast_std,
            second_peak_ncc: t.quality.second_peak_ncc,
            shading_share: t.quality.shading_share,
            lighting: t.lighting,
        }
    }
}
