#include "storage/sqlite/database.hpp"

#include <sqlite3.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <string>
#include <utility>

#include "storage/migrations.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {
namespace {

namespace fs = std::filesystem;

int64_t pragma_int(Database& db, const char* pragma) {
  Statement st(db, std::string("PRAGMA ") + pragma);
  return st.step() ? st.column_int64(0) : 0;
}

bool file_exists(const std::string& path) {
  std::error_code ec;
  return fs::exists(path, ec);
}

// A -wal file with content (a zero-length one holds no commit).
bool wal_has_frames(const std::string& path) {
  std::error_code ec;
  const auto size = fs::file_size(path + "-wal", ec);
  return !ec && size > 0;
}

// SQLite's header says WAL mode: file format write and read versions (bytes 18, 19) are 2.
bool wal_mode_header(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  char header[20] = {};
  return in.read(header, sizeof header) && header[18] == 2 && header[19] == 2;
}

std::string directory_of(const std::string& path) {
  const fs::path dir = fs::path(path).parent_path();
  return dir.empty() ? "." : dir.string();
}

// The path in an SQLite URI ("file:PATH?..."): '%', '?' and '#' are escaped.
std::string uri_path(const std::string& path) {
  std::string out;
  for (const char c : path) {
    if (c == '%' || c == '?' || c == '#') {
      static const char kHex[] = "0123456789ABCDEF";
      out += '%';
      out += kHex[(c >> 4) & 0xf];
      out += kHex[c & 0xf];
    } else {
      out += c;
    }
  }
  return out;
}

// What the file system says against reading `path` and its WAL files ("" when nothing): the
// cause behind SQLite's "unable to open database file" of a read-only open.
std::string unreadable_cause(const std::string& path) {
  for (const std::string& file : {path, path + "-wal", path + "-shm"}) {
    if (file_exists(file) && ::access(file.c_str(), R_OK) != 0) {
      return file + ": " + std::strerror(errno);
    }
  }
  return "";
}

}  // namespace

Database::Database(const std::string& path, const OpenOptions& options)
    : path_(path), read_only_(options.read_only) {
  const bool memory = path == ":memory:" || path.empty();
  // SQLite opens a directory without complaint and fails at the first read ("disk I/O error").
  if (std::error_code ec; !memory && fs::is_directory(path, ec)) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "cannot open database " + path + ": is a directory, not a database file");
  }
  if (options.read_only && !memory && !file_exists(path)) {
    // Never create a file by reading: report it as missing (or why it cannot be seen).
    struct stat st {};
    if (::stat(path.c_str(), &st) != 0 && errno != ENOENT) {
      throw StorageError::sqlite(StorageError::Kind::kEngine,
                                 "cannot open database " + path + ": " + std::strerror(errno),
                                 SQLITE_CANTOPEN);
    }
    throw StorageError(StorageError::Kind::kNotFound, "database not found: " + path);
  }
  const int flags =
      (options.read_only ? SQLITE_OPEN_READONLY : SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE) |
      SQLITE_OPEN_NOMUTEX;  // one thread per connection (see header)
  const int rc = options.read_only && !memory ? open_read_only(flags)
                                              : sqlite3_open_v2(path.c_str(), &db_, flags, nullptr);
  // Every failure of the open names the file once, and for a read-only open what the file
  // system says against it.
  const auto fail = [&](StorageError::Kind kind, std::string msg, int code) {
    sqlite3_close(db_);
    db_ = nullptr;
    if (msg.find(path_) == std::string::npos) msg = "cannot open database " + path_ + ": " + msg;
    if (options.read_only) {
      if (const std::string cause = unreadable_cause(path_); !cause.empty()) {
        msg += " (" + cause + ")";
      }
    } else if (const std::string dir = directory_of(path_);
               !memory && !file_exists(path_) && ::access(dir.c_str(), W_OK | X_OK) != 0) {
      // A new database: SQLite says only "unable to open database file"; the directory is why.
      msg += " (directory " + dir + ": " + std::strerror(errno) + ")";
    }
    throw StorageError::sqlite(kind, msg, code);
  };
  if (rc != SQLITE_OK) {
    fail(StorageError::Kind::kEngine, db_ ? sqlite3_errmsg(db_) : sqlite3_errstr(rc),
         db_ ? sqlite3_extended_errcode(db_) : rc);
  }
  // Every error carries its extended code (SQLITE_IOERR_WRITE, SQLITE_BUSY_SNAPSHOT, ...).
  sqlite3_extended_result_codes(db_, 1);
  try {
    configure(options);
    check_and_migrate(options);
  } catch (const StorageError& e) {
    if ((e.sqlite_code() & 0xff) == SQLITE_NOTADB) {
      fail(e.kind(), path_ + " is not a database (SQLite: " + sqlite3_errstr(SQLITE_NOTADB) + ")",
           e.sqlite_code());
    }
    fail(e.kind(), e.what(), e.sqlite_code());
  }
}

