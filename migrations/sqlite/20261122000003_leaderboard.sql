-- The leaderboard: users who submit (bearer tokens, stored as sha256 only), submissions and their evaluation.
CREATE TABLE users (
    id           INTEGER PRIMARY KEY,
    name         TEXT NOT NULL UNIQUE,
    token_sha256 TEXT NOT NULL UNIQUE,
    created_at   TEXT NOT NULL
);

-- A submission is one entry on one task: one checkpoint for every threshold or one per threshold, stored in the
-- object store under `submissions/<checkpoint_sha256>/`. It is also the evaluation job: a durable queue in SQL.
-- An evaluator claims it by writing its lease (owner + expiry); a heartbeat extends the lease while it plays; a
-- claim whose lease ran out is taken over by any evaluator, so a job outlives the process that started it.
CREATE TABLE submissions (
    id                 INTEGER PRIMARY KEY,
    user_id            INTEGER NOT NULL REFERENCES users (id),
    task               TEXT    NOT NULL,
    name               TEXT    NOT NULL,
    checkpoint_sha256  TEXT    NOT NULL,
    -- JSON: one object per checkpoint (slot, cost threshold or null, architecture name).
    checkpoints        TEXT    NOT NULL,
    state              TEXT    NOT NULL CHECK (state IN ('queued', 'running', 'finished', 'failed', 'cancelled')),
    reason             TEXT,
    attempts           INTEGER NOT NULL DEFAULT 0,
    lease_owner        TEXT,
    lease_expires_ms   INTEGER,
    created_at         TEXT    NOT NULL,
    created_ms         INTEGER NOT NULL,
    started_at         TEXT,
    finished_at        TEXT,
    episodes_per_threshold INTEGER NOT NULL,
    -- Means over the task's three cost thresholds (spec 4.1), set when finished.
    normalized_reward  REAL,
    normalized_cost    REAL
);
-- Dedupe: one live submission per checkpoint and task (a cancelled one may be submitted again).
CREATE UNIQUE INDEX submissions_checkpoint ON submissions (task, checkpoint_sha256) WHERE state != 'cancelled';
CREATE INDEX submissions_queue ON submissions (state, id);
CREATE INDEX submissions_user ON submissions (user_id, created_ms);

-- Every evaluated episode, by threshold and episode index (the seed behind the index is the server's secret).
CREATE TABLE evaluation_episodes (
    submission_id  INTEGER NOT NULL REFERENCES submissions (id),
    cost_threshold REAL    NOT NULL,
    episode        INTEGER NOT NULL,
    reward_return  REAL    NOT NULL,
    cost_return    REAL    NOT NULL,
    length         INTEGER NOT NULL,
    PRIMARY KEY (submission_id, cost_threshold, episode)
);
