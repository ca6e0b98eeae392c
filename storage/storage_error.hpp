// The one exception type of storage/, whichever database engine is behind it.
//
// Error policy (whole storage/ library): every failure is thrown as StorageError, and the
// service catches it at its edge (CLI run_*, daemon start / worker loop) to print one line and
// choose an exit code. kind() says what the open or the call found (a missing or foreign
// database, a schema too new or too old, a bad argument) or kEngine for a failure of the engine
// itself; condition() classifies every failure the same way for SQLite and PostgreSQL, each
// backend mapping its own codes (SQLite's result codes, PostgreSQL's SQLSTATE). transient()
// separates what a retry can heal from what it cannot: the daemon retries the first kind
// (service/daemon/intake/storage_retry.hpp). Data outcomes that are not failures are values:
// duplicate samples are counted in InsertStats, "not found" is std::nullopt.
#pragma once

#include <cstdint>
#include <stdexcept>
#include <string>

namespace magcal::storage {

class StorageError : public std::runtime_error {
 public:
  enum class Kind {
    kNotFound,     // read-only open of a missing file, or a PostgreSQL database that does not exist
    kForeignFile,  // not a magcal database (another application's file or schema)
    kNewerSchema,  // schema newer than this code: refuse rather than guess
    kOlderSchema,  // read-only open of a database that needs a migration first
    kInvalidArgument,
    kEngine,  // any other failure of the database engine: see condition()
  };
  // What failed, the same for every backend.
  enum class Condition {
    kNone,         // not the engine's failure (the kind says what)
    kBusy,         // a lock held past the wait (busy timeout, lock_timeout), a cancelled query
    kConflict,     // writers collided (serialization failure, deadlock): run the transaction again
    kIo,           // I/O error, or the file cannot be opened
    kDiskFull,     // no space left
    kReadOnly,     // the file or the server is read-only (e.g. a standby being promoted)
    kFileMoved,    // the SQLite file was deleted, renamed or replaced while open
    kUnavailable,  // the server is unreachable, shutting down, starting or out of connections
    kCorrupt,      // the database is damaged or not a database
    kConstraint,   // a constraint refused the change
    kOther,        // SQL, schema, permission, misuse: a retry does not help
  };

  // A failure that is not the engine's (condition kNone), or one classified by its caller.
  StorageError(Kind kind, const std::string& what, Condition condition = Condition::kNone)
      : std::runtime_error(what), kind_(kind), condition_(condition) {}
  // A SQLite failure: its extended result code (SQLITE_BUSY, SQLITE_IOERR_WRITE, ...).
  static StorageError sqlite(Kind kind, const std::string& what, int sqlite_code);
  // A PostgreSQL failure: its SQLSTATE ("40P01", "08006", ...).
  static StorageError postgres(Kind kind, const std::string& what, const std::string& sqlstate);

  Kind kind() const { return kind_; }
  Condition condition() const { return condition_; }
  // May heal by itself: busy, conflict, I/O, disk full, read-only, file moved, unavailable.
  // Everything else is permanent for this database and this code.
  bool transient() const;
  // The engine's own code for messages: "SQLite code 5", "SQLSTATE 40P01" ("" for none).
  std::string code() const;

  // The engine's codes themselves, for storage's own tests: 0 / "" when not that engine's.
  int sqlite_code() const { return sqlite_code_; }
  const std::string& sqlstate() const { return sqlstate_; }

  // A COMMIT that failed without telling whether it took effect (PostgreSQL: no reply in time,
  // or the connection lost while it was in flight): the transaction's id, which
  // Connection::commit_outcome() resolves once the server answers; 0 for every other failure
  // (the transaction was rolled back). Such an error is transient.
  int64_t in_doubt_transaction() const { return in_doubt_transaction_; }
  void set_in_doubt_transaction(int64_t transaction_id) { in_doubt_transaction_ = transaction_id; }

 private:
  Kind kind_;
  Condition condition_;
  int sqlite_code_ = 0;
  std::string sqlstate_;
  int64_t in_doubt_transaction_ = 0;
};

const char* to_string(StorageError::Condition condition);

}  // namespace magcal::storage
