//! End to end: the real `trn serve` under 32 concurrent clients, bad input, a
//! database swapped in by rename + SIGHUP while clients run, graceful
//! shutdown; three replicas behind a round-robin TCP balancer through a
//! rolling reload; `trn navigate --server` against `--db`; `trn coverage`
//! with `--db` and `--server`.

mod common;

use std::collections::BTreeSet;
use std::io::{BufRead, BufReader};
use std::net::{Shutdown, SocketAddr, TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Stdio};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, OnceLock};
use std::thread::JoinHandle;
use std::time::{Duration, Instant};

use common::{nav_fixture, run, stderr, trn};
use trn_geodesy::{metres_per_degree, Geodetic};
use trn_landmark::{wire, GeoBox, HeightGrid, Template, TemplateQuality, TerrainPatch};
use trn_store::{BboxQuery, DbWriter, LandmarkDb};

/// A running `trn serve`, killed when dropped.
struct Server {
    child: Child,
    url: String,
    log: PathBuf,
}

impl Server {
    fn start(db: &Path, log: PathBuf, extra: &[&str]) -> Server {
        let mut child = trn()
            .args(["serve", "--db", db.to_str().unwrap(), "--listen", "127.0.0.1:0"])
            .args(extra)
            .stdout(Stdio::piped())
            .stderr(std::fs::File::create(&log).unwrap())
            .spawn()
            .unwrap();
        let mut line = String::new();
        BufReader::new(child.stdout.take().unwrap()).read_line(&mut line).unwrap();
        let url = line.trim().strip_prefix("listening on ").map(str::to_owned).unwrap_or_else(|| {
            let _ = child.kill();
            panic!(
                "no address on stdout ({line:?}); log: {}",
                std::fs::read_to_string(&log).unwrap_or_default()
            )
        });
        Server { child, url, log }
    }

    fn signal(&self, sig: i32) {
        // SAFETY: kill(2) on our own child's pid.
        assert_eq!(unsafe { libc::kill(self.child.id() as i32, sig) }, 0);
    }

    fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

fn agent() -> ureq::Agent {
    ureq::Agent::config_builder()
        .http_status_as_error(false)
        .timeout_global(Some(Duration::from_secs(30)))
        .build()
        .into()
}

/// (status, content type, body) of a GET.
fn get(agent: &ureq::Agent, url: &str, accept: &str) -> (u16, String, Vec<u8>) {
    let mut r = agent.get(url).header("Accept", accept).call().unwrap_or_else(|e| panic!("{url}: {e}"));
    let ct = r.headers().get("content-type").and_then(|v| v.to_str().ok()).unwrap_or("").to_owned();
    let body = r.body_mut().with_config().limit(1 << 30).read_to_vec().unwrap();
    (r.status().as_u16(), ct, body)
}

fn post(agent: &ureq::Agent, url: &str, body: &str) -> (u16, Vec<u8>) {
    let mut r = agent
        .post(url)
        .header("Content-Type", "application/json")
        .send(body.as_bytes())
        .unwrap_or_else(|e| panic!("{url}: {e}"));
    (r.status().as_u16(), r.body_mut().with_config().limit(1 << 30).read_to_vec().unwrap())
}

/// `n` templates at two levels around (40 N, 105.5 W), 0.2 deg across.
fn write_db(path: &Path, n: usize, seed: u64) {
    let mut s = seed;
    let mut next = || {
        s = s.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (s >> 11) as f64 / (1u64 << 53) as f64
    };
    let mut ts: Vec<Template> = (0..n)
        .map(|i| {
            let level = (i % 2) as u8;
            let gsd_m = 8.0 * f64::from(1u32 << level);
            let (lat, lon) = (40.0 + 0.2 * next() - 0.1, -105.5 + 0.2 * next() - 0.1);
            let (m_lat, m_lon) = metres_per_degree(lat);
            let (hl, hb) = (16.0 * gsd_m / 2.0 / m_lon, 16.0 * gsd_m / 2.0 / m_lat);
            Template {
                id: 0,
                level,
                gsd_m,
                width_px: 16,
                height_px: 16,
                center: Geodetic::new(lat, lon, 1500.0),
                footprint: GeoBox::new(lon - hl, lat - hb, lon + hl, lat + hb),
                terrain: TerrainPatch {
                    plane_normal_enu: [0.0, 0.0, 1.0],
                    plane_residual_rms_m: 0.1,
                    height_grid: HeightGrid { n: 3, spacing_m: 8.0 * gsd_m, heights_m: vec![0.0; 9] },
                },
                quality: TemplateQuality {
                    shi_tomasi: (next() * 100.0) as f32,
                    contrast_std: 20.0,
                    second_peak_ncc: (next() * 0.9) as f32,
                    shading_share: next() as f32,
                },
                source: 0,
                lighting: 0,
                pixels: (0..256).map(|k| (k * 13 + i) as u8).collect(),
            }
        })
        .collect();
    let mut w = DbWriter::create(path).unwrap();
    w.set_metadata("test", &serde_json::json!({"seed": seed})).unwrap();
    w.insert_batch(&mut ts).unwrap();
    w.finish().unwrap();
}

fn info(agent: &ureq::Agent, url: &str) -> serde_json::Value {
    let (s, _, b) = get(agent, &format!("{url}/v1/info"), "application/json");
    assert_eq!(s, 200);
    serde_json::from_slice(&b).unwrap()
}

#[test]
fn thirty_two_clients_bad_input_reload_and_shutdown() {
    let dir = tempfile::tempdir().unwrap();
    let db_path = dir.path().join("map.gpkg");
    write_db(&db_path, 3000, 1);
    let server = Server::start(&db_path, dir.path().join("serve.log"), &["--connections", "4"]);
    let url = server.url.clone();

    // Expected answers from the store itself.
    let db = LandmarkDb::open(&db_path).unwrap();
    let boxes: Vec<(GeoBox, u8)> = (0..16)
        .map(|i| {
            let f = i as f64 / 16.0;
            (
                GeoBox::new(-105.6 + 0.15 * f, 39.92 + 0.1 * f, -105.56 + 0.15 * f, 39.96 + 0.1 * f),
                (i % 2) as u8,
            )
        })
        .collect();
    let expected: Vec<Vec<i64>> = boxes
        .iter()
        .map(|(b, l)| db.query_bbox_ids(&BboxQuery::new(*b).with_levels(*l..=*l)).unwrap())
        .collect();
    assert!(expected.iter().all(|e| !e.is_empty() && e.len() < 1000));
    let expected = Arc::new(expected);

    // 32 clients at once, each with its own connection, binary and JSON answers.
    let start = Instant::now();
    let threads: Vec<_> = (0..32)
        .map(|c| {
            let (url, boxes, expected) = (url.clone(), boxes.clone(), expected.clone());
            std::thread::spawn(move || {
                let agent = agent();
                for k in 0..40 {
                    let i = (c * 7 + k) % boxes.len();
                    let (b, l) = boxes[i];
                    let q = format!(
                        "{url}/v1/templates?bbox={},{},{},{}&level={l}",
                        b.min_lon_deg, b.min_lat_deg, b.max_lon_deg, b.max_lat_deg
                    );
                    if k % 2 == 0 {
                        let (s, ct, body) = get(&agent, &q, wire::MEDIA_TYPE);
                        assert_eq!((s, ct.as_str()), (200, wire::MEDIA_TYPE));
                        let ids: Vec<i64> =
                            wire::decode(&body).unwrap().templates.iter().map(|t| t.id).collect();
                        assert_eq!(ids, expected[i]);
                    } else {
                        let (s, _, body) = get(&agent, &q, "application/json");
                        assert_eq!(s, 200);
                        let j: serde_json::Value = serde_json::from_slice(&body).unwrap();
                        let ids: Vec<i64> = j["templates"]
                            .as_array()
                            .unwrap()
                            .iter()
                            .map(|t| t["id"].as_i64().unwrap())
                            .collect();
                        assert_eq!(ids, expected[i]);
                    }
                }
            })
        })
        .collect();
    for t in threads {
        t.join().expect("a client failed");
    }
    println!("32 clients x 40 queries in {:.2} s", start.elapsed().as_secs_f64());

    // Bad input: named 4xx, and the server keeps serving.
    let a = agent();
    for (q, word) in [
        ("/v1/templates?bbox=0,50,1,40", "reversed"),
        ("/v1/templates?bbox=NaN,0,1,1", "min_lon"),
        ("/v1/templates?bbox=0,0,1,1e999", "max_lat"),
        ("/v1/templates/xyz", "id"),
    ] {
        let (s, ct, body) = get(&a, &format!("{url}{q}"), "application/json");
        assert_eq!((s, ct.as_str()), (400, "application/json"), "{q}");
        let e: serde_json::Value = serde_json::from_slice(&body).unwrap();
        assert!(e["error"].as_str().unwrap().contains(word), "{q}: {e}");
    }
    let (s, body) = post(&a, &format!("{url}/v1/footprint"), "{not json");
    assert_eq!(s, 400, "{}", String::from_utf8_lossy(&body));
    // A body over the limit: 413 in JSON, unless the server has answered and
    // closed the connection while the client was still sending (broken pipe
    // or reset); tests/api.rs checks the 413 answer itself in process.
    let huge = format!("{{\"camera\": {{}}, \"poses\": [{}]}}", "0,".repeat(2 << 20));
    match agent()
        .post(&format!("{url}/v1/coverage"))
        .header("Content-Type", "application/json")
        .send(huge.as_bytes())
    {
        Ok(mut r) => {
            let body = r.body_mut().with_config().limit(1 << 30).read_to_vec().unwrap();
            assert_eq!(r.status().as_u16(), 413, "{}", String::from_utf8_lossy(&body));
            assert!(serde_json::from_slice::<serde_json::Value>(&body).unwrap()["error"].is_string());
        }
        Err(ureq::Error::Io(e)) => println!("huge body: connection closed while sending ({e})"),
        Err(e) => panic!("huge body: {e}"),
    }
    // The server closes a connection whose body it refused to read; a new one is served.
    let a = agent();
    let (s, _, _) = get(&a, &format!("{url}/health"), "application/json");
    assert_eq!(s, 200);

    // A new version of the database, renamed over the old path, SIGHUP: clients
    // running meanwhile see no error, and /v1/info changes.
    let before = info(&a, &url);
    assert_eq!(before["template_count"], 3000);
    let stop = Arc::new(AtomicBool::new(false));
    let done = Arc::new(AtomicUsize::new(0));
    let counts = Arc::new(std::sync::Mutex::new(std::collections::BTreeSet::new()));
    let loops: Vec<_> = (0..4)
        .map(|_| {
            let (url, stop, done, counts) = (url.clone(), stop.clone(), done.clone(), counts.clone());
            std::thread::spawn(move || {
                let agent = agent();
                while !stop.load(Ordering::Relaxed) {
                    let (s, _, body) = get(
                        &agent,
                        &format!("{url}/v1/templates?bbox=-106,39,-105,41&limit=10000"),
                        wire::MEDIA_TYPE,
                    );
                    assert_eq!(s, 200, "{}", String::from_utf8_lossy(&body));
                    let n = wire::decode(&body).unwrap().templates.len();
                    counts.lock().unwrap().insert(n);
                    done.fetch_add(1, Ordering::Relaxed);
                }
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let tmp = dir.path().join("map.gpkg.new");
    write_db(&tmp, 2000, 2);
    std::fs::rename(&tmp, &db_path).unwrap();
    server.signal(libc::SIGHUP);
    let t0 = Instant::now();
    let after = loop {
        let i = info(&a, &url);
        if i["database_id"] != before["database_id"] {
            break i;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "no reload; log:\n{}", server.log());
        std::thread::sleep(Duration::from_millis(50));
    };
    assert_eq!(after["template_count"], 2000);
    std::thread::sleep(Duration::from_millis(300));
    stop.store(true, Ordering::Relaxed);
    for l in loops {
        l.join().expect("a client saw an error during the reload");
    }
    assert_eq!(*counts.lock().unwrap(), [2000, 3000].into_iter().collect());
    println!("{} queries during the reload", done.load(Ordering::Relaxed));
    // A file that is not a database: the reload fails, the old version stays.
    std::fs::write(&tmp, b"not a database").unwrap();
    std::fs::rename(&tmp, &db_path).unwrap();
    server.signal(libc::SIGHUP);
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(info(&a, &url)["database_id"], after["database_id"]);
    assert!(server.log().contains("reload failed"), "{}", server.log());

    // SIGTERM: a clean exit.
    let mut server = server;
    server.signal(libc::SIGTERM);
    let t0 = Instant::now();
    let status = loop {
        if let Some(s) = server.child.try_wait().unwrap() {
            break s;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "still running after SIGTERM");
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "{status:?}; log:\n{}", server.log());
}

#[test]
fn watch_reloads_a_database_renamed_over_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let db_path = dir.path().join("map.gpkg");
    write_db(&db_path, 500, 3);
    let server = Server::start(&db_path, dir.path().join("watch.log"), &["--watch"]);
    let a = agent();
    let before = info(&a, &server.url);
    assert_eq!(before["template_count"], 500);
    let tmp = dir.path().join("map.gpkg.new");
    write_db(&tmp, 700, 4);
    std::fs::rename(&tmp, &db_path).unwrap();
    // No signal: the watcher notices the new file.
    let t0 = Instant::now();
    let after = loop {
        let i = info(&a, &server.url);
        if i["database_id"] != before["database_id"] {
            break i;
        }
        assert!(t0.elapsed() < Duration::from_secs(20), "no reload; log:\n{}", server.log());
        std::thread::sleep(Duration::from_millis(100));
    };
    assert_eq!(after["template_count"], 700);
    println!("--watch reloaded after {:.1} s", t0.elapsed().as_secs_f64());
}

/// A round-robin TCP (L4) load balancer, as HAProxy in TCP mode: each accepted
/// connection goes to the next backend, and the bytes are copied both ways
/// until either side closes.
struct Balancer {
    url: String,
    stop: Arc<AtomicBool>,
    /// Connections handed to each backend.
    connections: Arc<Vec<AtomicUsize>>,
    accept: Option<JoinHandle<()>>,
}

impl Balancer {
    fn start(backends: Vec<SocketAddr>) -> Balancer {
        let listener = TcpListener::bind("127.0.0.1:0").unwrap();
        let url = format!("http://{}", listener.local_addr().unwrap());
        let stop = Arc::new(AtomicBool::new(false));
        let connections: Arc<Vec<AtomicUsize>> =
            Arc::new(backends.iter().map(|_| AtomicUsize::new(0)).collect());
        let (st, counts) = (stop.clone(), connections.clone());
        let accept = std::thread::spawn(move || {
            for (n, client) in listener.incoming().enumerate() {
                if st.load(Ordering::Relaxed) {
                    break;
                }
                let Ok(client) = client else { continue };
                let i = n % backends.len();
                counts[i].fetch_add(1, Ordering::Relaxed);
                // A backend that cannot be reached: the client's connection is
                // dropped, and its request fails.
                let Ok(backend) = TcpStream::connect(backends[i]) else { continue };
                let (Ok(c2), Ok(b2)) = (client.try_clone(), backend.try_clone()) else { continue };
                for (mut from, mut to) in [(client, b2), (backend, c2)] {
                    let _ = from.set_nodelay(true);
                    std::thread::spawn(move || {
                        let _ = std::io::copy(&mut from, &mut to);
                        let _ = to.shutdown(Shutdown::Write);
                    });
                }
            }
        });
        Balancer { url, stop, connections, accept: Some(accept) }
    }
}

impl Drop for Balancer {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::Relaxed);
        // Wake the accept loop.
        let _ = TcpStream::connect(self.url.trim_start_matches("http://"));
        if let Some(t) = self.accept.take() {
            let _ = t.join();
        }
    }
}

/// What the store answers for one query: the templates (the first 200) and
/// whether more match.
type Answers = Vec<(Vec<Template>, bool)>;

#[test]
fn replicas_behind_a_balancer_reload_one_after_another_without_a_failed_request() {
    let t_start = Instant::now();
    let dir = tempfile::tempdir().unwrap();
    let db_path = dir.path().join("map.gpkg");
    write_db(&db_path, 3000, 11);
    // Three replicas over the same file, and the balancer in front.
    let replicas: Vec<Server> = (0..3)
        .map(|i| {
            let log = dir.path().join(format!("replica{i}.log"));
            Server::start(&db_path, log, &["--threads", "1", "--connections", "2"])
        })
        .collect();
    let a = agent();
    let old_id = info(&a, &replicas[0].url)["database_id"].as_str().unwrap().to_owned();
    for r in &replicas {
        assert_eq!(info(&a, &r.url)["database_id"], old_id.as_str(), "replicas of one file differ");
    }
    let balancer = Balancer::start(
        replicas.iter().map(|r| r.url.trim_start_matches("http://").parse().unwrap()).collect(),
    );

    // Random boxes, some at one level; the expected answers from the store.
    let mut seed = 99u64;
    let mut next = || {
        seed = seed.wrapping_mul(6_364_136_223_846_793_005).wrapping_add(1_442_695_040_888_963_407);
        (seed >> 11) as f64 / (1u64 << 53) as f64
    };
    let queries: Vec<(GeoBox, Option<u8>)> = (0..24)
        .map(|i| {
            let (lon, lat, r) = (-105.6 + 0.2 * next(), 39.9 + 0.2 * next(), 0.005 + 0.03 * next());
            (GeoBox::new(lon - r, lat - r, lon + r, lat + r), [None, Some(0), Some(1)][i % 3])
        })
        .collect();
    let answers = |db: &LandmarkDb| -> Answers {
        queries
            .iter()
            .map(|(b, l)| {
                let q = BboxQuery { bbox: *b, levels: l.map(|l| l..=l), limit: Some(201), lighting: None };
                let mut t = db.query_bbox(&q).unwrap();
                let truncated = t.len() > 200;
                t.truncate(200);
                (t, truncated)
            })
            .collect()
    };
    let old = Arc::new(answers(&LandmarkDb::open(&db_path).unwrap()));
    assert!(old.iter().all(|(t, _)| !t.is_empty()) && old.iter().any(|(_, tr)| *tr));
    let new: Arc<OnceLock<Answers>> = Arc::new(OnceLock::new());
    let old_etag = format!("W/\"{old_id}-b\"");

    // 8 clients through the balancer, binary answers, each checked against the
    // version its ETag names; 4 keep one connection, 4 open one per request.
    let stop = Arc::new(AtomicBool::new(false));
    let failures = Arc::new(Mutex::new(Vec::<String>::new()));
    let new_etags = Arc::new(Mutex::new(BTreeSet::<String>::new()));
    let (n_old, n_new) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicUsize::new(0)));
    let clients: Vec<_> = (0..8)
        .map(|c| {
            let (lb, stop, failures, new_etags) =
                (balancer.url.clone(), stop.clone(), failures.clone(), new_etags.clone());
            let (queries, old, new, old_etag) = (queries.clone(), old.clone(), new.clone(), old_etag.clone());
            let (n_old, n_new) = (n_old.clone(), n_new.clone());
            std::thread::spawn(move || {
                let keep_alive = c < 4;
                let mut kept = agent();
                let mut k = c * 5;
                while !stop.load(Ordering::Relaxed) {
                    k += 7;
                    let i = k % queries.len();
                    let (b, l) = queries[i];
                    let url = format!(
                        "{lb}/v1/templates?bbox={},{},{},{}&limit=200{}",
                        b.min_lon_deg,
                        b.min_lat_deg,
                        b.max_lon_deg,
                        b.max_lat_deg,
                        l.map(|l| format!("&level={l}")).unwrap_or_default()
                    );
                    if !keep_alive {
                        kept = agent();
                    }
                    let fail = |why: String| failures.lock().unwrap().push(format!("client {c}: {url}: {why}"));
                    let mut r = match kept.get(&url).header("Accept", wire::MEDIA_TYPE).call() {
                        Ok(r) => r,
                        Err(e) => {
                            fail(e.to_string());
                            continue;
                        }
                    };
                    let etag = r.headers().get("etag").and_then(|v| v.to_str().ok()).unwrap_or("").to_owned();
                    let body = match r.body_mut().with_config().limit(1 << 30).read_to_vec() {
                        Ok(b) => b,
                        Err(e) => {
                            fail(format!("reading the body: {e}"));
                            continue;
                        }
                    };
                    if r.status() != 200 {
                        fail(format!("HTTP {}: {}", r.status(), String::from_utf8_lossy(&body)));
                        continue;
                    }
                    let list = match wire::decode(&body) {
                        Ok(l) => l,
                        Err(e) => {
                            fail(format!("decoding: {e}"));
                            continue;
                        }
                    };
                    let (version, expected) = if etag == old_etag {
                        n_old.fetch_add(1, Ordering::Relaxed);
                        ("old", &old[i])
                    } else if let Some(new) = new.get() {
                        n_new.fetch_add(1, Ordering::Relaxed);
                        new_etags.lock().unwrap().insert(etag.clone());
                        ("new", &new[i])
                    } else {
                        fail(format!("ETag {etag} before the new version exists"));
                        continue;
                    };
                    if (&list.templates, list.truncated) != (&expected.0, expected.1) {
                        fail(format!(
                            "{} templates (truncated {}) under ETag {etag}, the {version} version has {} ({})",
                            list.templates.len(),
                            list.truncated,
                            expected.0.len(),
                            expected.1
                        ));
                    }
                }
            })
        })
        .collect();
    std::thread::sleep(Duration::from_millis(500));

