"""A prepared body: mesh, linear FEM, eigenmodes and per-mode coefficients.

Schulz et al. 2014, eqs. (1)-(5).

A :class:`Body` is what every later stage works on.  It holds the simulation tet mesh, the
user's surface embedded in it, the assembled M and K, the lowest r eigenmodes, and the
decoupled per-mode data of the spacetime energy (Schulz et al. 2014, eq. (4)):

    delta_i = (alpha + beta lambda_i) / 2,      g_i = phi_i^T g,   g = -M gravity.

Everything is inspectable: ``body.M``, ``body.K``, ``body.modes.eigenvalues``,
``body.modes.vectors``, ``body.delta``, ``body.modal_gravity``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field, replace
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np
import scipy.sparse as sp

from wiggly import checks
from wiggly.checks import vertex_set
from wiggly.errors import WigglyInputError, counted, warn
from wiggly.fem import DEFAULT_GRAVITY, Material, gravity_term, mass_matrix, stiffness_matrix
from wiggly.linalg import SPDSolver, factorize_spd
from wiggly.memo import Memo, value_key
from wiggly.mesh import Model, Surface, TetMesh, coarse_mesh, embed, load_model
from wiggly.modes import Modes, compute_modes
from wiggly.progress import deprecated_progress, say
from wiggly.warp import Warp, WarpLevel, coarse_level, fine_level

Where = Literal["surface", "tets"]
# Modes of a body unless asked otherwise (the rigid ones of a free body included).
DEFAULT_MODES = 40
# Bodies with more tets get a coarse warp (a coarse mesh of about COARSE_TETS tets) for the
# Gauss-Newton Jacobians DW Phi and a first solve (see wiggly.warp.transfer).
COARSE_WARP_ABOVE = 6000
COARSE_TETS = 2000


@dataclass(frozen=True)
class Damping:
    """Rayleigh damping D = alpha M + beta K (alpha in s^-1, beta in s); Schulz et al. eq. (1).

    Mode i is damped by ``alpha + beta lambda_i``: ``alpha`` also damps the rigid modes
    (lambda = 0), like air drag proportional to mass, so a free body falls as
    ``u'' + alpha u' = g`` (4.18 m in 1 s at the default alpha, not g t^2 / 2 = 4.9 m);
    ``alpha = 0`` gives the free fall, ``beta`` damps the fast modes most.
    """

    alpha: float = 0.5
    beta: float = 0.002

    def __post_init__(self) -> None:
        for name in ("alpha", "beta"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise WigglyInputError(
                    f"damping {name} = {v!r} is invalid: it must be a finite number >= 0 "
                    f"({'1/s' if name == 'alpha' else 's'})"
                )


class GroupSelection:
    """A vertex group on a warp level: the scalar selection ``S`` (s, n_L) of its vertices from
    the level's vertex values (barycentric rows for surface vertices, composed with a coarse
    level's lift P), its Gram ``C = S^T S`` (n_L, n_L) and, on demand, a factorization of
    ``C + mu I`` (mu = 1e-8 mean diag C; C is singular off the group) for fits of targets."""

    def __init__(self, S: sp.csr_matrix) -> None:
        self.S = sp.csr_matrix(S)
        self.St = sp.csr_matrix(self.S.T)
        self.C = sp.csr_matrix(self.St @ self.S)

    @cached_property
    def fit_solver(self) -> SPDSolver:
        C = self.C
        mu = 1e-8 * max(float(C.diagonal().mean()), np.finfo(float).tiny)
        return factorize_spd(sp.csr_matrix(C + mu * sp.identity(C.shape[0], format="csr")))


@dataclass(frozen=True, eq=False)
class Body:
    """A body ready for animation (mesh + FEM + modes).  Build it with :func:`prepare`.

    A body is immutable.  What it derives (the warp and its levels, the embedded basis, the
    vertex groups, gravity's modal terms) is computed on first use and kept by the body;
    :meth:`with_dynamics` gives the same body with other damping or gravity, sharing all of it
    that does not depend on them.

    Attributes
    ----------
    model : Model
        Tet mesh, the user's surface and its barycentric embedding.
    material : Material
    damping : Damping
    gravity : (3,) gravity acceleration in m/s^2 (y-up by default).
    fixed_vertices : (k,) tet-mesh vertex indices held at rest.
    M, K : (3n, 3n) sparse mass and stiffness (interleaved xyz dofs).
    modes : Modes
        Phi (3n, r) M-orthonormal, lambda (r,), rigid modes first.
    cache_dir : where derived meshes (the coarse warp's) are cached, as in :func:`prepare`.
    young : (m,) Young's modulus per tet where it varies (``prepare(young=...)``), else None.
    """

    model: Model
    material: Material
    damping: Damping
    gravity: np.ndarray
    fixed_vertices: np.ndarray
    M: sp.csr_matrix
    K: sp.csr_matrix
    modes: Modes
    lumped: bool = False
    cache_dir: str | os.PathLike[str] | Literal[False] | None = field(default=None, repr=False)
    young: np.ndarray | None = field(default=None, repr=False)
    # vertex groups seen on the warp levels, kept by value (vertex indices) for every solve;
    # not a field of __init__, so that dataclasses.replace (other modes) starts it empty
    _groups: Memo = field(default_factory=lambda: Memo(limit=512), repr=False, init=False)

    # derived data that does not depend on damping or gravity (shared by with_dynamics)
    _STATIC = ("mass", "surface_basis", "warp", "fine_level", "coarse_level", "surface_embedding")

    def with_dynamics(
        self,
        *,
        damping: Damping | None = None,
        gravity: tuple[float, float, float] | np.ndarray | None = None,
    ) -> Body:
        """This body with other damping and/or gravity: the same mesh, M, K and modes, and
        the same warp, coarse level and vertex groups (nothing is recomputed); the per-mode
        damping ``delta`` and the modal gravity follow the new values.  Returns ``self`` when
        nothing changes."""
        damping = self.damping if damping is None else _checked(
            damping, Damping, "damping", "Damping(alpha=0.5, beta=0.002)")
        g = self.gravity if gravity is None else _checked_gravity(gravity)
        if damping == self.damping and np.array_equal(g, self.gravity):
            return self
        new = replace(self, damping=damping, gravity=g)
        object.__setattr__(new, "_groups", self._groups)  # the same modes: the same Grams
        for name in self._STATIC:
            if name in self.__dict__:  # cached_property values of this body: its own data
                new.__dict__[name] = self.__dict__[name]
        return new

    # --- per-mode coefficients of the decoupled energy (Schulz et al. 2014, eq. (4)) -------
    def __repr__(self) -> str:  # a summary: the meshes and matrices are attributes
        fixed = f", {len(self.fixed_vertices)} fixed vertices" if len(self.fixed_vertices) else ""
        return (f"Body({self.model.source}: {self.tets.n_tets} tets, "
                f"{self.surface.n_vertices} surface vertices, {self.modes!r}, "
                f"E = {self.material.young:g} Pa, {self.mass:.3g} kg{fixed})")

    @property
    def r(self) -> int:
        """Number of modes."""
        return self.modes.r

    @property
    def eigenvalues(self) -> np.ndarray:
        """lambda_i in s^-2 (rigid modes exactly 0)."""
        return self.modes.eigenvalues

    @property
    def delta(self) -> np.ndarray:
        """Per-mode damping delta_i = (alpha + beta lambda_i) / 2 in s^-1."""
        return 0.5 * (self.damping.alpha + self.damping.beta * self.modes.eigenvalues)

    @cached_property
    def gravity_vector(self) -> np.ndarray:
        """Full constant term g = -M (gravity per node) of dynamics (1)."""
        return gravity_term(self.M, tuple(self.gravity))

    @cached_property
    def modal_gravity(self) -> np.ndarray:
        """g_i = phi_i^T g (in sqrt(kg) m / s^2)."""
        return self.modes.vectors.T @ self.gravity_vector

    @cached_property
    def mass(self) -> float:
        """Total mass in kg."""
        return float(self.M.sum() / 3.0)

    # --- geometry ------------------------------------------------------------------------
    @property
    def tets(self) -> TetMesh:
        return self.model.tets

    @property
    def surface(self) -> Surface:
        return self.model.surface

    def rest_positions(self, on: Where = "surface") -> np.ndarray:
        """Rest vertex positions (n, 3) of the surface or the tet mesh."""
        return self.surface.vertices if checks.where(on) == "surface" else self.tets.vertices

    def n_vertices(self, on: Where = "surface") -> int:
        return len(self.rest_positions(on))

    @cached_property
    def surface_basis(self) -> np.ndarray:
        """Modes evaluated on the embedded surface, (3p, r): E Phi (barycentric embedding)."""
        E = self.model.embedding.dof_matrix(self.tets.n_vertices)
        return np.ascontiguousarray(E @ self.modes.vectors)

    def basis(self, on: Where = "surface") -> np.ndarray:
        """Mode shapes as displacement rows (3n, r) for the surface or the tet mesh."""
        return self.surface_basis if checks.where(on) == "surface" else self.modes.vectors

    def basis_rows(self, vertices: np.ndarray, on: Where = "surface") -> np.ndarray:
        """Rows of the mode basis for the xyz dofs of ``vertices``: shape (3k, r) (A_k Phi)."""
        vertices = np.asarray(vertices, dtype=np.int64)
        dofs = (3 * vertices[:, None] + np.arange(3)).ravel()
        return self.basis(on)[dofs]

    @cached_property
    def warp(self) -> Warp:
        """Rotation-strain warp map W of this body (Schulz et al. 2014, Thm. 2), factored once."""
        return Warp(
            self.tets.vertices,
            self.tets.tets,
            masses=self.vertex_masses("tets"),
            fixed_vertices=self.fixed_vertices,
        )

    @cached_property
    def fine_level(self) -> WarpLevel:
        """The warp W bound to the modes (Jacobians, curvatures; Schulz et al. 2014, Theorem 2)."""
        return fine_level(self.warp, self.modes.vectors)

    @cached_property
    def coarse_level(self) -> WarpLevel:
        """The warp of a coarse mesh of the same solid (fTetWild, about ``COARSE_TETS`` tets,
        cached on disk) for the warped solve's first level and Newton matrices; the fine
        level itself up to ``COARSE_WARP_ABOVE`` tets.  See :mod:`wiggly.warp.transfer`."""
        if self.tets.n_tets <= COARSE_WARP_ABOVE:
            return self.fine_level
        coarse = coarse_mesh(self.tets, COARSE_TETS, cache_dir=self.cache_dir)
        if coarse is None:
            return self.fine_level
        n = self.tets.n_vertices
        return coarse_level(
            self.warp,
            coarse.vertices,
            coarse.tets,
            lift=embed(self.tets.vertices, coarse).matrix(coarse.n_vertices),
            interpolation=embed(coarse.vertices, self.tets).matrix(n),
            basis=self.modes.vectors,
        )

    @cached_property
    def surface_embedding(self) -> sp.csr_matrix:
        """(p, n) barycentric interpolation from tet vertices to surface vertices."""
        return self.model.embedding.matrix(self.tets.n_vertices)

    def to_surface(self, U: np.ndarray) -> np.ndarray:
        """Tet-vertex fields ``U`` (F, n, 3) carried to the surface vertices by the
        barycentric embedding: (F, p, 3), in ``U``'s dtype."""
        F, n, _ = U.shape
        E = self.surface_embedding
        out = E @ U.transpose(1, 0, 2).reshape(n, -1)
        return out.reshape(E.shape[0], F, 3).transpose(1, 0, 2).astype(U.dtype, copy=False)

    def scalar_selection(self, vertices: np.ndarray, on: Where = "surface") -> sp.csr_matrix:
        """Sparse (k, n) map from tet-mesh vertex values to those of ``vertices``."""
        vertices = np.asarray(vertices, np.int64)
        n = self.tets.n_vertices
        if on == "tets":
            return sp.csr_matrix(
                (np.ones(len(vertices)), (np.arange(len(vertices)), vertices)),
                shape=(len(vertices), n),
            )
        return sp.csr_matrix(self.surface_embedding[vertices])

    def group(
        self, level: WarpLevel, vertices: np.ndarray, on: Where = "surface"
    ) -> GroupSelection:
        """A vertex group on a warp level (:class:`GroupSelection`), kept per level and group:
        every problem and solve on this body shares it."""
        vertices = np.asarray(vertices, np.int64)
        name = "fine" if level.exact else "coarse"

        def compute() -> GroupSelection:
            S = self.scalar_selection(vertices, on)
            if not level.exact:
                S = sp.csr_matrix(S @ level.transfer.lift)
            return GroupSelection(S)

        return self._groups.get((name, on, value_key(vertices)), compute)

    def modal_gram(self, vertices: np.ndarray, on: Where = "surface") -> np.ndarray:
        """``Phi^T (C kron I_3) Phi`` (r, r) of a vertex group, C its Gram on the tet mesh
        (the linear keyframe term's matrix, Schulz et al. eq. (6)); kept per group."""
        vertices = np.asarray(vertices, np.int64)

        def compute() -> np.ndarray:
            C = self.group(self.fine_level, vertices, on).C
            Phi = self.modes.vectors.reshape(-1, 3, self.r)
            return sum(Phi[:, c].T @ (C @ Phi[:, c]) for c in range(3))

        return self._groups.get(("modal gram", on, value_key(vertices)), compute)

    def model_error(
        self, level: WarpLevel, vertices: np.ndarray, on: Where = "surface"
    ) -> tuple[np.ndarray, np.ndarray]:
        """A vertex group's terms of a coarse ``level``'s interpolation error of the modes,
        ``E = Phi - P R Phi`` (:attr:`WarpLevel.basis_error`): ``K2 = P^T C E`` (n_c, 3, r)
        and ``K3 = E^T C E`` (r, r), C the group's Gram on the tet mesh (the coarse Newton
        model's correction, :mod:`wiggly.solve.warped`); kept per level and group."""
        vertices = np.asarray(vertices, np.int64)
        name = "fine" if level.exact else "coarse"

        def compute() -> tuple[np.ndarray, np.ndarray]:
            E, P = level.basis_error, level.transfer.lift
            C = self.group(self.fine_level, vertices, on).C
            CE = np.stack([C @ E[:, c] for c in range(3)], axis=1)
            K2 = np.stack([P.T @ CE[:, c] for c in range(3)], axis=1)
            K3 = E.reshape(-1, self.r).T @ CE.reshape(-1, self.r)
            return K2, 0.5 * (K3 + K3.T)

        return self._groups.get(("model error", name, on, value_key(vertices)), compute)

    def vertex_masses(self, on: Where = "tets") -> np.ndarray:
        """Lumped vertex masses (kg) of the tet mesh, or interpolated to the surface vertices
        (``on = "surface"``: each surface vertex gets the barycentric mean of its tet's vertex
        masses per unit weight, so they do not sum to the body's mass)."""
        m = np.asarray(self.M.sum(axis=1)).ravel()[::3]
        if checks.where(on) == "tets":
            return m
        B = self.model.embedding.matrix(self.tets.n_vertices)
        w = np.asarray(B.sum(axis=0)).ravel()
        w = np.where(w > 0, w, 1.0)
        return B @ (m / w)


def tets_of(model: Model, vertices: np.ndarray, on: Where = "surface",
            whole: bool = False) -> np.ndarray:
    """Indices of the tets that belong to a vertex group.  A group of surface vertices owns
    the tets whose centre lies nearest to the part of the surface its vertices carry: the
    closest point of the surface's triangles, weighted by its barycentric coordinates on
    the group's vertices, at least one half (with ``whole``: a triangle of the group's
    vertices only).  So the groups of a surface share out the solid under it, its inside and
    the joints between groups included (a stiff antenna on a stiff head is stiff where they
    meet); ``whole`` keeps to the solid under the group's own triangles (a driven cap of a
    low-poly capsule, whose side triangles join it to the far end, holds the cap, not half
    the body).  A group of tet vertices owns the tets whose four corners are all in it."""
    T = model.tets.tets
    if on != "surface":
        mask = np.zeros(model.tets.n_vertices, bool)
        mask[np.asarray(vertices, np.int64)] = True
        return np.flatnonzero(mask[T].all(axis=1))
    import igl

    mask = np.zeros(model.surface.n_vertices, bool)
    mask[_surface_indices(model, vertices)] = True
    V = np.ascontiguousarray(model.surface.vertices, dtype=np.float64)
    F = np.ascontiguousarray(model.surface.faces, dtype=np.int64)
    if not len(F) or not mask.any():
        return np.zeros(0, np.int64)
    centres = np.ascontiguousarray(model.tets.vertices[T].mean(axis=1))
    _, face, closest = igl.point_mesh_squared_distance(centres, V, F)
    corners = F[face]
    if whole:
        return np.flatnonzero(mask[corners].all(axis=1))
    weights = np.nan_to_num(igl.barycentric_coordinates(
        closest, V[corners[:, 0]], V[corners[:, 1]], V[corners[:, 2]]))  # 0 on degenerate
    return np.flatnonzero((weights * mask[corners]).sum(axis=1) >= 0.5)


def _surface_indices(model: Model, surface_vertices: np.ndarray) -> np.ndarray:
    """Surface vertex indices as int64, each checked to lie on the surface."""
    idx = np.asarray(surface_vertices, np.int64)
    n = model.surface.n_vertices
    bad = idx[(idx < 0) | (idx >= n)]
    if bad.size:
        raise WigglyInputError(
            f"surface vertex index {int(bad[0])} is out of range: the surface has "
            f"{counted(n, 'vertex')}"
        )
    return idx


def fixed_from_surface(model: Model, surface_vertices: np.ndarray) -> np.ndarray:
    """Tet vertices carrying the given surface vertices (the corners of their tets)."""
    idx = _surface_indices(model, surface_vertices)
    emb = model.embedding
    w = emb.barycentric[idx]
    verts = emb.vertex_indices[idx]
    return np.unique(verts[np.abs(w) > 1e-9])


@deprecated_progress
def prepare(
    model: Model | str | os.PathLike[str],
    *,
    material: Material | None = None,
    damping: Damping | None = None,
    gravity: tuple[float, float, float] | np.ndarray = DEFAULT_GRAVITY,
    fixed_vertices: np.ndarray | list[int] | None = None,
    n_modes: int = DEFAULT_MODES,
    lumped: bool = False,
    cache_dir: str | os.PathLike[str] | Literal[False] | None = None,
    resolution: int | None = None,
    edge_length: float | None = None,
    young: np.ndarray | None = None,
    scale: float = 1.0,
    up: str = "y",
) -> Body:
    """Load (if a path), assemble M and K, compute ``n_modes`` eigenmodes (cached on disk).

    ``fixed_vertices`` are tet-mesh vertex indices (see :func:`fixed_from_surface` to fix
    by surface vertices).  ``n_modes`` counts the rigid modes of a free body (6).
    ``young`` gives a Young's modulus per tet (Pa) in place of ``material.young``, e.g. a
    softer tail (:func:`wiggly.body.tets_of` selects a vertex group's tets).  ``model`` is a
    path, ``builtin:NAME`` or a :class:`~wiggly.mesh.Model`; a surface in memory becomes one
    with :func:`wiggly.mesh.build_model`.  ``scale`` is the file's metres per unit (0.01 for
    a file in centimetres) and ``up`` its up axis ("y", or "z" for a Z-up file; a path
    only).
    """
    material = _checked(material, Material, "material", "Material(young=2e5, poisson=0.45, "
                        "density=1000.0)")
    damping = _checked(damping, Damping, "damping", "Damping(alpha=0.5, beta=0.002)")
    gravity = _checked_gravity(gravity)
    if not isinstance(model, Model):
        if not isinstance(model, str | os.PathLike):
            raise WigglyInputError(
                f"model should be a mesh file's path, 'builtin:NAME' or a wiggly.mesh.Model; got "
                f"a {type(model).__name__} (a surface in memory: wiggly.mesh.build_model(Surface("
                "vertices, faces), name))")
        path = Path(model)
        model = load_model(
            path, resolution=resolution, edge_length=edge_length, cache_dir=cache_dir,
            scale=scale, up=up)
    elif scale != 1.0 or up != "y":
        raise WigglyInputError("scale and up apply to a mesh file; a Model is used as it is "
                               "(scale or turn its surface before wiggly.mesh.build_model)")
    V, T = model.tets.vertices, model.tets.tets
    fixed = vertex_set(fixed_vertices, len(V), "fixed vertices")
    say(f"assembling linear FEM on {len(T)} tets, {len(V)} vertices")
    M = mass_matrix(V, T, material.density, lumped=lumped)
    K = stiffness_matrix(V, T, material.young if young is None else young, material.poisson)
    modes = compute_modes(
        K, M, n_modes, vertices=V, fixed_vertices=fixed, cache_dir=cache_dir, called="n_modes"
    )
    split = modes.split_group()
    if split:
        hz = math.sqrt(modes.next_eigenvalue) / (2 * math.pi)
        warn(
            f"n_modes = {n_modes} (simulation.modes in a scene) ends inside a group of modes "
            f"of equal frequency ({hz:.4g} Hz; this body is symmetric): its last {split} and "
            "at least one more share it, and which of them the basis holds is the "
            "eigensolver's pick, so symmetric keys get unequal answers; use "
            f"{n_modes - split} modes (without the group) or more (all of it)")
    if model.embedding is None:  # a new model: the caller's is not changed
        model = replace(model, embedding=embed(model.surface.vertices, model.tets))
    return Body(model, material, damping, gravity, fixed, M, K, modes, lumped, cache_dir,
                None if young is None else np.asarray(young, np.float64))


def _checked(value, kind: type, name: str, example: str):
    """``value`` if it is a ``kind`` (None: the default ``kind()``), else a clear refusal
    (a bare number or a dict would fail much later, deep in the solve)."""
    if value is None:
        return kind()
    if not isinstance(value, kind):
        raise WigglyInputError(f"{name} should be a wiggly.{kind.__name__}, e.g. {example}; got "
                               f"{checks.brief(value)}")
    return value


def _checked_gravity(gravity) -> np.ndarray:
    g = np.asarray(gravity, dtype=float).reshape(-1)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise WigglyInputError(f"gravity must be 3 finite numbers (m/s^2); got {g.tolist()}")
    g.flags.writeable = False
    return g

