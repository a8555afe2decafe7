//! The landmark server behind `trn serve`.
//!
//! The main type is [`AppState`]: the current version of the database (a
//! [`db::Database`]: a fixed pool of read-only SQLite connections, the
//! `/v1/info` answer and the ETag) behind an atomic pointer, so a reload
//! (SIGHUP, or a change of the file when `--watch` is on) swaps in the new file
//! while requests that started on the old one finish on it. [`router`] builds
//! the axum application on it (bounding-box, template, info, footprint and
//! coverage endpoints, OpenAPI document, with request ids, logs, compression,
//! ETags, timeouts, body and concurrency limits), [`serve`] runs it until
//! Ctrl-C or SIGTERM (graceful: in-flight requests finish).
//!
//! Database queries run on tokio's blocking pool, one pooled connection each.
//! Every bad input is answered with a 4xx and `{"error": "..."}` naming the
//! parameter; see `docs/SERVER.md` for the API and the binary encoding.
//! [`coverage_cli::run_cli`] is `trn coverage`, over a database file or, through
//! [`client`], a running server.
//!
//! ```
//! use trn_server::coverage::{plan_poses, CoverageRequest};
//!
//! // A coverage plan (the body of POST /v1/coverage, the file of `trn coverage
//! // --plan`): a camera and poses. A bad field is named in the answer.
//! let plan = r#"{"camera": {"width": 640, "height": 480, "hfov_deg": 40},
//!                "poses": [{"lat_deg": 40.0, "lon_deg": -111.0, "h_m": 10000, "q_ecef_cam": [1, 0, 0, 0]}]}"#;
//! let req: CoverageRequest = serde_json::from_str(plan).unwrap();
//! let (camera, poses) = plan_poses(&req).unwrap();
//! assert_eq!((camera.width, poses.len()), (640, 1));
//! let bad: CoverageRequest = serde_json::from_str(&plan.replace("40.0", "91.0")).unwrap();
//! assert!(plan_poses(&bad).unwrap_err().message.contains("lat_deg 91 is not in [-90, 90]"));
//! ```

// `!(x <= y)` is how these crates reject NaN along with out-of-range values.

pub mod api;
pub mod client;
pub mod coverage;
pub mod coverage_cli;
pub mod db;
pub mod error;
pub mod listing;

use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, SystemTime};

use arc_swap::ArcSwap;
use axum::http::{header, HeaderValue, Request, StatusCode};
use axum::response::Response;
use axum::routing::{get, post};
use axum::Router;
use tower::ServiceBuilder;
use tower_http::compression::CompressionLayer;
use tower_http::request_id::{MakeRequestId, PropagateRequestIdLayer, RequestId, SetRequestIdLayer};
use tower_http::timeout::TimeoutLayer;
use tower_http::trace::TraceLayer;
use tracing::{error, info, warn};

pub use db::Database;
pub use error::{ApiError, ServerError};

/// Default of `--cache-mb`: a database up to this size is served from memory.
pub const DEFAULT_CACHE_MB: u64 = 2048;

/// What `trn serve` is asked to do.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    pub db: PathBuf,
    /// `host:port`; port 0 picks a free one (the bound address is printed).
    pub listen: String,
    /// Read-only connections to the database (queries running at once).
    pub connections: usize,
    /// Requests handled at once; more wait.
    pub max_concurrency: usize,
    /// A request taking longer is answered 408.
    pub request_timeout: Duration,
    /// Largest request body (bytes); larger is answered 413.
    pub max_body_bytes: usize,
    /// Reload when the file at the path changes (checked every `watch_interval`).
    pub watch: bool,
    pub watch_interval: Duration,
    /// Tokio worker threads (default: the number of cores).
    pub threads: Option<usize>,
    /// Largest database (records and index, bytes) read whole into memory and
    /// served from there; a larger one is queried in SQLite. 0: never.
    pub cache_bytes: u64,
}

impl ServeOptions {
    pub fn new(db: PathBuf, listen: String) -> Self {
        let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
        Self {
            db,
            listen,
            connections: (2 * cores).max(4),
            max_concurrency: 1024,
            request_timeout: Duration::from_secs(30),
            max_body_bytes: 2 << 20,
            watch: false,
            watch_interval: Duration::from_secs(1),
            threads: None,
            cache_bytes: DEFAULT_CACHE_MB << 20,
        }
    }
}

