//! The one HTTP client of a `trn serve` landmark server, used by
//! `trn navigate --server` and `trn coverage --server`.
//!
//! - [`Remote`]: the transport. A plain `http://` base URL checked once, its
//!   host resolved once, a body limit, and every error naming the URL with the
//!   server's `{"error": ...}` message when it gave one ([`ClientError`]).
//! - [`collect_pages`]: follows a paged listing (`offset`, `truncated`) to its
//!   end, starting again when the database is reloaded in between (a new ETag).
//! - [`HttpSource`]: a [`trn_view::LandmarkSource`] over `GET /v1/info` and
//!   `GET /v1/templates` in the compact binary encoding ([`trn_landmark::wire`],
//!   lossless). The templates, and their order, are exactly those a
//!   [`trn_view::DbSource`] on the same file returns, so `trn navigate --server`
//!   gives the same poses as `--db`.
//!
//! ```
//! use trn_client::{collect_pages, Page, Remote};
//!
//! // A URL that is not a landmark server's is refused before anything is sent.
//! let e = Remote::new("ftp://example.org", std::time::Duration::from_secs(5)).err().unwrap();
//! assert!(e.to_string().starts_with("ftp://example.org: not a landmark server URL"));
//!
//! // Paging: three pages of a listing of 5 items, two per page.
//! let all = (0..5).collect::<Vec<u32>>();
//! let got = collect_pages(|offset| -> Result<Page<u32>, ()> {
//!     let items = all[offset..(offset + 2).min(5)].to_vec();
//!     Ok(Page { truncated: offset + items.len() < 5, items, etag: Some("v1".into()) })
//! })
//! .unwrap();
//! assert_eq!(got, all);
//! ```

use std::time::Duration;

use serde::Deserialize;
use trn_landmark::{wire, GeoBox, Template};
use trn_store::LevelInfo;
use trn_view::{LandmarkSource, SourceError};

/// Templates asked for per request (the server's largest page).
pub const PAGE_SIZE: usize = 10_000;
/// Largest response body read (bytes): a page of 10 000 templates of 64 x 64
/// px with 9 x 9 height grids takes about 45 MB, a coverage report of 10 000
/// points a few MB.
pub const MAX_BODY_BYTES: u64 = 256 << 20;

/// A request that failed: the URL, and why (the transport's error, or the
/// status and the server's message).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("{url}: {reason}")]
pub struct ClientError {
    pub url: String,
    pub reason: String,
}

fn error(url: &str, reason: impl Into<String>) -> ClientError {
    ClientError { url: url.to_owned(), reason: reason.into() }
}

#[derive(Deserialize)]
struct ErrorJson {
    error: String,
}

/// A landmark server reached over plain `http://`.
pub struct Remote {
    agent: ureq::Agent,
    base: String,
}

impl Remote {
    /// A client of the server at `base_url` (e.g. `http://127.0.0.1:8080`),
    /// each request allowed `timeout`; the host is looked up now, nothing is
    /// sent yet.
    pub fn new(base_url: &str, timeout: Duration) -> Result<Self, ClientError> {
        let base = base_url.trim_end_matches('/').to_owned();
        if !base.starts_with("http://") || base.len() == "http://".len() {
            return Err(error(
                base_url,
                "not a landmark server URL (give http://host:port, e.g. http://127.0.0.1:8080)",
            ));
        }
        let config =
            ureq::Agent::config_builder().timeout_global(Some(timeout)).http_status_as_error(false).build();
        let agent = ureq::Agent::with_parts(
            config,
            ureq::unversioned::transport::DefaultConnector::new(),
            OnceResolver::new(&base)?,
        );
        Ok(Self { agent, base })
    }

    /// The base URL, without a trailing `/`.
    pub fn base_url(&self) -> &str {
        &self.base
    }

    /// GET `path_and_query` (from `/`); the body and ETag of a 200.
    pub fn get(&self, path_and_query: &str, accept: &str) -> Result<(Vec<u8>, Option<String>), ClientError> {
        let mut body = Vec::new();
        let etag = self.get_into(path_and_query, accept, &mut body)?;
        Ok((body, etag))
    }

    /// [`Remote::get`] into `body` (cleared first), whose memory is reused.
    pub fn get_into(
        &self,
        path_and_query: &str,
        accept: &str,
        body: &mut Vec<u8>,
    ) -> Result<Option<String>, ClientError> {
        let url = format!("{}{path_and_query}", self.base);
        let resp = self.agent.get(&url).header("Accept", accept).call();
        answer(&url, resp, body)
    }

