-- The per-minute series hold most of the database's rows. As WITHOUT ROWID tables their
-- primary key is the table itself instead of a second copy of every row, which halves their
-- size. This clause is SQLite's; every query stays portable, and a PostgreSQL schema states
-- the same tables with plain primary keys.

CREATE TABLE spindle_samples_compact (
    machine_id  TEXT NOT NULL REFERENCES machines(id),
    t_ns        BIGINT NOT NULL,
    rpm         DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (machine_id, t_ns)
) WITHOUT ROWID;
INSERT INTO spindle_samples_compact (machine_id, t_ns, rpm)
    SELECT machine_id, t_ns, rpm FROM spindle_samples;
DROP TABLE spindle_samples;
ALTER TABLE spindle_samples_compact RENAME TO spindle_samples;

CREATE TABLE temperature_samples_compact (
    machine_id  TEXT NOT NULL REFERENCES machines(id),
    t_ns        BIGINT NOT NULL,
    sensor      TEXT NOT NULL,
    celsius     DOUBLE PRECISION NOT NULL,
    PRIMARY KEY (machine_id, sensor, t_ns)
) WITHOUT ROWID;
INSERT INTO temperature_samples_compact (machine_id, t_ns, sensor, celsius)
    SELECT machine_id, t_ns, sensor, celsius FROM temperature_samples;
DROP TABLE temperature_samples;
ALTER TABLE temperature_samples_compact RENAME TO temperature_samples;
