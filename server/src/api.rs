//! The HTTP API: handlers, their parameters and answers, and the OpenAPI document.

use std::sync::Arc;

use axum::extract::rejection::{JsonRejection, PathRejection, QueryRejection};
use axum::extract::{FromRequest, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};
use trn_landmark::{wire, GeoBox};
use trn_store::BboxQuery;
use utoipa::{IntoParams, OpenApi, ToSchema};

use crate::coverage::{self, CoverageReport, CoverageRequest, FootprintRequest, FootprintResponse};
use crate::db::{store_error, Info, Store};
use crate::error::{ApiError, ErrorBody};
use crate::listing::{TemplateSummary, DEFAULT_LIMIT, GEOJSON, MAX_LIMIT, MAX_OFFSET};
use crate::AppState;

/// `GET /v1/templates` answer (JSON).
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct TemplatesResponse {
    pub templates: Vec<TemplateSummary>,
    /// Whether more templates match than `limit` (ask again with `offset`).
    pub truncated: bool,
}

/// `GET /v1/templates` parameters; all as text so each gets its own message.
#[derive(Clone, Debug, Default, Deserialize, IntoParams)]
#[serde(deny_unknown_fields)]
#[into_params(parameter_in = Query)]
pub struct BboxParams {
    /// `min_lon,min_lat,max_lon,max_lat` in degrees (WGS84); `min_lon > max_lon`
    /// crosses the antimeridian.
    #[param(example = "-105.6,40.2,-105.4,40.4")]
    pub bbox: Option<String>,
    /// Only this pyramid level (0..=255), or `min..max` (inclusive).
    pub level: Option<String>,
    /// Most templates answered (1..=10000, default 1000); best first.
    pub limit: Option<String>,
    /// Skip this many of the best first (paging; default 0).
    pub offset: Option<String>,
    /// Only templates of this lighting (0..=255: 0 the ortho as imaged, k
    /// the database's k-th baked sun); default all.
    pub lighting: Option<String>,
}

/// The checked form of [`BboxParams`].
#[derive(Clone, Debug, PartialEq)]
pub struct TemplatesQuery {
    pub bbox: GeoBox,
    pub levels: Option<std::ops::RangeInclusive<u8>>,
    pub limit: usize,
    pub offset: usize,
    pub lighting: Option<u8>,
}

/// Parses `min_lon,min_lat,max_lon,max_lat`.
pub fn parse_bbox(text: &str) -> Result<GeoBox, ApiError> {
    let names = ["min_lon", "min_lat", "max_lon", "max_lat"];
    let parts: Vec<&str> = text.split(',').collect();
    if parts.len() != 4 {
        return Err(ApiError::bad_request(format!(
            "bbox: expected min_lon,min_lat,max_lon,max_lat (4 numbers in degrees), got {} value(s)",
            parts.len()
        )));
    }
    let mut v = [0.0; 4];
    for (i, p) in parts.iter().enumerate() {
        let shown: String = p.chars().take(40).collect();
        v[i] = p
            .trim()
            .parse::<f64>()
            .map_err(|_| ApiError::bad_request(format!("bbox: {} {shown:?} is not a number", names[i])))?;
        if !v[i].is_finite() {
            return Err(ApiError::bad_request(format!(
                "bbox: {} is {} (not a finite number)",
                names[i], v[i]
            )));
        }
        let range = if i % 2 == 0 { 180.0 } else { 90.0 };
        if v[i].abs() > range {
            return Err(ApiError::bad_request(format!(
                "bbox: {} {} is out of range [-{range}, {range}] degrees",
                names[i], v[i]
            )));
        }
    }
    if v[1] > v[3] {
        return Err(ApiError::bad_request(format!(
            "bbox: min_lat {} is above max_lat {} (reversed latitudes; only longitudes may wrap, \
             across the antimeridian)",
            v[1], v[3]
        )));
    }
    Ok(GeoBox::new(v[0], v[1], v[2], v[3]))
}

fn parse_number<T>(name: &str, text: &str, range: std::ops::RangeInclusive<T>) -> Result<T, ApiError>
where
    T: std::str::FromStr + PartialOrd + std::fmt::Display,
{
    let shown: String = text.chars().take(40).collect();
    let bad = || {
        ApiError::bad_request(format!(
            "{name}: {shown:?} is not an integer in {}..={}",
            range.start(),
            range.end()
        ))
    };
    let v = text.trim().parse::<T>().map_err(|_| bad())?;
    if !range.contains(&v) {
        return Err(bad());
    }
    Ok(v)
}

