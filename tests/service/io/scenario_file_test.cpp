#include "service/io/scenario_file.hpp"

#include <catch2/catch.hpp>

#include <string>

using namespace magcal;

namespace {
const std::string kScenarioDir = std::string(MAGCAL_SOURCE_DIR) + "/deploy/scenarios/";

// Field-by-field equality (degree round trips allow a few ulps).
void check_same(const Scenario& a, const Scenario& b) {
  constexpr double kRel = 1e-13;
  CHECK(a.sat_id == b.sat_id);
  CHECK(a.epoch_utime == b.epoch_utime);
  CHECK(a.duration_s == Approx(b.duration_s).epsilon(kRel));
  CHECK(a.sample_period_s == b.sample_period_s);
  CHECK(a.seed == b.seed);
  CHECK(a.orbit.semi_major_axis_m == Approx(b.orbit.semi_major_axis_m).epsilon(kRel));
  CHECK(a.orbit.eccentricity == b.orbit.eccentricity);
  CHECK(a.orbit.inclination_rad == Approx(b.orbit.inclination_rad).epsilon(kRel));
  CHECK(a.orbit.raan_rad == Approx(b.orbit.raan_rad).margin(1e-15));
  CHECK(a.orbit_options.j2 == b.orbit_options.j2);
  CHECK(a.attitude.mode == b.attitude.mode);
  CHECK((a.attitude.omega0_body_rad_s - b.attitude.omega0_body_rad_s).norm() < 1e-15);
  CHECK(a.attitude.inertia_kg_m2 == b.attitude.inertia_kg_m2);
  const SensorModelParameters &p = a.sensor, &q = b.sensor;
  CHECK(p.bias_nT == q.bias_nT);
  CHECK(p.D == q.D);
  CHECK(p.permeability == q.permeability);
  CHECK(p.internal_misalignment_mrad == q.internal_misalignment_mrad);
  CHECK(p.installation_deg == q.installation_deg);
  CHECK(p.noise_sigma_nT == q.noise_sigma_nT);
  CHECK(p.nonlinearity_fraction_fs == q.nonlinearity_fraction_fs);
  CHECK(p.hysteresis_fraction_fs == q.hysteresis_fraction_fs);
  CHECK(p.full_scale_nT == q.full_scale_nT);
  CHECK(p.saturation == q.saturation);
  CHECK(p.nbits == q.nbits);
  CHECK(p.temperature_coefficient_nT_per_C == q.temperature_coefficient_nT_per_C);
  CHECK(p.drift_nT_per_day == q.drift_nT_per_day);
  CHECK(p.temperature_amplitude_C == q.temperature_amplitude_C);
  CHECK(a.attitude_noise_deg == b.attitude_noise_deg);
  CHECK(a.gnss_noise_m == b.gnss_noise_m);
}
}  // namespace

TEST_CASE("deploy/scenarios/paper.toml and pure.toml equal the presets") {
  for (const char* name : {"paper", "pure"}) {
    INFO(name);
    const ScenarioLoadResult r = load_scenario_file(kScenarioDir + name + ".toml");
    REQUIRE(r.error == "");
    check_same(*r.scenario, *scenario_preset(name));
  }
  const ScenarioLoadResult t = load_scenario_file(kScenarioDir + "tumbling.toml");
  REQUIRE(t.error == "");
  CHECK(t.scenario->attitude.mode == AttitudeMode::tumbling);
  CHECK(t.scenario->gnss_noise_m == 10.0);
  CHECK(t.scenario->sensor.temperature_amplitude_C == 10.0);
}

TEST_CASE("scenario_to_toml round-trips through the parser") {
  for (const auto& name : scenario_preset_names()) {
    INFO(name);
    Scenario s = *scenario_preset(name);
    s.sensor.drift_nT_per_day = Eigen::Vector3d(1.5, -2.0, 0.25);
    s.attitude_noise_deg = 0.02;
    const ScenarioLoadResult r = parse_scenario_toml(scenario_to_toml(s), "roundtrip");
    REQUIRE(r.error == "");
    check_same(*r.scenario, s);
  }
}

