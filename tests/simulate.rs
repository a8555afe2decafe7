//! End to end: `trn simulate` on synthetic terrain (`trn synth`).
//!
//! - Geometry: ground points picked on the ortho's pixel grid are projected
//!   through the flight's truth pose and camera model, and the ortho patch
//!   around each is found in the rendered image at that pixel (< 0.2 px), for
//!   a nadir, a 60-degree tilted and a distorted 30-degree tilted camera, and
//!   a spinning nadir camera whose true focal length, principal point, k1 and
//!   clock differ from `camera.json` (the image must follow the true camera
//!   at the exposure time, where `camera.json` at the stamp is pixels off). The
//!   reference is built without the simulator's code: GDAL for the map
//!   projection and the rasters, a brute-force ray march through the DEM,
//!   `trn_camera` for the rays, the ortho's luma sampled bilinearly (averaged
//!   over the pixel's footprint where it spans several ortho pixels). Both
//!   images are smoothed (Gaussian, 1 px) and matched by Gaussian-weighted
//!   NCC at integer shifts, the peak refined by a quadratic fit; points whose
//!   reference is ambiguous (roads, smooth ramps: it matches itself elsewhere
//!   within the search) are skipped. A reference moved by one pixel must be
//!   reported one pixel off (the test can see a renderer error).
//! - The flight folder is complete and consistent (rates, sizes, truth,
//!   initial-guess errors) and reproducible from the seed.
//! - Tilted cameras on a rocket and a balloon see sky above the horizon.
//! - Bad inputs fail with one `error:` line naming the culprit and leave
//!   nothing behind; an existing flight folder is replaced whole.

mod common;

use std::path::{Path, PathBuf};
use std::process::Output;

use gdal::spatial_ref::{AxisMappingStrategy, CoordTransform, SpatialRef};
use gdal::Dataset;
use serde_json::{json, Value};
use trn_camera::{CameraModel, CameraPose, Pixel};
use trn_flight::Flight;
use trn_geodesy::{Ecef, Geodetic, LocalFrame, Ray};

/// Grey level of sky with realism off (the simulator's documented value).
const SKY_DN: u8 = 190;

// ---------------------------------------------------------------------------
// Running the simulator.

fn write_scenario(dir: &Path, name: &str, s: &Value) -> PathBuf {
    let p = dir.join(format!("{name}.json"));
    std::fs::write(&p, serde_json::to_string_pretty(s).unwrap()).unwrap();
    p
}

use common::simulate;

fn simulate_ok(ortho: &Path, dem: &Path, scenario: &Path, out: &Path, extra: &[&str]) {
    let o = simulate(ortho, dem, scenario, out, extra);
    assert!(o.status.success(), "simulate {} failed: {}", scenario.display(), common::stderr(&o));
}

/// A rendered frame as grey levels.
fn read_grey(path: &Path) -> (Vec<u8>, usize, usize) {
    let img = image::open(path).unwrap_or_else(|e| panic!("{}: {e}", path.display())).to_luma8();
    let (w, h) = img.dimensions();
    (img.into_raw(), w as usize, h as usize)
}

/// Temporary folders the simulator may leave next to `--out` if it fails badly.
fn temp_leftovers(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with(".trn-"))
        .collect()
}

// ---------------------------------------------------------------------------
// The independent reference: rasters and map projection through GDAL.

fn srs(epsg: u32) -> SpatialRef {
    let mut s = SpatialRef::from_epsg(epsg).unwrap();
    s.set_axis_mapping_strategy(AxisMappingStrategy::TraditionalGisOrder);
    s
}

/// A north-up raster in memory (one value per pixel).
struct Raster {
    gt: [f64; 6],
    w: usize,
    h: usize,
    v: Vec<f64>,
}

impl Raster {
    /// Band 1, or the Rec. 601 luma of bands 1-3 (`luma`).
    fn read(path: &Path, luma: bool) -> Raster {
        let ds = Dataset::open(path).unwrap();
        let gt = ds.geo_transform().unwrap();
        assert!(gt[2] == 0.0 && gt[4] == 0.0 && gt[5] < 0.0, "{}: not north-up", path.display());
        let band = |b: usize| ds.rasterband(b).unwrap().read_band_as::<f64>().unwrap();
        let (w, h) = ds.rasterband(1).unwrap().size();
        let v = if luma {
            let (r, g, b) = (band(1), band(2), band(3));
            (r.data().iter().zip(g.data()).zip(b.data()))
                .map(|((r, g), b)| 0.299 * r + 0.587 * g + 0.114 * b)
                .collect()
        } else {
            band(1).data().to_vec()
        };
        Raster { gt, w, h, v }
    }

    /// Fractional (col, row) of a map point, (0, 0) = centre of the top-left pixel.
    fn pixel_of(&self, e: f64, n: f64) -> (f64, f64) {
        ((e - self.gt[0]) / self.gt[1] - 0.5, (n - self.gt[3]) / self.gt[5] - 0.5)
    }

    /// Map coordinates of a (col, row) position (pixel-centre convention).
    fn map_of(&self, c: f64, r: f64) -> (f64, f64) {
        (self.gt[0] + (c + 0.5) * self.gt[1], self.gt[3] + (r + 0.5) * self.gt[5])
    }

    /// Bilinear value at (col, row); NaN outside the pixel centres' hull.
    fn bilinear(&self, c: f64, r: f64) -> f64 {
        let (wm, hm) = ((self.w - 1) as f64, (self.h - 1) as f64);
        if !(c >= 0.0 && r >= 0.0 && c <= wm && r <= hm) {
            return f64::NAN;
        }
        let (ic, ir) = ((c.floor() as usize).min(self.w - 2), (r.floor() as usize).min(self.h - 2));
        let (tc, tr) = (c - ic as f64, r - ir as f64);
        let v = |cc: usize, rr: usize| self.v[rr * self.w + cc];
        (v(ic, ir) * (1.0 - tc) + v(ic + 1, ir) * tc) * (1.0 - tr)
            + (v(ic, ir + 1) * (1.0 - tc) + v(ic + 1, ir + 1) * tc) * tr
    }
}

/// Latitude/longitude -> UTM, bilinear between nodes that GDAL transformed
/// exactly (nodes ~50 m apart: interpolation error well below a millimetre,
/// checked against GDAL in [`World::open`]), so the brute-force ray march can
/// afford millions of evaluations.
struct LatLonToUtm {
    north: f64,
    west: f64,
    dlat: f64,
    dlon: f64,
    n: usize,
    e: Vec<f64>,
    nn: Vec<f64>,
}

impl LatLonToUtm {
    fn utm(&self, lat: f64, lon: f64) -> Option<(f64, f64)> {
        let (r, c) = ((self.north - lat) / self.dlat, (lon - self.west) / self.dlon);
        let m = (self.n - 1) as f64;
        if !(r >= 0.0 && c >= 0.0 && r <= m && c <= m) {
            return None;
        }
        let (ir, ic) = ((r.floor() as usize).min(self.n - 2), (c.floor() as usize).min(self.n - 2));
        let (tr, tc) = (r - ir as f64, c - ic as f64);
        let i = ir * self.n + ic;
        let f = |v: &[f64]| {
            (v[i] * (1.0 - tc) + v[i + 1] * tc) * (1.0 - tr)
                + (v[i + self.n] * (1.0 - tc) + v[i + self.n + 1] * tc) * tr
        };
        Some((f(&self.e), f(&self.nn)))
    }
}

/// The synthetic ortho and DEM as read by GDAL, with the map projection.
struct World {
    ortho: Raster,
    dem: Raster,
    ll: LatLonToUtm,
    utm_to_ll: CoordTransform,
    dem_max: f64,
}

