//! The REST API of a dsrl server: the catalog, versions and manifests, byte-range downloads, admin ingest and
//! tags. Errors come back as [`ClientError::Server`] with the server's code, message and suggestions.

use std::path::Path;
use std::time::Duration;

use dsrl_suite::{HostedVersion, Manifest, Task};
use futures::StreamExt;
use reqwest::header::{AUTHORIZATION, CONTENT_LENGTH, CONTENT_TYPE, IF_RANGE, RANGE};
use reqwest::{Response, StatusCode};
use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use tokio::io::AsyncReadExt;

use crate::error::{ClientError, ErrorDocument};

/// Default server when neither `--server` nor `DSRL_SERVER` is set.
pub const DEFAULT_SERVER: &str = "http://127.0.0.1:7070";

/// A catalog entry: the task and its hosted versions, newest first.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TaskEntry {
    #[serde(flatten)]
    pub task: Task,
    pub versions: Vec<HostedVersion>,
}

#[derive(Debug, Deserialize)]
struct TaskList {
    tasks: Vec<TaskEntry>,
}

#[derive(Debug, Deserialize)]
struct VersionList {
    versions: Vec<HostedVersion>,
}

/// The server's answer to an ingest.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct IngestResult {
    /// `false`: identical data was already hosted.
    pub created: bool,
    pub task: String,
    pub version: HostedVersion,
    pub moved_tags: Vec<String>,
    pub manifest_url: String,
    pub download_url: String,
}

/// `GET /v1/server`: what a client needs to know before uploading.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct ServerInfo {
    pub name: String,
    pub version: String,
    pub max_upload_bytes: u64,
    /// Whether the token this client sent is a valid admin token.
    pub admin: bool,
}

#[derive(Debug, Clone, Default)]
pub struct IngestOptions {
    pub tags: Vec<String>,
    /// `paper` for MetaDrive files in the paper's 261-feature observation space.
    pub observation_space: Option<String>,
    pub license: Option<String>,
    /// Recipe provenance as JSON (`{"kind": "recipe", ...}`), for data the pipeline built.
    pub provenance_json: Option<String>,
    /// Leave `latest` where it is (a release imported beside the hosted data).
    pub keep_latest: bool,
}

#[derive(Debug, Clone)]
pub struct Client {
    base: String,
    http: reqwest::Client,
    token: Option<String>,
}

