"""``bbcity serve SITE``: a local look at an exported site over HTTP (Python's http.server).

Any static server serves a site; this one binds a loopback address by default, sends the
MIME types the viewer needs (``.js`` as JavaScript modules, ``.bin`` as bytes, ``.json``) and
keeps no cache, so a re-exported site shows at once.
"""

from __future__ import annotations

import errno
import functools
import http.server
import socket
import threading
from pathlib import Path

from core.errors import InputError
from core.fileio import DataFormatError, read_json

SITE_FILES = ("index.html", "site.json", "shaders.json", "viewer.js")
SITE_FORMAT = "bbcity-web-site"  # share.web_site.FORMAT (web_site imports render; serving needs none of it)


class NotASiteError(InputError):
    """The folder is not a site written by ``bbcity export web``."""


def check_site(site: Path) -> Path:
    """``site`` if it holds a site's files; NotASiteError naming what is missing otherwise."""
    site = Path(site)
    if not site.is_dir():
        raise NotASiteError(f"{site}: not a folder")
    missing = [name for name in SITE_FILES if not (site / name).is_file()]
    if missing:
        raise NotASiteError(f"{site}: not a site of bbcity export web (no {', '.join(missing)})")
    doc = read_json(site / "site.json")
    if not isinstance(doc, dict) or doc.get("format") != SITE_FORMAT or not isinstance(doc.get("tiles"), list):
        raise DataFormatError(site / "site.json", f"not a site's manifest (expected \"format\": \"{SITE_FORMAT}\" "
                                                  "and its tiles)")
    absent = [t.get("dir") for t in doc["tiles"] if not isinstance(t, dict) or not isinstance(t.get("dir"), str)
              or not (site / t["dir"] / "model.json").is_file()]
    if absent:
        raise DataFormatError(site / "site.json", f"{len(absent)} tile folder(s) without model.json, e.g. {absent[0]}")
    return site


class _Handler(http.server.SimpleHTTPRequestHandler):
    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map,
                      ".js": "text/javascript", ".json": "application/json", ".bin": "application/octet-stream"}

    def end_headers(self):
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, format, *args):  # quiet: the CLI prints where to look
        pass


class _Server6(http.server.ThreadingHTTPServer):
    address_family = socket.AF_INET6


def make_server(site: Path, port: int = 8000, host: str = "127.0.0.1") -> http.server.ThreadingHTTPServer:
    """A server of ``site`` on ``host:port`` (an IPv4 or IPv6 address or a name; port 0: any free
    one, ``server.server_port`` tells which), not started. An empty host (every interface) must be
    asked for as 0.0.0.0 or ::. A port in use or a host this machine cannot listen on raises
    OSError naming the option."""
    site = check_site(site)
    if not host.strip():
        raise InputError("--host is empty: give 127.0.0.1 (this machine), or 0.0.0.0 / :: (every interface)")
    handler = functools.partial(_Handler, directory=str(site))
    try:
        server = _Server6 if ":" in host else http.server.ThreadingHTTPServer
        return server((host, int(port)), handler)
    except OSError as e:
        if e.errno == errno.EADDRINUSE:
            raise OSError(errno.EADDRINUSE, f"port {port} on {host} is in use; give another --port") from None
        raise OSError(e.errno, f"--host {host}: cannot listen there ({e.strerror or e})") from None


def serve_in_background(site: Path, port: int = 0, host: str = "127.0.0.1"):
    """Start a server of ``site`` in a daemon thread; returns (server, base URL). Stop it with
    ``server.shutdown(); server.server_close()``."""
    server = make_server(site, port, host)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, site_url(host, server.server_port)


def site_url(host: str, port: int) -> str:
    """The address of a server on ``host:port`` (an IPv6 address in brackets)."""
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"
