// The ball's exit, checked by the frame loop every frame for every room: the same answer as
// clothball.game.rules.exit_edge (its formulas step for step, in the same order; tested
// against it in tests/server/test_frame_loop.py). Plain C++, no pybind11. Compiled without
// fused multiply-adds so that each product rounds as NumPy's does.
#pragma once
#include <cmath>

namespace cb::loop {

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC push_options
#pragma GCC optimize("fp-contract=off")
#endif

// Signed distance (m, seen from above) of the ball's centre outside each edge's line;
// positive: outside the corners' quadrilateral across that edge (rules.edge_distances).
// corners: 4 x 3 (x, y, z); ball: x, y, z.
inline void edge_distances(const double* ball, const double* corners, double out[4]) {
  double cx[4], cz[4];
  for (int k = 0; k < 4; ++k) {
    cx[k] = corners[3 * k];
    cz[k] = corners[3 * k + 2];
  }
  const double mx = (((cx[0] + cx[1]) + cx[2]) + cx[3]) / 4.0;
  const double mz = (((cz[0] + cz[1]) + cz[2]) + cz[3]) / 4.0;
  const double px = ball[0], pz = ball[2];
  for (int e = 0; e < 4; ++e) {
    const int f = (e + 1) % 4;
    const double ax = cx[e], az = cz[e];
    const double dx = cx[f] - ax, dz = cz[f] - az;
    const double length = std::sqrt(dx * dx + dz * dz);  // as rules.py: not hypot
    double nx, nz;
    if (length < 1e-12) {
      nx = ax - mx;
      nz = az - mz;
      const double nl = std::sqrt(nx * nx + nz * nz);
      if (nl > 1e-12) {
        nx /= nl;
        nz /= nl;
      } else {
        nx = 1.0;
        nz = 0.0;
      }
    } else {
      nx = dz / length;
      nz = -dx / length;
      if (nx * (ax - mx) + nz * (az - mz) < 0.0) {
        nx = -nx;
        nz = -nz;
      }
    }
    out[e] = (px - ax) * nx + (pz - az) * nz;
  }
}

// Height of edge e's corner-to-corner line where the ball's centre projects onto it.
inline double edge_height(const double* ball, const double* corners, int e) {
  const double* a = corners + 3 * e;
  const double* b = corners + 3 * ((e + 1) % 4);
  const double dx = b[0] - a[0], dz = b[2] - a[2];
  const double dd = dx * dx + dz * dz;
  double t = dd < 1e-24 ? 0.0 : ((ball[0] - a[0]) * dx + (ball[2] - a[2]) * dz) / dd;
  t = std::fmin(1.0, std::fmax(0.0, t));
  return a[1] + t * (b[1] - a[1]);
}

// The edge (0..3) the ball has left the cloth by, or -1 while it is in play: past an edge's
// line and below its height (the farthest such edge), else below the floor (the farthest
// edge; the first NaN distance, as NumPy's argmax).
inline int exit_edge(const double* ball, const double* corners, double floor_y) {
  double dist[4];
  edge_distances(ball, corners, dist);
  int best = -1;
  for (int e = 0; e < 4; ++e)
    if (dist[e] > 0.0 && ball[1] < edge_height(ball, corners, e) &&
        (best < 0 || dist[e] > dist[best]))
      best = e;
  if (best >= 0) return best;
  if (ball[1] < floor_y) {
    int arg = 0;
    for (int e = 0; e < 4; ++e) {
      if (std::isnan(dist[e])) return e;
      if (dist[e] > dist[arg]) arg = e;
    }
    return arg;
  }
  return -1;
}

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC pop_options
#endif

}  // namespace cb::loop
