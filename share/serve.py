"""``bbcity serve SITE``: a local look at an exported site over HTTP (Python's http.server).

Any static server serves a site; this one binds a loopback address by default, sends the
MIME types the viewer needs (``.js`` as JavaScript modules, ``.bin`` as bytes, ``.json``) and
keeps no cache, so a re-exported site shows at once.
"""

from __future__ import annotations

import errno
import functools
import http.server
import threading
from pathlib import Path

SITE_FILES = ("index.html", "site.json", "shaders.json", "viewer.js")


class NotASiteError(ValueError):
    """The folder is not a site written by ``bbcity export web``."""


def check_site(site: Path) -> Path:
    """``site`` if it holds a site's files; NotASiteError naming what is missing otherwise."""
    site = Path(site)
    if not site.is_dir():
        raise NotASiteError(f"{site}: not a folder")
    missing = [name for name in SITE_FILES if not (site / name).is_file()]
    if missing:
        raise NotASiteError(f"{site}: not a site of bbcity export web (no {', '.join(missing)})")
    return site


class _Handler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map,
                      ".js": "text/javascript", ".json": "application/json", ".bin": "application/octet-stream"}

    def end_headers(self):
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, format, *args):  # quiet: the CLI prints where to look
        pass


def make_server(site: Path, port: int = 8000, host: str = "127.0.0.1") -> http.server.ThreadingHTTPServer:
    """A server of ``site`` on ``host:port`` (port 0: any free one; ``server.server_port`` tells
    which), not started. A port in use raises OSError(EADDRINUSE) naming it."""
    site = check_site(site)
    handler = functools.partial(_Handler, directory=str(site))
    try:
        return http.server.ThreadingHTTPServer((host, int(port)), handler)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise OSError(errno.EADDRINUSE, f"port {port} on {host} is in use; give another --port") from None
        raise


def serve_in_background(site: Path, port: int = 0, host: str = "127.0.0.1"):
    """Start a server of ``site`` in a daemon thread; returns (server, base URL). Stop it with
    ``server.shutdown(); server.server_close()``."""
    server = make_server(site, port, host)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://{host}:{server.server_port}/"
