-- An operator acknowledges an alarm (POST /alarms/{id}/ack): seen, and what will be done about it. The alarm stays
-- open until its condition clears; acknowledged, it no longer counts among the unacknowledged, which the alerting
-- rules watch (ops/alerts.yml). Who, when and the note are kept: the audit trail of who saw what.
ALTER TABLE alarms ADD COLUMN acked_at REAL;   -- service clock (unix s); NULL: not acknowledged
ALTER TABLE alarms ADD COLUMN acked_by TEXT;   -- the REST token that acknowledged it, e.g. "token 3 (ops desk)"
ALTER TABLE alarms ADD COLUMN ack_note TEXT;
