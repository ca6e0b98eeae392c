// PgDatabase as an SqlSession (storage/sql_statement.hpp): the statements of the stores written
// once for both backends, each run by execute_prepared() (prepared once per connection), its
// ?N parameters as $N, numbers in binary.
#include "storage/postgres/pg_database.hpp"
#include "storage/postgres/pg_row.hpp"

namespace magcal::storage {
namespace {

class PgSqlStatement final : public SqlStatementOf<PgBinder> {
 public:
  PgSqlStatement(PgDatabase& db, std::string_view sql)
      : SqlStatementOf(PgBinder{params_}), db_(db), sql_(dollar_params(std::string(sql))) {}

  const SqlRow& row() const override { return row_; }
  bool next() override {
    run();
    return ++row_.adapter().row < result_.rows();
  }
  int64_t changes() override {
    run();
    return result_.affected_rows();
  }
  void reset() override {
    params_.clear();
    result_ = PgResult();
    ran_ = false;
    row_.adapter().row = -1;
  }

 private:
  void run() {
    if (ran_) return;
    result_ = db_.execute_prepared(sql_, params_, PgFormat::kBinary);
    ran_ = true;
  }

  PgDatabase& db_;
  std::string sql_;
  PgParams params_;
  PgResult result_;
  bool ran_ = false;
  SqlRowOf<PgRow> row_{PgRow{result_, -1}};
};

}  // namespace

std::unique_ptr<SqlStatement> PgDatabase::prepare(std::string_view sql) {
  return std::make_unique<PgSqlStatement>(*this, sql);
}

}  // namespace magcal::storage
