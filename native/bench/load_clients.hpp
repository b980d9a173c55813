// The load bench's clients in their steady state (clothball bench --load): every websocket
// of one client process, once Python has set it up (connected, upgraded, joined, ready:
// server/bench/benchclients.py), driven by one thread of its own without the interpreter
// (epoll, no websocket library), so that a room's clients cost a small fraction of what the
// server spends on it. For each client:
//
// * a player's HIPs at the hip rate, every player of the process paced round robin and
//   evenly staggered over the HIP period (real clients are not in step), each a 34-byte
//   frame masked with the zero key (a server unmasks whatever key it is given); the frames
//   of one socket due together go in one write;
// * server frames read in place: a CORNER for its frame and the HIP echo (seq, client time):
//   the HIP-to-CORNER latency, once per HIP (the first CORNER that echoes it), against the
//   time this pump sent that seq, into a fixed histogram of 10 µs bins (an echoed time other
//   than the one sent, or a seq not among the last kSentRing sent, counted instead); a MESH
//   counted from its type byte and skipped; a text message (events, scores: large or
//   fragmented) counted, an error (its first bytes `error_prefix`) kept; a ping answered
//   with a pong; a close answered, and the client counted closed.
//
// Memory is bounded: a client holds at most one small frame cut by the end of a read
// (kHoldMax), its unsent bytes are capped (kOutMax: a HIP past it is not sent, nor counted),
// and the histogram is fixed.
//
// The clock is CLOCK_MONOTONIC in seconds: Python's time.perf_counter() on Linux, so that a
// test can build the echoes the pump must read. `poll(now, wait_ms)` is one turn of the
// loop; `start()` runs a turn every kTurnS on a thread (a CORNER's receipt time is then
// the kernel's, SO_TIMESTAMPNS, not the turn's), the tests call poll() themselves.
#pragma once
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "loop/hip_msg.hpp"

struct epoll_event;

namespace cb::bench {

// docs/protocol.md's HIP (<BBHId3f): the bytes clothball.game.wire.protocol.encode_hip
// writes (tests/server/test_load_bench.py decodes the pump's with it).
using loop::kHipBytes;
using loop::kHipType;
constexpr std::size_t kHipFrameBytes = 2 + 4 + kHipBytes;  // header, zero key, HIP
constexpr double kHistBinS = 1e-5;       // latency histogram: 10 µs bins ...
constexpr std::size_t kHistBins = 100000;  // ... to 1 s; one more bin holds everything later
constexpr std::uint32_t kSentRing = 256;   // HIP send times kept a player (2 s at 120 Hz)
constexpr double kFarBehindS = 0.05;     // the pacer this late: it starts again from now
constexpr std::size_t kHoldMax = 4096;   // a frame longer than this is skipped as it comes
constexpr std::size_t kOutMax = 1 << 16;   // unsent bytes a client may hold
constexpr std::size_t kErrorKeep = 256;    // bytes of the newest error message kept
// The pump's thread takes a turn this often: not a multiple or divisor of the server's 1 ms
// frame, so that the turns (and the HIPs sent in them) drift across its frames as real
// clients' do, rather than keep one phase against them.
constexpr double kTurnS = 0.73e-3;

// A player's hand: a slow sine up and down its seat's reach.
struct Hand {
  double cx = 0, cy = 0, cz = 0, half_y = 0, phase = 0;
};

// One client's counters (cumulative).
struct ClientCounts {
  std::uint64_t hips = 0, corners = 0, meshes = 0, texts = 0, bytes = 0, errors = 0;
  std::int64_t frame = -1;  // the newest CORNER's frame
  bool closed = false;
};

struct Totals {
  std::uint64_t echo_unknown = 0;   // echoes of a seq not among the last kSentRing sent
  std::uint64_t echo_mismatch = 0;  // echoes whose time is not the one that HIP was sent with
  std::uint64_t behind = 0;         // times the pacer fell kFarBehindS behind
  std::string last_error;           // the newest error message's first bytes
};

double monotonic_s();

class LoadClients {
 public:
  LoadClients(double hip_rate, std::string error_prefix);
  ~LoadClients();
  LoadClients(const LoadClients&) = delete;
  LoadClients& operator=(const LoadClients&) = delete;

  // Takes `fd` (a connected, upgraded, non-blocking socket: the pump closes it) and the
  // bytes already read from it past what its setup consumed. `hand`: a player's, or null
  // (a spectator). Returns the client's index.
  int add(int fd, const std::string& pending, const Hand* hand);
  void start();                    // turns on a thread of its own until close()
  void poll(double now, int wait_ms);  // one turn (tests; not with start())
  // Counters of every client, the totals and the histogram (bins with a count), under the
  // lock; `mark`: the histogram cleared after the copy.
  void snap(bool mark, std::vector<ClientCounts>& counts, Totals& totals,
            std::vector<std::pair<std::uint32_t, std::uint64_t>>& hist);
  void close();  // a close frame to every open client, the thread stopped, the sockets closed

 private:
  struct Client;
  void turn(double now, const epoll_event* evs, int got);
  void pace(double now);
  void read(Client& c, double now);
  std::size_t frames(Client& c, const std::uint8_t* p, std::size_t n, double now);
  void corner(Client& c, const std::uint8_t* p, double now);
  void send(Client& c, const std::uint8_t* p, std::size_t n);
  void flush(Client& c);
  void finish(Client& c);

  double period_;
  std::string error_prefix_;
  int ep_ = -1, wake_ = -1;
  std::mutex mu_;  // everything below: the pump's turn, add and snap
  std::vector<std::unique_ptr<Client>> clients_;
  std::vector<int> players_;  // indices into clients_
  std::vector<std::uint64_t> hist_;
  Totals totals_;
  std::uint64_t k_ = 0;  // the next player's turn (round robin)
  double t_ = 0;         // when the next HIP is due
  bool paced_ = false;
  std::vector<std::uint8_t> scratch_;
  std::vector<int> dirty_;  // clients with frames queued in this turn
  std::thread thread_;
  bool stop_ = false, closed_ = false;
  bool arrival_ = false;  // receipt times from the kernel (on the thread)
};

}  // namespace cb::bench
