-- magcal schema (PostgreSQL twin of storage/migrations/0006_temperature_model.sql): the bias
-- temperature model. NULL means not modelled.
ALTER TABLE calibrations ADD COLUMN has_temperature_model bigint;
ALTER TABLE calibrations ADD COLUMN reference_temperature_C double precision;
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_x_nT_per_C double precision;
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_y_nT_per_C double precision;
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_z_nT_per_C double precision;
-- 6 little-endian doubles: upper triangle, row-major, of the k_T covariance ((nT/degC)^2).
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_cov bytea;
ALTER TABLE calibrations ADD COLUMN temperature_model_refit_id bigint;
