// samples table, on SQLite and on PostgreSQL (tests/storage/storage_backends.hpp): round trip,
// duplicates, window order and bounds, retention, atomic batches, a reader beside a writer,
// overlapping writers; and on SQLite a writer killed mid-stream.
#include "storage/sample_window_store.hpp"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <catch2/catch.hpp>
#include <cmath>
#include <filesystem>
#include <optional>
#include <random>

#include "storage/calibration_history.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/storage/storage_backends.hpp"

namespace fs = std::filesystem;
using namespace magcal::storage;
using magcal::test::BackendTest;
using magcal::test::PostgresBackend;
using magcal::test::SqliteBackend;

namespace {

constexpr int64_t kSecond = 1'000'000;
constexpr int64_t kT0 = 1'767'225'600LL * kSecond;  // 2026-01-01T00:00:00Z

struct TempDir {
  fs::path path;
  TempDir() {
    static int counter = 0;
    path = fs::temp_directory_path() /
           ("magcal_samples_test_" + std::to_string(::getpid()) + "_" + std::to_string(counter++));
    fs::create_directories(path);
  }
  ~TempDir() { fs::remove_all(path); }
  std::string file(const std::string& name) const { return (path / name).string(); }
};

StoredSample make_sample(const std::string& sat, int64_t utime, int64_t seq) {
  StoredSample s;
  s.sat_id = sat;
  s.utime = utime;
  s.seq = seq;
  s.receive_utime = utime + 5 * kSecond;
  const double a = 1e-3 * static_cast<double>(seq);
  s.b_sensor_nT = {20000.0 * std::cos(a), 20000.0 * std::sin(a), -30000.0 + seq};
  s.has_direction = seq % 2 == 0;
  s.h_body_nT = {19990.0 * std::cos(a), 19990.0 * std::sin(a), -29990.0};
  s.h_norm_nT = std::sqrt(19990.0 * 19990.0 + 29990.0 * 29990.0);
  s.has_attitude = seq % 3 == 0;
  s.q_body_from_eci = {0.5, 0.5, -0.5, 0.5};
  s.has_position = seq % 5 != 0;
  s.r_ecef_m = {7.0e6, -1.0e5 * a, 3.0e3};
  s.temperature_C = seq % 7 == 0 ? std::nan("") : 20.0 + 0.25 * static_cast<double>(seq % 4);
  return s;
}

std::vector<StoredSample> make_series(const std::string& sat, int n, int64_t step_utime,
                                      int64_t first_seq = 0) {
  std::vector<StoredSample> out;
  for (int k = 0; k < n; ++k) {
    out.push_back(make_sample(sat, kT0 + (first_seq + k) * step_utime, first_seq + k));
  }
  return out;
}

bool same_double(double a, double b) {
  return (std::isnan(a) && std::isnan(b)) || a == b;
}

void check_equal(const StoredSample& got, const StoredSample& want) {
  INFO("utime " << want.utime);
  CHECK(got.sat_id == want.sat_id);
  CHECK(got.utime == want.utime);
  CHECK(got.seq == want.seq);
  CHECK(got.receive_utime == want.receive_utime);
  CHECK(got.b_sensor_nT == want.b_sensor_nT);
  CHECK(got.has_direction == want.has_direction);
  for (int i = 0; i < 3; ++i) {
    CHECK(same_double(got.h_body_nT[i], want.has_direction ? want.h_body_nT[i] : std::nan("")));
  }
  CHECK(got.h_norm_nT == want.h_norm_nT);
  CHECK(got.has_attitude == want.has_attitude);
  if (want.has_attitude) CHECK(got.q_body_from_eci == want.q_body_from_eci);
  CHECK(got.has_position == want.has_position);
  if (want.has_position) CHECK(got.r_ecef_m == want.r_ecef_m);
  CHECK(same_double(got.temperature_C, want.temperature_C));
}

}  // namespace

