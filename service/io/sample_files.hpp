// Sample files shared by `magcal sim` (writing) and `magcal fit` (reading).
//
// CSV (design.md "CSV sample format"): header line required, columns located by name, extra
// columns ignored. Required columns:
//   t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT
//   t_s: seconds since 1970-01-01T00:00:00Z (leap seconds ignored); b: sensor frame (nT);
//   h: reference field in the BODY frame (nT).
// The writer adds optional extras: qw,qx,qy,qz (q_body_from_eci), r_ecef_x_m,r_ecef_y_m,
// r_ecef_z_m, temperature_C. Numbers are written with full precision (round-trip exact).
//
// LCM event log (lcm::LogFile): mag_sample_t on MAGCAL_SAMPLES, or mag_batch_t packets of N
// samples on MAGCAL_BATCH; each event's timestamp is the (first) sample utime.
//
// Errors are values: every function returns an error string (empty = ok) naming the file and,
// for CSV, the line.
#pragma once

#include <cstdint>
#include <cstdio>
#include <optional>
#include <string>
#include <vector>

#include <Eigen/Core>

#include "pipeline/calibration_types.hpp"
#include "schemas/magcal_messages.hpp"
#include "service/io/csv_line.hpp"
#include "service/io/sample_checks.hpp"

namespace magcal {

inline constexpr const char* kSamplesChannel = "MAGCAL_SAMPLES";
inline constexpr const char* kBatchChannel = "MAGCAL_BATCH";

// ---------------------------------------------------------------- CSV

// Optional per-row extras (present when the file has the columns).
struct CsvSampleExtras {
  std::optional<Eigen::Vector4d> q_body_from_eci;  // w,x,y,z
  std::optional<Eigen::Vector3d> r_ecef_m;
  std::optional<double> temperature_C;
};

struct CsvSampleRow {
  // utime = round(t_s * 1e6); has_reference_direction = true; temperature_C from the column
  // (NaN when absent or empty).
  CalibrationSample sample;
  CsvSampleExtras extras;
};

// The largest |component| of a field (b or h) a sample file may hold, nT: 1e7 nT = 10 mT.
// Earth's field is below ~67 000 nT everywhere at the surface and weaker in orbit, and
// spacecraft magnetometers saturate at ~1e5 nT (fluxgates) to ~1e6 nT (wide-range AMR/Hall
// parts); a value beyond 1e7 nT is no measurement of any sensor but a corrupt number, which
// would otherwise only surface as a singular fit.
inline constexpr double kMaxFieldComponent_nT = 1e7;

struct CsvReadResult {
  std::vector<CsvSampleRow> rows;
  std::string error;  // empty = ok; e.g. "file.csv line 17: column bz_nT: not a number"
  int64_t duplicates_dropped = 0;  // exact repeats of an earlier row (see read_sample_csv)
  int64_t missing_dropped = 0;     // rows with a required field empty or not finite
  bool ok() const { return error.empty(); }
};

// Reads a sample CSV (read_csv_table: BOM, `;` or tab separators and quoted fields accepted;
// "-" is standard input). Blank lines are skipped. The row rules every CSV input shares: a row
// whose required field is empty or not finite (NaN, inf) is dropped and counted in
// missing_dropped; an unparsable required field, or a field component beyond
// kMaxFieldComponent_nT, is an error naming the line and column (no partial result is returned
// then: rows is empty); rows may come in any order. The optional temperature_C column: empty or
// NaN = unknown; anything else that is not a number within the plausible range above is an
// error naming the line, as for the field columns.
// One time tag holds one sample (as magcald's ingest, which keeps the first sample of a
// spacecraft's utime and drops later ones): a row repeating an earlier row's utime with
// identical values (b, h and the extras) is dropped and counted in duplicates_dropped (counted
// twice, it would shrink every reported sigma by sqrt(2)); a row with the same utime but other
// values is an error naming both lines (which of the two is the measurement is unknowable).
CsvReadResult read_sample_csv(const std::string& path);
// The same on a table already read (its source names the file in errors).
CsvReadResult read_sample_csv(const CsvTable& table);

// Streaming CSV writer. Writes the header on open, one row per write(); close() flushes and
// reports I/O errors. Extras are written as empty fields when absent.
class SampleCsvWriter {
 public:
  SampleCsvWriter() = default;
  ~SampleCsvWriter();
  SampleCsvWriter(const SampleCsvWriter&) = delete;
  SampleCsvWriter& operator=(const SampleCsvWriter&) = delete;

  std::string open(const std::string& path);  // "" on success
  void write(const CalibrationSample& sample, const CsvSampleExtras& extras = {});
  std::string close();  // "" on success

 private:
  std::FILE* file_ = nullptr;
  std::string path_;
};

// Convenience: writes a whole set (no extras). "" on success.
std::string write_sample_csv(const std::string& path, const SampleSet& samples);

// ---------------------------------------------------------------- LCM log

// Streaming LCM log writer. batch_size 0 => one mag_sample_t event per sample on
// MAGCAL_SAMPLES; batch_size N > 0 => mag_batch_t events of up to N samples on MAGCAL_BATCH
// (keep N <= ~400, toolchain.md). All samples of a batch must share sat_id.
class SampleLcmLogWriter {
 public:
  SampleLcmLogWriter();
  ~SampleLcmLogWriter();
  SampleLcmLogWriter(const SampleLcmLogWriter&) = delete;
  SampleLcmLogWriter& operator=(const SampleLcmLogWriter&) = delete;

  std::string open(const std::string& path, int batch_size = 0);  // "" on success
  std::string write(const mag_sample_t& sample);                  // "" on success
  std::string close();  // flushes a partial batch; "" on success

 private:
  struct Impl;
  Impl* impl_;
};

struct LcmReadOptions {
  std::optional<std::string> sat_id;  // keep only this spacecraft when set
};

struct LcmReadResult {
  std::vector<magcal::mag_sample_t> samples;  // file order, batches expanded
  std::vector<std::string> sat_ids;           // every sat id seen (before filtering), sorted
  int64_t events = 0;                         // events on our two channels
  int64_t undecodable = 0;                    // events on our channels that failed to decode
  int64_t duplicates_dropped = 0;             // exact repeats of a kept sample (see below)
  std::string error;                          // empty = ok (file could not be opened, ...)
  bool ok() const { return error.empty(); }
};

// Reads mag_sample_t from MAGCAL_SAMPLES and mag_batch_t from MAGCAL_BATCH; other channels
// are ignored. Errors: the file is no readable LCM log (unreadable_lcm_log_reason), or it is
// one without a single decodable sample on these channels (naming the channels it holds).
// A log that holds samples, but none of options.sat_id, is not an error here (samples empty,
// sat_ids says who is there). One time tag holds one sample, as in read_sample_csv: a kept
// sample repeating an earlier one's spacecraft and utime with the same measurement and
// reference (seq aside) is dropped and counted; with other values it is an error naming both
// (their indices in `samples` order and their seq).
LcmReadResult read_sample_lcm_log(const std::string& path, const LcmReadOptions& options = {});

// Conversion used by `magcal fit` (temperature_C carried over when plausible, else NaN =
// unknown, as magcald's ingest takes it): has_reference =>
// h_body_nT with direction; otherwise
// has_reference_direction = false and h_body_nT is left zero (the caller computes |h| from
// IGRF at r_ecef).
CalibrationSample to_calibration_sample(const mag_sample_t& msg);

}  // namespace magcal
