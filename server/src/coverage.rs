//! Footprint and coverage queries: which landmarks a camera pose can use
//! (`POST /v1/footprint`), and how many along a planned trajectory
//! (`POST /v1/coverage`, `trn coverage`), with the navigator's own selection
//! ([`trn_view`]: footprint with horizon walking and angle filter,
//! level fit, projection into the image); the report as GeoJSON. The
//! request types check their fields and answer [`ApiError`]s that name them.
//! `trn coverage` ([`crate::coverage_cli`]) writes the report and draws it.

use serde::{Deserialize, Serialize};
use trn_camera::{CameraModel, CameraPose, Distortion};
use trn_geodesy::{Ecef, Enu, Geodetic, LocalFrame};
use trn_landmark::{GeoBox, Template};
use trn_view::{landmarks_in_view, terrain_near, DbLevel, FootprintParams, LandmarkSource, ViewError};
use utoipa::ToSchema;

use crate::error::ApiError;
use crate::listing::TemplateSummary;

/// Landmarks in view below this count make a stretch of poor coverage.
pub const DEFAULT_THRESHOLD: usize = 8;
/// Most trajectory points one coverage request may have (after densifying).
pub const MAX_POINTS: usize = 10_000;
/// Largest image side accepted (px).
pub const MAX_IMAGE_SIDE: u32 = 65_536;
/// Templates listed by a footprint answer unless `limit` says otherwise, and at most.
pub const DEFAULT_FOOTPRINT_LIMIT: usize = 1000;
pub const MAX_FOOTPRINT_LIMIT: usize = 10_000;

/// A camera: either `hfov_deg` (distortion-free, square pixels, centred
/// principal point) or the flight format's `camera.json` fields (`fx`, `fy`,
/// `cx`, `cy`, optional `distortion`; `q_cam_imu` is accepted and ignored).
#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CameraIn {
    /// Image size (px).
    pub width: u32,
    pub height: u32,
    /// Horizontal field of view, edge to edge (deg).
    pub hfov_deg: Option<f64>,
    /// Focal lengths and principal point (px; (0, 0) is the top-left pixel's centre).
    pub fx: Option<f64>,
    pub fy: Option<f64>,
    pub cx: Option<f64>,
    pub cy: Option<f64>,
    /// Brown-Conrady coefficients `{k1, k2, p1, p2, k3}` as in `camera.json`.
    #[schema(value_type = Option<Object>)]
    pub distortion: Option<Distortion>,
    /// Camera mounting of `camera.json`; ignored here.
    pub q_cam_imu: Option<[f64; 4]>,
}

impl CameraIn {
    pub fn to_model(&self, field: &str) -> Result<CameraModel, ApiError> {
        let bad = |m: String| ApiError::unprocessable(format!("{field}: {m}"));
        if self.width == 0 || self.height == 0 || self.width > MAX_IMAGE_SIDE || self.height > MAX_IMAGE_SIDE
        {
            return Err(bad(format!(
                "image size {}x{} px; each side must be 1..={MAX_IMAGE_SIDE}",
                self.width, self.height
            )));
        }
        let model = match (self.hfov_deg, self.fx, self.fy) {
            (Some(h), None, None) => {
                if !(h > 0.0 && h < 180.0) {
                    return Err(bad(format!("hfov_deg {h} must be in (0, 180) degrees")));
                }
                CameraModel::from_fov(self.width, self.height, h)
            }
            (None, Some(fx), Some(fy)) => CameraModel {
                width: self.width,
                height: self.height,
                fx,
                fy,
                cx: self.cx.unwrap_or(0.5 * (self.width as f64 - 1.0)),
                cy: self.cy.unwrap_or(0.5 * (self.height as f64 - 1.0)),
                distortion: self.distortion.unwrap_or_default(),
            },
            _ => {
                return Err(bad(
                    "give either hfov_deg, or fx and fy (with optional cx, cy, distortion)".into()
                ))
            }
        };
        model.validate().map_err(|e| bad(e.to_string()))?;
        Ok(model)
    }
}

