// The receive-and-store part of the daemon's worker on its own, without any owner: every valid
// sample stored once with the station id, repeats counted as duplicates, the owner's half of
// each spacecraft untouched, and retention only behind an owner's filter, with no transaction
// while nothing is old enough to delete.
#include <catch2/catch.hpp>

#include <limits>
#include <span>
#include <string>
#include <vector>

#include "service/daemon/intake/sample_intake.hpp"
#include "storage/calibration_history.hpp"
#include "storage/filter_state_store.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"

using namespace magcal;
using namespace magcal::test;

namespace {

constexpr int64_t kT0 = 1704067200000000;  // 2024-01-01T00:00:00Z
constexpr int64_t kStep = kLogStep_utime;
constexpr int64_t kHour = 3600LL * 1000000;

std::vector<mag_sample_t> samples(int n, const std::string& sat) {
  std::vector<mag_sample_t> out;
  for (int k = 0; k < n; ++k) out.push_back(turning_field_sample(sat, kT0, k));
  return out;
}

// The owner's side of a commit, recorded: what an intake hands to it, and that it is asked to
// write only in the transaction of a commit's last chunk.
struct RecordingParticipant final : CommitParticipant {
  int64_t rows_committed = 0;
  int writes = 0;
  bool has_writes() const override { return false; }
  void write() override { ++writes; }
  void written() override {}
  void samples_committed(std::span<const storage::StoredSample> rows) override {
    rows_committed += static_cast<int64_t>(rows.size());
  }
};

// The SQLite store, counting the delete statements retention runs (one per transaction).
class CountingStore final : public storage::SampleWindowStore {
 public:
  explicit CountingStore(storage::Connection& db)
      : SampleWindowStore(db), inner_(db.make_sample_window_store()) {}
  int delete_chunks = 0;

  storage::InsertStats insert_batch(std::span<const storage::StoredSample> s,
                                    std::vector<size_t>* dup, std::string_view station) override {
    return inner_->insert_batch(s, dup, station);
  }
  void read_window(std::string_view sat, int64_t t0, int64_t t1,
                   std::vector<storage::StoredSample>& out) override {
    inner_->read_window(sat, t0, t1, out);
  }
  int64_t count_in_window(std::string_view sat, int64_t t0, int64_t t1) override {
    return inner_->count_in_window(sat, t0, t1);
  }
  std::vector<storage::StationCount> count_by_station(std::string_view sat, int64_t t0,
                                                      int64_t t1) override {
    return inner_->count_by_station(sat, t0, t1);
  }
  std::optional<int64_t> newest_utime(std::string_view sat) override {
    return inner_->newest_utime(sat);
  }
  std::optional<int64_t> oldest_utime(std::string_view sat) override {
    return inner_->oldest_utime(sat);
  }
  int64_t count(std::string_view sat) override { return inner_->count(sat); }
  std::optional<int64_t> utime_at_rank(std::string_view sat, int64_t rank) override {
    return inner_->utime_at_rank(sat, rank);
  }
  std::vector<std::string> spacecraft() override { return inner_->spacecraft(); }

 protected:
  int64_t delete_chunk(std::string_view sat, int64_t cutoff, int chunk_rows) override {
    ++delete_chunks;
    // The inner store's own delete_chunk is not reachable: its public delete_before, a savepoint
    // inside the transaction the base class opened.
    return inner_->delete_before(sat, cutoff, chunk_rows).deleted;
  }

 private:
  std::unique_ptr<storage::SampleWindowStore> inner_;
};

DaemonConfig config_for(const std::string& db, const std::string& station) {
  DaemonConfig c;
  c.storage.db_path = db;
  c.station.id = station;
  c.storage.commit_every_samples = 100;
  return c;
}

struct Intake {
  DaemonConfig config;
  DaemonCounters counters;
  std::unique_ptr<storage::Connection> db;
  CountingStore store;
  SpacecraftFleet fleet;
  SampleIntake intake;
  RecordingParticipant owner;

  explicit Intake(const std::string& path)
      : config(config_for(path, "A")),
        db(storage::open_database(path)),
        store(*db),
        fleet(config.ukf.filter, &counters),
        intake(config, counters, std::make_unique<ReferenceField>(), *db, store, fleet) {}

  void feed(const std::vector<mag_sample_t>& s, size_t from, size_t to) {
    for (size_t i = from; i < to; ++i) {
      intake.begin_frame();
      intake.ingest(s[i], "", kT0 + 400LL * 86400 * 1000000);
      if (intake.batch_full()) REQUIRE(intake.try_commit(owner));
    }
    REQUIRE(intake.try_commit(owner));
  }
};

}  // namespace

