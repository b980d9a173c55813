"""The native MESH quantiser (native/loop/mesh_quant.hpp, ``_native.quantise_mesh``: what the
server's mesh encoder thread uses) against the Python one that defines the format
(``protocol.quantise`` and ``mesh_deltas``, docs/protocol.md): the same quantised nodes and
bounds for random meshes of every scale, offset and shape, flat axes included, and the same
MESH bytes (a bound of zero aside: +0 from the native one, where NumPy's min may keep a
-0, the same value; such a message decodes to the same numbers)."""

from __future__ import annotations

import numpy as np
import pytest
from clothball import _native
from clothball.game.wire import protocol as P


def _meshes(rng: np.random.Generator, count: int):
    for k in range(count):
        n = int(rng.integers(2, 40))
        scale = 10.0 ** rng.uniform(-7, 4)
        offset = rng.normal(0.0, 10.0 ** rng.uniform(-3, 5), 3)
        p = offset + rng.normal(0.0, scale, (n, n, 3))
        if k % 5 == 1:
            p[..., int(rng.integers(0, 3))] = offset[0]  # a flat axis: zero span
        if k % 7 == 2:
            p = np.round(p, 2)  # repeated values, exact bounds
        yield p


def test_the_native_quantiser_gives_the_python_ones_bits() -> None:
    rng = np.random.default_rng(33)
    for p in _meshes(rng, 3000):
        q, d, lo, hi = _native.quantise_mesh(p)
        pq, plo, phi = P.quantise(p)
        assert q.dtype == np.uint16 and q.shape == pq.shape
        assert np.array_equal(q, pq)
        assert np.array_equal(d, P.mesh_deltas(pq))
        assert np.array_equal(lo, plo) and np.array_equal(hi, phi)  # -0 == +0
        assert lo.tobytes() == (plo + 0.0).tobytes() and hi.tobytes() == (phi + 0.0).tobytes()


def test_a_mesh_from_the_native_quantiser_is_the_python_encoders_message() -> None:
    rng = np.random.default_rng(34)
    for k, p in enumerate(_meshes(rng, 300)):
        ball, hips = rng.normal(0.0, 1.0, 3), rng.normal(0.0, 1.0, (4, 3))
        compress = k % 2 == 0
        q, d, lo, hi = _native.quantise_mesh(p)
        got = P.encode_quantised_mesh(k, 0.25 * k, q, lo, hi, ball, 0.1, hips,
                                      compress=compress, deltas=d)
        want = P.encode_mesh(k, 0.25 * k, p, ball, 0.1, hips, compress=compress)
        if np.all(lo != 0.0) and np.all(hi != 0.0):
            assert got == want
        else:
            a, b = P.decode_mesh(got), P.decode_mesh(want)
            assert len(got) == len(want) and a.flags == b.flags and a.frame == b.frame
            assert np.array_equal(a.positions, b.positions) and np.array_equal(a.lo, b.lo)
    # a smooth cloth compresses: the delta-coded, zlib'd form, decoded within the bound
    u = np.linspace(-0.5, 0.5, 32)
    x, z = np.meshgrid(u, u)
    p = np.stack([x, 1.0 + 0.05 * np.sin(3 * x) * np.cos(2 * z), z], axis=-1)
    q, d, lo, hi = _native.quantise_mesh(p)
    msg = P.decode_mesh(P.encode_quantised_mesh(1, 0.0, q, lo, hi, [0, 0, 0], 0.1,
                                                np.zeros((4, 3)), deltas=d))
    assert msg.flags & P.FLAG_ZLIB and msg.flags & P.FLAG_DELTA
    assert np.abs(msg.positions - p).max() <= (hi - lo).max() / P.QMAX


def test_the_native_quantiser_refuses_what_is_not_a_mesh() -> None:
    for bad in (np.zeros((3, 4, 3)), np.zeros((3, 3, 2)), np.zeros((9, 3)), np.zeros((0, 0, 3))):
        with pytest.raises(ValueError):
            _native.quantise_mesh(bad)
