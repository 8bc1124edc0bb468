-- Verifications (issue: the R-test as a reference): a reference instrument's result compared
-- with the tool-setter result nearest in time, as the API returned it.
CREATE TABLE verifications (
    machine_id    TEXT NOT NULL REFERENCES machines(id),
    id            INTEGER NOT NULL,
    t_ns          BIGINT NOT NULL,     -- the reference time
    created_ns    BIGINT NOT NULL,     -- the service clock when it was posted
    requested_by  TEXT NOT NULL,
    instrument    TEXT NOT NULL,
    method        TEXT NOT NULL,       -- 'interpolated' or 'nearest'
    exceeds       BOOLEAN NOT NULL,    -- any error beyond k combined sigma
    worst_z       DOUBLE PRECISION NOT NULL,
    payload       TEXT NOT NULL,       -- the verification (JSON)
    PRIMARY KEY (machine_id, id)
);
CREATE INDEX verifications_by_time ON verifications (machine_id, t_ns);

-- The setter results around a reference time are read by time.
CREATE INDEX results_by_time ON results (machine_id, t_ns);