TEST_CASE("the intake alone stores each sample once and counts repeats as duplicates",
          "[sample_intake]") {
  TempDir tmp("magcal_intake_test_once");
  Intake in(tmp.file("m.db"));
  const auto a = samples(300, "SAT-A");
  in.feed(a, 0, a.size());
  in.feed(a, 100, 200);  // a repeated pass (another station's copy, a recorder dump)
  CHECK(in.counters.stored == 300);
  CHECK(in.counters.rejected_count(RejectReason::kDuplicate) == 100);
  CHECK(in.counters.rejected_total() == 100);
  CHECK(in.counters.missing_by_seq == 0);
  CHECK(in.store.count("SAT-A") == 300);
  const auto by_station = in.store.count_by_station("SAT-A", kT0, kT0 + 300 * kStep);
  REQUIRE(by_station.size() == 1);
  CHECK(by_station[0].station == "A");
  CHECK(in.owner.rows_committed == 300);
  CHECK(in.owner.writes >= 1);  // asked, once per commit, in its last transaction
  // Only the receive half of the spacecraft moved; nothing of an owner's was made.
  const SpacecraftTracker& t = *in.fleet.find("SAT-A");
  CHECK(t.newest_utime == a.back().utime);
  CHECK_FALSE(t.owned);
  CHECK_FALSE(t.ukf.state().has_time);
  CHECK(in.counters.ukf_updates == 0);
  CHECK(in.db->make_calibration_history()->spacecraft().empty());
  CHECK_FALSE(in.db->make_filter_state_store()->load("SAT-A", "ukf"));
  CHECK(in.intake.take_new_spacecraft() == std::vector<std::string>{"SAT-A"});
  CHECK(in.intake.take_new_spacecraft().empty());
}

TEST_CASE(
    "retention deletes only behind an owner's filter, and runs no transaction while the "
    "window fills",
    "[sample_intake][retention]") {
  TempDir tmp("magcal_intake_test_retention");
  Intake in(tmp.file("m.db"));
  const int64_t per_hour = kHour / kStep;
  const auto a = samples(static_cast<int>(20 * per_hour), "SAT-A");
  const int64_t window = in.config.window_utime();
  const auto margin = static_cast<int64_t>(in.config.storage.retention_margin_hours * 3.6e9);
  const auto run = [&] {
    in.intake.retention_at_next_commit();
    in.intake.run_retention_if_due(true);
  };
  // 6 h stored: not owned here, nothing may go.
  in.feed(a, 0, static_cast<size_t>(6 * per_hour));
  run();
  CHECK(in.store.delete_chunks == 0);
  // Owned, with a filter at the newest sample: the window has not filled, nothing to delete,
  // and no transaction for it.
  in.intake.allow_retention("SAT-A", a[static_cast<size_t>(6 * per_hour) - 1].utime);
  run();
  CHECK(in.store.delete_chunks == 0);
  // 20 h stored, the filter at 18 h: everything older than 18 h - window - margin goes.
  in.feed(a, static_cast<size_t>(6 * per_hour), a.size());
  const int64_t filtered = a[static_cast<size_t>(18 * per_hour)].utime;
  in.intake.allow_retention("SAT-A", filtered);
  run();
  CHECK(in.store.delete_chunks >= 1);
  const int64_t cutoff = filtered - window - margin;
  CHECK(in.store.oldest_utime("SAT-A").value() >= cutoff);
  CHECK(in.store.count_in_window("SAT-A", std::numeric_limits<int64_t>::min() / 2, cutoff) == 0);
  CHECK(in.store.newest_utime("SAT-A").value() == a.back().utime);
  // The same edge again: nothing older is left, so no transaction.
  const int chunks = in.store.delete_chunks;
  in.intake.allow_retention("SAT-A", filtered);
  run();
  CHECK(in.store.delete_chunks == chunks);
  // Given up (another daemon owns it now) before the pass: nothing is deleted here.
  in.intake.allow_retention("SAT-A", a.back().utime);
  in.intake.allow_retention("SAT-A", SpacecraftTracker::kNoTime);
  run();
  CHECK(in.store.delete_chunks == chunks);
}

TEST_CASE("a restore after samples came (the database reached late) keeps the newer time base",
          "[sample_intake]") {
  TempDir tmp("magcal_intake_test_late_restore");
  const auto a = samples(300, "SAT-A");
  const auto c = samples(300, "SAT-C");
  const auto d = samples(300, "SAT-D");
  {
    Intake earlier(tmp.file("m.db"));  // an earlier run stored the first 200 of each
    earlier.feed(a, 0, 200);
    earlier.feed(c, 0, 200);
    earlier.feed(d, 0, 200);
  }
  Intake in(tmp.file("m.db"));
  auto receive = [&](const std::vector<mag_sample_t>& s, size_t from, size_t to) {
    for (size_t i = from; i < to; ++i) {
      in.intake.begin_frame();
      in.intake.ingest(s[i], "", kT0 + 400LL * 86400 * 1000000);
    }
  };
  // Before the restore: SAT-A newer than its stored samples, SAT-C older, SAT-D two samples,
  // too few to corroborate a first time base (held).
  receive(a, 200, 250);
  receive(c, 100, 110);
  receive(d, 200, 202);
  CHECK(in.intake.held_samples() == 2);
  in.intake.restore(in.owner);
  CHECK(in.fleet.find("SAT-A")->newest_utime == a[249].utime);
  CHECK(in.fleet.find("SAT-C")->newest_utime == c[199].utime);
  CHECK(in.fleet.find("SAT-D")->newest_utime == d[201].utime);
  CHECK(in.intake.held_samples() == 0);  // on the stored time base: taken
  // The stored samples are known as such: a repeat is a duplicate, the next one is new.
  receive(c, 150, 151);
  receive(c, 200, 201);
  CHECK(in.counters.rejected_count(RejectReason::kDuplicate) == 1);
  REQUIRE(in.intake.try_commit(in.owner));
  CHECK(in.store.count("SAT-A") == 250);
  CHECK(in.store.count("SAT-C") == 201);
  CHECK(in.store.count("SAT-D") == 202);
  // SAT-C's ten older samples were stored before: duplicates at the insert.
  CHECK(in.counters.rejected_count(RejectReason::kDuplicate) == 11);
}
