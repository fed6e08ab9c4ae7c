"""Secondary motion on an existing animation: a *driver* animation of the user's surface keys a
vertex group at every driver frame, and the rest of the body moves freely.

The paper's partial keyframes (Schulz et al. 2014, eq. (6)) are used densely in time: the driven
group gets a position keyframe at every frame of the driver, the user adds sparse keys of
their own (e.g. "the ears are back at rest at 2 s"), and the solve (warped by default,
Theorem 2) gives the free parts (ears, tail, belly) their lag, overshoot and settling::

    import wiggly
    from wiggly.drive import driven_keyframes, enrich, read_driver

    body = wiggly.prepare("critter.glb", n_modes=40)
    driver = read_driver("critter.glb")                    # its skinned walk, every frame
    X = body.rest_positions()
    driven = (X[:, 0] > -0.28) & (X[:, 1] < 0.745)          # all but the tail and the ears
    body = enrich(body, driver, driven)                     # + the driver's shapes
    keys = driven_keyframes(body, driver, driven)
    keys.append(wiggly.Keyframe.rest(body, 3.0, driven, still=True))
    anim = wiggly.solve(body, keys, start=0.0, end=3.0)

Readers (:func:`read_driver` picks one by extension), each giving frame times and the
positions (F, n, 3) of the surface's n vertices in wiggly's axes (y up, metres):

* :mod:`~wiggly.drive.gltf` -- glTF 2.0 (``.glb``, ``.gltf``): morph-target and skinned
  animations (linear blend skinning), node transforms, per the specification;
* :mod:`~wiggly.drive.usd` -- USD (``.usd``, ``.usda``, ``.usdc``, ``.usdz``): time-sampled
  points, or UsdSkel skinning baked by USD;
* :mod:`~wiggly.drive.sequence` -- numbered OBJ files, and wiggly's ``.npz``.

:meth:`Driver.check` refuses a driver of another surface (naming both vertex counts),
:func:`enrich` adds the driver's shapes to the modal basis (Rayleigh-Ritz,
:mod:`~wiggly.drive.basis`: the lowest eigenmodes alone follow a skinned limb only to a few
percent), :func:`driven_keyframes` makes the keyframes and :func:`following` measures how
closely the solved motion follows them.
"""

from __future__ import annotations

import os
from pathlib import Path

from wiggly.drive.basis import enrich
from wiggly.drive.driver import (
    DRIVE_STIFFNESS,
    Driver,
    driven_keyframes,
    following,
    keyed_frames,
)
from wiggly.errors import WigglyInputError

__all__ = ["DRIVER_EXTENSIONS", "DRIVE_STIFFNESS", "Driver", "driven_keyframes", "enrich",
           "following", "keyed_frames", "read_driver"]

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


def read_driver(path: str | os.PathLike[str], *, animation: str | int | None = None,
                object: str | None = None, frame_rate: float | None = None,
                progress: bool = False) -> Driver:
    """Read a driver animation (format by extension, :data:`DRIVER_EXTENSIONS`).

    ``animation`` picks a glTF animation by name or index (default: the first); ``object``
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

        return read_obj_sequence(path, frame_rate=frame_rate, progress=progress)
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
