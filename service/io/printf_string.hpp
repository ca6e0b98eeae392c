// printf-formatted text into a std::string: the CLI's aligned tables are built as strings (so
// that `magcal` and the HTTP server share them) with exactly printf's formatting.
#pragma once

#include <string>

namespace magcal {

// Appends the printf-formatted text to *out.
void append_printf(std::string* out, const char* format, ...) __attribute__((format(printf, 2, 3)));

}  // namespace magcal