impl World {
    fn open(ortho: &Path, dem: &Path) -> World {
        let ortho = Raster::read(ortho, true);
        let dem = Raster::read(dem, false);
        let (utm, wgs) = (srs(32613), srs(4326));
        let utm_to_ll = CoordTransform::new(&utm, &wgs).unwrap();
        let ll_to_utm = CoordTransform::new(&wgs, &utm).unwrap();
        // Lat/lon box of the DEM.
        let (e0, n0) = dem.map_of(-0.5, -0.5);
        let (e1, n1) = dem.map_of(dem.w as f64 - 0.5, dem.h as f64 - 0.5);
        let mut xs = vec![e0, e1, e0, e1];
        let mut ys = vec![n0, n0, n1, n1];
        utm_to_ll.transform_coords(&mut xs, &mut ys, &mut [0.0; 4]).unwrap();
        let (west, east) =
            (xs.iter().cloned().fold(f64::MAX, f64::min), xs.iter().cloned().fold(f64::MIN, f64::max));
        let (south, north) =
            (ys.iter().cloned().fold(f64::MAX, f64::min), ys.iter().cloned().fold(f64::MIN, f64::max));
        let n = 161;
        let (dlat, dlon) = ((north - south) / (n - 1) as f64, (east - west) / (n - 1) as f64);
        let mut lons = Vec::with_capacity(n * n);
        let mut lats = Vec::with_capacity(n * n);
        for r in 0..n {
            for c in 0..n {
                lons.push(west + c as f64 * dlon);
                lats.push(north - r as f64 * dlat);
            }
        }
        ll_to_utm.transform_coords(&mut lons, &mut lats, &mut vec![0.0; n * n]).unwrap();
        let ll = LatLonToUtm { north, west, dlat, dlon, n, e: lons, nn: lats };
        // The interpolation agrees with GDAL's exact transform.
        let mut seed = 99u64;
        let mut rnd = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64
        };
        let pts: Vec<(f64, f64)> =
            (0..500).map(|_| (south + (north - south) * rnd(), west + (east - west) * rnd())).collect();
        let mut xs: Vec<f64> = pts.iter().map(|p| p.1).collect();
        let mut ys: Vec<f64> = pts.iter().map(|p| p.0).collect();
        ll_to_utm.transform_coords(&mut xs, &mut ys, &mut vec![0.0; pts.len()]).unwrap();
        let worst = pts
            .iter()
            .zip(xs.iter().zip(&ys))
            .map(|(&(lat, lon), (&x, &y))| {
                let (e, n) = ll.utm(lat, lon).unwrap();
                (e - x).hypot(n - y)
            })
            .fold(0.0, f64::max);
        assert!(worst < 1e-3, "lat/lon -> UTM interpolation is {worst} m off GDAL");
        let dem_max = dem.v.iter().cloned().fold(f64::MIN, f64::max);
        World { ortho, dem, ll, utm_to_ll, dem_max }
    }

    /// Latitude/longitude of UTM points (GDAL).
    fn to_lat_lon(&self, pts: &[(f64, f64)]) -> Vec<(f64, f64)> {
        let mut xs: Vec<f64> = pts.iter().map(|p| p.0).collect();
        let mut ys: Vec<f64> = pts.iter().map(|p| p.1).collect();
        self.utm_to_ll.transform_coords(&mut xs, &mut ys, &mut vec![0.0; pts.len()]).unwrap();
        ys.into_iter().zip(xs).collect()
    }

    /// DEM height (bilinear, ellipsoidal) at a latitude/longitude; NaN off the DEM.
    fn dem_at(&self, lat: f64, lon: f64) -> f64 {
        match self.ll.utm(lat, lon) {
            Some((e, n)) => {
                let (c, r) = self.dem.pixel_of(e, n);
                self.dem.bilinear(c, r)
            }
            None => f64::NAN,
        }
    }

    /// Height of an ECEF point above the terrain (NaN off the DEM).
    fn above(&self, p: &Ecef) -> f64 {
        let g = p.to_geodetic();
        g.h_m - self.dem_at(g.lat_deg, g.lon_deg)
    }

    /// Ortho (col, row) of a geodetic point (pixel-centre convention).
    fn ortho_xy(&self, g: &Geodetic) -> Option<(f64, f64)> {
        let (e, n) = self.ll.utm(g.lat_deg, g.lon_deg)?;
        Some(self.ortho.pixel_of(e, n))
    }

    /// Brute force: the first crossing of the terrain by the ray, marched by
    /// 3 m steps from 30 m before `s_ref` (moved back by 30 m at a time, up
    /// to 300 m, while that start is below the terrain) to 300 m after it,
    /// then bisected to a few nanometres; `None` when the ray leaves the DEM.
    fn hit(&self, ray: &Ray, s_ref: f64) -> Option<Ecef> {
        let f = |s: f64| self.above(&ray.point_at(s));
        let (mut s, end, step) = (s_ref - 30.0, s_ref + 300.0, 3.0);
        while !(f(s) > 0.0) {
            s -= 30.0;
            if s < s_ref - 300.0 || f(s).is_nan() {
                return None;
            }
        }
        while s < end {
            let s1 = s + step;
            let f1 = f(s1);
            if f1.is_nan() {
                return None;
            }
            if f1 <= 0.0 {
                let (mut a, mut b) = (s, s1);
                for _ in 0..30 {
                    let m = 0.5 * (a + b);
                    if f(m) > 0.0 {
                        a = m;
                    } else {
                        b = m;
                    }
                }
                return Some(ray.point_at(0.5 * (a + b)));
            }
            s = s1;
        }
        None
    }

    /// True when the segment from the terrain point `p` to `cam` stays above
    /// the terrain (sampled every 4 m from `p` until above the highest DEM node).
    fn visible(&self, cam: &Ecef, p: &Ecef) -> bool {
        let len = cam.distance_m(p);
        let u = (cam.0 - p.0) / len;
        let mut s = 2.0;
        while s < len {
            let q = Ecef(p.0 + u * s);
            let g = q.to_geodetic();
            if g.h_m > self.dem_max + 1.0 {
                return true;
            }
            if !(g.h_m - self.dem_at(g.lat_deg, g.lon_deg) > 0.0) {
                return false;
            }
            s += 4.0;
        }
        true
    }
}

// ---------------------------------------------------------------------------
// Patch matching.

/// Half size of the reference patch (25 x 25 pixels).
const HALF: usize = 12;
const PATCH: usize = 2 * HALF + 1;
/// Integer search range (pixels).
const SEARCH: i64 = 3;
/// Both images are smoothed by a Gaussian of this standard deviation (pixels)
/// before matching: the texture's edges (2-pixel roads) alias at one sample
/// per pixel, and the rendered image and the reference sample them at
/// different phases, which would bias sub-pixel peaks by up to ~0.3 px.
const BLUR_SIGMA: f64 = 1.0;
const BLUR_R: usize = 3;
/// Half size of the reference region around the projected pixel: the patch,
/// moved by up to the search range (for its distinctiveness) plus one pixel
/// (for the self-check), plus the blur's reach.
const REGION_HALF: usize = HALF + SEARCH as usize + 1 + BLUR_R;
const REGION: usize = 2 * REGION_HALF + 1;

/// Separable Gaussian blur (BLUR_SIGMA), borders clamped.
fn blur(img: &[f64], w: usize, h: usize) -> Vec<f64> {
    let k: Vec<f64> =
        (-(BLUR_R as i64)..=BLUR_R as i64).map(|i| (-0.5 * (i as f64 / BLUR_SIGMA).powi(2)).exp()).collect();
    let norm: f64 = k.iter().sum();
    let pass = |src: &[f64], horizontal: bool| -> Vec<f64> {
        let mut out = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                let mut acc = 0.0;
                for (t, kv) in k.iter().enumerate() {
                    let o = t as i64 - BLUR_R as i64;
                    let (xx, yy) = if horizontal {
                        ((x as i64 + o).clamp(0, w as i64 - 1) as usize, y)
                    } else {
                        (x, (y as i64 + o).clamp(0, h as i64 - 1) as usize)
                    };
                    acc += kv * src[yy * w + xx];
                }
                out[y * w + x] = acc / norm;
            }
        }
        out
    };
    pass(&pass(img, true), false)
}

/// Standard deviation (pixels) of the Gaussian weights of the NCC window:
/// features entering or leaving the window's border as it moves would
/// otherwise skew the correlation peak.
const WINDOW_SIGMA: f64 = 0.5 * HALF as f64;

