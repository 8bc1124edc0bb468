-- driftwatch schema v1. Portable SQL (SQLite now, PostgreSQL later): integer times in ns
-- since the Unix epoch, text ids, JSON payloads as text.

CREATE TABLE machines (
    id          TEXT PRIMARY KEY,
    kinematics  TEXT NOT NULL,
    created_ns  BIGINT NOT NULL
);

-- One row per measurement cycle, from the moment it starts.
CREATE TABLE cycles (
    machine_id  TEXT NOT NULL REFERENCES machines(id),
    cycle       BIGINT NOT NULL,
    started_ns  BIGINT NOT NULL,
    trigger     TEXT NOT NULL,          -- why it ran (warm-up, after stop, operator, ...)
    attempt     INTEGER NOT NULL DEFAULT 1,
    status      TEXT NOT NULL CHECK (status IN ('open', 'ok', 'rejected', 'abandoned')),
    finished_ns BIGINT,
    reason      TEXT,                   -- why it was rejected or abandoned
    PRIMARY KEY (machine_id, cycle)
);

-- Every detection as received (the contract's /probe/detection JSON).
CREATE TABLE detections (
    machine_id  TEXT NOT NULL,
    cycle       BIGINT NOT NULL,
    seq         INTEGER NOT NULL,
    t_ns        BIGINT NOT NULL,
    step        TEXT NOT NULL,
    payload     TEXT NOT NULL,
    PRIMARY KEY (machine_id, cycle, seq),
    FOREIGN KEY (machine_id, cycle) REFERENCES cycles(machine_id, cycle)
);

-- The solved result of a cycle (the contract's /cycle/result JSON) and its validation.
CREATE TABLE results (
    machine_id      TEXT NOT NULL,
    cycle           BIGINT NOT NULL,
    t_ns            BIGINT NOT NULL,    -- reference time
    status          TEXT NOT NULL CHECK (status IN ('ok', 'rejected')),
    reason          TEXT,
    residual_rms_um DOUBLE PRECISION,
    chi2            DOUBLE PRECISION,
    dof             INTEGER,
    payload         TEXT NOT NULL,
    PRIMARY KEY (machine_id, cycle),
    FOREIGN KEY (machine_id, cycle) REFERENCES cycles(machine_id, cycle)
);

-- One row per error of a result, for time series.
CREATE TABLE result_values (
    machine_id  TEXT NOT NULL,
    cycle       BIGINT NOT NULL,
    name        TEXT NOT NULL,
    t_ns        BIGINT NOT NULL,
    value       DOUBLE PRECISION NOT NULL,
    sigma       DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (machine_id, cycle, name),
    FOREIGN KEY (machine_id, cycle) REFERENCES results(machine_id, cycle)
);
CREATE INDEX result_values_by_time ON result_values (machine_id, name, t_ns);

-- Every compensation set ever served, versioned; the NC reads the newest.
CREATE TABLE compensation_sets (
    machine_id    TEXT NOT NULL REFERENCES machines(id),
    version       BIGINT NOT NULL,
    valid_from_ns BIGINT NOT NULL,
    source        TEXT NOT NULL CHECK (source IN ('measured', 'predicted')),
    cycle         BIGINT,
    reason        TEXT NOT NULL,
    payload       TEXT NOT NULL,
    PRIMARY KEY (machine_id, version)
);

-- Alert lifecycle events (raised, updated, resolved, acknowledged).
CREATE TABLE alert_events (
    machine_id  TEXT NOT NULL REFERENCES machines(id),
    alert_id    BIGINT NOT NULL,
    seq         INTEGER NOT NULL,
    t_ns        BIGINT NOT NULL,
    kind        TEXT NOT NULL,
    rule        TEXT NOT NULL,
    severity    TEXT NOT NULL,
    message     TEXT NOT NULL,
    value       DOUBLE PRECISION,
    PRIMARY KEY (machine_id, alert_id, seq)
);

-- Down-sampled series (at least one sample a minute); the raw stream is in MCAP.
CREATE TABLE spindle_samples (
    machine_id  TEXT NOT NULL REFERENCES machines(id),
    t_ns        BIGINT NOT NULL,
    rpm         DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (machine_id, t_ns)
);

CREATE TABLE temperature_samples (
    machine_id  TEXT NOT NULL REFERENCES machines(id),
    t_ns        BIGINT NOT NULL,
    sensor      TEXT NOT NULL,
    celsius     DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (machine_id, sensor, t_ns)
);

-- The MCAP files of each machine: written as NAME.mcap.partial, renamed when closed.
CREATE TABLE mcap_files (
    machine_id  TEXT NOT NULL REFERENCES machines(id),
    path        TEXT NOT NULL,
    opened_ns   BIGINT NOT NULL,
    closed_ns   BIGINT,
    status      TEXT NOT NULL CHECK (status IN ('open', 'closed', 'recovered')),
    messages    BIGINT,
    PRIMARY KEY (path)
);
