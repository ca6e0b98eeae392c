// The backends a store test runs on, as Catch2 template types: TEMPLATE_TEST_CASE(...,
// SqliteBackend, PostgresBackend) runs the same test on an SQLite file and on a PostgreSQL database
// (a throwaway server per test process, tests/storage/postgres/pg_test_server.hpp), each reported
// on its own. Without the PostgreSQL programs the PostgreSQL case is skipped (tests/test_skip.hpp;
// with CI=true it fails).
//
//   TestType backend;
//   auto db = backend.open();    // a new, empty database; nullptr: skipped, return at once
//   backend.open(options)        // the same, opened with these options (e.g. an old schema)
//   backend.open_again(options)  // another connection to the same database
//   backend.new_database()       // instead of open(): the path or URI of a new, empty database
//                                // for code that opens it itself (a worker, magcald); "": skipped
//   query_int(*db, sql)          // the one integer a query returns (a count), either backend
//   before_migration("_name")    // options that open at the schema before migration NNNN_name
#pragma once

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <filesystem>
#include <functional>
#include <memory>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "storage/connection.hpp"
#include "storage/migrations.hpp"
#include "storage/postgres/pg_database.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/statement.hpp"
#include "tests/storage/postgres/pg_test_server.hpp"

namespace magcal::test {

class SqliteBackend {
 public:
  static constexpr const char* kName = "sqlite";
  SqliteBackend() {
    static int counter = 0;
    dir_ = std::filesystem::temp_directory_path() /
           ("magcal_backend_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    std::filesystem::create_directories(dir_);
  }
  ~SqliteBackend() {
    std::error_code ignored;
    std::filesystem::remove_all(dir_, ignored);
  }
  SqliteBackend(const SqliteBackend&) = delete;
  SqliteBackend& operator=(const SqliteBackend&) = delete;

  std::unique_ptr<storage::Connection> open(const storage::OpenOptions& options = {}) {
    return open_again(options);
  }
  std::unique_ptr<storage::Connection> open_again(const storage::OpenOptions& options = {}) {
    return storage::open_database(new_database(), options);
  }
  std::string new_database() const { return (dir_ / "test.db").string(); }
  // SQL for a blob of n zero bytes.
  static std::string zero_blob_sql(int n) { return "zeroblob(" + std::to_string(n) + ")"; }

 private:
  std::filesystem::path dir_;
};

class PostgresBackend {
 public:
  static constexpr const char* kName = "postgres";
  std::unique_ptr<storage::Connection> open(const storage::OpenOptions& options = {}) {
    if (new_database().empty()) return nullptr;
    return open_again(options);
  }
  std::string new_database() {
    PgTestServer* server = pg_server_or_skip();
    uri_ = server == nullptr ? "" : server->create_database();
    return uri_;
  }
  std::unique_ptr<storage::Connection> open_again(const storage::OpenOptions& options = {}) {
    return storage::open_database(uri_, options);
  }
  static std::string zero_blob_sql(int n) {
    return "decode(repeat('00', " + std::to_string(n) + "), 'hex')";
  }

 private:
  std::string uri_;
};

// Opens at the schema just before the migration whose name ends with `name_suffix` (version N
// is the same schema on both backends), to write rows as an older magcal stored them.
inline storage::OpenOptions before_migration(std::string_view name_suffix) {
  const auto all = storage::migrations();
  const auto it = std::find_if(all.begin(), all.end(), [&](const storage::Migration& m) {
    return std::string_view(m.name).ends_with(name_suffix);
  });
  REQUIRE(it != all.end());
  storage::OpenOptions options;
  options.migrate_to = it->version - 1;
  return options;
}

inline int64_t query_int(storage::Connection& db, const std::string& sql) {
  if (auto* sqlite = dynamic_cast<storage::Database*>(&db)) {
    storage::Statement st(*sqlite, sql);
    REQUIRE(st.step());
    return st.column_int64(0);
  }
  return dynamic_cast<storage::PgDatabase&>(db).execute(sql).get_int64(0, 0);
}

// Runs body(i) for i = 0 .. n-1 on n threads, released together so that they collide (several
// daemons at once, each on its own connection). Returns each thread's StorageError message
// ("" when it threw none).
inline std::vector<std::string> run_at_once(int n, const std::function<void(int)>& body) {
  std::vector<std::string> errors(static_cast<size_t>(n));
  std::atomic<int> ready{0};
  std::vector<std::thread> threads;
  for (int i = 0; i < n; ++i) {
    threads.emplace_back([&, i] {
      ready.fetch_add(1);
      while (ready.load() < n) std::this_thread::yield();
      try {
        body(i);
      } catch (const storage::StorageError& e) {
        errors[static_cast<size_t>(i)] = e.what();
      }
    });
  }
  for (auto& t : threads) t.join();
  return errors;
}

template <typename Backend>
struct BackendTest {
  Backend backend;
  std::unique_ptr<storage::Connection> db = backend.open();  // nullptr: skipped
};

}  // namespace magcal::test
