#include "service/io/scenario_file.hpp"

#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <sstream>

#include <toml++/toml.h>

#include "pipeline/rotation.hpp"
#include "pipeline/time_utc.hpp"

namespace magcal {

namespace {

// Reads one TOML table, remembering which keys were used so unknown ones can be reported.
class TableReader {
 public:
  TableReader(const toml::table* table, std::string prefix, std::string* error)
      : table_(table), prefix_(std::move(prefix)), error_(error) {}

  std::string key_name(std::string_view key) const { return prefix_ + std::string(key); }

  const toml::node* find(std::string_view key) {
    used_.insert(std::string(key));
    return table_ ? table_->get(key) : nullptr;
  }
  void fail(std::string_view key, const std::string& what) {
    if (error_->empty()) *error_ = key_name(key) + ": " + what;
  }

  void number(std::string_view key, double* out) {
    const toml::node* n = find(key);
    if (!n) return;
    if (auto v = n->value<double>(); v && (n->is_floating_point() || n->is_integer())) {
      if (!std::isfinite(*v)) return fail(key, "must be finite");
      *out = *v;
    } else {
      fail(key, "must be a number");
    }
  }
  void integer(std::string_view key, int64_t* out) {
    const toml::node* n = find(key);
    if (!n) return;
    if (auto v = n->value_exact<int64_t>()) {
      *out = *v;
    } else {
      fail(key, "must be an integer");
    }
  }
  void boolean(std::string_view key, bool* out) {
    const toml::node* n = find(key);
    if (!n) return;
    if (auto v = n->value_exact<bool>()) {
      *out = *v;
    } else {
      fail(key, "must be true or false");
    }
  }
  void string(std::string_view key, std::string* out) {
    const toml::node* n = find(key);
    if (!n) return;
    if (auto v = n->value_exact<std::string>()) {
      *out = *v;
    } else {
      fail(key, "must be a string");
    }
  }
  template <int N>
  void vector(std::string_view key, Eigen::Matrix<double, N, 1>* out) {
    const toml::node* n = find(key);
    if (!n) return;
    const toml::array* a = n->as_array();
    if (!a || a->size() != N)
      return fail(key, "must be an array of " + std::to_string(N) + " numbers");
    Eigen::Matrix<double, N, 1> v;
    for (int i = 0; i < N; ++i) {
      auto x = (*a)[static_cast<size_t>(i)].value<double>();
      const toml::node& e = (*a)[static_cast<size_t>(i)];
      if (!x || !(e.is_floating_point() || e.is_integer()) || !std::isfinite(*x))
        return fail(key, "must be an array of " + std::to_string(N) + " finite numbers");
      v(i) = *x;
    }
    *out = v;
  }
  void matrix3(std::string_view key, Eigen::Matrix3d* out) {
    const toml::node* n = find(key);
    if (!n) return;
    const toml::array* a = n->as_array();
    const std::string what = "must be a 3x3 array of arrays of finite numbers";
    if (!a || a->size() != 3) return fail(key, what);
    Eigen::Matrix3d m;
    for (size_t r = 0; r < 3; ++r) {
      const toml::array* row = (*a)[r].as_array();
      if (!row || row->size() != 3) return fail(key, what);
      for (size_t c = 0; c < 3; ++c) {
        const toml::node& e = (*row)[c];
        auto x = e.value<double>();
        if (!x || !(e.is_floating_point() || e.is_integer()) || !std::isfinite(*x))
          return fail(key, what);
        m(static_cast<int>(r), static_cast<int>(c)) = *x;
      }
    }
    *out = m;
  }
  // Reports the first key of this table that nobody asked for.
  void check_unknown() {
    if (!table_) return;
    for (const auto& [k, v] : *table_) {
      if (!used_.count(std::string(k.str()))) {
        if (error_->empty()) *error_ = key_name(k.str()) + ": unknown key";
        return;
      }
    }
  }

