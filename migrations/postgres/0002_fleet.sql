-- Several service processes on one database share a fleet: each machine is run by the one
-- process holding its lease, renewed while it runs. `term` grows by one every time a machine
-- changes hands; the holder's writes of cycles and compensation sets are checked against it
-- (fenced) and carry it, so that the stored data shows who wrote what. Times are the
-- database's clock, ms since the Unix epoch, so that the processes' own clocks never compare.
CREATE TABLE leases (
    machine_id  TEXT PRIMARY KEY,
    holder      TEXT NOT NULL,
    url         TEXT,                   -- where the holder's API answers
    term        BIGINT NOT NULL,
    expires_ms  BIGINT NOT NULL
);

-- Every term of every lease: who held it, from when, last renewed when, released when
-- (NULL: not released, it expired or is held).
CREATE TABLE lease_terms (
    machine_id   TEXT NOT NULL,
    term         BIGINT NOT NULL,
    holder       TEXT NOT NULL,
    acquired_ms  BIGINT NOT NULL,
    renewed_ms   BIGINT NOT NULL,
    expires_ms   BIGINT NOT NULL,
    released_ms  BIGINT,
    PRIMARY KEY (machine_id, term)
);

-- The machine time a simulated fleet shares: t0_ns at database time wall0_ms, advancing
-- `scale` ns per ns. One row.
CREATE TABLE fleet_clock (
    id        INTEGER PRIMARY KEY CHECK (id = 1),
    t0_ns     BIGINT NOT NULL,
    wall0_ms  BIGINT NOT NULL,
    scale     DOUBLE PRECISION NOT NULL
);

-- The lease term a fleet process held when it wrote the row (NULL: a single process).
ALTER TABLE cycles ADD COLUMN lease_term BIGINT;
ALTER TABLE compensation_sets ADD COLUMN lease_term BIGINT;
