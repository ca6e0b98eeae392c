#include "service/io/status_report.hpp"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>

#include "pipeline/temperature_model.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/printf_string.hpp"
#include "service/io/result_json.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal {

namespace {

// The last refit's bias minus the previous one's. Where both model the bias temperature, the
// previous one is taken at the last one's T0 first (at_temperature, as the refit's change gate
// compares them): at 1.5 nT/degC a 10 degC change of the window's mean temperature is a 15 nT
// "change" of a sensor that did not change. A previous refit with a bias rate is moved by it to
// the last one's window end (at_utime, as the change gate does): the change is then what the
// rate did not predict.
std::optional<std::array<double, 3>> bias_change(const SpacecraftStatus& s) {
  if (!s.last_refit || !s.previous_refit) return std::nullopt;
  const storage::CalibrationRecord& last = *s.last_refit;
  const bool same_temperature =
      last.has_temperature_model == 1 && s.previous_refit->has_temperature_model == 1;
  CalibrationResult previous_refit = result_from_record(*s.previous_refit);
  if (same_temperature)
    previous_refit = at_temperature(previous_refit, last.reference_temperature_C);
  const Eigen::Vector3d previous =
      at_utime(previous_refit, last.window_end_utime).parameters.bias_nT;
  std::array<double, 3> d;
  for (size_t i = 0; i < 3; ++i) d[i] = last.bias_nT[i] - previous(static_cast<Eigen::Index>(i));
  return d;
}

nlohmann::json job_json(const storage::RefitJob& job) {
  nlohmann::json j;
  j["id"] = job.id;
  j["trigger"] = job.trigger;
  j["outcome"] = job.outcome;
  j["scheduled_time"] = history_time(job.scheduled_utime);
  j["started_time"] = job.started_utime ? nlohmann::json(history_time(*job.started_utime))
                                        : nlohmann::json(nullptr);
  j["finished_time"] = job.finished_utime ? nlohmann::json(history_time(*job.finished_utime))
                                          : nlohmann::json(nullptr);
  j["error"] = job.error;
  j["calibration_id"] =
      job.calibration_id ? nlohmann::json(*job.calibration_id) : nlohmann::json(nullptr);
  return j;
}

// "status, verdict", once when they say the same: a result the gates rejected has the status
// "rejected" as well as the verdict (the page's statusVerdict() does the same).
std::string status_verdict(const storage::CalibrationRecord& r) {
  const std::string status = storage::status_name(r.status);
  return status == r.verdict ? status : status + ", " + r.verdict;
}

void append_estimate(std::string* text, const char* label, const storage::CalibrationRecord& r) {
  append_printf(text,
                "  %-16s %s  %-8s bias [%9.2f %9.2f %9.2f] nT  1-sigma [%6.2f %6.2f %6.2f] nT  "
                "rms %.2f nT  %s\n",
                label, format_iso8601_utc(r.utime).c_str(), r.method.c_str(), r.bias_nT[0],
                r.bias_nT[1], r.bias_nT[2], r.bias_sigma_nT[0], r.bias_sigma_nT[1],
                r.bias_sigma_nT[2], r.residual_rms_nT, status_verdict(r).c_str());
  if (r.has_temperature_model == 1) {
    const Eigen::Vector3d sigma = result_from_record(r).temperature_coefficient_sigma_nT_per_C();
    const std::string source =
        r.temperature_model_refit_id > 0
            ? " (of refit " + std::to_string(r.temperature_model_refit_id) + ")"
            : "";
    append_printf(text,
                  "  %-16s bias at T0 = %.2f degC; k_T [%.3f %.3f %.3f] +- [%.3f %.3f %.3f] "
                  "nT/degC%s\n",
                  "", r.reference_temperature_C, r.temperature_coefficient_nT_per_C[0],
                  r.temperature_coefficient_nT_per_C[1], r.temperature_coefficient_nT_per_C[2],
                  sigma(0), sigma(1), sigma(2), source.c_str());
  }
  if (r.has_bias_rate == 1) {
    const Eigen::Vector3d sigma = result_from_record(r).bias_rate_sigma_nT_per_h();
    append_printf(text,
                  "  %-16s bias at the window's end; rate [%.3f %.3f %.3f] +- [%.3f %.3f %.3f] "
                  "nT/h\n",
                  "", r.bias_rate_nT_per_h[0], r.bias_rate_nT_per_h[1], r.bias_rate_nT_per_h[2],
                  sigma(0), sigma(1), sigma(2));
  }
}

// "gs-a 2000, gs-b 2320" (samples stored without a station: "no station N"); empty when no
// sample names a station (a single daemon's database from before stations).
std::string by_station_line(const std::vector<storage::StationCount>& counts) {
  std::string line;
  bool named = false;
  for (const auto& c : counts) {
    named = named || !c.station.empty();
    if (!line.empty()) line += ", ";
    line += (c.station.empty() ? std::string("no station") : c.station) + " " +
            std::to_string(c.samples);
  }
  return named ? line : "";
}

// StationStatus::settings_differ_from and settings_differences of every live station.
void mark_settings_differences(std::vector<StationStatus>& stations) {
  // Live stations that declare settings, grouped by their text.
  std::map<std::string, std::vector<const StationStatus*>> groups;
  for (const auto& st : stations) {
    if (st.live && st.row.settings) groups[st.row.settings->text].push_back(&st);
  }
  if (groups.size() < 2) return;
  size_t largest = 0, with_largest = 0;
  for (const auto& [text, members] : groups) largest = std::max(largest, members.size());
  for (const auto& [text, members] : groups) with_largest += members.size() == largest;
  for (auto& st : stations) {
    if (!st.live || !st.row.settings) continue;
    const std::string& mine = st.row.settings->text;
    const std::string* theirs = nullptr;
    if (with_largest == 1) {
      for (const auto& [text, members] : groups)
        if (members.size() == largest && text != mine) theirs = &text;
    } else {
      for (const auto& other : stations) {
        if (other.live && other.row.settings && other.row.settings->text != mine) {
          theirs = &other.row.settings->text;
          break;
        }
      }
    }
    if (theirs == nullptr) continue;  // of the majority
    for (const StationStatus* other : groups.at(*theirs))
      st.settings_differ_from.push_back(other->row.station);
    st.settings_differences =
        settings_differences(parse_station_settings(mine), parse_station_settings(*theirs));
  }
}

}  // namespace

