#include "storage/lease_store.hpp"

namespace magcal::storage {

void LeaseStore::check_request(std::string_view owner, int64_t ttl_utime) {
  if (owner.empty()) {
    throw StorageError(StorageError::Kind::kInvalidArgument, "a lease needs an owner");
  }
  if (ttl_utime <= 0) {
    throw StorageError(
        StorageError::Kind::kInvalidArgument,
        "a lease's time to live must be positive, not " + std::to_string(ttl_utime) + " us");
  }
}

std::optional<std::string> LeaseStore::owner_of(std::string_view sat_id, int64_t now_utime) {
  auto lease = get(sat_id);
  if (!lease || !lease->held_at(now_utime)) return std::nullopt;
  return std::move(lease->owner);
}

std::vector<std::string> LeaseStore::not_held(std::string_view owner,
                                              std::span<const Held> leases) {
  std::vector<std::string> out;
  for (const Held& l : leases) {
    if (!holds(l.sat_id, owner, l.epoch)) out.push_back(l.sat_id);
  }
  return out;
}

}  // namespace magcal::storage
