-- Drift monitor (issue 9). Alarms on the drive's clock: raised_at is the end of the window that made
-- the alarm certain, cleared_at when its condition was gone (NULL while open).
CREATE TABLE alarms (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    device          TEXT NOT NULL REFERENCES devices(id),
    cause           TEXT NOT NULL,
    parameters_json TEXT NOT NULL,
    evidence        TEXT NOT NULL,
    raised_at       REAL NOT NULL,
    cleared_at      REAL,
    clear_evidence  TEXT,
    created_at      REAL NOT NULL   -- service clock (unix s)
);
CREATE INDEX alarms_by_device ON alarms (device, cause, cleared_at);
-- At most one open alarm per device and cause: a restart or a replay cannot raise it twice.
CREATE UNIQUE INDEX alarms_one_open ON alarms (device, cause) WHERE cleared_at IS NULL;

-- Each device's monitor (baselines, detectors, open alarms) as JSON, and the last window seq it has seen;
-- written in the same transaction as the alarms it raised.
CREATE TABLE monitor_state (
    device     TEXT PRIMARY KEY REFERENCES devices(id),
    state_json TEXT NOT NULL,
    last_seq   INTEGER NOT NULL,
    updated_at REAL NOT NULL       -- service clock (unix s)
);

-- The agent's rejected samples per reason (optional on the wire: NULL for windows without it).
ALTER TABLE windows ADD COLUMN rejected_by_reason_json TEXT;
