-- Diagnoses run through the API on a stored time window (issue 5): the request and the
-- result as the diagnose command writes it (diagnosis.json), or why it failed.
CREATE TABLE diagnoses (
    machine_id    TEXT NOT NULL REFERENCES machines(id),
    id            INTEGER NOT NULL,
    requested_ns  BIGINT NOT NULL,
    requested_by  TEXT NOT NULL,
    from_ns       BIGINT NOT NULL,
    to_ns         BIGINT NOT NULL,
    status        TEXT NOT NULL,   -- 'done' or 'failed'
    summary       TEXT NOT NULL,
    result        TEXT,            -- JSON, when done
    PRIMARY KEY (machine_id, id)
);
