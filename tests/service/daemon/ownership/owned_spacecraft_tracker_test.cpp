// The owner-tracking part of the daemon's worker, through the worker that sequences it with the
// intake: without the spacecraft's lease it reads nothing back and writes nothing (the intake
// still stores every sample); with it, its UKF takes the union of all stations' stored samples;
// a refit that another station was still running when the lease came here re-anchors the new
// owner once it ends.
#include <catch2/catch.hpp>

#include <algorithm>
#include <chrono>
#include <string>
#include <vector>

#include "service/daemon/ingest_worker.hpp"
#include "service/io/calibration_record.hpp"
#include "storage/calibration_history.hpp"
#include "storage/filter_state_store.hpp"
#include "storage/lease_store.hpp"
#include "storage/refit_job_log.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"

using namespace magcal;
using namespace magcal::test;

namespace {

constexpr int64_t kT0 = 1704067200000000;  // 2024-01-01T00:00:00Z
constexpr int64_t kHour_utime = 3600LL * 1000000;

int64_t wall_now_utime() {
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

DaemonConfig station_config(const std::string& db, const std::string& station) {
  DaemonConfig c;
  c.storage.db_path = db;
  c.station.id = station;
  c.fleet.reorder_delay_s = 0.0;
  return c;
}

// Station B, live for an hour and holding SAT-1's lease, seen through its own connection.
struct StationB {
  std::unique_ptr<storage::Connection> db;
  std::unique_ptr<storage::LeaseStore> leases;
  int64_t epoch = 0;
  explicit StationB(const std::string& path)
      : db(storage::open_database(path)), leases(db->make_lease_store()) {
    const int64_t now = wall_now_utime();
    leases->heartbeat("B", "b-instance", {}, now, kHour_utime);
    leases->ensure("SAT-1");
    epoch = leases->try_acquire("SAT-1", "B", now, kHour_utime).value().epoch;
  }
  // B stores samples it received itself (the other half of the union).
  void store(const std::vector<mag_sample_t>& s) {
    std::vector<storage::StoredSample> rows;
    ReferenceField field;
    for (const auto& x : s) {
      fill_stored_sample(x, x.sat_id, *to_reference_sample(x, field), 0, rows.emplace_back());
    }
    db->make_sample_window_store()->insert_batch(rows, nullptr, "B");
  }
  void hand_over() { leases->release("SAT-1", "B", epoch, wall_now_utime()); }
};

// Station B (holding SAT-1's lease) and station A's worker, restored, on one database.
struct TwoStations {
  StationB b;
  DaemonCounters counters;
  IngestWorker a;
  explicit TwoStations(const std::string& db)
      : b(db), a(station_config(db, "A"), counters, std::make_unique<ReferenceField>(), {}) {
    a.restore();
  }
};

void feed(IngestWorker& w, const std::vector<mag_sample_t>& s, size_t per_frame = kLogBatch) {
  for (size_t i = 0; i < s.size(); i += per_frame) {
    IngestItem item;
    item.from_batch = true;
    item.batch_sat_id = s[i].sat_id;
    item.samples.assign(s.begin() + static_cast<long>(i),
                        s.begin() + static_cast<long>(std::min(s.size(), i + per_frame)));
    item.receive_utime = wall_now_utime();
    w.process(item);
  }
  w.commit();
}

std::vector<mag_sample_t> samples(int from, int to) {
  std::vector<mag_sample_t> out;
  for (int k = from; k < to; ++k) out.push_back(turning_field_sample("SAT-1", kT0, k));
  return out;
}

}  // namespace

TEST_CASE(
    "without the lease the worker stores, and its tracker reads and writes nothing, with "
    "it the UKF takes the union",
    "[owned_spacecraft_tracker]") {
  TempDir tmp("magcal_owner_test_union");
  TwoStations fleet(tmp.file("m.db"));
  auto& [b, counters, a] = fleet;
  feed(a, samples(0, 300));
  a.track_all_now();
  a.flush();
  CHECK_FALSE(a.owns("SAT-1"));
  CHECK(counters.stored == 300);
  CHECK(counters.ukf_updates == 0);
  CHECK(counters.snapshots == 0);
  CHECK_FALSE(a.fleet().find("SAT-1")->ukf.state().has_time);
  {
    auto db = storage::open_database(tmp.file("m.db"));
    CHECK(db->make_calibration_history()->spacecraft().empty());
    CHECK_FALSE(db->make_filter_state_store()->load("SAT-1", "ukf"));
  }
  // B received the next 200 and hands SAT-1 over: A's filter reads all 500 back.
  b.store(samples(300, 500));
  b.hand_over();
  a.maintain_leases();
  REQUIRE(a.owns("SAT-1"));
  a.track_all_now();
  CHECK(counters.ukf_updates == 500);
  CHECK(a.fleet().find("SAT-1")->filtered_utime == samples(499, 500)[0].utime);
  CHECK(counters.stored == 300);  // A stored only what it received
}

TEST_CASE("a refit still running elsewhere at the takeover re-anchors the new owner when it ends",
          "[owned_spacecraft_tracker][refit]") {
  TempDir tmp("magcal_owner_test_refit-elsewhere");
  TwoStations fleet(tmp.file("m.db"));
  auto& [b, counters, a] = fleet;
  const auto s = samples(0, 600);
  feed(a, s);
  // B (the owner) started the refit of the window ending at sample 499, then handed over.
  auto jobs = b.db->make_refit_job_log();
  const int64_t t_ref = s[499].utime;
  const int64_t job = jobs->claim("SAT-1", "scheduled", t_ref, wall_now_utime(), "B").value();
  b.hand_over();
  a.maintain_leases();
  REQUIRE(a.owns("SAT-1"));
  a.track_all_now();
  a.flush();
  const SpacecraftTracker& t = *a.fleet().find("SAT-1");
  CHECK(t.anchor_calibration_id == 0);
  // B's refit ends, accepted, after the takeover: A is told by nobody but the job log.
  CalibrationResult refit;
  refit.method = "twostep";
  refit.utime = refit.window_end_utime = t_ref;
  refit.window_start_utime = s[0].utime;
  refit.n_samples = 500;
  Vector9d p;
  p << 100.0, 200.0, 300.0, 0, 0, 0, 0, 0, 0;
  refit.parameters = CalibrationParameters::from_packed(p);
  Vector9d variance;
  variance << 4.0, 4.0, 4.0, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6, 1e-6;
  refit.covariance = variance.asDiagonal();
  refit.residual_rms_nT = 1.0;
  refit.status = CalibrationStatus::kOk;
  refit.accepted = true;
  const int64_t id = b.db->make_calibration_history()->append(record_from_result("SAT-1", refit));
  jobs->finish(job, storage::job_outcome::kOk, wall_now_utime(), "", id);
  a.maintain_leases();  // the next lease round looks again
  CHECK(t.anchor_calibration_id == id);
  CHECK(t.ukf.state().initialized);
  a.flush();  // the re-anchored state is stored with the next commit
  auto db = storage::open_database(tmp.file("m.db"));
  const auto stored = db->make_filter_state_store()->load("SAT-1", "ukf");
  REQUIRE(stored);
  CHECK(stored->anchor_calibration_id == id);
}

TEST_CASE("ownership follows reception: each station owns what it receives, also after a failover",
          "[owned_spacecraft_tracker][fleet]") {
  TempDir tmp("magcal_owner_test_reception");
  const std::string db = tmp.file("m.db");
  constexpr int kSats = 10;  // A receives the even ones, B the odd ones
  constexpr double kLease_s = 2.0;
  auto config = [&](const std::string& station) {
    DaemonConfig c = station_config(db, station);
    c.fleet.lease_s = kLease_s;
    return c;
  };
  int next_sample = 0;
  int newest_sample[2] = {-1, -1};  // by parity
  // 20 new samples of each of the station's spacecraft, received now (frames of 5: a new
  // spacecraft's first frame alone does not set its time).
  auto receive = [&](IngestWorker& w, int parity) {
    std::vector<mag_sample_t> s;
    for (int i = 0; i < 20; ++i) {
      for (int k = parity; k < kSats; k += 2) {
        s.push_back(turning_field_sample("SAT-" + std::to_string(k), kT0, next_sample + i));
      }
    }
    std::stable_sort(s.begin(), s.end(),
                     [](const auto& x, const auto& y) { return x.sat_id < y.sat_id; });
    feed(w, s, 5);
    next_sample += 20;
    newest_sample[parity] = next_sample - 1;
  };
  auto owners = [&](IngestWorker& a, IngestWorker* b) {
    std::string text;
    for (int k = 0; k < kSats; ++k) {
      const std::string sat = "SAT-" + std::to_string(k);
      text += a.owns(sat) ? 'A' : b != nullptr && b->owns(sat) ? 'B' : '-';
    }
    return text;
  };
  DaemonCounters counters_a, counters_b;
  IngestWorker a(config("A"), counters_a, std::make_unique<ReferenceField>(), {});
  auto b = std::make_unique<IngestWorker>(
      config("B"), counters_b, std::make_unique<ReferenceField>(), IngestWorker::Hooks{});
  b->restore();
  receive(*b, 1);
  a.restore();
  receive(a, 0);
  a.maintain_leases();
  b->maintain_leases();
  CHECK(owners(a, b.get()) == "ABABABABAB");

  // B dies (no clean stop): once its leases and its heartbeat ran out, A takes its spacecraft
  // over at its next lease round, though it does not receive them. (Lease times are the
  // callers' wall clock: the test waits until the store says they have expired.)
  b.reset();
  {
    const auto watch = storage::open_database(db);
    const auto leases = watch->make_lease_store();
    REQUIRE(wait_until(
        [&] {
          const int64_t now = wall_now_utime();
          const auto live = leases->live_stations(now);
          if (std::find(live.begin(), live.end(), "B") != live.end()) return false;
          const auto all = leases->list();
          return std::none_of(all.begin(), all.end(), [&](const storage::Lease& l) {
            return l.owner == "B" && l.held_at(now);
          });
        },
        10 * kLease_s));
  }
  a.maintain_leases();
  CHECK(owners(a, nullptr) == "AAAAAAAAAA");

  // B comes back and receives its spacecraft again: A, over its share, hands over those it does
  // not receive, and B takes them.
  DaemonCounters counters_b2;
  b = std::make_unique<IngestWorker>(config("B"), counters_b2, std::make_unique<ReferenceField>(),
                                     IngestWorker::Hooks{});
  b->restore();
  receive(*b, 1);
  receive(a, 0);
  a.maintain_leases();
  b->maintain_leases();
  CHECK(owners(a, b.get()) == "ABABABABAB");
  // Each owner's filter has taken its spacecraft's union to the newest sample.
  a.track_all_now();
  b->track_all_now();
  for (int k = 0; k < kSats; ++k) {
    const std::string sat = "SAT-" + std::to_string(k);
    IngestWorker& owner = k % 2 == 0 ? a : *b;
    INFO(sat);
    CHECK(owner.fleet().find(sat)->filtered_utime ==
          turning_field_sample(sat, kT0, newest_sample[k % 2]).utime);
  }

  // B's input ends (its replay ended, or it stops), then A leaves the fleet: B, draining, takes
  // none of A's spacecraft, though they are free and no other station is live; it keeps its own,
  // and a spacecraft it received whose lease is free it still takes (what it drains).
  // (A fast replay's worker runs its lease round after the input has ended: a spacecraft new
  // at B, received before the end, is B's then.)
  std::vector<mag_sample_t> newcomer;
  for (int i = 0; i < 20; ++i) newcomer.push_back(turning_field_sample("SAT-NEW", kT0, i));
  feed(*b, newcomer, 5);
  b->input_ended(true);
  a.leave_fleet();
  b->maintain_leases();
  CHECK(owners(a, b.get()) == "-B-B-B-B-B");
  CHECK(b->owns("SAT-NEW"));
}

TEST_CASE("a replay's end takes the free leases of what it received before its filters drain",
          "[owned_spacecraft_tracker][fleet]") {
  // Two stations on the default lease time (a round every 10 s, longer than this test): B
  // receives SAT-0 and SAT-1 while only their two leases exist, so its share (one of two) lets
  // it take one; A then receives SAT-2 and SAT-3, which raises B's share to two, but B's next
  // round would come only after its replay ended. At the end, B takes its other spacecraft
  // and filters it to its newest sample (a fast replay's daemon stops sooner than its round).
  TempDir tmp("magcal_owner_test_replay_end");
  const std::string db = tmp.file("m.db");
  DaemonCounters counters_a, counters_b;
  IngestWorker a(station_config(db, "A"), counters_a, std::make_unique<ReferenceField>(), {});
  IngestWorker b(station_config(db, "B"), counters_b, std::make_unique<ReferenceField>(), {});
  a.restore();
  b.restore();
  constexpr int kSamples = 40;
  auto receive = [&](IngestWorker& w, std::vector<std::string> sats) {
    std::vector<mag_sample_t> s;
    for (const auto& sat : sats) {
      for (int k = 0; k < kSamples; ++k) s.push_back(turning_field_sample(sat, kT0, k));
    }
    feed(w, s, 5);
  };
  receive(b, {"SAT-0", "SAT-1"});
  REQUIRE(b.owns("SAT-0") != b.owns("SAT-1"));
  receive(a, {"SAT-2", "SAT-3"});
  CHECK(a.owns("SAT-2"));
  CHECK(a.owns("SAT-3"));
  CHECK(!a.owns("SAT-0"));  // left to its receiver
  CHECK(!a.owns("SAT-1"));

  b.input_ended(true);
  b.track_all_now();
  for (const std::string sat : {"SAT-0", "SAT-1"}) {
    INFO(sat);
    CHECK(b.owns(sat));
    CHECK(b.fleet().find(sat)->filtered_utime ==
          turning_field_sample(sat, kT0, kSamples - 1).utime);
  }
}
