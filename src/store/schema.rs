//! The schema and its forward migrations.
//!
//! The schema version is `PRAGMA user_version`; `PRAGMA application_id` marks the file as an
//! axiscomp store so that another program's SQLite file is refused rather than altered.
//! `MIGRATIONS[i]` takes a store from version `i` to `i + 1`; each step runs in one transaction
//! together with the `user_version` bump, so a failed or interrupted migration leaves the file at
//! the previous version. Released steps are never edited: a change is a new step.
//!
//! Units (DESIGN §1): the store keeps the crate's internal units, so values round-trip exactly.
//! Every numeric column's name ends in its unit: `_mm`, `_rad`, `_mm2` (variance), `_c` (°C),
//! `_us` (µs since the Unix epoch, UTC). The calibration summary is the exception: it copies
//! figures out of the calibration file, which is in user units (`_um`, and µm/arcsec per DOF).
//! Tables are `STRICT`, so a value of the wrong type is refused instead of silently stored.

/// `PRAGMA application_id` of an axiscomp store ("AXCS").
pub const APPLICATION_ID: i32 = 0x4158_4353;

/// The schema version this build writes.
pub const LATEST: i64 = MIGRATIONS.len() as i64;

/// Forward migrations; `MIGRATIONS[i]` goes from version `i` to `i + 1`.
pub const MIGRATIONS: &[&str] = &[
    V1,
    V2,
    V3_FOLLOWER_MAPS,
    V4_RUN_TABLES,
    V5_AUDIT_OUTCOME,
    V6_FLAGS,
    V7_REFERENCES,
    V8_RESTATEMENTS,
    V9_MACHINES,
];

/// Version 1: the first schema.
const V1: &str = r#"
-- Calibrations of the head (DESIGN §3): the file verbatim and figures copied out of it.
CREATE TABLE calibrations (
    id               INTEGER PRIMARY KEY,
    created_us       INTEGER NOT NULL,              -- when stored
    layout_hash      TEXT    NOT NULL,              -- [meta] layout_hash: which head it fits
    file_text        TEXT    NOT NULL,              -- the calibration file (TOML, user units)
    file_created     TEXT    NOT NULL,              -- [meta] created
    poses            INTEGER NOT NULL CHECK (poses >= 0),
    rank             INTEGER NOT NULL CHECK (rank >= 0),
    condition_number REAL    NOT NULL,
    residual_rms_um  TEXT    NOT NULL CHECK (json_valid(residual_rms_um)), -- [6] per reading X1..Y3
    holdout_rms      TEXT    CHECK (holdout_rms IS NULL OR json_valid(holdout_rms)) -- [6] per DOF, µm/arcsec
) STRICT;
CREATE INDEX calibrations_layout ON calibrations (layout_hash, id);

-- Measurement runs (DESIGN §6): the plan and the configuration they were made with.
CREATE TABLE runs (
    id             INTEGER PRIMARY KEY,
    created_us     INTEGER NOT NULL,
    updated_us     INTEGER NOT NULL,
    state          TEXT    NOT NULL
                   CHECK (state IN ('planned', 'running', 'finished', 'aborted', 'failed')),
    axis           TEXT    NOT NULL,
    plan_json      TEXT    NOT NULL CHECK (json_valid(plan_json)),
    config_json    TEXT    NOT NULL CHECK (json_valid(config_json)),
    calibration_id INTEGER REFERENCES calibrations (id),
    notes          TEXT    NOT NULL DEFAULT ''
) STRICT;
CREATE INDEX runs_state ON runs (state, id);