 private:
  const toml::table* table_;
  std::string prefix_;
  std::string* error_;
  std::set<std::string> used_;
};

const char* j2_name(J2Model m) {
  return m == J2Model::secular ? "secular" : "none";
}
const char* mode_name(AttitudeMode m) {
  switch (m) {
    case AttitudeMode::nadir:
      return "nadir";
    case AttitudeMode::inertial:
      return "inertial";
    case AttitudeMode::spin:
      return "spin";
    case AttitudeMode::tumbling:
      return "tumbling";
  }
  return "nadir";
}

void read_orbit(TableReader& r, Scenario& s) {
  double a_km = s.orbit.semi_major_axis_m / 1000.0;
  const bool has_alt = r.find("altitude_km") != nullptr;
  const bool has_sma = r.find("semi_major_axis_km") != nullptr;
  if (has_alt && has_sma)
    return r.fail("altitude_km", "give altitude_km or semi_major_axis_km, not both");
  if (has_alt) {
    double alt = 0.0;
    r.number("altitude_km", &alt);
    if (alt < 100.0 || alt > 1e6) return r.fail("altitude_km", "must be in [100, 1e6] km");
    a_km = kEarthEquatorialRadius_m / 1000.0 + alt;
  }
  if (has_sma) r.number("semi_major_axis_km", &a_km);
  s.orbit.semi_major_axis_m = a_km * 1000.0;
  double inc = s.orbit.inclination_rad / kDegToRad, raan = s.orbit.raan_rad / kDegToRad;
  double argp = s.orbit.arg_perigee_rad / kDegToRad, m0 = s.orbit.mean_anomaly_rad / kDegToRad;
  r.number("eccentricity", &s.orbit.eccentricity);
  r.number("inclination_deg", &inc);
  r.number("raan_deg", &raan);
  r.number("arg_perigee_deg", &argp);
  r.number("mean_anomaly_deg", &m0);
  s.orbit.inclination_rad = inc * kDegToRad;
  s.orbit.raan_rad = raan * kDegToRad;
  s.orbit.arg_perigee_rad = argp * kDegToRad;
  s.orbit.mean_anomaly_rad = m0 * kDegToRad;
  std::string j2 = j2_name(s.orbit_options.j2);
  r.string("j2", &j2);
  if (j2 == "none") {
    s.orbit_options.j2 = J2Model::none;
  } else if (j2 == "secular") {
    s.orbit_options.j2 = J2Model::secular;
  } else {
    r.fail("j2", "must be \"none\" or \"secular\"");
  }
}

void read_attitude(TableReader& r, AttitudeProfileOptions& a) {
  std::string mode = mode_name(a.mode);
  r.string("mode", &mode);
  if (mode == "nadir") {
    a.mode = AttitudeMode::nadir;
  } else if (mode == "inertial") {
    a.mode = AttitudeMode::inertial;
  } else if (mode == "spin") {
    a.mode = AttitudeMode::spin;
  } else if (mode == "tumbling") {
    a.mode = AttitudeMode::tumbling;
  } else {
    r.fail("mode", "must be one of nadir, inertial, spin, tumbling");
  }
  r.vector<4>("q0_body_from_eci", &a.q0_body_from_eci);
  r.vector<3>("spin_axis_body", &a.spin_axis_body);
  double rate = a.spin_rate_rad_s / kDegToRad;
  r.number("spin_rate_deg_s", &rate);
  a.spin_rate_rad_s = rate * kDegToRad;
  r.vector<3>("inertia_kg_m2", &a.inertia_kg_m2);
  Eigen::Vector3d w = a.omega0_body_rad_s / kDegToRad;
  r.vector<3>("omega0_deg_s", &w);
  a.omega0_body_rad_s = w * kDegToRad;
  r.number("integration_step_s", &a.integration_step_s);
}

void read_sensor(TableReader& r, SensorModelParameters& p) {
  r.vector<3>("bias_nT", &p.bias_nT);
  r.matrix3("D", &p.D);
  r.matrix3("permeability", &p.permeability);
  r.vector<3>("internal_misalignment_mrad", &p.internal_misalignment_mrad);
  r.vector<3>("installation_deg", &p.installation_deg);
  r.number("noise_sigma_nT", &p.noise_sigma_nT);
  r.number("nonlinearity_fraction_fs", &p.nonlinearity_fraction_fs);
  r.number("hysteresis_fraction_fs", &p.hysteresis_fraction_fs);
  r.number("full_scale_nT", &p.full_scale_nT);
  r.boolean("saturation", &p.saturation);
  int64_t nbits = p.nbits;
  r.integer("nbits", &nbits);
  if (nbits < 0 || nbits > 64) r.fail("nbits", "must be 0 (off) or 4..32");
  p.nbits = static_cast<int>(nbits);
  r.vector<3>("temperature_coefficient_nT_per_C", &p.temperature_coefficient_nT_per_C);
  r.number("reference_temperature_C", &p.reference_temperature_C);
  r.vector<3>("drift_nT_per_day", &p.drift_nT_per_day);
}

void read_temperature(TableReader& r, SensorModelParameters& p) {
  r.number("mean_C", &p.temperature_mean_C);
  r.number("amplitude_C", &p.temperature_amplitude_C);
  r.number("period_s", &p.temperature_period_s);
  r.number("phase_deg", &p.temperature_phase_deg);
}

const toml::table* subtable(const toml::table& root, std::string_view key, std::string* error) {
  const toml::node* n = root.get(key);
  if (!n) return nullptr;
  if (!n->is_table() && error->empty())
    *error = std::string(key) + ": must be a table [" + std::string(key) + "]";
  return n->as_table();
}

}  // namespace

ScenarioLoadResult parse_scenario_toml(std::string_view text, std::string_view source_name) {
  ScenarioLoadResult result;
  const std::string src(source_name);
  toml::table root;
  try {
    root = toml::parse(text, src);
  } catch (const toml::parse_error& e) {
    std::ostringstream os;
    os << src << " line " << e.source().begin.line << ": " << e.description();
    result.error = os.str();
    return result;
  }
  std::string error;
  TableReader top(&root, "", &error);
  std::string base = "paper";
  top.string("base", &base);
  std::optional<Scenario> start = scenario_preset(base);
  if (!start) {
    result.error = src + ": base: unknown preset \"" + base + "\"";
    return result;
  }
  Scenario s = *start;
  // Without a `name` key the scenario is called after its file, never after its base preset:
  // a report must not say "paper" for data that is not the paper's.
  s.name = base + " (" + std::filesystem::path(src).filename().string() + ")";
  top.string("name", &s.name);
  top.string("sat_id", &s.sat_id);
  std::string epoch;
  top.string("epoch", &epoch);
  if (!epoch.empty()) {
    if (auto u = parse_iso8601_utc(epoch)) {
      s.epoch_utime = *u;
    } else {
      top.fail("epoch", "not an ISO 8601 UTC time");
    }
  }
  s.orbit.epoch_utime = s.epoch_utime;
  double hours = s.duration_s / 3600.0;
  top.number("duration_h", &hours);
  s.duration_s = hours * 3600.0;
  top.number("sample_period_s", &s.sample_period_s);
  int64_t seed = static_cast<int64_t>(s.seed);
  top.integer("seed", &seed);
  if (seed < 0) top.fail("seed", "must be >= 0");
  s.seed = static_cast<uint64_t>(seed);
  for (const char* t : {"orbit", "attitude", "sensor", "temperature", "knowledge"}) top.find(t);
  top.check_unknown();

  const toml::table* orbit = subtable(root, "orbit", &error);
  const toml::table* attitude = subtable(root, "attitude", &error);
  const toml::table* sensor = subtable(root, "sensor", &error);
  const toml::table* temperature = subtable(root, "temperature", &error);
  const toml::table* knowledge = subtable(root, "knowledge", &error);

  TableReader ro(orbit, "orbit.", &error);
  read_orbit(ro, s);
  ro.check_unknown();
  TableReader ra(attitude, "attitude.", &error);
  read_attitude(ra, s.attitude);
  ra.check_unknown();
  TableReader rs(sensor, "sensor.", &error);
  read_sensor(rs, s.sensor);
  rs.check_unknown();
  TableReader rt(temperature, "temperature.", &error);
  read_temperature(rt, s.sensor);
  rt.check_unknown();
  TableReader rk(knowledge, "knowledge.", &error);
  rk.number("attitude_noise_deg", &s.attitude_noise_deg);
  rk.number("gnss_noise_m", &s.gnss_noise_m);
  rk.boolean("temperature_reported", &s.temperature_reported);
  rk.check_unknown();

  if (error.empty()) error = s.validate();
  if (!error.empty()) {
    result.error = src + ": " + error;
    return result;
  }
  result.scenario = std::move(s);
  return result;
}

ScenarioLoadResult load_scenario_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) return {std::nullopt, path + ": cannot open scenario file"};
  std::ostringstream os;
  os << in.rdbuf();
  return parse_scenario_toml(os.str(), path);
}

