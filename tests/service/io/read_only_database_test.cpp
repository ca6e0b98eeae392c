// Read-only tools on a database in a directory they cannot write (service/io/
// read_only_database.hpp, storage::OpenOptions::read_only): `magcal status|history|serve` as
// real processes, and read_consistently in this process. Root ignores file permissions, so the
// directory is seen through a read-only bind mount in a mount namespace of this test process
// (its children share it); without root, in a user namespace of its own. Skips when neither is
// allowed here (fails under CI=true).
#include <fcntl.h>
#include <sched.h>
#include <sys/mount.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include "service/io/read_only_database.hpp"
#include "service/io/status_report.hpp"
#include "storage/calibration_history.hpp"
#include "storage/sample_window_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/test_skip.hpp"

namespace fs = std::filesystem;
using magcal::storage::CalibrationRecord;
using magcal::storage::Database;
using magcal::storage::SqliteCalibrationHistory;
using magcal::test::Run;
using magcal::test::run_magcal;
using magcal::test::TempDir;

namespace {

constexpr int64_t kSecond = 1'000'000;
constexpr int64_t kT0 = 1'767'225'600LL * kSecond;  // 2026-01-01T00:00:00Z

bool write_file(const std::string& path, const std::string& text) {
  std::ofstream out(path);
  out << text;
  return static_cast<bool>(out);
}

// `dir` seen read-only at `view` until destroyed. error() says why not when it could not be
// made.
class ReadOnlyView {
 public:
  ReadOnlyView(const std::string& dir, const std::string& view) : view_(view) {
    fs::create_directories(view);
    if (::geteuid() != 0) {
      // Root of a user namespace of our own may mount; our uid is its root.
      const uid_t uid = ::geteuid();
      const gid_t gid = ::getegid();
      if (::unshare(CLONE_NEWUSER | CLONE_NEWNS) != 0) {
        error_ = std::string("unshare(CLONE_NEWUSER): ") + std::strerror(errno);
        return;
      }
      write_file("/proc/self/setgroups", "deny");
      if (!write_file("/proc/self/uid_map", "0 " + std::to_string(uid) + " 1\n") ||
          !write_file("/proc/self/gid_map", "0 " + std::to_string(gid) + " 1\n")) {
        error_ = "cannot map this user into its namespace";
        return;
      }
    } else if (::unshare(CLONE_NEWNS) != 0) {
      error_ = std::string("unshare(CLONE_NEWNS): ") + std::strerror(errno);
      return;
    }
    // Our mounts stay in our namespace; then the bind mount, made read-only.
    if (::mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0 ||
        ::mount(dir.c_str(), view.c_str(), nullptr, MS_BIND, nullptr) != 0 ||
        ::mount(nullptr, view.c_str(), nullptr, MS_REMOUNT | MS_BIND | MS_RDONLY, nullptr) != 0) {
      error_ = std::string("read-only bind mount: ") + std::strerror(errno);
      return;
    }
    mounted_ = true;
    // What a user without write access meets.
    if (::access(view.c_str(), W_OK) == 0) error_ = view + " is still writable";
  }
  ~ReadOnlyView() {
    if (mounted_) ::umount2(view_.c_str(), MNT_DETACH);
  }
  const std::string& error() const { return error_; }

