-- Staged rollouts (issue 12, service/rollout.py): a change that touches many drives goes out in waves, each
-- wave soaks, abort criteria watch the outcomes. Every device's part is a row: the audit trail of who got the
-- change, when, what it ran before and how it ended. Times are the service clock, unix s.
CREATE TABLE rollouts (
    id              INTEGER PRIMARY KEY AUTOINCREMENT,
    name            TEXT NOT NULL,
    spec_json       TEXT NOT NULL,   -- the change, the wave rate, the soak, the abort criteria (as created)
    state           TEXT NOT NULL CHECK (state IN ('running', 'paused', 'aborted', 'completed')),
    reason          TEXT,            -- why it is paused, aborted or completed
    wave            INTEGER NOT NULL DEFAULT 0,   -- the wave in progress (the last one once ended)
    wave_started_at REAL,            -- NULL until the wave's first device is started
    counted_from    REAL NOT NULL,   -- abort criteria count outcomes decided from here (creation or resume)
    created_at      REAL NOT NULL,
    updated_at      REAL NOT NULL
);

CREATE TABLE rollout_devices (
    rollout         INTEGER NOT NULL REFERENCES rollouts(id),
    device          TEXT NOT NULL REFERENCES devices(id),
    wave            INTEGER NOT NULL,
    state           TEXT NOT NULL CHECK (state IN ('pending', 'in_progress', 'succeeded', 'unchanged',
                                                   'rejected', 'timed_out', 'regressed', 'rolled_back')),
    before_version  INTEGER,         -- the confirmed set the device ran when the change reached it
    version         INTEGER,         -- the set the change published
    started_at      REAL,
    decided_at      REAL,
    reason          TEXT,
    PRIMARY KEY (rollout, device)
);
CREATE INDEX rollout_devices_by_device ON rollout_devices (device, state);
CREATE INDEX rollout_devices_by_wave ON rollout_devices (rollout, wave);
-- the soak of a rollout (and the guard's trial) reads the windows a device ran on one set
CREATE INDEX windows_by_version ON windows (device, coefficients_version);
