-- magcal schema version 12: the field error a calibration leaves on its own window's samples
-- (pipeline/field_error.hpp): the calibrated field against the reference field, rms and worst of
-- the direction error (degrees) and of the magnitude error (nT). NULL: not computed (online
-- filter snapshots, rows written before this version; the direction also for a window without
-- reference directions).
ALTER TABLE calibrations ADD COLUMN field_direction_error_rms_deg REAL;
ALTER TABLE calibrations ADD COLUMN field_direction_error_worst_deg REAL;
ALTER TABLE calibrations ADD COLUMN field_magnitude_error_rms_nT REAL;
ALTER TABLE calibrations ADD COLUMN field_magnitude_error_worst_nT REAL;