    /// POST `json` to `path` (from `/`); the body and ETag of a 200.
    pub fn post_json(&self, path: &str, json: &[u8]) -> Result<(Vec<u8>, Option<String>), ClientError> {
        let url = format!("{}{path}", self.base);
        let resp = self
            .agent
            .post(&url)
            .header("Content-Type", "application/json")
            .header("Accept", "application/json")
            .send(json);
        let mut body = Vec::new();
        let etag = answer(&url, resp, &mut body)?;
        Ok((body, etag))
    }
}

/// The ETag of a 200 (its body in `body`); otherwise an error naming `url`
/// with the server's message (or the transport's).
fn answer(
    url: &str,
    resp: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
    body: &mut Vec<u8>,
) -> Result<Option<String>, ClientError> {
    let mut resp = resp.map_err(|e| error(url, format!("no answer from the landmark server ({e})")))?;
    let status = resp.status();
    let etag = resp.headers().get("etag").and_then(|v| v.to_str().ok()).map(str::to_owned);
    read_body_into(resp.body_mut(), MAX_BODY_BYTES, body)
        .map_err(|e| error(url, format!("reading the answer: {e}")))?;
    if status != 200 {
        let why = serde_json::from_slice::<ErrorJson>(body)
            .map(|e| e.error)
            .unwrap_or_else(|_| String::from_utf8_lossy(body).chars().take(200).collect());
        return Err(error(url, format!("HTTP {status}: {why}")));
    }
    Ok(etag)
}

/// Landmarks from a landmark server: levels from `GET /v1/info` once, every
/// query `GET /v1/templates?bbox=..&level=..` in the binary encoding, paged.
pub struct HttpSource {
    remote: Remote,
    levels: Vec<LevelInfo>,
    suns: Vec<trn_landmark::lighting::SunLight>,
    /// The last answer's bytes: the buffer is kept for the next.
    body: std::sync::Mutex<Vec<u8>>,
}

#[derive(Deserialize)]
struct InfoJson {
    levels: Vec<LevelJson>,
    #[serde(default)]
    metadata: serde_json::Value,
}

#[derive(Deserialize)]
struct LevelJson {
    level: u8,
    gsd_m: f64,
    template_px: u32,
    count: u64,
    extent: GeoBox,
}

fn source_error(e: ClientError) -> SourceError {
    SourceError(e.to_string())
}

impl HttpSource {
    /// Connects to the server at `base_url` (e.g. `http://127.0.0.1:8080`) and
    /// reads its levels.
    pub fn connect(base_url: &str) -> Result<Self, SourceError> {
        let remote = Remote::new(base_url, Duration::from_secs(60)).map_err(source_error)?;
        let (body, _) = remote.get("/v1/info", "application/json").map_err(source_error)?;
        let at = format!("{}/v1/info", remote.base_url());
        let info: InfoJson = serde_json::from_slice(&body)
            .map_err(|e| SourceError(format!("{at}: not the expected JSON: {e}")))?;
        let suns = trn_view::suns_of_metadata(info.metadata.get("suns"), &at)?;
        let levels = info
            .levels
            .into_iter()
            .map(|l| LevelInfo {
                level: l.level,
                gsd_m: l.gsd_m,
                template_px: l.template_px,
                count: l.count,
                extent: l.extent,
            })
            .collect();
        Ok(Self { remote, levels, suns, body: Default::default() })
    }

    /// `GET /v1/templates` of one level (and lighting), every page.
    fn templates(
        &self,
        bbox: &GeoBox,
        level: u8,
        lighting: Option<u8>,
    ) -> Result<Vec<Template>, SourceError> {
        // The server refuses coordinates off the globe; clamping them changes no
        // result (no footprint lies beyond), so the answer is the DbSource's.
        let b = GeoBox::new(
            bbox.min_lon_deg.clamp(-180.0, 180.0),
            bbox.min_lat_deg.clamp(-90.0, 90.0),
            bbox.max_lon_deg.clamp(-180.0, 180.0),
            bbox.max_lat_deg.clamp(-90.0, 90.0),
        );
        let lit = lighting.map(|k| format!("&lighting={k}")).unwrap_or_default();
        let mut body = self.body.lock().unwrap_or_else(|p| p.into_inner());
        collect_pages(|offset| {
            // `{}` prints the shortest decimal that parses back to the same f64.
            let path = format!(
                "/v1/templates?bbox={},{},{},{}&level={level}{lit}&limit={PAGE_SIZE}&offset={offset}",
                b.min_lon_deg, b.min_lat_deg, b.max_lon_deg, b.max_lat_deg,
            );
            let etag = self.remote.get_into(&path, wire::MEDIA_TYPE, &mut body).map_err(source_error)?;
            let page = wire::decode(&body)
                .map_err(|e| SourceError(format!("{}{path}: {e}", self.remote.base_url())))?;
            Ok(Page { items: page.templates, truncated: page.truncated, etag })
        })
    }

