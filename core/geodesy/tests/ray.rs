//! `intersect_ellipsoid` against a brute-force reference: a ternary search for
//! the ray's closest approach and bisection for the crossing, on
//! f(t) = (x/(a+h))^2 + (y/(a+h))^2 + (z/(b+h))^2 - 1, no quadratic formula.

use nalgebra::Vector3;
use trn_geodesy::{intersect_ellipsoid, Ecef, Geodetic, LocalFrame, Ray, WGS84_A, WGS84_B};

/// The raised ellipsoid (a + h, b + h) is not a surface of constant geodetic
/// height: its points lie within 1.41e-6 |h| of h (5 cm at 35 km).
const RAISED_HEIGHT_TOLERANCE: f64 = 1.5e-6;

/// Far enough for every ray here (unit directions, so metres).
const T_MAX_M: f64 = 1e8;

fn quadric(ray: &Ray, height_m: f64, t: f64) -> f64 {
    let p = ray.origin.0 + ray.direction * t;
    let (a, b) = (WGS84_A + height_m, WGS84_B + height_m);
    (p.x / a).powi(2) + (p.y / a).powi(2) + (p.z / b).powi(2) - 1.0
}

/// Bisection for the sign change of `f` on [lo, hi] (f(lo), f(hi) of opposite signs).
fn bisect(f: impl Fn(f64) -> f64, mut lo: f64, mut hi: f64) -> f64 {
    let f_lo_positive = f(lo) > 0.0;
    for _ in 0..400 {
        let mid = 0.5 * (lo + hi);
        if mid <= lo || mid >= hi {
            break;
        }
        if (f(mid) > 0.0) == f_lo_positive {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// Brute-force nearest forward crossing: the distance `t` along the (unit) ray.
fn reference_t(ray: &Ray, height_m: f64) -> Option<f64> {
    let f = |t: f64| quadric(ray, height_m, t);
    if f(0.0) < 0.0 {
        // Inside: the only forward crossing is the exit.
        assert!(f(T_MAX_M) > 0.0);
        return Some(bisect(f, 0.0, T_MAX_M));
    }
    // f is convex along a line: ternary search for its minimum on [0, T_MAX].
    let (mut lo, mut hi) = (0.0, T_MAX_M);
    for _ in 0..400 {
        let m1 = lo + (hi - lo) / 3.0;
        let m2 = hi - (hi - lo) / 3.0;
        if f(m1) < f(m2) {
            hi = m2;
        } else {
            lo = m1;
        }
    }
    let t_min = 0.5 * (lo + hi);
    if f(t_min) > 0.0 {
        return None;
    }
    Some(bisect(f, 0.0, t_min))
}

/// A unit ECEF direction `off_nadir_deg` from straight down, toward azimuth
/// `az_deg` (clockwise from north), at `g`.
fn direction(g: Geodetic, off_nadir_deg: f64, az_deg: f64) -> Vector3<f64> {
    let (so, co) = off_nadir_deg.to_radians().sin_cos();
    let (sa, ca) = az_deg.to_radians().sin_cos();
    LocalFrame::at(g).vector_to_ecef(&Vector3::new(so * sa, so * ca, -co))
}

/// Checks the analytic hit against the reference; returns the hit's error (m).
fn check(ray: &Ray, height_m: f64, tol_m: f64) -> Option<f64> {
    let got = intersect_ellipsoid(ray, height_m);
    let want = reference_t(ray, height_m);
    match (got, want) {
        (None, None) => None,
        (Some(p), Some(t)) => {
            let want_p = ray.point_at(t);
            let err_m = p.distance_m(&want_p);
            assert!(err_m < tol_m, "{ray:?} h={height_m}: {p:?} vs reference {want_p:?} ({err_m} m)");
            // The hit lies on the raised ellipsoid (|f| ~ 2 dh / R).
            let t_got = (p.0 - ray.origin.0).dot(&ray.direction);
            assert!(quadric(ray, height_m, t_got).abs() < 1e-12, "{ray:?}: off the quadric");
            Some(err_m)
        }
        (got, want) => panic!("{ray:?} h={height_m}: got {got:?}, reference t {want:?}"),
    }
}

fn camera(lat_deg: f64, lon_deg: f64, h_m: f64) -> Geodetic {
    Geodetic::new(lat_deg, lon_deg, h_m)
}

#[test]
fn nadir_hits_the_point_below() {
    for &(lat, lon, h_cam) in
        &[(35.1, -106.6, 30_000.0), (0.0, 0.0, 400_000.0), (90.0, 0.0, 3_000.0), (-45.0, 179.9, 1_600.0)]
    {
        let g = camera(lat, lon, h_cam);
        let ray = Ray::new(g.to_ecef(), -g.up_ecef());
        for &h in &[0.0, 1_500.0, -400.0] {
            check(&ray, h, 1e-6).expect("nadir ray must hit");
            // Along the normal: the point below, at height h up to the raised
            // ellipsoid's departure from a constant-height surface.
            let hit = intersect_ellipsoid(&ray, h).unwrap();
            let below = g.with_height(h).to_ecef();
            assert!(
                hit.distance_m(&below) < 1e-6 + RAISED_HEIGHT_TOLERANCE * h.abs(),
                "{hit:?} vs {below:?}"
            );
        }
    }
}

#[test]
fn oblique_rays_match_reference() {
    let mut n = 0;
    for &(lat, lon, h_cam) in &[(35.1, -106.6, 30_000.0), (-60.0, 20.0, 12_000.0), (89.99, 45.0, 35_000.0)] {
        let g = camera(lat, lon, h_cam);
        for off in [5.0, 30.0, 60.0, 75.0] {
            for az in [0.0, 45.0, 90.0, 200.0, 315.0] {
                let ray = Ray::new(g.to_ecef(), direction(g, off, az));
                for &h in &[0.0, 2_000.0, -400.0] {
                    check(&ray, h, 1e-6).expect("oblique ray below the horizon must hit");
                    n += 1;
                }
            }
        }
    }
    assert_eq!(n, 180);
}

#[test]
fn grazing_rays_near_the_horizon() {
    let g = camera(35.1, -106.6, 30_000.0);
    let origin = g.to_ecef();
    for az in [0.0, 90.0, 180.0, 270.0] {
        for &h in &[0.0, 3_000.0] {
            // The horizon (tangent) off-nadir angle, by bisection on hit / miss.
            let hits = |off: f64| reference_t(&Ray::new(origin, direction(g, off, az)), h).is_some();
            let (mut lo, mut hi) = (60.0, 90.0);
            assert!(hits(lo) && !hits(hi));
            for _ in 0..60 {
                let mid = 0.5 * (lo + hi);
                if hits(mid) {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            // Just inside the horizon: the crossing is hundreds of km away and
            // ill-conditioned in t, so the tolerance grows toward tangency.
            for (delta_deg, tol_m) in [(1e-1, 1e-5), (1e-3, 1e-4), (1e-5, 1e-2)] {
                let ray = Ray::new(origin, direction(g, lo - delta_deg, az));
                let err = check(&ray, h, tol_m).expect("ray below the horizon must hit");
                let range_km = intersect_ellipsoid(&ray, h).unwrap().distance_m(&origin) / 1e3;
                assert!(range_km > 300.0, "grazing range {range_km} km");
                eprintln!("az {az} h {h} horizon-{delta_deg} deg: range {range_km:.1} km, err {err:.2e} m");
            }
            // Just above the horizon: sky.
            let ray = Ray::new(origin, direction(g, hi + 1e-5, az));
            assert!(check(&ray, h, 1e-6).is_none());
            assert!(intersect_ellipsoid(&ray, h).is_none());
        }
    }
}

#[test]
fn sky_and_away_rays_miss() {
    let g = camera(35.1, -106.6, 30_000.0);
    // Horizontal and upward rays see sky.
    for off in [90.0, 120.0, 180.0] {
        let ray = Ray::new(g.to_ecef(), direction(g, off, 33.0));
        assert!(intersect_ellipsoid(&ray, 0.0).is_none(), "off-nadir {off}");
        assert!(reference_t(&ray, 0.0).is_none());
    }
    // A ray pointing away from an Earth it would hit if extended backwards.
    let ray = Ray::new(Geodetic::new(0.0, 0.0, 1e6).to_ecef(), Vector3::new(1.0, 0.0, 0.0));
    assert!(intersect_ellipsoid(&ray, 0.0).is_none());
    assert!(intersect_ellipsoid(&Ray { direction: -ray.direction, ..ray }, 0.0).is_some());
    // A degenerate direction hits nothing.
    let ray = Ray { origin: g.to_ecef(), direction: Vector3::zeros() };
    assert!(intersect_ellipsoid(&ray, 0.0).is_none());
}

#[test]
fn origin_inside_exits_forward() {
    // Camera at 1000 m, ellipsoid raised to 2000 m: the camera is inside.
    let g = camera(35.1, -106.6, 1_000.0);
    let origin = g.to_ecef();
    // Upward: leaves through the raised surface 1000 m above.
    let up = Ray::new(origin, g.up_ecef());
    check(&up, 2_000.0, 1e-6).unwrap();
    let hit = intersect_ellipsoid(&up, 2_000.0).unwrap();
    assert!((hit.to_geodetic().h_m - 2_000.0).abs() < RAISED_HEIGHT_TOLERANCE * 2_000.0);
    // Downward and oblique: the exit is on the far side of the Earth.
    for off in [0.0, 45.0, 80.0] {
        let ray = Ray::new(origin, direction(g, off, 10.0));
        check(&ray, 2_000.0, 1e-5).unwrap();
        let range_m = intersect_ellipsoid(&ray, 2_000.0).unwrap().distance_m(&origin);
        assert!(range_m > 1e6, "{off}: {range_m}");
    }
    // The Earth's centre.
    let ray = Ray::new(Ecef::new(0.0, 0.0, 0.0), Vector3::new(0.0, 0.0, 1.0));
    let hit = intersect_ellipsoid(&ray, 0.0).unwrap();
    assert!((hit.z() - WGS84_B).abs() < 1e-6);
}

#[test]
fn hits_on_the_ellipsoid_have_zero_height() {
    // Deterministic spread of cameras and look directions (a simple LCG).
    let mut state: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut uniform = |lo: f64, hi: f64| {
        state = state.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        lo + (hi - lo) * ((state >> 11) as f64 / (1u64 << 53) as f64)
    };
    for _ in 0..500 {
        let g = camera(uniform(-90.0, 90.0), uniform(-180.0, 180.0), uniform(10.0, 40_000.0));
        let ray = Ray::new(g.to_ecef(), direction(g, uniform(0.0, 80.0), uniform(0.0, 360.0)));
        let hit = intersect_ellipsoid(&ray, 0.0).expect("below the horizon");
        let h_m = hit.to_geodetic().h_m;
        assert!(h_m.abs() < 1e-3, "{g:?}: hit height {h_m} m");
    }
}

#[test]
fn raised_ellipsoid_height_is_nearly_constant() {
    let mut worst: f64 = 0.0;
    for &h in &[-400.0, 2_000.0, 9_000.0, 35_000.0] {
        for i in 0..=90 {
            let lat = i as f64;
            let g = camera(lat, 17.0, h + 50_000.0);
            for off in [0.0, 40.0] {
                let ray = Ray::new(g.to_ecef(), direction(g, off, 123.0));
                let hit_h = intersect_ellipsoid(&ray, h).unwrap().to_geodetic().h_m;
                worst = worst.max((hit_h - h).abs() / h.abs());
            }
        }
    }
    eprintln!("raised ellipsoid: worst |height - h| / |h| = {worst:.3e}");
    assert!(worst < RAISED_HEIGHT_TOLERANCE && worst > 1e-6, "{worst}");
}
