-- A dead letter keeps only the head of its payload; its full size and SHA-256 identify it.
ALTER TABLE dead_letters ADD COLUMN payload_bytes INTEGER;
ALTER TABLE dead_letters ADD COLUMN payload_sha256 TEXT;
UPDATE dead_letters SET payload_bytes = length(payload) WHERE payload_bytes IS NULL;
UPDATE dead_letters SET payload = substr(payload, 1, 65536) WHERE length(payload) > 65536;
