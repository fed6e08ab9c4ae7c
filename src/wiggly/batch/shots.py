"""The shots of a batch: scene files and expanded sweeps, their folder names, and the content
keys that make a batch resumable and let shots share a prepared body."""

from __future__ import annotations

import hashlib
import json
import os
import re
import warnings
from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Any

from wiggly.batch.sweep import RESERVED_NAMES, Sweep, is_sweep, read_toml, sweep_from_dict
from wiggly.body import Body
from wiggly.errors import WigglyInputError, warn
from wiggly.limits import MAX_SHOTS
from wiggly.progress import activity
from wiggly.scene import Scene, SimulationSpec, scene_from_dict, scene_to_dict
from wiggly.scene.spec import OUTPUT_EXTENSIONS

#: Version of the batch's folders and keys (a new one re-runs every shot).
BATCH_FORMAT = 1
#: Files of a batch's folder besides the shots' folders.
TOP_LEVEL = ("summary.csv", "summary.json", "contact-sheet.html", "contact-sheet.png")
#: Parameters listed for every shot in the summary (besides a sweep's own).
STANDARD_PARAMS = ("mesh.path", "mesh.resolution", "material.young", "material.poisson",
                   "material.density", "damping.alpha", "damping.beta", "simulation.gravity",
                   "simulation.modes", "simulation.warp", "time.start", "time.end")


@dataclass
class Shot:
    """One shot of a batch.

    ``scene`` is None when the shot's scene is invalid (``error`` says why); ``params`` are a
    sweep's values for it (TOML values by parameter path); ``outputs`` the file names written
    into its folder.  ``key`` (content of the scene, the mesh and what is written) and
    ``body_key`` (what the prepared body depends on) are filled by :func:`keyed`.
    """

    name: str
    origin: str
    scene: Scene | None
    error: str | None = None
    params: dict[str, Any] = field(default_factory=dict)
    outputs: tuple[str, ...] = ()
    seed: int | None = None
    sample: int | None = None
    key: str = ""
    body_key: str = ""
    warnings: list[str] = field(default_factory=list)  # said when its scene was read

    def parameters(self) -> dict[str, Any]:
        """The standard parameters of the shot's scene, then the sweep's."""
        out: dict[str, Any] = {}
        if self.scene is not None:
            s = self.scene
            start, end = s.time_range()
            std = (s.mesh.path, s.mesh.resolution, s.material.young, s.material.poisson,
                   s.material.density, s.damping.alpha, s.damping.beta,
                   list(s.simulation.gravity), s.simulation.modes, s.simulation.warp, start, end)
            out.update(zip(STANDARD_PARAMS, std, strict=True))
        out.update(self.params)
        return out


def collect(inputs: Sequence, write: Sequence[str] | None = None) -> tuple[list[Shot], list]:
    """The shots of ``inputs`` (scene files, sweep files, :class:`Scene` or :class:`Sweep`
    objects), with unique folder names, and the sweeps among them.  An unreadable or invalid
    scene file becomes a failed shot; an invalid sweep raises :class:`WigglyInputError`
    (it describes many shots).  A large sweep says that it is being expanded
    (:mod:`wiggly.progress`)."""
    if write is not None:  # the same for every shot: a mistake fails the batch, not each shot
        problem = check_output_names(write, "--write")
        if problem:
            raise WigglyInputError(problem)
    shots: list[Shot] = []
    sweeps: list[Sweep] = []
    given: set[Path] = set()
    for item in inputs:
        if isinstance(item, str | os.PathLike):
            if Path(item).resolve() in given:
                warn(f"{item} is given more than once; it runs once")
                continue
            given.add(Path(item).resolve())
        if isinstance(item, Sweep):
            sweeps.append(item)
            shots += _sweep_shots(item, write)
        elif isinstance(item, Scene):
            shots.append(_scene_shot(item, item.name, item.where(), write))
        else:
            path = Path(item)
            try:
                data = read_toml(path)
            except WigglyInputError as err:
                shots.append(Shot(_clean(path.stem), str(path), None, str(err)))
                continue
            if is_sweep(data):
                sweep = sweep_from_dict(data, where=str(path), source=path.resolve())
                sweeps.append(sweep)
                shots += _sweep_shots(sweep, write)
            else:
                try:
                    with _said() as said:
                        scene = scene_from_dict(data, where=str(path), source=path.resolve())
                except WigglyInputError as err:
                    shots.append(Shot(_clean(path.stem), str(path), None, str(err)))
                    continue
                shots.append(_scene_shot(scene, path.stem, str(path), write))
                shots[-1].warnings = said
        if len(shots) > MAX_SHOTS:
            raise WigglyInputError(f"the inputs make more than {MAX_SHOTS} shots "
                                   "(wiggly.limits.MAX_SHOTS); split the batch")
    _unique_names(shots)
    return shots, sweeps