int Database::open_read_only(int flags) {
  const std::string directory = directory_of(path_);
  if (!wal_mode_header(path_) || file_exists(path_ + "-shm") ||
      ::access(directory.c_str(), W_OK) == 0) {
    return sqlite3_open_v2(path_.c_str(), &db_, flags, nullptr);
  }
  // A WAL database without -shm in a directory we cannot write: no connection has it open.
  const std::string why_no_shm = directory + ": " + std::strerror(errno);
  if (wal_has_frames(path_)) {
    throw StorageError::sqlite(
        StorageError::Kind::kEngine,
        "cannot read " + path_ + ": its " + path_ +
            "-wal holds commits not yet in the file, and SQLite cannot create " + path_ +
            "-shm to read them (" + why_no_shm +
            "); open it once with write access (magcald or magcal refit), or "
            "read a copy in a writable directory",
        SQLITE_READONLY);
  }
  // The identity first: a writer that opens the file from here on is seen by
  // changed_since_open().
  immutable_file_ = identity_of(path_);
  if (!immutable_file_) {
    throw StorageError(StorageError::Kind::kNotFound, "database not found: " + path_);
  }
  const std::string uri = "file:" + uri_path(path_) + "?immutable=1";
  return sqlite3_open_v2(uri.c_str(), &db_, flags | SQLITE_OPEN_URI, nullptr);
}

