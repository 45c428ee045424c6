"""Pure-Python helpers of the Tyndall extension: no ``bpy`` import anywhere in this package.

* :mod:`.conversions` — Blender → Tyndall unit and parameter mappings (lights, volumes, phases, sky).
* :mod:`.scene_build` — plain-data records of what was gathered from Blender and the scene dict built from them.
* :mod:`.jobs` — the background job state machine the modal operators poll.
* :mod:`.files` — atomic writes and a staging folder that is committed all at once or not at all.
"""
