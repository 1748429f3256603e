-- rayd store schema, version 1. See proto/store.md.
-- Times are milliseconds since the Unix epoch (UTC). Ids are text: blob and scene ids are
-- 64 lowercase hex digits (blake3), job ids 32.
-- Portable to PostgreSQL as written (BIGINT, DOUBLE PRECISION, TEXT, CHECK, ON DELETE CASCADE).

CREATE TABLE scenes (
    id             TEXT PRIMARY KEY,
    content_type   TEXT NOT NULL,
    name           TEXT,
    summary        TEXT NOT NULL,
    created_at     BIGINT NOT NULL,
    latest_version BIGINT NOT NULL CHECK (latest_version >= 1)
);
CREATE INDEX scenes_by_page ON scenes (created_at, id);

CREATE TABLE scene_versions (
    scene_id   TEXT NOT NULL REFERENCES scenes (id) ON DELETE CASCADE,
    version    BIGINT NOT NULL CHECK (version >= 1),
    blob       TEXT NOT NULL,
    created_at BIGINT NOT NULL,
    PRIMARY KEY (scene_id, version)
);
CREATE INDEX scene_versions_by_blob ON scene_versions (blob);

CREATE TABLE jobs (
    id              TEXT PRIMARY KEY,
    kind            TEXT NOT NULL CHECK (kind IN ('trace', 'render')),
    scene_id        TEXT NOT NULL,
    version         BIGINT NOT NULL,
    request         TEXT NOT NULL,
    priority        BIGINT NOT NULL CHECK (priority BETWEEN 0 AND 100),
    state           TEXT NOT NULL
                    CHECK (state IN ('queued', 'running', 'succeeded', 'failed', 'cancelled')),
    progress        DOUBLE PRECISION NOT NULL CHECK (progress >= 0 AND progress <= 1),
    created_at      BIGINT NOT NULL,
    started_at      BIGINT,
    finished_at     BIGINT,
    stats           TEXT,
    error           TEXT,
    result_blob     TEXT,
    result_type     TEXT,
    idempotency_key TEXT UNIQUE,
    expires_at      BIGINT,
    FOREIGN KEY (scene_id, version) REFERENCES scene_versions (scene_id, version)
        ON DELETE CASCADE
);
CREATE INDEX jobs_by_page ON jobs (created_at, id);
CREATE INDEX jobs_by_state ON jobs (state, priority, created_at);
CREATE INDEX jobs_by_expiry ON jobs (expires_at);
CREATE INDEX jobs_by_result ON jobs (result_blob);
CREATE INDEX jobs_by_scene ON jobs (scene_id, version);

CREATE TABLE job_results (
    job_id       TEXT NOT NULL REFERENCES jobs (id) ON DELETE CASCADE,
    frame        BIGINT NOT NULL CHECK (frame >= 0),
    blob         TEXT NOT NULL,
    content_type TEXT NOT NULL,
    PRIMARY KEY (job_id, frame)
);
CREATE INDEX job_results_by_blob ON job_results (blob);
