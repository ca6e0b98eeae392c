// status_report (magcal status and /api/v1/spacecraft): the bias change between the last two
// refits, at one temperature when both model the bias temperature.
#include "service/io/status_report.hpp"

#include <catch2/catch.hpp>

using magcal::SpacecraftStatus;

namespace {

constexpr int64_t kT0 = 1577836800LL * 1'000'000;

magcal::storage::CalibrationRecord refit(int64_t utime, std::array<double, 3> bias_nT) {
  magcal::storage::CalibrationRecord r;
  r.sat_id = "S";
  r.method = "twostep";
  r.utime = utime;
  r.bias_nT = bias_nT;
  r.verdict = "accepted";
  return r;
}

}  // namespace

TEST_CASE("status: the bias change compares the two refits at the last one's T0") {
  // A sensor that did not change, k_T = (1.5, -1.5, 1.5) nT/degC, b(20 degC) = (1000, 800, 900):
  // refitted on windows whose mean temperatures (T0) were 17 and 22 degC.
  const std::array<double, 3> k = {1.5, -1.5, 1.5};
  auto at = [&](double t0_C) {
    return std::array<double, 3>{1000.0 + k[0] * (t0_C - 20.0), 800.0 + k[1] * (t0_C - 20.0),
                                 900.0 + k[2] * (t0_C - 20.0)};
  };
  SpacecraftStatus s;
  s.sat_id = "S";
  s.previous_refit = refit(kT0, at(17.0));
  s.last_refit = refit(kT0 + 21'600'000'000, at(22.0));
  const int64_t window = 43'200'000'000;

  SECTION("both modelled: no change") {
    for (auto* r : {&*s.previous_refit, &*s.last_refit}) {
      r->has_temperature_model = 1;
      r->temperature_coefficient_nT_per_C = k;
    }
    s.previous_refit->reference_temperature_C = 17.0;
    s.last_refit->reference_temperature_C = 22.0;
    const auto j = magcal::status_json({s}, window);
    const auto& d = j["spacecraft"][0]["bias_change_since_previous_refit_nT"];
    for (int i = 0; i < 3; ++i) CHECK(d[i].get<double>() == Approx(0.0).margin(1e-9));
    CHECK(magcal::status_text({s}, window).find("both at 22.00 degC") != std::string::npos);
  }
  SECTION("not modelled: the plain difference, and no temperature line") {
    const auto j = magcal::status_json({s}, window);
    const auto& d = j["spacecraft"][0]["bias_change_since_previous_refit_nT"];
    for (int i = 0; i < 3; ++i) CHECK(d[i].get<double>() == Approx(k[i] * 5.0));
    CHECK(magcal::status_text({s}, window).find("degC") == std::string::npos);
  }
}