TEMPLATE_TEST_CASE_METHOD(BackendTest, "samples round-trip exactly, including absent fields",
                          "[samples]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_sample_window_store();
  const auto series = make_series("SAT1", 50, 10 * kSecond);
  const InsertStats stats = store->insert_batch(series);
  CHECK(stats.inserted == 50);
  CHECK(stats.duplicates == 0);
  const auto back = store->window("SAT1", kT0, kT0 + 1000 * kSecond);
  REQUIRE(back.size() == series.size());
  for (size_t k = 0; k < back.size(); ++k) check_equal(back[k], series[k]);
  CHECK(store->count("SAT1") == 50);
  CHECK(store->newest_utime("SAT1") == series.back().utime);
  CHECK_FALSE(store->newest_utime("NOPE").has_value());
  CHECK(store->window("NOPE", kT0, kT0 + 1000 * kSecond).empty());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "read_windows reads several windows at once as read_window reads each",
                          "[samples]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_sample_window_store();
  const auto a = make_series("SAT-A", 30, 10 * kSecond);
  const auto b = make_series("SAT-B", 20, 10 * kSecond, 5);
  REQUIRE(store->insert_batch(a).inserted == 30);
  REQUIRE(store->insert_batch(b).inserted == 20);
  // In the order asked, empty ones (no rows in the range, no such spacecraft) included.
  const std::vector<SampleWindowStore::WindowRequest> requests{
      {"SAT-B", kT0, kT0 + 1000 * kSecond},
      {"NOPE", kT0, kT0 + 1000 * kSecond},
      {"SAT-A", kT0 + 100 * kSecond, kT0 + 200 * kSecond},
      {"SAT-A", kT0 + 5000 * kSecond, kT0 + 6000 * kSecond},
      {"SAT-A", kT0, kT0 + 30 * kSecond}};
  std::vector<StoredSample> rows{make_sample("STALE", kT0, 0)};
  std::vector<size_t> ends{7};
  store->read_windows(requests, rows, ends);
  REQUIRE(ends.size() == requests.size());
  size_t from = 0;
  for (size_t i = 0; i < requests.size(); ++i) {
    const auto want = store->window(requests[i].sat_id, requests[i].t0_utime, requests[i].t1_utime);
    REQUIRE(ends[i] - from == want.size());
    for (size_t k = 0; k < want.size(); ++k) check_equal(rows[from + k], want[k]);
    from = ends[i];
  }
  CHECK(rows.size() == 20 + 10 + 3);
  store->read_windows({}, rows, ends);
  CHECK(rows.empty());
  CHECK(ends.empty());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "duplicate (sat_id, utime) is rejected, counted, and the first copy kept",
                          "[samples]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_sample_window_store();
  auto first = make_series("SAT1", 10, kSecond);
  REQUIRE(store->insert_batch(first).inserted == 10);

  std::vector<StoredSample> second = make_series("SAT1", 5, kSecond, 8);  // 8, 9 stored already
  second.push_back(second.back());                                        // twice in one batch
  StoredSample changed = first[3];
  changed.b_sensor_nT[0] += 1.0;  // same key, different values: still a duplicate
  second.push_back(changed);
  StoredSample other_sat = first[3];
  other_sat.sat_id = "SAT2";  // same time, other spacecraft: not a duplicate
  second.push_back(other_sat);

  std::vector<size_t> duplicate_rows{99};  // cleared by the call
  const InsertStats stats = store->insert_batch(second, &duplicate_rows);
  CHECK(stats.inserted == 3 + 1);    // seq 10, 11, 12 and SAT2
  CHECK(stats.duplicates == 2 + 2);  // seq 8, 9, the repeat, the changed copy
  CHECK(duplicate_rows == std::vector<size_t>{0, 1, 5, 6});
  CHECK(store->count("SAT1") == 13);
  CHECK(store->count("SAT2") == 1);
  const auto back = store->window("SAT1", first[3].utime, first[3].utime + 1);
  REQUIRE(back.size() == 1);
  CHECK(back[0].b_sensor_nT == first[3].b_sensor_nT);
  CHECK(store->spacecraft() == std::vector<std::string>{"SAT1", "SAT2"});
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a sample is stored by the first station to deliver it, a copy from "
                          "another station is a duplicate that changes nothing",
                          "[samples]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_sample_window_store();
  const auto a = make_series("SAT1", 40, kSecond);                     // station A: seq 0..39
  std::vector<StoredSample> b = make_series("SAT1", 40, kSecond, 30);  // station B: seq 30..69
  for (auto& s : b) s.b_sensor_nT[0] += 100.0;  // B's copies differ: must not overwrite A's
  REQUIRE(store->insert_batch(a, nullptr, "station-A").inserted == 40);
  std::vector<size_t> duplicate_rows;
  const InsertStats from_b = store->insert_batch(b, &duplicate_rows, "station-B");
  CHECK(from_b.inserted == 30);
  CHECK(from_b.duplicates == 10);
  CHECK(duplicate_rows == std::vector<size_t>{0, 1, 2, 3, 4, 5, 6, 7, 8, 9});
  store->insert_batch(make_series("SAT1", 5, kSecond, 70));  // no station named
  store->insert_batch(make_series("SAT2", 7, kSecond), nullptr, "station-B");

  const auto back = store->window("SAT1", a[30].utime, a[40 - 1].utime + 1);
  REQUIRE(back.size() == 10);
  for (size_t k = 0; k < back.size(); ++k) check_equal(back[k], a[30 + k]);  // A's copies
  using Counts = std::vector<StationCount>;
  auto counts = [&](std::string_view sat, int64_t t0, int64_t t1) {
    Counts out = store->count_by_station(sat, t0, t1);
    std::vector<std::pair<std::string, int64_t>> pairs;
    for (const auto& c : out) pairs.emplace_back(c.station, c.samples);
    return pairs;
  };
  using Pairs = std::vector<std::pair<std::string, int64_t>>;
  CHECK(counts("SAT1", kT0, kT0 + 1000 * kSecond) ==
        Pairs{{"", 5}, {"station-A", 40}, {"station-B", 30}});
  // Only the window [t0, t1): A's last 5 and B's first 5.
  CHECK(counts("SAT1", a[35].utime, b[15].utime) == Pairs{{"station-A", 5}, {"station-B", 5}});
  CHECK(counts("SAT2", kT0, kT0 + 1000 * kSecond) == Pairs{{"station-B", 7}});
  CHECK(counts("NOPE", kT0, kT0 + 1000 * kSecond).empty());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "window query: t0 <= t < t1, ascending time, only the asked spacecraft",
                          "[samples]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_sample_window_store();
  auto a = make_series("SAT-A", 500, 3 * kSecond);
  auto b = make_series("SAT-B", 500, 3 * kSecond);
  // Out-of-order arrival (recorder playback) is normal: insert shuffled, in several batches.
  std::vector<StoredSample> all = a;
  all.insert(all.end(), b.begin(), b.end());
  std::mt19937 rng(7);
  std::shuffle(all.begin(), all.end(), rng);
  for (size_t k = 0; k < all.size(); k += 128) {
    const size_t n = std::min<size_t>(128, all.size() - k);
    store->insert_batch(std::span(all).subspan(k, n));
  }
  const int64_t t0 = a[100].utime;
  const int64_t t1 = a[300].utime;
  std::vector<StoredSample> window;
  store->read_window("SAT-A", t0, t1, window);
  REQUIRE(window.size() == 200);  // a[100] included, a[300] excluded
  CHECK(window.front().utime == t0);
  CHECK(window.back().utime == a[299].utime);
  CHECK(std::is_sorted(window.begin(), window.end(),
                       [](const auto& x, const auto& y) { return x.utime < y.utime; }));
  for (const auto& s : window) CHECK(s.sat_id == "SAT-A");
  CHECK(store->count_in_window("SAT-A", t0, t1) == 200);
  CHECK(store->count_in_window("SAT-B", t0, t1) == 200);
  // Empty and reversed ranges.
  CHECK(store->count_in_window("SAT-A", t0, t0) == 0);
  store->read_window("SAT-A", t1, t0, window);
  CHECK(window.empty());
  // The refit window (t_ref - W, t_ref] maps to [t_ref - W + 1, t_ref + 1).
  const int64_t t_ref = a[300].utime;
  const int64_t w = a[300].utime - a[100].utime;
  CHECK(store->count_in_window("SAT-A", t_ref - w + 1, t_ref + 1) == 200);
  // By rank, in time order whatever the arrival order (the key of an early refit).
  CHECK(store->utime_at_rank("SAT-A", 0) == a.front().utime);
  CHECK(store->utime_at_rank("SAT-A", 299) == a[299].utime);
  CHECK(store->utime_at_rank("SAT-B", 499) == b.back().utime);
  CHECK_FALSE(store->utime_at_rank("SAT-A", 500).has_value());
  CHECK_FALSE(store->utime_at_rank("SAT-A", -1).has_value());
  CHECK_FALSE(store->utime_at_rank("SAT-C", 0).has_value());
  // The ends of a spacecraft's stored window, whatever the order of arrival.
  CHECK(store->oldest_utime("SAT-A") == a.front().utime);
  CHECK(store->newest_utime("SAT-A") == a.back().utime);
  CHECK_FALSE(store->oldest_utime("SAT-C").has_value());
  CHECK_FALSE(store->newest_utime("SAT-C").has_value());
}