impl Client {
    pub fn new(base: &str) -> Result<Client, ClientError> {
        let base = base.trim_end_matches('/').to_owned();
        if !(base.starts_with("http://") || base.starts_with("https://")) {
            return Err(ClientError::Usage(format!(
                "server URL {base:?} must start with http:// or https://"
            )));
        }
        let http = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(10))
            // A stalled connection fails instead of hanging; a slow but moving download is fine.
            .read_timeout(read_timeout())
            .user_agent(concat!("dsrl-client/", env!("CARGO_PKG_VERSION")))
            .build()
            .map_err(|e| ClientError::Protocol(format!("building the HTTP client: {e}")))?;
        Ok(Client {
            base,
            http,
            token: None,
        })
    }

    pub fn with_token(mut self, token: Option<String>) -> Self {
        self.token = token;
        self
    }

    pub fn base(&self) -> &str {
        &self.base
    }

    fn url(&self, path: &str) -> String {
        format!("{}{path}", self.base)
    }

    async fn send(&self, request: reqwest::RequestBuilder) -> Result<Response, ClientError> {
        let what = request
            .try_clone()
            .and_then(|r| r.build().ok())
            .map(|r| format!("{} {}", r.method(), r.url().path()))
            .unwrap_or_else(|| "the request".to_owned());
        let response = request
            .send()
            .await
            .map_err(|source| self.transport_error(source, &what))?;
        check(response).await
    }

    /// A transport failure, named for what it was: a timeout (the server was reached but did not answer in time)
    /// is not "cannot reach".
    fn transport_error(&self, source: reqwest::Error, what: &str) -> ClientError {
        if source.is_builder() {
            // Nothing was sent: the request itself could not be made (a header value that is not one, say).
            return ClientError::Protocol(format!("{what} could not be sent: {source}"));
        }
        if source.is_timeout() {
            ClientError::Timeout {
                url: self.base.clone(),
                seconds: read_timeout().as_secs(),
                what: format!("{what} ({source})"),
            }
        } else {
            ClientError::Unreachable {
                url: self.base.clone(),
                source,
            }
        }
    }

    async fn get_json<T: DeserializeOwned>(&self, path: &str) -> Result<T, ClientError> {
        let response = self.send(self.http.get(self.url(path))).await?;
        response
            .json()
            .await
            .map_err(|e| ClientError::Protocol(format!("GET {path}: {e}")))
    }

    fn admin(&self, request: reqwest::RequestBuilder) -> Result<reqwest::RequestBuilder, ClientError> {
        Ok(request.header(AUTHORIZATION, format!("Bearer {}", self.require_token()?)))
    }

    fn require_token(&self) -> Result<&str, ClientError> {
        self.token.as_deref().ok_or_else(|| {
            ClientError::Usage(
                "admin operations need a token: pass --token or set DSRL_ADMIN_TOKEN (a local server keeps it in \
                 ~/.dsrl/server/admin-token)"
                    .into(),
            )
        })
    }

    /// The server's version and limits, and whether the client's token is the admin token.
    pub async fn server_info(&self) -> Result<ServerInfo, ClientError> {
        let mut request = self.http.get(self.url("/v1/server"));
        if let Some(token) = &self.token {
            request = request.header(AUTHORIZATION, format!("Bearer {token}"));
        }
        let response = self.send(request).await?;
        response
            .json()
            .await
            .map_err(|e| ClientError::Protocol(format!("GET /v1/server: {e}")))
    }

    pub async fn task(&self, task: &str) -> Result<TaskEntry, ClientError> {
        self.get_json(&format!("/v1/tasks/{}", seg(task))).await
    }

    pub async fn tasks(&self) -> Result<Vec<TaskEntry>, ClientError> {
        Ok(self.get_json::<TaskList>("/v1/tasks").await?.tasks)
    }

    pub async fn versions(&self, task: &str) -> Result<Vec<HostedVersion>, ClientError> {
        Ok(self
            .get_json::<VersionList>(&format!("/v1/datasets/{}/versions", seg(task)))
            .await?
            .versions)
    }

    /// The manifest of a version (by id or tag) and its JSON text as served.
    /// The manifest of a version (by id or tag), or with `filter` of the filtered version the server makes from
    /// it; and its JSON text as served.
    pub async fn manifest(
        &self,
        task: &str,
        reference: &str,
        filter: Option<&str>,
    ) -> Result<(Manifest, String), ClientError> {
        let path = format!("/v1/datasets/{}/versions/{}", seg(task), seg(reference));
        let response = self.send(with_filter(self.http.get(self.url(&path)), filter)).await?;
        let text = response
            .text()
            .await
            .map_err(|e| ClientError::Protocol(format!("GET {path}: {e}")))?;
        let manifest = serde_json::from_str(&text).map_err(|e| ClientError::Protocol(format!("manifest: {e}")))?;
        Ok((manifest, text))
    }

    /// The cost-reward plot of a version (or of what `filter` does to it) as SVG.
    pub async fn plot_svg(&self, task: &str, reference: &str, filter: Option<&str>) -> Result<String, ClientError> {
        let path = format!("/v1/datasets/{}/versions/{}/plot.svg", seg(task), seg(reference));
        let response = self.send(with_filter(self.http.get(self.url(&path)), filter)).await?;
        response
            .text()
            .await
            .map_err(|e| ClientError::Protocol(format!("GET {path}: {e}")))
    }

    /// Starts downloading `version` from byte `offset`. The `If-Range` condition makes the server send the whole
    /// file (200) instead of the range (206) if the version's bytes are not the ones the partial file holds.
    pub async fn download(&self, task: &str, version: &str, offset: u64) -> Result<Response, ClientError> {
        let path = format!("/v1/datasets/{}/versions/{}/download", seg(task), seg(version));
        let mut request = self.http.get(self.url(&path));
        if offset > 0 {
            request = request
                .header(RANGE, format!("bytes={offset}-"))
                .header(IF_RANGE, format!("\"{version}\""));
        }
        self.send(request).await
    }

    /// Starts downloading `version`'s HDF5 export (DSRL's layout, made once on the server and stored); its ETag is the
    /// export's sha256.
    pub async fn download_hdf5(&self, task: &str, version: &str) -> Result<Response, ClientError> {
        let path = format!("/v1/datasets/{}/versions/{}/download", seg(task), seg(version));
        self.send(self.http.get(self.url(&path)).query(&[("format", "hdf5")]))
            .await
    }

    /// The bar the callers of `ingest` draw (the CLI, the Python package): bytes sent of `size`, hidden unless
    /// `visible`.
    pub fn upload_bar(size: u64, visible: bool) -> indicatif::ProgressBar {
        let bar = if visible {
            indicatif::ProgressBar::new(size)
        } else {
            indicatif::ProgressBar::hidden()
        };
        bar.set_style(
            indicatif::ProgressStyle::with_template(
                "uploading [{bar:30}] {bytes}/{total_bytes} {binary_bytes_per_sec}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar
    }

    /// Uploads a Parquet or DSRL HDF5 file; `progress` is told how many bytes went out. Token, task and size
    /// are checked first with cheap requests, so a doomed upload is refused before a byte of it is sent.
    pub async fn ingest(
        &self,
        task: &str,
        file: &Path,
        options: &IngestOptions,
        progress: impl Fn(u64) + Send + Sync + 'static,
    ) -> Result<IngestResult, ClientError> {
        let open_error = ClientError::io(format!("opening {}", file.display()));
        let handle = tokio::fs::File::open(file).await.map_err(open_error)?;
        let size = handle
            .metadata()
            .await
            .map_err(ClientError::io("reading the file size"))?
            .len();
        self.require_token()?;
        let info = self.server_info().await?;
        if !info.admin {
            return Err(ClientError::Server {
                status: 403,
                code: "permission_denied".into(),
                message: "the token given is not this server's admin token (uploads need it)".into(),
                suggestions: Vec::new(),
            });
        }
        self.task(task).await?;
        if size > info.max_upload_bytes {
            return Err(ClientError::TooLarge {
                size,
                limit: info.max_upload_bytes,
            });
        }
        // An upload of these bytes the server is converting, or has converted, is followed rather than sent again:
        // a retry after a timeout or a broken connection does not start the conversion over.
        let sha256 = file_sha256(file).await?;
        let earlier = self.uploads(task, &sha256).await?;
        if let Some(converting) = earlier.iter().find(|u| u.state == "converting") {
            match self.follow_upload(converting.clone()).await {
                // Its server stopped converting it: this upload starts afresh.
                Err(ClientError::Server { code, .. }) if code == INTERRUPTED => {}
                Err(e) => return Err(e),
                Ok(done) => return self.identical(task, done, options).await,
            }
        } else if let Some(done) = earlier.iter().find(|u| u.state == "done") {
            let result: IngestResult = serde_json::from_value(done.result.clone().unwrap_or_default())
                .map_err(|e| ClientError::Protocol(format!("upload result: {e}")))?;
            return self.identical(task, result, options).await;
        }
        let file_name = file
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        // The server answers once the bytes are received and converts in the background (a paper-size file takes
        // minutes); the client follows the conversion while the server says it is at work.
        let mut query = vec![("filename", file_name), ("background", "true".to_owned())];
        if !options.tags.is_empty() {
            query.push(("tags", options.tags.join(",")));
        }
        if let Some(space) = &options.observation_space {
            query.push(("observation_space", space.clone()));
        }
        if let Some(license) = &options.license {
            query.push(("license", license.clone()));
        }
        if options.keep_latest {
            query.push(("latest", "false".to_owned()));
        }
        let body = futures::stream::unfold((handle, 0u64), move |(mut handle, sent)| async move {
            let mut buf = vec![0u8; 1 << 20];
            match handle.read(&mut buf).await {
                Ok(0) => None,
                Ok(n) => {
                    buf.truncate(n);
                    Some((Ok::<_, std::io::Error>(buf), (handle, sent + n as u64)))
                }
                Err(e) => Some((Err(e), (handle, sent))),
            }
        })
        .scan(0u64, move |sent, chunk| {
            if let Ok(c) = &chunk {
                *sent += c.len() as u64;
                progress(*sent);
            }
            futures::future::ready(Some(chunk))
        });
        let path = format!("/v1/datasets/{}/versions", seg(task));
        let mut request = self
            .http
            .post(self.url(&path))
            .query(&query)
            .header(CONTENT_TYPE, "application/octet-stream")
            .header(CONTENT_LENGTH, size)
            .body(reqwest::Body::wrap_stream(body));
        if let Some(p) = &options.provenance_json {
            request = request.header("dsrl-provenance", p.as_str());
        }
        let response = self.send(self.admin(request)?).await?;
        if response.status() == StatusCode::ACCEPTED {
            let upload: Upload = response
                .json()
                .await
                .map_err(|e| ClientError::Protocol(format!("ingest response: {e}")))?;
            return self.follow_upload(upload).await;
        }
        // A server that converts in the foreground answers with the result itself.
        response
            .json()
            .await
            .map_err(|e| ClientError::Protocol(format!("ingest response: {e}")))
    }

    /// What uploading bytes the server has converted before answers, without sending them again: the version they
    /// became, `created: false`, and this request's explicit tags pointed at it (as the server does for identical
    /// data; `latest` moves only with a new version).
    async fn identical(
        &self,
        task: &str,
        earlier: IngestResult,
        options: &IngestOptions,
    ) -> Result<IngestResult, ClientError> {
        let version = earlier.version.version.clone();
        let mut moved = Vec::new();
        for tag in &options.tags {
            let before = self
                .versions(task)
                .await?
                .into_iter()
                .find(|v| v.tags.contains(tag))
                .map(|v| v.version);
            self.tag(task, tag, &version).await?;
            if before.as_deref() != Some(version.as_str()) {
                moved.push(tag.clone());
            }
        }
        let record = self
            .versions(task)
            .await?
            .into_iter()
            .find(|v| v.version == version)
            .ok_or_else(|| ClientError::Protocol(format!("version {version} of an earlier upload is gone")))?;
        Ok(IngestResult {
            created: false,
            task: task.to_owned(),
            version: record,
            moved_tags: moved,
            manifest_url: earlier.manifest_url,
            download_url: earlier.download_url,
        })
    }

    /// `GET /v1/uploads?task=&sha256=`: the server's uploads of these bytes for the task, newest first (none from
    /// a server that does not convert in the background).
    pub async fn uploads(&self, task: &str, sha256: &str) -> Result<Vec<Upload>, ClientError> {
        let request = self
            .http
            .get(self.url("/v1/uploads"))
            .query(&[("task", task), ("sha256", sha256)]);
        match self.send(self.admin(request)?).await {
            Ok(response) => Ok(response
                .json::<UploadList>()
                .await
                .map_err(|e| ClientError::Protocol(format!("GET /v1/uploads: {e}")))?
                .uploads),
            Err(ClientError::Server { status: 404, .. }) => Ok(Vec::new()),
            Err(e) => Err(e),
        }
    }

    /// Waits for a background upload to end, for as long as the server heartbeats it: its result, or its error as
    /// the server's. An upload whose server stopped converting (killed, restarted) is an error that says so.
    pub async fn follow_upload(&self, mut upload: Upload) -> Result<IngestResult, ClientError> {
        loop {
            match upload.state.as_str() {
                "done" => {
                    let result = upload
                        .result
                        .ok_or_else(|| ClientError::Protocol("a finished upload without its result".into()))?;
                    return serde_json::from_value(result)
                        .map_err(|e| ClientError::Protocol(format!("upload result: {e}")));
                }
                "failed" => {
                    let error = upload.error.unwrap_or_default();
                    let code = error["code"].as_str().unwrap_or("internal").to_owned();
                    return Err(ClientError::Server {
                        status: status_of(&code),
                        message: error["message"].as_str().unwrap_or("the upload failed").to_owned(),
                        code,
                        suggestions: Vec::new(),
                    });
                }
                "interrupted" => {
                    return Err(ClientError::Server {
                        status: 503,
                        code: INTERRUPTED.into(),
                        message: format!(
                            "the server stopped converting upload {} (it was restarted or killed; its last sign of \
                             work was at {}): upload the file again",
                            upload.id, upload.updated_at
                        ),
                        suggestions: Vec::new(),
                    });
                }
                _ => {}
            }
            tokio::time::sleep(Duration::from_millis(500)).await;
            let request = self.http.get(self.url(&format!("/v1/uploads/{}", seg(&upload.id))));
            upload = self
                .send(self.admin(request)?)
                .await?
                .json()
                .await
                .map_err(|e| ClientError::Protocol(format!("GET /v1/uploads/{}: {e}", upload.id)))?;
        }
    }

    pub async fn tag(&self, task: &str, tag: &str, version: &str) -> Result<HostedVersion, ClientError> {
        let path = format!("/v1/datasets/{}/tags/{}", seg(task), seg(tag));
        let request = self
            .http
            .put(self.url(&path))
            .json(&serde_json::json!({ "version": version }));
        let response = self.send(self.admin(request)?).await?;
        response
            .json()
            .await
            .map_err(|e| ClientError::Protocol(format!("tag response: {e}")))
    }
}

/// The error code of an upload whose server stopped converting it.
const INTERRUPTED: &str = "upload_interrupted";

/// An upload the server converts in the background (`GET /v1/uploads/{upload}`).
#[derive(Debug, Clone, Deserialize)]
pub struct Upload {
    pub id: String,
    pub task: String,
    pub upload_sha256: String,
    /// `converting`, `done`, `failed` or `interrupted`.
    pub state: String,
    pub result: Option<serde_json::Value>,
    pub error: Option<serde_json::Value>,
    pub updated_at: String,
}

#[derive(Debug, Deserialize)]
struct UploadList {
    uploads: Vec<Upload>,
}

/// How long a request may wait for the server's next bytes: `DSRL_CLIENT_TIMEOUT` seconds, default 120.
pub fn read_timeout() -> Duration {
    std::env::var("DSRL_CLIENT_TIMEOUT")
        .ok()
        .and_then(|s| s.parse::<u64>().ok())
        .filter(|&s| s > 0)
        .map_or(Duration::from_secs(120), Duration::from_secs)
}

/// The HTTP status an error code of the server's table stands for (for an error read back from an upload).
fn status_of(code: &str) -> u16 {
    match code {
        "not_found" => 404,
        "invalid_argument" => 400,
        "payload_too_large" => 413,
        "unauthenticated" => 401,
        "permission_denied" => 403,
        "already_exists" => 409,
        "resource_exhausted" => 429,
        "unavailable" => 503,
        "insufficient_storage" => 507,
        _ => 500,
    }
}

/// sha256 of a file, read in 1 MiB blocks off the async runtime.
async fn file_sha256(path: &Path) -> Result<String, ClientError> {
    let path = path.to_owned();
    tokio::task::spawn_blocking(move || {
        use sha2::Digest;
        let mut file = std::fs::File::open(&path).map_err(ClientError::io(format!("opening {}", path.display())))?;
        let mut hasher = sha2::Sha256::new();
        std::io::copy(&mut file, &mut hasher).map_err(ClientError::io(format!("reading {}", path.display())))?;
        Ok(hex::encode(hasher.finalize()))
    })
    .await
    .map_err(|e| ClientError::Protocol(format!("hashing the file: {e}")))?
}

/// The checkpoint files of a submission folder, named as the server expects: `policy.json` and
/// `policy.safetensors` at the top (one checkpoint for every threshold), or in one subfolder per cost threshold.
pub fn submission_files(dir: &Path) -> Result<Vec<(String, std::path::PathBuf)>, ClientError> {
    const FILES: [&str; 2] = ["policy.json", "policy.safetensors"];
    let usage = |m: String| ClientError::Usage(m);
    if dir.join(FILES[0]).is_file() {
        return Ok(FILES.iter().map(|f| (f.to_string(), dir.join(f))).collect());
    }
    let entries = std::fs::read_dir(dir).map_err(|e| usage(format!("cannot read {}: {e}", dir.display())))?;
    let mut files = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| usage(format!("cannot read {}: {e}", dir.display())))?;
        let path = entry.path();
        if path.join(FILES[0]).is_file() {
            let slot = entry.file_name().to_string_lossy().into_owned();
            files.extend(FILES.iter().map(|f| (format!("{slot}/{f}"), path.join(f))));
        }
    }
    files.sort();
    if files.is_empty() {
        return Err(usage(format!(
            "{} holds no checkpoint: expected policy.json and policy.safetensors in it, or in one subfolder per \
             cost threshold",
            dir.display()
        )));
    }
    Ok(files)
}

