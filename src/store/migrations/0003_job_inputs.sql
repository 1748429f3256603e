-- rayd store schema, version 3: a job's input blob (an async trace's rays) named in a column
-- of its row, so that blob collection keeps it for as long as the job's record exists. Until
-- now the rays were named only inside the request's JSON, which collection does not read:
-- a trace job queued for longer than the collection's grace lost its rays. See
-- proto/store.md.

ALTER TABLE jobs ADD COLUMN input_blob TEXT;
UPDATE jobs SET input_blob = json_extract(request, '$.rays_blob')
    WHERE kind = 'trace' AND json_valid(request);
CREATE INDEX jobs_by_input ON jobs (input_blob);
