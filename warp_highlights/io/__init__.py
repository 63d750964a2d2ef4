"""Files in and out: light files, images, dataset folders, resampling, the highlight field's file, and
the atomic writing every output goes through.

Imports the model only (ARCHITECTURE.md).

- ``read_lp``: read an RTI ``.lp`` light file into a ``LightSet``.
- ``read_lights``: read any light file (``.lp``, relight's ``.dome`` or ``.relight``) into a ``LightSet``.
- ``write_lp``: write a ``LightSet`` as an ``.lp`` file, atomically.
- ``read_image``: one EXR (linear), PNG or JPEG (sRGB, decoded to linear) file as float32.
- ``write_image``: the same formats out, atomically; refuses non-finite images.
- ``image_size``: an image file's size from its header, without decoding it.
- ``image_shape``: the array shape ``read_image`` would return, from the header alone.
- ``DEFAULT_MAX_PIXELS``: the largest image the readers decode unless told otherwise (160 megapixels).
- ``IMAGE_EXTENSIONS``: the file endings ``read_image`` and ``write_image`` take.
- ``srgb_to_linear``: sRGB-encoded values in [0, 1] -> linear radiance.
- ``linear_to_srgb``: linear radiance -> sRGB-encoded values in [0, 1].
- ``display_rgb8``: linear radiance -> 8-bit sRGB RGB for showing or PNG.
- ``ReflectanceField``: a dataset in memory: images per light, lights, held-out ground truth, mask.
- ``DatasetWriter``: writes a dataset folder chunk by chunk (the renderer's output).
- ``resize_stack``: area-resample a stack of images to a working size.
- ``resample_image``: resample one image: area average where it shrinks, linear where it grows.
- ``working_size``: the working (width, height) for a requested size, checked against the images.
- ``save_field``: write a ``HighlightField`` to one file, atomically; returns the bytes written.
- ``load_field``: read a field file (this or an earlier format version), checking every part.
- ``field_size_report``: compressed bytes per part of a field's file.
- ``FORMAT_VERSION``: the field-file format version ``save_field`` writes.
- ``MAGIC``: the string that marks a field file's header.
- ``atomic_file``: write a file under a temporary name, renamed into place when complete.
- ``atomic_folder``: build a folder beside its target, swapped in when complete; replaces only ours.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        **dict.fromkeys(["read_lp", "read_lights", "write_lp"], "lightfile"),
        **dict.fromkeys(
            [
                "read_image", "write_image", "image_size", "image_shape", "DEFAULT_MAX_PIXELS", "IMAGE_EXTENSIONS",
                "srgb_to_linear", "linear_to_srgb", "display_rgb8"
            ],
            "images",
        ),
        **dict.fromkeys(["ReflectanceField", "DatasetWriter"], "dataset"),
        **dict.fromkeys(["resize_stack", "resample_image", "working_size"], "resample"),
        **dict.fromkeys(["save_field", "load_field", "field_size_report", "FORMAT_VERSION", "MAGIC"], "fieldfile"),
        **dict.fromkeys(["atomic_file", "atomic_folder"], "atomic"),
    },
)
