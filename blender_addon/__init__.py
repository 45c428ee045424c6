"""Tyndall for Blender: noise-free volumetric light (spots, IES, world fog) and skies.

The package is importable without bpy (``core`` holds the pure-Python helpers); the bpy
modules are imported by :func:`register`.
"""

from __future__ import annotations

from types import ModuleType

_modules: list[ModuleType] = []


def register() -> None:
    """Register the settings, operators and the sidebar panels."""
    import bpy

    from . import operators, panels, props

    props.register()
    for c in (*operators.classes, *panels.classes):
        bpy.utils.register_class(c)
    _modules[:] = [props, operators, panels]


def unregister() -> None:
    """Undo :func:`register`."""
    import bpy

    from . import operators, panels, props

    for c in reversed((*operators.classes, *panels.classes)):
        bpy.utils.unregister_class(c)
    props.unregister()
    _modules.clear()
