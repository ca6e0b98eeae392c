-- magcal schema: the bias temperature model. Applied in one transaction that sets
-- PRAGMA user_version to this migration's number. b(T) = bias + k_T (T - T0): the row's bias is
-- the bias at T0 = reference_temperature_C. The numbers are NULL unless has_temperature_model
-- is 1; has_temperature_model itself is NULL for rows written before this version and for
-- online results without a model to apply.
ALTER TABLE calibrations ADD COLUMN has_temperature_model INTEGER;  -- 1: modelled, 0: a refit
                                                                    -- whose data did not support it
ALTER TABLE calibrations ADD COLUMN reference_temperature_C REAL;   -- T0, deg C
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_x_nT_per_C REAL;  -- k_T per axis
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_y_nT_per_C REAL;
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_z_nT_per_C REAL;
-- Covariance of k_T, (nT/degC)^2: 6 little-endian doubles, upper triangle row-major
-- (xx xy xz yy yz zz).
ALTER TABLE calibrations ADD COLUMN temperature_coefficient_cov BLOB;
-- Online results (ukf/ekf) that applied a refit's temperature model: calibrations.id of that
-- refit (their own estimate is of the bias at its T0). NULL for refits (their model is their
-- own) and for online results without one.
ALTER TABLE calibrations ADD COLUMN temperature_model_refit_id INTEGER;
