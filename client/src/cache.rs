//! The local dataset cache. Layout, one folder per task and version, with DSRL-style file names inside:
//!
//! ```text
//! $DSRL_DATASET_DIR (default ~/.dsrl/datasets)/
//!   OfflineCarCircle-v0/
//!     <version sha256>/
//!       SafetyCarCircle-v0-100-1450.parquet   the version's bytes (sha256 = folder name)
//!       SafetyCarCircle-v0-100-1450.hdf5      DSRL's HDF5 layout, when fetched with --format hdf5
//!       manifest.json                          the manifest as served
//!       checksums.json                         sha256 and size of each file above
//!       .lock                                  held while a process fetches or verifies this version
//! ```
//!
//! A download goes to `<file>.part`, resumes with `Range` + `If-Range`, and is renamed only after its sha256
//! equals the version id, so a truncated or corrupt file never takes the final name. A cache hit is checked
//! cheaply (size and recorded hash); `verify` re-hashes everything.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use dsrl_suite::Manifest;
use dsrl_suite::hashing::sha256_reader;
use indicatif::{ProgressBar, ProgressStyle};
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::api::Client;
use crate::error::ClientError;

const CHECKSUMS: &str = "checksums.json";
const MANIFEST: &str = "manifest.json";
const LOCK: &str = ".lock";

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum OutputFormat {
    Parquet,
    Hdf5,
}

#[derive(Debug, Clone, Default)]
pub struct FetchOptions {
    pub hdf5: bool,
    /// A DSRL post-process filter (e.g. `noise=0.05`): fetch the filtered version the server makes.
    pub filter: Option<String>,
    /// Cap on download speed in bytes per second (like curl's `--limit-rate`).
    pub limit_rate: Option<u64>,
    /// Draw a progress bar (only shown when stderr is a terminal).
    pub progress: bool,
}

#[derive(Debug, Clone, Serialize)]
pub struct FetchOutcome {
    pub task: String,
    pub version: String,
    pub format: OutputFormat,
    /// The file to load: Parquet, or DSRL HDF5 with `--format hdf5`.
    pub path: PathBuf,
    /// The Parquet file, when it is complete in the cache (a `--format hdf5` fetch downloads only the server's
    /// HDF5 export, so the Parquet file is there only if an earlier fetch brought it).
    pub parquet_path: Option<PathBuf>,
    /// Nothing was downloaded or converted.
    pub cache_hit: bool,
    /// The HDF5 file was written from the Parquet file by this fetch.
    pub converted: bool,
    /// Byte offset a download resumed from, if it resumed a partial file.
    pub resumed_from: Option<u64>,
    pub downloaded_bytes: u64,
    pub byte_size: u64,
    pub seconds: f64,
}

/// Hash and size of each file of a cached version.
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
struct Checksums {
    files: BTreeMap<String, FileSum>,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct FileSum {
    sha256: String,
    size: u64,
}

#[derive(Debug, Clone, Serialize)]
pub struct FileReport {
    pub path: PathBuf,
    /// `ok`, `corrupt` (removed), or `missing`.
    pub status: &'static str,
    pub expected_sha256: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub actual_sha256: Option<String>,
}

#[derive(Debug, Clone, Default, Serialize)]
pub struct VerifyReport {
    pub files: Vec<FileReport>,
    /// Partial downloads (`.part`), kept so a later fetch resumes them.
    pub partial: Vec<PathBuf>,
    pub bytes_hashed: u64,
}

impl VerifyReport {
    pub fn corrupt(&self) -> usize {
        self.files.iter().filter(|f| f.status != "ok").count()
    }
}

#[derive(Debug, Clone)]
pub struct Cache {
    root: PathBuf,
}

impl Cache {
    pub fn new(root: impl Into<PathBuf>) -> Cache {
        Cache { root: root.into() }
    }

    /// `$DSRL_DATASET_DIR`, else `~/.dsrl/datasets` (DSRL's own default, so existing habits carry over).
    pub fn default_root() -> PathBuf {
        if let Some(dir) = std::env::var_os("DSRL_DATASET_DIR") {
            return PathBuf::from(dir);
        }
        let home = std::env::var_os("HOME")
            .map(PathBuf::from)
            .unwrap_or_else(|| PathBuf::from("."));
        home.join(".dsrl").join("datasets")
    }

    pub fn root(&self) -> &Path {
        &self.root
    }

