"""Synthetic reflectance fields with ground truth: shapes and a ray-traced renderer (Warp BVH).

Imports the model, io and the kernels (ARCHITECTURE.md). The teapot's control points are in ``data/``.

- ``render_dataset``: ray-trace a shape under many lights into a dataset folder, with ground truth.
- ``Renderer``: a mesh on a device; light directions -> full, specular and diffuse images.
- ``RenderSettings``: image size, samples per pixel, field of view, colour, seed.
- ``Material``: Lambertian albedo and ambient plus a Blinn-Phong or GGX lobe, uniform or in tiles of two.
- ``RenderedImages``: one light chunk's full, specular and diffuse images.
- ``default_material``: the built-in material of each synthetic shape.
- ``make_shape``: a built-in shape by name (donut, teapot, sphere, coin, bumpy) or a mesh file by path.
- ``TriangleMesh``: an indexed triangle mesh with outward winding and smooth vertex normals.
- ``load_mesh``: read any mesh file pyvista reads (PLY, OBJ, STL, ...).
- ``SHAPE_NAMES``: the built-in shapes.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        **dict.fromkeys(["render_dataset", "Renderer", "RenderSettings", "Material", "RenderedImages",
                         "default_material"], "render"),
        **dict.fromkeys(["make_shape", "TriangleMesh", "load_mesh", "SHAPE_NAMES"], "shapes"),
    },
)
