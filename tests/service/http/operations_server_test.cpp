// The operations server in-process over a small database written here: every route, the 400s,
// start errors, downsampling through the API, reading while a writer writes, and that the
// server never modifies the database file.
#include <arpa/inet.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstdio>
#include <filesystem>
#include <thread>

#include <catch2/catch.hpp>
#include <nlohmann/json.hpp>

#include "service/http/embedded_assets.hpp"
#include "service/http/operations_server.hpp"
#include "service/io/history_report.hpp"
#include "service/io/status_report.hpp"
#include "storage/calibration_history.hpp"
#include "storage/sqlite/database.hpp"
#include "storage/sqlite/sqlite_stores.hpp"
#include "tests/service/http_test_support.hpp"
#include "tests/test_skip.hpp"

using namespace magcal;
using magcal::test::http_get;
using magcal::test::TempDir;

namespace {

constexpr int64_t kMinute = 60'000'000LL;
constexpr int64_t kT0 = 1'577'836'800'000'000LL;  // 2020-01-01T00:00:00Z
constexpr int64_t kWindow = 12 * 60 * kMinute;

// One stored result; every 7th UKF snapshot rejected (not converged, rms unknown).
storage::CalibrationRecord record(const std::string& sat, const std::string& method, int k) {
  storage::CalibrationRecord r;
  r.sat_id = sat;
  r.method = method;
  r.utime = kT0 + k * kMinute;
  r.window_start_utime = kT0;
  r.window_end_utime = r.utime;
  r.n_samples = 6 * (k + 1);
  r.bias_nT = {1000.0 + 0.5 * std::sin(k), 800.0 - 0.01 * k, 900.0 + (k % 5)};
  r.D = {0.01, 0.02, 0.01, 1e-3 * (k % 3), 0.0, -1e-3};
  for (int i = 0; i < 9; ++i)
    r.cov[storage::cov_index(i, i)] = i < 3 ? 1.0 + 0.1 * k : 1e-8 * (k + 1);
  r.residual_rms_nT = 3.0 + 0.01 * k;
  if (method == "ukf" && k % 7 == 0) {
    r.status = 1;
    r.verdict = "rejected";
    r.rejection_reasons = {"not_converged: bias 1-sigma above 10 nT"};
    r.residual_rms_nT = std::numeric_limits<double>::quiet_NaN();
  }
  return r;
}

// SAT-A: 120 UKF snapshots (one a minute) and 2 twostep refits; SAT-B: 3 UKF snapshots.
void populate(const std::string& path) {
  storage::Database db(path);
  storage::SqliteCalibrationHistory history(db);
  storage::Transaction tx(db);
  for (int k = 0; k < 120; ++k) history.append(record("SAT-A", "ukf", k));
  for (int k : {30, 90}) history.append(record("SAT-A", "twostep", k));
  for (int k = 0; k < 3; ++k) history.append(record("SAT-B", "ukf", k));
  tx.commit();
}

http::ServerHooks default_hooks() {
  http::ServerHooks hooks;
  hooks.status_window_utime = kWindow;
  return hooks;
}

struct Fixture {
  TempDir dir{"magcal_http"};
  std::string db = dir.file("m.db");
  std::unique_ptr<http::OperationsServer> server;
  explicit Fixture(http::ServerHooks hooks = default_hooks()) {
    populate(db);
    std::string error;
    server = http::OperationsServer::start("127.0.0.1:0", db, std::move(hooks), &error);
    REQUIRE(server);
    REQUIRE(error.empty());
    REQUIRE(server->port() > 0);
  }
  test::HttpResult get(const std::string& path) const { return http_get(server->port(), path); }
  // What the CLI prints for the same request, through the shared io functions.
  std::string expected(const HistoryRequest& request) const {
    storage::OpenOptions ro;
    ro.read_only = true;
    storage::Database d(db, ro);
    std::string error;
    const auto q = parse_history_request(request, "--", &error);
    REQUIRE(q);
    const auto rows = read_history(d, *q);
    return request.format == "csv" ? history_csv_text(rows) : history_json_text(rows);
  }
};

void require_json_error(const test::HttpResult& r, int status, const std::string& fragment) {
  INFO(r.body);
  REQUIRE(r.status == status);
  REQUIRE(r.content_type == "application/json");
  const auto j = nlohmann::json::parse(r.body);
  REQUIRE(j.at("error").get<std::string>().find(fragment) != std::string::npos);
}

}  // namespace

