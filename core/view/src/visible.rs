//! Which landmarks a camera pose can use, without an image: the footprint
//! ([`crate::footprint`], horizon and angle filter), the database levels
//! around the one whose templates span about [`TARGET_PATCH_PX`] image
//! pixels at the image centre, each template kept only where its level fits
//! the local ground resolution best, and only where it
//! projects into the image. This is the selection of the per-frame pipeline
//! (`nav.rs`, before the spread over image cells), shared with the landmark
//! server's footprint and coverage queries.

use trn_camera::{CameraModel, CameraPose};
use trn_geodesy::Geodetic;
use trn_landmark::{GeoBox, Template};
use trn_store::LevelInfo;

use crate::footprint::{footprint, Footprint, FootprintError, FootprintParams};
use crate::source::{LandmarkSource, SourceError};

/// Levels queried on either side of the level that fits the image centre.
pub const LEVEL_SPAN: u8 = 2;

/// Radius around a position within which [`terrain_near`] looks (m).
pub const TERRAIN_RADIUS_M: f64 = 20_000.0;

/// Image pixels a template of the level chosen for a ground resolution spans
/// (the levels' footprints double, so the chosen one spans 23–45 px).
pub const TARGET_PATCH_PX: f64 = 32.0;

/// A database level as navigators choose it: by the ground its templates
/// span (a level may hold small native-resolution templates or larger
/// downsampled ones; what matters in the image is the footprint).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DbLevel {
    pub level: u8,
    /// Side of the level's templates on the ground (m).
    pub footprint_m: f64,
}

impl DbLevel {
    /// The levels of a database summary.
    pub fn of(infos: &[LevelInfo]) -> Vec<DbLevel> {
        infos
            .iter()
            .map(|l| DbLevel { level: l.level, footprint_m: l.gsd_m * l.template_px as f64 })
            .collect()
    }

    /// Image pixels a template of this level spans at `local_gsd_m`.
    pub fn span_px(&self, local_gsd_m: f64) -> f64 {
        self.footprint_m / local_gsd_m
    }
}

/// Database level whose templates span closest (in ratio) to
/// [`TARGET_PATCH_PX`] image pixels at `local_gsd_m` (m per pixel); `None`
/// without levels.
pub fn level_for(levels: &[DbLevel], local_gsd_m: f64) -> Option<DbLevel> {
    let miss = |l: &DbLevel| (l.span_px(local_gsd_m) / TARGET_PATCH_PX).ln().abs();
    levels.iter().copied().min_by(|a, b| miss(a).total_cmp(&miss(b)))
}

/// Smallest size (image pixels) of a template one level finer than the local
/// resolution for it to be used as well.
pub const MIN_FINE_PATCH_PX: f64 = 14.0;

/// Whether a template seen at `local_gsd_m` (m per image pixel) is used: its
/// level fits the local resolution best, or it is one level finer and still
/// spans [`MIN_FINE_PATCH_PX`] (more landmarks, whose independent errors
/// average out the narrow view's tilt/shift ambiguity).
pub fn level_fits(levels: &[DbLevel], t: &Template, local_gsd_m: f64) -> bool {
    let Some(DbLevel { level: best, .. }) = level_for(levels, local_gsd_m) else { return false };
    best == t.level
        || (best == t.level.saturating_add(1)
            && t.width_px as f64 * t.gsd_m / local_gsd_m >= MIN_FINE_PATCH_PX)
}

/// Ground sample distance (m per image pixel) at which the camera sees a
/// template, stretched by the incidence as in the navigator.
pub fn local_gsd_m(camera: &CameraModel, pose: &CameraPose, t: &Template) -> f64 {
    let c = t.center_ecef();
    let range = pose.position.distance_m(&c);
    let up = t.center.up_ecef();
    let cos_inc = ((pose.position.0 - c.0) / range.max(1e-9)).dot(&up).max(0.2);
    range / camera.fx.min(camera.fy) / cos_inc.sqrt()
}

/// The terrain near a position, as the navigator takes it for its first footprint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TerrainNear {
    /// Median height of the coarsest level's templates within
    /// [`TERRAIN_RADIUS_M`] (0 when there are none).
    pub height_m: f64,
}

