-- magcal schema (PostgreSQL twin of storage/migrations/0010_bias_rate.sql): the linear bias rate
-- of a refit. NULL means not modelled.
ALTER TABLE calibrations ADD COLUMN has_bias_rate bigint;
ALTER TABLE calibrations ADD COLUMN bias_rate_x_nT_per_h double precision;
ALTER TABLE calibrations ADD COLUMN bias_rate_y_nT_per_h double precision;
ALTER TABLE calibrations ADD COLUMN bias_rate_z_nT_per_h double precision;
-- 6 little-endian doubles, xx yy zz xy xz yz, of the rate covariance ((nT/h)^2).
ALTER TABLE calibrations ADD COLUMN bias_rate_cov bytea;
