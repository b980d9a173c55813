"""``clothball falcon``: check a Novint Falcon, benchmark its loop, print the udev rule.

``clothball falcon check [--firmware FILE] [--emulator]`` finds the device, loads the
firmware (the user's own copy of Novint's file) when needed, guides homing, then shows live
position, buttons and loop rate. ``clothball falcon bench`` runs the 1 kHz loop (on the
emulator by default) and reports its rate and period percentiles.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np

from ..devices import falcon as F

BUTTON_NAMES = ((1, "plus"), (2, "forward"), (4, "centre"), (8, "minus"))


def configure(parser: argparse.ArgumentParser) -> None:
    sub = parser.add_subparsers(dest="falcon_command", metavar="ACTION", required=True)
    check = sub.add_parser("check", help="find the Falcon, load firmware, home, show live state")
    _device_options(check)
    check.add_argument("--seconds", type=float, default=None,
                       help="how long to show live state (default: until Ctrl-C; 3 s on the "
                            "emulator)")
    bench = sub.add_parser("bench", help="measure the 1 kHz loop's rate and period jitter")
    _device_options(bench)
    bench.add_argument("--seconds", type=float, default=5.0, help="measurement time (s)")
    bench.add_argument("--usb", action="store_true", help="bench a real Falcon, not the emulator")
    bench.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    sub.add_parser("udev", help="print the udev rule that gives users access to the Falcon")


def _device_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--firmware", metavar="FILE",
                   help="Novint's Falcon firmware file (yours; clothball does not ship it). "
                        f"Default: ${F.FIRMWARE_ENV} or [falcon] firmware in the config file")
    p.add_argument("--emulator", action="store_true", help="use the emulated Falcon")
    p.add_argument("--index", type=int, default=0, help="which Falcon when several are plugged")
    p.add_argument("--homing-timeout", type=float, default=60.0, help="seconds to finish homing")


def _buttons(mask: int) -> str:
    names = [n for bit, n in BUTTON_NAMES if mask & bit]
    return ",".join(names) if names else "-"


def _open(args: argparse.Namespace, emulator: bool) -> F.FalconDevice:
    settings = F.FalconSettings(homing_timeout=args.homing_timeout)
    return F.open_falcon(args.firmware, emulator=emulator, index=args.index, settings=settings,
                         status=print)


def _reach() -> F.Reach:
    # The check shows device coordinates: a reach equal to the Falcon's own cube.
    return F.Reach(F.CUBE_CENTRE.copy(), F.CUBE_HALF.copy())


def check(args: argparse.Namespace) -> int:
    if not args.emulator:
        # A build without libusb cannot count the bus: a 0 there would be a false figure.
        if F._f.usb_transport_available():
            print(f"Falcons on the USB bus: {F._f.count_usb_devices()}")
        else:
            print("Falcons on the USB bus: not known (this build has no USB transport)")
    try:
        dev = _open(args, args.emulator)
    except F.NoDeviceError as e:
        # A FalconError like the others: status 2, as docs/falcon.md says.
        print(f"clothball falcon check: {e}\n"
              "No Falcon at hand? Try the emulated one: clothball falcon check --emulator",
              file=sys.stderr)
        return 2
    try:
        dev.start(_reach())
        seconds = args.seconds if args.seconds is not None else (3.0 if args.emulator else None)
        if dev.emulator is not None:  # a scripted hand circles so there is something to see
            dev.emulator.set_user([0.02, 0.0, 0.125], 200.0, 5.0)
        print("position in metres, device frame (x right, y up, z out); Ctrl-C to stop")
        t0 = time.monotonic()
        while seconds is None or time.monotonic() - t0 < seconds:
            time.sleep(0.1)
            if dev.emulator is not None:
                a = time.monotonic() - t0
                dev.emulator.set_user([0.02 * np.cos(a), 0.02 * np.sin(a), 0.125], 200.0, 5.0)
            snap, st = dev.snapshot(), dev.stats()
            if snap["error"]:
                print(f"\nFalcon lost: {snap['error']}", file=sys.stderr)
                return 3
            x, y, z = snap["position"]
            print(f"\rx {x:+.4f}  y {y:+.4f}  z {z:.4f}  buttons {_buttons(snap['buttons']):<20}"
                  f" loop {st['rate']:7.1f} Hz  p99 {st['period_p99'] * 1e3:5.2f} ms",
                  end="", flush=True)
        print()
    except KeyboardInterrupt:
        print()
    finally:
        dev.stop()
    print("Falcon check: OK")
    return 0


def bench(args: argparse.Namespace) -> int:
    dev = _open(args, not args.usb)
    try:
        dev.start(_reach())
        # A realistic load: a corner spring the scripted hand pulls against.
        dev.driver.set_corner(F.CUBE_CENTRE.tolist(), [0, 0, 0], [500.0] * 3, [3.0] * 3, 0.0)
        if dev.emulator is not None:
            dev.emulator.set_user([0.01, 0.005, 0.13], 300.0, 5.0)
        time.sleep(0.2)  # warm-up
        dev.driver.reset_stats()
        t0 = time.monotonic()
        while time.monotonic() - t0 < args.seconds:
            time.sleep(0.05)
            dev.driver.set_corner(F.CUBE_CENTRE.tolist(), [0, 0, 0], [500.0] * 3, [3.0] * 3, 0.0)
        st = dev.stats()
        err = dev.snapshot()["error"]
    finally:
        dev.stop()
    result: dict[str, Any] = {
        "device": dev.name,
        "seconds": st["elapsed"],
        "ticks": st["ticks"],
        "rate_hz": st["rate"],
        "period_mean_ms": st["period_mean"] * 1e3,
        "period_p50_ms": st["period_p50"] * 1e3,
        "period_p99_ms": st["period_p99"] * 1e3,
        "period_max_ms": st["period_max"] * 1e3,
        "late_ticks": st["late_ticks"],
        "missed_replies": st["missed_replies"],
        "targets": {"rate_hz_min": 950.0, "period_p99_ms_max": 1.5},
    }
    result["meets_targets"] = bool(result["rate_hz"] >= 950.0 and result["period_p99_ms"] <= 1.5)
    print(f"Falcon loop on {dev.name}: {result['rate_hz']:.1f} Hz over {result['seconds']:.1f} s "
          f"({result['ticks']} ticks)")
    print(f"period: mean {result['period_mean_ms']:.3f} ms, p50 {result['period_p50_ms']:.3f} ms,"
          f" p99 {result['period_p99_ms']:.3f} ms, max {result['period_max_ms']:.3f} ms; "
          f"late (>1.5 ms) {result['late_ticks']}, missed replies {result['missed_replies']}")
    print("targets (>= 950 Hz, p99 <= 1.5 ms): " + ("met" if result["meets_targets"] else "MISSED"))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    if err:
        print(f"Falcon lost: {err}", file=sys.stderr)
        return 3
    return 0


def run(args: argparse.Namespace) -> int:
    if args.falcon_command == "udev":
        print(f"# {F.UDEV_PATH}\n{F.UDEV_RULE}")
        print("# then: sudo udevadm control --reload-rules && sudo udevadm trigger; replug")
        return 0
    try:
        return check(args) if args.falcon_command == "check" else bench(args)
    except F.FalconError as e:
        print(f"clothball falcon {args.falcon_command}: {type(e).__name__}: {e}", file=sys.stderr)
        return 2


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m clothball.game.cli.falcon")
    configure(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