/// See [`TerrainNear`].
pub fn terrain_near(
    source: &dyn LandmarkSource,
    levels: &[DbLevel],
    at: &Geodetic,
) -> Result<TerrainNear, SourceError> {
    let (m_lat, m_lon) = trn_geodesy::metres_per_degree(at.lat_deg);
    let (dlat, dlon) = (TERRAIN_RADIUS_M / m_lat, TERRAIN_RADIUS_M / m_lon.max(1.0));
    let bbox = GeoBox::new(
        (at.lon_deg - dlon).max(-180.0),
        (at.lat_deg - dlat).max(-90.0),
        (at.lon_deg + dlon).min(180.0),
        (at.lat_deg + dlat).min(90.0),
    );
    let Some(coarsest) = levels.iter().map(|l| l.level).max() else {
        return Ok(TerrainNear { height_m: 0.0 });
    };
    let near = source.query(&bbox, coarsest)?;
    let mut h: Vec<f64> = near.iter().map(|t| t.center.h_m).collect();
    h.sort_by(f64::total_cmp);
    Ok(TerrainNear { height_m: h.get(h.len() / 2).copied().unwrap_or(0.0) })
}

/// The landmarks a pose can use.
#[derive(Clone, Debug)]
pub struct View {
    pub footprint: Footprint,
    /// The level that fits the image centre.
    pub center_level: u8,
    /// Templates in view, each at the level that fits its local GSD, in the
    /// source's order per level, levels finest first.
    pub templates: Vec<Template>,
}

/// Why a pose sees no landmarks at all.
#[derive(Debug, thiserror::Error)]
pub enum ViewError {
    #[error(transparent)]
    Footprint(#[from] FootprintError),
    #[error(transparent)]
    Source(#[from] SourceError),
    #[error("the landmark database has no templates")]
    NoLevels,
}

/// The templates `pose` can use (see the module documentation).
pub fn landmarks_in_view(
    source: &dyn LandmarkSource,
    levels: &[DbLevel],
    camera: &CameraModel,
    pose: &CameraPose,
    params: &FootprintParams,
) -> Result<View, ViewError> {
    let fp = footprint(camera, pose, params)?;
    let center_level = level_for(levels, fp.center_gsd_m).ok_or(ViewError::NoLevels)?.level;
    let lo = center_level.saturating_sub(LEVEL_SPAN);
    let hi = center_level.saturating_add(LEVEL_SPAN);
    let (w, h) = (camera.width as f64, camera.height as f64);
    // A database lit for several suns holds each landmark once per sun: count
    // each once (its first lighting).
    let first_lighting = (!source.suns()?.is_empty()).then_some(1u8);
    let mut templates = Vec::new();
    for l in levels.iter().map(|l| l.level).filter(|&l| l >= lo && l <= hi) {
        let found = match first_lighting {
            Some(k) => source.query_lit(&fp.bbox, l, k)?,
            None => source.query(&fp.bbox, l)?,
        };
        for t in found {
            if !level_fits(levels, &t, local_gsd_m(camera, pose, &t)) {
                continue;
            }
            let Some(p) = pose.project(camera, &t.center_ecef()) else { continue };
            if p.u >= 0.0 && p.v >= 0.0 && p.u < w && p.v < h {
                templates.push(t);
            }
        }
    }
    Ok(View { footprint: fp, center_level, templates })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn level_for_picks_the_closest_ratio() {
        // 16-px templates at 4 m, then 32 px at 4 and 8 m: footprints 64, 128, 256 m.
        let levels = [
            DbLevel { level: 0, footprint_m: 64.0 },
            DbLevel { level: 1, footprint_m: 128.0 },
            DbLevel { level: 2, footprint_m: 256.0 },
        ];
        let at = |g: f64| level_for(&levels, g).map(|l| l.level);
        // 64 m spans 32 px at 2 m; 128 m spans 32 px at 4 m.
        assert_eq!(at(2.0), Some(0));
        assert_eq!(at(2.7), Some(0));
        assert_eq!(at(3.0), Some(1));
        assert_eq!(at(5.0), Some(1));
        assert_eq!(at(6.0), Some(2));
        assert_eq!(at(1000.0), Some(2));
        assert_eq!(at(0.01), Some(0));
        assert_eq!(level_for(&[], 5.0), None);
        // The boundary between two levels is where both miss by the same ratio.
        let edge = 128.0 / TARGET_PATCH_PX / 2f64.sqrt();
        assert_eq!(at(edge * 0.99), Some(0));
        assert_eq!(at(edge * 1.01), Some(1));
    }

    #[test]
    fn levels_of_a_summary_carry_their_footprint() {
        let info = |level, gsd_m, template_px| LevelInfo {
            level,
            gsd_m,
            template_px,
            count: 1,
            extent: GeoBox::new(0.0, 0.0, 1.0, 1.0),
        };
        let l = DbLevel::of(&[info(0, 30.0, 16), info(1, 30.0, 32), info(2, 60.0, 32)]);
        assert_eq!(l.iter().map(|l| l.footprint_m).collect::<Vec<_>>(), [480.0, 960.0, 1920.0]);
        assert!((l[1].span_px(15.0) - 64.0).abs() < 1e-12);
    }
}
