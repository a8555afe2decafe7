//! `GeoidGrid` with synthetic grids: bilinear exactness, longitude wrap, edges.

use trn_geodesy::GeoidGrid;

/// A grid filled from `f(lat, lon)` at its nodes.
fn grid(
    north_lat_deg: f64,
    west_lon_deg: f64,
    d_deg: f64,
    rows: usize,
    cols: usize,
    f: impl Fn(f64, f64) -> f64,
) -> GeoidGrid {
    let mut undulation_m = Vec::with_capacity(rows * cols);
    for r in 0..rows {
        for c in 0..cols {
            undulation_m.push(f(north_lat_deg - r as f64 * d_deg, west_lon_deg + c as f64 * d_deg) as f32);
        }
    }
    GeoidGrid {
        name: "synthetic".into(),
        north_lat_deg,
        west_lon_deg,
        dlat_deg: d_deg,
        dlon_deg: d_deg,
        rows,
        cols,
        undulation_m,
    }
}

#[test]
fn bilinear_is_exact_on_a_plane() {
    // Regional 0.5-degree grid over 30..40 N, -110..-100 E.
    let plane = |lat: f64, lon: f64| 10.0 + 0.75 * (lat - 35.0) - 0.5 * (lon + 105.0);
    let g = grid(40.0, -110.0, 0.5, 21, 21, plane);
    assert!(!g.wraps());
    for &(lat, lon) in &[(35.0, -105.0), (35.123, -104.987), (30.0, -110.0), (40.0, -100.0), (39.99, -100.01)]
    {
        let n = g.undulation_at(lat, lon).unwrap();
        assert!((n - plane(lat, lon)).abs() < 1e-5, "({lat}, {lon}): {n} vs {}", plane(lat, lon));
    }
    // Also a bilinear (saddle) surface, which bilinear interpolation reproduces.
    let saddle = |lat: f64, lon: f64| 0.01 * (lat - 30.0) * (lon + 110.0);
    let g = grid(40.0, -110.0, 0.5, 21, 21, saddle);
    let n = g.undulation_at(33.3, -107.7).unwrap();
    assert!((n - saddle(33.3, -107.7)).abs() < 1e-5);
}

#[test]
fn regional_grid_is_none_outside() {
    let g = grid(40.0, -110.0, 0.5, 21, 21, |_, _| 1.0);
    for &(lat, lon) in
        &[(40.01, -105.0), (29.99, -105.0), (35.0, -110.01), (35.0, -99.99), (35.0, 70.0), (35.0, 249.9)]
    {
        assert_eq!(g.undulation_at(lat, lon), None, "({lat}, {lon})");
    }
    // The same longitudes written in [0, 360) are inside.
    assert_eq!(g.undulation_at(35.0, 250.0), Some(1.0));
    assert_eq!(g.undulation_at(35.0, 255.0), Some(1.0));
}

#[test]
fn regional_grid_across_the_antimeridian() {
    // 170 E .. 170 W (column 0 at 170, 21 columns of 1 degree).
    let g = grid(10.0, 170.0, 1.0, 11, 21, |_, lon| lon.rem_euclid(360.0));
    assert!((g.undulation_at(5.0, 175.5).unwrap() - 175.5).abs() < 1e-4);
    assert!((g.undulation_at(5.0, -175.0).unwrap() - 185.0).abs() < 1e-4);
    assert!((g.undulation_at(5.0, -170.0).unwrap() - 190.0).abs() < 1e-4);
    assert_eq!(g.undulation_at(5.0, -169.9), None);
    assert_eq!(g.undulation_at(5.0, 169.9), None);
}

#[test]
fn global_grid_wraps_in_longitude() {
    // 10-degree global grid, columns at -180, -170, ..., 170 (36 columns: no repeat).
    let f = |lat: f64, lon: f64| lat + 100.0 * (lon.to_radians()).cos();
    let g = grid(90.0, -180.0, 10.0, 19, 36, f);
    assert!(g.wraps());
    // Between the last column (170) and the first (-180 = 180): linear in between.
    let want = |lat: f64, lon_a: f64, lon_b: f64, w: f64| (1.0 - w) * f(lat, lon_a) + w * f(lat, lon_b);
    let n = g.undulation_at(20.0, 175.0).unwrap();
    assert!((n - want(20.0, 170.0, 180.0, 0.5)).abs() < 1e-4, "{n}");
    // The same point written in any longitude convention.
    for lon in [175.0, -185.0, 535.0, -545.0] {
        assert!((g.undulation_at(20.0, lon).unwrap() - n).abs() < 1e-9, "{lon}");
    }
    // Exactly on the seam, both sides.
    for lon in [180.0, -180.0, 540.0] {
        assert!((g.undulation_at(20.0, lon).unwrap() - f(20.0, 180.0)).abs() < 1e-4);
    }
    // A hair west of column 0 interpolates with the last column, never None.
    let n = g.undulation_at(20.0, -180.0 - 1e-12).unwrap();
    assert!((n - f(20.0, 180.0)).abs() < 1e-4);
    // The poles are nodes here.
    assert!((g.undulation_at(90.0, 33.0).unwrap() - want(90.0, 30.0, 40.0, 0.3)).abs() < 1e-4);
    assert!(g.undulation_at(-90.0, 0.0).is_some());
    assert_eq!(g.undulation_at(90.5, 0.0), None);
}

#[test]
fn global_grid_with_repeated_seam_column() {
    // Columns 0, 30, ..., 360 (13 columns: the last repeats the first).
    let f = |_: f64, lon: f64| (lon.to_radians()).sin() * 50.0;
    let g = grid(60.0, 0.0, 30.0, 5, 13, f);
    assert!(g.wraps());
    for lon in [-15.0, 345.0, 705.0] {
        let n = g.undulation_at(0.0, lon).unwrap();
        assert!((n - 0.5 * (f(0.0, 330.0) + f(0.0, 0.0))).abs() < 1e-4, "{lon}: {n}");
    }
    // Cell-centred global grid: poleward of the outer rows clamps to them.
    assert!((g.undulation_at(75.0, 30.0).unwrap() - f(60.0, 30.0)).abs() < 1e-4);
    assert!((g.undulation_at(-90.0, 90.0).unwrap() - f(-60.0, 90.0)).abs() < 1e-4);
}

#[test]
fn no_data_and_malformed_grids_give_none() {
    let mut g = grid(40.0, -110.0, 1.0, 11, 11, |_, _| 5.0);
    g.undulation_m[5 * 11 + 5] = f32::NAN; // node (35 N, 105 W)
    assert_eq!(g.undulation_at(35.5, -104.5), None);
    assert_eq!(g.undulation_at(34.5, -105.5), None);
    assert_eq!(g.undulation_at(36.5, -106.5), Some(5.0));
    g.undulation_m.pop();
    assert_eq!(g.undulation_at(36.5, -106.5), None);
    assert_eq!(grid(40.0, -110.0, 1.0, 0, 0, |_, _| 0.0).undulation_at(35.0, -105.0), None);
}
