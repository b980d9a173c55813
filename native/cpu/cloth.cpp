// CPU backend: the shared core stepped by OpenMP threads over rows. Compiled once per real
// type (CB_REAL is float or double) and part: the effect sets' frame loops are shared among
// CB_PARTS objects that compile in parallel, part k holding the sets E with
// E % CB_PARTS == k; part 0 also holds the backend itself (see native/CMakeLists.txt).
#include <omp.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <stdexcept>
#include <utility>
#include <vector>

#include "core/backend.hpp"
#include "core/forces.hpp"
#include "cpu/integrators.hpp"

#ifndef CB_PARTS
#define CB_PARTS 1
#define CB_PART 0
#endif

namespace cb {
// Named, not anonymous: the parts of this unit define the same class and meet in its table.
namespace cpu {

template <class R>
class CpuCloth;

template <class R>
using FramesFn = void (*)(CpuCloth<R>&, int, int, R);
template <class R>
using FramesTable = std::array<FramesFn<R>, kNumEffectSets>;

// Fills the entries of part `Part` (one specialisation per part object).
template <class R, int Part>
void fill_frames(FramesTable<R>& t);

template <class R>
class CpuCloth final : public Backend {
 public:
  // The vectors' length in the sweep's loops (GCC's choice on x86-64): the inner rows'
  // interior nodes go in blocks of whole vectors.
#if defined(__AVX512F__)
  static constexpr int kVec = 64 / sizeof(R);
#else
  static constexpr int kVec = 32 / sizeof(R);
#endif
  // Planes are spaced by a stride that is not a multiple of 4 KiB: at n = 64 the twelve
  // streams of a substep would otherwise fall into the same L1 sets and evict each other
  // (measured: 10x slower). A buffer has two rows or more of padding before its first plane
  // and after its last: the border loops read (and discard) neighbours beyond the grid.
  explicit CpuCloth(const Config& c)
      : N_(c.n * c.n), stride_((size_t(N_) + 15) / 16 * 16 + 16),
        pad_((2 * size_t(c.n) + 15) / 16 * 16) {
    for (auto& b : buf_) b.assign(2 * pad_ + 6 * stride_ + 16 * 6, R(0));
    configure(c);
  }

  void configure(const Config& c) override {
    if (c.n * c.n != N_) throw std::invalid_argument("configure: n cannot change");
    cfg_ = c;
    p_ = Params<R>::from(c);
    frames_ = table()[c.effects & (kNumEffectSets - 1)];
    strain_sweeps_ = strain_sweeps(c);
    threads_ = c.threads > 0 ? c.threads : omp_get_max_threads();
    contact_on_ = true;
    alt_ = make_cpu_integrator<R>(c);  // velocity Verlet, implicit Euler (their own units)
    // The border loops' table of the grips (PaddedPlanes): grip_node's values on the edges.
    grip_.assign(7 * size_t(N_), R(0));
    held_.clear();
    const int n = c.n;
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j) {
        if (!(c.effects & COUPLING) || !(i == 0 || i == n - 1 || j == 0 || j == n - 1)) continue;
        const GripNode<R> g = grip_node(p_, i, j);
        if (g.corner < 0) continue;
        const int q = i * n + j;
        grip_[q] = g.k;
        grip_view().grip_offset.set(q, g.offset);
        held_.push_back({q, g.corner});
      }
    set_grip_hips();
  }
  unsigned compiled_effects() const override {
    return compiled_effect_set(cfg_);
  }

  void set_hips(const double* h) override {
    for (int k = 0; k < 4; ++k) fin_.hips[k] = {R(h[3 * k]), R(h[3 * k + 1]), R(h[3 * k + 2])};
    set_grip_hips();
  }
  void set_wind(const double* w) override { fin_.wind = {R(w[0]), R(w[1]), R(w[2])}; }