impl Client {
    fn bearer(&self, request: reqwest::RequestBuilder, what: &str) -> Result<reqwest::RequestBuilder, ClientError> {
        let token = self.token.as_deref().ok_or_else(|| {
            ClientError::Usage(format!(
                "{what} needs a user token: pass --token or set DSRL_TOKEN (an admin creates one with \
                 `dsrl-client admin create-user NAME`)"
            ))
        })?;
        Ok(request.header(AUTHORIZATION, format!("Bearer {token}")))
    }

    async fn json_of(response: Response, what: &str) -> Result<serde_json::Value, ClientError> {
        response
            .json()
            .await
            .map_err(|e| ClientError::Protocol(format!("{what}: {e}")))
    }

    /// `POST /v1/users` (admin token): the new user with its token.
    pub async fn create_user(&self, name: &str) -> Result<serde_json::Value, ClientError> {
        let request = self
            .http
            .post(self.url("/v1/users"))
            .json(&serde_json::json!({ "name": name }));
        let response = self.send(self.admin(request)?).await?;
        Self::json_of(response, "create-user response").await
    }

    /// Uploads a checkpoint folder as a submission (user token); returns the queued submission.
    pub async fn submit(&self, dir: &Path, task: &str, name: &str) -> Result<serde_json::Value, ClientError> {
        // Part names are checkpoint paths (`threshold-10/policy.json`, ASCII by construction); sent verbatim,
        // since a percent-encoded `name*=` form is not read by every multipart parser.
        let mut form = reqwest::multipart::Form::new()
            .percent_encode_noop()
            .text("task", task.to_owned())
            .text("name", name.to_owned());
        for (part, path) in submission_files(dir)? {
            let bytes = tokio::fs::read(&path)
                .await
                .map_err(|e| ClientError::Usage(format!("cannot read {}: {e}", path.display())))?;
            form = form.part(part.clone(), reqwest::multipart::Part::bytes(bytes).file_name(part));
        }
        let request = self.http.post(self.url("/v1/submissions")).multipart(form);
        let response = self.send(self.bearer(request, "submitting")?).await?;
        Self::json_of(response, "submit response").await
    }

