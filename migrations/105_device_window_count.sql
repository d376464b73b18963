-- Each device's count of stored windows, kept with its row (the writer adds its batch's, retention takes off what it
-- deletes): GET /devices, the fleet page and `devices list` counted every device's windows on every read, which for
-- a fleet of 10,000 drives keeping 90 days of a window a minute is 1.3 billion index entries a read (measured at
-- ~57 ns each: over a minute). Counted once here.
ALTER TABLE devices ADD COLUMN windows INTEGER NOT NULL DEFAULT 0;
UPDATE devices SET windows = (SELECT count(*) FROM windows w WHERE w.device = devices.id);
