"""Size bounds shared by every entry point (scene files, the Python API, the CLI, the editor).

A typo such as ``resolution = 100000`` (for 14) or ``end = 1e6`` must be refused with a clear
message before any memory is spent, and every entry point must refuse the same values.  These
are the one definition of those bounds; validators read them from here and name them in
their messages.
"""

from __future__ import annotations

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