ScenarioLoadResult resolve_scenario(const std::string& preset_or_path) {
  if (auto s = scenario_preset(preset_or_path)) return {std::move(s), ""};
  if (preset_or_path.find('.') == std::string::npos &&
      preset_or_path.find('/') == std::string::npos) {
    std::string names;
    for (const auto& n : scenario_preset_names()) names += (names.empty() ? "" : ", ") + n;
    return {std::nullopt, "unknown scenario preset \"" + preset_or_path + "\" (presets: " + names +
                              "; or give a FILE.toml)"};
  }
  return load_scenario_file(preset_or_path);
}

std::string scenario_to_toml(const Scenario& s) {
  auto vec = [](const auto& v) {
    toml::array a;
    for (int i = 0; i < v.size(); ++i) a.push_back(v(i));
    return a;
  };
  auto mat = [&](const Eigen::Matrix3d& m) {
    toml::array a;
    for (int r = 0; r < 3; ++r) a.push_back(vec(Eigen::Vector3d(m.row(r).transpose())));
    return a;
  };
  toml::table root;
  root.insert("name", s.name);
  root.insert("sat_id", s.sat_id);
  root.insert("epoch", format_iso8601_utc(s.epoch_utime, 6));
  root.insert("duration_h", s.duration_s / 3600.0);
  root.insert("sample_period_s", s.sample_period_s);
  root.insert("seed", static_cast<int64_t>(s.seed));
  toml::table orbit;
  orbit.insert("semi_major_axis_km", s.orbit.semi_major_axis_m / 1000.0);
  orbit.insert("eccentricity", s.orbit.eccentricity);
  orbit.insert("inclination_deg", s.orbit.inclination_rad / kDegToRad);
  orbit.insert("raan_deg", s.orbit.raan_rad / kDegToRad);
  orbit.insert("arg_perigee_deg", s.orbit.arg_perigee_rad / kDegToRad);
  orbit.insert("mean_anomaly_deg", s.orbit.mean_anomaly_rad / kDegToRad);
  orbit.insert("j2", j2_name(s.orbit_options.j2));
  root.insert("orbit", orbit);
  toml::table att;
  att.insert("mode", mode_name(s.attitude.mode));
  att.insert("q0_body_from_eci", vec(s.attitude.q0_body_from_eci));
  att.insert("spin_axis_body", vec(s.attitude.spin_axis_body));
  att.insert("spin_rate_deg_s", s.attitude.spin_rate_rad_s / kDegToRad);
  att.insert("inertia_kg_m2", vec(s.attitude.inertia_kg_m2));
  att.insert("omega0_deg_s", vec(Eigen::Vector3d(s.attitude.omega0_body_rad_s / kDegToRad)));
  att.insert("integration_step_s", s.attitude.integration_step_s);
  root.insert("attitude", att);
  const SensorModelParameters& p = s.sensor;
  toml::table sen;
  sen.insert("bias_nT", vec(p.bias_nT));
  sen.insert("D", mat(p.D));
  sen.insert("permeability", mat(p.permeability));
  sen.insert("internal_misalignment_mrad", vec(p.internal_misalignment_mrad));
  sen.insert("installation_deg", vec(p.installation_deg));
  sen.insert("noise_sigma_nT", p.noise_sigma_nT);
  sen.insert("nonlinearity_fraction_fs", p.nonlinearity_fraction_fs);
  sen.insert("hysteresis_fraction_fs", p.hysteresis_fraction_fs);
  sen.insert("full_scale_nT", p.full_scale_nT);
  sen.insert("saturation", p.saturation);
  sen.insert("nbits", static_cast<int64_t>(p.nbits));
  sen.insert("temperature_coefficient_nT_per_C", vec(p.temperature_coefficient_nT_per_C));
  sen.insert("reference_temperature_C", p.reference_temperature_C);
  sen.insert("drift_nT_per_day", vec(p.drift_nT_per_day));
  root.insert("sensor", sen);
  toml::table temp;
  temp.insert("mean_C", p.temperature_mean_C);
  temp.insert("amplitude_C", p.temperature_amplitude_C);
  temp.insert("period_s", p.temperature_period_s);
  temp.insert("phase_deg", p.temperature_phase_deg);
  root.insert("temperature", temp);
  toml::table know;
  know.insert("attitude_noise_deg", s.attitude_noise_deg);
  know.insert("gnss_noise_m", s.gnss_noise_m);
  know.insert("temperature_reported", s.temperature_reported);
  root.insert("knowledge", know);
  std::ostringstream os;
  os << root << "\n";
  return os.str();
}

}  // namespace magcal
