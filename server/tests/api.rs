//! The HTTP API in process (the router, no socket): bounding-box queries
//! against a brute-force scan, the binary encoding against the stored
//! templates, caching headers, footprint and coverage, and generated bad input.

use std::sync::Arc;

use axum::body::Body;
use axum::http::{header, Request, StatusCode};
use axum::Router;
use proptest::prelude::*;
use tower::ServiceExt;
use trn_geodesy::{metres_per_degree, Geodetic};
use trn_landmark::{wire, GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};
use trn_server::{router, AppState, ServeOptions};
use trn_store::DbWriter;

struct Lcg(u64);

impl Lcg {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        self.0
    }
    fn unit(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * self.unit()
    }
    fn below(&mut self, n: u64) -> u64 {
        (self.next_u64() >> 32) % n
    }
}

fn wrap(lon: f64) -> f64 {
    if lon > 180.0 {
        lon - 360.0
    } else if lon < -180.0 {
        lon + 360.0
    } else {
        lon
    }
}

/// A 16 x 16 template at `level` (GSD 4 m * 2^level) centred at (lat, lon), ~1500 m high.
fn template(rng: &mut Lcg, level: u8, lat: f64, lon: f64) -> Template {
    let side = 16u32;
    let gsd_m = 4.0 * f64::from(1u32 << level);
    let (m_lat, m_lon) = metres_per_degree(lat);
    let (hl, hb) = (side as f64 * gsd_m / 2.0 / m_lon, side as f64 * gsd_m / 2.0 / m_lat);
    Template {
        id: 0,
        level,
        gsd_m,
        width_px: side,
        height_px: side,
        center: Geodetic::new(lat, lon, 1500.0 + rng.uniform(-20.0, 20.0)),
        footprint: GeoBox::new(wrap(lon - hl), lat - hb, wrap(lon + hl), lat + hb),
        terrain: TerrainPatch {
            plane_normal_enu: [0.0, 0.0, 1.0],
            plane_residual_rms_m: rng.uniform(0.0, 2.0),
            height_grid: HeightGrid { n: 3, spacing_m: 8.0 * gsd_m, heights_m: vec![0.5; 9] },
        },
        quality: TemplateQuality {
            shi_tomasi: rng.uniform(0.0, 500.0) as f32,
            contrast_std: rng.uniform(5.0, 60.0) as f32,
            second_peak_ncc: rng.below(8) as f32 / 10.0,
            shading_share: rng.below(5) as f32 / 4.0,
        },
        source: 0,
        lighting: rng.below(3) as u8,
        pixels: (0..side * side).map(|_| rng.below(256) as u8).collect(),
    }
}

/// Clusters: (lat, lon, half spread deg); one on the antimeridian.
const CLUSTERS: [(f64, f64, f64); 3] = [(40.0, -105.5, 0.15), (-17.0, 180.0, 0.05), (0.0, 0.0, 0.03)];

struct Fixture {
    _dir: tempfile::TempDir,
    templates: Vec<Template>,
    app: Router,
}

fn fixture() -> Fixture {
    fixture_with(trn_server::DEFAULT_CACHE_MB << 20)
}

/// The fixture served from memory (`cache_bytes` > 0) or from SQLite (0).
fn fixture_with(cache_bytes: u64) -> Fixture {
    let mut rng = Lcg(42);
    let mut templates = Vec::new();
    for (i, (lat0, lon0, s)) in CLUSTERS.iter().enumerate() {
        let n = if i == 0 { 2500 } else { 300 };
        for _ in 0..n {
            let level = rng.below(4) as u8;
            let lat = lat0 + rng.uniform(-s, *s);
            let lon = wrap(lon0 + rng.uniform(-s, *s));
            templates.push(template(&mut rng, level, lat, lon));
        }
    }
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("t.gpkg");
    let mut w = DbWriter::create(&path).unwrap();
    w.set_metadata("test", &serde_json::json!({"fixture": 1})).unwrap();
    for chunk in templates.chunks_mut(500) {
        w.insert_batch(chunk).unwrap();
    }
    w.finish().unwrap();
    let mut opts = ServeOptions::new(path, "127.0.0.1:0".into());
    opts.max_body_bytes = 64 << 10;
    opts.cache_bytes = cache_bytes;
    let app = router(Arc::new(AppState::open(opts).unwrap()));
    Fixture { _dir: dir, templates, app }
}

