"""Size bounds shared by every entry point (scene files, the Python API, the CLI, the editor).

A typo such as ``resolution = 100000`` (for 14) or ``end = 1e6`` must be refused with a clear
message before any memory is spent, and every entry point must refuse the same values.  These
are the one definition of those bounds; validators read them from here and name them in
their messages.
"""

from __future__ import annotations

import math

# Tet resolution (target tet edges along the bounding-box diagonal).  The tet count grows
# with its cube; bodies are also refused by their estimated tet count (MAX_TETS).
MAX_RESOLUTION = 200
# At least this many tet edges along the diagonal: with coarser targets fTetWild cannot meet
# its sizing and runs on (a torus at resolution 1: 31 s against 3.6 s at 2; an edge of seven
# diagonals: over 10 minutes and 14 GB).
MIN_RESOLUTION = 2
# Estimated tets of a body before tetrahedralizing (about 2 GB for modes and warp).
MAX_TETS = 400_000
# Eigenmodes per body.
MAX_MODES = 500
# Shot length in seconds and frames sampled for outputs and playback.
MAX_DURATION = 3600.0
MAX_FRAMES = 20_000
MAX_FPS = 1000.0
# Keyframes per shot, and the length of user-supplied names (keyframes, groups).
MAX_KEYFRAMES = 10_000
MAX_NAME_LENGTH = 200
# Shots of one batch (a sweep's grid points x samples, or scene files).
MAX_SHOTS = 100_000

# A span is a whole number of frames when it is within this many frames of one: a cycle that
# short of whole moves its seam by 4 microseconds at 24 fps, and 6-digit durations such as
# 0.333333 s at 24 fps (8 frames less 8e-6) are whole.
WHOLE_FRAMES = 1e-4


def frame_steps(duration: float, fps: float) -> tuple[float, bool]:
    """A span's length in frame steps at ``fps``, and whether that is a whole number (to
    :data:`WHOLE_FRAMES`): a loop's cycle must be, so that its last frame is its first."""
    steps = duration * fps
    return steps, abs(steps - round(steps)) <= WHOLE_FRAMES


def frame_count(duration: float, fps: float) -> int:
    """How many frames sample a span at ``fps``, its start included, and its end when it is
    a whole number of frames (:func:`frame_steps`) away."""
    steps, whole = frame_steps(duration, fps)
    return (round(steps) if whole else math.floor(steps)) + 1


def whole_frames_remedy(duration: float, fps: float) -> str:
    """How to make a span of ``duration`` s at ``fps`` a whole number of frames: the nearest
    whole duration, an fps for it, and whole-number frame rates near ``fps`` that fit, all
    with digits enough to pass :func:`frame_steps` as written."""
    n = max(1, round(duration * fps))
    exact = n / duration
    fits = [k for k in sorted(range(max(1, math.floor(fps) - 12), math.ceil(fps) + 13),
                              key=lambda k: abs(k - fps))
            if k != fps and abs(k - exact) > 1e-9 * k and frame_steps(duration, k)[1]][:2]
    whole = f" (or a whole {' or '.join(map(str, sorted(fits)))} fps)" if fits else ""
    return f"use a duration of {n / fps:.9g} s or fps = {exact:.9g}{whole}"
