"""``serve_folder``: an exported viewer, or a collection's gallery with its viewers, over HTTP on 127.0.0.1 only
(browsers refuse ``fetch`` from file://)."""

from __future__ import annotations

import functools
import http.server
from pathlib import Path

from ..model.errors import InputError

__all__ = ["HOST", "make_server"]

HOST = "127.0.0.1"
"""The only address served: the page is never reachable from other hosts."""


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    # not from the system's registry (Windows often maps .js to text/plain, and browsers refuse such a module)
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".js": "text/javascript",
                      ".json": "application/json",
                      ".html": "text/html", ".gz": "application/gzip", ".bin": "application/octet-stream"}

    def log_message(self, format, *args) -> None:  # noqa: A002 (the standard library's name)
        pass


def make_server(folder, port: int = 0) -> http.server.ThreadingHTTPServer:
    """A server of ``folder`` on ``HOST``:``port`` (0: any free port); call ``serve_forever``."""
    folder = Path(folder)
    if (not (folder / "index.html").is_file()
        or not ((folder / "manifest.json").is_file() or (folder / "collection.json").is_file())):
        raise InputError(f"{folder} is not an exported viewer or a collection (no index.html with manifest.json or "
                         f"collection.json); "
                         "make one with warp-highlights export or collection")
    handler = functools.partial(_QuietHandler, directory=str(folder))
    try:
        return http.server.ThreadingHTTPServer((HOST, port), handler)
    except OSError as error:
        raise InputError(f"cannot listen on {HOST}:{port} ({error.strerror or error}); choose another --port") from None
