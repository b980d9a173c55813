// A gateway's pump: every relayed connection's bytes both ways, and every seated player's
// HIPs in, CORNERs out and every watcher's MESH out, on one thread of its own (epoll),
// without Python. The gateway's Python accepts a client, opens its connection to the
// engine (the PROXY line), then hands both sockets here (`add`); from then on it sees only
// what is rare: the engine's lane messages (it parses them and opens the lane: `open_lane`),
// the engine's stream ending (it decides what to tell the client: `finish`), a block it
// must fetch, the frame wake-up to arm. docs/architecture.md ("Gateways") tells the whole.
//
// What it does with each connection is what the gateway's Python relay did
// (server/gateway/relay.py before this pump): backpressure at kWriteHigh buffered bytes a
// side, half-closes passed on, lane messages taken out of the engine's stream
// (net/follow.hpp), a lane's messages written only between two of the engine's (else
// the newest of each kind held), a CORNER skipped for a client with kWriteSkip unsent.
//
// And one thing the Python relay did not: a websocket client whose side stays behind (more
// than kWriteSkip unsent to it, or unsent bytes and none written) for longer than
// `slow_drop_s` is dropped as too slow (`behind`, `too_slow`): its engine's side is closed
// at once (the engine learns of it as of any client's close at its gateway), and the
// client gets a close frame, 1008 `too slow: ...`, after what is queued for it, where its
// stream is between two messages (else it is cut); kCloseWaitS later it is cut anyway.
#pragma once
#include <sys/epoll.h>

#include <atomic>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <queue>
#include <set>
#include <string>
#include <thread>
#include <unordered_map>
#include <vector>

#include "loop/hip_msg.hpp"
#include "net/follow.hpp"

namespace cb::loop {
struct RoomRecord;
}

namespace cb::net {

constexpr std::size_t kWriteHigh = 1 << 18;  // a side's buffered bytes: stop reading the other
constexpr std::size_t kWriteLow = kWriteHigh / 4;  // ... and read it again below this
constexpr std::size_t kWriteSkip = 1 << 16;  // a client this far behind: its CORNER skipped
constexpr std::size_t kChunk = 1 << 16;      // bytes read at a time
constexpr double kFrameS = 0.001;            // the frame loop's frame: the fastest CORNER
constexpr double kRetryFrameS = 0.00025;     // a CORNER due before its frame: again this soon,
constexpr int kRetries = 4;                  // this many times
constexpr double kMeshLookS = 0.004;         // the watched rooms' boards looked at this often
constexpr double kTimerMaxHz = 500.0;        // above: CORNERs on the frame wake-up
constexpr double kBlockRetryS = 0.5;         // between two asks for a missing block
using loop::kHipBytes;
constexpr double kCoalesceS = 0.001;         // the pump's tick while it has timers
constexpr double kSlowDropS = 5.0;           // server/limits.py's slow_drop_s default
constexpr double kCloseWaitS = 2.0;          // a dropped client's close: then it is cut

// A lane (server/shared/lanes.py LaneSpec): a seated player's hand and CORNER, and any
// client's MESH, served from the engine's shared memory.
struct LaneSpec {
  std::string room;  // as the engine's JSON writes it (quoted), to match the stream's
  std::int64_t block = 0;
  int slot = 0;
  int seat = -1;  // -1: not seated (MESH only)
  std::uint64_t occupant = 0;
  double lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};
  double corner_interval = 0;  // s
  double binary_rate = 0, binary_burst = 0;
  std::int64_t board = -1;  // -1: no MESH from the gateway
  std::size_t board_slot = 0;
};

// What the pump tells the gateway's Python (take_events).
struct Event {
  enum Kind { kLane = 1, kEnded = 2, kClosed = 3, kBlock = 4, kArm = 5 } kind = kLane;
  std::int64_t conn = 0;  // kBlock: the block's id; kArm: 1 on, 0 off
  std::string data;       // kLane: the message's payload; kEnded: the room (quoted) or ""
  bool between = false;   // kEnded: the stream was between two messages
  std::int64_t frame = -1;
  double time = 0.0;
};

// A shared memory the engine passed (a frame loop's block, or its mesh board), mapped here
// (or, for a pump in the engine's own process, its memory as it is: not `owned`).
struct Shared {
  bool board = false;
  bool owned = true;  // mapped here: unmapped here
  unsigned char* base = nullptr;
  std::size_t bytes = 0;
  loop::RoomRecord* records = nullptr;  // a block's
  int rooms = 0;
};

class Pump {
 public:
  // coalesce_s: the tick the pump runs on while it has lanes (0: each event wakes it), a
  // message's most added wait; slow_drop_s: how long a websocket client may stay behind
  // (server/limits.py's slow_drop_s).
  explicit Pump(double coalesce_s = kCoalesceS, double slow_drop_s = kSlowDropS);
  ~Pump();
  Pump(const Pump&) = delete;
  Pump& operator=(const Pump&) = delete;

