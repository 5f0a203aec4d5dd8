-- The station journal: one row per capture id. Portable SQL: SQLite and PostgreSQL run
-- the same migrations (refinery). IF NOT EXISTS: journals made before migrations have it.
CREATE TABLE IF NOT EXISTS captures (
    id TEXT PRIMARY KEY NOT NULL,
    dir TEXT NOT NULL,
    state TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed')),
    attempts INTEGER NOT NULL DEFAULT 0,
    subject TEXT,
    stage TEXT,
    error TEXT,
    seconds TEXT,
    result TEXT,
    queued_at DOUBLE PRECISION NOT NULL,
    started_at DOUBLE PRECISION,
    finished_at DOUBLE PRECISION,
    not_before DOUBLE PRECISION NOT NULL DEFAULT 0
);
CREATE INDEX IF NOT EXISTS captures_by_state ON captures (state, not_before, queued_at);
