//! Randomised bounding-box queries against a brute-force scan in Rust.

mod common;

use std::ops::RangeInclusive;

use common::{synthetic_template, write_db, Lcg};
use trn_landmark::{GeoBox, Template};
use trn_store::{BboxQuery, LandmarkDb};

/// Cluster centre (lat, lon) and half-spread (deg) of the synthetic templates.
const CLUSTERS: [(f64, f64, f64); 5] = [
    (46.0, 7.0, 0.05),    // dense Alps
    (46.5, 7.5, 0.6),     // sparse around it
    (-17.0, 180.0, 0.03), // on the antimeridian: footprints crossing it
    (0.0, 0.0, 0.02),     // both signs of zero
    (78.0, 15.0, 0.1),    // high latitude: wide footprints in longitude
];

fn wrap_lon(lon: f64) -> f64 {
    if lon > 180.0 {
        lon - 360.0
    } else if lon < -180.0 {
        lon + 360.0
    } else {
        lon
    }
}

fn next_up(x: f64) -> f64 {
    if x == 0.0 {
        f64::from_bits(1)
    } else if x > 0.0 {
        f64::from_bits(x.to_bits() + 1)
    } else {
        f64::from_bits(x.to_bits() - 1)
    }
}

fn next_down(x: f64) -> f64 {
    -next_up(-x)
}

fn make_templates(rng: &mut Lcg, n: usize) -> Vec<Template> {
    let mut out: Vec<Template> = Vec::with_capacity(n);
    for _ in 0..n {
        if !out.is_empty() && rng.chance(0.03) {
            // Same footprint and scores as an earlier one: only the id breaks the tie.
            let mut twin = out[rng.below(out.len() as u64) as usize].clone();
            twin.pixels[0] = twin.pixels[0].wrapping_add(1);
            out.push(twin);
            continue;
        }
        let (lat0, lon0, spread) = CLUSTERS[rng.below(CLUSTERS.len() as u64) as usize];
        let level = rng.below(5) as u8;
        let lat = lat0 + rng.uniform(-spread, spread);
        let lon = wrap_lon(lon0 + rng.uniform(-spread, spread));
        out.push(synthetic_template(rng, level, lat, lon));
    }
    out
}

fn random_levels(rng: &mut Lcg) -> Option<RangeInclusive<u8>> {
    match rng.below(10) {
        0..=3 => None,
        4..=5 => {
            let l = rng.below(6) as u8;
            Some(l..=l)
        }
        6 => Some(RangeInclusive::new(3, 1)), // empty on purpose
        7 => Some(0..=u8::MAX),
        _ => {
            let a = rng.below(5) as u8;
            let b = a + rng.below(5 - a as u64) as u8;
            Some(a..=b)
        }
    }
}

/// A box of the given kind; the template is where edge-related kinds take their edges.
fn random_box(rng: &mut Lcg, t: &Template) -> GeoBox {
    let fp = t.footprint;
    let size = 10f64.powf(rng.uniform(-6.0, 0.3));
    match rng.below(10) {
        // Anywhere around a cluster.
        0 | 1 => {
            let (lat0, lon0, spread) = CLUSTERS[rng.below(CLUSTERS.len() as u64) as usize];
            let lat = lat0 + rng.uniform(-2.0 * spread, 2.0 * spread);
            let lon = lon0 + rng.uniform(-2.0 * spread, 2.0 * spread);
            let (w, h) = (size * rng.uniform(0.2, 2.0), size * rng.uniform(0.2, 2.0));
            GeoBox::new(wrap_lon(lon - w), (lat - h).max(-90.0), wrap_lon(lon + w), (lat + h).min(90.0))
        }
        // Tiny box or a point at a footprint corner.
        2 => {
            let (lon, lat) = if rng.chance(0.5) {
                (fp.min_lon_deg, fp.min_lat_deg)
            } else {
                (fp.max_lon_deg, fp.max_lat_deg)
            };
            let eps = if rng.chance(0.5) { 0.0 } else { 1e-9 };
            GeoBox::new(lon - eps, lat - eps, lon + eps, lat + eps)
        }
        // Touching one footprint edge exactly from outside (or one ulp off).
        3..=5 => {
            // Exactly on the edge, or one ulp away from the footprint.
            let off = |x: f64, up: bool, pick: u64| match pick {
                0 => x,
                _ if up => next_up(x),
                _ => next_down(x),
            };
            let pick = rng.below(3);
            let lat_mid = 0.5 * (fp.min_lat_deg + fp.max_lat_deg);
            let lon_mid = 0.5 * (fp.min_lon_deg + fp.max_lon_deg);
            match rng.below(4) {
                0 => GeoBox::new(
                    off(fp.max_lon_deg, true, pick),
                    lat_mid - size,
                    fp.max_lon_deg + size,
                    lat_mid + size,
                ),
                1 => GeoBox::new(
                    fp.min_lon_deg - size,
                    lat_mid - size,
                    off(fp.min_lon_deg, false, pick),
                    lat_mid + size,
                ),
                2 => GeoBox::new(
                    lon_mid - size,
                    off(fp.max_lat_deg, true, pick),
                    lon_mid + size,
                    fp.max_lat_deg + size,
                ),
                _ => GeoBox::new(
                    lon_mid - size,
                    fp.min_lat_deg - size,
                    lon_mid + size,
                    off(fp.min_lat_deg, false, pick),
                ),
            }
        }
        // Crossing the antimeridian.
        6 | 7 => {
            let lat = -17.0 + rng.uniform(-0.05, 0.05);
            let (w_east, w_west) = (rng.uniform(0.0, 0.05), rng.uniform(0.0, 0.05));
            let (min_lon, max_lon) = match rng.below(4) {
                0 => (180.0 - w_east, -180.0 + w_west),
                1 => (180.0, -180.0 + w_west), // edge exactly on +180
                2 => (180.0 - w_east, -180.0), // edge exactly on -180
                _ => (fp.min_lon_deg.max(next_up(fp.max_lon_deg)), fp.max_lon_deg), // footprint-derived
            };
            GeoBox::new(min_lon, lat - size, max_lon, lat + size)
        }
        // The exact footprint of a template, and its ulp-shrunk version.
        8 => {
            if rng.chance(0.5) {
                fp
            } else {
                GeoBox::new(
                    next_up(fp.min_lon_deg),
                    next_up(fp.min_lat_deg),
                    next_down(fp.max_lon_deg),
                    next_down(fp.max_lat_deg),
                )
            }
        }
        // World, one hemisphere, or an empty ocean.
        _ => match rng.below(3) {
            0 => GeoBox::new(-180.0, -90.0, 180.0, 90.0),
            1 => GeoBox::new(0.0, -90.0, 180.0, 0.0),
            _ => GeoBox::new(-40.0, -40.0, -30.0, -30.0),
        },
    }
}

