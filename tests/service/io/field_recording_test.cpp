// Reader of foreign recording CSVs (service/io/field_recording.hpp) on small temp files:
// units, skip-first, missing altitude, nan quaternions, bad numbers naming the line.
#include "service/io/field_recording.hpp"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

#include <unistd.h>

#include <catch2/catch.hpp>

#include "pipeline/time_utc.hpp"

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
    CHECK(error.find(":3:") != std::string::npos);
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