impl TemplatesQuery {
    /// This query's page of `all` (best first, at most `offset + limit + 1`
    /// long), and whether the list goes on after it.
    fn page<T>(&self, all: Vec<T>) -> (Vec<T>, bool) {
        let truncated = all.len() > self.offset + self.limit;
        (all.into_iter().skip(self.offset).take(self.limit).collect(), truncated)
    }
}

impl BboxParams {
    pub fn check(&self) -> Result<TemplatesQuery, ApiError> {
        let bbox = parse_bbox(self.bbox.as_deref().ok_or_else(|| {
            ApiError::bad_request("bbox: missing (bbox=min_lon,min_lat,max_lon,max_lat in degrees)")
        })?)?;
        let levels = match self.level.as_deref() {
            None => None,
            Some(l) => Some(match l.split_once("..") {
                Some((a, b)) => {
                    let (a, b) = (parse_number("level", a, 0..=255u8)?, parse_number("level", b, 0..=255u8)?);
                    if a > b {
                        return Err(ApiError::bad_request(format!("level: range {a}..{b} is reversed")));
                    }
                    a..=b
                }
                None => {
                    let v = parse_number("level", l, 0..=255u8)?;
                    v..=v
                }
            }),
        };
        let limit = match self.limit.as_deref() {
            None => DEFAULT_LIMIT,
            Some(l) => parse_number("limit", l, 1..=MAX_LIMIT)?,
        };
        let offset = match self.offset.as_deref() {
            None => 0,
            Some(o) => parse_number("offset", o, 0..=MAX_OFFSET)?,
        };
        let lighting =
            self.lighting.as_deref().map(|l| parse_number("lighting", l, 0..=255u8)).transpose()?;
        Ok(TemplatesQuery { bbox, levels, limit, offset, lighting })
    }
}

/// Whether the client asked for the binary encoding.
fn wants_binary(headers: &HeaderMap) -> bool {
    accepts(headers, wire::MEDIA_TYPE)
}

fn accepts(headers: &HeaderMap, media: &str) -> bool {
    headers
        .get_all(header::ACCEPT)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|m| m.split(';').next().is_some_and(|m| m.trim().eq_ignore_ascii_case(media)))
}

/// Whether `If-None-Match` holds `etag` (weak comparison) or `*`.
fn not_modified(headers: &HeaderMap, etag: &str) -> bool {
    let strip = |t: &str| t.trim().trim_start_matches("W/").to_owned();
    let ours = strip(etag);
    headers
        .get_all(header::IF_NONE_MATCH)
        .iter()
        .filter_map(|v| v.to_str().ok())
        .flat_map(|v| v.split(','))
        .any(|t| t.trim() == "*" || strip(t) == ours)
}

/// Adds the ETag and the caching headers; a 304 when the client has it.
fn cached(headers: &HeaderMap, etag: &str, make: impl FnOnce() -> Response) -> Response {
    let mut r = if not_modified(headers, etag) { StatusCode::NOT_MODIFIED.into_response() } else { make() };
    let h = r.headers_mut();
    if let Ok(v) = HeaderValue::from_str(etag) {
        h.insert(header::ETAG, v);
    }
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    h.insert(header::VARY, HeaderValue::from_static("accept, accept-encoding"));
    r
}

fn body(content_type: &'static str, bytes: Vec<u8>) -> Response {
    ([(header::CONTENT_TYPE, HeaderValue::from_static(content_type))], bytes).into_response()
}

fn json<T: Serialize>(v: &T) -> Result<Vec<u8>, ApiError> {
    serde_json::to_vec(v).map_err(|e| ApiError::internal(format!("serialising the answer: {e}")))
}

/// A JSON body whose rejections (syntax, type, size, content type) answer with
/// the JSON error body and the rejection's status.
pub struct JsonBody<T>(pub T);