/// The server's state: the current database version and how to reopen it.
pub struct AppState {
    pub db: ArcSwap<Database>,
    opts: ServeOptions,
}

impl AppState {
    /// Opens the database (all connections).
    pub fn open(opts: ServeOptions) -> Result<Self, ServerError> {
        let db = Database::open(&opts.db, opts.connections, opts.cache_bytes)?;
        Ok(Self { db: ArcSwap::from_pointee(db), opts })
    }

    /// Reopens the file at the path and swaps it in; on failure the current
    /// version stays and the error is returned (and logged).
    pub async fn reload(self: &Arc<Self>) -> Result<(), ServerError> {
        let me = self.clone();
        let opened = tokio::task::spawn_blocking(move || {
            Database::open(&me.opts.db, me.opts.connections, me.opts.cache_bytes)
        })
        .await
        .map_err(|e| ServerError::Other(format!("reload task failed: {e}")))?;
        match opened {
            Ok(db) => {
                let old = self.db.swap(Arc::new(db));
                let new = self.db.load();
                info!(
                    "reloaded {}: database {} ({} templates), was {}",
                    self.opts.db.display(),
                    new.info.database_id,
                    new.info.template_count,
                    old.info.database_id
                );
                Ok(())
            }
            Err(e) => {
                error!("reload failed, still serving database {}: {e}", self.db.load().info.database_id);
                Err(e)
            }
        }
    }
}

/// Request ids: `<start time in hex>-<counter>`, unique per process start.
#[derive(Clone)]
struct Counter {
    prefix: Arc<str>,
    next: Arc<AtomicU64>,
}

impl MakeRequestId for Counter {
    fn make_request_id<B>(&mut self, _request: &Request<B>) -> Option<RequestId> {
        let n = self.next.fetch_add(1, Ordering::Relaxed);
        HeaderValue::from_str(&format!("{}-{n}", self.prefix)).ok().map(RequestId::new)
    }
}

/// Error answers made by the layers (timeout, unknown method, body limit)
/// get the JSON error body too.
async fn json_errors(resp: Response) -> Response {
    let s = resp.status();
    let is_json = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(s.is_client_error() || s.is_server_error()) || is_json {
        return resp;
    }
    let msg = match s {
        StatusCode::REQUEST_TIMEOUT => "the request took too long and was cancelled".to_owned(),
        StatusCode::PAYLOAD_TOO_LARGE => "the request body is too large".to_owned(),
        StatusCode::METHOD_NOT_ALLOWED => "method not allowed on this endpoint".to_owned(),
        s => s.canonical_reason().unwrap_or("error").to_owned(),
    };
    let mut out = error::json_error(s, &msg);
    if let Some(allow) = resp.headers().get(header::ALLOW) {
        out.headers_mut().insert(header::ALLOW, allow.clone());
    }
    out
}

/// The application: routes and layers over `state`.
pub fn router(state: Arc<AppState>) -> Router {
    let opts = &state.opts;
    let start = SystemTime::now().duration_since(SystemTime::UNIX_EPOCH).map_or(0, |d| d.as_secs());
    let ids = Counter { prefix: format!("{start:x}").into(), next: Arc::new(AtomicU64::new(1)) };
    let layers = ServiceBuilder::new()
        .layer(SetRequestIdLayer::x_request_id(ids))
        .layer(TraceLayer::new_for_http().make_span_with(|req: &Request<_>| {
            let id = req.headers().get("x-request-id").and_then(|v| v.to_str().ok()).unwrap_or("-");
            tracing::info_span!("request", id = %id, method = %req.method(), uri = %req.uri())
        }))
        .layer(PropagateRequestIdLayer::x_request_id())
        .layer(CompressionLayer::new().gzip(true).zstd(true))
        .layer(axum::middleware::map_response(json_errors))
        .layer(TimeoutLayer::with_status_code(StatusCode::REQUEST_TIMEOUT, opts.request_timeout))
        .layer(tower::limit::GlobalConcurrencyLimitLayer::new(opts.max_concurrency))
        .layer(axum::extract::DefaultBodyLimit::max(opts.max_body_bytes));
    Router::new()
        .route("/health", get(api::health))
        .route("/openapi.json", get(api::openapi))
        .route("/v1/info", get(api::info))
        .route("/v1/templates", get(api::templates))
        .route("/v1/templates/{id}", get(api::template))
        .route("/v1/footprint", post(api::footprint))
        .route("/v1/coverage", post(api::coverage))
        .fallback(api::not_found)
        .with_state(state)
        .layer(layers)
}

