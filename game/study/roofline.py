"""The roofline of the engine's hot kernels: what a node's semi-implicit Euler substep
costs, counted from the code (``native/core/forces.hpp``, ``native/cuda/substep.cuh``,
``tiled.cu``, ``batch.cu``), against the GPU's peak rates.

Counts are per node and substep, for an interior node (the borders are a few per cent of
the nodes at the sizes that matter) with the ball touching the cloth (contact on, the
game's case). A fused multiply-add counts two flops. Square roots, divisions and
reciprocal square roots count apart, as special-function ops (``sfu``): in float32 the
kernels use the approximate ones (``-prec-sqrt=false -prec-div=false``), each a
multi-function-unit instruction (16 a clock a multiprocessor, an eighth of the FP32 rate)
and a multiply or two; in float64 each is a Newton sequence of some 10-20 double ops, so
the float64 rows add those to the flops (``SFU_F64_FLOPS``).

Bytes: ``shared`` is what a node's substep reads and writes in shared memory (the tiled
frame and the fused batched frame keep the state there; each neighbour position read once
per node), ``dram`` the fewest bytes the launch-a-substep path moves through device memory
(its state read and written once a substep; neighbours hit in cache). The bound of a
kernel is the largest of the times these take at peak; the roofline fraction of a measured
time is that bound over the time.

Beside these counts, the instructions a node's substep issues where Nsight Compute counted
them (``INSTRUCTIONS``, measured, not counted from the code): at 4 warp instructions a
clock a multiprocessor, issue is the bound the kernels meet first (``issue``).

The peaks are the datasheet's for an H100/H200 SXM (132 multiprocessors at 1.98 GHz;
leads, not measurements), except device-memory bandwidth, which the bench measures (a
device-to-device copy).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from ..sim.scene import Scene


@dataclass(frozen=True)
class Peaks:
    """A GPU's peak rates, per second."""

    name: str
    sms: int
    clock_ghz: float
    copy_gbs: float | None = None  # measured device-to-device copy, read + write
    # The tiled frame's floor a substep, measured: the grid barrier with the halo's
    # exchange and the ball's update, on a cloth so small its nodes cost nothing (H200,
    # docs/benchmarks/gpu-h200-2026-11-28-roofline: 3.44 us). A substep's nodes cannot
    # overlap it, so the tiled frame's bound is this plus its nodes' time at peak.
    barrier_us: float | None = None

    @property
    def fp32_flops(self) -> float:  # 128 FP32 lanes a multiprocessor, an FMA a clock
        return self.sms * 128 * 2 * self.clock_ghz * 1e9

    @property
    def fp64_flops(self) -> float:  # 64 FP64 lanes
        return self.sms * 64 * 2 * self.clock_ghz * 1e9

    @property
    def sfu_ops(self) -> float:  # 16 multi-function-unit lanes
        return self.sms * 16 * self.clock_ghz * 1e9

    @property
    def shared_bytes(self) -> float:  # 32 banks of 4 bytes a clock
        return self.sms * 128 * self.clock_ghz * 1e9

    @property
    def issue(self) -> float:  # 4 schedulers, a warp instruction (32 threads) a clock
        return self.sms * 4 * 32 * self.clock_ghz * 1e9


HOPPER_SXM = Peaks("H100/H200 SXM (datasheet; the barrier an H200's)", 132, 1.98,
                   barrier_us=3.44)

