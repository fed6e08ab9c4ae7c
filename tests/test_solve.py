"""The linear sparse spacetime solve (Theorem 1) against mathematics and an independent method."""

from __future__ import annotations

import importlib
import itertools
import re
import warnings
from dataclasses import replace

import meshio
import numpy as np
import pytest
import scipy.sparse.linalg as spla

from wiggly import Damping, load_model, prepare
from wiggly.errors import WigglyInputError
from wiggly.fem import Material
from wiggly.framebased import solve_framebased
from wiggly.keyframes import Keyframe
from wiggly.primitives import box_mesh
from wiggly.solve import solve

from .conftest import make_body


def ends(body, on="tets"):
    X = body.rest_positions(on)
    return np.flatnonzero(X[:, 0] < 1e-9), np.flatnonzero(X[:, 0] > 1 - 1e-9)


def sparse_keys(body, velocity):
    _left, right = ends(body)
    allv = np.arange(body.n_vertices("tets"))
    return [
        Keyframe.rest(body, 0.0, allv, still=True, on="tets"),
        Keyframe.offset(
            body, 0.5, right, (0, 0.2, 0), on="tets", velocity=(0, 1.0, 0) if velocity else None
        ),
        Keyframe.offset(body, 1.0, right, (0, -0.1, 0.1), on="tets"),
    ]


@pytest.mark.parametrize("velocity", [False, True])
def test_theorem1_smoothness_at_nodes(bar, velocity):
    """C2 at nodes without a velocity constraint, only C1 where one is prescribed."""
    anim = solve(bar, sparse_keys(bar, velocity), warp=False, end=1.5)
    jumps = {}
    for t in (0.5, 1.0):
        L = anim.modal([t], 3, side="left")[:, 0]
        R = anim.modal([t], 3, side="right")[:, 0]
        jumps[t] = [np.max(np.abs(L[d] - R[d])) / np.max(np.abs(R[d])) for d in range(4)]
    # position-only node t = 1: value, velocity, acceleration continuous; jerk jumps
    assert max(jumps[1.0][:3]) < 1e-9 and jumps[1.0][3] > 1e-3
    if velocity:  # value and velocity continuous, acceleration jumps
        assert max(jumps[0.5][:2]) < 1e-9 and jumps[0.5][2] > 1e-3
    else:
        assert max(jumps[0.5][:3]) < 1e-9 and jumps[0.5][3] > 1e-3


def test_modes_satisfy_the_fourth_order_equation_between_nodes(bar):
    """Between nodes every mode solves the wiggly-spline equation q^(4) + 2 (lam - 2
    delta^2) q'' + lam (lam q + g) = 0, delta = (alpha + beta lam) / 2 (Theorem 1; the
    module doc of wiggly.splines), read through Animation.modal's 4th derivative."""
    anim = solve(bar, sparse_keys(bar, True), warp=False, end=1.5)
    q = anim.modal([0.2, 0.7, 1.3], 4)
    lam, d, g = bar.eigenvalues, bar.delta, bar.modal_gravity
    terms = np.stack([q[4], 2 * (lam - 2 * d**2) * q[2], lam * (lam * q[0] + g)])
    residual = np.abs(terms.sum(axis=0)) / np.abs(terms).sum(axis=0).clip(1e-300)
    assert residual.max() < 1e-8, residual.max()
    assert np.abs(q[4]).max() > 0  # the check is not of zeros


@pytest.mark.parametrize("velocity", [False, True])
def test_matches_frame_based_solution_with_first_order_convergence(bar, velocity):
    """An independent discretization of the same functional converges to our solution.

    The frame-based scheme sums residuals at interior frames only (first-order quadrature of
    the integral at the ends and at the keyframe kinks), so the expected rate is 1."""
    keys = sparse_keys(bar, velocity)
    anim = solve(bar, keys, warp=False, end=1.5, preroll=0)
    errors = []
    for fps in (80, 160, 320, 640):
        t, q = solve_framebased(bar, keys, fps, 0.0, 1.5)
        exact = anim.modal(t)[0]
        errors.append(np.max(np.abs(q - exact)) / np.max(np.abs(exact)))
    rates = np.log2(np.array(errors[:-1]) / errors[1:])
    assert errors[-1] < 2e-3
    assert np.all(rates > 0.85) and np.all(rates < 1.3), rates