    pub fn version_dir(&self, task: &str, version: &str) -> PathBuf {
        self.root.join(task).join(version)
    }

    /// Makes `task`'s version `reference` (id or tag) available locally and returns where it is.
    pub async fn fetch(
        &self,
        client: &Client,
        task: &str,
        reference: &str,
        options: &FetchOptions,
    ) -> Result<FetchOutcome, ClientError> {
        let started = Instant::now();
        // A full version id already complete in the cache needs no server at all (without a filter: the filtered
        // version's id is only known to the server).
        let offline = match options.filter {
            Some(_) => None,
            None => dsrl_suite::VersionId::try_from(reference.to_owned())
                .ok()
                .and_then(|v| self.cached_manifest(task, v.as_str())),
        };
        let manifest = match offline {
            Some(m) => m,
            None => client.manifest(task, reference, options.filter.as_deref()).await?.0,
        };
        let version = manifest.version.to_string();
        let dir = self.version_dir(manifest.task.as_str(), &version);
        std::fs::create_dir_all(&dir).map_err(ClientError::io(format!("creating {}", dir.display())))?;
        let _lock = lock(&dir).await?;

        let parquet = dir.join(&manifest.file_name);
        let mut checksums = read_checksums(&dir);
        let mut outcome = FetchOutcome {
            task: manifest.task.to_string(),
            version: version.clone(),
            format: if options.hdf5 {
                OutputFormat::Hdf5
            } else {
                OutputFormat::Parquet
            },
            path: parquet.clone(),
            parquet_path: None,
            cache_hit: true,
            converted: false,
            resumed_from: None,
            downloaded_bytes: 0,
            byte_size: manifest.byte_size,
            seconds: 0.0,
        };
        let manifest_json = serde_json::to_vec_pretty(&manifest).expect("manifest serializes");
        write_atomic(&dir.join(MANIFEST), &manifest_json)?;

        if options.hdf5 {
            let name = manifest.hdf5_file_name();
            let h5 = dir.join(&name);
            let known = checksums.files.get(&name).cloned();
            let hit = known.as_ref().is_some_and(|k| file_size(&h5) == Some(k.size));
            if !hit {
                // The server's stored export (made once per version for everyone), downloaded alone: the Parquet
                // file is not needed for it. A server without one (older than the format option) leaves the
                // conversion to this machine, which then needs the Parquet file.
                let sum = match download_hdf5(client, &manifest, &h5, options).await {
                    Ok(sum) => {
                        outcome.downloaded_bytes += sum.size;
                        sum
                    }
                    // Only a server that does not know the format (older than it) converts here: any other
                    // refusal is the answer, not a reason to download the Parquet file as well.
                    Err(ClientError::Server {
                        status: 400, message, ..
                    }) if message.contains("the formats are") || message.contains("unknown field") => {
                        self.ensure_parquet(client, &manifest, &dir, &mut checksums, &mut outcome, options)
                            .await?;
                        outcome.converted = true;
                        export_hdf5(&parquet, &h5).await?
                    }
                    Err(e) => return Err(e),
                };
                checksums.files.insert(name, sum);
                write_checksums(&dir, &checksums)?;
                outcome.cache_hit = false;
            }
            outcome.path = h5;
        } else {
            self.ensure_parquet(client, &manifest, &dir, &mut checksums, &mut outcome, options)
                .await?;
        }
        outcome.parquet_path = self.complete_parquet(&dir, &manifest, &checksums);
        outcome.seconds = started.elapsed().as_secs_f64();
        Ok(outcome)
    }

    /// Downloads (or resumes) the version's Parquet file unless it is already complete in the cache.
    async fn ensure_parquet(
        &self,
        client: &Client,
        manifest: &Manifest,
        dir: &Path,
        checksums: &mut Checksums,
        outcome: &mut FetchOutcome,
        options: &FetchOptions,
    ) -> Result<(), ClientError> {
        let expected = parquet_sum(manifest);
        if cheap_check(
            &dir.join(&manifest.file_name),
            checksums.files.get(&manifest.file_name),
            &expected,
        ) {
            return Ok(());
        }
        let (resumed_from, downloaded) = download(client, manifest, dir, options).await?;
        outcome.cache_hit = false;
        outcome.resumed_from = resumed_from;
        outcome.downloaded_bytes += downloaded;
        checksums.files.insert(manifest.file_name.clone(), expected);
        write_checksums(dir, checksums)
    }