-- One row per capture (run::Capture), written when taken; a resumed run that offers a capture
-- again is ignored by the UNIQUE key. Means, frame standard deviations (sd_) and standard
-- uncertainties (u_) in mm and rad.
CREATE TABLE captures (
    id           INTEGER PRIMARY KEY,
    run_id       INTEGER NOT NULL REFERENCES runs (id),
    run          INTEGER NOT NULL CHECK (run >= 1),
    target_index INTEGER NOT NULL CHECK (target_index >= 0),
    target_mm    REAL    NOT NULL,
    direction    TEXT    NOT NULL CHECK (direction IN ('+', '-')),
    dx_mm        REAL    NOT NULL,
    dy_mm        REAL    NOT NULL,
    dz_mm        REAL    NOT NULL,
    ex_rad       REAL    NOT NULL,
    ey_rad       REAL    NOT NULL,
    ez_rad       REAL    NOT NULL,
    sd_dx_mm     REAL    NOT NULL CHECK (sd_dx_mm >= 0),
    sd_dy_mm     REAL    NOT NULL CHECK (sd_dy_mm >= 0),
    sd_dz_mm     REAL    NOT NULL CHECK (sd_dz_mm >= 0),
    sd_ex_rad    REAL    NOT NULL CHECK (sd_ex_rad >= 0),
    sd_ey_rad    REAL    NOT NULL CHECK (sd_ey_rad >= 0),
    sd_ez_rad    REAL    NOT NULL CHECK (sd_ez_rad >= 0),
    u_dx_mm      REAL    NOT NULL CHECK (u_dx_mm >= 0),
    u_dy_mm      REAL    NOT NULL CHECK (u_dy_mm >= 0),
    u_dz_mm      REAL    NOT NULL CHECK (u_dz_mm >= 0),
    u_ex_rad     REAL    NOT NULL CHECK (u_ex_rad >= 0),
    u_ey_rad     REAL    NOT NULL CHECK (u_ey_rad >= 0),
    u_ez_rad     REAL    NOT NULL CHECK (u_ez_rad >= 0),
    frames       INTEGER NOT NULL CHECK (frames >= 0),
    material_c   REAL,
    air_c        REAL,
    unix_us      INTEGER NOT NULL,
    UNIQUE (run_id, run, target_index, direction)
) STRICT;
CREATE TRIGGER captures_immutable BEFORE UPDATE ON captures
BEGIN SELECT RAISE(ABORT, 'captures are immutable'); END;

-- Follower handovers (track::HandoverRecord), enough to re-stitch a run offline.
-- x2/y2: PSD2's X and Y; along/across: the follower axis and across it.
CREATE TABLE handovers (
    id                INTEGER PRIMARY KEY,
    run_id            INTEGER REFERENCES runs (id),  -- NULL: not taken during a run
    unix_us           INTEGER NOT NULL,
    kind              TEXT    NOT NULL CHECK (kind IN ('overlap', 'encoder')),
    before_x2_mm      REAL    NOT NULL,
    before_y2_mm      REAL    NOT NULL,
    after_x2_mm       REAL    NOT NULL,
    after_y2_mm       REAL    NOT NULL,
    n_before          INTEGER NOT NULL CHECK (n_before >= 0),
    n_after           INTEGER NOT NULL CHECK (n_after >= 0),
    sd_x2_mm          REAL    NOT NULL,
    sd_y2_mm          REAL    NOT NULL,
    encoder_before_mm REAL    NOT NULL,
    encoder_after_mm  REAL    NOT NULL,
    delta_along_mm    REAL    NOT NULL,
    delta_across_mm   REAL    NOT NULL,
    var_along_mm2     REAL    NOT NULL CHECK (var_along_mm2 >= 0),
    var_across_mm2    REAL    NOT NULL CHECK (var_across_mm2 >= 0)
) STRICT;
CREATE INDEX handovers_run ON handovers (run_id, unix_us);

-- Compensation tables (DESIGN §7); values as `comp` serialises them, CRC-32 of the payload.
CREATE TABLE tables (
    id            INTEGER PRIMARY KEY,
    kind          TEXT    NOT NULL CHECK (kind <> ''),
    axis          TEXT    NOT NULL,
    direction     TEXT    NOT NULL CHECK (direction IN ('+', '-', 'both')),
    generated_us  INTEGER NOT NULL,
    source_run_id INTEGER REFERENCES runs (id),
    values_json   TEXT    NOT NULL CHECK (json_valid(values_json)),
    crc           INTEGER NOT NULL CHECK (crc BETWEEN 0 AND 4294967295)
) STRICT;

-- Every attempt to publish a table to a PLC, with the PLC's answer.
CREATE TABLE publications (
    id         INTEGER PRIMARY KEY,
    table_id   INTEGER NOT NULL REFERENCES tables (id),
    target     TEXT    NOT NULL,                    -- PLC / plc-map name
    sequence   INTEGER NOT NULL CHECK (sequence >= 0),
    result     TEXT    NOT NULL CHECK (result IN ('accepted', 'rejected', 'failed')),
    error_code INTEGER,
    error_text TEXT,
    unix_us    INTEGER NOT NULL,
    CHECK ((result = 'accepted') = (error_code IS NULL AND error_text IS NULL))
) STRICT;
CREATE INDEX publications_table ON publications (table_id, id);

-- Who did what (DESIGN §8); append-only.
CREATE TABLE audit (
    id           INTEGER PRIMARY KEY,
    unix_us      INTEGER NOT NULL,
    uid          INTEGER,
    user         TEXT,
    pid          INTEGER,
    role         TEXT    NOT NULL,
    action       TEXT    NOT NULL CHECK (action <> ''),
    details_json TEXT    NOT NULL CHECK (json_valid(details_json))
) STRICT;
CREATE INDEX audit_time ON audit (unix_us);
CREATE TRIGGER audit_no_update BEFORE UPDATE ON audit
BEGIN SELECT RAISE(ABORT, 'the audit log is append-only'); END;
CREATE TRIGGER audit_no_delete BEFORE DELETE ON audit
BEGIN SELECT RAISE(ABORT, 'the audit log is append-only'); END;

