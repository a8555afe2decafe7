//! A client of a running `trn serve`, for `trn coverage --server`: the plan
//! goes to `POST /v1/coverage` as it is (the server computes the report, one
//! round trip), and the template footprints the map draws come from the
//! `GET /v1/templates` JSON listing, paged with `offset`. The transport is
//! [`trn_client::Remote`], the one HTTP client of the project; this module
//! only knows these two endpoints' answers. Every error names the URL (and
//! gives the server's `{"error": ...}` message when there is one).

use std::time::Duration;

use serde::Deserialize;
use trn_client::{collect_pages, ClientError, Page, Remote};
use trn_landmark::GeoBox;

use crate::coverage::{CoverageReport, TemplateBox};
use crate::listing::MAX_LIMIT;
use crate::ServerError;

/// A landmark server reached over plain `http://`.
pub struct Client {
    remote: Remote,
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

impl From<ClientError> for ServerError {
    fn from(e: ClientError) -> Self {
        ServerError::Remote { url: e.url, reason: e.reason }
    }
}

impl Client {
    /// A client of the server at `base_url` (e.g. `http://127.0.0.1:8080`);
    /// nothing is sent yet.
    pub fn new(base_url: &str) -> Result<Self, ServerError> {
        Ok(Self { remote: Remote::new(base_url, Duration::from_secs(600))? })
    }

    /// `POST /v1/coverage` with `plan` (the plan file's JSON, sent as it is).
    pub fn coverage(&self, plan: &[u8]) -> Result<CoverageReport, ServerError> {
        let (body, _) = self.remote.post_json("/v1/coverage", plan)?;
        serde_json::from_slice(&body).map_err(|e| {
            remote(&format!("{}/v1/coverage", self.remote.base_url()), format!("not a coverage report: {e}"))
        })
    }

    /// Level and footprint of every template meeting `area` (all levels),
    /// best first, as `LandmarkDb::query_bbox` lists them. Pages from two
    /// database versions (a reload in between) do not make one list: the
    /// listing starts again.
    pub fn template_boxes(&self, area: &GeoBox) -> Result<Vec<TemplateBox>, ServerError> {
        collect_pages(|offset| {
            // `{}` prints the shortest decimal that parses back to the same f64.
            let path = format!(
                "/v1/templates?bbox={},{},{},{}&limit={MAX_LIMIT}&offset={offset}",
                area.min_lon_deg, area.min_lat_deg, area.max_lon_deg, area.max_lat_deg,
            );
            let (body, etag) = self.remote.get(&path, "application/json")?;
            let page: Listing = serde_json::from_slice(&body).map_err(|e| {
                remote(&format!("{}{path}", self.remote.base_url()), format!("not a template listing: {e}"))
            })?;
            Ok(Page { items: page.templates, truncated: page.truncated, etag })
        })
    }
}
