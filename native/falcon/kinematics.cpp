#include "kinematics.hpp"

#include <algorithm>
#include <cmath>

namespace clothball_falcon {
namespace {
constexpr double kPi = 3.14159265358979323846;
}

double encoder_to_angle(int enc) { return (enc * kDegPerCount + kAngleOffsetDeg) * kPi / 180.0; }
double angle_to_encoder(double rad) { return (rad * 180.0 / kPi - kAngleOffsetDeg) / kDegPerCount; }

bool invert3(const Mat3& m, Mat3& o) {
  const double det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) -
                     m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0]) +
                     m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
  if (!std::isfinite(det) || std::abs(det) < 1e-300) return false;
  const double id = 1.0 / det;
  o[0][0] = (m[1][1] * m[2][2] - m[1][2] * m[2][1]) * id;
  o[0][1] = (m[0][2] * m[2][1] - m[0][1] * m[2][2]) * id;
  o[0][2] = (m[0][1] * m[1][2] - m[0][2] * m[1][1]) * id;
  o[1][0] = (m[1][2] * m[2][0] - m[1][0] * m[2][2]) * id;
  o[1][1] = (m[0][0] * m[2][2] - m[0][2] * m[2][0]) * id;
  o[1][2] = (m[0][2] * m[1][0] - m[0][0] * m[1][2]) * id;
  o[2][0] = (m[1][0] * m[2][1] - m[1][1] * m[2][0]) * id;
  o[2][1] = (m[0][1] * m[2][0] - m[0][0] * m[2][1]) * id;
  o[2][2] = (m[0][0] * m[1][1] - m[0][1] * m[1][0]) * id;
  return true;
}

Kinematics::Kinematics(const Geometry& g) : g_(g) {
  for (int i = 0; i < 3; ++i) {
    const double phi = g.phi_deg[i] * kPi / 180.0;
    cphi_[i] = std::cos(phi);
    sphi_[i] = std::sin(phi);
  }
}

void Kinematics::leg_frame(int i, const Vec3& p, double& u, double& v, double& w) const {
  u = cphi_[i] * p[0] + sphi_[i] * p[1] + g_.c - g_.r;
  v = -sphi_[i] * p[0] + cphi_[i] * p[1] - g_.s;
  w = p[2] + g_.f;
}

bool Kinematics::inverse(const Vec3& p, Vec3& theta) const {
  for (int i = 0; i < 3; ++i) {
    double u, v, w;
    leg_frame(i, p, u, v, w);
    const double A = 2 * g_.a * u, B = 2 * g_.a * w;
    const double C = u * u + v * v + w * w + g_.a * g_.a - g_.b * g_.b;
    const double R = std::hypot(A, B);
    if (!(R > 0) || std::abs(C) > R) return false;
    theta[i] = std::atan2(B, A) - std::acos(C / R);  // knee-out branch
  }
  return true;
}

bool Kinematics::jacobian_inverse(const Vec3& p, const Vec3& theta, Mat3& J) const {
  for (int i = 0; i < 3; ++i) {
    double u, v, w;
    leg_frame(i, p, u, v, w);
    const double ct = std::cos(theta[i]), st = std::sin(theta[i]);
    const double dG_dth = 2 * g_.a * (u * st - w * ct);
    if (std::abs(dG_dth) < 1e-12) return false;
    const double du = 2 * (u - g_.a * ct), dv = 2 * v, dw = 2 * (w - g_.a * st);
    const Vec3 dG_dp = {du * cphi_[i] - dv * sphi_[i], du * sphi_[i] + dv * cphi_[i], dw};
    for (int k = 0; k < 3; ++k) J[i][k] = -dG_dp[k] / dG_dth;
  }
  return true;
}

bool Kinematics::jacobian(const Vec3& p, const Vec3& theta, Mat3& J) const {
  Mat3 Ji;
  return jacobian_inverse(p, theta, Ji) && invert3(Ji, J);
}

bool Kinematics::forward(const Vec3& target, const Vec3& guess, Vec3& p, int max_iter,
                         double tol, int* iterations) const {
  p = guess;
  for (int it = 0; it < max_iter; ++it) {
    Vec3 th, J;
    Mat3 Jm;
    if (!inverse(p, th) || !jacobian(p, th, Jm)) {
      if (iterations) *iterations = it;
      return false;
    }
    double worst = 0;
    Vec3 r;
    for (int i = 0; i < 3; ++i) {
      r[i] = target[i] - th[i];
      worst = std::max(worst, std::abs(r[i]));
    }
    if (worst < tol) {
      if (iterations) *iterations = it;
      return true;
    }
    for (int k = 0; k < 3; ++k) J[k] = Jm[k][0] * r[0] + Jm[k][1] * r[1] + Jm[k][2] * r[2];
    // Newton step; near the edge of the workspace a full step can leave it, so halve the
    // step until every leg can reach the trial point.
    double lam = 1.0;
    Vec3 trial, th_trial;
    bool ok = false;
    for (int h = 0; h < 10 && !ok; ++h, lam *= 0.5) {
      for (int k = 0; k < 3; ++k) trial[k] = p[k] + lam * J[k];
      ok = inverse(trial, th_trial);
    }
    if (!ok) {
      if (iterations) *iterations = it + 1;
      return false;
    }
    p = trial;
  }
  Vec3 th;
  if (iterations) *iterations = max_iter;
  if (!inverse(p, th)) return false;
  // Out of iterations: accept only if the last step brought the residual near tolerance.
  for (int i = 0; i < 3; ++i)
    if (std::abs(target[i] - th[i]) > std::max(tol, 1e-6)) return false;
  return true;
}

bool Kinematics::torques(const Vec3& p, const Vec3& theta, const Vec3& F, Vec3& tau) const {
  Mat3 J;
  if (!jacobian(p, theta, J)) return false;
  for (int j = 0; j < 3; ++j) tau[j] = J[0][j] * F[0] + J[1][j] * F[1] + J[2][j] * F[2];
  return true;
}

bool Kinematics::force_from_torques(const Vec3& p, const Vec3& theta, const Vec3& tau,
                                    Vec3& F) const {
  Mat3 Ji;
  if (!jacobian_inverse(p, theta, Ji)) return false;
  for (int k = 0; k < 3; ++k) F[k] = Ji[0][k] * tau[0] + Ji[1][k] * tau[1] + Ji[2][k] * tau[2];
  return true;
}

std::array<int16_t, 3> torques_to_motors(const Vec3& tau_in, int limit) {
  Vec3 tau = tau_in;
  double m = 0;
  for (double t : tau) m = std::max(m, std::isfinite(t) ? std::abs(t) : 0.0);
  for (double& t : tau) if (!std::isfinite(t)) t = 0;
  if (m > kMaxTorque)
    for (double& t : tau) t *= kMaxTorque / m;
  Vec3 cmd;
  double cm = 0;
  for (int i = 0; i < 3; ++i) {
    cmd[i] = -tau[i] * kMotorPerTorque;
    cm = std::max(cm, std::abs(cmd[i]));
  }
  if (cm > limit)
    for (double& x : cmd) x *= double(limit) / cm;
  std::array<int16_t, 3> out;
  for (int i = 0; i < 3; ++i)
    out[i] = int16_t(std::clamp(std::lround(cmd[i]), -long(limit), long(limit)));
  return out;
}

Vec3 motors_to_torques(const std::array<int16_t, 3>& m) {
  return {-m[0] / kMotorPerTorque, -m[1] / kMotorPerTorque, -m[2] / kMotorPerTorque};
}

}  // namespace clothball_falcon
