// Reader of foreign recording CSVs (service/io/field_recording.hpp) on small temp files:
// units, skip-first, missing altitude, nan quaternions, bad numbers naming the line; the shapes
// a user's own export comes in (units in the header, BOM, `;`, quotes, zones, blank cells) and
// the row rules; the column table against docs/input-formats.md.
#include "service/io/field_recording.hpp"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>

#include <unistd.h>

#include <catch2/catch.hpp>

#include "pipeline/frames.hpp"
#include "pipeline/time_utc.hpp"
#include "service/io/reference_field.hpp"

using namespace magcal;

namespace {

// A temp file removed at scope exit.
struct TempCsv {
  std::string path;
  explicit TempCsv(const std::string& name, const std::string& text)
      : path((std::filesystem::temp_directory_path() /
              ("magcal_fr_" + name + "_" + std::to_string(::getpid()) + ".csv"))
                 .string()) {
    std::ofstream(path) << text;
  }
  ~TempCsv() {
    std::error_code ec;
    std::filesystem::remove(path, ec);
  }
};

const char* kAstroPi =
    "Date/Time,Latitude,Longitude,Temperature,MagX,MagY,MagZ\n"
    "2022-01-31 12:21:15,10.5,-20.25,33.7,1.5,-2.0,30.1\n"
    "2022-01-31 12:21:20,10.6,-20.00,33.7,1.6,-2.1,30.0\n"
    "2022-01-31 12:21:25,10.7,-19.75,33.8,1.7,-2.2,29.9\n";

const char* kBroad =
    "t_s,mag_x_uT,mag_y_uT,mag_z_uT,q_w,q_x,q_y,q_z,movement\n"
    "0.0,1.0,2.0,3.0,1.0,0.0,0.0,0.0,0\n"
    "0.0035,1.1,2.1,3.1,nan,nan,nan,nan,0\n"
    "0.007,1.2,2.2,3.2,0.0,2.0,0.0,0.0,1\n";

}  // namespace

TEST_CASE("Astro Pi layout: time, position, unit from the option, assumed altitude",
          "[recording]") {
  TempCsv f("astropi", kAstroPi);
  FieldRecordingOptions o;
  o.field_unit = FieldUnit::kMicroTesla;
  o.altitude_km = 420.0;
  std::string error;
  const auto rec = read_field_recording(f.path, o, &error);
  REQUIRE(rec);
  CHECK(error.empty());
  REQUIRE(rec->rows.size() == 3);
  CHECK(rec->has_position_columns);
  CHECK_FALSE(rec->has_quaternion_columns);
  CHECK(rec->field_unit_name == "uT");
  const FieldRecordingRow& r0 = rec->rows[0];
  CHECK(r0.utime == *parse_iso8601_utc("2022-01-31T12:21:15Z"));
  CHECK(rec->rows[1].utime - r0.utime == 5'000'000);
  CHECK(r0.b_sensor_nT.isApprox(Eigen::Vector3d(1500.0, -2000.0, 30100.0)));
  CHECK(r0.has_position);
  CHECK(r0.latitude_deg == 10.5);
  CHECK(r0.longitude_deg == -20.25);
  CHECK(r0.altitude_km == 420.0);
}

TEST_CASE("field units convert to nT", "[recording]") {
  TempCsv f("units", kAstroPi);
  const double raw_x = 1.5;
  for (const auto& [name, nT_per_unit] :
       {std::pair<const char*, double>{"nT", 1.0}, {"uT", 1e3}, {"G", 1e5}, {"mG", 1e2}}) {
    FieldRecordingOptions o;
    o.field_unit = parse_field_unit(name);
    REQUIRE(o.field_unit);
    CHECK(nanotesla_per_unit(*o.field_unit) == nT_per_unit);
    o.altitude_km = 400.0;
    std::string error;
    const auto rec = read_field_recording(f.path, o, &error);
    REQUIRE(rec);
    CHECK(rec->rows[0].b_sensor_nT.x() == Approx(raw_x * nT_per_unit));
  }
  CHECK_FALSE(parse_field_unit("tesla"));
  CHECK(parse_field_unit("µT") == FieldUnit::kMicroTesla);
}

TEST_CASE("unit is never guessed: MagX without --field-unit is an error", "[recording]") {
  TempCsv f("nounit", kAstroPi);
  FieldRecordingOptions o;
  o.altitude_km = 420.0;
  std::string error;
  CHECK_FALSE(read_field_recording(f.path, o, &error));
  CHECK(error.find("--field-unit") != std::string::npos);
}

