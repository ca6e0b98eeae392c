#include "service/http/metrics.hpp"

#include <limits>
#include <mutex>
#include <sstream>
#include <unordered_map>

#include <prometheus/counter.h>
#include <prometheus/family.h>
#include <prometheus/gauge.h>
#include <prometheus/histogram.h>
#include <prometheus/registry.h>
#include <prometheus/text_serializer.h>

#include "pipeline/time_utc.hpp"
#include "storage/calibration_history.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal::http {
namespace {

constexpr std::array<const char*, 3> kAxes{"x", "y", "z"};

// Counters only move forward: bring one up to a total kept elsewhere.
void raise_to(prometheus::Counter& c, int64_t total) {
  const double delta = static_cast<double>(total) - c.Value();
  if (delta > 0.0) c.Increment(delta);
}

struct Families {
  prometheus::Family<prometheus::Counter>* received;
  prometheus::Family<prometheus::Counter>* stored;
  prometheus::Family<prometheus::Counter>* rejected;
  prometheus::Family<prometheus::Counter>* missing;
  prometheus::Family<prometheus::Gauge>* queue_depth;
  prometheus::Family<prometheus::Counter>* queue_overflow;
  // magcal_storage_commit_seconds, magcal_sqlite_commit_seconds (deprecated): one histogram.
  std::array<prometheus::Family<prometheus::Histogram>*, 2> commit_seconds;
  prometheus::Family<prometheus::Gauge>* ukf_bias;
  prometheus::Family<prometheus::Gauge>* ukf_sigma;
  prometheus::Family<prometheus::Gauge>* ukf_accepted;
  prometheus::Family<prometheus::Counter>* refits;
  prometheus::Family<prometheus::Counter>* refits_claimed_elsewhere;
  prometheus::Family<prometheus::Gauge>* last_refit_success;
  prometheus::Family<prometheus::Gauge>* storage_healthy;
  // The daemon's alone (magcal serve has no such series).
  prometheus::Family<prometheus::Gauge>* storage_failing_s;
  prometheus::Family<prometheus::Gauge>* storage_pending;
  prometheus::Family<prometheus::Counter>* spilled;
  prometheus::Family<prometheus::Gauge>* spill_held;
  prometheus::Family<prometheus::Gauge>* spill_bytes;
  prometheus::Family<prometheus::Counter>* spill_recovered;
  prometheus::Family<prometheus::Counter>* spill_dropped;
  prometheus::Family<prometheus::Gauge>* owned;
  prometheus::Family<prometheus::Counter>* leases_lost;
  prometheus::Family<prometheus::Gauge>* fleet_settings_mismatch;
};

void register_storage_and_fleet_families(prometheus::Registry& r, Families& f);

// Every family of the contract, registered in one place for the daemon and `magcal serve`.
Families register_families(prometheus::Registry& r, const std::string& version) {
  using prometheus::BuildCounter;
  using prometheus::BuildGauge;
  Families f{};
  f.received = &BuildCounter()
                    .Name("magcal_samples_received_total")
                    .Help(
                        "Samples received per spacecraft (an undecodable frame counts 1 under "
                        "sat=\"\")")
                    .Register(r);
  f.stored = &BuildCounter()
                  .Name("magcal_samples_stored_total")
                  .Help("Samples committed to the database per spacecraft")
                  .Register(r);
  f.rejected = &BuildCounter()
                    .Name("magcal_samples_rejected_total")
                    .Help("Samples rejected, per reason")
                    .Register(r);
  f.missing = &BuildCounter()
                   .Name("magcal_samples_missing_total")
                   .Help("Samples missing by gaps in seq, per spacecraft")
                   .Register(r);
  f.queue_depth = &BuildGauge()
                       .Name("magcal_queue_depth")
                       .Help("Samples waiting in the receive queue")
                       .Register(r);
  f.queue_overflow = &BuildCounter()
                          .Name("magcal_queue_overflow_total")
                          .Help("Samples dropped because the receive queue was full")
                          .Register(r);
  f.commit_seconds = {&prometheus::BuildHistogram()
                           .Name("magcal_storage_commit_seconds")
                           .Help("Duration of each sample-batch transaction (failed too)")
                           .Register(r),
                      &prometheus::BuildHistogram()
                           .Name("magcal_sqlite_commit_seconds")
                           .Help("Deprecated: magcal_storage_commit_seconds under its first "
                                 "name (emitted on PostgreSQL too)")
                           .Register(r)};
  f.ukf_bias = &BuildGauge()
                    .Name("magcal_ukf_bias_nT")
                    .Help("Bias of the newest stored UKF snapshot, nT")
                    .Register(r);
  f.ukf_sigma = &BuildGauge()
                     .Name("magcal_ukf_bias_sigma_nT")
                     .Help("1-sigma of the newest stored UKF snapshot's bias, nT")
                     .Register(r);
  f.ukf_accepted = &BuildGauge()
                        .Name("magcal_ukf_snapshot_accepted")
                        .Help("1 when the newest stored UKF snapshot passed the acceptance gates")
                        .Register(r);
  f.refits = &BuildCounter()
                  .Name("magcal_refits_total")
                  .Help("Refits run, per spacecraft and verdict (accepted, rejected, error)")
                  .Register(r);
  f.refits_claimed_elsewhere = &BuildCounter()
                                    .Name("magcal_refits_claimed_elsewhere_total")
                                    .Help(
                                        "Refits due here that another station had claimed and "
                                        "runs (daemons sharing a database), per spacecraft")
                                    .Register(r);
  f.last_refit_success = &BuildGauge()
                              .Name("magcal_last_refit_success_timestamp_seconds")
                              .Help("Time (s since 1970, data time) of the newest accepted refit")
                              .Register(r);
  register_storage_and_fleet_families(r, f);
  BuildGauge()
      .Name("magcal_build_info")
      .Help("Build of magcal (value 1)")
      .Register(r)
      .Add({{"version", version}})
      .Set(1.0);
  return f;
}

// The storage, spill and fleet families of `f` (register_families' second half).
void register_storage_and_fleet_families(prometheus::Registry& r, Families& f) {
  using prometheus::BuildCounter;
  using prometheus::BuildGauge;
  f.storage_healthy = &BuildGauge()
                           .Name("magcal_storage_healthy")
                           .Help("1, or 0 while a storage operation fails and is retried")
                           .Register(r);
  f.storage_failing_s = &BuildGauge()
                             .Name("magcal_storage_failing_seconds")
                             .Help("How long storage has been failing, s (0 while it works)")
                             .Register(r);
  f.storage_pending = &BuildGauge()
                           .Name("magcal_storage_pending_samples")
                           .Help("Received samples held in memory, not committed yet")
                           .Register(r);
  f.spilled = &BuildCounter()
                   .Name("magcal_samples_spilled_total")
                   .Help("Samples written to the spill file during a database outage")
                   .Register(r);
  f.spill_held = &BuildGauge()
                      .Name("magcal_spill_samples")
                      .Help("Samples in the spill file, not committed yet (an earlier run's too)")
                      .Register(r);
  f.spill_bytes =
      &BuildGauge().Name("magcal_spill_bytes").Help("Size of the spill file, bytes").Register(r);
  f.spill_recovered = &BuildCounter()
                           .Name("magcal_spill_recovered_samples_total")
                           .Help("Samples committed at start from a spill file an earlier run left")
                           .Register(r);
  f.spill_dropped = &BuildCounter()
                         .Name("magcal_spill_dropped_records_total")
                         .Help("Records of a spill file cut off at start as torn or corrupt")
                         .Register(r);
  f.owned = &BuildGauge()
                 .Name("magcal_spacecraft_owned")
                 .Help(
                     "1 while this daemon holds the spacecraft's lease (runs its UKF and refits), "
                     "0 while another daemon of the fleet does")
                 .Register(r);
  f.leases_lost = &BuildCounter()
                       .Name("magcal_leases_lost_total")
                       .Help(
                           "Spacecraft leases lost to another daemon (this one stalled past the "
                           "lease, or the database was unreachable for that long)")
                       .Register(r);
  f.fleet_settings_mismatch =
      &BuildGauge()
           .Name("magcal_fleet_settings_mismatch")
           .Help(
               "Live stations of the fleet whose result-affecting settings differ from this "
               "daemon's (the results of a spacecraft then depend on which station owns it)")
           .Register(r);
}

std::string serialize(const prometheus::Registry& r) {
  std::ostringstream out;
  prometheus::TextSerializer().Serialize(out, r.Collect());
  return out.str();
}

}  // namespace

