// FNV-1a, 64 bits: a checksum that is the same on every build and platform (unlike std::hash),
// for data written by one process and checked by another (spill records, station settings).
// Not a cryptographic hash.
#pragma once

#include <cstdint>
#include <string_view>

namespace magcal {

inline uint64_t fnv1a_64(std::string_view data) {
  uint64_t h = 0xcbf29ce484222325ULL;
  for (const char c : data) {
    h ^= static_cast<unsigned char>(c);
    h *= 0x100000001b3ULL;
  }
  return h;
}

}  // namespace magcal
