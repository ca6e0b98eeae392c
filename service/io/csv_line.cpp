#include "service/io/csv_line.hpp"

#include <fstream>
#include <iostream>

namespace magcal {

std::vector<std::string> split_csv_line(std::string_view line, char separator) {
  std::vector<std::string> out;
  size_t i = 0;
  const auto is_blank = [](char c) { return c == ' ' || c == '\t' || c == '\r'; };
  while (true) {
    while (i < line.size() && line[i] != separator && is_blank(line[i])) ++i;
    std::string field;
    if (i < line.size() && line[i] == '"') {
      ++i;
      while (i < line.size()) {
        if (line[i] == '"') {
          if (i + 1 < line.size() && line[i + 1] == '"') {
            field += '"';
            i += 2;
            continue;
          }
          ++i;
          break;
        }
        field += line[i++];
      }
      // Anything but blanks between the closing quote and the separator is kept (a malformed
      // field stays visible in an error message rather than silently cut).
      std::string after;
      while (i < line.size() && line[i] != separator) after += line[i++];
      while (!after.empty() && is_blank(after.back())) after.pop_back();
      field += after;
    } else {
      const size_t end = line.find(separator, i);
      field.assign(
          line.substr(i, end == std::string_view::npos ? std::string_view::npos : end - i));
      i = end == std::string_view::npos ? line.size() : end;
      while (!field.empty() && is_blank(field.back())) field.pop_back();
    }
    out.push_back(std::move(field));
    if (i >= line.size()) break;
    ++i;  // the separator
    if (i == line.size()) {
      out.emplace_back();
      break;
    }
  }
  return out;
}

char detect_csv_separator(std::string_view header_line) {
  int commas = 0, semicolons = 0, tabs = 0;
  bool quoted = false;
  for (const char c : header_line) {
    if (c == '"') quoted = !quoted;
    if (quoted) continue;
    commas += c == ',';
    semicolons += c == ';';
    tabs += c == '\t';
  }
  if (semicolons > commas && semicolons >= tabs) return ';';
  if (tabs > commas && tabs > semicolons) return '\t';
  return ',';
}

std::string read_csv_table(const std::string& path, CsvTable* table) {
  *table = CsvTable{};
  table->source = path == "-" ? "standard input" : path;
  std::ifstream file;
  if (path != "-") {
    file.open(path);
    if (!file) return path + ": cannot open";
  }
  std::istream& in = path == "-" ? std::cin : file;
  std::string line;
  int line_no = 0;
  const auto blank = [](const std::string& l) {
    return l.find_first_not_of(" \t\r") == std::string::npos;
  };
  while (std::getline(in, line)) {
    ++line_no;
    // A UTF-8 byte-order mark (spreadsheet exports) is no part of the first column's name.
    if (line_no == 1 && line.rfind("\xEF\xBB\xBF", 0) == 0) line.erase(0, 3);
    if (blank(line)) continue;
    table->separator = detect_csv_separator(line);
    table->header = split_csv_line(line, table->separator);
    table->header_line = line_no;
    break;
  }
  if (table->header.empty()) return table->source + ": empty file (a header row is required)";
  while (std::getline(in, line)) {
    ++line_no;
    if (blank(line)) continue;
    table->rows.push_back({line_no, split_csv_line(line, table->separator)});
  }
  if (in.bad()) return table->source + ": read error";
  return "";
}

}  // namespace magcal