impl<S, T> FromRequest<S> for JsonBody<T>
where
    axum::Json<T>: FromRequest<S, Rejection = JsonRejection>,
    S: Send + Sync,
{
    type Rejection = ApiError;

    async fn from_request(req: Request, state: &S) -> Result<Self, Self::Rejection> {
        match axum::Json::<T>::from_request(req, state).await {
            Ok(axum::Json(v)) => Ok(Self(v)),
            Err(r) => Err(ApiError::new(r.status(), r.body_text())),
        }
    }
}

#[utoipa::path(get, path = "/health", responses((status = 200, description = "Serving", body = Object)))]
pub async fn health(State(state): State<Arc<AppState>>) -> Response {
    let db = state.db.load();
    axum::Json(serde_json::json!({"status": "ok", "database_id": db.info.database_id})).into_response()
}

#[utoipa::path(
    get,
    path = "/v1/info",
    responses((status = 200, body = Info), (status = 304, description = "Not modified (If-None-Match)"))
)]
pub async fn info(State(state): State<Arc<AppState>>, headers: HeaderMap) -> Response {
    let db = state.db.load_full();
    cached(&headers, &db.etag, || match json(&db.info) {
        Ok(b) => body("application/json", b),
        Err(e) => e.into_response(),
    })
}

#[utoipa::path(
    get,
    path = "/v1/templates",
    params(BboxParams),
    responses(
        (status = 200, description = "Best first. JSON, or the binary encoding with `Accept: application/vnd.trn.templates`",
         body = TemplatesResponse),
        (status = 304, description = "Not modified (If-None-Match)"),
        (status = 400, body = ErrorBody),
    )
)]
pub async fn templates(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    params: Result<Query<BboxParams>, QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(params) = params.map_err(|r| ApiError::bad_request(r.body_text()))?;
    let q = params.check()?;
    // One more than the page tells whether the list goes on.
    let query = BboxQuery {
        bbox: q.bbox,
        levels: q.levels.clone(),
        limit: Some(q.offset + q.limit + 1),
        lighting: q.lighting,
    };
    let db = state.db.load_full();
    if let (Some(cat), true) = (db.catalogue(), wants_binary(&headers)) {
        // From memory the records are already encoded: the answer is their
        // copy, a fraction of a millisecond, made right here rather than
        // through the blocking pool (a thread hand-over each way).
        let etag = representation_etag(&db.etag, true);
        return Ok(cached(&headers, &etag, || {
            let (page, truncated) = q.page(cat.query(&query));
            let mut out = Vec::with_capacity(wire::HEADER_LEN + page.iter().map(|r| r.len()).sum::<usize>());
            wire::write_header(&mut out, page.len() as u32, truncated);
            for r in page {
                out.extend_from_slice(r);
            }
            body(wire::MEDIA_TYPE, out)
        }));
    }
    read_answer(&state, &headers, move |store, binary| {
        let (list, truncated) = q.page(store.query_bbox(&query).map_err(store_error)?);
        if binary {
            Ok(wire::encode(&list, truncated))
        } else {
            json(&TemplatesResponse {
                templates: list.iter().map(TemplateSummary::from).collect(),
                truncated,
            })
        }
    })
    .await
}

/// The binary representation has an ETag of its own (`W/"<id>-b"`).
fn representation_etag(etag: &str, binary: bool) -> String {
    if binary {
        format!("{}-b\"", etag.trim_end_matches('"'))
    } else {
        etag.to_owned()
    }
}

/// Answers a read of the database in JSON or, when asked for, the binary
/// encoding: a 304 without running `query` when the client's ETag is current
/// (the binary representation has its own), else `query`'s bytes with the ETag.
async fn read_answer(
    state: &AppState,
    headers: &HeaderMap,
    query: impl FnOnce(Store<'_>, bool) -> Result<Vec<u8>, ApiError> + Send + 'static,
) -> Result<Response, ApiError> {
    let db = state.db.load_full();
    let binary = wants_binary(headers);
    let etag = representation_etag(&db.etag, binary);
    if not_modified(headers, &etag) {
        return Ok(cached(headers, &etag, || StatusCode::NOT_MODIFIED.into_response()));
    }
    let bytes = db.run(move |store| query(store, binary)).await?;
    let ct = if binary { wire::MEDIA_TYPE } else { "application/json" };
    Ok(cached(headers, &etag, || body(ct, bytes)))
}

#[utoipa::path(
    get,
    path = "/v1/templates/{id}",
    params(("id" = i64, Path, description = "Template id")),
    responses(
        (status = 200, description = "The whole template (pixels and height grid included) as JSON, or a \
         one-template list in the binary encoding", body = Object),
        (status = 400, body = ErrorBody),
        (status = 404, body = ErrorBody),
    )
)]
pub async fn template(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    id: Result<Path<String>, PathRejection>,
) -> Result<Response, ApiError> {
    let Path(id) = id.map_err(|r| ApiError::bad_request(r.body_text()))?;
    let shown: String = id.chars().take(40).collect();
    let id: i64 = id
        .parse()
        .map_err(|_| ApiError::bad_request(format!("id: {shown:?} is not a template id (an integer)")))?;
    read_answer(&state, &headers, move |store, binary| {
        let t = store
            .conn
            .template(id)
            .map_err(store_error)?
            .ok_or_else(|| ApiError::not_found(format!("id: no template {id} in this database")))?;
        if binary {
            Ok(wire::encode([&t], false))
        } else {
            json(&t)
        }
    })
    .await
}

