//! Dataset versions as a service: ingest (convert, validate, store, commit), resolve a tag or id, read the
//! manifest, stream the bytes, move tags. HTTP and gRPC handlers are thin layers over this.

use std::collections::HashMap;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use bytes::Bytes;
use dsrl_filters::plan::{Fate, plan};
use dsrl_filters::spec::{FilterError, FilterSpec};
use dsrl_suite::manifest::ManifestFacts;
use dsrl_suite::plot::{Point, cost_reward_svg};
use dsrl_suite::{Catalog, Manifest, ObservationSpace, Provenance, TagName, Task, VersionId, VersionRef};
use futures::StreamExt;
use futures::stream::BoxStream;
use object_store::{ObjectStore, ObjectStoreExt};
use tokio::io::AsyncWriteExt;

use super::converter::Converter;
use super::db::{self, Db, VersionRecord, now_rfc3339};
use super::objects;
use crate::error::ApiError;
use crate::metrics::{Metrics, OutcomeLabels};

/// A file under the server's temporary folder, removed when dropped (an ingest that fails or is cancelled
/// leaves nothing behind; a killed process leaves files that the next start-up clears).
#[derive(Debug)]
pub struct TempFile(PathBuf);

impl TempFile {
    pub fn path(&self) -> &Path {
        &self.0
    }
}

impl Drop for TempFile {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// What `latest` does on ingest.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LatestPolicy {
    /// Move `latest` to the new version (admin uploads).
    Move,
    /// Set `latest` only if the task has none yet (starter datasets at start-up).
    IfAbsent,
    /// Leave `latest` where it is (a release imported beside the hosted data, `latest=false`).
    Keep,
}

pub struct IngestRequest {
    pub task: String,
    pub upload: TempFile,
    /// sha256 of the uploaded bytes.
    pub upload_sha256: String,
    /// The uploader's name for the file, recorded in the provenance.
    pub file_name: String,
    pub observation_space: ObservationSpace,
    /// Named tags to point at the version, besides `latest`.
    pub tags: Vec<TagName>,
    pub license: Option<String>,
    /// Provenance of data built by a recipe; `None` records the upload itself as the source.
    pub recipe: Option<Provenance>,
    pub latest: LatestPolicy,
}

#[derive(Debug)]
pub struct IngestOutcome {
    /// `false` when an identical version already existed and nothing was stored.
    pub created: bool,
    pub version: VersionRecord,
    /// Tags that now point at the version and did not before.
    pub moved_tags: Vec<String>,
}

pub struct Datasets {
    pub catalog: Arc<Catalog>,
    db: Db,
    store: Arc<dyn ObjectStore>,
    tmp_dir: PathBuf,
    default_license: String,
    converter: Converter,
    next_temp: AtomicU64,
    metrics: Arc<Metrics>,
    /// For the local backend, the folder that holds the objects: filters read parents there without a copy.
    local_objects: Option<PathBuf>,
    /// One gate per filtered version being computed, so concurrent identical requests compute it once.
    in_flight: std::sync::Mutex<HashMap<String, Arc<tokio::sync::Mutex<()>>>>,
    /// Turns for derived work (filters, HDF5 exports): a bounded number compute at once.
    derivation_turns: Arc<tokio::sync::Semaphore>,
    /// Derived objects (by gate key) started and not finished on this replica, computing or waiting for a turn,
    /// with the number of requests waiting on each: a request for one already in progress joins it and adds no work.
    derivations_pending: std::sync::Mutex<HashMap<String, usize>>,
    limits: DerivedLimits,
    /// Versions being streamed to a client now (task, version) → streams: the run-time budget never removes them.
    serving: std::sync::Mutex<HashMap<(String, String), usize>>,
    /// Derived bytes started by requests without a token, with when: the anonymous budget's window.
    anonymous_derived: std::sync::Mutex<std::collections::VecDeque<(std::time::Instant, u64)>>,
}

/// The limits on derived work and data while the server runs.
#[derive(Debug, Clone)]
pub struct DerivedLimits {
    pub max_concurrent: u32,
    pub max_waiting: u32,
    pub anonymous_bytes_per_hour: u64,
    /// Applied after every new filtered version (and periodically by the server).
    pub gc: GcPolicy,
}

impl Default for DerivedLimits {
    fn default() -> Self {
        DerivedLimits {
            max_concurrent: 2,
            max_waiting: 16,
            anonymous_bytes_per_hour: u64::MAX,
            gc: GcPolicy {
                max_idle: std::time::Duration::from_secs(u64::MAX / 4),
                max_bytes: u64::MAX,
            },
        }
    }
}

/// Who asks for derived work: requests without a token are held to the anonymous budget.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Requester {
    Anonymous,
    Authenticated,
}

/// Counts a version as being streamed until dropped.
pub struct Serving {
    datasets: Arc<Datasets>,
    key: (String, String),
}

