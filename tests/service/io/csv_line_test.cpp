// The one CSV tokeniser of the file readers: fields split at every separator outside quotes,
// blanks around them and a CRLF line's carriage return removed, empty fields kept; the table
// reader drops a byte-order mark and finds the separator from the header.
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <string>
#include <string_view>
#include <vector>

#include <catch2/catch.hpp>

#include "service/io/csv_line.hpp"

using magcal::split_csv_line;

namespace {
std::vector<std::string> fields(std::string_view line) {
  std::vector<std::string> out;
  return split_csv_line(line);
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

TEST_CASE("quoted fields lose their quotes and keep separators and doubled quotes inside") {
  using V = std::vector<std::string>;
  CHECK(fields("\"Date/Time\", \"MagX\"") == V{"Date/Time", "MagX"});
  CHECK(fields("\"Bx, uT\",\"say \"\"x\"\"\",3") == V{"Bx, uT", "say \"x\"", "3"});
  CHECK(fields("\" a \",") == V{" a ", ""});
  CHECK(magcal::split_csv_line("1;2,5;3", ';') == V{"1", "2,5", "3"});
}

TEST_CASE("the separator is the header's most frequent of comma, semicolon and tab") {
  CHECK(magcal::detect_csv_separator("time;Bx (uT);By (uT)") == ';');
  CHECK(magcal::detect_csv_separator("time\tbx_nT\tby_nT") == '\t');
  CHECK(magcal::detect_csv_separator("t_s,bx_nT") == ',');
  CHECK(magcal::detect_csv_separator("\"a;b\",c") == ',');
  CHECK(magcal::detect_csv_separator("time") == ',');
}

TEST_CASE("the table reader drops a byte-order mark and blank lines, and names the lines") {
  const std::string path = (std::filesystem::temp_directory_path() /
                            ("magcal_csv_table_" + std::to_string(::getpid()) + ".csv"))
                               .string();
  std::ofstream(path) << "\xEF\xBB\xBF\"time\";\"Bx (uT)\"\r\n\r\n2024-01-01T00:00:00Z;1,5\r\n";
  magcal::CsvTable table;
  REQUIRE(magcal::read_csv_table(path, &table).empty());
  CHECK(table.separator == ';');
  CHECK(table.header == std::vector<std::string>{"time", "Bx (uT)"});
  REQUIRE(table.rows.size() == 1);
  CHECK(table.rows[0].line == 3);
  CHECK(table.rows[0].cells == std::vector<std::string>{"2024-01-01T00:00:00Z", "1,5"});
  std::filesystem::remove(path);
  CHECK(magcal::read_csv_table(path, &table).find("cannot open") != std::string::npos);
}