FleetStatus read_status(storage::Connection& db, int64_t window_utime) {
  FleetStatus fleet;
  std::vector<SpacecraftStatus>& all = fleet.spacecraft;
  storage::Transaction snapshot(db, storage::Transaction::Mode::kReadSnapshot);
  const auto samples = db.make_sample_window_store();
  const auto history = db.make_calibration_history();
  const auto jobs = db.make_refit_job_log();
  const auto leases = db.make_lease_store();
  const int64_t wall_now_utime = now_utime();
  std::set<std::string> sats;
  for (auto& id : samples->spacecraft()) sats.insert(std::move(id));
  for (auto& id : history->spacecraft()) sats.insert(std::move(id));
  for (const auto& id : sats) {
    SpacecraftStatus s;
    s.sat_id = id;
    s.last_sample_utime = samples->newest_utime(id);
    if (s.last_sample_utime) {
      // The refit window (newest - W, newest].
      // Saturating: a database written before the time bounds may hold any utime.
      const int64_t t0 = saturating_sub(*s.last_sample_utime, window_utime) + 1;
      const int64_t t1 = saturating_add(*s.last_sample_utime, 1);
      // One query: the window's count is the sum over its stations (a NULL station included).
      s.samples_by_station = samples->count_by_station(id, t0, t1);
      s.samples_in_window = 0;
      for (const auto& c : s.samples_by_station) s.samples_in_window += c.samples;
    }
    s.last_ukf = history->latest(id, "ukf");
    s.last_refit = history->latest_refit(id);
    s.previous_refit = history->previous_refit(id);
    s.last_job = jobs->latest(id);
    s.lease = leases->get(id);
    if (s.lease && s.lease->owner.empty()) s.lease.reset();  // registered, never owned
    s.owner_now = s.lease && s.lease->held_at(wall_now_utime);
    all.push_back(std::move(s));
  }
  for (auto& row : leases->stations()) {
    StationStatus st;
    st.live = row.live_at(wall_now_utime);
    for (const auto& s : all) st.spacecraft_owned += s.owner_now && s.lease->owner == row.station;
    st.row = std::move(row);
    fleet.stations.push_back(std::move(st));
  }
  mark_settings_differences(fleet.stations);
  return fleet;
}

