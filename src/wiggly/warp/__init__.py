"""Rotation-strain warping (Schulz et al. 2014, Theorem 2; Huang et al. 2011) and its derivatives.

* :class:`Warp` -- the map ``W`` of a tet mesh: ``apply``, ``jvp``, ``vjp``, with the Poisson
  matrix factored once and a :class:`~wiggly.warp.gauge.Gauge` per component;
* :class:`ModalWarp` -- a warp bound to the modes: Jacobians, second derivatives and the
  curvature terms of the warped solve's Newton matrix;
* :class:`WarpLevel` -- the warp of the body's mesh or of a coarser mesh of the same solid,
  with an :class:`IdentityTransfer` or a :class:`CoarseTransfer` between them;
* the per-tet passes run in kernels chosen once per mesh (:mod:`wiggly.warp.kernels`:
  compiled with numba, or vectorized numpy).
"""

from wiggly.warp.gauge import Gauge
from wiggly.warp.map import Warp
from wiggly.warp.modal import ModalWarp
from wiggly.warp.tetmath import rotation_coefficients
from wiggly.warp.transfer import (
    CoarseTransfer,
    IdentityTransfer,
    WarpLevel,
    coarse_level,
    fine_level,
)

__all__ = [
    "CoarseTransfer",
    "Gauge",
    "IdentityTransfer",
    "ModalWarp",
    "Warp",
    "WarpLevel",
    "coarse_level",
    "fine_level",
    "rotation_coefficients",
]
