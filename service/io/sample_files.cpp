#include "service/io/sample_files.hpp"

#include <algorithm>
#include <array>
#include <charconv>
#include <cmath>
#include <fstream>
#include <memory>
#include <set>
#include <unordered_map>

#include <lcm/lcm-cpp.hpp>

#include "pipeline/time_utc.hpp"
#include "service/io/csv_line.hpp"

namespace magcal {

namespace {

bool parse_double(std::string_view text, double* value) {
  if (text.empty()) return false;
  if (text.front() == '+') text.remove_prefix(1);
  const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), *value);
  return ec == std::errc() && ptr == text.data() + text.size() && std::isfinite(*value);
}

// Shortest round-trip representation.
void append_number(std::string& out, double v) {
  std::array<char, 32> buf{};
  const auto [ptr, ec] = std::to_chars(buf.data(), buf.data() + buf.size(), v);
  out.append(buf.data(), ec == std::errc() ? ptr : buf.data());
}

std::string join_names(const std::set<std::string>& names) {
  std::string out;
  for (const std::string& n : names) out += (out.empty() ? "" : ", ") + n;
  return out.empty() ? "none" : out;
}

// Same measurement and reference (the transport's seq aside: a re-sent frame may be renumbered).
bool same_measurement(const mag_sample_t& a, const mag_sample_t& b) {
  auto same = [](const double* x, const double* y, int n) { return std::equal(x, x + n, y); };
  return same(a.b_sensor_nT, b.b_sensor_nT, 3) && a.has_position == b.has_position &&
         (!a.has_position || same(a.r_ecef_m, b.r_ecef_m, 3)) && a.has_attitude == b.has_attitude &&
         (!a.has_attitude || same(a.q_body_from_eci, b.q_body_from_eci, 4)) &&
         a.has_reference == b.has_reference &&
         (!a.has_reference || same(a.h_body_nT, b.h_body_nT, 3)) &&
         (a.temperature_C == b.temperature_C ||
          (std::isnan(a.temperature_C) && std::isnan(b.temperature_C)));
}

bool same_extras(const CsvSampleExtras& a, const CsvSampleExtras& b) {
  auto same = [](const auto& x, const auto& y) {
    return x.has_value() == y.has_value() && (!x || *x == *y);
  };
  return same(a.q_body_from_eci, b.q_body_from_eci) && same(a.r_ecef_m, b.r_ecef_m) &&
         same(a.temperature_C, b.temperature_C);
}

constexpr std::array<const char*, 7> kRequired = {"t_s",   "bx_nT", "by_nT", "bz_nT",
                                                  "hx_nT", "hy_nT", "hz_nT"};
constexpr std::array<const char*, 4> kQuat = {"qw", "qx", "qy", "qz"};
constexpr std::array<const char*, 3> kPos = {"r_ecef_x_m", "r_ecef_y_m", "r_ecef_z_m"};

}  // namespace

