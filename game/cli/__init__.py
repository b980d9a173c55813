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
            p.set_defaults(_missing=unavailable(module, e))
    return parser


# Python packages whose pip name is not the name they are imported by.
PIP_NAMES = {"psycopg": "'psycopg[binary]'", "matplotlib": "matplotlib (or pip install '.[study]')"}


def unavailable(module: str, e: Exception) -> str:
    """Why a command whose module failed to import cannot run, and what to install."""
    missing = e.name if isinstance(e, ModuleNotFoundError) and e.name else None
    if missing is None:
        return f"importing {module} failed ({type(e).__name__}: {e})"
    top = missing.split(".")[0]
    if top == "clothball":
        fix = "this installation of clothball is incomplete: reinstall it (pip install .)"
    else:
        fix = f"pip install {PIP_NAMES.get(top, top)}"
    return f"importing {module} failed: the Python module {missing!r} is not installed ({fix})"


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    # Known arguments first: a command that could not be imported has no options of its
    # own, so its arguments would be refused before saying what is missing.
    args, extra = parser.parse_known_args(argv)
    if getattr(args, "_missing", None):
        print(f"clothball {args.command}: not available: {args._missing}", file=sys.stderr)
        return 2
    if extra:
        parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.argv = list(sys.argv[1:] if argv is None else argv)  # as given (host --workers)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO, format="%(message)s"
    )
    try:
        return int(importlib.import_module(args._module).run(args) or 0)
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
