"""Draw docs/architecture.png: the pipeline's stages, their modules and the data between them.

Run: ``.venv/bin/python scripts/make_architecture_diagram.py`` (matplotlib, Agg).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.patches import FancyArrowPatch, FancyBboxPatch

STAGES = [  # (x, y, title, module, paper)
    (0.8, 6.0, "mesh", "wiggly.mesh", "§1: surface, tets, embedding"),
    (3.6, 6.0, "fem", "wiggly.fem", "§2: M, K, gravity"),
    (6.4, 6.0, "modes", "wiggly.modes", "§3: K phi = lambda M phi"),
    (9.2, 6.0, "body", "wiggly.body", "prepared body (frozen)"),
    (0.8, 3.6, "keyframes / drive", "wiggly.keyframes, .drive", "§4: partial keyframes"),
    (3.6, 3.6, "splines", "wiggly.splines", "§4-5: wiggly basis, energy"),
    (6.4, 3.6, "solve", "wiggly.solve", "Thm 1 & 2: linear, Newton"),
    (9.2, 3.6, "warp", "wiggly.warp", "§6: W, DW, D^2W, levels"),
    (0.8, 1.2, "scene", "wiggly.scene", "scene files, build, run"),
    (3.6, 1.2, "export", "wiggly.export", "glTF, USD, OBJ, npz"),
    (6.4, 1.2, "render", "wiggly.render", "previews"),
    (9.2, 1.2, "cli / editor / batch", "wiggly.cli, .editor, .batch",
     "command line, browser, sweeps"),
]
ARROWS = [  # (from, to, label, curvature[, label position])
    ("mesh", "fem", "TetMesh", 0.0), ("fem", "modes", "M, K", 0.0),
    ("modes", "body", "Modes", 0.0), ("body", "warp", "tets, masses", 0.0),
    ("body", "solve", "Body", 0.0), ("splines", "solve", "energy forms", 0.0),
    ("keyframes / drive", "solve", "Keyframes", -0.35, (3.95, 4.85)),
    ("warp", "solve", "WarpLevel", 0.0),
    ("scene", "keyframes / drive", "groups", 0.0),
    ("scene", "solve", "Body, Keyframes", 0.25, (2.5, 1.85)),
    ("solve", "export", "positions", 0.0), ("solve", "render", "positions", 0.0),
    ("solve", "cli / editor / batch", "Animation", 0.0),
]


def main() -> None:
    fig, ax = plt.subplots(figsize=(12.5, 7.5))
    ax.set_xlim(0, 11.6)
    ax.set_ylim(0.2, 7.2)
    ax.axis("off")
    where = {}
    for x, y, title, module, paper in STAGES:
        box = FancyBboxPatch((x - 0.75, y - 0.55), 2.2, 1.1, boxstyle="round,pad=0.05",
                             fc="#eef3fa", ec="#33557f", lw=1.4)
        ax.add_patch(box)
        ax.text(x + 0.35, y + 0.25, title, ha="center", va="center", fontsize=13,
                weight="bold", color="#1c2f4a")
        ax.text(x + 0.35, y - 0.05, module, ha="center", va="center", fontsize=9,
                family="monospace", color="#33557f")
        ax.text(x + 0.35, y - 0.32, paper, ha="center", va="center", fontsize=8.5,
                color="#444444")
        where[title] = (x + 0.35, y)
    for a, b, label, rad, *at in ARROWS:
        (x0, y0), (x1, y1) = where[a], where[b]
        arrow = FancyArrowPatch((x0, y0), (x1, y1), arrowstyle="-|>", mutation_scale=14,
                                lw=1.1, color="#7a8aa0", shrinkA=45, shrinkB=45,
                                connectionstyle=f"arc3,rad={rad}")
        ax.add_patch(arrow)
        mx, my = at[0] if at else ((x0 + x1) / 2, (y0 + y1) / 2 + 0.12)
        ax.text(mx, my, label,
                ha="center", fontsize=8, color="#555555", style="italic",
                bbox={"fc": "white", "ec": "none", "alpha": 0.8, "pad": 1})
    ax.set_title("wiggly: stages, their modules, the paper's sections and the data between them",
                 fontsize=13)
    out = Path(__file__).resolve().parent.parent / "docs" / "architecture.png"
    fig.savefig(out, dpi=110, bbox_inches="tight")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
