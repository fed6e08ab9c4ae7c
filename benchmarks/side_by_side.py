"""Run a benchmark script at a baseline commit and at the working tree, interleaved, in one run.

The machine's speed drifts between minutes, so the two versions are measured in turns (A, B,
A, B, ...) and each row's medians are compared in the same run.  The baseline is checked out
into a temporary git worktree and run with the same interpreter, its own ``src`` first on
``PYTHONPATH`` (its numba kernels compile on its first run).

Run: ``.venv/bin/python benchmarks/side_by_side.py BASELINE bench_warped.py --rounds 3 --
--quick`` (arguments after ``--`` go to the benchmark); rows are matched by the first cell of
the benchmark's Markdown tables.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))
from common import table

ROOT = Path(__file__).resolve().parent.parent


def run(tree: Path, script: str, args: list[str]) -> dict[str, float]:
    """First numeric cell of every table row printed by ``tree/benchmarks/script``."""
    env = dict(os.environ, PYTHONPATH=str(tree / "src"))
    out = subprocess.run(
        [sys.executable, str(tree / "benchmarks" / script), *args],
        env=env, cwd=tree, capture_output=True, text=True, check=True,
    ).stdout
    rows = {}
    for line in out.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 2 or not line.startswith("|"):
            continue
        try:
            rows[cells[0]] = float(cells[1])
        except ValueError:  # a header, a separator or a text cell
            continue
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("baseline", help="git commit to compare against")
    ap.add_argument("script", help="benchmark script in benchmarks/")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--rows", nargs="*", help="rows to report (default: all in both)")
    argv = sys.argv[1:] if argv is None else argv
    ours, theirs = (argv[: argv.index("--")], argv[argv.index("--") + 1 :]) if "--" in argv \
        else (argv, [])
    args = ap.parse_args(ours)
    args.args = theirs  # everything after "--" goes to the benchmark script
    with tempfile.TemporaryDirectory() as tmp:
        base = Path(tmp) / "baseline"
        subprocess.run(["git", "worktree", "add", "--detach", str(base), args.baseline],
                       cwd=ROOT, check=True, capture_output=True)
        try:
            runs: dict[str, list[dict[str, float]]] = {"baseline": [], "now": []}
            for k in range(args.rounds):
                for name, tree in (("baseline", base), ("now", ROOT)):
                    runs[name].append(run(tree, args.script, args.args))
                    print(f"round {k + 1}: {name} done", file=sys.stderr, flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(base)], cwd=ROOT,
                           check=False, capture_output=True)
    rows = args.rows or [r for r in runs["now"][0] if r in runs["baseline"][0]]
    out = []
    for row in rows:
        a = statistics.median(r[row] for r in runs["baseline"] if row in r)
        b = statistics.median(r[row] for r in runs["now"] if row in r)
        out.append([row, a, b, b / a])
    print(table(
        f"{args.script}: baseline {args.baseline} against the working tree, interleaved, "
        f"{args.rounds} rounds (medians of the benchmark's own medians; {os.cpu_count()} cores)",
        ["row", "baseline", "now", "ratio now / baseline"], out,
    ))


if __name__ == "__main__":
    main()
