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
    for row in anim.constraint_residuals():  # every keyframe met to within a centimetre
        assert row["position_rms"] < 0.01
