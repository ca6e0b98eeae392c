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
