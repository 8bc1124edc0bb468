-- The store's epoch: a random name drawn when the schema is made, so that a set's ETag
-- (machine, epoch, version) never names two different sets, even when a database is emptied
-- and its versions start again at 1.
CREATE TABLE store_meta (
    key    TEXT PRIMARY KEY NOT NULL,
    value  TEXT NOT NULL
);
INSERT INTO store_meta (key, value) VALUES ('epoch', lower(hex(randomblob(6))));

-- Each machine's alert engine as it was after its last change (JSON: open alerts with their
-- ids and acknowledgements, the last id given out, references, last values), so that a
-- restart goes on from what the operators saw.
CREATE TABLE alert_state (
    machine_id  TEXT PRIMARY KEY NOT NULL REFERENCES machines(id),
    t_ns        BIGINT NOT NULL,
    state       TEXT NOT NULL
);
