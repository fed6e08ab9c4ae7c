"""``wiggly edit [SCENE_OR_MESH]``: the local web editor (:mod:`wiggly.editor`)."""

from __future__ import annotations

import argparse
import ipaddress
import signal
import sys
import threading
from pathlib import Path

HELP = "edit a scene in the browser (groups, keyframes, material; live solve)"
DESCRIPTION = """\
Start the local web editor on a scene file (.toml), a mesh (a new scene beside it) or a
bundled model (builtin:critter, builtin:plant, builtin:bar), and open it in the browser.
Select vertex groups on the surface, keyframe and pose them with gizmos, edit the material,
damping and gravity: every edit re-solves in the background and updates the playback.
Saves the same scene format as `wiggly animate` reads; exports glb/USD/MP4.

The editor reads and writes files only inside the directory of the file it was started on
(or, started without a file, the current directory), plus any --root (e.g. --root .. for a
mesh in the folder above the scene); edits are autosaved beside the scene
(.NAME.autosave.toml) with every browser tab's undo history (.NAME.history.jsonl), and both
are recovered when the editor is started again. A scene is open in one editor at a time: a
second `wiggly edit` on it is refused, naming the first one's process and address."""
EPILOG = """\
examples:
  wiggly edit shot.toml
  wiggly edit critter.obj                  # a new scene (Save writes critter.toml beside it)
  wiggly edit builtin:plant --port 8800 --no-browser
  wiggly edit shot.toml --host 0.0.0.0     # reachable from the network: see the warning"""


def add_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("path", metavar="SCENE_OR_MESH", nargs="?",
                        help="scene (.toml), mesh file, or builtin:<model>; default: choose in "
                             "the browser")
    parser.add_argument("--host", default="127.0.0.1",
                        help="address to listen on (default 127.0.0.1: this machine only)")
    parser.add_argument("--port", type=int, default=8765,
                        help="port (default 8765; 0: any free port; a busy port falls back to "
                             "a free one)")
    parser.add_argument("--root", metavar="DIR", action="append", default=[],
                        help="another directory the editor may read and write (repeatable)")
    parser.add_argument("--no-browser", action="store_true", help="do not open a browser")
    parser.add_argument("--no-autosave", action="store_true", help="do not autosave edits")
    parser.add_argument("--max-upload-mb", type=float, default=64.0, metavar="MB",
                        help="largest mesh upload accepted (default 64 MB)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log every request")


def roots_for(path: str | None, extra: list[str]) -> list[Path]:
    """Directories the editor may use: the file's directory (else the current one) first."""
    first = Path.cwd() if path is None or path.startswith("builtin:") else \
        Path(path).expanduser().resolve().parent
    return [first, *(Path(r).expanduser().resolve() for r in extra)]


def exposure_warning(host: str) -> str | None:
    """The warning printed when ``host`` is reachable from other machines (else None)."""
    try:
        exposed = not ipaddress.ip_address(host).is_loopback
    except ValueError:
        exposed = host != "localhost"
    if not exposed:
        return None
    return (f"listening on {host}: anyone who can reach this machine can read and write the "
            "scene files in the editor's directories. Use only on a trusted network.")


def _has_unsaved_edits(path: Path) -> bool:
    """Whether the scene file ``path`` (missing: deleted, or never saved) has edits kept
    beside it, which opening it recovers."""
    from wiggly.editor.autosave import autosave_path
    from wiggly.editor.history import history_path

    return path.suffix.lower() == ".toml" and (
        autosave_path(path).is_file() or history_path(path).is_file())


def start(args: argparse.Namespace):
    """Open the file and start the server on a background thread (``run`` waits on it)."""
    from wiggly.editor import EditorServer, Sandbox, Session
    from wiggly.errors import WigglyInputError

    warning = exposure_warning(args.host)
    if warning:
        print(f"wiggly: warning: {warning}", file=sys.stderr)
    if args.path is not None and not args.path.startswith("builtin:") and \
            not Path(args.path).expanduser().is_file() and \
            not _has_unsaved_edits(Path(args.path).expanduser()):
        raise WigglyInputError(f"{args.path}: no such file")
    session = Session(Sandbox(roots_for(args.path, args.root)), autosave=not args.no_autosave)
    try:
        if args.path is not None:
            p = args.path if args.path.startswith("builtin:") else \
                str(Path(args.path).expanduser().resolve())
            for notice in session.open(p)["notices"]:
                print(f"wiggly: {notice}", file=sys.stderr)
        kw = dict(max_upload=int(args.max_upload_mb * 2**20), verbose=args.verbose)
        try:
            server = EditorServer(session, args.host, args.port, **kw)
        except OSError:
            if args.port == 0:
                raise
            server = EditorServer(session, args.host, 0, **kw)  # the port is busy
    except BaseException:
        session.close()
        raise
    return server.start()


def run(args: argparse.Namespace) -> int:
    server = start(args)
    stop = threading.Event()

    def on_signal(*_) -> None:
        stop.set()

    # before the address is printed: a Ctrl+C right after it stops the editor cleanly too
    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        print(f"wiggly edit: {server.url}  (Ctrl+C to stop)", flush=True)
        if not args.no_browser:
            import webbrowser

            webbrowser.open(server.url)
        while not stop.wait(0.5):
            # native code run by the background threads (the tetrahedralizer) may install its
            # own SIGINT handler: take Ctrl+C back so that it stops the editor cleanly
            signal.signal(signal.SIGINT, on_signal)
        for line in stop_messages(server.session, autosave=not args.no_autosave):
            print(line, file=sys.stderr, flush=True)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        server.stop()
    return 0


def stop_messages(session, autosave: bool = True) -> list[str]:
    """What Ctrl+C prints: that an export under way is finished first, and where the
    unsaved edits are kept (or that they are lost, without autosave)."""
    import os
    import shlex

    from wiggly.editor.autosave import autosave_path
    from wiggly.editor.history import history_path
    from wiggly.editor.state import EditError

    out = []
    if session.exporting:
        out.append(f"wiggly edit: finishing the export of {', '.join(session.exporting)} "
                   "before stopping...")
    try:
        scene, dirty = session.scene, session.dirty
    except EditError:  # no scene open
        scene, dirty = None, False
    if scene is None or not dirty or scene.source is None:
        return [*out, "wiggly edit: stopped"]
    source = Path(scene.source)
    try:
        shown = os.path.relpath(source)
    except ValueError:  # another drive
        shown = str(source)
    shown = shown if not shown.startswith("..") else str(source)
    if not source.exists() and not (autosave_path(source).exists() or
                                    history_path(source).exists()):
        return [*out, f"wiggly edit: stopped; the new scene {source.name} was not saved "
                      "(it had no edits to keep)"]
    if not autosave:
        return [*out, f"wiggly edit: stopped; the unsaved edits of {source.name} are lost "
                      "(--no-autosave)"]
    kept = (f"the unsaved edits of {source.name} are kept beside it "
            f"({autosave_path(source).name}, {history_path(source).name})")
    if session.changed_on_disk:  # the next open keeps the other program's version
        stem = source.name.removesuffix(source.suffix)
        return [*out, f"wiggly edit: stopped; {kept}. {source.name} was changed on disk by "
                      f"another program: `wiggly edit {shlex.quote(shown)}` opens the disk's "
                      f"version and keeps these edits as the scene {stem}.unsaved-<date>-"
                      "<time>.toml beside it"]
    return [*out, f"wiggly edit: stopped; {kept}: `wiggly edit {shlex.quote(shown)}` opens "
                  "it with them, and Save writes them to the file"]
