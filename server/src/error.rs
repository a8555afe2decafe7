//! The server's errors: [`ServerError`] for what stops `trn serve` (it cannot
//! open the database, bind the address) or `trn coverage` (or a server it asks),
//! [`ApiError`] for one request's answer.

use std::path::PathBuf;

use axum::http::{header, HeaderValue, StatusCode};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use utoipa::ToSchema;

/// Why the server cannot start or go on; names the file or address.
#[derive(Debug, thiserror::Error)]
pub enum ServerError {
    #[error(transparent)]
    Store(#[from] trn_store::StoreError),
    #[error("{path}: {reason}", path = path.display())]
    File { path: PathBuf, reason: String },
    #[error("--listen {addr}: {reason}")]
    Listen { addr: String, reason: String },
    /// A landmark server asked by `trn coverage --server` (the URL asked).
    #[error("{url}: {reason}")]
    Remote { url: String, reason: String },
    #[error("{0}")]
    Other(String),
}

/// The JSON body of every error response.
#[derive(Clone, Debug, Serialize, ToSchema)]
pub struct ErrorBody {
    /// What was wrong, naming the parameter or field at fault.
    #[schema(example = "bbox: min_lat_deg 50 is above max_lat_deg 40 (reversed latitudes)")]
    pub error: String,
}

/// An error answer: a status and a message (`{"error": message}`).
#[derive(Clone, Debug, PartialEq)]
pub struct ApiError {
    pub status: StatusCode,
    pub message: String,
}

impl ApiError {
    pub fn new(status: StatusCode, message: impl Into<String>) -> Self {
        Self { status, message: message.into() }
    }

    pub fn bad_request(message: impl Into<String>) -> Self {
        Self::new(StatusCode::BAD_REQUEST, message)
    }

    pub fn unprocessable(message: impl Into<String>) -> Self {
        Self::new(StatusCode::UNPROCESSABLE_ENTITY, message)
    }

    pub fn not_found(message: impl Into<String>) -> Self {
        Self::new(StatusCode::NOT_FOUND, message)
    }

    /// A failure on our side (database read); logged, and answered with 503 so
    /// clients and load balancers retry elsewhere.
    pub fn internal(message: impl Into<String>) -> Self {
        let message = message.into();
        tracing::error!("{message}");
        Self::new(StatusCode::SERVICE_UNAVAILABLE, message)
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        json_error(self.status, &self.message)
    }
}

/// `{"error": message}` with `status`.
pub fn json_error(status: StatusCode, message: &str) -> Response {
    let body = serde_json::to_vec(&ErrorBody { error: message.to_owned() })
        .unwrap_or_else(|_| b"{\"error\":\"unprintable error\"}".to_vec());
    let mut r = (status, body).into_response();
    r.headers_mut().insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
    r
}

impl std::fmt::Display for ApiError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl std::error::Error for ApiError {}
