// Lab (not built with the package): times the CUDA batch (cuda/cloth.cu's CudaBatch, the
// engine behind ClothBatch on the GPU) with no Python in the loop: K classic cloths, one
// frame a call as a 1 kHz server steps them, so the rooms bench's frame time splits into
// the engine's part (this) and Python's (the rest). Classic effect set only
// (CB_LAB_EFFECT_SET), so it builds in seconds.
// Build (the flags of the package's CUDA units, native/CMakeLists.txt):
//   nvcc -O3 -std=c++17 --expt-relaxed-constexpr -arch=sm_90 -prec-div=false \
//     -prec-sqrt=false -Inative -Xcompiler -fopenmp tools/lab/batch_bench.cu -lgomp \
//     -o batch_bench
// Run:   python tools/lab/classic_configs.py 16 60 > classic.cfg
//        ./batch_bench classic.cfg 60 [K...]
// Prints per K: the frame's median and p99 (us) over 500 frames, each frame hands in for
// every slot, one step, corners and balls out (as the rooms bench), and the same per-slot
// (CLOTHBALL_CUDA_BATCH=0's path: every slot's own graph) for K <= 64.
#define CB_REAL float
#define CB_LAB_EFFECT_SET (STRUCTURAL | GRAVITY | DAMPING | BALL | COUPLING)
#include "../../native/cuda/cloth.cu"
#include "../../native/cuda/batch.cu"
#include "../../native/cuda/device.cu"
#include "../../native/cuda/tiled.cu"  // the tiled frame, which cloth.cu's CudaCloth names

#include <chrono>
#include <cstdlib>
#include <fstream>
#include <memory>
#include <sstream>

#include "../../native/core/batch.hpp"

namespace cb {  // the other integrators are not timed here
template <>
std::unique_ptr<CudaIntegrator<float>> make_cuda_verlet<float>(const Config&) { return nullptr; }
template <>
std::unique_ptr<CudaIntegrator<float>> make_cuda_implicit<float>(const Config&) { return nullptr; }
}  // namespace cb

using namespace cb;

struct Case {
  Config c;
  double height = 1, frame_dt = 1e-3, ball[6] = {};
  int substeps = 1;
};

static Case parse(const std::string& line) {
  Case k;
  std::stringstream ss(line);
  std::string kv;
  while (ss >> kv) {
    const auto eq = kv.find('=');
    const std::string key = kv.substr(0, eq);
    std::vector<double> v;
    std::stringstream vs(kv.substr(eq + 1));
    std::string t;
    while (std::getline(vs, t, ',')) v.push_back(std::stod(t));
    Config& c = k.c;
    if (key == "n") c.n = int(v[0]);
    else if (key == "rest_len") c.rest_len = v[0];
    else if (key == "node_mass") c.node_mass = v[0];
    else if (key == "k_struct") c.k_struct = v[0];
    else if (key == "k_shear") c.k_shear = v[0];
    else if (key == "k_bend") c.k_bend = v[0];
    else if (key == "struct_compress") c.struct_compress = v[0];
    else if (key == "damping") c.damping = v[0];
    else if (key == "ball_radius") c.ball_radius = v[0];
    else if (key == "ball_mass") c.ball_mass = v[0];
    else if (key == "ball_k") c.ball_k = v[0];
    else if (key == "ball_damping") c.ball_damping = v[0];
    else if (key == "ball_edges") c.ball_edges = v[0] != 0;
    else if (key == "coupling_k") c.coupling_k = v[0];
    else if (key == "effects") c.effects = unsigned(v[0]);
    else if (key == "gravity") for (int d = 0; d < 3; ++d) c.gravity[d] = v[d];
    else if (key == "height") k.height = v[0];
    else if (key == "substeps") k.substeps = int(v[0]);
    else if (key == "frame_dt") k.frame_dt = v[0];
    else if (key == "ball") for (int d = 0; d < 6; ++d) k.ball[d] = v[d];
  }
  return k;
}

