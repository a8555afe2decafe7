//! Which part of the ground a pose guess sees: the image corners projected
//! onto the WGS84 ellipsoid raised to the local terrain height, with IBAL's
//! horizon handling (a corner that sees sky walks toward the opposite corner
//! in steps until its ray meets the ground) and angle filter (corners walk
//! on until the line of sight is within `alpha_max` of the surface normal, so
//! landmarks near the horizon, seen edge-on, are not chosen).

use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_geodesy::{intersect_ellipsoid, Geodetic};
use trn_landmark::GeoBox;

#[derive(Clone, Copy, Debug)]
pub struct FootprintParams {
    /// Corner walking step (px).
    pub step_px: f64,
    /// Largest angle between a line of sight and the surface normal (deg).
    pub alpha_max_deg: f64,
    /// Height of the ellipsoid the corners are projected on (m, the local terrain).
    pub terrain_h_m: f64,
}

impl Default for FootprintParams {
    fn default() -> Self {
        Self { step_px: 10.0, alpha_max_deg: 75.0, terrain_h_m: 0.0 }
    }
}

/// The part of the ground in view.
#[derive(Clone, Debug)]
pub struct Footprint {
    /// The four corners after walking (top-left, top-right, bottom-right, bottom-left).
    pub corners_px: [Pixel; 4],
    pub corners: [Geodetic; 4],
    /// Box around the corners and the edge midpoints that see the ground.
    pub bbox: GeoBox,
    /// Whether some corner had to walk because it saw sky.
    pub horizon_in_view: bool,
    /// Whether some corner had to walk because of the angle filter.
    pub angle_limited: bool,
    /// Ground sample distance at the image centre's ground point (or the
    /// centre of the walked corners) in metres per pixel.
    pub center_gsd_m: f64,
    /// Distance from the camera to that ground point (m).
    pub center_range_m: f64,
}

#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum FootprintError {
    #[error("the camera is below the terrain height {0:.0} m")]
    BelowTerrain(f64),
    #[error(
        "corner {corner} walked across the image without seeing usable ground (sky or beyond alpha_max)"
    )]
    NoGround { corner: usize },
}

/// Where a pixel's ray meets the raised ellipsoid, and its incidence angle (deg).
fn ground(camera: &CameraModel, pose: &CameraPose, px: Pixel, h: f64) -> Option<(Geodetic, f64, f64)> {
    let ray = pose.ray(camera, px);
    let hit = intersect_ellipsoid(&ray, h)?;
    let g = hit.to_geodetic();
    let cos_inc = -ray.direction.dot(&g.up_ecef());
    (cos_inc > 0.0).then(|| (g, cos_inc.clamp(-1.0, 1.0).acos().to_degrees(), (hit.0 - ray.origin.0).norm()))
}

