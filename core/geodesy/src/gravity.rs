//! The Earth's gravity field as an inertial navigator needs it: the
//! gravitation of a point mass plus the second zonal harmonic J2, and gravity
//! in ECEF (gravitation plus the centrifugal acceleration of the Earth's
//! turn). Within ~1e-4 m/s^2 of WGS84 normal gravity (Somigliana's closed
//! form, [`normal_gravity_m_s2`], the independent reference of the tests)
//! from the surface to the stratosphere.

use nalgebra::{Matrix3, Vector3};

use crate::{Ecef, Geodetic, EARTH_RATE_RAD_S, WGS84_A, WGS84_E2, WGS84_F};

/// WGS84 gravitational constant GM (m^3/s^2).
pub const GM_M3_S2: f64 = 3.986_004_418e14;
/// Second zonal harmonic J2 (WGS84 / EGM96, -sqrt(5) * C20).
pub const J2: f64 = 1.082_629_821_313_8e-3;

/// Gravitation (not gravity: no centrifugal term) of a point mass plus J2
/// at the ECEF position `r` (m/s^2, ECEF).
pub fn gravitation_ecef(r: &Vector3<f64>) -> Vector3<f64> {
    let r2 = r.norm_squared();
    let k = 1.5 * J2 * WGS84_A * WGS84_A / r2;
    let zz = 5.0 * r.z * r.z / r2;
    let c = -GM_M3_S2 / (r2 * r2.sqrt());
    Vector3::new(
        c * r.x * (1.0 + k * (1.0 - zz)),
        c * r.y * (1.0 + k * (1.0 - zz)),
        c * r.z * (1.0 + k * (3.0 - zz)),
    )
}

/// Gravity in ECEF (m/s^2): gravitation plus the centrifugal acceleration
/// `-w x (w x r)`; what a plumb line at rest on the Earth feels, so an
/// accelerometer at rest reads its opposite.
pub fn gravity_ecef(p: &Ecef) -> Vector3<f64> {
    let r = p.0;
    let w2 = EARTH_RATE_RAD_S * EARTH_RATE_RAD_S;
    gravitation_ecef(&r) + Vector3::new(w2 * r.x, w2 * r.y, 0.0)
}

/// Gradient of the gravitation `d g / d r` (1/s^2, ECEF) of the point mass:
/// `GM / r^3 (3 u u^T - I)`. J2 and the centrifugal term change it by
/// ~0.1%, below what an error state filter needs (the vertical channel's
/// instability, `2 g / r` = 3e-6 /s^2, is the part that matters).
pub fn gravitation_gradient(p: &Ecef) -> Matrix3<f64> {
    let r = p.0.norm();
    let u = p.0 / r;
    (3.0 * u * u.transpose() - Matrix3::identity()) * (GM_M3_S2 / (r * r * r))
}

/// WGS84 normal gravity magnitude (m/s^2): Somigliana's formula with the
/// second-order free-air correction in height (NIMA TR8350.2, eq. 4-1, 4-3).
pub fn normal_gravity_m_s2(g: &Geodetic) -> f64 {
    let s2 = g.lat_rad().sin().powi(2);
    let gamma = 9.780_325_335_9 * (1.0 + 0.001_931_852_652_41 * s2) / (1.0 - WGS84_E2 * s2).sqrt();
    let m = 0.003_449_786_506_84;
    let h = g.h_m;
    gamma
        * (1.0 - 2.0 / WGS84_A * (1.0 + WGS84_F + m - 2.0 * WGS84_F * s2) * h
            + 3.0 * h * h / (WGS84_A * WGS84_A))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn gravity_is_normal_gravity_down_the_ellipsoid_normal() {
        // Somigliana's closed form is the field of the level ellipsoid; the
        // J2 model differs from it by the higher zonal terms (~1e-4 m/s^2).
        // Its direction leaves the ellipsoid normal with height: normal
        // gravity's northward component is 8.08e-9 /s^2 x h sin(2 lat)
        // (2.4e-5 rad at 30 km); the J2 model leaves that by under 1e-5 rad.
        for g in [
            Geodetic::new(0.0, 0.0, 0.0),
            Geodetic::new(40.7, -111.9, 1300.0),
            Geodetic::new(-67.0, 120.0, 3000.0),
            Geodetic::new(36.6, -118.3, 30_000.0),
            Geodetic::new(89.0, 10.0, 100.0),
        ] {
            let v = gravity_ecef(&g.to_ecef());
            let want = normal_gravity_m_s2(&g);
            assert!((v.norm() - want).abs() < 2e-4, "{g:?}: {} vs {want}", v.norm());
            let angle = (-v.normalize()).angle(&g.up_ecef());
            let deflection = 8.08e-9 * g.h_m * (2.0 * g.lat_rad()).sin().abs() / want;
            assert!(
                (angle - deflection).abs() < 1e-5,
                "{g:?}: {angle} rad from the normal, {deflection} expected"
            );
        }
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let p = Geodetic::new(36.6, -118.3, 30_000.0).to_ecef();
        let grad = gravitation_gradient(&p);
        for i in 0..3 {
            let mut d = Vector3::zeros();
            d[i] = 10.0;
            let num = (gravitation_ecef(&(p.0 + d)) - gravitation_ecef(&(p.0 - d))) / 20.0;
            assert!(
                (num - grad.column(i)).norm() < 5e-3 * grad.column(i).norm(),
                "{i}: {num} {}",
                grad.column(i)
            );
        }
    }
}
