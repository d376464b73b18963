-- A band's sum covers its windows with seq >= first_seq only, so a store with a horizon can drop the
-- oldest windows from it (subtracting: the statistics are additive) while keeping every window.
ALTER TABLE band_stats ADD COLUMN first_seq INTEGER NOT NULL DEFAULT 1;
CREATE INDEX windows_by_band ON windows (device, band, seq);