namespace {

// Where a sample CSV's columns are (their index in each row; -1: absent).
struct CsvColumns {
  std::array<int, 7> required{};  // kRequired
  std::array<int, 4> q{};         // kQuat, when has_q
  std::array<int, 3> r{};         // kPos, when has_r
  bool has_q = true;
  bool has_r = true;
  int temperature = -1;
};

// Locates the columns in the header; "" or what the header lacks.
std::string locate_columns(const std::vector<std::string>& header, CsvColumns* c) {
  auto column = [&](const char* name) -> int {
    const auto it = std::find(header.begin(), header.end(), name);
    return it == header.end() ? -1 : static_cast<int>(it - header.begin());
  };
  for (size_t i = 0; i < kRequired.size(); ++i) {
    c->required[i] = column(kRequired[i]);
    if (c->required[i] < 0) return std::string("header lacks column ") + kRequired[i];
  }
  for (size_t i = 0; i < 4; ++i) c->has_q = (c->q[i] = column(kQuat[i])) >= 0 && c->has_q;
  for (size_t i = 0; i < 3; ++i) c->has_r = (c->r[i] = column(kPos[i])) >= 0 && c->has_r;
  c->temperature = column("temperature_C");
  return "";
}

// The temperature_C field into the row (left unknown when empty or NaN); "" or what is wrong.
std::string parse_temperature(std::string_view text, CsvSampleRow* row) {
  while (!text.empty() && (text.front() == ' ' || text.front() == '\t')) text.remove_prefix(1);
  while (!text.empty() && (text.back() == ' ' || text.back() == '\t' || text.back() == '\r'))
    text.remove_suffix(1);
  const bool unknown = text.empty() || text == "nan" || text == "NaN" || text == "NAN";
  if (unknown) return "";
  double tc = 0.0;
  if (!parse_double(text, &tc))
    return "column temperature_C: not a number (empty or NaN = unknown)";
  if (std::isnan(plausible_temperature_C(tc))) {
    char value[32];
    std::snprintf(value, sizeof value, "%g", tc);
    return std::string("column temperature_C: ") + value +
           " degC is no sensor temperature (within [-150, 200] degC; empty or NaN = unknown)";
  }
  row->extras.temperature_C = row->sample.temperature_C = tc;
  return "";
}

// A field the row rules drop rather than refuse: empty (a blank cell) or a number that is not
// finite (NaN, inf), as exports write for a missing reading.
bool is_missing_value(std::string_view text) {
  double v = 0.0;
  if (text.empty()) return true;
  if (text.front() == '+' || text.front() == '-') text.remove_prefix(1);
  const auto [ptr, ec] = std::from_chars(text.data(), text.data() + text.size(), v);
  return ec == std::errc() && ptr == text.data() + text.size() && !std::isfinite(v);
}

// One data row's fields into `row`; "" or what is wrong with them. *missing is set (and ""
// returned) when a required field is empty or not finite: the row is dropped and counted.
std::string parse_row(const std::vector<std::string>& fields, const CsvColumns& c,
                      CsvSampleRow* row, bool* missing) {
  auto field = [&](int col, double* v) {
    return col < static_cast<int>(fields.size()) &&
           parse_double(fields[static_cast<size_t>(col)], v);
  };
  std::array<double, 7> v{};
  for (size_t i = 0; i < 7; ++i) {
    if (c.required[i] >= static_cast<int>(fields.size())) return "too few fields";
    if (field(c.required[i], &v[i])) continue;
    if (is_missing_value(fields[static_cast<size_t>(c.required[i])])) {
      *missing = true;
      return "";
    }
    return std::string("column ") + kRequired[i] + ": not a number";
  }
  if (std::abs(v[0]) > 1e11) return "column t_s: out of range";
  for (size_t i = 1; i < 7; ++i) {
    if (std::abs(v[i]) > kMaxFieldComponent_nT) {
      char value[32];
      std::snprintf(value, sizeof value, "%g", v[i]);
      return std::string("column ") + kRequired[i] + ": " + value +
             " nT is beyond any magnetometer's range (|value| <= 1e7 nT)";
    }
  }
  row->sample.utime = utime_from_seconds(v[0]);
  row->sample.b_sensor_nT = Eigen::Vector3d(v[1], v[2], v[3]);
  row->sample.h_body_nT = Eigen::Vector3d(v[4], v[5], v[6]);
  row->sample.has_reference_direction = true;
  // Extras are optional per row too: an empty or bad field leaves the extra unset.
  if (c.has_q) {
    Eigen::Vector4d qq;
    bool ok = true;
    for (int i = 0; i < 4; ++i) ok = field(c.q[static_cast<size_t>(i)], &qq(i)) && ok;
    if (ok) row->extras.q_body_from_eci = qq;
  }
  if (c.has_r) {
    Eigen::Vector3d rr;
    bool ok = true;
    for (int i = 0; i < 3; ++i) ok = field(c.r[static_cast<size_t>(i)], &rr(i)) && ok;
    if (ok) row->extras.r_ecef_m = rr;
  }
  if (c.temperature >= 0 && c.temperature < static_cast<int>(fields.size()))
    return parse_temperature(fields[static_cast<size_t>(c.temperature)], row);
  return "";
}

}  // namespace

