//! Landmark types shared by the builder, the store, the server and the navigator.
//!
//! The main type is [`Template`]: a small north-up image patch resampled on the
//! local tangent plane at its centre, 3D-referenced on the WGS84 ellipsoid, with
//! the terrain geometry (a plane fit and a coarse height grid) the navigator needs
//! to predict it into a camera image. Pure data, no I/O. Also: [`wire`], the
//! binary encoding of template lists; [`grid`], values on a latitude/longitude
//! grid; [`lighting`], the brightness of terrain under a sun (the builder bakes
//! it into templates, the simulator re-lights its worlds with it).
//!
//! ```
//! use trn_landmark::GeoBox;
//!
//! // A box across the antimeridian (min_lon > max_lon) holds points on both sides.
//! let b = GeoBox::new(179.5, -17.0, -179.5, -16.0);
//! assert!(b.crosses_antimeridian());
//! assert!(b.contains(179.9, -16.5) && b.contains(-179.9, -16.5) && !b.contains(0.0, -16.5));
//! // A box grown by 1 km on every side (about 0.009 deg of latitude).
//! let shore = GeoBox::new(-112.3, 40.6, -112.1, 40.8);
//! assert!(!shore.contains(-112.2, 40.805) && shore.grown_m(1000.0).contains(-112.2, 40.805));
//! ```

pub mod grid;
pub mod lighting;
pub mod wire;

use nalgebra::Vector3;
use serde::{Deserialize, Serialize};
use trn_geodesy::{Ecef, Enu, Geodetic, LocalFrame};

/// A box in geodetic longitude/latitude (degrees, WGS84). `min_lon > max_lon` means the
/// box crosses the antimeridian.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeoBox {
    pub min_lon_deg: f64,
    pub min_lat_deg: f64,
    pub max_lon_deg: f64,
    pub max_lat_deg: f64,
}

impl GeoBox {
    pub fn new(min_lon_deg: f64, min_lat_deg: f64, max_lon_deg: f64, max_lat_deg: f64) -> Self {
        Self { min_lon_deg, min_lat_deg, max_lon_deg, max_lat_deg }
    }

    /// The smallest box holding all points (no antimeridian crossing).
    pub fn around(points: impl IntoIterator<Item = (f64, f64)>) -> Option<Self> {
        let mut it = points.into_iter();
        let (lon, lat) = it.next()?;
        let mut b = Self::new(lon, lat, lon, lat);
        for (lon, lat) in it {
            b.min_lon_deg = b.min_lon_deg.min(lon);
            b.max_lon_deg = b.max_lon_deg.max(lon);
            b.min_lat_deg = b.min_lat_deg.min(lat);
            b.max_lat_deg = b.max_lat_deg.max(lat);
        }
        Some(b)
    }

    /// The smallest box holding all points, crossing the antimeridian where
    /// that is smaller (points at 179.9 and -179.9 deg make a 0.2 deg box, not
    /// a 359.8 deg one): the longitudes' largest gap, the wrap included, is
    /// left out.
    pub fn around_wrapped(points: impl IntoIterator<Item = (f64, f64)>) -> Option<Self> {
        let pts: Vec<(f64, f64)> = points.into_iter().collect();
        let b = Self::around(pts.iter().copied())?;
        let mut lons: Vec<f64> = pts.iter().map(|p| p.0).collect();
        lons.sort_by(f64::total_cmp);
        let wrap_gap = lons[0] + 360.0 - lons[lons.len() - 1];
        let (k, gap) = lons
            .windows(2)
            .enumerate()
            .map(|(k, w)| (k, w[1] - w[0]))
            .max_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap_or((0, 0.0));
        Some(if gap > wrap_gap { Self { min_lon_deg: lons[k + 1], max_lon_deg: lons[k], ..b } } else { b })
    }

    pub fn crosses_antimeridian(&self) -> bool {
        self.min_lon_deg > self.max_lon_deg
    }

    /// East-west extent (deg), across the antimeridian where the box crosses it.
    pub fn lon_span_deg(&self) -> f64 {
        if self.crosses_antimeridian() {
            self.max_lon_deg + 360.0 - self.min_lon_deg
        } else {
            self.max_lon_deg - self.min_lon_deg
        }
    }

