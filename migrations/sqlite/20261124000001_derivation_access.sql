-- When each filtered version was last asked for (milliseconds since the epoch), so that `dsrl-server gc` removes
-- the ones nobody uses first. Existing rows start at 0: never used since this was recorded.
ALTER TABLE dataset_derivations ADD COLUMN last_used_ms INTEGER NOT NULL DEFAULT 0;