/// A camera pose: WGS84 position and the attitude `q_ecef_cam` (`[w, x, y, z]`,
/// rotates camera-frame vectors into ECEF, as in the flight format).
#[derive(Clone, Copy, Debug, Deserialize, Serialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct PoseIn {
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid (m).
    pub h_m: f64,
    pub q_ecef_cam: [f64; 4],
}

/// A trajectory point without attitude (the attitude rule gives it).
#[derive(Clone, Copy, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct WaypointIn {
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid (m).
    pub h_m: f64,
}

/// How the camera points at a waypoint: tilted `tilt_deg` from nadir toward
/// the direction of travel turned clockwise by `azimuth_deg` (0: ahead, 90:
/// right); image up points that way (nadir: the direction of travel).
#[derive(Clone, Copy, Debug, Default, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct AttitudeRule {
    #[serde(default)]
    pub tilt_deg: f64,
    #[serde(default)]
    pub azimuth_deg: f64,
}

/// Largest height accepted for a pose (m): far beyond any camera that sees landmarks.
const MAX_HEIGHT_M: f64 = 1.0e8;

fn check_position(field: &str, lat: f64, lon: f64, h: f64) -> Result<Geodetic, ApiError> {
    let bad = |m: String| Err(ApiError::unprocessable(format!("{field}: {m}")));
    if !(lat.abs() <= 90.0) {
        return bad(format!("lat_deg {lat} is not in [-90, 90]"));
    }
    if !(lon.abs() <= 180.0) {
        return bad(format!("lon_deg {lon} is not in [-180, 180]"));
    }
    if !(h.abs() <= MAX_HEIGHT_M) {
        return bad(format!("h_m {h} is not a height in [-1e8, 1e8] m"));
    }
    Ok(Geodetic::new(lat, lon, h))
}

impl PoseIn {
    pub fn to_pose(&self, field: &str) -> Result<(Geodetic, CameraPose), ApiError> {
        let g = check_position(field, self.lat_deg, self.lon_deg, self.h_m)?;
        let q = self.q_ecef_cam;
        let norm = q.iter().map(|x| x * x).sum::<f64>().sqrt();
        if !(norm > 1e-6 && norm.is_finite()) {
            return Err(ApiError::unprocessable(format!(
                "{field}: q_ecef_cam {q:?} is not a rotation (a non-zero [w, x, y, z])"
            )));
        }
        Ok((g, CameraPose::new(g.to_ecef(), trn_camera::quat_from_wxyz(q))))
    }
}

fn check_alpha(alpha: Option<f64>) -> Result<f64, ApiError> {
    let a = alpha.unwrap_or(75.0);
    if !(a > 0.0 && a < 90.0) {
        return Err(ApiError::unprocessable(format!("alpha_max_deg {a} must be in (0, 90) degrees")));
    }
    Ok(a)
}

fn check_terrain(h: Option<f64>) -> Result<Option<f64>, ApiError> {
    match h {
        Some(h) if !(h.abs() <= 20_000.0) => {
            Err(ApiError::unprocessable(format!("terrain_h_m {h} is not a terrain height in [-2e4, 2e4] m")))
        }
        _ => Ok(h),
    }
}

/// `POST /v1/footprint` body.
#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct FootprintRequest {
    pub camera: CameraIn,
    pub pose: PoseIn,
    /// Largest angle between a line of sight and the surface normal (deg, default 75).
    pub alpha_max_deg: Option<f64>,
    /// Height of the ellipsoid the image corners are projected on (m); default:
    /// the median template height within 20 km, as the navigator starts.
    pub terrain_h_m: Option<f64>,
    /// Most templates listed (default 1000, at most 10000); `count` has them all.
    pub limit: Option<usize>,
}

