"""``wiggly batch`` (issue 14): 40 shots of the demo body, one at a time vs the local pool vs
a local Ray cluster, on the cores of this machine; throughput, and what each shot costs
(shared preparation vs its own solve) for the README's scaling on paper.

The shots are a sweep over the demo's keyframe targets (take-off height, landing spot), so
every shot shares one body and one time range; each writes a ``.npz``.  Wall times are
medians of repeated runs; the tet mesh and the modes stay in the disk cache between runs
(as on any re-run), the batch's prepared body does not (it is prepared in every run).

    .venv/bin/python benchmarks/bench_batch.py [--quick] [--shots N] [--no-ray]
"""

from __future__ import annotations

import os
import shutil
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

sys.path.insert(0, os.path.dirname(__file__))

from common import bench_cache, table

DEMO = Path(__file__).resolve().parents[1] / "src" / "wiggly" / "data" / "demo.toml"


def sweep_file(directory: Path, shots: int) -> Path:
    path = directory / "demo_sweep.toml"
    path.write_text(f"""
base = "{DEMO}"
samples = {shots}
seed = 14
[random]
"keyframes[take-off].position.offset[1]" = {{ uniform = [0.02, 0.07] }}
"keyframes[touch-down].position.offset[0]" = {{ uniform = [0.25, 0.35] }}
[output]
paths = ["shot.npz"]
""")
    return path


def _imports() -> float:
    t = time.perf_counter()
    import wiggly.render
    import wiggly.scene
    import wiggly.solve  # noqa: F401

    return time.perf_counter() - t


def worker_start() -> float:
    """Seconds to start a worker process as the pool does and import what a shot needs."""
    from wiggly.batch.backends import forkserver_context

    t = time.perf_counter()
    with ProcessPoolExecutor(1, mp_context=forkserver_context()) as pool:
        pool.submit(_imports).result()
    return time.perf_counter() - t


def _spin(seconds: float) -> float:
    t = time.process_time()
    while time.process_time() - t < seconds:
        pass
    return seconds


def free_cores(n: int, seconds: float = 2.0) -> float:
    """Cores this machine gives ``n`` busy processes now: ``n`` spins of ``seconds`` CPU
    seconds each, divided by their wall time (a shared or virtual machine gives less than
    ``n``; the wall times above depend on it, CPU seconds do not)."""
    from wiggly.batch.backends import forkserver_context

    with ProcessPoolExecutor(n, mp_context=forkserver_context()) as pool:
        list(pool.map(_spin, [0.1] * n))
        t = time.perf_counter()
        list(pool.map(_spin, [seconds] * n))
        return n * seconds / (time.perf_counter() - t)


def forget_prepared_bodies() -> None:
    shutil.rmtree(Path(os.environ["WIGGLY_CACHE_DIR"]) / "batch", ignore_errors=True)


def one_at_a_time(sweep: Path, out: Path) -> float:
    """The baseline: ``wiggly.scene.run`` per shot in this process (each builds its body from
    the disk cache and solves from scratch)."""
    from wiggly.batch.shots import collect
    from wiggly.scene import run

    shots, _ = collect([sweep])
    t, cpu = time.perf_counter(), time.process_time()
    for s in shots:
        run(s.scene, outputs=[out / f"{s.name}.npz"], overwrite=True)
    BASELINE_CPU.append((time.process_time() - cpu) / len(shots))
    return time.perf_counter() - t


BASELINE_CPU: list[float] = []


def batch(sweep: Path, out: Path, **kw) -> tuple[float, list[dict]]:
    from wiggly.batch import run

    forget_prepared_bodies()
    shutil.rmtree(out, ignore_errors=True)
    t = time.perf_counter()
    records = run(sweep, out, contact_sheet=kw.pop("contact_sheet", False), **kw)
    wall = time.perf_counter() - t
    assert all(r["status"] == "done" for r in records), [r["error"] for r in records]
    return wall, records


def median(records: list[dict], key: str) -> float:
    return statistics.median(r[key] for r in records if r.get(key) is not None)


