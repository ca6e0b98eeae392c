-- magcal schema version 9 (PostgreSQL twin of storage/migrations/0009_station_settings.sql):
-- each station's result-affecting settings and their hash. Meanings: see the SQLite file.
ALTER TABLE stations ADD COLUMN settings text;
ALTER TABLE stations ADD COLUMN settings_hash text;
