// Reading a database read-only at the service's edges (magcal status, history, serve, and the
// operations server's API), also where the user cannot write (storage::OpenOptions::read_only).
#pragma once

#include <memory>
#include <string>

#include "storage/connection.hpp"

namespace magcal {

// How many lock-free reads a writer may spoil before read_consistently gives up.
constexpr int kReadOnlyAttempts = 3;

// Runs read(*db) on `db_name` (a file or a PostgreSQL URI) opened read-only in `db` (opened on
// first use, kept for the next call) and returns what it returns, read in one snapshot (a read
// transaction). After a lock-free read of an SQLite file (see OpenOptions::read_only), when a
// writer opened the file meanwhile (Connection::changed_since_open()), it reopens (now through
// the writer's -shm) and reads again: an answer never mixes two states of the file. Throws
// storage::StorageError.
template <typename Read>
auto read_consistently(std::unique_ptr<storage::Connection>& db, const std::string& db_name,
                       Read&& read) {
  for (int attempt = 1;; ++attempt) {
    if (!db || db->changed_since_open()) {
      db.reset();
      storage::OpenOptions options;
      options.read_only = true;
      db = storage::open_database(db_name, options);
    }
    auto result = [&] {
      storage::Transaction snapshot(*db, storage::Transaction::Mode::kReadSnapshot);
      auto r = read(*db);
      snapshot.commit();
      return r;
    }();
    if (!db->changed_since_open()) return result;
    if (attempt == kReadOnlyAttempts) {
      throw storage::StorageError(storage::StorageError::Kind::kEngine,
                                  db->name() + ": a writer opened it during each of " +
                                      std::to_string(kReadOnlyAttempts) +
                                      " reads without locks (its directory is not writable here)",
                                  storage::StorageError::Condition::kBusy);
    }
  }
}

// The same on a connection of its own (a CLI command, one scrape).
template <typename Read>
auto read_consistently(const std::string& db_name, Read&& read) {
  std::unique_ptr<storage::Connection> db;
  return read_consistently(db, db_name, std::forward<Read>(read));
}

}  // namespace magcal
