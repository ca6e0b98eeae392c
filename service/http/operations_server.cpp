// The only translation unit that includes <httplib.h> (large; keep it to one).
#include "service/http/operations_server.hpp"

#include <httplib.h>
#include <netdb.h>
#include <sys/socket.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include <charconv>
#include <chrono>
#include <mutex>
#include <optional>
#include <set>
#include <thread>

#include <spdlog/spdlog.h>
#include <nlohmann/json.hpp>

#include "service/http/embedded_assets.hpp"
#include "service/io/history_report.hpp"
#include "service/io/read_only_database.hpp"
#include "service/io/status_report.hpp"
#include "storage/connection.hpp"

namespace magcal::http {

namespace {

constexpr const char* kJson = "application/json";
constexpr int kMaxPoints = 10000;
// Request threads. A browser holds up to 6 keep-alive connections, each occupying a thread
// until it closes: 16 threads (and a short keep-alive and read timeout) keep a page load or a
// few idle sockets from starving a Prometheus scrape. Database reads are serialised on the one
// connection anyway.
constexpr size_t kRequestThreads = 16;

struct BadRequest {
  std::string message;
};

void send_error(httplib::Response& res, int status, const std::string& message) {
  res.status = status;
  res.set_content(nlohmann::json{{"error", message}}.dump() + "\n", kJson);
}

// Another method on a path that only GET (and HEAD) serves: 405 with Allow.
void not_allowed(const httplib::Request& req, httplib::Response& res) {
  res.set_header("Allow", "GET, HEAD");
  send_error(res, 405, "method " + req.method + " not allowed on " + req.path + " (GET only)");
}

// A whole decimal integer in [lo, hi], else BadRequest naming the parameter.
int parse_int_param(const std::string& name, const std::string& text, int lo, int hi) {
  int value = 0;
  const auto res = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || res.ec != std::errc{} || res.ptr != text.data() + text.size() || value < lo ||
      value > hi) {
    throw BadRequest{name + " '" + text + "' is not an integer in " + std::to_string(lo) + ".." +
                     std::to_string(hi)};
  }
  return value;
}

// Every query parameter must be known and given at most once (a typo is an error, not ignored).
void check_params(const httplib::Request& req, const std::set<std::string>& known) {
  for (const auto& [name, value] : req.params) {
    if (!known.count(name)) throw BadRequest{"unknown parameter '" + name + "'"};
    if (req.params.count(name) > 1) throw BadRequest{"parameter '" + name + "' given twice"};
  }
}

std::string param(const httplib::Request& req, const std::string& name) {
  return req.has_param(name.c_str()) ? req.get_param_value(name.c_str()) : std::string();
}

}  // namespace

bool parse_listen(const std::string& listen, std::string* host, int* port, std::string* error) {
  const auto colon = listen.rfind(':');
  if (colon == std::string::npos || colon == 0 || colon + 1 == listen.size()) {
    *error = "listen address '" + listen + "' is not ADDR:PORT (e.g. 127.0.0.1:9780)";
    return false;
  }
  *host = listen.substr(0, colon);
  if (host->size() >= 2 && host->front() == '[' && host->back() == ']') {
    *host = host->substr(1, host->size() - 2);
  }
  const std::string port_text = listen.substr(colon + 1);
  const auto res = std::from_chars(port_text.data(), port_text.data() + port_text.size(), *port);
  if (res.ec != std::errc{} || res.ptr != port_text.data() + port_text.size() || *port < 0 ||
      *port > 65535) {
    *error = "listen address '" + listen + "': port '" + port_text + "' is not 0..65535";
    return false;
  }
  return true;
}

