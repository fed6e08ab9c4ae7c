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
from dataclasses import replace
from pathlib import Path

from wiggly.checks import positive_number
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
from wiggly.mesh.loading import UP_AXES, z_up_to_y_up
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


#: Driver formats that carry no units or axes of their own: ``scale`` and ``up`` of
#: :func:`read_driver` (``drive.scale``, ``drive.up_axis``) apply to them.
UNIT_FREE = (".obj", ".npz")
UNIT_FREE_NOTE = ("a glTF driver is in metres, y up, by its specification, and a USD driver "
                  "is read in metres, y up, by its stage's metersPerUnit and upAxis")


def _in_metres(driver: Driver, scale: float, up: str) -> Driver:
    """``driver`` with its positions multiplied by ``scale`` and turned from ``up`` to y up."""
    if scale == 1.0 and up == "y":
        return driver
    positions = driver.positions * scale
    return replace(driver, positions=z_up_to_y_up(positions) if up == "z" else positions)


@deprecated_progress
def read_driver(path: str | os.PathLike[str], *,
                animation: str | int | Sequence[str | int] | None = None,
                object: str | None = None, frame_rate: float | None = None,
                scale: float = 1.0, up: str = "y") -> Driver:
    """Read a driver animation (format by extension, :data:`DRIVER_EXTENSIONS`).

    ``animation`` picks a glTF animation by name or index (default: the first), or several
    to play together (a sequence: their channels merged, e.g. a rig's action and a shape-key
    action); ``object``
    keeps the glTF mesh nodes, or the USD meshes at or below prims, of that name (default:
    every mesh, in file order); ``frame_rate`` times an OBJ sequence without wiggly's
    ``# time`` comments (frame N at N / frame_rate s).  ``scale`` (metres per unit of the
    file) and ``up`` (its up axis, "y" or "z") bring an OBJ sequence or an npz written in
    other units or axes to wiggly's metres, y up, as :func:`wiggly.mesh.load_mesh` does for
    the mesh; glTF (metres, y up by its specification) and USD (its stage's
    ``metersPerUnit`` and ``upAxis``) carry their own axes and refuse ``up``, and ``scale``
    multiplies their metres (Blender writes its units as metres, so a scene in centimetres
    exports a body 100 times too large: ``scale = 0.01``).  Raises
    :class:`WigglyInputError` naming the file for anything it cannot read.
    """
    path = Path(path).expanduser()
    ext = path.suffix.lower()
    if ext not in DRIVER_EXTENSIONS:
        raise WigglyInputError(
            f"cannot read the driver {path}: unknown extension {path.suffix or '(none)'!r}; "
            f"use one of {', '.join(DRIVER_EXTENSIONS)}")
    if frame_rate is not None and not (frame_rate > 0 and frame_rate < float("inf")):
        raise WigglyInputError(f"frame_rate = {frame_rate!r} must be a number > 0")
    scale = positive_number(scale, "scale", "metres per unit of the driver file")
    if up not in UP_AXES:
        raise WigglyInputError(f"up = {up!r} is not an up axis; use one of {', '.join(UP_AXES)}")
    if up != "y" and ext not in UNIT_FREE:
        raise WigglyInputError(
            f"{path}: up applies to OBJ sequences and .npz drivers only; {UNIT_FREE_NOTE}")
    if ext == ".obj":
        from wiggly.drive.sequence import read_obj_sequence

        return _in_metres(read_obj_sequence(path, frame_rate=frame_rate), scale, up)
    if not path.is_file():
        raise WigglyInputError(f"cannot read the driver {path}: "
                               f"{'it is a directory' if path.is_dir() else 'no such file'}")
    if ext in (".glb", ".gltf"):
        from wiggly.drive.gltf import read_gltf

        return _in_metres(read_gltf(path, animation=animation, object=object), scale, "y")
    if ext == ".npz":
        from wiggly.drive.sequence import read_npz

        return _in_metres(read_npz(path), scale, up)
    from wiggly.drive.usd import read_usd

    return _in_metres(read_usd(path, object=object), scale, "y")