TEST_CASE("history route answers what the shared history text is, JSON and CSV") {
  Fixture f;
  HistoryRequest request;
  request.sat = "SAT-A";
  request.format = "json";
  auto r = f.get("/api/v1/history?sat=SAT-A");
  REQUIRE(r.status == 200);
  REQUIRE(r.content_type == "application/json");
  REQUIRE(r.body == f.expected(request));
  REQUIRE(nlohmann::json::parse(r.body).size() == 122);

  request.format = "csv";
  r = f.get("/api/v1/history?sat=SAT-A&format=csv");
  REQUIRE(r.status == 200);
  REQUIRE(r.content_type == "text/csv; charset=utf-8");
  REQUIRE(r.body == f.expected(request));

  // Filters: method, inclusive since/until, newest N in descending order.
  request.format = "json";
  request.method = "ukf";
  request.since = "2020-01-01T00:10:00Z";
  request.until = "2020-01-01T00:20:00Z";
  request.limit = 4;
  request.order = "desc";
  r = f.get(
      "/api/v1/history?sat=SAT-A&method=ukf&since=2020-01-01T00:10:00Z&until=2020-01-01T00:20:00Z"
      "&limit=4&order=desc");
  REQUIRE(r.status == 200);
  REQUIRE(r.body == f.expected(request));
  const auto rows = nlohmann::json::parse(r.body);
  REQUIRE(rows.size() == 4);
  REQUIRE(rows[0]["time"] == "2020-01-01T00:20:00Z");
  REQUIRE(rows[3]["time"] == "2020-01-01T00:17:00Z");

  // A known spacecraft with no row in the range: the empty array, like the CLI.
  r = f.get("/api/v1/history?sat=SAT-B&since=2021-01-01T00:00:00Z");
  REQUIRE(r.status == 200);
  REQUIRE(r.body == "[]\n");
}

TEST_CASE("bad history requests get 400 with a JSON error, never a crash") {
  Fixture f;
  require_json_error(f.get("/api/v1/history"), 400, "sat is required");
  require_json_error(f.get("/api/v1/history?sat=NOPE"), 400, "no data for spacecraft 'NOPE'");
  require_json_error(f.get("/api/v1/history?sat=SAT-A&since=yesterday"), 400,
                     "since 'yesterday' is not an ISO 8601 UTC time");
  require_json_error(f.get("/api/v1/history?sat=SAT-A&until=2020-13-01T00:00:00Z"), 400, "until");
  for (const char* limit : {"0", "-3", "abc", "1e3", "5x", "", "99999999999999"}) {
    require_json_error(f.get(std::string("/api/v1/history?sat=SAT-A&limit=") + limit), 400,
                       "limit");
  }
  require_json_error(f.get("/api/v1/history?sat=SAT-A&order=up"), 400, "order must be asc or desc");
  require_json_error(f.get("/api/v1/history?sat=SAT-A&method=kalman"), 400, "unknown method");
  require_json_error(f.get("/api/v1/history?sat=SAT-A&format=table"), 400, "format 'table'");
  require_json_error(f.get("/api/v1/history?sat=SAT-A&format=xml"), 400, "format 'xml'");
  for (const char* points : {"0", "-1", "10001", "many", "2.5"}) {
    require_json_error(f.get(std::string("/api/v1/history?sat=SAT-A&points=") + points), 400,
                       "points");
  }
  require_json_error(f.get("/api/v1/history?sat=SAT-A&points=10&format=csv"), 400,
                     "points needs format=json");
  require_json_error(f.get("/api/v1/history?sat=SAT-A&sat=SAT-B"), 400, "given twice");
  require_json_error(f.get("/api/v1/history?sat=SAT-A&satellite=x"), 400,
                     "unknown parameter 'satellite'");
  require_json_error(f.get("/api/v1/spacecraft?verbose=1"), 400, "unknown parameter");
  require_json_error(f.get("/api/v2/history"), 404, "no such path");
  // Still serving after all of that.
  REQUIRE(f.get("/api/v1/history?sat=SAT-B").status == 200);
}