    // A new version written next to the live file, renamed over it, then a
    // rolling reload: SIGHUP to one replica at a time, each serving the new
    // version before the next is told.
    let tmp = dir.path().join("map.gpkg.new");
    write_db(&tmp, 2500, 12);
    new.set(answers(&LandmarkDb::open(&tmp).unwrap())).unwrap();
    std::fs::rename(&tmp, &db_path).unwrap();
    let t_reload = Instant::now();
    let mut new_id = None;
    for r in &replicas {
        r.signal(libc::SIGHUP);
        let t0 = Instant::now();
        let id = loop {
            let id = info(&a, &r.url)["database_id"].as_str().unwrap().to_owned();
            if id != old_id {
                break id;
            }
            assert!(t0.elapsed() < Duration::from_secs(10), "no reload; log:\n{}", r.log());
            std::thread::sleep(Duration::from_millis(20));
        };
        assert_eq!(new_id.get_or_insert_with(|| id.clone()), &id, "replicas of one file differ");
        std::thread::sleep(Duration::from_millis(250));
    }
    let reload_s = t_reload.elapsed().as_secs_f64();
    std::thread::sleep(Duration::from_millis(250));
    stop.store(true, Ordering::Relaxed);
    for c in clients {
        c.join().expect("a client panicked");
    }

