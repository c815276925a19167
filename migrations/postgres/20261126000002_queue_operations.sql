-- Claims, heartbeats, progress and failure kinds of jobs, and the dedupe index that lets a checkpoint failed for a
-- reason outside it be submitted again; see migrations/sqlite.
ALTER TABLE submissions ADD COLUMN claimed_ms BIGINT;
ALTER TABLE submissions ADD COLUMN heartbeat_ms BIGINT;
ALTER TABLE submissions ADD COLUMN episodes_done BIGINT NOT NULL DEFAULT 0;
ALTER TABLE submissions ADD COLUMN failure TEXT;
ALTER TABLE submissions ADD COLUMN scoring_ms BIGINT;
DROP INDEX submissions_checkpoint;
CREATE UNIQUE INDEX submissions_checkpoint ON submissions (task, checkpoint_sha256)
    WHERE state != 'cancelled' AND NOT (state = 'failed' AND failure = 'infrastructure');
CREATE INDEX submissions_user_claims ON submissions (user_id, claimed_ms);