nlohmann::json status_json(const FleetStatus& fleet, int64_t window_utime) {
  nlohmann::json list = nlohmann::json::array();
  for (const auto& s : fleet.spacecraft) {
    nlohmann::json j;
    j["sat_id"] = s.sat_id;
    j["last_sample_time"] =
        s.last_sample_utime ? nlohmann::json(history_time(*s.last_sample_utime)) : nullptr;
    j["last_sample_utime"] =
        s.last_sample_utime ? nlohmann::json(*s.last_sample_utime) : nlohmann::json(nullptr);
    j["samples_in_window"] = s.samples_in_window;
    nlohmann::json by_station = nlohmann::json::array();
    for (const auto& c : s.samples_by_station) {
      by_station.push_back(
          {{"station", c.station.empty() ? nlohmann::json(nullptr) : nlohmann::json(c.station)},
           {"samples", c.samples}});
    }
    j["samples_by_station"] = std::move(by_station);
    const auto lease_json = [](const storage::Lease& l) {
      return nlohmann::json{{"station", l.owner},
                            {"lease_epoch", l.epoch},
                            {"lease_expires_time", format_iso8601_utc(l.expires_utime)},
                            {"lease_expires_utime", l.expires_utime}};
    };
    j["owner"] = s.owner_now ? lease_json(*s.lease) : nlohmann::json(nullptr);
    j["last_owner"] = s.lease ? lease_json(*s.lease) : nlohmann::json(nullptr);
    j["window_hours"] = static_cast<double>(window_utime) / 3.6e9;
    j["last_ukf"] = s.last_ukf ? history_record_json(*s.last_ukf) : nlohmann::json(nullptr);
    j["last_refit"] = s.last_refit ? history_record_json(*s.last_refit) : nlohmann::json(nullptr);
    j["last_refit_job"] = s.last_job ? job_json(*s.last_job) : nlohmann::json(nullptr);
    const auto d = bias_change(s);
    j["bias_change_since_previous_refit_nT"] =
        d ? nlohmann::json{json_number((*d)[0]), json_number((*d)[1]), json_number((*d)[2])}
          : nlohmann::json(nullptr);
    list.push_back(std::move(j));
  }
  nlohmann::json stations = nlohmann::json::array();
  const auto value_json = [](const std::optional<std::string>& v) {
    return v ? nlohmann::json(*v) : nlohmann::json(nullptr);
  };
  for (const auto& st : fleet.stations) {
    nlohmann::json differ = nullptr;
    if (!st.settings_differ_from.empty()) {
      nlohmann::json keys = nlohmann::json::array();
      for (const auto& d : st.settings_differences) {
        keys.push_back(
            {{"key", d.key}, {"here", value_json(d.here)}, {"there", value_json(d.there)}});
      }
      differ = {{"from", st.settings_differ_from}, {"keys", std::move(keys)}};
    }
    stations.push_back(
        {{"station", st.row.station},
         {"live", st.live},
         {"heartbeat_time", format_iso8601_utc(st.row.heartbeat_utime)},
         {"heartbeat_utime", st.row.heartbeat_utime},
         {"expires_time", format_iso8601_utc(st.row.expires_utime)},
         {"expires_utime", st.row.expires_utime},
         {"spacecraft_owned", st.spacecraft_owned},
         {"settings_hash", st.row.settings ? nlohmann::json(st.row.settings->hash) : nullptr},
         {"settings_differ", std::move(differ)}});
  }
  return nlohmann::json{{"spacecraft", list}, {"stations", stations}};
}

std::string status_json_text(const FleetStatus& fleet, int64_t window_utime) {
  return status_json(fleet, window_utime).dump(2) + "\n";
}