    /// The version's Parquet file if it is complete in the cache (checked cheaply).
    fn complete_parquet(&self, dir: &Path, manifest: &Manifest, checksums: &Checksums) -> Option<PathBuf> {
        let path = dir.join(&manifest.file_name);
        cheap_check(&path, checksums.files.get(&manifest.file_name), &parquet_sum(manifest)).then_some(path)
    }

    /// The manifest of a version that is complete in the cache (checked cheaply), if any.
    fn cached_manifest(&self, task: &str, version: &str) -> Option<Manifest> {
        let dir = self.version_dir(task, version);
        let manifest: Manifest = serde_json::from_slice(&std::fs::read(dir.join(MANIFEST)).ok()?).ok()?;
        let checksums = read_checksums(&dir);
        let ok = manifest.version.as_str() == version && self.complete_parquet(&dir, &manifest, &checksums).is_some();
        ok.then_some(manifest)
    }

    /// Re-hashes every cached file; corrupt ones are removed (and their checksum entries dropped) so the next
    /// fetch downloads them again.
    pub fn verify(&self, progress: bool) -> Result<VerifyReport, ClientError> {
        let mut report = VerifyReport::default();
        let mut dirs = Vec::new();
        for task in read_dir_sorted(&self.root)? {
            if task.is_dir() {
                dirs.extend(read_dir_sorted(&task)?.into_iter().filter(|p| p.is_dir()));
            }
        }
        let total: u64 = dirs
            .iter()
            .map(|d| read_checksums(d).files.values().map(|f| f.size).sum::<u64>())
            .sum();
        let bar = progress_bar(progress, total, "verifying");
        for dir in dirs {
            let _lock = lock_blocking(&dir)?;
            let mut checksums = read_checksums(&dir);
            let version = dir
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let mut changed = false;
            for (name, sum) in checksums.files.clone() {
                let path = dir.join(&name);
                // The Parquet file must hash to its folder's name, whatever checksums.json says.
                let expected = if name.ends_with(".parquet") {
                    version.clone()
                } else {
                    sum.sha256.clone()
                };
                let actual = match File::open(&path) {
                    Ok(f) => {
                        let (digest, n) = sha256_reader(ProgressReader { inner: f, bar: &bar })
                            .map_err(ClientError::io(format!("reading {}", path.display())))?;
                        report.bytes_hashed += n;
                        Some(hex::encode(digest))
                    }
                    Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
                    Err(e) => {
                        return Err(ClientError::Io {
                            context: format!("opening {}", path.display()),
                            source: e,
                        });
                    }
                };
                let status = match &actual {
                    None => "missing",
                    Some(a) if *a == expected => "ok",
                    Some(_) => "corrupt",
                };
                if status != "ok" {
                    let _ = std::fs::remove_file(&path);
                    checksums.files.remove(&name);
                    changed = true;
                }
                report.files.push(FileReport {
                    path,
                    status,
                    expected_sha256: expected,
                    actual_sha256: actual,
                });
            }
            if changed {
                write_checksums(&dir, &checksums)?;
            }
            for path in read_dir_sorted(&dir)? {
                if path.extension().is_some_and(|e| e == "part") {
                    report.partial.push(path);
                }
            }
        }
        bar.finish_and_clear();
        Ok(report)
    }
}

/// The checksum a version's Parquet file must have: its sha256 is the version id.
fn parquet_sum(manifest: &Manifest) -> FileSum {
    FileSum {
        sha256: manifest.version.to_string(),
        size: manifest.byte_size,
    }
}

/// Size and recorded hash agree with what the manifest promises.
fn cheap_check(path: &Path, recorded: Option<&FileSum>, expected: &FileSum) -> bool {
    recorded == Some(expected) && file_size(path) == Some(expected.size)
}

fn file_size(path: &Path) -> Option<u64> {
    std::fs::metadata(path).ok().map(|m| m.len())
}

fn read_dir_sorted(dir: &Path) -> Result<Vec<PathBuf>, ClientError> {
    let mut entries = match std::fs::read_dir(dir) {
        Ok(entries) => entries
            .map(|e| e.map(|e| e.path()))
            .collect::<Result<Vec<_>, _>>()
            .map_err(ClientError::io(format!("listing {}", dir.display())))?,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => vec![],
        Err(e) => {
            return Err(ClientError::Io {
                context: format!("listing {}", dir.display()),
                source: e,
            });
        }
    };
    entries.sort();
    Ok(entries)
}

fn read_checksums(dir: &Path) -> Checksums {
    std::fs::read(dir.join(CHECKSUMS))
        .ok()
        .and_then(|b| serde_json::from_slice(&b).ok())
        .unwrap_or_default()
}

fn write_checksums(dir: &Path, checksums: &Checksums) -> Result<(), ClientError> {
    write_atomic(
        &dir.join(CHECKSUMS),
        &serde_json::to_vec_pretty(checksums).expect("checksums serialize"),
    )
}

/// Write to a temporary name, sync, rename, sync the folder: readers see the old file or the new one.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ClientError> {
    let tmp = path.with_extension("tmp");
    let ctx = || format!("writing {}", path.display());
    let mut f = File::create(&tmp).map_err(ClientError::io(ctx()))?;
    f.write_all(bytes)
        .and_then(|_| f.sync_all())
        .map_err(ClientError::io(ctx()))?;
    std::fs::rename(&tmp, path).map_err(ClientError::io(ctx()))?;
    sync_dir(path.parent().unwrap_or(Path::new(".")))
}

