-- Each band sum's Σ window mean temperature × count per angle bin (64 little-endian float64), so that the refit
-- can take every angle bin to the band's temperature (encoder_core.stats.WindowStats.bin_temp). NULL in sums
-- written before it: they fall back to the band's mean temperature in every bin.
ALTER TABLE band_stats ADD COLUMN bin_temp BLOB;