/// Gaussian-weighted NCC of a PATCH x PATCH reference against the window of
/// `img` (row length `w`) whose top-left pixel is (x0, y0).
fn ncc(reference: &[f64], img: &[f64], w: usize, x0: usize, y0: usize) -> f64 {
    static WEIGHTS: std::sync::OnceLock<Vec<f64>> = std::sync::OnceLock::new();
    let weights = WEIGHTS.get_or_init(|| {
        (0..PATCH * PATCH)
            .map(|k| {
                let (di, dj) = ((k % PATCH) as f64 - HALF as f64, (k / PATCH) as f64 - HALF as f64);
                (-(di * di + dj * dj) / (2.0 * WINDOW_SIGMA * WINDOW_SIGMA)).exp()
            })
            .collect()
    });
    let (mut sw, mut sa, mut sb, mut saa, mut sbb, mut sab) = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0);
    for j in 0..PATCH {
        for i in 0..PATCH {
            let k = weights[j * PATCH + i];
            let a = reference[j * PATCH + i];
            let b = img[(y0 + j) * w + x0 + i];
            sw += k;
            sa += k * a;
            sb += k * b;
            saa += k * a * a;
            sbb += k * b * b;
            sab += k * a * b;
        }
    }
    let va = saa - sa * sa / sw;
    let vb = sbb - sb * sb / sw;
    (sab - sa * sb / sw) / (va * vb).sqrt().max(1e-12)
}

/// NCC at the integer shifts (dx, dy) in +-SEARCH of the window centred on
/// pixel `c` of `img`, row-major from (-SEARCH, -SEARCH).
fn ncc_surface(reference: &[f64], img: &[f64], w: usize, c: (usize, usize)) -> Vec<f64> {
    let mut scores = Vec::new();
    for dy in -SEARCH..=SEARCH {
        for dx in -SEARCH..=SEARCH {
            let (x0, y0) = (c.0 as i64 - HALF as i64 + dx, c.1 as i64 - HALF as i64 + dy);
            scores.push(ncc(reference, img, w, x0 as usize, y0 as usize));
        }
    }
    scores
}

/// Sub-pixel peak (du, dv, NCC) of an NCC surface (see [`ncc_surface`]):
/// the integer maximum, then the vertex of the quadratic in u and v
/// (`a + b u + c v + d u^2 + e uv + f v^2`) fitted to it and its eight
/// neighbours. (Separate parabolas along u and v would be biased where the
/// peak is an ellipse oblique to the axes, as along the synthetic ortho's
/// diagonal roads and in tilted views.) `Err` when the maximum lies on the
/// border of the search.
fn peak(scores: &[f64]) -> Result<(f64, f64, f64), String> {
    let span = (2 * SEARCH + 1) as usize;
    let best = (0..scores.len()).max_by(|&a, &b| scores[a].total_cmp(&scores[b])).unwrap();
    let (bx, by) = (best % span, best / span);
    if !(bx > 0 && by > 0 && bx + 1 < span && by + 1 < span) {
        return Err(format!(
            "NCC peak {:.3} on the border of the +-{SEARCH} px search (at {}, {})",
            scores[best],
            bx as i64 - SEARCH,
            by as i64 - SEARCH
        ));
    }
    // Least squares on the 3 x 3 grid (closed form).
    let (mut b, mut c, mut d, mut e, mut f) = (0.0, 0.0, 0.0, 0.0, 0.0);
    let mut total = 0.0;
    for y in -1i64..=1 {
        for x in -1i64..=1 {
            let s = scores[(by as i64 + y) as usize * span + (bx as i64 + x) as usize];
            let (xf, yf) = (x as f64, y as f64);
            total += s;
            b += xf * s / 6.0;
            c += yf * s / 6.0;
            d += xf * xf * s / 2.0;
            f += yf * yf * s / 2.0;
            e += xf * yf * s / 4.0;
        }
    }
    let (d, f) = (d - total / 3.0, f - total / 3.0);
    // Vertex: [2d e; e 2f] (u, v) = -(b, c).
    let det = 4.0 * d * f - e * e;
    if !(d < 0.0 && f < 0.0 && det > 1e-12) {
        return Err(format!("NCC peak {:.3} is not a maximum of the fitted quadratic", scores[best]));
    }
    let (su, sv) = ((-b * 2.0 * f + c * e) / det, (-c * 2.0 * d + b * e) / det);
    if su.abs() > 1.0 || sv.abs() > 1.0 {
        return Err(format!(
            "NCC peak {:.3}: fitted vertex ({su:.2}, {sv:.2}) px off the maximum",
            scores[best]
        ));
    }
    Ok((bx as f64 - SEARCH as f64 + su, by as f64 - SEARCH as f64 + sv, scores[best]))
}

/// The reference region (REGION x REGION pixels, pixel (i, j) centred on image
/// position p + (i - REGION_HALF, j - REGION_HALF)) from the ortho positions
/// seen through the pixel corners (`corners`, (REGION + 1)^2 nodes, node
/// (a, b) at p + (a - REGION_HALF - 0.5, b - REGION_HALF - 0.5)): each pixel
/// averages the ortho luminance over its footprint (k x k samples, positions
/// bilinear between its four corners, k from the footprint's size), then
/// the region is blurred as the rendered image is.
fn reference_region(world: &World, corners: &[(f64, f64)]) -> Option<Vec<f64>> {
    let nc = REGION + 1;
    let node = |a: usize, b: usize| corners[b * nc + a];
    let mut out = Vec::with_capacity(REGION * REGION);
    for b in 0..REGION {
        for a in 0..REGION {
            let q = [node(a, b), node(a + 1, b), node(a, b + 1), node(a + 1, b + 1)];
            let d = |i: usize, j: usize| (q[i].0 - q[j].0).hypot(q[i].1 - q[j].1);
            let ext = d(1, 0).max(d(2, 0));
            // The ortho at the pixel's centre, or averaged over its footprint
            // (samples ~1 ortho pixel apart) where it spans more than one
            // ortho pixel, as any anti-aliased rendering must.
            let k = (ext.ceil() as usize).clamp(1, 24);
            let mut sum = 0.0;
            for t in 0..k {
                for s in 0..k {
                    let (fs, ft) = ((s as f64 + 0.5) / k as f64, (t as f64 + 0.5) / k as f64);
                    let lerp = |g: fn((f64, f64)) -> f64| {
                        (g(q[0]) * (1.0 - fs) + g(q[1]) * fs) * (1.0 - ft)
                            + (g(q[2]) * (1.0 - fs) + g(q[3]) * fs) * ft
                    };
                    sum += world.ortho.bilinear(lerp(|p| p.0), lerp(|p| p.1));
                }
            }
            let v = sum / (k * k) as f64;
            if v.is_nan() {
                return None;
            }
            out.push(v);
        }
    }
    Some(blur(&out, REGION, REGION))
}

/// The PATCH x PATCH part of the region centred on p + (du, dv).
fn crop(region: &[f64], du: usize, dv: usize) -> Vec<f64> {
    let (x0, y0) = (REGION_HALF - HALF + du, REGION_HALF - HALF + dv);
    (0..PATCH).flat_map(|j| region[(y0 + j) * REGION + x0..(y0 + j) * REGION + x0 + PATCH].to_vec()).collect()
}

/// A patch is distinctive when, within the search range, it matches itself
/// only at its own place: NCC against its own region below `MAX_SELF_NCC`
/// everywhere outside the central 3 x 3 shifts, and below `MAX_SELF_NCC_1PX`
/// at the four one-pixel shifts (roads and smooth ramps are ambiguous).
const MAX_SELF_NCC: f64 = 0.9;
const MAX_SELF_NCC_1PX: f64 = 0.97;

fn distinctive(patch: &[f64], region: &[f64]) -> bool {
    let scores = ncc_surface(patch, region, REGION, (REGION_HALF, REGION_HALF));
    let span = (2 * SEARCH + 1) as usize;
    let (mut far, mut near) = (f64::MIN, f64::MIN);
    for (i, &s) in scores.iter().enumerate() {
        let (dx, dy) = ((i % span) as i64 - SEARCH, (i / span) as i64 - SEARCH);
        if dx.abs() > 1 || dy.abs() > 1 {
            far = far.max(s);
        } else if dx.abs() + dy.abs() == 1 {
            near = near.max(s);
        }
    }
    far < MAX_SELF_NCC && near < MAX_SELF_NCC_1PX
}