fn sync_dir(dir: &Path) -> Result<(), ClientError> {
    File::open(dir)
        .and_then(|d| d.sync_all())
        .map_err(ClientError::io(format!("syncing {}", dir.display())))
}

/// An exclusive lock on a version folder, so two processes fetching the same version take turns.
async fn lock(dir: &Path) -> Result<File, ClientError> {
    let dir = dir.to_owned();
    tokio::task::spawn_blocking(move || lock_blocking(&dir))
        .await
        .map_err(|e| ClientError::Protocol(format!("lock task: {e}")))?
}

fn lock_blocking(dir: &Path) -> Result<File, ClientError> {
    let path = dir.join(LOCK);
    let file = File::create(&path).map_err(ClientError::io(format!("creating {}", path.display())))?;
    match file.try_lock() {
        Ok(()) => return Ok(file),
        Err(std::fs::TryLockError::WouldBlock) => {
            eprintln!("waiting for another dsrl-client working on {}", dir.display());
        }
        Err(std::fs::TryLockError::Error(e)) => {
            return Err(ClientError::Io {
                context: format!("locking {}", path.display()),
                source: e,
            });
        }
    }
    file.lock()
        .map_err(ClientError::io(format!("locking {}", path.display())))?;
    Ok(file)
}

fn progress_bar(enabled: bool, total: u64, label: &'static str) -> ProgressBar {
    if !enabled {
        return ProgressBar::hidden();
    }
    // Draws only when stderr is a terminal.
    let bar = ProgressBar::new(total);
    bar.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {bytes}/{total_bytes} {binary_bytes_per_sec} eta {eta}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_message(label);
    bar
}

struct ProgressReader<'a, R> {
    inner: R,
    bar: &'a ProgressBar,
}

impl<R: Read> Read for ProgressReader<'_, R> {
    fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
        let n = self.inner.read(buf)?;
        self.bar.inc(n as u64);
        Ok(n)
    }
}

