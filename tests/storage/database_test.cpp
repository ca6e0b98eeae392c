// Connection, pragmas and migrations: new file, upgrade from version 1, foreign and newer files
// refused, read-only never creates, embedded migrations identical to storage/migrations/*.sql.
#include "storage/sqlite/database.hpp"

#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstring>

#include <catch2/catch.hpp>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "storage/calibration_history.hpp"
#include "storage/meta_store.hpp"
#include "storage/migrations.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "storage/sqlite/statement.hpp"
#include "tests/test_skip.hpp"

namespace fs = std::filesystem;
using namespace magcal::storage;

namespace {

struct TempDir {
  fs::path path;
  TempDir() {
    static int counter = 0;
    path = fs::temp_directory_path() /
           ("magcal_db_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    fs::create_directories(path);
  }
  ~TempDir() { fs::remove_all(path); }
  std::string file(const std::string& name) const { return (path / name).string(); }
};

int64_t query_int(Database& db, const std::string& sql) {
  Statement st(db, sql);
  REQUIRE(st.step());
  return st.column_int64(0);
}

std::string query_text(Database& db, const std::string& sql) {
  Statement st(db, sql);
  REQUIRE(st.step());
  return st.column_text(0);
}

StorageError::Kind open_error(const std::string& path, OpenOptions options = {}) {
  try {
    Database db(path, options);
  } catch (const StorageError& e) {
    return e.kind();
  }
  FAIL("open of " << path << " succeeded");
  return StorageError::Kind::kEngine;
}

}  // namespace

TEST_CASE("a new file gets the newest schema, WAL and the application id") {
  TempDir dir;
  Database db(dir.file("new.db"));
  CHECK(db.schema_version() == Database::latest_schema_version());
  CHECK(db.schema_version() == static_cast<int>(migrations().size()));
  CHECK(query_int(db, "PRAGMA application_id") == kApplicationId);
  CHECK(query_text(db, "PRAGMA journal_mode") == "wal");
  CHECK(query_int(db, "PRAGMA foreign_keys") == 1);
  CHECK(query_int(db, "PRAGMA synchronous") == 1);  // NORMAL
  for (const char* table : {"samples", "calibrations", "refit_jobs", "filter_states", "meta"}) {
    CHECK(query_int(db, std::string("SELECT count(*) FROM sqlite_schema WHERE name = '") + table +
                            "'") == 1);
  }
  CHECK(db.integrity_check() == "ok");
}

TEST_CASE("an in-memory database works the same") {
  Database db(":memory:");
  CHECK(db.schema_version() == Database::latest_schema_version());
  SqliteMetaStore meta(db);
  meta.set("k", "v");
  CHECK(meta.get("k") == "v");
  CHECK_FALSE(meta.get("absent").has_value());
}

TEST_CASE("migrations are numbered 1..N and each bumps user_version") {
  const auto all = migrations();
  REQUIRE(!all.empty());
  for (size_t k = 0; k < all.size(); ++k) {
    CHECK(all[k].version == static_cast<int>(k + 1));
    OpenOptions options;
    options.migrate_to = all[k].version;
    Database db(":memory:", options);
    CHECK(db.schema_version() == all[k].version);
  }
}

TEST_CASE("embedded migrations equal the .sql files in storage/migrations") {
  for (const Migration& m : migrations()) {
    const fs::path file =
        fs::path(MAGCAL_SOURCE_DIR) / "storage" / "migrations" / (std::string(m.name) + ".sql");
    INFO(file);
    std::ifstream in(file, std::ios::binary);
    REQUIRE(in.good());
    std::stringstream text;
    text << in.rdbuf();
    CHECK(text.str() == m.sql);
  }
}

TEST_CASE("a version-1 database is upgraded on open and keeps its data") {
  TempDir dir;
  const std::string path = dir.file("v1.db");
  {
    OpenOptions v1;
    v1.migrate_to = 1;
    Database db(path, v1);
    REQUIRE(db.schema_version() == 1);
    CHECK(query_int(db, "SELECT count(*) FROM sqlite_schema WHERE name = 'meta'") == 0);
    // A row as a version-1 magcal wrote it (today's CalibrationHistory writes newer columns).
    db.exec(
        "INSERT INTO calibrations (sat_id, method, utime, window_start_utime, window_end_utime, "
        "n_samples, bias_x_nT, bias_y_nT, bias_z_nT, D11, D22, D33, D12, D13, D23, cov, "
        "has_alignment, residual_rms_nT, status, verdict, software_version, created_utime) "
        "VALUES ('SAT1', 'twostep', 42, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, zeroblob(360), 0, "
        "0, 0, 'accepted', 'v1', 1)");
  }
  {
    // Read-only code does not migrate: it says what to do.
    OpenOptions ro;
    ro.read_only = true;
    CHECK(open_error(path, ro) == StorageError::Kind::kOlderSchema);
  }
  Database db(path);
  CHECK(db.schema_version() == Database::latest_schema_version());
  CHECK(query_int(db, "SELECT count(*) FROM sqlite_schema WHERE name = 'meta'") == 1);
  SqliteCalibrationHistory history(db);
  const auto latest = history.latest("SAT1", "twostep");
  REQUIRE(latest.has_value());
  CHECK(latest->utime == 42);
  // Columns added by later migrations read as unknown (NULL) for old rows.
  CHECK(std::isnan(latest->noise_scale));
  CHECK(latest->covariance_lag_window == -1);
  CHECK(latest->has_nonlinearity == -1);
  CHECK(std::isnan(latest->nis_mean));
  CHECK(latest->has_temperature_model == -1);
  CHECK(std::isnan(latest->reference_temperature_C));
  CHECK(latest->temperature_model_refit_id == 0);
  CHECK(db.integrity_check() == "ok");
}

TEST_CASE("a database from a newer magcal is refused") {
  TempDir dir;
  const std::string path = dir.file("newer.db");
  {
    Database db(path);
    db.exec("PRAGMA user_version = " + std::to_string(Database::latest_schema_version() + 1));
  }
  CHECK(open_error(path) == StorageError::Kind::kNewerSchema);
  OpenOptions ro;
  ro.read_only = true;
  CHECK(open_error(path, ro) == StorageError::Kind::kNewerSchema);
}

TEST_CASE("foreign and corrupt files are refused and left untouched") {
  TempDir dir;
  SECTION("another application's SQLite file") {
    const std::string path = dir.file("other.db");
    {
      // A plain SQLite file with a table and no (or another) application_id.
      Database tmp(":memory:");
      tmp.exec("VACUUM INTO '" + path + "'");
    }
    {
      OpenOptions raw;
      raw.migrate_to = 0;  // creates nothing
      Database db(path, raw);
      db.exec("PRAGMA application_id = 1234");
    }
    CHECK(open_error(path) == StorageError::Kind::kForeignFile);
  }
  SECTION("a SQLite file with tables but without application_id") {
    const std::string path = dir.file("plain.db");
    {
      OpenOptions raw;
      raw.migrate_to = 0;
      Database db(path, raw);
      db.exec("CREATE TABLE t(x)");
    }
    CHECK(open_error(path) == StorageError::Kind::kForeignFile);
  }
  SECTION("not a SQLite file at all") {
    const std::string path = dir.file("garbage.db");
    {
      std::ofstream out(path, std::ios::binary);
      for (int k = 0; k < 512; ++k) out << "this is not a database ";
    }
    const auto size = fs::file_size(path);
    CHECK(open_error(path) == StorageError::Kind::kForeignFile);
    OpenOptions ro;
    ro.read_only = true;
    CHECK(open_error(path, ro) == StorageError::Kind::kForeignFile);
    CHECK(fs::file_size(path) == size);
  }
}

TEST_CASE("read-only open never creates a file") {
  TempDir dir;
  const std::string path = dir.file("missing.db");
  OpenOptions ro;
  ro.read_only = true;
  CHECK(open_error(path, ro) == StorageError::Kind::kNotFound);
  CHECK_FALSE(fs::exists(path));
  // An empty file is not a magcal database either, and stays empty.
  { std::ofstream touch(path); }
  CHECK(open_error(path, ro) == StorageError::Kind::kForeignFile);
  CHECK(fs::file_size(path) == 0);
}

TEST_CASE("read-only connections cannot write") {
  TempDir dir;
  const std::string path = dir.file("ro.db");
  { Database db(path); }
  OpenOptions ro;
  ro.read_only = true;
  Database db(path, ro);
  CHECK(db.schema_version() == Database::latest_schema_version());
  CHECK_THROWS_AS(db.exec("CREATE TABLE x(y)"), StorageError);
}

TEST_CASE("a transaction rolls back unless committed, and nests as a savepoint") {
  Database db(":memory:");
  SqliteMetaStore meta(db);
  {
    Transaction tx(db);
    meta.set("a", "1");
  }
  CHECK_FALSE(meta.get("a").has_value());
  {
    Transaction outer(db);
    meta.set("b", "1");
    {
      Transaction inner(db);
      meta.set("c", "1");
    }  // inner rolled back, outer continues
    outer.commit();
  }
  CHECK(meta.get("b") == "1");
  CHECK_FALSE(meta.get("c").has_value());
}

TEST_CASE("errors carry SQLite's result code: transient faults apart from permanent ones") {
  TempDir tmp;
  const OpenOptions no_wait{.busy_timeout_ms = 0};
  Database writer(tmp.file("codes.db"), no_wait);
  Database other(tmp.file("codes.db"), no_wait);
  writer.exec("CREATE TABLE t (x INTEGER NOT NULL)");
  {
    // Another connection holds the write lock: BUSY, which a retry can heal.
    Transaction held(other);
    try {
      Transaction tx(writer);
      FAIL("a second writer got the write lock");
    } catch (const StorageError& e) {
      CHECK((e.sqlite_code() & 0xff) == 5);  // SQLITE_BUSY
      CHECK(e.condition() == StorageError::Condition::kBusy);
      CHECK(e.transient());
    }
  }
  Transaction tx(writer);  // released: the same call now succeeds
  tx.commit();
  // A constraint violation is permanent: retrying the same row cannot succeed.
  try {
    writer.exec("INSERT INTO t VALUES (NULL)");
    FAIL("NULL accepted in a NOT NULL column");
  } catch (const StorageError& e) {
    CHECK((e.sqlite_code() & 0xff) == 19);  // SQLITE_CONSTRAINT
    CHECK(e.condition() == StorageError::Condition::kConstraint);
    CHECK_FALSE(e.transient());
  }
  // Not SQLite's failure at all: no code, not transient.
  CHECK_FALSE(StorageError(StorageError::Kind::kNewerSchema, "x").transient());
}

TEST_CASE("a database file deleted or moved while open is reported, not written into") {
  TempDir tmp;
  const std::string path = tmp.file("moving.db");
  Database db(path);
  CHECK_NOTHROW(db.check_file_in_place());
  fs::rename(path, tmp.file("elsewhere.db"));
  try {
    db.check_file_in_place();
    FAIL("the move went unnoticed");
  } catch (const StorageError& e) {
    CHECK(e.sqlite_code() == kSqliteReadonlyDbMoved);
    CHECK(e.condition() == StorageError::Condition::kFileMoved);
    CHECK(e.transient());  // moved back, it works again
  }
  fs::rename(tmp.file("elsewhere.db"), path);
  CHECK_NOTHROW(db.check_file_in_place());
  fs::remove(path);
  CHECK_THROWS_AS(db.check_file_in_place(), StorageError);
  Database memory(":memory:");
  CHECK_NOTHROW(memory.check_file_in_place());
}

TEST_CASE("a directory is refused as a database, naming it, read-only or not") {
  TempDir tmp;
  const std::string folder = tmp.file("folder");
  fs::create_directories(folder);
  for (const bool read_only : {false, true}) {
    OpenOptions options;
    options.read_only = read_only;
    try {
      Database db(folder, options);
      FAIL("a directory opened as a database");
    } catch (const StorageError& e) {
      CHECK(e.kind() == StorageError::Kind::kInvalidArgument);
      CHECK(std::string(e.what()) ==
            "cannot open database " + folder + ": is a directory, not a database file");
      CHECK_FALSE(e.transient());  // retrying cannot help
    }
  }
  CHECK(fs::is_empty(folder));
}

TEST_CASE("a new database whose directory is missing names the directory") {
  TempDir tmp;
  const std::string missing_dir = tmp.file("no/such");
  try {
    Database db(missing_dir + "/new.db");
    FAIL("opened a database in a missing directory");
  } catch (const StorageError& e) {
    CHECK_THAT(e.what(), Catch::Contains("cannot open database " + missing_dir + "/new.db"));
    CHECK_THAT(e.what(),
               Catch::Contains("(directory " + missing_dir + ": " + std::strerror(ENOENT) + ")"));
  }
}

TEST_CASE("a new database whose directory is not writable names the directory") {
  TempDir tmp;
  const std::string locked = tmp.file("locked");
  fs::create_directories(locked);
  fs::permissions(locked, fs::perms::owner_read | fs::perms::owner_exec);
  // Root writes anywhere (CI runs as root): the open is then tried by a child that has dropped to
  // the unprivileged user "nobody" (65534), which the directory does not let write.
  auto open_message = []([[maybe_unused]] const std::string& path) -> std::string {
    try {
      Database db(path);
      return "opened";
    } catch (const StorageError& e) {
      return e.what();
    }
  };
  std::string message;
  if (::geteuid() != 0) {
    message = open_message(locked + "/new.db");
  } else {
    int fds[2];
    REQUIRE(::pipe(fds) == 0);
    const pid_t child = ::fork();
    REQUIRE(child >= 0);
    if (child == 0) {
      ::close(fds[0]);
      const std::string m = ::setgid(65534) == 0 && ::setuid(65534) == 0
                                ? open_message(locked + "/new.db")
                                : "cannot drop to nobody";
      const ssize_t written = ::write(fds[1], m.data(), m.size());
      ::_exit(written == static_cast<ssize_t>(m.size()) ? 0 : 1);
    }
    ::close(fds[1]);
    char buffer[512];
    ssize_t n = 0;
    while ((n = ::read(fds[0], buffer, sizeof buffer)) > 0) message.append(buffer, buffer + n);
    ::close(fds[0]);
    int status = 0;
    REQUIRE(::waitpid(child, &status, 0) == child);
    REQUIRE(WIFEXITED(status));
    CHECK(WEXITSTATUS(status) == 0);
  }
  INFO(message);
  CHECK_THAT(message, Catch::Contains("cannot open database " + locked + "/new.db"));
  CHECK_THAT(message, Catch::Contains("(directory " + locked + ": " + std::strerror(EACCES) + ")"));
  CHECK_FALSE(fs::exists(locked + "/new.db"));
  fs::permissions(locked, fs::perms::owner_all);
}

TEST_CASE("a write transaction refuses a file moved while open, and works once it is back") {
  TempDir tmp;
  const std::string path = tmp.file("moving.db");
  Database db(path);
  fs::rename(path, tmp.file("elsewhere.db"));
  try {
    Transaction tx(db);
    FAIL("a write transaction began on a moved file");
  } catch (const StorageError& e) {
    CHECK(e.condition() == StorageError::Condition::kFileMoved);
  }
  {
    Transaction read(db, Transaction::Mode::kReadSnapshot);  // reading is harmless
    read.commit();
  }
  fs::rename(tmp.file("elsewhere.db"), path);
  Transaction tx(db);
  tx.commit();
}

TEST_CASE("open_database: a postgresql:// or postgres:// URI is PostgreSQL, anything else a file") {
  CHECK(is_postgres_uri("postgresql://magcal@db.example/magcal"));
  CHECK(is_postgres_uri("postgres:///magcal?host=/run/postgresql"));
  CHECK_FALSE(is_postgres_uri("/var/lib/magcal/magcal.db"));
  CHECK_FALSE(is_postgres_uri("postgresql.db"));
  CHECK(dynamic_cast<Database*>(open_database(":memory:").get()) != nullptr);
  // A URI is never taken for a file name: a bad one is refused as a URI.
  try {
    open_database("postgresql://magcal@/db?no_such_option=1");
    FAIL("a bad URI was accepted");
  } catch (const StorageError& e) {
    CHECK(e.kind() == StorageError::Kind::kInvalidArgument);
  }
}