def test_constraint_residual_shrinks_as_weight_grows(bar):
    """Penalty method: the least-squares keyframe residual decreases monotonically to 0."""
    _, right = ends(bar, "surface")
    res = []
    for stiffness in (1e2, 1e4, 1e6, 1e8, 1e10, 1e12):
        keys = [
            Keyframe.rest(bar, 0.0, np.arange(bar.n_vertices()), still=True, stiffness=stiffness),
            Keyframe.offset(bar, 1.0, right, (0, 0.3, 0), stiffness=stiffness),
        ]
        res.append(solve(bar, keys, warp=False, end=1.5).constraint_residuals()[1]["position_rms"])
    assert all(a > b for a, b in itertools.pairwise(res)), res
    assert res[-1] < 1e-5 * res[0], res


def test_rest_keyframes_without_gravity_give_the_rest_state(tmp_path_factory):
    body = make_body(tmp_path_factory, gravity=(0, 0, 0))
    left, right = ends(body, "surface")
    keys = [
        Keyframe.rest(body, 0.0, left, still=True),
        Keyframe.rest(body, 0.7, right),
        Keyframe.rest(body, 1.3, np.r_[left, right], still=True),
    ]
    anim = solve(body, keys, warp=False, end=2.0)
    u = anim.displacements(anim.frame_times(60), "tets")
    assert np.max(np.abs(u)) < 1e-12
    assert np.max(np.abs(anim.values)) < 1e-12 and np.max(np.abs(anim.velocities)) < 1e-12


def test_free_fall_is_a_parabola(bar):
    """At rest at t = 0 and nothing else: the centre of mass falls freely (E = 0 motion),
    slowed only by the mass-proportional damping alpha: x'' = -alpha x' + g."""
    keys = [Keyframe.rest(bar, 0.0, np.arange(bar.n_vertices()), still=True)]
    anim = solve(bar, keys, warp=False, end=1.0)
    t = np.linspace(0, 1, 21)
    m = bar.vertex_masses("tets")
    com = np.einsum("i,fij->fj", m, anim.positions(t, "tets")) / m.sum()
    a = bar.damping.alpha
    expected = bar.gravity[1] * (t / a - (1 - np.exp(-a * t)) / a**2)
    assert np.max(np.abs(com[:, 1] - com[0, 1] - expected)) < 1e-4
    assert np.max(np.abs(com[:, [0, 2]] - com[0, [0, 2]])) < 1e-8
    assert anim.energy() < 1e-6 * bar.mass


def test_energy_equals_the_full_space_functional(bar):
    """E of eq. (3) evaluated with the full M, D = alpha M + beta K and K (not the modal
    decoupling) by quadrature agrees with the closed-form modal energy (free body:
    g lies in the span of M Phi)."""
    left, right = ends(bar, "surface")
    keys = [
        Keyframe.rest(bar, 0.0, left, still=True),
        Keyframe.offset(bar, 0.6, right, (0, 0.1, 0.05)),
        Keyframe.rigid(bar, 1.2, left, rotation=(0, 0, 0.2)),
    ]
    anim = solve(bar, keys, warp=False, end=1.5)
    x, w = np.polynomial.legendre.leggauss(12)
    edges = np.linspace(0, 1.5, 61)
    edges = np.unique(np.r_[edges, anim.nodes])
    t = (edges[:-1, None] + (x + 1) / 2 * np.diff(edges)[:, None]).ravel()
    wt = (w * np.diff(edges)[:, None] / 2).ravel()
    q = anim.modal(t, 2)
    Phi = bar.modes.vectors
    u, du, ddu = (q[d] @ Phi.T for d in range(3))
    M, K = bar.M, bar.K
    D = bar.damping.alpha * M + bar.damping.beta * K
    f = (M @ ddu.T + D @ du.T + K @ u.T).T + bar.gravity_vector
    lu = spla.splu(M.tocsc())
    Minv_f = lu.solve(f.T).T
    E_full = 0.5 * np.sum(wt * np.einsum("fi,fi->f", f, Minv_f))
    assert abs(E_full - anim.energy()) < 1e-8 * E_full


