//! Re-lighting of the terrain under a [`Sun`] other than the ortho's: an
//! illumination factor on every node of the terrain grid, computed once per
//! flight (`trn_landmark::lighting`: Lambertian shading and cast shadows, the
//! model `trn build --sun` bakes into templates), that the renderer
//! multiplies into each terrain pixel (bilinear at the pixel's hit point).

use trn_landmark::lighting::{illumination, SunLight};

pub use crate::effects::Sun;
use crate::scene::{LatLonGrid, Terrain};

/// The illumination factor on the terrain grid's nodes (1 where there is no DEM).
#[derive(Clone, Debug)]
pub struct Illumination {
    pub factor: LatLonGrid<f32>,
}

impl Illumination {
    /// The factor of every node of `terrain` under `sun` (validated: elevation
    /// in (0, 90], ambient in [0, 1]).
    pub fn new(terrain: &Terrain, sun: &Sun) -> Self {
        let g = &terrain.heights;
        let light =
            SunLight { azimuth_deg: sun.azimuth_deg, elevation_deg: sun.elevation_deg, ambient: sun.ambient };
        let factor = g.with_values(illumination(g, &light));
        Self { factor }
    }

    /// The factor at a fractional grid position (row, col); 1 outside the grid.
    #[inline]
    pub fn at(&self, row: f64, col: f64) -> f32 {
        self.factor.bilinear_at_or(row, col, 1.0)
    }