  void set_state(const double* pos, const double* vel) override {
    Planes<R> P = pos_(cur_), V = vel_(cur_);
    for (int q = 0; q < N_; ++q) {
      P.set(q, {R(pos[3 * q]), R(pos[3 * q + 1]), R(pos[3 * q + 2])});
      V.set(q, {R(vel[3 * q]), R(vel[3 * q + 1]), R(vel[3 * q + 2])});
    }
    finite_ = true;
    contact_on_ = true;
    if (alt_) alt_->invalidate();
  }
  void get_positions(double* out) override { copy_out(pos_(cur_), out); }
  void get_velocities(double* out) override { copy_out(vel_(cur_), out); }
  void get_normals(double* out) override {
    Planes<R> P = pos_(cur_);
    const int n = p_.n;
#pragma omp parallel for schedule(static) num_threads(threads_)
    for (int i = 0; i < n; ++i)
      for (int j = 0; j < n; ++j) {
        V3<R> nr = node_normal(P, n, i, j);
        double* o = out + 3 * size_t(i * n + j);
        o[0] = nr.x; o[1] = nr.y; o[2] = nr.z;
      }
  }
  void set_ball(const double* pv) override {
    ball_ = {{R(pv[0]), R(pv[1]), R(pv[2])}, {R(pv[3]), R(pv[4]), R(pv[5])}};
    contact_on_ = true;
    if (alt_) alt_->invalidate();
  }
  void get_ball(double* pv) override {
    const R v[6] = {ball_.p.x, ball_.p.y, ball_.p.z, ball_.v.x, ball_.v.y, ball_.v.z};
    std::copy(v, v + 6, pv);
  }
  void get_corners(double* out) override {
    Planes<R> P = pos_(cur_), V = vel_(cur_);
    for (int k = 0; k < 4; ++k) {
      V3<R> x, v;
      grip_point(p_, P, V, k, x, v);  // the point each hand holds
      const R vals[6] = {x.x, x.y, x.z, v.x, v.y, v.z};
      std::copy(vals, vals + 6, out + 6 * k);
    }
  }
  bool state_finite() override { return finite_; }
  bool ball_contact_on() override { return (cfg_.effects & BALL) != 0 && contact_on_; }
  std::string path() const override { return "cpu"; }
  void step(int frames, int substeps, double dt) override {
    if (alt_) {
      CpuView<R> v{p_, {pos_(0), pos_(1)}, {vel_(0), vel_(1)}, &cur_, &ball_, fin_, threads_, &finite_};
      alt_->frames(v, frames, substeps, R(dt));
      return;
    }
    frames_(*this, frames, substeps, R(dt));
  }

  // One frame loop per effect set; threads live across all substeps of the call and meet
  // at a barrier between substeps (the double buffer swap).
  template <unsigned E>
  static void run_frames(CpuCloth& c, int frames, int substeps, R dt) {
    const int nthreads = c.threads_;
    std::vector<R> partial(size_t(nthreads) * 16);  // per thread: contact sum, nearest; padded
    std::vector<R> checks(size_t(nthreads) * 16, R(0));
    const int total = frames * substeps;
    const int sweeps = c.strain_sweeps_;
#pragma omp parallel num_threads(nthreads)
    {
      const int tid = omp_get_thread_num();
      const Params<R> p = c.p_;  // locals: the compiler need not reload them past stores
      const FrameInputs<R> fin = c.fin_;
      R check = 0;  // stays 0 while every value this thread wrote is finite
      for (int s = 0; s < total; ++s) {
        const int cur = c.cur_;
        const PaddedPlanes<R> P = c.padded(c.pos_(cur)), V = c.padded(c.vel_(cur));
        const Planes<R> P2 = c.pos_(1 - cur), V2 = c.vel_(1 - cur);
        const V3<R> ball_p = c.ball_.p;
        R* mine = &partial[size_t(tid) * 16];
        // While no node can touch the ball, the contact force is compiled out of the sweep
        // (but the ball still moves, and the nearest node is still tracked).
        if constexpr ((E & BALL) != 0) {
          if (!c.contact_on_)
            sweep<(E & ~BALL), true>(p, P, V, P2, V2, fin, ball_p, dt, check, mine);
          else if (p.ball_edges)
            sweep<(E | BALL_EDGES), true>(p, P, V, P2, V2, fin, ball_p, dt, check, mine);
          else
            sweep<(E | BALL_NODES), true>(p, P, V, P2, V2, fin, ball_p, dt, check, mine);
        } else {
          sweep<E, false>(p, P, V, P2, V2, fin, ball_p, dt, check, mine);
        }
        if (sweeps) c.strain_limit(p, P2, V2, dt);  // one copy for all effect sets
#pragma omp barrier
#pragma omp single
        {
          if constexpr ((E & BALL) != 0) {
            V3<R> sum{R(0), R(0), R(0)};
            R nearest2 = partial[3];
            for (int t = 0; t < nthreads; ++t) {
              const R* o = &partial[size_t(t) * 16];
              sum += V3<R>{o[0], o[1], o[2]};
              nearest2 = o[3] < nearest2 ? o[3] : nearest2;
            }
            const V3<R> before = c.ball_.p;
            c.ball_ = ball_update<R>(p, c.ball_, sum, dt);
            c.contact_on_ = contact_possible(p, nearest2, c.ball_.p - before, sweeps > 0);
          }
          c.cur_ = 1 - cur;
        }
      }
      checks[size_t(tid) * 16] = check;
    }
    R all = c.ball_.p.x + c.ball_.p.y + c.ball_.p.z + c.ball_.v.x + c.ball_.v.y + c.ball_.v.z;
    all -= all;
    for (int t = 0; t < nthreads; ++t) all += checks[size_t(t) * 16];
    if (all != R(0)) c.finite_ = false;
  }

