-- Windows below seq_floor that the service does not have are gone for good: the agent said so on `received`
-- (`gone_below`, docs/wire.md), its outbox having dropped its oldest windows while full with the service away.
-- The contiguous watermark steps over them (Store.contiguous_seq): it is at least seq_floor - 1. 0: none gone.
ALTER TABLE devices ADD COLUMN seq_floor INTEGER NOT NULL DEFAULT 0;
