"""Sparse spacetime constraints: partial keyframes (Schulz et al. 2014, the energy E_C of eq. (6)).

A keyframe constrains some vertices (of the user's surface or of the tet mesh) at one time:
their positions (A_k u(t_k) = a_k) and/or their velocities (B_k u'(t_k) = b_k), as least
squares with weights c_A, c_B.  Position targets are given as

* absolute positions ``Keyframe(t, vertices, position=X)``,
* offsets from rest ``Keyframe.offset(t, vertices, d)``,
* a rigid transform of the selected rest vertices ``Keyframe.rigid(t, vertices, R, x)``,
* the rest state ``Keyframe.rest(t, vertices)`` (optionally with zero velocity),

and a full keyframe is the special case where every vertex is selected.

Weights.  ``E_C = 1/2 sum_k c_A |A_k u - a_k|^2 + c_B |B_k u' - b_k|^2`` (Schulz et al. 2014,
eq. (6)).  Unless given explicitly, c_A and c_B are set from a dimensionless ``stiffness`` s as
c_A = s m / (k T^3) and c_B = s m / (k T), with m the body's mass, k the number of selected
vertices and T the animation's duration: the units of the spacetime energy, so the same
``stiffness`` pulls equally hard whatever the size, mass or duration.  Not whatever the
material: a stiffer body resists a key more (its elastic energy grows with the square of
its modes' eigenvalues), so keys on stiff bodies need a higher ``stiffness``.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike

from wiggly.body import Body, Where
from wiggly.checks import vertex_indices
from wiggly.errors import WigglyInputError, warn

DEFAULT_STIFFNESS = 1e6


def _rotation(rotation: ArrayLike) -> np.ndarray:
    """A 3x3 rotation from a matrix or a rotation vector (axis * angle in radians); a vector
    of whole numbers turning by more than a full turn, (0, 90, 0), is warned about: degrees
    given as radians."""
    R = np.asarray(rotation, dtype=float)
    if R.shape == (3,):
        theta = float(np.linalg.norm(R))
        if not np.isfinite(theta):
            raise WigglyInputError(f"rotation = {R.tolist()} must be 3 finite numbers")
        if theta > 2 * np.pi and np.all(R == np.round(R)):
            warn(
                f"rotation = {R.tolist()} turns by {theta:g} rad ({np.degrees(theta):g} deg): a "
                "rotation vector is axis x angle in radians (scene files take Euler degrees); "
                "a 90 degree turn about y is (0, np.radians(90), 0)")
        if theta == 0:
            return np.eye(3)
        k = R / theta
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        return np.eye(3) + np.sin(theta) * Kx + (1 - np.cos(theta)) * Kx @ Kx
    if R.shape != (3, 3) or not np.all(np.isfinite(R)):
        raise WigglyInputError(
            f"rotation must be a 3x3 matrix or a rotation vector; got shape {R.shape}"
        )
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
        raise WigglyInputError("rotation matrix is not a proper rotation (R^T R = I, det R = 1)")
    return R


@dataclass
class Keyframe:
    """Constraints on some vertices at one time ``time`` (seconds).

    ``position`` (k, 3) absolute target positions (or None); ``velocity`` (k, 3) or (3,)
    target velocities in m/s (or None); ``on`` says whether ``vertices`` index the user's
    surface (default) or the tet mesh.  ``stiffness`` (dimensionless, see module doc) or
    explicit ``c_A`` / ``c_B`` set the weights.
    """

    time: float
    vertices: np.ndarray
    position: np.ndarray | None = None
    velocity: np.ndarray | None = None
    on: Where = "surface"
    stiffness: float = DEFAULT_STIFFNESS
    c_A: float | None = None
    c_B: float | None = None
    name: str = ""
    # how the target was specified, kept for scene files and the editor
    spec: dict = field(default_factory=dict, repr=False)
    # (vertices, their rest positions) on the body the constructors below read targets from:
    # a keyframe built on one body and solved on another is refused (:meth:`checked`)
    built_on: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False,
                                                           compare=False)

    def __post_init__(self) -> None:
        t = self.time
        if isinstance(t, bool) or not isinstance(t, int | float | np.integer | np.floating):
            raise WigglyInputError(f"keyframe{f' {self.name!r}' if self.name else ''}: time "
                                   f"should be a number of seconds; got {t!r}")
        if not np.isfinite(t):
            raise WigglyInputError(f"keyframe{f' {self.name!r}' if self.name else ''}: time "
                                   f"= {t!r} s; it must be a finite number")

    def __repr__(self) -> str:  # a summary: the targets are attributes
        what = [w for w, v in (("position", self.position), ("velocity", self.velocity))
                if v is not None]
        name = f", {self.name!r}" if self.name else ""
        weights = (f"c_A = {self.c_A:g}, c_B = {self.c_B:g}" if self.c_A is not None or
                   self.c_B is not None else f"stiffness {self.stiffness:g}")
        return (f"Keyframe(t = {self.time:g} s, {len(np.atleast_1d(self.vertices))} {self.on} "
                f"vertices, {' and '.join(what) or 'no target'}, {weights}{name})")

    # --- constructors for the target kinds ----------------------------------------------
    @classmethod
    def rest(
        cls, body: Body, time: float, vertices: ArrayLike, *, still: bool = False, **kw
    ) -> Keyframe:
        """Vertices at their rest positions (and at zero velocity if ``still``)."""
        on = kw.pop("on", "surface")
        v = vertex_indices(vertices, body.n_vertices(on), on, _named("rest", time, kw))
        X = body.rest_positions(on)[v]
        if still and kw.get("velocity") is not None:
            raise WigglyInputError("Keyframe.rest: give still=True (zero velocity) or a "
                                   "velocity, not both")
        vel = np.zeros(3) if still else kw.pop("velocity", None)
        kw.pop("velocity", None)
        return cls(time, v, X.copy(), vel, on, spec={"kind": "rest"},
                   built_on=(v.copy(), X.copy()), **kw)

    @classmethod
    def offset(
        cls, body: Body, time: float, vertices: ArrayLike, offset: ArrayLike, **kw
    ) -> Keyframe:
        """Vertices displaced from rest by ``offset`` ((3,) or (k, 3) metres)."""
        on = kw.pop("on", "surface")
        v = vertex_indices(vertices, body.n_vertices(on), on, _named("offset", time, kw))
        d = _vector_or_rows(offset, len(v), "Keyframe.offset: offset")
        X = body.rest_positions(on)[v]
        return cls(
            time,
            v,
            X + d,
            on=on,
            spec={"kind": "offset", "offset": np.asarray(offset, float)},
            built_on=(v.copy(), X.copy()),
            **kw,
        )

    @classmethod
    def rigid(
        cls,
        body: Body,
        time: float,
        vertices: ArrayLike,
        rotation: ArrayLike = (0, 0, 0),
        translation: ArrayLike = (0, 0, 0),
        center: ArrayLike | None = None,
        **kw,
    ) -> Keyframe:
        """Rest vertices rotated by ``rotation`` about ``center`` (default: their centroid),
        then translated: x = R (X - c) + c + translation.  ``rotation`` is a rotation vector
        (axis x angle, in radians, at most a full turn: a 90 degree turn about y is
        ``(0, np.radians(90), 0)``; scene files take Euler angles in degrees instead) or a
        3x3 rotation matrix (e.g. ``scipy.spatial.transform.Rotation.as_matrix()``)."""
        on = kw.pop("on", "surface")
        v = vertex_indices(vertices, body.n_vertices(on), on, _named("rigid", time, kw))
        X = body.rest_positions(on)[v]
        R = _rotation(rotation)
        c = (X.mean(axis=0) if center is None
             else _vector_or_rows(center, 0, "Keyframe.rigid: center"))
        x = (X - c) @ R.T + c + _vector_or_rows(translation, 0, "Keyframe.rigid: translation")
        spec = {
            "kind": "rigid",
            "rotation": np.asarray(rotation, float),
            "translation": np.asarray(translation, float),
            "center": c,
        }
        return cls(time, v, x, on=on, spec=spec, built_on=(v.copy(), X.copy()), **kw)

    # --- validation and weights ----------------------------------------------------------
    def checked(self, body: Body, t0: float, t1: float, label: str = "") -> Keyframe:
        """Validate against the body and the time range; return a normalized copy."""
        what = label or (f"keyframe '{self.name}'" if self.name else f"keyframe at t={self.time}")
        t = float(self.time)
        if not np.isfinite(t) or t < t0 - 1e-9 or t > t1 + 1e-9:
            raise WigglyInputError(
                f"{what}: time {self.time!r} is outside the animation's time range [{t0}, {t1}] s"
            )
        if self.on not in ("surface", "tets"):
            raise WigglyInputError(f"{what}: on = {self.on!r}; use 'surface' or 'tets'")
        _check_same_body(body, what, self.on, self.built_on)
        v = vertex_indices(self.vertices, body.n_vertices(self.on), self.on, what)
        pos = vel = None
        if self.position is not None:
            pos = _numbers(self.position, f"{what}: position targets")
            if pos.shape == (3,) and len(v) > 1:  # one point for a group: not what it means
                raise WigglyInputError(
                    f"{what}: one position target {pos.tolist()} for {len(v)} vertices would "
                    f"pull them all to that point; give ({len(v)}, 3) targets, one per vertex, "
                    "or use Keyframe.offset(body, time, vertices, offset) to move the group")
            if pos.shape == (3,):
                pos = np.broadcast_to(pos, (len(v), 3))
            if pos.shape != (len(v), 3):
                raise WigglyInputError(
                    f"{what}: position targets have shape {pos.shape}; expected ({len(v)}, 3), one "
                    "per selected vertex"
                )
            _finite(pos, f"{what}: position target")
        if self.velocity is not None:
            vel = (
                np.broadcast_to(np.asarray(self.velocity, float), (len(v), 3))
                if np.shape(self.velocity) in ((3,), (len(v), 3))
                else None
            )
            if vel is None:
                raise WigglyInputError(
                    f"{what}: velocity has shape {np.shape(self.velocity)}; expected (3,) or "
                    f"({len(v)}, 3)"
                )
            _finite(vel, f"{what}: velocity target")
        if pos is None and vel is None:
            raise WigglyInputError(f"{what}: it constrains neither positions nor velocities")
        for name in ("stiffness", "c_A", "c_B"):
            w = getattr(self, name)
            if w is not None and (not np.isfinite(w) or w < 0):
                raise WigglyInputError(f"{what}: {name} = {w!r} must be a finite number >= 0")
        _warn_if_held(body, what, v, self.on, pos, vel)
        t = min(max(t, t0), t1)
        return replace(self, time=t, vertices=v, position=pos, velocity=vel)

    def weights(self, body: Body, duration: float) -> tuple[float, float]:
        """(c_A, c_B) of eq. (6), from explicit values or the dimensionless stiffness."""
        k = max(len(self.vertices), 1)
        m = body.mass
        c_A = self.c_A if self.c_A is not None else self.stiffness * m / (k * duration**3)
        c_B = self.c_B if self.c_B is not None else self.stiffness * m / (k * duration)
        return float(c_A), float(c_B)




def _numbers(value: ArrayLike, what: str) -> np.ndarray:
    """``value`` as a float64 array, or a WigglyInputError naming it."""
    try:
        return np.asarray(value, dtype=float)
    except (TypeError, ValueError) as err:
        raise WigglyInputError(f"{what} should be numbers (metres); got {value!r:.80}") from err


def _vector_or_rows(value: ArrayLike, k: int, what: str) -> np.ndarray:
    """A (3,) vector, or with ``k`` > 0 also (k, 3) rows, as float64; (3,) is broadcast to
    (k, 3) when k > 0."""
    d = _numbers(value, what)
    if d.shape == (3,):
        return np.broadcast_to(d, (k, 3)) if k else d
    if k and d.shape == (k, 3):
        return d
    rows = f" or ({k}, 3), one per vertex" if k else ""
    raise WigglyInputError(f"{what} has shape {d.shape}; expected (3,){rows}")


def _check_same_body(body: Body, what: str, on: Where,
                     built_on: tuple[np.ndarray, np.ndarray] | None) -> None:
    """Refuse a keyframe whose constructor read its targets from another body: the vertices
    it was built with do not rest where they did there (within 1e-6 of the body's size, so
    the same surface read from a float32 file is the same body; so is the same surface
    meshed again, for surface keyframes)."""
    if built_on is None:
        return
    built, rest = built_on
    mesh = "surface" if on == "surface" else "tet-mesh"
    again = (" (meshing a surface again renumbers its tet-mesh vertices: key the surface, "
             "on = 'surface')" if on == "tets" else "")
    n = body.n_vertices(on)
    advice = (f"Build it with this body (Keyframe.rest / offset / rigid(body, ...)), or give "
              f"absolute targets with Keyframe(time, vertices, position=...){again}.")
    if len(built) and int(built.max()) >= n:
        raise WigglyInputError(
            f"{what} was built on another body: it was made with {mesh} vertex "
            f"{int(built.max())}, and this body has {n} {mesh} vertices. " + advice)
    all_rest = body.rest_positions(on)
    gap = np.linalg.norm(np.asarray(rest, float) - all_rest[built], axis=1)
    size = float(np.ptp(all_rest, axis=0).max())
    if not len(gap) or gap.max() <= 1e-6 * size:
        return
    worst = int(gap.argmax())
    raise WigglyInputError(
        f"{what} was built on another body: its {mesh} vertex {int(built[worst])} rests "
        f"{gap[worst]:.3g} m from where this body's does, so its targets come from that "
        "body's rest shape. " + advice)


def held(body: Body, v: np.ndarray, on: str) -> bool:
    """Whether the body's fixed vertices hold every vertex ``v`` (on ``on``): the modes
    vanish there (on surface points between fixed vertices, up to round-off: barycentric
    weights of 1e-17 on a free vertex)."""
    fixed = body.fixed_vertices
    if fixed is None or not len(fixed):
        return False
    return bool(np.abs(body.basis_rows(v, on)).max(initial=0.0)
                <= 1e-9 * np.abs(body.basis(on)).max())


def _warn_if_held(body: Body, what: str, v: np.ndarray, on: str, pos: np.ndarray | None,
                  vel: np.ndarray | None) -> None:
    """Warn when every vertex of a keyframe is held by the body's fixed vertices (the modes
    vanish there) and its target is not the rest pose: it cannot be met, nor move anything."""
    if not held(body, v, on):
        return
    rest = body.rest_positions(on)[v]
    size = float(np.ptp(body.rest_positions(on), axis=0).max())
    away = pos is not None and np.abs(pos - rest).max(initial=0.0) > 1e-9 * size
    if away or (vel is not None and np.any(vel != 0.0)):
        warn(f"{what}: all {len(v)} of its vertices are held by the fixed vertices, "
             "so it cannot be met and moves nothing (key vertices that are free, or "
             "remove it)")


def _finite(a: np.ndarray, what: str) -> None:
    bad = np.argwhere(~np.isfinite(a))
    if bad.size:
        i, c = bad[0]
        raise WigglyInputError(
            f"{what} of vertex #{i} (component {'xyz'[c]}) is {a[i, c]}; "
            "targets must be finite numbers"
        )


def _named(kind: str, time: float, kw: dict) -> str:
    """How a constructor's messages name the keyframe being made: ``Keyframe.rest at t =
    0.5 s ('feet')``."""
    name = kw.get("name")
    when = f"{float(time):g} s" if isinstance(time, numbers.Real) and not isinstance(
        time, bool) else repr(time)  # a time that is no number is refused after, as it is
    return f"Keyframe.{kind} at t = {when}" + (f" ({name!r})" if name else "")
