-- magcal schema (PostgreSQL twin of storage/migrations/0011_bias_variability.sql): the bias
-- variability a refit measured, 3 little-endian doubles (nT^2, x y z); NULL: none.
ALTER TABLE calibrations ADD COLUMN bias_variability_nT2 bytea;
