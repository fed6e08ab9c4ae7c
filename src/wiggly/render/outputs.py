"""Previews written to files: frames, MP4 and GIF videos, contact sheets and diagnostic
plots."""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from wiggly.checks import pixel_size
from wiggly.errors import WigglyInputError, warn
from wiggly.files import atomic_file, shown_name
from wiggly.progress import deprecated_progress, frames
from wiggly.render.preview import Preview
from wiggly.render.setup import (
    GIF_MAX_FPS,
    GIF_MAX_SIDE,
    MP4_CRF,
    SHEET_GAP,
    SHEET_HEADER,
    TEXT_COLOR,
    VIDEO_FORMATS,
    Highlight,
    output_path,
    preview_arrays,
)
from wiggly.solve.animation import DEFAULT_FPS

if TYPE_CHECKING:
    from PIL import Image


# ----------------------------------------------------------------------------------------------
# public entry points


def render_frame(times_or_time, positions, faces, *, at: float | None = None,
                 highlights: Sequence[Highlight] = (), size=(960, 540), up=(0.0, 1.0, 0.0),
                 ground: bool = True, camera=None, title: str | None = None,
                 anti_aliasing: bool = True) -> np.ndarray:
    """Render one image of the animation: (height, width, 3) uint8.

    Either a single pose, ``render_frame(time, positions (n, 3), faces)``, or a frame of an
    animation, ``render_frame(times (F,), positions (F, n, 3), faces, at=t)`` (default: the
    first frame).  The camera frames all frames, as in a video of the animation, so images at
    different times are comparable.  Other parameters as in :class:`Preview`.  Builds a new
    plotter per call (about 0.3 s); to render many frames use :class:`Preview` directly.
    """
    times = np.atleast_1d(np.asarray(times_or_time, dtype=np.float64))
    with Preview(times, positions, faces, highlights=highlights, size=size, up=up, ground=ground,
                 camera=camera, title=title, anti_aliasing=anti_aliasing) as preview:
        return preview.render(preview.times[0] if at is None else at)


def video_frame_times(times, fps: float | None = None,
                      max_fps: float | None = None) -> tuple[np.ndarray, float]:
    """Frame times of a video of an animation sampled at ``times``, and its frame rate.

    Without ``fps``, uniformly spaced ``times`` (spacing equal within 1e-6 relative) are used
    as they are, at ``fps = 1 / dt``.  Otherwise (or when that exceeds ``max_fps``) the video
    samples ``t0 + k / fps`` for ``k = 0 .. floor((t_end - t0) fps)``, with ``fps`` the given
    rate (default :data:`DEFAULT_FPS`) capped at ``max_fps``.
    """
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    if times.ndim != 1 or not np.all(np.isfinite(times)) or np.any(np.diff(times) <= 0):
        raise WigglyInputError("times should be a 1-d array, finite and strictly increasing")
    if fps is not None and not (math.isfinite(fps) and fps > 0):
        raise WigglyInputError(f"fps should be a positive number; got {fps}")
    if fps is None and len(times) > 1:
        dt = np.diff(times)
        native = 1.0 / dt.mean()
        if np.ptp(dt) <= 1e-6 * dt.mean() and (max_fps is None or native <= max_fps * (1 + 1e-9)):
            return times.copy(), float(native)
    if len(times) == 1:
        return times.copy(), float(fps or DEFAULT_FPS)
    rate = float(fps or DEFAULT_FPS)
    if max_fps is not None:
        rate = min(rate, max_fps)
    count = math.floor((times[-1] - times[0]) * rate + 1e-9) + 1
    return times[0] + np.arange(count) / rate, rate


def _scene_progress(times, what: str):
    return frames(times, len(times), shown_name(what))


