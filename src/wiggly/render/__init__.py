"""Offscreen previews of an animated surface: videos, contact sheets, single frames, plots.

Input is plain arrays, as produced by the solver: frame ``times`` (F,), surface vertex
``positions`` (F, n, 3) and triangle ``faces`` (m, 3).  One :class:`Preview` holds one
offscreen pyvista plotter for the whole animation; every frame only updates the mesh in place
(points, per-vertex normals and colors, the contact shadow, the labels) and re-renders, so a
frame costs one draw and one read-back.  :func:`render_video` writes MP4 (H.264, yuv420p,
through the ffmpeg binary shipped in the ``imageio-ffmpeg`` wheel) or GIF (Pillow, one global
palette, loops forever), :func:`render_contact_sheet` a PNG grid of frames,
:func:`render_frame` one image as an array, and :func:`plot_diagnostics` a matplotlib (Agg)
figure of the modal amplitudes and the keyframe residuals.

Scene
-----
The object is drawn with smooth (Phong) shading of area-weighted vertex normals recomputed every
frame, under soft directional key, fill and rim lights placed relative to the view, plus a faint
bounce from below, with FXAA anti-aliasing (default for stills, optional for videos).  A light
grey checkered ground (checker size 1, 2 or 5 x 10^k m, about half the object's size), fading
into the background, lies at the lowest value of the ``up``-coordinate over all frames; a
soft blob shadow under the object (an elliptical Gaussian fitted to the object's footprint,
darker and sharper when the object is close to the ground) shows contact.  The camera is fixed
for the whole animation and frames the bounding box of all frames, so motion is visible; the
default is a 3/4 perspective view with ``up`` up.  A :class:`Highlight` (a keyframed vertex
group) is blended into the vertex colors over ``window`` seconds (0.25 s) around its key time,
fully at the key time, where its target positions also appear as small spheres.  The time is
printed in the upper left corner, the labels of highlighted groups in the lower left.

Headless rendering
------------------
The VTK wheels (9.4 and later) choose the OpenGL window at run time: an X window when a display
is available, otherwise EGL (GPU or Mesa's llvmpipe software rasterizer, no X server needed),
otherwise OSMesa.  On Linux without ``DISPLAY``/``WAYLAND_DISPLAY`` this module sets
``VTK_DEFAULT_OPENGL_WINDOW=vtkEGLRenderWindow`` (unless already set) so VTK goes to EGL
directly instead of first failing to reach an X server.  When no backend works VTK does not
raise but crashes the process (segmentation fault), so before the first plotter of a process
:func:`check_offscreen` renders one pixel in a *subprocess* and raises :class:`RenderingError`
with the fix if that fails.  Fixes, in order of preference:

* install the Mesa EGL libraries (Debian 12: ``apt-get install libegl1 libgl1-mesa-dri``;
  they pull ``libegl-mesa0``, ``libglvnd0``, ``libgbm1``, ``libglapi-mesa`` and ``libllvm15``;
  the EGL path opens no X11 or libGL library);
* or OSMesa: ``apt-get install libosmesa6`` and
  ``VTK_DEFAULT_OPENGL_WINDOW=vtkOSOpenGLRenderWindow``;
* or a virtual X server: ``apt-get install xvfb libgl1 libglx-mesa0 libxcursor1`` and
  ``pyvista.start_xvfb()`` (or run under ``xvfb-run``).

``PYVISTA_OFF_SCREEN=true`` is not needed (plotters here are always created off-screen).  Set
``WIGGLY_RENDER_PROBE=0`` to skip the subprocess probe (saves about a second per process).

Speed: with software rendering (Mesa llvmpipe on 2 shared cores) a 10k-face object at 960x540
renders at about 20-24 frames/s, or 9-13 with FXAA (which is why videos default to no FXAA);
the per-frame numpy work (normals, colors, shadow) is under 3 ms.  Creating a :class:`Preview`
takes about 0.3 s (plus a second for the first VTK import and the probe).  A GPU through EGL
is much faster.

Modules: :mod:`~wiggly.render.setup` (constants, the headless backend and its probe, input
checks), :mod:`~wiggly.render.preview` (:class:`Preview`, the plotter of an animation),
:mod:`~wiggly.render.outputs` (frames, videos, contact sheets, plots).
"""

from wiggly.render.outputs import (
    plot_diagnostics,
    render_contact_sheet,
    render_frame,
    render_video,
    video_frame_times,
)
from wiggly.render.preview import Preview
from wiggly.render.setup import (
    CAMERA_PRESETS,
    GIF_MAX_FPS,
    GIF_MAX_SIDE,
    SHEET_GAP,
    SHEET_HEADER,
    VIDEO_FORMATS,
    Highlight,
    RenderingError,
    check_offscreen,
)
from wiggly.solve.animation import DEFAULT_FPS

__all__ = [
    "CAMERA_PRESETS",
    "DEFAULT_FPS",
    "GIF_MAX_FPS",
    "GIF_MAX_SIDE",
    "SHEET_GAP",
    "SHEET_HEADER",
    "VIDEO_FORMATS",
    "Highlight",
    "Preview",
    "RenderingError",
    "check_offscreen",
    "plot_diagnostics",
    "render_contact_sheet",
    "render_frame",
    "render_video",
    "video_frame_times",
]
