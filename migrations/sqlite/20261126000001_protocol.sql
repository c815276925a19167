-- What makes a result comparable (see suite/src/protocol.rs) and what it was trained on:
-- the protocol version a submission was scored under (set when it finishes; NULL for results scored before the
-- protocol was recorded), the dataset version its checkpoint says it was trained on (NULL when it does not say),
-- and, for a reference entry imported from data/reference/results.jsonl, its record (method, seed, training budget,
-- code commit, scoring) as JSON.
ALTER TABLE submissions ADD COLUMN protocol_version TEXT;
ALTER TABLE submissions ADD COLUMN dataset_version TEXT;
ALTER TABLE submissions ADD COLUMN reference TEXT;
