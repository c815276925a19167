//! Serving a version's bytes: `ETag` is the sha256 (the version id), `Range`/`If-Range` give resumable downloads,
//! `If-None-Match` saves re-downloads; the body streams from the object store without buffering the file.

use std::ops::Range;

use axum::body::Body;
use axum::extract::rejection::QueryRejection;
use axum::extract::{Path, Query, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use futures::StreamExt;

use crate::AppState;
use crate::error::ApiError;

/// The download's query: a filter, and the format (`parquet`, the default, or `hdf5`: DSRL's layout, converted once
/// per version on the server and stored).
#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DownloadQuery {
    pub filter: Option<String>,
    pub format: Option<String>,
}

/// What a `Range` header asks of a file of `size` bytes.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RangeRequest {
    /// No usable range: send everything (also for malformed or multi-range headers, which RFC 9110 lets a
    /// server ignore).
    Full,
    Partial(Range<u64>),
    Unsatisfiable,
}

pub fn parse_range(header: &str, size: u64) -> RangeRequest {
    let Some(spec) = header.trim().strip_prefix("bytes=") else {
        return RangeRequest::Full;
    };
    if spec.contains(',') {
        return RangeRequest::Full;
    }
    let Some((first, last)) = spec.split_once('-') else {
        return RangeRequest::Full;
    };
    let (first, last) = (first.trim(), last.trim());
    let parse = |s: &str| s.parse::<u64>().ok();
    match (first.is_empty(), last.is_empty()) {
        // bytes=-N: the last N bytes.
        (true, false) => match parse(last) {
            Some(0) => RangeRequest::Unsatisfiable,
            Some(n) if size > 0 => RangeRequest::Partial(size.saturating_sub(n)..size),
            Some(_) => RangeRequest::Unsatisfiable,
            None => RangeRequest::Full,
        },
        // bytes=A- : from A to the end.
        (false, true) => match parse(first) {
            Some(a) if a < size => RangeRequest::Partial(a..size),
            Some(_) => RangeRequest::Unsatisfiable,
            None => RangeRequest::Full,
        },
        // bytes=A-B, inclusive; B past the end is clamped.
        (false, false) => match (parse(first), parse(last)) {
            (Some(a), Some(b)) if a > b => RangeRequest::Full,
            (Some(a), Some(b)) if a < size => RangeRequest::Partial(a..b.min(size - 1) + 1),
            (Some(_), Some(_)) => RangeRequest::Unsatisfiable,
            _ => RangeRequest::Full,
        },
        (true, true) => RangeRequest::Full,
    }
}

/// Whether an `If-None-Match` value matches the strong `etag` (weak comparison, as RFC 9110 requires here).
fn none_match(value: &HeaderValue, etag: &str) -> bool {
    value.to_str().is_ok_and(|v| {
        v.split(',')
            .map(str::trim)
            .any(|t| t == "*" || t.trim_start_matches("W/") == etag)
    })
}

/// The status to answer with and the byte range to send (`None`: the whole file).
pub(crate) type Answer = (StatusCode, Option<Range<u64>>);

/// The conditional and range part of serving `size` bytes whose strong ETag is `etag`: `None` when
/// `If-None-Match` matches (answer 304 with `response`'s headers); otherwise the status and the byte range to send,
/// with `Content-Range` and `Content-Length` added to `response`. `If-Range` resumes only if the file is still the one
/// the client has part of; otherwise it is sent whole.
pub(crate) fn conditional_range(
    headers: &HeaderMap,
    etag: &str,
    size: u64,
    response: &mut HeaderMap,
) -> Result<Option<Answer>, ApiError> {
    if headers.get(header::IF_NONE_MATCH).is_some_and(|v| none_match(v, etag)) {
        return Ok(None);
    }
    let if_range_ok = headers
        .get(header::IF_RANGE)
        .is_none_or(|v| v.to_str().is_ok_and(|v| v.trim() == etag));
    let range = match headers.get(header::RANGE).and_then(|v| v.to_str().ok()) {
        Some(value) if if_range_ok => parse_range(value, size),
        _ => RangeRequest::Full,
    };
    let (status, byte_range) = match range {
        RangeRequest::Full => (StatusCode::OK, None),
        RangeRequest::Partial(r) => (StatusCode::PARTIAL_CONTENT, Some(r)),
        RangeRequest::Unsatisfiable => return Err(ApiError::RangeNotSatisfiable { size }),
    };
    if let Some(r) = &byte_range {
        let value = format!("bytes {}-{}/{size}", r.start, r.end - 1);
        response.insert(
            header::CONTENT_RANGE,
            HeaderValue::from_str(&value).map_err(ApiError::internal)?,
        );
    }
    let length = byte_range.as_ref().map_or(size, |r| r.end - r.start);
    response.insert(header::CONTENT_LENGTH, HeaderValue::from(length));
    Ok(Some((status, byte_range)))
}

