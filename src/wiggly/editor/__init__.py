"""``wiggly edit``: a local web editor for scenes (groups, keyframes, material, playback).

A small standard-library HTTP server (:mod:`wiggly.editor.server`) holds the scene as the
source of truth (:mod:`wiggly.editor.session`, edits in :mod:`wiggly.editor.state`, undo per
browser tab in :mod:`wiggly.editor.history`, autosave in :mod:`wiggly.editor.autosave`) and
serves a single-page three.js app (``static/``) that draws the body, poses keyframes with
gizmos and plays the solved motion.  Tetrahedralization and modes run in a child process
(:mod:`wiggly.editor.physics`); playback frames come from a linear solve at once and the warped
refinement in another child process (:mod:`wiggly.editor.playback`,
:mod:`wiggly.editor.refine`).  Files are confined to the directories the editor was started on
(:mod:`wiggly.editor.sandbox`).

    from wiggly.editor import serve
    server = serve("shot.toml")          # background thread; server.url; server.stop()
"""

from __future__ import annotations

import os
from pathlib import Path

from wiggly.editor.sandbox import Sandbox
from wiggly.editor.server import EditorServer
from wiggly.editor.session import Session

__all__ = ["EditorServer", "Sandbox", "Session", "serve"]


def serve(path: str | os.PathLike[str] | None = None, *, host: str = "127.0.0.1",
          port: int = 0, roots: list[str | os.PathLike[str]] | None = None,
          autosave: bool = True, **kw) -> EditorServer:
    """Start an editor on a background thread and open ``path`` (a scene, a mesh, or
    ``"builtin:<name>"``).  ``roots`` (default: the file's directory, else the current
    directory) are the only directories it reads and writes."""
    if roots is None:
        if path is not None and not str(path).startswith("builtin:"):
            roots = [Path(path).expanduser().resolve().parent]
        else:
            roots = [Path.cwd()]
    session = Session(Sandbox(list(roots)), autosave=autosave)
    if path is not None:
        p = str(path)
        session.open(p if p.startswith("builtin:") else str(Path(p).expanduser().resolve()))
    return EditorServer(session, host, port, **kw).start()
