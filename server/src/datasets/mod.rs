//! The dataset service, each of its sides in this folder: where datasets live (`service`: Parquet files and
//! manifests in an object store, their metadata and tags in the metadata database; the only module that touches
//! both, so the order "file, then manifest, then row" that makes ingest atomic is written in one place), uploads and
//! their conversion (`uploads`, `converter`), the REST routes (`rest`, `download`, DSRL's legacy URLs in
//! `dsrl_download`), the gRPC service (`grpc`), the browser's pages (`pages`) and the starters a fresh server hosts
//! (`starter`). The database and the object store themselves are opened by `dsrl-service`, which the evaluators
//! share.

pub mod converter;
pub mod download;
pub mod dsrl_download;
pub mod grpc;
pub mod pages;
pub mod rest;
pub mod service;
pub mod starter;
pub mod uploads;
pub use dsrl_service::{db, objects};
