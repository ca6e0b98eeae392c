// The Monte-Carlo harness (service/analysis/evaluation.hpp) on short spans: the paper scenario
// beats the paper's table by 3x with the alignment error below 0.03 deg, the pure-model scenario
// sits at the CRLB, the thermal rows show what the temperature model removes, and the table/JSON
// carry every row and the paper's numbers.
#include <cmath>

#include <catch2/catch.hpp>

#include "pipeline/scenario.hpp"
#include "service/analysis/evaluation.hpp"

using namespace magcal;

namespace {
const MethodStats& row(const EvaluationReport& r, const std::string& method) {
  for (const MethodStats& s : r.rows)
    if (s.method == method) return s;
  FAIL("no row " << method);
  return r.rows.front();
}
}  // namespace

TEST_CASE("paper scenario: every method >= 3x below the paper's bias MSE, alignment < 0.03 deg") {
  EvaluationOptions o;
  o.scenario = *scenario_preset("paper");
  o.runs = 3;
  o.seed = 100;
  REQUIRE(o.validate().empty());
  const EvaluationReport r = run_evaluation(o);
  REQUIRE(r.rows.size() == 10);
  for (const MethodStats& s : r.rows) {
    INFO(s.method);
    CHECK(s.runs_failed == 0);
    if (!std::isnan(s.paper.bias_mse_nT2)) {
      CHECK(s.bias_mse_nT2 * 3.0 <= s.paper.bias_mse_nT2);
    }
  }
  CHECK(row(r, "align Procrustes").alignment_error_deg < 0.03);
  CHECK(row(r, "align small-angle LS").alignment_error_deg < 0.03);
  // The thermal variant (+-15 degC, ~1 nT/degC): the temperature model removes the bias error
  // the 9-parameter fit keeps, and its reported sigma stays within 1 nT.
  const MethodStats& no_kt = row(r, "LM thermal, no temp");
  const MethodStats& kt = row(r, "LM thermal + k_T");
  CHECK(kt.runs_ok == 3);
  CHECK(kt.runs_rejected == 0);
  CHECK(kt.bias_mse_nT2 < no_kt.bias_mse_nT2);
  CHECK(kt.reported_sigma_nT <= 1.0);
  const nlohmann::json j = evaluation_to_json(r);
  CHECK(j["rows"].size() == 10);
  CHECK(j["rows"][1]["paper"]["bias_mse_nT2"] == 110.0);
  const std::string table = format_evaluation_table(r);
  CHECK(table.find("centered+LM") != std::string::npos);
  CHECK(table.find("(110)") != std::string::npos);
}

TEST_CASE("pure scenario: centered+LM near the CRLB (few runs: loose bound)") {
  EvaluationOptions o;
  o.scenario = *scenario_preset("pure");
  o.runs = 4;
  o.offline_hours = 2.0;
  o.online_hours = 3.0;
  REQUIRE(o.validate().empty());
  const EvaluationReport r = run_evaluation(o);
  const MethodStats& lm = row(r, "centered+LM");
  CHECK(lm.runs_ok == 4);
  // 12 pooled errors: the RMS ratio of an efficient estimator is within ~[0.6, 1.4] (chi2(12)
  // 99.9 %); the >= 50-run 1.3 bound is checked by `magcal evaluate --scenario pure --runs 50`
  // and by batch_calibration_test on model data.
  CHECK(lm.crlb_ratio < 1.6);
  CHECK(lm.alignment_error_deg < 0.01);
}

TEST_CASE("pure thermal scenario without a temperature channel: the sigma covers the swing") {
  // The sensor's bias swings +-15 degC x k_T with the orbit and no sample carries a temperature:
  // the refit reports the window's mean bias with the swing's variance (a sigma of 1.37 nT for a
  // 1.9 nT per-axis error before the swing term; 11 nT with it, 50 runs).
  EvaluationOptions o;
  o.scenario = *scenario_preset("pure");
  o.runs = 3;
  o.online = false;
  REQUIRE(o.validate().empty());
  const EvaluationReport r = run_evaluation(o);
  const MethodStats& no_temp = row(r, "LM thermal, no temp");
  CHECK(no_temp.runs_failed == 0);
  CHECK(std::sqrt(no_temp.bias_mse_nT2 / 3.0) < no_temp.reported_sigma_nT);
}

TEST_CASE("evaluation options are validated") {
  EvaluationOptions o;
  o.scenario = *scenario_preset("paper");
  o.runs = 0;
  CHECK_FALSE(o.validate().empty());
  o.runs = 1;
  o.online_hours = 6.0;  // not above offline_hours
  CHECK_FALSE(o.validate().empty());
}
