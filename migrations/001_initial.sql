-- encoder-fleet service history. Two clocks:
--   service clock (unix s): devices.first_seen/last_seen, received_at, updated_at, published_at;
--   drive clock (s, as on the wire): window_start/window_end, created_at of fits and coefficient
--   sets, `at` of acks.
-- Every window, fit, coefficient set and ack is kept: this is the audit trail.

CREATE TABLE devices (
    id              TEXT PRIMARY KEY,
    first_seen      REAL NOT NULL,
    last_seen       REAL NOT NULL,
    online          INTEGER NOT NULL DEFAULT 0,
    current_version INTEGER            -- latest version the agent reported using (window or applied ack)
);

CREATE TABLE windows (
    device               TEXT NOT NULL REFERENCES devices(id),
    seq                  INTEGER NOT NULL,
    window_start         REAL NOT NULL,
    window_end           REAL NOT NULL,
    band                 INTEGER NOT NULL,
    samples              INTEGER NOT NULL,
    rejected             INTEGER NOT NULL,
    temp_mean_c          REAL NOT NULL,
    temp_min_c           REAL NOT NULL,
    temp_max_c           REAL NOT NULL,
    temp_rate_c_per_s    REAL NOT NULL,
    coefficients_version INTEGER NOT NULL,
    angle_quality_deg    REAL NOT NULL,
    stats_json           TEXT NOT NULL,
    received_at          REAL NOT NULL,
    PRIMARY KEY (device, seq)
);
CREATE INDEX windows_by_start ON windows (device, window_start);
CREATE INDEX windows_by_end ON windows (device, window_end, seq);

-- Sum of every window of a band (WindowStats.merge), kept in step with `windows` in one
-- transaction, so a refit reads one row per band however long the history.
CREATE TABLE band_stats (
    device     TEXT NOT NULL REFERENCES devices(id),
    band       INTEGER NOT NULL,
    stats_json TEXT NOT NULL,
    windows    INTEGER NOT NULL,
    samples    INTEGER NOT NULL,
    updated_at REAL NOT NULL,
    PRIMARY KEY (device, band)
);

CREATE TABLE fits (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    device          TEXT NOT NULL REFERENCES devices(id),
    band            INTEGER NOT NULL,
    created_at      REAL NOT NULL,
    samples         INTEGER NOT NULL,
    quality_json    TEXT NOT NULL,
    correction_json TEXT NOT NULL
);
CREATE INDEX fits_by_band ON fits (device, band, id);

CREATE TABLE coefficient_sets (
    device       TEXT NOT NULL REFERENCES devices(id),
    version      INTEGER NOT NULL,
    created_at   REAL NOT NULL,
    basis        TEXT NOT NULL,
    body_json    TEXT NOT NULL,     -- the wire message, exactly as sent
    published_at REAL,              -- NULL until published
    PRIMARY KEY (device, version)
);

CREATE TABLE acks (
    id                INTEGER PRIMARY KEY AUTOINCREMENT,
    device            TEXT NOT NULL REFERENCES devices(id),
    version           INTEGER NOT NULL,
    status            TEXT NOT NULL,
    reason            TEXT,
    angle_quality_deg REAL,
    at                REAL NOT NULL,
    received_at       REAL NOT NULL
);
CREATE INDEX acks_by_device ON acks (device, version);

-- Input we could not accept, kept byte for byte for audit.
CREATE TABLE dead_letters (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    received_at REAL NOT NULL,
    key_expr    TEXT NOT NULL,
    reason      TEXT NOT NULL,
    detail      TEXT NOT NULL,
    payload     BLOB NOT NULL
);
CREATE INDEX dead_letters_by_reason ON dead_letters (reason);