def main(argv: list[str]) -> None:
    quick = "--quick" in argv
    shots = int(argv[argv.index("--shots") + 1]) if "--shots" in argv else (10 if quick else 40)
    repeats = 1 if quick else 3
    os.environ["WIGGLY_CACHE_DIR"] = bench_cache()  # workers and Ray inherit it
    from wiggly.batch.backends import cpu_count
    from wiggly.batch.worker import BodyJob, prepare_body
    from wiggly.scene import load_scene

    cores = cpu_count()
    work = Path(tempfile.mkdtemp(prefix="wiggly-bench-batch-"))
    sweep = sweep_file(work, shots)
    scene = load_scene(DEMO)
    from wiggly.batch.shots import body_scene

    # one-time costs: the body from an empty cache, and from the disk cache
    empty = work / "empty-cache"
    os.environ["WIGGLY_CACHE_DIR"] = str(empty)
    cold = prepare_body(BodyJob("cold", body_scene(scene), target=str(work / "cold.pickle")))
    os.environ["WIGGLY_CACHE_DIR"] = bench_cache()
    warm = [prepare_body(BodyJob("warm", body_scene(scene), target=str(work / "warm.pickle")))
            for _ in range(repeats + 1)][1:]
    start = statistics.median(worker_start() for _ in range(repeats))

    runs: dict[str, list[float]] = {}
    last: dict[str, list[dict]] = {}
    variants = [("one at a time (wiggly.scene.run per shot, in the driver)", None),
                ("batch, 1 worker process", {"workers": 1}),
                (f"batch, {cores} worker processes", {"workers": cores}),
                (f"batch, {cores} worker processes, cold solves",
                 {"workers": cores, "warm_start": False})]
    ray_init = None
    if "--no-ray" not in argv:
        try:
            import ray

            t = time.perf_counter()
            ray.init(num_cpus=cores, include_dashboard=False, log_to_driver=False)
            ray_init = time.perf_counter() - t
            variants.append((f"batch on Ray, local cluster of {cores} CPUs", {"ray": True}))
        except ImportError:
            print("(Ray is not installed: pip install 'wiggly[ray]'; its row is left out)")
    capacity = []
    for _ in range(repeats):
        capacity.append(free_cores(cores))
        for name, kw in variants:
            out = work / "out"
            if kw is None:
                shutil.rmtree(out, ignore_errors=True)
                out.mkdir()
                runs.setdefault(name, []).append(one_at_a_time(sweep, out))
            else:
                wall, records = batch(sweep, out, **kw)
                runs.setdefault(name, []).append(wall)
                last[name] = records
    sheet_wall, sheet = batch(sweep, work / "out", workers=cores, contact_sheet=True)
    if ray_init is not None:
        import ray

        ray.shutdown()

    base = statistics.median(runs[variants[0][0]])
    rows = []
    for name, _ in variants:
        wall = statistics.median(runs[name])
        cpu = statistics.median(BASELINE_CPU) if name not in last else \
            median(last[name], "cpu_seconds")
        rows.append([name, wall, 3600 * shots / wall, base / wall, cpu])
    rows.append([f"batch, {cores} worker processes, with thumbnails (1 run)", sheet_wall,
                 3600 * shots / sheet_wall, base / sheet_wall, median(sheet, "cpu_seconds")])
    print(table(f"{shots} shots of the demo body on {cores} cores (median of {repeats} runs)",
                ["how", "wall (s)", "shots/hour", "vs one at a time", "CPU s per shot"],
                rows))
    print(f"cores free for {cores} busy processes, before each round: "
          + ", ".join(f"{c:.2f}" for c in capacity) + "\n")

    pool = last[f"batch, {cores} worker processes"]
    cold_pool = last[f"batch, {cores} worker processes, cold solves"]
    setups = [r["setup_seconds"] for r in pool if r["setup_seconds"] > 0.05]
    split = [
        ["prepare the body: tet mesh, M and K, 40 modes (empty cache)",
         cold["prepare_seconds"], "once per body"],
        ["prepare the body, tet mesh and modes from the disk cache",
         statistics.median(w["prepare_seconds"] for w in warm), "once per body and batch"],
        ["start a worker process (fork from the server, imports)", start, "once per worker"],
        ["worker setup: fetch the body, factor the warp (first shot of a worker)",
         statistics.median(setups) if setups else 0.0, "once per body and worker"],
        ["solve, warm start from the worker's previous shot", median(pool, "solve_seconds"),
         "per shot"],
        ["solve from scratch (cold)", median(cold_pool, "solve_seconds"), "per shot"],
        ["write shot.npz", median(pool, "output_seconds"), "per shot"],
        ["thumbnail (240x180, offscreen)", median(sheet, "thumbnail_seconds"),
         "per shot, with the contact sheet"],
        ["driver: commit the folder, summary row", median(pool, "commit_seconds"),
         "per shot, in the driver"],
        ["a whole shot in its worker, wall / CPU (warm, .npz, no thumbnail)",
         f"{median(pool, 'shot_seconds'):.3g} / {median(pool, 'cpu_seconds'):.3g}",
         "per shot"],
    ]
    if ray_init is not None:
        split.append(["start the local Ray cluster", ray_init, "once per batch"])
        split.append(["driver on Ray: commit the folder, summary row",
                      median(last[f"batch on Ray, local cluster of {cores} CPUs"],
                             "commit_seconds"), "per shot, in the driver"])
    print(table("What a shot costs (medians; seconds)", ["part", "seconds", "paid"], split))
    size = statistics.median(r["output_bytes"] for r in pool)
    warm_share = sum(r["warm_start"] for r in pool) / len(pool)
    print(f"shot folder: {size / 1e6:.2f} MB (shot.npz, scene.toml, result.json); "
          f"{100 * warm_share:.0f} % of the pool's solves started warm; iterations warm / "
          f"cold: {median(pool, 'iterations'):.0f} / {median(cold_pool, 'iterations'):.0f}")
    shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main(sys.argv[1:])
