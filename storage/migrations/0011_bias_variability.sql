-- magcal schema version 11: the bias variability a refit measured: the bias's
-- variance about its window average, per axis, where the window's short-block biases show it
-- moving (a swing the model has no term for). Already in `cov`; stored on its own so that a
-- filter re-anchored on a refit read back from the database (after a restart or a takeover)
-- keeps it as model error, as one re-anchored on the fresh refit does.
-- 3 little-endian doubles, nT^2 (x y z); NULL: none measured (or a row before this version).
ALTER TABLE calibrations ADD COLUMN bias_variability_nT2 BLOB;
