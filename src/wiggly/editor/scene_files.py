"""The files of the editor's scene: its digest on disk, the scene read and checked, the
user's surface and its groups as the page draws them, and the state of its driver's files
(:class:`wiggly.editor.session.Session` uses them)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from wiggly.editor.autosave import autosave_path
from wiggly.editor.history import history_path
from wiggly.editor.scene_lock import held_by
from wiggly.editor.state import EditError, check_limits
from wiggly.errors import WigglyInputError
from wiggly.scene import MeshSpec, Scene, TimeSpec, load_scene, resolve_groups

__all__ = [
    "MESH_SUFFIXES",
    "SCENE_SUFFIX",
    "display_groups",
    "driver_ghost",
    "driver_stamp",
    "export_written",
    "file_digest",
    "free_name",
    "load_checked",
    "never_saved",
    "new_scene",
    "surface_of",
]

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf", ".msh", ".vtu", ".vtk",
                 ".mesh")
SCENE_SUFFIX = ".toml"


def new_scene(mesh_file: Path, builtin: str | None = None) -> Scene:
    """A fresh scene for a mesh: no groups or keyframes, a 2 s shot, saved beside the mesh
    (or in the current directory for a bundled model)."""
    if builtin is not None:
        scene = Scene(MeshSpec(f"builtin:{builtin}"), time=TimeSpec(end=2.0))
        scene.source = free_name(Path.cwd(), builtin)
        return scene
    scene = Scene(MeshSpec(mesh_file.name), time=TimeSpec(end=2.0))
    scene.source = free_name(mesh_file.parent, mesh_file.stem)
    return scene


def free_name(folder: Path, stem: str) -> Path:
    """``folder/stem.toml``, or ``stem-2.toml``, ... if taken (never overwrite a scene, nor
    take the name of one another editor has open)."""
    path, k = folder / f"{stem}{SCENE_SUFFIX}", 2
    while path.exists() or autosave_path(path).exists() or history_path(path).exists() or \
            held_by(path) is not None:
        path, k = folder / f"{stem}-{k}{SCENE_SUFFIX}", k + 1
    return path


def export_written(path: Path, shown: str) -> str:
    """What an export of ``path`` wrote, for its message: the file as the page names it
    (``shown``, e.g. ``out/shot.glb``), or for an OBJ the sequence of frame files
    ``out/NAME_0000.obj`` …."""
    if path.suffix.lower() != ".obj":
        return shown
    frames = sorted(path.parent.glob(f"{path.stem}_[0-9][0-9][0-9][0-9].obj"))
    if not frames:
        return shown
    folder = shown[:len(shown) - len(path.name)]
    return f"{folder}{frames[0].name} … {frames[-1].name} ({len(frames)} OBJ frames)"

def driver_stamp(scene: Scene) -> tuple | None:
    """The state of the scene's driver file(s) on disk: its path and the sizes and
    modification times of its file, or of an OBJ sequence's files (None: no [drive])."""
    if scene.drive is None:
        return None
    from wiggly.drive.sequence import sequence_files

    path = scene.resolve(scene.drive.path)
    files = ([f for _, f in sequence_files(path)] if path.suffix.lower() == ".obj"
             else [path])
    states = []
    for f in files:
        try:
            st = f.stat()
            states.append((f.name, st.st_size, st.st_mtime_ns))
        except OSError:
            states.append((f.name, None, None))
    return (str(path), tuple(states))


def file_digest(path: Path | None) -> str | None:
    """A digest of the file's bytes (None: no such file, or unreadable)."""
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest() if path else None
    except OSError:
        return None


def load_checked(path: Path) -> Scene:
    """The scene file at ``path``, checked against the editor's limits too; a problem is an
    :class:`EditError` naming the file."""
    try:
        scene = load_scene(path)
        check_limits(scene)
        return scene
    except WigglyInputError as err:
        raise EditError(f"{path.name}: {err}" if path.name not in str(err) else str(err)) \
            from None


def surface_of(scene: Scene):
    """The user's surface, read without tetrahedralizing (a tet mesh's boundary)."""
    from wiggly.mesh import Surface, TetMesh, load_mesh

    try:
        loaded = load_mesh(scene.mesh_file(), scene.mesh.metres_per_unit, scene.mesh.up)
    except WigglyInputError as err:
        raise EditError(str(err)) from None
    if isinstance(loaded, Surface):
        return loaded
    assert isinstance(loaded, TetMesh)
    return Surface(loaded.vertices, loaded.boundary_faces(), groups=dict(loaded.groups))


def display_groups(scene: Scene, surface, model) -> dict[str, np.ndarray]:
    """The scene's groups as surface vertex indices, as the page draws them (a group on the
    tets by the surface vertices nearest its tet vertices)."""
    resolved = (resolve_groups(scene, model) if model is not None
                else resolve_groups(scene, surface=surface))
    out = {}
    for name, idx in resolved.items():
        if scene.groups[name].on == "tets":
            from scipy.spatial import cKDTree

            _, idx = cKDTree(surface.vertices).query(model.tets.vertices[idx])
            idx = np.unique(idx)
        out[name] = np.asarray(idx, np.int64)
    return out


def never_saved(sandbox) -> list[str]:
    """Scenes never saved whose autosave or undo journal exists in ``sandbox``'s roots
    (edited before a crash), relative to the sandbox."""
    out: set[str] = set()
    for root in sandbox.roots:
        for suffix in (".autosave.toml", ".history.jsonl"):
            for kept in root.glob(f".*{suffix}"):
                scene = kept.with_name(kept.name[1:].removesuffix(suffix) + SCENE_SUFFIX)
                if not scene.exists() and sandbox.contains(kept):
                    out.add(sandbox.relative(scene))
    return sorted(out)


def driver_ghost(scene: Scene, surface) -> tuple[bytes, dict]:
    """The scene's driver (``[drive]``) as the editor's ghost: float32 positions (F, n, 3)
    of the driver frames that key the driven groups (:func:`wiggly.drive.keyed_frames`),
    and their meta: shot times, the driven groups, the file and its kind.  A scene without
    ``[drive]`` answers 404, a mesh not loaded yet (``surface`` None) 409; a driver that
    cannot be read, or animates another surface, 400 with the reader's message."""
    from wiggly.drive import keyed_frames
    from wiggly.progress import reporting
    from wiggly.scene.drive import scene_driver

    if scene.drive is None:
        raise EditError("the scene has no [drive]", 404)
    if surface is None:
        raise EditError("the mesh is not loaded yet", 409)
    drive = scene.drive
    try:
        with reporting(False):  # the page shows the driver, the terminal stays quiet
            driver = scene_driver(scene)
        why = driver.mismatch(surface.n_vertices, surface.faces, scene.mesh.path)
        if why is not None:
            raise WigglyInputError(f"{scene.where()}: drive.path = {drive.path!r}: {why}")
        start, end = scene.time_range()
        frames, times = keyed_frames(driver, offset=drive.offset, driver_range=drive.range,
                                     start=start, end=end)
    except WigglyInputError as err:
        raise EditError(str(err)) from None
    meta = {"n_frames": len(frames), "n_vertices": driver.n_vertices,
            "times": times.tolist(), "groups": list(drive.groups),
            "source": drive.path, "kind": driver.kind}
    return driver.positions[frames].astype("<f4").tobytes(), meta
