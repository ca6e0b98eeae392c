// Table `leases`: one owner per spacecraft in a fleet (design.md "Fleet"). The daemon holding a
// spacecraft's lease runs its online filter and its refits; it renews the lease well within its
// time to live, and when it dies another daemon takes the lease over once it has expired.
//
// Fencing: a lease's epoch counts its changes of owner. A holder remembers the epoch it was
// granted; renew() and holds() fail once another daemon has taken the lease, even if that one
// released it again, so a daemon that stalled past its lease finds out before it writes.
//
// Times are wall-clock utime given by the caller: daemons sharing a database keep their clocks
// in step (NTP) to well within a lease's time to live.
//
// An interface: SqlLeaseStore (storage/sql_lease_store.hpp, both backends) and PgLeaseStore
// (storage/postgres/pg_lease_store.hpp), made by Connection::make_lease_store(). Each call is one
// statement, atomic on its own: of daemons racing for one lease exactly one gets it.
#pragma once

#include <cstdint>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <vector>

#include "storage/connection.hpp"

namespace magcal::storage {

// A station's heartbeat row (table `stations`).
struct StationBeat {
  std::string instance;  // the process that beat (random per start)
  int64_t heartbeat_utime = 0;
  int64_t expires_utime = 0;
};

// The settings a station's results depend on, as it declares them in its heartbeat: canonical
// text and its hash (service/io/station_settings.hpp makes and compares them; storage keeps
// them as given).
struct StationSettings {
  std::string text;
  std::string hash;
};

// A station's row as `magcal status` lists it: live until expires_utime (a clean stop ends it at
// once, a daemon that died at its last heartbeat + [fleet] lease_s).
struct StationRow {
  std::string station;
  std::string instance;
  int64_t heartbeat_utime = 0;
  int64_t expires_utime = 0;
  // nullopt: unknown (a row written before schema version 9, or a beat that declared none).
  std::optional<StationSettings> settings;
  bool live_at(int64_t now_utime) const { return now_utime < expires_utime; }
};

struct Lease {
  std::string sat_id;
  std::string owner;  // the holder's station id (or the last holder's, once expired)
  int64_t epoch = 0;  // 1 for the first owner, +1 at every change of owner
  int64_t acquired_utime = 0;
  int64_t expires_utime = 0;
  bool held_at(int64_t now_utime) const { return now_utime < expires_utime; }
};

class LeaseStore {
 public:
  virtual ~LeaseStore() = default;

  // Takes the lease of `sat_id` for `owner` until now + ttl when it is free, expired or already
  // owner's (then a renewal, same epoch); a new owner gets the next epoch. nullopt when another
  // owner holds it. Throws StorageError (kInvalidArgument) for ttl_utime <= 0 or an empty owner.
  virtual std::optional<Lease> try_acquire(std::string_view sat_id, std::string_view owner,
                                           int64_t now_utime, int64_t ttl_utime) = 0;
  // Extends owner's lease of that epoch to now + ttl. False when the lease has changed owner
  // since (the caller lost it and must stop acting for the spacecraft).
  virtual bool renew(std::string_view sat_id, std::string_view owner, int64_t epoch,
                     int64_t now_utime, int64_t ttl_utime) = 0;
  // Owner's lease of that epoch under the next epoch, until now + ttl: a process that finds its
  // station's lease unexpired at its start (a restart after a crash, or a second process under
  // the same station id) takes it over this way, so that writes fenced by the old epoch fail and
  // no two processes write for the spacecraft. nullopt when it is no longer owner's of that epoch.
  virtual std::optional<Lease> reclaim(std::string_view sat_id, std::string_view owner,
                                       int64_t epoch, int64_t now_utime, int64_t ttl_utime) = 0;
  // Ends owner's lease of that epoch at now (another daemon may take it at once). False when it
  // was no longer owner's.
  virtual bool release(std::string_view sat_id, std::string_view owner, int64_t epoch,
                       int64_t now_utime) = 0;
  // True while the lease is still owner's of that epoch. Inside a write transaction it fences
  // the writes that follow: on PostgreSQL the lease row stays locked (FOR SHARE) until the
  // commit, so a takeover waits for it; SQLite serialises writers anyway.
  virtual bool holds(std::string_view sat_id, std::string_view owner, int64_t epoch) = 0;
  // A lease as its holder knows it.
  struct Held {
    std::string sat_id;
    int64_t epoch = 0;
  };
  // holds() for several of owner's leases at once (on PostgreSQL one statement): the sat_ids of
  // those it no longer holds, in the order given. Fences the same way.
  virtual std::vector<std::string> not_held(std::string_view owner, std::span<const Held> leases);

  // The lease row of `sat_id` (held or expired), nullopt when it never had one.
  virtual std::optional<Lease> get(std::string_view sat_id) = 0;
  // The daemon holding `sat_id` at now_utime, nullopt when none does.
  std::optional<std::string> owner_of(std::string_view sat_id, int64_t now_utime);
  // Every lease row, sorted by sat_id (for magcal status).
  virtual std::vector<Lease> list() = 0;

  // A lease row for `sat_id` without an owner (epoch 0, expired), unless it has one: every
  // daemon registers the spacecraft it receives, so that any live daemon may own them.
  virtual void ensure(std::string_view sat_id) = 0;
  // Extends every lease `owner` holds at now (not expired) to now + ttl, in one statement;
  // returns them (sat_id, epoch). A lease the caller thinks it holds and that is not among them
  // (expired, or taken over: another epoch) is lost.
  virtual std::vector<Lease> renew_all(std::string_view owner, int64_t now_utime,
                                       int64_t ttl_utime) = 0;

  // The daemons sharing the database (table `stations`): `station` (this process: `instance`,
  // with its `settings`; an empty text stores none) is live until now + ttl. Returns the row as
  // it was before (nullopt: the first beat ever), so a daemon sees another live process beating
  // under its id.
  virtual std::optional<StationBeat> heartbeat(std::string_view station, std::string_view instance,
                                               const StationSettings& settings, int64_t now_utime,
                                               int64_t ttl_utime) = 0;
  // Ends `station`'s heartbeat at now (a clean stop: the others rebalance at once).
  virtual void leave(std::string_view station, int64_t now_utime) = 0;
  // The stations live at now, sorted.
  virtual std::vector<std::string> live_stations(int64_t now_utime) = 0;
  // Every station that ever beat, live or not, sorted by station (for magcal status).
  virtual std::vector<StationRow> stations() = 0;

 protected:
  // Both backends' argument check: a non-empty owner, a positive time to live.
  static void check_request(std::string_view owner, int64_t ttl_utime);
};

}  // namespace magcal::storage