CsvReadResult read_sample_csv(const std::string& path) {
  CsvTable table;
  if (std::string error = read_csv_table(path, &table); !error.empty()) {
    CsvReadResult result;
    result.error = error.find("empty file") != std::string::npos
                       ? path +
                             ": empty file (header t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT "
                             "required)"
                       : error;
    return result;
  }
  return read_sample_csv(table);
}

CsvReadResult read_sample_csv(const CsvTable& table) {
  CsvReadResult result;
  const std::string& path = table.source;
  CsvColumns columns;
  if (const std::string lacks = locate_columns(table.header, &columns); !lacks.empty()) {
    result.error = path + " line " + std::to_string(table.header_line) + ": " + lacks;
    return result;
  }
  // utime -> index in rows and the line of that row, for the one-sample-per-time-tag rule.
  std::unordered_map<int64_t, std::pair<size_t, int>> row_of_utime;

  for (const CsvTable::Row& table_row : table.rows) {
    const int line_no = table_row.line;
    auto fail = [&](const std::string& what) {
      result.rows.clear();
      result.duplicates_dropped = 0;
      result.missing_dropped = 0;
      result.error = path + " line " + std::to_string(line_no) + ": " + what;
      return result;
    };
    CsvSampleRow row;
    bool missing = false;
    if (const std::string problem = parse_row(table_row.cells, columns, &row, &missing);
        !problem.empty()) {
      return fail(problem);
    }
    if (missing) {
      ++result.missing_dropped;
      continue;
    }
    const auto [seen, first] =
        row_of_utime.try_emplace(row.sample.utime, result.rows.size(), line_no);
    if (!first) {
      const CsvSampleRow& earlier = result.rows[seen->second.first];
      if (earlier.sample.b_sensor_nT == row.sample.b_sensor_nT &&
          earlier.sample.h_body_nT == row.sample.h_body_nT &&
          same_extras(earlier.extras, row.extras)) {
        ++result.duplicates_dropped;
        continue;
      }
      return fail("same t_s as line " + std::to_string(seen->second.second) +
                  " but other values (one time tag holds one sample)");
    }
    result.rows.push_back(std::move(row));
  }
  return result;
}

SampleCsvWriter::~SampleCsvWriter() {
  if (file_ != nullptr) std::fclose(file_);
}

std::string SampleCsvWriter::open(const std::string& path) {
  if (file_ != nullptr) return path + ": writer already open";
  path_ = path;
  file_ = std::fopen(path.c_str(), "w");
  if (file_ == nullptr) return path + ": cannot open for writing";
  std::fputs(
      "t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT,qw,qx,qy,qz,r_ecef_x_m,r_ecef_y_m,r_ecef_z_m,"
      "temperature_C\n",
      file_);
  return "";
}

void SampleCsvWriter::write(const CalibrationSample& s, const CsvSampleExtras& extras) {
  if (file_ == nullptr) return;
  std::string line;
  line.reserve(400);
  append_number(line, seconds_from_utime(s.utime));
  for (int i = 0; i < 3; ++i) line += ',', append_number(line, s.b_sensor_nT(i));
  for (int i = 0; i < 3; ++i) line += ',', append_number(line, s.h_body_nT(i));
  for (int i = 0; i < 4; ++i) {
    line += ',';
    if (extras.q_body_from_eci) append_number(line, (*extras.q_body_from_eci)(i));
  }
  for (int i = 0; i < 3; ++i) {
    line += ',';
    if (extras.r_ecef_m) append_number(line, (*extras.r_ecef_m)(i));
  }
  line += ',';
  if (extras.temperature_C) append_number(line, *extras.temperature_C);
  line += '\n';
  std::fwrite(line.data(), 1, line.size(), file_);
}