/// Smaller eigenvalue of the gradient structure tensor of the raster over
/// the (2 half + 1)^2 window centred on pixel (c, r): high where the texture
/// varies in every direction.
fn shi_tomasi(img: &Raster, c: usize, r: usize, half: usize) -> f64 {
    let (mut gxx, mut gyy, mut gxy) = (0.0, 0.0, 0.0);
    let v = |x: usize, y: usize| img.v[y * img.w + x];
    for y in r - half..=r + half {
        for x in c - half..=c + half {
            let gx = 0.5 * (v(x + 1, y) - v(x - 1, y));
            let gy = 0.5 * (v(x, y + 1) - v(x, y - 1));
            gxx += gx * gx;
            gyy += gy * gy;
            gxy += gx * gy;
        }
    }
    0.5 * (gxx + gyy - ((gxx - gyy).powi(2) + 4.0 * gxy * gxy).sqrt())
}

struct GeoCase {
    name: &'static str,
    tilt_deg: f64,
    /// Start height above the ellipsoid (m).
    start_h_m: f64,
    /// Ground point under the camera (UTM 13N).
    origin_utm: (f64, f64),
    distortion: [f64; 5],
    /// `camera_error` of the scenario (focal, principal point, k1, time offset).
    camera_error: Option<CameraErrorCase>,
}

/// A calibration and timing error: the image must follow the *true* camera at
/// the *exposure* time, not `camera.json` at the stamp.
struct CameraErrorCase {
    focal_rel: f64,
    principal_px: (f64, f64),
    k1: f64,
    time_offset_s: f64,
    /// The balloon's yaw rate (deg/s), so that the time offset shows.
    yaw_rate_deg_s: f64,
}

#[derive(Default)]
struct GeoSummary {
    offsets: Vec<f64>,
    worst_ncc: f64,
    /// Offsets measured for references deliberately moved by 1 px in u / v.
    shifted_u: Vec<f64>,
    shifted_v: Vec<f64>,
    /// Candidates rejected as ambiguous (not distinctive) or unusable.
    ambiguous: usize,
    unusable: usize,
}

/// One ground point: the ortho patch around it must be found where the truth
/// pose projects it (panics otherwise). `false` when the point cannot serve
/// (occluded, off the DEM or the ortho, ambiguous texture).
#[allow(clippy::too_many_arguments)]
fn check_point(
    world: &World,
    model: &CameraModel,
    pose: &CameraPose,
    img: &[f64],
    w: usize,
    (c, r): (usize, usize),
    p: &Ecef,
    px: Pixel,
    what: &str,
    sum: &mut GeoSummary,
) -> bool {
    let cam = pose.position;
    if !world.visible(&cam, p) {
        sum.unusable += 1;
        return false;
    }
    // The ray through the projected pixel meets the terrain at the point.
    let ray = pose.ray(model, px);
    let hit =
        world.hit(&ray, (p.0 - cam.0).dot(&ray.direction)).expect("the point's own ray hits the terrain");
    let (hx, hy) = world.ortho_xy(&hit.to_geodetic()).unwrap();
    assert!(
        (hx - c as f64).hypot(hy - r as f64) < 0.01,
        "{what}: its ray meets the terrain at ortho ({hx:.3}, {hy:.3})"
    );
    let off = REGION_HALF as f64 + 0.5;
    let nc = REGION + 1;
    // Each ray's search starts where it meets the horizontal plane through p.
    let up = p.to_geodetic().up_ecef();
    // Cheap pre-check of the texture's distinctiveness on a region made with
    // the local affine map image -> ortho (from two more exact hits).
    let mut jac = [(0.0, 0.0); 2];
    for (k, (du, dv)) in [(4.0, 0.0), (0.0, 4.0)].into_iter().enumerate() {
        let ray = pose.ray(model, Pixel::new(px.u + du, px.v + dv));
        let s_ref = (p.0 - cam.0).dot(&up) / ray.direction.dot(&up);
        let Some(x) = world.hit(&ray, s_ref).and_then(|x| world.ortho_xy(&x.to_geodetic())) else {
            sum.unusable += 1;
            return false;
        };
        jac[k] = ((x.0 - hx) / 4.0, (x.1 - hy) / 4.0);
    }
    let affine: Vec<(f64, f64)> = (0..nc * nc)
        .map(|i| {
            let (a, b) = ((i % nc) as f64 - off, (i / nc) as f64 - off);
            (hx + jac[0].0 * a + jac[1].0 * b, hy + jac[0].1 * a + jac[1].1 * b)
        })
        .collect();
    match reference_region(world, &affine) {
        Some(approx) if distinctive(&crop(&approx, 0, 0), &approx) => {}
        _ => {
            sum.ambiguous += 1;
            return false;
        }
    }
    // Ortho positions seen through the pixel corners around p.
    let mut corners = Vec::with_capacity(nc * nc);
    'grid: for b in 0..nc {
        for a in 0..nc {
            let ray = pose.ray(model, Pixel::new(px.u + a as f64 - off, px.v + b as f64 - off));
            let s_ref = (p.0 - cam.0).dot(&up) / ray.direction.dot(&up);
            match world.hit(&ray, s_ref).and_then(|x| world.ortho_xy(&x.to_geodetic())) {
                Some(xy) => corners.push(xy),
                None => break 'grid,
            }
        }
    }
    let Some(region) = (corners.len() == nc * nc).then(|| reference_region(world, &corners)).flatten() else {
        sum.unusable += 1;
        return false;
    };
    let base = crop(&region, 0, 0);
    if !distinctive(&base, &region) {
        sum.ambiguous += 1;
        return false;
    }
    let n0 = (px.u.round() as usize, px.v.round() as usize);
    let expected = (px.u - n0.0 as f64, px.v - n0.1 as f64);
    let measure = |patch: &[f64]| -> (f64, f64, f64) {
        let (du, dv, s) = peak(&ncc_surface(patch, img, w, n0)).unwrap_or_else(|e| panic!("{what}: {e}"));
        (du - expected.0, dv - expected.1, s)
    };
    let (eu, ev, s) = measure(&base);
    let off = eu.hypot(ev);
    assert!(s > 0.9, "{what}: NCC peak {s:.3}");
    assert!(off < 0.2, "{what}: the ortho patch is found {off:.3} px away ({eu:+.3}, {ev:+.3})");
    sum.offsets.push(off);
    sum.worst_ncc = sum.worst_ncc.min(s);
    // Self-check: a reference moved by one pixel is reported one pixel off.
    let (eu, ev, _) = measure(&crop(&region, 1, 0));
    assert!(
        (eu - 1.0).abs() < 0.25 && ev.abs() < 0.25,
        "{what}: self-check: a reference moved by (+1, 0) px measured ({eu:+.3}, {ev:+.3})"
    );
    sum.shifted_u.push(eu.hypot(ev));
    let (eu, ev, _) = measure(&crop(&region, 0, 1));
    assert!(
        eu.abs() < 0.25 && (ev - 1.0).abs() < 0.25,
        "{what}: self-check: a reference moved by (0, +1) px measured ({eu:+.3}, {ev:+.3})"
    );
    sum.shifted_v.push(eu.hypot(ev));
    true
}

