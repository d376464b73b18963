-- When the device's liveliness token last came back after being gone (service clock, unix s): an agent restarted
-- (perhaps upgraded) since it refused a set is asked again (service.runtime.FleetService._lag_refused). NULL: not
-- seen coming back since this column was added.
ALTER TABLE devices ADD COLUMN online_since REAL;
