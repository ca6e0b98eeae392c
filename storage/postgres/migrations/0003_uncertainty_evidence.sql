-- magcal schema version 3 on PostgreSQL: storage/migrations/0003_uncertainty_evidence.sql.
ALTER TABLE calibrations ADD COLUMN noise_scale double precision;
ALTER TABLE calibrations ADD COLUMN residual_autocorrelation double precision;
ALTER TABLE calibrations ADD COLUMN covariance_lag_window bigint;
ALTER TABLE calibrations ADD COLUMN residual_rms_all_nT double precision;
ALTER TABLE calibrations ADD COLUMN has_nonlinearity bigint;
ALTER TABLE calibrations ADD COLUMN k3_x double precision;
ALTER TABLE calibrations ADD COLUMN k3_y double precision;
ALTER TABLE calibrations ADD COLUMN k3_z double precision;
ALTER TABLE calibrations ADD COLUMN nis_mean double precision;
ALTER TABLE calibrations ADD COLUMN measurement_noise_nT double precision;