    let failures = failures.lock().unwrap();
    assert!(
        failures.is_empty(),
        "{} failed requests, the first: {:#?}",
        failures.len(),
        &failures[..failures.len().min(5)]
    );
    let (n_old, n_new) = (n_old.load(Ordering::Relaxed), n_new.load(Ordering::Relaxed));
    assert!(n_old > 0 && n_new > 0, "{n_old} answers from the old version, {n_new} from the new");
    let new_etag = format!("W/\"{}-b\"", new_id.unwrap());
    assert_eq!(*new_etags.lock().unwrap(), [new_etag.clone()].into_iter().collect());
    // Every replica answers with the new version and its ETag.
    let new = new.get().unwrap();
    for r in &replicas {
        let (b, l) = queries[0];
        let url = format!(
            "{}/v1/templates?bbox={},{},{},{}&limit=200{}",
            r.url,
            b.min_lon_deg,
            b.min_lat_deg,
            b.max_lon_deg,
            b.max_lat_deg,
            l.map(|l| format!("&level={l}")).unwrap_or_default()
        );
        let mut resp = a.get(&url).header("Accept", wire::MEDIA_TYPE).call().unwrap();
        assert_eq!(resp.headers().get("etag").unwrap().to_str().unwrap(), new_etag);
        let body = resp.body_mut().with_config().limit(1 << 30).read_to_vec().unwrap();
        assert_eq!(wire::decode(&body).unwrap().templates, new[0].0);
    }
    let per_replica: Vec<usize> = balancer.connections.iter().map(|n| n.load(Ordering::Relaxed)).collect();
    assert!(per_replica.iter().all(|&n| n > 0), "connections per replica: {per_replica:?}");
    println!(
        "{} answers through the balancer ({n_old} old, {n_new} new), connections per replica {per_replica:?}, \
         rolling reload {reload_s:.2} s, test {:.1} s",
        n_old + n_new,
        t_start.elapsed().as_secs_f64()
    );
}

