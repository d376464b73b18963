-- A device's part in a staged rollout may end 'offline' (service/rollout.py): the drive had no liveliness token
-- from its wave's start for the rollout's timeout_s, so no set was issued to it, and it counts as no failure (it
-- timed out, a failure, before). The state's CHECK is a table's: the table is made again with it, rows kept.
CREATE TABLE rollout_devices_080 (
    rollout         INTEGER NOT NULL REFERENCES rollouts(id),
    device          TEXT NOT NULL REFERENCES devices(id),
    wave            INTEGER NOT NULL,
    state           TEXT NOT NULL CHECK (state IN ('pending', 'in_progress', 'succeeded', 'unchanged', 'offline',
                                                   'rejected', 'timed_out', 'regressed', 'rolled_back')),
    before_version  INTEGER,         -- the confirmed set the device ran when the change reached it
    version         INTEGER,         -- the set the change published
    started_at      REAL,
    decided_at      REAL,
    reason          TEXT,
    PRIMARY KEY (rollout, device)
);
INSERT INTO rollout_devices_080 (rollout, device, wave, state, before_version, version, started_at, decided_at, reason)
    SELECT rollout, device, wave, state, before_version, version, started_at, decided_at, reason FROM rollout_devices;
DROP TABLE rollout_devices;
ALTER TABLE rollout_devices_080 RENAME TO rollout_devices;
CREATE INDEX rollout_devices_by_device ON rollout_devices (device, state);
CREATE INDEX rollout_devices_by_wave ON rollout_devices (rollout, wave);
