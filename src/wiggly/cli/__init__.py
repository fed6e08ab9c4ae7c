"""The ``wiggly`` command line: a thin layer over :mod:`wiggly.scene` and the library.

Each subcommand is a module with ``add_args(parser)`` and ``run(args) -> int`` (meshio style);
:func:`main` parses, dispatches and turns errors into exit codes:

* 0: success;
* 1: a user error (invalid scene or mesh, missing file, existing output, no OpenGL): one
  message on stderr, no traceback; an unexpected exception (a bug) prints its traceback and
  asks for a report;
* 2: a usage error (unknown option, missing argument), reported by argparse.

What the library logs on the ``wiggly`` logger goes to stderr while a command runs: its stage
lines (INFO) by default, DEBUG lines with ``-v``, only warnings and errors with ``-q``.
Stages are reported (:func:`wiggly.progress.reporting`) unless ``-q``; their bars are drawn
only on a terminal (:mod:`wiggly.progress`).
"""

from __future__ import annotations

import argparse
import difflib
import logging
import signal
import sys
import traceback
import warnings

from wiggly.cli import animate, batch, demo, edit, modes, render, schema
from wiggly.errors import WigglyInputError
from wiggly.files import terminate_as_exit
from wiggly.progress import reporting

__all__ = ["main"]

COMMANDS = {"animate": animate, "batch": batch, "edit": edit, "modes": modes, "render": render,
            "demo": demo, "schema": schema}
DESCRIPTION = """\
Animate elastic 3D objects from sparse keyframes (sparse spacetime constraints,
Schulz et al. 2014). A scene file (TOML) names the model, its material and the
keyframes; `wiggly animate` solves for the motion and writes glTF/USD/OBJ/npz
animations and MP4/GIF/PNG previews."""

