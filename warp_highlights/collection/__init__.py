"""Collections: hundreds of captures fitted, scored and published on a Dask cluster, one GPU per worker.

The top of the layers beside ``cli`` (ARCHITECTURE.md): each capture runs the ``warp-highlights`` commands in a
child process, so this package imports only ``io`` and ``model`` (and Dask distributed, when it runs).

- ``run``: the whole collection (``warp-highlights collection``); returns a ``CollectionResult``.
- ``CollectionResult``: what ``run`` did: the records, the captures processed, skipped and failed.
- ``visible_gpus``: the GPUs a local cluster would use, as ``CUDA_VISIBLE_DEVICES`` names them.
- ``find_captures``: the capture folders under some paths, uniquely named.
- ``Capture``: one capture: its name, dataset folder and held-out lights.
- ``JobOptions``: what each capture gets (fit options, hold-out, evaluation, export).
- ``process_capture``: one capture into its output folder, without Dask.
- ``CaptureFailed``: a capture's command failed: the step and its one-line message.
- ``write_gallery``: ``index.html`` and ``collection.json`` from the captures' records.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(
    __name__,
    {
        "run": "runner",
        "CollectionResult": "runner",
        "visible_gpus": "runner",
        "find_captures": "captures",
        "Capture": "captures",
        "JobOptions": "job",
        "process_capture": "job",
        "CaptureFailed": "job",
        "write_gallery": "gallery",
    },
)