// Why host:port cannot be bound, found after cpp-httplib's bind failed (it keeps the reason to
// itself): the name does not resolve, or the kernel's errno of a plain bind of its first address.
std::string bind_failure_reason(const std::string& host, int port) {
  addrinfo hints{};
  hints.ai_family = AF_UNSPEC;
  hints.ai_socktype = SOCK_STREAM;
  hints.ai_flags = AI_PASSIVE | AI_NUMERICSERV;
  // An address literal (even a wrong one, 999.1.1.1) is not looked up in DNS.
  if (host.find_first_not_of("0123456789.") == std::string::npos ||
      host.find(':') != std::string::npos) {
    hints.ai_flags |= AI_NUMERICHOST;
  }
  addrinfo* found = nullptr;
  const std::string port_text = std::to_string(port);
  if (const int rc = ::getaddrinfo(host.c_str(), port_text.c_str(), &hints, &found); rc != 0) {
    return "'" + host + "' is not an IP address or a name this machine resolves (" +
           ::gai_strerror(rc) + ")";
  }
  const int fd = ::socket(found->ai_family, found->ai_socktype, found->ai_protocol);
  int err = fd < 0 ? errno : 0;
  if (fd >= 0) {
    const int yes = 1;
    ::setsockopt(fd, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);  // as cpp-httplib binds
    if (::bind(fd, found->ai_addr, found->ai_addrlen) != 0) err = errno;
    ::close(fd);
  }
  ::freeaddrinfo(found);
  switch (err) {
    case EADDRINUSE:
      return "the port is in use";
    case EADDRNOTAVAIL:
      return "'" + host + "' is not an address of this machine";
    case EACCES:
      return "a port below 1024 needs privileges";
    case 0:
      return "the address is free now: try again";
    default:
      return std::strerror(err);
  }
}

std::string http_url(const std::string& host, int port) {
  const bool ipv6 = host.find(':') != std::string::npos;
  return "http://" + (ipv6 ? "[" + host + "]" : host) + ":" + std::to_string(port) + "/";
}

struct OperationsServer::Impl {
  ServerHooks hooks;
  std::mutex db_mutex;  // the connection belongs to one request thread at a time
  std::unique_ptr<storage::Connection> db;  // opened by serve(), before any request is taken
  std::string db_path;
  httplib::Server server;
  std::thread thread;
  std::string host;
  int port = 0;
  int listen_fd = -1;  // the bound socket: closed here if serve() never ran
  std::once_flag stopped;

  explicit Impl(ServerHooks h) : hooks(std::move(h)) {}

  void routes();
  // GET (and HEAD, which cpp-httplib answers from the GET route) on `path`; every other method
  // there gets 405 with Allow, not 404: the path exists.
  template <typename Handler>
  void get(const std::string& path, Handler&& handler);
  std::set<std::string> get_paths;  // every path get() registered
  void history(const httplib::Request& req, httplib::Response& res);
};

template <typename Handler>
void OperationsServer::Impl::get(const std::string& path, Handler&& handler) {
  server.Get(path, std::forward<Handler>(handler));
  get_paths.insert(path);
  server.Post(path, not_allowed);
  server.Put(path, not_allowed);
  server.Patch(path, not_allowed);
  server.Delete(path, not_allowed);
}

