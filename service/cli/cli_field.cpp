// `magcal field`: the IGRF field at one point and time (design.md).
//
// Geocentric input (--r-km, --colat-deg, --lon-deg): north/east/down are local geocentric
// (north = -B_theta, east = B_phi, down = -B_r), as the IGRF reference software prints X/Y/Z.
// Geodetic input (--lat-deg, --lon-deg, --alt-km, WGS-84): north/east/down are tangent to the
// ellipsoid; br/btheta/bphi stay geocentric at the same point.
#include <cmath>
#include <cstdio>
#include <iostream>
#include <numbers>

#include <nlohmann/json.hpp>

#include "pipeline/frames.hpp"
#include "pipeline/igrf.hpp"
#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"
#include "service/cli/cli_commands.hpp"
#include "service/io/reference_field.hpp"

namespace magcal::cli {
namespace {

int usage_error(const std::string& message) {
  std::cerr << "magcal field: " << message << "\n";
  return kExitUsage;
}

bool finite(const std::optional<double>& v) {
  return v && std::isfinite(*v);
}

}  // namespace

int run_field(const FieldArgs& args) {
  const auto utime = parse_iso8601_utc(args.time_iso);
  if (!utime) {
    return usage_error("cannot parse --time '" + args.time_iso +
                       "' (expected ISO 8601 UTC, e.g. 2025-06-01T12:00:00Z)");
  }
  const bool geocentric = args.r_km || args.colat_deg;
  const bool geodetic = args.lat_deg || args.alt_km;
  if (geocentric == geodetic) {
    return usage_error(
        "give either --r-km and --colat-deg (geocentric) or --lat-deg and "
        "--alt-km (geodetic WGS-84), with --lon-deg");
  }
  if (!finite(args.lon_deg)) return usage_error("--lon-deg must be a finite number");

  GeocentricPosition where;
  Eigen::Matrix3d ecef_from_ned;
  if (geocentric) {
    if (!finite(args.r_km) || !finite(args.colat_deg)) {
      return usage_error("geocentric input needs both --r-km and --colat-deg (finite numbers)");
    }
    if (*args.r_km <= 0.0) return usage_error("--r-km must be positive");
    if (*args.colat_deg < 0.0 || *args.colat_deg > 180.0) {
      return usage_error("--colat-deg must be within [0, 180]");
    }
    where.radius_m = *args.r_km * 1000.0;
    where.colatitude_rad = *args.colat_deg * kDegToRad;
    where.longitude_rad = *args.lon_deg * kDegToRad;
    ecef_from_ned = ecef_from_ned_geocentric(where.colatitude_rad, where.longitude_rad);
  } else {
    if (!finite(args.lat_deg) || !finite(args.alt_km)) {
      return usage_error("geodetic input needs both --lat-deg and --alt-km (finite numbers)");
    }
    if (*args.lat_deg < -90.0 || *args.lat_deg > 90.0) {
      return usage_error("--lat-deg must be within [-90, 90]");
    }
    GeodeticPosition g;
    g.latitude_rad = *args.lat_deg * kDegToRad;
    g.longitude_rad = *args.lon_deg * kDegToRad;
    g.altitude_m = *args.alt_km * 1000.0;
    const Eigen::Vector3d r = ecef_from_geodetic(g);
    if (r.norm() < 1000.0) return usage_error("--alt-km puts the point at the Earth's centre");
    where = geocentric_from_ecef(r);
    // Keep the given longitude at the poles (atan2(0, 0) would pick 0).
    where.longitude_rad = g.longitude_rad;
    ecef_from_ned = ecef_from_ned_geodetic(g.latitude_rad, g.longitude_rad);
  }

  std::string error;
  const auto field = ReferenceField::from_file(args.coefficients_file, &error);
  if (!field) {
    std::cerr << "magcal field: " << error << "\n";
    return kExitData;
  }
  const IgrfModel& model = field->model();
  const double year = decimal_year_from_utime(*utime);
  IgrfModel at_date = model;
  if (!at_date.set_date(year)) {
    char buf[256];
    std::snprintf(buf, sizeof buf,
                  "magcal field: %s (decimal year %.4f) is outside %s's validity %.1f-%.1f\n",
                  format_iso8601_utc(*utime).c_str(), year, model.table().name.c_str(),
                  model.table().valid_from_year, model.table().valid_to_year);
    std::cerr << buf;
    return kExitData;
  }

  const GeocentricField b = at_date.field_geocentric(where);
  const Eigen::Vector3d b_ecef = IgrfModel::ecef_from_geocentric_field(b, where);
  const Eigen::Vector3d ned = ecef_from_ned.transpose() * b_ecef;
  const double total = b_ecef.norm();

  if (args.json) {
    nlohmann::json j;
    j["time"] = format_iso8601_utc(*utime, 6);
    j["decimal_year"] = year;
    j["model"] = model.table().name;
    j["frame"] = geocentric ? "geocentric" : "geodetic";
    j["radius_km"] = where.radius_m / 1000.0;
    j["colatitude_deg"] = where.colatitude_rad / kDegToRad;
    j["longitude_deg"] = where.longitude_rad / kDegToRad;
    j["br_nT"] = b.br_nT;
    j["btheta_nT"] = b.btheta_nT;
    j["bphi_nT"] = b.bphi_nT;
    j["north_nT"] = ned.x();
    j["east_nT"] = ned.y();
    j["down_nT"] = ned.z();
    j["total_nT"] = total;
    j["b_ecef_nT"] = {b_ecef.x(), b_ecef.y(), b_ecef.z()};
    std::cout << j.dump(2) << "\n";
    return kExitOk;
  }

  char buf[1024];
  std::snprintf(buf, sizeof buf,
                "%s at %s (decimal year %.6f)\n"
                "position (geocentric): r = %.3f km, colatitude = %.6f deg, longitude = %.6f deg\n"
                "  Br      %12.2f nT   (up)\n"
                "  Btheta  %12.2f nT   (south)\n"
                "  Bphi    %12.2f nT   (east)\n"
                "  north   %12.2f nT   (%s)\n"
                "  east    %12.2f nT\n"
                "  down    %12.2f nT\n"
                "  total   %12.2f nT\n",
                model.table().name.c_str(), format_iso8601_utc(*utime, 3).c_str(), year,
                where.radius_m / 1000.0, where.colatitude_rad / kDegToRad,
                where.longitude_rad / kDegToRad, b.br_nT, b.btheta_nT, b.bphi_nT, ned.x(),
                geocentric ? "geocentric" : "geodetic", ned.y(), ned.z(), total);
  std::cout << buf;
  return kExitOk;
}

}  // namespace magcal::cli
