"""``bbcity serve``: an exported site served over HTTP for a local look."""

from __future__ import annotations

from pathlib import Path

from ..options import int_range


def add(sub) -> None:
    """The ``serve`` command on the subcommands ``sub``."""
    p = sub.add_parser("serve", help="serve an exported site over HTTP for a local look",
                       description="""Serve SITE (written by bbcity export web) at http://HOST:PORT/ until Ctrl-C. Any
                                      static HTTP server does the same; this one sends no cache headers.""")
    p.add_argument("site", type=Path, help="site folder (bbcity export web)")
    p.add_argument("--port", type=int_range(0, 65535), default=8000, help="TCP port (default 8000; 0: any free one)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    p.set_defaults(func=run)


def run(args) -> int:
    """Serve until Ctrl-C (a stop, not an error: exit code 0)."""
    from share.serve import make_server, site_url

    server = make_server(args.site, args.port, args.host)
    print(f"serving {args.site} at {site_url(args.host, server.server_port)} (Ctrl-C to stop)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:  # the way to stop a server: not an error
        print("stopped")
    finally:
        server.server_close()
    return 0
