-- When each filtered version was last asked for (milliseconds since the epoch); see migrations/sqlite.
ALTER TABLE dataset_derivations ADD COLUMN last_used_ms BIGINT NOT NULL DEFAULT 0;
