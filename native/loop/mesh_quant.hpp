// A MESH's quantisation and row deltas (docs/protocol.md, MESH), as
// game.wire.protocol.quantise and encode_mesh compute them with NumPy: the same operations
// in the same order on doubles, so the same bits (but for a bound of zero, +0 here where
// NumPy's min or max may keep a -0: the same value). The unit that includes this is compiled
// without floating-point contraction (native/CMakeLists.txt): a fused multiply-add would
// round (p - lo) * scale + 0.5 once where NumPy rounds twice. For finite positions (the
// frame loop's: a non-finite room is stopped before its mesh is gathered).
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>

namespace cb::loop {

constexpr double kMeshQMax = 65535.0;  // protocol.QMAX

// p: n * n nodes, 3 doubles each (row-major (n, n, 3)). Writes q and delta (n * n * 3
// each; delta along each row: a row's first node as it is, each next one minus the one
// before, wrapping as uint16) and the box lo, hi (3 each).
inline void quantise_mesh(const double* p, int n, std::uint16_t* q, std::uint16_t* delta,
                          double* lo, double* hi) {
  const size_t nodes = size_t(n) * size_t(n);
  double mn[3] = {p[0], p[1], p[2]}, mx[3] = {p[0], p[1], p[2]};
  for (size_t k = 1; k < nodes; ++k)
    for (int d = 0; d < 3; ++d) {
      const double v = p[3 * k + size_t(d)];
      mn[d] = v < mn[d] ? v : mn[d];
      mx[d] = v > mx[d] ? v : mx[d];
    }
  double scale[3];
  for (int d = 0; d < 3; ++d) {
    // The box in float32 (the protocol sends a float32 per bound); + 0.0 makes a -0 +0.
    lo[d] = double(float(mn[d])) + 0.0;
    hi[d] = std::max(double(float(mx[d])), lo[d]) + 0.0;
    const double span = hi[d] - lo[d];
    scale[d] = span > 0.0 ? kMeshQMax / span : 0.0;
  }
  for (size_t k = 0; k < nodes; ++k)
    for (int d = 0; d < 3; ++d) {
      double x = (p[3 * k + size_t(d)] - lo[d]) * scale[d];
      x += 0.5;  // round half up
      x = x < 0.0 ? 0.0 : (x > kMeshQMax ? kMeshQMax : x);
      q[3 * k + size_t(d)] = std::uint16_t(x);
    }
  for (int i = 0; i < n; ++i) {
    const size_t row = 3 * size_t(i) * size_t(n);
    for (int d = 0; d < 3; ++d) delta[row + size_t(d)] = q[row + size_t(d)];
    for (size_t c = 3; c < 3 * size_t(n); ++c)
      delta[row + c] = std::uint16_t(q[row + c] - q[row + c - 3]);
  }
}

}  // namespace cb::loop
