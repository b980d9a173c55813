#include "coupling.hpp"

#include <algorithm>
#include <cmath>

namespace clothball_falcon {

void Coupling::set_corner(const CornerSample& s) {
  const double fc = cfg_.corner_velocity_cutoff_hz;
  if (!have_cdot_ || !corner_.valid || fc <= 0) {
    cdot_f_ = s.velocity;
  } else {
    const double dt = std::clamp(s.received_at - corner_.received_at, 0.0, 1.0);
    const double tau = 1.0 / (2 * M_PI * fc);
    const double beta = dt / (tau + dt);
    for (int i = 0; i < 3; ++i) cdot_f_[i] += beta * (s.velocity[i] - cdot_f_[i]);
  }
  have_cdot_ = true;
  corner_ = s;
}

void Coupling::reset() {
  have_cdot_ = false;
  g_ = 0;
  prev_U_ = 0;
  have_prev_ = false;
  window_.clear();
  window_sum_ = 0;
  total_generated_ = total_dissipated_ = 0;
}

CouplingOutput Coupling::compute(double now, const Vec3& h, const Vec3& hdot, double dt) {
  CouplingOutput out;
  dt = std::isfinite(dt) ? std::clamp(dt, 0.0, 0.1) : 0.0;
  const bool valid = corner_.valid;
  const double age = valid ? std::max(0.0, now - corner_.received_at) : -1.0;
  out.age = age;
  const bool fresh = valid && age <= cfg_.stale_after;
  // Fade state: ramps at constant rates towards 1 (fresh) or 0 (stale or none).
  if (fresh)
    g_ = cfg_.fade_in > 0 ? std::min(1.0, g_ + dt / cfg_.fade_in) : 1.0;
  else
    g_ = cfg_.fade_out > 0 ? std::max(0.0, g_ - dt / cfg_.fade_out) : 0.0;
  const double g = g_ * g_ * (3 - 2 * g_);  // smoothstep: no kink at either end
  out.gain = g;

  Vec3 Fc{0, 0, 0};
  double U = 0, P_hand = 0;
  if (valid) {
    const double te = std::min(age, cfg_.max_extrapolation);
    for (int i = 0; i < 3; ++i) {
      const double K = std::clamp(corner_.stiffness[i], 0.0, cfg_.max_stiffness) * g;
      const double B = std::clamp(corner_.damping[i], 0.0, cfg_.max_damping) * g;
      const double c = corner_.position[i] + cdot_f_[i] * te;
      out.corner[i] = c;
      const double x = h[i] - c, xd = hdot[i] - cdot_f_[i];
      Fc[i] = -K * x - B * xd;
      if (!std::isfinite(Fc[i])) Fc[i] = 0;
      U += 0.5 * K * x * x;
      P_hand += Fc[i] * hdot[i];
    }
  }

  // Passivity observer over the window, then the controller.
  double alpha = 0;
  if (have_prev_ && dt > 0) {
    const double e = (U - prev_U_) + P_hand * dt;
    if (e > 0) total_generated_ += e;
    window_.emplace_back(now, e);
    window_sum_ += e;
  }
  while (!window_.empty() && window_.front().first <= now - cfg_.passivity_window) {
    window_sum_ -= window_.front().second;
    window_.pop_front();
  }
  out.window_energy = window_sum_;
  if (cfg_.passivity && window_sum_ > 0 && dt > 0) {
    const double v2 = hdot[0] * hdot[0] + hdot[1] * hdot[1] + hdot[2] * hdot[2];
    if (v2 > 1e-12) {
      alpha = std::min(window_sum_ / (dt * v2), cfg_.max_passivity_damping);
      const double dissipated = alpha * v2 * dt;
      total_dissipated_ += dissipated;
      window_sum_ -= dissipated;
      if (!window_.empty()) window_.back().second -= dissipated;
    }
  }
  out.alpha = alpha;
  prev_U_ = U;
  have_prev_ = true;

  Vec3 F;
  double n2 = 0;
  for (int i = 0; i < 3; ++i) {
    F[i] = Fc[i] - alpha * hdot[i];
    n2 += F[i] * F[i];
  }
  const double n = std::sqrt(n2);
  if (n > cfg_.max_force) {
    for (double& f : F) f *= cfg_.max_force / n;
    out.clamped = true;
  }
  out.force = F;
  return out;
}

}  // namespace clothball_falcon
