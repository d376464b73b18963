-- `encoder-fleet audit` reads the fleet's published sets in the order they went out, a page at a time: without
-- this index each page sorted every set ever made.
CREATE INDEX coefficient_sets_by_published ON coefficient_sets (published_at, device, version);
