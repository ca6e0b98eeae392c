#include "storage/storage_error.hpp"

#include <sqlite3.h>

#include <string_view>

namespace magcal::storage {
namespace {

using Condition = StorageError::Condition;

Condition sqlite_condition(int code) {
  if (code == SQLITE_READONLY_DBMOVED) return Condition::kFileMoved;
  switch (code & 0xff) {
    case SQLITE_OK:
      return Condition::kNone;
    case SQLITE_BUSY:
    case SQLITE_LOCKED:
    case SQLITE_PROTOCOL:  // a WAL lock race: SQLite's own advice is to retry
      return Condition::kBusy;
    case SQLITE_IOERR:
    case SQLITE_CANTOPEN:
      return Condition::kIo;
    case SQLITE_FULL:
      return Condition::kDiskFull;
    case SQLITE_READONLY:
      return Condition::kReadOnly;
    case SQLITE_CORRUPT:
    case SQLITE_NOTADB:
      return Condition::kCorrupt;
    case SQLITE_CONSTRAINT:
      return Condition::kConstraint;
    default:
      return Condition::kOther;
  }
}

Condition postgres_condition(std::string_view sqlstate) {
  if (sqlstate.empty()) return Condition::kNone;
  const std::string_view cls = sqlstate.substr(0, 2);
  if (sqlstate == "53100") return Condition::kDiskFull;
  if (cls == "08" || cls == "53") return Condition::kUnavailable;  // connection, resources
  if (cls == "58") return Condition::kIo;
  if (cls == "23") return Condition::kConstraint;
  if (sqlstate == "40001" || sqlstate == "40P01" || sqlstate == "72000") {
    return Condition::kConflict;  // serialization failure, deadlock, snapshot too old
  }
  if (sqlstate == "55P03" || sqlstate == "57014") return Condition::kBusy;  // lock, cancel
  if (sqlstate == "57P01" || sqlstate == "57P02" || sqlstate == "57P03" || sqlstate == "57P05") {
    return Condition::kUnavailable;  // shutting down, starting, idle session timeout
  }
  if (sqlstate == "25006") return Condition::kReadOnly;  // a standby (being promoted)
  if (sqlstate == "XX001" || sqlstate == "XX002") return Condition::kCorrupt;
  return Condition::kOther;
}

}  // namespace

StorageError StorageError::sqlite(Kind kind, const std::string& what, int sqlite_code) {
  StorageError e(kind, what, sqlite_condition(sqlite_code));
  e.sqlite_code_ = sqlite_code;
  return e;
}

StorageError StorageError::postgres(Kind kind, const std::string& what,
                                    const std::string& sqlstate) {
  StorageError e(kind, what, postgres_condition(sqlstate));
  e.sqlstate_ = sqlstate;
  return e;
}

bool StorageError::transient() const {
  switch (condition_) {
    case Condition::kBusy:
    case Condition::kConflict:
    case Condition::kIo:
    case Condition::kDiskFull:
    case Condition::kReadOnly:
    case Condition::kFileMoved:
    case Condition::kUnavailable:
      return true;
    case Condition::kNone:
    case Condition::kCorrupt:
    case Condition::kConstraint:
    case Condition::kOther:
      return false;
  }
  return false;
}

std::string StorageError::code() const {
  if (sqlite_code_ != 0) return "SQLite code " + std::to_string(sqlite_code_);
  if (!sqlstate_.empty()) return "SQLSTATE " + sqlstate_;
  return "";
}

const char* to_string(StorageError::Condition condition) {
  switch (condition) {
    case Condition::kNone:
      return "none";
    case Condition::kBusy:
      return "busy";
    case Condition::kConflict:
      return "conflict";
    case Condition::kIo:
      return "io";
    case Condition::kDiskFull:
      return "disk_full";
    case Condition::kReadOnly:
      return "read_only";
    case Condition::kFileMoved:
      return "file_moved";
    case Condition::kUnavailable:
      return "unavailable";
    case Condition::kCorrupt:
      return "corrupt";
    case Condition::kConstraint:
      return "constraint";
    case Condition::kOther:
      return "other";
  }
  return "other";
}

}  // namespace magcal::storage
