"""Public meshes from package registries, fetched into a cache (not shipped with wiggly).

Each source is an ordinary registry package, fetched with its own client; a source that
cannot be had (no npm, no apt-get, no network) is skipped with the reason:

- PyPI ``pyvista`` (a wiggly dependency) ships ``examples/ant.ply``, ``airplane.ply``,
  ``nut.ply`` (MIT);
- PyPI ``pymeshfix`` ships ``examples/StanfordBunny.ply`` (a scan with holes; ``pip
  download``, not installed);
- npm ``bunny`` (the Stanford bunny as JavaScript arrays, credited to the Stanford 3D
  scanning repository) and ``stl-models`` (MIT: ``objects/gearwheel.bin.stl``), via ``npm
  pack``;
- Debian ``libcgal-demo`` (CGAL's demo data: classic research meshes such as elephant, cow,
  armadillo, camel), via ``apt-get download`` (no install).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
import tarfile
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

CGAL_MESHES = ("elephant", "cow", "armadillo", "man", "mannequin-devil", "camel", "pig",
               "lion-head", "mushroom", "ChineseDragon-10kv", "elephant-with-holes",
               "diplodocus", "bull", "elk")


@dataclass(frozen=True)
class PublicMesh:
    name: str
    source: str  # registry and package
    path: Path


def cache_root() -> Path:
    base = os.environ.get("WIGGLY_TEST_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "wiggly-test")
    return Path(base) / "public-meshes"


def _run(cmd: list[str], cwd: Path) -> None:
    subprocess.run(cmd, cwd=cwd, check=True, capture_output=True, timeout=600)


def _pyvista() -> list[PublicMesh]:
    import pyvista.examples

    folder = Path(pyvista.examples.__file__).parent
    return [PublicMesh(n, "PyPI pyvista", folder / f"{n}.ply") for n in ("ant", "airplane", "nut")
            if (folder / f"{n}.ply").is_file()]


def _pymeshfix(root: Path) -> list[PublicMesh]:
    target = root / "pymeshfix" / "StanfordBunny.ply"
    if not target.is_file():
        work = Path(tempfile.mkdtemp(dir=root))
        try:
            _run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "-d",
                  str(work), "pymeshfix"], root)
            wheel = next(work.glob("pymeshfix-*.whl"))
            with zipfile.ZipFile(wheel) as z:
                data = z.read("pymeshfix/examples/StanfordBunny.ply")
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(data)
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return [PublicMesh("StanfordBunny (scan)", "PyPI pymeshfix", target)]


def _npm(root: Path) -> list[PublicMesh]:
    folder = root / "npm"
    bunny, gear = folder / "bunny.off", folder / "gearwheel.stl"
    if not (bunny.is_file() and gear.is_file()):
        npm = shutil.which("npm")
        if npm is None:
            raise RuntimeError("npm is not installed")
        folder.mkdir(parents=True, exist_ok=True)
        _run([npm, "pack", "--silent", "bunny@1.0.1", "stl-models@0.12.0"], folder)
        with tarfile.open(folder / "bunny-1.0.1.tgz") as t:
            js = t.extractfile("package/index.js").read().decode()
        arrays = re.findall(r"(positions|cells)\s*[:=]\s*(\[\s*\[.*?\]\s*\])", js, re.S)
        data = {k: json.loads(v) for k, v in arrays}
        lines = ["OFF", f"{len(data['positions'])} {len(data['cells'])} 0"]
        lines += [" ".join(map(repr, p)) for p in data["positions"]]
        lines += ["3 " + " ".join(map(str, c)) for c in data["cells"]]
        bunny.write_text("\n".join(lines) + "\n")
        with tarfile.open(folder / "stl-models-0.12.0.tgz") as t:
            gear.write_bytes(t.extractfile("package/objects/gearwheel.bin.stl").read())
    return [PublicMesh("bunny", "npm bunny", bunny),
            PublicMesh("gearwheel", "npm stl-models", gear)]


def _cgal(root: Path) -> list[PublicMesh]:
    folder = root / "cgal"
    wanted = [folder / f"{n}.off" for n in CGAL_MESHES]
    if not all(p.is_file() for p in wanted):
        apt = shutil.which("apt-get")
        if apt is None:
            raise RuntimeError("apt-get is not available")
        work = Path(tempfile.mkdtemp(dir=root))
        try:
            _run([apt, "download", "libcgal-demo"], work)
            deb = next(work.glob("libcgal-demo_*.deb"))
            _run(["dpkg-deb", "-x", str(deb), "x"], work)
            data = next((work / "x").rglob("data.tar.gz"))
            folder.mkdir(parents=True, exist_ok=True)
            with tarfile.open(data) as t:
                for n in CGAL_MESHES:
                    (folder / f"{n}.off").write_bytes(
                        t.extractfile(f"data/meshes/{n}.off").read())
        finally:
            shutil.rmtree(work, ignore_errors=True)
    return [PublicMesh(p.stem, "Debian libcgal-demo", p) for p in wanted]


def public_meshes() -> tuple[list[PublicMesh], list[str]]:
    """The meshes that could be had, and why the others could not."""
    root = cache_root()
    root.mkdir(parents=True, exist_ok=True)
    meshes, skipped = _pyvista(), []
    for fetch in (_pymeshfix, _npm, _cgal):
        try:
            meshes += fetch(root)
        except (OSError, RuntimeError, subprocess.SubprocessError, StopIteration,
                KeyError) as err:
            skipped.append(f"{fetch.__name__.strip('_')}: {err}")
    return meshes, skipped
