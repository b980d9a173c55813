"""Shared fixtures and helpers.

GPU tests are generated per backend: they skip where no CUDA device is present, unless
CLOTHBALL_REQUIRE_GPU=1, which turns those skips into failures. Server helpers are in
``tests/server/conftest.py``; nothing here needs more than the engine (the GPU machine runs
the engine tests without the server's dependencies).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable

import pytest
from clothball.game import cuda_unavailable_reason

REQUIRE_GPU = os.environ.get("CLOTHBALL_REQUIRE_GPU", "") not in ("", "0")


def require_cuda() -> None:
    why = cuda_unavailable_reason()
    if why:
        if REQUIRE_GPU:
            pytest.fail(f"CLOTHBALL_REQUIRE_GPU=1 but the CUDA backend is unavailable: {why}")
        pytest.skip(f"no CUDA backend: {why}")


@pytest.fixture(params=["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def backend(request: pytest.FixtureRequest) -> str:
    if request.param == "cuda":
        require_cuda()
    return request.param


@pytest.fixture
def cuda() -> str:
    """The CUDA backend, for tests of it alone."""
    require_cuda()
    return "cuda"


@pytest.fixture(params=["float32", "float64"])
def precision(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture
def clothball_cli() -> Callable[..., subprocess.CompletedProcess[str]]:
    """Runs ``clothball ARGS`` in a subprocess of this interpreter, output captured."""

    def run(*args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "clothball.game.cli", *args],
                              capture_output=True, text=True, timeout=timeout)

    return run