# --- Counted from native/core/forces.hpp (see the module's docstring for the rules) ------
# spring_force on the GPU: d = pj - pi (3), |d|^2 (5), len = d2 r (1), len - rest (1), the
# compress select (1), k ext r (2), d s (3), the node's f += (3); r = rsqrt(d2) (sfu).
# (Before issue 41: 17 flops and 2 sfu, a square root and a division.)
SPRING_FLOPS, SPRING_SFU = 19, 1
# ball_contact (eq. 4) and its sum: d (3), |d|^2 (5), radius - r (1), k (..) (1), d s (3),
# the centred select (1), f += (3); sqrt and division (sfu).
CONTACT_FLOPS, CONTACT_SFU = 17, 2
# edge_contact_share, each of 4 edges: e (3), e.e (5), (c - x).e (8), clamps (2),
# x + e t - c (9), ball_contact (17 - 3 for its own f +=), (1 - t) (4), c += (3); its
# division and ball_contact's two (sfu). Nodes' own contact is then not computed.
EDGE_CONTACT_FLOPS, EDGE_CONTACT_SFU = 4 * 48, 4 * 3
# plate_sum (interior, coefficients folded): 4 neighbours (x - xi) c + t (9 each), 4 at two
# (x - xi) + t (6 each), 4 diagonals (x - xi) 2 + t (9 each), then -k_plate (3), f += (3).
PLATE_FLOPS = 4 * 9 + 4 * 6 + 4 * 9 + 6
# gravity (3), damping v c (6), kick v += f (inv_mass dt) (7), drift x += v dt (6),
# check_finite (8), track_nearest (9).
NODE_FLOPS = 3 + 6 + 7 + 6 + 8 + 9
# A double square root or division: a 64-bit reciprocal-root seed, then Newton steps.
SFU_F64_FLOPS = 16


# Instructions a node's substep issues, per thread, as Nsight Compute counted them (warp
# instructions executed x 32 over the node-substeps of one launch; H200, the kernels of
# a9ee57b, tools/gpu_roofline.sh's ncu step): the bound these kernels meet first. Their
# flops are 40 % (classic) to 45 % (default) of them: the rest is the neighbours' shared
# loads, the bounds tests of the border code every node runs (node_force<Interior =
# false>: the grip's, the springs', the plate's coefficient flags), index arithmetic, the
# two passes of the tiled frame, the finite check and the ball's tracking. The float64
# counts are of the kernels as at 50bb4ae (2026-11-29, tools/lab/ncu_float64.sh); a
# float64 instruction issues no faster than a float32 one, so their issue bound is, if
# anything, low.
# (path, scene, precision) -> instructions a node-substep.
INSTRUCTIONS = {
    ("tiled", "classic", "float32"): 342.4,       # n = 768, 100 substeps
    ("tiled", "default", "float32"): 864.7,       # n = 512, 86 substeps
    ("tiled", "classic", "float64"): 444.4,       # n = 640, 68 substeps (2026-11-29)
    ("tiled", "default", "float64"): 1061.3,      # n = 384, 73 substeps (2026-11-29)
    ("batch_fused", "classic", "float32"): 310.6,  # n = 60, 264 slots, 8 substeps
    ("batch_fused", "default", "float32"): 769.3,  # n = 48, 264 slots, 9 substeps
}


@dataclass(frozen=True)
class NodeCost:
    """One node's substep: flops, special-function ops, shared-memory and device-memory
    bytes (see the module docstring)."""

    flops: int
    sfu: int
    shared_bytes: int
    dram_bytes: int


def node_cost(effects: frozenset[str] | set[str], precision: str, path: str,
              plate: bool = False, edges: bool = False) -> NodeCost:
    """What one interior node's semi-implicit Euler substep costs on ``path`` ("substeps",
    "node_a_thread", "tiled" or "batch_fused")."""
    springs = 4 * sum(1 for e in ("structural", "shear", "bend") if e in effects)
    flops = NODE_FLOPS + springs * SPRING_FLOPS
    sfu = springs * SPRING_SFU
    if "bend" in effects and plate:
        flops += PLATE_FLOPS
    if "ball" in effects:
        flops += EDGE_CONTACT_FLOPS if edges else CONTACT_FLOPS
        sfu += EDGE_CONTACT_SFU if edges else CONTACT_SFU
    size = 4 if precision == "float32" else 8
    # Distinct neighbour positions read: the springs' (the plate's 12 are the same nodes),
    # and every structural neighbour for edge contact (the same as the structural springs').
    neighbours = springs if springs else (4 if edges else 0)
    state = 3 * size  # a position or a velocity
    if path == "tiled":
        # kick: own position and velocity, neighbours' positions, velocity written; drift:
        # position and velocity read, position written (tiled.cu's two passes).
        shared = (1 + neighbours) * state + 2 * state + 3 * state
    elif path == "batch_fused":
        # se_substep_body between the block's two shared buffers: reads as the kick,
        # the new position and velocity written.
        shared = (1 + neighbours) * state + state + 2 * state
    else:
        shared = 0
    dram = 4 * state if path in ("substeps", "node_a_thread") else 0
    return NodeCost(flops, sfu, shared, dram)