std::optional<Database::FileIdentity> Database::identity_of(const std::string& path) {
  struct stat st {};
  if (::stat(path.c_str(), &st) != 0) return std::nullopt;
  return FileIdentity{static_cast<uint64_t>(st.st_dev), static_cast<uint64_t>(st.st_ino),
                      static_cast<int64_t>(st.st_size),
                      static_cast<int64_t>(st.st_mtim.tv_sec) * 1'000'000'000 + st.st_mtim.tv_nsec};
}

bool Database::changed_since_open() const {
  if (!immutable_file_) return false;
  return file_exists(path_ + "-shm") || wal_has_frames(path_) ||
         identity_of(path_) != immutable_file_;
}

Database::~Database() {
  // Statements belong to the stores, which are destroyed first (they hold a Database&);
  // sqlite3_close_v2 still copes if one is left.
  if (db_) sqlite3_close_v2(db_);
}

static_assert(kSqliteReadonlyDbMoved == SQLITE_READONLY_DBMOVED);

void Database::configure(const OpenOptions& options) {
  // A reader (the CLI, the sqlite3 shell) or a second writer (`magcal refit`) holding a lock
  // must make us wait briefly, never fail: the daemon's ingest would otherwise drop batches.
  sqlite3_busy_timeout(db_, options.busy_timeout_ms);
  // Referential integrity (refit_jobs.calibration_id -> calibrations.id) is off by default in
  // SQLite and per connection.
  exec("PRAGMA foreign_keys = ON");
  if (options.read_only) return;
  // SQLite silently falls back to a read-only open when the file is not writable: say so now
  // (a clear error at start) rather than at the first commit.
  if (sqlite3_db_readonly(db_, "main") == 1) {
    throw StorageError::sqlite(StorageError::Kind::kEngine,
                               "cannot open database " + path_ + " for writing (read-only file?)",
                               SQLITE_READONLY);
  }
  // WAL: readers never block the writer and see a consistent snapshot while it writes; a
  // crash leaves every committed transaction intact. Persistent in the file.
  exec("PRAGMA journal_mode = WAL");
  // NORMAL in WAL mode: no fsync per commit (the insert rate needs it); an application crash
  // loses nothing committed, a power loss at most the last commits, never consistency.
  exec("PRAGMA synchronous = NORMAL");
}

void Database::check_and_migrate(const OpenOptions& options) {
  const auto all = migrations();
  const int latest = static_cast<int>(all.size());
  const int target = migration_target(options, latest);

  auto check = [&](int64_t app_id, int64_t version, bool empty) {
    if (app_id == 0 && version == 0 && empty) return;  // a new file: ours to initialise
    if (app_id != kApplicationId) {
      throw StorageError(
          StorageError::Kind::kForeignFile,
          path_ + " is not a magcal database (application_id " + std::to_string(app_id) + ")");
    }
    if (version > latest) {
      throw StorageError(StorageError::Kind::kNewerSchema,
                         path_ + " has schema version " + std::to_string(version) +
                             ", newer than this magcal knows (" + std::to_string(latest) +
                             "): upgrade magcal");
    }
  };
  auto is_empty = [&] {
    Statement st(*this, "SELECT count(*) FROM sqlite_schema");
    return st.step() && st.column_int64(0) == 0;
  };

  int64_t version = pragma_int(*this, "user_version");
  check(pragma_int(*this, "application_id"), version, is_empty());
  if (version >= target) return;
  if (options.read_only) {
    if (version == 0) {
      throw StorageError(StorageError::Kind::kForeignFile,
                         path_ + " is empty, not a magcal database");
    }
    throw StorageError(StorageError::Kind::kOlderSchema,
                       path_ + " has schema version " + std::to_string(version) +
                           "; open it once read-write (magcald or magcal refit) to upgrade");
  }
  // Each migration in its own IMMEDIATE transaction; re-read the version under the write lock
  // because another process may have migrated meanwhile.
  for (const Migration& m : all) {
    if (m.version > target) break;
    Transaction tx(*this);
    const int64_t app_id = pragma_int(*this, "application_id");
    version = pragma_int(*this, "user_version");
    check(app_id, version, version == 0 && is_empty());
    if (m.version <= version) continue;
    if (m.version != version + 1) {
      throw StorageError(StorageError::Kind::kEngine, "migration gap before " + std::string(m.name),
                         StorageError::Condition::kOther);
    }
    if (m.version == 1) exec("PRAGMA application_id = " + std::to_string(kApplicationId));
    exec(m.sql);
    exec("PRAGMA user_version = " + std::to_string(m.version));
    tx.commit();
  }
}

int Database::latest_schema_version() {
  return static_cast<int>(migrations().size());
}

int Database::schema_version() const {
  return static_cast<int>(pragma_int(const_cast<Database&>(*this), "user_version"));
}

void Database::exec(std::string_view sql) {
  const std::string text(sql);
  char* err = nullptr;
  const int rc = sqlite3_exec(db_, text.c_str(), nullptr, nullptr, &err);
  if (rc != SQLITE_OK) {
    std::string msg = err ? err : sqlite3_errstr(rc);
    sqlite3_free(err);
    const auto kind = (rc & 0xff) == SQLITE_NOTADB ? StorageError::Kind::kForeignFile
                                                   : StorageError::Kind::kEngine;
    throw StorageError::sqlite(kind, path_ + ": " + msg, rc);
  }
}

int64_t Database::last_insert_id() const {
  return sqlite3_last_insert_rowid(db_);
}

std::string Database::integrity_check() {
  Statement st(*this, "PRAGMA integrity_check");
  std::string report;
  while (st.step()) {
    if (!report.empty()) report += '\n';
    report += st.column_text(0);
  }
  return report;
}

void Database::check_file_in_place() {
  int moved = 0;
  if (sqlite3_file_control(db_, "main", SQLITE_FCNTL_HAS_MOVED, &moved) != SQLITE_OK) return;
  if (moved) {
    throw StorageError::sqlite(
        StorageError::Kind::kEngine,
        path_ +
            ": the database file was deleted, renamed or replaced while open; "
            "nothing more is committed into it",
        SQLITE_READONLY_DBMOVED);
  }
}

bool Database::begin_transaction(TransactionMode mode) {
  // Inside an outer transaction (a caller grouping several store calls) nest as a savepoint.
  if (sqlite3_get_autocommit(db_) == 0) {
    exec("SAVEPOINT magcal_tx");
    return true;
  }
  if (mode == TransactionMode::kWrite) check_file_in_place();
  exec(mode == TransactionMode::kWrite ? "BEGIN IMMEDIATE" : "BEGIN DEFERRED");
  return false;
}

void Database::commit_transaction(bool nested) {
  exec(nested ? "RELEASE magcal_tx" : "COMMIT");
}

void Database::end_transaction(bool nested, bool committed) noexcept {
  if (committed || db_ == nullptr) return;
  const char* sql = nested ? "ROLLBACK TO magcal_tx; RELEASE magcal_tx" : "ROLLBACK";
  sqlite3_exec(db_, sql, nullptr, nullptr, nullptr);
}

std::unique_ptr<SampleWindowStore> Database::make_sample_window_store() {
  return std::make_unique<SqliteSampleWindowStore>(*this);
}

}  // namespace magcal::storage