std::string SampleCsvWriter::close() {
  if (file_ == nullptr) return "";
  const bool write_error = std::ferror(file_) != 0;
  const bool close_error = std::fclose(file_) != 0;
  file_ = nullptr;
  if (write_error || close_error) return path_ + ": write error";
  return "";
}

std::string write_sample_csv(const std::string& path, const SampleSet& samples) {
  SampleCsvWriter w;
  if (std::string e = w.open(path); !e.empty()) return e;
  for (const auto& s : samples) w.write(s);
  return w.close();
}

// ---------------------------------------------------------------- LCM log

struct SampleLcmLogWriter::Impl {
  std::unique_ptr<lcm::LogFile> log;
  std::string path;
  int batch_size = 0;
  mag_batch_t batch;
  int64_t event_number = 0;
  std::vector<uint8_t> buffer;
  bool failed = false;

  template <typename T>
  std::string write_event(const T& msg, int64_t utime, const char* channel) {
    const int size = msg.getEncodedSize();
    buffer.resize(static_cast<size_t>(size));
    if (msg.encode(buffer.data(), 0, size) != size) return path + ": encoding failed";
    lcm::LogEvent ev;
    ev.eventnum = event_number++;
    ev.timestamp = utime;
    ev.channel = channel;
    ev.datalen = size;
    ev.data = buffer.data();
    if (log->writeEvent(&ev) != 0) {
      failed = true;
      return path + ": write error";
    }
    return "";
  }
  std::string flush_batch() {
    if (batch.samples.empty()) return "";
    batch.n = static_cast<int32_t>(batch.samples.size());  // n must match before encoding
    batch.sat_id = batch.samples.front().sat_id;
    std::string e = write_event(batch, batch.samples.front().utime, kBatchChannel);
    batch.samples.clear();
    batch.n = 0;
    return e;
  }
};

SampleLcmLogWriter::SampleLcmLogWriter() : impl_(new Impl) {}
SampleLcmLogWriter::~SampleLcmLogWriter() {
  delete impl_;
}

std::string SampleLcmLogWriter::open(const std::string& path, int batch_size) {
  if (batch_size < 0) return "batch size must be >= 0";
  impl_->path = path;
  impl_->batch_size = batch_size;
  impl_->log = std::make_unique<lcm::LogFile>(path, "w");
  if (!impl_->log->good()) {
    impl_->log.reset();
    return path + ": cannot open for writing";
  }
  return "";
}

std::string SampleLcmLogWriter::write(const mag_sample_t& sample) {
  if (!impl_->log) return "log not open";
  if (impl_->batch_size == 0) return impl_->write_event(sample, sample.utime, kSamplesChannel);
  if (!impl_->batch.samples.empty() && impl_->batch.samples.front().sat_id != sample.sat_id) {
    if (std::string e = impl_->flush_batch(); !e.empty()) return e;
  }
  impl_->batch.samples.push_back(sample);
  if (static_cast<int>(impl_->batch.samples.size()) >= impl_->batch_size)
    return impl_->flush_batch();
  return "";
}

std::string SampleLcmLogWriter::close() {
  if (!impl_->log) return "";
  std::string e = impl_->flush_batch();
  // lcm::LogFile flushes and closes in its destructor; fflush first to see errors.
  if (std::fflush(impl_->log->getFilePtr()) != 0 || std::ferror(impl_->log->getFilePtr()) != 0)
    impl_->failed = true;
  impl_->log.reset();
  if (e.empty() && impl_->failed) e = impl_->path + ": write error";
  return e;
}