TEST_CASE("skip-first drops the first N data rows and counts them", "[recording]") {
  TempCsv f("skip", kAstroPi);
  FieldRecordingOptions o;
  o.field_unit = FieldUnit::kMicroTesla;
  o.altitude_km = 420.0;
  o.skip_first = 2;
  std::string error;
  const auto rec = read_field_recording(f.path, o, &error);
  REQUIRE(rec);
  REQUIRE(rec->rows.size() == 1);
  CHECK(rec->n_skipped_first == 2);
  CHECK(rec->rows[0].b_sensor_nT.z() == Approx(29900.0));
  o.skip_first = 3;  // nothing left
  CHECK_FALSE(read_field_recording(f.path, o, &error));
  CHECK(error.find("no data rows") != std::string::npos);
}

TEST_CASE("position without altitude column needs an assumed altitude", "[recording]") {
  TempCsv f("noalt", kAstroPi);
  FieldRecordingOptions o;
  o.field_unit = FieldUnit::kMicroTesla;
  std::string error;
  CHECK_FALSE(read_field_recording(f.path, o, &error));
  CHECK(error.find("altitude") != std::string::npos);
  CHECK(error.find(f.path) != std::string::npos);
}

TEST_CASE("BROAD layout: unit from column names, nan quaternions counted, rows kept",
          "[recording]") {
  TempCsv f("broad", kBroad);
  std::string error;
  const auto rec = read_field_recording(f.path, {}, &error);
  REQUIRE(rec);
  REQUIRE(rec->rows.size() == 3);
  CHECK(rec->field_unit_name == "uT");
  CHECK(rec->has_quaternion_columns);
  CHECK_FALSE(rec->has_position_columns);
  CHECK(rec->n_missing_quaternion == 1);
  CHECK(rec->rows[0].has_quaternion);
  CHECK_FALSE(rec->rows[1].has_quaternion);
  CHECK(rec->rows[2].has_quaternion);
  CHECK(rec->rows[2].q_file.isApprox(QuaternionWxyz(0.0, 1.0, 0.0, 0.0)));  // normalised
  CHECK(rec->rows[1].utime - rec->rows[0].utime == 3500);
  CHECK(rec->rows[1].b_sensor_nT.isApprox(Eigen::Vector3d(1100.0, 2100.0, 3100.0)));
}

TEST_CASE("bad numbers and corrupt files are errors naming the line", "[recording]") {
  FieldRecordingOptions o;
  o.field_unit = FieldUnit::kMicroTesla;
  o.altitude_km = 420.0;
  std::string error;
  SECTION("bad field value on line 3") {
    TempCsv f("badnum",
              std::string(kAstroPi).replace(std::string(kAstroPi).find("1.6"), 3, "1.6x"));
    CHECK_FALSE(read_field_recording(f.path, o, &error));
    CHECK(error.find("line 3") != std::string::npos);
    CHECK(error.find("1.6x") != std::string::npos);
  }
  SECTION("bad time") {
    TempCsv f("badtime",
              "Date/Time,Latitude,Longitude,MagX,MagY,MagZ\n"
              "2022-01-31 12:21:15,1,2,3,4,5\nyesterday,1,2,3,4,5\n");
    CHECK_FALSE(read_field_recording(f.path, o, &error));
    CHECK(error.find("line 3") != std::string::npos);
  }
  SECTION("missing magnetometer columns") {
    TempCsv f("nomag", "Date/Time,Latitude,Longitude\n2022-01-31 12:21:15,1,2\n");
    CHECK_FALSE(read_field_recording(f.path, o, &error));
    CHECK(error.find("magnetometer") != std::string::npos);
  }
  SECTION("empty file and absent file") {
    TempCsv f("empty", "");
    CHECK_FALSE(read_field_recording(f.path, o, &error));
    CHECK(error.find("empty") != std::string::npos);
    CHECK_FALSE(read_field_recording(f.path + ".absent", o, &error));
    CHECK(error.find("cannot open") != std::string::npos);
  }
  SECTION("non-finite field rows are dropped and counted") {
    TempCsv f("nanfield", "t_s,bx_uT,by_uT,bz_uT\n0,1,2,3\n1,nan,2,3\n2,1,2,3\n");
    const auto rec = read_field_recording(f.path, {}, &error);
    REQUIRE(rec);
    CHECK(rec->rows.size() == 2);
    CHECK(rec->n_rejected_non_finite == 1);
  }
}

TEST_CASE("design sample CSV header is recognised", "[recording]") {
  CHECK(is_design_sample_csv_header("t_s,bx_nT,by_nT,bz_nT,hx_nT,hy_nT,hz_nT"));
  CHECK_FALSE(is_design_sample_csv_header("Date/Time,Latitude,Longitude,MagX,MagY,MagZ"));
  CHECK_FALSE(is_design_sample_csv_header("t_s,mag_x_uT,mag_y_uT,mag_z_uT"));
}

