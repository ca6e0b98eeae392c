#include "service/config/daemon_config.hpp"

#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <climits>
#include <cmath>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <map>
#include <set>
#include <sstream>

#include <fmt/format.h>
#include <toml++/toml.h>

#include "service/http/operations_server.hpp"
#include "service/io/fnv1a.hpp"
#include "storage/connection.hpp"

namespace magcal {

std::optional<int> parse_daily_time_utc(const std::string& text) {
  if (text.size() != 5 || text[2] != ':') return std::nullopt;
  for (int i : {0, 1, 3, 4}) {
    if (text[static_cast<size_t>(i)] < '0' || text[static_cast<size_t>(i)] > '9')
      return std::nullopt;
  }
  const int h = (text[0] - '0') * 10 + (text[1] - '0');
  const int m = (text[3] - '0') * 10 + (text[4] - '0');
  if (h > 23 || m > 59) return std::nullopt;
  return h * 60 + m;
}

namespace {

// A setter reads one TOML value into the config; returns an error ("expected ...") or "".
using Setter = std::function<std::string(const toml::node&)>;
// The value as the station's settings text shows it (service/io/station_settings.hpp).
using Shower = std::function<std::string()>;
struct Binding {
  Setter set;
  Shower show;
};
using Section = std::map<std::string, Binding>;

// Shortest text that reads back as the same double ("6", "0.25", "1e-06").
std::string show_double(double v) {
  return fmt::format("{}", v);
}

Binding bind(std::string& out) {
  return {[&out](const toml::node& n) -> std::string {
            auto v = n.value_exact<std::string>();
            if (!v) return "expected a string";
            out = *v;
            return "";
          },
          [&out] { return out; }};
}
Binding bind(double& out) {
  return {[&out](const toml::node& n) -> std::string {
            auto v = n.value<double>();  // integers are accepted for floats
            if (!v || !n.is_number()) return "expected a number";
            if (!std::isfinite(*v)) return "expected a finite number";
            out = *v;
            return "";
          },
          [&out] { return show_double(out); }};
}
Binding bind(int& out) {
  return {[&out](const toml::node& n) -> std::string {
            auto v = n.value_exact<int64_t>();
            if (!v) return "expected an integer";
            if (*v < INT32_MIN || *v > INT32_MAX) return "integer out of range";
            out = static_cast<int>(*v);
            return "";
          },
          [&out] { return std::to_string(out); }};
}
Binding bind(int64_t& out) {
  return {[&out](const toml::node& n) -> std::string {
            auto v = n.value_exact<int64_t>();
            if (!v) return "expected an integer";
            out = *v;
            return "";
          },
          [&out] { return std::to_string(out); }};
}
Binding bind(bool& out) {
  return {[&out](const toml::node& n) -> std::string {
            auto v = n.value_exact<bool>();
            if (!v) return "expected true or false";
            out = *v;
            return "";
          },
          [&out] { return std::string(out ? "true" : "false"); }};
}
template <typename E>
Binding bind_enum(E& out, std::map<std::string, E> names) {
  return {[&out, names](const toml::node& n) -> std::string {
            auto v = n.value_exact<std::string>();
            std::string all;
            for (const auto& [k, e] : names) all += (all.empty() ? "" : ", ") + ("\"" + k + "\"");
            if (!v || !names.count(*v)) return "expected one of " + all;
            out = names.at(*v);
            return "";
          },
          [&out, names] {
            for (const auto& [k, e] : names)
              if (e == out) return k;
            return std::string("?");
          }};
}
// Lists of up to this many names show as the names; longer ones as a count and a hash.
constexpr size_t kMaxListedNames = 8;

Binding bind_string_list(std::vector<std::string>& out) {
  return {[&out](const toml::node& n) -> std::string {
            const auto* arr = n.as_array();
            if (!arr) return "expected an array of strings";
            std::vector<std::string> values;
            for (const auto& e : *arr) {
              auto v = e.value_exact<std::string>();
              if (!v || v->empty()) return "expected an array of non-empty strings";
              values.push_back(*v);
            }
            out = std::move(values);
            return "";
          },
          // As a set: the order in the file does not matter.
          [&out] {
            std::vector<std::string> sorted = out;
            std::sort(sorted.begin(), sorted.end());
            sorted.erase(std::unique(sorted.begin(), sorted.end()), sorted.end());
            std::string joined;
            for (const auto& name : sorted) joined += (joined.empty() ? "" : ",") + name;
            if (sorted.size() <= kMaxListedNames) return "[" + joined + "]";
            return fmt::format("{} names, fnv1a {:016x}", sorted.size(), fnv1a_64(joined));
          }};
}
Binding bind_vector9(Vector9d& out) {
  return {[&out](const toml::node& n) -> std::string {
            const auto* arr = n.as_array();
            if (!arr || arr->size() != 9) {
              return "expected an array of 9 numbers [b1 b2 b3 D11 D22 D33 D12 D13 D23]";
            }
            Vector9d v;
            for (size_t i = 0; i < 9; ++i) {
              auto x = (*arr)[i].value<double>();
              if (!x || !(*arr)[i].is_number() || !std::isfinite(*x) || *x < 0.0) {
                return "expected 9 finite numbers >= 0";
              }
              v(static_cast<int>(i)) = *x;
            }
            out = v;
            return "";
          },
          [&out] {
            std::string shown;
            for (int i = 0; i < 9; ++i) shown += (i == 0 ? "[" : ", ") + show_double(out(i));
            return shown + "]";
          }};
}

std::map<std::string, Section> key_table(DaemonConfig& c) {
  auto& f = c.ukf.filter;
  auto& g = c.gates;
  return {
      {"lcm",
       {{"url", bind(c.lcm.url)},
        {"publish_url", bind(c.lcm.publish_url)},
        {"samples_channel", bind(c.lcm.samples_channel)},
        {"batch_channel", bind(c.lcm.batch_channel)},
        {"calibration_channel", bind(c.lcm.calibration_channel)},
        {"status_channel", bind(c.lcm.status_channel)}}},
      {"storage",
       {{"db_path", bind(c.storage.db_path)},
        {"window_hours", bind(c.storage.window_hours)},
        {"retention_margin_hours", bind(c.storage.retention_margin_hours)},
        {"commit_every_samples", bind(c.storage.commit_every_samples)},
        {"commit_every_ms", bind(c.storage.commit_every_ms)},
        {"busy_timeout_ms", bind(c.storage.busy_timeout_ms)},
        {"max_failure_s", bind(c.storage.max_failure_s)},
        {"max_pending_samples", bind(c.storage.max_pending_samples)},
        {"pg_max_failure_s", bind(c.storage.pg_max_failure_s)},
        {"spill_dir", bind(c.storage.spill_dir)},
        {"spill_max_bytes", bind(c.storage.spill_max_bytes)},
        {"stop_max_failure_s", bind(c.storage.stop_max_failure_s)},
        {"pg_reply_timeout_s", bind(c.storage.pg_reply_timeout_s)}}},
      {"refit",
       {{"daily_at_utc", bind(c.refit.daily_at_utc)},
        {"every_hours", bind(c.refit.every_hours)},
        {"clock", bind(c.refit.clock)},
        {"min_samples", bind(c.refit.min_samples)},
        {"early_growth", bind(c.refit.early_growth)},
        {"robust", bind(c.refit.robust)}}},
      {"ukf",
       {{"sigma_nT", bind(f.sigma_nT)},
        {"snapshot_every_s", bind(c.ukf.snapshot_every_s)},
        {"process_noise", bind_vector9(f.process_noise_per_sqrt_hour)},
        {"alpha", bind(f.alpha)},
        {"beta", bind(f.beta)},
        {"kappa", bind(f.kappa)},
        {"cold_start",
         bind_enum(f.cold_start,
                   std::map<std::string, FilterOptions::ColdStart>{
                       {"data", FilterOptions::ColdStart::kFromData},
                       {"zero", FilterOptions::ColdStart::kZero},
                       {"first_sample_scale", FilterOptions::ColdStart::kFirstSampleScale}})},
        {"initial_bias_sigma_nT", bind(f.initial_bias_sigma_nT)},
        {"initial_D_sigma", bind(f.initial_D_sigma)},
        {"gate_nis", bind(f.gate_nis)},
        {"nis_window", bind(f.nis_window)},
        {"nis_inconsistent_mean", bind(f.nis_inconsistent_mean)},
        {"consistency_action",
         bind_enum(f.consistency_action,
                   std::map<std::string, FilterOptions::ConsistencyAction>{
                       {"inflate", FilterOptions::ConsistencyAction::kInflate},
                       {"reseed", FilterOptions::ConsistencyAction::kReseed}})},
        {"inflation_factor", bind(f.inflation_factor)},
        {"converged_bias_sigma_nT", bind(f.converged_bias_sigma_nT)},
        {"ok_needs_refit", bind(f.ok_needs_model_error)}}},
      {"gates",
       {{"residual_enabled", bind(g.residual_enabled)},
        {"expected_residual_nT", bind(g.expected_residual_nT)},
        {"residual_test", bind_enum(g.residual_test,
                                    std::map<std::string, GateOptions::ResidualTest>{
                                        {"factor", GateOptions::ResidualTest::kFactor},
                                        {"chi_square", GateOptions::ResidualTest::kChiSquare}})},
        {"residual_factor", bind(g.residual_factor)},
        {"residual_tail_probability", bind(g.residual_tail_probability)},
        {"observability_enabled", bind(g.observability_enabled)},
        {"max_fisher_condition", bind(g.max_fisher_condition)},
        {"min_fisher_eigenvalue", bind(g.min_fisher_eigenvalue)},
        {"coverage_enabled", bind(g.coverage_enabled)},
        {"min_coverage_eigenvalue", bind(g.min_coverage_eigenvalue)},
        {"bounds_enabled", bind(g.bounds_enabled)},
        {"max_bias_nT", bind(g.max_bias_nT)},
        {"max_scale", bind(g.max_scale)},
        {"max_nonorthogonality", bind(g.max_nonorthogonality)},
        {"max_alignment_residual_fraction", bind(g.max_alignment_residual_fraction)},
        {"change_enabled", bind(g.change_enabled)},
        {"change_tail_probability", bind(g.change_tail_probability)},
        {"bias_change_floor_nT", bind(g.bias_change_floor_nT)},
        {"D_change_floor", bind(g.D_change_floor)}}},
      {"sensor", {{"range_nT", bind(c.sensor.range_nT)}}},
      {"igrf", {{"coefficients_file", bind(c.igrf.coefficients_file)}}},
      {"log", {{"level", bind(c.log.level)}, {"status_every_s", bind(c.log.status_every_s)}}},
      {"ingest",
       {{"max_time_jump_s", bind(c.ingest.max_time_jump_s)},
        {"max_future_s", bind(c.ingest.max_future_s)}}},
      {"service",
       {{"whitelist", bind_string_list(c.service.whitelist)},
        {"queue_capacity_samples", bind(c.service.queue_capacity_samples)},
        {"status_every_s", bind(c.service.status_every_s)},
        {"min_position_km", bind(c.service.min_position_km)},
        {"max_position_km", bind(c.service.max_position_km)}}},
      {"http", {{"listen", bind(c.http.listen)}}},
      {"station", {{"id", bind(c.station.id)}}},
      {"fleet",
       {{"lease_s", bind(c.fleet.lease_s)}, {"reorder_delay_s", bind(c.fleet.reorder_delay_s)}}},
  };
}

// "" (off) or ADDR:PORT with a port in 0..65535 (binding is checked at start).
std::string check_listen(const std::string& listen) {
  std::string host, error;
  int port = 0;
  if (listen.empty() || http::parse_listen(listen, &host, &port, &error)) return "";
  return "[http] listen: expected \"ADDR:PORT\" (e.g. \"127.0.0.1:9780\", port 0 = any free "
         "one) or \"\" (off), got \"" +
         listen + "\"";
}

// A station id is written into every stored sample and names lease owners in magcal status:
// short, printable, no spaces (it is a label, and a word in logs).
constexpr size_t kMaxStationIdLength = 64;

std::string check_station_id(const std::string& id) {
  const bool printable =
      std::all_of(id.begin(), id.end(), [](char c) { return c > ' ' && c < 127; });
  if (!id.empty() && id.size() <= kMaxStationIdLength && printable) return "";
  std::string shown;
  for (const char c : id.substr(0, kMaxStationIdLength)) shown += c >= ' ' && c < 127 ? c : '?';
  return "[station] id: must be 1-" + std::to_string(kMaxStationIdLength) +
         " printable ASCII characters without spaces (default: the host name), got \"" + shown +
         (id.size() > kMaxStationIdLength ? "...\" (" + std::to_string(id.size()) + " characters)"
                                          : "\"");
}

std::string check_channel(const std::string& key, const std::string& name) {
  if (name.empty() || name.size() > 63) return key + ": channel name must be 1-63 characters";
  return "";
}

// Keys that change no estimate, verdict or stored sample: where data comes from and where it
// goes, how and when it is committed, what an outage may cost, logging, the operations server,
// the station's own name. Every other key affects results (a new key does too, until listed
// here): the owner of a spacecraft applies them, so stations sharing spacecraft must agree.
bool affects_results(const std::string& section, const std::string& key) {
  static const std::set<std::string> kOperationalSections = {"lcm", "log", "http", "station"};
  static const std::set<std::string> kOperationalKeys = {"storage.db_path",
                                                         "storage.retention_margin_hours",
                                                         "storage.commit_every_samples",
                                                         "storage.commit_every_ms",
                                                         "storage.busy_timeout_ms",
                                                         "storage.max_failure_s",
                                                         "storage.max_pending_samples",
                                                         "storage.pg_max_failure_s",
                                                         "storage.spill_dir",
                                                         "storage.spill_max_bytes",
                                                         "storage.stop_max_failure_s",
                                                         "storage.pg_reply_timeout_s",
                                                         "service.queue_capacity_samples",
                                                         "service.status_every_s"};
  return kOperationalSections.count(section) == 0 &&
         kOperationalKeys.count(section + "." + key) == 0;
}

// The IGRF model a station computes the reference field with: its content, not its path (the
// same file may sit elsewhere on another host).
std::string igrf_identity(const std::string& coefficients_file) {
  if (coefficients_file.empty()) return "built-in IGRF-14";
  std::ifstream in(coefficients_file, std::ios::binary);
  std::stringstream content;
  content << in.rdbuf();
  if (!in) return "unreadable " + coefficients_file;
  return fmt::format("file fnv1a {:016x}", fnv1a_64(content.str()));
}

}  // namespace

std::string default_station_id() {
  char name[HOST_NAME_MAX + 1] = {};
  if (::gethostname(name, sizeof name - 1) != 0) return "";
  return name;
}

bool DaemonConfig::postgres() const {
  return storage::is_postgres_uri(storage.db_path);
}

std::string DaemonConfig::spill_path() const {
  if (!postgres() || storage.spill_max_bytes == 0) return "";
  std::string dir = storage.spill_dir;
  if (dir.empty()) {
    const char* state = std::getenv("STATE_DIRECTORY");  // systemd: may list several, ':'
    dir = state != nullptr ? std::string(state).substr(0, std::string(state).find(':')) : ".";
  }
  // The station id is printable ASCII without spaces (check_station_id); '/' and the like
  // must not make a path of it.
  std::string name = "magcal-spill-";
  for (const char ch : station.id)
    name += std::isalnum(static_cast<unsigned char>(ch)) || ch == '-' || ch == '_' || ch == '.'
                ? ch
                : '_';
  return dir + "/" + name + ".spill";
}

std::map<std::string, std::string> DaemonConfig::result_settings() const {
  DaemonConfig copy = *this;  // key_table() binds for writing too
  std::map<std::string, std::string> out;
  for (const auto& [section, keys] : key_table(copy)) {
    for (const auto& [key, binding] : keys) {
      if (affects_results(section, key)) out[section + "." + key] = binding.show();
    }
  }
  out["igrf.coefficients_file"] = igrf_identity(igrf.coefficients_file);
  return out;
}

std::string DaemonConfig::validate() const {
  for (const auto& [key, name] : {std::pair{"[lcm] samples_channel", lcm.samples_channel},
                                  {"[lcm] batch_channel", lcm.batch_channel},
                                  {"[lcm] calibration_channel", lcm.calibration_channel},
                                  {"[lcm] status_channel", lcm.status_channel}}) {
    if (auto e = check_channel(key, name); !e.empty()) return e;
  }
  if (storage.db_path.empty()) return "[storage] db_path: must not be empty";
  // A mistyped URI is a bad value (exit 1), not a database that cannot be opened (exit 2).
  if (const std::string e = storage::database_value_error(storage.db_path); !e.empty()) {
    return "[storage] db_path: " + e;
  }
  if (!(storage.window_hours > 0.0)) return "[storage] window_hours: must be > 0";
  if (!(storage.retention_margin_hours >= 0.0)) {
    return "[storage] retention_margin_hours: must be >= 0";
  }
  if (storage.commit_every_samples < 1) return "[storage] commit_every_samples: must be >= 1";
  if (storage.commit_every_ms < 1) return "[storage] commit_every_ms: must be >= 1";
  if (storage.busy_timeout_ms < 0) return "[storage] busy_timeout_ms: must be >= 0";
  if (!(storage.max_failure_s > 0.0)) return "[storage] max_failure_s: must be > 0";
  if (storage.max_pending_samples < storage.commit_every_samples) {
    return "[storage] max_pending_samples: must be >= commit_every_samples";
  }
  if (!(storage.pg_max_failure_s > 0.0)) return "[storage] pg_max_failure_s: must be > 0";
  if (storage.spill_max_bytes < 0) {
    return "[storage] spill_max_bytes: must be >= 0 (0 = no spill file)";
  }
  if (!(storage.stop_max_failure_s > 0.0)) return "[storage] stop_max_failure_s: must be > 0";
  if (!(storage.pg_reply_timeout_s > 0.0 && storage.pg_reply_timeout_s <= 3600.0)) {
    return "[storage] pg_reply_timeout_s: must be > 0 and at most 3600 (s)";
  }
  // A lock wait must end as a lock timeout (busy_timeout_ms) before it could look like a server
  // that does not answer. (PostgreSQL only: SQLite has no reply deadline.)
  if (postgres() && !(storage.pg_reply_timeout_s * 1000.0 > storage.busy_timeout_ms)) {
    return fmt::format(
        "[storage] pg_reply_timeout_s ({:g} s) must be above busy_timeout_ms ({} ms): a lock "
        "wait must end as a lock timeout before it looks like a server that does not answer",
        storage.pg_reply_timeout_s, storage.busy_timeout_ms);
  }
  if (!parse_daily_time_utc(refit.daily_at_utc)) {
    return "[refit] daily_at_utc: expected \"HH:MM\" (UTC), got \"" + refit.daily_at_utc + "\"";
  }
  if (!(refit.every_hours >= 0.0)) return "[refit] every_hours: must be >= 0 (0 = off)";
  if (refit.every_hours > 0.0 && refit.every_hours < 1.0 / 60.0) {
    return "[refit] every_hours: must be 0 (off) or at least one minute";
  }
  if (refit.clock != "wall" && refit.clock != "data") {
    return "[refit] clock: expected \"wall\" or \"data\", got \"" + refit.clock + "\"";
  }
  if (refit.min_samples < 10) return "[refit] min_samples: must be >= 10";
  if (!(refit.early_growth == 0.0 || (refit.early_growth >= 1.1 && refit.early_growth <= 100.0))) {
    return "[refit] early_growth: must be 0 (only the first refit) or within [1.1, 100]";
  }
  if (auto e = ukf.filter.validate(); !e.empty()) return "[ukf] " + e;
  if (!(ukf.snapshot_every_s > 0.0)) return "[ukf] snapshot_every_s: must be > 0";
  if (auto e = gates.validate(); !e.empty()) return "[gates] " + e;
  if (!(sensor.range_nT > 0.0)) return "[sensor] range_nT: must be > 0";
  static const char* kLevels[] = {"trace", "debug", "info", "warn", "error", "critical", "off"};
  bool level_ok = false;
  for (const char* l : kLevels) level_ok = level_ok || log.level == l;
  if (!level_ok) {
    return "[log] level: expected trace|debug|info|warn|error|critical|off, got \"" + log.level +
           "\"";
  }
  if (!(log.status_every_s > 0.0)) return "[log] status_every_s: must be > 0";
  if (auto e = check_listen(http.listen); !e.empty()) return e;
  if (auto e = check_station_id(station.id); !e.empty()) return e;
  if (!(fleet.lease_s >= 1.0 && fleet.lease_s <= 3600.0)) {
    return "[fleet] lease_s: must be within [1, 3600] s";
  }
  if (!(fleet.reorder_delay_s >= 0.0 && fleet.reorder_delay_s <= 86400.0)) {
    return "[fleet] reorder_delay_s: must be within [0, 86400] s";
  }
  // Bounded so that the microsecond conversions stay far from the int64 limits.
  if (!(ingest.max_time_jump_s >= 1.0 && ingest.max_time_jump_s <= 1e6)) {
    return "[ingest] max_time_jump_s: must be within [1, 1e6] s";
  }
  if (!(ingest.max_future_s >= 0.0 && ingest.max_future_s <= 1e6)) {
    return "[ingest] max_future_s: must be within [0, 1e6] s";
  }
  if (service.queue_capacity_samples < 1000) {
    return "[service] queue_capacity_samples: must be >= 1000";
  }
  if (!(service.status_every_s > 0.0)) return "[service] status_every_s: must be > 0";
  if (!(service.min_position_km > 0.0 && service.max_position_km > service.min_position_km)) {
    return "[service] min_position_km/max_position_km: need 0 < min < max";
  }
  return "";
}

ConfigLoad parse_daemon_config(const std::string& toml_text, const std::string& origin) {
  ConfigLoad out;
  toml::table root;
  try {
    root = toml::parse(toml_text, origin);
  } catch (const toml::parse_error& e) {
    std::ostringstream msg;
    msg << origin << ":" << e.source().begin.line << ": " << e.description();
    out.error = msg.str();
    return out;
  }
  auto table = key_table(out.config);
  for (auto&& [section_key, section_node] : root) {
    const std::string section(section_key.str());
    const auto sit = table.find(section);
    if (sit == table.end()) {
      out.error = origin + ": unknown section [" + section + "]";
      return out;
    }
    const auto* section_table = section_node.as_table();
    if (!section_table) {
      out.error = origin + ": [" + section + "] must be a table";
      return out;
    }
    for (auto&& [key, node] : *section_table) {
      const std::string name(key.str());
      const auto kit = sit->second.find(name);
      if (kit == sit->second.end()) {
        out.error = origin + ": unknown key [" + section + "] " + name;
        return out;
      }
      if (auto e = kit->second.set(node); !e.empty()) {
        out.error = origin + ": [" + section + "] " + name + ": " + e;
        return out;
      }
    }
  }
  if (auto e = out.config.validate(); !e.empty()) out.error = origin + ": " + e;
  return out;
}

ConfigLoad load_daemon_config(const std::string& path) {
  if (path.empty()) {
    ConfigLoad out;
    out.error = out.config.validate();
    return out;
  }
  std::ifstream in(path);
  if (!in) {
    ConfigLoad out;
    out.error = "config " + path + ": cannot open";
    return out;
  }
  std::stringstream ss;
  ss << in.rdbuf();
  return parse_daemon_config(ss.str(), path);
}

}  // namespace magcal
