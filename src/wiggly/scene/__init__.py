"""Scene files: one shot (body, material, sparse keyframes, outputs) as TOML.

The format is specified in ``docs/scene-format.md``.  The package reads it, checks it
completely before anything is computed, writes it back (an exact round trip) and runs it:

    scene file -> Scene -> mesh, groups -> Body + Keyframes -> solve -> export / render

* :mod:`~wiggly.scene.spec` -- the scene as dataclasses (field names are the TOML keys);
* :mod:`~wiggly.scene.validation` -- the checking framework: one description per key drives
  the validator (messages name the file, key and value) and the JSON Schema;
* :mod:`~wiggly.scene.schema` -- the format's description, :func:`load_scene`,
  :func:`scene_from_dict` (structure first, then references between keys);
* :mod:`~wiggly.scene.toml` -- :func:`scene_to_dict`, :func:`save_scene`;
* :mod:`~wiggly.scene.groups` -- named vertex groups resolved against the mesh;
* :mod:`~wiggly.scene.build` -- :func:`build`: mesh, groups, body and keyframes, the one path
  the CLI and the editor take;
* :mod:`~wiggly.scene.run` -- :func:`run`: outputs checked first, the solve, outputs written
  all or nothing.

Checks that need the mesh (a group selects vertices, absolute targets have one row per
vertex) run right after the mesh is read and before it is tetrahedralized.
"""

from wiggly.export import GLTF_TARGETS
from wiggly.mesh import BUILTIN_MODELS
from wiggly.scene.build import body_of, build, fixed_vertices_of, keyframes_of, modes_key
from wiggly.scene.groups import resolve_groups
from wiggly.scene.run import (
    check_outputs,
    keyframe_highlights,
    problem_of,
    render_preview,
    run,
    solve_scene,
    with_overrides,
    write_outputs,
)
from wiggly.scene.schema import load_scene, scene_from_dict, scene_schema
from wiggly.scene.spec import (
    CAMERAS,
    FORMAT,
    GEOMETRY_EXTENSIONS,
    OUTPUT_EXTENSIONS,
    PALETTE,
    PREVIEW_EXTENSIONS,
    Absolute,
    Box,
    DampingSpec,
    FromMesh,
    GroupSpec,
    Indices,
    KeyframeSpec,
    MaterialSpec,
    MeshSpec,
    Nearest,
    Offset,
    OutputSpec,
    Rest,
    Rigid,
    Scene,
    SimulationSpec,
    Sphere,
    TimeSpec,
    builtin_model,
)
from wiggly.scene.toml import save_scene, scene_to_dict, scene_to_toml

__all__ = [
    "BUILTIN_MODELS",
    "CAMERAS",
    "FORMAT",
    "GEOMETRY_EXTENSIONS",
    "GLTF_TARGETS",
    "OUTPUT_EXTENSIONS",
    "PALETTE",
    "PREVIEW_EXTENSIONS",
    "Absolute",
    "Box",
    "DampingSpec",
    "FromMesh",
    "GroupSpec",
    "Indices",
    "KeyframeSpec",
    "MaterialSpec",
    "MeshSpec",
    "Nearest",
    "Offset",
    "OutputSpec",
    "Rest",
    "Rigid",
    "Scene",
    "SimulationSpec",
    "Sphere",
    "TimeSpec",
    "body_of",
    "build",
    "builtin_model",
    "check_outputs",
    "fixed_vertices_of",
    "keyframe_highlights",
    "keyframes_of",
    "load_scene",
    "modes_key",
    "problem_of",
    "render_preview",
    "resolve_groups",
    "run",
    "save_scene",
    "scene_from_dict",
    "scene_schema",
    "scene_to_dict",
    "scene_to_toml",
    "solve_scene",
    "with_overrides",
    "write_outputs",
]