/// A point on the ground (deg).
#[derive(Clone, Copy, Debug, Serialize, ToSchema)]
pub struct LatLon {
    pub lat_deg: f64,
    pub lon_deg: f64,
}

/// `POST /v1/footprint` answer.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct FootprintResponse {
    /// Box around the walked corners and edge midpoints (deg).
    #[schema(value_type = Object)]
    pub bbox: GeoBox,
    /// Image corners after horizon walking and the angle filter (TL, TR, BR, BL).
    pub corners: Vec<LatLon>,
    pub horizon_in_view: bool,
    pub angle_limited: bool,
    /// Ground sample distance at the image centre (m/px) and the level that fits it.
    pub center_gsd_m: f64,
    pub center_level: u8,
    pub terrain_h_m: f64,
    /// Usable landmarks in view (each at the level that fits its local GSD, inside the image).
    pub count: usize,
    pub templates: Vec<TemplateSummary>,
    pub truncated: bool,
}

fn view_error(field: &str, e: ViewError) -> ApiError {
    match e {
        ViewError::Source(e) => ApiError::internal(e.0),
        e => ApiError::unprocessable(format!("{field}: {e}")),
    }
}

fn terrain_for(
    source: &dyn LandmarkSource,
    levels: &[DbLevel],
    given: Option<f64>,
    at: &Geodetic,
) -> Result<f64, ApiError> {
    match given {
        Some(h) => Ok(h),
        None => terrain_near(source, levels, at).map(|t| t.height_m).map_err(|e| ApiError::internal(e.0)),
    }
}

/// Checks a footprint request before it reaches the database.
pub fn check_footprint(
    req: &FootprintRequest,
) -> Result<(CameraModel, CameraPose, Geodetic, f64, usize), ApiError> {
    let camera = req.camera.to_model("camera")?;
    let (g, pose) = req.pose.to_pose("pose")?;
    let alpha = check_alpha(req.alpha_max_deg)?;
    check_terrain(req.terrain_h_m)?;
    let limit = req.limit.unwrap_or(DEFAULT_FOOTPRINT_LIMIT);
    if !(1..=MAX_FOOTPRINT_LIMIT).contains(&limit) {
        return Err(ApiError::unprocessable(format!("limit {limit} must be in 1..={MAX_FOOTPRINT_LIMIT}")));
    }
    Ok((camera, pose, g, alpha, limit))
}

/// The landmarks one pose can use.
pub fn footprint_query(
    source: &dyn LandmarkSource,
    levels: &[DbLevel],
    req: &FootprintRequest,
) -> Result<FootprintResponse, ApiError> {
    let (camera, pose, g, alpha, limit) = check_footprint(req)?;
    let terrain_h_m = terrain_for(source, levels, req.terrain_h_m, &g)?;
    let params = FootprintParams { alpha_max_deg: alpha, terrain_h_m, ..Default::default() };
    let view =
        landmarks_in_view(source, levels, &camera, &pose, &params).map_err(|e| view_error("pose", e))?;
    let fp = &view.footprint;
    let count = view.templates.len();
    Ok(FootprintResponse {
        bbox: fp.bbox,
        corners: fp.corners.iter().map(|c| LatLon { lat_deg: c.lat_deg, lon_deg: c.lon_deg }).collect(),
        horizon_in_view: fp.horizon_in_view,
        angle_limited: fp.angle_limited,
        center_gsd_m: fp.center_gsd_m,
        center_level: view.center_level,
        terrain_h_m,
        count,
        templates: view.templates.iter().take(limit).map(TemplateSummary::from).collect(),
        truncated: count > limit,
    })
}

