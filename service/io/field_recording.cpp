#include "service/io/field_recording.hpp"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <string_view>
#include <utility>

#include <fmt/format.h>
#include <fmt/ranges.h>

#include "pipeline/frames.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/reference_field.hpp"
#include "service/io/sample_checks.hpp"

namespace magcal {
namespace {

std::string lower(std::string s) {
  std::transform(s.begin(), s.end(), s.begin(), [](unsigned char c) { return std::tolower(c); });
  return s;
}

// A header cell split into the name the table compares (lower case, blanks and '-' as '_') and
// the unit written in parentheses or brackets after it ("Bx (uT)" -> "bx", "ut").
struct HeaderName {
  std::string name;
  std::string unit;
};

HeaderName header_name(const std::string& cell) {
  HeaderName h;
  std::string text = cell;
  const size_t open = text.find_last_of("([");
  if (open != std::string::npos && open > 0 && (text.back() == ')' || text.back() == ']')) {
    h.unit = lower(text.substr(open + 1, text.size() - open - 2));
    text.erase(open);
  }
  while (!text.empty() && (text.back() == ' ' || text.back() == '\t')) text.pop_back();
  for (char& c : text)
    if (c == ' ' || c == '-') c = '_';
  h.name = lower(text);
  return h;
}

// The field unit a (lower-case) unit text names.
std::optional<FieldUnit> unit_from_text(const std::string& unit) {
  if (unit == "nt") return FieldUnit::kNanoTesla;
  if (unit == "ut" || unit == "\xc2\xb5t" || unit == "\xce\xbct") return FieldUnit::kMicroTesla;
  if (unit == "mg") return FieldUnit::kMilliGauss;
  if (unit == "g" || unit == "gauss") return FieldUnit::kGauss;
  return std::nullopt;
}

// A field column's name without its unit suffix ("mag_x_ut" -> "mag_x", unit uT).
std::string strip_field_unit_suffix(const std::string& name, std::optional<FieldUnit>* unit) {
  static constexpr std::pair<std::string_view, FieldUnit> kSuffixes[] = {
      {"_nt", FieldUnit::kNanoTesla},
      {"_ut", FieldUnit::kMicroTesla},
      {"_\xc2\xb5t", FieldUnit::kMicroTesla},
      {"_mg", FieldUnit::kMilliGauss},
      {"_g", FieldUnit::kGauss}};
  const std::string_view text(name);
  for (const auto& [suffix, suffix_unit] : kSuffixes) {
    if (text.size() > suffix.size() && text.substr(text.size() - suffix.size()) == suffix) {
      *unit = suffix_unit;
      return std::string(text.substr(0, text.size() - suffix.size()));
    }
  }
  return name;
}

bool is_field_column(RecordingColumn c) {
  return c >= RecordingColumn::kBx && c <= RecordingColumn::kHz;
}

// What a value cell holds: a finite number, a missing reading (empty or not finite: the row
// rules drop its row) or something else (an error).
enum class Cell { kNumber, kMissing, kBad };

Cell parse_cell(std::string text, char separator, double* out) {
  if (text.empty()) return Cell::kMissing;
  // `;`-separated exports (European locales) write a decimal comma.
  if (separator == ';') std::replace(text.begin(), text.end(), ',', '.');
  const char* first = text.data();
  const char* last = text.data() + text.size();
  if (*first == '+') ++first;
  const auto [ptr, ec] = std::from_chars(first, last, *out);
  if (ec != std::errc() || ptr != last) return Cell::kBad;
  return std::isfinite(*out) ? Cell::kNumber : Cell::kMissing;
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

// True when an ISO 8601 time names its zone (Z or an offset after the time of day).
bool iso_time_has_zone(const std::string& text) {
  if (text.size() <= 10) return false;
  const std::string clock = text.substr(10);
  return clock.find_first_of("Zz+") != std::string::npos || clock.find('-') != std::string::npos;
}

}  // namespace

std::optional<FieldUnit> parse_field_unit(const std::string& text) {
  if (text == "mG" || text == "mg") return FieldUnit::kMilliGauss;
  return unit_from_text(lower(text));
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

const std::vector<RecordingColumnSpec>& recording_column_table() {
  using C = RecordingColumn;
  static const std::vector<RecordingColumnSpec> table = {
      {C::kTime,
       {"t_s", "time", "t", "date/time", "datetime", "date_time", "time_utc", "utc", "timestamp",
        "epoch"},
       "s or ISO 8601",
       "t_s: seconds since 1970-01-01T00:00:00Z; any other name: ISO 8601 text (a time without "
       "Z or +hh:mm is taken as UTC, and fit says so unless the header says UTC)"},
      {C::kBx, {"bx", "b_x", "magx", "mag_x"}, "nT|uT|G|mG", "measured field, sensor frame"},
      {C::kBy, {"by", "b_y", "magy", "mag_y"}, "nT|uT|G|mG", ""},
      {C::kBz, {"bz", "b_z", "magz", "mag_z"}, "nT|uT|G|mG", ""},
      {C::kHx,
       {"hx", "h_x", "ref_x", "b_ref_x"},
       "nT|uT|G|mG",
       "reference field, body frame (optional)"},
      {C::kHy, {"hy", "h_y", "ref_y", "b_ref_y"}, "nT|uT|G|mG", ""},
      {C::kHz, {"hz", "h_z", "ref_z", "b_ref_z"}, "nT|uT|G|mG", ""},
      {C::kLatitude,
       {"latitude", "lat", "lat_deg", "latitude_deg"},
       "deg",
       "geodetic latitude, WGS-84 (optional position)"},
      {C::kLongitude,
       {"longitude", "lon", "lng", "lon_deg", "longitude_deg"},
       "deg",
       "east longitude"},
      {C::kAltitude,
       {"altitude", "alt", "alt_km", "altitude_km", "elevation", "height", "alt_m", "altitude_m"},
       "km (m with _m or (m))",
       "above the ellipsoid; none: --alt-km"},
      {C::kRx,
       {"r_ecef_x_m", "ecef_x_m", "x_ecef_m", "r_ecef_x", "ecef_x"},
       "m",
       "position, ECEF/ITRF (optional, instead of latitude/longitude)"},
      {C::kRy, {"r_ecef_y_m", "ecef_y_m", "y_ecef_m", "r_ecef_y", "ecef_y"}, "m", ""},
      {C::kRz, {"r_ecef_z_m", "ecef_z_m", "z_ecef_m", "r_ecef_z", "ecef_z"}, "m", ""},
      {C::kQw,
       {"qw", "q_w", "q0", "q_0"},
       "-",
       "attitude q_body_from_eci, scalar first (optional): h_body = A(q) B_eci"},
      {C::kQx, {"qx", "q_x", "q1", "q_1"}, "-", ""},
      {C::kQy, {"qy", "q_y", "q2", "q_2"}, "-", ""},
      {C::kQz, {"qz", "q_z", "q3", "q_3"}, "-", ""},
      {C::kTemperature,
       {"temperature_c", "temp_c", "temperature", "temp", "sensor_temperature_c", "mag_temp_c"},
       "degC",
       "sensor temperature (optional; empty or NaN = unknown): the bias temperature model"},
  };
  return table;
}

std::string recording_column_table_text() {
  std::string out;
  for (const RecordingColumnSpec& spec : recording_column_table()) {
    const std::string names = fmt::format("{}", fmt::join(spec.names, " "));
    out += fmt::format("  {:<54} {:<14} {}\n", names, spec.unit, spec.meaning);
  }
  return out;
}

bool is_design_sample_csv_header(const std::vector<std::string>& header) {
  for (const char* name : {"t_s", "bx_nT", "by_nT", "bz_nT", "hx_nT", "hy_nT", "hz_nT"})
    if (std::find(header.begin(), header.end(), name) == header.end()) return false;
  return true;
}

bool is_design_sample_csv_header(const std::string& header_line) {
  return is_design_sample_csv_header(
      split_csv_line(header_line, detect_csv_separator(header_line)));
}

namespace {

// Where each table column is in the header (-1: absent), with the unit its name gave.
struct RecordingColumns {
  std::array<int, kRecordingColumnCount> index{};
  std::array<std::optional<FieldUnit>, kRecordingColumnCount> field_unit{};
  std::array<std::string, kRecordingColumnCount> unit_text{};
  int at(RecordingColumn c) const { return index[static_cast<size_t>(c)]; }
};

// The explicit name an option gives a column ("" when none).
const std::string& explicit_name(RecordingColumn c, const FieldRecordingOptions& o) {
  static const std::string none;
  switch (c) {
    case RecordingColumn::kTime:
      return o.time_column;
    case RecordingColumn::kLatitude:
      return o.latitude_column;
    case RecordingColumn::kLongitude:
      return o.longitude_column;
    case RecordingColumn::kAltitude:
      return o.altitude_column;
    case RecordingColumn::kBx:
      return o.bx_column;
    case RecordingColumn::kBy:
      return o.by_column;
    case RecordingColumn::kBz:
      return o.bz_column;
    default:
      return none;
  }
}

RecordingColumns find_recording_columns(const std::vector<std::string>& header,
                                        const FieldRecordingOptions& options) {
  RecordingColumns c;
  c.index.fill(-1);
  std::vector<HeaderName> names;
  for (const std::string& cell : header) names.push_back(header_name(cell));
  for (const RecordingColumnSpec& spec : recording_column_table()) {
    const size_t k = static_cast<size_t>(spec.column);
    const std::string& given = explicit_name(spec.column, options);
    for (size_t i = 0; i < names.size() && c.index[k] < 0; ++i) {
      if (std::find(c.index.begin(), c.index.end(), static_cast<int>(i)) != c.index.end())
        continue;  // one column, one meaning
      std::optional<FieldUnit> unit = unit_from_text(names[i].unit);
      std::string name = names[i].name;
      if (is_field_column(spec.column)) name = strip_field_unit_suffix(name, &unit);
      const bool match = !given.empty()
                             ? lower(header[i]) == lower(given) || names[i].name == lower(given)
                             : std::any_of(spec.names.begin(), spec.names.end(),
                                           [&](const char* alias) { return name == alias; });
      if (!match) continue;
      c.index[k] = static_cast<int>(i);
      c.field_unit[k] = unit;
      c.unit_text[k] = names[i].unit;
    }
  }
  return c;
}

// A row as read, with its file line (for the row rules' messages).
struct ReadRow {
  FieldRecordingRow row;
  int line = 0;
};

bool same_values(const FieldRecordingRow& a, const FieldRecordingRow& b) {
  const auto same_number = [](double x, double y) {
    return x == y || (std::isnan(x) && std::isnan(y));
  };
  return a.b_sensor_nT == b.b_sensor_nT && a.has_reference == b.has_reference &&
         a.h_body_nT == b.h_body_nT && a.has_position == b.has_position &&
         a.r_ecef_m == b.r_ecef_m && a.has_quaternion == b.has_quaternion && a.q_file == b.q_file &&
         same_number(a.temperature_C, b.temperature_C);
}

}  // namespace

std::optional<FieldRecording> read_field_recording(const std::string& path,
                                                   const FieldRecordingOptions& options,
                                                   std::string* error) {
  CsvTable table;
  if (std::string e = read_csv_table(path, &table); !e.empty()) {
    if (error) *error = e;
    return std::nullopt;
  }
  return read_field_recording(table, options, error);
}

std::optional<FieldRecording> read_field_recording(const CsvTable& table,
                                                   const FieldRecordingOptions& options,
                                                   std::string* error) {
  const std::string& path = table.source;
  const auto fail = [&](const std::string& msg) -> std::optional<FieldRecording> {
    if (error) *error = path + ": " + msg;
    return std::nullopt;
  };
  const auto& header = table.header;
  using C = RecordingColumn;
  const RecordingColumns c = find_recording_columns(header, options);
  const auto has = [&](C col) { return c.at(col) >= 0; };
  if (!has(C::kTime))
    return fail(
        "no time column (expected t_s in seconds since 1970, or time, timestamp, Date/Time, "
        "time_utc with ISO 8601 text; see magcal fit --help)");
  if (!has(C::kBx) || !has(C::kBy) || !has(C::kBz))
    return fail(
        "no magnetometer columns (expected bx/by/bz, MagX/MagY/MagZ or mag_x..mag_z, with the "
        "unit as a suffix _nT or in parentheses: bx_nT, \"Bx (uT)\"; see magcal fit --help)");
  if (has(C::kLatitude) != has(C::kLongitude))
    return fail("latitude and longitude must come together");
  const bool has_geodetic = has(C::kLatitude);
  const bool has_ecef = has(C::kRx) && has(C::kRy) && has(C::kRz);
  const bool has_h = has(C::kHx) && has(C::kHy) && has(C::kHz);

  FieldRecording rec;
  rec.source = path;
  rec.has_reference_columns = has_h;
  rec.has_position_columns = has_geodetic || has_ecef;
  rec.has_quaternion_columns = has(C::kQw) && has(C::kQx) && has(C::kQy) && has(C::kQz);
  rec.has_temperature_column = has(C::kTemperature);
  rec.time_column = header[static_cast<size_t>(c.at(C::kTime))];
  if (has_geodetic && !has_ecef && !has(C::kAltitude) && !options.altitude_km)
    return fail("the file has no altitude column: give the altitude (e.g. --alt-km 420)");

  // Columns a row of the table took, in table order; the rest are named as ignored. Partial
  // groups (two of three axes) are not used.
  std::vector<bool> used(header.size(), false);
  const auto use = [&](C col) {
    if (has(col)) used[static_cast<size_t>(c.at(col))] = true;
  };
  for (C col : {C::kTime, C::kBx, C::kBy, C::kBz}) use(col);
  if (has_h)
    for (C col : {C::kHx, C::kHy, C::kHz}) use(col);
  if (has_ecef)
    for (C col : {C::kRx, C::kRy, C::kRz}) use(col);
  else if (has_geodetic)
    for (C col : {C::kLatitude, C::kLongitude, C::kAltitude}) use(col);
  if (rec.has_quaternion_columns)
    for (C col : {C::kQw, C::kQx, C::kQy, C::kQz}) use(col);
  use(C::kTemperature);
  for (const RecordingColumnSpec& spec : recording_column_table())
    if (has(spec.column) && used[static_cast<size_t>(c.at(spec.column))])
      rec.used_columns.push_back(header[static_cast<size_t>(c.at(spec.column))]);
  for (size_t i = 0; i < header.size(); ++i)
    if (!used[i]) rec.ignored_columns.push_back(header[i]);

  std::optional<FieldUnit> unit = options.field_unit;
  if (!unit) unit = c.field_unit[static_cast<size_t>(C::kBx)];
  if (!unit)
    return fail("the field unit is not in the column name '" +
                header[static_cast<size_t>(c.at(C::kBx))] +
                "': name it (bx_nT, \"Bx (uT)\") or give it (--field-unit uT|nT|G|mG)");
  rec.field_unit_name = unit_name(*unit);
  const double scale = nanotesla_per_unit(*unit);
  std::optional<FieldUnit> h_unit = has_h ? c.field_unit[static_cast<size_t>(C::kHx)] : unit;
  if (!h_unit) h_unit = unit;
  const double h_scale = nanotesla_per_unit(*h_unit);
  const HeaderName time_name = header_name(rec.time_column);
  const bool time_is_seconds = time_name.name == "t_s" || time_name.unit == "s";
  const bool header_says_utc = time_name.unit == "utc" || time_name.unit == "z" ||
                               time_name.name.find("utc") != std::string::npos;
  const std::string& alt_unit = c.unit_text[static_cast<size_t>(C::kAltitude)];
  const std::string alt_name =
      has(C::kAltitude) ? header_name(header[static_cast<size_t>(c.at(C::kAltitude))]).name : "";
  const double alt_km_per_unit =
      alt_unit == "m" ||
              (alt_name.size() > 2 && alt_name.compare(alt_name.size() - 2, 2, "_m") == 0)
          ? 1e-3
          : 1.0;

  std::vector<ReadRow> rows;
  rows.reserve(table.rows.size());
  int data_row = 0;
  for (const CsvTable::Row& table_row : table.rows) {
    const int line_no = table_row.line;
    if (data_row++ < options.skip_first) {
      ++rec.n_skipped_first;
      continue;
    }
    const auto& cells = table_row.cells;
    const auto cell = [&](C col) -> const std::string& {
      static const std::string empty;
      const int i = c.at(col);
      return i >= 0 && static_cast<size_t>(i) < cells.size() ? cells[static_cast<size_t>(i)]
                                                             : empty;
    };
    std::string bad;  // the first unreadable value, named in the error
    bool missing = false;
    const auto number = [&](C col, const char* what) -> double {
      double v = std::nan("");
      const Cell kind = parse_cell(cell(col), table.separator, &v);
      if (kind == Cell::kMissing) missing = true;
      if (kind == Cell::kBad && bad.empty()) bad = fmt::format("bad {} '{}'", what, cell(col));
      return v;
    };
    const auto line_error = [&](const std::string& what) {
      return fail(fmt::format("line {}: {}", line_no, what));
    };

    FieldRecordingRow row;
    const std::string& time_text = cell(C::kTime);
    if (time_is_seconds) {
      const double t_s = number(C::kTime, "time");
      if (bad.empty() && !missing) row.utime = utime_from_seconds(t_s);
    } else if (time_text.empty()) {
      missing = true;
    } else if (const auto t = parse_iso8601_utc(time_text)) {
      row.utime = *t;
      if (!header_says_utc && !iso_time_has_zone(time_text)) ++rec.n_times_without_zone;
    } else {
      double seconds = 0.0;
      if (parse_cell(time_text, table.separator, &seconds) == Cell::kNumber)
        return line_error("bad time '" + time_text +
                          "': ISO 8601 expected (name the column t_s "
                          "for seconds since 1970-01-01T00:00:00Z)");
      return line_error("bad time '" + time_text +
                        "' (ISO 8601 expected, e.g. 2024-03-01T12:00:00Z)");
    }
    row.b_sensor_nT = Eigen::Vector3d(number(C::kBx, "field value"), number(C::kBy, "field value"),
                                      number(C::kBz, "field value")) *
                      scale;
    if (has_h) {
      row.has_reference = true;
      row.h_body_nT =
          Eigen::Vector3d(number(C::kHx, "reference value"), number(C::kHy, "reference value"),
                          number(C::kHz, "reference value")) *
          h_scale;
    }
    if (has_ecef) {
      row.has_position = true;
      row.r_ecef_m = Eigen::Vector3d(number(C::kRx, "position"), number(C::kRy, "position"),
                                     number(C::kRz, "position"));
      if (row.r_ecef_m.allFinite()) {
        const GeodeticPosition g = geodetic_from_ecef(row.r_ecef_m);
        row.latitude_deg = g.latitude_rad * kRadToDeg;
        row.longitude_deg = g.longitude_rad * kRadToDeg;
        row.altitude_km = g.altitude_m * 1e-3;
      }
    } else if (has_geodetic) {
      row.has_position = true;
      row.latitude_deg = number(C::kLatitude, "latitude");
      row.longitude_deg = number(C::kLongitude, "longitude");
      row.altitude_km = has(C::kAltitude) ? number(C::kAltitude, "altitude") * alt_km_per_unit
                                          : *options.altitude_km;
      row.r_ecef_m = ecef_from_geodetic(
          {row.latitude_deg * kDegToRad, row.longitude_deg * kDegToRad, row.altitude_km * 1e3});
    }
    if (!bad.empty()) return line_error(bad);
    if (missing) {
      ++rec.n_rejected_non_finite;
      continue;
    }
    if (rec.has_quaternion_columns) {
      // A quaternion cell that is not a number at all is an error; an empty or NaN one leaves
      // the row without attitude (kept, counted).
      bool quaternion_missing = false;
      QuaternionWxyz q;
      const C cols[4] = {C::kQw, C::kQx, C::kQy, C::kQz};
      for (int i = 0; i < 4; ++i) {
        const Cell kind = parse_cell(cell(cols[i]), table.separator, &q(i));
        if (kind == Cell::kBad) return line_error("bad quaternion '" + cell(cols[i]) + "'");
        quaternion_missing = quaternion_missing || kind == Cell::kMissing;
      }
      if (!quaternion_missing && q.norm() > 0.5) {
        row.has_quaternion = true;
        row.q_file = q.normalized();
      } else {
        ++rec.n_missing_quaternion;
      }
    }
    if (rec.has_temperature_column) {
      double t_C = 0.0;
      const Cell kind = parse_cell(cell(C::kTemperature), table.separator, &t_C);
      if (kind == Cell::kBad)
        return line_error("bad temperature '" + cell(C::kTemperature) +
                          "' (empty or NaN = unknown)");
      if (kind == Cell::kNumber) row.temperature_C = plausible_temperature_C(t_C);
    }
    rows.push_back({row, line_no});
  }

  // Row rules: time order, one sample per time tag.
  for (size_t k = 1; k < rows.size(); ++k)
    if (rows[k].row.utime < rows[k - 1].row.utime) ++rec.n_out_of_order;
  std::stable_sort(rows.begin(), rows.end(),
                   [](const ReadRow& a, const ReadRow& b) { return a.row.utime < b.row.utime; });
  rec.rows.reserve(rows.size());
  for (size_t k = 0; k < rows.size(); ++k) {
    if (k > 0 && rows[k].row.utime == rows[k - 1].row.utime) {
      if (same_values(rows[k].row, rows[k - 1].row)) {
        ++rec.n_duplicates_dropped;
        continue;
      }
      return fail(fmt::format(
          "lines {} and {}: the same time with other values (one time tag holds one sample)",
          std::min(rows[k - 1].line, rows[k].line), std::max(rows[k - 1].line, rows[k].line)));
    }
    rec.rows.push_back(rows[k].row);
  }
  if (rec.rows.empty()) return fail("no data rows");
  return rec;
}

bool recording_has_reference_directions(const FieldRecording& rec) {
  return rec.has_reference_columns || (rec.has_position_columns && rec.has_quaternion_columns);
}

const char* describe(QuaternionReading reading) {
  switch (reading) {
    case QuaternionReading::kAsStated:
      return "w, x, y, z, body from ECI (as stated)";
    case QuaternionReading::kScalarLast:
      return "x, y, z, w (scalar last)";
    case QuaternionReading::kConjugate:
      return "the conjugate (ECI from body)";
    case QuaternionReading::kScalarLastConjugate:
      return "x, y, z, w (scalar last) and the conjugate (ECI from body)";
  }
  return "?";
}

namespace {

QuaternionWxyz read_quaternion(const QuaternionWxyz& q_file, QuaternionReading reading) {
  const bool scalar_last = reading == QuaternionReading::kScalarLast ||
                           reading == QuaternionReading::kScalarLastConjugate;
  const bool conjugate = reading == QuaternionReading::kConjugate ||
                         reading == QuaternionReading::kScalarLastConjugate;
  const QuaternionWxyz q =
      scalar_last ? QuaternionWxyz(q_file(3), q_file(0), q_file(1), q_file(2)) : q_file;
  return conjugate ? quaternion_conjugate(q) : q;
}

}  // namespace

SampleSet samples_from_recording(const FieldRecording& rec, ReferenceField& field,
                                 std::string* error, QuaternionReading reading) {
  SampleSet samples;
  samples.reserve(rec.rows.size());
  for (size_t k = 0; k < rec.rows.size(); ++k) {
    const FieldRecordingRow& row = rec.rows[k];
    CalibrationSample s;
    s.utime = row.utime;
    s.b_sensor_nT = row.b_sensor_nT;
    s.temperature_C = row.temperature_C;
    if (row.has_reference) {
      s.h_body_nT = row.h_body_nT;
      s.has_reference_direction = true;
    } else {
      std::optional<Eigen::Vector3d> h;
      if (row.has_position && row.has_quaternion) {
        h = field.field_body_nT(row.utime, row.r_ecef_m, read_quaternion(row.q_file, reading));
        s.has_reference_direction = true;
      } else if (row.has_position) {
        h = field.field_ecef_nT(row.utime, row.r_ecef_m);
        if (h) h = Eigen::Vector3d(h->norm(), 0.0, 0.0);  // only |h| is meaningful
      }
      if (!h) {
        if (error)
          *error = fmt::format(
              "{}: row {} ({}): no IGRF reference (time outside the model or "
              "invalid position)",
              rec.source, k + 1, format_iso8601_utc(row.utime));
        return {};
      }
      s.h_body_nT = *h;
    }
    samples.push_back(s);
  }
  return samples;
}

}  // namespace magcal
