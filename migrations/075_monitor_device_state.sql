-- The device's state as its monitor judged it when this row was written (ok | watch | alarm | offline | unknown):
-- GET /devices, /fleet/health and a device's health read it for the devices this process does not monitor (the
-- other members' partitions; REST with no running service) without parsing every ~36 KB state. NULL: written
-- before this column was added (read from state_json).
ALTER TABLE monitor_state ADD COLUMN device_state TEXT;
