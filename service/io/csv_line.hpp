// The one CSV tokeniser of the file readers (sample_files, field_recording): the files magcal
// reads are plain comma-separated numbers and names, without quoted commas or line breaks.
#pragma once

#include <string_view>
#include <vector>

namespace magcal {

// The fields of one line, split at every comma, with spaces and tabs before and spaces, tabs and
// a carriage return (a CRLF file) after each field removed. "a,b," has three fields, the last
// empty; an empty line has one empty field. The views point into `line`.
std::vector<std::string_view> split_csv_line(std::string_view line);

}  // namespace magcal