// One spacecraft's series, created when the daemon first counts it. The UKF gauges and the
// last-success time appear with their first value: no bias of 0 nT before there is one.
struct SpacecraftSeries {
  prometheus::Counter* received = nullptr;
  prometheus::Counter* stored = nullptr;
  prometheus::Counter* missing = nullptr;
  prometheus::Counter* refits_accepted = nullptr;
  prometheus::Counter* refits_rejected = nullptr;
  prometheus::Counter* refits_error = nullptr;
  prometheus::Counter* refits_claimed_elsewhere = nullptr;
  std::array<prometheus::Gauge*, 3> ukf_bias_nT{};
  std::array<prometheus::Gauge*, 3> ukf_bias_sigma_nT{};
  prometheus::Gauge* ukf_snapshot_accepted = nullptr;
  prometheus::Gauge* last_refit_success_s = nullptr;
  prometheus::Gauge* owned = nullptr;
};

struct DaemonMetrics::Impl {
  Impl(const std::string& version, const std::string& station,
       const std::vector<double>& commit_bucket_bounds_s);
  SpacecraftSeries& series(const std::string& sat_label);
  void apply_totals(const Totals& t);
  void apply_spacecraft(const SpacecraftTotals& sc);
  void apply_commit_seconds(const Totals& t);

