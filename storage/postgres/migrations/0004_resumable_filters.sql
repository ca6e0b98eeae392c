-- magcal schema version 4 (PostgreSQL twin of storage/migrations/0004_resumable_filters.sql):
-- what a restart after a crash (or another daemon taking a spacecraft over) needs to resume the
-- online filter exactly.
-- A refit's model error (p_9 - p, 9 little-endian doubles; NULL = zero or unknown): the online
-- filter's re-anchor takes it, so a re-anchor can be re-applied from the history alone.
ALTER TABLE calibrations ADD COLUMN model_error bytea;
-- calibrations.id of the refit the stored state was last re-anchored on (0: none); NULL: saved
-- before version 4 (unknown, taken as the newest).
ALTER TABLE filter_states ADD COLUMN anchor_calibration_id bigint;
