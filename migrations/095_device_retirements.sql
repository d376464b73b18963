-- A drive taken out of the fleet (replaced, scrapped, moved to a test bench): POST /devices/{id}/retire. Its history
-- stays (every window, set, ack and alarm: the audit trail of what reached it); it leaves the fleet's counts, its
-- alarms leave the open counts the alerting rules watch, no refit or rollout serves it, and what it still sends is
-- kept as dead letters (reason device_retired) until it is reinstated. One row per retirement, reinstated or not:
-- who took it out and who brought it back, and why.
CREATE TABLE device_retirements (
    id             INTEGER PRIMARY KEY AUTOINCREMENT,
    device         TEXT NOT NULL REFERENCES devices(id),
    retired_at     REAL NOT NULL,   -- service clock (unix s)
    retired_by     TEXT NOT NULL,   -- the REST token, e.g. "token 3 (ops desk)"
    note           TEXT NOT NULL,
    reinstated_at  REAL,            -- NULL: still retired
    reinstated_by  TEXT,
    reinstate_note TEXT
);
-- At most one retirement in force per device: two operators retiring it at once cannot both succeed.
CREATE UNIQUE INDEX device_retired_now ON device_retirements (device) WHERE reinstated_at IS NULL;
