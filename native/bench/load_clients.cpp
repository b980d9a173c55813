// The load bench's native client pump: see load_clients.hpp. Built with -ffp-contract=off
// (native/CMakeLists.txt): a HIP's position is the sine Python's would compute, bit for bit.
#include "bench/load_clients.hpp"

#include <fcntl.h>
#include <sys/epoll.h>
#include <sys/eventfd.h>
#include <sys/socket.h>
#include <sys/uio.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstring>
#include <memory>
#include <stdexcept>

#include "loop/corner_msg.hpp"
#include "loop/mesh_msg.hpp"
#include "net/wsframe.hpp"

namespace cb::bench {

namespace {
constexpr std::uint64_t kWakeTag = ~std::uint64_t(0);
constexpr std::size_t kRead = 1 << 16;  // bytes read from a socket at a time
constexpr std::uint8_t kZeroKey[4] = {0, 0, 0, 0};
constexpr std::size_t kCornerHead = 16;  // <BBHId before the CORNER's frame (<q)
constexpr double kPi = 3.14159265358979323846;

template <class T>
T get(const std::uint8_t* p) {
  T v;
  std::memcpy(&v, p, sizeof v);  // little-endian hosts, as the wire
  return v;
}
template <class T>
std::uint8_t* put(std::uint8_t* p, T v) {
  std::memcpy(p, &v, sizeof v);
  return p + sizeof v;
}
}  // namespace

double monotonic_s() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);  // what time.perf_counter() reads on Linux
  return double(ts.tv_sec) + double(ts.tv_nsec) * 1e-9;
}

struct LoadClients::Client {
  int fd = -1;
  int index = 0;
  bool player = false;
  Hand hand;
  std::uint32_t seq = 0;       // the newest HIP sent
  std::uint32_t echo_seq = 0;  // the newest HIP seq a CORNER echoed
  std::vector<double> sent;    // send times by seq (mod kSentRing), players only
  ClientCounts n;
  std::vector<std::uint8_t> hold;  // a small frame cut by the end of a read
  std::uint64_t skip = 0;          // payload bytes of a long frame still to come
  std::vector<std::uint8_t> out;   // bytes not yet written
  bool out_wait = false;           // EPOLLOUT asked for
  bool queued = false;             // in dirty_
};

LoadClients::LoadClients(double hip_rate, std::string error_prefix)
    : period_(1.0 / hip_rate), error_prefix_(std::move(error_prefix)),
      hist_(kHistBins + 1, 0), scratch_(kRead + kHoldMax + net::kMaxHeader + 1) {
  ep_ = epoll_create1(EPOLL_CLOEXEC);
  wake_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (ep_ < 0 || wake_ < 0) throw std::runtime_error(std::string("epoll: ") + strerror(errno));
  epoll_event ev{};
  ev.events = EPOLLIN;
  ev.data.u64 = kWakeTag;
  epoll_ctl(ep_, EPOLL_CTL_ADD, wake_, &ev);
}

LoadClients::~LoadClients() { close(); }

int LoadClients::add(int fd, const std::string& pending, const Hand* hand) {
  std::lock_guard<std::mutex> lock(mu_);
  if (closed_) {
    ::close(fd);
    throw std::runtime_error("the load clients are closed");
  }
  fcntl(fd, F_SETFL, fcntl(fd, F_GETFL) | O_NONBLOCK);
  if (arrival_) {  // each read's receipt time from the kernel (read())
    const int on = 1;
    setsockopt(fd, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on);
  }
  clients_.push_back(std::make_unique<Client>());
  Client* c = clients_.back().get();
  c->fd = fd;
  c->index = int(clients_.size()) - 1;
  if (hand != nullptr) {
    c->player = true;
    c->hand = *hand;
    c->sent.assign(kSentRing, 0.0);
    players_.push_back(c->index);
  }
  epoll_event ev{};
  ev.events = EPOLLIN;
  ev.data.u64 = std::uint64_t(c->index);
  if (epoll_ctl(ep_, EPOLL_CTL_ADD, fd, &ev) != 0) {
    finish(*c);
    return c->index;
  }
  if (!pending.empty()) {  // frames that came with the setup's last read
    c->n.bytes += pending.size();
    const auto* p = reinterpret_cast<const std::uint8_t*>(pending.data());
    const std::size_t used = frames(*c, p, pending.size(), monotonic_s());
    if (!c->n.closed) c->hold.assign(p + used, p + pending.size());
    for (int i : dirty_) flush(*clients_[std::size_t(i)]);
    for (int i : dirty_) clients_[std::size_t(i)]->queued = false;
    dirty_.clear();
  }
  const std::uint64_t one = 1;
  (void)!write(wake_, &one, sizeof one);  // the pacer's period changed
  return c->index;
}

