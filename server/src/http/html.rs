//! What every HTML page of the site shares (the dataset browser, the leaderboard, a submission's results): one
//! layout with the navigation and one style sheet, and HTML escaping.

/// The site's style: readable tables, unsafe entries in red, no script.
pub const STYLE: &str = "body{font-family:sans-serif;margin:2em;max-width:75em}table{border-collapse:collapse;\
    margin:1em 0}td,th{border:1px solid #ccc;padding:.3em .6em;text-align:right;vertical-align:middle}\
    td.name,th.name{text-align:left}pre{background:#f4f4f4;padding:.6em;overflow-x:auto}\
    .missing{color:#888}.error{color:#a33}tr.unsafe td{color:#a33}";

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