PRAGMA application_id = 1096303443;
"#;

/// Version 2: the beam alignments per axis (issue 13), for the pre-run check and the record.
const V2: &str = r#"
CREATE TABLE alignments (
    id          INTEGER PRIMARY KEY,
    unix_us     INTEGER NOT NULL,
    axis        TEXT    NOT NULL CHECK (axis <> ''),
    from_mm     REAL    NOT NULL,
    to_mm       REAL    NOT NULL,
    passed      INTEGER NOT NULL CHECK (passed IN (0, 1)),
    yaw_rad     REAL    NOT NULL,                  -- the beam's residual angle to the travel
    pitch_rad   REAL    NOT NULL,
    check_text  TEXT    NOT NULL,
    advice_json TEXT    NOT NULL CHECK (json_valid(advice_json)),
    CHECK (from_mm < to_mm)
) STRICT;
CREATE INDEX alignments_axis ON alignments (axis, id);
"#;

/// Version 3: follower error maps (`follower::FollowerMap`), kept whole as TOML with where they
/// came from; at most one is in use.
const V3_FOLLOWER_MAPS: &str = r#"
CREATE TABLE follower_maps (
    id          INTEGER PRIMARY KEY,
    created_us  INTEGER NOT NULL,
    source      TEXT    NOT NULL CHECK (source IN ('certificate', 'self-calibration', 'both')),
    name        TEXT    NOT NULL,              -- the certificate's file, or how it was made
    map_toml    TEXT    NOT NULL,              -- the map (TOML, internal units)
    in_use      INTEGER NOT NULL DEFAULT 0 CHECK (in_use IN (0, 1))
) STRICT;
CREATE UNIQUE INDEX follower_maps_in_use ON follower_maps (in_use) WHERE in_use = 1;
"#;

/// Version 4: the compensation tables active in the PLC while a run ran (issue 15), read when
/// the run started: one row per run saying where they were read and whether they are known,
/// and one row per active table (its kind and acting axis, sequence and CRC, the stored table
/// when the store has it, and whether the PLC's staging area confirmed it by reading back).
const V4_RUN_TABLES: &str = r#"
CREATE TABLE run_tables_read (
    run_id   INTEGER PRIMARY KEY REFERENCES runs (id),
    unix_us  INTEGER NOT NULL,
    known    INTEGER NOT NULL CHECK (known IN (0, 1)),  -- 0: the PLC could not be read
    source   TEXT    NOT NULL                            -- where, or why they are unknown
) STRICT;
CREATE TABLE run_tables (
    run_id    INTEGER NOT NULL REFERENCES run_tables_read (run_id),
    kind      TEXT    NOT NULL CHECK (kind <> ''),
    axis      TEXT    NOT NULL CHECK (axis <> ''),
    table_id  INTEGER REFERENCES tables (id),
    sequence  INTEGER NOT NULL CHECK (sequence > 0),
    crc       INTEGER NOT NULL CHECK (crc BETWEEN 0 AND 4294967295),
    read_back INTEGER NOT NULL CHECK (read_back IN (0, 1)),
    PRIMARY KEY (run_id, kind, axis)
) STRICT;
"#;

/// Version 5: the audit log says what became of each request (issue 24): `done`, or `refused`
/// with the reason. Entries written before say `recorded` (the request was recorded before it
/// was handled, its outcome not kept).
const V5_AUDIT_OUTCOME: &str = r#"
ALTER TABLE audit ADD COLUMN outcome TEXT NOT NULL DEFAULT 'recorded'
    CHECK (outcome IN ('recorded', 'done', 'refused'));
ALTER TABLE audit ADD COLUMN reason TEXT;
"#;

