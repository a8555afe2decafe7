//! The builder's EGM96 conversion (Debian's egm96_15.gtx read with GDAL,
//! interpolated in trn-geodesy) against PROJ's own (pyproj fixture, see
//! scripts/fixtures/geoid_pyproj.py).

use std::path::Path;

use trn_builder::terrain::load_geoid;

#[test]
fn egm96_undulation_matches_proj() {
    let grid = load_geoid(Path::new(trn_builder::EGM96_GRID)).expect("proj-data's egm96_15.gtx");
    let fixture = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/pyproj_egm96.csv");
    let mut rdr = csv::Reader::from_path(&fixture).unwrap();
    let mut worst = 0f64;
    let mut n = 0;
    for rec in rdr.records() {
        let rec = rec.unwrap();
        let f = |i: usize| rec[i].parse::<f64>().unwrap();
        let (lat, lon, want) = (f(0), f(1), f(2));
        let got = grid.undulation_at(lat, lon).unwrap_or_else(|| panic!("no undulation at {lat},{lon}"));
        worst = worst.max((got - want).abs());
        assert!((got - want).abs() < 0.01, "{lat},{lon}: {got:.4} m, PROJ {want:.4} m");
        n += 1;
    }
    assert!(n >= 50);
    eprintln!("{n} points, worst difference from PROJ {:.2} mm", worst * 1000.0);
}
