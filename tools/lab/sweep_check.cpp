// Lab (not built with the package): a host check of core/sweep.hpp, the sweep that computes
// each spring once. 32 std::threads a warp, the shuffles through a barrier; against
// node_force with only springs, float64, every node of whole cloths and of tiles.
// Build: g++ -std=c++20 -O1 -ffp-contract=off -Inative tools/lab/sweep_check.cpp -pthread
#include <barrier>
#include <cstdio>
#include <random>
#include <thread>
#include <vector>
#include <cmath>
#include "core/sweep.hpp"
using namespace cb;
using R = double;

struct Sim {
  static inline std::barrier<>* bar = nullptr;
  static inline V3<R> buf[32];
  static inline thread_local int lane = 0;
  static V3<R> xch(V3<R> v, int from) {
    buf[lane] = v;
    bar->arrive_and_wait();
    V3<R> r = (from >= 0 && from < 32) ? buf[from] : v;
    bar->arrive_and_wait();
    return r;
  }
  static V3<R> up(V3<R> v, int d) { return xch(v, lane - d); }
  static V3<R> down(V3<R> v, int d) { return xch(v, lane + d); }
};

template <unsigned E>
int check(int n, int i0, int i1, int j0, int j1, int reach, int warps, unsigned seed) {
  Config c; c.n = n; c.rest_len = 0.1; c.node_mass = 1; c.k_struct = 100; c.k_shear = 50; c.k_bend = 20;
  c.struct_compress = 0.3; c.effects = E; c.gravity[1] = 0;
  Params<R> p = Params<R>::from(c);
  std::vector<R> x(n*n), y(n*n), z(n*n);
  std::mt19937 g(seed); std::uniform_real_distribution<R> u(-0.03, 0.03);
  for (int i = 0; i < n; ++i) for (int j = 0; j < n; ++j) { int q=i*n+j; x[q]=j*0.1+u(g); y[q]=u(g); z[q]=i*0.1+u(g);}
  // Mask the nodes outside the window with NaN: reading them spoils the sum.
  const int c0 = std::max(j0 - reach, 0), c1 = std::min(j1 + reach, n);
  const int r0 = std::max(i0 - reach, 0), r1 = std::min(i1 + reach, n);
  std::vector<R> X=x, Y=y, Z=z;
  for (int i = 0; i < n; ++i) for (int j = 0; j < n; ++j) if (i<r0||i>=r1||j<c0||j>=c1) { int q=i*n+j; X[q]=Y[q]=Z[q]=NAN; }
  Planes<R> P{X.data(), Y.data(), Z.data()};
  Planes<R> Pfull{x.data(), y.data(), z.data()};
  SweepRegion rg{i0, i1, j0, j1, c0, c1};
  SweepPlan plan = sweep_plan<E>(rg, warps);
  if (plan.bands == 0) { printf("no plan\n"); return 1; }
  std::vector<V3<R>> got(n*n, V3<R>{NAN,NAN,NAN}); std::vector<int> hits(n*n, 0);
  for (int w = 0; w < warps; ++w) {
    std::barrier<> bar(32); Sim::bar = &bar;
    std::vector<std::thread> th;
    for (int l = 0; l < 32; ++l) th.emplace_back([&, l] {
      Sim::lane = l;
      sweep_region<R, E, Sim>(p, P, rg, plan, w*32 + l, [&](int i, int j, V3<R> f) { got[i*n+j] = f; hits[i*n+j]++; });
    });
    for (auto& t : th) t.join();
  }
  // Reference: node_force with only springs (no gravity, damping, plate, ball, coupling).
  int bad = 0; R worst = 0;
  FrameInputs<R> fin{};
  for (int i = 0; i < n; ++i) for (int j = 0; j < n; ++j) {
    const int q = i*n+j; const bool in = i>=i0&&i<i1&&j>=j0&&j<j1;
    if (hits[q] != (in?1:0)) { if (bad++ < 5) printf("node %d,%d hits %d\n", i, j, hits[q]); continue; }
    if (!in) continue;
    V3<R> contact{};
    V3<R> want = node_force<R, E>(p, Pfull, Pfull, Pfull.get(q), V3<R>{0,0,0}, i, j, fin, V3<R>{0,0,0}, contact);
    R e = std::fabs(want.x-got[q].x)+std::fabs(want.y-got[q].y)+std::fabs(want.z-got[q].z);
    R m = std::fabs(want.x)+std::fabs(want.y)+std::fabs(want.z);
    if (!(e <= 1e-12 * (1 + m))) { if (bad++ < 5) printf("node %d,%d err %g (%g)\n", i, j, e, m); }
    worst = std::max(worst, e);
  }
  printf("E=%u n=%d region [%d,%d)x[%d,%d) warps %d plan v0 %d vw %d bands %d rows %d: bad %d worst %g\n",
         E, n, i0, i1, j0, j1, warps, plan.v0, plan.vw, plan.bands, plan.rows, bad, worst);
  return bad;
}

int main() {
  int bad = 0;
  constexpr unsigned CL = STRUCTURAL, DF = STRUCTURAL | SHEAR | BEND, SH = STRUCTURAL | SHEAR, BO = STRUCTURAL | BEND;
  for (int n : {7, 20, 48, 60}) {
    bad += check<CL>(n, 0, n, 0, n, 1, 16, n);
    bad += check<DF>(n, 0, n, 0, n, 2, 16, n);
    bad += check<SH>(n, 0, n, 0, n, 1, 32, n);
    bad += check<BO>(n, 0, n, 0, n, 2, 8, n);
  }
  // Tiles of a larger cloth: interior, edges, corners, each with its halo only.
  const int n = 100;
  for (auto t : std::vector<std::array<int,4>>{{0,30,0,40},{30,61,40,83},{70,100,60,100},{0,100,45,90},{45,55,0,100}}) {
    bad += check<CL>(n, t[0], t[1], t[2], t[3], 1, 32, 3);
    bad += check<DF>(n, t[0], t[1], t[2], t[3], 2, 32, 3);
    bad += check<SH>(n, t[0], t[1], t[2], t[3], 1, 32, 3);
    bad += check<BO>(n, t[0], t[1], t[2], t[3], 2, 32, 3);
  }
  printf(bad ? "FAILED %d\n" : "all ok\n", bad);
  return bad != 0;
}
