// A strict reader of the Prometheus text exposition format 0.0.4, written in the tests
// independently of prometheus-cpp (which writes it): # HELP / # TYPE lines, samples
// `name{label="value",...} value`, escapes \\ \" \n in label values. Every sample must belong to
// a family declared by # TYPE before it (histograms: _bucket with le, _sum, _count); anything
// else is a parse error with the line.
#pragma once

#include <cmath>
#include <cstdlib>
#include <map>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

namespace magcal::test {

struct PromSample {
  std::string name;
  std::map<std::string, std::string> labels;
  double value = 0.0;
};

struct PromText {
  std::map<std::string, std::string> types;  // family -> counter|gauge|histogram|summary|untyped
  std::vector<PromSample> samples;
  std::string error;  // empty = parsed

  // Sum of `name` over the samples whose labels include `match`.
  double sum(const std::string& name, const std::map<std::string, std::string>& match = {}) const {
    double s = 0.0;
    for (const auto& x : samples) {
      if (x.name != name) continue;
      bool ok = true;
      for (const auto& [k, v] : match) {
        const auto it = x.labels.find(k);
        ok = ok && it != x.labels.end() && it->second == v;
      }
      if (ok) s += x.value;
    }
    return s;
  }
  // The one sample of `name` with exactly these labels, if present.
  std::optional<double> value(const std::string& name,
                              const std::map<std::string, std::string>& labels = {}) const {
    for (const auto& x : samples) {
      if (x.name == name && x.labels == labels) return x.value;
    }
    return std::nullopt;
  }
  bool has(const std::string& name) const {
    for (const auto& x : samples) {
      if (x.name == name) return true;
    }
    return false;
  }
};

namespace prom_detail {

inline bool is_name_char(char c, bool first) {
  return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || c == '_' || c == ':' ||
         (!first && c >= '0' && c <= '9');
}

inline std::optional<double> parse_number(const std::string& s) {
  if (s == "+Inf") return HUGE_VAL;
  if (s == "-Inf") return -HUGE_VAL;
  if (s == "NaN") return std::nan("");
  if (s.empty()) return std::nullopt;
  char* end = nullptr;
  const double v = std::strtod(s.c_str(), &end);
  if (end != s.c_str() + s.size()) return std::nullopt;
  return v;
}

// The family a sample name belongs to, given the declared types.
inline std::optional<std::string> family_of(const std::string& name,
                                            const std::map<std::string, std::string>& types) {
  if (types.count(name)) return name;
  for (const char* suffix : {"_bucket", "_sum", "_count"}) {
    const std::string sfx(suffix);
    if (name.size() > sfx.size() && name.compare(name.size() - sfx.size(), sfx.size(), sfx) == 0) {
      const std::string base = name.substr(0, name.size() - sfx.size());
      const auto it = types.find(base);
      if (it != types.end() && (it->second == "histogram" || it->second == "summary")) return base;
    }
  }
  return std::nullopt;
}

}  // namespace prom_detail

inline PromText parse_prometheus_text(const std::string& text) {
  using namespace prom_detail;
  PromText out;
  std::istringstream in(text);
  std::string line;
  int n = 0;
  auto fail = [&](const std::string& why) {
    out.error = "line " + std::to_string(n) + ": " + why + ": " + line;
    return out;
  };
  while (std::getline(in, line)) {
    ++n;
    if (line.empty()) continue;
    if (line[0] == '#') {
      std::istringstream w(line);
      std::string hash, kind, name;
      w >> hash >> kind >> name;
      if (kind == "TYPE") {
        std::string type;
        w >> type;
        if (type != "counter" && type != "gauge" && type != "histogram" && type != "summary" &&
            type != "untyped")
          return fail("bad type");
        if (out.types.count(name)) return fail("family declared twice");
        out.types[name] = type;
      }
      continue;  // HELP and comments
    }
    size_t i = 0;
    PromSample s;
    while (i < line.size() && is_name_char(line[i], i == 0)) s.name += line[i++];
    if (s.name.empty()) return fail("no metric name");
    if (i < line.size() && line[i] == '{') {
      ++i;
      while (i < line.size() && line[i] != '}') {
        std::string key;
        while (i < line.size() && is_name_char(line[i], key.empty())) key += line[i++];
        if (key.empty() || i + 1 >= line.size() || line[i] != '=' || line[i + 1] != '"')
          return fail("bad label");
        i += 2;
        std::string value;
        while (i < line.size() && line[i] != '"') {
          if (line[i] == '\\') {
            if (i + 1 >= line.size()) return fail("bad escape");
            const char e = line[i + 1];
            if (e == 'n') {
              value += '\n';
            } else if (e == '\\' || e == '"') {
              value += e;
            } else {
              return fail("bad escape");
            }
            i += 2;
          } else {
            value += line[i++];
          }
        }
        if (i >= line.size()) return fail("unterminated label value");
        ++i;  // closing quote
        if (s.labels.count(key)) return fail("label twice");
        s.labels[key] = value;
        if (i < line.size() && line[i] == ',') ++i;
      }
      if (i >= line.size()) return fail("unterminated labels");
      ++i;  // '}'
    }
    if (i >= line.size() || line[i] != ' ') return fail("no value");
    std::istringstream rest(line.substr(i + 1));
    std::string value_text, timestamp, extra;
    rest >> value_text >> timestamp >> extra;
    const auto v = parse_number(value_text);
    if (!v) return fail("bad value");
    if (!extra.empty() || (!timestamp.empty() && !parse_number(timestamp)))
      return fail("trailing text");
    s.value = *v;
    const auto family = family_of(s.name, out.types);
    if (!family) return fail("sample of an undeclared family");
    if (out.types[*family] == "histogram" && s.name == *family + "_bucket" && !s.labels.count("le"))
      return fail("bucket without le");
    out.samples.push_back(std::move(s));
  }
  return out;
}

}  // namespace magcal::test