TEST_CASE("a small file overrides only what it names") {
  const ScenarioLoadResult r = parse_scenario_toml(
      "base = \"paper\"\nsat_id = \"X-9\"\nduration_h = 1\n[orbit]\naltitude_km = 700\nj2 = "
      "\"secular\"\n"
      "[sensor]\nnbits = 12\n",
      "mini.toml");
  REQUIRE(r.error == "");
  CHECK(r.scenario->sat_id == "X-9");
  CHECK(r.scenario->sample_count() == 360);
  CHECK(r.scenario->orbit.semi_major_axis_m == Approx(kEarthEquatorialRadius_m + 700e3));
  CHECK(r.scenario->orbit_options.j2 == J2Model::secular);
  CHECK(r.scenario->sensor.nbits == 12);
  CHECK(r.scenario->sensor.bias_nT == scenario_preset("paper")->sensor.bias_nT);
}

TEST_CASE("scenario file errors name the key") {
  auto error_of = [](const std::string& text) { return parse_scenario_toml(text, "f.toml").error; };
  CHECK(error_of("[sensor]\nbias_nt = [1, 2, 3]\n").find("sensor.bias_nt: unknown key") !=
        std::string::npos);
  CHECK(error_of("colour = 1\n").find("colour: unknown key") != std::string::npos);
  CHECK(error_of("[orbit]\neccentricity = 1.5\n").find("orbit.eccentricity") != std::string::npos);
  CHECK(error_of("[orbit]\ninclination_deg = \"high\"\n")
            .find("orbit.inclination_deg: must be a number") != std::string::npos);
  CHECK(error_of("[sensor]\nD = [[1, 2], [3, 4]]\n").find("sensor.D") != std::string::npos);
  CHECK(error_of("[sensor]\nnbits = 2\n").find("sensor.nbits") != std::string::npos);
  CHECK(error_of("[sensor]\nnbits = 12.5\n").find("sensor.nbits: must be an integer") !=
        std::string::npos);
  CHECK(error_of("[sensor]\nnoise_sigma_nT = -3\n").find("sensor.noise_sigma_nT") !=
        std::string::npos);
  CHECK(error_of("[attitude]\nmode = \"wobble\"\n").find("attitude.mode") != std::string::npos);
  CHECK(error_of("[attitude]\nmode = \"tumbling\"\ninertia_kg_m2 = [1, 1, 5]\n")
            .find("attitude.inertia_kg_m2") != std::string::npos);
  CHECK(error_of("epoch = \"yesterday\"\n").find("epoch") != std::string::npos);
  CHECK(error_of("epoch = \"1850-01-01\"\n").find("epoch") != std::string::npos);
  CHECK(error_of("base = \"nope\"\n").find("base") != std::string::npos);
  CHECK(error_of("sensor = 3\n").find("sensor: must be a table") != std::string::npos);
  CHECK(error_of("[knowledge]\ngnss_noise_m = -1\n").find("knowledge.gnss_noise_m") !=
        std::string::npos);
  CHECK(error_of("[temperature]\nmean = 3\n").find("temperature.mean: unknown key") !=
        std::string::npos);
  CHECK(error_of("[orbit]\naltitude_km = 500\nsemi_major_axis_km = 7000\n")
            .find("orbit.altitude_km") != std::string::npos);
  // Syntax errors carry the line.
  const std::string syntax = error_of("seed = 1\n[orbit\n");
  CHECK(syntax.find("f.toml line 2") != std::string::npos);
  CHECK(load_scenario_file("/nonexistent/x.toml").error.find("cannot open") != std::string::npos);
  CHECK(resolve_scenario("papr").error.find("unknown scenario preset") != std::string::npos);
  CHECK(resolve_scenario("pure").ok());
}