/// Projects the image corners (walking them as IBAL does) and returns the
/// ground in view.
pub fn footprint(
    camera: &CameraModel,
    pose: &CameraPose,
    params: &FootprintParams,
) -> Result<Footprint, FootprintError> {
    let h = params.terrain_h_m;
    if pose.position.to_geodetic().h_m <= h {
        return Err(FootprintError::BelowTerrain(h));
    }
    let c = camera.corners();
    let mut corners_px = c;
    let mut corners = [Geodetic::new(0.0, 0.0, 0.0); 4];
    let (mut horizon, mut limited) = (false, false);
    for i in 0..4 {
        let (from, to) = (c[i], c[(i + 2) % 4]);
        let len = from.distance_px(&to);
        let (du, dv) = ((to.u - from.u) / len, (to.v - from.v) / len);
        let mut k = 0.0;
        loop {
            if k > len {
                return Err(FootprintError::NoGround { corner: i });
            }
            let px = Pixel::new(from.u + du * k, from.v + dv * k);
            match ground(camera, pose, px, h) {
                Some((g, inc, _)) if inc <= params.alpha_max_deg => {
                    corners_px[i] = px;
                    corners[i] = g;
                    break;
                }
                Some(_) => limited = true,
                None => horizon = true,
            }
            k += params.step_px;
        }
    }
    let mut pts: Vec<(f64, f64)> = corners.iter().map(|g| (g.lon_deg, g.lat_deg)).collect();
    for i in 0..4 {
        let (a, b) = (corners_px[i], corners_px[(i + 1) % 4]);
        let mid = Pixel::new(0.5 * (a.u + b.u), 0.5 * (a.v + b.v));
        if let Some((g, inc, _)) = ground(camera, pose, mid, h) {
            if inc <= params.alpha_max_deg {
                pts.push((g.lon_deg, g.lat_deg));
            }
        }
    }
    // Across the antimeridian, the small box that crosses it.
    let bbox = GeoBox::around_wrapped(pts).expect("four corners");
    // GSD where the camera looks: the principal point when it sees usable
    // ground, else the middle of the walked corners.
    let centre = camera.principal_point();
    let mid = Pixel::new(
        corners_px.iter().map(|p| p.u).sum::<f64>() / 4.0,
        corners_px.iter().map(|p| p.v).sum::<f64>() / 4.0,
    );
    let (g_centre, inc, range) = ground(camera, pose, centre, h)
        .filter(|x| x.1 <= params.alpha_max_deg)
        .or_else(|| ground(camera, pose, mid, h))
        .unwrap_or((corners[0], 0.0, pose.position.distance_m(&corners[0].to_ecef())));
    let _ = g_centre;
    // Pixel footprint across the line of sight, stretched by the incidence.
    let pixel_angle = 1.0 / camera.fx.min(camera.fy);
    let center_gsd_m = range * pixel_angle / inc.to_radians().cos().max(0.2).sqrt();
    Ok(Footprint {
        corners_px,
        corners,
        bbox,
        horizon_in_view: horizon,
        angle_limited: limited,
        center_gsd_m,
        center_range_m: range,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::{Ecef, LocalFrame};

    fn pose_looking(h: f64, tilt_deg: f64) -> CameraPose {
        // Look north, tilted from nadir by tilt_deg; image up toward the horizon.
        let frame = LocalFrame::at(Geodetic::new(40.0, -105.5, 0.0));
        let pos = frame.to_ecef(trn_geodesy::Enu::new(0.0, 0.0, h));
        let target = frame.to_ecef(trn_geodesy::Enu::new(0.0, h * tilt_deg.to_radians().tan(), 0.0));
        let north = frame.to_ecef(trn_geodesy::Enu::new(0.0, 1.0, 0.0)).0
            - frame.to_ecef(trn_geodesy::Enu::new(0.0, 0.0, 0.0)).0;
        let up_hint = if tilt_deg == 0.0 { north } else { Geodetic::new(40.0, -105.5, 0.0).up_ecef() };
        CameraPose::look_at(pos, target, up_hint)
    }

    #[test]
    fn nadir_view_keeps_the_corners() {
        let cam = CameraModel::from_fov(1024, 768, 32.0);
        let pose = pose_looking(30_000.0, 0.0);
        let f = footprint(&cam, &pose, &FootprintParams::default()).unwrap();
        assert!(!f.horizon_in_view && !f.angle_limited);
        assert_eq!(f.corners_px, cam.corners());
        // 32 deg across 30 km: about 17.2 km wide, GSD ~16.8 m.
        let (m_lat, m_lon) = trn_geodesy::metres_per_degree(40.0);
        let width = (f.bbox.max_lon_deg - f.bbox.min_lon_deg) * m_lon;
        let height = (f.bbox.max_lat_deg - f.bbox.min_lat_deg) * m_lat;
        assert!((width.max(height) - 17_200.0).abs() < 300.0, "{width} x {height}");
        assert!((f.center_gsd_m - 16.8).abs() < 0.2, "{}", f.center_gsd_m);
    }

    #[test]
    fn a_view_across_the_antimeridian_is_a_small_box_that_crosses_it() {
        // Nadir at 180 deg, 30 km up: the 17 km wide view straddles the
        // antimeridian, and its box crosses it rather than spanning the globe.
        let cam = CameraModel::from_fov(1024, 768, 32.0);
        let at = Geodetic::new(-17.0, 180.0, 0.0);
        let frame = LocalFrame::at(at);
        let pos = frame.to_ecef(trn_geodesy::Enu::new(0.0, 0.0, 30_000.0));
        let north = frame.to_ecef(trn_geodesy::Enu::new(0.0, 1.0, 0.0)).0 - at.to_ecef().0;
        let pose = CameraPose::look_at(pos, at.to_ecef(), north);
        let f = footprint(&cam, &pose, &FootprintParams::default()).unwrap();
        assert!(f.bbox.crosses_antimeridian(), "{:?}", f.bbox);
        let (_, m_lon) = trn_geodesy::metres_per_degree(-17.0);
        assert!((f.bbox.lon_span_deg() * m_lon - 17_200.0).abs() < 300.0, "{:?}", f.bbox);
        assert!(f.corners.iter().all(|c| f.bbox.contains(c.lon_deg, c.lat_deg)));
        assert!(
            f.bbox.contains(180.0, -17.0) && f.bbox.contains(-179.99, -17.0) && !f.bbox.contains(0.0, -17.0)
        );
    }

    #[test]
    fn horizon_corners_walk_until_they_see_ground() {
        // 76 deg lens tilted 70 deg: the top corners see sky.
        let cam = CameraModel::from_fov(1024, 768, 76.0);
        let pose = pose_looking(10_000.0, 70.0);
        let f =
            footprint(&cam, &pose, &FootprintParams { alpha_max_deg: 89.9, ..Default::default() }).unwrap();
        assert!(f.horizon_in_view);
        for i in [0, 1] {
            let p = f.corners_px[i];
            assert!(p.v > 0.0, "corner {i} moved down: {p:?}");
            // One step back toward the corner sees sky (or stays at the corner).
            let c = cam.corners()[i];
            let o = cam.corners()[(i + 2) % 4];
            let len = c.distance_px(&o);
            let back = Pixel::new(p.u - (o.u - c.u) / len * 10.0, p.v - (o.v - c.v) / len * 10.0);
            assert!(ground(&cam, &pose, back, 0.0).is_none(), "corner {i}: the step before also hits");
        }
        // Bottom corners see ground and stay.
        assert_eq!(f.corners_px[2], cam.corners()[2]);
        // The angle filter moves the top corners further down.
        let g =
            footprint(&cam, &pose, &FootprintParams { alpha_max_deg: 70.0, ..Default::default() }).unwrap();
        assert!(g.angle_limited);
        for i in [0, 1] {
            assert!(g.corners_px[i].v > f.corners_px[i].v);
            let inc = ground(&cam, &pose, g.corners_px[i], 0.0).unwrap().1;
            assert!(inc <= 70.0, "{inc}");
        }
    }

    #[test]
    fn looking_at_the_sky_is_an_error() {
        let cam = CameraModel::from_fov(640, 480, 40.0);
        let g = Geodetic::new(40.0, -105.5, 10_000.0);
        let pose = CameraPose::look_at(
            g.to_ecef(),
            Ecef(g.to_ecef().0 + g.up_ecef() * 1000.0),
            Geodetic::new(41.0, -105.5, 0.0).to_ecef().0,
        );
        assert!(matches!(
            footprint(&cam, &pose, &FootprintParams::default()),
            Err(FootprintError::NoGround { .. })
        ));
        let below = CameraPose::look_at(
            Geodetic::new(40.0, -105.5, 100.0).to_ecef(),
            Geodetic::new(40.0, -105.4, 0.0).to_ecef(),
            g.up_ecef(),
        );
        assert!(matches!(
            footprint(&cam, &below, &FootprintParams { terrain_h_m: 500.0, ..Default::default() }),
            Err(FootprintError::BelowTerrain(_))
        ));
    }
}
