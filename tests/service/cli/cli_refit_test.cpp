// `magcal refit` through the real binary: a refit that cannot run (an unknown spacecraft, too
// few samples in its window) is refused with exit 2 and one line naming the spacecraft and the
// database, and writes nothing: no job row, no result, the file's bytes unchanged.
#include <algorithm>
#include <filesystem>
#include <string>
#include <vector>

#include <catch2/catch.hpp>

#include "storage/sample_window_store.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "storage/sqlite/statement.hpp"
#include "tests/service/cli_test_support.hpp"
#include "tests/service/daemon_test_support.hpp"

using magcal::test::Run;
using magcal::test::run_magcal;
using magcal::test::slurp;
using magcal::test::TempDir;

namespace {

int64_t count_rows(const std::string& db, const std::string& table) {
  magcal::storage::OpenOptions read_only;
  read_only.read_only = true;
  magcal::storage::Database d(db, read_only);
  magcal::storage::Statement st(d, "SELECT count(*) FROM " + table);
  REQUIRE(st.step());
  return st.column_int64(0);
}

}  // namespace

TEST_CASE("a refit that cannot run is refused and writes nothing") {
  TempDir dir("magcal_refit");
  const std::string db = dir.file("few.db");
  {
    // SAT1: 20 samples, fewer than the default [refit] min_samples.
    magcal::storage::Database d(db);
    magcal::storage::SqliteSampleWindowStore samples(d);
    std::vector<magcal::storage::StoredSample> batch(20);
    for (size_t k = 0; k < batch.size(); ++k) {
      batch[k].sat_id = "SAT1";
      batch[k].utime = 1'767'225'600'000'000 + static_cast<int64_t>(k) * 10'000'000;
      batch[k].seq = static_cast<int64_t>(k);
      batch[k].h_norm_nT = 30000.0;
    }
    samples.insert_batch(batch);
  }
  const std::string before = slurp(db);
  struct Case {
    std::string sat, message;
  };
  for (const Case& c : {Case{"NOPE", "no stored samples for 'NOPE' in " + db +
                                         " (spacecraft stored: SAT1); nothing written"},
                        Case{"SAT1", "20 samples in the window, "}}) {
    const Run r = run_magcal("refit --db " + db + " --sat " + c.sat, dir);
    INFO(c.sat << ": " << r.err);
    CHECK(r.exit_code == 2);
    CHECK(r.out.empty());
    CHECK(std::count(r.err.begin(), r.err.end(), '\n') == 1);
    CHECK(r.err.find("magcal refit: " + c.message) != std::string::npos);
    CHECK(slurp(db) == before);
    CHECK(slurp(db + "-wal").empty());  // no commit waits in a -wal either
    CHECK(count_rows(db, "refit_jobs") == 0);
    CHECK(count_rows(db, "calibrations") == 0);
  }
}
