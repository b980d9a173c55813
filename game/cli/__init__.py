"""The ``clothball`` command. Each subcommand lives in its own module, imported lazily,
which provides ``configure(parser)`` and ``run(args) -> int``."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "bench": ("clothball.game.cli.bench", "measure time per substep (the paper's Table 1)"),
    "accuracy": ("clothball.game.cli.accuracy", "error against wall time per integrator, "
                 "precision, step and grid size"),
    "scenes": ("clothball.game.cli.scenes", "list the shipped scenes and their effects"),
    "falcon": ("clothball.game.cli.falcon", "check a Novint Falcon and bench its 1 kHz loop"),
    "host": ("clothball.game.cli.host", "run a game server (rooms, bots, spectators, replays)"),
    "play": ("clothball.game.cli.play", "play in a desktop window (mouse, Falcon or bot)"),
    "replay": ("clothball.game.cli.replay", "play a recorded round back (pause, seek, speed)"),
    "replays": ("clothball.game.cli.replays", "list, prune and export the host's recorded "
                "rounds (its data directory)"),
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="clothball", description="Real-time haptic cloth game and its cloth engine."
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log more")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        try:
            importlib.import_module(module).configure(p)
        except Exception as e:  # noqa: BLE001 - one broken command must not break the others
            p.set_defaults(_missing=f"{type(e).__name__}: {e}")
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # as given (host --workers)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s"
    )
    if getattr(args, "_missing", None):
        print(f"clothball {args.command}: not available ({args._missing})", file=sys.stderr)
        return 2
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
