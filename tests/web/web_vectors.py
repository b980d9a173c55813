"""The shared protocol test vectors: binary messages made by the Python encoder
(``clothball.game.wire.protocol``) and what the Python decoder reads from them.

``tests/data/protocol_vectors.json`` is this module's output. ``test_web_vectors.py``
checks the file is current; ``test_web_browser.py`` checks the browser's decoder
(``assets/web/protocol.js``) reads every vector exactly as Python does, refusals included.

Regenerate after a protocol change::

    python tests/web_vectors.py
"""

from __future__ import annotations

import base64
import json
import struct
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from clothball import _native
from clothball.game.wire import protocol as P
from clothball.game.wire.replay import read_replay, write_replay

VECTORS = Path(__file__).parent.parent / "data" / "protocol_vectors.json"
# Version-1 MESH messages and a replay of them, made by the encoder before version 2
# (tests/data/mesh_v1.json says how): old replays' bytes, which every decoder still reads.
MESH_V1 = Path(__file__).parent.parent / "data" / "mesh_v1.json"


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _floats(a: Any) -> list[float]:
    return [float(x) for x in np.asarray(a, dtype=np.float64).reshape(-1)]


def expectation(data: bytes) -> dict[str, Any]:
    """What the Python decoder reads from one binary message, as JSON-able values, or the
    code of the error it raises."""
    try:
        m = P.decode_binary(data)
    except P.ProtocolError as e:
        return {"error": e.code}
    if isinstance(m, P.Hip):
        return {"kind": "HIP", "position": list(m.position), "seq": m.seq, "time": m.time}
    if isinstance(m, P.Corner):
        return {
            "kind": "CORNER", "frame": m.frame, "seat": m.seat, "position": _floats(m.position),
            "velocity": _floats(m.velocity), "force": _floats(m.force),
            "stiffness": m.stiffness, "ballPosition": _floats(m.ball_position),
            "ballVelocity": _floats(m.ball_velocity), "hipSeq": m.hip_seq,
            "hipTime": m.hip_time if np.isfinite(m.hip_time) else None,
            "serverTime": m.server_time,
        }
    if isinstance(m, P.Mesh):
        return {
            "kind": "MESH", "frame": m.frame, "serverTime": m.server_time,
            "n": int(m.positions.shape[0]), "flags": m.flags, "version": m.version,
            "lo": _floats(m.lo),
            "hi": _floats(m.hi), "ballPosition": _floats(m.ball_position),
            "ballRadius": m.ball_radius, "hips": _floats(m.hips),
            "positions": _floats(m.positions),
        }
    assert isinstance(m, P.Track)
    return {
        "kind": "TRACK", "frame": m.frame, "serverTime": m.server_time,
        "ballPosition": _floats(m.ball_position), "ballVelocity": _floats(m.ball_velocity),
        "hips": _floats(m.hips), "corners": _floats(m.corners),
    }


def sheet(n: int, seed: int, sag: float = 0.2, noise: float = 1e-3) -> np.ndarray:
    """A hanging cloth: an n x n grid of 1 m sagging in the middle, with a little noise."""
    rng = np.random.default_rng(seed)
    u = np.linspace(-0.5, 0.5, n)
    x, z = np.meshgrid(u, u)  # x along j, z along i: the server's layout
    y = 1.0 - sag * (1.0 - (2 * x) ** 2) * (1.0 - (2 * z) ** 2)
    p = np.stack([x, y, z], axis=-1)
    return p + rng.normal(0.0, noise, p.shape)