def _scene_shot(scene: Scene, name: str, origin: str, write) -> Shot:
    names = tuple(write) if write is not None else tuple(Path(p).name for p in
                                                          scene.output.paths)
    shot = Shot(_clean(name), origin, scene, outputs=names)
    error = check_output_names(names, "--write" if write is not None else "output.paths")
    if error:
        shot.scene, shot.error = None, f"{origin}: {error}"
    return shot


def _sweep_shots(sweep: Sweep, write) -> list[Shot]:
    names = tuple(write) if write is not None else sweep.outputs if sweep.outputs is not None \
        else tuple(Path(p).name for p in sweep.base.output.paths)
    problem = check_output_names(names, "--write" if write is not None else "output.paths")
    if problem:
        raise WigglyInputError(f"{sweep.where()}: {problem}")
    width = max(4, len(str(len(sweep) - 1)))
    out = []
    with activity(f"checking the {len(sweep)} shots of {sweep.where()}", len(sweep) > 1000):
        for i in range(len(sweep)):
            out.append(_sweep_shot(sweep, i, width, names))
    return out


def _sweep_shot(sweep: Sweep, i: int, width: int, names: tuple[str, ...]) -> Shot:
    """Shot ``i`` of a sweep (invalid: ``scene`` None and the validator's ``error``)."""
    sample, values = sweep.values(i)
    origin = f"{sweep.where()} shot {i}"
    shot = Shot(_clean(f"{sweep.name}-{i:0{width}d}"), origin, None, params=values,
                outputs=names, seed=sweep.seed, sample=sample)
    try:
        with _said() as shot.warnings:
            shot.scene = sweep.scene(values, f"{origin} ({_describe(values)})", origin)
    except WigglyInputError as err:
        shot.error = str(err)
    return shot


@contextmanager
def _said() -> Iterator[list[str]]:
    """The warnings of the block, each once, kept for the shot's record and said again (the
    console shows them as ``wiggly animate`` does)."""
    kept: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield kept
    for w in caught:
        if str(w.message) not in kept:
            kept.append(str(w.message))
            warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)


def _describe(values: dict) -> str:
    return ", ".join(f"{k} = {json.dumps(v)}" for k, v in values.items()) or "the base scene"


def check_output_names(names: Iterable[str], what: str) -> str | None:
    """Why a shot's output file names cannot all go into one folder, or None."""
    seen = set()
    for name in names:
        if Path(name).name != name or name in ("", ".", ".."):
            return (f"{what}: {name!r} has folders; a batch writes every output of a shot into "
                    "the shot's folder, so give file names")
        if Path(name).suffix.lower() not in OUTPUT_EXTENSIONS:
            return (f"{what}: {name!r} has an unsupported extension; use one of "
                    f"{', '.join(OUTPUT_EXTENSIONS)}")
        if name in RESERVED_NAMES:
            return (f"{what}: {name!r} is a file the batch writes itself "
                    f"({', '.join(RESERVED_NAMES)})")
        if name in seen:
            return (f"{what}: two outputs are named {name!r}; a batch writes them into one "
                    "folder per shot")
        seen.add(name)
    return None


def _clean(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]", "_", name).lstrip(".") or "shot"


def _unique_names(shots: list[Shot]) -> None:
    """Give scene files of the same name as an earlier one their folder's name as a prefix,
    then numbers."""
    by_name: dict[str, list[Shot]] = {}
    for s in shots:
        by_name.setdefault(s.name, []).append(s)
    for name, same in by_name.items():
        if len(same) > 1:  # the first keeps its name: adding a file renames no shot done
            for s in same[1:]:
                parent = Path(s.origin).parent.name if s.scene is None or s.scene.source is None \
                    else s.scene.source.parent.name
                if parent and not s.params:
                    s.name = _clean(f"{parent}-{name}")
    taken = set(TOP_LEVEL)
    for s in shots:
        base, k = s.name, 2
        while s.name in taken:
            s.name, k = f"{base}-{k}", k + 1
        taken.add(s.name)


