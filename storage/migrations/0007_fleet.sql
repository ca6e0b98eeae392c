-- magcal schema version 7: several stations and daemons sharing one database (design.md
-- "Fleet"). Applied in one transaction that sets PRAGMA user_version = 7.

-- The station that stored the sample: the first to deliver it (a later copy from another
-- station is a duplicate and changes nothing). NULL: stored before version 7, or by a writer
-- that names no station.
ALTER TABLE samples ADD COLUMN station TEXT;

-- The station whose daemon claimed the refit (RefitJobLog::claim). NULL: not claimed (a manual
-- refit, or a row written before version 7).
ALTER TABLE refit_jobs ADD COLUMN claimed_by TEXT;
-- Each claimed refit (spacecraft, trigger, due time) runs once for the whole fleet: at most one
-- claimed job per key holds it. An interrupted job (its daemon died) gives the claim up, so
-- the spacecraft's next owner runs the refit again under a new job row.
CREATE UNIQUE INDEX refit_jobs_one_claim ON refit_jobs (sat_id, trigger_kind, scheduled_utime)
  WHERE claimed_by IS NOT NULL AND outcome <> 'interrupted';

-- One owner per spacecraft (LeaseStore): the daemon that runs its online filter and its
-- refits. A lease is its owner's until expires_utime unless renewed; then any daemon may take
-- it over. The row stays when released or expired, so epoch keeps counting.
CREATE TABLE leases (
  sat_id         TEXT    NOT NULL PRIMARY KEY,
  owner          TEXT    NOT NULL,  -- station id of the daemon holding (or last holding) it
  epoch          INTEGER NOT NULL,  -- 1 at the first owner, +1 at every change of owner: a
                                    -- writer whose epoch is no longer current lost the lease
  acquired_utime INTEGER NOT NULL,  -- wall clock: when this owner took it
  expires_utime  INTEGER NOT NULL   -- wall clock: the owner's until then unless renewed
) WITHOUT ROWID;