// ---------------------------------------------------------------- a user's own export

namespace {

std::optional<FieldRecording> read_text(const std::string& name, const std::string& text,
                                        std::string* error, const FieldRecordingOptions& o = {}) {
  TempCsv f(name, text);
  return read_field_recording(f.path, o, error);
}

}  // namespace

TEST_CASE("export shapes: units in quoted headers, ISO times with a zone, extra columns named",
          "[recording][export]") {
  std::string error;
  const auto rec = read_text("quoted",
                             "\"Time\",\"Bx (uT)\",\"By (uT)\",\"Bz (uT)\",mode,\"comment, free\"\n"
                             "2025-03-01T12:00:00Z,1.5,-2,30,safe,\"a, b\"\n"
                             "2025-03-01T12:00:01+01:00,1.5,-2,30,safe,x\n",
                             &error);
  REQUIRE(rec);
  CHECK(rec->field_unit_name == "uT");
  CHECK(rec->rows.size() == 2);
  CHECK(rec->n_times_without_zone == 0);
  // +01:00 is an hour earlier in UTC: rows sorted by time, the order counted.
  CHECK(rec->rows[0].utime == *parse_iso8601_utc("2025-03-01T11:00:01Z"));
  CHECK(rec->n_out_of_order == 1);
  CHECK(rec->rows[1].b_sensor_nT.isApprox(Eigen::Vector3d(1500, -2000, 30000)));
  CHECK(rec->used_columns == std::vector<std::string>{"Time", "Bx (uT)", "By (uT)", "Bz (uT)"});
  CHECK(rec->ignored_columns == std::vector<std::string>{"mode", "comment, free"});
}

TEST_CASE("export shapes: a time without a zone is counted (stated), unless the header says UTC",
          "[recording][export]") {
  std::string error;
  const std::string rows = "2025-03-01 12:00:00,1,2,3\n2025-03-01 12:00:01,1,2,3\n";
  auto rec = read_text("nozone", "timestamp,bx_nT,by_nT,bz_nT\n" + rows, &error);
  REQUIRE(rec);
  CHECK(rec->n_times_without_zone == 2);
  CHECK(rec->rows[0].utime == *parse_iso8601_utc("2025-03-01T12:00:00Z"));
  for (const char* header :
       {"time_utc,Bx_nT,By_nT,Bz_nT\n", "Time (UTC),bx (nT),by (nT),bz (nT)\n"}) {
    rec = read_text("utc", header + rows, &error);
    REQUIRE(rec);
    CHECK(rec->n_times_without_zone == 0);
  }
}

TEST_CASE("export shapes: byte-order mark, semicolons with a decimal comma, gauss in brackets",
          "[recording][export]") {
  std::string error;
  const auto rec = read_text("semicolon",
                             "\xEF\xBB\xBFtime;Bx [G];By [G];Bz [G];Temperature\r\n"
                             "2025-03-01T12:00:00Z;0,21;-0,03;0,401;18,5\r\n"
                             "2025-03-01T12:00:01Z;0,22;-0,03;0,402;\r\n",
                             &error);
  INFO(error);
  REQUIRE(rec);
  CHECK(rec->field_unit_name == "G");
  REQUIRE(rec->rows.size() == 2);
  CHECK(rec->rows[0].b_sensor_nT.isApprox(Eigen::Vector3d(21000, -3000, 40100)));
  CHECK(rec->has_temperature_column);
  CHECK(rec->rows[0].temperature_C == 18.5);
  CHECK(std::isnan(rec->rows[1].temperature_C));  // empty = unknown, the row kept
}

TEST_CASE("row rules: blank and NaN cells drop the row, repeats dropped, conflicts named",
          "[recording][export]") {
  std::string error;
  const std::string header = "t_s,bx_nT,by_nT,bz_nT,lat,lon,alt_km\n";
  auto rec = read_text("blank",
                       header +
                           "3,1,2,3,10,20,500\n1,1,,3,10,20,500\n2,1,2,3,,20,500\n"
                           "0,1,2,3,10,20,500\n4,NaN,2,3,10,20,500\n3,1,2,3,10,20,500\n"
                           "5,1,2,3,10,20,500\n",
                       &error);
  INFO(error);
  REQUIRE(rec);
  CHECK(rec->rows.size() == 3);  // t = 0, 3, 5
  CHECK(rec->n_rejected_non_finite == 3);
  CHECK(rec->n_duplicates_dropped == 1);
  CHECK(rec->n_out_of_order == 1);
  CHECK(rec->rows[0].utime == 0);
  CHECK(rec->rows[2].utime == 5'000'000);
  rec = read_text("conflict", header + "3,1,2,3,10,20,500\n1,1,2,3,10,20,500\n3,9,2,3,10,20,500\n",
                  &error);
  CHECK_FALSE(rec);
  CHECK(error.find("lines 2 and 4") != std::string::npos);
}

