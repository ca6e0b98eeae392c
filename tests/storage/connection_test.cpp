// open_database() and the names it gives a --db value (storage/connection.hpp): a password in a
// PostgreSQL URI never reaches a message, not even when libpq quotes the URI back in its own
// parse error; libpq's key=value form and an upper-case scheme are refused, never created as an
// SQLite file of that name. No server is needed: every case fails before connecting.
#include <filesystem>
#include <string>

#include <catch2/catch.hpp>

#include "storage/connection.hpp"
#include "storage/storage_error.hpp"

using magcal::storage::database_name;
using magcal::storage::open_database;
using magcal::storage::StorageError;

namespace {

// The message open_database(db) throws.
std::string open_error(const std::string& db) {
  try {
    open_database(db);
  } catch (const StorageError& e) {
    return e.what();
  }
  FAIL("opened " << db);
  return "";
}

}  // namespace

TEST_CASE("a --db value's password shows in no name and no message") {
  CHECK(database_name("postgresql://magcal:s3cret@db:5432/m") ==
        "postgresql://magcal:***@db:5432/m");
  CHECK(database_name("postgresql://magcal@db/m?sslmode=require&password=s3cret") ==
        "postgresql://magcal@db/m?sslmode=require&password=***");
  CHECK(database_name("/var/lib/magcal/magcal.db") == "/var/lib/magcal/magcal.db");
  // Malformed URIs, which libpq's parse error quotes back (whole, or the bad token).
  for (const std::string db : {"postgresql://magcal:s3cret@[::1:55611/trial",
                               "postgresql://magcal:s3cret@[::1]x:55611/trial",
                               "postgresql://magcal:s3cr%zzet@127.0.0.1:55611/trial",
                               "postgresql://magcal@127.0.0.1/trial?password=s3cret&bogus"}) {
    const std::string message = open_error(db);
    INFO(db << " -> " << message);
    CHECK(message.find("invalid PostgreSQL URI") != std::string::npos);
    CHECK(message.find("s3cr") == std::string::npos);
    CHECK(message.find("***") != std::string::npos);
  }
  // A percent-encoded password is masked as written and decoded.
  CHECK(magcal::storage::without_database_secrets("postgresql://u:p%40ss@h/d",
                                                  "bad p%40ss and p@ss") == "bad *** and ***");
}

TEST_CASE("libpq's key=value form and an upper-case scheme are refused, no file is created") {
  const std::string keywords = "host=127.0.0.1 port=55611 user=magcal password=s3cret dbname=m";
  const std::string message = open_error(keywords);
  INFO(message);
  CHECK(message.find("is a libpq key=value connection string") != std::string::npos);
  CHECK(message.find("s3cret") == std::string::npos);
  CHECK(message.find("password=***") != std::string::npos);
  CHECK_FALSE(std::filesystem::exists(keywords));

  const std::string upper = "POSTGRESQL://magcal:s3cret@127.0.0.1/m";
  const std::string upper_message = open_error(upper);
  INFO(upper_message);
  CHECK(upper_message.find("lower case") != std::string::npos);
  CHECK(upper_message.find("s3cret") == std::string::npos);
  CHECK_FALSE(std::filesystem::exists(upper));
}