  std::shared_ptr<prometheus::Registry> registry = std::make_shared<prometheus::Registry>();
  Families f;
  prometheus::Gauge* queue_depth;
  prometheus::Counter* queue_overflow;
  std::array<prometheus::Histogram*, 2> commit_seconds{};  // storage_, sqlite_ (deprecated)
  std::vector<int64_t> commit_counts_seen;
  double commit_sum_seen_s = 0.0;
  prometheus::Gauge* storage_healthy;
  prometheus::Gauge* storage_failing_s;
  prometheus::Gauge* storage_pending;
  prometheus::Counter* spilled;
  prometheus::Gauge* spill_held;
  prometheus::Gauge* spill_bytes;
  prometheus::Counter* spill_recovered;
  prometheus::Counter* spill_dropped;
  prometheus::Counter* leases_lost;
  prometheus::Gauge* fleet_settings_mismatch;

  std::mutex mutex;  // the totals source and scrapes
  std::unordered_map<std::string, std::unique_ptr<SpacecraftSeries>> series_by_sat;
  std::function<Totals()> totals_source;
  std::unordered_map<std::string, prometheus::Counter*> rejected_by_reason;
};

DaemonMetrics::Impl::Impl(const std::string& version, const std::string& station,
                          const std::vector<double>& commit_bucket_bounds_s)
    : f(register_families(*registry, version)) {
  prometheus::BuildGauge()
      .Name("magcal_station_info")
      .Help("The daemon's ground station, its [station] id (value 1)")
      .Register(*registry)
      .Add({{"station", station}})
      .Set(1.0);
  queue_depth = &f.queue_depth->Add({});
  queue_overflow = &f.queue_overflow->Add({});
  commit_counts_seen.assign(commit_bucket_bounds_s.size() + 1, 0);
  for (size_t i = 0; i < commit_seconds.size(); ++i) {
    commit_seconds[i] = &f.commit_seconds[i]->Add({}, commit_bucket_bounds_s);
  }
  storage_healthy = &f.storage_healthy->Add({});
  storage_healthy->Set(1.0);
  storage_failing_s = &f.storage_failing_s->Add({});
  storage_pending = &f.storage_pending->Add({});
  spilled = &f.spilled->Add({});
  spill_held = &f.spill_held->Add({});
  spill_bytes = &f.spill_bytes->Add({});
  spill_recovered = &f.spill_recovered->Add({});
  spill_dropped = &f.spill_dropped->Add({});
  leases_lost = &f.leases_lost->Add({});
  fleet_settings_mismatch = &f.fleet_settings_mismatch->Add({});
}

