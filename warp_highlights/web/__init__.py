"""The web viewer: a fitted field exported as a static page that relights it in the browser (WebGL2).

- ``export_viewer``: write index.html, viewer.js, manifest.json and the field's arrays into a folder.
- ``make_server``: an HTTP server of an exported folder on 127.0.0.1 only.
"""

from .._api import lazy_exports

__getattr__, __dir__, __all__ = lazy_exports(__name__, {"export_viewer": "export", "make_server": "serve"})
