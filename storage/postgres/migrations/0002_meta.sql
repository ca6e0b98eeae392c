-- magcal schema version 2 on PostgreSQL: storage/migrations/0002_meta.sql.
CREATE TABLE meta (
  key   text NOT NULL PRIMARY KEY,
  value text NOT NULL
);
