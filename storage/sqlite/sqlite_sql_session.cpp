// Database as an SqlSession (storage/sql_statement.hpp): its statements for the stores written
// once for both backends.
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/sqlite_row.hpp"
#include "storage/sqlite/statement.hpp"

namespace magcal::storage {
namespace {

class SqliteSqlStatement final : public SqlStatementOf<SqliteBinder> {
 public:
  SqliteSqlStatement(Database& db, std::string_view sql)
      : SqlStatementOf(SqliteBinder{st_}), st_(db, sql), row_(SqliteRow{st_}) {}

  const SqlRow& row() const override { return row_; }
  bool next() override { return st_.step(); }
  int64_t changes() override { return st_.execute(); }
  void reset() override {
    st_.reset();
    binder_.index = 1;
  }

 private:
  Statement st_;
  SqlRowOf<SqliteRow> row_;
};

}  // namespace

std::unique_ptr<SqlStatement> Database::prepare(std::string_view sql) {
  return std::make_unique<SqliteSqlStatement>(*this, sql);
}

}  // namespace magcal::storage