fn geometric_case(dir: &Path, world: &World, ortho: &Path, dem: &Path, case: &GeoCase) -> GeoSummary {
    let (lat, lon) = world.to_lat_lon(&[case.origin_utm])[0];
    let d = case.distortion;
    let mut scenario = json!({
        "name": case.name,
        "origin": {"lat": lat, "lon": lon},
        "camera": {
            "width": 640, "height": 480, "hfov_deg": 40.0, "tilt_deg": case.tilt_deg,
            "distortion": {"k1": d[0], "k2": d[1], "p1": d[2], "p2": d[3], "k3": d[4]}
        },
        "trajectory": {
            "kind": "balloon", "start_h_m": case.start_h_m, "duration_s": 10.0,
            "pendulum_deg": 0.0, "yaw_rate_deg_s": 0.0, "spin_bursts": 0
        }
    });
    // With a time offset, a second frame one offset later gives the truth at
    // the first frame's exposure.
    let mut duration = "0".to_string();
    if let Some(e) = &case.camera_error {
        scenario["camera_error"] = json!({
            "focal_rel": e.focal_rel, "principal_du_px": e.principal_px.0, "principal_dv_px": e.principal_px.1,
            "k1": e.k1, "time_offset_s": e.time_offset_s
        });
        scenario["trajectory"]["yaw_rate_deg_s"] = json!(e.yaw_rate_deg_s);
        scenario["frame_rate_hz"] = json!(1.0 / e.time_offset_s);
        duration = format!("{}", e.time_offset_s);
    }
    let sc = write_scenario(dir, case.name, &scenario);
    let out = dir.join(format!("flight-{}", case.name));
    simulate_ok(ortho, dem, &sc, &out, &["--duration", &duration]);

    let flight = Flight::open(&out).unwrap();
    let n_frames = if case.camera_error.is_some() { 2 } else { 1 };
    assert_eq!(flight.frames.len(), n_frames, "{}: frames for --duration {duration}", case.name);
    let nominal = trn_flight::read_camera(&out.join("camera.json")).unwrap().model;
    let k = nominal.distortion;
    assert_eq!([k.k1, k.k2, k.p1, k.p2, k.k3], d, "{}: camera.json lens", case.name);
    if d == [0.0; 5] {
        assert!((nominal.hfov_deg() - 40.0).abs() < 1e-9, "{}: hfov {}", case.name, nominal.hfov_deg());
    }
    let truth = flight.truth.as_ref().unwrap()[n_frames - 1];
    let pose = CameraPose::new(truth.position.to_ecef(), truth.q_ecef_cam);
    // The camera that took the image: camera.json with the errors applied.
    let mut model = nominal;
    if let Some(e) = &case.camera_error {
        model.fx *= 1.0 + e.focal_rel;
        model.fy *= 1.0 + e.focal_rel;
        model.cx += e.principal_px.0;
        model.cy += e.principal_px.1;
        model.distortion.k1 += e.k1;
        assert_eq!(flight.frames[1].t, truth.t);
    }
    let stamped = flight.truth.as_ref().unwrap()[0];
    let stamped = CameraPose::new(stamped.position.to_ecef(), stamped.q_ecef_cam);
    let mut naive_shift = Vec::new();
    let (grey, w, h) = read_grey(&flight.image_path(&flight.frames[0]));
    assert_eq!((w, h), (model.width as usize, model.height as usize));
    let img = blur(&grey.iter().map(|&v| v as f64).collect::<Vec<_>>(), w, h);

    // Candidate ground points on the ortho's pixel grid, inside the image
    // with room for the patch and the search.
    let mut grid = Vec::new();
    for r in (30..world.ortho.h - 30).step_by(11) {
        for c in (30..world.ortho.w - 30).step_by(11) {
            grid.push((c, r));
        }
    }
    let utm: Vec<(f64, f64)> = grid.iter().map(|&(c, r)| world.ortho.map_of(c as f64, r as f64)).collect();
    let ll = world.to_lat_lon(&utm);
    let margin = (REGION_HALF + 3) as f64;
    let mut cands = Vec::new();
    for ((&(c, r), &(e, n)), &(lat, lon)) in grid.iter().zip(&utm).zip(&ll) {
        let (dc, dr) = world.dem.pixel_of(e, n);
        let p = Geodetic::new(lat, lon, world.dem.bilinear(dc, dr)).to_ecef();
        let pc = pose.to_camera(&p);
        // Well inside the field of view (no fold-back of the lens polynomial).
        if !(pc.z > 0.0 && (pc.x / pc.z).hypot(pc.y / pc.z) < 0.6) {
            continue;
        }
        let Some(px) = pose.project(&model, &p) else { continue };
        // Where a navigator trusting camera.json and the stamp would predict it.
        if let Some(q) = stamped.project(&nominal, &p) {
            naive_shift.push((q.u - px.u).hypot(q.v - px.v));
        }
        if px.u < margin || px.v < margin || px.u > w as f64 - 1.0 - margin || px.v > h as f64 - 1.0 - margin
        {
            continue;
        }
        cands.push(((c, r), p, px, shi_tomasi(&world.ortho, c, r, HALF)));
    }
    // Spread the points over the image: in each cell of a 7 x 5 grid, the
    // candidate nearest the cell's centre that can serve.
    let (gx, gy) = (7, 5);
    let mut sum = GeoSummary { worst_ncc: 1.0, ..Default::default() };
    for cy in 0..gy {
        for cx in 0..gx {
            let centre = ((cx as f64 + 0.5) * w as f64 / gx as f64, (cy as f64 + 0.5) * h as f64 / gy as f64);
            let mut cell: Vec<_> = cands
                .iter()
                .filter(|(_, _, px, _)| {
                    (px.u * gx as f64 / w as f64).floor() as usize == cx
                        && (px.v * gy as f64 / h as f64).floor() as usize == cy
                })
                .collect();
            // Most textured first (corners of roads and fields), nearer the
            // cell's centre on ties.
            cell.sort_by(|a, b| {
                let da = (a.2.u - centre.0).hypot(a.2.v - centre.1);
                let db = (b.2.u - centre.0).hypot(b.2.v - centre.1);
                b.3.total_cmp(&a.3).then(da.total_cmp(&db))
            });
            for &&(cr, p, px, _) in cell.iter().take(40) {
                let what = format!(
                    "{}: ground point at ortho ({}, {}) seen at ({:.2}, {:.2})",
                    case.name, cr.0, cr.1, px.u, px.v
                );
                if check_point(world, &model, &pose, &img, w, cr, &p, px, &what, &mut sum) {
                    break;
                }
            }
        }
    }
    if case.camera_error.is_some() {
        // The errors matter: trusting camera.json at the stamp would be pixels off.
        let m = mean(&naive_shift);
        println!("{}: camera.json at the stamp predicts {m:.2} px off on average", case.name);
        assert!(m > 3.0, "{}: the camera error moves the projection by only {m:.2} px", case.name);
    }
    assert!(
        sum.offsets.len() >= 25,
        "{}: only {} usable ground points ({} candidates in view, {} ambiguous, {} unusable)",
        case.name,
        sum.offsets.len(),
        cands.len(),
        sum.ambiguous,
        sum.unusable
    );
    sum
}

fn mean(v: &[f64]) -> f64 {
    v.iter().sum::<f64>() / v.len() as f64
}

#[test]
fn rendered_pixels_see_the_ground_points_the_truth_pose_projects() {
    let dir = tempfile::tempdir().unwrap();
    // 6 km at 4 m; DEM at 60 m, ~50 m relief, ellipsoidal heights.
    let (ortho, dem) = common::synth(dir.path(), 1500, 4.0, 440000.0, 3);
    let world = World::open(&ortho, &dem);
    let (e0, n0) = world.ortho.map_of(-0.5, -0.5);
    let size = world.ortho.w as f64 * world.ortho.gt[1];
    let centre = (e0 + 0.5 * size, n0 - 0.5 * size);
    let terrain = world.dem.v.iter().sum::<f64>() / world.dem.v.len() as f64;
    let no_lens = [0.0; 5];
    // 640 x 480 at 40 deg: f = 879 px, so ~3.3 km above the terrain gives ~3.8 m
    // at nadir; the tilted cameras stand south of the centre and look north.
    let cases = [
        GeoCase {
            name: "nadir",
            tilt_deg: 0.0,
            start_h_m: terrain + 3300.0,
            origin_utm: (centre.0 + 130.0, centre.1 - 70.0),
            distortion: no_lens,
            camera_error: None,
        },
        GeoCase {
            name: "tilt60",
            tilt_deg: 60.0,
            start_h_m: terrain + 1400.0,
            origin_utm: (centre.0, centre.1 - 2600.0),
            distortion: no_lens,
            camera_error: None,
        },
        GeoCase {
            name: "tilt30-distorted",
            tilt_deg: 30.0,
            start_h_m: terrain + 3300.0,
            origin_utm: (centre.0, centre.1 - 2100.0),
            distortion: [-0.25, 0.08, 0.001, -0.0005, 0.0],
            camera_error: None,
        },
        GeoCase {
            name: "nadir-calibration-and-clock-error",
            tilt_deg: 0.0,
            start_h_m: terrain + 3300.0,
            origin_utm: (centre.0 + 130.0, centre.1 - 70.0),
            distortion: no_lens,
            camera_error: Some(CameraErrorCase {
                focal_rel: 0.01,
                principal_px: (1.5, -1.0),
                k1: -0.02,
                time_offset_s: 0.05,
                yaw_rate_deg_s: 20.0,
            }),
        },
    ];
    for case in &cases {
        let s = geometric_case(dir.path(), &world, &ortho, &dem, case);
        println!(
            "{}: {} ground points ({} ambiguous skipped), offset mean {:.3} px, worst {:.3} px, \
             worst NCC {:.3}; references moved by 1 px measured {:.3} px (u) / {:.3} px (v) on average",
            case.name,
            s.offsets.len(),
            s.ambiguous,
            mean(&s.offsets),
            s.offsets.iter().cloned().fold(0.0, f64::max),
            s.worst_ncc,
            mean(&s.shifted_u),
            mean(&s.shifted_v)
        );
    }
}

