#include "storage/postgres/pg_filter_state_store.hpp"

#include <algorithm>
#include <numeric>
#include <tuple>

#include "storage/filter_state_sql.hpp"
#include "storage/postgres/pg_row.hpp"

namespace magcal::storage {

void PgFilterStateStore::save_all(std::span<const FilterState> states) {
  static const std::vector<std::string> sql = [] {
    std::vector<std::string> out;
    for (size_t k = 0; k <= kMaxLog2RowsPerUpsert; ++k) {
      out.push_back(dollar_params(filter_state_sql::upsert(size_t{1} << k)));
    }
    return out;
  }();
  // Key order (stable: the later of two states of one key is the one kept, as by successive
  // saves), each key once.
  std::vector<size_t> order(states.size());
  std::iota(order.begin(), order.end(), size_t{0});
  auto key = [&](size_t i) { return std::tie(states[i].sat_id, states[i].method); };
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return key(a) < key(b); });
  size_t kept = 0;
  for (size_t i = 0; i < order.size(); ++i) {
    if (i + 1 < order.size() && key(order[i]) == key(order[i + 1])) continue;
    order[kept++] = order[i];
  }
  order.resize(kept);
  for_each_power_of_two_run(order.size(), kMaxLog2RowsPerUpsert, [&](size_t begin, size_t k) {
    params_.clear();
    PgBinder binder{params_};
    for (size_t i = begin; i < begin + (size_t{1} << k); ++i) {
      row_codec::write<FilterStateRow>(states[order[i]], binder);
    }
    db_.execute_prepared(sql[k], params_);
  });
}

}  // namespace magcal::storage
