//! Geodetic <-> ECEF and ECEF -> ENU against pyproj (PROJ) reference values.
//! Fixtures: `scripts/fixtures/geodesy_pyproj.py`.

use std::path::PathBuf;

use trn_geodesy::{Ecef, Geodetic, LocalFrame};

fn fixture_rows(name: &str) -> Vec<Vec<f64>> {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name);
    let mut reader = csv::Reader::from_path(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let rows: Vec<Vec<f64>> =
        reader.records().map(|r| r.unwrap().iter().map(|f| f.parse::<f64>().unwrap()).collect()).collect();
    assert!(rows.len() > 100, "{name}: only {} rows", rows.len());
    rows
}

/// Longitude difference folded into (-180, 180], so 180 and -180 agree.
fn lon_diff_deg(a: f64, b: f64) -> f64 {
    let d = (a - b).rem_euclid(360.0);
    if d > 180.0 {
        d - 360.0
    } else {
        d
    }
}

#[test]
fn geodetic_to_ecef_matches_pyproj() {
    let mut worst_m: f64 = 0.0;
    for r in fixture_rows("pyproj_geodetic_ecef.csv") {
        let g = Geodetic::new(r[0], r[1], r[2]);
        let want = Ecef::new(r[3], r[4], r[5]);
        let err_m = g.to_ecef().distance_m(&want);
        assert!(err_m < 1e-3, "{g:?}: {:?} vs pyproj {want:?} ({err_m} m)", g.to_ecef());
        worst_m = worst_m.max(err_m);
    }
    eprintln!("geodetic -> ECEF worst error vs pyproj: {worst_m:.3e} m");
}

#[test]
fn ecef_to_geodetic_matches_pyproj() {
    let mut worst_m: f64 = 0.0;
    for r in fixture_rows("pyproj_geodetic_ecef.csv") {
        let want = Geodetic::new(r[0], r[1], r[2]);
        let got = Ecef::new(r[3], r[4], r[5]).to_geodetic();
        // Angles as metres on the ground (1 degree < 112 km), the longitude
        // weighted by the distance from the axis.
        let radius_m = want.prime_vertical_radius_m() + want.h_m;
        let lat_err_m = (got.lat_deg - want.lat_deg).to_radians().abs() * radius_m;
        let lon_err_m = lon_diff_deg(got.lon_deg, want.lon_deg).to_radians().abs()
            * radius_m
            * want.lat_rad().cos().abs();
        let h_err_m = (got.h_m - want.h_m).abs();
        let err_m = lat_err_m.max(lon_err_m).max(h_err_m);
        assert!(err_m < 1e-3, "{want:?} -> {got:?} (lat {lat_err_m} m, lon {lon_err_m} m, h {h_err_m} m)");
        worst_m = worst_m.max(err_m);
    }
    eprintln!("ECEF -> geodetic worst error vs pyproj: {worst_m:.3e} m");
}

#[test]
fn geodetic_ecef_round_trip_is_micrometre_exact() {
    for r in fixture_rows("pyproj_geodetic_ecef.csv") {
        let g = Geodetic::new(r[0], r[1], r[2]);
        let p = g.to_ecef();
        let back = p.to_geodetic();
        assert!((back.h_m - g.h_m).abs() < 1e-6, "{g:?} -> {back:?}");
        assert!((back.lat_deg - g.lat_deg).abs() < 1e-11, "{g:?} -> {back:?}");
        if g.lat_deg.abs() < 90.0 {
            assert!(lon_diff_deg(back.lon_deg, g.lon_deg).abs() < 1e-11, "{g:?} -> {back:?}");
        }
        // Also in ECEF, which is indifferent to the longitude at the poles.
        let err_m = back.to_ecef().distance_m(&p);
        assert!(err_m < 1e-6, "{g:?}: ECEF round trip off by {err_m} m");
    }
}

#[test]
fn enu_matches_pyproj_topocentric() {
    let mut worst_m: f64 = 0.0;
    for r in fixture_rows("pyproj_topocentric.csv") {
        let frame = LocalFrame::at(Geodetic::new(r[0], r[1], r[2]));
        let p = Ecef::new(r[3], r[4], r[5]);
        let want = nalgebra::Vector3::new(r[6], r[7], r[8]);
        let got = frame.to_enu(&p);
        let err_m = (got.0 - want).norm();
        assert!(err_m < 1e-3, "origin {:?}, {p:?}: {got:?} vs pyproj {want:?}", frame.origin());
        // And back to ECEF.
        let back_m = frame.to_ecef(got).distance_m(&p);
        assert!(back_m < 1e-6, "ENU -> ECEF round trip off by {back_m} m");
        worst_m = worst_m.max(err_m);
    }
    eprintln!("ECEF -> ENU worst error vs pyproj topocentric: {worst_m:.3e} m");
}
