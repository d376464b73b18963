-- Labels an operator gives a drive (PUT /devices/{id}/labels): where it is and what it drives, e.g. site=plant-3,
-- line=7, axis=z. A fleet of thousands is read and changed by them: GET /devices and /fleet/health select by labels,
-- and a rollout can take the drives that carry them.
CREATE TABLE device_labels (
    device TEXT NOT NULL REFERENCES devices(id),
    name   TEXT NOT NULL,
    value  TEXT NOT NULL,
    PRIMARY KEY (device, name)
);
CREATE INDEX device_labels_by_value ON device_labels (name, value, device);
