-- The fleet's database and the role its daemons connect as (docs/fleet.md), for psql where
-- createuser/createdb are not at hand (a managed PostgreSQL service):
--   psql -h DB_HOST -U postgres -v ON_ERROR_STOP=1 -f create-database.sql
-- then give the role a password in psql (`\password magcal`) and put it in ~/.pgpass of the
-- user magcald runs as (/var/lib/magcal/.pgpass, mode 0600). magcald creates and migrates its
-- tables itself on its first start. The role needs to own the database, nothing more: since
-- PostgreSQL 15 only the owner may create tables in a new database's public schema.
CREATE ROLE magcal LOGIN;
-- A non-superuser admin (CREATEROLE, CREATEDB: the usual managed service) may give a database
-- only to a role it is a member of; for a superuser this changes nothing.
GRANT magcal TO CURRENT_USER;
CREATE DATABASE magcal OWNER magcal;
