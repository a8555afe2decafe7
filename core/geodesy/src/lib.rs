//! WGS84 geodesy for terrain relative navigation. No I/O.
//!
//! The main types are the three position frames: [`Geodetic`] (latitude and
//! longitude in degrees, height in metres above the WGS84 *ellipsoid*), [`Ecef`]
//! (Earth-centred, Earth-fixed, metres) and [`Enu`] (east/north/up metres in the
//! [`LocalFrame`] tangent to the ellipsoid at an origin). Around them: ellipsoid
//! normals, ray/ellipsoid intersection (also with the ellipsoid raised by a
//! height), geoid undulation grids for orthometric heights, and the gravity
//! field an inertial navigator integrates ([`gravity`]).
//!
//! ```
//! use trn_geodesy::{Enu, Geodetic, LocalFrame};
//!
//! // Geodetic -> ECEF -> geodetic, and 100 m north on the tangent plane.
//! let g = Geodetic::new(45.0, 7.0, 1000.0);
//! let back = g.to_ecef().to_geodetic();
//! assert!((back.lat_deg - 45.0).abs() < 1e-10 && (back.h_m - 1000.0).abs() < 1e-6);
//! let north = LocalFrame::at(g).to_ecef(Enu::new(0.0, 100.0, 0.0));
//! assert!((north.distance_m(&g.to_ecef()) - 100.0).abs() < 1e-9);
//! assert!(north.to_geodetic().lat_deg > 45.0);
//! ```

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

mod geoid;
pub mod gravity;
mod ray;

pub use geoid::GeoidGrid;
pub use ray::{intersect_ellipsoid, Ray};

/// WGS84 semi-major axis (m).
pub const WGS84_A: f64 = 6_378_137.0;
/// WGS84 flattening.
pub const WGS84_F: f64 = 1.0 / 298.257_223_563;
/// WGS84 semi-minor axis (m).
pub const WGS84_B: f64 = WGS84_A * (1.0 - WGS84_F);
/// First eccentricity squared.
pub const WGS84_E2: f64 = WGS84_F * (2.0 - WGS84_F);
/// Earth rotation rate (rad/s) about the ECEF +z axis (WGS84 value).
pub const EARTH_RATE_RAD_S: f64 = 7.292_115e-5;

/// Geodetic position on WGS84: degrees, and height above the ellipsoid (m).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Geodetic {
    pub lat_deg: f64,
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid (not above the geoid).
    pub h_m: f64,
}

/// Earth-centred, Earth-fixed position (m).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Ecef(pub Vector3<f64>);

/// East/north/up offset (m) in a [`LocalFrame`].
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Enu(pub Vector3<f64>);

impl Geodetic {
    pub fn new(lat_deg: f64, lon_deg: f64, h_m: f64) -> Self {
        Self { lat_deg, lon_deg, h_m }
    }

    pub fn lat_rad(&self) -> f64 {
        self.lat_deg.to_radians()
    }

    pub fn lon_rad(&self) -> f64 {
        self.lon_deg.to_radians()
    }

    /// Prime vertical radius of curvature N(lat).
    pub fn prime_vertical_radius_m(&self) -> f64 {
        let s = self.lat_rad().sin();
        WGS84_A / (1.0 - WGS84_E2 * s * s).sqrt()
    }

    /// Meridional radius of curvature M(lat).
    pub fn meridian_radius_m(&self) -> f64 {
        let s = self.lat_rad().sin();
        WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s * s).powf(1.5)
    }

    pub fn to_ecef(&self) -> Ecef {
        let (sl, cl) = self.lat_rad().sin_cos();
        let (so, co) = self.lon_rad().sin_cos();
        let n = self.prime_vertical_radius_m();
        Ecef(Vector3::new(
            (n + self.h_m) * cl * co,
            (n + self.h_m) * cl * so,
            (n * (1.0 - WGS84_E2) + self.h_m) * sl,
        ))
    }

    /// Unit outward ellipsoid normal (the local "up") in ECEF.
    pub fn up_ecef(&self) -> Vector3<f64> {
        let (sl, cl) = self.lat_rad().sin_cos();
        let (so, co) = self.lon_rad().sin_cos();
        Vector3::new(cl * co, cl * so, sl)
    }

    /// The same point with another height.
    pub fn with_height(&self, h_m: f64) -> Self {
        Self { h_m, ..*self }
    }
}

impl Ecef {
    pub fn new(x_m: f64, y_m: f64, z_m: f64) -> Self {
        Self(Vector3::new(x_m, y_m, z_m))
    }

    pub fn x(&self) -> f64 {
        self.0.x
    }
    pub fn y(&self) -> f64 {
        self.0.y
    }
    pub fn z(&self) -> f64 {
        self.0.z
    }

    pub fn distance_m(&self, other: &Ecef) -> f64 {
        (self.0 - other.0).norm()
    }

