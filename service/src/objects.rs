//! The object store holding Parquet files and manifests: a local folder by default, S3 when configured. Keys:
//! `datasets/<task>/<version>.parquet` and `datasets/<task>/<version>.manifest.json`. Writes to a key are atomic
//! (local: write a staging file, then rename; S3: complete a multipart upload), so a key never holds half a file.

use std::io::{Read, Seek, SeekFrom};
use std::ops::Range;
use std::path::Path as FsPath;
use std::sync::Arc;

use bytes::Bytes;
use futures::future::BoxFuture;
use futures::stream::{BoxStream, StreamExt, TryStreamExt};
use futures::{FutureExt, TryFutureExt};
use object_store::aws::AmazonS3Builder;
use object_store::local::LocalFileSystem;
use object_store::path::Path;
use object_store::prefix::PrefixStore;
use object_store::{GetOptions, GetRange, GetResultPayload, ObjectStore, ObjectStoreExt, PutPayload, WriteMultipart};
use parquet::arrow::arrow_reader::ArrowReaderOptions;
use parquet::arrow::async_reader::AsyncFileReader;
use parquet::errors::ParquetError;
use parquet::file::metadata::{ParquetMetaData, ParquetMetaDataReader};
use tokio::io::AsyncReadExt;

use crate::config::{StorageBackend, StorageConfig};

/// Size of the parts of a multipart upload and of the reads that feed it.
const UPLOAD_PART_BYTES: usize = 16 << 20;
/// Size of the reads that stream a local file to a client: large enough that per-chunk overhead vanishes.
const DOWNLOAD_CHUNK_BYTES: usize = 1 << 20;

pub fn build(config: &StorageConfig, data_dir: &FsPath) -> anyhow::Result<Arc<dyn ObjectStore>> {
    match config.backend {
        StorageBackend::Local => {
            let root = data_dir.join("objects");
            std::fs::create_dir_all(&root)?;
            Ok(Arc::new(LocalFileSystem::new_with_prefix(&root)?))
        }
        StorageBackend::S3 => {
            let s3 = &config.s3;
            anyhow::ensure!(
                !s3.bucket.is_empty(),
                "storage.s3.bucket must be set for the s3 backend"
            );
            let mut builder = AmazonS3Builder::from_env()
                .with_bucket_name(&s3.bucket)
                .with_allow_http(s3.allow_http);
            if let Some(region) = &s3.region {
                builder = builder.with_region(region);
            }
            if let Some(endpoint) = &s3.endpoint {
                builder = builder.with_endpoint(endpoint);
            }
            let store = builder.build()?;
            Ok(if s3.prefix.is_empty() {
                Arc::new(store)
            } else {
                Arc::new(PrefixStore::new(store, s3.prefix.as_str()))
            })
        }
    }
}

pub fn dataset_key(task: &str, version: &str) -> Path {
    Path::from(format!("datasets/{task}/{version}.parquet"))
}

/// A DSRL-layout HDF5 export, by the sha256 of its bytes.
pub fn hdf5_key(digest: &str) -> Path {
    Path::from(format!("hdf5/{digest}.hdf5"))
}

pub fn manifest_key(task: &str, version: &str) -> Path {
    Path::from(format!("datasets/{task}/{version}.manifest.json"))
}

/// Copies a local file to `dest` as one atomic object; returns the stored size.
pub async fn upload_file(store: &dyn ObjectStore, local: &FsPath, dest: &Path) -> object_store::Result<u64> {
    let upload = store.put_multipart(dest).await?;
    let mut writer = WriteMultipart::new_with_chunk_size(upload, UPLOAD_PART_BYTES);
    let mut file = tokio::fs::File::open(local)
        .await
        .map_err(|source| object_store::Error::Generic {
            store: "upload",
            source: Box::new(source),
        })?;
    let mut buf = vec![0u8; UPLOAD_PART_BYTES];
    loop {
        let n = match file.read(&mut buf).await {
            Ok(0) => break,
            Ok(n) => n,
            Err(source) => {
                writer.abort().await?;
                return Err(object_store::Error::Generic {
                    store: "upload",
                    source: Box::new(source),
                });
            }
        };
        writer.wait_for_capacity(4).await?;
        writer.write(&buf[..n]);
    }
    writer.finish().await?;
    Ok(store.head(dest).await?.size)
}

