"""Looped (periodic) shots: the wiggly splines wrap around from the last node to the first."""

from __future__ import annotations

import numpy as np
import pytest

from wiggly.errors import WigglyInputError
from wiggly.framebased import solve_framebased
from wiggly.keyframes import Keyframe
from wiggly.solve import SpacetimeProblem, solve
from wiggly.splines import evaluate

from .conftest import make_body

END = 1.2


@pytest.fixture(scope="module")
def bar(tmp_path_factory):
    return make_body(tmp_path_factory, shape=(10, 2, 2), n_modes=10)


def keys_of(body, velocity=False):
    X = body.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.8)
    return [
        Keyframe.rest(body, 0.0, np.arange(len(X))),
        Keyframe.offset(body, 0.4, tip, (0, 0.1, 0),
                        velocity=(0.0, 0.0, 0.4) if velocity else None),
        Keyframe.offset(body, 0.9, tip, (0, -0.05, 0.03)),
    ]


def one_sided(anim, t, n, side):
    return anim.modal(np.array([t]), n, side=side)[n, 0]


@pytest.mark.parametrize("warp", [False, True], ids=["linear", "warped"])
def test_the_seam_is_continuous_in_position_and_velocity(bar, warp):
    anim = solve(bar, keys_of(bar), end=END, warp=warp, loop=True)
    assert anim.loop and (not warp or anim.info["converged"])
    P = anim.positions([0.0, END])
    V = anim.velocities_at([0.0, END])
    assert np.abs(P[1] - P[0]).max() <= 1e-9 * np.abs(P).max()
    assert np.abs(V[1] - V[0]).max() <= 1e-9 * np.abs(V).max()
    assert np.abs(V).max() > 0.1  # a moving loop, not a trivial one


def test_theorem_1_orders_hold_at_every_node_and_across_the_seam(bar):
    """C^2 at nodes without a velocity keyframe (the seam included: its second derivative
    from the left at the end equals the one from the right at the start), only C^1 at a node
    with one; on each interval the ODE of Theorem 1 holds."""
    anim = solve(bar, keys_of(bar, velocity=True), end=END, warp=False, loop=True)
    scale = np.abs(anim.modal(np.linspace(0, END, 50), 2)[2]).max()
    seam = one_sided(anim, END, 2, "left") - one_sided(anim, 0.0, 2, "right")
    assert np.abs(seam).max() <= 1e-9 * scale
    assert np.abs(one_sided(anim, 0.9, 2, "left") - one_sided(anim, 0.9, 2, "right")).max() \
        <= 1e-9 * scale
    jump = one_sided(anim, 0.4, 2, "left") - one_sided(anim, 0.4, 2, "right")
    assert np.abs(jump).max() > 1e-3 * scale  # the velocity keyframe's node: only C^1
    for t in (0.4, 0.9):
        d1 = one_sided(anim, t, 1, "left") - one_sided(anim, t, 1, "right")
        assert np.abs(d1).max() <= 1e-9 * np.abs(anim.modal(np.array([t]), 1)[1]).max()
    # inside intervals: q'''' + 2 (lam - 2 delta^2) q'' + lam (lam q + g) = 0, per mode
    lam, delta, g = bar.eigenvalues, bar.delta, bar.modal_gravity
    k = 1
    h = anim.nodes[k + 1] - anim.nodes[k]
    data = np.stack([anim.values[k], anim.velocities[k], anim.values[k + 1],
                     anim.velocities[k + 1]], axis=-1)
    basis = anim.basis.take(k * bar.r + np.arange(bar.r))
    d = evaluate(basis, data, g, np.full(bar.r, 0.37), 4)
    residual = d[4] + 2 * (lam - 2 * delta**2) * d[2] + lam * (lam * d[0] + g)
    assert np.abs(residual).max() <= 1e-6 * (np.abs(d[4]).max() + np.abs(lam**2 * d[0]).max())
    assert h > 0


def test_a_periodic_frame_based_reference_converges_to_the_loop(bar):
    """A periodic grid with central differences (wrapping around) approaches the looped
    wiggly solution at second order as its step shrinks."""
    keys = keys_of(bar)
    anim = solve(bar, keys, end=END, warp=False, loop=True)
    errors = []
    for fps in (50, 100, 200, 400):
        t, q = solve_framebased(bar, keys, fps, 0.0, END, loop=True)
        errors.append(np.abs(anim.modal(t)[0] - q).max())
    rates = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(np.abs(rates[1:] - 2.0) < 0.15), rates


