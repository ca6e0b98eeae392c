-- magcal schema version 8 (PostgreSQL twin of storage/migrations/0008_stations.sql): the
-- daemons of a fleet know one another. Meanings: see the SQLite file.
CREATE TABLE stations (
  station         text   NOT NULL PRIMARY KEY,
  heartbeat_utime bigint NOT NULL,
  expires_utime   bigint NOT NULL,
  instance        text   NOT NULL DEFAULT ''
);