/// Downloads the version into `<file>.part` (resuming it if present), checks size and sha256, renames it.
/// Returns the offset resumed from and the bytes transferred.
async fn download(
    client: &Client,
    manifest: &Manifest,
    dir: &Path,
    options: &FetchOptions,
) -> Result<(Option<u64>, u64), ClientError> {
    let size = manifest.byte_size;
    let version = manifest.version.to_string();
    let final_path = dir.join(&manifest.file_name);
    let part = dir.join(format!("{}.part", manifest.file_name));
    let mut offset = file_size(&part).unwrap_or(0);
    if offset > size {
        offset = 0;
    }
    let mut downloaded = 0u64;
    let mut resumed_from = None;
    let bar = progress_bar(options.progress, size, "downloading");
    if offset < size {
        let mut response = client.download(manifest.task.as_str(), &version, offset).await?;
        let append = match response.status().as_u16() {
            206 => {
                let content_range = response.headers().get("content-range").and_then(|v| v.to_str().ok());
                let expected = format!("bytes {offset}-{}/{size}", size - 1);
                if content_range != Some(expected.as_str()) {
                    return Err(ClientError::Protocol(format!(
                        "asked for bytes {offset}- but got Content-Range {content_range:?}"
                    )));
                }
                resumed_from = Some(offset);
                true
            }
            200 => false,
            other => {
                return Err(ClientError::Protocol(format!("download answered HTTP {other}")));
            }
        };
        let start = if append { offset } else { 0 };
        bar.set_position(start);
        // Writing and hashing run on their own thread so they overlap with receiving.
        let (tx, rx) = std::sync::mpsc::sync_channel::<bytes::Bytes>(16);
        let writer_part = part.clone();
        let writer = std::thread::spawn(move || write_and_hash(&writer_part, append, start, rx));
        let started = Instant::now();
        let mut network_error = None;
        loop {
            match response.chunk().await {
                Ok(Some(chunk)) => {
                    downloaded += chunk.len() as u64;
                    bar.inc(chunk.len() as u64);
                    if tx.send(chunk).is_err() {
                        break; // the writer failed; its error is reported below
                    }
                    if let Some(rate) = options.limit_rate {
                        let due = Duration::from_secs_f64(downloaded as f64 / rate as f64);
                        if let Some(wait) = due.checked_sub(started.elapsed()) {
                            tokio::time::sleep(wait).await;
                        }
                    }
                }
                Ok(None) => break,
                Err(e) => {
                    network_error = Some(e);
                    break;
                }
            }
        }
        drop(tx);
        let (digest, written) = writer
            .join()
            .map_err(|_| ClientError::Protocol("the writer thread panicked".into()))?
            .map_err(ClientError::io(format!("writing {}", part.display())))?;
        bar.finish_and_clear();
        if let Some(e) = network_error {
            return Err(ClientError::Unreachable {
                url: format!(
                    "{} (download interrupted after {written} of {size} bytes; fetch again to resume)",
                    client.base()
                ),
                source: e,
            });
        }
        if written == size {
            return finish(&part, &final_path, hex::encode(digest), &version).map(|()| (resumed_from, downloaded));
        }
        if written < size {
            return Err(ClientError::Integrity(format!(
                "the server ended the download at {written} of {size} bytes; the partial file is kept, fetch again to resume"
            )));
        }
        let _ = std::fs::remove_file(&part);
        return Err(ClientError::Integrity(format!(
            "received {written} bytes, more than the {size} the manifest says"
        )));
    }
    // The partial file is already complete (a previous run died between the last byte and the rename).
    let (digest, _) = sha256_reader(File::open(&part).map_err(ClientError::io(format!("opening {}", part.display())))?)
        .map_err(ClientError::io(format!("reading {}", part.display())))?;
    finish(&part, &final_path, hex::encode(digest), &version).map(|()| (Some(offset), 0))
}

/// Accepts a complete `.part` file only if it hashes to the version id; a mismatch removes it.
fn finish(part: &Path, final_path: &Path, actual: String, version: &str) -> Result<(), ClientError> {
    if actual != version {
        let _ = std::fs::remove_file(part);
        return Err(ClientError::Integrity(format!(
            "the downloaded file hashes to {actual}, not to the version id {version}; it was removed, fetch again"
        )));
    }
    std::fs::rename(part, final_path).map_err(ClientError::io(format!("renaming to {}", final_path.display())))?;
    sync_dir(final_path.parent().unwrap_or(Path::new(".")))
}

/// Hashes the first `start` bytes already in `part` (when appending), then writes and hashes every received
/// chunk; returns the sha256 of the whole file and its length.
fn write_and_hash(
    part: &Path,
    append: bool,
    start: u64,
    chunks: std::sync::mpsc::Receiver<bytes::Bytes>,
) -> std::io::Result<([u8; 32], u64)> {
    let mut hasher = Sha256::new();
    let file = if append {
        let mut existing = File::open(part)?.take(start);
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = existing.read(&mut buf)?;
            if n == 0 {
                break;
            }
            hasher.update(&buf[..n]);
        }
        let file = std::fs::OpenOptions::new().write(true).open(part)?;
        file.set_len(start)?;
        let mut file = file;
        std::io::Seek::seek(&mut file, std::io::SeekFrom::Start(start))?;
        file
    } else {
        File::create(part)?
    };
    let mut file = dsrl_suite::writeback::WritebackFile::resuming(file, start);
    for chunk in chunks {
        hasher.update(&chunk);
        file.write_all(&chunk)?;
    }
    let written = file.bytes_written();
    // Most pages are already on their way to disk, so this wait is short.
    file.into_inner().sync_data()?;
    Ok((hasher.finalize().into(), written))
}

