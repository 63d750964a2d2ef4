"""Every Warp kernel of warp-highlights, one module per concern, each kernel beside its launch wrapper.

Installed as ``warp_highlights.kernels`` (see pyproject.toml).
"""
