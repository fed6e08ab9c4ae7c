"""``wiggly batch --ray`` on a local Ray cluster of two CPUs (``ray.init(num_cpus=2)``):
the body is prepared once into the object store and every shot agrees with its scene solved
alone.  Skipped, with the reason, when Ray (the optional extra) is not installed."""

from __future__ import annotations

import json
import os

import pytest

ray = pytest.importorskip(
    "ray", reason='Ray is an optional extra (pip install "wiggly[ray]"); make test installs it')

from tests.test_batch import check_shot_against_alone, write_sweep  # noqa: E402
from wiggly.batch import run  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False,
             object_store_memory=256 * 2**20)
    yield
    ray.shutdown()


def test_sweep_on_a_ray_cluster(cluster, tmp_path):
    # the workers and this process share the cache directory of the environment, so that
    # solving a shot alone here meshes the bar as they did (fTetWild is not reproducible)
    out = tmp_path / "out"
    records = run(write_sweep(tmp_path), out, ray=True, contact_sheet=False)
    assert [r["status"] for r in records] == ["done"] * 4, [r["error"] for r in records]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["backend"] == "a Ray cluster of 2 CPUs"
    # one body, prepared once by a Ray worker, fetched from the object store by the others
    (body,) = summary["bodies"]
    assert body["status"] == "done" and body["shots"] == 4 and body["cached"] is False
    workers = {r["worker"] for r in records} | {body["worker"]}
    assert all(int(w.rsplit(":", 1)[1]) != os.getpid() for w in workers)
    for r in records:
        assert sorted(p.name for p in (out / r["folder"]).iterdir()) == \
            ["bar.npz", "result.json", "scene.toml"]
    for r in records[:2]:
        check_shot_against_alone(out, r)
    assert ray.is_initialized()  # a cluster the caller started is left running
    again = run(write_sweep(tmp_path), out, ray=True, contact_sheet=False)
    assert all(r["resumed"] for r in again)
