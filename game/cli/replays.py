"""``clothball replays``: the host's recorded rounds, from the data directory itself.

    clothball replays list [--limit N] [--room R] [--player P] [--json]
    clothball replays prune [--max-mib M] [--max-days D] [--dry-run]
    clothball replays export ID [ID ...] --to PATH

It reads and writes the index beside a running server (SQLite waits for the server's
writes; leftover ``.tmp`` files, the server's rounds being written, are left alone). The
host sees every round, private rooms' included. ``--data`` as for ``clothball host``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sqlite3
import sys
import time
from pathlib import Path
from typing import Any

from ...server.app import default_data_dir
from ...server.limits import DEFAULT
from ...server.storage.index import ReplayIndex, Retention
from ...server.storage.sqlite import SqliteIndex


def _positive(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number > 0, got {text!r}") from None
    if not (v > 0 and v != float("inf")):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}")
    return v


def configure(parser: argparse.ArgumentParser) -> None:
    data_help = f"the server's data directory (default: {default_data_dir()})"
    parser.add_argument("--data", type=Path, default=None, help=data_help)
    # --data after the action too (`clothball replays list --data DIR`)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--data", type=Path, default=argparse.SUPPRESS, help=data_help)
    sub = parser.add_subparsers(dest="action", metavar="ACTION", required=True)
    ls = sub.add_parser("list", help="the recorded rounds, newest first", parents=[common])
    ls.add_argument("--limit", type=int, default=50, help="at most N rounds (default 50)")
    ls.add_argument("--room", default=None, help="only this room's rounds (its id)")
    ls.add_argument("--player", default=None, help="only rounds where a seat had this name")
    ls.add_argument("--json", action="store_true", help="one JSON object per line")
    pr = sub.add_parser("prune", help="remove the rounds retention would not keep, oldest "
                                      "first (each file with its index row)", parents=[common])
    pr.add_argument("--max-mib", type=_positive, default=DEFAULT.replays_max_mib,
                    help="keep at most this many MiB of rounds (default %(default)g, the "
                         "server's replays_max_mib)")
    pr.add_argument("--max-days", type=_positive, default=DEFAULT.replays_max_days,
                    help="keep no round older than this (default %(default)g, the server's "
                         "replays_max_days)")
    pr.add_argument("--dry-run", action="store_true", help="list what would go, remove nothing")
    ex = sub.add_parser("export", help="copy rounds' files (.cbr, for `clothball replay`)",
                        parents=[common])
    ex.add_argument("ids", nargs="+", metavar="ID", help="round ids (from `replays list`)")
    ex.add_argument("--to", type=Path, required=True, metavar="PATH",
                    help="a directory (each round as ID.cbr in it) or, for one round, a file")


def _fail(msg: str) -> int:
    print(f"clothball replays: {msg}", file=sys.stderr)
    return 1


def _line(r: dict[str, Any]) -> str:
    when = time.strftime("%Y-%m-%d %H:%M", time.localtime(r["ended_at"]))
    names = ", ".join(p.get("name") or "-" for p in r["players"] if isinstance(p, dict))
    private = "  private" if r["private"] else ""
    return (f"{r['id']}  {when}  room {r['room_name']}  round {r['round']}  "
            f"{r['duration_s']:.1f} s  {r['bytes'] / 2**20:.2f} MiB  [{names}]{private}")


def run(args: argparse.Namespace) -> int:
    data: Path = args.data or default_data_dir()
    index = data / "index.sqlite"
    if not index.is_file():
        return _fail(f"no replay index in {data} (no {index.name}); name the server's data "
                     "directory with --data")
    try:
        # Listing and exporting write nothing: they work on a read-only or full disk too.
        store = SqliteIndex(data, recover=False) if args.action == "prune" else \
            SqliteIndex(data, read_only=True)
    except (OSError, sqlite3.Error) as e:
        return _fail(f"cannot open the replay index in {data}: {e}")
    try:
        return _ACTIONS[args.action](store, args)
    except sqlite3.OperationalError as e:
        return _fail(f"the replay index in {data} is not usable now ({e}); is a server "
                     "holding it locked? Try again shortly")
    finally:
        store.close()


def _list(store: ReplayIndex, args: argparse.Namespace) -> int:
    rows = store.list_all(limit=max(1, args.limit), room_id=args.room, player=args.player)
    for r in rows:
        print(json.dumps(r) if args.json else _line(r))
    if not args.json:
        total = store.count_all(room_id=args.room, player=args.player)
        print(f"{len(rows)} of {total} rounds shown; {store.rounds} rounds, "
              f"{store.bytes / 2**20:.1f} MiB in {store.dir}")
    return 0


def _prune(store: ReplayIndex, args: argparse.Namespace) -> int:
    keep = Retention(int(args.max_mib * 2**20), args.max_days * 86400.0)
    gone = store.prune(keep, dry_run=args.dry_run, limit=None)
    for r in gone:
        print(("would remove " if args.dry_run else "removed ") + _line(r))
    mib = sum(r["bytes"] for r in gone) / 2**20
    verb = "would remove" if args.dry_run else "removed"
    print(f"{verb} {len(gone)} rounds ({mib:.1f} MiB) to keep {keep.describe()}; "
          f"{store.rounds} rounds, {store.bytes / 2**20:.1f} MiB left")
    return 0


def _export(store: ReplayIndex, args: argparse.Namespace) -> int:
    dest: Path = args.to
    if len(args.ids) > 1 and not dest.is_dir():
        return _fail(f"--to {dest} must be an existing directory to export "
                     f"{len(args.ids)} rounds")
    sources = []
    for rid in args.ids:
        path = store.file_of(rid)
        if path is None:
            return _fail(f"no round {rid!r} in {store.dir}; `clothball replays list` shows "
                         "the ids")
        sources.append((rid, path))
    for rid, path in sources:
        target = dest / f"{rid}.cbr" if dest.is_dir() else dest
        if target.exists():
            return _fail(f"{target} exists; remove it or choose another --to")
        try:
            shutil.copyfile(path, target)
        except FileNotFoundError:
            if not target.parent.is_dir():
                return _fail(f"cannot write {target}: no directory {target.parent}")
            return _fail(f"round {rid!r} was removed while being exported")
        except OSError as e:
            return _fail(f"cannot write {target}: {e.strerror or e}")
        print(f"{rid} -> {target}")
    return 0


_ACTIONS = {"list": _list, "prune": _prune, "export": _export}
