-- Filtered datasets. A filtered version is a dataset version like any other (content-addressed, immutable);
-- `derived` keeps it out of version listings, and `dataset_derivations` maps (parent, canonical filter) to it so a
-- repeated request is a lookup, never a recomputation.
ALTER TABLE dataset_versions ADD COLUMN derived INTEGER NOT NULL DEFAULT 0;

CREATE TABLE dataset_derivations (
    task       TEXT NOT NULL,
    parent     TEXT NOT NULL,
    filter     TEXT NOT NULL,
    version    TEXT NOT NULL,
    created_at TEXT NOT NULL,
    PRIMARY KEY (task, parent, filter),
    FOREIGN KEY (task, parent) REFERENCES dataset_versions (task, version),
    FOREIGN KEY (task, version) REFERENCES dataset_versions (task, version)
);
