"""Export of an animated triangle surface: glTF binary, USD, an OBJ sequence or npz.

The last stage of the pipeline (exporting the motion to animation tools) only
sees plain arrays, a :class:`SurfaceAnimation`: frame times, per-frame vertex positions of the
user's own surface (same vertices, same order, same faces and UVs) and its triangles, plus
optional per-vertex texture coordinates and rest normals.  :func:`write_animation` picks the
format from the file extension (:data:`SUPPORTED`); :func:`read_animation` reads every format
back (tests, and ``wiggly render`` of an exported file).

Formats
-------
``.glb``
    glTF 2.0 binary (pygltflib).  The base mesh is the rest pose (``rest``; frame 0 when it is
    not given): POSITION, NORMAL (the rest normals when given, else the recomputed ones),
    TEXCOORD_0 (when uvs) and uint16/uint32 indices.  Frame k is morph target k (POSITION and
    NORMAL deltas from the base, so the shading follows the deformation), and one animation
    drives the node's ``weights`` with a LINEAR sampler whose keyframe k has weight 1 on target
    k and 0 elsewhere: between frames positions interpolate linearly, and at most two targets
    are active at once.  The mesh's default weights are 0 (a viewer that ignores animations
    shows the rest pose).  Blender imports the base as the ``Basis`` shape key and the targets
    as shape keys (named ``frame_0000``, ...  by ``mesh.extras.targetNames``); three.js plays
    the clip with an ``AnimationMixer``.  **Compact layout** (``gltf_targets="modes"``, linear
    motions): two targets per mode i on the surface, its shape scaled by ``s_i = max |q_i|`` and
    negated, with weights max(+-q_i(t) / s_i, 0) in [0, 1] (Blender clamps shape keys to that
    range): the positions are exactly those of the per-frame layout, at and between frames; the
    NORMAL deltas are the normals' derivatives at rest (first order).  Size about ``2 n r 24 + 2
    F r 4`` bytes instead of ``F n 24``.  All data is float32 and 4-byte aligned; the deltas of
    all frames share one bufferView with ``byteStride`` 12; every POSITION accessor (base and
    targets) has its exact min/max.  glTF puts the texture origin at the top-left corner, so V
    is written as ``1 - v`` (and flipped back on reading): :class:`SurfaceAnimation` uvs follow
    the OBJ/USD convention (origin bottom-left).  glTF forbids negative times: if ``times[0] <
    0`` the clip is shifted to start at 0; with ``frame_start`` frame k is at ``(frame_start +
    k) / fps`` s (Blender puts a key at t s on frame ``t * fps`` of its scene, so at the same
    fps keys land on frames ``frame_start``, ``frame_start + 1``, ...); the exact times in
    seconds are kept in the animation's ``extras.wiggly.times`` (and read back from there),
    and for uniform frames their rate in ``extras.wiggly.frames_per_second`` (glTF itself
    has none: set the importing scene's rate to it, as Blender's importer maps seconds to
    frames at the scene's rate).
    Size is about ``F * n * 24`` bytes (position and normal deltas per frame): 300 frames of 20k
    vertices take 147 MB.
``.usd``, ``.usda``, ``.usdc``
    A ``UsdGeom.Mesh`` ``/<name>/<name>`` under an Xform ``/<name>`` (the default prim, kind
    component; Blender names the imported object ``<name>``) with time-sampled ``points`` and
    ``extent``; ``subdivisionScheme = "none"``;
    ``primvars:st`` (vertex interpolation) from the uvs; time-sampled vertex ``normals`` only
    when the animation has rest normals (otherwise renderers compute smooth normals).  Stage
    metadata: upAxis Y, metersPerUnit 1, start/end time codes.  Time codes: when the frame
    times are uniform (dt equal to 1e-6 relative), ``timeCodesPerSecond = framesPerSecond =
    1 / dt`` (rounded to an integer when within 1e-6 of one) and frame k has time code
    ``times[0] / dt + k`` (``frame_start + k`` with ``frame_start``); otherwise
    ``timeCodesPerSecond = 1000`` and time code = milliseconds.  Reading gives ``time = time
    code / timeCodesPerSecond`` (shifted by the start time and frame kept in the layer's
    ``customLayerData["wiggly"]``).  Blender's importer sets its scene's frame range from the
    time codes but ignores the frame rate: export at the Blender scene's fps.  ``.usd`` is
    written in the binary crate format (usd-core's default).
``.obj``
    An OBJ sequence: ``out/frame.obj`` writes ``out/frame_0000.obj``, ``out/frame_0001.obj``,
    ... (frame index zero-padded to at least 4 digits, more when F > 10000), each with
    ``v``, ``vt`` (when uvs), ``vn`` and ``f a/a/a`` lines (1-based, the same index for
    position, uv and normal; ``f a//a`` without uvs), an ``o <name>`` line and a
    ``# time <seconds>`` comment (read back as the frame time).  Vertex order and faces are
    the input's.  Positions and uvs are written with ``%.9g`` (float32 values come back bit
    for bit), normals with ``%.6g``.  Each frame's text is made by a single C-level ``%``
    over a preformatted block (the uv and face lines are formatted once): 120 frames of 5k
    vertices take about 2 s (106 MB), 300 frames of 20k vertices about 14 s (1.1 GB), on
    two busy cores.  Overwriting a sequence also deletes the frames of an earlier, longer
    sequence with the same name.
``.npz``
    Compressed numpy archive with ``format_version``, ``times`` (float64), ``positions``
    (float32), ``faces`` (int64), ``name`` and optional ``uvs`` and ``normals`` (float32).

Per-frame normals are recomputed from each frame (area-weighted vertex normals).  When the
animation has rest normals (e.g. smooth normals across a UV seam), frame k's normal is the
rest normal rotated by the smallest rotation taking the normal recomputed on the rest pose
(frame 0 when no rest pose is given) to the recomputed frame-k normal, so the rest pose
shows the file's normals exactly.

Every write is all or nothing: data goes to temporary files in the output's directory and
is moved into place only when every file is complete (:class:`wiggly.files.OutputSet`;
:func:`stage_animation` adds an animation to a set shared with other outputs), so a failure
never leaves a partial output, a temporary file, or a replaced one.  An existing output is
an error unless ``overwrite=True``.  Missing parent directories are created.

Modules: :mod:`~wiggly.export.animation` (:class:`SurfaceAnimation`, checks, normals, time
codes), one per format (:mod:`~wiggly.export.gltf`, :mod:`~wiggly.export.usd`,
:mod:`~wiggly.export.obj`, :mod:`~wiggly.export.npz`), and :mod:`~wiggly.export.formats`
(writing and reading by extension).
"""

from wiggly.export.animation import (
    FORMAT_VERSION,
    GLTF_TARGETS,
    SUPPORTED,
    SurfaceAnimation,
    vertex_normals,
)
from wiggly.export.formats import (
    read_animation,
    stage_animation,
    surface_animation,
    write_animation,
)

__all__ = [
    "FORMAT_VERSION",
    "GLTF_TARGETS",
    "SUPPORTED",
    "SurfaceAnimation",
    "read_animation",
    "stage_animation",
    "surface_animation",
    "vertex_normals",
    "write_animation",
]
