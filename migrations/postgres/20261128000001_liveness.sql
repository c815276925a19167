-- One row that `/healthz` writes and commits on every probe: a database that answers reads but cannot commit (an
-- unwritable volume, a full disk) is reported as degraded instead of "ok".
CREATE TABLE health_probe (
    id BIGINT PRIMARY KEY,
    probed_ms BIGINT NOT NULL
);
-- Every evaluator, wherever it runs, says here that it is alive while it waits for work and while it scores
-- (`seen_ms`); queue estimates count only those seen recently, and say "unknown" when there are none.
CREATE TABLE evaluator_liveness (
    owner TEXT PRIMARY KEY,
    seen_ms BIGINT NOT NULL
);