void LoadClients::start() {
  std::lock_guard<std::mutex> lock(mu_);
  if (closed_) throw std::runtime_error("the load clients are closed");
  if (thread_.joinable()) throw std::runtime_error("the pump is started already");
  arrival_ = true;
  const int on = 1;
  for (const auto& c : clients_)
    if (!c->n.closed) setsockopt(c->fd, SOL_SOCKET, SO_TIMESTAMPNS, &on, sizeof on);
  thread_ = std::thread([this] {
    std::vector<epoll_event> evs(4096);
    double next = monotonic_s();
    for (;;) {
      bool idle;
      {
        std::lock_guard<std::mutex> l(mu_);
        if (stop_) return;
        idle = clients_.empty();
      }
      if (idle) {  // nothing to pace or read: woken by an add (or close)
        epoll_event ev;
        (void)epoll_wait(ep_, &ev, 1, -1);
        next = monotonic_s();
      } else {
        // A turn every kTurnS, one sleep each, every socket ready by then taken in it: the
        // wake-ups (costly in a VM) do not grow with the clients. A HIP goes at the turn it
        // falls due in; a CORNER's receipt time is the kernel's (read()).
        next += kTurnS;
        const double now = monotonic_s();
        if (next < now) next = now;  // late: no burst of turns to catch up
        timespec ts;
        ts.tv_sec = time_t(next);
        ts.tv_nsec = long((next - double(ts.tv_sec)) * 1e9);
        clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
      }
      std::lock_guard<std::mutex> l(mu_);
      if (stop_) return;
      const int got = epoll_wait(ep_, evs.data(), int(evs.size()), 0);
      turn(monotonic_s(), evs.data(), got);
    }
  });
}

void LoadClients::poll(double now, int wait_ms) {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (closed_) throw std::runtime_error("the load clients are closed");
    if (thread_.joinable()) throw std::runtime_error("the pump runs on its thread");
  }
  std::vector<epoll_event> evs(4096);
  const int got = epoll_wait(ep_, evs.data(), int(evs.size()), wait_ms);
  std::lock_guard<std::mutex> lock(mu_);
  turn(now, evs.data(), got);
}

// One turn, under the lock: the HIPs due, the sockets `evs` says are ready, then every
// socket with bytes queued, each in one write.
void LoadClients::turn(double now, const epoll_event* evs, int got) {
  pace(now);
  for (int e = 0; e < got; ++e) {
    if (evs[e].data.u64 == kWakeTag) {
      std::uint64_t v;
      (void)!::read(wake_, &v, sizeof v);
      continue;
    }
    Client& c = *clients_[std::size_t(evs[e].data.u64)];
    if (c.n.closed) continue;
    if (evs[e].events & (EPOLLIN | EPOLLHUP | EPOLLERR)) read(c, now);
    if (!c.n.closed && (evs[e].events & EPOLLOUT)) flush(c);
  }
  for (int i : dirty_) {
    Client& c = *clients_[std::size_t(i)];
    c.queued = false;
    if (!c.n.closed) flush(c);
  }
  dirty_.clear();
}

// Every player's HIPs due by `now`, round robin, evenly staggered over the period.
void LoadClients::pace(double now) {
  if (players_.empty()) {
    paced_ = false;
    return;
  }
  if (!paced_) {
    t_ = now;
    paced_ = true;
  }
  const std::size_t n = players_.size();
  const double gap = period_ / double(n);
  if (now - t_ > kFarBehindS) {
    ++totals_.behind;
    t_ = now;
  }
  // The slots due now; a socket written at its last slot of the turn (its frames due
  // together in one write, each as soon as it is made: the time it carries is the send's).
  const std::uint64_t due = t_ <= now ? std::uint64_t((now - t_) / gap) + 1 : 0;
  std::uint8_t f[kHipFrameBytes];
  for (std::uint64_t j = 0; j < due; ++j) {
    Client& c = *clients_[std::size_t(players_[k_ % n])];
    ++k_;
    if (c.n.closed || c.out.size() + kHipFrameBytes > kOutMax) continue;  // not sent
    const double at = arrival_ ? monotonic_s() : now;  // the tests' turns: their clock
    const std::uint32_t seq = ++c.seq;
    c.sent[seq & (kSentRing - 1)] = at;
    const Hand& h = c.hand;
    const double y = h.cy + 0.3 * std::sin(kPi * at + h.phase) * h.half_y;
    std::uint8_t* p = f + net::write_head(f, net::kOpBinary, kHipBytes, kZeroKey);
    p = put(p, kHipType);
    p = put(p, loop::kProtocolVersion);
    p = put(p, std::uint16_t(0));
    p = put(p, seq);
    p = put(p, at);
    p = put(p, float(h.cx));
    p = put(p, float(y));
    put(p, float(h.cz));
    c.out.insert(c.out.end(), f, f + kHipFrameBytes);
    ++c.n.hips;
    if (j + n >= due) flush(c);  // (else the socket comes again this turn)
  }
  t_ += double(due) * gap;
}