SpacecraftSeries& DaemonMetrics::Impl::series(const std::string& label) {
  if (const auto it = series_by_sat.find(label); it != series_by_sat.end()) return *it->second;
  auto m = std::make_unique<SpacecraftSeries>();
  m->received = &f.received->Add({{"sat", label}});
  m->stored = &f.stored->Add({{"sat", label}});
  m->missing = &f.missing->Add({{"sat", label}});
  m->refits_accepted = &f.refits->Add({{"sat", label}, {"verdict", "accepted"}});
  m->refits_rejected = &f.refits->Add({{"sat", label}, {"verdict", "rejected"}});
  m->refits_error = &f.refits->Add({{"sat", label}, {"verdict", "error"}});
  m->refits_claimed_elsewhere = &f.refits_claimed_elsewhere->Add({{"sat", label}});
  m->owned = &f.owned->Add({{"sat", label}});
  return *series_by_sat.emplace(label, std::move(m)).first->second;
}

void DaemonMetrics::Impl::apply_totals(const Totals& t) {
  for (const auto& [reason, total] : t.rejected_by_reason) {
    auto it = rejected_by_reason.find(reason);
    if (it == rejected_by_reason.end()) {
      it = rejected_by_reason.emplace(reason, &f.rejected->Add({{"reason", reason}})).first;
    }
    raise_to(*it->second, total);
  }
  queue_depth->Set(static_cast<double>(t.queue_depth));
  raise_to(*queue_overflow, t.queue_overflow);
  storage_healthy->Set(t.storage_healthy ? 1.0 : 0.0);
  storage_failing_s->Set(t.storage_failing_s);
  storage_pending->Set(static_cast<double>(t.storage_pending));
  raise_to(*spilled, t.spilled);
  spill_held->Set(static_cast<double>(t.spill_held));
  spill_bytes->Set(static_cast<double>(t.spill_bytes));
  raise_to(*spill_recovered, t.spill_recovered);
  raise_to(*spill_dropped, t.spill_dropped);
  raise_to(*leases_lost, t.leases_lost);
  fleet_settings_mismatch->Set(static_cast<double>(t.fleet_settings_mismatch));
  for (const SpacecraftTotals& sc : t.spacecraft) apply_spacecraft(sc);
  apply_commit_seconds(t);
}

void DaemonMetrics::Impl::apply_spacecraft(const SpacecraftTotals& sc) {
  SpacecraftSeries& m = series(sc.sat_label);
  raise_to(*m.received, sc.received);
  raise_to(*m.stored, sc.stored);
  raise_to(*m.missing, sc.missing);
  raise_to(*m.refits_accepted, sc.refits_accepted);
  raise_to(*m.refits_rejected, sc.refits_rejected);
  raise_to(*m.refits_error, sc.refits_error);
  raise_to(*m.refits_claimed_elsewhere, sc.refits_claimed_elsewhere);
  m.owned->Set(sc.owned ? 1.0 : 0.0);
  if (sc.has_ukf_snapshot) {
    if (!m.ukf_snapshot_accepted) {
      for (size_t i = 0; i < 3; ++i) {
        m.ukf_bias_nT[i] = &f.ukf_bias->Add({{"sat", sc.sat_label}, {"axis", kAxes[i]}});
        m.ukf_bias_sigma_nT[i] = &f.ukf_sigma->Add({{"sat", sc.sat_label}, {"axis", kAxes[i]}});
      }
      m.ukf_snapshot_accepted = &f.ukf_accepted->Add({{"sat", sc.sat_label}});
    }
    for (size_t i = 0; i < 3; ++i) {
      m.ukf_bias_nT[i]->Set(sc.ukf_bias_nT[i]);
      m.ukf_bias_sigma_nT[i]->Set(sc.ukf_bias_sigma_nT[i]);
    }
    m.ukf_snapshot_accepted->Set(sc.ukf_accepted ? 1.0 : 0.0);
  }
  if (sc.last_refit_success_utime != 0) {
    if (!m.last_refit_success_s) {
      m.last_refit_success_s = &f.last_refit_success->Add({{"sat", sc.sat_label}});
    }
    m.last_refit_success_s->Set(static_cast<double>(sc.last_refit_success_utime) * 1e-6);
  }
}

