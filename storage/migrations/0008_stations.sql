-- magcal schema version 8: the daemons of a fleet know one another (design.md "Fleet"). Applied
-- in one transaction that sets PRAGMA user_version = 8.

-- One row per daemon (station id) that shares the database, renewed by its heartbeat. A daemon
-- is live until expires_utime; the live daemons share the spacecraft leases evenly.
CREATE TABLE stations (
  station         TEXT    NOT NULL PRIMARY KEY,
  heartbeat_utime INTEGER NOT NULL,  -- wall clock of its last heartbeat
  expires_utime   INTEGER NOT NULL,  -- wall clock: live until then unless it beats again
  instance        TEXT    NOT NULL DEFAULT ''  -- the beating process (random per start): two
                                               -- live processes with one id are a misuse
) WITHOUT ROWID;
