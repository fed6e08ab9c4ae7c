"""Run every benchmark and print their tables (what `make bench` calls)."""

from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.dirname(__file__))

import bench_core
import bench_warped

if __name__ == "__main__":
    quick = "--quick" in sys.argv
    args = ["--quick"] if quick else []
    bench_core.main(args)
    bench_warped.main(args)
    import bench_batch

    bench_batch.main(args)
    if os.path.exists(os.path.join(os.path.dirname(__file__), "bench_editor.py")):
        import bench_editor

        bench_editor.main(args)