 private:
  std::string view_, error_;
  bool mounted_ = false;
};

// The view, or nullptr after skipping the test (saying why).
std::unique_ptr<ReadOnlyView> read_only_view_or_skip(const std::string& dir,
                                                     const std::string& view) {
  auto read_only = std::make_unique<ReadOnlyView>(dir, view);
  if (read_only->error().empty()) return read_only;
  magcal::test::skip_or_fail("no read-only view of a directory here: " + read_only->error());
  return nullptr;
}

CalibrationRecord record(const std::string& sat, int64_t utime, double bias_x) {
  CalibrationRecord r;
  r.sat_id = sat;
  r.method = "twostep";
  r.utime = utime;
  r.window_start_utime = utime - 3600 * kSecond;
  r.window_end_utime = utime;
  r.n_samples = 360;
  r.bias_nT = {bias_x, 20.0, 30.0};
  for (int i = 0; i < 9; ++i) r.cov[magcal::storage::cov_index(i, i)] = i < 3 ? 2.25 : 1e-8;
  r.residual_rms_nT = 3.0;
  r.verdict = "accepted";
  return r;
}

// A closed database with samples and two results of SAT1 (no -wal or -shm left).
void build_database(const std::string& path) {
  Database db(path);
  magcal::storage::SqliteSampleWindowStore samples(db);
  std::vector<magcal::storage::StoredSample> batch(100);
  for (size_t k = 0; k < batch.size(); ++k) {
    batch[k].sat_id = "SAT1";
    batch[k].utime = kT0 + static_cast<int64_t>(k) * 10 * kSecond;
    batch[k].h_norm_nT = 30000.0;
  }
  samples.insert_batch(batch);
  SqliteCalibrationHistory history(db);
  history.append(record("SAT1", kT0 + 500 * kSecond, 10.0));
  history.append(record("SAT1", kT0 + 990 * kSecond, 11.0));
}

// The spacecraft magcal status --json lists.
std::vector<std::string> status_spacecraft(const std::string& json) {
  std::vector<std::string> ids;
  const auto status = nlohmann::json::parse(json);
  for (const auto& s : status["spacecraft"]) ids.push_back(s["sat_id"]);
  return ids;
}

}  // namespace

TEST_CASE("status, history and serve read a database in a directory they cannot write") {
  TempDir dir("magcal_ro");
  const std::string data = dir.file("data"), view = dir.file("view");
  fs::create_directories(data);
  build_database(data + "/m.db");
  REQUIRE_FALSE(fs::exists(data + "/m.db-shm"));
  const auto read_only = read_only_view_or_skip(data, view);
  if (!read_only) return;
  // No daemon has it open, so it is read immutable; nothing is created next to it.
  const std::vector<std::string> commands = {"status --db %", "status --db % --json",
                                             "history --db % --sat SAT1 --format csv"};
  const auto run_on = [&](const std::string& command, const std::string& db) {
    std::string line = command;
    line.replace(line.find('%'), 1, db);
    return run_magcal(line, dir);
  };
  std::vector<Run> there;
  for (const auto& command : commands) there.push_back(run_on(command, view + "/m.db"));
  magcal::test::ServeProcess serve(view + "/m.db", dir);
  const auto api = magcal::test::http_get(serve.port(), "/api/v1/history?sat=SAT1");
  INFO(api.body);
  CHECK(api.status == 200);
  CHECK(nlohmann::json::parse(api.body).size() == 2);
  CHECK(magcal::test::http_get(serve.port(), "/api/v1/spacecraft").status == 200);
  CHECK(magcal::test::http_get(serve.port(), "/metrics").status == 200);
  CHECK(serve.stop() == 0);
  CHECK(std::distance(fs::directory_iterator(data), fs::directory_iterator()) == 1);
  // The same answers as where they can write.
  for (size_t k = 0; k < commands.size(); ++k) {
    INFO(commands[k] << ": " << there[k].err);
    CHECK(there[k].exit_code == 0);
    CHECK(there[k].err.empty());
    CHECK(there[k].out == run_on(commands[k], data + "/m.db").out);
    CHECK(there[k].out.find("SAT1") != std::string::npos);
  }
}

TEST_CASE("with a writer holding the database (its -wal and -shm present), they read its commits") {
  TempDir dir("magcal_ro_live");
  const std::string data = dir.file("data"), view = dir.file("view");
  fs::create_directories(data);
  build_database(data + "/m.db");
  Database writer(data + "/m.db");
  SqliteCalibrationHistory(writer).append(record("SAT2", kT0 + 1000 * kSecond, 5.0));
  REQUIRE(fs::exists(data + "/m.db-shm"));
  const auto read_only = read_only_view_or_skip(data, view);
  if (!read_only) return;
  const Run r = run_magcal("status --db " + view + "/m.db --json", dir);
  INFO(r.err);
  CHECK(r.exit_code == 0);
  CHECK(status_spacecraft(r.out) == std::vector<std::string>{"SAT1", "SAT2"});
}

