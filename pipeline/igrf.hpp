// IGRF spherical-harmonic main-field synthesis (Schmidt semi-normalised Gauss coefficients).
//
//   B = -grad V,  V(r, theta, phi) = a sum_{n=1..N} (a/r)^{n+1} sum_{m=0..n}
//                  (g_n^m cos m phi + h_n^m sin m phi) P_n^m(cos theta),   a = 6371.2 km
//
// Coefficients are piecewise linear in decimal year between the model epochs; after the last
// main-field epoch they follow the secular variation (the official rule). The SV is stored as
// one more knot at the end of validity, c(end) = c(last) + (end - last) SV (which is what the
// official .shc file carries), so one piecewise-linear rule covers the whole span. Dates
// outside the model's validity are refused.
//
// Synthesis: Schmidt semi-normalised P_n^m(cos theta) by the standard recursions, with
// Q_n^m = P_n^m / sin(theta) (m >= 1) carried by the same recursions (Q_1^1 = 1), so B_phi and
// dP/dtheta never divide by sin(theta): the poles are exact, not a limit. Fixed-size stack
// arrays up to kIgrfMaxDegree; no heap allocation per evaluation.
//   B_r     =  sum (n+1) (a/r)^(n+2) sum (g cos m phi + h sin m phi) P_n^m
//   B_theta = -sum (a/r)^(n+2) sum (g cos m phi + h sin m phi) dP_n^m/dtheta
//   B_phi   =  sum (a/r)^(n+2) sum m (g sin m phi - h cos m phi) Q_n^m The built-in table is
//   IGRF-14 (1900.0-2030.0, degree 13),
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
// Largest degree any loaded file may have (files with more are refused).
constexpr int kIgrfMaxDegree = 20;

// Packed index of (n, m), n >= 1, 0 <= m <= n: n = 1 -> 0, 1; n = 2 -> 2, 3, 4; ...
constexpr int igrf_pack_index(int n, int m) {
  return n * (n + 1) / 2 - 1 + m;
}
constexpr int igrf_packed_size(int max_degree) {
  return max_degree * (max_degree + 3) / 2;
}

// All epochs' coefficients, in the model's native layout.
struct IgrfCoefficientTable {
  std::string name;                 // e.g. "IGRF-14"
  int max_degree = 0;               // 13 for IGRF-14
  double valid_from_year = 0.0;     // 1900.0
  double valid_to_year = 0.0;       // 2030.0
  std::vector<double> epochs_year;  // knots of the piecewise-linear time dependence
  // g_nT[e] / h_nT[e]: coefficients at knot e, packed with igrf_pack_index (h(n,0) = 0),
  // igrf_packed_size(max_degree) each, nT. The last knot is valid_to_year (see above).
  std::vector<std::vector<double>> g_nT;
  std::vector<std::vector<double>> h_nT;
};

// Builds a table from main-field epochs plus a secular variation (nT/yr) valid from the last
// epoch to valid_to_year (the official .txt layout), appending the SV knot at valid_to_year.
// Used by the .txt parser and the generated built-in table, so both give identical numbers.
IgrfCoefficientTable igrf_table_from_epochs_and_sv(std::string name, int max_degree,
                                                   std::vector<double> epochs_year,
                                                   std::vector<std::vector<double>> g_nT,
                                                   std::vector<std::vector<double>> h_nT,
                                                   const std::vector<double>& g_sv_nT_per_yr,
                                                   const std::vector<double>& h_sv_nT_per_yr,
                                                   double valid_to_year);

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
// many positions at the same date costs only the synthesis (callers decide when to re-date).
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
  // Rotates a geocentric (r, theta, phi) field into ECEF axes at that point.
  static Eigen::Vector3d ecef_from_geocentric_field(const GeocentricField& b,
                                                    const GeocentricPosition& p);

  const IgrfCoefficientTable& table() const { return table_; }

 private:
  IgrfCoefficientTable table_;
  double date_year_ = 0.0;
  std::vector<double> g_;  // coefficients at date_year_, packed as in the table
  std::vector<double> h_;
};

}  // namespace magcal