void LoadClients::read(Client& c, double now) {
  std::uint8_t* buf = scratch_.data();
  const std::size_t held = c.hold.size();
  if (held) std::memcpy(buf, c.hold.data(), held);
  iovec iov{buf + held, kRead};
  alignas(cmsghdr) char ctl[CMSG_SPACE(sizeof(timespec))];
  msghdr msg{};
  msg.msg_iov = &iov;
  msg.msg_iovlen = 1;
  if (arrival_) {
    msg.msg_control = ctl;
    msg.msg_controllen = sizeof ctl;
  }
  const ssize_t r = recvmsg(c.fd, &msg, MSG_DONTWAIT);
  if (r == 0 || (r < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR)) {
    finish(c);  // the server hung up
    return;
  }
  if (r < 0) return;
  // On its thread the pump reads a CORNER's receipt time from the kernel (when its newest
  // segment arrived, CLOCK_REALTIME), not from the turn: the latency is then not read a
  // turn late. The tests' turns (poll) keep the clock they are given.
  for (cmsghdr* m = arrival_ ? CMSG_FIRSTHDR(&msg) : nullptr; m; m = CMSG_NXTHDR(&msg, m)) {
    if (m->cmsg_level == SOL_SOCKET && m->cmsg_type == SCM_TIMESTAMPNS) {
      timespec at;
      std::memcpy(&at, CMSG_DATA(m), sizeof at);
      timespec rt;
      clock_gettime(CLOCK_REALTIME, &rt);
      const double ago = double(rt.tv_sec - at.tv_sec) + double(rt.tv_nsec - at.tv_nsec) * 1e-9;
      const double mono = monotonic_s();
      if (ago >= 0 && ago < 1.0) now = mono - ago;
    }
  }
  c.n.bytes += std::uint64_t(r);
  const std::size_t n = held + std::size_t(r);
  const std::size_t used = frames(c, buf, n, now);
  if (!c.n.closed) c.hold.assign(buf + used, buf + n);
}

// The frames in `p` (`n` bytes): returns how many bytes were used; the rest is a small
// frame not yet whole (or a long one's header before its first payload byte).
std::size_t LoadClients::frames(Client& c, const std::uint8_t* p, std::size_t n, double now) {
  std::size_t pos = 0;
  for (;;) {
    if (c.skip) {
      const std::size_t take = std::size_t(std::min<std::uint64_t>(c.skip, n - pos));
      c.skip -= take;
      pos += take;
      if (c.skip) return pos;
    }
    net::FrameHead h;
    if (!net::read_head(p + pos, n - pos, h)) return pos;
    if (h.masked) {  // a server never masks (RFC 6455 5.1): not a server to measure
      totals_.last_error = "protocol: a masked frame from the server";
      ++c.n.errors;
      finish(c);
      return n;
    }
    const std::size_t avail = n - pos - h.size;
    const std::uint8_t op = h.opcode();
    const std::uint8_t* body = p + pos + h.size;
    if (h.length > kHoldMax) {  // counted from its header and first byte, then skipped
      if (avail == 0) return pos;
      if (op == net::kOpBinary && body[0] == loop::kMeshType) ++c.n.meshes;
      else if (op == net::kOpText) ++c.n.texts;
      pos += h.size;
      c.skip = h.length;
      continue;
    }
    const std::size_t len = std::size_t(h.length);
    if (avail < len) return pos;
    if (op == net::kOpBinary && len > 0) {
      if (body[0] == loop::kMeshType) ++c.n.meshes;
      else if (body[0] == loop::kCornerType && len == std::size_t(loop::kCornerBytes))
        corner(c, body, now);
    } else if (op == net::kOpText) {
      ++c.n.texts;
      if (len >= error_prefix_.size() &&
          std::memcmp(body, error_prefix_.data(), error_prefix_.size()) == 0) {
        ++c.n.errors;
        totals_.last_error.assign(reinterpret_cast<const char*>(body), std::min(len, kErrorKeep));
      }
    } else if (op == net::kOpPing) {
      std::uint8_t f[net::kMaxHeader + 125];
      const std::size_t m = std::min<std::size_t>(len, 125);
      const std::size_t hs = net::write_head(f, net::kOpPong, m, kZeroKey);
      std::memcpy(f + hs, body, m);
      send(c, f, hs + m);
    } else if (op == net::kOpClose) {  // answered with its status code, then closed
      std::uint8_t f[net::kMaxHeader + 2];
      const std::size_t m = len >= 2 ? 2 : 0;
      const std::size_t hs = net::write_head(f, net::kOpClose, m, kZeroKey);
      std::memcpy(f + hs, body, m);
      send(c, f, hs + m);
      flush(c);
      finish(c);
      return n;
    }
    pos += h.size + len;
  }
}

