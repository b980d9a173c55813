// The CUDA tiled frame's layout and when it is taken (cuda/tiled.cu runs it). Plain C++,
// no CUDA: the bindings expose it so that the choice is tested where there is no GPU.
//
// The tiled frame runs a lone cloth's whole frame in one cooperative launch: the grid is
// cut into tiles, one block each and at most one a multiprocessor, and each block keeps
// its tile's state (6 planes) with a halo of the positions around it in shared memory for
// the whole frame. The substeps meet at a grid barrier; between them only the tile's
// border positions go out (to L2) and its halo's come in, and the ball's sums go through
// the same atomics as a launch a substep. The state is read from device memory once a
// frame and written once, instead of once a substep.
#pragma once
#include <algorithm>
#include <cstddef>
#include <cstdlib>
#include <string>
#include <vector>

#include "params.hpp"

namespace cb {

// A block's threads: as many as the multiprocessor holds at the registers a node's float64
// update takes (128; float32's: 56).
constexpr int tiled_threads(size_t real_bytes) { return real_bytes == 4 ? 1024 : 512; }

// The smallest n at which the tiled frame is taken by default, by the halo's depth. Below
// it a launch a substep, over a state that stays in L2, is about as fast. On an H100 (µs a
// substep, a launch a substep against tiled) classic float32 4.67 / 5.50 at n = 384, 5.40
// / 5.54 at 512, 10.32 / 9.02 at 768, 22.11 / 14.43 at 1024; classic float64 7.30 / 7.79
// at 384, 10.46 / 9.88 at 512; default float32 7.28 / 6.89 at 384, 9.03 / 8.25 at 512. A
// node with bending springs (reach 2: the default's 12 springs and plate term) has more
// to compute for the state it keeps on chip, and gains from n = 320: on an H200 (issue 41,
// two runs alternated) default float32 5.53 / 5.80 at 256, 7.28 / 6.52 at 320, 9.40 /
// 8.65 at 384, 9.53 / 9.22 at 448, 12.1 / 9.56 at 480; float64 6.90 / 9.42 at 256, 11.4 /
// 10.1 at 320, 14.9 / 12.0 at 384, 15.7 / 15.1 at 448, 20.0 / 15.7 at 480; classic there
// float32 5.33 / 5.96 at 384 and 6.05 / 6.57 at 512, float64 8.17 / 8.42 at 384 and 9.88 /
// 9.22 at 512 (docs/benchmarks/gpu-h200-2026-11-28-roofline).
constexpr int kTiledMinN = 512;      // reach 1: structural and shear springs
constexpr int kTiledMinNBend = 320;  // reach 2: bending springs
inline int tiled_min_n(int reach) { return reach >= 2 ? kTiledMinNBend : kTiledMinN; }

struct TiledPlan {
  int tiles_y = 0, tiles_x = 0;  // 0: no tiling fits
  int th = 0, tw = 0;            // the largest tile's nodes (rows, columns)
  int reach = 1;                 // halo depth: how far a node's springs reach
  size_t shared_bytes = 0;       // a block's: the largest tile and its halo, 6 planes
  int tiles() const { return tiles_y * tiles_x; }
  bool ok() const { return tiles_y > 0; }
};

// Halo depth: bending springs reach two nodes, structural and shear springs and edge
// contact one.
inline int tiled_reach(unsigned effects) { return (effects & BEND) != 0 ? 2 : 1; }

// Whether the configuration can run tiled: semi-implicit Euler without strain limiting
// (its passes run along whole lines) and without wind (it reads the neighbours'
// velocities, which a tile updates in place).
inline bool tiled_capable(const Config& c) {
  return c.integrator == SEMI_IMPLICIT_EULER && (c.effects & (STRAIN_LIMIT | WIND)) == 0;
}

// Tiles for the n x n cloth on at most `blocks` blocks of at most `shared_max` bytes of
// shared memory each: the fewest nodes in the largest tile (a substep's critical path),
// then the fewest cells with its halo. ok() is false when no tiling fits. `compact`: among
// the tilings within kWorkSlack of those fewest nodes, the one of the smallest perimeter
// (th + tw), then the fewest nodes: a tall thin tile's side halo is a column of the cloth,
// read from L2 a sector a row after every grid barrier, and its border a column written
// so. On an H200 (issue 41) classic n = 688 took 4 x 33 tiles of 172 x 21 (3 612 nodes)
// over 11 x 12 of 63 x 58 (3 654), and its frame's p50 was 17 % over n = 680's (11 x 12).
// CLOTHBALL_CUDA_TILED_PLAN=work (tiled_plan_for) takes the fewest nodes alone, to measure.
constexpr double kWorkSlack = 0.03;

inline TiledPlan tiled_plan(int n, int reach, size_t real_bytes, int blocks,
                            size_t shared_max, bool compact = true) {
  struct Cand {
    TiledPlan plan;
    long work, cells;
  };
  std::vector<Cand> fits;
  long best_work = 0;
  for (int ty = 1; ty <= std::min(blocks, n); ++ty) {
    const int th = (n + ty - 1) / ty;
    const int rows = (n + th - 1) / th;  // tiles actually used down the cloth
    const int tx = std::min(blocks / rows, n);
    if (tx < 1) continue;
    const int tw = (n + tx - 1) / tx;
    const int cols = (n + tw - 1) / tw;
    const long work = long(th) * tw;
    const long cells = long(th + 2 * reach) * (tw + 2 * reach);
    const size_t bytes = size_t(cells) * 6 * real_bytes;
    if (bytes > shared_max) continue;
    fits.push_back({{rows, cols, th, tw, reach, bytes}, work, cells});
    if (fits.size() == 1 || work < best_work) best_work = work;
  }
  TiledPlan best;
  long bw = 0, bc = 0, bp = 0;
  for (const Cand& f : fits) {
    const long per = long(f.plan.th) + f.plan.tw;
    bool better;
    if (!best.ok()) {
      better = !compact || double(f.work) <= double(best_work) * (1.0 + kWorkSlack);
    } else if (compact) {
      if (double(f.work) > double(best_work) * (1.0 + kWorkSlack)) continue;
      better = per < bp || (per == bp && (f.work < bw || (f.work == bw && f.cells < bc)));
    } else {
      better = f.work < bw || (f.work == bw && f.cells < bc);
    }
    if (better) {
      best = f.plan;
      bw = f.work;
      bc = f.cells;
      bp = per;
    }
  }
  return best;
}

// The plan for configuration c on a device of `blocks` co-resident blocks (one a
// multiprocessor) and `shared_max` bytes of shared memory a block.
inline TiledPlan tiled_plan_for(const Config& c, size_t real_bytes, int blocks,
                                size_t shared_max) {
  if (!tiled_capable(c)) return {};
  const char* env = std::getenv("CLOTHBALL_CUDA_TILED_PLAN");
  const bool compact = !(env && std::string(env) == "work");
  return tiled_plan(c.n, tiled_reach(c.effects), real_bytes, blocks, shared_max, compact);
}

// Whether to take the tiled frame: it must fit, and then CLOTHBALL_CUDA_TILED decides
// ("1": wherever it fits, the tests' way to check it on small cloths; "0": never), else
// n >= tiled_min_n(its halo's depth).
inline bool tiled_wanted(const TiledPlan& plan, int n) {
  if (!plan.ok()) return false;
  const char* env = std::getenv("CLOTHBALL_CUDA_TILED");
  if (env && std::string(env) == "1") return true;
  if (env && std::string(env) == "0") return false;
  return n >= tiled_min_n(plan.reach);
}

}  // namespace cb