  // One semi-implicit Euler sweep over this thread's rows (its share of them, then a
  // barrier). Writes the thread's contact sum to out[0..2] and, with Track, its smallest
  // squared distance from a new node position to the ball's current centre to out[3].
  // The parameters come by value: as locals the compiler knows the plane stores cannot
  // change them, so it keeps them in registers and unswitches the loop on the contact mode
  // (through references the contact-on sweep ran 4x slower).
  template <unsigned E, bool Track>
  static void sweep(const Params<R> p, const PaddedPlanes<R> PP, const PaddedPlanes<R> VP,
                    const Planes<R> P2, const Planes<R> V2, const FrameInputs<R> fin,
                    V3<R> ball_p, R dt, R& check, R* out) {
    const int n = p.n;
    const int nt = omp_get_num_threads(), t = omp_get_thread_num();
    const int i0 = int(long(n) * t / nt), i1 = int(long(n) * (t + 1) / nt);
    R cx = 0, cy = 0, cz = 0;  // this thread's share of the contact sum (eq. 5)
    R near2 = std::numeric_limits<R>::infinity();
    // Where a row has room for them, its interior nodes in blocks of whole vectors from
    // j = 2 (kVec a vector: no scalar remainder, whose nodes cost many vectorised ones)...
    // Below 48 nodes a row the blocks' loops cost more than they save (measured, 2-core Zen 4:
    // 10-15 % a frame gained at n = 96-128 in float32, lost at n = 24-48).
    const int m = (n - 4) / kVec * kVec >= 48 ? (n - 4) / kVec * kVec : 0;
    // ... and the rest, the border nodes (within 2 of an edge) and what the blocks leave of
    // the inner rows, as the runs of the grid (row after row) between the blocks, through
    // the padded view: there node_force selects the absent neighbours' terms out rather than
    // branching over them, so that these loops vectorise too (branching, a border node cost
    // 15x an interior one). See border.
    const Planes<R> P = PP, V = VP;
    int done = i0 * n;  // the nodes before this one are done
    R sums[4] = {0, 0, 0, 0};  // border's: contact sum, check
    for (int i = std::max(i0, 2); i < std::min(i1, n - 2) && m > 0; ++i) {
      border<E>(p, PP, VP, P2, V2, fin, ball_p, dt, done, i * n + 2, sums);
#pragma omp simd reduction(+ : cx, cy, cz, check)
      for (int j = 2; j < 2 + m; ++j) {
        const V3<R> ct = se_node_update<R, E, true>(p, P, V, P2, V2, fin, ball_p, i, j, dt, check);
        cx += ct.x; cy += ct.y; cz += ct.z;
      }
      done = i * n + 2 + m;
    }
    border<E>(p, PP, VP, P2, V2, fin, ball_p, dt, done, i1 * n, sums);
    cx += sums[0]; cy += sums[1]; cz += sums[2]; check += sums[3];
    // The rows' nearest node to the ball, in a pass of its own: folded into the loops
    // above, the min reduction made GCC's vectorised sweep 3.4x slower (n = 64).
    if constexpr (Track) {
      for (int i = i0; i < i1; ++i) {
        const R* x = P2.x + size_t(i) * n;
        const R* y = P2.y + size_t(i) * n;
        const R* z = P2.z + size_t(i) * n;
#pragma omp simd reduction(min : near2)
        for (int j = 0; j < n; ++j) {
          const R dx = x[j] - ball_p.x, dy = y[j] - ball_p.y, dz = z[j] - ball_p.z;
          const R r2 = dx * dx + dy * dy + dz * dz;
          near2 = r2 < near2 ? r2 : near2;
        }
      }
    }
    out[0] = cx; out[1] = cy; out[2] = cz; out[3] = near2;
#pragma omp barrier
  }

  // sweep's nodes lo..hi-1 (in the grid's order) through the padded view, as one loop.
  // Adds their contact sum to sums[0..2] and their check to sums[3]. i and j vary from
  // lane to lane: GCC 12 does not vectorise a select on a loop-invariant compound
  // condition, such as "i > 0 && j > 0" in a loop over one row.
  template <unsigned E>
  static void border(const Params<R> p, const PaddedPlanes<R> PP, const PaddedPlanes<R> VP,
                     const Planes<R> P2, const Planes<R> V2, const FrameInputs<R> fin,
                     V3<R> ball_p, R dt, int lo, int hi, R* sums) {
    const int n = p.n;
    const float inv_n = 1.0f / float(n);
    R cx = 0, cy = 0, cz = 0, check = 0;
#pragma omp simd reduction(+ : cx, cy, cz, check)
    for (int k = lo; k < hi; ++k) {
      // (i, j) of node k: the estimate of the row is off by at most one (k < 2^24).
      int i = int(float(k) * inv_n), j = k - i * n;
      i = j < 0 ? i - 1 : (j >= n ? i + 1 : i);
      j = k - i * n;
      const V3<R> ct = se_node_update<R, E>(p, PP, VP, P2, V2, fin, ball_p, i, j, dt, check);
      cx += ct.x; cy += ct.y; cz += ct.z;
    }
    sums[0] += cx; sums[1] += cy; sums[2] += cz; sums[3] += check;
  }

