// The Falcon driver: firmware, homing and the 1 kHz I/O thread that renders the coupling
// force locally. One tick = write one command packet, read one report, forward kinematics,
// velocity estimate, coupling force, Jacobian-transpose torques, motor commands (sent on
// the next tick). The same tick runs on a thread (start/stop) or stepped by hand with a
// scripted clock (step), which is how the tests drive it deterministically.
#pragma once
#include <atomic>
#include <memory>
#include <mutex>
#include <string>
#include <thread>
#include <vector>

#include "codec.hpp"
#include "coupling.hpp"
#include "firmware.hpp"
#include "kinematics.hpp"
#include "transport.hpp"

namespace clothball_falcon {

struct DriverConfig {
  CouplingConfig coupling;
  double period = 1e-3;             // s, loop period
  double velocity_cutoff_hz = 40;   // low-pass on the finite-difference velocity
  int read_timeout_ms = 20;         // per reply
  int max_missed_replies = 100;     // consecutive; then the device counts as gone
  bool realtime = true;             // try SCHED_FIFO (ignored when not permitted)
};

struct Snapshot {
  Vec3 position{0, 0, 0.125}, velocity{}, force{}, corner{};
  std::array<int16_t, 3> motor{0, 0, 0}, encoder{0, 0, 0};
  uint8_t buttons = 0, homed = 0;
  double gain = 0, alpha = 0, window_energy = 0, age = -1, time = 0;
  long ticks = 0;
  bool running = false;
  std::string error;  // non-empty once the device is gone
};

struct LoopStats {
  long ticks = 0, missed_replies = 0, late_ticks = 0;
  double elapsed = 0, rate = 0;
  double period_mean = 0, period_p50 = 0, period_p99 = 0, period_max = 0, period_min = 0;
  size_t dropped_bytes = 0;
};

class Driver {
 public:
  Driver(std::shared_ptr<Transport> t, const DriverConfig& cfg = DriverConfig());
  ~Driver();
  Driver(const Driver&) = delete;
  Driver& operator=(const Driver&) = delete;

  // Setup (blocking, not while the loop runs).
  bool firmware_loaded();
  // Loads the firmware when it is not running yet; returns the attempts used (0: already).
  int ensure_firmware(const std::string& path, const FirmwareOptions& opt);
  // Homing mode until all three homed bits are set; HomingTimeoutError after timeout_s.
  void home(double timeout_s);

  void start();
  void stop();
  bool running() const { return running_.load(); }

  // Latest corner state, device frame; `age` = seconds since it was received.
  void set_corner(const Vec3& c, const Vec3& cdot, const Vec3& K, const Vec3& B, double age);
  // The same with the receive time on the driver clock (scripted clocks in tests).
  void set_corner_at(const Vec3& c, const Vec3& cdot, const Vec3& K, const Vec3& B,
                     double received_at);
  void clear_corner();
  void set_config(const DriverConfig& cfg);
  DriverConfig config() const;

  // One tick at scripted time `now` (seconds; only while the thread is stopped).
  Snapshot step(double now);
  // Force override for tests and `check`: render this force (device frame) instead.
  void set_force_override(bool on, const Vec3& f);

  Snapshot snapshot() const;
  LoopStats stats() const;
  void reset_stats();
  double now() const;  // driver clock, s
  std::string describe() const { return transport_->describe(); }
  void close();

 private:
  void tick(double now);
  void run();
  bool exchange(const HostCommand& cmd, DeviceReport& rep);

  std::shared_ptr<Transport> transport_;
  DriverConfig cfg_;
  Kinematics kin_;
  Coupling coupling_;
  PacketReader reader_;

  mutable std::mutex corner_mu_;  // corner_ and cfg_ changes from other threads
  CornerSample corner_;
  bool corner_dirty_ = false;
  bool cfg_dirty_ = false;
  DriverConfig pending_cfg_;
  bool override_on_ = false;
  Vec3 override_force_{};

  mutable std::mutex snap_mu_;
  Snapshot snap_;

  // Loop state (loop thread only).
  Vec3 p_{0, 0, 0.125}, v_{};
  double last_now_ = -1;
  std::array<int16_t, 3> motor_{0, 0, 0};
  int missed_ = 0;
  bool normal_mode_ = false;
  long ticks_ = 0;

  // Statistics.
  mutable std::mutex stats_mu_;
  std::vector<double> periods_;  // ring buffer
  size_t period_next_ = 0;
  long stat_ticks_ = 0, stat_missed_ = 0, stat_late_ = 0;
  double stat_start_ = -1, stat_last_ = -1;

  std::atomic<size_t> dropped_{0};
  std::atomic<bool> running_{false};
  std::atomic<bool> stop_{false};
  std::thread thread_;
  long epoch_ns_;
};

}  // namespace clothball_falcon
