#!/usr/bin/env python3
"""A picture of a recording as a user sees it in the Rerun web viewer: serves the .rrd with
`rerun --web-viewer` on 127.0.0.1 and takes a headless-Chromium screenshot of its default
layout (the blueprint the recording carries).

    .venv/bin/python scripts/viewer_screenshot.py recordings/sim-<UTC>.rrd --out layout.png

Needs Debian's `chromium` (apt-get install -y chromium); the viewer then runs on Chromium's
software rasterizer (--disable-gpu). The viewer's WebAssembly takes tens of seconds to load
there, and `chromium --screenshot` shoots at the page's load event: the page it opens holds
the viewer in a frame plus an image that this script's own server answers only after `--wait`
seconds, which holds the load event (and the screenshot) back until the viewer has drawn.
Everything listens on 127.0.0.1 only.
"""

from __future__ import annotations

import argparse
import contextlib
import http.server
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse
import urllib.request
from pathlib import Path

CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
]
PIXEL = bytes.fromhex(
    "89504e470d0a1a0a0000000d4948445200000001000000010806000000"
    "1f15c4890000000d49444154789c6360000002000154a24f5d0000000049454e44ae426082"
)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


def page_server(viewer_url: str, wait_s: float, width: int, height: int):
    """An HTTP server on 127.0.0.1: `/` frames the viewer, `/hold.png` answers after wait_s."""
    page = (
        "<!DOCTYPE html><html><body style='margin:0;overflow:hidden'>"
        f"<iframe src='{viewer_url}' style='border:0;width:{width}px;height:{height}px'></iframe>"
        "<img src='/hold.png' style='position:absolute;left:0;top:0;width:1px;height:1px'>"
        "</body></html>"
    ).encode()

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:  # noqa: N802 - the stdlib's name
            if self.path == "/hold.png":
                time.sleep(wait_s)
                body, kind = PIXEL, "image/png"
            else:
                body, kind = page, "text/html"
            self.send_response(200)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__.splitlines()[1],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    ap.add_argument("rrd", type=Path, help="a recording (.rrd)")
    ap.add_argument("--out", type=Path, default=Path("viewer.png"), help="screenshot (PNG)")
    ap.add_argument("--wait", type=float, default=90.0, help="seconds the viewer gets to draw")
    ap.add_argument("--size", default="1600x1000", help="window size in pixels, WxH")
    ap.add_argument("--chromium", default="chromium", help="the browser's command")
    args = ap.parse_args(argv)
    if not args.rrd.is_file():
        print(f"error: {args.rrd}: no such file", file=sys.stderr)
        return 2
    chromium = shutil.which(args.chromium)
    if chromium is None:
        print(f"error: no {args.chromium} on PATH (apt-get install -y chromium)", file=sys.stderr)
        return 2
    width, height = (int(v) for v in args.size.lower().split("x"))
    rerun = Path(sys.executable).parent / "rerun"
    web_port, grpc_port = free_port(), free_port()
    viewer = subprocess.Popen(
        [
            str(rerun),
            "--web-viewer",
            "--bind",
            "127.0.0.1",
            "--web-viewer-port",
            str(web_port),
            "--port",
            str(grpc_port),
            str(args.rrd),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    server = None
    try:
        wait_http(f"http://127.0.0.1:{web_port}/", 60)
        proxy = urllib.parse.quote(f"rerun+http://127.0.0.1:{grpc_port}/proxy", safe="")
        server = page_server(f"http://127.0.0.1:{web_port}/?url={proxy}", args.wait, width, height)
        with tempfile.TemporaryDirectory(prefix="mrrig-chromium-") as profile:
            subprocess.run(
                [
                    chromium,
                    *CHROMIUM_FLAGS,
                    f"--user-data-dir={profile}",
                    f"--window-size={width},{height}",
                    f"--screenshot={args.out.resolve()}",
                    f"http://127.0.0.1:{server.server_address[1]}/",
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                timeout=args.wait + 120,
                check=True,
            )
    finally:
        if server is not None:
            server.shutdown()
        viewer.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            viewer.wait(10)
        if viewer.poll() is None:
            viewer.kill()
    print(f"screenshot: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
