"""The Novint Falcon as a clothball input device.

``open_falcon()`` finds the device (or builds the emulator), makes sure its firmware runs
(uploading the user's own copy of Novint's file when needed) and returns a
:class:`FalconDevice`. ``start(reach)`` homes the device (the user pulls the grip out and
pushes it in) and starts the native 1 kHz loop, which renders the coupling force locally:

    F = g(age) * (-K (h - c_ext) - B (h_dot - c_dot)) - alpha * h_dot

from the latest corner state the server sent (``update_corner``), extrapolated by its
velocity, faded out when updates go stale and damped by a passivity controller (see
``docs/falcon.md``).

Mapping. The Falcon's usable cube (x, y in +/-0.03 m, z in [0.095, 0.155] m, device frame:
x right, y up, z out of the device towards the user) maps per axis and affinely onto the
corner's reach box: falcon x -> world x, falcon y -> world y (up), falcon z -> world z
(pulling the grip towards you moves the hand towards +z). ``axis_signs`` flips axes. Forces
are rendered at ``force_scale`` device newtons per world newton; a world stiffness K acting
over world displacements that are ``scale`` times the device displacement becomes the
device stiffness ``force_scale * K * scale`` per axis, capped at ``max_stiffness``.
"""

from __future__ import annotations

import logging
import os
import time
import tomllib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ... import _native
from .base import CornerState, Reach

log = logging.getLogger(__name__)
_f = _native.falcon

# Errors a user can act on (all derive from FalconError, a RuntimeError).
FalconError = _f.FalconError
NoDeviceError = _f.NoDeviceError
AccessDeniedError = _f.AccessDeniedError
FirmwareError = _f.FirmwareError
FirmwareLoadError = _f.FirmwareLoadError
HomingTimeoutError = _f.HomingTimeoutError
DeviceGoneError = _f.DeviceGoneError

CUBE_LO = np.array([-_f.CUBE_HALF_XY, -_f.CUBE_HALF_XY, _f.CUBE_Z_MIN])
CUBE_HI = np.array([_f.CUBE_HALF_XY, _f.CUBE_HALF_XY, _f.CUBE_Z_MAX])
CUBE_CENTRE = (CUBE_LO + CUBE_HI) / 2
CUBE_HALF = (CUBE_HI - CUBE_LO) / 2

FIRMWARE_ENV = "CLOTHBALL_FALCON_FIRMWARE"
UDEV_RULE: str = _f.udev_rule()
UDEV_PATH = "/etc/udev/rules.d/99-novint-falcon.rules"


def config_path() -> Path:
    """The user's clothball config file (TOML); ``[falcon] firmware = "..."`` names the file."""
    import platformdirs

    return Path(platformdirs.user_config_dir("clothball")) / "config.toml"


def configured_firmware() -> str | None:
    """The firmware path from ``$CLOTHBALL_FALCON_FIRMWARE`` or the config file, if any."""
    env = os.environ.get(FIRMWARE_ENV)
    if env:
        return env
    path = config_path()
    if path.is_file():
        try:
            with path.open("rb") as fh:
                value = tomllib.load(fh).get("falcon", {}).get("firmware")
        except (OSError, tomllib.TOMLDecodeError) as e:
            log.warning("could not read %s: %s", path, e)
            return None
        if value:
            return str(Path(str(value)).expanduser())
    return None


@dataclass(frozen=True)
class FalconMapping:
    """Per-axis affine map between the Falcon's usable cube and a corner's reach box."""

    reach: Reach
    axis_signs: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @property
    def signs(self) -> np.ndarray:
        return np.asarray(self.axis_signs, dtype=np.float64)

    @property
    def scale(self) -> np.ndarray:
        """World metres per device metre, per axis."""
        return np.asarray(self.reach.half_extent, dtype=np.float64) / CUBE_HALF

    def to_world(self, p_device: npt.ArrayLike) -> np.ndarray:
        u = (np.asarray(p_device, dtype=np.float64) - CUBE_CENTRE) / CUBE_HALF * self.signs
        return self.reach.from_unit(u)

    def to_device(self, p_world: np.ndarray) -> np.ndarray:
        """Inverse of ``to_world`` (not clamped: corners may sit outside the reach box)."""
        u = (np.asarray(p_world, dtype=np.float64) - self.reach.centre) / self.reach.half_extent
        return CUBE_CENTRE + u * self.signs * CUBE_HALF

    def velocity_to_device(self, v_world: np.ndarray) -> np.ndarray:
        return np.asarray(v_world, dtype=np.float64) / self.scale * self.signs

    def force_to_world(self, f_device: np.ndarray, force_scale: float) -> np.ndarray:
        return np.asarray(f_device, dtype=np.float64) * self.signs / force_scale