    /// Whether `other` lies inside this box (closed), antimeridian aware on
    /// both sides.
    pub fn contains_box(&self, other: &GeoBox) -> bool {
        other.halves().all(|o| {
            self.halves().any(|s| {
                s.min_lon_deg <= o.min_lon_deg
                    && o.max_lon_deg <= s.max_lon_deg
                    && s.min_lat_deg <= o.min_lat_deg
                    && o.max_lat_deg <= s.max_lat_deg
            })
        })
    }

    /// Splits an antimeridian-crossing box into two ordinary boxes.
    pub fn split_antimeridian(&self) -> Vec<GeoBox> {
        self.halves().collect()
    }

    /// [`GeoBox::split_antimeridian`] without allocating (hot in queries).
    fn halves(&self) -> impl Iterator<Item = GeoBox> {
        let crosses = self.crosses_antimeridian();
        let first = if crosses { GeoBox { max_lon_deg: 180.0, ..*self } } else { *self };
        let second = crosses.then_some(GeoBox { min_lon_deg: -180.0, ..*self });
        std::iter::once(first).chain(second)
    }

    /// Closed-interval intersection test, antimeridian aware on both sides.
    pub fn intersects(&self, other: &GeoBox) -> bool {
        self.halves().any(|a| {
            other.halves().any(|b| {
                a.min_lon_deg <= b.max_lon_deg
                    && b.min_lon_deg <= a.max_lon_deg
                    && a.min_lat_deg <= b.max_lat_deg
                    && b.min_lat_deg <= a.max_lat_deg
            })
        })
    }

    pub fn intersection(&self, other: &GeoBox) -> Option<GeoBox> {
        let b = GeoBox::new(
            self.min_lon_deg.max(other.min_lon_deg),
            self.min_lat_deg.max(other.min_lat_deg),
            self.max_lon_deg.min(other.max_lon_deg),
            self.max_lat_deg.min(other.max_lat_deg),
        );
        (b.min_lon_deg < b.max_lon_deg && b.min_lat_deg < b.max_lat_deg).then_some(b)
    }

    /// The box grown by `dlon_deg` and `dlat_deg` on every side: latitudes
    /// clamped at the poles, longitudes wrapped across the antimeridian (a box
    /// grown past it crosses it; one grown around the globe spans it all).
    pub fn grown(&self, dlon_deg: f64, dlat_deg: f64) -> GeoBox {
        let (min_lat, max_lat) =
            ((self.min_lat_deg - dlat_deg).max(-90.0), (self.max_lat_deg + dlat_deg).min(90.0));
        if self.lon_span_deg() + 2.0 * dlon_deg >= 360.0 {
            return GeoBox::new(-180.0, min_lat, 180.0, max_lat);
        }
        let wrap = |l: f64| {
            if l < -180.0 {
                l + 360.0
            } else if l > 180.0 {
                l - 360.0
            } else {
                l
            }
        };
        GeoBox::new(wrap(self.min_lon_deg - dlon_deg), min_lat, wrap(self.max_lon_deg + dlon_deg), max_lat)
    }

    /// [`GeoBox::grown`] by `metres` on every side (degrees at the box's
    /// middle latitude, [`trn_geodesy::metres_per_degree`]).
    pub fn grown_m(&self, metres: f64) -> GeoBox {
        let (m_lat, m_lon) = trn_geodesy::metres_per_degree(0.5 * (self.min_lat_deg + self.max_lat_deg));
        self.grown((metres / m_lon.max(1.0)).min(180.0), (metres / m_lat).min(90.0))
    }

    pub fn contains(&self, lon_deg: f64, lat_deg: f64) -> bool {
        self.halves().any(|b| {
            lon_deg >= b.min_lon_deg
                && lon_deg <= b.max_lon_deg
                && lat_deg >= b.min_lat_deg
                && lat_deg <= b.max_lat_deg
        })
    }
}

