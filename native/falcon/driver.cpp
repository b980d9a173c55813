#include "driver.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/prctl.h>
#include <time.h>

#include <algorithm>
#include <cmath>

#include "errors.hpp"

namespace clothball_falcon {
namespace {

long mono_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return long(ts.tv_sec) * 1000000000L + ts.tv_nsec;
}

void sleep_until_ns(long t) {
  timespec ts{};
  ts.tv_sec = t / 1000000000L;
  ts.tv_nsec = t % 1000000000L;
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

constexpr size_t kPeriodRing = 1 << 16;

}  // namespace

Driver::Driver(std::shared_ptr<Transport> t, const DriverConfig& cfg)
    : transport_(std::move(t)), cfg_(cfg), coupling_(cfg.coupling), epoch_ns_(mono_ns()) {
  if (!transport_) throw FalconError("no transport");
  periods_.reserve(kPeriodRing);
}

Driver::~Driver() {
  try {
    stop();
  } catch (...) {
  }
}

double Driver::now() const { return double(mono_ns() - epoch_ns_) * 1e-9; }

bool Driver::firmware_loaded() {
  if (running()) throw FalconError("stop the loop first");
  normal_mode_ = clothball_falcon::firmware_loaded(*transport_);
  return normal_mode_;
}

int Driver::ensure_firmware(const std::string& path, const FirmwareOptions& opt) {
  if (running()) throw FalconError("stop the loop first");
  normal_mode_ = false;
  if (clothball_falcon::firmware_loaded(*transport_)) {
    normal_mode_ = true;
    return 0;
  }
  const auto image = read_firmware_file(path);
  const int attempts = load_firmware(*transport_, image, opt);
  normal_mode_ = true;
  return attempts;
}

bool Driver::exchange(const HostCommand& cmd, DeviceReport& rep) {
  if (!normal_mode_) {  // a device whose firmware already runs: set the line up once
    enter_normal_mode(*transport_);
    reader_.clear();
    normal_mode_ = true;
  }
  const Packet out = encode_command(cmd);
  transport_->write(out.data(), out.size());
  const long deadline = mono_ns() + long(cfg_.read_timeout_ms) * 1000000L;
  uint8_t buf[64];
  for (;;) {
    while (auto p = reader_.next())
      if (auto r = decode_report(*p)) {
        rep = *r;
        return true;
      }
    const long left_ms = (deadline - mono_ns()) / 1000000L;
    const size_t got = transport_->read(buf, sizeof buf, int(std::max(0L, left_ms)));
    if (got == 0 && mono_ns() >= deadline) return false;
    reader_.feed(buf, got);
  }
}

void Driver::home(double timeout_s) {
  if (running()) throw FalconError("stop the loop first");
  const long start = mono_ns();
  long next = start;
  const long period = long(cfg_.period * 1e9);
  int missed = 0;
  for (;;) {
    HostCommand cmd;
    cmd.flags = kFlagHoming | kFlagBlue;
    DeviceReport rep;
    if (exchange(cmd, rep)) {
      missed = 0;
      std::lock_guard<std::mutex> lock(snap_mu_);
      snap_.homed = rep.homed;
      snap_.buttons = rep.buttons;
      snap_.encoder = rep.encoder;
      if (rep.all_homed()) return;
    } else if (++missed > cfg_.max_missed_replies) {
      throw DeviceGoneError("the Falcon stopped answering during homing: check the USB cable "
                            "and the power supply");
    }
    if (double(mono_ns() - start) * 1e-9 > timeout_s)
      throw HomingTimeoutError(
          "homing timed out after " + std::to_string(int(timeout_s)) +
          " s: pull the Falcon's grip all the way out, then push it all the way in, and run "
          "again (the LED turns from blue to green when homed)");
    next += period;
    if (mono_ns() < next) sleep_until_ns(next);
  }
}

void Driver::set_corner(const Vec3& c, const Vec3& cdot, const Vec3& K, const Vec3& B,
                        double age) {
  set_corner_at(c, cdot, K, B, now() - std::max(0.0, std::isfinite(age) ? age : 1e9));
}

void Driver::set_corner_at(const Vec3& c, const Vec3& cdot, const Vec3& K, const Vec3& B,
                           double received_at) {
  CornerSample s;
  s.position = c;
  s.velocity = cdot;
  s.stiffness = K;
  s.damping = B;
  s.received_at = received_at;
  s.valid = true;
  if (!std::isfinite(received_at)) throw FalconError("corner receive time must be finite");
  for (int i = 0; i < 3; ++i)
    if (!std::isfinite(c[i]) || !std::isfinite(cdot[i]) || !std::isfinite(K[i]) ||
        !std::isfinite(B[i]))
      throw FalconError("corner state must be finite");
  std::lock_guard<std::mutex> lock(corner_mu_);
  corner_ = s;
  corner_dirty_ = true;
}

void Driver::clear_corner() {
  std::lock_guard<std::mutex> lock(corner_mu_);
  corner_.valid = false;
  corner_dirty_ = true;
}

void Driver::set_config(const DriverConfig& cfg) {
  std::lock_guard<std::mutex> lock(corner_mu_);
  pending_cfg_ = cfg;
  cfg_dirty_ = true;
  if (!running()) {
    cfg_ = cfg;
    coupling_.set_config(cfg.coupling);
    cfg_dirty_ = false;
  }
}

DriverConfig Driver::config() const {
  std::lock_guard<std::mutex> lock(corner_mu_);
  return cfg_dirty_ ? pending_cfg_ : cfg_;
}

void Driver::set_force_override(bool on, const Vec3& f) {
  std::lock_guard<std::mutex> lock(corner_mu_);
  override_on_ = on;
  override_force_ = f;
}

void Driver::tick(double now) {
  bool ovr;
  Vec3 ovr_f;
  {
    std::lock_guard<std::mutex> lock(corner_mu_);
    if (corner_dirty_) {
      if (corner_.valid) coupling_.set_corner(corner_);
      else coupling_.clear_corner();
      corner_dirty_ = false;
    }
    if (cfg_dirty_) {
      cfg_ = pending_cfg_;
      coupling_.set_config(cfg_.coupling);
      cfg_dirty_ = false;
    }
    ovr = override_on_;
    ovr_f = override_force_;
  }
  const double dt = last_now_ < 0 ? cfg_.period : std::max(0.0, now - last_now_);
  last_now_ = now;

  HostCommand cmd;
  DeviceReport rep;
  const bool homed_before = snap_.homed == 0x7;
  cmd.motor = homed_before ? motor_ : std::array<int16_t, 3>{0, 0, 0};
  cmd.flags = homed_before ? kFlagGreen : (kFlagHoming | kFlagBlue);
  const bool got = exchange(cmd, rep);
  if (!got) {
    ++missed_;
    {
      std::lock_guard<std::mutex> lock(stats_mu_);
      ++stat_missed_;
    }
    if (missed_ > cfg_.max_missed_replies)
      throw DeviceGoneError("the Falcon stopped answering (" + std::to_string(missed_) +
                            " replies missed): check the USB cable and the power supply");
    return;
  }
  missed_ = 0;
  ++ticks_;
  dropped_.store(reader_.dropped_bytes(), std::memory_order_relaxed);

  Vec3 theta;
  for (int i = 0; i < 3; ++i) theta[i] = encoder_to_angle(rep.encoder[size_t(i)]);
  Vec3 p;
  if (!kin_.forward(theta, p_, p) && !kin_.forward(theta, Vec3{0, 0, 0.125}, p)) p = p_;
  if (ticks_ == 1 || rep.homed != snap_.homed) {
    // First reply, or homing moved the encoder origin: no velocity from the jump.
    p_ = p;
    v_ = {0, 0, 0};
  } else if (dt > 0) {
    const double rc = 1.0 / (2 * M_PI * cfg_.velocity_cutoff_hz);
    const double beta = dt / (rc + dt);
    for (int i = 0; i < 3; ++i) v_[i] += beta * ((p[i] - p_[i]) / dt - v_[i]);
  }
  p_ = p;

  CouplingOutput out = coupling_.compute(now, p_, v_, dt);
  if (ovr) {
    out.force = ovr_f;
    double n = std::sqrt(ovr_f[0] * ovr_f[0] + ovr_f[1] * ovr_f[1] + ovr_f[2] * ovr_f[2]);
    if (n > cfg_.coupling.max_force)
      for (double& f : out.force) f *= cfg_.coupling.max_force / n;
  }
  Vec3 tau{0, 0, 0}, th_p;
  if (rep.all_homed() && kin_.inverse(p_, th_p) && kin_.torques(p_, th_p, out.force, tau))
    motor_ = torques_to_motors(tau);
  else
    motor_ = {0, 0, 0};

  std::lock_guard<std::mutex> lock(snap_mu_);
  snap_.position = p_;
  snap_.velocity = v_;
  snap_.force = rep.all_homed() ? out.force : Vec3{0, 0, 0};
  snap_.corner = out.corner;
  snap_.motor = motor_;
  snap_.encoder = rep.encoder;
  snap_.buttons = rep.buttons;
  snap_.homed = rep.homed;
  snap_.gain = out.gain;
  snap_.alpha = out.alpha;
  snap_.window_energy = out.window_energy;
  snap_.age = out.age;
  snap_.time = now;
  snap_.ticks = ticks_;
}

Snapshot Driver::step(double now) {
  if (running()) throw FalconError("step() while the loop thread runs");
  if (!snap_.error.empty()) throw DeviceGoneError(snap_.error);
  try {
    tick(now);
  } catch (const DeviceGoneError& e) {
    std::lock_guard<std::mutex> lock(snap_mu_);
    snap_.error = e.what();
    throw;
  }
  return snapshot();
}

void Driver::run() {
  prctl(PR_SET_TIMERSLACK, 1000UL, 0, 0, 0);  // 1 us timer slack for this thread
  if (cfg_.realtime) {
    sched_param sp{};
    sp.sched_priority = 10;
    pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);  // fails quietly unprivileged
  }
  const long period = long(cfg_.period * 1e9);
  long next = mono_ns();
  while (!stop_.load(std::memory_order_relaxed)) {
    const long t = mono_ns();
    const double now = double(t - epoch_ns_) * 1e-9;
    {
      std::lock_guard<std::mutex> lock(stats_mu_);
      if (stat_last_ >= 0) {
        const double dtp = now - stat_last_;
        if (periods_.size() < kPeriodRing) periods_.push_back(dtp);
        else periods_[period_next_] = dtp;
        period_next_ = (period_next_ + 1) % kPeriodRing;
        if (dtp > 1.5 * cfg_.period) ++stat_late_;
      } else {
        stat_start_ = now;
      }
      stat_last_ = now;
      ++stat_ticks_;
    }
    try {
      tick(now);
    } catch (const std::exception& e) {
      std::lock_guard<std::mutex> lock(snap_mu_);
      snap_.error = e.what();
      break;
    }
    next += period;
    const long lag = mono_ns() - next;
    if (lag > 5 * period) next = mono_ns();  // fell far behind: do not burst to catch up
    else if (lag < 0) sleep_until_ns(next);
  }
  // Leave the motors off.
  try {
    HostCommand off;
    const Packet pk = encode_command(off);
    if (snapshot().error.empty()) transport_->write(pk.data(), pk.size());
  } catch (...) {
  }
  std::lock_guard<std::mutex> lock(snap_mu_);
  snap_.running = false;
  running_.store(false);
}

