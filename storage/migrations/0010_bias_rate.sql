-- magcal schema version 10: the linear bias rate of a refit, for a bias that drifts within its
-- window: b(t) = bias + r (t - window end), so the row's bias is the bias at window_end_utime. The
-- numbers are NULL unless has_bias_rate is 1; has_bias_rate itself is NULL for rows written
-- before this version and for online results.
ALTER TABLE calibrations ADD COLUMN has_bias_rate INTEGER;  -- 1: modelled, 0: a refit whose data
                                                            -- did not support it
ALTER TABLE calibrations ADD COLUMN bias_rate_x_nT_per_h REAL;  -- r per axis
ALTER TABLE calibrations ADD COLUMN bias_rate_y_nT_per_h REAL;
ALTER TABLE calibrations ADD COLUMN bias_rate_z_nT_per_h REAL;
-- Covariance of r, (nT/h)^2: 6 little-endian doubles, xx yy zz xy xz yz.
ALTER TABLE calibrations ADD COLUMN bias_rate_cov BLOB;
