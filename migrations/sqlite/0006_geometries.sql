-- Linear-axis geometry versions (issue 19): a machine's measured scale, squareness and ISO 230-1
-- component errors (e.g. from a laser step diagonal), as posted through the API. The newest
-- is what every solve of the machine starts from; each cycle result names the version.
CREATE TABLE geometries (
    machine_id    TEXT NOT NULL REFERENCES machines(id),
    version       BIGINT NOT NULL,
    created_ns    BIGINT NOT NULL,     -- the service clock when it was posted
    requested_by  TEXT NOT NULL,
    source        TEXT NOT NULL,       -- what measured it, in the poster's words
    payload       TEXT NOT NULL,       -- the geometry (JSON, the LinearGeometry document)
    PRIMARY KEY (machine_id, version)
);