void LoadClients::corner(Client& c, const std::uint8_t* p, double now) {
  const auto frame = get<std::int64_t>(p + kCornerHead);
  const auto seq = get<std::uint32_t>(p + loop::kCornerBytes - 12);
  const auto echoed = get<double>(p + loop::kCornerBytes - 8);
  ++c.n.corners;
  c.n.frame = frame;
  if (seq == c.echo_seq || seq == 0) return;  // not the first CORNER that echoes a HIP
  c.echo_seq = seq;
  if (!c.player || std::uint32_t(c.seq - seq) >= kSentRing) {
    ++totals_.echo_unknown;  // a seq this client never sent (or long ago)
    return;
  }
  const double sent = c.sent[seq & (kSentRing - 1)];
  if (!(echoed == sent)) ++totals_.echo_mismatch;  // another time than this HIP's
  const double bins = (now - sent) / kHistBinS;
  const std::size_t i = !(bins >= 0) ? 0 : bins >= double(kHistBins) ? kHistBins
                                                                       : std::size_t(bins);
  ++hist_[i];
}

void LoadClients::send(Client& c, const std::uint8_t* p, std::size_t n) {
  c.out.insert(c.out.end(), p, p + n);
  if (!c.queued) {
    c.queued = true;
    dirty_.push_back(c.index);
  }
}

void LoadClients::flush(Client& c) {
  std::size_t done = 0;
  while (done < c.out.size()) {
    const ssize_t w = ::send(c.fd, c.out.data() + done, c.out.size() - done,
                             MSG_DONTWAIT | MSG_NOSIGNAL);
    if (w > 0) {
      done += std::size_t(w);
      continue;
    }
    if (w < 0 && errno == EINTR) continue;
    if (w < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) break;
    finish(c);
    return;
  }
  c.out.erase(c.out.begin(), c.out.begin() + std::ptrdiff_t(done));
  const bool want = !c.out.empty();
  if (want != c.out_wait) {  // write readiness asked for only while bytes wait
    epoll_event ev{};
    ev.events = EPOLLIN | (want ? EPOLLOUT : 0u);
    ev.data.u64 = std::uint64_t(c.index);
    epoll_ctl(ep_, EPOLL_CTL_MOD, c.fd, &ev);
    c.out_wait = want;
  }
}

void LoadClients::finish(Client& c) {
  if (c.n.closed) return;
  c.n.closed = true;
  epoll_ctl(ep_, EPOLL_CTL_DEL, c.fd, nullptr);  // (a close alone does not while a dup lives)
  ::close(c.fd);
  c.fd = -1;
  c.out.clear();
  c.out.shrink_to_fit();
  c.hold.clear();
  c.hold.shrink_to_fit();
  c.skip = 0;
}

void LoadClients::snap(bool mark, std::vector<ClientCounts>& counts, Totals& totals,
                       std::vector<std::pair<std::uint32_t, std::uint64_t>>& hist) {
  std::lock_guard<std::mutex> lock(mu_);
  counts.clear();
  counts.reserve(clients_.size());
  for (const auto& c : clients_) counts.push_back(c->n);
  totals = totals_;
  hist.clear();
  for (std::size_t i = 0; i < hist_.size(); ++i)
    if (hist_[i]) hist.emplace_back(std::uint32_t(i), hist_[i]);
  if (mark) std::fill(hist_.begin(), hist_.end(), 0);
}

void LoadClients::close() {
  {
    std::lock_guard<std::mutex> lock(mu_);
    if (closed_) return;
    closed_ = stop_ = true;
    std::uint8_t f[net::kMaxHeader + 2];
    const std::uint8_t status[2] = {0x03, 0xE8};  // 1000, normal closure
    const std::size_t hs = net::write_head(f, net::kOpClose, 2, kZeroKey);
    std::memcpy(f + hs, status, 2);
    for (const auto& c : clients_) {
      if (c->n.closed) continue;
      c->out.insert(c->out.end(), f, f + hs + 2);
      flush(*c);  // best effort: what does not go at once is dropped with the socket
      if (!c->n.closed) {
        ::close(c->fd);
        c->fd = -1;
      }
    }
    const std::uint64_t one = 1;
    (void)!write(wake_, &one, sizeof one);
  }
  if (thread_.joinable()) thread_.join();
  ::close(ep_);
  ::close(wake_);
  ep_ = wake_ = -1;
}

}  // namespace cb::bench
