// The worker's time plausibility: one frame, or a whole shifted packet, cannot move a
// spacecraft's time; genuine gaps and recorder dumps are accepted once corroborated.
#include <catch2/catch.hpp>

#include "tests/service/daemon/ingest_worker_fixture.hpp"

using namespace magcal;
using namespace magcal::worker_test;

namespace {

constexpr int64_t kHour = 3600LL * 1000000;

// One frame per sample, as a live mag_sample_t feed; then the shutdown step.
void feed_frames(IngestWorker& w, const std::vector<mag_sample_t>& frames) {
  for (const auto& s : frames) w.process(single(s));
  w.settle_held();
  w.commit();
}

}  // namespace

TEST_CASE("one rogue time tag is rejected and every valid sample kept", "[ingest_worker][time]") {
  const auto valid = simulate(400, 11);
  struct Case {
    const char* name;
    int64_t utime;
    RejectReason expect;
  };
  const int64_t mid = valid[200].utime;
  const Case cases[] = {
      {"20 h ahead", mid + 20 * kHour, RejectReason::kTimeJump},
      {"2 h ahead", mid + 2 * kHour, RejectReason::kTimeJump},
      {"20 h behind", mid - 20 * kHour, RejectReason::kOlderThanWindow},
      {"utime 0", 0, RejectReason::kTimeOutOfRange},
      {"int64 min", std::numeric_limits<int64_t>::min(), RejectReason::kTimeOutOfRange},
      {"int64 max", std::numeric_limits<int64_t>::max(), RejectReason::kTimeOutOfRange},
      {"past the wall clock", kT0 + 400LL * 86400 * 1000000, RejectReason::kFutureTime},
  };
  for (const auto& c : cases) {
    for (const size_t at : {size_t{0}, size_t{1}, size_t{200}, valid.size()}) {
      DYNAMIC_SECTION(c.name << " at frame " << at) {
        TempDb tmp("rogue");
        DaemonCounters counters;
        auto w = make_worker(test_config(tmp.path()), counters);
        auto frames = valid;
        auto rogue = valid[std::min(at, valid.size() - 1)];
        rogue.utime = c.utime;
        frames.insert(frames.begin() + static_cast<long>(at), rogue);
        feed_frames(*w, frames);
        const auto expect = at == valid.size() && c.expect == RejectReason::kTimeJump
                                ? RejectReason::kJumpUnconfirmed  // last: nothing followed
                                : c.expect;
        CHECK(counters.stored == static_cast<int64_t>(valid.size()));
        CHECK(counters.rejected_count(expect) == 1);
        CHECK(counters.rejected_total() == 1);
        CHECK(stored_rows(tmp.path()) == static_cast<int64_t>(valid.size()));
        CHECK(w->fleet().find("SAT-1")->newest_utime == valid.back().utime);
        CHECK(w->data_clock_utime() == valid.back().utime);
        CHECK(w->held_samples() == 0);
      }
    }
  }
}

TEST_CASE("a genuine gap is accepted once later samples corroborate it", "[ingest_worker][time]") {
  auto frames = simulate(300, 12);
  for (size_t k = 150; k < frames.size(); ++k) frames[k].utime += 3 * kHour;  // 3 h gap
  TempDb tmp("gap");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  for (size_t k = 0; k < 152; ++k) w->process(single(frames[k]));
  // The first two after the gap are held: not stored, not in the filter, not the time base.
  CHECK(w->held_samples() == 2);
  CHECK(w->fleet().find("SAT-1")->newest_utime == frames[149].utime);
  CHECK(w->data_clock_utime() == frames[149].utime);
  for (size_t k = 152; k < frames.size(); ++k) w->process(single(frames[k]));
  w->settle_held();
  w->commit();
  CHECK(counters.stored == 300);
  CHECK(counters.rejected_total() == 0);
  CHECK(w->fleet().find("SAT-1")->newest_utime == frames.back().utime);
  // Stored in order, each once.
  storage::Database db(tmp.path());
  storage::SqliteSampleWindowStore store(db);
  std::vector<storage::StoredSample> rows;
  store.read_window("SAT-1", frames.front().utime, frames.back().utime + 1, rows);
  REQUIRE(rows.size() == 300);
  for (size_t k = 0; k < rows.size(); ++k) CHECK(rows[k].utime == frames[k].utime);
}

TEST_CASE("a recorder dump of older in-window samples is accepted", "[ingest_worker][time]") {
  const auto s = simulate(600, 13);
  TempDb tmp("dump");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  std::vector<mag_sample_t> frames(s.begin() + 300, s.end());  // live first
  frames.insert(frames.end(), s.begin(), s.begin() + 300);     // then the recorder's dump
  feed_frames(*w, frames);
  CHECK(counters.stored == 600);
  CHECK(counters.rejected_total() == 0);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s.back().utime);
}

