// The one CSV tokeniser of the file readers: fields split at every comma, blanks around them and
// a CRLF line's carriage return removed, empty fields kept.
#include <string>
#include <string_view>
#include <vector>

#include <catch2/catch.hpp>

#include "service/io/csv_line.hpp"

using magcal::split_csv_line;

namespace {
std::vector<std::string> fields(std::string_view line) {
  std::vector<std::string> out;
  for (const std::string_view f : split_csv_line(line)) out.emplace_back(f);
  return out;
}
}  // namespace

TEST_CASE("a CSV line splits at every comma, blanks around the fields removed") {
  using V = std::vector<std::string>;
  CHECK(fields("t_s,bx_nT,by_nT") == V{"t_s", "bx_nT", "by_nT"});
  CHECK(fields(" 1.5 ,\t-2e3\t, 7") == V{"1.5", "-2e3", "7"});
  CHECK(fields("1,2,3\r") == V{"1", "2", "3"});  // a CRLF file read by getline
  CHECK(fields("1, 2 \r") == V{"1", "2"});
}

TEST_CASE("empty CSV fields are kept, so columns keep their positions") {
  using V = std::vector<std::string>;
  CHECK(fields("1,,3") == V{"1", "", "3"});
  CHECK(fields("1,2,") == V{"1", "2", ""});
  CHECK(fields(",") == V{"", ""});
  CHECK(fields("") == V{""});
  CHECK(fields("  ") == V{""});
}

TEST_CASE("quotes are field content for the tokeniser (readers that allow them strip them)") {
  using V = std::vector<std::string>;
  CHECK(fields("\"Date/Time\", \"MagX\"") == V{"\"Date/Time\"", "\"MagX\""});
}
