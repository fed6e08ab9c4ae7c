"""What a solved scene says of its body: a held body that sags far (:func:`static_sag`), a
joint on which its parts hinge almost freely (:func:`thin_joint`), and a material too soft
for the shot (:func:`soft_note`)."""

from __future__ import annotations

import numpy as np

from wiggly.mesh.defects import diagonal
from wiggly.scene.spec import Scene

__all__ = ["JOINT_SHARE", "SAG", "soft_note", "static_sag", "thin_joint"]


#: A body held by fixed vertices whose static sag under gravity exceeds this share of its
#: size is warned about (linear elasticity then models it poorly).
SAG = 0.2


def static_sag(body, modes: tuple[np.ndarray, np.ndarray] | None = None) -> float | None:
    """The largest displacement (m) of the body's static equilibrium under gravity in its
    modes, ``q_i = -g_i / lambda_i`` (eq. (4) at rest: the energy's minimiser without
    keyframes), or None for a body with rigid modes (nothing holds it, so it falls).
    ``modes`` (Psi, lambda): other modes to take, e.g. those of the free parts with a driven
    group held."""
    u = _sag_field(body, modes)
    return None if u is None else float(np.sqrt((u**2).sum(axis=1)).max())


def _sag_field(body, modes: tuple[np.ndarray, np.ndarray] | None) -> np.ndarray | None:
    """The static sag's tet-vertex displacements (n, 3) of :func:`static_sag`, or None."""
    if not np.any(body.gravity):
        return None
    if modes is None:
        if body.modes.n_rigid:
            return None
        modes = (body.modes.vectors, body.modes.eigenvalues)
    psi, lam = modes
    if not len(lam) or np.any(lam <= 0):
        return None
    q = -(psi.T @ body.gravity_vector) / lam
    return (psi @ q).reshape(-1, 3)


#: A sag whose elastic energy lies for half in at most this share of the tets bends the body
#: at a joint, not along it (two boxes meeting at an edge: 1.0 %; soft bars, a critter and a
#: plant held at one end, at two resolutions: 5.5-11 %).
JOINT_SHARE = 0.02


def thin_joint(scene: Scene, body,
               held: tuple[np.ndarray, np.ndarray] | None = None) -> str | None:
    """Why the motion may swing far when a held body's sag under gravity (more than ``SAG``
    of its size, :func:`static_sag`) bends it at a joint: half its elastic energy in at most
    ``JOINT_SHARE`` of the tets that move (two parts meeting at an edge, which the tets join
    by a sliver), so that the parts hinge on it almost freely; None otherwise.  Counted
    among the moving tets, not all: a cantilevered tail holds half its energy near its root,
    a few per cent of a big held body's tets.  A body nothing holds is judged by its softest
    mode instead, when that is far the softest (:func:`_hinge_mode`)."""
    from wiggly.fem import lame_parameters, tet_gradients

    u, what = _sag_field(body, held), "its sag under gravity"
    X, T = body.tets.vertices, body.tets.tets
    size = diagonal(body.rest_positions())
    if u is None and held is None:  # nothing holds it: its softest mode, if far the softest
        u, what = _hinge_mode(body), "its softest mode"
    elif u is not None and np.sqrt((u**2).sum(axis=1)).max() <= SAG * size:
        u = None
    if u is None or len(T) < 2:
        return None
    grads, vol = tet_gradients(X, T)
    G = np.einsum("mai,maj->mij", u[T], grads)  # du_i / dX_j per tet
    eps = 0.5 * (G + G.transpose(0, 2, 1))
    lam, mu = lame_parameters(body.material.young, body.material.poisson)
    energy = vol * (mu * np.einsum("mij,mij->m", eps, eps)
                    + 0.5 * lam * np.trace(eps, axis1=1, axis2=2) ** 2)
    order = np.argsort(energy)[::-1]
    k = int(np.searchsorted(np.cumsum(energy[order]), 0.5 * energy.sum())) + 1
    moving = int(np.count_nonzero(np.abs(u[T]).max(axis=(1, 2)) > 0))  # not all held
    if k > JOINT_SHARE * moving:  # a thin tail's root on a big held body is no hinge
        return None
    near = X[T[order[:k]]].reshape(-1, 3).mean(axis=0)
    return (f"the body bends almost freely at a joint near ({near[0]:.3g}, {near[1]:.3g}, "
            f"{near[2]:.3g}) m: {k} of its {len(T)} tets {'holds' if k == 1 else 'hold'} half "
            f"the elastic energy of {what}, as where two parts meet at an edge "
            "or a corner; its parts hinge there, and keys or gravity can swing them far. Join "
            "the parts by a face in the model (overlap them a little), or fix or key each part")


def _hinge_mode(body) -> np.ndarray | None:
    """A free body's softest elastic mode (n, 3), when its frequency is below half the next
    mode's, as a hinge's (two boxes joined by a sliver at an edge: 0.54 against 2.3 Hz; a
    review's two cubes sharing an edge: 0.042 Hz, one cube 9.7 Hz; the bundled and reviewed
    bodies 0.87-0.99), else None."""
    modes = body.modes
    k = modes.n_rigid
    lam = np.asarray(modes.eigenvalues)
    if not k or len(lam) < k + 2 or not 0 < lam[k] < 0.25 * lam[k + 1]:
        return None
    return np.asarray(modes.vectors)[:, k].reshape(-1, 3)


def soft_note(scene: Scene, body,
              held: tuple[np.ndarray, np.ndarray] | None = None) -> str | None:
    """Why the motion may look wrong when gravity alone would bend a held body by more than
    ``SAG`` of its size: the material is too soft for the body's size (a default material on
    a body of metres), and the sag would dominate the motion; None otherwise.  A body is
    held by its fixed vertices, or by the driven group of a secondary-motion ``[drive]``:
    ``held`` are then the free parts' modes (Psi, lambda) that the solve used
    (:attr:`wiggly.drive.SecondaryMotion.held_modes`).  Static sag scales as 1 / Young's
    modulus, so the note says which modulus sags 5 %.  The command line logs it (a stage
    line; silent with ``-q``), the editor shows it once per scene; both ask
    :func:`thin_joint` first, and say this note only where the sag is not a joint's."""
    held_by = "its fixed vertices hold" if held is None else "its driven group holds"
    sag = static_sag(body, held)
    size = diagonal(body.rest_positions())
    if sag is None or sag <= SAG * size:
        return None
    young = scene.material.young
    own = ", and the groups' own" if any(g.young is not None for g in scene.groups.values()) \
        else ""
    warped = (" (warped, it keeps its length and hangs instead, but bent further than the "
              "model holds)" if scene.simulation.warp else "")
    return (
        f"under gravity alone linear elasticity would sag the body by {sag:.3g} m "
        f"({100 * sag / size:.0f} % of its size) where {held_by} it, more than it models "
        f"well{warped}: the material is soft for a body of {size:.3g} m. "
        f"Raise material.young ({young:g} Pa{own}; {young * sag / (0.05 * size):.2g} Pa sags "
        "about 5 %), or lower simulation.gravity")
