// IGRF spherical-harmonic main-field synthesis (Schmidt semi-normalised Gauss coefficients).
//
//   B = -grad V,  V(r, theta, phi) = a sum_{n=1..N} (a/r)^{n+1} sum_{m=0..n}
//                  (g_n^m cos m phi + h_n^m sin m phi) P_n^m(cos theta),   a = 6371.2 km
//
// Coefficients are piecewise linear in decimal year between the model epochs; after the last
// main-field epoch they follow the secular variation (the official rule). Dates outside the
// model's validity are refused. The built-in table is IGRF-14 (1900.0-2030.0, degree 13),
// generated from the official coefficient file; any IGRF coefficient file in the official
// text format (igrfNNcoeffs.txt) or .shc format can be loaded instead.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <Eigen/Core>

#include "pipeline/frames.hpp"

namespace magcal {

constexpr double kIgrfReferenceRadius_m = 6371200.0;

// All epochs' coefficients, in the model's native layout.
struct IgrfCoefficientTable {
  std::string name;                      // e.g. "IGRF-14"
  int max_degree = 0;                    // 13 for IGRF-14
  double valid_from_year = 0.0;          // 1900.0
  double valid_to_year = 0.0;            // 2030.0
  std::vector<double> epochs_year;       // knots of the piecewise-linear time dependence
  // coefficients[e] holds, for epoch e, g/h packed as: for n = 1..N, m = 0..n:
  // g(n,m) at index n*(n+1)/2 - 1 + m ... see igrf.cpp (pack_index) -- plus h in a parallel
  // vector. Both are in nT.
  std::vector<std::vector<double>> g_nT;
  std::vector<std::vector<double>> h_nT;
};

// The built-in IGRF-14 table (compiled in; no file needed at run time).
const IgrfCoefficientTable& builtin_igrf14();

// Parse an official coefficient file. Text is the file's content; format detected from it
// (the IAGA/NCEI "g/h n m ..." table or the .shc layout). On error returns nullopt and sets
// *error to one clear line naming the line number and the problem.
std::optional<IgrfCoefficientTable> parse_igrf_coefficients(std::string_view text,
                                                            std::string* error);

struct GeocentricField {
  double br_nT = 0.0;      // radial (up)
  double btheta_nT = 0.0;  // along increasing colatitude (south)
  double bphi_nT = 0.0;    // east
  double north_nT() const { return -btheta_nT; }
  double east_nT() const { return bphi_nT; }
  double down_nT() const { return -br_nT; }
};

// Evaluates the field; holds the time-interpolated coefficients of one date, so evaluating
// many positions at the same date (or within `refresh_years`) costs only the synthesis.
class IgrfModel {
 public:
  explicit IgrfModel(const IgrfCoefficientTable& table = builtin_igrf14());

  bool is_valid_date(double decimal_year) const;
  // Interpolate coefficients to this date; returns false (and leaves the model unchanged) if
  // the date is outside the table's validity.
  bool set_date(double decimal_year);
  double date() const { return date_year_; }

  // Field at a geocentric point for the current date. Exact at the poles (no 1/sin(theta)).
  GeocentricField field_geocentric(const GeocentricPosition& p) const;
  // Field vector in ECEF (ITRF) axes at an ECEF position, for the current date.
  Eigen::Vector3d field_ecef_nT(const Eigen::Vector3d& r_ecef_m) const;

  const IgrfCoefficientTable& table() const { return table_; }

 private:
  IgrfCoefficientTable table_;
  double date_year_ = 0.0;
  std::vector<double> g_;  // coefficients at date_year_, packed as in the table
  std::vector<double> h_;
};

}  // namespace magcal
