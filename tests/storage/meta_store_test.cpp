// meta table, on SQLite and on PostgreSQL (tests/storage/storage_backends.hpp): set, replace, get.
#include "storage/meta_store.hpp"

#include <catch2/catch.hpp>

#include "tests/storage/storage_backends.hpp"

using namespace magcal::storage;
using magcal::test::BackendTest;
using magcal::test::PostgresBackend;
using magcal::test::SqliteBackend;

TEMPLATE_TEST_CASE_METHOD(BackendTest,
                          "a meta value is stored, replaced and read back, an unknown key has none",
                          "[meta]", SqliteBackend, PostgresBackend) {
  if (!this->db) return;
  const auto meta = this->db->make_meta_store();
  CHECK_FALSE(meta->get("daemon_version").has_value());
  meta->set("daemon_version", "0.1.0");
  meta->set("started_utime", "1767225600000000");
  meta->set("daemon_version", "0.2.0 \xC3\xA9");  // replaced; UTF-8 kept
  CHECK(meta->get("daemon_version") == "0.2.0 \xC3\xA9");
  CHECK(meta->get("started_utime") == "1767225600000000");
  // Another connection sees what was committed.
  CHECK(this->backend.open_again()->make_meta_store()->get("daemon_version") == "0.2.0 \xC3\xA9");
}
