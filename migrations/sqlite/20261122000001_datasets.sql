-- Hosted dataset versions. A version is immutable and content-addressed: `version` is the sha256 of its Parquet
-- bytes. The row is written last, after the file and manifest are stored, so a row always names complete data.
CREATE TABLE dataset_versions (
    task              TEXT    NOT NULL,
    version           TEXT    NOT NULL,
    byte_size         INTEGER NOT NULL,
    episodes          INTEGER NOT NULL,
    transitions       INTEGER NOT NULL,
    observation_space TEXT    NOT NULL CHECK (observation_space IN ('simulator', 'paper')),
    created_at        TEXT    NOT NULL,
    -- The full manifest JSON (also stored beside the Parquet file in the object store).
    manifest          TEXT    NOT NULL,
    PRIMARY KEY (task, version)
);

-- Movable names for versions: `latest` and named releases.
CREATE TABLE dataset_tags (
    task       TEXT NOT NULL,
    tag        TEXT NOT NULL,
    version    TEXT NOT NULL,
    updated_at TEXT NOT NULL,
    PRIMARY KEY (task, tag),
    FOREIGN KEY (task, version) REFERENCES dataset_versions (task, version)
);
