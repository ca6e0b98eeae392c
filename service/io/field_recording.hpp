// Reader for real magnetometer recordings in "foreign" CSV layouts: a time column,
// a measured field in any unit, and optionally a sub-satellite geodetic position (latitude,
// longitude, altitude — or an assumed constant altitude) and/or an attitude quaternion.
// Columns are found by header name (known aliases, or given explicitly); the field is converted
// to nT at this edge so everything downstream is in nT.
//
// Known layouts it recognises without options:
//   Astro Pi:  Date/Time, Latitude, Longitude, ..., MagX, MagY, MagZ (µT)
//   BROAD:     t_s, mag_x_uT, mag_y_uT, mag_z_uT, q_w, q_x, q_y, q_z (IMU -> ENU, may be nan)
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/rotation.hpp"

namespace magcal {

enum class FieldUnit { kNanoTesla, kMicroTesla, kGauss, kMilliGauss };
// "nT", "uT" (or "µT"), "G", "mG"; nullopt when unknown.
std::optional<FieldUnit> parse_field_unit(const std::string& text);
double nanotesla_per_unit(FieldUnit unit);

struct FieldRecordingOptions {
  // Unit of the field columns. nullopt: taken from the column name suffix (_nT, _uT, _G, _mG),
  // else an error (a unit is never guessed from the numbers).
  std::optional<FieldUnit> field_unit;
  int skip_first = 0;                 // rows dropped at the start (start-up transients)
  std::optional<double> altitude_km;  // used when the file has no altitude column
  // Explicit column names (empty: auto-detect from the known aliases).
  std::string time_column, latitude_column, longitude_column, altitude_column;
  std::string bx_column, by_column, bz_column;
};

struct FieldRecordingRow {
  int64_t utime = 0;
  Eigen::Vector3d b_sensor_nT = Eigen::Vector3d::Zero();
  bool has_position = false;
  double latitude_deg = 0.0;  // geodetic (WGS-84)
  double longitude_deg = 0.0;
  double altitude_km = 0.0;
  bool has_quaternion = false;
  QuaternionWxyz q_file = QuaternionWxyz(1, 0, 0, 0);  // as stored in the file
};

struct FieldRecording {
  std::vector<FieldRecordingRow> rows;
  bool has_position_columns = false;
  bool has_quaternion_columns = false;
  int n_skipped_first = 0;
  int n_missing_quaternion = 0;   // rows whose quaternion is nan (kept, has_quaternion false)
  int n_rejected_non_finite = 0;  // rows whose field or position is not finite (dropped)
  std::string time_column;        // what was detected, for the report
  std::string field_unit_name;
};

// Reads a whole recording. On error returns nullopt and sets *error to one line naming the
// file line and the problem (missing column, bad number, unknown unit, no altitude, ...).
std::optional<FieldRecording> read_field_recording(const std::string& path,
                                                   const FieldRecordingOptions& options,
                                                   std::string* error);

// True when the CSV header is the design's sample format (t_s,bx_nT,...,hz_nT), which the
// regular sample reader handles.
bool is_design_sample_csv_header(const std::string& header_line);

}  // namespace magcal