    pub fn base_url(&self) -> &str {
        self.remote.base_url()
    }
}

/// One page of a listing: its items, whether more follow, the version's ETag.
pub struct Page<T> {
    pub items: Vec<T>,
    pub truncated: bool,
    pub etag: Option<String>,
}

/// Follows a paged listing (`fetch` gets the offset) to its end. Pages from
/// two database versions (a reload in between, seen as a new ETag) do not make
/// one list: the listing starts again.
pub fn collect_pages<T, E>(mut fetch: impl FnMut(usize) -> Result<Page<T>, E>) -> Result<Vec<T>, E> {
    let mut out = Vec::new();
    let mut first_etag = None;
    loop {
        let page = fetch(out.len())?;
        if out.is_empty() {
            first_etag = page.etag;
        } else if page.etag != first_etag {
            out.clear();
            first_etag = None;
            continue;
        }
        let n = page.items.len();
        out.extend(page.items);
        if !page.truncated || n == 0 {
            return Ok(out);
        }
    }
}

/// The server's addresses, looked up once at connect. ureq's own resolver
/// looks the host up before every request, and with a timeout set does it on a
/// new thread: a thread per query.
#[derive(Debug)]
struct OnceResolver {
    addrs: Vec<std::net::SocketAddr>,
}

impl OnceResolver {
    fn new(base: &str) -> Result<Self, ClientError> {
        use std::net::ToSocketAddrs;
        let uri: ureq::http::Uri = base.parse().map_err(|e| error(base, format!("not a URL: {e}")))?;
        let host = uri.host().ok_or_else(|| error(base, "no host in the URL"))?;
        let host = host.trim_start_matches('[').trim_end_matches(']');
        let port = uri.port_u16().unwrap_or(80);
        let addrs: Vec<_> = (host, port)
            .to_socket_addrs()
            .map_err(|e| error(base, format!("cannot resolve {host}: {e}")))?
            .collect();
        if addrs.is_empty() {
            return Err(error(base, format!("{host} has no address")));
        }
        Ok(Self { addrs })
    }
}

impl ureq::unversioned::resolver::Resolver for OnceResolver {
    fn resolve(
        &self,
        _uri: &ureq::http::Uri,
        _config: &ureq::config::Config,
        _timeout: ureq::unversioned::transport::NextTimeout,
    ) -> Result<ureq::unversioned::resolver::ResolvedSocketAddrs, ureq::Error> {
        let mut out = self.empty();
        // ureq holds at most 16.
        for a in self.addrs.iter().take(16) {
            out.push(*a);
        }
        Ok(out)
    }
}

/// Reads a whole body of at most `limit` bytes into `buf` (cleared first),
/// reserved from its `Content-Length`: a megabyte answer read into a growing
/// vector is copied about twice over on the way, and a new one each time
/// costs the allocator's page faults.
pub fn read_body_into(body: &mut ureq::Body, limit: u64, buf: &mut Vec<u8>) -> Result<(), ureq::Error> {
    use std::io::Read;
    buf.clear();
    buf.reserve(body.content_length().unwrap_or(0).min(limit) as usize);
    body.with_config().limit(limit).reader().read_to_end(buf)?;
    Ok(())
}

impl LandmarkSource for HttpSource {
    fn levels(&self) -> Result<Vec<LevelInfo>, SourceError> {
        Ok(self.levels.clone())
    }

    fn suns(&self) -> Result<Vec<trn_landmark::lighting::SunLight>, SourceError> {
        Ok(self.suns.clone())
    }

    fn query(&self, bbox: &GeoBox, level: u8) -> Result<Vec<Template>, SourceError> {
        self.templates(bbox, level, None)
    }

    fn query_lit(&self, bbox: &GeoBox, level: u8, lighting: u8) -> Result<Vec<Template>, SourceError> {
        self.templates(bbox, level, Some(lighting))
    }
}