TEST_CASE("the first samples of a spacecraft need corroboration too", "[ingest_worker][time]") {
  const auto valid = simulate(100, 14);
  SECTION("a rogue first frame does not set the time base") {
    for (const int64_t offset : {20 * kHour, -20 * kHour, 400 * 24 * kHour}) {
      TempDb tmp("first");
      DaemonCounters counters;
      auto w = make_worker(test_config(tmp.path()), counters);
      auto frames = valid;
      auto rogue = valid[0];
      rogue.utime += offset;
      frames.insert(frames.begin(), rogue);
      feed_frames(*w, frames);
      INFO("offset " << offset / kHour << " h");
      CHECK(counters.stored == 100);
      CHECK(counters.rejected_total() == 1);
      CHECK(w->fleet().find("SAT-1")->newest_utime == valid.back().utime);
    }
  }
  SECTION("one batch frame cannot set it alone; the next frame confirms it") {
    TempDb tmp("batch");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    w->process(batch(valid, 0, 10));
    CHECK(w->held_samples() == 10);
    CHECK(counters.stored == 0);
    w->process(single(valid[10]));
    CHECK(w->held_samples() == 0);
    w->commit();
    CHECK(counters.stored == 11);
  }
  SECTION("a spacecraft that only ever sent one frame: stored at shutdown") {
    TempDb tmp("lonely");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    w->process(batch(valid, 0, 5));
    CHECK(w->held_samples() == 5);
    w->settle_held();
    w->commit();
    CHECK(counters.stored == 5);
    CHECK(counters.rejected_total() == 0);
    CHECK(stored_rows(tmp.path()) == 5);
    CHECK(w->fleet().find("SAT-1")->newest_utime == valid[4].utime);
  }
  SECTION("too few single frames to corroborate: stored at shutdown") {
    TempDb tmp("few");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    for (size_t k = 0; k < static_cast<size_t>(SpacecraftTracker::kCorroborating); ++k) {
      w->process(single(valid[k]));
    }
    CHECK(w->held_samples() == SpacecraftTracker::kCorroborating);
    w->settle_held();
    w->commit();
    CHECK(counters.stored == SpacecraftTracker::kCorroborating);
    CHECK(counters.rejected_total() == 0);
  }
  SECTION("held first samples are stored after kFirstHoldMax_s, without a shutdown") {
    TempDb tmp("bounded");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    w->process(batch(valid, 0, 3));
    const auto now = std::chrono::steady_clock::now();
    w->release_first_holds(now);  // not yet
    CHECK(w->held_samples() == 3);
    w->release_first_holds(
        now + std::chrono::duration_cast<std::chrono::nanoseconds>(
                  std::chrono::duration<double>(SpacecraftTracker::kFirstHoldMax_s + 0.1)));
    CHECK(w->held_samples() == 0);
    w->commit();
    CHECK(counters.stored == 3);
    // Later samples go on from that base as usual.
    for (size_t k = 3; k < valid.size(); ++k) w->process(single(valid[k]));
    w->settle_held();
    w->commit();
    CHECK(counters.stored == static_cast<int64_t>(valid.size()));
    CHECK(counters.rejected_total() == 0);
  }
  SECTION("at shutdown a lone rogue among uncorroborated first samples is outvoted") {
    for (const int64_t offset : {20 * kHour, -20 * kHour}) {
      TempDb tmp("outvoted");
      DaemonCounters counters;
      auto w = make_worker(test_config(tmp.path()), counters);
      auto rogue = valid[0];
      rogue.utime += offset;
      w->process(single(rogue));
      w->process(single(valid[0]));
      w->process(single(valid[1]));
      w->settle_held();
      w->commit();
      INFO("offset " << offset / kHour << " h");
      CHECK(counters.stored == 2);
      CHECK(counters.rejected_total() == 1);
      CHECK(counters.rejected_count(offset > 0 ? RejectReason::kJumpUnconfirmed
                                               : RejectReason::kOlderThanWindow) == 1);
      CHECK(w->fleet().find("SAT-1")->newest_utime == valid[1].utime);
    }
  }
}

TEST_CASE("a whole downlink packet with a shifted time base cannot move the time",
          "[ingest_worker][time]") {
  // One mag_batch_t of 200 samples, all consistently 20 h ahead (a corrupted packet time base):
  // one frame, however many samples, never corroborates itself.
  const auto s = simulate(1000, 17);
  TempDb tmp("packet");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  feed(*w, s, 0, 400);
  auto shifted = batch(s, 400, 600);
  for (auto& x : shifted.samples) x.utime += 20 * kHour;
  w->process(shifted);
  CHECK(w->held_samples() == 200);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s[399].utime);
  for (size_t k = 400; k < s.size(); k += 200) w->process(batch(s, k, k + 200));
  w->settle_held();
  w->commit();
  CHECK(counters.stored == 1000);
  CHECK(counters.rejected_count(RejectReason::kTimeJump) == 200);
  CHECK(stored_rows(tmp.path()) == 1000);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s.back().utime);
}