def test_full_keyframes_are_interpolated(bar):
    """Full keyframes (every vertex) as the special case: the motion passes through them."""
    allv = np.arange(bar.n_vertices())
    X = bar.rest_positions()
    bend = np.c_[np.zeros(len(X)), 0.05 * np.sin(np.pi * X[:, 0]), np.zeros(len(X))]
    keys = [
        Keyframe.rest(bar, 0.0, allv, still=True, stiffness=1e9),
        Keyframe(1.0, allv, X + bend, stiffness=1e9),
    ]
    anim = solve(bar, keys, warp=False, end=1.5)
    P = anim.positions([1.0])[0]
    # the target is reachable only within the span of the modes: compare with its projection
    Phi = bar.surface_basis
    coef, *_ = np.linalg.lstsq(Phi, bend.ravel(), rcond=None)
    best = (Phi @ coef).reshape(-1, 3)
    assert np.max(np.abs(P - X - best)) < 1e-5


def test_cantilever_sags_under_gravity_to_static_equilibrium(cantilever):
    """A fixed body with heavy damping and no keyframes settles at K u = -g (modal)."""
    anim = solve(cantilever, [], warp=False, end=30.0)
    q = anim.modal([30.0])[0, 0]
    q_eq = -cantilever.modal_gravity / cantilever.eigenvalues
    assert np.allclose(q, q_eq, rtol=1e-6, atol=1e-9)
    assert anim.energy() < 1e-9 * cantilever.mass  # it starts in equilibrium: free


def test_solver_vectorized_sampling_matches_pointwise(bar):
    keys = sparse_keys(bar, True)
    anim = solve(bar, keys, warp=False, end=1.5)
    t = np.linspace(0, 1.5, 37)
    P = anim.positions(t)
    for k in (0, 11, 36):
        assert np.allclose(P[k], anim.positions([t[k]])[0], atol=1e-14)


# --- bad input ---------------------------------------------------------------------------
def test_one_frame_written_in_single_precision_is_one_node(bar):
    """A key at t = 0.1 and another at float32(0.1) (1.5e-9 s later: the same frame from a
    tool that writes single precision) share a node and are both met, instead of leaving an
    interval of nanoseconds that no factorization survives; keys a frame apart stay apart."""
    X = bar.rest_positions()
    tip, root = np.flatnonzero(X[:, 0] > 0.99), np.flatnonzero(X[:, 0] < 0.01)
    t32 = float(np.float32(0.1))
    assert t32 != 0.1
    keys = [Keyframe.offset(bar, 0.1, tip, (0.0, 0.1, 0.0)), Keyframe.rest(bar, t32, root)]
    anim = solve(bar, keys, warp=False, end=1.0)
    assert len(anim.nodes) == 3  # start, the shared node, end
    assert max(r["position_max"] for r in anim.constraint_residuals()) < 5e-3
    frame = solve(bar, [keys[0], Keyframe.rest(bar, 0.1 + 1 / 240, root)], warp=False, end=1.0)
    assert len(frame.nodes) == 4


