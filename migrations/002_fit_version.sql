-- Each fit names the coefficient set it was computed for, and whether that set took it
-- (a band whose running correction was already right keeps it; the fit is kept for the audit all the same).
ALTER TABLE fits ADD COLUMN version INTEGER;
ALTER TABLE fits ADD COLUMN adopted INTEGER NOT NULL DEFAULT 1;
