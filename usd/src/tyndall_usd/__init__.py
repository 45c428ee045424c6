"""tyndall_usd: USD stages ⇄ Tyndall scenes, with ``pxr`` from ``usd-core`` (never ``bpy``).

>>> from tyndall_usd import convert_stage
>>> conv = convert_stage("shot.usda")          # doctest: +SKIP
>>> conv.scene["lights"][0]["type"], conv.skipped   # doctest: +SKIP
('spot', [{'prim': '/root/Area/Area', 'reason': 'RectLight is not supported ...'}])

``convert_stage`` reads what Blender 5.0's USD exporter writes (SphereLight + ShapingAPI,
DistantLight, DomeLight, Mesh, Camera, xform ops, metersPerUnit, upAxis) plus the
documented ``tyndall:*`` attributes (medium, IES strength, sky, output settings; see
usd/README.md). ``write_results_layer`` writes the sky DomeLight, the sun DistantLight
and the result images back as a USD layer; ``write_stage`` writes a scene as a USD stage
in Blender's conventions (the inverse of ``convert_stage``).
"""

from __future__ import annotations

from .reader import Conversion, SkySettings, UsdSceneError, convert_stage, open_stage
from .stage_writer import write_stage
from .writer import RESULT_ASSETS, read_results_layer, write_results_layer

__version__ = "0.1.0"

__all__ = [
    "RESULT_ASSETS",
    "Conversion",
    "SkySettings",
    "UsdSceneError",
    "__version__",
    "convert_stage",
    "open_stage",
    "read_results_layer",
    "write_results_layer",
    "write_stage",
]
