// Reading a database read-only at the service's edges (magcal status, history, serve, and the
// operations server's API), also where the user cannot write (storage::OpenOptions::read_only).
#pragma once

#include <optional>
#include <string>

#include "storage/database.hpp"

namespace magcal {

// How many lock-free reads a writer may spoil before read_consistently gives up.
constexpr int kReadOnlyAttempts = 3;

// Runs read(*db) on `path` opened read-only in `db` (opened on first use, kept for the next
// call) and returns what it returns. After a lock-free (immutable) read, when a writer opened
// the file meanwhile, it reopens (now through the writer's -shm) and reads again: an answer
// never mixes two states of the file. Throws storage::StorageError.
template <typename Read>
auto read_consistently(std::optional<storage::Database>& db, const std::string& path, Read&& read) {
  for (int attempt = 1;; ++attempt) {
    if (!db || db->changed_since_open()) {
      db.reset();
      storage::OpenOptions options;
      options.read_only = true;
      db.emplace(path, options);
    }
    auto result = read(*db);
    if (!db->changed_since_open()) return result;
    if (attempt == kReadOnlyAttempts) {
      throw storage::StorageError(storage::StorageError::Kind::kEngine,
                                  path + ": a writer opened it during each of " +
                                      std::to_string(kReadOnlyAttempts) +
                                      " reads without locks (its directory is not writable here)",
                                  storage::StorageError::Condition::kBusy);
    }
  }
}

// The same on a connection of its own (a CLI command, one scrape).
template <typename Read>
auto read_consistently(const std::string& path, Read&& read) {
  std::optional<storage::Database> db;
  return read_consistently(db, path, std::forward<Read>(read));
}

}  // namespace magcal
