// The one CSV tokeniser and table reader of the file readers (sample_files, field_recording).
// Tolerant of what spreadsheet and telemetry exports contain: a UTF-8 byte-order mark, `;` or tab
// separators (found from the header line), quoted fields ("a,b" and "say ""x"""), CRLF line ends
// and blank lines.
#pragma once

#include <string>
#include <string_view>
#include <vector>

namespace magcal {

// The fields of one line, split at every `separator` outside double quotes, with spaces and tabs
// around each field and a carriage return (a CRLF file) at the end removed. A quoted field loses
// its quotes and keeps what is inside them verbatim ("" is one quote). "a,b," has three fields,
// the last empty; an empty line has one empty field.
std::vector<std::string> split_csv_line(std::string_view line, char separator = ',');

// The separator a header line uses: the most frequent of `,`, `;` and tab outside quotes (`,`
// when none occurs or on a tie).
char detect_csv_separator(std::string_view header_line);

// A whole CSV file: the header (first non-blank line) and every further non-blank line.
struct CsvTable {
  std::string source;  // the path, or "standard input" for "-"
  char separator = ',';
  int header_line = 0;
  std::vector<std::string> header;
  struct Row {
    int line = 0;  // 1-based line number in the file
    std::vector<std::string> cells;
  };
  std::vector<Row> rows;
};

// Reads `path` ("-": standard input) into *table. "" on success, else one line naming the file
// (cannot open, empty, read error).
std::string read_csv_table(const std::string& path, CsvTable* table);

}  // namespace magcal
