// Vectors and matrices of doubles as blobs (SQLite BLOB, PostgreSQL bytea): raw little-endian
// IEEE-754 doubles, so the round trip is bit-exact on both backends. Internal to storage/.
#pragma once

#include <bit>
#include <cstddef>
#include <cstring>
#include <span>
#include <string>

#include "storage/storage_error.hpp"

namespace magcal::storage {

static_assert(std::endian::native == std::endian::little,
              "blobs hold little-endian doubles; add byte swapping for this platform");

// A blob read back into `out`: exactly out.size() doubles, else StorageError (condition
// kCorrupt) naming `what` (the column, e.g. "filter_states.P").
inline void doubles_from_blob(const void* blob, size_t size, std::span<double> out,
                              const std::string& what) {
  if (size != sizeof(double) * out.size()) {
    throw StorageError(StorageError::Kind::kEngine,
                       what + " has " + std::to_string(size) + " bytes, expected " +
                           std::to_string(sizeof(double) * out.size()),
                       StorageError::Condition::kCorrupt);
  }
  std::memcpy(out.data(), blob, size);
}

}  // namespace magcal::storage
