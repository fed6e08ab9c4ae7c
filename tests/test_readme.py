"""The README's Python example runs as written and does what it says."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(tmp_path, monkeypatch):
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path))
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    anim, frames, body = namespace["anim"], namespace["frames"], namespace["body"]
    assert frames.shape == (len(anim.frame_times(30)), body.surface.n_vertices, 3)
    assert np.all(np.isfinite(frames))
    # soft keyframes: the feet's rest keys at 0 and 1.6 s met to within 5 mm; at 0.8 s, where
    # the planted feet and the head's 25 cm lift pull against each other, both within a tenth
    # of the lift
    rows = anim.constraint_residuals()
    assert [r["time"] for r in rows] == [0.0, 0.8, 1.6, 0.8]
    assert rows[0]["position_rms"] < 0.005 and rows[2]["position_rms"] < 0.005
    assert rows[1]["position_rms"] < 0.025 and rows[3]["position_rms"] < 0.025