@dataclass
class FalconSettings:
    """How the Falcon renders the corner (device units unless said otherwise)."""

    force_scale: float = 1.0  # device newtons per world newton
    max_stiffness: float = 1000.0  # N/m per axis (the Falcon is stable up to ~3000)
    damping: float = 3.0  # N s/m, relative-velocity coupling damping
    max_force: float = 6.0  # N (the motors give about 8 N)
    stale_after: float = 0.100  # s
    fade_out: float = 0.050  # s
    fade_in: float = 0.250  # s
    passivity: bool = True
    homing_timeout: float = 60.0  # s
    axis_signs: tuple[float, float, float] = (1.0, 1.0, 1.0)
    extra: dict[str, Any] = field(default_factory=dict)

    def driver_config(self) -> _f.DriverConfig:
        cfg = _f.DriverConfig()
        c = cfg.coupling
        c.max_stiffness = self.max_stiffness
        c.max_force = self.max_force
        c.stale_after = self.stale_after
        c.fade_out = self.fade_out
        c.fade_in = self.fade_in
        c.passivity = self.passivity
        cfg.coupling = c
        return cfg


class FalconDevice:
    """A Novint Falcon (or its emulator) driving one corner; implements ``base.Device``."""

    def __init__(
        self,
        driver: _f.Driver,
        *,
        emulator: _f.EmulatorTransport | None = None,
        settings: FalconSettings | None = None,
        clock: Callable[[], float] = time.monotonic,
        status: Callable[[str], None] | None = None,
    ) -> None:
        self.driver = driver
        self.emulator = emulator
        self.settings = settings or FalconSettings()
        self.name = "falcon-emulator" if emulator is not None else "falcon"
        self._clock = clock
        self._status = status or (lambda msg: log.info("%s", msg))
        self.mapping: FalconMapping | None = None
        self._last_world: np.ndarray | None = None
        self._error: str | None = None
        self._stopped = False

    # -- base.Device -------------------------------------------------------------------
    def start(self, reach: Reach) -> None:
        self.mapping = FalconMapping(reach, self.settings.axis_signs)
        self._last_world = np.asarray(reach.centre, dtype=np.float64).copy()
        if self.driver.snapshot()["homed"] != 0x7:
            self.home()
        self.driver.start()

    def stop(self) -> None:
        if self._stopped:
            return
        self._stopped = True
        self.driver.stop()
        self.driver.close()

    def hand_position(self) -> np.ndarray:
        if self.mapping is None:
            raise FalconError("FalconDevice.start(reach) first")
        snap = self.driver.snapshot()
        if snap["error"] is not None:
            self._gone(snap["error"])
        else:
            self._last_world = self.mapping.reach.clamp(self.mapping.to_world(snap["position"]))
        assert self._last_world is not None
        return self._last_world.copy()

    def update_corner(self, state: CornerState) -> None:
        if self.mapping is None or self._error is not None:
            return
        m, s = self.mapping, self.settings
        k_dev = s.force_scale * float(state.stiffness) * m.scale
        b_dev = np.full(3, s.damping)
        age = max(0.0, self._clock() - float(state.received_at))
        try:
            self.driver.set_corner(
                m.to_device(state.position).tolist(),
                m.velocity_to_device(state.velocity).tolist(),
                k_dev.tolist(),
                b_dev.tolist(),
                age,
            )
        except FalconError as e:  # non-finite input: drop the sample, keep the last one
            log.debug("corner sample refused: %s", e)

    # -- Falcon specifics --------------------------------------------------------------
    def home(self, timeout: float | None = None) -> None:
        """Homing mode until all three encoders are homed (HomingTimeoutError)."""
        self._status(
            "Falcon: homing - pull the grip all the way out, then push it all the way in "
            "(the LED turns green when done)"
        )
        self.driver.home(self.settings.homing_timeout if timeout is None else timeout)
        self._status("Falcon: homed")

    @property
    def error(self) -> str | None:
        """Why the device stopped (unplugged, not answering), or None while it works."""
        if self._error is None:
            err = self.driver.snapshot()["error"]
            if err is not None:
                self._gone(err)
        return self._error

    def _gone(self, err: str) -> None:
        if self._error is None:
            self._error = err
            log.warning(
                "Falcon lost: %s. Your corner rests where it was and the game goes on; "
                "replug the Falcon and rejoin to play on.",
                err,
            )

    def buttons(self) -> int:
        return int(self.driver.snapshot()["buttons"])

    def snapshot(self) -> dict[str, Any]:
        """The loop's latest tick (device frame): position, force, motor, gain, alpha, ..."""
        return dict(self.driver.snapshot())

    def stats(self) -> dict[str, float]:
        """Loop statistics: rate (Hz), period mean/p50/p99/max (s), late ticks, misses."""
        return dict(self.driver.stats())

    def hold(
        self, world_target: np.ndarray, stiffness: float = 300.0, damping: float = 5.0
    ) -> None:
        """Emulator only: a scripted user pulls the grip towards a world point."""
        if self.emulator is None or self.mapping is None:
            raise FalconError("hold() needs the emulator and a started device")
        self.emulator.set_user(self.mapping.to_device(world_target).tolist(), stiffness, damping)


