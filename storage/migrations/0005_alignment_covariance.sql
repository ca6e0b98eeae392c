-- magcal schema version 5: the alignment's uncertainty, so history and the API report
-- the rotation-vector covariance and the roll/pitch/yaw sigmas of stored results as `fit` does.
-- Applied in one transaction that sets PRAGMA user_version to this migration's number.
-- 6 little-endian doubles, rad^2, in the order 11 22 33 12 13 23 (as D), of the covariance
-- of the rotation error dtheta in the sensor frame, R_true = exp(-[dtheta x]) R_hat
-- (pipeline/calibration_result.hpp AlignmentEstimate). NULL: no alignment, or stored before
-- version 5 (unknown).
ALTER TABLE calibrations ADD COLUMN alignment_covariance_rad2 BLOB;
