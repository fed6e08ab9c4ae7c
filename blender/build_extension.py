"""Build the wiggly Blender extension zip (what ``blender --command extension build`` makes,
without needing Blender): the add-on's files at the zip's root, named after the manifest.

usage: python blender/build_extension.py [OUTPUT_DIR]   (default: dist/)
"""

from __future__ import annotations

import os
import sys
import tomllib
import zipfile
from pathlib import Path

SOURCE = Path(__file__).resolve().parent / "wiggly_blender"


def build(out_dir: Path) -> Path:
    manifest = tomllib.loads((SOURCE / "blender_manifest.toml").read_text())
    out_dir.mkdir(parents=True, exist_ok=True)
    target = out_dir / f"{manifest['id']}-{manifest['version']}.zip"
    tmp = target.with_name(f".{target.name}.tmp{os.getpid()}")
    files = sorted(p for p in SOURCE.rglob("*") if p.is_file() and "__pycache__" not in p.parts
                   and p.suffix in {".py", ".toml"})
    try:
        with zipfile.ZipFile(tmp, "w", zipfile.ZIP_DEFLATED) as z:
            for path in files:
                z.write(path, path.relative_to(SOURCE).as_posix())
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return target


if __name__ == "__main__":
    path = build(Path(sys.argv[1]) if len(sys.argv) > 1 else Path("dist"))
    print(f"[make] {path}: install it in Blender 4.2+ with Edit > Preferences > Get Extensions "
          "> Install from Disk")
