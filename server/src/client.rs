//! A client of a running `trn serve`, for `trn coverage --server`: the plan
//! goes to `POST /v1/coverage` as it is (the server computes the report, one
//! round trip), and the template footprints the map draws come from the
//! `GET /v1/templates` JSON listing, paged with `offset`. Only the HTTP side:
//! the report and the map are [`crate::coverage`]'s. Every error names the URL
//! (and gives the server's `{"error": ...}` message when there is one).

use std::time::Duration;

use serde::Deserialize;
use trn_landmark::GeoBox;
use trn_navigator::http_source::{collect_pages, Page};

use crate::api::MAX_LIMIT;
use crate::coverage::{CoverageReport, TemplateBox};
use crate::ServerError;

/// Largest answer read (bytes): a coverage report of 10 000 points, or a page
/// of 10 000 template summaries, is a few MB.
const MAX_BODY_BYTES: u64 = 256 << 20;

/// A landmark server reached over plain `http://`.
pub struct Client {
    agent: ureq::Agent,
    base: String,
}

#[derive(Deserialize)]
struct ErrorJson {
    error: String,
}

/// A page of the `GET /v1/templates` JSON listing (other fields ignored).
#[derive(Deserialize)]
struct Listing {
    templates: Vec<TemplateBox>,
    truncated: bool,
}

fn remote(url: &str, reason: impl Into<String>) -> ServerError {
    ServerError::Remote { url: url.to_owned(), reason: reason.into() }
}

impl Client {
    /// A client of the server at `base_url` (e.g. `http://127.0.0.1:8080`);
    /// nothing is sent yet.
    pub fn new(base_url: &str) -> Result<Self, ServerError> {
        let base = base_url.trim_end_matches('/').to_owned();
        if !base.starts_with("http://") || base.len() == "http://".len() {
            return Err(remote(
                base_url,
                "not a landmark server URL (give http://host:port, e.g. http://127.0.0.1:8080)",
            ));
        }
        let agent = ureq::Agent::config_builder()
            .http_status_as_error(false)
            .timeout_global(Some(Duration::from_secs(600)))
            .build()
            .into();
        Ok(Self { agent, base })
    }

    /// `POST /v1/coverage` with `plan` (the plan file's JSON, sent as it is).
    pub fn coverage(&self, plan: &[u8]) -> Result<CoverageReport, ServerError> {
        let url = format!("{}/v1/coverage", self.base);
        let resp = self
            .agent
            .post(&url)
            .header("Content-Type", "application/json")
            .header("Accept", "application/json")
            .send(plan);
        let (body, _) = answer(&url, resp)?;
        serde_json::from_slice(&body).map_err(|e| remote(&url, format!("not a coverage report: {e}")))
    }

    /// Level and footprint of every template meeting `area` (all levels),
    /// best first, as `LandmarkDb::query_bbox` lists them. Pages from two
    /// database versions (a reload in between) do not make one list: the
    /// listing starts again.
    pub fn template_boxes(&self, area: &GeoBox) -> Result<Vec<TemplateBox>, ServerError> {
        collect_pages(|offset| {
            // `{}` prints the shortest decimal that parses back to the same f64.
            let url = format!(
                "{}/v1/templates?bbox={},{},{},{}&limit={MAX_LIMIT}&offset={offset}",
                self.base, area.min_lon_deg, area.min_lat_deg, area.max_lon_deg, area.max_lat_deg,
            );
            let resp = self.agent.get(&url).header("Accept", "application/json").call();
            let (body, etag) = answer(&url, resp)?;
            let page: Listing = serde_json::from_slice(&body)
                .map_err(|e| remote(&url, format!("not a template listing: {e}")))?;
            Ok(Page { items: page.templates, truncated: page.truncated, etag })
        })
    }
}

/// The body and ETag of a 200; otherwise an error naming `url` with the
/// server's message (or the transport's).
fn answer(
    url: &str,
    resp: Result<ureq::http::Response<ureq::Body>, ureq::Error>,
) -> Result<(Vec<u8>, Option<String>), ServerError> {
    let mut resp = resp.map_err(|e| remote(url, format!("no answer from the landmark server ({e})")))?;
    let status = resp.status();
    let etag = resp.headers().get("etag").and_then(|v| v.to_str().ok()).map(str::to_owned);
    let body = resp
        .body_mut()
        .with_config()
        .limit(MAX_BODY_BYTES)
        .read_to_vec()
        .map_err(|e| remote(url, format!("reading the answer: {e}")))?;
    if status != 200 {
        let why = serde_json::from_slice::<ErrorJson>(&body)
            .map(|e| e.error)
            .unwrap_or_else(|_| String::from_utf8_lossy(&body).chars().take(200).collect());
        return Err(remote(url, format!("HTTP {status}: {why}")));
    }
    Ok((body, etag))
}
