-- Compact storage of compensation sets and detections.
--
-- Predicted sets go out every few minutes while the machine works: a year holds over a
-- hundred thousand. Each row now keeps only what cannot be derived: the columns, and in
-- `payload` the errors and their uncertainties ({"errors": {...}, "sigma": {...}}); the NC
-- offsets are computed from the errors when read. Rows written before keep their whole set
-- as payload, which holds the same two maps, so they read the same. WITHOUT ROWID, as in
-- 0002, stores the table once instead of a second copy as its primary-key index.

CREATE TABLE compensation_sets_compact (
    machine_id    TEXT NOT NULL REFERENCES machines(id),
    version       BIGINT NOT NULL,
    valid_from_ns BIGINT NOT NULL,
    source        TEXT NOT NULL CHECK (source IN ('measured', 'predicted')),
    cycle         BIGINT,
    reason        TEXT NOT NULL,
    payload       TEXT NOT NULL,
    PRIMARY KEY (machine_id, version)
) WITHOUT ROWID;
INSERT INTO compensation_sets_compact
    SELECT machine_id, version, valid_from_ns, source, cycle, reason, payload
    FROM compensation_sets;
DROP TABLE compensation_sets;
ALTER TABLE compensation_sets_compact RENAME TO compensation_sets;

-- Detections likewise: one copy of each row instead of the row plus its key index.
CREATE TABLE detections_compact (
    machine_id  TEXT NOT NULL,
    cycle       BIGINT NOT NULL,
    seq         INTEGER NOT NULL,
    t_ns        BIGINT NOT NULL,
    step        TEXT NOT NULL,
    payload     TEXT NOT NULL,
    PRIMARY KEY (machine_id, cycle, seq),
    FOREIGN KEY (machine_id, cycle) REFERENCES cycles(machine_id, cycle)
) WITHOUT ROWID;
INSERT INTO detections_compact
    SELECT machine_id, cycle, seq, t_ns, step, payload FROM detections;
DROP TABLE detections;
ALTER TABLE detections_compact RENAME TO detections;
