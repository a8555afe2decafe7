//! Ray / ellipsoid intersection: where a camera ray meets the WGS84 ellipsoid,
//! or the ellipsoid raised by a constant height (a first guess of the ground
//! point before the terrain is known).
use crate::{Ecef, WGS84_A, WGS84_B};
use nalgebra::Vector3;

/// A half-line in ECEF: `origin + t * direction`, `t >= 0`. The direction
/// need not be a unit vector (then `t` is not in metres).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Ecef,
    pub direction: Vector3<f64>,
}

impl Ray {
    /// A ray with its direction normalized, so that `t` is in metres.
    pub fn new(origin: Ecef, direction: Vector3<f64>) -> Self {
        Self { origin, direction: direction.normalize() }
    }

    /// The point at parameter `t` along the ray.
    pub fn point_at(&self, t: f64) -> Ecef {
        Ecef(self.origin.0 + self.direction * t)
    }
}

/// Nearest forward intersection of `ray` with the WGS84 ellipsoid raised by
/// `height_m` (semi-axes `a + h`, `b + h`), or `None` when the ray misses it
/// (sees sky), points away, or has a zero direction.
///
/// The raised ellipsoid is not a surface of constant geodetic height: its
/// points lie within 1.41e-6 |h| of height h (3 mm at 2 km, 5 cm at 35 km).
///
/// When the origin is inside the raised ellipsoid (below `height_m`), every
/// forward ray leaves it exactly once, and that exit point is returned: for a
/// downward ray it lies on the far side of the Earth, so callers that need
/// "the ground below" must check that the origin is above `height_m`.
pub fn intersect_ellipsoid(ray: &Ray, height_m: f64) -> Option<Ecef> {
    let a = WGS84_A + height_m;
    let b = WGS84_B + height_m;
    // Scale to the unit sphere: x/a, y/a, z/b; then |o + t d|^2 = 1.
    let s = Vector3::new(1.0 / a, 1.0 / a, 1.0 / b);
    let o = ray.origin.0.component_mul(&s);
    let d = ray.direction.component_mul(&s);
    let qa = d.dot(&d);
    let qb = 2.0 * o.dot(&d);
    let qc = o.dot(&o) - 1.0;
    let disc = qb * qb - 4.0 * qa * qc;
    if !(disc >= 0.0 && qa > 0.0) {
        return None;
    }
    // Roots without cancellation: q has the magnitude of the larger term.
    let q = -0.5 * (qb + qb.signum() * disc.sqrt());
    let r0 = q / qa;
    let r1 = if q != 0.0 { qc / q } else { r0 };
    let (t0, t1) = (r0.min(r1), r0.max(r1));
    let t = if t0 >= 0.0 {
        t0
    } else if t1 >= 0.0 {
        t1
    } else {
        return None;
    };
    Some(ray.point_at(t))
}
