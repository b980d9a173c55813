// A Falcon that lives in memory: answers the firmware handshake, echoes the upload, then
// simulates the delta arm (hand position -> inverse kinematics -> encoder counts; motor
// commands -> joint torques -> grip force moving a hand with mass and damping). Each host
// packet advances the simulation by one fixed step (1 ms), as the real device answers
// lock-step; a scripted "user" spring can hold the grip.
#pragma once
#include <deque>
#include <mutex>
#include <random>

#include "codec.hpp"
#include "kinematics.hpp"
#include "transport.hpp"

namespace clothball_falcon {

struct EmulatorOptions {
  bool firmware_loaded = false;  // already running firmware at start
  int handshake_failures = 0;    // ignore this many handshake requests before answering
  int rejected_uploads = 0;      // corrupt the echo of this many uploads (-1: all)
  int home_after_packets = 200;  // homing completes after this many homing packets (-1: never)
  bool fragment = false;         // hand out replies in small pieces, with line noise between
  double step = 1e-3;            // simulated seconds per packet
  double hand_mass = 0.15;       // kg: grip, arms and a relaxed hand
  double hand_damping = 1.0;     // N s / m
  unsigned seed = 1;
};

struct EmulatorState {
  Vec3 position{}, velocity{};
  Vec3 motor_force{};  // force the motors put on the grip (N)
  std::array<int16_t, 3> motor{0, 0, 0};
  std::array<int16_t, 3> encoder{0, 0, 0};
  uint8_t flags = 0, buttons = 0, homed = 0;
  bool firmware_loaded = false, unplugged = false;
  long packets = 0, handshakes = 0, uploads = 0;
  size_t uploaded_bytes = 0;
};

class EmulatorTransport final : public Transport {
 public:
  explicit EmulatorTransport(const EmulatorOptions& opt = EmulatorOptions());

  void control(uint8_t request, uint16_t value) override;
  void write(const uint8_t* data, size_t n) override;
  size_t read(uint8_t* out, size_t max, int timeout_ms) override;
  std::string describe() const override { return "emulated Novint Falcon"; }

  // Scripted user: a spring-damper pulling the grip towards `target` (stiffness 0: let go).
  void set_user(const Vec3& target, double stiffness, double damping);
  void set_position(const Vec3& p);  // teleport the grip (velocity zeroed)
  void set_buttons(uint8_t b);
  void unplug();
  EmulatorState state() const;
  // Uploaded image (for tests comparing with the file).
  std::vector<uint8_t> uploaded() const;

 private:
  enum class Mode { Boot, WaitA, Upload, Running };
  void step_sim(const HostCommand& c);
  void queue(const uint8_t* d, size_t n);

  EmulatorOptions opt_;
  Kinematics kin_;
  mutable std::mutex mu_;
  std::mt19937 rng_;
  Mode mode_;
  uint16_t baud_ = 0;
  bool dtr_ = false;
  bool corrupt_upload_ = false;
  int handshake_failures_left_;
  std::deque<uint8_t> out_;
  PacketReader in_;
  std::vector<uint8_t> upload_;
  EmulatorState s_;
  Vec3 theta_{};
  Vec3 user_target_{0, 0, 0.125};
  double user_k_ = 0, user_b_ = 0;
  long homing_packets_ = 0;
  std::array<int16_t, 3> home_offset_{};
};

}  // namespace clothball_falcon