impl Drop for Serving {
    fn drop(&mut self) {
        let mut serving = self.datasets.serving.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(n) = serving.get_mut(&self.key) {
            *n -= 1;
            if *n == 0 {
                serving.remove(&self.key);
            }
        }
    }
}

/// What the dataset service is made of.
pub struct DatasetsSetup {
    pub catalog: Arc<Catalog>,
    pub db: Db,
    pub store: Arc<dyn ObjectStore>,
    /// For the local backend, the folder holding the objects.
    pub local_objects: Option<PathBuf>,
    /// Emptied on start: whatever is there was left by a process that died mid-ingest.
    pub tmp_dir: PathBuf,
    pub default_license: String,
    pub converter: Converter,
    pub metrics: Arc<Metrics>,
    pub limits: DerivedLimits,
}

impl Datasets {
    pub fn new(setup: DatasetsSetup) -> std::io::Result<Datasets> {
        let DatasetsSetup {
            catalog,
            db,
            store,
            local_objects,
            tmp_dir,
            default_license,
            converter,
            metrics,
            limits,
        } = setup;
        if tmp_dir.exists() {
            std::fs::remove_dir_all(&tmp_dir)?;
        }
        std::fs::create_dir_all(&tmp_dir)?;
        Ok(Datasets {
            catalog,
            db,
            store,
            tmp_dir,
            default_license,
            converter,
            next_temp: AtomicU64::new(0),
            metrics,
            local_objects,
            in_flight: Default::default(),
            derivation_turns: Arc::new(tokio::sync::Semaphore::new(limits.max_concurrent.max(1) as usize)),
            derivations_pending: std::sync::Mutex::new(HashMap::new()),
            limits,
            serving: Default::default(),
            anonymous_derived: Default::default(),
        })
    }

    pub fn limits(&self) -> &DerivedLimits {
        &self.limits
    }

    /// Marks `record` as being streamed until the returned guard is dropped.
    pub fn serving(self: &Arc<Self>, record: &VersionRecord) -> Serving {
        let key = (record.task.to_string(), record.version.to_string());
        *self
            .serving
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .entry(key.clone())
            .or_default() += 1;
        Serving {
            datasets: self.clone(),
            key,
        }
    }

    fn is_serving(&self, task: &str, version: &str) -> bool {
        self.serving
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .contains_key(&(task.to_owned(), version.to_owned()))
    }

    /// Admits a request for the derived object `key`: one already in progress is joined (no new work, nothing
    /// charged); new work is refused past the waiting room (503, `Retry-After`) and, for a request without a
    /// token, past the anonymous budget of the last hour (429, `Retry-After`), which records its `bytes`.
    fn admit(&self, key: &str, requester: Requester, bytes: u64) -> Result<(), ApiError> {
        let mut pending_work = self.derivations_pending.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(waiting) = pending_work.get_mut(key) {
            *waiting += 1;
            return Ok(());
        }
        let pending = pending_work.len() as u64;
        let room = u64::from(self.limits.max_concurrent.max(1)) + u64::from(self.limits.max_waiting);
        if pending >= room {
            return Err(ApiError::Busy {
                message: format!(
                    "{pending} derived datasets are being computed or waiting (datasets.max_concurrent_derivations \
                     + datasets.max_waiting_derivations = {room})"
                ),
                retry_after: 30,
            });
        }
        if requester == Requester::Anonymous {
            let hour = std::time::Duration::from_secs(3600);
            let mut window = self.anonymous_derived.lock().unwrap_or_else(|e| e.into_inner());
            while window.front().is_some_and(|(at, _)| at.elapsed() >= hour) {
                window.pop_front();
            }
            let used: u64 = window.iter().map(|(_, b)| b).sum();
            if used.saturating_add(bytes) > self.limits.anonymous_bytes_per_hour {
                let retry_after = window
                    .front()
                    .map_or(3600, |(at, _)| hour.saturating_sub(at.elapsed()).as_secs().max(1));
                return Err(ApiError::RateLimited {
                    message: format!(
                        "requests without a token have started {used} bytes of derived data in the last hour; the \
                         limit is {} (datasets.anonymous_derived_bytes_per_hour): send an admin or user token",
                        self.limits.anonymous_bytes_per_hour
                    ),
                    retry_after,
                });
            }
            window.push_back((std::time::Instant::now(), bytes));
        }
        pending_work.insert(key.to_owned(), 1);
        Ok(())
    }

    /// A turn among `max_concurrent_derivations`: taken by whoever computes a derived object, once it has found
    /// that nobody did before it (requests waiting for the same object hold none).
    async fn derivation_turn(&self) -> Result<tokio::sync::OwnedSemaphorePermit, ApiError> {
        self.derivation_turns
            .clone()
            .acquire_owned()
            .await
            .map_err(ApiError::internal)
    }

