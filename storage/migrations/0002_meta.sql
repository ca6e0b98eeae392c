-- magcal schema version 2: a few named values about the database itself (e.g. the version of
-- the daemon that last opened it). Applied in one transaction that sets PRAGMA user_version = 2.
CREATE TABLE meta (
  key   TEXT NOT NULL PRIMARY KEY,
  value TEXT NOT NULL
) WITHOUT ROWID;