def scene_cost(scene: Scene, precision: str, path: str) -> NodeCost:
    """node_cost for a scene as the engine runs it."""
    plate = float(scene["cloth"].get("bending_stiffness", 0.0) or 0.0) > 0.0
    edges = scene["ball"].get("contact", "nodes") == "edges"
    return node_cost(scene.effects, precision, path, plate=plate, edges=edges)


def bound_us(cost: NodeCost, node_substeps: float, precision: str, peaks: Peaks,
             frames_bytes: float = 0.0) -> dict[str, float]:
    """Microseconds each resource needs at its peak for ``node_substeps`` node-substeps
    (plus ``frames_bytes`` of device memory moved once, the fused paths' state in and
    out): flops, special functions (float32: their unit; float64: as double flops),
    shared memory, device memory."""
    if precision == "float32":
        fp = cost.flops / peaks.fp32_flops
        sfu = cost.sfu / peaks.sfu_ops
    else:
        fp = (cost.flops + cost.sfu * SFU_F64_FLOPS) / peaks.fp64_flops
        sfu = 0.0
    out = {"flops": fp * node_substeps * 1e6, "sfu": sfu * node_substeps * 1e6,
           "shared": cost.shared_bytes / peaks.shared_bytes * node_substeps * 1e6}
    dram = cost.dram_bytes * node_substeps + frames_bytes
    out["dram"] = dram / (peaks.copy_gbs * 1e9) * 1e6 if peaks.copy_gbs else 0.0
    return out


def roofline(scene: Scene, precision: str, path: str, nodes: int, substeps: int,
             measured_us: float, peaks: Peaks = HOPPER_SXM, slots: int = 1,
             frame_io: bool = True) -> dict[str, Any]:
    """A frame of ``slots`` cloths of ``nodes`` nodes each, ``substeps`` substeps, that
    took ``measured_us``: its operation counts, each resource's time at peak, the bound
    (the largest) and the fraction of the measured time it is. ``frame_io``: count the
    fused paths' state in and out of device memory once (a whole frame's time)."""
    cost = scene_cost(scene, precision, path)
    node_substeps = float(nodes) * substeps * slots
    size = 4 if precision == "float32" else 8
    fused = path in ("tiled", "batch_fused")
    once = 12.0 * size * nodes * slots if fused and frame_io else 0.0
    times = bound_us(cost, node_substeps, precision, peaks, once)
    instructions = INSTRUCTIONS.get((path, scene.name, precision))
    if instructions is not None:  # measured, where Nsight Compute counted this kernel
        times["issue"] = instructions * node_substeps / peaks.issue * 1e6
    bound = max(times, key=lambda k: times[k])
    floor = peaks.barrier_us * substeps if path == "tiled" and peaks.barrier_us else 0.0
    return {"flops_per_node_substep": cost.flops, "sfu_per_node_substep": cost.sfu,
            "instructions_per_node_substep": instructions,
            "shared_bytes_per_node_substep": cost.shared_bytes,
            "dram_bytes_per_node_substep": cost.dram_bytes,
            "bound_us": times, "bound": bound,
            "roofline_fraction": times[bound] / measured_us if measured_us > 0 else 0.0,
            # the tiled frame's: its barriers' floor, then the bound (0: no such floor)
            "barrier_us": floor,
            "roofline_fraction_with_barrier": ((times[bound] + floor) / measured_us
                                               if measured_us > 0 and floor else 0.0),
            "peaks": peaks.name,
            "achieved_gflops": (cost.flops * node_substeps / (measured_us * 1e-6) / 1e9
                                if measured_us > 0 else 0.0)}
