// The gateway's pump (net/pump.hpp).
#include "net/pump.hpp"

#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/mman.h>
#include <sys/socket.h>
#include <pthread.h>
#include <sys/uio.h>
#include <unistd.h>

#include <cerrno>
#include <cmath>
#include <cstring>
#include <ctime>
#include <stdexcept>

#include "loop/block.hpp"
#include "loop/board.hpp"

namespace cb::net {

namespace lp = cb::loop;

namespace {
constexpr std::uint64_t kCmdTag = 1, kWakeTag = 3;
constexpr int kCorner = 0, kMesh = 1;

// epoll data: a connection's id times 2, plus 1 for its engine side.
std::uint64_t tag(std::int64_t id, bool engine) { return std::uint64_t(id) * 2 + (engine ? 1 : 0); }

void drain(int fd) {
  std::uint64_t v;
  while (::read(fd, &v, sizeof v) == sizeof v) {
  }
}
void poke(int fd) {
  const std::uint64_t one = 1;
  [[maybe_unused]] ssize_t r = ::write(fd, &one, sizeof one);
}
}  // namespace

double monotonic() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

double on_grid(double t) { return std::ceil(t / kFrameS) * kFrameS; }

// A token bucket (server/shared/bucket.py): the client's binary rate with its burst.
struct Bucket {
  double rate = 0, burst = 0, tokens = 0, t = 0;
  bool take(double now) {
    tokens = std::min(burst, tokens + (now - t) * rate);
    t = now;
    if (tokens >= 1.0) {
      tokens -= 1.0;
      return true;
    }
    return false;
  }
};

struct Pump::Lane {
  LaneSpec spec;
  Bucket bucket;
  bool fast = true;  // HIPs taken here (off for good once the client passes its rate)
  std::int64_t sent_frame = -1;
  int retries = 0;
  double due = 0;
  std::uint64_t gen = 0;  // its timers' (a timer of an earlier lane is stale)
  bool timer = false;     // its CORNERs on its own timer (else on the frame wake-up)
};

struct Pump::Conn {
  std::int64_t id = 0;
  int cfd = -1, efd = -1;
  std::string to_client, to_engine;
  std::size_t c_off = 0, e_off = 0;  // bytes of each already written
  bool c_eof = false;      // the client ended its side
  bool e_shut = false;     // and that end was passed on to the engine
  bool e_ended = false;    // the engine's stream ended (the gateway was told)
  bool finishing = false;  // the gateway's tail is queued: then the client's end
  bool c_shut = false;     // the client's side was ended
  bool c_paused = false, e_paused = false;  // reading stopped (the other side is behind)
  // The engine hung up while its reading was stopped: out of the poll until it is read
  // again (a hang-up is reported on every wait, whatever the interest).
  bool e_parked = false;
  std::uint32_t c_mask = 0, e_mask = 0;     // epoll interest now
  bool dirty = false, dead = false;
  ClientTap tap{kHipBytes};
  bool tapping = false;
  ServerFollow srv;
  std::unique_ptr<Lane> lane;
  std::uint64_t lane_gen = 0;
  bool has_pending[2] = {false, false};
  std::string pending[2];  // a lane's newest held CORNER and MESH (frame included)
  double behind_since = 0;  // monotonic: since when the client has been behind (0: not)
  double cut_at = 0;        // dropped as too slow: cut then (0: not dropped)
  bool slow_queued = false; // a look at it is in slow_
  std::size_t c_buffered() const { return to_client.size() - c_off; }
  std::size_t e_buffered() const { return to_engine.size() - e_off; }
};

Pump::Pump(double coalesce_s, double slow_drop_s)
    : coalesce_s_(coalesce_s), slow_drop_s_(slow_drop_s) {
  ep_ = epoll_create1(EPOLL_CLOEXEC);
  cmd_fd_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  event_fd_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (ep_ < 0 || cmd_fd_ < 0 || event_fd_ < 0)
    throw std::runtime_error(std::string("the gateway's pump could not start: ") +
                             std::strerror(errno));
  epoll_event ev{};
  ev.events = EPOLLIN;
  ev.data.u64 = kCmdTag;
  epoll_ctl(ep_, EPOLL_CTL_ADD, cmd_fd_, &ev);
  thread_ = std::thread([this] { run(); });
}

Pump::~Pump() {
  stop();
  if (thread_.joinable()) thread_.join();
  for (int fd : {ep_, cmd_fd_, event_fd_})
    if (fd >= 0) ::close(fd);
}

void Pump::post(std::function<void()> f) {
  {
    std::lock_guard<std::mutex> g(cmd_mu_);
    cmds_.push_back(std::move(f));
  }
  poke(cmd_fd_);
}

void Pump::emit(Event e) {
  bool first;
  {
    std::lock_guard<std::mutex> g(ev_mu_);
    first = events_.empty();
    events_.push_back(std::move(e));
  }
  if (first) poke(event_fd_);
}

std::vector<Event> Pump::take_events() {
  drain(event_fd_);
  std::vector<Event> out;
  std::lock_guard<std::mutex> g(ev_mu_);
  out.swap(events_);
  return out;
}

// --- the calls ------------------------------------------------------------------------------

std::int64_t Pump::add(int client_fd, int engine_fd, std::string to_engine, bool client_eof) {
  const std::int64_t id = next_id_.fetch_add(1);
  live_.fetch_add(1);
  post([this, id, client_fd, engine_fd, to_engine = std::move(to_engine), client_eof]() mutable {
    auto c = std::make_unique<Conn>();
    c->id = id;
    c->cfd = client_fd;
    c->efd = engine_fd;
    c->to_engine = std::move(to_engine);
    c->c_eof = client_eof;
    Conn& r = *c;
    conns_.emplace(id, std::move(c));
    for (bool engine : {false, true}) {
      epoll_event ev{};
      ev.events = 0;
      ev.data.u64 = tag(id, engine);
      epoll_ctl(ep_, EPOLL_CTL_ADD, engine ? engine_fd : client_fd, &ev);
    }
    interest(r);
    mark(r);
  });
  return id;
}

void Pump::open_lane(std::int64_t conn, LaneSpec spec) {
  post([this, conn, spec = std::move(spec)]() mutable {
    auto it = conns_.find(conn);
    if (it == conns_.end()) return;
    Conn& c = *it->second;
    end_lane(c);
    auto lane = std::make_unique<Lane>();
    const double now = monotonic();
    lane->spec = std::move(spec);
    lane->bucket = Bucket{lane->spec.binary_rate, lane->spec.binary_burst,
                          lane->spec.binary_burst, now};
    lane->due = now;
    lane->gen = ++c.lane_gen;
    const LaneSpec& sp = lane->spec;
    c.lane = std::move(lane);
    if (sp.seat >= 0) {
      const bool framed = sp.corner_interval < 1.0 / kTimerMaxHz - 1e-4 && !no_wake_;
      if (framed) {
        set_framed(c, true);
      } else {
        c.lane->timer = true;
        schedule(now, c.id, c.lane->gen);
      }
    }
    if (sp.board >= 0) {
      Watch& w = watched_[{sp.board, std::size_t(sp.slot) * sp.board_slot}];
      w.conns.insert(c.id);
      w.slot_bytes = sp.board_slot;
      if (!mesh_timer_) {
        mesh_timer_ = true;
        schedule(now, 0, 0);
      }
    }
    shared(sp.block);  // asked for now if missing
  });
}

void Pump::close_lane(std::int64_t conn) {
  post([this, conn] {
    auto it = conns_.find(conn);
    if (it != conns_.end()) end_lane(*it->second);
  });
}

void Pump::set_maps(const std::vector<MapIn>& maps) {
  std::unordered_map<std::int64_t, Shared> made;
  auto release = [](const Shared& s) {
    if (s.owned) munmap(s.base, s.bytes);
  };
  auto undo = [&made, &release] {
    for (auto& kv : made) release(kv.second);
  };
  for (const MapIn& m : maps) {
    void* p = m.addr != nullptr
                  ? m.addr
                  : mmap(nullptr, m.bytes, PROT_READ | PROT_WRITE, MAP_SHARED, m.fd, 0);
    if (p == MAP_FAILED) {
      const int e = errno;
      undo();
      throw std::runtime_error(std::string("a block from the engine could not be mapped: ") +
                               std::strerror(e));
    }
    Shared s;
    s.board = m.board;
    s.owned = m.addr == nullptr;
    s.base = static_cast<unsigned char*>(p);
    s.bytes = m.bytes;
    if (!m.board) {
      const auto* h = reinterpret_cast<const lp::Header*>(p);
      if (m.bytes < sizeof(lp::Header) || h->magic != lp::kBlockMagic ||
          h->version != lp::kBlockVersion || h->room_bytes != sizeof(lp::RoomRecord) ||
          h->total_bytes > m.bytes) {
        release(s);
        undo();
        throw std::runtime_error("not a frame loop block of this build (magic, version or size)");
      }
      s.records = reinterpret_cast<lp::RoomRecord*>(s.base + h->rooms_offset);
      s.rooms = int(h->rooms);
    }
    made.emplace(m.id, s);
  }
  post([this, made = std::move(made)]() mutable {
    unmap_all();
    shared_ = std::move(made);
  });
}

void Pump::drop_maps() {
  post([this] { unmap_all(); });
}

void Pump::unmap_all() {
  for (auto& kv : shared_)
    if (kv.second.owned) munmap(kv.second.base, kv.second.bytes);
  shared_.clear();
}

void Pump::set_wake(int fd) {
  post([this, fd] {
    if (wake_fd_ >= 0) {
      epoll_ctl(ep_, EPOLL_CTL_DEL, wake_fd_, nullptr);
      ::close(wake_fd_);
    }
    wake_fd_ = fd;
    epoll_event ev{};
    ev.events = EPOLLIN;
    ev.data.u64 = kWakeTag;
    epoll_ctl(ep_, EPOLL_CTL_ADD, fd, &ev);
  });
}

void Pump::no_wake() {
  post([this] {
    no_wake_ = true;
    if (wake_fd_ >= 0) {
      epoll_ctl(ep_, EPOLL_CTL_DEL, wake_fd_, nullptr);
      ::close(wake_fd_);
      wake_fd_ = -1;
    }
    const double now = monotonic();
    for (std::int64_t id : std::set<std::int64_t>(framed_)) {
      auto it = conns_.find(id);
      if (it == conns_.end() || !it->second->lane) continue;
      set_framed(*it->second, false);
      it->second->lane->timer = true;
      schedule(now, id, it->second->lane->gen);
    }
  });
}

void Pump::finish(std::int64_t conn, std::string tail) {
  post([this, conn, tail = std::move(tail)] {
    auto it = conns_.find(conn);
    if (it == conns_.end()) return;
    Conn& c = *it->second;
    if (!c.c_shut && !c.finishing) c.to_client += tail;
    c.finishing = true;
    mark(c);
  });
}

void Pump::abort(std::int64_t conn) {
  post([this, conn] {
    auto it = conns_.find(conn);
    if (it != conns_.end()) kill(*it->second);
  });
}

void Pump::stop() {
  if (!running_.load()) return;
  post([this] { running_ = false; });
}

// --- the thread -----------------------------------------------------------------------------

void Pump::run() {
  pthread_setname_np(pthread_self(), "cb-pump");  // for /proc and the load bench
  epoll_event evs[256];
  int n = 0;
  while (running_.load()) {
    // While it has timers (lanes, watched boards) the pump runs on a tick of coalesce_s_ (a
    // frame), not on each event: it sleeps to the next tick, then takes every event that
    // came meanwhile in one pass. A wake-up costs far more than a message (on the H200
    // host, 10.7 µs of CPU a message at 128 rooms when each HIP woke its gateway; ~25 µs a
    // wake-up on the 2-core VM), and the CORNER timers are on the frame grid anyway; a
    // HIP waits at most a tick more (the frame loop takes hands once a frame). Without
    // timers (relaying only) it waits on the sockets as they come.
    if (coalesce_s_ > 0 && !timers_.empty() && n < 256) {
      const double until = std::ceil(monotonic() / coalesce_s_) * coalesce_s_;
      timespec ts;
      ts.tv_sec = time_t(until);
      ts.tv_nsec = long((until - std::floor(until)) * 1e9);
      clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
      n = epoll_wait(ep_, evs, 256, 0);
    } else {
      n = wait(evs, 256);
    }
    if (n < 0 && errno != EINTR) break;
    for (int i = 0; i < n; ++i) {
      const std::uint64_t t = evs[i].data.u64;
      if (t == kCmdTag) {
        on_cmd();
      } else if (t == kWakeTag) {
        on_wake();
      } else {
        auto it = conns_.find(std::int64_t(t / 2));
        if (it == conns_.end() || it->second->dead) continue;
        if (t & 1) on_engine(*it->second, evs[i].events);
        else on_client(*it->second, evs[i].events);
      }
    }
    on_timers();
    on_slow();
    // Each connection written once a pass, whatever came for it (several CORNERs, a MESH,
    // the engine's bytes): one system call.
    std::vector<Conn*> dirty;
    dirty.swap(dirty_);
    for (Conn* c : dirty) {
      if (c->dead || !c->dirty) continue;
      c->dirty = false;
      flush(*c);
    }
    for (std::int64_t id : dead_) conns_.erase(id);
    dead_.clear();
  }
  for (auto& kv : conns_) {
    Conn& c = *kv.second;
    if (!c.dead) {
      ::close(c.cfd);
      if (c.efd >= 0) ::close(c.efd);
    }
  }
  conns_.clear();
  live_ = 0;
  unmap_all();
  if (wake_fd_ >= 0) ::close(wake_fd_);
  wake_fd_ = -1;
}

void Pump::on_cmd() {
  drain(cmd_fd_);
  std::vector<std::function<void()>> cmds;
  {
    std::lock_guard<std::mutex> g(cmd_mu_);
    cmds.swap(cmds_);
  }
  for (auto& f : cmds) f();
}

// `c` is written at the end of this pass (once, whatever came for it).
void Pump::mark(Conn& c) {
  if (!c.dirty) {
    c.dirty = true;
    dirty_.push_back(&c);
  }
}

void Pump::interest(Conn& c) {
  if (c.dead) return;
  std::uint32_t cm = 0, em = 0;
  if (!c.c_eof && !c.c_paused) cm |= EPOLLIN | EPOLLRDHUP;
  if (c.c_buffered()) cm |= EPOLLOUT;
  if (!c.e_paused) em |= EPOLLIN | EPOLLRDHUP;
  if (c.e_buffered()) em |= EPOLLOUT;
  if (cm != c.c_mask) {
    epoll_event ev{};
    ev.events = cm;
    ev.data.u64 = tag(c.id, false);
    epoll_ctl(ep_, EPOLL_CTL_MOD, c.cfd, &ev);
    c.c_mask = cm;
  }
  if (c.e_ended || (c.e_parked && c.e_paused)) return;
  if (em != c.e_mask || c.e_parked) {
    epoll_event ev{};
    ev.events = em;
    ev.data.u64 = tag(c.id, true);
    epoll_ctl(ep_, c.e_parked ? EPOLL_CTL_ADD : EPOLL_CTL_MOD, c.efd, &ev);
    c.e_mask = em;
    c.e_parked = false;
  }
}

void Pump::on_client(Conn& c, std::uint32_t ev) {
  if (ev & EPOLLOUT) flush(c);
  if (c.dead) return;
  // An error, or both ways shut (a reset, or a close after its end; or while its reading
  // is stopped): nothing more can pass.
  if (((ev & EPOLLERR) && !(ev & EPOLLIN)) || ((ev & EPOLLHUP) && (c.c_eof || c.c_paused))) {
    kill(c);
    return;
  }
  if (!(ev & (EPOLLIN | EPOLLRDHUP | EPOLLHUP)) || c.c_eof || c.c_paused) return;
  std::uint8_t buf[kChunk];
  const ssize_t r = ::read(c.cfd, buf, sizeof buf);
  if (r < 0) {
    if (errno == EAGAIN || errno == EINTR) return;
    kill(c);  // one side failed: the other is ended too
    return;
  }
  if (r == 0) {
    c.c_eof = true;
    interest(c);
    mark(c);  // the end goes on to the engine once what is queued has
    close_if_done(c);
    return;
  }
  if (c.e_ended) return;  // nothing more can reach the engine: dropped
  if (!c.tapping && c.srv.websocket) c.tapping = true;  // the handshake is done: frames
  if (c.tapping) {
    c.tap.feed(buf, std::size_t(r), c.to_engine,
               [this, &c](const std::uint8_t* p, std::size_t n) { return take_hip(c, p, n); });
  } else {
    append(c.to_engine, buf, std::size_t(r));
  }
  if (c.e_buffered()) {
    if (c.e_buffered() > kWriteHigh) c.c_paused = true;
    mark(c);
  }
  if (!c.dirty) interest(c);  // (else the pass's flush sets it, once)
}

void Pump::on_engine(Conn& c, std::uint32_t ev) {
  if (ev & EPOLLOUT) flush(c);
  if (c.dead || c.e_ended) return;
  if (c.e_paused) {
    if ((ev & (EPOLLHUP | EPOLLERR)) && !c.e_parked) {
      epoll_ctl(ep_, EPOLL_CTL_DEL, c.efd, nullptr);
      c.e_parked = true;
    }
    return;
  }
  if (!(ev & (EPOLLIN | EPOLLRDHUP | EPOLLHUP | EPOLLERR))) return;
  std::uint8_t buf[kChunk];
  const ssize_t r = ::read(c.efd, buf, sizeof buf);
  if (r < 0 && (errno == EAGAIN || errno == EINTR)) return;
  if (r <= 0) {
    engine_ended(c);
    return;
  }
  const bool writing = !c.c_shut && !c.finishing;
  std::string dropped;
  c.srv.feed(buf, std::size_t(r), writing ? c.to_client : dropped,
             [this, &c](std::string_view lane) {
               Event e;
  e.kind = Event::kLane;
               e.conn = c.id;
               e.data.assign(lane);
               emit(std::move(e));
             });
  if (writing && (c.has_pending[0] || c.has_pending[1]) && c.srv.between_messages())
    flush_pending(c);
  if (c.c_buffered()) {
    if (c.c_buffered() > kWriteHigh) c.e_paused = true;
    mark(c);
  }
  if (!c.dirty) interest(c);  // (else the pass's flush sets it, once)
}

void Pump::engine_ended(Conn& c) {
  if (c.e_ended) return;
  c.e_ended = true;
  c.to_engine.clear();  // nothing more can reach it
  c.e_off = 0;
  // Out of the poll for good: a closed peer's hang-up would be reported on every wait.
  if (!c.e_parked) epoll_ctl(ep_, EPOLL_CTL_DEL, c.efd, nullptr);
  // Its lane ends too: a MESH the engine put on its board before it died, read after this,
  // would follow the room_stopped the gateway writes with the frame it reports here.
  end_lane(c);
  c.has_pending[kCorner] = c.has_pending[kMesh] = false;
  Event e;
  e.kind = Event::kEnded;
  e.conn = c.id;
  e.between = c.srv.between_messages() && !c.c_shut && !c.finishing;
  e.data = c.srv.room;
  e.frame = c.srv.frame;
  e.time = c.srv.time;
  emit(std::move(e));
}

// Writes what is queued for each side (the connection may die of it).
void Pump::flush(Conn& c) {
  if (c.dead) return;
  auto write_side = [this, &c](int fd, std::string& q, std::size_t& off) -> bool {
    while (off < q.size()) {
      const ssize_t w = ::send(fd, q.data() + off, q.size() - off, MSG_NOSIGNAL);
      if (w < 0) {
        if (errno == EAGAIN || errno == EINTR) break;
        return false;
      }
      off += std::size_t(w);
    }
    if (off == q.size()) {
      q.clear();
      off = 0;
    } else if (off > (1u << 20) && off * 2 > q.size()) {
      q.erase(0, off);
      off = 0;
    }
    return true;
  };
  const std::size_t unsent = c.c_buffered();
  if (!write_side(c.cfd, c.to_client, c.c_off)) {
    kill(c);
    return;
  }
  behind(c, c.c_buffered() < unsent);
  if (!c.e_ended && !write_side(c.efd, c.to_engine, c.e_off)) {
    engine_ended(c);
  }
  if (c.e_paused && c.c_buffered() < kWriteLow) c.e_paused = false;
  if (c.c_paused && c.e_buffered() < kWriteLow) c.c_paused = false;
  if (c.c_eof && !c.e_shut && !c.e_buffered()) {
    c.e_shut = true;
    if (!c.e_ended) ::shutdown(c.efd, SHUT_WR);
  }
  if (c.finishing && !c.c_shut && !c.c_buffered()) {
    c.c_shut = true;
    ::shutdown(c.cfd, SHUT_WR);
  }
  interest(c);
  close_if_done(c);
}

// Both ways have ended (the client's end passed on, the engine's and its tail written):
// the connection is closed.
void Pump::close_if_done(Conn& c) {
  if (!c.dead && c.c_eof && c.c_shut) kill(c);
}

void Pump::kill(Conn& c) {
  if (c.dead) return;
  end_lane(c);
  epoll_ctl(ep_, EPOLL_CTL_DEL, c.cfd, nullptr);
  if (!c.e_ended && !c.e_parked) epoll_ctl(ep_, EPOLL_CTL_DEL, c.efd, nullptr);
  ::close(c.cfd);
  if (c.efd >= 0) ::close(c.efd);
  c.dead = true;
  dead_.push_back(c.id);
  live_.fetch_sub(1);
  Event e;
  e.kind = Event::kClosed;
  e.conn = c.id;
  emit(std::move(e));
}

// --- too slow -------------------------------------------------------------------------------

// After a write to the client (`wrote`: some of its unsent bytes went): since when a
// websocket client has been behind, with bytes unsent to it and none of them taken since,
// or more than kWriteSkip unsent (a write that leaves it at most that starts the time
// again; one that leaves none ends it). One behind past slow_drop_s_ is dropped (on_slow).
void Pump::behind(Conn& c, bool wrote) {
  const std::size_t unsent = c.c_buffered();
  if (!c.srv.websocket || unsent == 0) {
    c.behind_since = 0;
    return;
  }
  if (c.behind_since > 0 && !(wrote && unsent <= kWriteSkip)) return;
  c.behind_since = monotonic();
  if (!c.slow_queued) {
    c.slow_queued = true;
    slow_.push(Timer{c.behind_since + slow_drop_s_, c.id, 0});
  }
}

void Pump::on_slow() {
  if (slow_.empty()) return;
  const double now = monotonic();
  while (!slow_.empty() && slow_.top().at <= now) {
    const Timer t = slow_.top();
    slow_.pop();
    auto it = conns_.find(t.conn);
    if (it == conns_.end() || it->second->dead) continue;
    Conn& c = *it->second;
    c.slow_queued = false;
    double next = 0;
    if (c.cut_at > 0) {
      if (now >= c.cut_at) kill(c);  // its close did not go out in time
      else next = c.cut_at;
    } else if (c.behind_since > 0) {
      if (now - c.behind_since >= slow_drop_s_) too_slow(c, now);
      else next = c.behind_since + slow_drop_s_;  // caught up since, then behind again
      if (c.cut_at > 0) next = c.cut_at;
    }
    if (next > 0 && !c.dead) {
      c.slow_queued = true;
      slow_.push(Timer{next, c.id, 0});
    }
  }
}

// Drops a client that stayed behind (as the engine drops one: server/conn.py): the
// engine's side closed now, and, where the client's stream is between two messages, a
// close frame (1008) after what is queued for it, then the client's end; cut at once where
// no close frame can be written, and kCloseWaitS from now where it has not gone out.
void Pump::too_slow(Conn& c, double now) {
  slow_drops_.fetch_add(1, std::memory_order_relaxed);
  const bool can_close = !c.c_shut && !c.finishing && c.srv.between_messages();
  end_lane(c);
  c.has_pending[kCorner] = c.has_pending[kMesh] = false;
  cut_engine(c);
  if (!can_close) {
    kill(c);
    return;
  }
  static const char kReason[] = "too slow: the connection has been backed up too long";
  const std::size_t n = 2 + sizeof kReason - 1;
  std::uint8_t head[kMaxHeader];
  const std::size_t hn = write_head(head, kOpClose, n);
  append(c.to_client, head, hn);
  const std::uint8_t code[2] = {1008 >> 8, 1008 & 0xFF};
  append(c.to_client, code, 2);
  append(c.to_client, reinterpret_cast<const std::uint8_t*>(kReason), sizeof kReason - 1);
  c.finishing = true;
  c.cut_at = now + kCloseWaitS;
  mark(c);
}

// The engine's side closed (its reading and writing done with): the engine sees its
// client's connection end, as when a client goes.
void Pump::cut_engine(Conn& c) {
  if (c.efd < 0) return;
  if (!c.e_ended && !c.e_parked) epoll_ctl(ep_, EPOLL_CTL_DEL, c.efd, nullptr);
  ::close(c.efd);
  c.efd = -1;
  c.e_ended = true;
  c.e_paused = false;
  c.to_engine.clear();
  c.e_off = 0;
}

// --- lanes ----------------------------------------------------------------------------------

void Pump::end_lane(Conn& c) {
  if (!c.lane) return;
  const LaneSpec& sp = c.lane->spec;
  set_framed(c, false);
  if (sp.board >= 0) {
    auto it = watched_.find({sp.board, std::size_t(sp.slot) * sp.board_slot});
    if (it != watched_.end()) {
      it->second.conns.erase(c.id);
      if (it->second.conns.empty()) watched_.erase(it);
    }
  }
  c.lane.reset();
  ++c.lane_gen;
}

Shared* Pump::shared(std::int64_t id) {
  auto it = shared_.find(id);
  if (it != shared_.end()) return &it->second;
  const double now = monotonic();
  if (now - block_asked_at_ > kBlockRetryS) {
    block_asked_at_ = now;
    Event e;
  e.kind = Event::kBlock;
    e.conn = id;
    emit(std::move(e));
  }
  return nullptr;
}

bool Pump::take_hip(Conn& c, const std::uint8_t* p, std::size_t n) {
  Lane* lane = c.lane.get();
  if (lane == nullptr || lane->spec.seat < 0 || !lane->fast) return false;
  const LaneSpec& sp = lane->spec;
  Shared* s = shared(sp.block);
  if (s == nullptr || s->board || sp.slot < 0 || sp.slot >= s->rooms || sp.seat >= lp::kSeats)
    return false;
  if (!lane->bucket.take(monotonic())) {
    lane->fast = false;  // the engine's own limit and errors from here on
    return false;
  }
  // docs/protocol.md's HIP (<BBHId3f): well formed, else the engine answers it
  if (n != kHipBytes || p[0] != lp::kHipType || p[1] != lp::kProtocolVersion || p[2] != 0 || p[3] != 0)
    return false;
  std::uint32_t seq;
  double time;
  float xyz[3];
  std::memcpy(&seq, p + 4, 4);
  std::memcpy(&time, p + 8, 8);
  std::memcpy(xyz, p + 16, 12);
  if (!std::isfinite(time)) return false;
  double pos[3];
  for (int d = 0; d < 3; ++d) {
    pos[d] = double(xyz[d]);
    if (!std::isfinite(pos[d]) || !(sp.lo[d] <= pos[d] && pos[d] <= sp.hi[d])) return false;
  }
  if (!lp::write_hand(s->records[sp.slot], sp.seat, sp.occupant, pos, seq, time)) return false;
  in_.fetch_add(1, std::memory_order_relaxed);
  return true;
}

int Pump::send_newest(Conn& c) {
  Lane& lane = *c.lane;
  const LaneSpec& sp = lane.spec;
  if (c.srv.room != sp.room) return 0;
  Shared* s = shared(sp.block);
  if (s == nullptr || s->board || sp.slot < 0 || sp.slot >= s->rooms) return 0;
  std::uint8_t msg[lp::kCornerBytes];
  std::uint64_t occupant = 0;
  const std::int64_t frame = lp::read_corner(s->records[sp.slot], sp.seat, msg, occupant);
  if (frame < lane.sent_frame) return -1;  // the slot holds another room now
  if (frame == lane.sent_frame) return 0;
  lane.sent_frame = frame;
  if (occupant != sp.occupant) return 0;  // made from a former occupant's hand: its echo
  write_lane(c, kCorner, msg, lp::kCornerBytes);
  return 1;
}

void Pump::corner_timer(Conn& c) {
  Lane& lane = *c.lane;
  const double now = monotonic();
  const int sent = send_newest(c);
  if (sent < 0) return;  // the lane has ended: its timer stops
  if (sent) {
    lane.retries = 0;
  } else if (c.srv.room == lane.spec.room && shared_.count(lane.spec.block)) {
    if (lane.retries < kRetries) {
      // due just before the loop published the next frame: again a little later
      ++lane.retries;
      schedule(now + kRetryFrameS, c.id, lane.gen);
      return;
    }
    lane.retries = 0;  // no new frame (the room sleeps): on at the rate
  }
  const double interval = std::max(lane.spec.corner_interval, kFrameS);
  const double due = lane.due + interval;
  lane.due = due > now ? due : now + interval;
  schedule(on_grid(lane.due), c.id, lane.gen);
}

void Pump::on_frame(Conn& c, double now) {
  Lane& lane = *c.lane;
  if (now < lane.due - kFrameS / 2) return;
  const int sent = send_newest(c);
  if (sent < 0) {
    set_framed(c, false);
  } else if (sent) {
    const double due = lane.due + std::max(lane.spec.corner_interval, kFrameS);
    lane.due = due > now ? due : now + kFrameS / 2;
  }
}

void Pump::set_framed(Conn& c, bool on) {
  if (on) framed_.insert(c.id);
  else framed_.erase(c.id);
  const bool want = !framed_.empty();
  if (want != armed_want_ && !no_wake_) {
    armed_want_ = want;
    Event e;
  e.kind = Event::kArm;
    e.conn = want ? 1 : 0;
    emit(std::move(e));
  }
}

void Pump::on_wake() {
  drain(wake_fd_);
  const double now = monotonic();
  for (std::int64_t id : std::vector<std::int64_t>(framed_.begin(), framed_.end())) {
    auto it = conns_.find(id);
    if (it != conns_.end() && !it->second->dead && it->second->lane) on_frame(*it->second, now);
  }
}

// A lane's message to its client, between two of the engine's messages (else the newest
// of each kind is held until the engine's stream is between two), unless the client is
// behind on reading. The stream's follower learns its room's frame from it.
void Pump::write_lane(Conn& c, int kind, const std::uint8_t* payload, std::size_t n) {
  if (c.c_shut || c.finishing || c.c_buffered() > kWriteSkip) return;
  std::uint8_t head[kMaxHeader];
  const std::size_t hn = write_head(head, kOpBinary, n);
  if (c.srv.between_messages()) {
    append(c.to_client, head, hn);
    append(c.to_client, payload, n);
    c.srv.sent_binary(payload, n);
    out_.fetch_add(1, std::memory_order_relaxed);
    mark(c);
  } else {
    c.pending[kind].assign(reinterpret_cast<const char*>(payload), n);
    c.has_pending[kind] = true;
  }
}

void Pump::flush_pending(Conn& c) {
  for (int kind : {kCorner, kMesh}) {
    if (!c.has_pending[kind]) continue;
    c.has_pending[kind] = false;
    std::string held;
    held.swap(c.pending[kind]);
    write_lane(c, kind, reinterpret_cast<const std::uint8_t*>(held.data()), held.size());
  }
}

void Pump::look_meshes() {
  for (auto it = watched_.begin(); it != watched_.end(); ++it) {
    const auto [board_id, offset] = it->first;
    Watch& w = it->second;
    Shared* s = shared(board_id);
    if (s == nullptr || !s->board || w.conns.empty()) continue;
    const std::size_t slot_bytes = w.slot_bytes;
    if (slot_bytes <= lp::kBoardHead || offset + slot_bytes > s->bytes) continue;
    mesh_buf_.resize(slot_bytes - lp::kBoardHead);
    std::int64_t frame = -1;
    const std::int64_t n =
        lp::board_read(s->base + offset, w.sent, mesh_buf_.data(), mesh_buf_.size(), frame);
    if (frame < w.sent) w.sent = -1;  // the slot was cleared for another room
    if (n <= 0) continue;
    w.sent = frame;
    for (std::int64_t id : w.conns) {
      auto ci = conns_.find(id);
      if (ci == conns_.end() || ci->second->dead || !ci->second->lane) continue;
      Conn& c = *ci->second;
      if (c.srv.room == c.lane->spec.room) write_lane(c, kMesh, mesh_buf_.data(), std::size_t(n));
    }
  }
}

// --- timers ---------------------------------------------------------------------------------

void Pump::schedule(double at, std::int64_t conn, std::uint64_t gen) {
  timers_.push(Timer{at, conn, gen});
}

void Pump::on_timers() {
  const double now = monotonic();
  while (!timers_.empty() && timers_.top().at <= now) {
    const Timer t = timers_.top();
    timers_.pop();
    if (t.conn == 0) {
      look_meshes();
      if (watched_.empty()) mesh_timer_ = false;
      else schedule(now + kMeshLookS, 0, 0);
      continue;
    }
    auto it = conns_.find(t.conn);
    if (it == conns_.end() || it->second->dead) continue;
    Conn& c = *it->second;
    if (!c.lane || c.lane->gen != t.gen || !c.lane->timer) continue;
    corner_timer(c);
  }
}

// Waits for the sockets until the earliest timer (epoll_pwait2: to the nanosecond, without
// a timer descriptor's two system calls a wake-up; epoll_wait's whole milliseconds where
// the kernel lacks it).
int Pump::wait(epoll_event* evs, int max) {
  if (timers_.empty() && slow_.empty()) return epoll_wait(ep_, evs, max, -1);
  double at = timers_.empty() ? slow_.top().at : timers_.top().at;
  if (!slow_.empty()) at = std::min(at, slow_.top().at);
  double d = at - monotonic();
  if (d < 0) d = 0;
  if (pwait2_) {
    timespec ts;
    ts.tv_sec = time_t(d);
    ts.tv_nsec = long((d - std::floor(d)) * 1e9);
    const int n = epoll_pwait2(ep_, evs, max, &ts, nullptr);
    if (n >= 0 || errno != ENOSYS) return n;
    pwait2_ = false;
  }
  return epoll_wait(ep_, evs, max, int(std::ceil(d * 1000.0)));
}

}  // namespace cb::net
