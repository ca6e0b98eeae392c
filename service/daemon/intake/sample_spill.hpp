// The spill file: validated samples a station received while its PostgreSQL database was
// unreachable (each commit interval's batch while commits fail, so a crash during an outage
// loses no more than one interval). The worker appends the pending batch here instead of
// stopping intake, and commits the file back (chunk by chunk, oldest first) when
// the database returns; a file left behind by a daemon that stopped or was killed during an outage
// is committed at its next start. The file is created (or opened) when the daemon starts and
// stays open, locked and holding nothing until an outage: a spill_dir that cannot take it is a
// start error, not a surprise in the middle of an outage. It is removed when the daemon ends
// with nothing in it.
//
// Format (one machine writes and reads it: native byte order, no portability promised):
//   header  "MGSPILL1", u64 offset of the first record not yet committed, u32 length + the
//           database it was written for (its name without password, for the log)
//           (holding nothing: the header alone)
//   record  u32 payload length, u64 FNV-1a of the payload, payload (one storage::StoredSample,
//           in the order of its field list, storage/sample_row.hpp: a new field changes the
//           payload, so it needs a new magic and a reader for this one)
// Appends are one write and an fdatasync each (a commit interval's batch), so a crash
// leaves at most a torn last record: at open it is cut off and counted (dropped_records()), with
// everything after the first record that is short or fails its checksum. The committed offset is
// written after each chunk reaches the database; a crash between the two only repeats that chunk
// (its rows come back as duplicates of themselves, which the insert counts).
//
// Not thread-safe: the worker owns it. The file is locked (flock) while open, so a second
// daemon configured with the same path refuses to start instead of mixing two streams.
#pragma once

#include <cstdint>
#include <span>
#include <stdexcept>
#include <string>
#include <vector>

#include "storage/sample_window_store.hpp"

namespace magcal {

// The spill file cannot be created, written, read or locked (its path and the OS error, by
// strerror and errno name).
class SpillError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

// A spill file that holds samples received for another database than the one configured now: a
// start error (committing them into this database would put one station's samples where they
// were never meant to go; the file is kept as it is).
class SpillForAnotherDatabase : public SpillError {
 public:
  using SpillError::SpillError;
};

class SampleSpill {
 public:
  // A longer payload is corruption (a sample is ~150 bytes and its sat_id; no LCM frame is
  // this large).
  static constexpr uint32_t kMaxPayloadBytes = 1u << 26;

  // Opens `path` if it exists (the records after its committed offset are held; a torn or
  // corrupt tail is cut off and counted), else creates it; either way it stays open and locked.
  // `database` is recorded in a new file's header. Throws SpillError.
  SampleSpill(std::string path, std::string database, int64_t max_bytes);
  // Removes the file when it holds nothing.
  ~SampleSpill();
  SampleSpill(const SampleSpill&) = delete;
  SampleSpill& operator=(const SampleSpill&) = delete;

  // Appends `rows` durably (one write, fdatasync). False, and nothing written, when the file
  // would grow past max_bytes. Throws SpillError on an I/O error (the file is cut back to what
  // it held before).
  bool append(std::span<const storage::StoredSample> rows);

  // The next (at most max_rows) held records, oldest first, into `out` (cleared). They stay
  // held until commit_read(); reading again without it returns the same records.
  size_t read_chunk(size_t max_rows, std::vector<storage::StoredSample>& out);
  // The records of the last read_chunk() are in the database: no longer held. The file is
  // cut back to its header once it holds nothing. Throws SpillError.
  void commit_read();

  // Samples in the file not yet committed.
  int64_t held_samples() const { return held_; }
  // Bytes of its records (0 when it holds nothing; the header is not counted).
  int64_t bytes() const { return end_ - header_bytes_; }
  int64_t max_bytes() const { return max_bytes_; }
  // Records cut off at open (torn or corrupt; a run of such bytes counts as one).
  int64_t dropped_records() const { return dropped_; }
  // The database named in the header of the file found at open ("" when none was found).
  const std::string& found_database() const { return found_database_; }
  const std::string& path() const { return path_; }

 private:
  void open_existing();
  void create();
  void close_and_remove();
  // Holding nothing: cut back to the header.
  void empty();
  void write_committed_offset();
  // pread of exactly `n` bytes at `offset` (false at end of file).
  bool read_exact(int64_t offset, void* out, size_t n) const;
  [[noreturn]] void fail(const std::string& what) const;

  std::string path_;
  std::string database_;
  int64_t max_bytes_;
  int fd_ = -1;
  int64_t header_bytes_ = 0;
  int64_t committed_ = 0;  // offset of the first held record
  int64_t end_ = 0;        // end of the last complete record (= file size)
  int64_t held_ = 0;
  int64_t dropped_ = 0;
  std::string found_database_;
  // Of the last read_chunk(): where it ended and how many records it returned.
  int64_t read_end_ = 0;
  int64_t read_count_ = 0;
  std::vector<char> buffer_;  // encoding and decoding (reused)
};

}  // namespace magcal
