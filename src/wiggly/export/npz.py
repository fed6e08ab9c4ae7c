"""wiggly's own npz layout."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from wiggly.errors import WigglyInputError
from wiggly.export.animation import FORMAT_VERSION, SurfaceAnimation

# ----------------------------------------------------------------------------------------------
# npz


def write_npz(path: Path, anim: SurfaceAnimation) -> None:
    arrays = {
        "format_version": np.array(FORMAT_VERSION),
        "times": anim.times,
        "positions": anim.positions.astype(np.float32),
        "faces": anim.faces,
        "name": np.array(anim.name),
        "loop": np.array(bool(anim.loop)),
    }
    if anim.uvs is not None:
        arrays["uvs"] = anim.uvs.astype(np.float32)
    if anim.normals is not None:
        arrays["normals"] = anim.normals.astype(np.float32)
    with open(path, "wb") as f:
        np.savez_compressed(f, **arrays)


def read_npz(path: Path) -> SurfaceAnimation:
    try:
        with np.load(path, allow_pickle=False) as data:
            d = {key: data[key] for key in data.files}
    except (OSError, ValueError) as e:
        raise WigglyInputError(f"cannot read {path}: not a numpy npz archive ({e})") from e
    missing = [key for key in ("format_version", "times", "positions", "faces") if key not in d]
    if missing:
        raise WigglyInputError(
            f"cannot read {path}: missing arrays {missing}; a wiggly animation npz has "
            "format_version, times, positions, faces (and optional uvs, normals, name)"
        )
    if int(d["format_version"]) > FORMAT_VERSION:
        raise WigglyInputError(
            f"cannot read {path}: format_version {int(d['format_version'])} was written by a "
            f"newer wiggly (this one reads up to {FORMAT_VERSION}); upgrade wiggly"
        )
    return SurfaceAnimation(d["times"], d["positions"], d["faces"], d.get("uvs"),
                            d.get("normals"), str(d.get("name", "wiggly")),
                            loop=bool(d.get("loop", False)))