def test_a_loop_needs_keyframes_that_hold_the_body(bar):
    X = bar.rest_positions()
    tip = np.flatnonzero(X[:, 0] > 0.8)
    with pytest.raises(WigglyInputError, match="looped motion undetermined"):
        solve(bar, [Keyframe(0.5, tip, velocity=(0, 1.0, 0))], end=END, warp=False, loop=True)
    with pytest.raises(WigglyInputError, match="does not apply to a looped shot"):
        SpacetimeProblem(bar, 0.0, END, preroll=1.0, loop=True)


def test_a_looped_warm_start_is_not_taken_by_an_unlooped_problem(bar):
    keys = keys_of(bar)
    looped = SpacetimeProblem(bar, 0.0, END, loop=True).solve(keys, warped=True)
    plain = SpacetimeProblem(bar, 0.0, END).solve(keys, warped=True,
                                                  warm_start=looped.warm_start)
    assert not plain.info["warm_start"] and plain.info["converged"]


def test_a_looped_scene_exports_cycles_without_a_seam(tmp_path):
    """A scene with ``[time] loop = true``: glTF keeps the seam frame (equal to the first, so
    a time-based player wraps between identical poses), USD leaves it out (a frame-based
    player steps from the last frame to the first); both say they loop."""
    from wiggly.export import read_animation
    from wiggly.scene import load_scene, run

    scene = tmp_path / "loop.toml"
    scene.write_text("""
format = 1
[mesh]
path = "builtin:bar"
resolution = 6
[simulation]
modes = 10
warp = false
[time]
end = 1.0
fps = 10
loop = true
[groups.left]
box = { min = [-1, -1, -1], max = [0.05, 1, 1] }
[groups.tip]
box = { min = [0.85, -1, -1], max = [2, 1, 1] }
[[keyframes]]
time = 0.0
group = "left"
position = "rest"
[[keyframes]]
time = 0.5
group = "tip"
position = { offset = [0.0, 0.1, 0.0] }
[output]
paths = ["out/loop.glb", "out/loop.usda"]
""")
    run(load_scene(scene))
    glb, usd = read_animation(tmp_path / "out/loop.glb"), read_animation(tmp_path / "out/loop.usda")
    assert glb.loop and usd.loop
    assert glb.n_frames == 11 and usd.n_frames == 10
    assert np.abs(glb.positions[-1] - glb.positions[0]).max() <= 1e-6
    np.testing.assert_allclose(usd.positions, glb.positions[:-1], atol=1e-6)
    assert np.abs(glb.positions[5] - glb.positions[0]).max() > 0.05


def test_a_looped_animation_written_from_python_needs_whole_frames_per_cycle(bar, tmp_path):
    """write_animation of a 1.2 s loop at 25 fps (30 frames a cycle; the clip ends on the
    cycle's end) writes it; at 24 fps (28.8 frames
    a cycle, whose seam would jump by a part of a frame) it is refused, naming both numbers
    and a frame rate that fits, and nothing is written."""
    from wiggly.export import read_animation, write_animation

    anim = solve(bar, keys_of(bar), end=END, warp=False, loop=True)
    written = read_animation(write_animation(tmp_path / "fits.glb", anim, fps=25))
    assert written.loop and written.n_frames == 31 and written.times[-1] == pytest.approx(END)
    with pytest.raises(WigglyInputError, match=r"1.2 s at 24 fps is 28.8 frames.*fps = "
                                               r"24.1666667 \(or a whole 20 or 25 fps\)"):
        write_animation(tmp_path / "jumps.glb", anim, fps=24)
    assert not (tmp_path / "jumps.glb").exists()


@pytest.mark.parametrize("duration, fps", [(1.0, 25.5), (0.75, 29.3333), (1.01, 30),
                                           (1 / 3, 24), (1.001, 29.97), (2.0, 23.976)])
def test_the_whole_frames_remedy_is_accepted_as_written(duration, fps):
    """The remedy's numbers, read back as a user types them, make whole frames: 6-digit
    suggestions such as 0.333333 s at 24 fps were refused (8 frames less 8e-6), and so were
    the 29.97 fps ones."""
    import re

    from wiggly.limits import frame_steps, whole_frames_remedy

    said = whole_frames_remedy(duration, fps)
    shorter, rate = (float(x) for x in re.findall(r"(?:of|=) ([0-9.]+)", said)[:2])
    assert frame_steps(shorter, fps)[1] and frame_steps(duration, rate)[1], said
    for whole in re.findall(r"(\d+) (?:or|fps)", said.split("whole")[-1]) if "whole" in said \
            else []:
        assert frame_steps(duration, int(whole))[1], said