TEMPLATE_TEST_CASE_METHOD(BackendTest, "a batch that fails stores nothing of itself", "[samples]",
                          SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_sample_window_store();
  auto batch = make_series("SAT1", 20, kSecond);
  batch[13].h_norm_nT = std::nan("");  // NOT NULL column: the insert fails mid-batch
  CHECK_THROWS_AS(store->insert_batch(batch), StorageError);
  CHECK(store->count("SAT1") == 0);
  batch[13].h_norm_nT = 50000.0;
  CHECK(store->insert_batch(batch).inserted == 20);
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "retention deletes exactly what is older than newest - window - margin",
                          "[samples]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto store = this->db->make_sample_window_store();
  const auto history = this->db->make_calibration_history();
  const int64_t step = 10 * kSecond;
  const auto a = make_series("SAT1", 3000, step);  // 30 000 s of data
  const auto b = make_series("SAT2", 100, step);
  store->insert_batch(a);
  store->insert_batch(b);
  CalibrationRecord r;
  r.sat_id = "SAT1";
  r.method = "ukf";
  r.utime = a.front().utime;  // a result about the oldest data: never deleted
  history->append(r);

  const int64_t window_utime = 6 * 3600 * kSecond / 3;  // 2 h
  const int64_t margin_utime = 1800 * kSecond;          // 0.5 h
  const int64_t cutoff = a.back().utime - window_utime - margin_utime;
  const auto expected_kept =
      std::count_if(a.begin(), a.end(), [&](const auto& s) { return s.utime >= cutoff; });
  REQUIRE(expected_kept > 0);
  REQUIRE(expected_kept < static_cast<long>(a.size()));
  const int chunk = 250;
  const RetentionStats stats = store->apply_retention("SAT1", window_utime, margin_utime, chunk);
  CHECK(stats.deleted == static_cast<int64_t>(a.size()) - expected_kept);
  CHECK(stats.transactions == stats.deleted / chunk + 1);
  CHECK(store->count("SAT1") == expected_kept);
  const auto kept = store->window("SAT1", std::numeric_limits<int64_t>::min(),
                                  std::numeric_limits<int64_t>::max());
  REQUIRE(!kept.empty());
  CHECK(kept.front().utime == cutoff);  // the sample exactly at the cutoff stays (10 s grid)
  CHECK(store->count("SAT2") == 100);   // other spacecraft untouched
  CHECK(history->latest("SAT1", "ukf").has_value());

  // Idempotent; an unknown spacecraft is a no-op.
  CHECK(store->apply_retention("SAT1", window_utime, margin_utime, chunk).deleted == 0);
  CHECK(store->apply_retention("NOPE", window_utime, margin_utime).deleted == 0);
  CHECK_THROWS_AS(store->delete_before("SAT1", cutoff, 0), StorageError);
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a reader sees only committed batches while a writer is mid-transaction",
                          "[samples]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  auto& writer_db = this->db;
  const auto writer = writer_db->make_sample_window_store();
  writer->insert_batch(make_series("SAT1", 100, kSecond));

  OpenOptions ro;
  ro.read_only = true;
  const auto reader_db = this->backend.open_again(ro);
  const auto reader = reader_db->make_sample_window_store();
  {
    Transaction open_batch(*writer_db);
    writer->insert_batch(make_series("SAT1", 100, kSecond, 100));  // nested: not yet committed
    CHECK(reader->count("SAT1") == 100);
    open_batch.commit();
  }
  CHECK(reader->count("SAT1") == 200);
}

