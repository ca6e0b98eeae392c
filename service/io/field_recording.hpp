// Reader for magnetometer recordings in any CSV layout (a user's telemetry export, Astro Pi,
// BROAD, or magcal's own sample format): a time column, a measured field in any unit, and
// optionally a reference field in the body frame, a position (ECEF, or geodetic latitude,
// longitude and altitude), an attitude quaternion and a sensor temperature. Columns are found
// by header name (recording_column_table(), or given explicitly); the field is converted to nT
// at this edge so everything downstream is in nT.
//
// The table reader (csv_line.hpp) accepts a byte-order mark, `;` or tab separators and quoted
// fields. A header may carry its unit in parentheses or brackets: `Bx (uT)`, `Time (UTC)`.
// Row rules (the same as read_sample_csv's): a row with a required field (time, field, position)
// empty or not finite is dropped and counted; rows are put in time order; an exact repeat of a
// row is dropped and counted, a row with the same time and other values is an error naming both
// lines; any other unreadable value is an error naming the line.
#pragma once

#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"
#include "pipeline/rotation.hpp"
#include "service/io/csv_line.hpp"

namespace magcal {

class ReferenceField;

enum class FieldUnit { kNanoTesla, kMicroTesla, kGauss, kMilliGauss };
// "nT", "uT" (or "µT"), "G", "mG" (any case but the m/G distinction); nullopt when unknown.
std::optional<FieldUnit> parse_field_unit(const std::string& text);
double nanotesla_per_unit(FieldUnit unit);

// What a column means. The order is the order of the documented table.
enum class RecordingColumn {
  kTime,
  kBx,
  kBy,
  kBz,
  kHx,
  kHy,
  kHz,
  kLatitude,
  kLongitude,
  kAltitude,
  kRx,
  kRy,
  kRz,
  kQw,
  kQx,
  kQy,
  kQz,
  kTemperature,
};
inline constexpr int kRecordingColumnCount = 18;

// One row of the accepted-columns table: the names a header may use (lower case, compared
// after the header is lower-cased, its unit in parentheses or brackets taken off and blanks
// turned into `_`), its unit and meaning.
struct RecordingColumnSpec {
  RecordingColumn column;
  std::vector<const char*> names;
  const char* unit;
  const char* meaning;
};
// The one table of accepted column names: the reader matches with it, `magcal fit --help` and
// docs/input-formats.md print it.
const std::vector<RecordingColumnSpec>& recording_column_table();
// The table as aligned text (one line a column), for --help.
std::string recording_column_table_text();

struct FieldRecordingOptions {
  // Unit of the field columns. nullopt: taken from the column name (a suffix _nT, _uT, _G, _mG,
  // or a unit in parentheses), else an error (a unit is never guessed from the numbers).
  std::optional<FieldUnit> field_unit;
  int skip_first = 0;                 // rows dropped at the start (start-up transients)
  std::optional<double> altitude_km;  // used when the file has latitude/longitude but no altitude
  // Explicit column names (empty: auto-detect from the table).
  std::string time_column, latitude_column, longitude_column, altitude_column;
  std::string bx_column, by_column, bz_column;
};

struct FieldRecordingRow {
  int64_t utime = 0;
  Eigen::Vector3d b_sensor_nT = Eigen::Vector3d::Zero();
  bool has_reference = false;  // reference field in the body frame, from the file
  Eigen::Vector3d h_body_nT = Eigen::Vector3d::Zero();
  bool has_position = false;
  Eigen::Vector3d r_ecef_m = Eigen::Vector3d::Zero();
  double latitude_deg = 0.0;  // geodetic (WGS-84)
  double longitude_deg = 0.0;
  double altitude_km = 0.0;
  bool has_quaternion = false;
  QuaternionWxyz q_file = QuaternionWxyz(1, 0, 0, 0);               // as stored in the file
  double temperature_C = std::numeric_limits<double>::quiet_NaN();  // NaN = unknown
};

struct FieldRecording {
  std::string source;                   // the path, or "standard input"
  std::vector<FieldRecordingRow> rows;  // in time order
  bool has_reference_columns = false;   // hx, hy, hz
  bool has_position_columns = false;    // latitude/longitude(/altitude) or r_ecef
  bool has_quaternion_columns = false;
  bool has_temperature_column = false;
  int n_skipped_first = 0;
  int n_missing_quaternion = 0;   // rows whose quaternion is nan (kept, has_quaternion false)
  int n_rejected_non_finite = 0;  // rows with a required field empty or not finite (dropped)
  int n_duplicates_dropped = 0;   // exact repeats of an earlier row (dropped)
  int n_out_of_order = 0;         // rows whose time is before the previous row's (sorted)
  // Times without a zone (no Z, no +hh:mm), taken as UTC; 0 when the header says UTC.
  int n_times_without_zone = 0;
  std::string time_column;  // what was detected, for the report
  std::string field_unit_name;
  std::vector<std::string> used_columns;     // header names, in table order
  std::vector<std::string> ignored_columns;  // header names no table row took
};

// Reads a whole recording ("-": standard input). On error returns nullopt and sets *error to
// one line naming the file (line) and the problem, with the fix where there is one.
std::optional<FieldRecording> read_field_recording(const std::string& path,
                                                   const FieldRecordingOptions& options,
                                                   std::string* error);
// The same on a table already read.
std::optional<FieldRecording> read_field_recording(const CsvTable& table,
                                                   const FieldRecordingOptions& options,
                                                   std::string* error);

// True when the recording gives every row a reference direction: a body-frame reference in the
// file, or a position and an attitude to compute one from (samples_from_recording).
bool recording_has_reference_directions(const FieldRecording& rec);

// The recording as calibration samples. The reference is the file's body-frame field, else the
// IGRF field at the row's position rotated into the body frame with the row's quaternion
// (q_body_from_eci, w x y z: h_body = A(q) B_eci, as magcald's ingest); a row without a
// quaternion keeps |h| only. Empty with *error set when a row has no IGRF field.
// How a row's quaternion is read: as stated (w x y z, q_body_from_eci), or one of the usual
// misreadings fit tries when an alignment is refused (to name the likely one).
enum class QuaternionReading { kAsStated, kScalarLast, kConjugate, kScalarLastConjugate };
// What a reading means, for a message ("x, y, z, w (scalar last)", ...).
const char* describe(QuaternionReading reading);
SampleSet samples_from_recording(const FieldRecording& rec, ReferenceField& field,
                                 std::string* error,
                                 QuaternionReading reading = QuaternionReading::kAsStated);

// True when the CSV header holds every column of the design's sample format
// (t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT), which read_sample_csv reads.
bool is_design_sample_csv_header(const std::vector<std::string>& header);
bool is_design_sample_csv_header(const std::string& header_line);

}  // namespace magcal
