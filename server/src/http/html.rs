//! What every HTML page of the site shares (the dataset browser, the leaderboard, a submission's results): one
//! layout with the navigation and one style sheet, and HTML escaping.

/// The site's style: readable tables, unsafe entries in red, no script.
pub const STYLE: &str = "body{font-family:sans-serif;margin:2em;max-width:75em}table{border-collapse:collapse;\
    margin:1em 0}td,th{border:1px solid #ccc;padding:.3em .6em;text-align:right;vertical-align:middle}\
    td.name,th.name{text-align:left}pre{background:#f4f4f4;padding:.6em;overflow-x:auto}\
    .missing{color:#888}.error{color:#a33}tr.unsafe td{color:#a33}";

/// What every page may load: its own inline style, images and forms from this server, nothing else (the pages have
/// no script), and no framing by other sites.
pub const CONTENT_SECURITY_POLICY: &str = "default-src 'none'; style-src 'unsafe-inline'; img-src 'self' data:; \
                                           form-action 'self'; base-uri 'none'; frame-ancestors 'none'";

/// Adds the defensive headers: `X-Content-Type-Options: nosniff` on every answer, and on HTML pages the content
/// security policy, `X-Frame-Options: DENY` and `Referrer-Policy: no-referrer`. Escaping already keeps injected
/// text inert; these keep a future escaping mistake from becoming a script or a clickjacking frame.
pub async fn defensive_headers(mut response: axum::response::Response) -> axum::response::Response {
    use axum::http::{HeaderValue, header};
    let html = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|t| t.starts_with("text/html"));
    let headers = response.headers_mut();
    headers.insert(header::X_CONTENT_TYPE_OPTIONS, HeaderValue::from_static("nosniff"));
    if html {
        headers.insert(
            header::CONTENT_SECURITY_POLICY,
            HeaderValue::from_static(CONTENT_SECURITY_POLICY),
        );
        headers.insert(header::X_FRAME_OPTIONS, HeaderValue::from_static("DENY"));
        headers.insert(header::REFERRER_POLICY, HeaderValue::from_static("no-referrer"));
    }
    response
}

pub fn escape(text: &str) -> String {
    text.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
        .replace('"', "&quot;")
        .replace('\'', "&#39;")
}

/// A whole page: `title`, the site's navigation (datasets, leaderboard, API), then `body`.
pub fn page(title: &str, body: &str) -> String {
    format!(
        "<!doctype html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{}</title><style>{STYLE}</style>\
         </head><body>\n<nav><p><a href=\"/\">datasets</a> · <a href=\"/leaderboard\">leaderboard</a> · \
         <a href=\"/openapi.json\">API</a></p></nav>\n{body}</body></html>\n",
        escape(title)
    )
}
