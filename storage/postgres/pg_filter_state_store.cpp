#include "storage/postgres/pg_filter_state_store.hpp"

#include <algorithm>
#include <numeric>
#include <tuple>

#include "storage/filter_state_sql.hpp"
#include "storage/postgres/pg_row.hpp"

namespace magcal::storage {
namespace {

// The upsert of `rows` states (distinct keys: a statement cannot update one row twice).
std::string upsert_sql(size_t rows) {
  return multi_row_values_sql(
      "INSERT INTO filter_states (" + row_codec::column_list<FilterStateRow>() + ") VALUES ", rows,
      row_codec::column_count<FilterStateRow>(), 1, "", filter_state_sql::kReplace);
}

std::vector<FilterState> states(const PgResult& r) {
  std::vector<FilterState> out;
  for (int row = 0; row < r.rows(); ++row) {
    out.push_back(row_codec::read<FilterStateRow>(PgRow{r, row}));
  }
  return out;
}

}  // namespace

void PgFilterStateStore::save(const FilterState& s) {
  save_all(std::span(&s, 1));
}

void PgFilterStateStore::save_all(std::span<const FilterState> states) {
  static const std::vector<std::string> sql = [] {
    std::vector<std::string> out;
    for (size_t k = 0; k <= kMaxLog2RowsPerUpsert; ++k) out.push_back(upsert_sql(size_t{1} << k));
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

std::optional<FilterState> PgFilterStateStore::load(std::string_view sat_id,
                                                    std::string_view method) {
  static const std::string sql = dollar_params(filter_state_sql::load());
  PgParams p;
  p.add(sat_id).add(method);
  auto found = states(db_.execute_prepared(sql, p, PgFormat::kBinary));
  if (found.empty()) return std::nullopt;
  return std::move(found.front());
}

std::vector<FilterState> PgFilterStateStore::load_all() {
  static const std::string sql = filter_state_sql::load_all();
  return states(db_.execute_prepared(sql, {}, PgFormat::kBinary));
}

}  // namespace magcal::storage
