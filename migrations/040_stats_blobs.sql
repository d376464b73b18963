-- 040: a window's statistics and a band's sum as compact blobs (fleet_wire.messages.pack_stats:
-- MessagePack with the moment and bin arrays as little-endian float64 bytes, ~3.6 KB instead of ~7.5 KB
-- of JSON text that had to be parsed and re-serialised). Rows written before keep their stats_json and
-- are still read; new rows carry `stats` and an empty stats_json (adding a column is instant, rebuilding
-- the table to drop NOT NULL would copy the whole history in one transaction).
ALTER TABLE windows ADD COLUMN stats BLOB;
ALTER TABLE band_stats ADD COLUMN stats BLOB;
