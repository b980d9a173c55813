// The native frame loop (frame_loop.hpp; docs/frameloop.md).
#include "loop/frame_loop.hpp"

#include <pthread.h>
#include <sys/eventfd.h>
#include <sys/mman.h>
#include <sys/resource.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>

#include "loop/exit.hpp"

namespace cb::loop {

double monotonic_now() {
  timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

namespace {

void sleep_until(double t) {
  timespec ts;
  ts.tv_sec = time_t(std::floor(t));
  ts.tv_nsec = long((t - std::floor(t)) * 1e9);
  if (ts.tv_nsec >= 1000000000L) {
    ts.tv_sec += 1;
    ts.tv_nsec -= 1000000000L;
  }
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

const double kNaN = std::numeric_limits<double>::quiet_NaN();
const double kInf = std::numeric_limits<double>::infinity();

}  // namespace

FrameLoop::FrameLoop(Batch& batch, LoopConfig cfg)
    : batch_(batch), cfg_(std::move(cfg)), cap_(batch.capacity()) {
  if (cfg_.frame_dt <= 0.0) throw std::invalid_argument("frame_dt must be > 0");
  if (cfg_.fixed_substeps <= 0 && cfg_.substep_speeds.empty())
    throw std::invalid_argument("automatic substeps need substep_speeds");
  if (!(cfg_.gust_period > 0.0) || !std::isfinite(cfg_.gust_amplitude))
    throw std::invalid_argument("gusts need a period > 0 and a finite amplitude");
  bytes_ = block_bytes(cap_);
  // A memfd, so that another process may map the same block (docs/frameloop.md), unless
  // the process may not make a file that large (RLIMIT_FSIZE: growing it would raise
  // SIGXFSZ): then shared anonymous memory, the same layout, no fd.
  rlimit fsize{};
  getrlimit(RLIMIT_FSIZE, &fsize);
  if (fsize.rlim_cur == RLIM_INFINITY || fsize.rlim_cur >= rlim_t(bytes_)) {
    memfd_ = int(memfd_create("clothball-frames", MFD_CLOEXEC));
    if (memfd_ < 0 || ftruncate(memfd_, off_t(bytes_)) != 0)
      throw std::runtime_error(std::string("frame block: ") + std::strerror(errno));
  }
  base_ = memfd_ >= 0
              ? mmap(nullptr, bytes_, PROT_READ | PROT_WRITE, MAP_SHARED, memfd_, 0)
              : mmap(nullptr, bytes_, PROT_READ | PROT_WRITE, MAP_SHARED | MAP_ANONYMOUS, -1, 0);
  if (base_ == MAP_FAILED) {
    if (memfd_ >= 0) close(memfd_);
    throw std::runtime_error(std::string("frame block mmap: ") + std::strerror(errno));
  }
  auto* bytes = static_cast<unsigned char*>(base_);
  hdr_ = reinterpret_cast<Header*>(bytes);
  rooms_ = reinterpret_cast<RoomRecord*>(bytes + rooms_offset());
  eng_ = reinterpret_cast<EngineRecord*>(bytes + engine_offset(cap_));
  *hdr_ = Header{};
  hdr_->magic = kBlockMagic;
  hdr_->version = kBlockVersion;
  hdr_->header_bytes = sizeof(Header);
  hdr_->rooms = std::uint32_t(cap_);
  hdr_->room_bytes = sizeof(RoomRecord);
  hdr_->engine_bytes = sizeof(EngineRecord);
  hdr_->lateness_capacity = kLatenessRing;
  hdr_->rooms_offset = rooms_offset();
  hdr_->engine_offset = engine_offset(cap_);
  hdr_->total_bytes = bytes_;
  hdr_->frame_dt = cfg_.frame_dt;
  hdr_->epoch = cfg_.epoch;
  efd_ = eventfd(0, EFD_NONBLOCK | EFD_CLOEXEC);
  if (efd_ < 0) throw std::runtime_error(std::string("eventfd: ") + std::strerror(errno));
  const size_t n = size_t(cap_);
  done_.assign(n, 0);
  next_mesh_.assign(n, 0);
  next_track_.assign(n, 0);
  was_awake_.assign(n, 0);
  failed_.assign(n, 0);
  hips_.assign(12 * n, 0.0);
  corners_.assign(24 * n, 0.0);
  balls_.assign(6 * n, 0.0);
  finite_.assign(n, 1);
  applied_seq_.assign(4 * n, 0);
  applied_occupant_.assign(4 * n, 0);
  applied_time_.assign(4 * n, kNaN);
}

FrameLoop::~FrameLoop() {
  stop();
  if (efd_ >= 0) close(efd_);
  if (base_ != nullptr && base_ != MAP_FAILED) munmap(base_, bytes_);
  if (memfd_ >= 0) close(memfd_);
}

void FrameLoop::start() {
  if (thread_.joinable()) return;
  stop_ = false;
  thread_ = std::thread([this] { run(); });
}

void FrameLoop::acquire() {
  waiting_.fetch_add(1, std::memory_order_acq_rel);
  mutex_.lock();
  waiting_.fetch_sub(1, std::memory_order_acq_rel);
}

void FrameLoop::stop() {
  acquire();
  stop_ = true;
  release();
  idle_cv_.notify_all();
  notify_service();
  if (thread_.joinable()) thread_.join();
}

bool FrameLoop::running() const { return thread_.joinable(); }

double FrameLoop::cpu_seconds() const {
  clockid_t cid;
  timespec ts{};
  if (!thread_.joinable() ||
      pthread_getcpuclockid(const_cast<std::thread&>(thread_).native_handle(), &cid) != 0 ||
      clock_gettime(cid, &ts) != 0)
    return 0.0;
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}

void FrameLoop::add_room(int slot, bool awake) {
  RoomRecord& r = rooms_[slot];
  std::memset(static_cast<void*>(&r), 0, sizeof(RoomRecord));
  for (int s = 0; s < kSeats; ++s) r.applied_time[s] = kNaN;
  r.corner_due = 0.0;
  r.exit_edge = -1;
  r.fail_frame = -1;
  const size_t k = size_t(slot);
  done_[k] = next_mesh_[k] = next_track_[k] = 0;
  failed_[k] = 0;
  for (size_t a = 4 * k; a < 4 * k + 4; ++a) {
    applied_seq_[a] = applied_occupant_[a] = 0;
    applied_time_[a] = kNaN;
  }
  was_awake_[k] = awake ? 1 : 0;
  store(r.awake, std::uint32_t(awake ? 1 : 0));
  store(r.used, std::uint32_t(1));
  if (awake && idle_ && std::isnan(resume_at_)) resume_at_ = now();
  idle_cv_.notify_all();
}

void FrameLoop::remove_room(int slot) {
  store(rooms_[slot].used, std::uint32_t(0));
  std::lock_guard<std::mutex> g(mesh_mutex_);
  meshes_.erase(std::remove_if(meshes_.begin(), meshes_.end(),
                               [slot](const MeshSnapshot& m) { return m.slot == slot; }),
                meshes_.end());
}

void FrameLoop::set_awake(int slot, bool awake) {
  if (awake) {
    acquire();  // not lost between the loop's check and wait
    if (idle_ && std::isnan(resume_at_)) resume_at_ = now();
    store(rooms_[slot].awake, std::uint32_t(1));
    release();
    idle_cv_.notify_all();
  } else {
    store(rooms_[slot].awake, std::uint32_t(0));
  }
}

void FrameLoop::set_hip(int slot, int seat, const double* pos, std::uint64_t seq, double time,
                        std::uint64_t occupant) {
  RoomRecord& r = rooms_[slot];
  const std::uint32_t v = lock_hand(r, seat);
  for (int d = 0; d < 3; ++d) r.hip_pos[seat][d] = pos[d];
  r.hip_seq[seat] = seq;
  r.hip_time[seat] = time;
  r.hip_occupant[seat] = occupant;
  r.seat_occupant[seat] = occupant;
  r.hip_has[seat] = 1;
  unlock_hand(r, seat, v);
}

void FrameLoop::clear_hip(int slot, int seat, std::uint64_t occupant) {
  RoomRecord& r = rooms_[slot];
  const std::uint32_t v = lock_hand(r, seat);
  r.hip_has[seat] = 0;
  r.hip_occupant[seat] = occupant;
  r.seat_occupant[seat] = occupant;
  unlock_hand(r, seat, v);
}

void FrameLoop::set_armed(int slot, bool armed) {
  store(rooms_[slot].armed, std::uint32_t(armed ? 1 : 0));
}
void FrameLoop::set_recording(int slot, bool on) {
  store(rooms_[slot].recording, std::uint32_t(on ? 1 : 0));
}
void FrameLoop::set_corner_due(int slot, double server_time) {
  store(rooms_[slot].corner_due, server_time);
}

double FrameLoop::now() const {
  return cfg_.manual_clock ? manual_now_.load(std::memory_order_acquire) : monotonic_now();
}

void FrameLoop::set_clock(double t) {
  manual_now_.store(t, std::memory_order_release);
  acquire();  // not lost between the loop's check and its wait
  release();
  idle_cv_.notify_all();
}

// Each live room's wind for its next frame (ClothBatch.step's gusts, from the room's own
// simulated time): the frame loop steps a frame a call while gusts blow.
void FrameLoop::set_gusts(const std::vector<int>& live, int frames_into_pass) {
  const double two_pi = 6.283185307179586;
  for (int s : live) {
    const double t = double(rooms_[s].frame + frames_into_pass) * cfg_.frame_dt;
    const double f = 1.0 + cfg_.gust_amplitude * std::sin(two_pi * t / cfg_.gust_period);
    const double w[3] = {cfg_.wind[0] * f, cfg_.wind[1] * f, cfg_.wind[2] * f};
    batch_.at(s).set_wind(w);
  }
}

void FrameLoop::add_wake(int fd) {
  std::lock_guard<std::mutex> g(wake_mutex_);
  if (std::find(wakes_.begin(), wakes_.end(), fd) == wakes_.end()) wakes_.push_back(fd);
}

void FrameLoop::remove_wake(int fd) {
  std::lock_guard<std::mutex> g(wake_mutex_);
  wakes_.erase(std::remove(wakes_.begin(), wakes_.end(), fd), wakes_.end());
}

int FrameLoop::take_events(std::vector<int>& slots, std::vector<std::uint32_t>& bits) {
  // The eventfd drained first, then the flag cleared, then the rooms read: an event set
  // after the flag is cleared writes the eventfd again (and is read now or on that wake-up);
  // one set before it is in the rooms read below. (Clearing the flag before draining could
  // swallow a write whose events this read has taken and leave the flag set: no wake-up
  // ever again.)
  // One read takes the whole count (no EFD_SEMAPHORE) and leaves it at 0; no write can
  // come before the flag is cleared below, so a second read would find nothing.
  std::uint64_t drained;
  [[maybe_unused]] ssize_t got = read(efd_, &drained, sizeof(drained));
  store(signalled_, std::uint32_t(0));
  fence();
  slots.clear();
  bits.clear();
  for (int s = 0; s < cap_; ++s) {
    const std::uint32_t b = __atomic_exchange_n(&rooms_[s].events, 0u, __ATOMIC_ACQ_REL);
    if (b != 0) {
      slots.push_back(s);
      bits.push_back(b);
    }
  }
  return int(slots.size());
}

void FrameLoop::read_room(int slot, RoomRecord& out) const {
  const RoomRecord& r = rooms_[slot];
  for (;;) {
    const std::uint32_t v0 = load(r.out_lock);
    if (v0 & 1u) {
      std::this_thread::yield();
      continue;
    }
    std::memcpy(static_cast<void*>(&out), &r, sizeof(RoomRecord));
    fence();
    if (load(r.out_lock) == v0) return;
  }
}

bool FrameLoop::wait_service(double timeout) {
  std::unique_lock<std::mutex> g(mesh_mutex_);
  mesh_cv_.wait_for(g, std::chrono::duration<double>(timeout),
                    [this] { return service_flag_ || !meshes_.empty(); });
  const bool any = service_flag_ || !meshes_.empty();
  service_flag_ = false;
  return any;
}

void FrameLoop::notify_service() {
  {
    std::lock_guard<std::mutex> g(mesh_mutex_);
    service_flag_ = true;
  }
  mesh_cv_.notify_all();
}

std::vector<MeshSnapshot> FrameLoop::take_meshes() {
  std::lock_guard<std::mutex> g(mesh_mutex_);
  std::vector<MeshSnapshot> out;
  out.swap(meshes_);
  return out;
}

void FrameLoop::signal() {
  if (__atomic_exchange_n(&signalled_, 1u, __ATOMIC_ACQ_REL) == 0) {
    const std::uint64_t one = 1;
    [[maybe_unused]] ssize_t w = write(efd_, &one, sizeof(one));
  }
}

// Automatic substeps: the most any stepped room's ball needs (as ClothBatch.substeps).
int FrameLoop::substeps_for(const std::vector<int>& live) {
  if (cfg_.fixed_substeps > 0) return cfg_.fixed_substeps;
  batch_.get_corners_all(corners_.data(), balls_.data());
  const auto& lim = cfg_.substep_speeds;
  int most = 1;
  for (int s : live) {
    const double* b = balls_.data() + 6 * size_t(s);
    const double speed = cfg_.has_ball ? std::sqrt(b[3] * b[3] + b[4] * b[4] + b[5] * b[5]) : 0.0;
    int k = int(std::lower_bound(lim.begin(), lim.end(), speed) - lim.begin()) + 1;
    most = std::max(most, std::min(k, int(lim.size())));
  }
  return most;
}

void FrameLoop::run() {
  // Named for /proc, top and the load bench's per-thread CPU (15 bytes at most).
  pthread_setname_np(pthread_self(), "cb-frame-loop");
  const double dt = cfg_.frame_dt;
  const bool gusts = cfg_.gust_amplitude != 0.0;
  double t0 = now();
  long long done = 0;  // frames simulated since t0
  bool was_idle = true;
  std::vector<int> live;
  live.reserve(size_t(cap_));
  std::unique_lock<std::mutex> lock(mutex_);
  while (!stop_) {
    if (waiting_.load(std::memory_order_acquire) > 0) {
      // Someone waits to change the batch (a room added or removed, the server stopping):
      // a loop that is behind would otherwise hold the lock from pass to pass and starve
      // it (a std::mutex hands over to no one in particular), freezing the event loop
      // that waits. Let every waiter in, then take the lock back.
      lock.unlock();
      while (waiting_.load(std::memory_order_acquire) > 0) std::this_thread::yield();
      lock.lock();
      continue;
    }
    live.clear();
    for (int s = 0; s < cap_; ++s) {
      RoomRecord& r = rooms_[s];
      if (!load(r.used) || failed_[size_t(s)]) continue;
      const bool awake = load(r.awake) != 0;
      if (awake != bool(was_awake_[size_t(s)])) {
        batch_.set_active(s, awake);
        was_awake_[size_t(s)] = awake;
        // Woken: pace from now, a mesh at once; the slept time is not replayed.
        if (awake) done_[size_t(s)] = next_mesh_[size_t(s)] = next_track_[size_t(s)] = 0;
      }
      if (awake) live.push_back(s);
    }
    if (live.empty()) {
      // Nothing to step: wait for a room or a wake-up, using no CPU.
      was_idle = idle_ = true;
      idle_cv_.wait_for(lock, std::chrono::milliseconds(50));
      continue;
    }
    if (was_idle) {  // pace afresh, from the first room's arrival: the idle time is not replayed
      t0 = std::isnan(resume_at_) ? now() : resume_at_;
      resume_at_ = std::numeric_limits<double>::quiet_NaN();
      was_idle = idle_ = false;
      done = 0;
    }
    const double t_now = now();
    long long behind = (long long)std::floor((t_now - t0 + cfg_.timer_slack) / dt) - done;
    if (behind <= 0) {
      if (cfg_.manual_clock) {  // until set_clock moves it (or a room changes)
        idle_cv_.wait_for(lock, std::chrono::milliseconds(5));
        continue;
      }
      lock.unlock();
      sleep_until(t0 + double(done + 1) * dt - cfg_.timer_slack);
      lock.lock();
      continue;
    }
    if (behind > cfg_.max_catchup) {
      const long long skip = behind - cfg_.max_catchup;
      t0 += double(skip) * dt;
      eng_->skipped += skip;
      for (int s : live) rooms_[s].skipped += skip;
      behind = cfg_.max_catchup;
    }
    // A quarter of the frames due (at least one) per pass: each pass takes the newest
    // hands and publishes its corners, so a HIP waits for part of the backlog, not all.
    const int frames = int(std::min<long long>(behind, 1 + behind / 4));
    // This pass's hands: each seat's newest (sequence-locked), else its anchor.
    for (int s : live) {
      RoomRecord& r = rooms_[s];
      double* h = hips_.data() + 12 * size_t(s);
      for (int seat = 0; seat < kSeats; ++seat) {
        for (int spins = 0;; ++spins) {
          const std::uint32_t v0 = load(r.hip_lock[seat]);
          // A lock held this long: its writer died (lock_hand); this pass, no hand.
          const bool dead = (v0 & 1u) && spins >= kLockSpins;
          if ((v0 & 1u) && !dead) continue;
          // (a hand written for an occupant that has left the seat: none)
          const bool has = !dead && r.hip_has[seat] != 0 &&
                           r.hip_occupant[seat] == r.seat_occupant[seat];
          for (int d = 0; d < 3; ++d) h[3 * seat + d] = has ? r.hip_pos[seat][d] : cfg_.anchors[3 * seat + d];
          const std::uint64_t seq = has ? r.hip_seq[seat] : 0;
          const double t = has ? r.hip_time[seat] : kNaN;
          const std::uint64_t occ = has ? r.hip_occupant[seat] : r.seat_occupant[seat];
          fence();
          if (!dead && load(r.hip_lock[seat]) != v0) continue;
          const size_t a = 4 * size_t(s) + size_t(seat);  // published with the frame
          applied_seq_[a] = seq;
          applied_time_[a] = t;
          applied_occupant_[a] = occ;
          break;
        }
      }
    }
    batch_.set_hips_all(hips_.data());
    int remaining = frames;
    while (remaining > 0) {
      const int substeps = substeps_for(live);
      int chunk = cfg_.fixed_substeps > 0 ? remaining : std::min(remaining, cfg_.max_frames_per_call);
      chunk = std::min(chunk, std::max(1, std::numeric_limits<int>::max() / substeps));
      if (gusts) {  // the wind changes every frame
        chunk = 1;
        set_gusts(live, frames - remaining);
      }
      batch_.step(chunk, substeps, dt / substeps, finite_.data());
      for (int s : live) rooms_[s].substeps = std::uint32_t(substeps);
      remaining -= chunk;
      bool any_failed = false;
      for (int s : live)
        if (!finite_[size_t(s)] && !failed_[size_t(s)]) {
          failed_[size_t(s)] = 1;
          any_failed = true;
          batch_.set_active(s, false);  // kept, not stepped: the server removes it
          RoomRecord& r = rooms_[s];
          r.fail_frame = r.frame + frames;
          __atomic_fetch_or(&r.events, kEventFailed, __ATOMIC_ACQ_REL);
        }
      if (any_failed) {
        live.erase(std::remove_if(live.begin(), live.end(),
                                  [this](int s) { return failed_[size_t(s)] != 0; }),
                   live.end());
        signal();
        if (live.empty()) break;
      }
    }
    done += frames;
    eng_->passes += 1;
    eng_->live = std::int64_t(live.size());
    batch_.get_corners_all(corners_.data(), balls_.data());
    const double t_end = now();
    const double server_time = t_end - cfg_.epoch;
    // How late the pass's last frame ended against when it was due; none when early (a
    // frame may start up to timer_slack before it is due, and a small room's can end
    // before then too: a negative p50 on a quiet machine, CI at 257aaaf).
    const double late = std::max(0.0, t_end - (t0 + double(done) * dt));
    bool any = false;
    std::vector<int> due;
    for (int s : live) {
      publish(s, frames, server_time, corners_.data() + 24 * size_t(s),
              balls_.data() + 6 * size_t(s), hips_.data() + 12 * size_t(s), any);
      const size_t k = size_t(s);
      if (cfg_.mesh_every > 0 && done_[k] >= next_mesh_[k]) {
        next_mesh_[k] = done_[k] + cfg_.mesh_every;
        due.push_back(s);
      }
    }
    if (!due.empty()) {
      // The due rooms' nodes in one transfer (Batch::gather_positions), handed to the
      // encoder thread, which quantises and compresses them off this loop.
      const size_t per = 3 * size_t(cfg_.nodes);
      stage_.resize(per * due.size());
      batch_.gather_positions(due.data(), int(due.size()), stage_.data());
      {
        std::lock_guard<std::mutex> g(mesh_mutex_);
        for (size_t i = 0; i < due.size(); ++i) {
          const int s = due[i];
          const RoomRecord& r = rooms_[s];
          auto it = std::find_if(meshes_.begin(), meshes_.end(),
                                 [s](const MeshSnapshot& m) { return m.slot == s; });
          if (it == meshes_.end()) it = meshes_.insert(meshes_.end(), MeshSnapshot{});
          it->slot = s;
          it->frame = r.frame;
          it->server_time = server_time;
          std::memcpy(it->ball, r.ball, sizeof(it->ball));
          std::memcpy(it->hips, hips_.data() + 12 * size_t(s), sizeof(it->hips));
          it->positions.assign(stage_.begin() + std::ptrdiff_t(per * i),
                               stage_.begin() + std::ptrdiff_t(per * (i + 1)));
        }
      }
      mesh_cv_.notify_all();
    }
    const std::uint64_t c = eng_->lateness_count;
    eng_->lateness[c % kLatenessRing] = late;
    store(eng_->lateness_count, c + 1);
    if (any) signal();
    {
      // Under the lock: a wake removed and closed is never written (nor its number reused).
      std::lock_guard<std::mutex> g(wake_mutex_);
      const std::uint64_t one = 1;
      for (int fd : wakes_) (void)!write(fd, &one, sizeof(one));  // full (never): woken anyway
    }
  }
}

void FrameLoop::publish(int slot, int frames, double server_time, const double* corners,
                        const double* ball, const double* hips, bool& any) {
  RoomRecord& r = rooms_[slot];
  const size_t k = size_t(slot);
  done_[k] += frames;
  const std::uint32_t v = r.out_lock;
  store(r.out_lock, v + 1);
  fence();
  r.frame += frames;
  r.steps += 1;
  r.server_time = server_time;
  for (int seat = 0; seat < kSeats; ++seat) {
    const size_t a = 4 * k + size_t(seat);
    r.applied_seq[seat] = applied_seq_[a];
    r.applied_time[seat] = applied_time_[a];
    r.applied_occupant[seat] = applied_occupant_[a];
  }
  for (int seat = 0; seat < kSeats; ++seat)
    for (int d = 0; d < 3; ++d) {
      const double p = corners[6 * seat + d];
      r.corner_pos[seat][d] = p;
      r.corner_vel[seat][d] = corners[6 * seat + 3 + d];
      r.hips[seat][d] = hips[3 * seat + d];
      r.force[seat][d] = -cfg_.stiffness * (hips[3 * seat + d] - p);
    }
  std::memcpy(r.ball, ball, sizeof(r.ball));
  for (int seat = 0; seat < kSeats; ++seat)
    encode_corner(r.corner_msg[seat], r.frame, server_time, seat, r.corner_pos[seat],
                  r.corner_vel[seat], r.force[seat], cfg_.stiffness, ball,
                  r.applied_seq[seat], r.applied_time[seat]);
  store(r.out_lock, v + 2);
  std::uint32_t ev = 0;
  if (cfg_.has_ball) {
    if (load(r.armed)) {
      double cp[12];
      for (int seat = 0; seat < kSeats; ++seat)
        for (int d = 0; d < 3; ++d) cp[3 * seat + d] = r.corner_pos[seat][d];
      const int edge = exit_edge(ball, cp, cfg_.floor_y);
      if (edge >= 0) {
        store(r.armed, std::uint32_t(0));
        r.exit_edge = edge;
        r.exit_frame = r.frame;
        for (int d = 0; d < 3; ++d) r.exit_ball[d] = ball[d];
        ev |= kEventExit;
      }
    } else if (ball[1] < cfg_.lost_ball_y) {
      // Nobody is playing and the ball fell off: put it back, keep it bounded.
      const double pv[6] = {cfg_.ball_start[0], cfg_.ball_start[1], cfg_.ball_start[2], 0, 0, 0};
      batch_.at(slot).set_ball(pv);
    }
  }
  if (server_time >= load(r.corner_due)) ev |= kEventCorner;
  if (load(r.recording) && done_[k] >= next_track_[k]) {
    next_track_[k] = done_[k] + cfg_.track_every;
    const std::uint64_t c = r.track_count;
    double* t = r.track[c % kTrackRing];
    t[0] = double(r.frame);
    t[1] = server_time;
    std::memcpy(t + 2, ball, 6 * sizeof(double));
    std::memcpy(t + 8, hips, 12 * sizeof(double));
    for (int seat = 0; seat < kSeats; ++seat)
      for (int d = 0; d < 3; ++d) t[20 + 3 * seat + d] = corners[6 * seat + d];
    store(r.track_count, c + 1);
  }
  if (ev) {
    __atomic_fetch_or(&r.events, ev, __ATOMIC_ACQ_REL);
    any = true;
  }
}

}  // namespace cb::loop
