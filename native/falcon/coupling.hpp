// The local haptic law, evaluated every tick of the 1 kHz loop (device frame, SI units):
//
//   c_ext = c + c_dot * min(age, max_extrapolation)           (age of the corner sample)
//   F     = g(age) * ( -K (h - c_ext) - B (h_dot - c_dot) )  - alpha * h_dot
//
// g fades linearly-in-time (through a smoothstep) to 0 over fade_out once the sample is
// older than stale_after, and back to 1 over fade_in once fresh samples arrive, so the
// spring never snaps. alpha is the time-domain passivity controller. Seen from the hand,
// the coupling and everything behind it (network, server, cloth) should be passive: it may
// give back only energy the hand put in. The observer sums over a short window
//   e_k = (U_k - U_{k-1}) + F_c . h_dot dt,   U = 1/2 sum_i g K_i x_i^2,  x = h - c_ext
// (energy that appeared in the spring or went out to the hand without the hand doing the
// work: zero for an ideal spring to a still corner, negative for a damper, positive when
// the delayed corner, extrapolation error or a rising gain pump energy in). When the window
// total is positive, alpha damps the hand just enough to dissipate it this tick (bounded),
// and the dissipation is credited back to the window. Energy the cloth really puts in (a
// ball tugging the corner) is damped as well: the price of an observer that sees only the
// local side (the protocol carries no energy budget), bounded by max_passivity_damping.
#pragma once
#include <deque>
#include <utility>

#include "kinematics.hpp"

namespace clothball_falcon {

struct CouplingConfig {
  double stale_after = 0.100;        // s: samples older than this fade the coupling out
  double fade_out = 0.050;           // s: gain 1 -> 0 once stale
  double fade_in = 0.250;            // s: gain 0 -> 1 once fresh
  double max_extrapolation = 0.100;  // s: c is extrapolated by c_dot for at most this long
  double max_stiffness = 3000.0;     // N/m, per axis (the Falcon's upper end at 1 kHz)
  double max_damping = 20.0;         // N s/m, per axis
  double max_force = 8.0;            // N, norm of the rendered force
  // Optional low-pass on the received corner velocity (used by the extrapolation and the
  // damper); 0 = off, the default. The server's corner velocity jitters (a light node
  // pulled by HIPs that arrive at irregular times), but the filter's lag makes the
  // delayed coupling less stable (tests/test_falcon_coupling.py), so it is opt-in.
  double corner_velocity_cutoff_hz = 0.0;
  bool passivity = true;
  double passivity_window = 0.050;   // s
  double max_passivity_damping = 20.0;  // N s/m
};

struct CornerSample {
  Vec3 position{}, velocity{};  // device frame
  Vec3 stiffness{}, damping{};  // per axis, device frame
  double received_at = 0;       // driver clock, s
  bool valid = false;
};

struct CouplingOutput {
  Vec3 force{};          // N on the grip (after the passivity damper and the force cap)
  Vec3 corner{};         // c_ext
  double gain = 0;       // smoothstepped fade factor in [0, 1]
  double age = 0;        // s; -1 without a corner sample
  double alpha = 0;      // passivity damping this tick, N s/m
  double window_energy = 0;  // J generated over the observer window (before alpha)
  bool clamped = false;
};

class Coupling {
 public:
  explicit Coupling(const CouplingConfig& cfg = CouplingConfig()) : cfg_(cfg) {}
  void set_corner(const CornerSample& s);
  void clear_corner() { corner_.valid = false; }
  // One tick at time `now` with hand position/velocity; dt = time since the last tick.
  CouplingOutput compute(double now, const Vec3& h, const Vec3& hdot, double dt);
  void reset();
  const CouplingConfig& config() const { return cfg_; }
  void set_config(const CouplingConfig& c) { cfg_ = c; }
  double raw_gain() const { return g_; }
  double total_generated() const { return total_generated_; }
  double total_dissipated() const { return total_dissipated_; }

 private:
  CouplingConfig cfg_;
  CornerSample corner_;
  Vec3 cdot_f_{};        // low-passed corner velocity
  bool have_cdot_ = false;
  double g_ = 0;        // fade state before smoothstep
  double prev_U_ = 0;
  bool have_prev_ = false;
  std::deque<std::pair<double, double>> window_;  // (time, energy)
  double window_sum_ = 0;
  double total_generated_ = 0, total_dissipated_ = 0;
};

}  // namespace clothball_falcon