/// Version 6: every stored capture true or flagged (issue 24). The events of a run that could
/// move its positioning reference, and the captures its judge flagged: the capture as taken
/// (JSON, `run::Capture`), why, whether it had been stored (it is moved out of `captures` in
/// the same transaction), and the operator's exclusion. A flag whose run, target and direction
/// have a capture in `captures` was retaken.
const V6_FLAGS: &str = r#"
CREATE TABLE run_events (
    id       INTEGER PRIMARY KEY,
    run_id   INTEGER NOT NULL REFERENCES runs (id),
    unix_us  INTEGER NOT NULL,
    kind     TEXT    NOT NULL CHECK (kind <> ''),
    detail   TEXT    NOT NULL
) STRICT;
CREATE INDEX run_events_run ON run_events (run_id, id);
CREATE TABLE capture_flags (
    id              INTEGER PRIMARY KEY,
    run_id          INTEGER NOT NULL REFERENCES runs (id),
    run             INTEGER NOT NULL CHECK (run >= 1),
    target_index    INTEGER NOT NULL CHECK (target_index >= 0),
    direction       TEXT    NOT NULL CHECK (direction IN ('+', '-')),
    unix_us         INTEGER NOT NULL,                      -- when it was flagged
    capture_json    TEXT    NOT NULL CHECK (json_valid(capture_json)),
    reason          TEXT    NOT NULL CHECK (reason <> ''),
    was_stored      INTEGER NOT NULL CHECK (was_stored IN (0, 1)),
    excluded_by     TEXT,
    excluded_us     INTEGER,
    excluded_reason TEXT CHECK (excluded_reason IS NULL OR excluded_reason <> '')
) STRICT;
CREATE INDEX capture_flags_run ON capture_flags (run_id, id);
"#;

/// Version 7: the zero reference survives a restart (issue 24). Each change of the live
/// zero reference (taken, shifted, a turn of the head found, a return to it that agreed,
/// forgotten) is a row; the newest is the reference in force. `state_json` is the reference
/// (`service::measure::ReferenceState`), NULL when there is none; `decoupler` names the
/// decoupling it is in the terms of, so that a service started with another one does not
/// take it.
const V7_REFERENCES: &str = r#"
CREATE TABLE zero_references (
    id          INTEGER PRIMARY KEY,
    unix_us     INTEGER NOT NULL,
    decoupler   TEXT    NOT NULL,
    state_json  TEXT    CHECK (state_json IS NULL OR json_valid(state_json))
) STRICT;
"#;

/// Version 8: a stored capture's u stated again (issue 24), captures staying as taken
/// (`captures_immutable`): each row is the u of one capture (its key and time) as a later check
/// bounds it, and why; the newest for a capture is its u in force (`Store::captures`).
const V8_RESTATEMENTS: &str = r#"
CREATE TABLE capture_restatements (
    id           INTEGER PRIMARY KEY,
    run_id       INTEGER NOT NULL REFERENCES runs (id),
    run          INTEGER NOT NULL CHECK (run >= 1),
    target_index INTEGER NOT NULL CHECK (target_index >= 0),
    direction    TEXT    NOT NULL CHECK (direction IN ('+', '-')),
    capture_us   INTEGER NOT NULL,
    u_dx_mm      REAL    NOT NULL CHECK (u_dx_mm >= 0),
    u_dy_mm      REAL    NOT NULL CHECK (u_dy_mm >= 0),
    u_dz_mm      REAL    NOT NULL CHECK (u_dz_mm >= 0),
    u_ex_rad     REAL    NOT NULL CHECK (u_ex_rad >= 0),
    u_ey_rad     REAL    NOT NULL CHECK (u_ey_rad >= 0),
    u_ez_rad     REAL    NOT NULL CHECK (u_ez_rad >= 0),
    unix_us      INTEGER NOT NULL,
    reason       TEXT    NOT NULL CHECK (reason <> '')
) STRICT;
CREATE INDEX capture_restatements_run ON capture_restatements (run_id, run, target_index, direction);
"#;

/// Version 9: machine records and their commissioning (issue 27). A machine is its record as
/// the builder wrote it (TOML, `commission::record`); each set-up's run is a row, attached or
/// (run_id NULL) detached, the newest row per set-up the one in force, so the history of what
/// measured the machine stays.
const V9_MACHINES: &str = r#"
CREATE TABLE machines (
    id          INTEGER PRIMARY KEY,
    name        TEXT    NOT NULL CHECK (name <> ''),
    record_toml TEXT    NOT NULL CHECK (record_toml <> ''),
    created_us  INTEGER NOT NULL
) STRICT;
CREATE TABLE machine_setups (
    id         INTEGER PRIMARY KEY,
    machine_id INTEGER NOT NULL REFERENCES machines (id),
    setup      INTEGER NOT NULL CHECK (setup >= 0),
    run_id     INTEGER REFERENCES runs (id),
    unix_us    INTEGER NOT NULL
) STRICT;
CREATE INDEX machine_setups_machine ON machine_setups (machine_id, setup);
"#;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn application_id_literal_matches_the_constant() {
        // The pragma cannot take a bound parameter, so V1 spells the number out.
        assert!(V1.contains(&format!("PRAGMA application_id = {APPLICATION_ID};")));
        assert_eq!(LATEST, 9);
    }
}