TEST_CASE("a lock-free read notices a writer that opened the file meanwhile and reads again") {
  TempDir dir("magcal_ro_race");
  const std::string data = dir.file("data"), view = dir.file("view");
  fs::create_directories(data);
  build_database(data + "/m.db");
  const auto read_only = read_only_view_or_skip(data, view);
  if (!read_only) return;
  std::unique_ptr<magcal::storage::Connection> reader;
  // An SQLite reader: its immutable() open is what this case is about.
  const auto immutable = [&reader] { return dynamic_cast<Database&>(*reader).immutable(); };
  const auto ids = [](magcal::storage::Connection& db) {
    std::vector<std::string> out;
    for (const auto& s : magcal::read_status(db, 3600 * kSecond).spacecraft)
      out.push_back(s.sat_id);
    return out;
  };
  CHECK(magcal::read_consistently(reader, view + "/m.db", ids) == std::vector<std::string>{"SAT1"});
  REQUIRE(immutable());
  CHECK_FALSE(reader->changed_since_open());
  {
    Database writer(data + "/m.db");
    CHECK(reader->changed_since_open());  // its -shm appeared
    SqliteCalibrationHistory(writer).append(record("SAT2", kT0 + 1000 * kSecond, 5.0));
    // The next read reopens, through the writer's -shm, and sees its commit.
    CHECK(magcal::read_consistently(reader, view + "/m.db", ids) ==
          std::vector<std::string>{"SAT1", "SAT2"});
    CHECK_FALSE(immutable());
    reader.reset();  // the writer, last to close, checkpoints and removes its -wal and -shm
  }
  // The writer closed: an immutable read again, of the new content.
  REQUIRE_FALSE(fs::exists(data + "/m.db-shm"));
  CHECK(magcal::read_consistently(reader, view + "/m.db", ids) ==
        std::vector<std::string>{"SAT1", "SAT2"});
  CHECK(immutable());
  // A file changed under an immutable connection (size, time) is noticed too.
  {
    Database writer(data + "/m.db");
    SqliteCalibrationHistory(writer).append(record("SAT3", kT0 + 1100 * kSecond, 6.0));
  }
  CHECK(reader->changed_since_open());
}

TEST_CASE("a -wal with commits but no -shm where they cannot write: one line, file and cause") {
  TempDir dir("magcal_ro_hot");
  const std::string data = dir.file("data"), copy = dir.file("copy"), view = dir.file("view");
  fs::create_directories(data);
  fs::create_directories(copy);
  build_database(data + "/m.db");
  {
    // What a writer that crashed leaves: commits in the -wal, not yet in the file.
    Database writer(data + "/m.db");
    writer.exec("PRAGMA wal_autocheckpoint = 0");
    SqliteCalibrationHistory(writer).append(record("SAT2", kT0 + 1000 * kSecond, 5.0));
    fs::copy_file(data + "/m.db", copy + "/m.db");
    fs::copy_file(data + "/m.db-wal", copy + "/m.db-wal");
  }
  REQUIRE(fs::file_size(copy + "/m.db-wal") > 0);
  {
    const auto read_only = read_only_view_or_skip(copy, view);
    if (!read_only) return;
    const Run r = run_magcal("status --db " + view + "/m.db", dir);
    INFO(r.err);
    CHECK(r.exit_code == 2);
    CHECK(r.out.empty());
    CHECK(std::count(r.err.begin(), r.err.end(), '\n') == 1);
    CHECK(r.err.find("cannot read " + view + "/m.db: its " + view + "/m.db-wal holds commits") !=
          std::string::npos);
    CHECK(r.err.find(view + ": " + std::strerror(EROFS)) != std::string::npos);
  }
  // Where it can write, the same copy reads with the commit.
  const Run r = run_magcal("status --db " + copy + "/m.db --json", dir);
  INFO(r.err);
  CHECK(status_spacecraft(r.out) == std::vector<std::string>{"SAT1", "SAT2"});
}