# ----------------------------------------------------------------------------------------------
# content keys


class Digests:
    """SHA-256 of mesh files, computed once per file (by path, size and modification time)."""

    def __init__(self) -> None:
        self._known: dict[tuple, str] = {}

    def __call__(self, path: Path) -> str:
        st = path.stat()
        key = (str(path), st.st_size, st.st_mtime_ns)
        if key not in self._known:
            h = hashlib.sha256()
            with open(path, "rb") as f:
                for block in iter(lambda: f.read(1 << 20), b""):
                    h.update(block)
            self._known[key] = h.hexdigest()
        return self._known[key]


def body_scene(scene: Scene) -> Scene:
    """What a prepared body depends on: the mesh, the material, the modes, the mass matrix, the
    fixed groups (and a ``[drive]``'s driver and groups, whose shapes join the modes).
    Damping and gravity are applied per shot (they change only the per-mode coefficients), so
    shots that differ in them share the body."""
    sim = scene.simulation
    groups = set(sim.fixed) | {g for g, spec in scene.groups.items() if spec.young is not None}
    extra = {}
    if scene.drive is not None and scene.drive.adds_shapes:  # the driver's shapes join the modes
        groups |= set(scene.drive.groups)
        extra = {"drive": scene.drive, "time": scene.time}
    return Scene(mesh=scene.mesh, material=scene.material,
                 simulation=SimulationSpec(modes=sim.modes, lumped_mass=sim.lumped_mass,
                                           fixed=sim.fixed, warp=sim.warp),
                 groups={g: scene.groups[g] for g in sorted(groups)}, source=scene.source,
                 **extra)


def _content(scene: Scene, digest: Digests) -> dict:
    d = scene_to_dict(scene)
    d["mesh"]["path"] = (scene.mesh.path if scene.mesh.path.startswith("builtin:") else
                         "sha256:" + digest(scene.mesh_file()))
    if scene.mesh.path.startswith("builtin:"):
        d["mesh"]["sha256"] = digest(scene.mesh_file())
    for key in ("paths", "overwrite"):  # the batch decides what is written, and where
        d["output"].pop(key, None)
    return d


def _hash(data: Any) -> str:
    text = json.dumps(data, sort_keys=True, separators=(",", ":"), default=list)
    return hashlib.sha256(text.encode()).hexdigest()


def keyed(shots: list[Shot], digest: Digests) -> None:
    """Fill each valid shot's ``key`` (its scene and mesh content, and its outputs) and
    ``body_key``.  A mesh file that cannot be read fails its shots."""
    from wiggly import __version__

    layout = [f.name for f in fields(Body)]  # a changed Body cannot reuse prepared ones
    for s in shots:
        if s.scene is None:
            continue
        try:
            content = _content(s.scene, digest)
            body = _content(body_scene(s.scene), digest)
        except OSError as err:
            s.error = f"{s.scene.where()}: mesh.path = {s.scene.mesh.path!r}: cannot read it " \
                      f"({err.strerror or err})"
            s.scene = None
            continue
        s.key = _hash({"batch": BATCH_FORMAT, "wiggly": __version__, "scene": content,
                       "outputs": list(s.outputs)})
        s.body_key = _hash({"batch": BATCH_FORMAT, "wiggly": __version__, "body": body,
                            "layout": layout})


def saved_scene(shot: Shot) -> Scene:
    """The shot's scene as saved in its folder: the mesh and a ``[drive]``'s driver by
    absolute path, the outputs by their names in the folder (``wiggly animate scene.toml
    --overwrite`` redoes the shot)."""
    scene = shot.scene
    assert scene is not None
    mesh = scene.mesh if scene.mesh.path.startswith("builtin:") else \
        replace(scene.mesh, path=os.fspath(scene.mesh_file().resolve()))
    drive = scene.drive if scene.drive is None else \
        replace(scene.drive, path=os.fspath(scene.resolve(scene.drive.path).resolve()))
    return replace(scene, mesh=mesh, drive=drive,
                   output=replace(scene.output, paths=shot.outputs, overwrite=False),
                   source=None)