    /// ECEF to geodetic: Bowring's initial latitude, then Newton-like fixed-point
    /// iterations on the latitude; converges to well below a micrometre for all
    /// heights from the Earth's centre region out to orbit.
    pub fn to_geodetic(&self) -> Geodetic {
        let (x, y, z) = (self.0.x, self.0.y, self.0.z);
        let p = x.hypot(y);
        let lon = y.atan2(x);
        if p < 1e-9 {
            // On the polar axis.
            let lat = if z >= 0.0 { 90.0 } else { -90.0 };
            return Geodetic::new(lat, 0.0, z.abs() - WGS84_B);
        }
        let ep2 = WGS84_E2 / (1.0 - WGS84_E2);
        // Bowring (1976) initial parametric latitude.
        let beta = (WGS84_A * z).atan2(WGS84_B * p);
        let (sb, cb) = beta.sin_cos();
        let mut lat = (z + ep2 * WGS84_B * sb.powi(3)).atan2(p - WGS84_E2 * WGS84_A * cb.powi(3));
        let mut h = 0.0;
        for _ in 0..4 {
            let (sl, cl) = lat.sin_cos();
            let n = WGS84_A / (1.0 - WGS84_E2 * sl * sl).sqrt();
            // Height along the normal, stable at all latitudes.
            h = p * cl + z * sl - WGS84_A * (1.0 - WGS84_E2 * sl * sl).sqrt();
            lat = z.atan2(p * (1.0 - WGS84_E2 * n / (n + h)));
        }
        Geodetic::new(lat.to_degrees(), lon.to_degrees(), h)
    }
}

impl Enu {
    pub fn new(east_m: f64, north_m: f64, up_m: f64) -> Self {
        Self(Vector3::new(east_m, north_m, up_m))
    }
    pub fn east_m(&self) -> f64 {
        self.0.x
    }
    pub fn north_m(&self) -> f64 {
        self.0.y
    }
    pub fn up_m(&self) -> f64 {
        self.0.z
    }
}

/// The local tangent frame (east, north, up) at an origin on or above the ellipsoid.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LocalFrame {
    origin: Geodetic,
    origin_ecef: Ecef,
    /// Columns: east, north, up unit vectors in ECEF; maps ENU vectors to ECEF.
    r_ecef_enu: Matrix3<f64>,
}

impl LocalFrame {
    pub fn at(origin: Geodetic) -> Self {
        let (sl, cl) = origin.lat_rad().sin_cos();
        let (so, co) = origin.lon_rad().sin_cos();
        let east = Vector3::new(-so, co, 0.0);
        let north = Vector3::new(-sl * co, -sl * so, cl);
        let up = Vector3::new(cl * co, cl * so, sl);
        Self { origin, origin_ecef: origin.to_ecef(), r_ecef_enu: Matrix3::from_columns(&[east, north, up]) }
    }

    pub fn origin(&self) -> Geodetic {
        self.origin
    }

    pub fn origin_ecef(&self) -> Ecef {
        self.origin_ecef
    }

    /// Rotation taking ENU vectors into ECEF.
    pub fn r_ecef_enu(&self) -> Matrix3<f64> {
        self.r_ecef_enu
    }

    pub fn to_enu(&self, p: &Ecef) -> Enu {
        Enu(self.r_ecef_enu.transpose() * (p.0 - self.origin_ecef.0))
    }

    pub fn to_ecef(&self, p: Enu) -> Ecef {
        Ecef(self.origin_ecef.0 + self.r_ecef_enu * p.0)
    }

    pub fn vector_to_enu(&self, v_ecef: &Vector3<f64>) -> Vector3<f64> {
        self.r_ecef_enu.transpose() * v_ecef
    }

    pub fn vector_to_ecef(&self, v_enu: &Vector3<f64>) -> Vector3<f64> {
        self.r_ecef_enu * v_enu
    }
}

/// Metres per degree of latitude and of longitude at a latitude (for sizing boxes).
pub fn metres_per_degree(lat_deg: f64) -> (f64, f64) {
    let g = Geodetic::new(lat_deg, 0.0, 0.0);
    let per_lat = g.meridian_radius_m() * std::f64::consts::PI / 180.0;
    let per_lon = g.prime_vertical_radius_m() * lat_deg.to_radians().cos() * std::f64::consts::PI / 180.0;
    (per_lat, per_lon)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_geodetic_ecef() {
        for &(lat, lon, h) in &[
            (0.0, 0.0, 0.0),
            (45.0, 7.0, 1000.0),
            (-33.9, 151.2, -50.0),
            (89.9999, 10.0, 35_000.0),
            (-90.0, 0.0, 0.0),
            (40.3, -105.6, 3500.0),
            (12.0, 179.9999, 400_000.0),
        ] {
            let g = Geodetic::new(lat, lon, h);
            let back = g.to_ecef().to_geodetic();
            assert!((back.lat_deg - lat).abs() < 1e-10, "{lat} {lon} {h}: {back:?}");
            if lat.abs() < 90.0 {
                assert!((back.lon_deg - lon).abs() < 1e-10);
            }
            assert!((back.h_m - h).abs() < 1e-6, "{back:?}");
        }
    }

    #[test]
    fn local_frame_round_trip_and_up() {
        let f = LocalFrame::at(Geodetic::new(40.0, -105.0, 2500.0));
        let p = Enu::new(120.0, -40.0, 7.5);
        let back = f.to_enu(&f.to_ecef(p));
        assert!((back.0 - p.0).norm() < 1e-8);
        let up_point = Geodetic::new(40.0, -105.0, 2600.0).to_ecef();
        let enu = f.to_enu(&up_point);
        assert!((enu.0 - Vector3::new(0.0, 0.0, 100.0)).norm() < 1e-8);
    }
}
