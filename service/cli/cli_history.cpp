// `magcal history`: stored calibration results of one spacecraft as an aligned table, CSV or a
// JSON array (design.md). Reads the database read-only (never creates or upgrades a file) and
// works while the daemon writes (WAL snapshot).
//
// JSON objects are service/io/result_json.hpp's keys for the stored fields (the same keys as
// `fit --json`) plus sat_id, id, time / window_start / window_end (ISO 8601 UTC),
// software_version and created_time. CSV has the same fields flat (design.md column names).
#include <charconv>
#include <cstdio>
#include <iostream>
#include <string>
#include <tuple>
#include <vector>

#include <nlohmann/json.hpp>

#include "pipeline/time_utc.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/io/calibration_record.hpp"
#include "service/io/result_json.hpp"
#include "storage/calibration_history.hpp"
#include "storage/database.hpp"
#include "storage/sample_window_store.hpp"

namespace magcal::cli {

namespace {

// Shortest text that reads back to the same double; empty for NaN (absent).
std::string csv_number(double v) {
  if (v != v) return "";
  char buf[32];
  const auto res = std::to_chars(buf, buf + sizeof buf, v);
  return std::string(buf, res.ptr);
}

std::string csv_quoted(const std::string& s) {
  if (s.find_first_of(",\"\n\r") == std::string::npos) return s;
  std::string out = "\"";
  for (const char c : s) {
    if (c == '"') out += '"';
    out += c;
  }
  return out + '"';
}

void print_csv(const std::vector<storage::CalibrationRecord>& rows) {
  std::cout << "time,utime,sat_id,method,window_start,window_end,window_start_utime,"
               "window_end_utime,n_samples,bias_x_nT,bias_y_nT,bias_z_nT,bias_sigma_x_nT,"
               "bias_sigma_y_nT,bias_sigma_z_nT,D11,D22,D33,D12,D13,D23,R11,R12,R13,R21,R22,R23,"
               "R31,R32,R33,residual_rms_nT,iterations,status,verdict,rejection_reasons,"
               "software_version,id,noise_scale,residual_autocorrelation,covariance_lag_window,"
               "residual_rms_all_nT,has_nonlinearity,k3_x,k3_y,k3_z,nis_mean,"
               "measurement_noise_nT\n";
  for (const auto& r : rows) {
    std::string line = history_time(r.utime) + ',' + std::to_string(r.utime) + ',' +
                       csv_quoted(r.sat_id) + ',' + csv_quoted(r.method) + ',' +
                       history_time(r.window_start_utime) + ',' + history_time(r.window_end_utime) +
                       ',' + std::to_string(r.window_start_utime) + ',' +
                       std::to_string(r.window_end_utime) + ',' + std::to_string(r.n_samples);
    for (const double v : r.bias_nT) line += ',' + csv_number(v);
    for (const double v : r.bias_sigma_nT) line += ',' + csv_number(v);
    for (const double v : r.D) line += ',' + csv_number(v);
    for (const double v : r.R_sensor_from_body) {
      line += ',' + (r.has_alignment ? csv_number(v) : std::string());
    }
    std::string reasons;
    for (const auto& reason : r.rejection_reasons)
      reasons += (reasons.empty() ? "" : "; ") + reason;
    line += ',' + csv_number(r.residual_rms_nT) + ',' + std::to_string(r.iterations) + ',' +
            storage::status_name(r.status) + ',' + r.verdict + ',' + csv_quoted(reasons) + ',' +
            csv_quoted(r.software_version) + ',' + std::to_string(r.id);
    // Issue 10 evidence, appended after the design.md columns (empty = unknown).
    line += ',' + csv_number(r.noise_scale) + ',' + csv_number(r.residual_autocorrelation) + ',' +
            (r.covariance_lag_window >= 0 ? std::to_string(r.covariance_lag_window) : "") + ',' +
            csv_number(r.residual_rms_all_nT) + ',' +
            (r.has_nonlinearity >= 0 ? std::to_string(r.has_nonlinearity) : "");
    for (const double v : r.k3) line += ',' + (r.has_nonlinearity == 1 ? csv_number(v) : "");
    line += ',' + csv_number(r.nis_mean) + ',' + csv_number(r.measurement_noise_nT);
    std::cout << line << '\n';
  }
}

void print_table(const std::vector<storage::CalibrationRecord>& rows) {
  std::printf("%-20s  %-8s  %6s  %27s  %20s  %8s  %-13s  %s\n", "time (UTC)", "method", "n",
              "bias x, y, z (nT)", "1-sigma (nT)", "rms (nT)", "status", "verdict");
  for (const auto& r : rows) {
    std::printf("%-20s  %-8s  %6d  %8.2f %8.2f %9.2f  %6.2f %6.2f %6.2f  %8.3f  %-13s  %s",
                format_iso8601_utc(r.utime).c_str(), r.method.c_str(), r.n_samples, r.bias_nT[0],
                r.bias_nT[1], r.bias_nT[2], r.bias_sigma_nT[0], r.bias_sigma_nT[1],
                r.bias_sigma_nT[2], r.residual_rms_nT, storage::status_name(r.status),
                r.verdict.c_str());
    for (size_t k = 0; k < r.rejection_reasons.size(); ++k) {
      std::printf("%s%s", k == 0 ? ": " : "; ", r.rejection_reasons[k].c_str());
    }
    std::printf("\n");
  }
}

bool known_method(const std::string& m) {
  return m == "ukf" || m == "ekf" || m == "centered" || m == "twostep";
}

}  // namespace

int run_history(const HistoryArgs& args) {
  storage::HistoryQuery q;
  q.sat_id = args.sat;
  if (!args.method.empty() && !known_method(args.method)) {
    std::cerr << "magcal history: unknown --method '" << args.method
              << "' (ukf, ekf, centered, twostep)\n";
    return kExitUsage;
  }
  q.method = args.method;
  for (auto [text, out, name] : {std::tuple{&args.since, &q.since_utime, "--since"},
                                 std::tuple{&args.until, &q.until_utime, "--until"}}) {
    if (text->empty()) continue;
    *out = parse_iso8601_utc(*text);
    if (!*out) {
      std::cerr << "magcal history: " << name << " '" << *text
                << "' is not an ISO 8601 UTC time (e.g. 2026-01-01T12:00:00Z)\n";
      return kExitUsage;
    }
  }
  if (args.limit && *args.limit <= 0) {
    std::cerr << "magcal history: --limit must be positive\n";
    return kExitUsage;
  }
  if (args.order != "asc" && args.order != "desc") {
    std::cerr << "magcal history: --order must be asc or desc\n";
    return kExitUsage;
  }
  if (args.format != "table" && args.format != "csv" && args.format != "json") {
    std::cerr << "magcal history: --format must be table, csv or json\n";
    return kExitUsage;
  }
  q.limit = args.limit;
  q.descending = args.order == "desc";

  std::vector<storage::CalibrationRecord> rows;
  try {
    storage::OpenOptions options;
    options.read_only = true;
    storage::Database db(args.db, options);
    storage::Transaction snapshot(db, storage::Transaction::Mode::kDeferred);
    storage::CalibrationHistory history(db);
    rows = history.query(q);
    if (rows.empty()) {
      // Unknown spacecraft (nothing stored at all): a note, not an error.
      storage::HistoryQuery any;
      any.sat_id = args.sat;
      any.limit = 1;
      storage::SampleWindowStore samples(db);
      if (history.query(any).empty() && !samples.newest_utime(args.sat)) {
        std::cerr << "magcal history: no data for spacecraft '" << args.sat << "' in " << args.db
                  << "\n";
        return kExitOk;
      }
    }
  } catch (const storage::StorageError& e) {
    std::cerr << "magcal history: " << e.what() << "\n";
    return kExitData;
  }

  if (args.format == "json") {
    nlohmann::json out = nlohmann::json::array();
    for (const auto& r : rows) out.push_back(history_record_json(r));
    std::cout << out.dump(2) << "\n";
  } else if (args.format == "csv") {
    print_csv(rows);
  } else if (rows.empty()) {
    std::cerr << "magcal history: no results for '" << args.sat << "' with these filters\n";
  } else {
    print_table(rows);
  }
  return kExitOk;
}

}  // namespace magcal::cli