void OperationsServer::Impl::routes() {
  server.new_task_queue = [] { return new httplib::ThreadPool(kRequestThreads); };
  // SO_REUSEADDR only: cpp-httplib's default also sets SO_REUSEPORT, which would let a second
  // server (a magcald and a magcal serve) silently share a port and split its requests.
  server.set_socket_options([this](socket_t sock) {
    int yes = 1;
    ::setsockopt(sock, SOL_SOCKET, SO_REUSEADDR, &yes, sizeof yes);
    listen_fd = sock;  // cpp-httplib calls this for the listening socket only
  });
  server.set_keep_alive_timeout(1);
  // A client that opens a connection and sends nothing (or trickles a header) holds a request
  // thread until this timeout: short, so that a few idle sockets cannot stall health probes
  // and scrapes for long (a trickle of one header line per second still can: loopback default).
  server.set_read_timeout(1, 0);
  server.set_write_timeout(5, 0);
  server.set_payload_max_length(64 * 1024);  // GET only: no request needs a body
  // A request without Content-Length or Transfer-Encoding has no body (RFC 9112 6.3), but
  // cpp-httplib 0.11 reads a POST/PUT/PATCH/DELETE's body without a length until the client
  // closes its side (read_content_without_length): a client that waits for the answer (curl
  // -X POST) got 400 after the 1 s read timeout, never the route's 405. Such requests are
  // answered here, before the library reads: 405 with Allow on a path of ours, else 404. A
  // request with a length or chunked body goes on to the routes (its body read, the
  // connection kept in step).
  server.set_pre_routing_handler([this](const httplib::Request& req, httplib::Response& res) {
    if (req.method == "GET" || req.method == "HEAD" || req.has_header("Content-Length") ||
        req.has_header("Transfer-Encoding"))
      return httplib::Server::HandlerResponse::Unhandled;
    if (get_paths.count(req.path) != 0) {
      not_allowed(req, res);
    } else {
      res.status = 404;  // the error handler says "no such path"
    }
    return httplib::Server::HandlerResponse::Handled;
  });

  get("/metrics", [this](const httplib::Request&, httplib::Response& res) {
    if (!hooks.metrics_text) return send_error(res, 404, "no metrics in this server");
    res.set_content(hooks.metrics_text(), "text/plain; version=0.0.4; charset=utf-8");
  });
  auto probe = [this](const std::function<bool()>& hook, const char* yes, const char* no) {
    return [this, &hook, yes, no](const httplib::Request&, httplib::Response& res) {
      const bool ok = !hook || hook();
      res.status = ok ? 200 : 503;
      std::string body = ok ? yes : no;
      if (hooks.probe_detail) body += hooks.probe_detail();
      res.set_content(body, "text/plain; charset=utf-8");
    };
  };
  get("/-/healthy", probe(hooks.healthy, "magcal is healthy.\n", "magcal is unhealthy.\n"));
  get("/-/ready", probe(hooks.ready, "magcal is ready.\n", "magcal is not ready.\n"));
  get("/api/v1/spacecraft", [this](const httplib::Request& req, httplib::Response& res) {
    check_params(req, {});
    std::lock_guard lock(db_mutex);
    const auto all = read_consistently(db, db_path, [this](storage::Connection& d) {
      return read_status(d, hooks.status_window_utime);
    });
    res.set_content(status_json_text(all, hooks.status_window_utime), kJson);
  });
  get("/api/v1/history",
      [this](const httplib::Request& req, httplib::Response& res) { history(req, res); });
  get("/", [](const httplib::Request&, httplib::Response& res) {
    res.set_content(std::string(kIndexHtml), "text/html; charset=utf-8");
  });
  get("/static/chart.js", [](const httplib::Request&, httplib::Response& res) {
    res.set_header("Cache-Control", "max-age=86400");
    res.set_content(std::string(kChartJs), "application/javascript; charset=utf-8");
  });

  server.set_exception_handler(
      [](const httplib::Request&, httplib::Response& res, std::exception_ptr ep) {
        try {
          std::rethrow_exception(ep);
        } catch (const BadRequest& e) {
          send_error(res, 400, e.message);
        } catch (const storage::StorageError& e) {
          // A lock held past the busy timeout or an I/O error may heal: tell the client to retry.
          send_error(res, e.transient() ? 503 : 500, std::string("database: ") + e.what());
        } catch (const std::exception& e) {
          send_error(res, 500, e.what());
        } catch (...) {
          send_error(res, 500, "unknown error");
        }
      });
  server.set_error_handler([](const httplib::Request& req, httplib::Response& res) {
    if (!res.body.empty()) return;  // a route's own error (400, 503) already has its JSON body
    send_error(
        res, res.status,
        res.status == 404 ? "no such path: " + req.path : "HTTP " + std::to_string(res.status));
  });
}

