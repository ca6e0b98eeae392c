#include "service/daemon/intake/sample_spill.hpp"

#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include <fmt/format.h>

#include "service/io/fnv1a.hpp"
#include "storage/sample_row.hpp"

namespace magcal {
namespace {

constexpr char kMagic[8] = {'M', 'G', 'S', 'P', 'I', 'L', 'L', '1'};
constexpr size_t kRecordHeaderBytes = sizeof(uint32_t) + sizeof(uint64_t);

template <typename T>
void put(std::vector<char>& out, const T& v) {
  const auto* p = reinterpret_cast<const char*>(&v);
  out.insert(out.end(), p, p + sizeof(T));
}

// Reads values off a payload; ok() is false once one ran past its end.
class Reader {
 public:
  Reader(const char* data, size_t n) : p_(data), end_(data + n) {}
  template <typename T>
  T get() {
    T v{};
    if (static_cast<size_t>(end_ - p_) < sizeof(T)) {
      ok_ = false;
      return v;
    }
    std::memcpy(&v, p_, sizeof(T));
    p_ += sizeof(T);
    return v;
  }
  std::string get_string(size_t n) {
    if (static_cast<size_t>(end_ - p_) < n) {
      ok_ = false;
      return {};
    }
    std::string s(p_, n);
    p_ += n;
    return s;
  }
  // Every byte used, none missing.
  bool done() const { return ok_ && p_ == end_; }

 private:
  const char* p_;
  const char* end_;
  bool ok_ = true;
};

// A record's payload walks the sample's field list (storage/sample_row.hpp) in its order: the key
// as u32 length + bytes, each number in native byte order, every group's values whether present
// or not. The presence flags (the stored one and those of the optional groups, in list order:
// bits 1, 2, 4) share one byte, at the place of the stored flag.
class Encoder {
 public:
  explicit Encoder(std::vector<char>& out) : out_(out) {}
  void key(const char*, const std::string& v) {
    put(out_, static_cast<uint32_t>(v.size()));
    out_.insert(out_.end(), v.begin(), v.end());
  }
  void integer(const char*, int64_t v) { put(out_, v); }
  void real(const char*, double v) { put(out_, v); }
  void nullable_real(const char*, double v) { put(out_, v); }
  template <size_t N, typename Array>
  void reals(const char* const (&)[N], const Array& v) {
    put(out_, v);
  }
  void flag(const char*, bool v) {
    flags_at_ = out_.size();
    put(out_, static_cast<uint8_t>(v ? 1 : 0));
    next_bit_ = 2;
  }
  template <size_t N, typename Array>
  void flagged(const char* const (&)[N], const Array& v, bool) {
    put(out_, v);
  }
  template <size_t N, typename Array>
  void optional(const char* const (&)[N], const Array& v, bool present) {
    if (present) out_[flags_at_] = static_cast<char>(out_[flags_at_] | next_bit_);
    next_bit_ = static_cast<uint8_t>(next_bit_ << 1);
    put(out_, v);
  }

 private:
  std::vector<char>& out_;
  size_t flags_at_ = 0;
  uint8_t next_bit_ = 0;
};

class Decoder {
 public:
  explicit Decoder(Reader& in) : in_(in) {}
  void key(const char*, std::string& v) { v = in_.get_string(in_.get<uint32_t>()); }
  void integer(const char*, int64_t& v) { v = in_.get<int64_t>(); }
  void real(const char*, double& v) { v = in_.get<double>(); }
  void nullable_real(const char*, double& v) { v = in_.get<double>(); }
  template <size_t N, typename Array>
  void reals(const char* const (&)[N], Array& v) {
    v = in_.get<Array>();
  }
  void flag(const char*, bool& v) {
    flags_ = in_.get<uint8_t>();
    v = (flags_ & 1) != 0;
    next_bit_ = 2;
  }
  template <size_t N, typename Array>
  void flagged(const char* const (&)[N], Array& v, bool) {
    v = in_.get<Array>();
  }
  template <size_t N, typename Array>
  void optional(const char* const (&)[N], Array& v, bool& present) {
    present = (flags_ & next_bit_) != 0;
    next_bit_ = static_cast<uint8_t>(next_bit_ << 1);
    v = in_.get<Array>();
  }

