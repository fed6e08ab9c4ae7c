"""``wiggly batch INPUT...``: many shots, from scene files or a sweep, locally or on Ray."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from wiggly.errors import counted, warn

HELP = "run many shots: scene files or a sweep, locally or on a Ray cluster"
DESCRIPTION = """\
Run many shots: scene files (docs/scene-format.md) or a sweep file, which names a
base scene and grids or random draws over its parameters (docs/sweep-format.md).
Shots run on one worker process per core, or on a Ray cluster with --ray. Each
distinct body (mesh, material, modes, fixed groups) is prepared once and shared.
Each shot writes its outputs into a folder of its own, with its scene.toml and
result.json; the batch writes summary.csv, summary.json and contact sheets
(contact-sheet.html, contact-sheet.png). A shot that fails is reported and never
stops the others. Running the same batch again skips the shots already done.
Exit code 0 when every shot succeeded, 1 when any failed (or the inputs are
invalid), 2 for a usage error."""
EPILOG = """\
examples:
  wiggly batch shots/*.toml -o out/shots
  wiggly batch examples/sweeps/jump_sweep.toml           # into the sweep's [output] dir
  wiggly batch sweep.toml -j 4 --write shot.glb --write preview.gif
  wiggly batch sweep.toml --ray                          # a new local Ray cluster
  wiggly batch sweep.toml --ray-address auto             # the cluster this machine is in
  wiggly batch sweep.toml --dry-run                      # list the shots, run nothing
  wiggly batch --schema > sweep.schema.json              # JSON Schema of sweep files

Ray is an optional extra: pip install "wiggly[ray]"."""


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("inputs", metavar="INPUT", nargs="*",
                        help="scene files and sweep files (.toml)")
    parser.add_argument("-o", "--out", metavar="DIR",
                        help="folder of the shots and the summary (default: a sweep's "
                             "[output] dir, else ./wiggly-batch)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("-j", "--workers", type=_count, metavar="N",
                       help="local worker processes (default: one per core)")
    where.add_argument("--ray", action="store_true",
                       help="run on a Ray cluster: RAY_ADDRESS's, else a new local one")
    parser.add_argument("--ray-address", metavar="ADDRESS",
                        help="run on the Ray cluster at ADDRESS (auto, host:6379, "
                             "ray://host:10001)")
    parser.add_argument("-w", "--write", metavar="NAME", action="append",
                        help="file written into every shot's folder (repeatable; replaces "
                             "the scenes' and sweeps' outputs), e.g. shot.glb, preview.gif; "
                             "--write none: no outputs, only the summary")
    parser.add_argument("--overwrite", action="store_true",
                        help="replace folders of shots whose scene or outputs changed")
    parser.add_argument("--no-sheet", action="store_true",
                        help="no thumbnails or contact sheets (nothing rendered)")
    parser.add_argument("--thumbnail-time", type=float, metavar="T",
                        help="thumbnails at T seconds (default: the frame farthest from rest)")
    parser.add_argument("--cold", action="store_true",
                        help="solve every shot from scratch (default: from the previous "
                             "solution of the same problem in the worker, which is faster)")
    parser.add_argument("--dry-run", action="store_true",
                        help="list the shots and their parameters; run nothing")
    parser.add_argument("--schema", action="store_true",
                        help="print the JSON Schema of sweep files and exit")
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    if args.schema:
        from wiggly.batch import sweep_schema

        print(json.dumps(sweep_schema(), indent=2))
        return 0
    if not args.inputs:
        print("wiggly batch: error: give scene files or a sweep file (see --help)",
              file=sys.stderr)
        return 2
    if args.ray_address is not None and args.workers is not None:
        print("wiggly batch: error: -j counts local processes; a Ray cluster uses its CPUs: "
              "give -j or --ray-address, not both", file=sys.stderr)
        return 2
    folders = [i for i in args.inputs if Path(i).is_dir()]
    if folders:
        print(f"wiggly batch: error: {', '.join(folders)}: "
              f"{'is a folder' if len(folders) == 1 else 'are folders'}; give the scene files "
              f"in it ({Path(folders[0], '*.toml')}) or a sweep file", file=sys.stderr)
        return 2
    if not any(Path(i).is_file() for i in args.inputs):  # typos: before any folder is made
        print(f"wiggly batch: error: no such file: {', '.join(args.inputs)} (give scene "
              "files (.toml) or a sweep file; of several, a missing one is a failed shot)",
              file=sys.stderr)
        return 2
    if args.write is not None and any(w.lower() == "none" for w in args.write):
        if len(args.write) > 1:
            print("wiggly batch: error: --write none (no outputs, only the summary) cannot go "
                  f"with other names ({', '.join(w for w in args.write if w.lower() != 'none')})"
                  "; give one or the other", file=sys.stderr)
            return 2
        args.write = []
    if args.dry_run:
        return _dry_run(args)
    from wiggly.batch import run as run_batch

    out = _out_dir(args)
    ray = args.ray_address or args.ray or None
    started = time.time()
    try:
        records = run_batch(args.inputs, out, workers=args.workers, ray=ray,
                            write=args.write, overwrite=args.overwrite,
                            contact_sheet=not args.no_sheet,
                            thumbnail_time=args.thumbnail_time, warm_start=not args.cold)
    except (KeyboardInterrupt, SystemExit):  # Ctrl+C, or SIGTERM (terminate_as_exit)
        print(interrupted(out, started), file=sys.stderr)
        raise
    print(report(records, out, args))
    return 0 if all(r["status"] == "done" for r in records) else 1


def report(records: list[dict], out: Path, args: argparse.Namespace) -> str:
    """What ran, what failed (with the message), where the summary is."""
    done = [r for r in records if r["status"] == "done"]
    resumed = sum(bool(r.get("resumed")) for r in done)
    failed = [r for r in records if r["status"] != "done"]
    lines = [f"{counted(len(records), 'shot')}: {len(done)} done"
             + (f" ({resumed} in an earlier run)" if resumed else "")
             + (f", {len(failed)} failed" if failed else "")]
    for r in failed:
        error = (r.get("error") or r["status"]).splitlines()
        lines.append(f"  {r['shot']}: {error[0]}")
        lines += [f"    {e}" for e in error[1:4]]
    lines.append(f"summary    {Path(out, 'summary.csv').resolve()}")
    if not args.no_sheet:
        lines.append(f"sheet      {Path(out, 'contact-sheet.html').resolve()}")
    return "\n".join(lines)


def interrupted(out: Path, started: float) -> str:
    """What an interrupted batch left: the counts of its summary (written on Ctrl+C once
    its shots run; not an earlier batch's, from before ``started``), and that running it
    again finishes it."""
    summary = Path(out, "summary.json")
    try:
        if summary.stat().st_mtime < started:
            raise ValueError("an earlier batch's summary")
        totals = json.loads(summary.read_text("utf-8"))["totals"]
        counts = (f"{totals['done']} of {counted(totals['shots'], 'shot')} done, "
                  f"{totals['not_run']} not run; summary {Path(out, 'summary.csv').resolve()}; ")
    except (OSError, ValueError, KeyError, TypeError):
        counts = ""
    return (f"wiggly batch: interrupted: {counts}the shots done are kept in {out}, and the "
            "same command runs the rest")


def _out_dir(args: argparse.Namespace) -> Path:
    """``-o``, else a single sweep's ``[output] dir``, else ``./wiggly-batch``."""
    if args.out:
        return Path(args.out)
    from wiggly.batch import load_sweep
    from wiggly.batch.driver import default_out_dir
    from wiggly.batch.sweep import is_sweep, read_toml
    from wiggly.errors import WigglyInputError

    sweeps = []
    for given in args.inputs:
        try:
            data = read_toml(Path(given))
        except WigglyInputError:  # the batch reports it as a failed shot
            data = {}
        if is_sweep(data):
            sweeps.append(load_sweep(given))
    out = default_out_dir(args.inputs, sweeps)
    ignored = [s.where() for s in sweeps if s.out_dir is not None and s.out_dir != out]
    if ignored:

        warn(f"{', '.join(ignored)}: a sweep's [output] dir applies when the sweep is "
             f"the only input; with {len(args.inputs)} inputs the batch goes to {out} "
             "(-o names the folder)")
    return out


def _dry_run(args: argparse.Namespace) -> int:
    """List the shots, each with every problem of its scene and what its folder in the
    batch's folder holds (done before, another shot, or files wiggly did not write)."""
    from wiggly.batch.driver import RESULT, read_result
    from wiggly.batch.shots import Digests, collect, keyed

    shots, _ = collect(args.inputs, args.write)
    out = _out_dir(args)
    keyed([s for s in shots if s.scene is not None], Digests())
    bad, done = 0, 0
    for s in shots:
        if s.scene is None:
            bad += 1
            lines = (s.error or "").splitlines() or [""]
            print(f"{s.name}: invalid: {lines[0]}")
            for line in lines[1:]:
                print(f"    {line}")
            continue
        values = ", ".join(f"{k} = {json.dumps(v)}" for k, v in s.params.items())
        folder = Path(out, s.name)
        state = ""
        if folder.exists():
            old = read_result(folder)
            if old is None:
                state = f" [{folder} holds no shot (no {RESULT}): refused]"
            elif old.get("key") == s.key and old.get("status") == "done":
                state, done = " [done in an earlier run]", done + 1
            else:
                state = " [its folder holds another shot: replaced only with --overwrite]"
        print(f"{s.name}: {values or s.origin}{state}")
    print(f"{counted(len(shots), 'shot')} into {out}" + (f", {bad} invalid" if bad else "")
          + (f", {done} done in an earlier run" if done else ""))
    return 1 if bad else 0


def _count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be at least 1")
    return value
