-- Uploads converted in the background (POST .../versions?background=true): the upload's state, so that a client
-- waits for a server that is still converting instead of timing out, and a retried upload of the same bytes
-- (task, upload_sha256) follows the conversion already under way instead of starting another.
-- state: converting, done (result holds the ingest's answer) or failed (error_code, error_message);
-- updated_ms: the converting server's heartbeat (a stale one means the conversion was interrupted).
CREATE TABLE uploads (
    id TEXT PRIMARY KEY,
    task TEXT NOT NULL,
    upload_sha256 TEXT NOT NULL,
    file_name TEXT NOT NULL,
    byte_size INTEGER NOT NULL,
    state TEXT NOT NULL,
    result TEXT,
    error_code TEXT,
    error_message TEXT,
    created_ms INTEGER NOT NULL,
    updated_ms INTEGER NOT NULL
);
CREATE INDEX uploads_by_file ON uploads (task, upload_sha256);