@deprecated_progress
def render_video(path, times, positions, faces, *, highlights: Sequence[Highlight] = (),
                 fps: float | None = None, size=(960, 540), up=(0.0, 1.0, 0.0),
                 ground: bool = True, camera=None, title: str | None = None,
                 anti_aliasing: bool = False, overwrite: bool = False,
                 clock: bool = True) -> Path:
    """Render the animation to an ``.mp4`` or ``.gif`` video; return the path.

    ``anti_aliasing`` (FXAA) is off by default here: with software rendering it halves the
    frame rate (about 10 instead of 20 frames/s for 10k faces at 960x540 on 2 cores).

    Frame times follow :func:`video_frame_times`.  MP4: H.264, yuv420p, constant quality (CRF
    :data:`MP4_CRF`), ``+faststart``; an odd width or height is reduced by one pixel (yuv420p
    needs even sizes).  GIF: frame delays are whole centiseconds, so the rate is
    ``100 / round(100 / fps)`` with fps capped at :data:`GIF_MAX_FPS`; frames are rendered at
    ``size`` and downscaled (Lanczos, which anti-aliases too: no FXAA then) to at most
    :data:`GIF_MAX_SIDE` pixels per side; one 256-color palette for all frames; loops forever.
    Written atomically (temporary file in the same directory, then :func:`os.replace`); an
    existing ``path`` is kept unless ``overwrite``.  Scene parameters as in :class:`Preview`.
    The frames are counted as :mod:`wiggly.progress` says (a bar on a terminal).
    """
    path = output_path(path, VIDEO_FORMATS, overwrite)
    w, h = pixel_size(size)
    gif = path.suffix.lower() == ".gif"
    if gif:
        anti_aliasing = anti_aliasing and GIF_MAX_SIDE / max(w, h) > 0.67
    elif w % 2 or h % 2:
        warn(f"{shown_name(path)}: an H.264 video needs an even width and height: the "
             f"size {w} x {h} is written as {w - w % 2} x {h - h % 2}")
        w, h = w - w % 2, h - h % 2
    with Preview(times, positions, faces, highlights=highlights, size=(w, h), up=up,
                 ground=ground, camera=camera, title=title,
                 anti_aliasing=anti_aliasing, clock=clock) as preview:
        if gif:
            requested = fps if fps is not None else video_frame_times(preview.times)[1]
            delay_cs = max(round(100 / GIF_MAX_FPS), round(100 / requested))
            frame_times, _ = video_frame_times(preview.times, 100 / delay_cs)
        else:
            frame_times, rate = video_frame_times(preview.times, fps)
        frames = _scene_progress(frame_times, path.name)
        with atomic_file(path) as tmp:
            if gif:
                _write_gif(tmp, preview, frame_times, frames, delay_cs)
            else:
                _write_mp4(tmp, preview, frames, rate)
    return path


def _write_mp4(tmp: Path, preview: Preview, frames, fps: float) -> None:
    import imageio_ffmpeg

    w, h = preview.size
    writer = imageio_ffmpeg.write_frames(
        str(tmp), (w, h), fps=fps, codec="libx264", pix_fmt_in="rgb24", pix_fmt_out="yuv420p",
        quality=None, macro_block_size=1, ffmpeg_log_level="error",
        output_params=["-crf", str(MP4_CRF), "-preset", "veryfast", "-movflags", "+faststart"])
    writer.send(None)  # start ffmpeg
    try:
        for t in frames:
            writer.send(preview.render(t))
    finally:
        writer.close()


def _write_gif(tmp: Path, preview: Preview, frame_times: np.ndarray, frames, delay_cs: int) -> None:
    from PIL import Image

    w, h = preview.size
    scale = min(1.0, GIF_MAX_SIDE / max(w, h))
    out_size = (max(1, round(w * scale)), max(1, round(h * scale)))

    def image(t: float) -> Image.Image:
        im = Image.fromarray(preview.render(t))
        return im if out_size == (w, h) else im.resize(out_size, Image.Resampling.LANCZOS)

    # one palette for all frames, from a few samples including the highlighted key times
    t0, t1 = frame_times[0], frame_times[-1]
    samples = list(np.linspace(t0, t1, 5)) + [hl.time for hl in preview.highlights
                                             if t0 <= hl.time <= t1]
    palette = _gif_palette([image(t) for t in samples])

    def quantized() -> Iterator[Image.Image]:
        for t in frames:
            yield image(t).quantize(palette=palette, dither=Image.Dither.NONE)

    it = quantized()
    first = next(it)
    # Pillow stores each frame cropped to where it differs from the previous one
    first.save(tmp, format="GIF", save_all=True, append_images=it, duration=10 * delay_cs, loop=0)


def _gif_palette(images) -> Image.Image:
    """A 256-color palette image: median cut of the *distinct* colors of ``images``.

    Median cut of all pixels spends the palette on the large smooth background and leaves
    the object (and the few highlight-colored pixels) banded or grey; cutting the set of
    distinct colors gives every region colors in proportion to its tonal range instead.
    """
    from PIL import Image

    distinct = np.unique(np.concatenate([np.asarray(im).reshape(-1, 3) for im in images]), axis=0)
    return Image.fromarray(distinct[None]).quantize(256, method=Image.Quantize.MEDIANCUT)