def test_a_looped_scenes_previews_show_the_seam_once(tmp_path, monkeypatch):
    """A looping .gif/.mp4 plays its frames round and round, so a looped scene's previews
    leave out the seam frame (it repeats the first), as USD does: 10 frames per 1 s cycle at
    10 fps, not 11."""
    import importlib

    from wiggly.scene import load_scene

    scene_run = importlib.import_module("wiggly.scene.run")  # the module, not run()

    test_a_looped_scene_exports_cycles_without_a_seam(tmp_path)  # writes loop.toml
    shown = {}
    monkeypatch.setattr(scene_run, "render_preview", lambda path, times, positions, faces,
                        **_: shown.setdefault(path.suffix, (len(times), positions)))
    scene_run.run(load_scene(tmp_path / "loop.toml"),
                  outputs=[str(tmp_path / "p.gif"), str(tmp_path / "p.npz")], overwrite=True)
    count, positions = shown[".gif"]
    assert count == 10 and np.abs(positions[-1] - positions[0]).max() > 1e-3


def test_a_looped_scene_needs_whole_frames_per_cycle(tmp_path):
    from wiggly.scene import scene_from_dict

    with pytest.raises(WigglyInputError, match=r"time.loop = true needs a whole number"):
        scene_from_dict({"mesh": {"path": "builtin:bar"},
                         "time": {"end": 1.05, "fps": 10, "loop": True}}, "s.toml")


def test_an_undetermined_loop_in_a_scene_names_the_scene_file(tmp_path):
    """A looped scene keyed only by a velocity: the refusal starts with the scene file."""
    from wiggly.scene import load_scene
    from wiggly.scene import run as run_scene

    (tmp_path / "loop.toml").write_text(
        'format = 1\n[mesh]\npath = "builtin:bar"\n[simulation]\nmodes = 12\n'
        'gravity = [0.0, 0.0, 0.0]\n[time]\nend = 1.0\nfps = 10\nloop = true\n'
        '[groups.tip]\nbox = { min = [0.9, -1, -1], max = [2, 1, 1] }\n'
        '[[keyframes]]\ntime = 0.5\ngroup = "tip"\nvelocity = [0.0, 1.0, 0.0]\n')
    with pytest.raises(WigglyInputError, match=r"^.*loop\.toml: time\.loop = true, but no "
                                               r"keyframe has a position.*looped motion is "
                                               r"undetermined"):
        run_scene(load_scene(tmp_path / "loop.toml"), outputs=[])


def test_opposite_velocity_keys_do_not_place_a_loop(tmp_path):
    """A free capsule keyed by two opposite velocities: the rigid modes' offsets are free,
    but the factorization gets through on rounding (it placed the capsule's centroid 0.28 m
    off); the solve refuses instead."""
    import trimesh

    import wiggly

    trimesh.creation.capsule(height=0.6, radius=0.15).export(tmp_path / "capsule.stl")
    body = wiggly.prepare(str(tmp_path / "capsule.stl"), n_modes=12, resolution=12,
                          cache_dir=False)
    top = np.flatnonzero(body.rest_positions()[:, 2] > 0.3)
    keys = [Keyframe(0.25, top, velocity=(0.5, 0.0, 0.0)),
            Keyframe(0.75, top, velocity=(-0.5, 0.0, 0.0))]
    for warp in (False, True):
        with pytest.raises(WigglyInputError, match="looped motion undetermined"):
            solve(body, keys, end=1.0, warp=warp, loop=True)


def test_a_frame_rate_from_the_command_line_is_checked_against_the_loop(tmp_path):
    from wiggly.scene import load_scene, with_overrides

    (tmp_path / "loop.toml").write_text(
        'format = 1\n[mesh]\npath = "builtin:bar"\n[time]\nend = 1.0\nfps = 30\n'
        'loop = true\n[groups.tip]\nbox = { min = [0.9, -1, -1], max = [2, 1, 1] }\n'
        '[[keyframes]]\ntime = 0.5\ngroup = "tip"\nposition = "rest"\n')
    scene = load_scene(tmp_path / "loop.toml")
    assert with_overrides(scene, fps=24).time.fps == 24
    with pytest.raises(WigglyInputError, match=r"loop\.toml: time\.loop = true needs a whole "
                                               r"number of frames per cycle: 1 s at 25\.5 fps "
                                               r"\(from --fps 25\.5\)"):
        with_overrides(scene, fps=25.5)