// Cloth.reset(): the cloth at rest, the hands at the corners, the ball placed.
static void reset(Backend& b, const Case& k) {
  const int n = k.c.n;
  const double L = k.c.rest_len, half = 0.5 * L * (n - 1);
  std::vector<double> pos(3 * size_t(n) * n), vel(pos.size(), 0.0), hips(12);
  for (int i = 0; i < n; ++i)
    for (int j = 0; j < n; ++j) {
      double* x = &pos[3 * (size_t(i) * n + j)];
      x[0] = -half + j * L; x[1] = k.height; x[2] = -half + i * L;
    }
  b.set_state(pos.data(), vel.data());
  const int corners[4] = {corner_node(0, n), corner_node(1, n), corner_node(2, n), corner_node(3, n)};
  for (int c = 0; c < 4; ++c)
    for (int d = 0; d < 3; ++d) hips[3 * c + d] = pos[3 * size_t(corners[c]) + d];
  b.set_hips(hips.data());
  b.set_ball(k.ball);
}

// Median and p99 of one frame (hands in, step, corners out) over `frames` frames, us.
static std::pair<double, double> time_frames(Batch& batch, int K, const Case& k, int frames) {
  std::vector<double> hips(12 * size_t(K)), corners(24 * size_t(K)), balls(6 * size_t(K));
  std::vector<std::uint8_t> finite(static_cast<size_t>(K));
  for (int s = 0; s < K; ++s) batch.at(s).get_corners(&corners[24 * size_t(s)]);
  for (int s = 0; s < K; ++s)
    for (int c = 0; c < 4; ++c)
      for (int d = 0; d < 3; ++d)
        hips[12 * size_t(s) + 3 * c + d] = corners[24 * size_t(s) + 6 * c + d];
  const double dt = k.frame_dt / k.substeps;
  std::vector<double> t;
  for (int f = -20; f < frames; ++f) {
    const auto t0 = std::chrono::steady_clock::now();
    batch.set_hips_all(hips.data());
    batch.step(1, k.substeps, dt, finite.data());
    batch.get_corners_all(corners.data(), balls.data());
    const std::chrono::duration<double> d = std::chrono::steady_clock::now() - t0;
    if (f >= 0) t.push_back(1e6 * d.count());
  }
  std::sort(t.begin(), t.end());
  return {t[t.size() / 2], t[size_t(0.99 * double(t.size() - 1))]};
}

static void run(const Case& k, int K, bool batched) {
  Batch batch([](const Config& c) { return make_cuda_backend_t<float>(c); }, k.c, K, false, 0,
              batched ? Batch::StepperFactory([](Backend& b, int cap) {
                return make_cuda_batch_stepper_t<float>(b, cap);
              })
                      : Batch::StepperFactory());
  for (int s = 0; s < K; ++s) {
    batch.open(s);
    reset(batch.at(s), k);
  }
  const auto [p50, p99] = time_frames(batch, K, k, 500);
  std::printf("%6d %6d %-8s %10.1f %10.1f\n", k.c.n, K, batched ? "batched" : "per-slot", p50, p99);
  std::fflush(stdout);
}

int main(int argc, char** argv) {
  if (argc < 3) {
    std::fprintf(stderr, "usage: %s CONFIG_FILE n [K...]\n", argv[0]);
    return 2;
  }
  const int n = std::atoi(argv[2]);
  std::vector<int> Ks;
  for (int a = 3; a < argc; ++a) Ks.push_back(std::atoi(argv[a]));
  if (Ks.empty()) Ks = {1, 16, 64, 256, 512, 1024, 2048};
  std::ifstream in(argv[1]);
  std::string line;
  std::printf("%6s %6s %-8s %10s %10s\n", "n", "rooms", "path", "p50_us", "p99_us");
  while (std::getline(in, line)) {
    const Case k = parse(line);
    if (k.c.n != n) continue;
    for (int K : Ks) {
      run(k, K, true);
      if (K <= 64) run(k, K, false);
    }
  }
  return 0;
}