 private:
  // Strain limiting, inside the threads' parallel region: each pass limits the rows (one
  // chain per row, rows shared among the threads), then the columns, in place in (P2, V2).
  // The implicit barrier of each omp for keeps rows and columns apart.
  void strain_limit(const Params<R>& p, const Planes<R>& P2, const Planes<R>& V2, R dt) {
    const int n = p.n;
    const R inv_dt = R(1) / dt;
    for (int k = 0; k < strain_sweeps_; ++k) {
#pragma omp for schedule(static)
      for (int i = 0; i < n; ++i) strain_limit_line<R>(p, P2, V2, i * n, 1, inv_dt);
#pragma omp for schedule(static)
      for (int j = 0; j < n; ++j) strain_limit_line<R>(p, P2, V2, j, n, inv_dt);
    }
  }

  template <int... Part>
  static FramesTable<R> gather(std::integer_sequence<int, Part...>) {
    FramesTable<R> t{};
    (fill_frames<R, Part>(t), ...);
    return t;
  }
  static const FramesTable<R>& table() {
    static const FramesTable<R> t = gather(std::make_integer_sequence<int, CB_PARTS>{});
    return t;
  }

  // Buffer b starts 48 values later than buffer b-1, for the same reason as the stride.
  R* plane(int b, int k) { return buf_[b].data() + pad_ + size_t(k) * stride_ + size_t(b) * 48; }
  Planes<R> pos_(int b) { return {plane(b, 0), plane(b, 1), plane(b, 2)}; }
  Planes<R> vel_(int b) { return {plane(b, 3), plane(b, 4), plane(b, 5)}; }
  PaddedPlanes<R> grip_view() {
    R* g = grip_.data();
    const size_t N = size_t(N_);
    return {{}, g, {g + N, g + 2 * N, g + 3 * N}, {g + 4 * N, g + 5 * N, g + 6 * N}};
  }
  PaddedPlanes<R> padded(Planes<R> X) {
    PaddedPlanes<R> v = grip_view();
    static_cast<Planes<R>&>(v) = X;
    return v;
  }
  void set_grip_hips() {
    const PaddedPlanes<R> g = grip_view();
    for (const auto& [q, corner] : held_) g.grip_hip.set(q, fin_.hips[corner]);
  }
  void copy_out(Planes<R> P, double* out) const {
    for (int q = 0; q < N_; ++q) {
      out[3 * q] = P.x[q]; out[3 * q + 1] = P.y[q]; out[3 * q + 2] = P.z[q];
    }
  }

  const int N_;
  const size_t stride_, pad_;
  Config cfg_;
  Params<R> p_{};
  std::vector<R> buf_[2];
  int cur_ = 0;
  int strain_sweeps_ = 0;
  int threads_ = 1;
  bool finite_ = true;
  bool contact_on_ = true;  // may a node touch the ball in the next substep?
  FrameInputs<R> fin_{};
  std::vector<R> grip_;  // the grip table (grip_view)
  std::vector<std::pair<int, int>> held_;  // the held nodes and their hands
  Ball<R> ball_{};
  FramesFn<R> frames_ = nullptr;
  std::unique_ptr<CpuIntegrator<R>> alt_;  // null: semi-implicit Euler (run_frames)
};

template <class R, unsigned... K>
void fill_part(FramesTable<R>& t, std::integer_sequence<unsigned, K...>) {
  ((t[K * CB_PARTS + CB_PART] = &CpuCloth<R>::template run_frames<K * CB_PARTS + CB_PART>), ...);
}

template <>
void fill_frames<CB_REAL, CB_PART>(FramesTable<CB_REAL>& t) {
  static_assert(kNumEffectSets % CB_PARTS == 0, "CB_PARTS must divide the effect sets");
  fill_part<CB_REAL>(t, std::make_integer_sequence<unsigned, kNumEffectSets / CB_PARTS>{});
}

}  // namespace cpu

#if CB_PART == 0
template <>
std::unique_ptr<Backend> make_cpu_backend_t<CB_REAL>(const Config& c) {
  return std::make_unique<cpu::CpuCloth<CB_REAL>>(c);
}
#endif

}  // namespace cb