// The histogram takes what was observed since the last scrape.
void DaemonMetrics::Impl::apply_commit_seconds(const Totals& t) {
  if (t.commit_bucket_counts.size() != commit_counts_seen.size()) return;
  std::vector<double> increments(commit_counts_seen.size(), 0.0);
  bool any = false;
  for (size_t i = 0; i < increments.size(); ++i) {
    const int64_t delta = t.commit_bucket_counts[i] - commit_counts_seen[i];
    if (delta <= 0) continue;
    increments[i] = static_cast<double>(delta);
    commit_counts_seen[i] = t.commit_bucket_counts[i];
    any = true;
  }
  if (!any) return;
  for (prometheus::Histogram* h : commit_seconds) {
    h->ObserveMultiple(increments, t.commit_sum_s - commit_sum_seen_s);
  }
  commit_sum_seen_s = t.commit_sum_s;
}

DaemonMetrics::DaemonMetrics(const std::string& version, const std::string& station,
                             std::vector<double> commit_bucket_bounds_s)
    : impl_(std::make_unique<Impl>(version, station, commit_bucket_bounds_s)) {}

DaemonMetrics::~DaemonMetrics() = default;

void DaemonMetrics::set_totals_source(std::function<Totals()> source) {
  std::lock_guard lock(impl_->mutex);
  impl_->totals_source = std::move(source);
}

std::string DaemonMetrics::text() {
  std::lock_guard lock(impl_->mutex);
  if (impl_->totals_source) impl_->apply_totals(impl_->totals_source());
  return serialize(*impl_->registry);
}

std::string database_metrics_text(storage::Connection& db, const std::string& version,
                                  int64_t window_utime) {
  prometheus::Registry registry;
  const Families f = register_families(registry, version);
  const auto samples = db.make_sample_window_store();
  const auto history = db.make_calibration_history();
  // A database knows the samples it holds now, not how many were ever stored (retention
  // deletes): a gauge of its own, never magcal_samples_stored_total (a counter must not fall).
  auto& window = prometheus::BuildGauge()
                     .Name("magcal_window_samples")
                     .Help(
                         "Samples in the window ending at the spacecraft's newest sample, per "
                         "spacecraft, as magcal status counts them (magcal serve)")
                     .Register(registry);
  auto& by_station = prometheus::BuildGauge()
                         .Name("magcal_window_samples_by_station")
                         .Help(
                             "Samples in the window ending at the spacecraft's newest sample, per "
                             "spacecraft and the station that stored them (magcal serve)")
                         .Register(registry);
  for (const auto& sat : samples->spacecraft()) {
    const auto newest = samples->newest_utime(sat);
    if (!newest) continue;  // (deleted since the list was read)
    int64_t held = 0;
    // The window (newest - W, newest], as magcal status counts it (saturating: a database
    // written before the time bounds may hold any utime).
    for (const auto& c : samples->count_by_station(sat, saturating_sub(*newest, window_utime) + 1,
                                                   saturating_add(*newest, 1))) {
      by_station.Add({{"sat", sat}, {"station", c.station}}).Set(static_cast<double>(c.samples));
      held += c.samples;
    }
    window.Add({{"sat", sat}}).Set(static_cast<double>(held));
  }
  for (const auto& sat : history->spacecraft()) {
    if (const auto ukf = history->latest(sat, "ukf")) {
      for (size_t i = 0; i < 3; ++i) {
        f.ukf_bias->Add({{"sat", sat}, {"axis", kAxes[i]}}).Set(ukf->bias_nT[i]);
        f.ukf_sigma->Add({{"sat", sat}, {"axis", kAxes[i]}}).Set(ukf->bias_sigma_nT[i]);
      }
      f.ukf_accepted->Add({{"sat", sat}}).Set(ukf->verdict == "accepted" ? 1.0 : 0.0);
    }
    for (const char* method : {"centered", "twostep"}) {
      storage::HistoryQuery q;
      q.sat_id = sat;
      q.method = method;
      for (const auto& r : history->query(q)) {
        f.refits->Add({{"sat", sat}, {"verdict", r.verdict}}).Increment();
      }
    }
    if (const auto ok = history->latest_accepted_refit(sat)) {
      f.last_refit_success->Add({{"sat", sat}}).Set(static_cast<double>(ok->utime) * 1e-6);
    }
  }
  return serialize(registry);
}

}  // namespace magcal::http
