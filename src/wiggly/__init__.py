"""wiggly: animate elastic 3D objects from sparse spacetime keyframes.

An implementation of Schulz, von Tycowicz, Seidel & Hildebrandt, "Animating deformable objects
using sparse spacetime constraints" (SIGGRAPH 2014).  The pipeline, one module per stage:

    mesh -> fem -> modes -> splines -> keyframes / solve (<- warp) -> export / render / cli

Typical use::

    import wiggly
    body = wiggly.prepare("critter.obj", n_modes=40)            # tets, M, K, eigenmodes
    feet = body.surface.vertices[:, 1] < 0.05
    keys = [wiggly.Keyframe.rest(body, 0.0, feet, still=True),
            wiggly.Keyframe.offset(body, 0.6, feet, (0, 0.3, 0))]
    anim = wiggly.solve(body, keys, duration=2.0)                # warped by default
    frames = anim.positions(anim.frame_times(30))                # (F, n, 3) on your surface
"""

from wiggly.body import Body, Damping, fixed_from_surface, prepare
from wiggly.errors import WigglyInputError
from wiggly.fem import Material
from wiggly.keyframes import Keyframe
from wiggly.mesh import Model, Surface, TetMesh, load_mesh, load_model, tetrahedralize
from wiggly.modes import Modes, compute_modes
from wiggly.solve import Animation, SolveOptions, SpacetimeProblem, WarpedSolveWarning, solve
from wiggly.splines import energy_form, wiggly_basis
from wiggly.warp import Warp

__version__ = "0.1.0"

__all__ = [
    "Animation", "Body", "Damping", "Keyframe", "Material", "Model", "Modes", "SolveOptions",
    "SpacetimeProblem", "Surface", "TetMesh", "Warp", "WarpedSolveWarning", "WigglyInputError",
    "__version__", "compute_modes", "energy_form", "fixed_from_surface", "load_mesh",
    "load_model", "prepare", "solve", "tetrahedralize", "wiggly_basis",
]