TEMPLATE_TEST_CASE("writers of overlapping batches each store a sample once, whoever is first",
                   "[samples]", SqliteBackend, PostgresBackend) {
  // Two connections (two stations) deliver the same samples in opposite order: every sample is
  // stored once, and the copies each writer did not store are counted as its duplicates.
  TestType backend;
  const auto first_db = backend.open();
  if (!first_db) return;
  const auto second_db = backend.open_again();
  const auto first = first_db->make_sample_window_store();
  const auto second = second_db->make_sample_window_store();
  auto forward = make_series("SAT1", 600, kSecond);
  forward.insert(forward.end(), forward.begin() + 100, forward.begin() + 110);  // repeats
  std::vector<StoredSample> backward(forward.rbegin(), forward.rend());
  const InsertStats a = first->insert_batch(std::span(forward).first(300));
  const InsertStats b = second->insert_batch(backward);
  const InsertStats c = first->insert_batch(std::span(forward).subspan(300));
  CHECK(a.inserted + b.inserted + c.inserted == 600);
  CHECK(a.duplicates + b.duplicates + c.duplicates == 2 * 610 - 600);
  CHECK(first->count("SAT1") == 600);
  CHECK(second->count_in_window("SAT1", kT0, kT0 + 600 * kSecond) == 600);
}

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "concurrent writers of shuffled overlapping batches neither deadlock nor "
                          "store a sample twice",
                          "[samples]", SqliteBackend, PostgresBackend) {
  // Three stations deliver the same samples, each in its own shuffled order: each batch is
  // written in the one global key order, so the writers wait for each other instead of
  // deadlocking (PostgreSQL), and the counts add up exactly.
  if (!this->db) return;
  const auto all = make_series("SAT1", 3000, kSecond);
  constexpr int kWriters = 3;
  std::vector<InsertStats> stats(kWriters);
  std::vector<std::unique_ptr<Connection>> connections;
  for (int w = 0; w < kWriters; ++w) connections.push_back(this->backend.open_again());
  const auto errors = magcal::test::run_at_once(kWriters, [&](int w) {
    const auto store = connections[static_cast<size_t>(w)]->make_sample_window_store();
    const std::string station = "station-" + std::to_string(w);
    std::vector<StoredSample> mine = all;
    std::mt19937 rng(static_cast<unsigned>(100 + w));
    std::shuffle(mine.begin(), mine.end(), rng);
    for (size_t k = 0; k < mine.size(); k += 200) {
      const InsertStats s = store->insert_batch(std::span(mine).subspan(k, 200), nullptr, station);
      stats[static_cast<size_t>(w)].inserted += s.inserted;
      stats[static_cast<size_t>(w)].duplicates += s.duplicates;
    }
  });
  int64_t inserted = 0, duplicates = 0;
  for (int w = 0; w < kWriters; ++w) {
    CHECK(errors[static_cast<size_t>(w)] == "");
    inserted += stats[static_cast<size_t>(w)].inserted;
    duplicates += stats[static_cast<size_t>(w)].duplicates;
  }
  CHECK(inserted == 3000);
  CHECK(duplicates == (kWriters - 1) * 3000);
  const auto store = this->db->make_sample_window_store();
  CHECK(store->count("SAT1") == 3000);
  // Each sample is recorded under the station whose insert stored it.
  const auto by_station = store->count_by_station("SAT1", kT0, kT0 + 3000 * kSecond);
  REQUIRE(by_station.size() <= static_cast<size_t>(kWriters));
  for (const auto& c : by_station) {
    const int w = c.station.back() - '0';
    REQUIRE((w >= 0 && w < kWriters));
    CHECK(c.samples == stats[static_cast<size_t>(w)].inserted);
  }
}

