-- What an evaluator shows while it scores, and what makes the queue fair:
-- claimed_ms: when the job was last claimed (the queue serves the user served longest ago first);
-- heartbeat_ms: the evaluator's last heartbeat; episodes_done: episodes scored so far in this attempt;
-- failure: why a failed job failed, 'checkpoint' (it would fail again) or 'infrastructure' (an evaluator, worker or
-- policy process lost to something outside the checkpoint; the same checkpoint may be submitted again);
-- scoring_ms: how long the finished attempt took, claim to result (the queue's estimates come from them).
ALTER TABLE submissions ADD COLUMN claimed_ms INTEGER;
ALTER TABLE submissions ADD COLUMN heartbeat_ms INTEGER;
ALTER TABLE submissions ADD COLUMN episodes_done INTEGER NOT NULL DEFAULT 0;
ALTER TABLE submissions ADD COLUMN failure TEXT;
ALTER TABLE submissions ADD COLUMN scoring_ms INTEGER;
-- Dedupe: one live submission per checkpoint and task; a cancelled one, or one that failed for a reason outside
-- its checkpoint, may be submitted again.
DROP INDEX submissions_checkpoint;
CREATE UNIQUE INDEX submissions_checkpoint ON submissions (task, checkpoint_sha256)
    WHERE state != 'cancelled' AND NOT (state = 'failed' AND failure = 'infrastructure');
CREATE INDEX submissions_user_claims ON submissions (user_id, claimed_ms);