    /// The factor at a point; 1 outside the grid.
    #[inline]
    pub fn at_latlon(&self, lat_deg: f64, lon_deg: f64) -> f32 {
        self.factor.bilinear_or(lat_deg, lon_deg, 1.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use trn_geodesy::metres_per_degree;

    const LAT0: f64 = 40.2;
    const LON0: f64 = -105.7;
    const D: f64 = 0.0005;
    const N: usize = 201;

    /// Terrain on a 201 x 201 grid of 0.0005 deg (~55 m north, ~42 m east)
    /// with heights from `f(east_m, north_m)` measured from the grid's centre.
    fn terrain(f: impl Fn(f64, f64) -> f64) -> Terrain {
        let (lat_c, lon_c) = centre();
        let mut values = Vec::new();
        for r in 0..N {
            for c in 0..N {
                let (e, n) = enu(LAT0 - r as f64 * D, LON0 + c as f64 * D, lat_c, lon_c);
                values.push(f(e, n) as f32);
            }
        }
        Terrain::new(LatLonGrid {
            north_lat_deg: LAT0,
            west_lon_deg: LON0,
            dlat_deg: D,
            dlon_deg: D,
            rows: N,
            cols: N,
            values,
        })
        .unwrap()
    }

    fn centre() -> (f64, f64) {
        (LAT0 - D * (N / 2) as f64, LON0 + D * (N / 2) as f64)
    }

    /// East and north (m) of a point from (lat_c, lon_c), east with the
    /// point's own longitude scale (exact along each row).
    fn enu(lat: f64, lon: f64, lat_c: f64, lon_c: f64) -> (f64, f64) {
        ((lon - lon_c) * metres_per_degree(lat).1, (lat - lat_c) * metres_per_degree(lat_c).0)
    }

    fn sun(azimuth_deg: f64, elevation_deg: f64) -> Sun {
        Sun { azimuth_deg, elevation_deg, ambient: 0.25 }
    }

    /// The factor in full shadow.
    fn shadow_factor(s: &Sun) -> f64 {
        s.ambient / (s.ambient + (1.0 - s.ambient) * s.elevation_deg.to_radians().sin())
    }

    /// Every node with its east/north position from the centre and factor.
    fn nodes(il: &Illumination) -> Vec<(f64, f64, f64)> {
        let (lat_c, lon_c) = centre();
        let g = &il.factor;
        (0..N * N)
            .map(|i| {
                let (r, c) = (i / N, i % N);
                let (e, n) = enu(LAT0 - r as f64 * D, LON0 + c as f64 * D, lat_c, lon_c);
                (e, n, g.values[i] as f64)
            })
            .collect()
    }

    #[test]
    fn flat_ground_keeps_the_ortho_brightness() {
        let t = terrain(|_, _| 1500.0);
        for (az, el) in [(0.0, 10.0), (135.0, 35.0), (290.0, 80.0), (-45.0, 90.0)] {
            let il = Illumination::new(&t, &sun(az, el));
            assert!(il.factor.values.iter().all(|&f| (f - 1.0).abs() < 1e-6), "az {az} el {el}");
        }
    }

    #[test]
    fn ridge_shadow_falls_where_the_sun_says() {
        // A north-south wall 200 m high and ~130 m wide (east 0..130 m), sun
        // from the east at 20 degrees: shadow west of its foot to 200 / tan 20
        // = 549 m, light beyond, none on the sunny side.
        let (h, wall) = (200.0, 0.0..130.0);
        let t = terrain(|e, _| if wall.contains(&e) { 1500.0 + h } else { 1500.0 });
        let s = sun(90.0, 20.0);
        let il = Illumination::new(&t, &s);
        let len = h / 20f64.to_radians().tan();
        let dark = shadow_factor(&s);
        // Column spacing (~42.6 m): the wall's west face is one cell wide.
        let cell = D * metres_per_degree(LAT0).1;
        let (mut shadowed, mut lit) = (0, 0);
        for (e, n, f) in nodes(&il) {
            if n.abs() > 3000.0 {
                continue;
            }
            // Distance west of the wall's top edge (the first node on the wall).
            let west_of_top = -e;
            if west_of_top > cell && west_of_top < len - 1.5 * cell {
                assert!((f - dark).abs() < 1e-4, "({e:.0}, {n:.0}) in shadow: {f} vs {dark}");
                shadowed += 1;
            } else if west_of_top > len + 1.5 * cell || e > wall.end + cell {
                assert!((f - 1.0).abs() < 1e-4, "({e:.0}, {n:.0}) in light: {f}");
                lit += 1;
            }
        }
        assert!(shadowed > 1000 && lit > 10_000, "{shadowed} shadowed, {lit} lit nodes");
        // The penumbra's middle at the shadow's end: along a row the factor
        // crosses halfway between dark and 1 within a third of a cell of it.
        let mid_row = N / 2;
        let row: Vec<(f64, f64)> = nodes(&il)[mid_row * N..(mid_row + 1) * N]
            .iter()
            .map(|&(e, _, f)| (-e, f))
            .filter(|&(w, _)| w > len - 3.0 * cell && w < len + 3.0 * cell)
            .collect();
        let half = 0.5 * (dark + 1.0);
        let cross = row
            .windows(2)
            .find_map(|p| {
                let ((w1, f1), (w0, f0)) = (p[0], p[1]);
                ((f0 - half) * (f1 - half) <= 0.0 && f0 != f1)
                    .then(|| w0 + (half - f0) / (f1 - f0) * (w1 - w0))
            })
            .expect("an edge");
        assert!((cross - len).abs() < cell / 3.0, "edge at {cross:.1} m, expected {len:.1} m");
    }

    #[test]
    fn oblique_sun_casts_a_block_shadow_along_its_azimuth() {
        // A block 300 m high and 400 x 400 m, sun from the south-east (135
        // deg) at 25 degrees: the shadow points north-west and reaches
        // 300 / tan 25 = 643 m from the block. A point is in the shadow when
        // its ray toward the sun enters the block within that distance.
        let (h, (hx, hy)) = (300.0, (200.0, 200.0));
        let t = terrain(|e, n| if e.abs() <= hx && n.abs() <= hy { 1500.0 + h } else { 1500.0 });
        let s = sun(135.0, 25.0);
        let il = Illumination::new(&t, &s);
        // The block's top as the nodes see it (the bilinear surface falls
        // from its outer nodes to the next ones).
        let on_top = |(e, n, _): &(f64, f64, f64)| e.abs() <= hx && n.abs() <= hy;
        let nodes_top: Vec<(f64, f64, f64)> = nodes(&il).into_iter().filter(on_top).collect();
        let hx = nodes_top.iter().map(|p| p.0.abs()).fold(0.0, f64::max);
        let hy = nodes_top.iter().map(|p| p.1.abs()).fold(0.0, f64::max);
        let len = h / 25f64.to_radians().tan();
        let dark = shadow_factor(&s);
        let u = (std::f64::consts::FRAC_1_SQRT_2, -std::f64::consts::FRAC_1_SQRT_2);
        // Distance along u from (e, n) to where the ray enters the block (slabs).
        let enter = |e: f64, n: f64| -> Option<f64> {
            let slab = |p: f64, d: f64, half: f64| ((-half - p) / d).min((half - p) / d);
            let slab_out = |p: f64, d: f64, half: f64| ((-half - p) / d).max((half - p) / d);
            let t_in = slab(e, u.0, hx).max(slab(n, u.1, hy));
            let t_out = slab_out(e, u.0, hx).min(slab_out(n, u.1, hy));
            (t_in <= t_out && t_out >= 0.0).then_some(t_in.max(0.0))
        };
        let shadowed_at = |e: f64, n: f64| enter(e, n).is_some_and(|t| t < len);
        // About 1.5 steps of the diagonal sweep (~60 m): the edges may move that much.
        let margin = 90.0;
        let ring: Vec<(f64, f64)> = (0..16)
            .map(|k| {
                let a = k as f64 * std::f64::consts::TAU / 16.0;
                (margin * a.cos(), margin * a.sin())
            })
            .collect();
        let (mut deep, mut clear, mut tip) = (0, 0, f64::MIN);
        let mut worst_clear: f64 = 0.0;
        for (e, n, f) in nodes(&il) {
            if e.abs() <= hx + 60.0 && n.abs() <= hy + 60.0 {
                continue; // the block and its faces
            }
            let around = ring.iter().filter(|(de, dn)| shadowed_at(e + de, n + dn)).count();
            if around == ring.len() && shadowed_at(e, n) {
                assert!((f - dark).abs() < 0.02, "({e:.0}, {n:.0}) should be in shadow: {f} vs {dark}");
                deep += 1;
            } else if around == 0 && !shadowed_at(e, n) {
                worst_clear = worst_clear.max((f - 1.0).abs());
                clear += 1;
            }
            if f < 0.5 * (1.0 + dark) {
                // Shadowed nodes lie within the margin of the shadow.
                assert!(around > 0 || shadowed_at(e, n), "({e:.0}, {n:.0}) shadowed, far from the shadow");
                if let Some(t) = enter(e, n) {
                    tip = tip.max(t);
                }
            }
        }
        assert!(worst_clear < 1e-4, "light outside the shadow: worst |factor - 1| = {worst_clear}");
        assert!(deep > 30 && clear > 30_000, "{deep} in deep shadow, {clear} clear");
        println!("{deep} nodes in deep shadow, tip at {tip:.0} m for {len:.0} m");
        assert!((tip - len).abs() < 60.0, "shadow reaches {tip:.0} m, expected {len:.0} m");
    }

    #[test]
    fn lambert_on_planes_of_known_slope() {
        // 30 degree planes facing east, west and north under suns of known
        // elevation (the plane's heights follow each row's own longitude
        // scale: a missing cos(lat) would tilt them wrong).
        let g = 30f64.to_radians().tan();
        let f = |ns: f64, s: &Sun| {
            let a = s.ambient;
            (a + (1.0 - a) * ns.max(0.0)) / (a + (1.0 - a) * s.elevation_deg.to_radians().sin())
        };
        let mid = (N / 2) * N + N / 2;
        for el in [20.0f64, 45.0, 60.0] {
            let e_rad = el.to_radians();
            let s = sun(90.0, el);
            // Facing the sun (descending eastward): n.s = sin(E + 30).
            let east = Illumination::new(&terrain(|e, _| 1500.0 - g * e), &s);
            let want = f((e_rad + 30f64.to_radians()).sin(), &s);
            assert!(
                (east.factor.values[mid] as f64 - want).abs() < 1e-4,
                "{el}: {}",
                east.factor.values[mid]
            );
            // Facing away: sin(E - 30), nothing when the sun is lower than the slope.
            let west = Illumination::new(&terrain(|e, _| 1500.0 + g * e), &s);
            let want = f((e_rad - 30f64.to_radians()).sin(), &s);
            assert!(
                (west.factor.values[mid] as f64 - want).abs() < 1e-4,
                "{el}: {}",
                west.factor.values[mid]
            );
            // Facing north, the sun in the east: n.s = cos 30 sin E.
            let north = Illumination::new(&terrain(|_, n| 1500.0 - g * n), &s);
            let want = f(30f64.to_radians().cos() * e_rad.sin(), &s);
            assert!(
                (north.factor.values[mid] as f64 - want).abs() < 1e-4,
                "{el}: {}",
                north.factor.values[mid]
            );
        }
        // A sun from the north on the north-facing plane: sin(E + 30).
        let s = sun(0.0, 40.0);
        let north = Illumination::new(&terrain(|_, n| 1500.0 - g * n), &s);
        let want = f(70f64.to_radians().sin(), &s);
        assert!((north.factor.values[mid] as f64 - want).abs() < 1e-4);
    }

    #[test]
    fn no_data_and_outside_are_left_alone() {
        let mut t = terrain(|e, _| 1500.0 + 0.5 * e.max(0.0));
        t.heights.values[(N / 2) * N + N / 2] = f32::NAN;
        let il = Illumination::new(&t, &sun(270.0, 30.0));
        assert_eq!(il.factor.values[(N / 2) * N + N / 2], 1.0);
        assert!(il.factor.values.iter().all(|f| f.is_finite()));
        assert_eq!(il.at(-1.0, 3.0), 1.0);
        assert_eq!(il.at(3.0, N as f64), 1.0);
    }
}