def test_keys_too_close_to_solve_are_named_not_blamed_on_preroll(bar, monkeypatch):
    """When keys a hair apart leave a numerically singular system (merging switched off here),
    the message names the keys and their times, not a pre-roll of 0 that was never given."""
    for module in ("wiggly.solve.problem", "wiggly.solve.nodes"):
        monkeypatch.setattr(importlib.import_module(module), "merge_tolerance",
                            lambda start, end: 0.0)
    tip = np.flatnonzero(bar.rest_positions()[:, 0] > 0.99)
    keys = [Keyframe.offset(bar, 0.5, tip, (0.0, 0.2, 0.0), name="a"),
            Keyframe.offset(bar, 0.5 + 1e-9, tip, (0.0, 0.2, 0.0), name="b")]
    with pytest.raises(WigglyInputError) as err:
        solve(bar, keys, warp=False, end=1.0)
    text = str(err.value)
    assert "#0 ('a'), #1 ('b') at t = 0.5 s and 0.500000001 s are 1e-09 s apart" in text, text
    assert "preroll" not in text, text


def test_a_singular_linear_system_is_explained_by_its_likely_cause(bar, monkeypatch):
    """When the factorization fails (forced here), the message names what can cause it: a
    key weighted beyond double precision, no pre-roll with a start left open, or else the
    pre-roll that was given, not a pre-roll of 0 that was not."""
    problem = importlib.import_module("wiggly.solve.problem")

    class Singular:
        def __init__(self, ab):
            raise np.linalg.LinAlgError("not positive definite")

    monkeypatch.setattr(problem, "BandedCholesky", Singular)
    tip = np.flatnonzero(bar.rest_positions()[:, 0] > 0.99)
    heavy = Keyframe.offset(bar, 0.5, tip, (0.0, 0.1, 0.0), stiffness=1e16, name="heavy")
    plain = Keyframe.offset(bar, 0.5, tip, (0.0, 0.1, 0.0))
    for keys, preroll, says in (
        ([plain, heavy], None, "keyframe #1 ('heavy') weighs too much for double precision "
                               "(stiffness 1e+16)"),
        ([plain], 0.0, "undetermined and preroll is 0"),
        ([plain], None, "numerically singular (preroll 1 s)"),
    ):
        with pytest.raises(WigglyInputError, match=re.escape(says)):
            solve(bar, keys, warp=False, end=1.0, preroll=preroll)


def test_keyframe_outside_time_range(bar):
    with pytest.raises(WigglyInputError, match=r"time 3.0 is outside .*\[0.0, 2.0\]"):
        solve(bar, [Keyframe.rest(bar, 3.0, [0])], warp=False, end=2.0)


