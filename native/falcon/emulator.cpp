#include "emulator.hpp"

#include <algorithm>
#include <cmath>

#include "errors.hpp"

namespace clothball_falcon {

EmulatorTransport::EmulatorTransport(const EmulatorOptions& opt)
    : opt_(opt), rng_(opt.seed), mode_(opt.firmware_loaded ? Mode::Running : Mode::Boot),
      handshake_failures_left_(opt.handshake_failures) {
  s_.firmware_loaded = opt.firmware_loaded;
  s_.position = {0, 0, 0.125};
  kin_.inverse(s_.position, theta_);
  // Before homing the encoders count from wherever the device was switched on.
  std::uniform_int_distribution<int> off(-600, 600);
  for (auto& o : home_offset_) o = int16_t(off(rng_));
}

void EmulatorTransport::control(uint8_t request, uint16_t value) {
  std::lock_guard<std::mutex> lock(mu_);
  if (s_.unplugged) throw DeviceGoneError("the emulated Falcon was unplugged");
  switch (request) {
    case ftdi::kReset:
      if (value == ftdi::kPurgeRx) out_.clear();
      if (value == ftdi::kPurgeTx) in_.clear();
      break;
    case ftdi::kModemCtrl:
      if (value == ftdi::kDtrHigh) {
        if (!dtr_) {  // a DTR rising edge resets the microcontroller into its boot loader
          mode_ = Mode::Boot;
          s_.firmware_loaded = false;
          s_.homed = 0;
          homing_packets_ = 0;
          out_.clear();
        }
        dtr_ = true;
      } else if (value == ftdi::kDtrLow) {
        dtr_ = false;
      }
      break;
    case ftdi::kBaudRate:
      baud_ = value;
      if (value == ftdi::kBaudNormal) {
        if (mode_ == Mode::Upload && !upload_.empty() && !corrupt_upload_) {
          s_.firmware_loaded = true;
          s_.uploaded_bytes = upload_.size();
        }
        if (mode_ != Mode::Running && s_.firmware_loaded) mode_ = Mode::Running;
        if (!s_.firmware_loaded) mode_ = Mode::Boot;
      }
      break;
    default:
      break;
  }
}

void EmulatorTransport::queue(const uint8_t* d, size_t n) {
  if (opt_.fragment) {
    // Line noise before the reply: stray bytes, including a lone '>' and a cut-off packet.
    std::uniform_int_distribution<int> pick(0, 3);
    switch (pick(rng_)) {
      case 0: out_.push_back(0x00); out_.push_back(kEnd); break;
      case 1: out_.push_back(kStart); out_.push_back(0x45); out_.push_back(0x46); break;
      case 2: out_.push_back(0x13); break;
      default: break;
    }
  }
  out_.insert(out_.end(), d, d + n);
}

void EmulatorTransport::write(const uint8_t* data, size_t n) {
  std::lock_guard<std::mutex> lock(mu_);
  if (s_.unplugged) throw DeviceGoneError("the emulated Falcon was unplugged");
  switch (mode_) {
    case Mode::Boot: {
      static const uint8_t ask[] = {0x0A, 0x43, 0x0D};
      if (baud_ == ftdi::kBaudFirmware && dtr_ && n == 3 && std::equal(data, data + 3, ask)) {
        ++s_.handshakes;
        if (handshake_failures_left_ > 0) {
          --handshake_failures_left_;
        } else {
          static const uint8_t reply[] = {0x0A, 0x44, 0x2C, 0x0D};
          out_.insert(out_.end(), reply, reply + 4);
          mode_ = Mode::WaitA;
        }
      }
      break;
    }
    case Mode::WaitA:
      if (baud_ == ftdi::kBaudUpload && !dtr_ && n == 1 && data[0] == 0x41) {
        out_.push_back(0x41);
        mode_ = Mode::Upload;
        upload_.clear();
        ++s_.uploads;
        corrupt_upload_ = opt_.rejected_uploads < 0 || s_.uploads <= opt_.rejected_uploads;
      }
      break;
    case Mode::Upload:
      if (baud_ == ftdi::kBaudUpload) {
        const size_t start = out_.size();
        out_.insert(out_.end(), data, data + n);
        // A rejected upload comes back garbled.
        if (corrupt_upload_ && n > 0) out_[start + n / 2] ^= 0x5A;
        upload_.insert(upload_.end(), data, data + n);
      }
      break;
    case Mode::Running:
      if (baud_ == ftdi::kBaudNormal) {
        in_.feed(data, n);
        while (auto p = in_.next()) {
          if (auto c = decode_command(*p)) {
            step_sim(*c);
            DeviceReport r;
            r.encoder = s_.encoder;
            r.buttons = s_.buttons;
            r.homed = s_.homed;
            const Packet reply = encode_report(r);
            queue(reply.data(), reply.size());
          }
        }
      }
      break;
  }
}

size_t EmulatorTransport::read(uint8_t* out, size_t max, int /*timeout_ms*/) {
  std::lock_guard<std::mutex> lock(mu_);
  if (s_.unplugged) throw DeviceGoneError("the emulated Falcon was unplugged");
  size_t n = std::min(max, out_.size());
  if (opt_.fragment && n > 0) {
    std::uniform_int_distribution<size_t> piece(1, 7);
    n = std::min(n, piece(rng_));
  }
  std::copy(out_.begin(), out_.begin() + long(n), out);
  out_.erase(out_.begin(), out_.begin() + long(n));
  return n;
}

void EmulatorTransport::step_sim(const HostCommand& c) {
  ++s_.packets;
  s_.flags = c.flags;
  s_.motor = c.motor;
  if (c.flags & kFlagHoming) {
    ++homing_packets_;
    if (opt_.home_after_packets >= 0 && homing_packets_ >= opt_.home_after_packets)
      s_.homed = 0x7;
  }
  const double dt = opt_.step;
  Vec3 F{};
  kin_.force_from_torques(s_.position, theta_, motors_to_torques(c.motor), F);
  s_.motor_force = F;
  Vec3 p = s_.position, v = s_.velocity;
  for (int k = 0; k < 3; ++k) {
    const double user = user_k_ * (user_target_[k] - p[k]) - user_b_ * v[k];
    const double acc = (F[k] + user - opt_.hand_damping * v[k]) / opt_.hand_mass;
    v[k] += acc * dt;  // semi-implicit Euler
    p[k] += v[k] * dt;
  }
  // The mechanism's end stops: a box a little larger than the usable cube.
  const Vec3 lo = {-0.055, -0.055, 0.075}, hi = {0.055, 0.055, 0.175};
  for (int k = 0; k < 3; ++k)
    if (p[k] < lo[k] || p[k] > hi[k]) {
      p[k] = std::clamp(p[k], lo[k], hi[k]);
      v[k] = 0;
    }
  Vec3 th;
  if (kin_.inverse(p, th)) {
    s_.position = p;
    s_.velocity = v;
    theta_ = th;
  } else {
    s_.velocity = {0, 0, 0};
  }
  for (int i = 0; i < 3; ++i) {
    long enc = std::lround(angle_to_encoder(theta_[i]));
    if ((s_.homed >> i & 1) == 0) enc += home_offset_[size_t(i)];
    s_.encoder[size_t(i)] = int16_t(std::clamp(enc, -32768L, 32767L));
  }
}

void EmulatorTransport::set_user(const Vec3& target, double stiffness, double damping) {
  std::lock_guard<std::mutex> lock(mu_);
  user_target_ = target;
  user_k_ = std::max(0.0, stiffness);
  user_b_ = std::max(0.0, damping);
}

void EmulatorTransport::set_position(const Vec3& p) {
  std::lock_guard<std::mutex> lock(mu_);
  Vec3 th;
  if (!kin_.inverse(p, th)) throw FalconError("position out of the Falcon's reach");
  s_.position = p;
  s_.velocity = {0, 0, 0};
  theta_ = th;
}

void EmulatorTransport::set_buttons(uint8_t b) {
  std::lock_guard<std::mutex> lock(mu_);
  s_.buttons = b & 0xF;
}

void EmulatorTransport::unplug() {
  std::lock_guard<std::mutex> lock(mu_);
  s_.unplugged = true;
}

EmulatorState EmulatorTransport::state() const {
  std::lock_guard<std::mutex> lock(mu_);
  return s_;
}

std::vector<uint8_t> EmulatorTransport::uploaded() const {
  std::lock_guard<std::mutex> lock(mu_);
  return upload_;
}

}  // namespace clothball_falcon