struct Answer {
    status: StatusCode,
    headers: axum::http::HeaderMap,
    body: Vec<u8>,
}

impl Answer {
    fn json(&self) -> serde_json::Value {
        serde_json::from_slice(&self.body).unwrap_or_else(|e| {
            panic!("{} not JSON ({e}): {:?}", self.status, String::from_utf8_lossy(&self.body))
        })
    }
    fn error(&self) -> String {
        self.json()["error"]
            .as_str()
            .unwrap_or_else(|| panic!("no error field: {:?}", self.json()))
            .to_owned()
    }
}

async fn call(app: &Router, req: Request<Body>) -> Answer {
    let r = app.clone().oneshot(req).await.unwrap();
    let status = r.status();
    let headers = r.headers().clone();
    let body = axum::body::to_bytes(r.into_body(), usize::MAX).await.unwrap().to_vec();
    Answer { status, headers, body }
}

fn get(uri: &str) -> Request<Body> {
    Request::get(uri).body(Body::empty()).unwrap()
}

fn get_binary(uri: &str) -> Request<Body> {
    Request::get(uri).header(header::ACCEPT, wire::MEDIA_TYPE).body(Body::empty()).unwrap()
}

fn post(uri: &str, body: impl Into<Body>) -> Request<Body> {
    Request::post(uri).header(header::CONTENT_TYPE, "application/json").body(body.into()).unwrap()
}

fn rt() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build().unwrap()
}