#[utoipa::path(
    post,
    path = "/v1/footprint",
    request_body = FootprintRequest,
    responses(
        (status = 200, body = FootprintResponse),
        (status = 400, body = ErrorBody),
        (status = 422, body = ErrorBody),
    )
)]
pub async fn footprint(
    State(state): State<Arc<AppState>>,
    JsonBody(req): JsonBody<FootprintRequest>,
) -> Result<Response, ApiError> {
    coverage::check_footprint(&req)?;
    let db = state.db.load_full();
    let levels = db.levels.clone();
    let bytes = db
        .run(move |store| {
            let r = coverage::footprint_query(&store, &levels, &req)?;
            json(&r)
        })
        .await?;
    Ok(body("application/json", bytes))
}

#[utoipa::path(
    post,
    path = "/v1/coverage",
    request_body = CoverageRequest,
    responses(
        (status = 200, description = "JSON report, or GeoJSON with `Accept: application/geo+json`",
         body = CoverageReport),
        (status = 400, body = ErrorBody),
        (status = 413, body = ErrorBody),
        (status = 422, body = ErrorBody),
    )
)]
pub async fn coverage(
    State(state): State<Arc<AppState>>,
    headers: HeaderMap,
    JsonBody(req): JsonBody<CoverageRequest>,
) -> Result<Response, ApiError> {
    coverage::plan_poses(&req)?;
    let geojson = accepts(&headers, GEOJSON);
    let db = state.db.load_full();
    let levels = db.levels.clone();
    let bytes = db
        .run(move |store| {
            let r = coverage::coverage_query(&store, &levels, &req)?;
            if geojson {
                json(&coverage::to_geojson(&r))
            } else {
                json(&r)
            }
        })
        .await?;
    Ok(body(if geojson { GEOJSON } else { "application/json" }, bytes))
}

#[derive(OpenApi)]
#[openapi(
    info(
        title = "trn landmark server",
        description = "Landmark templates for terrain relative navigation: \
        bounding-box, footprint and coverage queries over one immutable landmark database. Errors are \
        `{\"error\": \"...\"}` with a 4xx status naming the parameter at fault. The binary template \
        encoding (`Accept: application/vnd.trn.templates`) is specified in docs/SERVER.md."
    ),
    paths(health, info, templates, template, footprint, coverage),
    components(schemas(
        ErrorBody,
        TemplateSummary,
        TemplatesResponse,
        Info,
        FootprintRequest,
        FootprintResponse,
        CoverageRequest,
        CoverageReport,
        coverage::CameraIn,
        coverage::PoseIn,
        coverage::WaypointIn,
        coverage::AttitudeRule,
        coverage::LatLon,
        coverage::CoveragePoint,
        coverage::Stretch
    ))
)]
pub struct ApiDoc;

pub async fn openapi() -> Response {
    match ApiDoc::openapi().to_json() {
        Ok(s) => body("application/json", s.into_bytes()),
        Err(e) => ApiError::internal(format!("OpenAPI document: {e}")).into_response(),
    }
}

/// Unknown paths.
pub async fn not_found(req: Request) -> ApiError {
    let path: String = req.uri().path().chars().take(200).collect();
    ApiError::not_found(format!("no such endpoint: {} {path} (see /openapi.json)", req.method()))
}
