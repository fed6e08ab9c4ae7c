"""Run every benchmark and print their tables (what `make bench` calls)."""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))

import bench_batch
import bench_core
import bench_editor
import bench_warped


def main(argv: list[str] | None = None) -> None:
    args = ["--quick"] if "--quick" in (sys.argv[1:] if argv is None else argv) else []
    bench_core.main(args)
    bench_warped.main(args)
    bench_batch.main(args)
    bench_editor.main(args)


if __name__ == "__main__":
    main()