void OperationsServer::Impl::history(const httplib::Request& req, httplib::Response& res) {
  check_params(req, {"sat", "method", "since", "until", "limit", "order", "format", "points"});
  HistoryRequest request;
  request.sat = param(req, "sat");
  if (request.sat.empty()) throw BadRequest{"sat is required (a spacecraft id)"};
  request.method = param(req, "method");
  request.since = param(req, "since");
  request.until = param(req, "until");
  if (req.has_param("limit")) {
    request.limit = parse_int_param("limit", param(req, "limit"), 1, 1'000'000'000);
  }
  if (req.has_param("order")) request.order = param(req, "order");
  request.format = req.has_param("format") ? param(req, "format") : "json";
  if (request.format != "json" && request.format != "csv") {
    throw BadRequest{"format '" + request.format + "' is not json or csv"};
  }
  std::optional<int> points;
  if (req.has_param("points")) {
    points = parse_int_param("points", param(req, "points"), 1, kMaxPoints);
    if (request.format != "json") throw BadRequest{"points needs format=json"};
  }
  std::string error;
  const auto query = parse_history_request(request, "", &error);
  if (!query) throw BadRequest{error};

  std::vector<storage::CalibrationRecord> rows;
  {
    std::lock_guard lock(db_mutex);
    bool known = true;
    rows = read_consistently(db, db_path, [&](storage::Connection& d) {
      auto found = read_history(d, *query);
      known = !found.empty() || spacecraft_known(d, request.sat);
      return found;
    });
    if (!known) {
      throw BadRequest{"no data for spacecraft '" + request.sat + "'"};
    }
  }
  if (points) {
    res.set_content(downsample_history(rows, *query, *points).dump() + "\n", kJson);
  } else if (request.format == "csv") {
    res.set_content(history_csv_text(rows), "text/csv; charset=utf-8");
  } else {
    res.set_content(history_json_text(rows), kJson);
  }
}

OperationsServer::OperationsServer(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}

std::unique_ptr<OperationsServer> OperationsServer::start(const std::string& listen,
                                                          const std::string& db_path,
                                                          ServerHooks hooks, std::string* error) {
  auto server = bind(listen, std::move(hooks), error);
  if (!server || !server->serve(db_path, error)) return nullptr;
  return server;
}

std::unique_ptr<OperationsServer> OperationsServer::bind(const std::string& listen,
                                                         ServerHooks hooks, std::string* error) {
  std::string host;
  int port = 0;
  if (!parse_listen(listen, &host, &port, error)) return nullptr;
  if (hooks.status_window_utime <= 0) {
    *error = "operations server: status_window_utime must be > 0";
    return nullptr;
  }
  auto impl = std::make_unique<Impl>(std::move(hooks));
  impl->routes();
  if (port == 0) {
    port = impl->server.bind_to_any_port(host);
    if (port <= 0) {
      *error = "cannot bind " + listen + ": " + bind_failure_reason(host, 0);
      return nullptr;
    }
  } else if (!impl->server.bind_to_port(host, port)) {
    *error = "cannot bind " + listen + ": " + bind_failure_reason(host, port);
    return nullptr;
  }
  impl->host = host;
  impl->port = port;
  return std::unique_ptr<OperationsServer>(new OperationsServer(std::move(impl)));
}

bool OperationsServer::serve(const std::string& db_path, std::string* error, bool connect_later,
                             int reply_timeout_ms) {
  try {
    storage::OpenOptions options;
    options.read_only = true;
    options.connect_later = connect_later;
    options.reply_timeout_ms = reply_timeout_ms;
    impl_->db = storage::open_database(db_path, options);
    impl_->db_path = db_path;
  } catch (const storage::StorageError& e) {
    *error = std::string("cannot open the database read-only: ") + e.what();
    return false;
  }
  Impl* raw = impl_.get();
  impl_->thread = std::thread([raw] { raw->server.listen_after_bind(); });
  // stop() is a no-op until the listener runs: wait for it (it only has to enter its loop).
  for (int i = 0; i < 5000 && !impl_->server.is_running(); ++i) {
    std::this_thread::sleep_for(std::chrono::milliseconds(1));
  }
  spdlog::info("operations server: {} (database {}, read-only)", url(), impl_->db->name());
  return true;
}

std::string OperationsServer::url() const {
  return http_url(impl_->host, impl_->port);
}

int OperationsServer::port() const {
  return impl_->port;
}

void OperationsServer::stop() {
  std::call_once(impl_->stopped, [this] {
    if (impl_->thread.joinable()) {
      impl_->server.stop();  // closes the socket
      impl_->thread.join();
    } else if (impl_->listen_fd >= 0) {
      ::close(impl_->listen_fd);  // bound, never served: cpp-httplib's stop() would not close it
    }
  });
}

OperationsServer::~OperationsServer() {
  stop();
}

}  // namespace magcal::http
