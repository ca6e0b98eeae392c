#include "storage/postgres/pg_lease_store.hpp"

#include <algorithm>

namespace magcal::storage {

std::vector<std::string> PgLeaseStore::not_held(std::string_view owner,
                                                std::span<const Held> leases) {
  if (leases.empty()) return {};
  std::vector<std::string> sats;
  std::vector<int64_t> epochs;
  for (const Held& l : leases) {
    sats.push_back(l.sat_id);
    epochs.push_back(l.epoch);
  }
  PgParams p;
  p.add(owner).add_array(sats).add_array(epochs);
  // Locked in one order (sat_id, as renew_all and the takeovers' single rows need no other), so
  // two fences never wait for each other crosswise.
  const PgResult r = db_.execute_prepared(
      "SELECT l.sat_id FROM leases l JOIN unnest($2::text[], $3::bigint[]) AS q(sat_id, epoch) "
      "ON l.sat_id = q.sat_id AND l.epoch = q.epoch WHERE l.owner = $1 ORDER BY l.sat_id "
      "FOR SHARE OF l",
      p);
  std::vector<std::string> held;
  held.reserve(static_cast<size_t>(r.rows()));
  for (int row = 0; row < r.rows(); ++row) held.push_back(r.get_text(row, 0));
  std::sort(held.begin(), held.end());
  std::vector<std::string> out;
  for (const Held& l : leases) {
    if (!std::binary_search(held.begin(), held.end(), l.sat_id)) out.push_back(l.sat_id);
  }
  return out;
}

}  // namespace magcal::storage