TEST_CASE("spacecraft route is the status JSON, and the probes, metrics hook, page and Chart.js") {
  SECTION("without hooks") {
    Fixture f;
    auto r = f.get("/api/v1/spacecraft");
    REQUIRE(r.status == 200);
    REQUIRE(r.content_type == "application/json");
    storage::OpenOptions ro;
    ro.read_only = true;
    storage::Database d(f.db, ro);
    REQUIRE(r.body == status_json_text(read_status(d, kWindow), kWindow));
    const auto j = nlohmann::json::parse(r.body);
    REQUIRE(j["spacecraft"].size() == 2);
    REQUIRE(j["spacecraft"][0]["sat_id"] == "SAT-A");
    REQUIRE(j["spacecraft"][0]["last_refit"]["time"] == "2020-01-01T01:30:00Z");

    REQUIRE(f.get("/-/healthy").status == 200);
    REQUIRE(f.get("/-/ready").status == 200);
    require_json_error(f.get("/metrics"), 404, "no metrics");

    r = f.get("/");
    REQUIRE(r.status == 200);
    REQUIRE(r.content_type == "text/html; charset=utf-8");
    REQUIRE(r.body == http::kIndexHtml);
    REQUIRE(r.body.find("/static/chart.js") != std::string::npos);
    r = f.get("/static/chart.js");
    REQUIRE(r.status == 200);
    REQUIRE(r.content_type == "application/javascript; charset=utf-8");
    REQUIRE(r.body == http::kChartJs);
    REQUIRE(r.body.size() > 100'000);
    REQUIRE(r.body.find("Chart.js v" + std::string(http::kChartJsVersion)) != std::string::npos);
  }
  SECTION("with hooks: their answers, changing while the server runs") {
    std::atomic<bool> healthy{true}, ready{false};
    std::atomic<int> scrapes{0};
    auto hooks = default_hooks();
    hooks.healthy = [&] { return healthy.load(); };
    hooks.ready = [&] { return ready.load(); };
    hooks.metrics_text = [&] {
      return "# TYPE magcal_scrapes counter\nmagcal_scrapes " + std::to_string(++scrapes) + "\n";
    };
    Fixture f(hooks);
    REQUIRE(f.get("/-/healthy").status == 200);
    REQUIRE(f.get("/-/ready").status == 503);
    ready = true;
    healthy = false;
    REQUIRE(f.get("/-/healthy").status == 503);
    REQUIRE(f.get("/-/ready").status == 200);
    const auto r = f.get("/metrics");
    REQUIRE(r.status == 200);
    REQUIRE(r.content_type == "text/plain; version=0.0.4; charset=utf-8");
    REQUIRE(r.body == "# TYPE magcal_scrapes counter\nmagcal_scrapes 1\n");
  }
}

TEST_CASE("points=N through the API: the rows of the same query, bucketed") {
  Fixture f;
  const auto r = f.get("/api/v1/history?sat=SAT-A&method=ukf&points=7");
  REQUIRE(r.status == 200);
  const auto j = nlohmann::json::parse(r.body);
  REQUIRE(j["rows"] == 120);
  REQUIRE(j["points"] == 7);
  REQUIRE(j["series"].size() == 1);
  int64_t total = 0;
  for (const auto& b : j["series"][0]["buckets"]) total += b["count"].get<int64_t>();
  REQUIRE(total == 120);
  REQUIRE(j["series"][0]["buckets"].size() == 7);
  // Both methods: one series each, counts per series = rows per method.
  const auto all = nlohmann::json::parse(f.get("/api/v1/history?sat=SAT-A&points=3").body);
  REQUIRE(all["series"].size() == 2);
  REQUIRE(all["series"][1]["method"] == "twostep");
  int64_t refits = 0;
  for (const auto& b : all["series"][1]["buckets"]) refits += b["count"].get<int64_t>();
  REQUIRE(refits == 2);
}

TEST_CASE("start errors: bad listen address, port in use, missing or foreign database") {
  TempDir dir("magcal_http_err");
  const std::string db = dir.file("m.db");
  populate(db);
  std::string error;
  REQUIRE_FALSE(http::OperationsServer::start("127.0.0.1", db, default_hooks(), &error));
  REQUIRE(error.find("not ADDR:PORT") != std::string::npos);
  REQUIRE_FALSE(http::OperationsServer::start("127.0.0.1:70000", db, default_hooks(), &error));
  REQUIRE(error.find("not 0..65535") != std::string::npos);
  REQUIRE_FALSE(http::OperationsServer::start("203.0.113.7:0", db, default_hooks(), &error));
  REQUIRE(
      error.find("cannot bind 203.0.113.7:0: '203.0.113.7' is not an address of this machine") !=
      std::string::npos);
  REQUIRE_FALSE(http::OperationsServer::start("999.1.1.1:0", db, default_hooks(), &error));
  REQUIRE(error.find("cannot bind 999.1.1.1:0: '999.1.1.1' is not an IP address") !=
          std::string::npos);

  auto first = http::OperationsServer::start("127.0.0.1:0", db, default_hooks(), &error);
  REQUIRE(first);
  const std::string taken = "127.0.0.1:" + std::to_string(first->port());
  REQUIRE_FALSE(http::OperationsServer::start(taken, db, default_hooks(), &error));
  REQUIRE(error.find("cannot bind " + taken + ": the port is in use") != std::string::npos);

  REQUIRE_FALSE(
      http::OperationsServer::start("127.0.0.1:0", dir.file("absent.db"), default_hooks(), &error));
  REQUIRE(error.find("cannot open the database") != std::string::npos);
  REQUIRE_FALSE(std::filesystem::exists(dir.file("absent.db")));  // never created
  {
    std::ofstream junk(dir.file("junk.db"));
    junk << "not a database at all, just some text that is long enough to be a header....";
  }
  REQUIRE_FALSE(
      http::OperationsServer::start("127.0.0.1:0", dir.file("junk.db"), default_hooks(), &error));
  REQUIRE(error.find("cannot open the database") != std::string::npos);
  auto no_window = default_hooks();
  no_window.status_window_utime = 0;
  REQUIRE_FALSE(http::OperationsServer::start("127.0.0.1:0", db, no_window, &error));

  // stop() is idempotent and the destructor after it is fine.
  first->stop();
  first->stop();
  REQUIRE(http_get(std::stoi(taken.substr(taken.rfind(':') + 1)), "/-/healthy").status == -1);
}

TEST_CASE("the server reads while a writer commits, and the writer is never refused") {
  Fixture f;
  std::atomic<bool> done{false};
  std::atomic<int> written{0};
  // Reads that saw some of the writer's rows but not all: proof that the two overlapped.
  std::atomic<int> reads_mid_write{0};
  std::thread writer([&] {
    storage::Database db(f.db);  // the daemon's role: its own read-write connection
    storage::SqliteCalibrationHistory history(db);
    for (int k = 120; k < 420; ++k) {
      storage::Transaction tx(db);
      history.append(record("SAT-A", "ukf", k));
      tx.commit();
      ++written;
      // Halfway, the writer waits for a read (on a slow machine the commits could all land
      // between two reads); it keeps its connection open meanwhile.
      if (k == 270) test::wait_until([&] { return reads_mid_write > 0; }, 10);
    }
    done = true;
  });
  int reads = 0;
  size_t last_rows = 0;
  while (!done || reads < 5) {
    const auto r = f.get("/api/v1/history?sat=SAT-A&method=ukf&format=csv");
    REQUIRE(r.status == 200);
    // A consistent snapshot: header plus whole rows, never fewer than before.
    const size_t rows = static_cast<size_t>(std::count(r.body.begin(), r.body.end(), '\n')) - 1;
    REQUIRE(rows >= last_rows);
    REQUIRE(rows >= 120);
    if (rows > 120 && rows < 420) ++reads_mid_write;
    last_rows = rows;
    ++reads;
  }
  writer.join();
  REQUIRE(written == 300);
  CHECK(reads_mid_write > 0);
  const auto r = f.get("/api/v1/history?sat=SAT-A&method=ukf&points=1");
  REQUIRE(nlohmann::json::parse(r.body)["rows"] == 420);
}

TEST_CASE("the server never modifies the database file") {
  TempDir dir("magcal_http_ro");
  const std::string db = dir.file("m.db");
  populate(db);  // closed: checkpointed, no -wal left
  REQUIRE_FALSE(std::filesystem::exists(db + "-wal"));
  struct stat before {};
  REQUIRE(::stat(db.c_str(), &before) == 0);
  const auto bytes_before = test::slurp(db);
  {
    std::string error;
    auto server = http::OperationsServer::start("127.0.0.1:0", db, default_hooks(), &error);
    REQUIRE(server);
    for (const char* path : {"/api/v1/spacecraft", "/api/v1/history?sat=SAT-A",
                             "/api/v1/history?sat=SAT-A&format=csv&points=3",
                             "/api/v1/history?sat=SAT-A&points=50", "/-/healthy"}) {
      http_get(server->port(), path);
    }
  }
  struct stat after {};
  REQUIRE(::stat(db.c_str(), &after) == 0);
  REQUIRE(after.st_size == before.st_size);
  REQUIRE(after.st_mtim.tv_sec == before.st_mtim.tv_sec);
  REQUIRE(after.st_mtim.tv_nsec == before.st_mtim.tv_nsec);
  REQUIRE(test::slurp(db) == bytes_before);
  // SQLite's read-only reader of a WAL database may leave an empty -wal / the -shm index
  // behind (not the database); it never writes a frame into the -wal.
  if (std::filesystem::exists(db + "-wal")) REQUIRE(std::filesystem::file_size(db + "-wal") == 0);
}

TEST_CASE("another method on a known path is 405 with Allow, an unknown path stays 404") {
  Fixture f;
  httplib::Client client("127.0.0.1", f.server->port());
  for (const char* path : {"/metrics", "/-/healthy", "/-/ready", "/api/v1/spacecraft",
                           "/api/v1/history", "/", "/static/chart.js"}) {
    INFO(path);
    for (int method = 0; method < 4; ++method) {
      const auto res = method == 0   ? client.Post(path, "x", "text/plain")
                       : method == 1 ? client.Put(path, "x", "text/plain")
                       : method == 2 ? client.Patch(path, "x", "text/plain")
                                     : client.Delete(path);
      INFO("method " << method);
      REQUIRE(res);
      CHECK(res->status == 405);
      CHECK(res->get_header_value("Allow") == "GET, HEAD");
      CHECK(res->get_header_value("Content-Type") == "application/json");
      CHECK(nlohmann::json::parse(res->body).at("error").get<std::string>().find("not allowed") !=
            std::string::npos);
    }
    const auto head = client.Head(path);
    REQUIRE(head);
    CHECK(head->status != 405);
  }
  const auto post = client.Post("/no/such/path", "x", "text/plain");
  REQUIRE(post);
  CHECK(post->status == 404);
  CHECK(f.get("/no/such/path").status == 404);
}

TEST_CASE("URLs put IPv6 hosts in brackets") {
  CHECK(http::http_url("127.0.0.1", 9780) == "http://127.0.0.1:9780/");
  CHECK(http::http_url("::1", 9780) == "http://[::1]:9780/");
  CHECK(http::http_url("fe80::1%lo", 80) == "http://[fe80::1%lo]:80/");
  CHECK(http::http_url("localhost", 1) == "http://localhost:1/");
}

// Its own test case: the skip below comes before any assertion, so it never hides a failure.
TEST_CASE("a server on the IPv6 loopback says its URL with the host in brackets") {
  TempDir dir("magcal_http_v6");
  const std::string db = dir.file("m.db");
  populate(db);
  std::string error;
  auto server = http::OperationsServer::start("[::1]:0", db, default_hooks(), &error);
  if (!server) {
    magcal::test::skip_or_fail("no IPv6 loopback here: " + error);
    return;
  }
  CHECK(server->url() == "http://[::1]:" + std::to_string(server->port()) + "/");
  httplib::Client client("::1", server->port());
  const auto res = client.Get("/-/healthy");
  REQUIRE(res);
  CHECK(res->status == 200);
}

TEST_CASE("a bound server that never serves gives its port back") {
  TempDir dir("magcal_http_bind");
  std::string error;
  auto bound = http::OperationsServer::bind("127.0.0.1:0", default_hooks(), &error);
  REQUIRE(bound);
  const std::string listen = "127.0.0.1:" + std::to_string(bound->port());
  REQUIRE_FALSE(http::OperationsServer::bind(listen, default_hooks(), &error));  // taken
  bound.reset();  // never served: the socket is closed all the same
  const std::string db = dir.file("m.db");
  populate(db);
  auto again = http::OperationsServer::start(listen, db, default_hooks(), &error);
  REQUIRE(again);
  CHECK(http_get(again->port(), "/-/healthy").status == 200);
}

namespace {

// A raw TCP connection to 127.0.0.1:port (no HTTP client in the way); -1 when it fails.
int raw_connect(int port) {
  const int fd = ::socket(AF_INET, SOCK_STREAM, 0);
  if (fd < 0) return -1;
  sockaddr_in addr{};
  addr.sin_family = AF_INET;
  addr.sin_port = htons(static_cast<uint16_t>(port));
  addr.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
  if (::connect(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr) != 0) {
    ::close(fd);
    return -1;
  }
  return fd;
}

// Seconds until the server closes `fd` (recv returns 0 or an error), at most limit_s.
double seconds_until_closed(int fd, double limit_s) {
  const auto start = std::chrono::steady_clock::now();
  timeval tv{0, 50'000};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  while (true) {
    char byte = 0;
    const ssize_t n = ::recv(fd, &byte, 1, 0);
    const double t =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    if (n == 0 || (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) return t;
    if (t > limit_s) return t;
  }
}

// Sends `request` on a raw connection and returns what the server answers until it closes or
// stays silent for limit_s (the client does not close its side: it waits, as a real one does).
std::string raw_exchange(int port, const std::string& request, double limit_s) {
  const int fd = raw_connect(port);
  REQUIRE(fd >= 0);
  REQUIRE(::send(fd, request.data(), request.size(), 0) == static_cast<ssize_t>(request.size()));
  timeval tv{0, 50'000};
  ::setsockopt(fd, SOL_SOCKET, SO_RCVTIMEO, &tv, sizeof tv);
  std::string answer;
  const auto start = std::chrono::steady_clock::now();
  while (std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() <
         limit_s) {
    char buf[4096];
    const ssize_t n = ::recv(fd, buf, sizeof buf, 0);
    if (n > 0) {
      answer.append(buf, static_cast<size_t>(n));
      // The whole answer is in once its JSON body (Content-Length) has arrived.
      const auto head_end = answer.find("\r\n\r\n");
      const auto len_at = answer.find("Content-Length: ");
      if (head_end != std::string::npos && len_at != std::string::npos &&
          answer.size() >= head_end + 4 + std::stoul(answer.substr(len_at + 16)))
        break;
    } else if (n == 0 || (errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) {
      break;
    }
  }
  ::close(fd);
  return answer;
}

}  // namespace

TEST_CASE("a method without a body (no Content-Length) on a known path is 405 at once") {
  // RFC 9112 6.3: a request without Content-Length or Transfer-Encoding has no body. The
  // client keeps its side open and waits for the answer, as curl -X POST does.
  Fixture f;
  for (const char* method : {"POST", "PUT", "PATCH", "DELETE", "OPTIONS"}) {
    INFO(method);
    const auto t0 = std::chrono::steady_clock::now();
    const std::string answer = raw_exchange(
        f.server->port(),
        std::string(method) + " /api/v1/spacecraft HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", 5.0);
    const double answered_s =
        std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    INFO(answer);
    CHECK(answer.rfind("HTTP/1.1 405", 0) == 0);
    CHECK(answer.find("Allow: GET, HEAD\r\n") != std::string::npos);
    CHECK(answer.find("not allowed") != std::string::npos);
    CHECK(answered_s < 0.5);  // not after the server's 1 s read timeout
  }
  const std::string unknown =
      raw_exchange(f.server->port(), "POST /no/such/path HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n", 5.0);
  INFO(unknown);
  CHECK(unknown.rfind("HTTP/1.1 404", 0) == 0);
  CHECK(unknown.find("no such path") != std::string::npos);
  // A body with its length still works, and the connection stays usable after it.
  const std::string with_body = raw_exchange(
      f.server->port(), "POST /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Length: 3\r\n\r\nabc",
      5.0);
  CHECK(with_body.rfind("HTTP/1.1 405", 0) == 0);
}

TEST_CASE("silent connections do not hold request threads: closed within the timeouts") {
  // More connections that send nothing than the server has request threads: each is dropped
  // after the 1 s keep-alive wait, so a probe that comes after them is answered in about that.
  Fixture f;
  constexpr int kSilent = 24;  // > kRequestThreads (16)
  std::vector<int> fds;
  for (int i = 0; i < kSilent; ++i) {
    const int fd = raw_connect(f.server->port());
    REQUIRE(fd >= 0);
    fds.push_back(fd);
  }
  const auto t0 = std::chrono::steady_clock::now();
  CHECK(f.get("/-/healthy").status == 200);
  const double probe_s =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  double slowest_close_s = 0.0;
  for (const int fd : fds) {
    slowest_close_s = std::max(slowest_close_s, seconds_until_closed(fd, 10.0));
    ::close(fd);
  }
  INFO("probe answered after " << probe_s << " s; silent sockets closed within " << slowest_close_s
                               << " s");
  CHECK(probe_s < 4.0);
  CHECK(slowest_close_s < 4.0);
  std::printf("%d silent connections: probe answered after %.2f s, all closed within %.2f s\n",
              kSilent, probe_s, slowest_close_s);
}