/// Terrain under a template, relative to its local tangent frame (ENU at the centre).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TerrainPatch {
    /// Unit normal of the least-squares plane through the terrain, in the ENU frame.
    pub plane_normal_enu: [f64; 3],
    /// RMS distance of the terrain samples from that plane (m): how far the
    /// planar template model is off.
    pub plane_residual_rms_m: f64,
    /// Heights (m, relative to the centre's ellipsoidal height) on an `n x n`
    /// grid spanning the template footprint, row 0 north, column 0 west.
    pub height_grid: HeightGrid,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HeightGrid {
    pub n: u32,
    /// Grid spacing on the tangent plane (m).
    pub spacing_m: f64,
    pub heights_m: Vec<f32>,
}

impl HeightGrid {
    /// Bilinear height (m, relative to the centre) at a tangent-plane offset.
    pub fn height_at(&self, east_m: f64, north_m: f64) -> f64 {
        let n = self.n as usize;
        if n == 0 || self.heights_m.len() != n * n {
            return 0.0;
        }
        let half = (n as f64 - 1.0) / 2.0;
        let col = (east_m / self.spacing_m + half).clamp(0.0, n as f64 - 1.0);
        let row = (half - north_m / self.spacing_m).clamp(0.0, n as f64 - 1.0);
        // (Truncation is the floor of these non-negative values, without a
        // call to libm's `floor` on targets without SSE4.1.)
        let (c0, r0) = (col as usize, row as usize);
        let (c1, r1) = ((c0 + 1).min(n - 1), (r0 + 1).min(n - 1));
        let (fc, fr) = (col - c0 as f64, row - r0 as f64);
        let h = |r: usize, c: usize| self.heights_m[r * n + c] as f64;
        (h(r0, c0) * (1.0 - fc) + h(r0, c1) * fc) * (1.0 - fr)
            + (h(r1, c0) * (1.0 - fc) + h(r1, c1) * fc) * fr
    }

    /// Share of the grid's nodes the template's own terrain hides from a
    /// viewer `view_deg` from the vertical, for each of 8 azimuths (north,
    /// then clockwise in 45-degree steps; the viewer lies that way): a node
    /// is hidden when the terrain toward the viewer, within the grid, rises
    /// above its line of sight.
    pub fn hidden_shares(&self, view_deg: f64) -> [f64; 8] {
        let n = self.n as usize;
        let mut out = [0.0; 8];
        if n < 2 || self.heights_m.len() != n * n || view_deg <= 0.0 {
            return out;
        }
        let rise = 1.0 / view_deg.to_radians().tan();
        // Terrain that never rises faster than the line of sight hides nothing:
        // the bilinear surface's slope along any direction is at most the sum of
        // its steepest east and north node differences.
        let h = |r: usize, c: usize| self.heights_m[r * n + c] as f64;
        let (mut gx, mut gy) = (0.0f64, 0.0f64);
        for r in 0..n {
            for c in 0..n {
                if c + 1 < n {
                    gx = gx.max((h(r, c + 1) - h(r, c)).abs());
                }
                if r + 1 < n {
                    gy = gy.max((h(r + 1, c) - h(r, c)).abs());
                }
            }
        }
        if (gx + gy) / self.spacing_m <= rise {
            return out;
        }
        let half = (n as f64 - 1.0) / 2.0 * self.spacing_m;
        let step = self.spacing_m / 2.0;
        for (a, share) in out.iter_mut().enumerate() {
            let az = a as f64 * std::f64::consts::FRAC_PI_4;
            let (de, dn) = (az.sin(), az.cos());
            let mut hidden = 0;
            for r in 0..n {
                for c in 0..n {
                    let (e0, n0) = (-half + c as f64 * self.spacing_m, half - r as f64 * self.spacing_m);
                    let h0 = self.heights_m[r * n + c] as f64;
                    let mut s = step;
                    loop {
                        let (e, nn) = (e0 + s * de, n0 + s * dn);
                        if e.abs() > half + 1e-9 || nn.abs() > half + 1e-9 {
                            break;
                        }
                        if self.height_at(e, nn) > h0 + s * rise + 1e-3 {
                            hidden += 1;
                            break;
                        }
                        s += step;
                    }
                }
            }
            *share = hidden as f64 / (n * n) as f64;
        }
        out
    }