TEST_CASE("export shapes refused name the fix", "[recording][export]") {
  std::string error;
  CHECK_FALSE(read_text("nounit", "time,Bx,By,Bz\n2025-03-01T12:00:00Z,1,2,3\n", &error));
  CHECK(error.find("\"Bx (uT)\"") != std::string::npos);
  CHECK(error.find("--field-unit") != std::string::npos);
  CHECK_FALSE(read_text("numtime", "time,bx_nT,by_nT,bz_nT\n1700000000,1,2,3\n", &error));
  CHECK(error.find("name the column t_s") != std::string::npos);
  CHECK_FALSE(read_text("notime", "when,bx_nT,by_nT,bz_nT\n1,1,2,3\n", &error));
  CHECK(error.find("no time column") != std::string::npos);
  CHECK(error.find("timestamp") != std::string::npos);
  CHECK_FALSE(read_text("badq", "t_s,bx_nT,by_nT,bz_nT,q0,q1,q2,q3\n1,1,2,3,1,0,0,zero\n", &error));
  CHECK(error.find("line 2: bad quaternion 'zero'") != std::string::npos);
}

TEST_CASE("position, attitude and temperature: ECEF or geodetic, q0..q3 scalar first",
          "[recording][export]") {
  std::string error;
  // The same place twice: geodetic (altitude in metres) and ECEF.
  const Eigen::Vector3d r = ecef_from_geodetic({0.5, 1.0, 500e3});
  std::ostringstream ecef;
  ecef.precision(17);
  ecef << "t_s,bx_nT,by_nT,bz_nT,r_ecef_x_m,r_ecef_y_m,r_ecef_z_m,q0,q1,q2,q3,temp_C\n"
       << "1700000000,"
       << "1,2,3," << r.x() << "," << r.y() << "," << r.z() << ",0,0,2,0,21\n";
  auto rec = read_text("ecef", ecef.str(), &error);
  REQUIRE(rec);
  std::ostringstream geodetic;
  geodetic.precision(17);
  geodetic << "t_s,bx_nT,by_nT,bz_nT,latitude,longitude,altitude (m),qw,qx,qy,qz,temperature_C\n"
           << "1700000000,1,2,3," << 0.5 * kRadToDeg << "," << 1.0 * kRadToDeg
           << ",500000,0,0,2,0,21\n";
  auto rec2 = read_text("geodetic", geodetic.str(), &error);
  REQUIRE(rec2);
  for (const auto* x : {&*rec, &*rec2}) {
    CHECK(x->has_position_columns);
    CHECK(x->has_quaternion_columns);
    CHECK(recording_has_reference_directions(*x));
    REQUIRE(x->rows.size() == 1);
    CHECK((x->rows[0].r_ecef_m - r).norm() < 1e-3);
    CHECK(x->rows[0].q_file.isApprox(QuaternionWxyz(0, 0, 1, 0)));
    CHECK(x->rows[0].temperature_C == 21.0);
  }
  CHECK(rec2->rows[0].altitude_km == Approx(500.0));
  // The body-frame reference is the daemon's: IGRF at the position, rotated with q.
  ReferenceField field;
  const SampleSet samples = samples_from_recording(*rec, field, &error);
  REQUIRE(samples.size() == 1);
  CHECK(samples[0].has_reference_direction);
  const auto h = field.field_body_nT(1'700'000'000'000'000, r, QuaternionWxyz(0, 0, 1, 0));
  REQUIRE(h);
  CHECK((samples[0].h_body_nT - *h).norm() < 1e-6);
  CHECK(samples[0].temperature_C == 21.0);
}

TEST_CASE("every accepted column name is on docs/input-formats.md", "[recording]") {
  std::ifstream in(std::string(MAGCAL_SOURCE_DIR) + "/docs/input-formats.md");
  REQUIRE(in);
  std::stringstream text;
  text << in.rdbuf();
  const std::string doc = text.str();
  for (const RecordingColumnSpec& spec : recording_column_table()) {
    for (const char* name : spec.names) {
      INFO(name);
      CHECK(doc.find(std::string("`") + name + "`") != std::string::npos);
    }
  }
  CHECK(recording_column_table_text().find("temperature_c") != std::string::npos);
}
