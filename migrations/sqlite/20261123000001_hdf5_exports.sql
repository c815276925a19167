-- DSRL-layout HDF5 exports of versions (what DSRL's own `get_dataset` downloads from `/download/{file}`). Each is
-- converted once from the version's Parquet and stored content-addressed under `hdf5/<sha256>.hdf5`; this table
-- maps the version to it, so a repeated request is a lookup.
CREATE TABLE dataset_hdf5_exports (
    task       TEXT NOT NULL,
    version    TEXT NOT NULL,
    digest     TEXT NOT NULL,
    byte_size  INTEGER NOT NULL,
    created_at TEXT NOT NULL,
    PRIMARY KEY (task, version),
    FOREIGN KEY (task, version) REFERENCES dataset_versions (task, version)
);