def messages() -> list[tuple[str, bytes]]:
    """Named binary messages: valid ones of every type, then damaged ones."""
    hips = np.array([[-0.5, 1.0, -0.5], [0.5, 1.02, -0.5], [0.55, 1.1, 0.52], [-0.5, 1.0, 0.5]])
    out: list[tuple[str, bytes]] = [
        ("hip", P.encode_hip([0.1, -0.25, 0.5], 7, 12.5)),
        ("hip_seq_wraps", P.encode_hip([0.0, 1.0, 0.0], 2**32 + 5, 0.0)),
        ("corner", P.encode_corner(123456789012, 2, [0.5, 1.0, 0.5], [0.01, -0.2, 0.0],
                                   [1.5, -2.25, 0.125], 1000.0, [0.0, 1.3, 0.05],
                                   [0.2, -1.0, 0.0], 99, 3.25, 4.5)),
        ("corner_no_hip", P.encode_corner(1, 0, [0, 0, 0], [0, 0, 0], [0, 0, 0], 0.0,
                                          [0, 0, 0], [0, 0, 0], 0, float("nan"), 0.0)),
        ("track", P.encode_track(5000, 5.0, [0.1, 1.2, -0.1], [0.5, -0.5, 0.0], hips,
                                 hips + 0.01)),
    ]
    for n, seed, compress in ((2, 1, False), (3, 2, True), (16, 3, True), (16, 3, False),
                              (33, 4, True)):
        p = sheet(n, seed)
        out.append((f"mesh_n{n}_{'zlib' if compress else 'raw'}",
                    P.encode_mesh(1000 + n, 1.0 + n / 1000, p, [0.0, 1.3, 0.0], 0.08, hips,
                                  compress=compress)))
    flat = sheet(8, 6, sag=0.0, noise=0.0)  # zero extent in y: every y quantises to lo
    out.append(("mesh_flat", P.encode_mesh(7, 0.007, flat, [0, 1.2, 0], 0.05, hips)))
    rough = np.random.default_rng(7).uniform(-1.0, 1.0, (12, 12, 3))  # does not compress
    out.append(("mesh_rough", P.encode_mesh(8, 0.008, rough, [0, 1.2, 0], 0.05, hips)))
    big_frame = P.encode_mesh(2**40 + 3, 1e6, sheet(4, 8), [0, 1, 0], 0.1, hips)
    out.append(("mesh_big_frame", big_frame))
    # the server's encoder (C++): its planes deflated as literals and by libdeflate
    for deflater in ("literals", "libdeflate"):
        out.append((f"mesh_native_{deflater}", _native.encode_mesh_msg(
            sheet(36, 9), 2000, 2.0, [0.0, 1.3, 0.0], 0.08, hips.reshape(12), True, 2,
            deflater)))
    v1 = json.loads(MESH_V1.read_text())["messages"]
    out += [(f"mesh_v1_{k}_{'zlib' if m['flags'] else 'raw'}", base64.b64decode(m["b64"]))
            for k, m in enumerate(v1)]

    # damaged messages: the expected refusal is whatever the Python decoder says
    good = dict(out)
    mesh = good["mesh_n16_zlib"]
    raw = good["mesh_n16_raw"]
    out += [
        ("bad_empty", b""),
        ("bad_short_header", good["hip"][:10]),
        ("bad_type", bytes([9]) + good["hip"][1:]),
        ("bad_version", good["hip"][:1] + bytes([P.PROTOCOL_VERSION + 1]) + good["hip"][2:]),
        ("bad_hip_size", good["hip"] + b"\0"),
        ("bad_hip_nan", good["hip"][:16] + struct.pack("<3f", 0.0, float("nan"), 0.0)),
        ("bad_time_inf", good["hip"][:8] + struct.pack("<d", float("inf")) + good["hip"][16:]),
        ("bad_corner_size", good["corner"][:-1]),
        ("bad_corner_flags", good["corner"][:2] + struct.pack("<H", 1) + good["corner"][4:]),
        ("bad_track_flags", good["track"][:2] + struct.pack("<H", 1) + good["track"][4:]),
        ("bad_track_size", good["track"] + b"\0\0"),
        ("bad_mesh_short", mesh[:40]),
        ("bad_mesh_n", mesh[:24] + struct.pack("<H", 1) + mesh[26:]),
        ("bad_mesh_n_big", mesh[:24] + struct.pack("<H", P.MAX_MESH_N + 1) + mesh[26:]),
        ("bad_mesh_flags", mesh[:2] + struct.pack("<H", 4 | P.FLAG_ZLIB) + mesh[4:]),
        ("bad_mesh_version", mesh[:1] + bytes([P.MESH_VERSION + 1]) + mesh[2:]),
        ("bad_mesh_version_0", mesh[:1] + bytes([0]) + mesh[2:]),
        ("bad_mesh_v1_payload_short", good["mesh_v1_1_raw"][:-2]),
        ("bad_mesh_zlib", mesh[:116] + b"\x78\x01garbage-not-deflate" + mesh[140:]),
        ("bad_mesh_payload_short", raw[:-2]),
        ("bad_mesh_payload_long", raw + b"\0\0"),
        ("bad_mesh_zlib_too_big", raw[:2] + struct.pack("<H", P.FLAG_ZLIB) + raw[4:116]
         + __import__("zlib").compress(raw[116:] + b"\0\0", 1)),
    ]
    return out


