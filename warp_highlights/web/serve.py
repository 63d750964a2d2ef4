"""``serve_folder``: an exported viewer, or a collection's gallery with its viewers, over HTTP on 127.0.0.1 only
(browsers refuse ``fetch`` from file://).

Only regular files inside the folder are served: folders without ``index.html`` (no listings), links that lead
out of the folder, and special files (FIFOs, devices, sockets: never opened) answer 404. A client that goes
away mid-download ends its request quietly.
"""

from __future__ import annotations

import functools
import http.server
import os
import socket
import stat
import sys
from http import HTTPStatus
from pathlib import Path
from urllib.parse import urlsplit

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

    def send_head(self):
        """The file's headers (and the open file), or 404 for anything but a regular file inside the folder."""
        path = self.translate_path(self.path)
        if os.path.isdir(path):
            if not urlsplit(self.path).path.endswith("/"):
                return super().send_head()  # the redirect to the folder's URL with its slash
            path = os.path.join(path, "index.html")
        if not self._servable(path):
            self.send_error(HTTPStatus.NOT_FOUND, "File not found")
            return None
        return super().send_head()

    def list_directory(self, path):
        """No folder listings."""
        self.send_error(HTTPStatus.NOT_FOUND, "File not found")
        return None

    def _servable(self, path: str) -> bool:
        """Whether ``path``, its links followed, is a regular file inside the served folder."""
        root = os.path.realpath(self.directory)
        real = os.path.realpath(path)
        try:
            inside = os.path.commonpath([root, real]) == root
            return inside and stat.S_ISREG(os.stat(real).st_mode)
        except (OSError, ValueError):
            return False


class _QuietServer(http.server.ThreadingHTTPServer):
    """A threading HTTP server that says nothing when a client goes away mid-request."""

    def handle_error(self, request, client_address) -> None:
        if isinstance(sys.exc_info()[1], (ConnectionError, socket.timeout)):
            return  # the client closed the connection (a stopped download, a reloaded page)
        super().handle_error(request, client_address)


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
        return _QuietServer((HOST, port), handler)
    except OSError as error:
        raise InputError(f"cannot listen on {HOST}:{port} ({error.strerror or error}); choose another --port") from None