EPILOG = """\
examples:
  wiggly demo                                 # the bundled demo into ./wiggly-demo/
  wiggly animate examples/jump.toml           # writes the scene's [output] paths
  wiggly animate shot.toml -o shot.glb -o shot.mp4 --overwrite
  wiggly batch shots/*.toml -o out/                # many shots (or a sweep), all cores
  wiggly edit shot.toml                       # the browser editor
  wiggly modes builtin:plant -n 12            # eigenfrequencies of a model
  wiggly render out/shot.npz -o shot.gif      # preview an exported animation
  wiggly schema > scene.schema.json           # JSON Schema of scene files

`wiggly COMMAND --help` describes each command. Scene format: docs/scene-format.md."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``wiggly`` and its subcommands."""
    from wiggly import __version__

    parser = argparse.ArgumentParser(
        prog="wiggly", description=DESCRIPTION, epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"wiggly {__version__}")
    _add_verbosity(parser, quiet=False)
    sub = parser.add_subparsers(title="commands", dest="command", metavar="COMMAND")
    for name, module in COMMANDS.items():
        p = sub.add_parser(name, help=module.HELP, description=module.DESCRIPTION,
                           epilog=module.EPILOG,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
        module.add_args(p)
        _add_verbosity(p)
        p.set_defaults(run=module.run)
    return parser


def _add_verbosity(parser: argparse.ArgumentParser, quiet: bool = True) -> None:
    """``-v`` (DEBUG lines too) before or after the command; ``-q`` (no bars, only warnings
    and errors) after it, on every command."""
    options = {a for action in parser._actions for a in action.option_strings}
    if "-v" not in options:
        parser.add_argument("-v", "--verbose", action="count", default=argparse.SUPPRESS,
                            help="also show the library's debugging lines")
    if quiet and "-q" not in options:
        parser.add_argument("-q", "--quiet", action="store_true", default=argparse.SUPPRESS,
                            help="no progress bars or stage lines: only warnings and errors")


class _Stderr(logging.Handler):
    """Writes the ``wiggly`` logger's records to the *current* ``sys.stderr``: stage lines as
    ``[wiggly] ...``, warnings and errors as ``wiggly: warning: ...``."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            message = record.getMessage()
            if record.levelno >= logging.WARNING:
                message = f"wiggly: {record.levelname.lower()}: {message}"
            else:
                message = f"[wiggly] {message}"
            print(message, file=sys.stderr, flush=True)
        except Exception:
            self.handleError(record)


def _logging_level(args: argparse.Namespace) -> int:
    verbose = getattr(args, "verbose", 0)
    if getattr(args, "quiet", False):
        return logging.WARNING
    return logging.DEBUG if isinstance(verbose, int) and verbose > 0 else logging.INFO


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    print(f"wiggly: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run ``wiggly`` with ``argv`` (default: ``sys.argv[1:]``); return the exit code."""
    parser = build_parser()
    try:
        args, extra = parser.parse_known_args(argv)
    except SystemExit as exit_:  # --help, --version (0) or a usage error (2)
        return exit_.code if isinstance(exit_.code, int) else 2
    if extra:
        return _unrecognized(parser, args, extra)
    if args.command is None:
        parser.print_help(sys.stderr)
        return 2
    from wiggly.render import RenderingError

    logger = logging.getLogger("wiggly")
    handler, level = _Stderr(), logger.level
    logger.addHandler(handler)
    logger.setLevel(_logging_level(args))
    with warnings.catch_warnings(), reporting(logger.isEnabledFor(logging.INFO)):
        warnings.showwarning = _show_warning
        try:
            with terminate_as_exit():  # temporary outputs are removed as on Ctrl+C
                return int(args.run(args) or 0)
        except SystemExit as exit_:
            if exit_.code != 128 + signal.SIGTERM:
                raise
            print("wiggly: terminated", file=sys.stderr)
            return exit_.code
        except (WigglyInputError, RenderingError) as err:
            _error(str(err))
        except OSError as err:  # missing file, permissions, disk full
            where = f": {err.filename}" if err.filename else ""
            _error(f"{err.strerror or err}{where}")
        except KeyboardInterrupt:
            print("wiggly: interrupted", file=sys.stderr)
            return 130
        except Exception:
            traceback.print_exc()
            print("wiggly: internal error (this is a bug in wiggly, not in your input); please "
                  "report it to wiggly's maintainers with the traceback above and your scene "
                  "file", file=sys.stderr)
        finally:
            logger.removeHandler(handler)
            logger.setLevel(level)
        return 1


#: What an option a user may guess for means instead.
_MEANT = {"--warp": "the solve is warped by default; --linear solves without the warp",
          "--warped": "the solve is warped by default; --linear solves without the warp",
          "--force": "--overwrite replaces existing outputs"}


def _unrecognized(parser: argparse.ArgumentParser, args: argparse.Namespace,
                  extra: list[str]) -> int:
    """A usage error for arguments the command does not take: its own usage, and the
    options it has that come closest (the top-level usage named none of them)."""
    command = getattr(args, "command", None)
    sub = next((a.choices[command] for a in parser._actions
                if isinstance(a, argparse._SubParsersAction) and command in a.choices), parser)
    options = [o for a in sub._actions for o in a.option_strings if o.startswith("--")]
    flags = [w.split("=", 1)[0] for w in extra if w.startswith("-")]
    hints = []
    for flag in flags:
        close = difflib.get_close_matches(flag, options, n=1, cutoff=0.6)
        hint = _MEANT.get(flag) or (f"did you mean {close[0]}?" if close else None)
        if hint:
            hints.append(hint if len(flags) == 1 else f"{flag}: {hint}")
    sub.print_usage(sys.stderr)
    name = f"wiggly {command}" if command else "wiggly"
    print(f"{name}: error: unrecognized arguments: {' '.join(extra)}"
          + (f" ({'; '.join(hints)})" if hints else "")
          + f"; `{name} --help` lists its options", file=sys.stderr)
    return 2


def _error(message: str) -> None:
    for line in message.splitlines() or [""]:
        print(f"wiggly: error: {line}", file=sys.stderr)