// ---------------------------------------------------------------------------
// The flight folder.

/// Every realism effect on, with its defaults.
fn all_realism() -> Value {
    json!({
        "sun": {}, "spectral": {}, "brightness_field": {}, "photometric": {}, "haze": {}, "noise": {}, "vignetting": {},
        "motion_blur": {}, "clouds": {}, "cords": {}
    })
}

/// Relative path -> bytes of every file under `dir`.
fn tree(dir: &Path) -> Vec<(PathBuf, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.strip_prefix(dir).unwrap().to_path_buf(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn flight_folder_is_complete_consistent_and_reproducible() {
    let dir = tempfile::tempdir().unwrap();
    let (ortho, dem) = common::synth(dir.path(), 500, 5.0, 440000.0, 11);
    let scenario = |seed: u64| {
        json!({
            "name": "short balloon",
            "seed": seed,
            "camera": {"width": 160, "height": 120, "hfov_deg": 40.0, "exposure_s": 0.01},
            "frame_rate_hz": 4.0,
            "trajectory": {"kind": "balloon", "start_h_m": 4600.0, "duration_s": 1.5},
            "realism": all_realism()
        })
    };
    let sc = write_scenario(dir.path(), "seed7", &scenario(7));
    let out = dir.path().join("flight");
    simulate_ok(&ortho, &dem, &sc, &out, &[]);

    let flight = Flight::open(&out).unwrap_or_else(|e| panic!("the flight does not read back: {e}"));
    // Camera: the scenario's size and field of view.
    let model = flight.camera.model;
    assert_eq!((model.width, model.height), (160, 120));
    assert!((model.hfov_deg() - 40.0).abs() < 1e-9, "hfov {}", model.hfov_deg());
    // Frames: 1.5 s at 4 Hz, times k / rate, images of the camera's size.
    assert_eq!(flight.frames.len(), 7);
    for (k, f) in flight.frames.iter().enumerate() {
        assert!((f.t - k as f64 / 4.0).abs() < 1e-6, "frame {k} at t = {}", f.t);
        let (_, w, h) = read_grey(&flight.image_path(f));
        assert_eq!((w, h), (160, 120), "{}", f.image.display());
    }
    let (t_first, t_last) = (flight.frames[0].t, flight.frames[6].t);
    // IMU: 200 Hz (the default) over the whole flight, accelerometer included.
    let imu = &flight.imu;
    assert!(
        imu[0].t <= t_first + 1e-9 && imu[imu.len() - 1].t >= t_last - 1e-9,
        "IMU does not span the frames"
    );
    assert_eq!(imu.len(), 301);
    for pair in imu.windows(2) {
        assert!((pair[1].t - pair[0].t - 1.0 / 200.0).abs() < 2e-6, "IMU step at t = {}", pair[1].t);
    }
    assert!(imu.iter().all(|s| s.f_imu_m_s2.is_some()));
    // Truth: a row at every frame time.
    let truth = flight.truth.as_ref().expect("truth.csv");
    for f in &flight.frames {
        assert!(truth.iter().any(|r| (r.t - f.t).abs() < 1e-6), "no truth row at t = {}", f.t);
        assert!(flight.truth_at(f.t).is_some());
    }
    // Initial guess: off the first truth row by exactly the default errors.
    let t0 = truth.iter().find(|r| (r.t - t_first).abs() < 1e-6).unwrap();
    assert!((flight.init.t - t_first).abs() < 1e-6);
    let enu = LocalFrame::at(t0.position).to_enu(&flight.init.position.to_ecef());
    let horizontal = enu.east_m().hypot(enu.north_m());
    assert!((horizontal - 300.0).abs() < 0.05, "init.json is {horizontal:.3} m off horizontally");
    assert!((enu.up_m().abs() - 100.0).abs() < 0.05, "init.json is {:.3} m off vertically", enu.up_m());
    let angle = flight.init.q_ecef_cam.angle_to(&t0.q_ecef_cam).to_degrees();
    assert!((angle - 2.0).abs() < 1e-4, "init.json attitude is {angle:.6} deg off");

    // Same seed: byte-identical folder, images included (with another
    // number of threads, too).
    let again = dir.path().join("flight-again");
    simulate_ok(&ortho, &dem, &sc, &again, &["--threads", "1"]);
    let (a, b) = (tree(&out), tree(&again));
    assert_eq!(a.iter().map(|f| &f.0).collect::<Vec<_>>(), b.iter().map(|f| &f.0).collect::<Vec<_>>());
    for ((name, x), (_, y)) in a.iter().zip(&b) {
        assert!(x == y, "{} differs between two runs with the same seed", name.display());
    }
    // Another seed: other images.
    let sc8 = write_scenario(dir.path(), "seed8", &scenario(8));
    let other = dir.path().join("flight-other");
    simulate_ok(&ortho, &dem, &sc8, &other, &[]);
    let flight8 = Flight::open(&other).unwrap();
    assert_eq!(flight8.frames.len(), 7);
    for (f, g) in flight.frames.iter().zip(&flight8.frames) {
        let (x, y) = (read_grey(&flight.image_path(f)).0, read_grey(&flight8.image_path(g)).0);
        assert!(x != y, "{} is the same with seeds 7 and 8", f.image.display());
    }
    assert!(temp_leftovers(dir.path()).is_empty(), "left behind: {:?}", temp_leftovers(dir.path()));
}

// ---------------------------------------------------------------------------
// Sky above the horizon.

/// Checks each frame: the top rows are uniform sky, the bottom rows textured
/// ground inside the ortho.
fn check_sky_and_ground(flight_dir: &Path, what: &str) {
    let flight = Flight::open(flight_dir).unwrap();
    assert!(flight.frames.len() >= 2, "{what}: {} frames", flight.frames.len());
    for f in &flight.frames {
        let (grey, w, h) = read_grey(&flight.image_path(f));
        let rows = |r: std::ops::Range<usize>| grey[r.start * w..r.end * w].to_vec();
        let top = rows(0..4);
        assert!(
            top.iter().all(|&v| v == SKY_DN),
            "{what}, t = {}: the top rows are not all sky ({SKY_DN}): {:?}",
            f.t,
            &top[..w]
        );
        let bottom = rows(h - 10..h);
        let n = bottom.len() as f64;
        let share = |dn: u8| bottom.iter().filter(|&&v| v == dn).count() as f64 / n;
        let mean = bottom.iter().map(|&v| v as f64).sum::<f64>() / n;
        let sd = (bottom.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n).sqrt();
        assert!(
            share(SKY_DN) < 0.05 && share(0) < 0.05 && sd > 3.0,
            "{what}, t = {}: the bottom rows do not look like ortho ground (sky {:.2}, nodata {:.2}, sd {sd:.1})",
            f.t,
            share(SKY_DN),
            share(0)
        );
    }
}

#[test]
fn cameras_tilted_80_degrees_see_sky_above_the_horizon() {
    let dir = tempfile::tempdir().unwrap();
    // 3 km at 5 m; the vehicles stand 1 km south of the centre and look north.
    let (ortho, dem) = common::synth(dir.path(), 600, 5.0, 440000.0, 21);
    let world = World::open(&ortho, &dem);
    let (e0, n0) = world.ortho.map_of(-0.5, -0.5);
    let (lat, lon) = world.to_lat_lon(&[(e0 + 1500.0, n0 - 2500.0)])[0];
    let ground = world.dem_at(lat, lon);
    // A 30-degree vertical field of view around 80 degrees from nadir: the top
    // rows look 5 degrees above the horizontal, the bottom ones 65 degrees
    // from nadir (ground ~1 km ahead from 400 m up).
    let camera = json!({"width": 160, "height": 120, "hfov_deg": 40.0, "tilt_deg": 80.0});
    let balloon = json!({
        "origin": {"lat": lat, "lon": lon},
        "camera": camera,
        "frame_rate_hz": 2.0,
        "trajectory": {"kind": "balloon", "start_h_m": ground + 400.0, "duration_s": 1.0}
    });
    let sc = write_scenario(dir.path(), "balloon80", &balloon);
    let out = dir.path().join("balloon80");
    simulate_ok(&ortho, &dem, &sc, &out, &[]);
    check_sky_and_ground(&out, "balloon, camera tilted 80 deg");

    let rocket = json!({
        "origin": {"lat": lat, "lon": lon},
        "camera": camera,
        "frame_rate_hz": 2.0,
        "trajectory": {"kind": "rocket", "start_h_m": 350.0}
    });
    let sc = write_scenario(dir.path(), "rocket80", &rocket);
    let out = dir.path().join("rocket80");
    simulate_ok(&ortho, &dem, &sc, &out, &["--duration", "1"]);
    check_sky_and_ground(&out, "rocket, camera tilted 80 deg");
    // The rocket climbs.
    let truth = Flight::open(&out).unwrap().truth.unwrap();
    assert!(truth[truth.len() - 1].position.h_m > truth[0].position.h_m + 100.0);
}

// ---------------------------------------------------------------------------
// Bad inputs.

/// The run failed with exactly one `error:` line, the last one, naming all of
/// `names`; nothing was left next to `--out`.
fn assert_fails(o: &Output, names: &[&str], dir: &Path, what: &str) {
    let err = common::stderr(o);
    assert!(!o.status.success(), "{what}: the simulation succeeded");
    let lines: Vec<&str> = err.lines().filter(|l| !l.trim().is_empty()).collect();
    let errors: Vec<&&str> = lines.iter().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(errors.len(), 1, "{what}: expected one error line, got: {err}");
    assert!(lines.last().unwrap().starts_with("error:"), "{what}: the error is not the last line: {err}");
    println!("{what}: {}", errors[0]);
    for n in names {
        assert!(errors[0].contains(n), "{what}: the error does not name {n:?}: {}", errors[0]);
    }
    assert!(temp_leftovers(dir).is_empty(), "{what}: left behind {:?}", temp_leftovers(dir));
}

#[test]
fn bad_inputs_fail_with_one_clear_error_and_leave_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 200, 10.0, 440000.0, 31);
    let good = json!({
        "camera": {"width": 64, "height": 48, "hfov_deg": 40.0},
        "trajectory": {"kind": "balloon", "start_h_m": 4000.0, "duration_s": 1.0}
    });
    let good_sc = write_scenario(d, "good", &good);
    let out = d.join("flight");
    let run = |sc: &Path, ortho: &Path, dem: &Path, extra: &[&str]| simulate(ortho, dem, sc, &out, extra);

    let missing = d.join("missing-ortho.tif");
    assert_fails(&run(&good_sc, &missing, &dem, &[]), &["missing-ortho.tif"], d, "missing ortho");
    let missing = d.join("missing-dem.tif");
    assert_fails(&run(&good_sc, &ortho, &missing, &[]), &["missing-dem.tif"], d, "missing DEM");
    let missing = d.join("missing-scenario.json");
    assert_fails(&run(&missing, &ortho, &dem, &[]), &["missing-scenario.json"], d, "missing scenario");
    assert_fails(&run(&good_sc, &ortho, &dem, &["--duration=-1"]), &["--duration"], d, "negative --duration");

    let syntax = d.join("syntax.json");
    std::fs::write(&syntax, "{\"camera\": {\"width\": 64,,}").unwrap();
    assert_fails(&run(&syntax, &ortho, &dem, &[]), &["syntax.json", "line 1"], d, "JSON syntax error");

    // (name, change to the good scenario, what the error must name)
    let bad: [(&str, Value, &[&str]); 7] = [
        (
            "unknown-field",
            json!({"camera": {"width": 64, "height": 48, "hfov_deg": 40.0, "fov": 3}}),
            &["fov"],
        ),
        ("unknown-top-field", json!({"frame_rate": 4}), &["frame_rate"]),
        ("hfov0", json!({"camera": {"width": 64, "height": 48, "hfov_deg": 0.0}}), &["camera.hfov_deg"]),
        ("rate-1", json!({"frame_rate_hz": -1.0}), &["frame_rate_hz"]),
        ("imu50", json!({"imu": {"rate_hz": 50.0}}), &["imu.rate_hz"]),
        (
            "pendulum",
            json!({"trajectory": {"kind": "balloon", "pendulum_deg": 75.0}}),
            &["balloon.pendulum_deg"],
        ),
        ("far-origin", json!({"origin": {"lat": 10.0, "lon": 10.0}}), &["origin"]),
    ];
    for (name, change, names) in bad {
        let mut s = good.clone();
        for (k, v) in change.as_object().unwrap() {
            s[k] = v.clone();
        }
        let sc = write_scenario(d, name, &s);
        let mut names = names.to_vec();
        let file = format!("{name}.json");
        names.push(&file);
        assert_fails(&run(&sc, &ortho, &dem, &[]), &names, d, name);
        assert!(!out.exists(), "{name}: --out was created");
    }

    // --out is a folder with other files (not a flight): refused, untouched.
    let precious = d.join("precious");
    std::fs::create_dir(&precious).unwrap();
    std::fs::write(precious.join("notes.txt"), "keep me").unwrap();
    let o = simulate(&ortho, &dem, &good_sc, &precious, &[]);
    assert_fails(&o, &["precious", "not a flight folder"], d, "--out is another folder");
    assert_eq!(tree(&precious), vec![(PathBuf::from("notes.txt"), b"keep me".to_vec())]);
    // --out is a file: refused, untouched.
    let file = d.join("a-file");
    std::fs::write(&file, "data").unwrap();
    assert_fails(&simulate(&ortho, &dem, &good_sc, &file, &[]), &["a-file"], d, "--out is a file");
    assert_eq!(std::fs::read(&file).unwrap(), b"data");
}

