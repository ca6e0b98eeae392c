#include "storage/connection.hpp"

#include <algorithm>
#include <array>
#include <cctype>
#include <string_view>
#include <vector>

#include "storage/postgres/pg_database.hpp"
#include "storage/sql_calibration_history.hpp"
#include "storage/sql_filter_state_store.hpp"
#include "storage/sql_lease_store.hpp"
#include "storage/sql_meta_store.hpp"
#include "storage/sql_refit_job_log.hpp"
#include "storage/sqlite/database.hpp"

namespace magcal::storage {

namespace {

// The secrets a --db value carries: the password of a URI's user:password@ and every
// password=VALUE (URI query, or a libpq keyword string), each as written and percent-decoded.
std::vector<std::string> database_secrets(const std::string& db) {
  std::vector<std::string> secrets;
  auto add = [&](std::string value) {
    if (value.empty()) return;
    secrets.push_back(value);
    std::string decoded;
    for (std::size_t i = 0; i < value.size(); ++i) {
      if (value[i] == '%' && i + 2 < value.size() &&
          std::isxdigit(static_cast<unsigned char>(value[i + 1])) &&
          std::isxdigit(static_cast<unsigned char>(value[i + 2]))) {
        decoded += static_cast<char>(std::stoi(value.substr(i + 1, 2), nullptr, 16));
        i += 2;
      } else {
        decoded += value[i];
      }
    }
    if (decoded != value) secrets.push_back(decoded);
  };
  const std::size_t scheme = db.find("://");
  if (scheme != std::string::npos) {
    const std::size_t authority = scheme + 3;
    const std::size_t authority_end = db.find_first_of("/?", authority);
    const std::size_t at = db.rfind('@', authority_end);
    if (at != std::string::npos && at >= authority) {
      const std::size_t colon = db.find(':', authority);
      if (colon < at) add(db.substr(colon + 1, at - colon - 1));
    }
  }
  for (std::size_t key = db.find("password="); key != std::string::npos;
       key = db.find("password=", key + 1)) {
    const char before = key == 0 ? ' ' : db[key - 1];
    if (before != '?' && before != '&' && !std::isspace(static_cast<unsigned char>(before))) {
      continue;
    }
    const std::size_t value = key + 9;
    add(db.substr(value, db.find_first_of("& \t\n", value) - value));
  }
  // Longest first: a secret that contains another is replaced whole.
  std::sort(secrets.begin(), secrets.end(),
            [](const std::string& a, const std::string& b) { return a.size() > b.size(); });
  return secrets;
}

// The scheme of a URI-like --db value that is neither a PostgreSQL URI nor meant as a file:
// "WORD://..." (any scheme: an SQLite path never looks like that), "ANY TEXT://..." before any
// other '/' (a space typed into the scheme: "postgres ql://"), or "WORD:..." where WORD is a
// near miss of postgres ("postgres:/x", "postgresql:x", "pgsql:"). Returned as typed, with its
// colon and slashes ("postgressql://"); "" when the value is none of these.
std::string mistyped_uri_scheme(const std::string& db) {
  if (const std::size_t sep = db.find("://");
      sep != std::string::npos && sep > 0 && db.find('/') == sep + 1) {
    const std::size_t path = db.find_first_not_of('/', sep + 1);
    return db.substr(0, path == std::string::npos ? db.size() : path);
  }
  std::size_t end = 0;
  while (end < db.size() && (std::isalnum(static_cast<unsigned char>(db[end])) || db[end] == '+' ||
                             db[end] == '-' || db[end] == '.')) {
    ++end;
  }
  if (end == 0 || end >= db.size() || db[end] != ':' ||
      !std::isalpha(static_cast<unsigned char>(db[0]))) {
    return "";
  }
  std::string word = db.substr(0, end);
  std::transform(word.begin(), word.end(), word.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  const std::size_t path = db.find_first_not_of('/', end + 1);
  const std::string typed = db.substr(0, path == std::string::npos ? db.size() : path);
  const bool like_postgres = word.starts_with("pg") || word.starts_with("postg");
  if (db.compare(end, 3, "://") == 0 || like_postgres) return typed;
  return "";
}

// "host=... dbname=...": libpq's keyword form, which magcal does not take (a --db value is a
// URI or a file path), recognised by a first word that is one of libpq's common keywords.
bool is_libpq_keyword_string(const std::string& db) {
  static constexpr std::array<std::string_view, 9> kKeywords = {
      "host", "hostaddr", "port", "dbname", "user", "password", "service", "sslmode", "passfile"};
  const std::size_t start = db.find_first_not_of(" \t");
  if (start == std::string::npos) return false;
  const std::size_t equals = db.find('=', start);
  if (equals == std::string::npos) return false;
  std::string_view word(db.data() + start, equals - start);
  while (!word.empty() && word.back() == ' ') word.remove_suffix(1);
  return std::find(kKeywords.begin(), kKeywords.end(), word) != kKeywords.end();
}

}  // namespace

std::string without_database_secrets(const std::string& db, std::string text) {
  for (const std::string& secret : database_secrets(db)) {
    for (std::size_t at = text.find(secret); at != std::string::npos;
         at = text.find(secret, at + 3)) {
      text.replace(at, secret.size(), "***");
    }
  }
  return text;
}

std::string database_name(const std::string& db) {
  return without_database_secrets(db, db);
}

Capabilities capabilities_of(std::string_view db) {
  if (!is_postgres_uri(db)) return {};
  return Capabilities{.commit_may_block = false,
                      .spill_during_outage = true,
                      .failure_is_unhealthy = false,
                      .unreachable_at_start_is_outage = true,
                      .open_creates_missing = false};
}

std::string database_value_error(const std::string& db) {
  if (is_postgres_uri(db)) return "";
  const std::size_t scheme_end = db.find("://");
  std::string scheme = db.substr(0, scheme_end == std::string::npos ? 0 : scheme_end + 3);
  std::transform(scheme.begin(), scheme.end(), scheme.begin(),
                 [](unsigned char c) { return static_cast<char>(std::tolower(c)); });
  // (Built by append: GCC 12 warns falsely (-Wrestrict) on "literal" + std::string here.)
  std::string error = "'";
  if (is_postgres_uri(scheme)) {
    return error.append(database_name(db))
        .append("': write the URI scheme in lower case (postgresql:// or postgres://)");
  }
  if (const std::string typed = mistyped_uri_scheme(db); !typed.empty()) {
    return "unknown database URI scheme '" + typed +
           "': use postgresql:// (or postgres://) for PostgreSQL, or a file path for SQLite";
  }
  if (is_libpq_keyword_string(db)) {
    return error.append(database_name(db))
        .append(
            "' is a libpq key=value connection string: --db takes an SQLite file or a URI "
            "(postgresql://USER@HOST:PORT/DBNAME)");
  }
  return "";
}

std::unique_ptr<Connection> open_database(const std::string& db, const OpenOptions& options) {
  if (is_postgres_uri(db)) return std::make_unique<PgDatabase>(db, options);
  if (const std::string error = database_value_error(db); !error.empty()) {
    throw StorageError(StorageError::Kind::kInvalidArgument, error);
  }
  return std::make_unique<Database>(db, options);
}

Connection::CommitOutcome Connection::commit_outcome(int64_t transaction_id) {
  throw StorageError(StorageError::Kind::kInvalidArgument,
                     name() + ": no commit in doubt on this database (transaction " +
                         std::to_string(transaction_id) + ")");
}

int migration_target(const OpenOptions& options, int latest) {
  const int target = options.migrate_to < 0 ? latest : options.migrate_to;
  if (target > latest) {
    throw StorageError(
        StorageError::Kind::kInvalidArgument,
        "migrate_to " + std::to_string(target) + " > known schema " + std::to_string(latest));
  }
  return target;
}

std::unique_ptr<RefitJobLog> Connection::make_refit_job_log() {
  return std::make_unique<SqlRefitJobLog>(sql_session());
}

std::unique_ptr<FilterStateStore> Connection::make_filter_state_store() {
  return std::make_unique<SqlFilterStateStore>(sql_session());
}

std::unique_ptr<MetaStore> Connection::make_meta_store() {
  return std::make_unique<SqlMetaStore>(sql_session());
}

std::unique_ptr<CalibrationHistory> Connection::make_calibration_history() {
  return std::make_unique<SqlCalibrationHistory>(sql_session());
}

std::unique_ptr<LeaseStore> Connection::make_lease_store() {
  return std::make_unique<SqlLeaseStore>(sql_session());
}

}  // namespace magcal::storage