/// Downloads the server's HDF5 export of the manifest's version to `h5` (via `.part` + rename), checking its sha256
/// against the ETag the server gave; returns its checksum.
async fn download_hdf5(
    client: &Client,
    manifest: &Manifest,
    h5: &Path,
    options: &FetchOptions,
) -> Result<FileSum, ClientError> {
    let mut response = client
        .download_hdf5(manifest.task.as_str(), manifest.version.as_str())
        .await?;
    let etag = response
        .headers()
        .get("etag")
        .and_then(|v| v.to_str().ok())
        .map(|v| v.trim_matches('"').to_owned())
        .ok_or_else(|| ClientError::Protocol("the HDF5 export came without an ETag".into()))?;
    let size = response.content_length().unwrap_or(0);
    let bar = progress_bar(options.progress, size, "downloading HDF5");
    let part = PathBuf::from(format!("{}.part", h5.display()));
    let (tx, rx) = std::sync::mpsc::sync_channel::<bytes::Bytes>(16);
    let writer_part = part.clone();
    let writer = std::thread::spawn(move || write_and_hash(&writer_part, false, 0, rx));
    let mut failed = None;
    loop {
        match response.chunk().await {
            Ok(Some(chunk)) => {
                bar.inc(chunk.len() as u64);
                if tx.send(chunk).is_err() {
                    break;
                }
            }
            Ok(None) => break,
            Err(e) => {
                failed = Some(ClientError::Protocol(format!("downloading the HDF5 export: {e}")));
                break;
            }
        }
    }
    drop(tx);
    bar.finish_and_clear();
    let (digest, size) = writer
        .join()
        .map_err(|_| ClientError::Protocol("the HDF5 writer thread panicked".into()))?
        .map_err(ClientError::io(format!("writing {}", part.display())))?;
    if let Some(e) = failed {
        return Err(e);
    }
    let written = FileSum {
        sha256: hex::encode(digest),
        size,
    };
    if written.sha256 != etag {
        let _ = std::fs::remove_file(&part);
        return Err(ClientError::Integrity(format!(
            "the HDF5 export of {} hashed to {} but the server named {etag}",
            manifest.version, written.sha256
        )));
    }
    std::fs::rename(&part, h5).map_err(ClientError::io(format!("renaming to {}", h5.display())))?;
    Ok(written)
}

/// Writes DSRL's HDF5 layout next to the Parquet file (via `.part` + rename); returns its checksum.
#[cfg(feature = "hdf5")]
async fn export_hdf5(parquet: &Path, h5: &Path) -> Result<FileSum, ClientError> {
    let (parquet, h5) = (parquet.to_owned(), h5.to_owned());
    tokio::task::spawn_blocking(move || {
        let part = PathBuf::from(format!("{}.part", h5.display()));
        let file = File::open(&parquet).map_err(ClientError::io(format!("opening {}", parquet.display())))?;
        let reader = dsrl_suite::parquet_file::ParquetTransitions::open(file)
            .map_err(|e| ClientError::Conversion(e.to_string()))?;
        dsrl_suite::hdf5_file::write_dsrl_hdf5(reader, &part).map_err(|e| ClientError::Conversion(e.to_string()))?;
        let (digest, size) = sha256_reader(File::open(&part).map_err(ClientError::io("reading the HDF5 file"))?)
            .map_err(ClientError::io("hashing the HDF5 file"))?;
        File::open(&part)
            .and_then(|f| f.sync_all())
            .map_err(ClientError::io("syncing the HDF5 file"))?;
        std::fs::rename(&part, &h5).map_err(ClientError::io(format!("renaming to {}", h5.display())))?;
        Ok(FileSum {
            sha256: hex::encode(digest),
            size,
        })
    })
    .await
    .map_err(|e| ClientError::Protocol(format!("conversion task: {e}")))?
}

/// A build without HDF5 (the Python package's wheel) cannot convert: the server must export.
#[cfg(not(feature = "hdf5"))]
async fn export_hdf5(_parquet: &Path, _h5: &Path) -> Result<FileSum, ClientError> {
    Err(ClientError::Conversion(
        "the server has no HDF5 export (it is older than the `format` option) and this client was built without \
         HDF5: fetch the Parquet file, or use a dsrl-client CLI built with HDF5"
            .into(),
    ))
}
