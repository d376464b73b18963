-- The guard (issue 8): every published fit set is on trial until its outcome is measured; then it is
-- confirmed or rolled back (a new set, basis 'rollback', restores the last good one). Sets made before
-- the guard existed count as confirmed. Every transition is kept in set_events for the audit trail.
ALTER TABLE coefficient_sets ADD COLUMN state TEXT NOT NULL DEFAULT 'confirmed';
ALTER TABLE coefficient_sets ADD COLUMN state_reason TEXT;
ALTER TABLE coefficient_sets ADD COLUMN restores_version INTEGER;

CREATE TABLE set_events (
    id          INTEGER PRIMARY KEY AUTOINCREMENT,
    device      TEXT NOT NULL REFERENCES devices(id),
    version     INTEGER NOT NULL,
    state       TEXT NOT NULL,      -- trial | confirmed | rolled_back
    at          REAL NOT NULL,      -- drive clock of the newest window the decision saw
    decided_at  REAL NOT NULL,      -- service clock, unix s
    reason      TEXT NOT NULL
);
CREATE INDEX set_events_by_device ON set_events (device, id);
