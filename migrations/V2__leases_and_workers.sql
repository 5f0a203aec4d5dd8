-- Jobs claimed by workers on several machines: the claiming worker and until when its
-- lease runs (Unix seconds); the workers themselves with their last heartbeat.
ALTER TABLE captures ADD COLUMN worker TEXT;
ALTER TABLE captures ADD COLUMN lease_until DOUBLE PRECISION NOT NULL DEFAULT 0;
CREATE INDEX captures_by_lease ON captures (state, lease_until);
CREATE TABLE workers (
    name TEXT PRIMARY KEY NOT NULL,
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    started_at DOUBLE PRECISION NOT NULL,
    heartbeat_at DOUBLE PRECISION NOT NULL,
    job TEXT,
    jobs_done INTEGER NOT NULL DEFAULT 0
);