/// `POST /v1/coverage` body (and `trn coverage --plan`): a camera and either
/// `poses`, or `waypoints` with an `attitude` rule (and `step_m` to add points
/// between them).
#[derive(Clone, Debug, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct CoverageRequest {
    pub camera: CameraIn,
    pub poses: Option<Vec<PoseIn>>,
    pub waypoints: Option<Vec<WaypointIn>>,
    pub attitude: Option<AttitudeRule>,
    /// With waypoints: a point at least every `step_m` metres along the way.
    pub step_m: Option<f64>,
    /// Fewer usable landmarks than this make a stretch of poor coverage (default 8).
    pub threshold: Option<usize>,
    pub alpha_max_deg: Option<f64>,
    /// Terrain height for every point (m); default: per point, as `/v1/footprint`.
    pub terrain_h_m: Option<f64>,
}

/// One trajectory point's coverage.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CoveragePoint {
    pub index: usize,
    pub lat_deg: f64,
    pub lon_deg: f64,
    pub h_m: f64,
    /// Usable landmarks in view.
    pub landmarks: usize,
    /// The level fitting the image centre (null when no ground is in view).
    pub center_level: Option<u8>,
    /// The footprint's box (null when no ground is in view).
    #[schema(value_type = Option<Object>)]
    pub bbox: Option<GeoBox>,
    /// Why no landmark can be in view (sky, below the terrain), if so.
    pub note: Option<String>,
}

/// Consecutive points below the threshold.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct Stretch {
    pub start_index: usize,
    pub end_index: usize,
    pub min_landmarks: usize,
    /// Along the trajectory, first to last point of the stretch (m).
    pub length_m: f64,
}

/// `POST /v1/coverage` answer.
#[derive(Clone, Debug, Serialize, Deserialize, ToSchema)]
pub struct CoverageReport {
    pub threshold: usize,
    pub points: Vec<CoveragePoint>,
    pub stretches: Vec<Stretch>,
    pub min_landmarks: usize,
    /// Share of the points below the threshold.
    pub share_below: f64,
}

/// The trajectory's poses, checked (waypoints turned into poses by the rule).
pub fn plan_poses(req: &CoverageRequest) -> Result<(CameraModel, Vec<(Geodetic, CameraPose)>), ApiError> {
    let camera = req.camera.to_model("camera")?;
    check_alpha(req.alpha_max_deg)?;
    check_terrain(req.terrain_h_m)?;
    if let Some(t) = req.threshold {
        if t > 1_000_000 {
            return Err(ApiError::unprocessable(format!("threshold {t} must be at most 1000000")));
        }
    }
    let poses = match (&req.poses, &req.waypoints) {
        (Some(p), None) => {
            if req.attitude.is_some() || req.step_m.is_some() {
                return Err(ApiError::unprocessable("attitude and step_m go with waypoints, not poses"));
            }
            if p.len() > MAX_POINTS {
                return Err(too_many(p.len()));
            }
            p.iter()
                .enumerate()
                .map(|(i, p)| p.to_pose(&format!("poses[{i}]")))
                .collect::<Result<Vec<_>, _>>()?
        }
        (None, Some(w)) => waypoint_poses(w, req.attitude.unwrap_or_default(), req.step_m)?,
        _ => return Err(ApiError::unprocessable("give either poses or waypoints (exactly one of them)")),
    };
    if poses.is_empty() {
        return Err(ApiError::unprocessable("the trajectory has no points"));
    }
    Ok((camera, poses))
}

fn too_many(n: usize) -> ApiError {
    ApiError::new(
        axum::http::StatusCode::PAYLOAD_TOO_LARGE,
        format!("{n} trajectory points; at most {MAX_POINTS} per request (split the trajectory)"),
    )
}

