-- cubecal profile store, schema version 1: every committed profile, one row per passing run.
-- Applied by `cubecal profile migrate` (src/profile/postgres.rs lists the migrations in order).
--
-- A camera's versions share `identity` (the raw identity's UTF-8 bytes: a bytea, because a hostile USB
-- serial may hold NUL, which PostgreSQL's text refuses). `state` says which version is in use; the
-- partial unique index makes "two current profiles of one camera" impossible whatever a client does.
CREATE TABLE cubecal_profile (
    id               bigserial   PRIMARY KEY,
    identity         bytea       NOT NULL,
    -- profile::store::folder_name(identity): the same safe name the file store gives the camera
    folder           text        NOT NULL,
    state            text        NOT NULL CHECK (state IN ('current', 'history', 'rolled_back')),
    -- idempotency key of the run (a second commit of the same run stores nothing)
    run_id           text        NOT NULL UNIQUE,
    -- the profile document's exact bytes (the file store's current.json) and their SHA-256
    document         bytea       NOT NULL,
    sha256           text        NOT NULL,
    created          text        NOT NULL,
    -- provenance, for audits: which station, rig, software and verdict produced the profile
    station          text        NOT NULL,
    rig_name         text        NOT NULL,
    rig_sha256       text        NOT NULL,
    software_version text        NOT NULL,
    verdict_pass     boolean     NOT NULL CHECK (verdict_pass),
    report           text,
    committed_at     timestamptz NOT NULL DEFAULT now()
);

CREATE UNIQUE INDEX cubecal_profile_one_current ON cubecal_profile (identity) WHERE state = 'current';
CREATE INDEX cubecal_profile_versions ON cubecal_profile (identity, id);
CREATE INDEX cubecal_profile_current_folder ON cubecal_profile (folder) WHERE state = 'current';