    /// `GET /v1/users/{name}/submissions`: every submission a user made, newest first.
    pub async fn user_submissions(&self, name: &str) -> Result<serde_json::Value, ClientError> {
        self.get_json(&format!("/v1/users/{}/submissions", seg(name))).await
    }

    pub async fn submission(&self, id: i64) -> Result<serde_json::Value, ClientError> {
        self.get_json(&format!("/v1/submissions/{id}")).await
    }

    /// `GET /v1/submissions/{id}?wait=SECONDS`: the submission once it has ended, or after `wait_seconds` (at most
    /// 60) as it is then. One request replaces polling: the evaluator that ends the submission wakes the waiting
    /// request.
    pub async fn submission_when_ended(&self, id: i64, wait_seconds: u32) -> Result<serde_json::Value, ClientError> {
        self.get_json(&format!("/v1/submissions/{id}?wait={wait_seconds}"))
            .await
    }

    /// `GET /v1/submissions/{id}/episodes/{threshold}/{episode}/replay.json`: `Some(replay)` once made, `None`
    /// while it is queued (the request queues it).
    pub async fn episode_replay(
        &self,
        id: i64,
        threshold: f64,
        episode: u32,
    ) -> Result<Option<serde_json::Value>, ClientError> {
        let path = format!("/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.json");
        let response = self.send(self.http.get(self.url(&path))).await?;
        if response.status() == reqwest::StatusCode::ACCEPTED {
            return Ok(None);
        }
        Self::json_of(response, "replay").await.map(Some)
    }