 private:
  Reader& in_;
  uint8_t flags_ = 0;
  uint8_t next_bit_ = 0;
};

void encode(const storage::StoredSample& s, std::vector<char>& out) {
  Encoder encoder(out);
  storage::sample_row::fields(s, encoder);
}

bool decode(const char* data, size_t n, storage::StoredSample& s) {
  Reader in(data, n);
  Decoder decoder(in);
  storage::sample_row::fields(s, decoder);
  return in.done() && !s.sat_id.empty();
}

}  // namespace

SampleSpill::SampleSpill(std::string path, std::string database, int64_t max_bytes)
    : path_(std::move(path)), database_(std::move(database)), max_bytes_(max_bytes) {
  try {
    if (::access(path_.c_str(), F_OK) == 0) open_existing();
    if (fd_ < 0) create();  // (none, or one that held nothing: removed)
  } catch (const SpillError&) {
    if (fd_ >= 0) ::close(fd_);  // (no destructor runs)
    throw;
  }
}

SampleSpill::~SampleSpill() {
  if (held_ == 0) {
    close_and_remove();
  } else if (fd_ >= 0) {
    ::close(fd_);  // also releases the lock
  }
}

void SampleSpill::fail(const std::string& what) const {
  const int e = errno;
  const char* name = ::strerrorname_np(e);
  throw SpillError(fmt::format("spill file {}: {}: {} ({})", path_, what, std::strerror(e),
                               name != nullptr ? name : "unknown errno"));
}

bool SampleSpill::read_exact(int64_t offset, void* out, size_t n) const {
  auto* p = static_cast<char*>(out);
  while (n > 0) {
    const ssize_t got = ::pread(fd_, p, n, offset);
    if (got < 0 && errno == EINTR) continue;
    if (got < 0) fail("read");
    if (got == 0) return false;
    p += got;
    n -= static_cast<size_t>(got);
    offset += got;
  }
  return true;
}

void SampleSpill::open_existing() {
  fd_ = ::open(path_.c_str(), O_RDWR | O_CLOEXEC);
  if (fd_ < 0) fail("cannot open");
  if (::flock(fd_, LOCK_EX | LOCK_NB) != 0)
    fail("locked by another process (another magcald with this [station] id and spill_dir?)");
  char magic[sizeof kMagic];
  uint64_t committed = 0;
  uint32_t name_bytes = 0;
  if (!read_exact(0, magic, sizeof magic) || std::memcmp(magic, kMagic, sizeof kMagic) != 0 ||
      !read_exact(sizeof magic, &committed, sizeof committed) ||
      !read_exact(sizeof magic + sizeof committed, &name_bytes, sizeof name_bytes) ||
      name_bytes > kMaxPayloadBytes) {
    errno = 0;
    throw SpillError("spill file " + path_ +
                     ": not a magcal spill file (no MGSPILL1 header); move it away to start");
  }
  header_bytes_ =
      static_cast<int64_t>(sizeof magic + sizeof committed + sizeof name_bytes + name_bytes);
  found_database_.resize(name_bytes);
  if (!read_exact(header_bytes_ - name_bytes, found_database_.data(), name_bytes)) {
    found_database_.clear();
  }
  committed_ = std::max(header_bytes_, static_cast<int64_t>(committed));
  // Every record after the committed offset is checked; the first short or corrupt one ends
  // the file (records are appended in order, so nothing valid can follow a torn one).
  const off_t size = ::lseek(fd_, 0, SEEK_END);
  if (size < 0) fail("seek");
  // (An offset past the end, stopped while emptying it after the cut: holds nothing.)
  int64_t at = committed_;
  storage::StoredSample row;
  while (at < size) {
    uint32_t n = 0;
    uint64_t sum = 0;
    if (!read_exact(at, &n, sizeof n) || !read_exact(at + 4, &sum, sizeof sum) ||
        n > kMaxPayloadBytes) {
      break;
    }
    buffer_.resize(n);
    if (!read_exact(at + static_cast<int64_t>(kRecordHeaderBytes), buffer_.data(), n) ||
        fnv1a_64({buffer_.data(), n}) != sum || !decode(buffer_.data(), n, row)) {
      break;
    }
    at += static_cast<int64_t>(kRecordHeaderBytes + n);
    ++held_;
  }
  if (at < size) {
    ++dropped_;
    if (::ftruncate(fd_, at) != 0) fail("cannot cut off its torn end");
  }
  end_ = at;
  if (held_ == 0) close_and_remove();
}

void SampleSpill::create() {
  fd_ = ::open(path_.c_str(), O_RDWR | O_CREAT | O_EXCL | O_CLOEXEC, 0640);
  if (fd_ < 0) fail("cannot create");
  if (::flock(fd_, LOCK_EX | LOCK_NB) != 0)
    fail("locked by another process (another magcald with this [station] id and spill_dir?)");
  header_bytes_ =
      static_cast<int64_t>(sizeof kMagic + sizeof(uint64_t) + sizeof(uint32_t) + database_.size());
  const auto offset = static_cast<uint64_t>(header_bytes_);
  const auto name_bytes = static_cast<uint32_t>(database_.size());
  std::string header(kMagic, sizeof kMagic);
  header.append(reinterpret_cast<const char*>(&offset), sizeof offset);
  header.append(reinterpret_cast<const char*>(&name_bytes), sizeof name_bytes);
  header += database_;
  if (::pwrite(fd_, header.data(), header.size(), 0) != static_cast<ssize_t>(header.size())) {
    const int e = errno;
    ::close(fd_);
    fd_ = -1;
    ::unlink(path_.c_str());
    errno = e;
    fail("cannot write its header");
  }
  committed_ = end_ = header_bytes_;
}

void SampleSpill::close_and_remove() {
  if (fd_ >= 0) {
    ::unlink(path_.c_str());  // while still locked: no other process opens a half-removed file
    ::close(fd_);
    fd_ = -1;
  }
  committed_ = end_ = header_bytes_ = held_ = 0;
  read_end_ = read_count_ = 0;
}

bool SampleSpill::append(std::span<const storage::StoredSample> rows) {
  if (rows.empty()) return true;
  buffer_.clear();
  for (const auto& s : rows) {
    const size_t at = buffer_.size();
    buffer_.resize(at + kRecordHeaderBytes);
    encode(s, buffer_);
    const auto n = static_cast<uint32_t>(buffer_.size() - at - kRecordHeaderBytes);
    const uint64_t sum = fnv1a_64({buffer_.data() + at + kRecordHeaderBytes, n});
    std::memcpy(buffer_.data() + at, &n, sizeof n);
    std::memcpy(buffer_.data() + at + sizeof n, &sum, sizeof sum);
  }
  // (The header is small against a batch: not counted against the bound.)
  if (bytes() + static_cast<int64_t>(buffer_.size()) > max_bytes_) return false;
  const char* p = buffer_.data();
  size_t left = buffer_.size();
  int64_t at = end_;
  while (left > 0) {
    const ssize_t put_bytes = ::pwrite(fd_, p, left, at);
    if (put_bytes < 0 && errno == EINTR) continue;
    if (put_bytes <= 0) {
      const int e = errno;
      if (::ftruncate(fd_, end_) != 0) {
        // (Cut back at the next open: a torn tail.)
      }
      errno = e;
      fail("write");
    }
    p += put_bytes;
    left -= static_cast<size_t>(put_bytes);
    at += put_bytes;
  }
  if (::fdatasync(fd_) != 0) {
    const int e = errno;
    if (::ftruncate(fd_, end_) != 0) {
      // (As above.)
    }
    errno = e;
    fail("fdatasync");
  }
  end_ = at;
  held_ += static_cast<int64_t>(rows.size());
  return true;
}

size_t SampleSpill::read_chunk(size_t max_rows, std::vector<storage::StoredSample>& out) {
  out.clear();
  int64_t at = committed_;
  while (out.size() < max_rows && at < end_) {
    uint32_t n = 0;
    uint64_t sum = 0;
    if (!read_exact(at, &n, sizeof n) || !read_exact(at + 4, &sum, sizeof sum) ||
        n > kMaxPayloadBytes) {
      errno = EIO;
      fail("record changed since it was written");
    }
    buffer_.resize(n);
    if (!read_exact(at + static_cast<int64_t>(kRecordHeaderBytes), buffer_.data(), n) ||
        fnv1a_64({buffer_.data(), n}) != sum || !decode(buffer_.data(), n, out.emplace_back())) {
      errno = EIO;
      fail("record changed since it was written");
    }
    at += static_cast<int64_t>(kRecordHeaderBytes + n);
  }
  read_end_ = at;
  read_count_ = static_cast<int64_t>(out.size());
  return out.size();
}

void SampleSpill::commit_read() {
  if (read_count_ == 0) return;
  committed_ = read_end_;
  held_ -= read_count_;
  read_count_ = 0;
  if (committed_ >= end_) {
    empty();
    return;
  }
  write_committed_offset();
}

void SampleSpill::empty() {
  // The offset first: stopped before the cut, the file holds only committed records.
  write_committed_offset();
  if (::ftruncate(fd_, header_bytes_) != 0) fail("cannot cut it back to its header");
  committed_ = end_ = header_bytes_;
  write_committed_offset();
  read_end_ = read_count_ = 0;
}

void SampleSpill::write_committed_offset() {
  const auto offset = static_cast<uint64_t>(committed_);
  if (::pwrite(fd_, &offset, sizeof offset, sizeof kMagic) != sizeof offset) fail("write");
}

}  // namespace magcal
