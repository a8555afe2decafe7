//! Load generator for `scripts/bench_serve.sh`: typical navigator queries (the
//! nadir footprint of a 1024 x 768, 32 deg camera at a random place and height
//! over the database, at the level that fits its ground resolution, as the
//! navigator asks for it), made in-process against the store (SQLite, and the
//! in-memory catalogue the server uses) and over HTTP against a running
//! `trn serve` through `trn_client::HttpSource` (binary encoding,
//! keep-alive, each client its own connection), all decoded into templates.
//! Prints one JSON line per mode: throughput and latency percentiles.
//!
//! `bench_serve --db DB [--url http://127.0.0.1:8080] [--clients 4] [--seconds 10]`

use std::path::PathBuf;
use std::sync::Arc;
use std::time::{Duration, Instant};

use trn_camera::{CameraModel, CameraPose};
use trn_client::HttpSource;
use trn_geodesy::Geodetic;
use trn_landmark::GeoBox;
use trn_store::{BboxQuery, LandmarkDb};
use trn_view::footprint::{footprint, FootprintParams};
use trn_view::visible::level_for;
use trn_view::LandmarkSource;

fn arg(args: &[String], name: &str) -> Option<String> {
    args.iter().position(|a| a == name).and_then(|i| args.get(i + 1).cloned())
}

/// Deterministic queries: (bbox, level).
fn queries(db: &LandmarkDb, n: usize) -> Vec<(GeoBox, u8)> {
    let levels = trn_view::visible::DbLevel::of(&db.levels().unwrap());
    let e = db.extent().unwrap().expect("empty database");
    let h_terrain = 1500.0;
    let cam = CameraModel::from_fov(1024, 768, 32.0);
    let mut s = 12345u64;
    let mut unit = || {
        s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    // The resolution at which the finest level's templates span the target size.
    let finest = levels.first().unwrap().footprint_m / trn_view::visible::TARGET_PATCH_PX;
    let mut out = Vec::with_capacity(n);
    while out.len() < n {
        // Heights whose centre GSD spans the finest 4 levels.
        let gsd = finest * 2f64.powf(unit() * 3.5);
        let h = gsd * cam.fx;
        let lat = e.min_lat_deg + (e.max_lat_deg - e.min_lat_deg) * unit();
        let lon = e.min_lon_deg + (e.max_lon_deg - e.min_lon_deg) * unit();
        let g = Geodetic::new(lat, lon, h_terrain + h);
        let north =
            Geodetic::new(lat + 0.01, lon, 0.0).to_ecef().0 - Geodetic::new(lat, lon, 0.0).to_ecef().0;
        let pose = CameraPose::look_at(g.to_ecef(), Geodetic::new(lat, lon, h_terrain).to_ecef(), north);
        let fp = footprint(&cam, &pose, &FootprintParams { terrain_h_m: h_terrain, ..Default::default() })
            .unwrap();
        let level = level_for(&levels, fp.center_gsd_m).unwrap().level;
        out.push((fp.bbox, level));
    }
    out
}

struct Stats {
    latencies_us: Vec<u64>,
    templates: usize,
}

fn run_clients(
    clients: usize,
    seconds: f64,
    qs: Arc<Vec<(GeoBox, u8)>>,
    make: impl Fn(usize) -> Box<dyn FnMut(&GeoBox, u8) -> usize + Send> + Sync,
) -> (Stats, f64) {
    let deadline = Instant::now() + Duration::from_secs_f64(seconds);
    let t0 = Instant::now();
    let stats: Vec<Stats> = std::thread::scope(|sc| {
        let handles: Vec<_> = (0..clients)
            .map(|c| {
                let mut f = make(c);
                let qs = qs.clone();
                sc.spawn(move || {
                    let mut st = Stats { latencies_us: Vec::new(), templates: 0 };
                    let mut i = c * 997;
                    while Instant::now() < deadline {
                        let (b, l) = qs[i % qs.len()];
                        let t = Instant::now();
                        st.templates += f(&b, l);
                        st.latencies_us.push(t.elapsed().as_micros() as u64);
                        i += 1;
                    }
                    st
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    let wall = t0.elapsed().as_secs_f64();
    let mut all = Stats { latencies_us: Vec::new(), templates: 0 };
    for s in stats {
        all.latencies_us.extend(s.latencies_us);
        all.templates += s.templates;
    }
    all.latencies_us.sort_unstable();
    (all, wall)
}

fn report(mode: &str, clients: usize, st: &Stats, wall: f64) {
    let n = st.latencies_us.len();
    let pct = |p: f64| st.latencies_us[((n as f64 * p).ceil() as usize).clamp(1, n) - 1] as f64 / 1000.0;
    println!(
        "{}",
        serde_json::json!({
            "mode": mode, "clients": clients, "queries": n, "seconds": (wall * 100.0).round() / 100.0,
            "queries_per_s": (n as f64 / wall).round(),
            "templates_per_query": (st.templates as f64 / n as f64).round(),
            "p50_ms": pct(0.5), "p90_ms": pct(0.9), "p99_ms": pct(0.99), "max_ms": pct(1.0),
        })
    );
}

fn main() {
    let args: Vec<String> = std::env::args().collect();
    let db_path = PathBuf::from(arg(&args, "--db").expect("--db DB"));
    let clients: usize = arg(&args, "--clients").map_or(4, |v| v.parse().unwrap());
    let seconds: f64 = arg(&args, "--seconds").map_or(10.0, |v| v.parse().unwrap());
    let url = arg(&args, "--url");
    let db = LandmarkDb::open(&db_path).unwrap();
    let qs = Arc::new(queries(&db, 2000));
    let mode = arg(&args, "--mode").unwrap_or_else(|| "both".into());
    if mode == "both" || mode == "inprocess" {
        let (st, wall) = run_clients(clients, seconds, qs.clone(), |_| {
            let conn = LandmarkDb::open(&db_path).unwrap();
            Box::new(move |b: &GeoBox, l: u8| {
                conn.query_bbox(&BboxQuery::new(*b).with_levels(l..=l)).unwrap().len()
            })
        });
        report("in-process", clients, &st, wall);
    }
    if mode == "both" || mode == "memory" {
        // The server's hot path without HTTP: the whole database in memory.
        let cat = Arc::new(db.load_catalogue().unwrap());
        let (st, wall) = run_clients(clients, seconds, qs.clone(), |_| {
            let cat = cat.clone();
            Box::new(move |b: &GeoBox, l: u8| {
                cat.query_templates(&BboxQuery::new(*b).with_levels(l..=l)).unwrap().len()
            })
        });
        report("in-process-memory", clients, &st, wall);
    }
    if let Some(url) = url.filter(|_| mode == "both" || mode == "http") {
        // Exactly the navigator's client: one connection per source.
        let (st, wall) = run_clients(clients, seconds, qs, |_| {
            let source = HttpSource::connect(&url).unwrap();
            Box::new(move |b: &GeoBox, l: u8| source.query(b, l).unwrap().len())
        });
        report("http", clients, &st, wall);
    }
}