@deprecated_progress
def render_contact_sheet(path, times, positions, faces, *, n_frames: int = 8, columns: int = 4,
                         at: Sequence[float] | None = None,
                         highlights: Sequence[Highlight] = (), tile_size=(480, 270),
                         up=(0.0, 1.0, 0.0), ground: bool = True, camera=None,
                         title: str | None = None, anti_aliasing: bool = True,
                         overwrite: bool = False, clock: bool = True) -> Path:
    """A PNG grid of frames (each with its time label, unless ``clock`` is False), row by
    row; return the path.

    The frames are at ``n_frames`` (at most the animation's own count) evenly spaced times
    from the first to the last (or at the times ``at``, e.g. the key times).  With ``N``
    frames, ``c = min(columns, N)`` columns and ``rows = ceil(N / c)``, the image is
    ``c * tile_w + (c + 1) * SHEET_GAP`` pixels wide and ``rows * tile_h + (rows + 1) *
    SHEET_GAP`` (plus :data:`SHEET_HEADER` with a ``title``) high.  Written atomically; an
    existing ``path`` is kept unless ``overwrite``.
    """
    path = output_path(path, (".png",), overwrite)
    tw, th = pixel_size(tile_size, "tile_size")
    times, positions, faces = preview_arrays(times, positions, faces)
    if at is None:
        if not (isinstance(n_frames, int | np.integer) and n_frames >= 1):
            raise WigglyInputError(f"n_frames should be an integer >= 1; got {n_frames!r}")
        # no more tiles than the animation has frames (one frame: one tile, not 8 copies)
        sheet_times = np.linspace(times[0], times[-1], min(n_frames, len(times)))
    else:
        sheet_times = np.atleast_1d(np.asarray(at, dtype=np.float64))
        if sheet_times.ndim != 1 or len(sheet_times) == 0 or not np.all(np.isfinite(sheet_times)):
            raise WigglyInputError(f"at should be a non-empty list of finite times; got {at!r}")
    if not (isinstance(columns, int | np.integer) and columns >= 1):
        raise WigglyInputError(f"columns should be an integer >= 1; got {columns!r}")
    count = len(sheet_times)
    cols = min(columns, count)
    rows = -(-count // cols)
    gap = SHEET_GAP
    header = SHEET_HEADER if title else 0
    sheet = np.full((header + rows * th + (rows + 1) * gap, cols * tw + (cols + 1) * gap, 3), 250,
                    dtype=np.uint8)
    with Preview(times, positions, faces, highlights=highlights, size=(tw, th), up=up,
                 ground=ground, camera=camera, anti_aliasing=anti_aliasing,
                 clock=clock) as preview:
        for k, t in enumerate(_scene_progress(sheet_times, path.name)):
            r, c = divmod(k, cols)
            y, x = header + gap + r * (th + gap), gap + c * (tw + gap)
            sheet[y:y + th, x:x + tw] = preview.render(t)
    from PIL import Image, ImageDraw, ImageFont

    image = Image.fromarray(sheet)
    if title:
        font = ImageFont.load_default(size=round(0.55 * header))
        ImageDraw.Draw(image).text((gap + 4, header / 2 + gap / 2), title, anchor="lm",
                                   fill=tuple(round(255 * c) for c in TEXT_COLOR), font=font)
    with atomic_file(path) as tmp:
        image.save(tmp, format="PNG", optimize=True)
    return path


def plot_diagnostics(path, times, modal, residuals: Sequence[dict], eigenvalues, *,
                     n_rigid: int | None = None, title: str | None = None, max_labeled: int = 8,
                     size=(10.0, 7.5), dpi: int = 110, overwrite: bool = False) -> Path:
    """A PNG of the solve: modal amplitudes over time and keyframe residuals; return the path.

    Three panels over a shared time axis: the rigid modes' amplitudes ``q_i(t)`` (eigenvalue 0,
    the first ``n_rigid``; default: the count of eigenvalues <= ``1e-12 max |lambda|``), the
    elastic modes' amplitudes labeled with their frequency ``sqrt(lambda) / (2 pi)`` (the lowest
    ``max_labeled`` in color, the others thin grey), and per keyframe (``residuals``: dicts with
    ``time``, ``name`` and optional ``position_rms`` (m), ``position_max`` (m), ``velocity_rms``
    (m/s), as from ``Animation.constraint_residuals()``) bars of the RMS position error (mm) and,
    on a second axis, the RMS velocity error (mm/s) at the key times; the maximum position
    error is a dot.  Key times are dashed lines in every panel.  Written atomically.
    """
    path = output_path(path, (".png",), overwrite)
    times = np.atleast_1d(np.asarray(times, dtype=np.float64))
    modal = np.asarray(modal, dtype=np.float64)
    lam = np.atleast_1d(np.asarray(eigenvalues, dtype=np.float64))
    if modal.ndim != 2 or modal.shape[0] != len(times):
        raise WigglyInputError(
            f"modal should have shape (F, r) with F = {len(times)} times; shape is {modal.shape}")
    if lam.shape != (modal.shape[1],):
        raise WigglyInputError(
            f"eigenvalues should have shape ({modal.shape[1]},) (one per mode); shape is "
            f"{lam.shape}")
    if n_rigid is None:
        n_rigid = int(np.sum(np.abs(lam) <= 1e-12 * max(np.max(np.abs(lam)), 1.0)))
    if not 0 <= n_rigid <= len(lam):
        raise WigglyInputError(f"n_rigid should be in 0..{len(lam)}; got {n_rigid}")
    for k, row in enumerate(residuals):
        if not isinstance(row, dict) or "time" not in row:
            raise WigglyInputError(
                f"residuals[{k}] should be a dict with a 'time' key; got {row!r}")

    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=dpi, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(3, 1, sharex=True, height_ratios=(1, 1.4, 1))
    ax_rigid, ax_elastic, ax_res = axes
    key_times = [float(row["time"]) for row in residuals]
    for ax in axes:
        for t in key_times:
            ax.axvline(t, color="0.35", lw=0.9, ls=(0, (4, 3)), zorder=1.5)
        ax.grid(True, color="0.92", zorder=0)
        ax.axhline(0, color="0.6", lw=0.6)

    # a free body's rigid modes are the translations, then rotations (M-orthonormalized)
    rigid_names = ["tx", "ty", "tz", "rot 1", "rot 2", "rot 3"] if n_rigid == 6 else None
    for i in range(n_rigid):
        name = rigid_names[i] if rigid_names else f"rigid {i + 1}"
        ax_rigid.plot(times, modal[:, i], lw=1.5, label=name)
    ax_rigid.set_ylabel("rigid modes\nq (kg$^{1/2}$ m)")
    if n_rigid:
        ax_rigid.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize="small",
                        frameon=False)
    else:
        ax_rigid.text(0.5, 0.5, "no rigid modes (the body is fixed)", transform=ax_rigid.transAxes,
                      ha="center", va="center", color="0.4")

    freq = np.sqrt(np.maximum(lam, 0)) / (2 * np.pi)
    cmap = __import__("matplotlib").colormaps["viridis"]
    n_el = len(lam) - n_rigid
    for j, i in enumerate(range(n_rigid, len(lam))):
        if j < max_labeled:
            ax_elastic.plot(times, modal[:, i], lw=1.4, color=cmap(j / max(1, min(n_el,
                            max_labeled) - 1) * 0.9), label=f"mode {i + 1}: {freq[i]:.3g} Hz")
        else:
            ax_elastic.plot(times, modal[:, i], lw=0.7, color="0.7",
                            label=f"modes {max_labeled + n_rigid + 1}..{len(lam)}"
                            if j == max_labeled else None)
    ax_elastic.set_ylabel("elastic modes\nq (kg$^{1/2}$ m)")
    if n_el:
        ax_elastic.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize="small",
                          frameon=False)

    span = float(times[-1] - times[0]) if len(times) > 1 else 1.0
    width = 0.012 * span
    pos = [(row["time"], 1e3 * row["position_rms"], 1e3 * row.get("position_max", np.nan))
           for row in residuals if row.get("position_rms") is not None]
    vel = [(row["time"], 1e3 * row["velocity_rms"]) for row in residuals
           if row.get("velocity_rms") is not None]
    if pos:
        t, rms, mx = map(np.asarray, zip(*pos, strict=True))
        ax_res.bar(t - width / 2, rms, width, color="#d95f02", label="position RMS")
        ax_res.plot(t - width / 2, mx, "o", ms=4, color="#7f2704", label="position max")
    ax_res.set_ylabel("position error (mm)")
    ax_res.set_ylim(bottom=0)
    ax_vel = ax_res.twinx()
    if vel:
        t, rms = map(np.asarray, zip(*vel, strict=True))
        ax_vel.bar(t + width / 2, rms, width, color="#1b9e77", hatch="//", edgecolor="white",
                   label="velocity RMS")
    ax_vel.set_ylabel("velocity error (mm/s)")
    ax_vel.set_ylim(bottom=0)
    handles = ax_res.get_legend_handles_labels()
    handles2 = ax_vel.get_legend_handles_labels()
    if handles[0] or handles2[0]:
        ax_res.legend(handles[0] + handles2[0], handles[1] + handles2[1], loc="upper left",
                      fontsize="small", frameon=False, ncols=3)
    else:
        ax_res.text(0.5, 0.5, "no keyframes", transform=ax_res.transAxes, ha="center",
                    va="center", color="0.4")
    for ax in (ax_res, ax_vel):  # headroom for the legend
        top = ax.get_ylim()[1]
        ax.set_ylim(0, 1.35 * top)
    ax_res.set_xlabel("time (s)")
    if len(times) > 1:
        ax_res.set_xlim(times[0], times[-1])
    if residuals:  # keyframe names on top, over their dashed lines through all panels
        names = ax_rigid.secondary_xaxis("top")
        names.set_xticks(key_times, [str(row.get("name", "")) for row in residuals],
                         fontsize="small", color="0.25")
        names.tick_params(length=3)
    if title:
        fig.suptitle(title)
    with atomic_file(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