    /// `GET …/replay.gif`: the replay's animation (made first through [`Self::episode_replay`]).
    pub async fn episode_replay_gif(&self, id: i64, threshold: f64, episode: u32) -> Result<Vec<u8>, ClientError> {
        let path = format!("/v1/submissions/{id}/episodes/{threshold}/{episode}/replay.gif");
        let response = self.send(self.http.get(self.url(&path))).await?;
        let bytes = response
            .bytes()
            .await
            .map_err(|e| ClientError::Protocol(format!("GET {path}: {e}")))?;
        Ok(bytes.to_vec())
    }

    pub async fn cancel(&self, id: i64) -> Result<serde_json::Value, ClientError> {
        let request = self.http.post(self.url(&format!("/v1/submissions/{id}/cancel")));
        let response = self.send(self.bearer(request, "cancelling")?).await?;
        Self::json_of(response, "cancel response").await
    }

    pub async fn leaderboard(&self, task: Option<&str>) -> Result<serde_json::Value, ClientError> {
        let mut request = self.http.get(self.url("/v1/leaderboard"));
        if let Some(task) = task {
            request = request.query(&[("task", task)]);
        }
        Self::json_of(self.send(request).await?, "leaderboard").await
    }
}

fn with_filter(request: reqwest::RequestBuilder, filter: Option<&str>) -> reqwest::RequestBuilder {
    match filter {
        Some(f) if !f.is_empty() => request.query(&[("filter", f)]),
        _ => request,
    }
}

/// Turns an error status into [`ClientError::Server`] using the server's error document.
async fn check(response: Response) -> Result<Response, ClientError> {
    let status = response.status();
    if status.is_success() || status == StatusCode::NOT_MODIFIED {
        return Ok(response);
    }
    let text = response.text().await.unwrap_or_default();
    Err(match serde_json::from_str::<ErrorDocument>(&text) {
        Ok(doc) => ClientError::Server {
            status: status.as_u16(),
            code: doc.error.code,
            message: doc.error.message,
            suggestions: doc.error.suggestions,
        },
        Err(_) => ClientError::Server {
            status: status.as_u16(),
            code: status
                .canonical_reason()
                .unwrap_or("error")
                .to_lowercase()
                .replace(' ', "_"),
            message: format!("HTTP {status}: {}", text.trim()),
            suggestions: vec![],
        },
    })
}

/// A path segment: ids and tags are plain ASCII by construction, but a user can type anything.
fn seg(s: &str) -> String {
    s.bytes()
        .map(|b| {
            if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'_' | b'.') {
                (b as char).to_string()
            } else {
                format!("%{b:02X}")
            }
        })
        .collect()
}
