"""``serve`` against a real server on 127.0.0.1: only regular files inside its folder, no listings, nothing blocks
on a FIFO, and a client that goes away is no traceback."""

from __future__ import annotations

import contextlib
import os
import socket
import struct
import threading
import time
import urllib.error
import urllib.request

import pytest

from warp_highlights.web.serve import make_server


@pytest.fixture()
def site(tmp_path):
    """A served folder: index.html, manifest.json, a 16 MB file, a FIFO, links in and out, folders with and without
    an index; yields (base URL, server)."""
    folder = tmp_path / "site"
    folder.mkdir()
    (folder / "index.html").write_text("<p>viewer</p>")
    (folder / "manifest.json").write_text("{}")
    (folder / "big.bin").write_bytes(os.urandom(16 * 1024 * 1024))
    os.mkfifo(folder / "pipe.bin")
    (tmp_path / "secret.txt").write_text("outside")
    (folder / "out.txt").symlink_to(tmp_path / "secret.txt")
    (folder / "in.json").symlink_to(folder / "manifest.json")
    (folder / "zero.bin").symlink_to("/dev/zero")
    (folder / "bare").mkdir()
    (folder / "bare" / "a.json").write_text("{}")
    (folder / "page").mkdir()
    (folder / "page" / "index.html").write_text("<p>page</p>")
    (folder / "elsewhere").symlink_to(tmp_path, target_is_directory=True)
    server = make_server(folder, 0)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield f"http://127.0.0.1:{server.server_address[1]}", server
    finally:
        server.shutdown()
        server.server_close()


def _status(url: str) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=10) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as error:
        return error.code, b""


SERVED = {"/index.html": b"<p>viewer</p>", "/": b"<p>viewer</p>", "/in.json": b"{}", "/page/": b"<p>page</p>",
          "/bare/a.json": b"{}"}
"""Paths the site serves, with their bodies."""
REFUSED = ("/bare/", "/out.txt", "/elsewhere/secret.txt", "/elsewhere/", "/pipe.bin", "/zero.bin", "/../secret.txt")
"""Paths answered 404: a folder without an index, links out of the folder, a FIFO, a device, a path above it."""


@pytest.mark.parametrize(("path", "status", "body"),
                         [(path, 200, body) for path, body in SERVED.items()] + [(path, 404, b"") for path in REFUSED])
def test_only_regular_files_inside_the_folder_are_served(site, path, status, body):
    base, _ = site
    started = time.monotonic()
    assert _status(base + path) == (status, body)
    assert time.monotonic() - started < 5  # a FIFO is never opened: nothing waits for a writer


def test_a_fifo_request_leaves_no_thread_blocked(site):
    base, _ = site
    before = threading.active_count()
    for _ in range(3):
        assert _status(base + "/pipe.bin")[0] == 404
    deadline = time.monotonic() + 5
    while threading.active_count() > before and time.monotonic() < deadline:
        time.sleep(0.05)
    assert threading.active_count() <= before


def test_a_client_that_goes_away_mid_download_is_no_traceback(site, capfd):
    base, server = site
    port = server.server_address[1]
    for _ in range(3):
        client = socket.create_connection(("127.0.0.1", port), timeout=10)
        client.sendall(b"GET /big.bin HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        assert client.recv(1024).startswith(b"HTTP/1.0 200")
        client.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))  # a reset, not a goodbye
        client.close()
    time.sleep(1.0)  # the handler threads meet the reset while they write
    assert _status(base + "/index.html")[0] == 200  # still serving
    with contextlib.suppress(Exception):
        server.shutdown()
    err = capfd.readouterr().err
    assert "Traceback" not in err and "ConnectionResetError" not in err and "BrokenPipeError" not in err, err
