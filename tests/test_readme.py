"""The README's Python example runs as written and does what it says."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[1] / "README.md"


def test_readme_python_example_runs(tmp_path, monkeypatch):
    monkeypatch.setenv("WIGGLY_CACHE_DIR", str(tmp_path))
    monkeypatch.chdir(tmp_path)  # it writes jump.glb where it runs
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), re.S)
    assert blocks, "README has no python example"
    namespace: dict = {}
    exec(compile(blocks[0], "README.md", "exec"), namespace)
    anim, frames, body = namespace["anim"], namespace["frames"], namespace["body"]
    assert frames.shape == (len(anim.frame_times(30)), body.surface.n_vertices, 3)
    assert np.all(np.isfinite(frames))
    # soft keyframes: the feet's rest keys at 0, 1.6 and 2.5 s met to within 5 mm; at 0.8 s,
    # where the feet and the head's 25 cm lift pull against each other, both within a tenth of
    # the lift; keyed to the end, the body stands at the end (it does not fall)
    rows = anim.constraint_residuals()
    assert [r["time"] for r in rows] == [0.0, 0.8, 1.6, 2.5, 0.8]
    assert all(rows[j]["position_rms"] < 0.005 for j in (0, 2, 3))
    assert rows[1]["position_rms"] < 0.025 and rows[4]["position_rms"] < 0.025
    X, feet = body.rest_positions(), namespace["feet"]
    assert np.linalg.norm(frames[-1][feet] - X[feet], axis=1).max() < 0.01
    from wiggly.export import read_animation

    written = read_animation(tmp_path / "jump.glb")  # the motion, as exported
    np.testing.assert_allclose(written.positions[-1], frames[-1], atol=1e-5)


def test_readme_is_a_short_overview_without_process_history():
    """The README fits on a few screens; details live in docs/, and user-facing text names
    no issue numbers or commit hashes."""
    text = README.read_text()
    assert len(text.splitlines()) < 200
    assert not re.search(r"\bissues? \d+", text, re.I)
    assert not re.search(r"\b(commit|baseline) [0-9a-f]{7,40}\b", text)
    for link in re.findall(r"\]\((docs/[^)#]+)\)", text):
        assert (README.parent / link).is_file(), f"README links to a missing page {link}"


def test_docs_pages_name_no_issue_numbers_or_commits():
    docs = README.parent / "docs"
    for page in sorted(docs.glob("*.md")):
        text = page.read_text()
        assert not re.search(r"\bissues? \d+", text, re.I), f"{page.name} names an issue"
        assert not re.search(r"\bcommit [0-9a-f]{7,40}\b", text), f"{page.name} names a commit"
