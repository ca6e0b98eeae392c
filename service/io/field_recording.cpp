#include "service/io/field_recording.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <fstream>

#include "pipeline/time_utc.hpp"
#include "service/io/csv_line.hpp"

namespace magcal {
namespace {

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

std::string trim(const std::string& s) {
  const auto b = s.find_first_not_of(" \t\r\"");
  if (b == std::string::npos) return {};
  const auto e = s.find_last_not_of(" \t\r\"");
  return s.substr(b, e - b + 1);
}

// The cells of a CSV line, without the blanks and double quotes around them.
std::vector<std::string> split_csv(const std::string& line) {
  std::vector<std::string> out;
  if (line.empty()) return out;
  for (const std::string_view cell : split_csv_line(line)) out.push_back(trim(std::string(cell)));
  return out;
}

// Index of the first header cell matching `explicit_name` (if given) or any alias
// (case-insensitive); -1 when absent.
int find_column(const std::vector<std::string>& header, const std::string& explicit_name,
                std::initializer_list<const char*> aliases) {
  for (size_t i = 0; i < header.size(); ++i) {
    const std::string h = lower(header[i]);
    if (!explicit_name.empty()) {
      if (h == lower(explicit_name)) return static_cast<int>(i);
      continue;
    }
    for (const char* a : aliases)
      if (h == a) return static_cast<int>(i);
  }
  return -1;
}

std::optional<FieldUnit> unit_from_column_name(const std::string& name) {
  const std::string n = lower(name);
  const auto ends_with = [&](const char* suffix) {
    const std::string s(suffix);
    return n.size() > s.size() && n.compare(n.size() - s.size(), s.size(), s) == 0;
  };
  if (ends_with("_nt")) return FieldUnit::kNanoTesla;
  if (ends_with("_ut")) return FieldUnit::kMicroTesla;
  if (ends_with("_mg")) return FieldUnit::kMilliGauss;
  if (ends_with("_g")) return FieldUnit::kGauss;
  return std::nullopt;
}

bool parse_double(const std::string& s, double* out) {
  if (s.empty()) return false;
  const std::string l = lower(s);
  if (l == "nan") {
    *out = std::nan("");
    return true;
  }
  const char* first = s.data();
  const char* last = s.data() + s.size();
  if (*first == '+') ++first;
  const auto [ptr, ec] = std::from_chars(first, last, *out);
  return ec == std::errc() && ptr == last;
}

const char* unit_name(FieldUnit u) {
  switch (u) {
    case FieldUnit::kNanoTesla:
      return "nT";
    case FieldUnit::kMicroTesla:
      return "uT";
    case FieldUnit::kGauss:
      return "G";
    case FieldUnit::kMilliGauss:
      return "mG";
  }
  return "?";
}

}  // namespace

std::optional<FieldUnit> parse_field_unit(const std::string& text) {
  if (text == "nT") return FieldUnit::kNanoTesla;
  if (text == "uT" || text == "µT") return FieldUnit::kMicroTesla;
  if (text == "G") return FieldUnit::kGauss;
  if (text == "mG") return FieldUnit::kMilliGauss;
  return std::nullopt;
}

double nanotesla_per_unit(FieldUnit unit) {
  switch (unit) {
    case FieldUnit::kNanoTesla:
      return 1.0;
    case FieldUnit::kMicroTesla:
      return 1e3;
    case FieldUnit::kGauss:
      return 1e5;  // 1 G = 1e-4 T = 1e5 nT
    case FieldUnit::kMilliGauss:
      return 1e2;
  }
  return 1.0;
}

bool is_design_sample_csv_header(const std::string& header_line) {
  const auto h = split_csv(header_line);
  for (const char* name : {"t_s", "bx_nT", "by_nT", "bz_nT", "hx_nT", "hy_nT", "hz_nT"})
    if (std::find(h.begin(), h.end(), name) == h.end()) return false;
  return true;
}

namespace {

// The columns of a recording CSV (-1: absent), by name (options) or by the usual spellings.
struct RecordingColumns {
  int time, lat, lon, alt, bx, by, bz, qw, qx, qy, qz;
};

RecordingColumns find_recording_columns(const std::vector<std::string>& header,
                                        const FieldRecordingOptions& options) {
  RecordingColumns c;
  c.time = find_column(header, options.time_column,
                       {"date/time", "datetime", "time", "t_s", "utc", "timestamp"});
  c.lat = find_column(header, options.latitude_column, {"latitude", "lat", "lat_deg"});
  c.lon = find_column(header, options.longitude_column, {"longitude", "lon", "lon_deg"});
  c.alt = find_column(header, options.altitude_column,
                      {"altitude", "alt", "alt_km", "altitude_km", "elevation"});
  c.bx = find_column(header, options.bx_column,
                     {"magx", "mag_x", "mag_x_ut", "mag_x_nt", "bx", "bx_nt", "bx_ut"});
  c.by = find_column(header, options.by_column,
                     {"magy", "mag_y", "mag_y_ut", "mag_y_nt", "by", "by_nt", "by_ut"});
  c.bz = find_column(header, options.bz_column,
                     {"magz", "mag_z", "mag_z_ut", "mag_z_nt", "bz", "bz_nt", "bz_ut"});
  c.qw = find_column(header, "", {"q_w", "qw"});
  c.qx = find_column(header, "", {"q_x", "qx"});
  c.qy = find_column(header, "", {"q_y", "qy"});
  c.qz = find_column(header, "", {"q_z", "qz"});
  return c;
}

}  // namespace

std::optional<FieldRecording> read_field_recording(const std::string& path,
                                                   const FieldRecordingOptions& options,
                                                   std::string* error) {
  const auto fail = [&](const std::string& msg) -> std::optional<FieldRecording> {
    if (error) *error = path + ": " + msg;
    return std::nullopt;
  };
  std::ifstream in(path);
  if (!in) return fail("cannot open file");
  std::string line;
  if (!std::getline(in, line)) return fail("empty file (a header row is required)");
  const auto header = split_csv(line);

  const RecordingColumns c = find_recording_columns(header, options);
  if (c.time < 0) return fail("no time column (expected Date/Time, time or t_s)");
  if (c.bx < 0 || c.by < 0 || c.bz < 0)
    return fail("no magnetometer columns (expected MagX/MagY/MagZ, mag_x_uT.. or bx_nT..)");
  if ((c.lat < 0) != (c.lon < 0)) return fail("latitude and longitude must come together");

  FieldRecording rec;
  rec.has_position_columns = c.lat >= 0;
  rec.has_quaternion_columns = c.qw >= 0 && c.qx >= 0 && c.qy >= 0 && c.qz >= 0;
  rec.time_column = header[static_cast<size_t>(c.time)];
  if (rec.has_position_columns && c.alt < 0 && !options.altitude_km)
    return fail("the file has no altitude column: give the altitude (e.g. --alt-km 420)");

  std::optional<FieldUnit> unit = options.field_unit;
  if (!unit) unit = unit_from_column_name(header[static_cast<size_t>(c.bx)]);
  if (!unit)
    return fail("the field unit is not in the column name '" + header[static_cast<size_t>(c.bx)] +
                "': give it (--field-unit uT|nT|G|mG)");
  rec.field_unit_name = unit_name(*unit);
  const double scale = nanotesla_per_unit(*unit);
  const bool time_is_seconds = lower(rec.time_column) == "t_s";

  int line_no = 1;
  int data_row = 0;
  while (std::getline(in, line)) {
    ++line_no;
    if (trim(line).empty()) continue;
    if (data_row++ < options.skip_first) {
      ++rec.n_skipped_first;
      continue;
    }
    const auto cells = split_csv(line);
    const auto cell = [&](int c) -> const std::string& {
      static const std::string empty;
      return c >= 0 && static_cast<size_t>(c) < cells.size() ? cells[static_cast<size_t>(c)]
                                                             : empty;
    };
    const auto number = [&](int c, const char* what, double* out) -> bool {
      if (parse_double(cell(c), out)) return true;
      if (error)
        *error = path + ":" + std::to_string(line_no) + ": bad " + what + " '" + cell(c) + "'";
      return false;
    };

    FieldRecordingRow row;
    if (time_is_seconds) {
      double t_s = 0.0;
      if (!number(c.time, "time", &t_s) || !std::isfinite(t_s)) return std::nullopt;
      row.utime = utime_from_seconds(t_s);
    } else {
      const auto t = parse_iso8601_utc(cell(c.time));
      if (!t) return fail("line " + std::to_string(line_no) + ": bad time '" + cell(c.time) + "'");
      row.utime = *t;
    }
    for (int axis = 0; axis < 3; ++axis) {
      double v = 0.0;
      if (!number(axis == 0 ? c.bx : axis == 1 ? c.by : c.bz, "field value", &v))
        return std::nullopt;
      row.b_sensor_nT(axis) = v * scale;
    }
    if (rec.has_position_columns) {
      row.has_position = true;
      if (!number(c.lat, "latitude", &row.latitude_deg)) return std::nullopt;
      if (!number(c.lon, "longitude", &row.longitude_deg)) return std::nullopt;
      if (c.alt >= 0) {
        if (!number(c.alt, "altitude", &row.altitude_km)) return std::nullopt;
      } else {
        row.altitude_km = *options.altitude_km;
      }
    }
    if (!row.b_sensor_nT.allFinite() || (row.has_position && !(std::isfinite(row.latitude_deg) &&
                                                               std::isfinite(row.longitude_deg) &&
                                                               std::isfinite(row.altitude_km)))) {
      ++rec.n_rejected_non_finite;
      continue;
    }
    if (rec.has_quaternion_columns) {
      QuaternionWxyz q;
      bool ok = true;
      const int cols[4] = {c.qw, c.qx, c.qy, c.qz};
      for (int i = 0; i < 4; ++i) ok = number(cols[i], "quaternion", &q(i)) && ok;
      if (!ok) return std::nullopt;
      if (q.allFinite() && q.norm() > 0.5) {
        row.has_quaternion = true;
        row.q_file = q.normalized();
      } else {
        ++rec.n_missing_quaternion;
      }
    }
    rec.rows.push_back(row);
  }
  if (rec.rows.empty()) return fail("no data rows");
  return rec;
}

}  // namespace magcal