LcmReadResult read_sample_lcm_log(const std::string& path, const LcmReadOptions& options) {
  LcmReadResult result;
  if (std::string why = unreadable_lcm_log_reason(path); !why.empty()) {
    result.error = why;
    return result;
  }
  lcm::LogFile log(path, "r");
  if (!log.good()) {
    result.error = path + ": cannot open as an LCM log";
    return result;
  }
  std::set<std::string> ids;
  std::set<std::string> other_channels;
  // utime -> index in samples (several spacecraft may share a utime), for the
  // one-sample-per-time-tag rule; the first conflict found is the error.
  std::unordered_multimap<int64_t, size_t> sample_of_utime;
  std::string conflict;
  auto keep = [&](mag_sample_t&& s) {
    ids.insert(s.sat_id);
    if (options.sat_id && *options.sat_id != s.sat_id) return;
    const auto [first, last] = sample_of_utime.equal_range(s.utime);
    for (auto it = first; it != last; ++it) {
      const mag_sample_t& earlier = result.samples[it->second];
      if (earlier.sat_id != s.sat_id) continue;
      if (same_measurement(earlier, s)) {
        ++result.duplicates_dropped;
      } else if (conflict.empty()) {
        conflict = path + ": samples " + std::to_string(it->second) + " (seq " +
                   std::to_string(earlier.seq) + ") and " + std::to_string(result.samples.size()) +
                   " (seq " + std::to_string(s.seq) + ") of spacecraft '" + s.sat_id +
                   "' share utime " + std::to_string(s.utime) +
                   " with other values (one time tag holds one sample)";
      }
      return;
    }
    sample_of_utime.emplace(s.utime, result.samples.size());
    result.samples.push_back(std::move(s));
  };
  while (const lcm::LogEvent* ev = log.readNextEvent()) {
    if (ev->channel == kSamplesChannel) {
      ++result.events;
      mag_sample_t s;
      if (!well_formed_lcm_frame(ev->data, ev->datalen, false) ||
          s.decode(ev->data, 0, ev->datalen) != ev->datalen) {
        ++result.undecodable;
        continue;
      }
      keep(std::move(s));
    } else if (ev->channel == kBatchChannel) {
      ++result.events;
      mag_batch_t b;
      if (!well_formed_lcm_frame(ev->data, ev->datalen, true) ||
          b.decode(ev->data, 0, ev->datalen) != ev->datalen) {
        ++result.undecodable;
        continue;
      }
      for (auto& s : b.samples) keep(std::move(s));
    } else if (other_channels.size() < 10) {
      other_channels.insert(ev->channel);
    }
  }
  result.sat_ids.assign(ids.begin(), ids.end());
  if (result.events == 0) {
    result.error = path + ": an LCM log, but without events on " + kSamplesChannel + " or " +
                   kBatchChannel + " (channels in it: " + join_names(other_channels) + ")";
  } else if (result.events == result.undecodable) {
    result.error = path + ": none of its " + std::to_string(result.events) + " events on " +
                   kSamplesChannel + "/" + kBatchChannel +
                   " decodes as magcal.mag_sample_t/mag_batch_t (another message type?)";
  }
  if (result.ok() && !conflict.empty()) result.error = conflict;
  if (!result.ok()) {
    result.samples.clear();
    result.duplicates_dropped = 0;
  }
  return result;
}

CalibrationSample to_calibration_sample(const mag_sample_t& msg) {
  CalibrationSample s;
  s.utime = msg.utime;
  s.b_sensor_nT = Eigen::Vector3d(msg.b_sensor_nT[0], msg.b_sensor_nT[1], msg.b_sensor_nT[2]);
  s.temperature_C = plausible_temperature_C(static_cast<double>(msg.temperature_C));
  if (msg.has_reference) {
    s.h_body_nT = Eigen::Vector3d(msg.h_body_nT[0], msg.h_body_nT[1], msg.h_body_nT[2]);
    s.has_reference_direction = true;
  } else {
    s.has_reference_direction = false;
  }
  return s;
}

}  // namespace magcal
