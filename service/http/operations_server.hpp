// The read-only operations server (design.md "Operations surface"), one implementation for
// `magcald --http-listen` and `magcal serve`:
//   GET /metrics            hooks.metrics_text() as Prometheus text (404 without the hook)
//   GET /-/healthy          200 / 503 from hooks.healthy (200 without the hook)
//   GET /-/ready            200 / 503 from hooks.ready (200 without the hook: the DB is open)
//   GET /api/v1/spacecraft  exactly the stdout of `magcal status --json`
//   GET /api/v1/history?sat=&method=&since=&until=&limit=&order=&format=json|csv
//                           exactly the stdout of `magcal history` with the same arguments;
//                           &points=N (1..10000, JSON only): downsample_history()
//                           (service/io/history_report.hpp) over the same rows
//   GET /                   the plots page; GET /static/chart.js the plotting library
// A bad request (missing or unknown spacecraft, bad time, limit, order, method, format or
// points, an unknown or repeated parameter) gets 400 with {"error": "..."}; an unknown path 404;
// another method than GET (or HEAD) on a known path 405 with "Allow: GET, HEAD";
// a database error 503 (transient: locked, I/O) or 500, always with a JSON error body.
//
// Threads: the server runs on its own thread (cpp-httplib's listener plus a small pool of
// request threads) with its own read-only database connection (an SQLite file or PostgreSQL),
// opened once at start and shared by the request threads under a mutex; every request reads in
// one short read transaction (one snapshot), so a writer (the daemon's ingest) is never blocked
// by it (SQLite's WAL, PostgreSQL's MVCC).
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <string>

namespace magcal::http {

struct ServerHooks {
  std::function<std::string()>
      metrics_text;               // Prometheus text exposition for /metrics (empty fn: 404)
  std::function<bool()> healthy;  // /-/healthy: 200 when true, 503 when false
  std::function<bool()> ready;    // /-/ready: 200 when true, 503 when false
  // A line added to both probes' bodies ("" or an empty fn: none): what the answer rests on,
  // e.g. a storage outage being ridden out.
  std::function<std::string()> probe_detail;
  // The refit window /api/v1/spacecraft counts samples in (the daemon's [storage]
  // window_hours; `magcal serve` and `magcal status` use the default config's). Must be > 0.
  int64_t status_window_utime = 0;
};

// Splits a listen address "ADDR:PORT" (IPv6 as "[ADDR]:PORT") into host and port 0..65535
// (0 = any free port). False and *error set (one line) when it is not one. The one parser for
// `magcal serve --listen`, `magcald --http-listen` and the config check of `[http] listen`.
bool parse_listen(const std::string& listen, std::string* host, int* port, std::string* error);

// "http://HOST:PORT/", IPv6 hosts in brackets ("http://[::1]:9780/").
std::string http_url(const std::string& host, int port);

class OperationsServer {
 public:
  // bind() then serve(): nullptr and *error set (one line) when either fails.
  static std::unique_ptr<OperationsServer> start(const std::string& listen,
                                                 const std::string& db_path, ServerHooks hooks,
                                                 std::string* error);
  // Binds listen = "ADDR:PORT" (IPv6 as "[ADDR]:PORT"; port 0 = any free port) and nothing
  // else: no file is touched, so a daemon can find a taken port before it creates its
  // database. Connections wait in the backlog until serve(). nullptr and *error when it cannot.
  static std::unique_ptr<OperationsServer> bind(const std::string& listen, ServerHooks hooks,
                                                std::string* error);
  // Opens db_path (a file or a PostgreSQL URI) read-only with its own connection (never writes,
  // never creates the file) and serves on its own thread (created here: it and its request
  // threads inherit the calling thread's priority). False and *error set when the database
  // cannot be opened. `connect_later` (magcald): a PostgreSQL server that cannot be reached now
  // does not fail it (storage::OpenOptions::connect_later); the API answers 503 until it can.
  // `reply_timeout_ms`: storage::OpenOptions::reply_timeout_ms (a request on a server that does
  // not answer fails with 503 then).
  bool serve(const std::string& db_path, std::string* error, bool connect_later = false,
             int reply_timeout_ms = 10000);
  int port() const;         // the bound port
  std::string url() const;  // http_url() of the bound address
  void stop();              // idempotent; also in the destructor
  ~OperationsServer();

  OperationsServer(const OperationsServer&) = delete;
  OperationsServer& operator=(const OperationsServer&) = delete;

 private:
  struct Impl;
  explicit OperationsServer(std::unique_ptr<Impl> impl);
  std::unique_ptr<Impl> impl_;
};

}  // namespace magcal::http