fn waypoint_poses(
    w: &[WaypointIn],
    rule: AttitudeRule,
    step_m: Option<f64>,
) -> Result<Vec<(Geodetic, CameraPose)>, ApiError> {
    if !(rule.tilt_deg >= 0.0 && rule.tilt_deg < 90.0) {
        return Err(ApiError::unprocessable(format!(
            "attitude.tilt_deg {} must be in [0, 90)",
            rule.tilt_deg
        )));
    }
    if !rule.azimuth_deg.is_finite() {
        return Err(ApiError::unprocessable("attitude.azimuth_deg must be a number of degrees"));
    }
    if let Some(s) = step_m {
        if !(s >= 1.0 && s.is_finite()) {
            return Err(ApiError::unprocessable(format!("step_m {s} must be at least 1 m")));
        }
    }
    if w.len() > MAX_POINTS {
        return Err(too_many(w.len()));
    }
    let pts: Vec<Geodetic> = w
        .iter()
        .enumerate()
        .map(|(i, p)| check_position(&format!("waypoints[{i}]"), p.lat_deg, p.lon_deg, p.h_m))
        .collect::<Result<_, _>>()?;
    // Densify: linear in latitude, longitude (the short way round) and height.
    let mut dense = Vec::new();
    for (i, p) in pts.iter().enumerate() {
        dense.push(*p);
        let (Some(s), Some(q)) = (step_m, pts.get(i + 1)) else { continue };
        let n = (p.to_ecef().distance_m(&q.to_ecef()) / s).ceil();
        if n as usize + dense.len() > MAX_POINTS {
            return Err(too_many(n as usize + dense.len()));
        }
        let dlon = (q.lon_deg - p.lon_deg + 540.0).rem_euclid(360.0) - 180.0;
        for k in 1..n as usize {
            let f = k as f64 / n;
            let lon = (p.lon_deg + f * dlon + 540.0).rem_euclid(360.0) - 180.0;
            dense.push(Geodetic::new(
                p.lat_deg + f * (q.lat_deg - p.lat_deg),
                lon,
                p.h_m + f * (q.h_m - p.h_m),
            ));
        }
    }
    let mut out = Vec::with_capacity(dense.len());
    let mut heading = Enu::new(0.0, 1.0, 0.0);
    for i in 0..dense.len() {
        let frame = LocalFrame::at(dense[i]);
        // Direction of travel: toward the next point (the last keeps the previous).
        if let Some(next) = dense.get(i + 1) {
            let d = frame.to_enu(&next.to_ecef()).0;
            let horiz = nalgebra::Vector3::new(d.x, d.y, 0.0);
            if horiz.norm() > 1e-6 {
                heading = Enu(horiz.normalize());
            }
        }
        let az = rule.azimuth_deg.to_radians();
        let (s, c) = az.sin_cos();
        // Clockwise from the heading, seen from above (east = north turned right).
        let dir =
            nalgebra::Vector3::new(c * heading.0.x + s * heading.0.y, c * heading.0.y - s * heading.0.x, 0.0);
        let tilt = rule.tilt_deg.to_radians();
        let look = dir * tilt.sin() - nalgebra::Vector3::z() * tilt.cos();
        let pos = dense[i].to_ecef();
        let to_ecef = |v: nalgebra::Vector3<f64>| frame.vector_to_ecef(&v);
        let target = Ecef(pos.0 + to_ecef(look) * 1000.0);
        out.push((dense[i], CameraPose::look_at(pos, target, to_ecef(dir))));
    }
    Ok(out)
}

