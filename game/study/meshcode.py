"""``clothball bench --mesh``: what a MESH costs the server's encoder, and its bytes.

The encoder is the frame loop's (``native/loop/mesh_msg.hpp``, run by its service thread
for every due room), timed in C++ (``_native.time_mesh_encoder``: one thread, its scratch
kept, as the service thread runs it; no binding in the figures): today's version 2
(2-D residuals in byte planes, deflated as literals with a Huffman code a plane, or by
libdeflate's level 1: the server takes literals from n = 36 on, libdeflate below) and
version 1 (row deltas interleaved, zlib:
the coding before it, still built for this comparison), in the same run, interleaved in
blocks so that a busy machine slows them alike. The cloths are the game's:
the default scene from its start (the flat cloth in the hands, the ball dropped onto it),
hands on the move, a state every 33 frames (a MESH at 30 Hz) for a second of play, each
encoded ``rounds`` times per version.
"""

from __future__ import annotations

import statistics
from collections.abc import Callable
from typing import Any

import numpy as np

from ... import _native
from ..sim.cloth import Cloth
from ..sim.scene import Scene

MESH_EVERY = 33  # frames between MESHes at 30 Hz
PLAY_FRAMES = 1000  # a second of play
BLOCKS = 5  # the versions alternate this many times
# (version, deflater): what each row times (version 1's is always zlib).
CODINGS = {(1, "zlib"): "v1: row deltas, interleaved, zlib L1",
           (2, "libdeflate"): "v2 planes, libdeflate L1",
           (2, "literals"): "v2 planes, literals"}


def cloth_states(n: int, backend: str = "auto") -> np.ndarray:
    """(k, n, n, 3): the default scene's cloth from the game's start, a state a MESH."""
    cloth = Cloth(Scene.load("default").with_changes({"cloth": {"n": n}}), backend)
    rest = cloth.hips()
    phase = np.arange(4)[:, None] * (np.pi / 2)
    states = []
    for f in range(MESH_EVERY, PLAY_FRAMES + 1, MESH_EVERY):
        # the players' hands: a few centimetres of slow motion each, out of step
        cloth.set_hips(rest + 0.03 * np.sin(2 * np.pi * f / 700.0 + phase))
        cloth.step(MESH_EVERY)
        states.append(np.asarray(cloth.positions(), dtype=np.float64))
    return np.stack(states)


def run_mesh(sizes: list[int], rounds: int, backend: str = "auto",
             progress: Callable[[str], None] | None = None) -> list[dict[str, Any]]:
    """A row per (n, coding): µs per MESH (median, p90) and its bytes (median, range)."""
    rows = []
    for n in sizes:
        states = cloth_states(n, backend)
        times: dict[tuple[int, str], list[float]] = {c: [] for c in CODINGS}
        sizes_of: dict[tuple[int, str], np.ndarray] = {}
        per_block = max(1, rounds // BLOCKS)
        for _ in range(BLOCKS):
            for version, deflater in CODINGS:
                sec, nbytes = _native.time_mesh_encoder(
                    states, version, per_block, "auto" if version == 1 else deflater)
                times[(version, deflater)] += list(sec * 1e6)
                sizes_of[(version, deflater)] = nbytes
        for (version, deflater), label in CODINGS.items():
            t, b = times[(version, deflater)], sizes_of[(version, deflater)]
            rows.append({
                "n": n, "version": version, "deflater": deflater, "coding": label,
                "states": int(states.shape[0]), "encodes": len(t),
                "us_median": statistics.median(t),
                "us_p90": float(np.percentile(t, 90)),
                "bytes_median": float(np.median(b)), "bytes_min": int(b.min()),
                "bytes_max": int(b.max()), "bytes_raw": 116 + 6 * n * n,
            })
        if progress:
            progress(f"n = {n}")
    return rows


def print_mesh(rows: list[dict[str, Any]]) -> None:
    print(f"{'n':>4} {'coding':38s} {'us median':>9} {'us p90':>8} {'bytes':>7} "
          f"{'(min-max)':>13} {'raw':>6}")
    for r in rows:
        print(f"{r['n']:4d} {r['coding']:38s} {r['us_median']:9.1f} {r['us_p90']:8.1f} "
              f"{r['bytes_median']:7.0f} {r['bytes_min']:6d}-{r['bytes_max']:<6d} "
              f"{r['bytes_raw']:6d}")
    by = {(r["n"], r["version"], r["deflater"]): r for r in rows}
    for n in sorted({r["n"] for r in rows}):
        old = by[(n, 1, "zlib")]
        for d in ("literals", "libdeflate"):
            new = by[(n, 2, d)]
            print(f"n = {n}: v2 ({d}) takes {new['us_median'] / old['us_median']:.2f}x v1's "
                  f"time, {new['bytes_median'] / old['bytes_median']:.2f}x its bytes "
                  f"({new['states']} cloth states, {new['encodes']} encodes a coding)")