void Driver::start() {
  if (running()) return;
  if (thread_.joinable()) thread_.join();
  {
    std::lock_guard<std::mutex> lock(snap_mu_);
    if (!snap_.error.empty()) throw DeviceGoneError(snap_.error);
    snap_.running = true;
  }
  reset_stats();
  stop_.store(false);
  running_.store(true);
  last_now_ = -1;
  thread_ = std::thread([this] { run(); });
}

void Driver::stop() {
  stop_.store(true);
  if (thread_.joinable()) thread_.join();
  running_.store(false);
}

void Driver::close() {
  stop();
  transport_->close();
}

Snapshot Driver::snapshot() const {
  std::lock_guard<std::mutex> lock(snap_mu_);
  Snapshot s = snap_;
  s.running = running();
  return s;
}

void Driver::reset_stats() {
  std::lock_guard<std::mutex> lock(stats_mu_);
  periods_.clear();
  period_next_ = 0;
  stat_ticks_ = stat_missed_ = stat_late_ = 0;
  stat_start_ = stat_last_ = -1;
}

LoopStats Driver::stats() const {
  LoopStats s;
  std::vector<double> p;
  {
    std::lock_guard<std::mutex> lock(stats_mu_);
    p = periods_;
    s.ticks = stat_ticks_;
    s.missed_replies = stat_missed_;
    s.late_ticks = stat_late_;
    s.elapsed = stat_start_ >= 0 ? stat_last_ - stat_start_ : 0;
  }
  s.dropped_bytes = dropped_.load(std::memory_order_relaxed);
  if (s.elapsed > 0 && s.ticks > 1) s.rate = double(s.ticks - 1) / s.elapsed;
  if (!p.empty()) {
    std::sort(p.begin(), p.end());
    double sum = 0;
    for (double x : p) sum += x;
    s.period_mean = sum / double(p.size());
    auto q = [&](double f) { return p[std::min(p.size() - 1, size_t(f * double(p.size())))]; };
    s.period_p50 = q(0.5);
    s.period_p99 = q(0.99);
    s.period_min = p.front();
    s.period_max = p.back();
  }
  return s;
}

}  // namespace clothball_falcon
