// Lab (not built with the package): times the production CUDA backend of
// native/cuda/cloth.cu on the classic scene with no Python in the loop, compiled for the
// classic effect set only (CB_LAB_EFFECT_SET), so a kernel change builds in seconds here
// and runs on the GPU machine without the package's 3-minute build.
// Configurations come from tools/lab/classic_configs.py (the package's own scene code).
// Build (the flags of the package's cloth unit, native/CMakeLists.txt):
//   nvcc -O3 -std=c++17 --expt-relaxed-constexpr -arch=sm_90 -prec-div=false \
//     -prec-sqrt=false -Inative tools/lab/substep_bench.cu -o substep_bench
// Run:   python tools/lab/classic_configs.py > classic.cfg; ./substep_bench classic.cfg [max_n]
// Two timings per size, median of 7 runs of >= 20 ms each, us per substep:
//   chunked: frames in calls of 10 with a sync between (what Cloth.step does, minus Python)
//   stream:  all frames in one call (the GPU's own rate)
#define CB_REAL float
#define CB_LAB_EFFECT_SET (STRUCTURAL | GRAVITY | DAMPING | BALL | COUPLING)
#include "../../native/cuda/cloth.cu"
#include "../../native/cuda/batch.cu"  // the batch's kernels, which cloth.cu's CudaBatch names
#include "../../native/cuda/device.cu"
#include "../../native/cuda/tiled.cu"  // the tiled frame, which cloth.cu's CudaCloth names

#include <chrono>
#include <fstream>
#include <sstream>

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

static std::vector<double> nums(const std::string& s) {
  std::vector<double> v;
  std::stringstream ss(s);
  std::string t;
  while (std::getline(ss, t, ',')) v.push_back(std::stod(t));
  return v;
}

static Case parse(const std::string& line) {
  Case k;
  std::stringstream ss(line);
  std::string kv;
  while (ss >> kv) {
    const auto eq = kv.find('=');
    const std::string key = kv.substr(0, eq);
    const std::vector<double> v = nums(kv.substr(eq + 1));
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

template <class F>
static double median_us(F run, int substeps_per_run) {
  std::vector<double> t;
  for (int r = 0; r < 7; ++r) {
    const auto t0 = std::chrono::steady_clock::now();
    run();
    const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    t.push_back(1e6 * s / substeps_per_run);
  }
  std::sort(t.begin(), t.end());
  return t[3];
}

int main(int argc, char** argv) {
  if (argc < 2) { std::fprintf(stderr, "usage: %s CONFIG_FILE [max_n]\n", argv[0]); return 2; }
  const int max_n = argc > 2 ? std::atoi(argv[2]) : 1 << 30;
  std::ifstream in(argv[1]);
  std::string line;
  std::printf("%6s %9s %13s %12s %8s\n", "n", "substeps", "chunked_us", "stream_us", "contact");
  while (std::getline(in, line)) {
    Case k = parse(line);
    if (k.c.n > max_n) continue;
    auto b = make_cuda_backend_t<float>(k.c);
    reset(*b, k);
    const int S = k.substeps;
    const double dt = k.frame_dt / S;
    // A fingerprint of the state 100 frames after the reset (the ball still in the air,
    // so no float atomics: deterministic): builds that compute the same thing print the
    // same digits.
    b->step(100, S, dt);
    std::vector<double> pos(3 * size_t(k.c.n) * k.c.n);
    b->get_positions(pos.data());
    double fp = 0;
    for (size_t q = 0; q < pos.size(); ++q) fp += pos[q] * double(q % 7 + 1);
    std::printf("fingerprint n=%d %.17g\n", k.c.n, fp);
    reset(*b, k);
    b->step(2, S, dt);  // warm-up: graph capture
    int frames = 10;    // grow to >= 20 ms a run, in whole chunks of 10
    for (;;) {
      const auto t0 = std::chrono::steady_clock::now();
      b->step(frames, S, dt);
      const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
      if (s >= 0.02 || frames >= 1 << 16) break;
      frames *= 2;
    }
    double pv[6];
    const double chunked = median_us([&] {
      for (int f = 0; f < frames; f += 10) { b->step(10, S, dt); b->get_ball(pv); b->state_finite(); }
    }, frames * S);
    const double stream = median_us([&] { b->step(frames, S, dt); }, frames * S);
    std::printf("%6d %9d %13.3f %12.3f %8d\n", k.c.n, S, chunked, stream, int(b->ball_contact_on()));
    std::fflush(stdout);
  }
  return 0;
}
