"""Scene settings of the Tyndall panels (``scene.tyndall``)."""

from __future__ import annotations

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty, PointerProperty, StringProperty


def _is_sun(_self: bpy.types.PropertyGroup, obj: bpy.types.Object) -> bool:
    return obj.type == "LIGHT" and obj.data.type == "SUN"


class TyndallSettings(bpy.types.PropertyGroup):
    """Settings of the Tyndall sidebar tab."""

    directory: StringProperty(  # type: ignore[valid-type]
        name="Output Folder",
        description="Folder for stage/scene, volumetrics.exr, sky.exr and report.json (// = next to the .blend)",
        subtype="DIR_PATH",
        default="//tyndall/",
    )
    tolerance: FloatProperty(  # type: ignore[valid-type]
        name="Tolerance",
        description=(
            "Relative error tolerance. The default 1e-3 keeps the error below a quarter of an 8-bit display "
            "step (1/255). The pixel filter at beam and shadow edges sets the run time below it "
            "(a 640x360 stage on 2 cores: 2.5 s at 1e-2, 8 s at 1e-3, 46 s at 1e-4); 1e-2 for quick previews, "
            "1e-4 or less for references"
        ),
        default=1e-3,
        min=1e-12,
        max=0.5,
        precision=6,
    )
    threads: IntProperty(name="Threads", description="Worker threads (0 = all cores)", default=0, min=0, max=4096)  # type: ignore[valid-type]
    resolution_scale: FloatProperty(  # type: ignore[valid-type]
        name="Resolution Scale",
        description="Factor on the render resolution (after its percentage)",
        default=1.0,
        min=0.01,
        max=4.0,
    )
    include_sun: BoolProperty(  # type: ignore[valid-type]
        name="Sun Lamps in Volume",
        description="Let sun lamps light the medium (Cycles extinguishes a sun behind an infinite world volume)",
        default=False,
    )
    apply_results: BoolProperty(  # type: ignore[valid-type]
        name="Apply Results",
        description="After computing, set up the compositor / world / sun from the results",
        default=True,
    )
    use_lightgroups: BoolProperty(  # type: ignore[valid-type]
        name="Light Groups",
        description="One Cycles light group per light, so each light's surface contribution can be attenuated",
        default=True,
    )
    mute_world_volume: BoolProperty(  # type: ignore[valid-type]
        name="Mute World Volume",
        description=(
            "Render surfaces without the world volume and the exported fog boxes' volumes (the links are "
            "muted, not removed): the compositor adds Tyndall's transmittance and in-scatter, so Cycles must "
            "not render the haze as well"
        ),
        default=True,
    )
    # sky
    sky_use_sun_lamp: BoolProperty(  # type: ignore[valid-type]
        name="From Sun Lamp", description="Take the sun direction from a sun lamp", default=True
    )
    sky_sun_object: PointerProperty(type=bpy.types.Object, name="Sun Lamp", poll=_is_sun)  # type: ignore[valid-type]
    sky_elevation: FloatProperty(name="Sun Elevation", default=30.0, min=-90.0, max=90.0, subtype="NONE")  # type: ignore[valid-type]
    sky_rotation: FloatProperty(name="Sun Rotation", default=0.0, min=-360.0, max=360.0)  # type: ignore[valid-type]
    sky_air: FloatProperty(name="Air", default=1.0, min=0.0, max=10.0)  # type: ignore[valid-type]
    sky_aerosol: FloatProperty(name="Aerosol (Haze)", default=1.0, min=0.0, max=10.0)  # type: ignore[valid-type]
    sky_ozone: FloatProperty(name="Ozone", default=1.0, min=0.0, max=10.0)  # type: ignore[valid-type]
    sky_altitude: FloatProperty(name="Altitude", default=0.0, min=0.0, max=60000.0, unit="LENGTH")  # type: ignore[valid-type]
    sky_width: IntProperty(
        name="Width", description="Texture width in px (height is half)", default=1024, min=8, max=16384
    )  # type: ignore[valid-type]
    sky_sun_disc: BoolProperty(name="Sun Disc", default=True)  # type: ignore[valid-type]
    sky_multiple_scattering: BoolProperty(  # type: ignore[valid-type]
        name="Multiple Scattering", description="Approximate second-order term (off by default)", default=False
    )
    sky_update_sun: BoolProperty(  # type: ignore[valid-type]
        name="Update Sun Lamp",
        description="Set the sun lamp's colour, strength and direction from the sky",
        default=True,
    )


classes: tuple[type, ...] = (TyndallSettings,)


def register() -> None:
    for c in classes:
        bpy.utils.register_class(c)
    bpy.types.Scene.tyndall = PointerProperty(type=TyndallSettings)


def unregister() -> None:
    del bpy.types.Scene.tyndall
    for c in reversed(classes):
        bpy.utils.unregister_class(c)
