"""Running wiggly out of process: ``wiggly animate`` on the exported shot, in its own
process group (Esc stops it and whatever it started), its progress read from its output.

Out of process rather than in Blender's Python: Blender pins its own Python and numpy, which
wiggly's dependencies (scipy, numba, fTetWild, ...) need not match; a separate process keeps
Blender's interface responsive during a long solve (no GIL shared), can be stopped at once
and cannot take Blender down with it.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from .shot import Shot, ShotError, write_shot

#: A number as wiggly prints it.
_NUMBER = r"-?\d+(?:\.\d*)?(?:e[-+]?\d+)?"


def wiggly_command(command: str) -> str:
    """The wiggly program of the preferences as a path; ShotError when it is not there."""
    where = ("set the path of the wiggly command of the Python environment where wiggly is "
             "installed (e.g. .venv/bin/wiggly) in Edit > Preferences > Add-ons > wiggly")
    if command.strip().startswith("//"):  # a preference serves every .blend file
        raise ShotError(f"the wiggly command '{command}' is relative to a .blend file (//), "
                        f"but the preference serves them all: give an absolute path: {where}")
    path = os.path.expanduser(command.strip() or "wiggly")
    found = shutil.which(path)
    if found is not None:
        return found
    if os.path.isdir(path):
        raise ShotError(f"the wiggly command '{command}' is a folder, not a program: {where}")
    if os.path.isfile(path):
        raise ShotError(f"the wiggly command '{command}' is a file that cannot be run (not "
                        f"executable, or not a program): {where}")
    raise ShotError(f"the wiggly command '{command}' was not found: install wiggly in a "
                    f"Python environment and {where}")


#: scene-file settings (regular expressions) as the Wiggly panel names them, for wiggly's
#: messages shown in Blender
PANEL_NAMES = (
    # advice for scene files the user writes; the add-on writes the mesh and driver itself
    (r"; and check that mesh\.path is the driver's mesh at its rest pose \([^)]*\), not "
     r"another scale or pose of it", ""),
    (r"\bsimulation\.fixed = \[([^\]]*)\]", r"the Fixed role (groups \1)"),
    (r"\bsimulation\.fixed\b", "the Fixed role"),
    (r"\bmesh\.path\b", "the mesh"),
    (r"\bmaterial\.young\b", "Young's modulus"),
    (r"\bmaterial\.poisson\b", "Poisson ratio"),
    (r"\bmaterial\.density\b", "Density"),
    (r"\bsimulation\.modes\b", "Modes"),
    (r"\bsimulation\.gravity\b", "the scene's Gravity"),
    (r"\bsimulation\.warp\b", "Warp"),
    (r"\bmesh\.resolution\b", "Resolution"),
    (r"\bdrive\.stiffness\b", "Drive stiffness"),
    (r"\bdrive\.intensity\b", "Intensity"),
    (r"\bdrive\.free_modes\b", "Free modes"),
    (r"\bkeyframes\[(\d+)\]", r"key \1"),
)

#: characters of wiggly's stage line shown in the status bar
STATUS_WIDTH = 120

#: seconds wiggly gets to end on Esc before it is killed (its outputs are written atomically,
#: so a kill leaves no half-written file; the add-on removes its temporary folder)
GRACE = 0.5


class Solve:
    """One ``wiggly animate`` run on ``shot`` in a temporary folder."""

    def __init__(self, shot: Shot, command: str):
        self.shot = shot
        self.command = wiggly_command(command)
        self.folder = Path(tempfile.mkdtemp(prefix="wiggly-blender-"))
        self.files = write_shot(shot, self.folder / "shot.toml")
        self.result = self.folder / "result.npz"
        self.log = self.folder / "wiggly.log"
        self.process: subprocess.Popen | None = None
        self.started = 0.0

    def start(self) -> None:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        with open(self.log, "wb") as log:
            self.process = subprocess.Popen(
                [self.command, "animate", str(self.files["scene"]), "-o", str(self.result),
                 "--overwrite"], cwd=self.folder, stdout=log, stderr=subprocess.STDOUT,
                stdin=subprocess.DEVNULL, env=env, start_new_session=os.name == "posix")
        self.started = time.perf_counter()

    def poll(self) -> int | None:
        return self.process.poll()

    def wait(self) -> int:
        return self.process.wait()

    def status(self) -> str:
        """The latest progress line of wiggly (its stage, a counter or elapsed time)."""
        try:
            with open(self.log, "rb") as f:
                f.seek(max(0, f.seek(0, os.SEEK_END) - 4096))
                tail = f.read().decode("utf-8", "replace")
        except OSError:
            return ""
        lines = [s.strip() for s in re.split(r"[\r\n]", tail) if s.strip()]
        stages = [s for s in lines if s.startswith("[wiggly]")]  # not a warning's paragraph
        if not stages:
            return "starting"
        text = self._plain(stages[-1])
        return text if len(text) <= STATUS_WIDTH else text[:STATUS_WIDTH - 3] + "..."

    def _plain(self, text: str) -> str:
        """wiggly's text without the add-on's own temporary folder and files (the report
        names the object instead), and with the scene file's setting names as the panel
        shows them (:data:`PANEL_NAMES`)."""
        mesh = self.files["mesh"].name
        for internal in (f'mesh.path = "{mesh}": ', f"mesh.path = '{mesh}': ",
                         f"{self.files['scene']}: ", f"{self.files['scene'].name}: ",
                         f"{self.folder}{os.sep}{mesh}: ", f"{mesh}: "):
            text = text.replace(internal, "")
        for name in (f"{self.folder}{os.sep}{mesh}", mesh):
            text = text.replace(name, "the mesh")
        driver = self.files.get("driver")
        if driver is not None:  # the object's own animation, which the add-on wrote
            for name in (f"{self.folder}{os.sep}{driver.name}", driver.name):
                text = text.replace(f"the driver {name}", "the animation")
                text = text.replace(name, "the animation")
        for name in (f"{self.folder}{os.sep}{self.result.name}", self.result.name):
            text = text.replace(name, "the bake")
        for key, label in PANEL_NAMES:
            text = re.sub(key, label, text)
        return self._blender_terms(text.replace(f"{self.folder}{os.sep}", ""))

    def _blender_terms(self, text: str) -> str:
        """wiggly's times (seconds from the shot's start) as the scene's frames, its places
        (y up, metres) in the object's local coordinates, and its group names as the Blender
        vertex groups' names."""
        shot = getattr(self, "shot", None)
        if shot is None:
            return text

        def frame(t: str) -> str:
            return f"{round(shot.frame_start + float(t) * shot.fps, 2):g}"

        def place(m: re.Match) -> str:
            p = shot.local(np.array([float(m[1]), float(m[2]), float(m[3])]))
            return f"({p[0]:.3g}, {p[1]:.3g}, {p[2]:.3g}) in the object's local coordinates"

        text = re.sub(rf"\bt = ({_NUMBER}) to ({_NUMBER}) s\b",
                      lambda m: f"frames {frame(m[1])} to {frame(m[2])}", text)
        text = re.sub(rf"\bbetween t = ({_NUMBER}) and ({_NUMBER}) s\b",
                      lambda m: f"between frames {frame(m[1])} and {frame(m[2])}", text)
        text = re.sub(rf"\bt = ({_NUMBER}) s\b", lambda m: f"frame {frame(m[1])}", text)
        text = re.sub(rf"\bat ({_NUMBER}) s\b", lambda m: f"at frame {frame(m[1])}", text)
        text = re.sub(rf"\(({_NUMBER}), ({_NUMBER}), ({_NUMBER})\) m(?![\w/^])", place, text)
        for name, label in shot.labels.items():
            if name != label:
                text = text.replace(f"'{name}'", f"'{label}'")
        return text

    def warnings(self) -> list[str]:
        """wiggly's warnings and notes of the run (a key it missed, a surface that is not
        closed, a solve that did not converge, a material too soft for the body's size, ...),
        one line each, as the add-on reports them."""
        try:
            text = self.log.read_text("utf-8", "replace")
        except OSError:
            return []
        lines = [s.strip() for s in re.split(r"[\r\n]", text)]
        return [self._plain(s.split(":", 2 if s.startswith("wiggly:") else 1)[-1].strip())
                for s in lines if s.startswith(("wiggly: warning:", "[wiggly] note:"))]

    def failure(self) -> str:
        """wiggly's own message (its last lines, without a traceback) of a failed run."""
        text = self.log.read_text("utf-8", "replace")
        lines = [s.strip() for s in re.split(r"[\r\n]", text) if s.strip()
                 and not s.startswith(("Traceback", "  File", "    "))]
        errors = [s.split("error:", 1)[1].strip() for s in lines if "error:" in s]
        message = " ".join(errors or lines[-3:]) or f"exit code {self.process.returncode}"
        if not errors and "animate" in message and "can't open file" in message:
            return (f"the wiggly command {self.command} is not wiggly's program (it could "
                    "not run 'animate'): set the path of the wiggly command of the "
                    "environment where wiggly is installed (e.g. .venv/bin/wiggly) in Edit > "
                    "Preferences > Add-ons > wiggly")
        return self._plain(message)

    def cancel(self) -> None:
        """Stop wiggly (and the programs it runs) at once: SIGTERM, and SIGKILL after
        :data:`GRACE` s (a terminate becomes a Python exit in wiggly, which waits for the native
        call it is in, e.g. a mesh check of seconds, while Blender's interface waits here)."""
        if self.process is not None and self.process.poll() is None:
            if os.name == "posix":
                os.killpg(self.process.pid, signal.SIGTERM)
            else:
                self.process.terminate()
            try:
                self.process.wait(timeout=GRACE)
            except subprocess.TimeoutExpired:
                if os.name == "posix":
                    os.killpg(self.process.pid, signal.SIGKILL)
                else:
                    self.process.kill()
                self.process.wait()

    def cleanup(self) -> None:
        shutil.rmtree(self.folder, ignore_errors=True)
