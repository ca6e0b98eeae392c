-- magcal schema version 4: what a restart after a crash (or another daemon taking a spacecraft
-- over) needs to resume the online filter exactly. Applied in one transaction that sets PRAGMA
-- user_version = 4.
-- A refit's model error (p_9 - p, 9 little-endian doubles; NULL = zero or unknown): the online
-- filter's re-anchor takes it, so a re-anchor can be re-applied from the history alone.
ALTER TABLE calibrations ADD COLUMN model_error BLOB;
-- calibrations.id of the refit the stored state was last re-anchored on (0: none); NULL: saved
-- before version 4 (unknown, taken as the newest).
ALTER TABLE filter_states ADD COLUMN anchor_calibration_id INTEGER;
