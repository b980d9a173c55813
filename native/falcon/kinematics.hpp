// Delta-robot kinematics of the Novint Falcon (R. E. Stamper's parameter set).
//
// Device frame: x right, y up, z along the device axis, growing as the grip is pulled out
// (metres). Leg i is rotated by phi_i = {90, -30, -150} + 15 degrees about z. In the leg's
// frame the grip point is
//     u =  cos(phi) x + sin(phi) y + c - r      (radial, from the hip axis)
//     v = -sin(phi) x + cos(phi) y - s          (along the hip axis)
//     w =  z + f                                (along the device axis)
// The thigh (length a) turns by theta about the hip axis, so the knee sits at
// (a cos theta, 0, a sin theta); the parallelogram (length b, offsets d = e at both ends,
// which cancel) joins knee and grip: |(u, v, w) - knee|^2 = b^2. That gives, per leg,
//     A cos theta + B sin theta = C,  A = 2 a u, B = 2 a w, C = u^2 + v^2 + w^2 + a^2 - b^2
// solved in closed form (knee-out branch). The forward kinematics runs Newton-Raphson on
// the inverse, the Jacobian comes from implicit differentiation of the leg constraints,
// and joint torques are tau = J^T F (virtual work) with J = d p / d theta.
#pragma once
#include <array>
#include <cstdint>

namespace clothball_falcon {

using Vec3 = std::array<double, 3>;
using Mat3 = std::array<Vec3, 3>;  // row-major: m[row][col]

struct Geometry {
  double a = 0.060, b = 0.1025, c = 0.01443, d = 0.01125, e = 0.01125, f = -0.025;
  double r = 0.0400, s = -0.02309;
  double phi_deg[3] = {90.0 + 15.0, -30.0 + 15.0, -150.0 + 15.0};
};

// The usable cube the game maps onto a corner's reach (metres, device frame).
constexpr double kCubeHalfXY = 0.03;
constexpr double kCubeZMin = 0.095;
constexpr double kCubeZMax = 0.155;

// Encoder counts <-> thigh angle: theta_deg = enc * (pi 0.01425 / (320 * 4)) /
// (pi 0.110 / 360) + 35.
constexpr double kDegPerCount = (0.01425 / (320.0 * 4.0)) / (0.110 / 360.0);
constexpr double kAngleOffsetDeg = 35.0;

double encoder_to_angle(int enc);     // radians
double angle_to_encoder(double rad);  // counts, not rounded

// Motor command units: command = -tau * kMotorPerTorque, torque tau in N m.
constexpr double kMotorPerTorque = 10000.0;
constexpr double kMaxTorque = 30.0;   // |tau| above this scales all three down
constexpr int kMotorLimit = 4096;     // documented firmware cap on |command|

class Kinematics {
 public:
  explicit Kinematics(const Geometry& g = Geometry());

  // Closed-form inverse kinematics. False when p is out of reach of some leg.
  bool inverse(const Vec3& p, Vec3& theta) const;
  // Newton-Raphson on the inverse, warm-started from `guess`; at most max_iter iterations,
  // stops when the largest angle residual is below tol (radians). False when it fails.
  bool forward(const Vec3& theta, const Vec3& guess, Vec3& p, int max_iter = 15,
               double tol = 1e-10, int* iterations = nullptr) const;
  // d theta / d p at (p, theta = inverse(p)); false at a singular leg.
  bool jacobian_inverse(const Vec3& p, const Vec3& theta, Mat3& dtheta_dp) const;
  // d p / d theta (the inverse of the above).
  bool jacobian(const Vec3& p, const Vec3& theta, Mat3& dp_dtheta) const;

  // Joint torques for a Cartesian force on the grip: tau = J^T F.
  bool torques(const Vec3& p, const Vec3& theta, const Vec3& force, Vec3& tau) const;
  // The Cartesian force that joint torques produce on the grip: F = (J^-1)^T tau.
  bool force_from_torques(const Vec3& p, const Vec3& theta, const Vec3& tau, Vec3& force) const;

  const Geometry& geometry() const { return g_; }

 private:
  Geometry g_;
  double cphi_[3], sphi_[3];
  void leg_frame(int i, const Vec3& p, double& u, double& v, double& w) const;
};

// Torques -> motor commands: if max |tau| > kMaxTorque all three are scaled down; then
// command = -tau * kMotorPerTorque, scaled (all three together, keeping the direction) so
// that max |command| <= limit, and finally clamped to [-limit, limit] as a last guard.
std::array<int16_t, 3> torques_to_motors(const Vec3& tau, int limit = kMotorLimit);
// Motor commands -> torques (what the emulator's motors apply).
Vec3 motors_to_torques(const std::array<int16_t, 3>& motor);

bool invert3(const Mat3& m, Mat3& out);

}  // namespace clothball_falcon
