-- magcal schema version 7 (PostgreSQL twin of storage/migrations/0007_fleet.sql): several
-- stations and daemons sharing one database. Meanings: see the SQLite file.
ALTER TABLE samples ADD COLUMN station text;

ALTER TABLE refit_jobs ADD COLUMN claimed_by text;
CREATE UNIQUE INDEX refit_jobs_one_claim ON refit_jobs (sat_id, trigger_kind, scheduled_utime)
  WHERE claimed_by IS NOT NULL AND outcome <> 'interrupted';

CREATE TABLE leases (
  sat_id         text   NOT NULL PRIMARY KEY,
  owner          text   NOT NULL,
  epoch          bigint NOT NULL,
  acquired_utime bigint NOT NULL,
  expires_utime  bigint NOT NULL
);

-- Spacecraft ids of the samples in byte order, as SQLite compares them: the primary key then
-- compares ids with memcmp instead of the database's locale (about 10 % of an insert's time,
-- measured), and windows and lists sort the same on both backends.
ALTER TABLE samples ALTER COLUMN sat_id TYPE text COLLATE "C";
