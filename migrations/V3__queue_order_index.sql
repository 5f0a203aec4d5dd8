-- Claims take the oldest queued job: a partial index in that order serves them without
-- sorting the queue (SQLite and PostgreSQL both have partial indexes).
CREATE INDEX captures_queue ON captures (queued_at, id) WHERE state = 'queued';
