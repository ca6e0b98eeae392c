#include "service/io/printf_string.hpp"

#include <cstdarg>
#include <cstdio>

namespace magcal {

void append_printf(std::string* out, const char* format, ...) {
  va_list args;
  va_start(args, format);
  va_list again;
  va_copy(again, args);
  const int n = std::vsnprintf(nullptr, 0, format, args);
  va_end(args);
  if (n > 0) {
    const size_t old_size = out->size();
    out->resize(old_size + static_cast<size_t>(n) + 1);  // room for vsnprintf's terminator
    std::vsnprintf(out->data() + old_size, static_cast<size_t>(n) + 1, format, again);
    out->resize(old_size + static_cast<size_t>(n));
  }
  va_end(again);
}

}  // namespace magcal