std::string status_text(const FleetStatus& fleet, int64_t window_utime) {
  std::string text =
      "(times in UTC: data time, the samples' time tags, unless marked wall clock)\n";
  for (const auto& s : fleet.spacecraft) {
    append_printf(&text, "%s\n", s.sat_id.c_str());
    if (s.last_sample_utime) {
      append_printf(&text, "  %-16s %s  (%lld samples in the %.4g h window)\n", "last sample",
                    format_iso8601_utc(*s.last_sample_utime).c_str(),
                    static_cast<long long>(s.samples_in_window),
                    static_cast<double>(window_utime) / 3.6e9);
    } else {
      append_printf(&text, "  %-16s none stored\n", "last sample");
    }
    if (const std::string line = by_station_line(s.samples_by_station); !line.empty()) {
      append_printf(&text, "  %-16s %s\n", "by station", line.c_str());
    }
    if (s.lease) {
      // Who runs its UKF and refits now (a fleet sharing the database; one daemon alone too).
      append_printf(&text, "  %-16s %s%s (lease epoch %lld, %s %s (wall clock))\n", "owner",
                    s.owner_now ? "" : "none; last ", s.lease->owner.c_str(),
                    static_cast<long long>(s.lease->epoch), s.owner_now ? "until" : "ended",
                    format_iso8601_utc(s.lease->expires_utime).c_str());
    }
    if (s.last_ukf) {
      append_estimate(&text, "last ukf", *s.last_ukf);
    } else {
      append_printf(&text, "  %-16s none\n", "last ukf");
    }
    if (s.last_refit) {
      append_estimate(&text, "last refit", *s.last_refit);
      for (const auto& reason : s.last_refit->rejection_reasons) {
        append_printf(&text, "  %-16s   rejected: %s\n", "", reason.c_str());
      }
    } else {
      append_printf(&text, "  %-16s none\n", "last refit");
    }
    if (s.last_job) {
      // When the job ran is wall-clock time. A scheduled job's due time is on the [refit] clock
      // (data time, or wall clock when so configured: the job log does not say which); a new
      // spacecraft's first and early refits are due at a sample's time (data time); a manual
      // refit is due when it runs.
      const storage::RefitJob& job = *s.last_job;
      std::string when;
      const auto trigger = storage::refit_trigger_from_string(job.trigger);
      if (trigger != storage::RefitTrigger::kManual) {
        when = ", due " + format_iso8601_utc(job.scheduled_utime) +
               (trigger && storage::is_early_refit(*trigger) ? " (data time)" : " ([refit] clock)");
      }
      if (job.started_utime) {
        when += ", ran " + format_iso8601_utc(*job.started_utime) + " (wall clock)";
      }
      append_printf(&text, "  %-16s %s (%s%s)%s%s\n", "last refit job", job.outcome.c_str(),
                    job.trigger.c_str(), when.c_str(), job.error.empty() ? "" : ": ",
                    job.error.c_str());
    }
    if (const auto d = bias_change(s)) {
      append_printf(&text,
                    "  %-16s [%+9.2f %+9.2f %+9.2f] nT  (|change| %.2f nT) since the refit of %s\n",
                    "bias change", (*d)[0], (*d)[1], (*d)[2],
                    std::sqrt((*d)[0] * (*d)[0] + (*d)[1] * (*d)[1] + (*d)[2] * (*d)[2]),
                    format_iso8601_utc(s.previous_refit->utime).c_str());
      if (s.last_refit->has_temperature_model == 1 && s.previous_refit->has_temperature_model == 1)
        append_printf(&text, "  %-16s both at %.2f degC (the last refit's T0)\n", "",
                      s.last_refit->reference_temperature_C);
      if (s.previous_refit->has_bias_rate == 1)
        append_printf(&text, "  %-16s the previous refit moved by its bias rate to %s\n", "",
                      format_iso8601_utc(s.last_refit->window_end_utime).c_str());
    }
  }
  if (!fleet.stations.empty()) {
    // The daemons sharing the database: which are up, and who does the tracking work.
    text += "stations (wall clock)\n";
    for (const auto& st : fleet.stations) {
      if (st.live) {
        append_printf(&text, "  %-16s live, last beat %s, owns %lld spacecraft\n",
                      st.row.station.c_str(), format_iso8601_utc(st.row.heartbeat_utime).c_str(),
                      static_cast<long long>(st.spacecraft_owned));
        if (!st.settings_differ_from.empty()) {
          // Its results differ from those of the others for the spacecraft it owns.
          std::string from;
          for (const auto& name : st.settings_differ_from)
            from += (from.empty() ? "" : ", ") + name;
          append_printf(&text, "  %-16s SETTINGS DIFFER from %s: %s\n", "", from.c_str(),
                        describe_differences(st.settings_differences).c_str());
        }
      } else {
        append_printf(&text, "  %-16s gone since %s\n", st.row.station.c_str(),
                      format_iso8601_utc(st.row.expires_utime).c_str());
      }
    }
  }
  return text;
}

}  // namespace magcal
