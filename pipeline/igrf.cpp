// IGRF synthesis, time interpolation and the coefficient-file parser (see igrf.hpp).
#include "pipeline/igrf.hpp"

#include <array>
#include <cctype>
#include <charconv>
#include <cmath>
#include <utility>

namespace magcal {
namespace {

constexpr int kMaxPacked = igrf_packed_size(kIgrfMaxDegree);

// ---------------------------------------------------------------------------------------------
// Parsing helpers.

std::vector<std::string_view> split_tokens(std::string_view line) {
  std::vector<std::string_view> out;
  size_t i = 0;
  while (i < line.size()) {
    while (i < line.size() && std::isspace(static_cast<unsigned char>(line[i]))) ++i;
    const size_t start = i;
    while (i < line.size() && !std::isspace(static_cast<unsigned char>(line[i]))) ++i;
    if (i > start) out.push_back(line.substr(start, i - start));
  }
  return out;
}

std::optional<double> to_double(std::string_view s) {
  double v = 0.0;
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
  if (ec != std::errc() || ptr != s.data() + s.size() || !std::isfinite(v)) return std::nullopt;
  return v;
}

std::optional<int> to_int(std::string_view s) {
  int v = 0;
  const auto [ptr, ec] = std::from_chars(s.data(), s.data() + s.size(), v);
  if (ec != std::errc() || ptr != s.data() + s.size()) return std::nullopt;
  return v;
}

struct Line {
  int number;  // 1-based
  std::string_view text;
};

// Non-empty, non-comment lines with their numbers; comment lines are collected separately.
void split_lines(std::string_view text, std::vector<Line>* data,
                 std::vector<std::string_view>* comments) {
  int number = 0;
  size_t pos = 0;
  while (pos <= text.size()) {
    size_t end = text.find('\n', pos);
    if (end == std::string_view::npos) end = text.size();
    std::string_view line = text.substr(pos, end - pos);
    if (!line.empty() && line.back() == '\r') line.remove_suffix(1);
    ++number;
    const auto first = line.find_first_not_of(" \t");
    if (first != std::string_view::npos) {
      if (line[first] == '#') {
        comments->push_back(line);
      } else {
        data->push_back({number, line});
      }
    }
    if (end == text.size()) break;
    pos = end + 1;
  }
}

// "IGRF-14" if a comment names the generation ("14th Generation ..." or "IGRF 14"), else "IGRF".
std::string model_name_from_comments(const std::vector<std::string_view>& comments) {
  for (std::string_view c : comments) {
    const auto tokens = split_tokens(c);
    for (size_t i = 0; i < tokens.size(); ++i) {
      std::string_view t = tokens[i];
      if (i + 1 < tokens.size() && (t == "IGRF" || t == "igrf") && to_int(tokens[i + 1]))
        return "IGRF-" + std::string(tokens[i + 1]);
      size_t digits = 0;
      while (digits < t.size() && std::isdigit(static_cast<unsigned char>(t[digits]))) ++digits;
      if (digits > 0 && i + 1 < tokens.size() &&
          (tokens[i + 1] == "Generation" || tokens[i + 1] == "generation"))
        return "IGRF-" + std::string(t.substr(0, digits));
    }
  }
  return "IGRF";
}

std::string at_line(int number, const std::string& what) {
  return "line " + std::to_string(number) + ": " + what;
}

bool fail(std::string* error, std::string message) {
  if (error) *error = std::move(message);
  return false;
}

// Checks every coefficient n = 1..N, 0 <= m <= n (g) and 1 <= m <= n (h) was given.
bool check_complete(const std::vector<std::vector<char>>& seen_g,
                    const std::vector<std::vector<char>>& seen_h, int max_degree, int last_line,
                    std::string* error) {
  for (int n = 1; n <= max_degree; ++n) {
    for (int m = 0; m <= n; ++m) {
      const int k = igrf_pack_index(n, m);
      const char* missing = !seen_g[0][k] ? "g" : (m > 0 && !seen_h[0][k]) ? "h" : nullptr;
      if (missing) {
        return fail(
            error, at_line(last_line, "file ends without coefficient " + std::string(missing) +
                                          "(" + std::to_string(n) + "," + std::to_string(m) + ")"));
      }
    }
  }
  return true;
}

// The official IAGA/NCEI table: "c/s deg ord ..." labels, "g/h n m <epochs> YYYY-YY", rows.
std::optional<IgrfCoefficientTable> parse_txt(const std::vector<Line>& lines, std::string name,
                                              std::string* error) {
  size_t i = 0;
  if (i < lines.size() && split_tokens(lines[i].text).front() == "c/s") ++i;  // labels
  if (i >= lines.size()) {
    fail(error, "no epoch line (\"g/h n m 1900.0 ...\") found");
    return std::nullopt;
  }
  const auto header = split_tokens(lines[i].text);
  if (header.size() < 5 || header[0] != "g/h") {
    fail(error, at_line(lines[i].number, "expected the epoch line \"g/h n m <epochs> <SV>\""));
    return std::nullopt;
  }
  std::vector<double> epochs;
  for (size_t k = 3; k + 1 < header.size(); ++k) {
    const auto e = to_double(header[k]);
    if (!e || (!epochs.empty() && *e <= epochs.back())) {
      fail(error, at_line(lines[i].number,
                          "bad or non-increasing epoch '" + std::string(header[k]) + "'"));
      return std::nullopt;
    }
    epochs.push_back(*e);
  }
  // The SV column label reads e.g. "2025-30": SV valid from the last epoch to 2030.
  const std::string_view sv_label = header.back();
  double valid_to = epochs.back() + 5.0;
  const auto dash = sv_label.find('-');
  const auto sv_from =
      dash == std::string_view::npos ? std::nullopt : to_int(sv_label.substr(0, dash));
  const auto sv_to =
      dash == std::string_view::npos ? std::nullopt : to_int(sv_label.substr(dash + 1));
  if (!sv_from || !sv_to || *sv_from != static_cast<int>(epochs.back())) {
    fail(error, at_line(lines[i].number,
                        "last column must be the SV label \"YYYY-YY\" after the "
                        "last epoch, got '" +
                            std::string(sv_label) + "'"));
    return std::nullopt;
  }
  if (*sv_to < 100) {
    const int century = *sv_from / 100 * 100;
    valid_to = century + *sv_to + (century + *sv_to <= *sv_from ? 100 : 0);
  } else {
    valid_to = *sv_to;
  }
  ++i;

  const size_t n_epochs = epochs.size();
  std::vector<std::vector<double>> g(n_epochs, std::vector<double>(kMaxPacked, 0.0));
  std::vector<std::vector<double>> h = g;
  std::vector<double> g_sv(kMaxPacked, 0.0), h_sv(kMaxPacked, 0.0);
  std::vector<std::vector<char>> seen_g(1, std::vector<char>(kMaxPacked, 0)), seen_h = seen_g;
  int max_degree = 0;
  for (; i < lines.size(); ++i) {
    const auto tok = split_tokens(lines[i].text);
    const int ln = lines[i].number;
    if (tok.size() != n_epochs + 4) {
      fail(error, at_line(ln, "expected " + std::to_string(n_epochs + 4) + " columns (g|h n m, " +
                                  std::to_string(n_epochs) + " epochs, SV), got " +
                                  std::to_string(tok.size())));
      return std::nullopt;
    }
    const bool is_g = tok[0] == "g", is_h = tok[0] == "h";
    const auto n = to_int(tok[1]), m = to_int(tok[2]);
    if ((!is_g && !is_h) || !n || !m) {
      fail(error, at_line(ln, "expected \"g|h n m ...\""));
      return std::nullopt;
    }
    if (*n < 1 || *n > kIgrfMaxDegree || *m < 0 || *m > *n || (is_h && *m == 0)) {
      fail(error,
           at_line(ln, "invalid degree/order n=" + std::to_string(*n) + " m=" + std::to_string(*m) +
                           " (supported n = 1.." + std::to_string(kIgrfMaxDegree) + ")"));
      return std::nullopt;
    }
    const int k = igrf_pack_index(*n, *m);
    auto& seen = is_g ? seen_g[0] : seen_h[0];
    if (seen[k]) {
      fail(error, at_line(ln, "duplicate coefficient"));
      return std::nullopt;
    }
    seen[k] = 1;
    for (size_t e = 0; e <= n_epochs; ++e) {
      const auto v = to_double(tok[3 + e]);
      if (!v) {
        fail(error, at_line(ln, "bad number '" + std::string(tok[3 + e]) + "'"));
        return std::nullopt;
      }
      if (e < n_epochs) {
        (is_g ? g : h)[e][k] = *v;
      } else {
        (is_g ? g_sv : h_sv)[k] = *v;
      }
    }
    max_degree = std::max(max_degree, *n);
  }
  if (max_degree == 0) {
    fail(error, "no coefficient rows found");
    return std::nullopt;
  }
  if (!check_complete(seen_g, seen_h, max_degree, lines.back().number, error)) return std::nullopt;
  const int size = igrf_packed_size(max_degree);
  for (auto& v : g) v.resize(size);
  for (auto& v : h) v.resize(size);
  g_sv.resize(size);
  h_sv.resize(size);
  return igrf_table_from_epochs_and_sv(std::move(name), max_degree, std::move(epochs), std::move(g),
                                       std::move(h), g_sv, h_sv, valid_to);
}

// The .shc layout: "nmin nmax ntimes order step [start end]", an epochs line, "n m c..." rows
// (m < 0: h_n^|m|), piecewise linear in time (order 2).
std::optional<IgrfCoefficientTable> parse_shc(const std::vector<Line>& lines, std::string name,
                                              std::string* error) {
  const auto head = split_tokens(lines[0].text);
  std::vector<double> hv;
  for (auto t : head) {
    const auto v = to_double(t);
    if (!v) {
      fail(error, at_line(lines[0].number, "bad .shc header value '" + std::string(t) + "'"));
      return std::nullopt;
    }
    hv.push_back(*v);
  }
  const int nmin = static_cast<int>(hv[0]), nmax = static_cast<int>(hv[1]);
  const int ntimes = static_cast<int>(hv[2]), order = static_cast<int>(hv[3]);
  if (nmin != 1 || nmax < 1 || nmax > kIgrfMaxDegree || ntimes < 1) {
    fail(error, at_line(lines[0].number, ".shc header: need nmin = 1, 1 <= nmax <= " +
                                             std::to_string(kIgrfMaxDegree) + ", ntimes >= 1"));
    return std::nullopt;
  }
  if (!(order == 2 || (order == 1 && ntimes == 1))) {
    fail(error, at_line(lines[0].number,
                        ".shc header: only piecewise-linear (order 2) time "
                        "dependence is supported, got order " +
                            std::to_string(order)));
    return std::nullopt;
  }
  if (lines.size() < 2) {
    fail(error, at_line(lines[0].number, ".shc file ends before its epochs line"));
    return std::nullopt;
  }
  const auto etok = split_tokens(lines[1].text);
  std::vector<double> epochs;
  for (auto t : etok) {
    const auto v = to_double(t);
    if (!v || (!epochs.empty() && *v <= epochs.back())) {
      fail(error, at_line(lines[1].number, "bad or non-increasing epoch '" + std::string(t) + "'"));
      return std::nullopt;
    }
    epochs.push_back(*v);
  }
  if (static_cast<int>(epochs.size()) != ntimes) {
    fail(error, at_line(lines[1].number, "expected " + std::to_string(ntimes) +
                                             " epochs (header's ntimes), got " +
                                             std::to_string(epochs.size())));
    return std::nullopt;
  }
  const double valid_from = hv.size() >= 7 ? hv[5] : epochs.front();
  const double valid_to = hv.size() >= 7 ? hv[6] : epochs.back();
  if (valid_from < epochs.front() || valid_to > epochs.back() || valid_from > valid_to) {
    fail(error, at_line(lines[0].number, ".shc header: validity outside the epochs"));
    return std::nullopt;
  }

  const int size = igrf_packed_size(nmax);
  std::vector<std::vector<double>> g(ntimes, std::vector<double>(size, 0.0)), h = g;
  std::vector<std::vector<char>> seen_g(1, std::vector<char>(size, 0)), seen_h = seen_g;
  for (size_t i = 2; i < lines.size(); ++i) {
    const auto tok = split_tokens(lines[i].text);
    const int ln = lines[i].number;
    if (static_cast<int>(tok.size()) != ntimes + 2) {
      fail(error,
           at_line(ln, "expected " + std::to_string(ntimes + 2) + " columns (n m, " +
                           std::to_string(ntimes) + " epochs), got " + std::to_string(tok.size())));
      return std::nullopt;
    }
    const auto n = to_int(tok[0]), m = to_int(tok[1]);
    if (!n || !m || *n < 1 || *n > nmax || std::abs(*m) > *n) {
      fail(error, at_line(ln, "invalid degree/order (expected \"n m ...\" with 1 <= n <= " +
                                  std::to_string(nmax) + ", |m| <= n)"));
      return std::nullopt;
    }
    const bool is_h = *m < 0;
    const int k = igrf_pack_index(*n, std::abs(*m));
    auto& seen = is_h ? seen_h[0] : seen_g[0];
    if (seen[k]) {
      fail(error, at_line(ln, "duplicate coefficient"));
      return std::nullopt;
    }
    seen[k] = 1;
    for (int e = 0; e < ntimes; ++e) {
      const auto v = to_double(tok[2 + e]);
      if (!v) {
        fail(error, at_line(ln, "bad number '" + std::string(tok[2 + e]) + "'"));
        return std::nullopt;
      }
      (is_h ? h : g)[e][k] = *v;
    }
  }
  if (!check_complete(seen_g, seen_h, nmax, lines.back().number, error)) return std::nullopt;
  IgrfCoefficientTable t;
  t.name = std::move(name);
  t.max_degree = nmax;
  t.valid_from_year = valid_from;
  t.valid_to_year = valid_to;
  t.epochs_year = std::move(epochs);
  t.g_nT = std::move(g);
  t.h_nT = std::move(h);
  return t;
}

}  // namespace

IgrfCoefficientTable igrf_table_from_epochs_and_sv(std::string name, int max_degree,
                                                   std::vector<double> epochs_year,
                                                   std::vector<std::vector<double>> g_nT,
                                                   std::vector<std::vector<double>> h_nT,
                                                   const std::vector<double>& g_sv_nT_per_yr,
                                                   const std::vector<double>& h_sv_nT_per_yr,
                                                   double valid_to_year) {
  IgrfCoefficientTable t;
  t.name = std::move(name);
  t.max_degree = max_degree;
  t.valid_from_year = epochs_year.front();
  t.valid_to_year = valid_to_year;
  const double span = valid_to_year - epochs_year.back();
  std::vector<double> g_end = g_nT.back(), h_end = h_nT.back();
  for (size_t k = 0; k < g_end.size(); ++k) {
    g_end[k] += span * g_sv_nT_per_yr[k];
    h_end[k] += span * h_sv_nT_per_yr[k];
  }
  if (span > 0.0) {
    epochs_year.push_back(valid_to_year);
    g_nT.push_back(std::move(g_end));
    h_nT.push_back(std::move(h_end));
  }
  t.epochs_year = std::move(epochs_year);
  t.g_nT = std::move(g_nT);
  t.h_nT = std::move(h_nT);
  return t;
}

std::optional<IgrfCoefficientTable> parse_igrf_coefficients(std::string_view text,
                                                            std::string* error) {
  std::vector<Line> lines;
  std::vector<std::string_view> comments;
  split_lines(text, &lines, &comments);
  if (lines.empty()) {
    fail(error, "empty coefficient file (no data lines)");
    return std::nullopt;
  }
  std::string name = model_name_from_comments(comments);
  const auto first = split_tokens(lines[0].text);
  if (first[0] == "c/s" || first[0] == "g/h") return parse_txt(lines, std::move(name), error);
  bool numeric = first.size() >= 5 && first.size() <= 7;
  for (auto t : first) numeric = numeric && to_double(t).has_value();
  if (numeric) return parse_shc(lines, std::move(name), error);
  fail(error, at_line(lines[0].number,
                      "unrecognised coefficient file: expected the IGRF table (\"c/s deg ord\" / "
                      "\"g/h n m\" header) or a .shc header \"nmin nmax ntimes order step start "
                      "end\""));
  return std::nullopt;
}

// ---------------------------------------------------------------------------------------------
// Model.

IgrfModel::IgrfModel(const IgrfCoefficientTable& table) : table_(table) {
  // Start at the first knot so evaluation is defined even before set_date().
  date_year_ = table_.epochs_year.empty() ? 0.0 : table_.epochs_year.front();
  g_ = table_.g_nT.empty() ? std::vector<double>() : table_.g_nT.front();
  h_ = table_.h_nT.empty() ? std::vector<double>() : table_.h_nT.front();
}

bool IgrfModel::is_valid_date(double y) const {
  return std::isfinite(y) && y >= table_.valid_from_year && y <= table_.valid_to_year;
}

bool IgrfModel::set_date(double y) {
  if (!is_valid_date(y) || table_.epochs_year.empty()) return false;
  const auto& ep = table_.epochs_year;
  size_t i = 0;
  while (i + 2 < ep.size() && y >= ep[i + 1]) ++i;
  if (ep.size() == 1) {
    g_ = table_.g_nT[0];
    h_ = table_.h_nT[0];
  } else {
    const double w = (y - ep[i]) / (ep[i + 1] - ep[i]);
    const auto& g0 = table_.g_nT[i];
    const auto& g1 = table_.g_nT[i + 1];
    const auto& h0 = table_.h_nT[i];
    const auto& h1 = table_.h_nT[i + 1];
    for (size_t k = 0; k < g_.size(); ++k) {
      g_[k] = g0[k] + w * (g1[k] - g0[k]);
      h_[k] = h0[k] + w * (h1[k] - h0[k]);
    }
  }
  date_year_ = y;
  return true;
}

GeocentricField IgrfModel::field_geocentric(const GeocentricPosition& p) const {
  const int N = table_.max_degree;
  const double ct = std::cos(p.colatitude_rad), st = std::sin(p.colatitude_rad);
  // P: P_n^m (all m); Q: P_n^m / sin(theta) (m >= 1); both Schmidt semi-normalised.
  std::array<double, kMaxPacked + 1> P{}, Q{};
  auto at = [](int n, int m) { return igrf_pack_index(n, m) + 1; };  // slot 0 = P_0^0
  std::array<double, kIgrfMaxDegree + 1> cos_m{}, sin_m{};
  cos_m[0] = 1.0;
  const double cp = std::cos(p.longitude_rad), sp = std::sin(p.longitude_rad);
  for (int m = 1; m <= N; ++m) {
    cos_m[m] = cos_m[m - 1] * cp - sin_m[m - 1] * sp;
    sin_m[m] = sin_m[m - 1] * cp + cos_m[m - 1] * sp;
  }

  // Zonal P_n^0 and sectoral seeds, then the degree recursion for each order:
  //   P_n^m = ((2n-1) cos P_{n-1}^m - sqrt((n-1)^2 - m^2) P_{n-2}^m) / sqrt(n^2 - m^2)
  // The same linear recursion holds for Q = P / sin(theta) with Q_1^1 = 1,
  // Q_m^m = sqrt((2m-1)/(2m)) sin(theta) Q_{m-1}^{m-1}.
  P[0] = 1.0;
  for (int m = 0; m <= N; ++m) {
    double* arr = m == 0 ? P.data() : Q.data();
    if (m == 1) {
      Q[at(1, 1)] = 1.0;
    } else if (m >= 2) {
      Q[at(m, m)] = std::sqrt((2.0 * m - 1.0) / (2.0 * m)) * st * Q[at(m - 1, m - 1)];
    }
    const int n0 = m == 0 ? 1 : m + 1;
    for (int n = n0; n <= N; ++n) {
      const double prev1 = (n - 1 >= m) ? arr[n - 1 == 0 ? 0 : at(n - 1, m)] : 0.0;
      const double prev2 = (n - 2 >= m) ? arr[n - 2 == 0 ? 0 : at(n - 2, m)] : 0.0;
      const double k2 = (n - 2 >= m) ? std::sqrt(double((n - 1) * (n - 1) - m * m)) : 0.0;
      arr[at(n, m)] =
          ((2.0 * n - 1.0) * ct * prev1 - k2 * prev2) / std::sqrt(double(n * n - m * m));
    }
  }
  for (int n = 1; n <= N; ++n)
    for (int m = 1; m <= n; ++m) P[at(n, m)] = st * Q[at(n, m)];

  const double ratio = kIgrfReferenceRadius_m / p.radius_m;
  double rpow = ratio * ratio;  // (a/r)^(n+2) at n = 0
  double br = 0.0, bt = 0.0, bp = 0.0;
  for (int n = 1; n <= N; ++n) {
    rpow *= ratio;
    double sum_r = 0.0, sum_t = 0.0, sum_p = 0.0;
    for (int m = 0; m <= n; ++m) {
      const int k = igrf_pack_index(n, m);
      const double gc = g_[k] * cos_m[m] + h_[k] * sin_m[m];
      // dP_n^m/dtheta = n cos Q_n^m - sqrt(n^2 - m^2) Q_{n-1}^m   (m >= 1)
      // dP_n^0/dtheta = -sqrt(n(n+1)/2) P_n^1
      double dp;
      if (m == 0) {
        dp = -std::sqrt(0.5 * n * (n + 1)) * P[at(n, 1)];
      } else {
        const double q_prev = (n - 1 >= m) ? Q[at(n - 1, m)] : 0.0;
        dp = n * ct * Q[at(n, m)] - std::sqrt(double(n * n - m * m)) * q_prev;
        sum_p += m * (g_[k] * sin_m[m] - h_[k] * cos_m[m]) * Q[at(n, m)];
      }
      sum_r += gc * P[at(n, m)];
      sum_t += gc * dp;
    }
    br += (n + 1) * rpow * sum_r;
    bt -= rpow * sum_t;
    bp += rpow * sum_p;
  }
  return {br, bt, bp};
}

Eigen::Vector3d IgrfModel::ecef_from_geocentric_field(const GeocentricField& b,
                                                      const GeocentricPosition& p) {
  const double st = std::sin(p.colatitude_rad), ct = std::cos(p.colatitude_rad);
  const double sp = std::sin(p.longitude_rad), cp = std::cos(p.longitude_rad);
  const Eigen::Vector3d e_r(st * cp, st * sp, ct);
  const Eigen::Vector3d e_t(ct * cp, ct * sp, -st);
  const Eigen::Vector3d e_p(-sp, cp, 0.0);
  return b.br_nT * e_r + b.btheta_nT * e_t + b.bphi_nT * e_p;
}

Eigen::Vector3d IgrfModel::field_ecef_nT(const Eigen::Vector3d& r_ecef_m) const {
  const GeocentricPosition p = geocentric_from_ecef(r_ecef_m);
  return ecef_from_geocentric_field(field_geocentric(p), p);
}

}  // namespace magcal
