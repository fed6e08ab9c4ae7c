"""wiggly in Blender: key vertex groups with Empties, drive them with the object's own
animation, solve with wiggly (Schulz et al. 2014) out of process and bake the result back
as a Mesh Cache (PC2) or shape keys. See docs/blender.md."""

from . import operators, panel, properties

_MODULES = (properties, operators, panel)


def register() -> None:
    for module in _MODULES:
        module.register()


def unregister() -> None:
    for module in reversed(_MODULES):
        module.unregister()
