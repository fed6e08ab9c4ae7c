"""F-curves across Blender versions: 4.2/4.3 keep them on the action, 4.4+ in the channel bag
of the data-block's action slot (5.0 has only that)."""

from __future__ import annotations


def _channelbag(datablock, create: bool = False):
    ad = datablock.animation_data
    if ad is None or ad.action is None:
        return None
    action = ad.action
    if not hasattr(ad, "action_slot"):
        return action  # 4.2/4.3: the action itself holds .fcurves
    from bpy_extras import anim_utils

    if create and ad.action_slot is not None:
        return anim_utils.action_ensure_channelbag_for_slot(action, ad.action_slot)
    if ad.action_slot is None:
        return None
    return anim_utils.action_get_channelbag_for_slot(action, ad.action_slot)


def fcurves_of(datablock) -> list:
    """The F-curves animating ``datablock`` (its assigned action and slot), or []."""
    bag = _channelbag(datablock)
    return list(bag.fcurves) if bag is not None else []


def new_fcurve(datablock, data_path: str, name: str):
    """A new F-curve of ``datablock.<data_path>`` in its action (made, named ``name``, if
    missing)."""
    import bpy

    ad = datablock.animation_data or datablock.animation_data_create()
    if ad.action is None:
        ad.action = bpy.data.actions.new(name)
    if hasattr(ad.action, "fcurve_ensure_for_datablock"):
        return ad.action.fcurve_ensure_for_datablock(datablock, data_path)
    return ad.action.fcurves.new(data_path)


def remove_fcurves(datablock, keep) -> int:
    """Remove the F-curves of ``datablock`` whose data path ``keep(path)`` refuses; their
    count."""
    bag = _channelbag(datablock)
    if bag is None:
        return 0
    gone = [c for c in bag.fcurves if not keep(c.data_path)]
    for c in gone:
        bag.fcurves.remove(c)
    return len(gone)