def test_a_keyframe_on_fixed_vertices_only_warns(cantilever):
    """A keyframe whose vertices the fixed end holds cannot be met: it warns, naming the
    keyframe, when its target is away from rest or it has a velocity; at rest it is
    harmless and silent."""
    X = cantilever.rest_positions("tets")
    held = np.flatnonzero(X[:, 0] < 1e-9)
    lifted = Keyframe(0.5, held, X[held] + [0.0, 0.1, 0.0], on="tets", name="lift")
    with pytest.warns(UserWarning, match=rf"'lift'.*all {len(held)} of its vertices are held") \
            as said:
        solve(cantilever, [lifted], warp=False, end=1.0)
    # missed by 10 % of the size, but said once: raising its stiffness would not help
    assert not [w for w in said if "missed by more than" in str(w.message)]
    with pytest.warns(UserWarning, match="held by the fixed vertices"):
        solve(cantilever, [Keyframe(0.5, held, on="tets", velocity=(1.0, 0, 0))], warp=False,
              end=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solve(cantilever, [Keyframe.rest(cantilever, 0.5, held, on="tets")], warp=False,
              end=1.0)


def test_missed_velocity_keys_are_warned_about(bar):
    """Velocity keys missed by more than 5 % of their speed (or, for a still key, of the body's
    size per the shot's duration) are named with how far: here, two keys at one time that
    contradict each other; met ones are not."""
    allv = np.arange(bar.n_vertices())
    still = Keyframe.rest(bar, 0.5, allv, still=True, name="still")
    up = Keyframe(0.5, allv[:20], velocity=(0.0, 2.0, 0.0), name="up")
    with pytest.warns(UserWarning) as said:
        solve(bar, [still, up], warp=False, end=1.0)
    (text,) = [str(w.message) for w in said if "missed by more than" in str(w.message)]
    assert text.startswith("2 of 2 keyframes missed by more than 5 % of the body's size or "
                           "their velocity by 5 % of its speed"), text
    assert re.search(r"keyframes\[0\] \('still'\) at t = 0.5 s by velocity 0.9\d+ m/s, 9\d % "
                     r"of 1.0\d m/s, the body's size per the shot's duration", text), text
    assert re.search(r"keyframes\[1\] \('up'\) at t = 0.5 s by velocity 0.8\d+ m/s, 4\d % of "
                     "its speed", text), text
    assert "warp=True" not in text
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        solve(bar, [Keyframe.rest(bar, 0.0, allv, still=True), up], warp=False, end=1.0)


def test_keys_a_stiff_material_resists_are_warned_about(tmp_path_factory):
    """A key whose target lies away from rest and is missed by most of that offset is named,
    even when the miss is far below 5 % of the body's size: the tip of a clamped 1 m bar keyed
    30 mm up barely moves at Young's modulus 1e11 (the default stiffness weighs the key against
    the mass, not the material); at 1e5 it is met and nothing is said."""
    V, _ = box_mesh((10, 2, 2), (1.0, 0.1, 0.1))
    clamp = np.flatnonzero(V[:, 0] < 1e-9)
    for young, warned in ((1e11, True), (1e5, False)):
        body = make_body(tmp_path_factory, fixed=clamp, young=young, gravity=(0, 0, 0))
        tip = np.flatnonzero(body.rest_positions()[:, 0] > 0.99)
        key = Keyframe.offset(body, 0.5, tip, (0.0, 0.03, 0.0), name="tip")
        with warnings.catch_warnings(record=True) as said:
            warnings.simplefilter("always")
            anim = solve(body, [key], warp=False, end=1.0)
        moved = anim.positions([0.5])[0, tip, 1].mean() - body.rest_positions()[tip, 1].mean()
        texts = [str(w.message) for w in said if "missed by more than" in str(w.message)]
        if warned:
            assert moved < 0.015  # most of the 30 mm offset missed, well under 5 % of 1 m
            (text,) = texts
            assert "or 50 % of their offset from rest" in text, text
            assert re.search(r"keyframes\[0\] \('tip'\) at t = 0.5 s by 0.0\d* m, "
                             r"\d+ % of its 0.03 m offset from rest", text), text
            assert "Young's modulus" in text and "warp=True" not in text, text
        else:
            assert abs(moved - 0.03) < 0.003 and not texts, texts


def test_a_held_keyframe_warns_also_when_its_rows_are_round_off(cantilever, monkeypatch):
    """Surface points between fixed vertices get mode rows of round-off (1e-17), not exact
    zeros: a velocity key there is held all the same, and warned about."""
    X = cantilever.rest_positions("tets")
    held = np.flatnonzero(X[:, 0] < 1e-9)
    rows = type(cantilever).basis_rows
    monkeypatch.setattr(type(cantilever), "basis_rows",
                        lambda self, v, on="surface": rows(self, v, on) + 1e-17)
    with pytest.warns(UserWarning, match="held by the fixed vertices"):
        solve(cantilever, [Keyframe(0.5, held, on="tets", velocity=(0.0, 2.0, 0))], warp=False,
              end=1.0)


def test_unknown_vertex_index(bar):
    n = bar.n_vertices()
    with pytest.raises(
        WigglyInputError, match=f"vertex index {n + 5} does not exist.*{n} vertices"
    ):
        solve(bar, [Keyframe(0.5, [1, n + 5], np.zeros((2, 3)))], warp=False, end=1.0)
    with pytest.raises(WigglyInputError, match="vertex index -1"):
        Keyframe.rest(bar, 0.0, [-1])
    # an empty selection names the keyframe being made (it said "keyframe: selects no
    # vertices", while errors at the solve name "keyframe #0 at t=...")
    for made in (lambda: Keyframe.rest(bar, 0.5, [], name="feet"),
                 lambda: Keyframe.offset(bar, 0.5, [], (0, 0.1, 0), name="feet"),
                 lambda: Keyframe.rigid(bar, 0.5, [], (0, 0.1, 0), name="feet")):
        with pytest.raises(WigglyInputError, match=r"Keyframe\.(rest|offset|rigid) at t = "
                                                   r"0\.5 s \('feet'\): selects no vertices"):
            made()


def test_a_keyframe_built_on_another_body_is_refused(bar, cantilever, tmp_path_factory):
    """Keyframe.rest / offset / rigid read targets from the body they are given; solving them
    on a body whose rest shape differs at those vertices is a mistake, named; the same rest
    shape (another damping, fixed vertices) is the same body."""
    longer = make_body(tmp_path_factory, size=(1.5, 0.1, 0.1))
    tip = np.flatnonzero(bar.rest_positions()[:, 0] > 1 - 1e-9)
    for kf in (Keyframe.rest(longer, 0.5, tip), Keyframe.offset(longer, 0.5, tip, (0, 0.1, 0)),
               Keyframe.rigid(longer, 0.5, tip, (0, 0, 0.3))):
        with pytest.raises(WigglyInputError, match=r"built on another body: its surface vertex "
                           r"\d+ rests 0.5 m from"):
            solve(bar, [kf], warp=False, end=1.0)
    same = [Keyframe.rest(cantilever, 0.5, tip), Keyframe.rigid(bar, 0.5, tip, (0, 0, 0.3))]
    anim = solve(bar.with_dynamics(damping=Damping(0.1, 0.001)), same, warp=False, end=1.0)
    assert np.abs(anim.positions([0.5])[0][tip] - same[0].position).max() < 0.05
    # absolute targets belong to no body
    solve(bar, [Keyframe(0.5, tip, longer.rest_positions()[tip])], warp=False, end=1.0)
    # the same bar read from float32 coordinates (rounded by about 1e-9 m) is the same body
    V, T = box_mesh((10, 2, 2), (1.0, 0.1, 0.1))
    path = tmp_path_factory.mktemp("f32") / "bar.vtu"
    meshio.write(path, meshio.Mesh(V.astype(np.float32), [("tetra", T)]))
    rounded = prepare(load_model(path), n_modes=10, cache_dir=False)
    assert 0 < np.abs(rounded.rest_positions() - bar.rest_positions()).max() < 1e-7
    solve(rounded, [Keyframe.rest(bar, 0.5, tip)], warp=False, end=1.0)
    # a keyframe whose vertices were changed after it was built is still of its body
    moved = replace(Keyframe.rest(bar, 0.5, tip), vertices=tip[:4],
                    position=bar.rest_positions()[tip[:4]])
    solve(bar, [moved], warp=False, end=1.0)
    # a vertex the body does not have: named as another body's
    bigger = make_body(tmp_path_factory, shape=(20, 2, 2), size=(2.0, 0.1, 0.1))
    far = Keyframe.rest(bigger, 0.5, [bigger.n_vertices() - 1])
    with pytest.raises(WigglyInputError, match=rf"built on another body: it was made with "
                       rf"surface vertex {bigger.n_vertices() - 1}, and this body has "
                       rf"{bar.n_vertices()} surface vertices"):
        solve(bar, [far], warp=False, end=1.0)


def test_nan_target(bar):
    target = bar.rest_positions()[[0, 1]].copy()
    target[1, 2] = np.nan
    with pytest.raises(WigglyInputError, match=r"vertex #1 .component z. is nan"):
        solve(bar, [Keyframe(0.5, [0, 1], target)], warp=False, end=1.0)


def test_wrong_target_shape_and_empty_keyframe(bar):
    with pytest.raises(WigglyInputError, match=r"shape \(4, 3\); expected \(2, 3\)"):
        solve(bar, [Keyframe(0.5, [0, 1], np.zeros((4, 3)))], warp=False, end=1.0)
    with pytest.raises(WigglyInputError, match="neither positions nor velocities"):
        solve(bar, [Keyframe(0.5, [0, 1])], warp=False, end=1.0)


@pytest.mark.parametrize(
    "field,kwargs,pattern",
    [
        ("young", dict(young=-1.0), "young"),
        ("poisson", dict(poisson=0.5), "poisson"),
        ("density", dict(density=0.0), "density"),
    ],
)
def test_negative_material_constants(field, kwargs, pattern):
    with pytest.raises(WigglyInputError, match=pattern):
        Material(**kwargs)


def test_negative_damping_and_empty_range(bar):
    from wiggly.body import Damping

    with pytest.raises(WigglyInputError, match="alpha = -1"):
        Damping(alpha=-1)
    with pytest.raises(WigglyInputError, match="empty"):
        solve(bar, [], warp=False, start=1.0, end=1.0)


def test_python_api_mistakes_are_named(tmp_path_factory):
    """What a newcomer gets wrong in Python: each is refused with a message naming the
    argument, the value and what would be right (they were raw numpy or attribute errors, a
    silent wrong mesh, or a crash deep in the solve)."""
    import wiggly
    from wiggly.body import Damping

    body = make_body(tmp_path_factory, shape=(6, 2, 2), n_modes=8)
    X = body.rest_positions()
    key = Keyframe.rest(body, 0.0, np.arange(len(X)))
    anim = solve(body, [key], duration=1.0, warp=False)
    cases = {
        "on typo": (lambda: body.rest_positions(on="Surface"), "on = 'Surface': use 'surface'"),
        "on typo, positions": (lambda: anim.positions([0.5], on="tet"), "on = 'tet'"),
        "on typo, keyframe": (lambda: Keyframe.rest(body, 0.0, [0, 1], on="bogus"),
                              "on = 'bogus'"),
        "one keyframe": (lambda: solve(body, key), "put it in a list: [key]"),
        "a path": (lambda: solve("bar.obj", [key]), "body should be a wiggly.Body"),
        "None key": (lambda: solve(body, [key, None]), "keyframes[1] is a NoneType"),
        "long shot": (lambda: solve(body, [key], duration=1e6), "at most 3600 s"),
        "duration and end": (lambda: solve(body, [key], duration=1.0, end=2.0),
                             "give duration (1.0 s) or end (2.0 s), not both"),
        "warp as text": (lambda: solve(body, [key], duration=1.0, warp="yes"),
                         "warp should be True or False"),
        "damping number": (lambda: wiggly.prepare(body.model, damping=0.5),
                           "damping should be a wiggly.Damping"),
        "material dict": (lambda: wiggly.prepare(body.model, material={"young": 1e6}),
                          "material should be a wiggly.Material"),
        "dynamics number": (lambda: body.with_dynamics(damping=0.5),
                            "damping should be a wiggly.Damping"),
        "fps 0": (lambda: anim.frame_times(0), "fps should be a number > 0"),
        "no times": (lambda: anim.positions([]), "times should be a non-empty list"),
        "NaN time": (lambda: anim.positions([np.nan]), "1 that are not finite numbers"),
        "fps huge": (lambda: anim.frame_times(1e5), "more than 1000 frames per second"),
        "one point for a group": (
            lambda: solve(body, [Keyframe(0.5, np.arange(10), position=np.zeros(3))],
                          duration=1.0, warp=False), "would pull them all to that point"),
        "offsets of the wrong shape": (
            lambda: Keyframe.offset(body, 0.5, [0, 1], np.zeros((3, 3))),
            "offset has shape (3, 3); expected (3,) or (2, 3), one per vertex"),
        "translation of two numbers": (
            lambda: Keyframe.rigid(body, 0.5, [0, 1], translation=(1.0, 2.0)),
            "translation has shape (2,); expected (3,)"),
        "still and a velocity": (
            lambda: Keyframe.rest(body, 0.0, [0], still=True, velocity=(1.0, 0, 0)),
            "give still=True (zero velocity) or a velocity, not both"),
        "time as text": (lambda: Keyframe.rest(body, "soon", [0]),
                         "time should be a number of seconds; got 'soon'"),
        "time in a list": (lambda: Keyframe.rest(body, [0.5], [0]),
                           "time should be a number of seconds; got [0.5]"),
        "NaN keyframe time": (lambda: solve(body, [Keyframe.rest(body, np.nan, [0])]),
                              "time = nan s; it must be a finite number"),
        "targets as text": (
            lambda: solve(body, [Keyframe(0.5, [0], position=[["a", "b", "c"]])],
                          duration=1.0, warp=False),
            "position targets should be numbers (metres)"),
        "derivative -1": (lambda: anim.displacements([0.5], derivative=-1),
                          "derivative should be an integer in [0, 3]; got -1"),
        "derivative 1.5": (lambda: anim.displacements([0.5], derivative=1.5),
                           "derivative should be an integer in [0, 3]; got 1.5"),
        "side": (lambda: anim.modal([0.5], 1, side="middle"),
                 "side should be 'left' or 'right'; got 'middle'"),
        "integer dtype": (lambda: anim.positions([0.5], dtype=np.int32),
                          "dtype should be a floating type"),
        "2-D indices": (lambda: Keyframe.offset(body, 0.5, [[0, 1], [2, 3]], (0, 0.1, 0)),
                        "vertex indices should be a flat list; got an array of shape (2, 2)"),
        "every vertex fixed": (
            lambda: wiggly.prepare(body.model, n_modes=5, cache_dir=False,
                                   fixed_vertices=np.arange(body.tets.n_vertices)),
            "every vertex is fixed: no degrees of freedom are left to move"),
    }
    for label, (call, says) in cases.items():
        with pytest.raises(WigglyInputError) as err, warnings.catch_warnings():
            warnings.simplefilter("error", RuntimeWarning)  # no numpy noise before the message
            call()
        assert says in str(err.value), (label, str(err.value))
    assert body.with_dynamics(damping=Damping(0.1, 0.001)).damping.alpha == 0.1
    with pytest.warns(UserWarning, match="in radians") as said:  # degrees given as radians
        Keyframe.rigid(body, 1.0, [0, 1, 2], rotation=(0, 90, 0))
    assert [w.filename for w in said] == [__file__]  # the user's line, not wiggly's
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # several turns in radians: no warning
        Keyframe.rigid(body, 1.0, [0, 1, 2], rotation=(0, 0, 4 * np.pi + 0.3))


def test_refined_nodes_keep_every_node_and_split_long_steps_evenly():
    """Every original node stays; no step is longer than asked; a long interval is split
    into equal steps; nothing changes where every step is short enough."""
    from wiggly.solve.nodes import refine_nodes

    nodes = np.array([0.0, 0.1, 1.0, 1.05, 3.0])
    out = refine_nodes(nodes, 0.25)
    assert np.isin(nodes, out).all()
    assert np.diff(out).max() <= 0.25 + 1e-12 and np.all(np.diff(out) > 0)
    inside = out[(out >= 1.05) & (out <= 3.0)]
    np.testing.assert_allclose(np.diff(inside), (3.0 - 1.05) / 8)
    assert refine_nodes(nodes, 5.0) is nodes