#[test]
fn an_existing_flight_folder_is_replaced_whole() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 200, 10.0, 440000.0, 41);
    let scenario = |rate: f64| {
        json!({
            "camera": {"width": 64, "height": 48, "hfov_deg": 40.0},
            "frame_rate_hz": rate,
            "trajectory": {"kind": "balloon", "start_h_m": 4000.0, "duration_s": 1.0}
        })
    };
    let out = d.join("flight");
    let sc = write_scenario(d, "rate8", &scenario(8.0));
    simulate_ok(&ortho, &dem, &sc, &out, &[]);
    assert_eq!(Flight::open(&out).unwrap().frames.len(), 9);
    std::fs::write(out.join("stray.txt"), "old").unwrap();
    // A run that fails leaves the old flight as it was.
    let before = tree(&out);
    let o = simulate(&ortho, &d.join("missing-dem.tif"), &sc, &out, &[]);
    assert_fails(&o, &["missing-dem.tif"], d, "failed run over an existing flight");
    assert!(tree(&out) == before, "a failed run changed the existing flight");

    let sc = write_scenario(d, "rate2", &scenario(2.0));
    simulate_ok(&ortho, &dem, &sc, &out, &[]);
    let flight = Flight::open(&out).unwrap();
    assert_eq!(flight.frames.len(), 3);
    assert!(!out.join("stray.txt").exists(), "a file of the old flight survived");
    let images = std::fs::read_dir(out.join("images")).unwrap().count();
    assert_eq!(images, 3, "old images survived");
    let names: Vec<String> = std::fs::read_dir(d)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(!names.iter().any(|n| n.starts_with(".trn-")), "left behind: {names:?}");
}

