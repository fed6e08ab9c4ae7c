"""Which files the editor may read and write: only inside the directories it was started on.

Every path that comes from the browser goes through :meth:`Sandbox.resolve`: it is taken
relative to the first root, made absolute with every symlink followed (``os.path.realpath``),
and refused unless the result lies inside one of the roots (themselves resolved).  So ``..``
components, absolute paths elsewhere and symlinks pointing out of a root are all refused, and
a refused path says which roots are allowed.
"""

from __future__ import annotations

import os
from pathlib import Path

from wiggly.editor.state import EditError

__all__ = ["Sandbox"]

MAX_PATH = 4096


class Sandbox:
    """Paths inside ``roots`` (directories; the first one is where relative paths start)."""

    def __init__(self, roots: list[str | os.PathLike[str]]):
        if not roots:
            raise ValueError("the sandbox needs at least one root directory")
        self.roots = [Path(os.path.realpath(r)) for r in roots]
        for r in self.roots:
            if not r.is_dir():
                raise EditError(f"{r} is not a directory")

    @property
    def home(self) -> Path:
        return self.roots[0]

    def contains(self, path: str | os.PathLike[str]) -> bool:
        real = Path(os.path.realpath(path))
        return any(real == r or real.is_relative_to(r) for r in self.roots)

    def resolve(self, path: object, *, must_exist: bool = False,
                suffixes: tuple[str, ...] | None = None) -> Path:
        """The real path of ``path`` (relative to the first root); :class:`EditError` (403) if
        it leaves the roots, (404) if ``must_exist`` and it does not, (400) for a suffix not in
        ``suffixes``."""
        if not isinstance(path, str) or not path or len(path) > MAX_PATH or "\x00" in path:
            raise EditError(f"a path must be a non-empty string of at most {MAX_PATH} "
                            f"characters; got {str(path)[:80]!r}")
        p = Path(path).expanduser() if path.startswith("~") else Path(path)
        if not p.is_absolute():
            p = self.home / p
        real = Path(os.path.realpath(p))
        if not any(real == r or real.is_relative_to(r) for r in self.roots):
            raise EditError(f"{path}: outside the directories this editor may use "
                            f"({', '.join(map(str, self.roots))}; wiggly edit --root DIR "
                            "adds one)", 403)
        if suffixes is not None and real.suffix.lower() not in suffixes:
            raise EditError(f"{path}: expected a file ending in {', '.join(suffixes)}")
        if must_exist and not real.is_file():
            raise EditError(f"{path}: no such file", 404)
        return real

    def relative(self, path: Path) -> str:
        """How the browser shows ``path``: relative to the first root when inside it."""
        path = Path(path)
        try:
            return str(path.relative_to(self.home))
        except ValueError:
            return str(path)

    def shown(self, message: str) -> str:
        """``message`` with the paths inside the first root shown as :meth:`relative` shows
        them (a notice about ``/home/me/shots/creature.obj`` says ``creature.obj``)."""
        return message.replace(f"{self.home}{os.sep}", "")

    def listing(self, suffixes: tuple[str, ...], limit: int = 2000,
                max_depth: int = 4) -> list[str]:
        """Files with the given suffixes under the roots (symlinks leaving them skipped)."""
        out: list[str] = []
        for root in self.roots:
            base_depth = len(root.parts)
            for dirpath, dirnames, filenames in os.walk(root):
                here = Path(dirpath)
                dirnames[:] = sorted(d for d in dirnames if not d.startswith(".")
                                     and d not in ("__pycache__", "node_modules"))
                if len(here.parts) - base_depth >= max_depth:
                    dirnames[:] = []
                for f in sorted(filenames):
                    p = here / f
                    # hidden files are the editor's own (autosaves, kept journals)
                    if p.suffix.lower() in suffixes and not f.startswith(".") \
                            and self.contains(p):
                        out.append(str(p) if root != self.home else self.relative(p))
                        if len(out) >= limit:
                            return out
        return out
