"""Exports from the editor: the scene solved as ``wiggly animate`` solves it, written in a
worker thread (a mixin of :class:`wiggly.editor.session.Session`)."""

from __future__ import annotations

import traceback
from pathlib import Path
from typing import Any

from wiggly.editor.scene_files import export_written
from wiggly.editor.state import EditError, EditorState
from wiggly.errors import WigglyInputError
from wiggly.progress import reporting
from wiggly.scene import OUTPUT_EXTENSIONS, resolve_groups

__all__ = ["Exports"]


class Exports:
    """``export`` for :class:`~wiggly.editor.session.Session` (its sandbox, state, physics,
    bus and export pool); :attr:`exporting` names the files of the export under way."""

    exporting: list[str] | None = None

    def export(self, paths: Any, overwrite: Any = False) -> dict:
        if not isinstance(paths, list) or not paths or len(paths) > 8:
            raise EditError("paths must be a list of 1 to 8 output files")
        if not isinstance(overwrite, bool):
            raise EditError("overwrite must be true or false")
        real = [self.sandbox.resolve(p, suffixes=OUTPUT_EXTENSIONS) for p in paths]
        from wiggly.scene import check_outputs

        try:
            check_outputs(real, True)
        except WigglyInputError as err:
            raise EditError(str(err)) from None
        existing = [p for p in real if p.exists() or (
            p.suffix.lower() == ".obj" and p.with_name(f"{p.stem}_0000.obj").exists())]
        if existing and not overwrite:
            raise EditError(f"{', '.join(self.sandbox.relative(p) for p in existing)} "
                            f"{'exists' if len(existing) == 1 else 'exist'}: overwrite, or "
                            "export under other names", 409)
        with self._lock:
            state, version = self.state, self.version
        self._export_pool.submit(self._export, state, version, real, overwrite)
        return {"paths": [self.sandbox.relative(p) for p in real]}

    def _export(self, state: EditorState, version: int, paths: list[Path], overwrite: bool):
        """Solve the scene as ``wiggly animate`` does (same body) and write ``paths``."""
        with reporting(False):  # the page shows the export; the terminal stays quiet
            self._solve_and_write(state, paths, overwrite, version)

    def _solve_and_write(self, state: EditorState, paths: list[Path], overwrite: bool,
                         version: int | None = None):
        scene = state.scene
        names = [p.name for p in paths]
        self.exporting = names
        self.bus.publish("export", stage="running", message=f"exporting {', '.join(names)}")
        try:
            from wiggly.scene import keyframe_highlights, keyframes_of, solve_scene, write_outputs

            body = self.physics.body(scene, abandon=self._stop.is_set, hold=True)
            if body is None:
                return
            groups = resolve_groups(scene, body.model)
            keys = keyframes_of(scene, body, groups)
            # the library's solve, as `wiggly animate` runs it; its warnings are not caught
            # here: warnings.catch_warnings changes process-wide state, and a block of this
            # thread overlapping the playback thread's would restore the other's wrongly
            # (warnings then stayed ignored); the playback's solve shows the same ones
            anim = solve_scene(scene, body, keys)
            write_outputs(scene, anim, paths, overwrite=overwrite,
                          highlights=keyframe_highlights(scene, body, anim.keyframes, groups))
            written = [export_written(p, self.sandbox.relative(p)) for p in paths]
            # an edit made while it ran is not in it: say so, rather than seem current
            later = version is not None and self.version != version
            since = (" (the scene as it was when the export started: edits made since are not "
                     "in it; export again to include them)" if later else "")
            self.bus.publish("export", stage="done",
                             message=f"exported {', '.join(written)}{since}",
                             paths=[self.sandbox.relative(p) for p in paths])
        except Exception as err:
            if not isinstance(err, WigglyInputError):
                traceback.print_exc()
            self.bus.publish("export", stage="error", message=f"export failed: {err}")
        finally:
            self.exporting = None