#[test]
fn serve_names_bad_options() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.gpkg");
    let o = run(&["serve", "--db", missing.to_str().unwrap(), "--listen", "127.0.0.1:0"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("nope.gpkg"), "{}", stderr(&o));
    let db = dir.path().join("map.gpkg");
    write_db(&db, 10, 3);
    let o = run(&["serve", "--db", db.to_str().unwrap(), "--listen", "not an address"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--listen"), "{}", stderr(&o));
    let o = run(&["serve", "--db", db.to_str().unwrap(), "--timeout-s", "0"]);
    assert!(stderr(&o).contains("--timeout-s"), "{}", stderr(&o));
    for bad in ["-1", "lots", "99999999999"] {
        let o = run(&["serve", "--db", db.to_str().unwrap(), "--cache-mb", bad]);
        assert!(!o.status.success(), "--cache-mb {bad} accepted");
        // clap names the option, or (for "-1", read as a flag) the value.
        assert!(stderr(&o).contains("--cache-mb") || stderr(&o).contains(bad), "{}", stderr(&o));
    }
    let o = run(&["navigate", "--db", "x", "--server", "http://y", "--flight", "f", "--out", "o"]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--server"), "{}", stderr(&o));

    // trn coverage: exactly one of --db and --server; a server URL that is
    // not http://, or where nothing listens, is named.
    let plan = dir.path().join("plan.json");
    std::fs::write(&plan, "{}").unwrap();
    let plan = plan.to_str().unwrap();
    let o = run(&["coverage", "--db", db.to_str().unwrap(), "--server", "http://y", "--plan", plan]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--db") && stderr(&o).contains("--server"), "{}", stderr(&o));
    let o = run(&["coverage", "--plan", plan]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--db") && stderr(&o).contains("--server"), "{}", stderr(&o));
    let o = run(&["coverage", "--server", "ftp://example.org", "--plan", plan]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("ftp://example.org"), "{}", stderr(&o));
    let closed = {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        format!("http://{}", l.local_addr().unwrap())
    };
    let o = run(&["coverage", "--server", &closed, "--plan", plan]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains(&format!("{closed}/v1/coverage: no answer")), "{}", stderr(&o));
}

/// `trn navigate` of `flight` into `out` (its folder created) with the
/// landmark `source` and `extra` options; its stderr.
fn navigate_into(flight: &Path, source: &[&str], extra: &[&str], out: &Path) -> String {
    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
    let mut args = vec!["navigate", "--flight", flight.to_str().unwrap(), "--out", out.to_str().unwrap()];
    args.extend_from_slice(source);
    args.extend_from_slice(extra);
    let o = run(&args);
    assert!(o.status.success(), "navigate {source:?} failed: {}", stderr(&o));
    stderr(&o)
}

/// The rows of a poses file but the per-frame time column (ms, last).
fn poses_without_time(p: &Path) -> Vec<String> {
    std::fs::read_to_string(p)
        .unwrap()
        .lines()
        .map(|l| l.rsplit_once(',').map_or(l, |x| x.0).to_owned())
        .collect()
}

#[test]
fn navigate_through_the_server_gives_the_same_poses_and_coverage_maps_them() {
    // As tests/navigate.rs: a synthetic map, its database, a 3 s nadir flight.
    let fixture = nav_fixture();
    let (root, db, flight) = (fixture.root(), &fixture.db, &fixture.flight);
    let server = Server::start(db, root.join("serve.log"), &[]);
    let (by_db, by_http) = (root.join("db").join("poses.csv"), root.join("http").join("poses.csv"));
    navigate_into(flight, &["--db", db.to_str().unwrap()], &[], &by_db);
    navigate_into(flight, &["--server", &server.url], &[], &by_http);
    // Identical but the per-frame time column.
    let (a, b) = (poses_without_time(&by_db), poses_without_time(&by_http));
    assert!(a.len() > 10, "{} rows", a.len());
    assert_eq!(a, b, "poses through the server differ from the database's");
    assert_eq!(
        std::fs::read(by_db.with_file_name("matches.csv")).unwrap(),
        std::fs::read(by_http.with_file_name("matches.csv")).unwrap()
    );
    assert!(a.iter().skip(1).filter(|l| l.contains(",fix,")).count() >= a.len() * 9 / 10);

    // trn coverage on the flight's truth, as poses: every point sees landmarks.
    let truth = std::fs::read_to_string(flight.join("truth.csv")).unwrap();
    let poses: Vec<serde_json::Value> = truth
        .lines()
        .skip(1)
        .step_by(4)
        .map(|l| {
            let v: Vec<f64> = l.split(',').map(|x| x.parse().unwrap()).collect();
            serde_json::json!({"lat_deg": v[1], "lon_deg": v[2], "h_m": v[3], "q_ecef_cam": [v[4], v[5], v[6], v[7]]})
        })
        .collect();
    let plan = root.join("plan.json");
    let camera = std::fs::read_to_string(flight.join("camera.json")).unwrap();
    std::fs::write(
        &plan,
        format!(r#"{{"camera": {camera}, "poses": {}}}"#, serde_json::Value::from(poses.clone())),
    )
    .unwrap();
    let (geojson, png) = (root.join("cov.geojson"), root.join("cov.png"));
    let o = run(&[
        "coverage",
        "--db",
        db.to_str().unwrap(),
        "--plan",
        plan.to_str().unwrap(),
        "--geojson",
        geojson.to_str().unwrap(),
        "--png",
        png.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "coverage failed: {}", stderr(&o));
    let report: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let pts = report["points"].as_array().unwrap();
    assert_eq!(pts.len(), poses.len());
    assert!(report["min_landmarks"].as_u64().unwrap() >= 8, "{report}");
    assert_eq!(report["stretches"].as_array().unwrap().len(), 0);
    let g: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&geojson).unwrap()).unwrap();
    assert_eq!(g["type"], "FeatureCollection");
    let map = image::open(&png).unwrap().to_rgb8();
    assert_eq!(map.width(), 1024);
    assert!(map.pixels().any(|p| p[0] == p[1] && p[1] == p[2] && p[0] < 255), "no footprint drawn");
    // The server's answer is the same report.
    let body = std::fs::read_to_string(&plan).unwrap();
    let (s, answer) = post(&agent(), &format!("{}/v1/coverage", server.url), &body);
    assert_eq!(s, 200, "{}", String::from_utf8_lossy(&answer));
    assert_eq!(serde_json::from_slice::<serde_json::Value>(&answer).unwrap(), report);

    // trn coverage --server: the same report, GeoJSON and map, byte for byte.
    let (geojson2, png2) = (root.join("cov-server.geojson"), root.join("cov-server.png"));
    let o2 = run(&[
        "coverage",
        "--server",
        &server.url,
        "--plan",
        plan.to_str().unwrap(),
        "--geojson",
        geojson2.to_str().unwrap(),
        "--png",
        png2.to_str().unwrap(),
    ]);
    assert!(o2.status.success(), "coverage --server failed: {}", stderr(&o2));
    assert_eq!(String::from_utf8_lossy(&o2.stdout), String::from_utf8_lossy(&o.stdout));
    assert!(std::fs::read(&geojson).unwrap() == std::fs::read(&geojson2).unwrap(), "GeoJSON differs");
    assert!(std::fs::read(&png).unwrap() == std::fs::read(&png2).unwrap(), "PNG differs");
    // A plan the server refuses: its message, naming the URL and the field.
    let bad = root.join("bad-plan.json");
    std::fs::write(
        &bad,
        format!(
            r#"{{"camera": {camera}, "poses": [{{"lat_deg": 91, "lon_deg": 0, "h_m": 1000, "q_ecef_cam": [1, 0, 0, 0]}}]}}"#
        ),
    )
    .unwrap();
    let o = run(&["coverage", "--server", &server.url, "--plan", bad.to_str().unwrap()]);
    assert!(!o.status.success());
    let e = stderr(&o);
    assert!(e.contains(&format!("{}/v1/coverage: HTTP 422", server.url)), "{e}");
    assert!(e.contains("poses[0]: lat_deg 91 is not in [-90, 90]"), "{e}");
}

/// A database lit for two suns: `trn navigate --sun` asks the server for its
/// lighting only (`&lighting=K`) and gets what the database gives it directly.
#[test]
fn navigate_a_lit_database_through_the_server() {
    let fixture = nav_fixture();
    let root = fixture.root();
    let (ortho, dem) = (root.join("synth-ortho-21.tif"), root.join("synth-dem-21.tif"));
    let db = root.join("lit.gpkg");
    let s = |p: &Path| p.to_str().unwrap().to_owned();
    let o = run(&[
        "build",
        "--ortho",
        &s(&ortho),
        "--dem",
        &s(&dem),
        "--dem-vertical",
        "ellipsoid",
        "--spacing",
        "32",
        "--sun",
        "135,35",
        "--sun",
        "250,20",
        "--out",
        &s(&db),
    ]);
    assert!(o.status.success(), "build failed: {}", stderr(&o));
    let server = Server::start(&db, root.join("serve-lit.log"), &[]);
    let (by_db, by_http) = (root.join("lit-db").join("poses.csv"), root.join("lit-http").join("poses.csv"));
    let sun = ["--sun", "250,21"];
    let log = navigate_into(&fixture.flight, &["--db", &s(&db)], &sun, &by_db);
    assert!(log.contains("lighting 2"), "the sun nearest 250/21 is the second: {log}");
    navigate_into(&fixture.flight, &["--server", &server.url], &sun, &by_http);
    let (a, b) = (poses_without_time(&by_db), poses_without_time(&by_http));
    assert_eq!(a, b, "poses through the server differ from the database's");
    assert!(a.iter().skip(1).filter(|l| l.contains(",fix,")).count() >= a.len() * 9 / 10, "{a:?}");

    // Coverage counts each landmark once, from the file and through the
    // server (which reads the database's suns once, at load), as the
    // database with one lighting (the fixture's, built alike) does.
    let truth = std::fs::read_to_string(fixture.flight.join("truth.csv")).unwrap();
    let v: Vec<f64> = truth.lines().nth(1).unwrap().split(',').map(|x| x.parse().unwrap()).collect();
    let plan = root.join("lit-plan.json");
    std::fs::write(
        &plan,
        format!(
            r#"{{"camera": {{"width": 320, "height": 240, "hfov_deg": 40}},
                "waypoints": [{{"lat_deg": {}, "lon_deg": {}, "h_m": {}}}],
                "attitude": {{"tilt_deg": 0, "azimuth_deg": 0}}}}"#,
            v[1], v[2], v[3]
        ),
    )
    .unwrap();
    let in_view = |source: &[&str]| -> Vec<u64> {
        let mut args = vec!["coverage", "--plan", plan.to_str().unwrap()];
        args.extend_from_slice(source);
        let o = run(&args);
        assert!(o.status.success(), "coverage {source:?} failed: {}", stderr(&o));
        let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        j["points"].as_array().unwrap().iter().map(|p| p["landmarks"].as_u64().unwrap()).collect()
    };
    let unlit = in_view(&["--db", fixture.db.to_str().unwrap()]);
    assert!(unlit.iter().all(|&n| n > 10), "{unlit:?}");
    assert_eq!(in_view(&["--db", &s(&db)]), unlit);
    assert_eq!(in_view(&["--server", &server.url]), unlit);
}
