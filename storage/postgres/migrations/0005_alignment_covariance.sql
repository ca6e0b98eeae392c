-- magcal schema version 5 (PostgreSQL twin of storage/migrations/0005_alignment_covariance.sql):
-- the alignment's rotation-vector covariance, 6 little-endian doubles, rad^2 (11 22 33 12 13 23,
-- as D); NULL: no alignment, or stored before version 5 (unknown).
ALTER TABLE calibrations ADD COLUMN alignment_covariance_rad2 bytea;