/// Runs the server until Ctrl-C or SIGTERM; `on_ready` gets the bound address.
pub fn serve(opts: ServeOptions, on_ready: impl FnOnce(SocketAddr)) -> Result<(), ServerError> {
    let mut rt = tokio::runtime::Builder::new_multi_thread();
    if let Some(n) = opts.threads {
        rt.worker_threads(n.max(1));
    }
    let rt = rt.enable_all().build().map_err(|e| ServerError::Other(format!("tokio runtime: {e}")))?;
    rt.block_on(serve_async(opts, on_ready))
}

async fn serve_async(opts: ServeOptions, on_ready: impl FnOnce(SocketAddr)) -> Result<(), ServerError> {
    let listen = opts.listen.clone();
    let state = Arc::new(AppState::open(opts.clone())?);
    {
        let db = state.db.load();
        info!(
            "serving {}: database {}, {} templates in {} levels, {} connections",
            opts.db.display(),
            db.info.database_id,
            db.info.template_count,
            db.info.levels.len(),
            opts.connections
        );
    }
    let listener = tokio::net::TcpListener::bind(&listen)
        .await
        .map_err(|e| ServerError::Listen { addr: listen.clone(), reason: e.to_string() })?;
    let addr =
        listener.local_addr().map_err(|e| ServerError::Listen { addr: listen, reason: e.to_string() })?;
    info!("listening on http://{addr}");
    on_ready(addr);
    spawn_reloaders(&state)?;
    // No Nagle: the last partial segment of an answer goes out at once
    // instead of waiting for the client's (possibly delayed) ACK.
    let listener = axum::serve::ListenerExt::tap_io(listener, |tcp| {
        if let Err(e) = tcp.set_nodelay(true) {
            warn!("TCP_NODELAY on a new connection: {e}");
        }
    });
    axum::serve(listener, router(state))
        .with_graceful_shutdown(shutdown_signal())
        .await
        .map_err(|e| ServerError::Other(format!("server: {e}")))?;
    info!("stopped");
    Ok(())
}

/// SIGHUP reloads; with `--watch`, so does a new file at the path.
fn spawn_reloaders(state: &Arc<AppState>) -> Result<(), ServerError> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, SignalKind};
        let mut hup =
            signal(SignalKind::hangup()).map_err(|e| ServerError::Other(format!("SIGHUP handler: {e}")))?;
        let st = state.clone();
        tokio::spawn(async move {
            while hup.recv().await.is_some() {
                info!("SIGHUP: reloading {}", st.opts.db.display());
                let _ = st.reload().await;
            }
        });
    }
    if state.opts.watch {
        let st = state.clone();
        tokio::spawn(async move {
            let stamp = |p: &std::path::Path| {
                std::fs::metadata(p).ok().map(|m| {
                    #[cfg(unix)]
                    let ino = std::os::unix::fs::MetadataExt::ino(&m);
                    #[cfg(not(unix))]
                    let ino = 0u64;
                    (ino, m.len(), m.modified().ok())
                })
            };
            let mut last = stamp(&st.opts.db);
            loop {
                tokio::time::sleep(st.opts.watch_interval).await;
                let now = stamp(&st.opts.db);
                if now.is_some() && now != last {
                    info!("{} changed: reloading", st.opts.db.display());
                    if st.reload().await.is_ok() {
                        last = now;
                    } else {
                        warn!("will retry when the file changes again");
                        last = now;
                    }
                }
            }
        });
    }
    Ok(())
}

async fn shutdown_signal() {
    let ctrl_c = async {
        let _ = tokio::signal::ctrl_c().await;
    };
    #[cfg(unix)]
    let term = async {
        match tokio::signal::unix::signal(tokio::signal::unix::SignalKind::terminate()) {
            Ok(mut s) => {
                s.recv().await;
            }
            Err(_) => std::future::pending::<()>().await,
        }
    };
    #[cfg(not(unix))]
    let term = std::future::pending::<()>();
    tokio::select! {
        _ = ctrl_c => {},
        _ = term => {},
    }
    info!("shutting down: finishing the requests in flight");
}
