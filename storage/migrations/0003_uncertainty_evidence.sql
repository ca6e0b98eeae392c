-- magcal schema version 3: the evidence behind every calibration's uncertainty, so a reader can
-- judge it (estimation.md section 7). Applied in one transaction that sets PRAGMA
-- user_version = 3.
-- NULL means unknown: rows written before version 3, or a method that does not compute it.
ALTER TABLE calibrations ADD COLUMN noise_scale REAL;               -- sqrt(chi2 / (n - p))
ALTER TABLE calibrations ADD COLUMN residual_autocorrelation REAL;  -- lag 1, normalised residuals
ALTER TABLE calibrations ADD COLUMN covariance_lag_window INTEGER;  -- HAC lag window (samples)
ALTER TABLE calibrations ADD COLUMN residual_rms_all_nT REAL;       -- rms over all samples
                                                                    -- (robust: also rejected ones)
ALTER TABLE calibrations ADD COLUMN has_nonlinearity INTEGER;       -- 1: extended model used
ALTER TABLE calibrations ADD COLUMN k3_x REAL;                      -- per-axis nonlinearity
ALTER TABLE calibrations ADD COLUMN k3_y REAL;                      -- coefficient (NULL unless
ALTER TABLE calibrations ADD COLUMN k3_z REAL;                      -- has_nonlinearity = 1)
ALTER TABLE calibrations ADD COLUMN nis_mean REAL;                  -- online filters
ALTER TABLE calibrations ADD COLUMN measurement_noise_nT REAL;      -- online filters
