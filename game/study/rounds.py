"""``clothball bench --rounds N``: how long rounds last when bots play a real room.

A spectator (an ordinary network client) watches a room where bots play match after match
and times each round from its ``round_start`` event to its ``score`` event. Time is the
simulation's, counted in frames: the frame number of the newest MESH the spectator had
when each event arrived, times the scene's ``frame_dt`` (the room runs locked to wall time,
but a loaded machine may drop frames; frames are what the players lived through). Both ends
are read the same way, so the count is good to about one MESH period (``mesh_hz``).

The caller supplies the room (``game.cli.bench`` starts a server with four bots); this
module only needs its websocket address.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from ..net.client import NetClient
from ..wire import protocol as P

# Bins of the printed distribution, s (the last one is open).
BINS = (0.0, 2.0, 5.0, 10.0, 15.0, 20.0, 30.0, 60.0)
TARGET_MEDIAN_S = 10.0  # issue 19: four default bots play rounds of 10 s or more (median)


@dataclass
class Round:
    round: int
    seconds: float  # simulated time from round_start to the score
    wall_seconds: float  # the spectator's clock between the two events
    frames: int
    edge: int
    conceded_by: int | None


def mesh_frame(data: bytes) -> int:
    """The frame number of a MESH message (the first field after the header)."""
    return int(P.MESH_BODY.unpack_from(data, P.HEADER.size)[0])


async def watch_rounds(url: str, room: str, rounds: int, round_timeout: float = 300.0,
                       progress: Callable[[Round], None] | None = None) -> list[Round]:
    """Watch ``room`` until ``rounds`` rounds have been scored; their lengths, in order.
    A round already under way when the spectator arrives is not counted."""
    client = await NetClient.connect(url, name="rounds-bench", role="spectator", room=room,
                                     mesh=True, decode_mesh=False)
    frame_dt = float(client.geometry["frame_dt"])
    latest = {"frame": -1}
    started: dict[str, Any] = {}
    out: list[Round] = []
    done = asyncio.Event()
    changed = asyncio.Event()

    def on_mesh(data: bytes) -> None:
        latest["frame"] = mesh_frame(data)

    def on_message(msg: dict[str, Any]) -> None:
        if msg.get("type") != "event":
            return
        ev = msg.get("event")
        if ev == "round_start":
            started.update(round=msg.get("round"), frame=latest["frame"],
                           wall=time.perf_counter())
            changed.set()
        elif ev == "score" and started and started["round"] == msg.get("round"):
            frames = latest["frame"] - started["frame"]
            r = Round(int(msg["round"]), frames * frame_dt, time.perf_counter() - started["wall"],
                      frames, int(msg["edge"]), msg.get("conceded_by"))
            started.clear()
            out.append(r)
            changed.set()
            if progress is not None:
                progress(r)
            if len(out) >= rounds:
                done.set()

    client.on_mesh = on_mesh
    client.on_message = on_message
    try:
        while not done.is_set():
            changed.clear()
            waiter = asyncio.ensure_future(changed.wait())
            closed = asyncio.ensure_future(client.wait_closed(timeout=1e9))
            finished, _ = await asyncio.wait({waiter, closed}, timeout=round_timeout,
                                             return_when=asyncio.FIRST_COMPLETED)
            waiter.cancel()
            closed.cancel()
            if closed in finished:
                raise ConnectionError(f"the server closed the connection after {len(out)} "
                                      "rounds")
            if not finished:
                raise TimeoutError(f"no round started or ended within {round_timeout:g} s "
                                   f"(after {len(out)} rounds)")
    finally:
        await client.close()
    return out


def summarise(rounds: list[Round]) -> dict[str, Any]:
    """Median, quartiles, extremes and a histogram of the round lengths (s)."""
    s = np.array([r.seconds for r in rounds], dtype=np.float64)
    if s.size == 0:
        raise ValueError("no rounds to summarise")
    edges = [*BINS, float("inf")]
    counts, _ = np.histogram(s, bins=edges)
    q1, med, q3 = np.percentile(s, [25, 50, 75])
    return {
        "rounds": int(s.size), "median_s": float(med), "q1_s": float(q1), "q3_s": float(q3),
        "mean_s": float(s.mean()), "min_s": float(s.min()), "max_s": float(s.max()),
        "histogram": [{"from_s": lo, "to_s": hi if np.isfinite(hi) else None, "count": int(c)}
                      for lo, hi, c in zip(edges[:-1], edges[1:], counts, strict=True)],
        "target_median_s": TARGET_MEDIAN_S, "meets_target": bool(med >= TARGET_MEDIAN_S),
        "lengths_s": [round(float(x), 3) for x in s],
    }


def print_rounds(summary: dict[str, Any], rounds: list[Round]) -> None:
    print("round lengths, s: " + " ".join(f"{r.seconds:.1f}" for r in rounds))
    print(f"{summary['rounds']} rounds: median {summary['median_s']:.1f} s (quartiles "
          f"{summary['q1_s']:.1f} to {summary['q3_s']:.1f}), mean {summary['mean_s']:.1f}, "
          f"shortest {summary['min_s']:.1f}, longest {summary['max_s']:.1f}")
    width = max(1, max(b["count"] for b in summary["histogram"]))
    for b in summary["histogram"]:
        hi = f"{b['to_s']:g}" if b["to_s"] is not None else ""
        bar = "#" * round(30 * b["count"] / width)
        print(f"  {b['from_s']:>4g} - {hi:<4} s  {b['count']:4d}  {bar}")
    verdict = "meets" if summary["meets_target"] else "misses"
    print(f"median {verdict} the {summary['target_median_s']:g} s target (issue 19)")


def as_json(rounds: list[Round]) -> list[dict[str, Any]]:
    return [asdict(r) for r in rounds]
