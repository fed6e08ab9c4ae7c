"""Landing in Blender: our .glb, .gltf and .usd files imported by real Blender (PyPI ``bpy``,
headless), checked as the README's Blender section promises: the Basis shape key is the rest
mesh, keys and USD samples land on frames frame_start, frame_start + 1, ... at the scene's
fps (exported at that fps), positions match the animation, the object is named after the
model.

``bpy`` pins its own numpy and Python (3.11), so it lives in its own environment
(``make blender`` makes ``.venv-blender``; ``WIGGLY_BLENDER_PYTHON`` names another
interpreter) and runs ``tests/blender/inspect_imports.py`` in a subprocess.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from wiggly.export import SurfaceAnimation, write_animation
from wiggly.keyframes import Keyframe
from wiggly.solve import solve

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = Path(__file__).parent / "blender" / "inspect_imports.py"
FPS = 24  # a new Blender scene's frame rate
FRAME_START = 1  # a new Blender scene's first frame


def blender_view(python: str, tmp_path: Path, frames: list[int], files: list[Path]) -> dict:
    out = tmp_path / "blender.json"
    done = subprocess.run([python, str(SCRIPT), str(out), str(FPS), *map(str, frames), "--",
                           *map(str, files)], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    return json.loads(out.read_text())


def z_up(P: np.ndarray) -> np.ndarray:
    """Our y-up metres as Blender's z-up world coordinates (both importers convert)."""
    return np.stack([P[..., 0], -P[..., 2], P[..., 1]], axis=-1)


def test_glb_and_usd_land_in_blender_as_documented(bar, tmp_path, blender_python):
    X = bar.rest_positions()
    tip = np.flatnonzero(X[:, 0] > X[:, 0].max() - 1e-9)
    root = np.flatnonzero(X[:, 0] < 1e-9)
    keys = [Keyframe.rest(bar, 0.2, root, still=True), Keyframe.rest(bar, 0.2, tip),
            Keyframe.offset(bar, 0.7, tip, (0.0, 0.3, 0.0))]
    anim = solve(bar, keys, start=0.2, end=1.2, warp=False)  # starts at 0.2 s on purpose
    times = anim.frame_times(FPS)
    # the bar is a tet mesh: its surface is the boundary (Blender drops unused vertices)
    used = np.unique(bar.surface.faces)
    X = X[used]
    faces = np.searchsorted(used, bar.surface.faces)
    positions = anim.positions(times)[:, used]
    shapes = bar.surface_basis.T.reshape(bar.r, -1, 3)[:, used]
    data = SurfaceAnimation(times, positions, faces, name="bar", rest=X, mode_shapes=shapes,
                            modal=anim.modal(times)[0])
    glb = write_animation(tmp_path / "frames.glb", data, frame_start=FRAME_START)
    compact = write_animation(tmp_path / "modes.glb", data, frame_start=FRAME_START,
                              gltf_targets="modes")
    usd = write_animation(tmp_path / "bar.usdc", data, frame_start=FRAME_START)
    text = write_animation(tmp_path / "frames.gltf", data, frame_start=FRAME_START)
    F = len(times)
    frames = [FRAME_START, FRAME_START + F // 3, FRAME_START + F - 1]
    view = blender_view(blender_python, tmp_path, frames, [glb, compact, usd, text])
    size = float(np.ptp(X, axis=0).max())
    for path in (glb, compact, usd, text):
        seen = view[str(path)]
        assert seen["objects"] == ["bar"], seen["objects"]  # named after the model
        assert seen["fps"] == FPS  # the scene keeps its rate; we exported at it
        for f in frames:
            error = np.abs(np.array(seen["positions"][str(f)]) - z_up(positions[f - FRAME_START]))
            assert error.max() < 1e-6 * size, (path.name, f, error.max())
    for path in (glb, compact, text):
        seen = view[str(path)]
        assert seen["shape_keys"][0] == "Basis"
        np.testing.assert_allclose(seen["basis"], z_up(X), atol=1e-6 * size)  # the rest mesh
        assert seen["key_frames"] == list(range(FRAME_START, FRAME_START + F))
        assert seen["frame_range"] == [1, 250]  # the glTF importer leaves it (README says so)
    assert len(view[str(compact)]["shape_keys"]) - 1 <= 2 * bar.r < F
    assert view[str(usd)]["frame_range"] == [FRAME_START, FRAME_START + F - 1]
    assert view[str(usd)]["modifiers"] == ["MESH_SEQUENCE_CACHE"]


def test_a_blender_rig_drives_its_mesh_on_its_own_frames(tmp_path, blender_python):
    """A skinned glTF exported from Blender (two objects under one armature, scaled by 2 and
    moved; a 24 fps scene from frame 1), used as docs/secondary-motion.md says: the same file
    as mesh and driver, the output at the scene's rate with frame_start left out.  Imported
    back into Blender, the driven half of the bar lies where Blender's own rig puts it at the
    same frame."""
    frames = [1, 7, 13, 20, 24]  # the shot's 1 s: frames 0..24
    glb, evaluated = tmp_path / "rig.glb", tmp_path / "rig.json"
    done = subprocess.run([blender_python, str(SCRIPT.parent / "make_rig.py"), str(glb),
                           str(evaluated), *map(str, frames)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    blender = json.loads(evaluated.read_text())
    scene = tmp_path / "rig.toml"
    scene.write_text(f"""format = 1
[mesh]
path = "{glb.name}"
resolution = 12
[material]
young = 1e5
[time]
end = 1.0
fps = {FPS}
[simulation]
modes = 12
[groups.driven]
box = {{ min = [-10.0, -10.0, -10.0], max = [1.25, 10.0, 10.0] }}
[drive]
path = "{glb.name}"
group = "driven"
""")
    out = tmp_path / "rig_wiggly.glb"
    done = subprocess.run([sys.executable, "-m", "wiggly", "animate", str(scene), "-o",
                           str(out), "--quiet"], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    seen = blender_view(blender_python, tmp_path, frames, [out])[str(out)]
    rest = np.array(blender["rest"])
    basis = np.array(seen["basis"])
    match = np.linalg.norm(basis[:, None] - rest[None], axis=2)
    order = match.argmin(axis=1)  # imported vertex -> Blender's vertex at rest
    assert match.min(axis=1).max() < 1e-5  # the rest mesh lands at Blender's rest (scale 2)
    driven = rest[order, 0] < 0.3 + 2 * 0.45  # the root bone's half, in Blender's world x
    assert driven.sum() > 20
    for f in frames:
        there = np.array(blender["frames"][str(f)])[order]
        error = np.linalg.norm(np.array(seen["positions"][str(f)]) - there, axis=1)[driven]
        assert error.max() < 2e-3, (f, error.max())  # metres; one frame late is ~30 mm