def test_a_frame_rate_from_the_command_line_replaces_the_files_for_the_loop(tmp_path):
    """A loop file at 25.5 fps (25.5 frames a cycle) animated with --fps 30: the cycle is
    checked at the outputs' rate, not refused at the file's (it was, though --fps overrides
    [time] fps); without --fps it is refused, with the remedy."""
    from wiggly.cli import main
    from wiggly.scene import load_scene

    (tmp_path / "loop.toml").write_text(
        'format = 1\n[mesh]\npath = "builtin:bar"\nresolution = 6\n[simulation]\nmodes = 8\n'
        'warp = false\n[time]\nend = 1.0\nfps = 25.5\nloop = true\n[groups.tip]\n'
        'box = { min = [0.9, -1, -1], max = [2, 1, 1] }\n'
        '[[keyframes]]\ntime = 0.5\ngroup = "tip"\nposition = "rest"\n')
    with pytest.raises(WigglyInputError, match=r"25\.5 frames; use a duration of"):
        load_scene(tmp_path / "loop.toml")
    assert load_scene(tmp_path / "loop.toml", output_fps=30).time.fps == 25.5
    assert main(["animate", str(tmp_path / "loop.toml"), "--fps", "30", "-o",
                 str(tmp_path / "loop.npz"), "-q"]) == 0
    assert main(["animate", str(tmp_path / "loop.toml"), "--fps", "25.5", "-o",
                 str(tmp_path / "other.npz"), "-q"]) == 1


def test_a_looped_gltf_starts_at_zero_whatever_the_shots_start(tmp_path):
    """Time-based players (three.js) cycle a clip over [0, its last key]: a loop of [0.5,
    1.5] s is written as [0, 1] s (it held its first pose for a third of every cycle); a
    shot that is no loop keeps its own time; with frame_start the frames are Blender's."""
    import trimesh

    from wiggly.export import SurfaceAnimation, read_animation, write_animation

    sphere = trimesh.creation.icosphere(1)
    times = 0.5 + np.arange(11) / 10.0
    lift = 0.1 * np.sin(2 * np.pi * (times - 0.5))[:, None, None] * np.array([0.0, 1.0, 0.0])
    positions = np.asarray(sphere.vertices)[None] + lift
    loop = SurfaceAnimation(times, positions, sphere.faces, name="cycle", loop=True)
    once = SurfaceAnimation(times, positions, sphere.faces, name="once")
    def key_range(path) -> tuple[float, float]:  # what a player reads: the sampler's input
        import pygltflib

        gltf = pygltflib.GLTF2().load(str(path))
        accessor = gltf.accessors[gltf.animations[0].samplers[0].input]
        return accessor.min[0], accessor.max[0]

    assert key_range(write_animation(tmp_path / "cycle.glb", loop)) == pytest.approx((0, 1))
    assert key_range(write_animation(tmp_path / "once.glb", once)) == pytest.approx((0.5, 1.5))
    assert key_range(write_animation(tmp_path / "framed.glb", loop, frame_start=1)) == \
        pytest.approx((0.1, 1.1))
    # wiggly reads its own times back (its extras keep the shot's)
    np.testing.assert_allclose(read_animation(tmp_path / "cycle.glb").times, times, atol=1e-9)


def test_keys_of_a_group_that_disagree_at_a_loops_seam_are_warned_about():
    """In a loop the end is the start: a group at rest at 0 s and lifted at 1 s cannot meet
    both (the solve misses both by half, and the missed-keys warning advised stiffness);
    the same target at both ends is fine."""
    import warnings

    from wiggly.scene import scene_from_dict

    def scene(end_target):
        return {"mesh": {"path": "builtin:bar"}, "time": {"end": 1.0, "fps": 10, "loop": True},
                "groups": {"tip": {"box": {"min": [0.9, -1, -1], "max": [2, 1, 1]}}},
                "keyframes": [{"time": 0.0, "group": "tip", "position": "rest"},
                              {"time": 1.0, "group": "tip", "position": end_target}]}

    with pytest.warns(UserWarning, match=r"keyframes\[0\] \(t = 0 s\) and keyframes\[1\] "
                                         r"\(t = 1 s\) key group 'tip' with another position, "
                                         r"but in a loop t = 1 s is t = 0 s"):
        scene_from_dict(scene({"offset": [0.0, 0.1, 0.0]}), "s.toml")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene_from_dict(scene("rest"), "s.toml")
