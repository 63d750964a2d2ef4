"""warp-highlights: relight reflectance fields with moving specular highlights, built on NVIDIA Warp."""

__version__ = "0.1.0"
