-- rayd store schema, version 2: the delivery of render jobs' callbacks. See proto/store.md.
-- One row per job that asked for a callback, written when the job is submitted, so that a
-- delivery still owed after a crash is found at the next start. Deleted with its job.

CREATE TABLE job_callbacks (
    job_id     TEXT PRIMARY KEY REFERENCES jobs (id) ON DELETE CASCADE,
    url        TEXT NOT NULL,
    state      TEXT NOT NULL CHECK (state IN ('pending', 'delivered', 'failed')),
    attempts   BIGINT NOT NULL CHECK (attempts >= 0),
    error      TEXT,
    updated_at BIGINT NOT NULL
);
CREATE INDEX job_callbacks_by_state ON job_callbacks (state);