    /// Runs derived work for the object `key` (admitted by `admit`) in a task of its own: it completes and is
    /// recorded even when the request that started it is gone (a client's timeout, a proxy's), and later requests
    /// find it.
    async fn detached<T: Send + 'static>(
        self: &Arc<Self>,
        key: String,
        work: impl std::future::Future<Output = Result<T, ApiError>> + Send + 'static,
    ) -> Result<T, ApiError> {
        let this = self.clone();
        let handle = tokio::spawn(async move {
            let result = work.await;
            let mut pending = this.derivations_pending.lock().unwrap_or_else(|e| e.into_inner());
            if let Some(waiting) = pending.get_mut(&key) {
                *waiting -= 1;
                if *waiting == 0 {
                    pending.remove(&key);
                }
            }
            result
        });
        handle.await.map_err(ApiError::internal)?
    }

    pub fn db(&self) -> &Db {
        &self.db
    }

    pub fn store(&self) -> &Arc<dyn ObjectStore> {
        &self.store
    }

    pub fn temp_file(&self, purpose: &str) -> TempFile {
        let n = self.next_temp.fetch_add(1, Ordering::Relaxed);
        TempFile(self.tmp_dir.join(format!("{purpose}-{}-{n}", std::process::id())))
    }

    pub fn task(&self, id: &str) -> Result<&Task, ApiError> {
        Ok(self.catalog.get(id)?)
    }

    /// The version a reference (id, tag, or empty for `latest`) names now.
    pub async fn resolve(&self, task: &str, reference: &str) -> Result<(&Task, VersionRecord), ApiError> {
        let task = self.task(task)?;
        let reference = if reference.is_empty() {
            TagName::LATEST
        } else {
            reference
        };
        let parsed: VersionRef = reference
            .parse()
            .map_err(|e| ApiError::InvalidArgument(format!("{e}")))?;
        let not_found = || ApiError::VersionNotFound {
            task: task.id.to_string(),
            reference: reference.to_owned(),
        };
        let version = match parsed {
            VersionRef::Version(v) => v,
            VersionRef::Tag(tag) => self.db.tagged(&task.id, &tag).await?.ok_or_else(not_found)?,
        };
        let record = self.db.version(&task.id, &version).await?.ok_or_else(not_found)?;
        Ok((task, record))
    }

    /// The manifest as served: the stored one, with what the version is on this server (`hosting`: its starter,
    /// with the notice that says so, or a full build) where its tags say.
    pub async fn manifest_json(&self, record: &VersionRecord) -> Result<String, ApiError> {
        let (task, version) = ids(record)?;
        let stored = self.db.manifest(&task, &version).await?.ok_or_else(|| {
            ApiError::Internal(format!(
                "version {} of {} has no manifest row",
                record.version, record.task
            ))
        })?;
        let Some(hosting) = dsrl_suite::Hosting::of(self.task(&record.task)?, record.episodes, &record.tags) else {
            return Ok(stored);
        };
        let mut manifest: serde_json::Map<String, serde_json::Value> =
            serde_json::from_str(&stored).map_err(ApiError::internal)?;
        manifest.insert(
            "hosting".into(),
            serde_json::to_value(hosting).map_err(ApiError::internal)?,
        );
        serde_json::to_string(&manifest).map_err(ApiError::internal)
    }

    /// The Parquet bytes of a version, or a byte range of them.
    pub async fn read(
        &self,
        record: &VersionRecord,
        range: Option<Range<u64>>,
    ) -> Result<BoxStream<'static, std::io::Result<Bytes>>, ApiError> {
        let key = objects::dataset_key(&record.task, &record.version);
        Ok(objects::read(self.store.as_ref(), &key, range).await?)
    }

    /// Stores a version's Parquet file and manifest under their keys (each write atomic) and checks the stored size.
    /// `file` is a synced temporary file: with the local backend it is renamed into place (same filesystem, no
    /// copy), otherwise uploaded.
    async fn store_objects(&self, manifest: &Manifest, json: &str, file: &Path) -> Result<(), ApiError> {
        let (task, version) = (manifest.task.as_str(), manifest.version.as_str());
        let data_key = objects::dataset_key(task, version);
        let stored = self.store_file(file, &data_key).await?;
        if stored != manifest.byte_size {
            return Err(ApiError::Internal(format!(
                "stored {data_key} has {stored} bytes, expected {}",
                manifest.byte_size
            )));
        }
        let manifest_key = objects::manifest_key(task, version);
        objects::put_bytes(self.store.as_ref(), &manifest_key, json.as_bytes().to_vec()).await?;
        Ok(())
    }

    pub async fn manifest(&self, record: &VersionRecord) -> Result<Manifest, ApiError> {
        serde_json::from_str(&self.manifest_json(record).await?).map_err(ApiError::internal)
    }

    /// The version a request names: `reference` itself, or, with a filter, the version the filter makes from it
    /// (computed once, then looked up).
    pub async fn resolve_filtered(
        self: &Arc<Self>,
        task: &str,
        reference: &str,
        filter: Option<&str>,
        requester: Requester,
    ) -> Result<(&Task, VersionRecord), ApiError> {
        let (task, parent) = self.resolve(task, reference).await?;
        let Some(spec) = self.parse_filter(task, filter)? else {
            return Ok((task, parent));
        };
        let record = self
            .derive(task, &parent, &spec, filter.unwrap_or_default(), requester)
            .await?;
        Ok((task, record))
    }

    fn parse_filter(&self, task: &Task, filter: Option<&str>) -> Result<Option<FilterSpec>, ApiError> {
        FilterSpec::parse(filter.unwrap_or_default(), task).map_err(|e| self.rejected(e))
    }

    fn count_filter(&self, outcome: &'static str) {
        self.metrics.filters.get_or_create(&OutcomeLabels { outcome }).inc();
    }

    fn rejected(&self, e: FilterError) -> ApiError {
        self.count_filter("rejected");
        ApiError::InvalidArgument(e.to_string())
    }

    async fn derive(
        self: &Arc<Self>,
        task: &Task,
        parent: &VersionRecord,
        spec: &FilterSpec,
        request: &str,
        requester: Requester,
    ) -> Result<VersionRecord, ApiError> {
        let canonical = spec.canonical();
        if let Some((found, last_used_ms)) = self.derivation(task, parent, &canonical).await? {
            self.count_filter("cached");
            // Garbage collection goes by last use; recorded at most once a minute, so reads stay reads.
            if db::now_ms() - last_used_ms >= db::DERIVATION_TOUCH_MS {
                self.db.touch_derivation(&task.id, &parent.version, &canonical).await?;
            }
            return Ok(found);
        }
        let gate = derivation_gate(task.id.as_str(), &parent.version, &canonical);
        self.admit(&gate, requester, parent.byte_size)?;
        let this = self.clone();
        let (task, parent, spec, request) = (task.clone(), parent.clone(), spec.clone(), request.to_owned());
        let record = self
            .detached(gate.clone(), async move {
                this.one_at_a_time(gate, async {
                    // Whoever held the gate before us has committed its result.
                    if let Some((found, _)) = this.derivation(&task, &parent, &canonical).await? {
                        this.count_filter("cached");
                        return Ok(found);
                    }
                    let _turn = this.derivation_turn().await?;
                    let started = std::time::Instant::now();
                    let record = this
                        .compute_derivation(&task, &parent, &spec, &canonical, &request)
                        .await?;
                    this.count_filter("computed");
                    this.metrics.filter_seconds.observe(started.elapsed().as_secs_f64());
                    Ok(record)
                })
                .await
            })
            .await?;
        self.enforce_derived_budget().await?;
        Ok(record)
    }

    /// Past the run-time budget (filtered versions and their HDF5 exports), the least recently used filtered
    /// versions go, with their exports (never one being streamed).
    async fn enforce_derived_budget(&self) -> Result<(), ApiError> {
        let policy = self.limits.gc.clone();
        if self.db.derived_bytes().await? > policy.max_bytes {
            let report = self.collect_garbage(&policy, false).await?;
            tracing::info!(
                removed = report.removed.len(),
                bytes = report.derived_bytes_after,
                "derived data over budget"
            );
        }
        Ok(())
    }

    /// Runs `work` while holding the gate named `key`, so that concurrent requests for the same derived object
    /// (an ingested version, a filtered version, an HDF5 export) compute it once: a later holder finds the first
    /// one's result. The in-process gate queues this replica's requests; the database's lock (PostgreSQL) queues
    /// the replicas.
    async fn one_at_a_time<T>(
        &self,
        key: String,
        work: impl std::future::Future<Output = Result<T, ApiError>>,
    ) -> Result<T, ApiError> {
        let gate = self
            .in_flight
            .lock()
            .expect("in-flight map")
            .entry(key.clone())
            .or_default()
            .clone();
        let turn = gate.lock().await;
        let result = self.db.exclusively(&key, work).await;
        self.in_flight.lock().expect("in-flight map").remove(&key);
        drop(turn);
        result
    }

    /// Removes filtered versions by the policy: every one unused for `max_idle`, then the least recently used
    /// until all together fit `max_bytes`. Each removal holds the version's derivation gate (the lock a replica
    /// computing that filter holds), deletes the rows in one transaction, then the objects, so a replica never
    /// serves a row whose file is gone, and a concurrent request for the same filter computes it again afterwards.
    /// A download already streaming the removed file may fail; the client's retry recomputes the filter.
    pub async fn collect_garbage(&self, policy: &GcPolicy, dry_run: bool) -> Result<GcReport, ApiError> {
        let candidates = self.db.collectable_derivations().await?;
        let mut total = self.db.derived_bytes().await?;
        let cutoff = db::now_ms().saturating_sub(policy.max_idle.as_millis() as i64);
        let mut report = GcReport {
            derived_bytes_before: total,
            ..GcReport::default()
        };
        for candidate in candidates {
            let idle = candidate.last_used_ms < cutoff;
            if (!idle && total <= policy.max_bytes) || self.is_serving(&candidate.task, &candidate.version) {
                report.kept += 1;
                continue;
            }
            if !dry_run && !self.remove_derived(&candidate).await? {
                continue;
            }
            total = total.saturating_sub(candidate.byte_size);
            report.removed.push(candidate);
        }
        report.derived_bytes_after = total;
        Ok(report)
    }

    async fn remove_derived(&self, record: &db::DerivationRecord) -> Result<bool, ApiError> {
        let gate = derivation_gate(&record.task, &record.parent, &record.filter);
        self.one_at_a_time(gate, async {
            let mut tx = self.db.begin().await?;
            let Some(export) = db::remove_derived(&mut tx, record).await? else {
                return Ok(false);
            };
            let export = match export {
                Some(digest) if !db::hdf5_digest_in_use(&mut tx, &digest).await? => Some(digest),
                _ => None,
            };
            tx.commit().await?;
            let mut keys = vec![
                objects::dataset_key(&record.task, &record.version),
                objects::manifest_key(&record.task, &record.version),
            ];
            keys.extend(export.map(|digest| objects::hdf5_key(&digest)));
            for key in keys {
                match self.store.delete(&key).await {
                    Ok(()) | Err(object_store::Error::NotFound { .. }) => {}
                    Err(e) => return Err(e.into()),
                }
            }
            tracing::info!(task = %record.task, version = %record.version, filter = %record.filter,
                bytes = record.byte_size, "removed a filtered version");
            Ok(true)
        })
        .await
    }

    /// Puts a synced temporary file at `key` (renamed into place with the local backend, uploaded otherwise) and
    /// returns the stored size.
    async fn store_file(&self, file: &Path, key: &object_store::path::Path) -> Result<u64, ApiError> {
        let renamed = match &self.local_objects {
            Some(root) => objects::rename_into(root, file, key)
                .await
                .map_err(ApiError::internal)?,
            None => None,
        };
        match renamed {
            Some(size) => Ok(size),
            None => Ok(objects::upload_file(self.store.as_ref(), file, key).await?),
        }
    }

    async fn derivation(
        &self,
        task: &Task,
        parent: &VersionRecord,
        canonical: &str,
    ) -> Result<Option<(VersionRecord, i64)>, ApiError> {
        let Some((version, last_used_ms)) = self.db.derivation(&task.id, &parent.version, canonical).await? else {
            return Ok(None);
        };
        Ok(self.db.version(&task.id, &version).await?.map(|v| (v, last_used_ms)))
    }

    /// Plans the filter from the parent's episode index, gathers and writes the output on a blocking thread,
    /// stores it, and commits the version and the derivation together.
    async fn compute_derivation(
        &self,
        task: &Task,
        parent: &VersionRecord,
        spec: &FilterSpec,
        canonical: &str,
        request: &str,
    ) -> Result<VersionRecord, ApiError> {
        let parent_manifest = self.manifest(parent).await?;
        let planned = plan(spec, task, &parent_manifest.episode_index).map_err(|e| self.rejected(e))?;
        let counts = planned.counts.clone();
        let (source, _download) = self.readable_copy(parent).await?;
        let out = self.temp_file("filtered");
        let space = parent_manifest.observation_space.kind;
        let (obs_dim, act_dim) = (parent_manifest.observation_space.dim as usize, task.act_dim as usize);
        let (task_owned, out_path) = (task.clone(), out.path().to_owned());
        let scratch = self.temp_file("spill");
        let scratch_path = scratch.path().to_owned();
        let episodes = parent_manifest.episode_index;
        // Streamed in bounded memory (the kept episodes spill to a scratch file and are read back in output order).
        let converted = tokio::task::spawn_blocking(move || {
            dsrl_filters::apply::filter_to(
                &source,
                &episodes,
                &planned,
                &task_owned,
                space,
                obs_dim,
                act_dim,
                &out_path,
                &scratch_path,
            )
        })
        .await
        .map_err(ApiError::internal)?
        .map_err(|e| ApiError::Internal(format!("filtering {}: {e}", parent.version)))?;
        let now = now_rfc3339();
        let manifest = Manifest::new(
            task,
            converted.version.clone(),
            converted.byte_size,
            converted.episode_index,
            ManifestFacts {
                observation_space: space,
                provenance: Provenance::Filter {
                    parent: parent.version.clone(),
                    filter: canonical.to_owned(),
                    request: request.to_owned(),
                    seed: spec.grid.map(|_| spec.seed),
                    counts,
                    reference: dsrl_filters::UPSTREAM.to_owned(),
                },
                license: parent_manifest.license,
                created_at: now.clone(),
            },
        );
        let json = serde_json::to_string(&manifest).map_err(ApiError::internal)?;
        if self.db.version(&task.id, &manifest.version).await?.is_none() {
            self.store_objects(&manifest, &json, out.path()).await?;
        }
        let mut tx = self.db.begin().await?;
        db::insert_version(&mut tx, &manifest, &json).await?;
        db::insert_derivation(&mut tx, &task.id, &parent.version, canonical, &manifest.version, &now).await?;
        tx.commit().await?;
        tracing::info!(task = %task.id, parent = %parent.version, filter = canonical, version = %manifest.version,
            "computed a filtered version");
        self.db
            .version(&task.id, &manifest.version)
            .await?
            .ok_or_else(|| ApiError::Internal("filtered version row vanished after commit".into()))
    }

    /// The DSRL-layout HDF5 export of a version: (sha256 of its bytes, size). Converted from the Parquet once, on
    /// the first request (concurrent first requests convert once), stored content-addressed under
    /// `hdf5/<sha256>.hdf5` and recorded; later requests are a lookup.
    pub async fn hdf5_export(
        self: &Arc<Self>,
        record: &VersionRecord,
        requester: Requester,
    ) -> Result<(String, u64), ApiError> {
        if let Some(found) = self.db.hdf5_export(&record.task, &record.version).await? {
            self.count_export("cached");
            return Ok(found);
        }
        let key = format!("hdf5/{}/{}", record.task, record.version);
        self.admit(&key, requester, record.byte_size)?;
        let this = self.clone();
        let owned = record.clone();
        let export = self
            .detached(key, async move { this.compute_hdf5_export(&owned).await })
            .await?;
        // A filtered version's export counts toward the derived budget, as the version itself does (an original
        // version's does not: the query counts derived versions only).
        self.enforce_derived_budget().await?;
        Ok(export)
    }

    fn count_export(&self, outcome: &'static str) {
        self.metrics
            .hdf5_exports
            .get_or_create(&OutcomeLabels { outcome })
            .inc();
    }

    async fn compute_hdf5_export(&self, record: &VersionRecord) -> Result<(String, u64), ApiError> {
        let key = format!("hdf5/{}/{}", record.task, record.version);
        self.one_at_a_time(key, async {
            if let Some(found) = self.db.hdf5_export(&record.task, &record.version).await? {
                self.count_export("cached");
                return Ok(found);
            }
            let _turn = self.derivation_turn().await?;
            let started = std::time::Instant::now();
            let (source, _download) = self.readable_copy(record).await?;
            let out = self.temp_file("hdf5");
            let out_path = out.path().to_owned();
            let (digest, size) = tokio::task::spawn_blocking(move || -> Result<(String, u64), String> {
                // Decoding the Parquet file is the export's longest step: its row groups are decoded on every core.
                let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
                let transitions = dsrl_suite::parquet_file::ParquetTransitions::open_read_ahead(&source, threads)
                    .map_err(|e| e.to_string())?;
                dsrl_suite::hdf5_file::write_dsrl_hdf5(transitions, &out_path).map_err(|e| e.to_string())?;
                let mut hasher = <sha2::Sha256 as sha2::Digest>::new();
                let file = std::fs::File::open(&out_path).map_err(|e| e.to_string())?;
                let mut file = std::io::BufReader::with_capacity(1 << 20, file);
                let size = std::io::copy(&mut file, &mut hasher).map_err(|e| e.to_string())?;
                Ok((hex::encode(sha2::Digest::finalize(hasher)), size))
            })
            .await
            .map_err(ApiError::internal)?
            .map_err(|e| ApiError::Internal(format!("converting {} to HDF5: {e}", record.version)))?;
            let object = objects::hdf5_key(&digest);
            let stored = self.store_file(out.path(), &object).await?;
            if stored != size {
                return Err(ApiError::Internal(format!(
                    "stored {object} has {stored} bytes, expected {size}"
                )));
            }
            self.db
                .insert_hdf5_export(&record.task, &record.version, &digest, size, &now_rfc3339())
                .await?;
            self.count_export("computed");
            tracing::info!(task = %record.task, version = %record.version, digest, bytes = size,
                seconds = started.elapsed().as_secs_f64(), "exported a version as DSRL HDF5");
            Ok((digest, size))
        })
        .await
    }

    /// The bytes of a stored HDF5 export, or a byte range of them.
    pub async fn read_hdf5(
        &self,
        digest: &str,
        range: Option<Range<u64>>,
    ) -> Result<BoxStream<'static, std::io::Result<Bytes>>, ApiError> {
        Ok(objects::read(self.store.as_ref(), &objects::hdf5_key(digest), range).await?)
    }

    /// A local file with the version's bytes: the object itself for the local backend, else a downloaded copy
    /// (returned too, so it lives as long as the caller needs it).
    async fn readable_copy(&self, record: &VersionRecord) -> Result<(PathBuf, Option<TempFile>), ApiError> {
        if let Some(root) = &self.local_objects {
            let path = root.join(objects::dataset_key(&record.task, &record.version).as_ref());
            return Ok((path, None));
        }
        let copy = self.temp_file("parent");
        let mut file = tokio::fs::File::create(copy.path()).await.map_err(ApiError::internal)?;
        let mut stream = self.read(record, None).await?;
        while let Some(chunk) = stream.next().await {
            let chunk = chunk.map_err(|e| ApiError::Unavailable(format!("reading {}: {e}", record.version)))?;
            file.write_all(&chunk).await.map_err(ApiError::internal)?;
        }
        file.flush().await.map_err(ApiError::internal)?;
        Ok((copy.path().to_owned(), Some(copy)))
    }

    /// The cost–reward scatter of a version, or of what a filter would do to it (decisions only, no data read).
    pub async fn plot_svg(&self, task: &str, reference: &str, filter: Option<&str>) -> Result<String, ApiError> {
        let (task, record) = self.resolve(task, reference).await?;
        let manifest = self.manifest(&record).await?;
        let spec = self.parse_filter(task, filter)?;
        let short = dsrl_suite::ids::short_hex(&record.version);
        let (title, subtitle, points): (String, Option<String>, Vec<Point>) = match &spec {
            None => (
                format!("{} {short}: {} trajectories", task.id, manifest.episodes),
                None,
                manifest
                    .episode_index
                    .iter()
                    .map(|e| Point {
                        cost_return: e.cost_return,
                        reward_return: e.reward_return,
                        fate: Fate::Kept,
                    })
                    .collect(),
            ),
            Some(spec) => {
                let planned = plan(spec, task, &manifest.episode_index).map_err(|e| self.rejected(e))?;
                let points = planned
                    .fates
                    .iter()
                    .zip(&planned.returns)
                    .map(|(&fate, &(c, r))| Point {
                        cost_return: c,
                        reward_return: r,
                        fate,
                    })
                    .collect();
                let c = &planned.counts;
                (
                    format!(
                        "{} {short}: {} of {} trajectories kept",
                        task.id, c.output_episodes, c.input_episodes
                    ),
                    Some(format!("filter: {}", spec.canonical())),
                    points,
                )
            }
        };
        let task = task.clone();
        tokio::task::spawn_blocking(move || cost_reward_svg(&task, &title, subtitle.as_deref(), &points))
            .await
            .map_err(ApiError::internal)?
            .map_err(ApiError::Internal)
    }

    pub async fn versions(&self, task: &str) -> Result<(&Task, Vec<VersionRecord>), ApiError> {
        let task = self.task(task)?;
        Ok((task, self.db.versions(Some(&task.id)).await?))
    }

    /// Every task of the catalog, in catalog order, with its hosted versions (newest first): one query.
    pub async fn catalog_with_versions(&self) -> Result<Vec<(&Task, Vec<VersionRecord>)>, ApiError> {
        let mut by_task: HashMap<String, Vec<VersionRecord>> = HashMap::new();
        for v in self.db.versions(None).await? {
            by_task.entry(v.task.clone()).or_default().push(v);
        }
        Ok(self
            .catalog
            .tasks()
            .iter()
            .map(|task| (task, by_task.remove(task.id.as_str()).unwrap_or_default()))
            .collect())
    }

    /// Converts and validates the upload, stores the canonical file and its manifest, then commits the row and
    /// tags in one transaction. Until that commit nothing is visible; after it everything is.
    pub async fn ingest(&self, req: IngestRequest) -> Result<IngestOutcome, ApiError> {
        let task = self.task(&req.task)?.clone();
        let canonical = self.temp_file("canonical");
        let space = req.observation_space;
        let (format, converted) = self
            .converter
            .convert(req.upload.path(), &task, space, canonical.path())
            .await?;
        drop(req.upload);
        let version = converted.version.clone();
        let now = now_rfc3339();

        // Replicas that get the same bytes at once (two starting together with the same starters) store and
        // record them once: the second finds the version.
        let gate = format!("ingest/{}/{}", task.id, version);
        self.one_at_a_time(gate, async {
            let Some(existing) = self.db.version(&task.id, &version).await? else {
                let provenance = req.recipe.unwrap_or(Provenance::Import {
                    file_name: req.file_name,
                    sha256: req.upload_sha256,
                    source_format: format.as_str().to_owned(),
                    dropped_columns: converted.dropped_columns,
                });
                let manifest = Manifest::new(
                    &task,
                    version.clone(),
                    converted.byte_size,
                    converted.episode_index,
                    ManifestFacts {
                        observation_space: space,
                        provenance,
                        license: req.license.unwrap_or_else(|| self.default_license.clone()),
                        created_at: now.clone(),
                    },
                );
                let json = serde_json::to_string(&manifest).map_err(ApiError::internal)?;
                self.store_objects(&manifest, &json, canonical.path()).await?;
                drop(canonical);
                let mut tx = self.db.begin().await?;
                let created = db::insert_version(&mut tx, &manifest, &json).await?;
                let mut moved = Vec::new();
                if space == ObservationSpace::Simulator && req.latest != LatestPolicy::Keep {
                    let only_if_absent = req.latest == LatestPolicy::IfAbsent;
                    if db::set_tag(&mut tx, &task.id, &TagName::latest(), &version, &now, only_if_absent).await? {
                        moved.push(TagName::LATEST.to_owned());
                    }
                }
                moved.extend(self.set_tags(&mut tx, &task, &version, space, &req.tags, &now).await?);
                tx.commit().await?;
                let record = self
                    .db
                    .version(&task.id, &version)
                    .await?
                    .ok_or_else(|| ApiError::Internal("version row vanished after commit".into()))?;
                tracing::info!(task = %task.id, version = %version, created, "ingested dataset version");
                return Ok(IngestOutcome {
                    created,
                    version: record,
                    moved_tags: moved,
                });
            };

            // Identical bytes: nothing to store. Tags the request names explicitly still apply.
            let space = existing
                .observation_space
                .parse::<ObservationSpace>()
                .map_err(ApiError::Internal)?;
            let mut tx = self.db.begin().await?;
            let moved = self.set_tags(&mut tx, &task, &version, space, &req.tags, &now).await?;
            tx.commit().await?;
            let record = self.db.version(&task.id, &version).await?.expect("exists");
            Ok(IngestOutcome {
                created: false,
                version: record,
                moved_tags: moved,
            })
        })
        .await
    }

    async fn set_tags(
        &self,
        tx: &mut sqlx::Transaction<'static, sqlx::Any>,
        task: &Task,
        version: &VersionId,
        space: ObservationSpace,
        tags: &[TagName],
        now: &str,
    ) -> Result<Vec<String>, ApiError> {
        let mut moved = Vec::new();
        for tag in tags {
            if tag.as_str() == TagName::LATEST && space == ObservationSpace::Paper {
                return Err(ApiError::InvalidArgument(
                    "latest must name a version in the simulator's observation space; this one is in the \
                     paper's"
                        .into(),
                ));
            }
            if db::set_tag(tx, &task.id, tag, version, now, false).await? {
                moved.push(tag.to_string());
            }
        }
        Ok(moved)
    }

    /// Points `tag` of `task` at an existing version.
    pub async fn tag(&self, task: &str, tag: &str, version: &str) -> Result<VersionRecord, ApiError> {
        let tag: TagName = tag.parse().map_err(|e| ApiError::InvalidArgument(format!("{e}")))?;
        let version_id: VersionId = version.parse().map_err(|e| ApiError::InvalidArgument(format!("{e}")))?;
        let (task, record) = self.resolve(task, version_id.as_str()).await?;
        let space = record
            .observation_space
            .parse::<ObservationSpace>()
            .map_err(ApiError::Internal)?;
        let mut tx = self.db.begin().await?;
        self.set_tags(&mut tx, task, &version_id, space, &[tag], &now_rfc3339())
            .await?;
        tx.commit().await?;
        Ok(self.resolve(task.id.as_str(), version_id.as_str()).await?.1)
    }
}

fn ids(record: &VersionRecord) -> Result<(dsrl_suite::TaskId, VersionId), ApiError> {
    let task = record.task.parse().map_err(ApiError::internal)?;
    let version = record.version.parse().map_err(ApiError::internal)?;
    Ok((task, version))
}

/// The gate (in-process and across replicas) of one filter applied to one parent version: held while the filter
/// is computed, and while garbage collection removes its result.
fn derivation_gate(task: &str, parent: &str, canonical_filter: &str) -> String {
    format!("{task}/{parent}/{canonical_filter}")
}

/// Which filtered versions garbage collection removes.
#[derive(Debug, Clone)]
pub struct GcPolicy {
    /// Unused (not asked for by a filter) for longer than this: removed.
    pub max_idle: std::time::Duration,
    /// All filtered versions together above this: the least recently used are removed until they fit.
    pub max_bytes: u64,
}

#[derive(Debug, Default, serde::Serialize)]
pub struct GcReport {
    pub removed: Vec<db::DerivationRecord>,
    pub kept: usize,
    pub derived_bytes_before: u64,
    pub derived_bytes_after: u64,
}