/// Brute force: matching templates best first.
fn brute(ts: &[Template], bbox: &GeoBox, levels: (u8, u8), lighting: Option<u8>) -> Vec<i64> {
    let mut m: Vec<&Template> = ts
        .iter()
        .filter(|t| {
            t.level >= levels.0
                && t.level <= levels.1
                && lighting.is_none_or(|k| k == t.lighting)
                && bbox.intersects(&t.footprint)
        })
        .collect();
    m.sort_by(|a, b| {
        a.quality
            .second_peak_ncc
            .total_cmp(&b.quality.second_peak_ncc)
            .then(b.quality.shi_tomasi.total_cmp(&a.quality.shi_tomasi))
            .then(a.id.cmp(&b.id))
    });
    m.iter().map(|t| t.id).collect()
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

#[test]
fn bbox_queries_equal_a_brute_force_scan() {
    // From memory (the default) and from SQLite (a database over the cache).
    for cache_bytes in [trn_server::DEFAULT_CACHE_MB << 20, 0] {
        bbox_queries_equal_a_brute_force_scan_with(cache_bytes);
    }
}

fn bbox_queries_equal_a_brute_force_scan_with(cache_bytes: u64) {
    let f = fixture_with(cache_bytes);
    let rt = rt();
    let memory = rt.block_on(call(&f.app, get("/v1/info"))).json()["memory_bytes"].as_u64().unwrap();
    assert_eq!(memory > 0, cache_bytes > 0, "memory_bytes {memory} with a cache of {cache_bytes}");
    let mut rng = Lcg(7);
    let mut nonempty = 0;
    let mut truncated_seen = 0;
    for i in 0..300 {
        let (lat0, lon0, s) = CLUSTERS[rng.below(3) as usize];
        let (w, h) = (rng.uniform(0.0, 2.5 * s), rng.uniform(0.0, 2.5 * s));
        let (clon, clat) = (lon0 + rng.uniform(-s, s), lat0 + rng.uniform(-s, s));
        let mut bbox = GeoBox::new(
            wrap(clon - w / 2.0),
            (clat - h / 2.0).max(-90.0),
            wrap(clon + w / 2.0),
            clat + h / 2.0,
        );
        if i % 10 == 0 {
            // Touch a footprint edge exactly, or miss it by one ulp.
            let t = &f.templates[rng.below(f.templates.len() as u64) as usize];
            let e = t.footprint.max_lon_deg;
            bbox = if i % 20 == 0 {
                GeoBox::new(e, t.footprint.min_lat_deg, e, t.footprint.max_lat_deg)
            } else {
                GeoBox::new(next_up(e), t.footprint.min_lat_deg, next_up(e), t.footprint.max_lat_deg)
            };
        }
        let levels = match rng.below(3) {
            0 => (0, 255),
            1 => {
                let l = rng.below(4) as u8;
                (l, l)
            }
            _ => (1, 2),
        };
        let limit = [1usize, 7, 50, 1000][rng.below(4) as usize];
        let offset = [0usize, 3, 40][rng.below(3) as usize];
        let level_param = match levels {
            (0, 255) => String::new(),
            (a, b) if a == b => format!("&level={a}"),
            (a, b) => format!("&level={a}..{b}"),
        };
        // A quarter of the queries ask for one lighting (the templates have 0..=2).
        let lighting = (rng.below(4) == 0).then(|| rng.below(3) as u8);
        let lighting_param = lighting.map(|k| format!("&lighting={k}")).unwrap_or_default();
        let uri = format!(
            "/v1/templates?bbox={},{},{},{}{level_param}{lighting_param}&limit={limit}&offset={offset}",
            bbox.min_lon_deg, bbox.min_lat_deg, bbox.max_lon_deg, bbox.max_lat_deg
        );
        let all = brute(&f.templates, &bbox, levels, lighting);
        let want: Vec<i64> = all.iter().skip(offset).take(limit).copied().collect();
        let want_truncated = all.len() > offset + limit;
        let a = rt.block_on(call(&f.app, get(&uri)));
        assert_eq!(a.status, StatusCode::OK, "{uri}: {}", String::from_utf8_lossy(&a.body));
        let j = a.json();
        let got: Vec<i64> =
            j["templates"].as_array().unwrap().iter().map(|t| t["id"].as_i64().unwrap()).collect();
        assert_eq!(got, want, "{uri}");
        assert_eq!(j["truncated"].as_bool(), Some(want_truncated), "{uri}");
        // The binary answer: the same list, every template equal to the stored one.
        let b = rt.block_on(call(&f.app, get_binary(&uri)));
        assert_eq!(b.headers[header::CONTENT_TYPE], wire::MEDIA_TYPE);
        let list = wire::decode(&b.body).unwrap();
        assert_eq!(list.truncated, want_truncated);
        let ids: Vec<i64> = list.templates.iter().map(|t| t.id).collect();
        assert_eq!(ids, want, "{uri}");
        for t in &list.templates {
            assert_eq!(t, &f.templates[(t.id - 1) as usize], "template {}", t.id);
        }
        nonempty += usize::from(!want.is_empty());
        truncated_seen += usize::from(want_truncated);
    }
    assert!(nonempty > 150 && truncated_seen > 20, "{nonempty} non-empty, {truncated_seen} truncated");
}

#[test]
fn template_by_id_info_health_openapi_and_etags() {
    let f = fixture();
    let rt = rt();
    let t = &f.templates[10];
    let a = rt.block_on(call(&f.app, get(&format!("/v1/templates/{}", t.id))));
    assert_eq!(a.status, StatusCode::OK);
    let back: Template = serde_json::from_slice(&a.body).unwrap();
    assert_eq!(back.pixels, t.pixels);
    assert_eq!(back.id, t.id);
    let b = rt.block_on(call(&f.app, get_binary(&format!("/v1/templates/{}", t.id))));
    assert_eq!(wire::decode(&b.body).unwrap().templates, vec![t.clone()]);
    let missing = rt.block_on(call(&f.app, get("/v1/templates/999999")));
    assert_eq!(missing.status, StatusCode::NOT_FOUND);
    assert!(missing.error().contains("999999"));

    let info = rt.block_on(call(&f.app, get("/v1/info")));
    assert_eq!(info.status, StatusCode::OK);
    let j = info.json();
    assert_eq!(j["template_count"].as_u64(), Some(f.templates.len() as u64));
    assert_eq!(j["levels"].as_array().unwrap().len(), 4);
    assert_eq!(j["metadata"]["test"]["fixture"], 1);
    let etag = info.headers[header::ETAG].to_str().unwrap().to_owned();
    assert!(etag.contains(j["database_id"].as_str().unwrap()), "{etag}");
    // Revalidation: 304 with the same ETag, on info and on queries.
    for uri in ["/v1/info", "/v1/templates?bbox=-106,39,-105,41&limit=5"] {
        let first = rt.block_on(call(&f.app, get(uri)));
        let tag = first.headers[header::ETAG].clone();
        let req = Request::get(uri).header(header::IF_NONE_MATCH, tag.clone()).body(Body::empty()).unwrap();
        let again = rt.block_on(call(&f.app, req));
        assert_eq!(again.status, StatusCode::NOT_MODIFIED, "{uri}");
        assert!(again.body.is_empty());
        assert_eq!(again.headers[header::ETAG], tag);
    }
    // The binary representation has its own tag.
    let b = rt.block_on(call(&f.app, get_binary("/v1/templates?bbox=-106,39,-105,41&limit=5")));
    assert_ne!(b.headers[header::ETAG].to_str().unwrap(), etag);

    let h = rt.block_on(call(&f.app, get("/health")));
    assert_eq!(h.json()["status"], "ok");
    assert!(h.headers.contains_key("x-request-id"));
    let o = rt.block_on(call(&f.app, get("/openapi.json"))).json();
    for p in ["/v1/templates", "/v1/templates/{id}", "/v1/info", "/v1/footprint", "/v1/coverage", "/health"] {
        assert!(o["paths"][p].is_object(), "{p} missing from the OpenAPI document");
    }

    // Compression when asked for.
    for enc in ["gzip", "zstd"] {
        let req = Request::get("/v1/templates?bbox=-106,39,-105,41")
            .header(header::ACCEPT_ENCODING, enc)
            .body(Body::empty())
            .unwrap();
        let a = rt.block_on(call(&f.app, req));
        assert_eq!(a.status, StatusCode::OK);
        assert_eq!(a.headers[header::CONTENT_ENCODING], enc);
    }
}

/// A nadir camera `h_m` above (lat, lon), image up north.
fn nadir_pose(lat: f64, lon: f64, h_m: f64) -> serde_json::Value {
    let g = Geodetic::new(lat, lon, h_m);
    let north = Geodetic::new(lat + 0.01, lon, 0.0).to_ecef().0 - Geodetic::new(lat, lon, 0.0).to_ecef().0;
    let p = trn_camera::CameraPose::look_at(g.to_ecef(), Geodetic::new(lat, lon, 0.0).to_ecef(), north);
    let q = trn_camera::quat_to_wxyz(&p.q_ecef_cam);
    serde_json::json!({"lat_deg": lat, "lon_deg": lon, "h_m": h_m, "q_ecef_cam": q})
}

#[test]
fn footprint_and_coverage_count_the_landmarks_in_view() {
    let f = fixture();
    let rt = rt();
    let camera = serde_json::json!({"width": 640, "height": 480, "hfov_deg": 40});
    let pose = nadir_pose(40.0, -105.5, 1500.0 + 25_000.0);
    let body = serde_json::json!({"camera": camera, "pose": pose, "terrain_h_m": 1500.0, "limit": 10000});
    let a = rt.block_on(call(&f.app, post("/v1/footprint", body.to_string())));
    assert_eq!(a.status, StatusCode::OK, "{}", String::from_utf8_lossy(&a.body));
    let j = a.json();
    // Reference: every stored template, no box query: the level fit and the
    // projection into the image, with the same camera.
    let cam = trn_camera::CameraModel::from_fov(640, 480, 40.0);
    let p: trn_server::coverage::PoseIn = serde_json::from_value(pose.clone()).unwrap();
    let (_, cp) = p.to_pose("pose").unwrap();
    // The fixture's templates are 16 px at 4 m x 2^level.
    let levels: Vec<trn_view::visible::DbLevel> = (0..4)
        .map(|l| trn_view::visible::DbLevel { level: l, footprint_m: 16.0 * 4.0 * f64::from(1u32 << l) })
        .collect();
    let centre = trn_view::visible::level_for(&levels, j["center_gsd_m"].as_f64().unwrap()).unwrap().level;
    let mut want: Vec<i64> = f
        .templates
        .iter()
        .filter(|t| t.level + 2 >= centre && t.level <= centre + 2)
        .filter(|t| trn_view::visible::level_fits(&levels, t, trn_view::visible::local_gsd_m(&cam, &cp, t)))
        .filter(|t| {
            cp.project(&cam, &t.center_ecef())
                .is_some_and(|q| q.u >= 0.0 && q.v >= 0.0 && q.u < 640.0 && q.v < 480.0)
        })
        .map(|t| t.id)
        .collect();
    want.sort();
    let mut got: Vec<i64> =
        j["templates"].as_array().unwrap().iter().map(|t| t["id"].as_i64().unwrap()).collect();
    got.sort();
    assert!(want.len() > 20, "only {} templates in view", want.len());
    assert_eq!(got, want);
    assert_eq!(j["count"].as_u64(), Some(want.len() as u64));
    assert_eq!(j["horizon_in_view"], false);

    // A trajectory from the cluster out over empty ground and back: one stretch below.
    let wps: Vec<serde_json::Value> = [(40.0, -105.5), (40.0, -104.5), (40.0, -105.45)]
        .iter()
        .map(|(la, lo)| serde_json::json!({"lat_deg": la, "lon_deg": lo, "h_m": 26_500.0}))
        .collect();
    let plan =
        serde_json::json!({"camera": camera, "waypoints": wps, "step_m": 4000.0, "terrain_h_m": 1500.0});
    let a = rt.block_on(call(&f.app, post("/v1/coverage", plan.to_string())));
    assert_eq!(a.status, StatusCode::OK, "{}", String::from_utf8_lossy(&a.body));
    let r = a.json();
    let pts = r["points"].as_array().unwrap();
    assert!(pts.len() > 40, "{} points", pts.len());
    assert_eq!(r["threshold"], 8);
    assert!(pts[0]["landmarks"].as_u64().unwrap() >= 8);
    assert!(pts.last().unwrap()["landmarks"].as_u64().unwrap() >= 8);
    let st = r["stretches"].as_array().unwrap();
    assert_eq!(st.len(), 1, "{st:?}");
    for (i, p) in pts.iter().enumerate() {
        let inside = i >= st[0]["start_index"].as_u64().unwrap() as usize
            && i <= st[0]["end_index"].as_u64().unwrap() as usize;
        assert_eq!(p["landmarks"].as_u64().unwrap() < 8, inside, "point {i}");
    }
    // The same as GeoJSON.
    let req = Request::post("/v1/coverage")
        .header(header::CONTENT_TYPE, "application/json")
        .header(header::ACCEPT, "application/geo+json")
        .body(Body::from(plan.to_string()))
        .unwrap();
    let g = rt.block_on(call(&f.app, req));
    assert_eq!(g.headers[header::CONTENT_TYPE], "application/geo+json");
    let g = g.json();
    assert_eq!(g["type"], "FeatureCollection");
    let kinds: Vec<&str> =
        g["features"].as_array().unwrap().iter().map(|f| f["properties"]["kind"].as_str().unwrap()).collect();
    assert_eq!(kinds.iter().filter(|k| **k == "below_threshold").count(), 1);
    assert_eq!(kinds.iter().filter(|k| **k == "point").count(), pts.len());

    // Served from SQLite instead of memory: the same answers, byte for byte.
    let sqlite = fixture_with(0);
    for (uri, req) in [("/v1/footprint", body.to_string()), ("/v1/coverage", plan.to_string())] {
        let from_memory = rt.block_on(call(&f.app, post(uri, req.clone())));
        let from_sqlite = rt.block_on(call(&sqlite.app, post(uri, req)));
        assert_eq!(from_sqlite.status, StatusCode::OK, "{uri}");
        assert!(from_memory.body == from_sqlite.body, "{uri}: memory and SQLite answers differ");
    }
}

/// A bad request that must name what was wrong: (method, uri, body, status, words in the error).
type BadCase<'a> = (&'a str, String, Option<String>, u16, &'a [&'a str]);

