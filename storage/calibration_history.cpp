#include "storage/calibration_history.hpp"

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <limits>

#include "storage/calibration_row.hpp"
#include "storage/sqlite_stores.hpp"

#ifndef MAGCAL_VERSION
#define MAGCAL_VERSION "unknown"
#endif

namespace magcal::storage {

const char* status_name(int status) {
  switch (status) {
    case 0:
      return "ok";
    case 1:
      return "not_converged";
    case 2:
      return "unobservable";
    case 3:
      return "failed";
    case 4:
      return "rejected";
    default:
      return "unknown";
  }
}

bool is_refit_method(std::string_view method) {
  return method == "centered" || method == "twostep";
}

void CalibrationHistory::append_all(std::span<const CalibrationRecord> records) {
  for (const CalibrationRecord& r : records) append(r);
}

std::optional<CalibrationRecord> CalibrationHistory::latest_refit(std::string_view sat_id) {
  return newest_refit_until(sat_id, std::numeric_limits<int64_t>::max());
}

std::optional<CalibrationRecord> CalibrationHistory::previous_refit(std::string_view sat_id) {
  const auto latest = latest_refit(sat_id);
  if (!latest || latest->utime == std::numeric_limits<int64_t>::min()) return std::nullopt;
  return newest_refit_until(sat_id, latest->utime - 1);
}

std::optional<CalibrationRecord> CalibrationHistory::latest_accepted_refit(
    std::string_view sat_id) {
  return latest_accepted_refit(sat_id, std::numeric_limits<int64_t>::min(), 0);
}

namespace calibration_row {

void check_appendable(const CalibrationRecord& r) {
  if (r.verdict != "accepted" && r.verdict != "rejected") {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "verdict must be 'accepted' or 'rejected', not '" + r.verdict + "'");
  }
  if (r.status < 0 || r.status > 4) {
    throw StorageError(StorageError::Kind::kInvalidArgument,
                       "status out of range: " + std::to_string(r.status));
  }
}

std::string json_string_array(const std::vector<std::string>& items) {
  std::string out = "[";
  for (size_t k = 0; k < items.size(); ++k) {
    if (k) out += ',';
    out += '"';
    for (const char c : items[k]) {
      switch (c) {
        case '"':
          out += "\\\"";
          break;
        case '\\':
          out += "\\\\";
          break;
        case '\n':
          out += "\\n";
          break;
        case '\t':
          out += "\\t";
          break;
        case '\r':
          out += "\\r";
          break;
        default:
          if (static_cast<unsigned char>(c) < 0x20) {
            char buf[8];
            std::snprintf(buf, sizeof buf, "\\u%04x", c);
            out += buf;
          } else {
            out += c;
          }
      }
    }
    out += '"';
  }
  return out + "]";
}

int64_t created_utime(const CalibrationRecord& r) {
  if (r.created_utime != 0) return r.created_utime;
  return std::chrono::duration_cast<std::chrono::microseconds>(
             std::chrono::system_clock::now().time_since_epoch())
      .count();
}

std::string_view software_version(const CalibrationRecord& r) {
  return r.software_version.empty() ? std::string_view(MAGCAL_VERSION)
                                    : std::string_view(r.software_version);
}

}  // namespace calibration_row

namespace {

// calibration_row's sink and row on an SQLite statement.
struct SqliteBinder {
  Statement& st;
  int index = 1;
  void integer(int64_t v) { st.bind(index++, v); }
  void real(double v) { st.bind(index++, v); }  // NaN binds as NULL
  void text(std::string_view v) { st.bind(index++, v); }
  void doubles(std::span<const double> v) { st.bind_blob(index++, v.data(), v.size_bytes()); }
  void null() { st.bind_null(index++); }
};

struct SqliteRow {
  Statement& st;
  bool is_null(int c) const { return st.is_null(c); }
  int64_t integer(int c) const { return st.column_int64(c); }
  double real(int c) const { return st.column_double(c); }
  std::string text(int c) const { return st.column_text(c); }
  bool blob(int c, std::span<double> out, const std::string& what) const {
    if (st.is_null(c)) return false;
    const auto bytes = st.column_blob(c);
    doubles_from_blob(bytes.data(), bytes.size(), out, what);
    return true;
  }
};

}  // namespace