pub async fn download(
    State(state): State<AppState>,
    Path((task, reference)): Path<(String, String)>,
    query: Result<Query<DownloadQuery>, QueryRejection>,
    headers: HeaderMap,
) -> Result<Response, ApiError> {
    let query = query
        .map(|Query(q)| q)
        .map_err(|e| ApiError::InvalidArgument(e.body_text()))?;
    let hdf5 = match query.format.as_deref() {
        None | Some("parquet") => false,
        Some("hdf5") => true,
        Some(other) => {
            return Err(ApiError::InvalidArgument(format!(
                "format {other:?}: the formats are parquet (default) and hdf5"
            )));
        }
    };
    let requester = crate::http::auth::requester(&state, &headers).await;
    let (task, record) = state
        .datasets
        .resolve_filtered(&task, &reference, query.filter.as_deref(), requester)
        .await?;
    // A version id (with or without a filter) names immutable bytes; a tag can move, so caches must revalidate.
    let named_by_id = reference.parse::<dsrl_suite::VersionId>().is_ok();
    let mut response_headers = HeaderMap::new();
    response_headers.insert(
        header::CACHE_CONTROL,
        HeaderValue::from_static(if named_by_id {
            "public, max-age=31536000, immutable"
        } else {
            "no-cache"
        }),
    );
    if hdf5 {
        let file_name = format!("{}.hdf5", task.dataset_file_stem(record.episodes));
        return serve_hdf5_export(&state, &record, &headers, requester, &file_name, response_headers).await;
    }
    let etag = format!("\"{}\"", record.version);
    let size = record.byte_size;
    response_headers.insert(header::ETAG, HeaderValue::from_str(&etag).map_err(ApiError::internal)?);
    response_headers.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    let Some((status, byte_range)) = conditional_range(&headers, &etag, size, &mut response_headers)? else {
        return Ok((StatusCode::NOT_MODIFIED, response_headers).into_response());
    };
    response_headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/vnd.apache.parquet"),
    );
    // The manifest's `file_name`, derived the same way.
    let file_name = format!("{}.parquet", task.dataset_file_stem(record.episodes));
    if let Ok(v) = HeaderValue::from_str(&format!("attachment; filename=\"{file_name}\"")) {
        response_headers.insert(header::CONTENT_DISPOSITION, v);
    }
    let metrics = state.metrics.clone();
    // Counted as being served until the stream ends (or the client goes): the derived-data budget leaves it alone.
    let serving = state.datasets.serving(&record);
    let stream = state.datasets.read(&record, byte_range).await?.inspect(move |chunk| {
        let _ = &serving;
        if let Ok(bytes) = chunk {
            metrics.download_bytes.inc_by(bytes.len() as u64);
        }
    });
    Ok((status, response_headers, Body::from_stream(stream)).into_response())
}

/// Serves a version's HDF5 export (DSRL's layout, converted once per version and stored content-addressed) under
/// `file_name`: its sha256 is the ETag; ranges and conditional requests as for the Parquet file. Shared by
/// `?format=hdf5` and DSRL's own download URLs, which add their headers in `response_headers`.
pub(crate) async fn serve_hdf5_export(
    state: &AppState,
    record: &dsrl_service::db::VersionRecord,
    headers: &HeaderMap,
    requester: crate::datasets::service::Requester,
    file_name: &str,
    mut response_headers: HeaderMap,
) -> Result<Response, ApiError> {
    let (digest, size) = state.datasets.hdf5_export(record, requester).await?;
    let etag = format!("\"{digest}\"");
    let value = |v: &str| HeaderValue::from_str(v).map_err(ApiError::internal);
    response_headers.insert(header::ETAG, value(&etag)?);
    response_headers.insert(header::ACCEPT_RANGES, HeaderValue::from_static("bytes"));
    response_headers.insert("x-dsrl-version", value(&record.version)?);
    let Some((status, byte_range)) = conditional_range(headers, &etag, size, &mut response_headers)? else {
        return Ok((StatusCode::NOT_MODIFIED, response_headers).into_response());
    };
    response_headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/x-hdf5"));
    response_headers.insert(
        header::CONTENT_DISPOSITION,
        value(&format!("attachment; filename=\"{file_name}\""))?,
    );
    let metrics = state.metrics.clone();
    let stream = state
        .datasets
        .read_hdf5(&digest, byte_range)
        .await?
        .inspect(move |chunk| {
            if let Ok(bytes) = chunk {
                metrics.download_bytes.inc_by(bytes.len() as u64);
            }
        });
    Ok((status, response_headers, Body::from_stream(stream)).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ranges() {
        use RangeRequest::*;
        assert_eq!(parse_range("bytes=0-9", 100), Partial(0..10));
        assert_eq!(parse_range("bytes=90-", 100), Partial(90..100));
        assert_eq!(parse_range("bytes=-10", 100), Partial(90..100));
        assert_eq!(parse_range("bytes=-1000", 100), Partial(0..100));
        assert_eq!(parse_range("bytes=95-200", 100), Partial(95..100));
        assert_eq!(parse_range("bytes=100-", 100), Unsatisfiable);
        assert_eq!(parse_range("bytes=100-200", 100), Unsatisfiable);
        assert_eq!(parse_range("bytes=-0", 100), Unsatisfiable);
        assert_eq!(parse_range("bytes=0-", 0), Unsatisfiable);
        // Malformed or multi-range: ignored, the whole file is sent.
        assert_eq!(parse_range("bytes=9-1", 100), Full);
        assert_eq!(parse_range("bytes=0-1,5-6", 100), Full);
        assert_eq!(parse_range("items=0-1", 100), Full);
        assert_eq!(parse_range("bytes=a-b", 100), Full);
    }

    #[test]
    fn if_none_match() {
        let etag = "\"abc\"";
        assert!(none_match(&HeaderValue::from_static("\"abc\""), etag));
        assert!(none_match(&HeaderValue::from_static("W/\"abc\""), etag));
        assert!(none_match(&HeaderValue::from_static("\"x\", \"abc\""), etag));
        assert!(none_match(&HeaderValue::from_static("*"), etag));
        assert!(!none_match(&HeaderValue::from_static("\"abd\""), etag));
    }
}
