// open_database() and the names it gives a --db value (storage/connection.hpp): a password in a
// PostgreSQL URI never reaches a message, not even when libpq quotes the URI back in its own
// parse error; libpq's key=value form and an upper-case scheme are refused, never created as an
// SQLite file of that name, nor is a mistyped scheme; libpq's multi-line errors read as one
// line of sentences. No server is needed: every case fails before or at connecting.
#include <filesystem>
#include <string>
#include <utility>
#include <vector>

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

TEST_CASE("a mistyped URI scheme is named, not taken for an SQLite path") {
  for (const auto& [db, scheme] : std::vector<std::pair<std::string, std::string>>{
           {"postgressql://magcal@h/m", "postgressql://"},
           {"postgres:/x", "postgres:/"},
           {"postgresql:/x", "postgresql:/"},
           {"postgresql:x", "postgresql:"},
           {"pgsql://h/m", "pgsql://"},
           {"mysql://h/m", "mysql://"},
           {"postgres ql://magcal@h/m", "postgres ql://"},
           {"postgress://magcal@h/m", "postgress://"},
           {"sqlite:///tmp/m.db", "sqlite:///"}}) {
    const std::string message = open_error(db);
    INFO(db << " -> " << message);
    CHECK(message == "unknown database URI scheme '" + scheme +
                         "': use postgresql:// (or postgres://) for PostgreSQL, or a file path "
                         "for SQLite");
    CHECK_FALSE(std::filesystem::exists(db));
  }
  // A relative path with a colon in its first name stays a file path (its folder is missing).
  for (const std::string path : {"run:2-nonexistent-magcal/x.db", "c:nonexistent-magcal/x.db"}) {
    const std::string message = open_error(path);
    INFO(path << " -> " << message);
    CHECK(message.find("unknown database URI scheme") == std::string::npos);
    CHECK(message.find("x.db") != std::string::npos);
  }
}

TEST_CASE("libpq's multi-line error is one line of sentences") {
  // Nothing listens on port 1: refused at once, with libpq's hint on a continuation line.
  const std::string message = open_error("postgresql://magcal@127.0.0.1:1/m");
  INFO(message);
  CHECK(message.find('\n') == std::string::npos);
  CHECK(message.find('\t') == std::string::npos);
  CHECK(message.find("Connection refused. Is the server running") != std::string::npos);
  CHECK(message.back() != ' ');
}