#[test]
fn bad_requests_are_named() {
    let f = fixture();
    let rt = rt();
    let cam = r#"{"width": 640, "height": 480, "hfov_deg": 40}"#;
    let pose = r#"{"lat_deg": 40, "lon_deg": -105.5, "h_m": 7500, "q_ecef_cam": [1, 0, 0, 0]}"#;
    let cases: Vec<BadCase> = vec![
        ("GET", "/v1/templates".into(), None, 400, &["bbox", "missing"]),
        ("GET", "/v1/templates?bbox=1,2,3".into(), None, 400, &["bbox", "4 numbers"]),
        ("GET", "/v1/templates?bbox=NaN,0,1,1".into(), None, 400, &["min_lon", "finite"]),
        ("GET", "/v1/templates?bbox=0,50,1,40".into(), None, 400, &["reversed"]),
        ("GET", "/v1/templates?bbox=0,0,1,91".into(), None, 400, &["max_lat", "range"]),
        ("GET", "/v1/templates?bbox=-1e308,0,1,1".into(), None, 400, &["min_lon", "range"]),
        ("GET", "/v1/templates?bbox=0,0,1,1e999".into(), None, 400, &["max_lat"]),
        ("GET", "/v1/templates?bbox=a,0,1,1".into(), None, 400, &["min_lon", "not a number"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&level=256".into(), None, 400, &["level"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&level=3..1".into(), None, 400, &["level", "reversed"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&limit=0".into(), None, 400, &["limit"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&limit=99999999999999999999".into(), None, 400, &["limit"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&offset=-1".into(), None, 400, &["offset"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&lighting=256".into(), None, 400, &["lighting"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&lighting=sun".into(), None, 400, &["lighting"]),
        ("GET", "/v1/templates?bbox=0,0,1,1&colour=red".into(), None, 400, &["colour"]),
        ("GET", "/v1/templates/abc".into(), None, 400, &["id", "abc"]),
        ("GET", "/v1/templates/99999999999999999999".into(), None, 400, &["id"]),
        ("GET", "/v1/nothing".into(), None, 404, &["/v1/nothing"]),
        ("DELETE", "/v1/info".into(), None, 405, &["method"]),
        ("POST", "/v1/footprint".into(), Some("{".into()), 400, &["JSON"]),
        ("POST", "/v1/footprint".into(), Some("[]".into()), 422, &[]),
        ("POST", "/v1/footprint".into(), Some(format!(r#"{{"camera": {cam}}}"#)), 422, &["pose"]),
        (
            "POST",
            "/v1/footprint".into(),
            Some(format!(r#"{{"camera": {{"width": 0, "height": 480, "hfov_deg": 40}}, "pose": {pose}}}"#)),
            422,
            &["camera", "size"],
        ),
        (
            "POST",
            "/v1/footprint".into(),
            Some(format!(
                r#"{{"camera": {cam}, "pose": {{"lat_deg": 91, "lon_deg": 0, "h_m": 1, "q_ecef_cam": [1,0,0,0]}}}}"#
            )),
            422,
            &["pose", "lat_deg"],
        ),
        (
            "POST",
            "/v1/footprint".into(),
            Some(format!(
                r#"{{"camera": {cam}, "pose": {{"lat_deg": 1, "lon_deg": 0, "h_m": 1, "q_ecef_cam": [0,0,0,0]}}}}"#
            )),
            422,
            &["q_ecef_cam"],
        ),
        // Identity attitude at 40N looks away from the Earth: no ground in view.
        (
            "POST",
            "/v1/footprint".into(),
            Some(format!(r#"{{"camera": {cam}, "pose": {pose}, "terrain_h_m": 0}}"#)),
            422,
            &["pose", "ground"],
        ),
        (
            "POST",
            "/v1/footprint".into(),
            Some(format!(r#"{{"camera": {cam}, "pose": {pose}, "alpha_max_deg": 95}}"#)),
            422,
            &["alpha_max_deg"],
        ),
        (
            "POST",
            "/v1/coverage".into(),
            Some(format!(r#"{{"camera": {cam}}}"#)),
            422,
            &["poses or waypoints"],
        ),
        (
            "POST",
            "/v1/coverage".into(),
            Some(format!(
                r#"{{"camera": {cam}, "waypoints": [{{"lat_deg": 0, "lon_deg": 0, "h_m": 1000}}, {{"lat_deg": 10, "lon_deg": 0, "h_m": 1000}}], "step_m": 1}}"#
            )),
            413,
            &["points"],
        ),
        (
            "POST",
            "/v1/coverage".into(),
            Some(format!(r#"{{"camera": {cam}, "poses": [], "extra": 1}}"#)),
            422,
            &["extra"],
        ),
        (
            "POST",
            "/v1/coverage".into(),
            Some(format!("{{\"camera\": {cam}, \"poses\": [{}]}}", vec![pose; 3000].join(","))),
            413,
            &["length limit"],
        ),
    ];
    for (method, uri, body, status, words) in cases {
        let req = match &body {
            Some(b) => Request::builder()
                .method(method)
                .uri(&uri)
                .header(header::CONTENT_TYPE, "application/json")
                .body(Body::from(b.clone())),
            None => Request::builder().method(method).uri(&uri).body(Body::empty()),
        }
        .unwrap();
        let a = rt.block_on(call(&f.app, req));
        assert_eq!(a.status.as_u16(), status, "{method} {uri}: {}", String::from_utf8_lossy(&a.body));
        assert!(a.headers[header::CONTENT_TYPE].to_str().unwrap().starts_with("application/json"), "{uri}");
        let e = a.error();
        for w in words {
            assert!(e.contains(w), "{method} {uri}: {e:?} does not say {w:?}");
        }
    }
    // Without a JSON content type.
    let req = Request::post("/v1/coverage").body(Body::from("{}")).unwrap();
    let a = rt.block_on(call(&f.app, req));
    assert_eq!(a.status, StatusCode::UNSUPPORTED_MEDIA_TYPE);
    assert!(a.error().to_lowercase().contains("content-type"));
}

fn arb_number() -> impl Strategy<Value = String> {
    prop_oneof![
        (-200.0f64..200.0).prop_map(|v| v.to_string()),
        any::<f64>().prop_map(|v| v.to_string()),
        Just("NaN".to_owned()),
        Just("inf".to_owned()),
        Just("-0".to_owned()),
        "[ -~]{0,12}",
    ]
}

fn arb_query() -> impl Strategy<Value = String> {
    (
        proptest::collection::vec(arb_number(), 0..6),
        proptest::option::of("[0-9a-z.\\-]{0,6}"),
        proptest::option::of("[0-9\\-]{0,22}"),
        proptest::option::of("[a-z_]{1,8}"),
    )
        .prop_map(|(nums, level, limit, extra)| {
            let enc = |s: &str| {
                s.bytes()
                    .map(|b| {
                        if b.is_ascii_alphanumeric() || b"-.,_".contains(&b) {
                            (b as char).to_string()
                        } else {
                            format!("%{b:02X}")
                        }
                    })
                    .collect::<String>()
            };
            let mut q = format!("bbox={}", enc(&nums.join(",")));
            if let Some(l) = level {
                q += &format!("&level={}", enc(&l));
            }
            if let Some(l) = limit {
                q += &format!("&limit={}", enc(&l));
            }
            if let Some(e) = extra {
                q += &format!("&{e}=1");
            }
            q
        })
}

fn arb_body() -> impl Strategy<Value = String> {
    let num = prop_oneof![
        any::<f64>().prop_map(|v| if v.is_finite() { v.to_string() } else { "1e400".into() }),
        (-100.0f64..100.0).prop_map(|v| v.to_string()),
        Just("null".to_owned()),
        Just("\"x\"".to_owned())
    ];
    prop_oneof![
        "[ -~]{0,64}",
        (num.clone(), num.clone(), num.clone(), num.clone(), num.clone(), num.clone()).prop_map(|(a, b, c, d, e, g)| format!(
            r#"{{"camera": {{"width": 640, "height": 480, "hfov_deg": {a}}}, "pose": {{"lat_deg": {b}, "lon_deg": {c}, "h_m": {d}, "q_ecef_cam": [{e}, {g}, 0.5, 0.5]}}}}"#
        )),
        (num.clone(), num.clone(), num.clone(), num).prop_map(|(a, b, c, d)| format!(
            r#"{{"camera": {{"width": 64, "height": 48, "fx": {a}, "fy": 50}}, "waypoints": [{{"lat_deg": {b}, "lon_deg": {c}, "h_m": 5000}}, {{"lat_deg": 40, "lon_deg": -105.5, "h_m": {d}}}], "step_m": 2000}}"#
        )),
    ]
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, failure_persistence: None, ..ProptestConfig::default() })]

    /// Whatever the query string or body: a 200, or a 4xx with a JSON error, never a 5xx.
    #[test]
    fn generated_input_never_fails_the_server(query in arb_query(), body in arb_body(), which in 0..3usize) {
        thread_local! {
            static F: (Fixture, tokio::runtime::Runtime) = (fixture(), rt());
        }
        F.with(|(f, rt)| {
            let req = match which {
                0 => get(&format!("/v1/templates?{query}")),
                1 => post("/v1/footprint", body.clone()),
                _ => post("/v1/coverage", body.clone()),
            };
            let a = rt.block_on(call(&f.app, req));
            let s = a.status.as_u16();
            prop_assert!(s == 200 || (400..500).contains(&s), "{s} for {query} / {body}: {}", String::from_utf8_lossy(&a.body));
            if s != 200 {
                prop_assert!(!a.error().is_empty());
            }
            Ok(())
        })?;
    }
}

#[test]
fn a_request_over_the_timeout_is_answered_408_in_json() {
    let f = fixture();
    let rt = rt();
    let state = AppState::open({
        let info = rt.block_on(call(&f.app, get("/v1/info"))).json();
        let mut o = ServeOptions::new(info["path"].as_str().unwrap().into(), "127.0.0.1:0".into());
        o.request_timeout = std::time::Duration::from_micros(1);
        o
    })
    .unwrap();
    let app = router(Arc::new(state));
    let pose = nadir_pose(40.0, -105.5, 26_500.0);
    let poses = vec![pose; 2000];
    let body = serde_json::json!({"camera": {"width": 640, "height": 480, "hfov_deg": 40}, "poses": poses});
    let a = rt.block_on(call(&app, post("/v1/coverage", body.to_string())));
    assert_eq!(a.status, StatusCode::REQUEST_TIMEOUT);
    assert!(a.error().contains("too long"), "{}", a.error());
    // Other servers over the same file are unaffected.
    assert_eq!(rt.block_on(call(&f.app, get("/health"))).status, StatusCode::OK);
}
