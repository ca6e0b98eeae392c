-- magcal schema (PostgreSQL twin of storage/migrations/0012_field_error.sql): the field error a
-- calibration leaves on its window, rms and worst, direction in degrees, magnitude in nT. NULL:
-- not computed.
ALTER TABLE calibrations ADD COLUMN field_direction_error_rms_deg double precision;
ALTER TABLE calibrations ADD COLUMN field_direction_error_worst_deg double precision;
ALTER TABLE calibrations ADD COLUMN field_magnitude_error_rms_nT double precision;
ALTER TABLE calibrations ADD COLUMN field_magnitude_error_worst_nT double precision;
