"""Bots: a ``Device`` that plays one corner, and a player that runs it over the protocol.

The bot guards its edge (seat ``s`` guards corner ``s`` -> ``s+1``, see ``game.rules``)
and, by ``help_neighbour``, the previous seat's edge, which its corner also holds up: it
predicts where the ball will be a moment ahead and, the closer that is to those edges near
its corner, the more it lifts its corner and pulls it outward (a raised, taut edge rolls
the ball back in). Now and then, when the ball is safely away, it flicks its corner up to
send the ball towards the far corner, where other players guard. ``difficulty`` (0..1)
sets how fast it reacts (reaction delay 250 -> 50 ms), how strongly it answers, and how
much its hand wanders.

``BotPlayer`` connects to a server like any human client (``game.net.client``), takes a
seat (by reconnect token when the server assigned it) and sends its hand position at
``rate_hz``.
"""

from __future__ import annotations

import asyncio
import collections
import logging
from typing import Any

import numpy as np

from .devices.base import CornerState, Reach
from .net.client import NetClient, ServerError

log = logging.getLogger("clothball.bots")

# JSON messages a bot keeps: it waits only for the next few (the server's own bots run
# inside it, and 2000 room-state messages a bot were megabytes).
BOT_HISTORY = 200


class BotDevice:
    """A simulated hand for one corner. Implements ``game.devices.base.Device``."""

    name = "bot"
    # How the bots play (the game's feel: `clothball bench --rounds` measures the rounds
    # they make; docs/benchmarks/rounds.md).
    look_ahead = 0.3  # s: where the ball will be, as the bot judges the threat
    flick_lift = 1.0  # a flick raises the corner this fraction of its reach (up)
    flick_every = (2.0, 6.0)  # s between flicks (times 1.5 - 0.5 difficulty)
    help_neighbour = 0.8  # how much it also guards the previous seat's edge (0..1)

    def __init__(self, seat: int, anchors: np.ndarray, difficulty: float = 0.6,
                 rng: np.random.Generator | None = None) -> None:
        if not 0 <= seat < 4:
            raise ValueError(f"seat: must be 0..3, got {seat}")
        if not (isinstance(difficulty, int | float) and 0.0 <= difficulty <= 1.0):
            raise ValueError(f"difficulty: must be in [0, 1], got {difficulty!r}")
        self.seat = seat
        self.anchors = np.asarray(anchors, dtype=np.float64).reshape(4, 3)
        self.difficulty = float(difficulty)
        self.rng = rng or np.random.default_rng()
        self.reach: Reach | None = None
        self.corner = CornerState()
        self.time = 0.0
        self._balls: collections.deque[tuple[float, np.ndarray, np.ndarray]] = collections.deque(
            maxlen=256)
        self._wander = np.zeros(3)
        self._flick_until = -1.0
        self._next_flick = self.rng.uniform(1.0, 4.0)
        centre = self.anchors.mean(axis=0)
        # The two edges this corner holds up: our own (corner s -> s+1, ours at its start)
        # and the previous seat's (corner s-1 -> s, ours at its end).
        self._edges = [self._edge(seat, (seat + 1) % 4, centre),
                       self._edge((seat - 1) % 4, seat, centre)]
        self._edge_len = self._edges[0][3]
        out = self.anchors[seat] - centre
        out[1] = 0.0
        self._outward = out / max(1e-12, float(np.linalg.norm(out)))
        self.size = self._edge_len

    def _edge(self, i: int, j: int, centre: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
        """Edge from corner i to corner j (plan view): start, unit direction, outward
        normal, length."""
        a, b = self.anchors[i][[0, 2]], self.anchors[j][[0, 2]]
        d = b - a
        length = max(1e-12, float(np.hypot(*d)))
        normal = np.array([d[1], -d[0]]) / length
        if float(np.dot(normal, a - centre[[0, 2]])) < 0:
            normal = -normal
        return a, d / length, normal, length

    def _threat(self, pred: np.ndarray) -> float:
        """0 (the ball safely inside) .. 1 (about to leave) for the edges at this corner,
        weighted towards our corner's end of each and towards our own edge."""
        worst = 0.0
        for k, (a, direction, normal, length) in enumerate(self._edges):
            outside = float(np.dot(pred - a, normal))  # > 0: beyond that edge
            along = float(np.clip(np.dot(pred - a, direction) / length, 0.0, 1.0))
            near_us = 1.0 - 0.5 * (along if k == 0 else 1.0 - along)
            weight = 1.0 if k == 0 else self.help_neighbour
            threat = float(np.clip(1.0 + outside / (0.35 * self.size), 0.0, 1.0))
            worst = max(worst, weight * threat * near_us)
        return worst

    # --- Device ---------------------------------------------------------------------------
    def start(self, reach: Reach) -> None:
        self.reach = reach

    def stop(self) -> None:
        self.reach = None

    def update_corner(self, state: CornerState) -> None:
        self.corner = state

    def update_ball(self, position: np.ndarray, velocity: np.ndarray, t: float) -> None:
        """The ball's latest state (from the CORNER stream) at time ``t`` (s)."""
        p = np.asarray(position, dtype=np.float64)
        if self._balls and float(np.linalg.norm(p - self._balls[-1][1])) > 0.25 * self.size:
            # The ball was put back for a new round: the next flick comes a whole interval
            # later (drawn afresh, so the four bots do not flick together as it lands).
            self._next_flick = t + self._flick_interval()
        self._balls.append((t, p, np.asarray(velocity, dtype=np.float64)))
        self.time = max(self.time, t)

    def _flick_interval(self) -> float:
        lo, hi = self.flick_every
        return float(self.rng.uniform(lo, hi)) * (1.5 - 0.5 * self.difficulty)

    def _seen_ball(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The ball as this bot perceives it: delayed by its reaction time."""
        if not self._balls:
            return None
        delay = 0.25 - 0.2 * self.difficulty
        target = self.time - delay
        for t, p, v in reversed(self._balls):
            if t <= target:
                return p, v
        return self._balls[0][1], self._balls[0][2]

    def hand_position(self) -> np.ndarray:
        if self.reach is None:
            raise RuntimeError("bot device not started")
        reach = self.reach
        ext = reach.half_extent
        h = reach.centre.copy()
        skill = self.difficulty
        # Wandering hand: a slow random walk, larger for weaker bots.
        self._wander = 0.98 * self._wander + self.rng.normal(0.0, 0.02, 3)
        h += self._wander * ext * (0.35 - 0.25 * skill)
        seen = self._seen_ball()
        if seen is None:
            return reach.clamp(h)
        p, v = seen
        pred = p[[0, 2]] + v[[0, 2]] * self.look_ahead
        threat = self._threat(pred)
        gain = 0.5 + 0.5 * skill
        h[1] += ext[1] * gain * threat
        h += self._outward * ext * 0.5 * gain * threat
        # Attack: a quick flick up while the ball is away from our edges.
        if self.time >= self._next_flick and threat < 0.3:
            self._flick_until = self.time + 0.15
            self._next_flick = self.time + self._flick_interval()
        if self.time < self._flick_until:
            h[1] = max(h[1], reach.centre[1] + self.flick_lift * ext[1])
        return reach.clamp(h)


class BotPlayer:
    """A bot playing through the server's protocol, like a human client."""

    def __init__(self, url: str, difficulty: float = 0.6, rate_hz: float = 100.0,
                 name: str = "bot") -> None:
        self.url = url
        self.difficulty = difficulty
        self.rate_hz = rate_hz
        self.name = name
        self.client: NetClient | None = None
        self.device: BotDevice | None = None

    async def run(self, room: str | None = None, token: str | None = None,
                  seat: int | None = None, code: str | None = None) -> None:
        """Join (by token, or a seat of ``room``) and play until the connection closes."""
        self.client = client = await NetClient.connect(
            self.url, name=self.name, role="player", room=room, token=token, seat=seat,
            code=code, corner_rate=self.rate_hz, mesh=False, history=BOT_HISTORY)
        try:
            joined = client.joined
            assert joined is not None and client.reach is not None
            anchors = np.array(joined["geometry"]["anchors"])
            self.device = dev = BotDevice(joined["seat"], anchors, self.difficulty)
            dev.start(client.reach)

            def on_corner(c: Any) -> None:
                dev.update_corner(client.corner_state() or CornerState())
                dev.update_ball(c.ball_position, c.ball_velocity, c.server_time)

            client.on_corner = on_corner
            period = 1.0 / self.rate_hz
            loop = asyncio.get_running_loop()
            next_t = loop.time()
            while client._reader is not None and not client._reader.done():
                await client.send_hip(dev.hand_position())
                next_t += period
                delay = next_t - loop.time()
                if delay < -0.5:
                    next_t = loop.time()
                await asyncio.sleep(max(0.0, delay))
        except (ConnectionError, OSError):
            pass
        except Exception as e:  # websockets' ConnectionClosed among them
            if type(e).__name__ not in ("ConnectionClosedOK", "ConnectionClosedError",
                                        "ConnectionClosed"):
                raise
        finally:
            if self.device is not None:
                self.device.stop()
            await client.close()


async def run_bot(url: str, room: str, token: str, difficulty: float) -> None:
    """What the server spawns for a seat it gives to a bot."""
    try:
        await BotPlayer(url, difficulty).run(room=room, token=token)
    except (ServerError, ConnectionError, OSError, TimeoutError) as e:
        log.info("bot for room %s stopped: %s", room, e)