    /// The least of [`HeightGrid::hidden_shares`]: what the template's own
    /// relief hides at `view_deg` from the vertical even from its best side.
    /// A mission whose views are that oblique from every side cannot predict
    /// that much of it.
    pub fn hidden_share_best_side(&self, view_deg: f64) -> f64 {
        self.hidden_shares(view_deg).into_iter().fold(1.0, f64::min)
    }
}

/// How good a landmark the template is: the builder's selection scores.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TemplateQuality {
    /// Shi-Tomasi strength: smaller eigenvalue of the mean structure tensor,
    /// in (grey levels / pixel)^2.
    pub shi_tomasi: f32,
    /// Standard deviation of the template's grey levels.
    pub contrast_std: f32,
    /// Highest normalised cross-correlation of the template against its own
    /// surroundings away from the true position (lower is more distinctive).
    pub second_peak_ncc: f32,
    /// How much of the template's contrast relief shading could make: the
    /// spread of its terrain's brightness factor over a set of suns (the
    /// build's `--sun`s, else four azimuths at 35°) times its mean grey
    /// level, over `contrast_std`, at most 1. Near 0 the texture is albedo
    /// (stable under any sun); near 1 it may be mostly shading and shadow.
    pub shading_share: f32,
}

/// One landmark: a north-up image template on the local tangent plane.
///
/// Pixel `(col, row)` (centre convention as the flight format: `(0, 0)` is the
/// centre of the top-left pixel) shows the terrain at the tangent-plane offset
/// `east = (col - (w - 1) / 2) * gsd`, `north = ((h - 1) / 2 - row) * gsd` from
/// the centre, at the height the [`TerrainPatch`] gives there.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Template {
    /// Database id (0 before it is stored).
    pub id: i64,
    /// Pyramid level: ground sample distance = base GSD * 2^level.
    pub level: u8,
    pub gsd_m: f64,
    pub width_px: u32,
    pub height_px: u32,
    /// Centre, WGS84 ellipsoidal height.
    pub center: Geodetic,
    pub footprint: GeoBox,
    pub terrain: TerrainPatch,
    pub quality: TemplateQuality,
    /// Index into the build's list of ortho sources.
    pub source: u32,
    /// Lighting of the pixels: 0 the ortho as imaged, k >= 1 rendered under
    /// the build's k-th `--sun` (database metadata `suns`). A database built
    /// with several suns holds each landmark once per sun.
    pub lighting: u8,
    /// Grey levels, row-major, row 0 north.
    pub pixels: Vec<u8>,
}

impl Template {
    pub fn center_ecef(&self) -> Ecef {
        self.center.to_ecef()
    }

    pub fn local_frame(&self) -> LocalFrame {
        LocalFrame::at(self.center)
    }

    /// Tangent-plane offset of a template pixel (col, row) from the centre.
    pub fn pixel_offset_enu(&self, col: f64, row: f64) -> Enu {
        let e = (col - (self.width_px as f64 - 1.0) / 2.0) * self.gsd_m;
        let n = ((self.height_px as f64 - 1.0) / 2.0 - row) * self.gsd_m;
        Enu::new(e, n, self.terrain.height_grid.height_at(e, n))
    }

    /// ECEF position of the terrain seen at template pixel (col, row).
    pub fn pixel_ecef(&self, col: f64, row: f64) -> Ecef {
        self.local_frame().to_ecef(self.pixel_offset_enu(col, row))
    }

    pub fn plane_normal_enu(&self) -> Vector3<f64> {
        Vector3::from(self.terrain.plane_normal_enu)
    }