SqliteCalibrationHistory::SqliteCalibrationHistory(Database& db)
    : db_(db),
      insert_(db, insert_sql()),
      query_all_(db, calibration_row::select_sql("WHERE sat_id = ?1 AND utime >= ?2 AND "
                                                 "utime <= ?3 ORDER BY utime DESC, id DESC "
                                                 "LIMIT ?4")),
      query_method_(db, calibration_row::select_sql("WHERE sat_id = ?1 AND utime >= ?2 AND "
                                                    "utime <= ?3 AND method = ?5 ORDER BY utime "
                                                    "DESC, id DESC LIMIT ?4")),
      latest_(db, calibration_row::select_sql(
                      "WHERE sat_id = ?1 AND method = ?2 ORDER BY utime DESC, id DESC LIMIT 1")),
      get_(db, calibration_row::select_sql("WHERE id = ?1")),
      refits_(db, calibration_row::select_sql(std::string("WHERE sat_id = ?1 AND ") +
                                              calibration_row::kRefitMethods +
                                              " AND utime <= ?2 ORDER BY utime DESC, id DESC "
                                              "LIMIT 1")),
      accepted_refit_(db,
                      calibration_row::select_sql(
                          std::string("WHERE sat_id = ?1 AND ") + calibration_row::kRefitMethods +
                          " AND verdict = 'accepted' AND window_end_utime - "
                          "window_start_utime >= ?2 AND n_samples >= ?3 ORDER BY utime DESC, "
                          "id DESC LIMIT 1")),
      spacecraft_(db, "SELECT DISTINCT sat_id FROM calibrations ORDER BY sat_id"),
      reasons_(db, "SELECT value FROM json_each(?1)") {}

std::string SqliteCalibrationHistory::insert_sql() {
  std::string sql =
      std::string("INSERT INTO calibrations (") + calibration_row::kInsertColumns + ") VALUES (";
  for (int i = 1; i <= calibration_row::kInsertValues; ++i) {
    sql += (i > 1 ? ", ?" : "?") + std::to_string(i);
  }
  return sql + ")";
}

int64_t SqliteCalibrationHistory::append(const CalibrationRecord& r) {
  calibration_row::check_appendable(r);
  const std::string reasons = calibration_row::json_string_array(r.rejection_reasons);
  auto use = insert_.use();
  SqliteBinder binder{insert_};
  calibration_row::write(r, reasons, binder);
  insert_.execute();
  return db_.last_insert_id();
}

CalibrationRecord SqliteCalibrationHistory::read_row(Statement& st) {
  SqliteRow row{st};
  return calibration_row::read(row, [this](const std::string& json) {
    std::vector<std::string> out;
    auto use = reasons_.use();
    reasons_.bind(1, json);
    while (reasons_.step()) out.push_back(reasons_.column_text(0));
    return out;
  });
}

std::vector<CalibrationRecord> SqliteCalibrationHistory::rows(Statement& st) {
  std::vector<CalibrationRecord> out;
  while (st.step()) out.push_back(read_row(st));
  return out;
}

std::vector<CalibrationRecord> SqliteCalibrationHistory::query(const HistoryQuery& q) {
  Statement& st = q.method.empty() ? query_all_ : query_method_;
  std::vector<CalibrationRecord> out;
  {
    auto use = st.use();
    st.bind(1, q.sat_id);
    st.bind(2, q.since_utime.value_or(std::numeric_limits<int64_t>::min()));
    st.bind(3, q.until_utime.value_or(std::numeric_limits<int64_t>::max()));
    st.bind(4, q.limit ? static_cast<int64_t>(*q.limit) : int64_t{-1});  // -1: no limit
    if (!q.method.empty()) st.bind(5, q.method);
    out = rows(st);
  }
  // Selected newest first (so LIMIT keeps the newest); printed in the asked order.
  if (!q.descending) std::reverse(out.begin(), out.end());
  return out;
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::first(Statement& st) {
  if (!st.step()) return std::nullopt;
  return read_row(st);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::latest(std::string_view sat_id,
                                                                  std::string_view method) {
  auto use = latest_.use();
  latest_.bind(1, sat_id).bind(2, method);
  return first(latest_);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::get(int64_t id) {
  auto use = get_.use();
  get_.bind(1, id);
  return first(get_);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::newest_refit_until(
    std::string_view sat_id, int64_t until_utime) {
  auto use = refits_.use();
  refits_.bind(1, sat_id).bind(2, until_utime);
  return first(refits_);
}

std::optional<CalibrationRecord> SqliteCalibrationHistory::latest_accepted_refit(
    std::string_view sat_id, int64_t min_window_span_utime, int min_samples) {
  auto use = accepted_refit_.use();
  accepted_refit_.bind(1, sat_id).bind(2, min_window_span_utime).bind(3, int64_t{min_samples});
  return first(accepted_refit_);
}

std::vector<std::string> SqliteCalibrationHistory::spacecraft() {
  std::vector<std::string> out;
  auto use = spacecraft_.use();
  while (spacecraft_.step()) out.push_back(spacecraft_.column_text(0));
  return out;
}

}  // namespace magcal::storage