/// Usable landmarks at every point of the trajectory, and the stretches below the threshold.
pub fn coverage_query(
    source: &dyn LandmarkSource,
    levels: &[DbLevel],
    req: &CoverageRequest,
) -> Result<CoverageReport, ApiError> {
    let (camera, poses) = plan_poses(req)?;
    let alpha = check_alpha(req.alpha_max_deg)?;
    let threshold = req.threshold.unwrap_or(DEFAULT_THRESHOLD);
    let mut points = Vec::with_capacity(poses.len());
    for (i, (g, pose)) in poses.iter().enumerate() {
        let terrain_h_m = terrain_for(source, levels, req.terrain_h_m, g)?;
        let params = FootprintParams { alpha_max_deg: alpha, terrain_h_m, ..Default::default() };
        let (landmarks, center_level, bbox, note) =
            match landmarks_in_view(source, levels, &camera, pose, &params) {
                Ok(v) => (v.templates.len(), Some(v.center_level), Some(v.footprint.bbox), None),
                Err(ViewError::Source(e)) => return Err(ApiError::internal(e.0)),
                Err(e) => (0, None, None, Some(e.to_string())),
            };
        points.push(CoveragePoint {
            index: i,
            lat_deg: g.lat_deg,
            lon_deg: g.lon_deg,
            h_m: g.h_m,
            landmarks,
            center_level,
            bbox,
            note,
        });
    }
    let mut stretches = Vec::new();
    let mut i = 0;
    while i < points.len() {
        if points[i].landmarks >= threshold {
            i += 1;
            continue;
        }
        let start = i;
        let mut length_m = 0.0;
        while i + 1 < points.len() && points[i + 1].landmarks < threshold {
            length_m += poses[i].1.position.distance_m(&poses[i + 1].1.position);
            i += 1;
        }
        let min_landmarks = points[start..=i].iter().map(|p| p.landmarks).min().unwrap_or(0);
        stretches.push(Stretch { start_index: start, end_index: i, min_landmarks, length_m });
        i += 1;
    }
    let below = points.iter().filter(|p| p.landmarks < threshold).count();
    Ok(CoverageReport {
        threshold,
        min_landmarks: points.iter().map(|p| p.landmarks).min().unwrap_or(0),
        share_below: below as f64 / points.len() as f64,
        points,
        stretches,
    })
}

/// The report as a GeoJSON FeatureCollection (RFC 7946, lon/lat/h): the whole
/// trajectory as a LineString, each stretch below the threshold as a
/// LineString, each point as a Point with its landmark count.
pub fn to_geojson(r: &CoverageReport) -> serde_json::Value {
    use serde_json::json;
    let coord = |p: &CoveragePoint| json!([p.lon_deg, p.lat_deg, p.h_m]);
    let mut features = vec![json!({
        "type": "Feature",
        "geometry": {"type": "LineString", "coordinates": r.points.iter().map(coord).collect::<Vec<_>>()},
        "properties": {"kind": "trajectory", "threshold": r.threshold, "min_landmarks": r.min_landmarks},
    })];
    for s in &r.stretches {
        let pts: Vec<_> = r.points[s.start_index..=s.end_index].iter().map(coord).collect();
        let geometry = if pts.len() == 1 {
            json!({"type": "Point", "coordinates": pts[0]})
        } else {
            json!({"type": "LineString", "coordinates": pts})
        };
        features.push(json!({
            "type": "Feature",
            "geometry": geometry,
            "properties": {"kind": "below_threshold", "start_index": s.start_index, "end_index": s.end_index,
                           "min_landmarks": s.min_landmarks, "length_m": s.length_m},
        }));
    }
    for p in &r.points {
        features.push(json!({
            "type": "Feature",
            "geometry": {"type": "Point", "coordinates": coord(p)},
            "properties": {"kind": "point", "index": p.index, "landmarks": p.landmarks,
                           "below_threshold": p.landmarks < r.threshold},
        }));
    }
    json!({"type": "FeatureCollection", "features": features})
}

/// What the map needs of a template: its level and footprint (the
/// `GET /v1/templates` JSON listing has both, under these names).
#[derive(Clone, Copy, Debug, PartialEq, Deserialize)]
pub struct TemplateBox {
    pub level: u8,
    pub footprint: GeoBox,
}

impl From<&Template> for TemplateBox {
    fn from(t: &Template) -> Self {
        Self { level: t.level, footprint: t.footprint }
    }
}

