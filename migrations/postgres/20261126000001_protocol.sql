-- The protocol version, the trained-on dataset version and the reference record of a submission; see
-- migrations/sqlite.
ALTER TABLE submissions ADD COLUMN protocol_version TEXT;
ALTER TABLE submissions ADD COLUMN dataset_version TEXT;
ALTER TABLE submissions ADD COLUMN reference TEXT;