def open_falcon(
    firmware: str | os.PathLike[str] | None = None,
    *,
    emulator: bool = False,
    index: int = 0,
    settings: FalconSettings | None = None,
    emulator_options: _f.EmulatorOptions | None = None,
    firmware_options: _f.FirmwareOptions | None = None,
    status: Callable[[str], None] | None = None,
) -> FalconDevice:
    """Open a Falcon (USB, or the emulator) with its firmware running, not yet homed.

    ``firmware`` defaults to ``$CLOTHBALL_FALCON_FIRMWARE`` or ``[falcon] firmware`` in the
    config file; it is only needed when the device is not running firmware yet. The
    emulator starts with its firmware loaded unless a firmware file is given (then it is
    uploaded to it like to a real device). Raises NoDeviceError, AccessDeniedError (with
    the udev rule), FirmwareError, FirmwareLoadError.
    """
    settings = settings or FalconSettings()
    path = os.fspath(firmware) if firmware is not None else configured_firmware()
    emu = None
    transport: _f.Transport
    if emulator:
        opts = emulator_options or _f.EmulatorOptions()
        if emulator_options is None:
            opts.firmware_loaded = path is None
        emu = _f.EmulatorTransport(opts)
        transport = emu
    else:
        transport = _f.open_usb_transport(index)
    driver = _f.Driver(transport, settings.driver_config())
    say = status or (lambda msg: log.info("%s", msg))
    try:
        if not driver.firmware_loaded():
            say(f"Falcon: loading firmware from {path}" if path else "Falcon: no firmware")
            attempts = driver.ensure_firmware(path or "", firmware_options or _f.FirmwareOptions())
            say(f"Falcon: firmware loaded ({attempts} attempt{'s' if attempts != 1 else ''})")
    except BaseException:
        driver.close()
        raise
    return FalconDevice(driver, emulator=emu, settings=settings, status=status)


__all__ = [
    "AccessDeniedError",
    "DeviceGoneError",
    "FalconDevice",
    "FalconError",
    "FalconMapping",
    "FalconSettings",
    "FirmwareError",
    "FirmwareLoadError",
    "HomingTimeoutError",
    "NoDeviceError",
    "UDEV_RULE",
    "configured_firmware",
    "open_falcon",
]