/// The area whose templates the map of `report` draws: the box around the
/// points' footprint boxes, clamped to the globe (a valid `bbox` for the
/// server; no footprint lies beyond). `None` when no point sees the ground.
pub fn map_area(report: &CoverageReport) -> Option<GeoBox> {
    let b = GeoBox::around(
        report
            .points
            .iter()
            .filter_map(|p| p.bbox)
            .flat_map(|b| [(b.min_lon_deg, b.min_lat_deg), (b.max_lon_deg, b.max_lat_deg)]),
    )?;
    let (lon, lat) = (|x: f64| x.clamp(-180.0, 180.0), |x: f64| x.clamp(-90.0, 90.0));
    Some(GeoBox::new(lon(b.min_lon_deg), lat(b.min_lat_deg), lon(b.max_lon_deg), lat(b.max_lat_deg)))
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_landmark::{HeightGrid, TemplateQuality, TerrainPatch};
    use trn_store::LevelInfo;
    use trn_view::SourceError;

    /// One level of 32 px templates at 10 m (320 m footprints), on the ground
    /// (h = 0) every 0.005 deg of a box, and nothing else.
    struct Grid {
        templates: Vec<Template>,
    }

    impl Grid {
        fn new(lon: (f64, f64), lat: (f64, f64)) -> Self {
            let mut templates = Vec::new();
            let step = 0.005;
            let (nx, ny) = (((lon.1 - lon.0) / step) as usize, ((lat.1 - lat.0) / step) as usize);
            for j in 0..=ny {
                for i in 0..=nx {
                    let t = Template {
                        id: templates.len() as i64 + 1,
                        level: 0,
                        gsd_m: 10.0,
                        width_px: 32,
                        height_px: 32,
                        center: Geodetic::new(lat.0 + j as f64 * step, lon.0 + i as f64 * step, 0.0),
                        footprint: GeoBox::new(0.0, 0.0, 0.0, 0.0),
                        terrain: TerrainPatch {
                            plane_normal_enu: [0.0, 0.0, 1.0],
                            plane_residual_rms_m: 0.0,
                            height_grid: HeightGrid { n: 2, spacing_m: 320.0, heights_m: vec![0.0; 4] },
                        },
                        quality: TemplateQuality {
                            shi_tomasi: 10.0,
                            contrast_std: 20.0,
                            second_peak_ncc: 0.5,
                            shading_share: 0.0,
                        },
                        source: 0,
                        lighting: 0,
                        pixels: vec![128; 32 * 32],
                    };
                    let corners = t.footprint_corners();
                    let footprint = GeoBox::around(corners.iter().map(|g| (g.lon_deg, g.lat_deg))).unwrap();
                    templates.push(Template { footprint, ..t });
                }
            }
            Self { templates }
        }
    }

    impl LandmarkSource for Grid {
        fn levels(&self) -> Result<Vec<trn_store::LevelInfo>, SourceError> {
            let extent = GeoBox::around(self.templates.iter().flat_map(|t| {
                let f = t.footprint;
                [(f.min_lon_deg, f.min_lat_deg), (f.max_lon_deg, f.max_lat_deg)]
            }))
            .unwrap();
            Ok(vec![LevelInfo {
                level: 0,
                gsd_m: 10.0,
                template_px: 32,
                count: self.templates.len() as u64,
                extent,
            }])
        }

        fn query(&self, bbox: &GeoBox, level: u8) -> Result<Vec<Template>, SourceError> {
            Ok(self
                .templates
                .iter()
                .filter(|t| t.level == level && t.footprint.intersects(bbox))
                .cloned()
                .collect())
        }
    }

    /// A nadir pass at 10 km from over the landmarks (west) to beyond them (east).
    fn plan() -> CoverageRequest {
        serde_json::from_value(serde_json::json!({
            "camera": {"width": 1024, "height": 768, "hfov_deg": 40.0},
            "waypoints": [{"lat_deg": 40.0, "lon_deg": -111.0, "h_m": 10000.0},
                          {"lat_deg": 40.0, "lon_deg": -110.5, "h_m": 10000.0}],
            "attitude": {"tilt_deg": 0.0},
            "step_m": 2000.0,
            "threshold": 60,
            "terrain_h_m": 0.0
        }))
        .unwrap()
    }

    #[test]
    fn coverage_counts_the_landmarks_in_view_and_finds_the_stretch_without() {
        let source = Grid::new((-111.05, -110.85), (39.95, 40.05));
        let levels = DbLevel::of(&source.levels().unwrap());
        let r = coverage_query(&source, &levels, &plan()).unwrap();
        // 0.5 deg of longitude at 40 deg N is 42.6 km: a point every 2 km or less.
        assert!(r.points.len() >= 22, "{}", r.points.len());
        // Over the grid a 7.3 x 5.5 km view holds ~130 of its 430 x 560 m cells.
        let first = &r.points[0];
        assert!(first.landmarks > 100 && first.center_level == Some(0), "{first:?}");
        // East of -110.8 (the grid's edge plus half a view) nothing is in view:
        // one stretch from where the count drops below 60 to the end.
        let far: Vec<_> = r.points.iter().filter(|p| p.lon_deg > -110.78).collect();
        assert!(!far.is_empty() && far.iter().all(|p| p.landmarks == 0), "{far:?}");
        assert_eq!(r.stretches.len(), 1, "{:?}", r.stretches);
        let s = &r.stretches[0];
        assert_eq!(s.end_index, r.points.len() - 1);
        assert!(r.points[..s.start_index].iter().all(|p| p.landmarks >= 60));
        assert!(r.points[s.start_index..].iter().all(|p| p.landmarks < 60));
        assert_eq!((s.min_landmarks, r.min_landmarks), (0, 0));
        let below = r.points.len() - s.start_index;
        assert!((r.share_below - below as f64 / r.points.len() as f64).abs() < 1e-12);
        // The stretch's length is the distance along the points it spans.
        let (a, b) = (&r.points[s.start_index], &r.points[s.end_index]);
        let ends = Geodetic::new(a.lat_deg, a.lon_deg, a.h_m)
            .to_ecef()
            .distance_m(&Geodetic::new(b.lat_deg, b.lon_deg, b.h_m).to_ecef());
        assert!((s.length_m - ends).abs() < 0.01 * ends, "{} {ends}", s.length_m);
        // GeoJSON: the trajectory, the stretch, and every point.
        let g = to_geojson(&r);
        assert_eq!(g["features"].as_array().unwrap().len(), 1 + 1 + r.points.len());
        assert_eq!(g["features"][1]["properties"]["kind"], "below_threshold");
        // The map's area holds every point's footprint box.
        let area = map_area(&r).unwrap();
        assert!(r.points.iter().filter_map(|p| p.bbox).all(|b| area.contains(b.min_lon_deg, b.min_lat_deg)));
    }

    #[test]
    fn bad_plans_are_named_and_a_source_failure_is_a_503() {
        let mut req = plan();
        req.waypoints.as_mut().unwrap()[1].lat_deg = 95.0;
        let source = Grid::new((-111.05, -110.85), (39.95, 40.05));
        let levels = DbLevel::of(&source.levels().unwrap());
        let e = coverage_query(&source, &levels, &req).unwrap_err();
        assert!(e.message.contains("lat_deg 95 is not in [-90, 90]"), "{}", e.message);
        assert_eq!(e.status, axum::http::StatusCode::UNPROCESSABLE_ENTITY);

        struct Broken;
        impl LandmarkSource for Broken {
            fn levels(&self) -> Result<Vec<LevelInfo>, SourceError> {
                Err(SourceError("db.gpkg: disk I/O error".into()))
            }
            fn query(&self, _: &GeoBox, _: u8) -> Result<Vec<Template>, SourceError> {
                Err(SourceError("db.gpkg: disk I/O error".into()))
            }
        }
        // The database's failure, not the client's: retry elsewhere (never a 500).
        let e = coverage_query(&Broken, &levels, &plan()).unwrap_err();
        assert_eq!(e.status, axum::http::StatusCode::SERVICE_UNAVAILABLE);
        assert!(e.message.contains("db.gpkg"), "{}", e.message);
    }
}