    /// Corners of the footprint (NW, NE, SE, SW) on the tangent plane, as geodetic points.
    pub fn footprint_corners(&self) -> [Geodetic; 4] {
        let frame = self.local_frame();
        let (w, h) = (self.width_px as f64 - 0.5, self.height_px as f64 - 0.5);
        [(-0.5, -0.5), (w, -0.5), (w, h), (-0.5, h)].map(|(c, r)| {
            let enu = self.pixel_offset_enu(c, r);
            frame.to_ecef(enu).to_geodetic()
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn grid(n: u32, spacing_m: f64, h: impl Fn(f64, f64) -> f64) -> HeightGrid {
        let half = (n as f64 - 1.0) / 2.0 * spacing_m;
        let heights_m = (0..n * n)
            .map(|i| {
                let (r, c) = ((i / n) as f64, (i % n) as f64);
                h(-half + c * spacing_m, half - r * spacing_m) as f32
            })
            .collect();
        HeightGrid { n, spacing_m, heights_m }
    }

    #[test]
    fn flat_and_gentle_terrain_hides_nothing_a_wall_hides_what_is_behind_it() {
        assert_eq!(grid(9, 10.0, |_, _| 0.0).hidden_shares(80.0), [0.0; 8]);
        // A 20-degree slope rising east is seen from anywhere within 70 degrees of the vertical.
        let slope = grid(9, 10.0, |e, _| e * 20f64.to_radians().tan());
        assert_eq!(slope.hidden_shares(65.0), [0.0; 8]);
        // It faces west: seen from 75 degrees off the vertical from the east (its
        // back), it hides itself; from the west nothing hides.
        let s = slope.hidden_shares(75.0);
        assert!(s[2] > 0.5 && s[6] == 0.0, "{s:?}");
        assert_eq!(slope.hidden_share_best_side(75.0), 0.0);
        // A ridge 30 m high at e = 0, 10 m wide: from 45 degrees, the nodes
        // within 30 m behind it on the far side are hidden.
        let ridge = grid(9, 10.0, |e, _| if e.abs() < 1.0 { 30.0 } else { 0.0 });
        let s = ridge.hidden_shares(45.0);
        // Brute force: from the east (az 90), node (e, n) with e < 0 is hidden when
        // 30 > (0 - e) * cot(45) -> e > -30: columns e = -10, -20 (e = -30 touches).
        assert!((s[2] - 2.0 * 9.0 / 81.0).abs() < 1e-9, "{s:?}");
        assert!((s[6] - 2.0 * 9.0 / 81.0).abs() < 1e-9, "{s:?}");
        // Along the ridge (north, south) nothing is hidden: its best side hides nothing.
        assert_eq!((s[0], s[4]), (0.0, 0.0));
        assert_eq!(ridge.hidden_share_best_side(45.0), 0.0);
        // A pit 40 m deep and 20 m across hides its floor from every side at 45 degrees.
        let pit = grid(9, 10.0, |e, n| if e.abs() < 11.0 && n.abs() < 11.0 { -40.0 } else { 0.0 });
        assert!(pit.hidden_share_best_side(45.0) > 0.0);
        assert_eq!(pit.hidden_share_best_side(5.0), 0.0);
    }

    #[test]
    fn geobox_grows_by_degrees_and_metres_within_the_globe() {
        let b = GeoBox::new(-118.6, 37.2, -118.4, 37.4);
        let g = b.grown(0.1, 0.2);
        let want = [-118.7, 37.0, -118.3, 37.6];
        let got = [g.min_lon_deg, g.min_lat_deg, g.max_lon_deg, g.max_lat_deg];
        assert!(got.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-12), "{g:?}");
        // 10 km: against geodesic distances along a meridian and a parallel.
        let g = b.grown_m(10_000.0);
        let south = Geodetic::new(g.min_lat_deg, -118.5, 0.0).to_ecef();
        let south_edge = Geodetic::new(b.min_lat_deg, -118.5, 0.0).to_ecef();
        assert!((south.distance_m(&south_edge) - 10_000.0).abs() < 20.0, "{g:?}");
        let west = Geodetic::new(37.3, g.min_lon_deg, 0.0).to_ecef();
        let west_edge = Geodetic::new(37.3, b.min_lon_deg, 0.0).to_ecef();
        assert!((west.distance_m(&west_edge) - 10_000.0).abs() < 20.0, "{g:?}");
        // Clamped at the poles; across the antimeridian a box wraps and
        // crosses it, and a crossing box grows on both sides.
        assert_eq!(
            GeoBox::new(179.0, 89.0, 179.5, 89.5).grown(2.0, 2.0),
            GeoBox::new(177.0, 87.0, -178.5, 90.0)
        );
        let crossing = GeoBox::new(179.0, 0.0, -179.0, 1.0);
        let g = crossing.grown(0.5, 0.5);
        assert_eq!(g, GeoBox::new(178.5, -0.5, -178.5, 1.5));
        assert!((g.lon_span_deg() - 3.0).abs() < 1e-12 && g.contains_box(&crossing));
        // Grown around the globe: every longitude.
        assert_eq!(crossing.grown(179.0, 0.0), GeoBox::new(-180.0, 0.0, 180.0, 1.0));
        assert_eq!(
            GeoBox::new(-10.0, 0.0, 10.0, 1.0).grown(170.0, 0.0),
            GeoBox::new(-180.0, 0.0, 180.0, 1.0)
        );
    }

    #[test]
    fn geobox_around_the_antimeridian_is_the_small_box() {
        // Points on both sides of 180 deg: the 0.2 deg box, not the 359.8 deg one.
        let b = GeoBox::around_wrapped([(179.9, 10.0), (-179.9, 10.5), (179.95, 10.2)]).unwrap();
        assert_eq!(b, GeoBox::new(179.9, 10.0, -179.9, 10.5));
        assert!(b.crosses_antimeridian() && (b.lon_span_deg() - 0.2).abs() < 1e-9);
        // Elsewhere the same as `around`, whatever the order of the points.
        let pts = [(-111.0, 40.0), (-110.5, 40.5), (-110.8, 39.9)];
        assert_eq!(GeoBox::around_wrapped(pts), GeoBox::around(pts));
        assert_eq!(GeoBox::around_wrapped([(5.0, 1.0)]), Some(GeoBox::new(5.0, 1.0, 5.0, 1.0)));
        assert_eq!(GeoBox::around_wrapped(std::iter::empty()), None);
        // Containment across the antimeridian.
        assert!(b.contains_box(&GeoBox::new(179.95, 10.1, -179.95, 10.4)));
        assert!(b.contains_box(&GeoBox::new(-179.95, 10.1, -179.92, 10.4)));
        assert!(!b.contains_box(&GeoBox::new(179.0, 10.1, 179.95, 10.4)));
        assert!(!GeoBox::new(-10.0, 0.0, 10.0, 1.0).contains_box(&b));
    }

    #[test]
    fn geobox_antimeridian_split_and_intersect() {
        let b = GeoBox::new(179.0, -1.0, -179.0, 1.0);
        assert!(b.crosses_antimeridian());
        assert_eq!(b.split_antimeridian().len(), 2);
        assert!(b.intersects(&GeoBox::new(179.5, 0.0, 179.9, 0.5)));
        assert!(b.intersects(&GeoBox::new(-179.5, 0.0, -179.2, 0.5)));
        assert!(!b.intersects(&GeoBox::new(0.0, 0.0, 1.0, 0.5)));
        assert!(b.contains(-179.5, 0.0));
        assert!(!b.contains(0.0, 0.0));
    }

    #[test]
    fn height_grid_bilinear_matches_plane() {
        // h = 0.1 e - 0.2 n is reproduced exactly by bilinear interpolation.
        let n = 5u32;
        let spacing = 10.0;
        let mut heights = Vec::new();
        for r in 0..n {
            for c in 0..n {
                let e = (c as f64 - 2.0) * spacing;
                let nn = (2.0 - r as f64) * spacing;
                heights.push((0.1 * e - 0.2 * nn) as f32);
            }
        }
        let g = HeightGrid { n, spacing_m: spacing, heights_m: heights };
        for (e, nn) in [(0.0, 0.0), (3.3, -7.1), (-19.0, 19.0), (12.5, 4.0)] {
            assert!((g.height_at(e, nn) - (0.1 * e - 0.2 * nn)).abs() < 1e-5);
        }
    }
}