/// Moves a local file to `key` under a local object store's `root` with one atomic rename; `None` when the two are
/// on different filesystems (then the caller copies).
pub async fn rename_into(root: &FsPath, file: &FsPath, key: &Path) -> std::io::Result<Option<u64>> {
    let dest = root.join(key.as_ref());
    let parent = dest.parent().expect("object keys have a folder").to_owned();
    tokio::fs::create_dir_all(&parent).await?;
    match tokio::fs::rename(file, &dest).await {
        Ok(()) => {}
        Err(e) if e.kind() == std::io::ErrorKind::CrossesDevices => return Ok(None),
        Err(e) => return Err(e),
    }
    // Make the rename itself durable.
    tokio::task::spawn_blocking(move || std::fs::File::open(&parent)?.sync_all())
        .await
        .map_err(std::io::Error::other)??;
    Ok(Some(tokio::fs::metadata(&dest).await?.len()))
}

pub async fn put_bytes(store: &dyn ObjectStore, dest: &Path, bytes: Vec<u8>) -> object_store::Result<()> {
    store.put(dest, PutPayload::from(bytes)).await.map(|_| ())
}

/// The bytes of `key` (or of `range` of it) as a stream. Local files are read in large chunks on a blocking
/// thread; object_store's own local stream reads 8 KiB at a time, which caps throughput well below the disk.
pub async fn read(
    store: &dyn ObjectStore,
    key: &Path,
    range: Option<Range<u64>>,
) -> object_store::Result<BoxStream<'static, std::io::Result<Bytes>>> {
    let options = GetOptions {
        range: range.map(GetRange::Bounded),
        ..Default::default()
    };
    let result = store.get_opts(key, options).await?;
    let byte_range = result.range.clone();
    match result.payload {
        GetResultPayload::File(file, _) => Ok(stream_file(file, byte_range)),
        GetResultPayload::Stream(stream) => Ok(stream.map_err(std::io::Error::other).boxed()),
    }
}

fn stream_file(mut file: std::fs::File, range: Range<u64>) -> BoxStream<'static, std::io::Result<Bytes>> {
    let (tx, rx) = tokio::sync::mpsc::channel::<std::io::Result<Bytes>>(4);
    tokio::task::spawn_blocking(move || {
        let mut remaining = range.end - range.start;
        if let Err(e) = file.seek(SeekFrom::Start(range.start)) {
            let _ = tx.blocking_send(Err(e));
            return;
        }
        while remaining > 0 {
            let want = remaining.min(DOWNLOAD_CHUNK_BYTES as u64);
            // Not `vec![0; n]`: zero-filling a buffer that is overwritten at once costs a pass over every byte.
            let mut buf = Vec::with_capacity(want as usize);
            match (&mut file).take(want).read_to_end(&mut buf) {
                Ok(n) if n as u64 == want => {
                    remaining -= want;
                    // A closed channel means the client went away: stop reading.
                    if tx.blocking_send(Ok(Bytes::from(buf))).is_err() {
                        return;
                    }
                }
                Ok(_) => {
                    let _ = tx.blocking_send(Err(std::io::ErrorKind::UnexpectedEof.into()));
                    return;
                }
                Err(e) => {
                    let _ = tx.blocking_send(Err(e));
                    return;
                }
            }
        }
    });
    tokio_stream::wrappers::ReceiverStream::new(rx).boxed()
}

/// Random access to a Parquet object of known size, for the async Parquet reader (byte ranges only: the footer
/// and the column chunks it asks for, never the whole object).
#[derive(Debug, Clone)]
pub struct ParquetObject {
    store: Arc<dyn ObjectStore>,
    key: Path,
    size: u64,
}

impl ParquetObject {
    pub fn new(store: Arc<dyn ObjectStore>, key: Path, size: u64) -> Self {
        ParquetObject { store, key, size }
    }
}

impl AsyncFileReader for ParquetObject {
    fn get_bytes(&mut self, range: Range<u64>) -> BoxFuture<'_, parquet::errors::Result<Bytes>> {
        self.store
            .get_range(&self.key, range)
            .map_err(|e| ParquetError::External(Box::new(e)))
            .boxed()
    }

    fn get_metadata<'a>(
        &'a mut self,
        options: Option<&'a ArrowReaderOptions>,
    ) -> BoxFuture<'a, parquet::errors::Result<Arc<ParquetMetaData>>> {
        async move {
            let size = self.size;
            let metadata = ParquetMetaDataReader::new()
                .with_arrow_reader_options(options)
                .load_and_finish(self, size)
                .await?;
            Ok(Arc::new(metadata))
        }
        .boxed()
    }
}
