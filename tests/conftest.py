"""Shared fixtures and helpers.

GPU tests are generated per backend: they skip where no CUDA device is present, unless
CLOTHBALL_REQUIRE_GPU=1, which turns those skips into failures. Server helpers are in
``tests/server/conftest.py``; nothing here needs more than the engine (the GPU machine runs
the engine tests without the server's dependencies).

Randomised (hypothesis) tests draw the same examples on every run unless asked otherwise:
``HYPOTHESIS_PROFILE`` picks a profile, ``ci`` by default (derandomised: the examples are
a function of the test, so a run fails or passes for what the code does, not for what
was drawn; no example database), ``wide`` for a hunt (a random seed each run, failures
saved in ``.hypothesis/`` and tried first next time, 10x the examples: ``WIDE_FACTOR``).
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Callable

import pytest
from clothball.game import cuda_unavailable_reason

REQUIRE_GPU = os.environ.get("CLOTHBALL_REQUIRE_GPU", "") not in ("", "0")
PROFILE = os.environ.get("HYPOTHESIS_PROFILE", "ci")
WIDE_FACTOR = 10  # the wide profile's examples per test, over the default's


def examples(n: int) -> int:
    """A test's example count ``n`` as run under the chosen profile (``wide``: more)."""
    return n * WIDE_FACTOR if PROFILE == "wide" else n


try:
    from hypothesis import settings
except ImportError:  # the engine tests alone (the GPU machine) need no hypothesis
    pass
else:
    settings.register_profile("ci", derandomize=True, database=None)
    settings.register_profile("wide", derandomize=False, max_examples=examples(100))
    if PROFILE not in ("ci", "wide"):
        raise pytest.UsageError(f"HYPOTHESIS_PROFILE={PROFILE!r}: the profiles are ci "
                                "(the default, derandomised) and wide (random, more examples)")
    settings.load_profile(PROFILE)


def require_cuda() -> None:
    why = cuda_unavailable_reason()
    if why:
        if REQUIRE_GPU:
            pytest.fail(f"CLOTHBALL_REQUIRE_GPU=1 but the CUDA backend is unavailable: {why}")
        pytest.skip(f"no CUDA backend: {why}")


def usb_transport_missing() -> str:
    """Why this build of the native module cannot reach a real Falcon ('' when it can):
    CMake leaves the USB transport out where libusb-1.0 is not installed."""
    from clothball._native import falcon

    if falcon.usb_transport_available():
        return ""
    return ("this build has no USB Falcon transport (libusb-1.0 was not found when it was "
            "built): apt-get install libusb-1.0-0-dev pkg-config, then reinstall (pip install .)")


# A test of the real Falcon's USB path (its errors without a device): skipped, saying what
# to install, in a build without the transport.
needs_usb_transport = pytest.mark.skipif(bool(usb_transport_missing()),
                                         reason=usb_transport_missing() or "USB transport built")


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
