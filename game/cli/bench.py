"""``clothball bench``: time per substep (the paper's Table 1 re-measured, ``--effects``),
the rooms and the largest cloth one engine steps at 1 kHz (``--rooms``, ``--largest``), a
MESH's encoder (``--mesh``), the game server under load (``--server``, ``--load``), or its
replay index's HTTP queries at scale (``--index``)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ... import _native
from ...server.bench import (
    admitbench,
    emptybench,
    indexbench,
    loadbench,
    soakbench,
    upgradebench,
)
from ...server.room import RoomSettings
from ...server.thread import ServerThread
from ..rules import EDGE_NAMES
from ..sim.cloth import cuda_unavailable_reason
from ..sim.scene import Scene, SceneError
from ..sim.threads import busy_note
from ..study import largest, meshcode, rooms, rounds
from ..study.bench import (
    csv_list,
    gpu_target_verdicts,
    print_effects,
    print_skip_check,
    print_table,
    run_effects,
    run_table,
    select_backends,
)

GAME_SCENE = "default"  # the shipped game's scene (classic is the paper's set-up)
LARGEST_SCENE = "classic"  # --largest: the paper's scene, then the game's


def configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quick", action="store_true", help="a short run: few sizes, few repeats")
    p.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    p.add_argument("--scene", default=None,
                   help=f"scene name or path (default classic; --rounds: {GAME_SCENE})")
    p.add_argument("--sizes", help="comma-separated n values (default: the paper's sizes)")
    p.add_argument("--backends", default="auto", help="cpu,cuda or auto (every one present)")
    p.add_argument("--precisions", default="float32,float64", help="float32,float64")
    p.add_argument("--repeats", type=int, default=None,
                   help="timed repeats (median taken); --largest: each size timed this many "
                        "times, judged by the median of the p99s (default 3)")
    p.add_argument(
        "--effects",
        action="store_true",
        help="time each effect alone and added one at a time (on --scene, default classic)",
    )
    p.add_argument(
        "--rooms", action="store_true",
        help="how many rooms (batched cloths, hands in and corners out, no network) one "
             "engine steps at 1 kHz, per backend and n (--sizes; default 16,60)",
    )
    p.add_argument(
        "--largest", action="store_true",
        help="the largest n one cloth steps at 1 kHz (frame p99 <= 1 ms, corners read each "
             "frame), bisected per scene (--scene; default classic and default) and precision, "
             "with the bytes a frame moves against the copy bandwidth",
    )
    p.add_argument("--largest-frames", type=int, default=300, metavar="F",
                   help="--largest: frames timed per size (default %(default)s)")
    p.add_argument("--largest-max", type=int, default=largest.MAX_N, metavar="N",
                   help="--largest: the largest n tried (default %(default)s)")
    p.add_argument(
        "--mesh", action="store_true",
        help="the server's MESH encoder, µs and bytes a message, version 2 beside version 1, "
             "on the game's cloth from its start, per n (--sizes; default 16,48,96)",
    )
    p.add_argument("--mesh-rounds", type=int, default=50, metavar="R",
                   help="--mesh: times each cloth state is encoded per version "
                        "(default %(default)s)")
    p.add_argument("--rooms-frames", type=int, default=300, metavar="F",
                   help="--rooms: frames timed per room count (default %(default)s)")
    p.add_argument("--max-rooms", type=int, default=4096, metavar="K",
                   help="--rooms: stop growing at K rooms (default %(default)s)")
    p.add_argument(
        "--rounds", type=int, default=None, metavar="N",
        help="time N rounds of four bots in a real room (a server on loopback); prints "
             "their lengths, median and distribution (--json: every round)",
    )
    p.add_argument(
        "--server", action="store_true", help="benchmark the game server instead (see --help)"
    )
    p.add_argument(
        "--load", action="store_true",
        help="how many rooms (4 players at the desktop client's rates + spectators) the server "
             "holds with frame lateness and CORNER delivery within target",
    )
    p.add_argument(
        "--index", action="store_true",
        help="the replay index's HTTP queries with 100 000 rounds, and /healthz meanwhile",
    )
    loadbench.configure_server_flags(p)
    indexbench.configure_index_flags(p)
    emptybench.configure_empty_flags(p)
    soakbench.configure_soak_flags(p)
    admitbench.configure_admit_flags(p)
    upgradebench.configure_upgrade_flags(p)


def run(args: argparse.Namespace) -> int:
    if args.rounds is not None:
        return run_rounds_cmd(args)
    if args.largest:
        return run_largest_cmd(args)
    if args.upgrades:
        return upgradebench.run_upgrades(args)
    if args.server or args.load:  # their scene: classic at n = 64 unless --scene says
        # Checked here, before any server process starts (its failure is a traceback there).
        why = cuda_unavailable_reason() if args.server_backend == "cuda" else ""
        if why:
            print(f"clothball bench: --server-backend cuda: {why}", file=sys.stderr)
            return 2
        return loadbench.run_load(args) if args.load else loadbench.run(args)
    if args.scene is None:  # the burst is issue 40's: `clothball host`'s own scene
        args.scene = "default" if args.admit_burst else "classic"
    if args.empty_rooms is not None:
        return emptybench.run_empty(args)
    if args.soak:
        return soakbench.run_soak(args)
    if args.admit:
        return admitbench.run_admit(args)
    if args.index:
        return indexbench.run(args)
    busy = busy_note()  # looked at before the bench's own work starts
    if busy:
        print(busy, file=sys.stderr, flush=True)
    if args.mesh:
        code = run_mesh_cmd(args)
        if busy and code == 0:
            print(busy)
        return code
    if args.rooms:
        code = run_rooms_cmd(args)
        if busy and code == 0:
            print(busy)
        return code
    if args.effects:
        try:
            rows = run_effects(args)
        except (ValueError, SceneError) as e:
            print(f"clothball bench: {e}", file=sys.stderr)
            return 2
        print_effects(rows)
        print("\nball contact skipped while the ball is off the cloth:")
        print_skip_check(rows)
        if args.json:
            Path(args.json).write_text(json.dumps({"rows": rows, "argv": sys.argv[1:]}, indent=2))
            print(f"wrote {args.json}")
        return 0
    try:
        rows = run_table(args)
    except (ValueError, SceneError) as e:
        print(f"clothball bench: {e}", file=sys.stderr)
        return 2
    copy_gbs = None
    if any(r["backend"] == "cuda" for r in rows):
        copy_gbs = _native.cuda_copy_bandwidth_gbs(1 << 30)
        print(f"device-to-device copy: {copy_gbs:.0f} GB/s (read + write)")
    print_table(rows, copy_gbs)
    if busy:
        print(busy)
    verdicts = gpu_target_verdicts(rows, copy_gbs)
    if verdicts:
        print("\nissue 2's GPU targets (stated for an H100):")
        for line in verdicts:
            print("  " + line)
    if args.json:
        out = {"rows": rows, "copy_gbs": copy_gbs, "argv": sys.argv[1:]}
        Path(args.json).write_text(json.dumps(out, indent=2))
        print(f"wrote {args.json}")
    return 0


def run_rooms_cmd(args: argparse.Namespace) -> int:
    from tqdm import tqdm  # noqa: PLC0415

    try:
        base = Scene.load(args.scene)
        backends = select_backends(args)
        precisions = (["float32"] if args.precisions == "float32,float64"
                      else csv_list(args.precisions, "precisions", ("float32", "float64")))
        sizes = [int(s) for s in csv_list(args.sizes or "16,60", "sizes")]
        if any(not 2 <= s <= 512 for s in sizes):
            raise ValueError("--sizes: each n must be in 2..512 for --rooms")
        if not 10 <= args.rooms_frames <= 100_000:
            raise ValueError("--rooms-frames: must be in 10..100000")
        if not 1 <= args.max_rooms <= 65_536:
            raise ValueError("--max-rooms: must be in 1..65536")
    except (ValueError, SceneError) as e:
        print(f"clothball bench: {e}", file=sys.stderr)
        return 2
    cases = [(b, p, n) for b in backends for p in precisions for n in sizes]
    with tqdm(desc="rooms", unit="count", file=sys.stderr) as bar:
        def progress(label: str) -> None:
            bar.set_postfix_str(label[:70])
            bar.update(1)

        rows = rooms.run_rooms(base, cases, args.rooms_frames, args.max_rooms, progress)
    rooms.print_rooms(rows)
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "argv": sys.argv[1:]}, indent=2))
        print(f"wrote {args.json}")
    return 0


def run_mesh_cmd(args: argparse.Namespace) -> int:
    try:
        items = csv_list(args.sizes or "16,48,96", "sizes")
        if not all(s.isdigit() and 2 <= int(s) <= 1024 for s in items):
            raise ValueError("--sizes: each n must be an integer in 2..1024 for --mesh")
        sizes = [int(s) for s in items]
        if not 1 <= args.mesh_rounds <= 100_000:
            raise ValueError("--mesh-rounds: must be in 1..100000")
    except ValueError as e:
        print(f"clothball bench: {e}", file=sys.stderr)
        return 2
    backend = "auto" if args.backends == "auto" else csv_list(args.backends, "backends")[0]
    rows = meshcode.run_mesh(sizes, args.mesh_rounds, backend,
                             lambda label: print(f"  {label} done", file=sys.stderr))
    meshcode.print_mesh(rows)
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows, "argv": sys.argv[1:]}, indent=2))
        print(f"wrote {args.json}")
    return 0


def run_largest_cmd(args: argparse.Namespace) -> int:
    """The largest cloth held at 1 kHz per scene and precision (``game.study.largest``)."""
    from tqdm import tqdm  # noqa: PLC0415

    try:
        scenes = [Scene.load(name) for name in (
            [args.scene] if args.scene else [LARGEST_SCENE, GAME_SCENE])]
        backends = select_backends(args)
        if args.backends == "auto":
            backends = backends[-1:]  # the GPU where there is one
        precisions = csv_list(args.precisions, "precisions", ("float32", "float64"))
        if not 10 <= args.largest_frames <= 100_000:
            raise ValueError("--largest-frames: must be in 10..100000")
        if not largest.STEP_N <= args.largest_max <= 8192:
            raise ValueError(f"--largest-max: must be in {largest.STEP_N}..8192")
        repeats = largest.REPEATS if args.repeats is None else args.repeats
        if not 1 <= repeats <= 100:
            raise ValueError("--repeats: must be in 1..100")
    except (ValueError, SceneError) as e:
        print(f"clothball bench: {e}", file=sys.stderr)
        return 2
    copy_gbs = _native.cuda_copy_bandwidth_gbs(1 << 30) if "cuda" in backends else None
    cases = [(sc, b, p) for sc in scenes for b in backends for p in precisions]
    with tqdm(desc="largest", unit="size", file=sys.stderr) as bar:
        def progress(label: str) -> None:
            bar.set_postfix_str(label[:70])
            bar.update(1)

        rows = largest.run_largest(cases, args.largest_frames, args.largest_max, copy_gbs,
                                   progress, repeats)
    largest.print_largest(rows, copy_gbs)
    if args.json:
        out = {"rows": rows, "copy_gbs": copy_gbs, "repeats": repeats,
               "frames": args.largest_frames, "argv": sys.argv[1:]}
        Path(args.json).write_text(json.dumps(out, indent=2))
        print(f"wrote {args.json}")
    return 0


def run_rounds_cmd(args: argparse.Namespace) -> int:
    """Four bots (the rooms' default skill) play in a server on loopback; a spectator times
    ``--rounds`` rounds (``game.study.rounds``)."""
    import asyncio  # noqa: PLC0415
    import tempfile  # noqa: PLC0415

    try:
        if not 1 <= args.rounds <= 10_000:
            raise ValueError(f"--rounds: must be in 1..10000, got {args.rounds}")
        scene = Scene.load(args.scene or GAME_SCENE)
        backend = select_backends(args)[0]
    except (ValueError, SceneError) as e:
        print(f"clothball bench: {e}", file=sys.stderr)
        return 2
    # The game's room settings, but a short pause between matches: it is no round's part.
    settings = RoomSettings(autoplay=True, restart_delay=1.0)
    print(f"{args.rounds} rounds of 4 bots (skill {settings.bot_difficulty:g}) on scene "
          f"{scene.name} (n {scene.n}, {backend}), countdown {settings.countdown:g} s",
          flush=True)

    def progress(r: rounds.Round) -> None:
        print(f"  round {r.round}: {r.seconds:5.1f} s (ball off the {EDGE_NAMES[r.edge]} "
              f"edge)", file=sys.stderr, flush=True)

    with tempfile.TemporaryDirectory(prefix="clothball-rounds-") as data:
        sys.setswitchinterval(0.0005)  # the room thread needs the GIL briefly every frame
        with ServerThread(Path(data), scenes={scene.name: scene}, backend=backend, bots=4,
                          room_settings=settings) as st:
            room = st.call(lambda srv: srv.main_room.id)
            try:
                played = asyncio.run(rounds.watch_rounds(st.ws_url, room, args.rounds,
                                                         progress=progress))
            except (TimeoutError, ConnectionError) as e:
                print(f"clothball bench: {e}", file=sys.stderr)
                return 1
            skipped = st.call(lambda srv: srv.main_room.sim.stats.skipped_frames)
    summary = rounds.summarise(played)
    summary.update(scene=scene.name, n=scene.n, backend=backend,
                   bot_difficulty=settings.bot_difficulty, skipped_frames=int(skipped))
    rounds.print_rounds(summary, played)
    if skipped:
        print(f"note: the room dropped {skipped} frames (a loaded machine); lengths count "
              "the frames simulated", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(
            {"summary": summary, "rounds": rounds.as_json(played), "argv": sys.argv[1:]},
            indent=2))
        print(f"wrote {args.json}")
    return 0