  // --- called from any thread (each queued for the pump's own) ------------------------
  // Both sockets are the pump's from now on (it closes them); `to_engine` goes first to
  // the engine (the PROXY line, what the client sent before); `client_eof`: the client
  // has ended its side already. Returns the connection's id.
  std::int64_t add(int client_fd, int engine_fd, std::string to_engine, bool client_eof);
  void open_lane(std::int64_t conn, LaneSpec spec);
  void close_lane(std::int64_t conn);
  // (id, board?, memfd, bytes): mapped here (the fds stay the caller's); replaces all.
  // With `addr` (the engine's own pump): that memory as it is, which the caller keeps
  // mapped until the pump has stopped or been given maps without it.
  struct MapIn {
    std::int64_t id;
    bool board;
    int fd;
    std::size_t bytes;
    void* addr = nullptr;
  };
  void set_maps(const std::vector<MapIn>& maps);  // throws on a bad one, maps nothing then
  void drop_maps();
  void set_wake(int fd);  // the frame wake-up (an eventfd, the pump's to close)
  void no_wake();         // there is none: framed lanes use timers
  void finish(std::int64_t conn, std::string tail);  // tail to the client, then its end
  void abort(std::int64_t conn);
  void stop();

  int event_fd() const { return event_fd_; }
  std::vector<Event> take_events();
  std::uint64_t messages_in() const { return in_.load(std::memory_order_relaxed); }
  std::uint64_t messages_out() const { return out_.load(std::memory_order_relaxed); }
  std::size_t connections() const { return live_.load(std::memory_order_relaxed); }
  std::uint64_t slow_drops() const { return slow_drops_.load(std::memory_order_relaxed); }
  double slow_drop_s() const { return slow_drop_s_; }

 private:
  struct Lane;
  struct Conn;
  struct Timer {
    double at;
    std::int64_t conn;  // 0: the MESH look
    std::uint64_t gen;
    bool operator>(const Timer& o) const { return at > o.at; }
  };
  struct Watch {
    std::set<std::int64_t> conns;
    std::int64_t sent = -1;
    std::size_t slot_bytes = 0;  // of the board's slots (the lanes' board_slot)
  };

  void run();
  void post(std::function<void()> f);
  void emit(Event e);
  void on_cmd();
  void on_client(Conn& c, std::uint32_t ev);
  void on_engine(Conn& c, std::uint32_t ev);
  void on_wake();
  void on_timers();
  int wait(epoll_event* evs, int max);
  void schedule(double at, std::int64_t conn, std::uint64_t gen);
  void interest(Conn& c);
  void mark(Conn& c);
  void flush(Conn& c);
  void engine_ended(Conn& c);
  void close_if_done(Conn& c);
  void kill(Conn& c);
  // too slow
  void behind(Conn& c, bool wrote);
  void on_slow();
  void too_slow(Conn& c, double now);
  void cut_engine(Conn& c);
  void end_lane(Conn& c);
  // lanes
  bool take_hip(Conn& c, const std::uint8_t* p, std::size_t n);
  int send_newest(Conn& c);  // 1 sent, 0 none newer, -1 the lane has ended
  void corner_timer(Conn& c);
  void on_frame(Conn& c, double now);
  void set_framed(Conn& c, bool on);
  void write_lane(Conn& c, int kind, const std::uint8_t* payload, std::size_t n);
  void flush_pending(Conn& c);
  void look_meshes();
  Shared* shared(std::int64_t id);
  void unmap_all();

  int ep_ = -1, cmd_fd_ = -1, event_fd_ = -1, wake_fd_ = -1;
  bool pwait2_ = true;
  double coalesce_s_;
  double slow_drop_s_;
  bool no_wake_ = false, armed_want_ = false;
  std::thread thread_;
  std::atomic<bool> running_{true};
  std::atomic<std::int64_t> next_id_{16};
  std::atomic<std::uint64_t> in_{0}, out_{0};
  std::atomic<std::size_t> live_{0};
  std::atomic<std::uint64_t> slow_drops_{0};

  std::mutex cmd_mu_;
  std::vector<std::function<void()>> cmds_;
  std::mutex ev_mu_;
  std::vector<Event> events_;

  // the pump thread's own
  std::unordered_map<std::int64_t, std::unique_ptr<Conn>> conns_;
  std::unordered_map<std::int64_t, Shared> shared_;
  std::priority_queue<Timer, std::vector<Timer>, std::greater<Timer>> timers_;
  // When to look again at a client that is behind (or cut one dropped): apart from
  // timers_, whose presence puts the pump on its tick.
  std::priority_queue<Timer, std::vector<Timer>, std::greater<Timer>> slow_;
  std::set<std::int64_t> framed_;
  std::map<std::pair<std::int64_t, std::size_t>, Watch> watched_;
  bool mesh_timer_ = false;
  std::vector<std::uint8_t> mesh_buf_;
  std::vector<Conn*> dirty_;
  std::vector<std::int64_t> dead_;  // closed this pass: erased at its end
  double block_asked_at_ = -1e9;
};

double monotonic();
// `t` rounded up to a whole frame: CORNER timers on this grid share wake-ups
// (server/lanes/lane.py on_grid, whose reason holds here too).
double on_grid(double t);

}  // namespace cb::net