TEST_CASE("a shifted batch frame cannot move the time, the hold stays bounded",
          "[ingest_worker][time]") {
  const auto s = simulate(400, 15);
  TempDb tmp("shifted");
  DaemonCounters counters;
  auto w = make_worker(test_config(tmp.path()), counters);
  // Frame by frame: a new spacecraft's time base needs samples from more than one frame.
  for (size_t k = 0; k < 200; ++k) w->process(single(s[k]));
  REQUIRE(w->held_samples() == 0);
  auto shifted = batch(s, 200, 220);  // 20 consistent samples, all 20 h ahead
  for (auto& x : shifted.samples) x.utime += 20 * kHour;
  w->process(shifted);
  CHECK(w->held_samples() == 20);
  // Repeated rogues are duplicates of what is held, not corroboration.
  w->process(shifted);
  CHECK(counters.rejected_count(RejectReason::kDuplicate) == 20);
  for (size_t k = 200; k < s.size(); ++k) w->process(single(s[k]));
  w->settle_held();
  w->commit();
  CHECK(counters.stored == 400);
  CHECK(counters.rejected_count(RejectReason::kTimeJump) == 20);
  CHECK(w->fleet().find("SAT-1")->newest_utime == s.back().utime);

  // Many mutually inconsistent rogues: the hold never exceeds its capacity.
  for (int k = 0; k < 100; ++k) {
    auto r = s.back();
    r.utime += (2 + 2 * k) * kHour;  // 2 h apart: none corroborates another
    w->process(single(r));
    CHECK(w->held_samples() <= SpacecraftTracker::kHeldCapacity);
  }
  w->settle_held();
  CHECK(counters.rejected_count(RejectReason::kTimeJump) +
            counters.rejected_count(RejectReason::kJumpUnconfirmed) ==
        120);
}

TEST_CASE("random rogue frames never cost a valid sample", "[ingest_worker][time]") {
  const auto valid = simulate(300, 16);
  std::mt19937_64 rng(20261130);
  std::uniform_int_distribution<size_t> position(0, valid.size());
  std::uniform_int_distribution<int> n_rogues(1, SpacecraftTracker::kCorroborating);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  const int64_t window = DaemonConfig{}.window_utime();
  const int64_t jump = DaemonConfig{}.max_time_jump_utime();
  for (int draw = 0; draw < 40; ++draw) {
    auto frames = valid;
    const int n = n_rogues(rng);
    int64_t previous = 0;
    for (int r = 0; r < n; ++r) {
      auto rogue = valid[std::min(position(rng), valid.size() - 1)];
      // Ahead by more than the jump, behind by more than the window, or garbage; rogues far
      // apart from each other (fewer than kCorroborating + 1 can never corroborate anyway).
      const double u = unit(rng);
      if (u < 0.45) {
        rogue.utime = std::max(previous, valid.back().utime) + jump + 1 +
                      static_cast<int64_t>(unit(rng) * 1e4 * 3.6e9);
        previous = rogue.utime + jump + 1;
      } else if (u < 0.9) {
        rogue.utime =
            valid.front().utime - window - 1 - static_cast<int64_t>(unit(rng) * 1e4 * 3.6e9);
      } else {
        rogue.utime = static_cast<int64_t>(rng());
      }
      frames.insert(frames.begin() + static_cast<long>(position(rng)), rogue);
    }
    TempDb tmp("draw");
    DaemonCounters counters;
    auto w = make_worker(test_config(tmp.path()), counters);
    feed_frames(*w, frames);
    INFO("draw " << draw << ": " << n << " rogues");
    CHECK(counters.stored == static_cast<int64_t>(valid.size()));
    CHECK(counters.rejected_total() == n);
    CHECK(w->fleet().find("SAT-1")->newest_utime == valid.back().utime);
  }
}

TEST_CASE("sequence numbers at the int64 limits do not overflow", "[ingest_worker][time]") {
  SpacecraftTracker t(std::make_shared<const MagnetometerUkf::Options>());
  constexpr int64_t kMax = std::numeric_limits<int64_t>::max();
  constexpr int64_t kMin = std::numeric_limits<int64_t>::min();
  CHECK(t.received_seq.observe(kMin + 1) == 0);
  CHECK(t.received_seq.observe(kMax) == 0);  // a reset, not 2^64 missing
  CHECK(t.received_seq.last_seq == kMax);
  CHECK(t.received_seq.observe(kMin + 1) == 0);
  CHECK(t.received_seq.observe(kMin + 4) == 0);  // a gap of 2, not yet confirmed
  CHECK(t.received_seq.observe(kMin + 5) == 2);  // confirmed
  CHECK(t.received_seq.observe(kMin) == 0);      // older: the edge stays
  CHECK(t.received_seq.last_seq == kMin + 5);
}
