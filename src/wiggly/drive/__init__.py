"""Secondary motion on an existing animation: a *driver* animation of the user's surface owns
a vertex group, and physics moves the rest of the body (tail, ears, belly, antennae).

:func:`secondary_motion` (the default of a scene's ``[drive]``) takes the driver as a moving
rest state, extended over the body, and solves the free parts' complementary motion: its
fixed-interface modes, each a wiggly spline forced by the driver's accelerations
(:mod:`wiggly.drive.secondary`; Schulz et al. 2014, Theorem 1 with a forcing term), plus
sparse keys of the user's own on the free parts::

    import wiggly
    from wiggly.drive import read_driver, secondary_motion

    body = wiggly.prepare("critter.glb", n_modes=12)
    driver = read_driver("critter.glb")                    # its skinned walk, every frame
    X = body.rest_positions()
    driven = (X[:, 0] > -0.28) & (X[:, 1] < 0.745)          # all but the tail and the ears
    anim = secondary_motion(body, driver, driven, start=0.0, end=3.0)

The older model keys the driven group at every driver frame with the paper's partial
keyframes (eq. (6)) and minimises the spacetime energy of the whole body
(:func:`driven_keyframes`, with :func:`enrich` adding the driver's shapes to the modes, and
:func:`driver_poses` starting the warped solve at the driver's whole poses); there the free
parts are carried nearly rigidly while the driver plays.

Readers (:func:`read_driver` picks one by extension), each giving frame times and the
positions (F, n, 3) of the surface's n vertices in wiggly's axes (y up, metres):

* :mod:`~wiggly.drive.gltf` -- glTF 2.0 (``.glb``, ``.gltf``): morph-target and skinned
  animations (linear blend skinning), node transforms, per the specification;
* :mod:`~wiggly.drive.usd` -- USD (``.usd``, ``.usda``, ``.usdc``, ``.usdz``): time-sampled
  points, or UsdSkel skinning baked by USD;
* :mod:`~wiggly.drive.sequence` -- numbered OBJ files, and wiggly's ``.npz``.

:meth:`Driver.check` refuses a driver of another surface (naming both vertex counts),
:func:`following` measures how closely a solved motion follows the driver.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

from wiggly.drive.basis import driver_poses, enrich
from wiggly.drive.driver import (
    DRIVE_STIFFNESS,
    Driver,
    driven_keyframes,
    following,
    keyed_frames,
)
from wiggly.drive.secondary import SecondaryMotion, secondary_motion
from wiggly.errors import WigglyInputError
from wiggly.progress import deprecated_progress

__all__ = ["DRIVER_EXTENSIONS", "DRIVE_STIFFNESS", "Driver", "SecondaryMotion",
           "driven_keyframes", "driver_poses", "enrich", "following", "keyed_frames", "read_driver",
           "secondary_motion"]

#: Driver formats by file extension.
DRIVER_EXTENSIONS = {
    ".glb": "glTF binary: skinned or morph-target animation",
    ".gltf": "glTF: skinned or morph-target animation",
    ".usd": "USD: time-sampled points or UsdSkel skinning",
    ".usda": "USD (text)",
    ".usdc": "USD (binary)",
    ".usdz": "USD (zip package)",
    ".obj": "OBJ sequence: walk_####.obj, walk_000001.obj or wiggly's walk.obj",
    ".npz": "wiggly animation (wiggly.export)",
}


@deprecated_progress
def read_driver(path: str | os.PathLike[str], *,
                animation: str | int | Sequence[str | int] | None = None,
                object: str | None = None, frame_rate: float | None = None) -> Driver:
    """Read a driver animation (format by extension, :data:`DRIVER_EXTENSIONS`).

    ``animation`` picks a glTF animation by name or index (default: the first), or several
    to play together (a sequence: their channels merged, e.g. a rig's action and a shape-key
    action); ``object``
    keeps the glTF mesh nodes, or the USD meshes at or below prims, of that name (default:
    every mesh, in file order); ``frame_rate`` times an OBJ sequence without wiggly's
    ``# time`` comments (frame N at N / frame_rate s).  Raises :class:`WigglyInputError`
    naming the file for anything it cannot read.
    """
    path = Path(path).expanduser()
    ext = path.suffix.lower()
    if ext not in DRIVER_EXTENSIONS:
        raise WigglyInputError(
            f"cannot read the driver {path}: unknown extension {path.suffix or '(none)'!r}; "
            f"use one of {', '.join(DRIVER_EXTENSIONS)}")
    if frame_rate is not None and not (frame_rate > 0 and frame_rate < float("inf")):
        raise WigglyInputError(f"frame_rate = {frame_rate!r} must be a number > 0")
    if ext == ".obj":
        from wiggly.drive.sequence import read_obj_sequence

        return read_obj_sequence(path, frame_rate=frame_rate)
    if not path.is_file():
        raise WigglyInputError(f"cannot read the driver {path}: "
                               f"{'it is a directory' if path.is_dir() else 'no such file'}")
    if ext in (".glb", ".gltf"):
        from wiggly.drive.gltf import read_gltf

        return read_gltf(path, animation=animation, object=object)
    if ext == ".npz":
        from wiggly.drive.sequence import read_npz

        return read_npz(path)
    from wiggly.drive.usd import read_usd

    return read_usd(path, object=object)