fn brute_force(templates: &[Template], q: &BboxQuery) -> Vec<i64> {
    let mut hits: Vec<&Template> = templates
        .iter()
        .filter(|t| {
            q.levels.as_ref().is_none_or(|r| r.contains(&t.level))
                && q.lighting.is_none_or(|k| k == t.lighting)
                && q.bbox.intersects(&t.footprint)
        })
        .collect();
    hits.sort_by(|a, b| {
        a.quality
            .second_peak_ncc
            .total_cmp(&b.quality.second_peak_ncc)
            .then(b.quality.shi_tomasi.total_cmp(&a.quality.shi_tomasi))
            .then(a.id.cmp(&b.id))
    });
    hits.truncate(q.limit.unwrap_or(usize::MAX));
    hits.into_iter().map(|t| t.id).collect()
}

#[test]
fn random_queries_match_brute_force() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg::new(20_240_611);
    let mut templates = make_templates(&mut rng, 4000);
    let crossing = templates.iter().filter(|t| t.footprint.crosses_antimeridian()).count();
    assert!(crossing >= 5, "only {crossing} footprints cross the antimeridian");
    let (path, _) = write_db(dir.path(), "random.gpkg", &mut templates);
    let db = LandmarkDb::open(&path).unwrap();

    let (mut nonempty, mut crossing_hits, mut limited, mut total_hits) = (0, 0, 0, 0);
    for i in 0..1500 {
        let anchor = &templates[rng.below(templates.len() as u64) as usize];
        let mut q = BboxQuery::new(random_box(&mut rng, anchor));
        q.levels = random_levels(&mut rng);
        if rng.chance(0.2) {
            q.limit = Some(rng.below(20) as usize);
        }
        if rng.chance(0.25) {
            q.lighting = Some(rng.below(2) as u8);
        }
        let expected = brute_force(&templates, &q);
        let got = db.query_bbox_ids(&q).unwrap();
        assert_eq!(got, expected, "query {i}: {q:?}");
        nonempty += usize::from(!expected.is_empty());
        crossing_hits += usize::from(q.bbox.crosses_antimeridian() && !expected.is_empty());
        limited += usize::from(q.limit.is_some_and(|l| l > 0 && expected.len() == l));
        total_hits += expected.len();
    }
    println!("{nonempty} non-empty queries, {crossing_hits} across the antimeridian, {limited} cut by the limit, {total_hits} hits");
    assert!(nonempty > 600 && crossing_hits > 50 && limited > 30, "test data too sparse");
}

#[test]
fn edges_touch_and_ulps_miss() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Lcg::new(7);
    // Footprint edges at values float32 cannot hold, so the R*Tree bounds are rounded.
    let mut templates = vec![synthetic_template(&mut rng, 0, 46.123_456_789, 7.987_654_321)];
    let (path, _) = write_db(dir.path(), "edges.gpkg", &mut templates);
    let db = LandmarkDb::open(&path).unwrap();
    let fp = templates[0].footprint;
    assert_ne!(fp.max_lon_deg as f32 as f64, fp.max_lon_deg);
    let ids = |b: GeoBox| db.query_bbox_ids(&BboxQuery::new(b)).unwrap();
    let lat = fp.min_lat_deg;
    // East edge: touching matches, one ulp further east does not.
    assert_eq!(ids(GeoBox::new(fp.max_lon_deg, lat, fp.max_lon_deg + 1.0, lat)), vec![1]);
    assert!(ids(GeoBox::new(next_up(fp.max_lon_deg), lat, fp.max_lon_deg + 1.0, lat)).is_empty());
    // North edge.
    let lon = fp.min_lon_deg;
    assert_eq!(ids(GeoBox::new(lon, fp.max_lat_deg, lon, fp.max_lat_deg + 1.0)), vec![1]);
    assert!(ids(GeoBox::new(lon, next_up(fp.max_lat_deg), lon, fp.max_lat_deg + 1.0)).is_empty());
    // West and south edges.
    assert_eq!(ids(GeoBox::new(fp.min_lon_deg - 1.0, lat, fp.min_lon_deg, lat)), vec![1]);
    assert!(ids(GeoBox::new(fp.min_lon_deg - 1.0, lat, next_down(fp.min_lon_deg), lat)).is_empty());
    assert_eq!(ids(GeoBox::new(lon, fp.min_lat_deg - 1.0, lon, fp.min_lat_deg)), vec![1]);
    assert!(ids(GeoBox::new(lon, fp.min_lat_deg - 1.0, lon, next_down(fp.min_lat_deg))).is_empty());
}