def replay_vector() -> dict[str, Any]:
    """A small replay file, written by the server's writer, and what its reader finds."""
    hips = np.array([[-0.5, 1.0, -0.5], [0.5, 1.0, -0.5], [0.5, 1.0, 0.5], [-0.5, 1.0, 0.5]])
    header = {
        "format": "clothball-replay", "id": "vector-round-1", "room_id": "r1",
        "room_name": "vectors", "scene": "tiny", "round": 1,
        "players": [{"seat": s, "kind": "bot", "name": f"bot-{s}"} for s in range(4)],
        "conceded_edge": 1, "conceded_by": 1, "scorers": [0, 2, 3], "scores": [1, 0, 1, 1],
        "geometry": {"n": 5, "size": 1.0, "frame_dt": 0.001}, "track_hz": 100.0,
    }
    records: list[tuple[int, bytes]] = []
    ev = {"type": "event", "event": "round_start", "room": "r1", "frame": 100, "time": 0.1,
          "round": 1}
    records.append((0, P.encode_json(ev).encode()))
    for k in range(4):
        frame = 100 + 33 * k
        records.append((1, P.encode_mesh(frame, frame / 1000, sheet(5, 20 + k),
                                         [0.1 * k, 1.2, 0.0], 0.08, hips)))
        records.append((1, P.encode_track(frame, frame / 1000, [0.1 * k, 1.2, 0.0],
                                          [1.0, 0.0, 0.0], hips, hips)))
    ev2 = {"type": "event", "event": "score", "room": "r1", "frame": 200, "time": 0.2,
           "round": 1, "edge": 1, "conceded_by": 1, "scorers": [0, 2, 3],
           "scores": [1, 0, 1, 1]}
    records.append((0, P.encode_json(ev2).encode()))
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "vector-round-1.cbr"
        write_replay(path, header, records)
        data = path.read_bytes()
    head, recs = read_replay(data)
    expect = []
    for kind, rec in recs:
        if kind == 0:
            expect.append({"record": 0, "json": json.loads(rec)})
        else:
            expect.append({"record": 1, **expectation(rec)})
    return {"b64": b64(data), "header": head, "records": expect}


def replay_v1_vector() -> dict[str, Any]:
    """An old replay (version-1 MESH records) and what today's reader finds in it."""
    data = base64.b64decode(json.loads(MESH_V1.read_text())["replay_b64"])
    head, recs = read_replay(data)
    return {"b64": b64(data), "header": head,
            "records": [{"record": 1, **expectation(rec)} for _, rec in recs]}


def build() -> dict[str, Any]:
    return {
        "about": "Made by tests/web/web_vectors.py from clothball.game.wire.protocol; "
                 "regenerate with `python -m tests.web.web_vectors`.",
        "protocol_version": P.PROTOCOL_VERSION,
        "binary": [{"name": name, "b64": b64(data), "expect": expectation(data)}
                   for name, data in messages()],
        "replay": replay_vector(),
        "replay_v1": replay_v1_vector(),
    }


def write(path: Path = VECTORS) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(build(), indent=1, allow_nan=False) + "\n")


if __name__ == "__main__":
    write()
    print(f"wrote {VECTORS}")