// SQLite only: a file's crash safety (PostgreSQL's is the server's own).
TEST_CASE("a writer killed mid-stream loses no committed batch and leaves a sound file") {
  TempDir dir;
  const std::string path = dir.file("crash.db");
  { Database create(path); }
  constexpr int kBatch = 200;
  int fds[2];
  REQUIRE(::pipe(fds) == 0);
  const pid_t child = ::fork();
  REQUIRE(child >= 0);
  if (child == 0) {
    // Child: write batches forever, report each committed batch number on the pipe.
    ::close(fds[0]);
    try {
      Database db(path);
      SqliteSampleWindowStore store(db);
      for (int64_t n = 0;; ++n) {
        store.insert_batch(make_series("SAT1", kBatch, kSecond, n * kBatch));
        if (::write(fds[1], &n, sizeof n) != sizeof n) ::_exit(3);
      }
    } catch (...) {
      ::_exit(2);
    }
  }
  ::close(fds[1]);
  int64_t committed = -1;
  int64_t n = 0;
  while (committed < 25 && ::read(fds[0], &n, sizeof n) == sizeof n) committed = n;
  REQUIRE(::kill(child, SIGKILL) == 0);  // almost certainly inside the next batch
  int status = 0;
  ::waitpid(child, &status, 0);
  ::close(fds[0]);
  REQUIRE(WIFSIGNALED(status));
  REQUIRE(committed >= 25);

  Database db(path);
  CHECK(db.integrity_check() == "ok");
  SqliteSampleWindowStore store(db);
  const int64_t stored = store.count("SAT1");
  CHECK(stored >= (committed + 1) * kBatch);  // every acknowledged batch is there...
  CHECK(stored % kBatch == 0);                // ...and no half batch
  const auto all = store.window("SAT1", kT0, kT0 + stored * kSecond);
  CHECK(static_cast<int64_t>(all.size()) == stored);  // contiguous from the first sample
}
