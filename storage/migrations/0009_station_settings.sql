-- magcal schema version 9: each station says which settings its results depend on (design.md
-- "Fleet"). Applied in one transaction that sets PRAGMA user_version = 9.

-- The station's result-affecting settings as canonical text, one "section.key=value" line per
-- key, sorted by key (service/io/station_settings.hpp), and a hash of that text, written by
-- every heartbeat. Stations that share spacecraft compare them: the owner of a spacecraft runs
-- its UKF and refits, so its settings make the results. NULL: unknown (a row written before
-- version 9).
ALTER TABLE stations ADD COLUMN settings TEXT;
ALTER TABLE stations ADD COLUMN settings_hash TEXT;
