"""Looking at fields and their results: the pyvista designer and drawing kit, plots, animations, sheets.

Imports the model, io and relight (to draw relit images), never fit or the command line
(ARCHITECTURE.md). pyvista and matplotlib are imported on first use.

- ``LightDesigner``: the ``view`` window: light sphere, relit image and Gaussian paths; drag the light.
- ``viz``: the pyvista pieces the designer is made of (triangulation, paths, ellipses, image plane).
- ``plots``: the evaluation report's matplotlib figures, written as PNG files.
- ``orbit``: light directions on a circle of constant elevation (a looping animation).
- ``great_circle``: light directions along the shorter great-circle arc between two directions.
- ``through_directions``: light directions along great-circle arcs through a list of directions.
- ``parse_light_path``: a light path from its command-line form (``orbit:35``, ``great:...``, a file).
- ``write_animation``: frames -> GIF, WebP, APNG, MP4 or a folder of PNG/EXR frames, atomically.
- ``contact_sheet``: full, specular and diffuse images of some lights of a dataset, side by side.
- ``save_contact_sheet``: the same written to a PNG file, atomically.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "LightDesigner": "designer",
        **dict.fromkeys(["orbit", "great_circle", "through_directions", "parse_light_path"], "light_paths"),
        "write_animation": "animation",
        **dict.fromkeys(["contact_sheet", "save_contact_sheet"], "preview"),
    },
    modules={"viz": "viz", "plots": "plots"},
)
