"""MESH payload codings against their deflate cost (issue 43, Deliver 2: a MESH ≤ 50 µs at
n = 48, its bytes no larger than today's). The nodes of a default-scene cloth after 400
frames, quantised and row-delta coded as the loop does (``_native.quantise_mesh``), then
deflated (zlib streams, which ``DecompressionStream("deflate")`` reads) as they are today
(x, y, z interleaved, 16-bit little-endian), as byte planes (every low byte, then every high
byte), and as axis and byte planes; with zlib and with libdeflate (``pip install deflate``,
its Python binding) at level 1. Medians of 7 runs; run it on a quiet machine.

Usage: python tools/lab/mesh_coding.py [--n 48]

It deflates one buffer over and over, which flatters every coder (the branch predictor
learns the input): the figures of record are ``clothball bench --mesh``'s, the server's
encoder over many cloth states in turn (docs/benchmarks/load.md, "MESH codings").
"""

from __future__ import annotations

import argparse
import statistics
import time
import zlib

import numpy as np
from clothball import _native
from clothball.game.sim.cloth import Cloth
from clothball.game.sim.scene import Scene


def timed(f, k: int = 300) -> tuple[float, int]:  # type: ignore[no-untyped-def]
    runs = []
    for _ in range(7):
        t0 = time.perf_counter()
        for _ in range(k):
            out = f()
        runs.append((time.perf_counter() - t0) / k)
    return statistics.median(runs) * 1e6, len(out)


def main() -> None:
    p = argparse.ArgumentParser(prog="python tools/lab/mesh_coding.py")
    p.add_argument("--n", type=int, default=48)
    n = p.parse_args().n
    cloth = Cloth(Scene.load("default").with_changes({"cloth": {"n": n}}), "cpu", threads=1)
    cloth.step(400)
    _, delta, _, _ = _native.quantise_mesh(np.asarray(cloth.positions(), float).reshape(n, n, 3))
    codings = {
        "interleaved (today)": delta.tobytes(),
        "byte planes": np.ascontiguousarray(delta.reshape(-1).view(np.uint8).reshape(-1, 2).T)
        .tobytes(),
        "axis + byte planes": np.ascontiguousarray(
            np.ascontiguousarray(delta.reshape(-1, 3).T).view(np.uint8).reshape(3, -1, 2)
            .transpose(0, 2, 1)).tobytes(),
    }
    coders = {"zlib L1": lambda b: zlib.compress(b, 1)}
    try:
        import deflate  # libdeflate

        coders["libdeflate L1"] = lambda b: deflate.zlib_compress(b, 1)
    except ImportError:
        print("(libdeflate's binding not installed: pip install deflate)")
    print(f"n = {n}: {delta.nbytes} bytes of row deltas")
    for name, raw in codings.items():
        for cname, coder in coders.items():
            us, size = timed(lambda raw=raw, coder=coder: coder(raw))
            print(f"{name:22s} {cname:14s} {us:7.1f} us {size:6d} bytes")


if __name__ == "__main__":
    main()