/// Ctrl-C during rendering stops the simulation at the next frame: one
/// `error:` line, no `--out`, no temporary folder.
#[test]
fn ctrl_c_cancels_and_leaves_nothing() {
    use std::io::Read;
    use std::process::Stdio;
    use std::time::{Duration, Instant};
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (ortho, dem) = common::synth(d, 200, 10.0, 440000.0, 51);
    let sc = write_scenario(
        d,
        "long",
        &json!({"camera": {"width": 320, "height": 240, "hfov_deg": 40},
                "trajectory": {"kind": "balloon", "start_h_m": 4500, "end_h_m": 3000}}),
    );
    let out = d.join("flight");
    let mut child = common::trn()
        .args(["simulate", "--ortho", ortho.to_str().unwrap(), "--dem", dem.to_str().unwrap()])
        .args([
            "--dem-vertical",
            "ellipsoid",
            "--scenario",
            sc.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("start trn simulate");
    let mut pipe = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        pipe.read_to_string(&mut s).ok();
        s
    });
    let started = Instant::now();
    // Wait until frames are being written into the temporary flight folder.
    let rendering = || {
        std::fs::read_dir(d).unwrap().map(|e| e.unwrap().path()).any(|p| {
            p.file_name().unwrap().to_string_lossy().starts_with(".trn-sim-")
                && std::fs::read_dir(p.join("images")).is_ok_and(|mut i| i.next().is_some())
        })
    };
    while !rendering() {
        assert!(child.try_wait().unwrap().is_none(), "simulation ended before it rendered");
        assert!(started.elapsed() < Duration::from_secs(60), "no frame after 60 s");
        std::thread::sleep(Duration::from_millis(10));
    }
    let kill = std::process::Command::new("kill").args(["-INT", &child.id().to_string()]).status().unwrap();
    assert!(kill.success());
    let sent = Instant::now();
    let status = loop {
        if let Some(st) = child.try_wait().unwrap() {
            break st;
        }
        if sent.elapsed() > Duration::from_secs(30) {
            child.kill().ok();
            child.wait().ok();
            panic!("still running 30 s after SIGINT");
        }
        std::thread::sleep(Duration::from_millis(10));
    };
    let err = reader.join().unwrap();
    assert!(status.code().is_some_and(|c| c != 0), "{status:?}, stderr:\n{err}");
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error:")).collect();
    assert_eq!(lines.len(), 1, "stderr:\n{err}");
    assert!(lines[0].contains("cancelled"), "{}", lines[0]);
    assert!(!out.exists());
    let left = common::leftovers(d, &[&ortho, &dem, &sc]);
    assert!(left.is_empty(), "cancelled simulation left behind: {left:?}");
}

// ---------------------------------------------------------------------------
// The database's DEM: not the rendered one.

#[test]
fn degraded_dem_differs_from_the_rendered_one_by_the_stated_amount() {
    let dir = tempfile::tempdir().unwrap();
    let (_, dem) = common::synth(dir.path(), 600, 5.0, 440000.0, 4);
    let out = dir.path().join("db-dem.tif");
    let o = common::run(&[
        "degrade-dem",
        "--dem",
        dem.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--cell-m",
        "180",
        "--noise-m",
        "3",
        "--noise-scale-m",
        "400",
        "--seed",
        "9",
    ]);
    assert!(o.status.success(), "degrade-dem failed: {}", common::stderr(&o));
    let report: Value = serde_json::from_slice(&o.stdout).unwrap();
    let src = Dataset::open(&dem).unwrap();
    let dst = Dataset::open(&out).unwrap();
    // Same CRS; cells 3x coarser (the synthetic DEM is at 60 m), same corner.
    assert!(src.spatial_ref().unwrap() == dst.spatial_ref().unwrap(), "CRS changed");
    let (gs, gd) = (src.geo_transform().unwrap(), dst.geo_transform().unwrap());
    let f = (180.0 / gs[1]).round();
    assert_eq!(report["factor"].as_f64().unwrap(), f);
    assert!((gd[1] - f * gs[1]).abs() < 1e-9 && (gd[5] - f * gs[5]).abs() < 1e-9);
    assert_eq!((gd[0], gd[3]), (gs[0], gs[3]));
    let read = |ds: &Dataset| {
        let b = ds.rasterband(1).unwrap();
        let (w, h) = b.size();
        (b.read_band_as::<f64>().unwrap().data().to_vec(), w, h)
    };
    let (a, w, h) = read(&src);
    let (b, wd, hd) = read(&dst);
    assert_eq!((wd, hd), (w.div_ceil(f as usize), h.div_ceil(f as usize)));
    // Against the block means computed here: the difference is the noise, of
    // the stated RMS, correlated over ~400 m (neighbours at 180 m alike).
    let f = f as usize;
    let mut diff = vec![0.0; wd * hd];
    for j in 0..hd {
        for i in 0..wd {
            let cells: Vec<f64> = (j * f..((j + 1) * f).min(h))
                .flat_map(|r| (i * f..((i + 1) * f).min(w)).map(move |c| (r, c)))
                .map(|(r, c)| a[r * w + c])
                .collect();
            let mean = cells.iter().sum::<f64>() / cells.len() as f64;
            diff[j * wd + i] = b[j * wd + i] - mean;
        }
    }
    let rms = (diff.iter().map(|d| d * d).sum::<f64>() / diff.len() as f64).sqrt();
    assert!((rms - 3.0).abs() < 0.01, "noise RMS {rms} vs 3 m");
    let lag1 = (0..hd)
        .flat_map(|j| (0..wd - 1).map(move |i| (j, i)))
        .map(|(j, i)| diff[j * wd + i] * diff[j * wd + i + 1]);
    let rho1 = lag1.sum::<f64>() / ((wd - 1) * hd) as f64 / (rms * rms);
    assert!(rho1 > 0.7, "correlated noise: lag-1 correlation {rho1}");

    // Bad options: one error line naming the option, nothing written.
    let bad = dir.path().join("bad.tif");
    for (args, name) in [
        (vec!["--cell-m=-5"], "--cell-m"),
        (vec!["--noise-m", "nan"], "--noise-m"),
        (vec!["--noise-scale-m=-1"], "--noise-scale-m"),
    ] {
        let mut all = vec!["degrade-dem", "--dem", dem.to_str().unwrap(), "--out", bad.to_str().unwrap()];
        all.extend(args);
        let o = common::run(&all);
        assert_fails(&o, &[name], dir.path(), name);
        assert!(!bad.exists(), "{name}: left {}", bad.display());
    }
    let missing = dir.path().join("missing.tif");
    let o = common::run(&["degrade-dem", "--dem", missing.to_str().unwrap(), "--out", bad.to_str().unwrap()]);
    assert_fails(&o, &["missing.tif"], dir.path(), "missing DEM");
    assert!(!bad.exists());
}

// ---------------------------------------------------------------------------
// The camera's spectral response.

#[test]
fn spectral_weights_make_the_camera_luminance_from_the_ortho_bands() {
    let dir = tempfile::tempdir().unwrap();
    let (ortho, dem) = common::synth(dir.path(), 300, 5.0, 440000.0, 6);
    let sources = trn_sim::SceneSources {
        ortho: ortho.clone(),
        ortho_bands: None,
        dem: trn_raster::DemInputs {
            files: vec![dem.clone()],
            vertical: Some(trn_raster::DemVertical::Ellipsoid),
            geoid: None,
        },
    };
    // The ortho's bands read by GDAL: the camera's grey level is their weighted sum.
    let ds = Dataset::open(&ortho).unwrap();
    let band = |b: usize| ds.rasterband(b).unwrap().read_band_as::<f64>().unwrap().data().to_vec();
    let (r, g, b) = (band(1), band(2), band(3));
    let w = ds.raster_size().0;
    let weights = [0.2f32, 0.5, 0.3];
    let scene = trn_sim::load_scene(&sources, Some(weights)).unwrap();
    let luma = trn_sim::load_scene(&sources, None).unwrap();
    let mut differs = 0;
    for (x, y) in [(3usize, 7usize), (120, 45), (250, 260), (297, 2), (17, 199)] {
        let k = y * w + x;
        let want = weights[0] as f64 * r[k] + weights[1] as f64 * g[k] + weights[2] as f64 * b[k];
        let got = scene.ortho.sample_level(0, x as f64, y as f64) as f64;
        assert!((got - want).abs() < 1e-3, "({x}, {y}): {got} vs {want}");
        let rec601 = 0.299 * r[k] + 0.587 * g[k] + 0.114 * b[k];
        let l = luma.ortho.sample_level(0, x as f64, y as f64) as f64;
        assert!((l - rec601).abs() < 1e-3, "({x}, {y}): luma {l} vs {rec601}");
        differs += ((got - l).abs() > 0.5) as usize;
    }
    assert!(differs >= 3, "the weights change the grey levels");
    // A one-band ortho cannot give a spectral response: the error names the file and the key.
    let grey = dir.path().join("grey.tif");
    let o = std::process::Command::new("gdal_translate")
        .args(["-q", "-b", "1", ortho.to_str().unwrap(), grey.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(o.status.success());
    let err = trn_sim::load_scene(&trn_sim::SceneSources { ortho: grey.clone(), ..sources }, Some(weights))
        .unwrap_err()
        .to_string();
    assert!(err.contains("grey.tif") && err.contains("realism.spectral"), "{err}");
}
