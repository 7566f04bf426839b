"""Headless-Chromium helper for tests: screenshot a local HTML file while recording every
network request it tries to make (through a recording proxy on 127.0.0.1)."""

from __future__ import annotations

import shutil
import socket
import subprocess
import tempfile
import threading
from pathlib import Path

import numpy as np


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


class RecordingProxy:
    """A tiny HTTP proxy on loopback that records the request line of every connection and
    refuses it (403). Any external URL the page loads shows up in ``requests``."""

    def __init__(self) -> None:
        self.requests: list[str] = []
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._sock.bind(("127.0.0.1", 0))
        self._sock.listen(16)
        self._sock.settimeout(0.2)
        self.port = self._sock.getsockname()[1]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def __enter__(self) -> RecordingProxy:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self._sock.close()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._sock.accept()
            except OSError:
                continue
            with conn:
                conn.settimeout(1.0)
                try:
                    data = conn.recv(4096)
                except OSError:
                    data = b""
                line = data.split(b"\r\n", 1)[0].decode("latin-1", "replace")
                if line:
                    self.requests.append(line)
                try:
                    conn.sendall(b"HTTP/1.1 403 Forbidden\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                except OSError:
                    pass


def _host(request_line: str) -> str:
    parts = request_line.split()
    if len(parts) < 2:
        return request_line
    target = parts[1]
    if "://" in target:
        target = target.split("://", 1)[1]
    return target.split("/", 1)[0].split(":", 1)[0]


_NOISE: set[str] | None = None

#: Chromium's own background services (updates, accounts, optimisation hints, time, safe
#: browsing). They are contacted whatever the page is, so they say nothing about the page.
BROWSER_SERVICE_SUFFIXES = ("google.com", "googleapis.com", "gvt1.com", "gstatic.com")


def _is_browser_service(host: str) -> bool:
    return any(host == s or host.endswith("." + s) for s in BROWSER_SERVICE_SUFFIXES)


def browser_noise_hosts(chromium: str) -> set[str]:
    """Hosts Chromium contacts by itself (update and account services) for a blank page."""
    global _NOISE
    if _NOISE is None:
        with tempfile.TemporaryDirectory() as d:
            blank = Path(d) / "blank.html"
            blank.write_text("<html><body></body></html>")
            _NOISE = {_host(r) for r in _raw_screenshot(blank, Path(d) / "b.png", chromium, (200, 200), 3000)}
    return _NOISE


def screenshot(html: Path, png: Path, chromium: str, size=(1100, 850), budget_ms: int = 8000) -> list[str]:
    """Render ``html`` headless to ``png``; return the external requests the PAGE attempted
    (requests to hosts that Chromium also contacts for a blank page are its own background
    traffic and are left out)."""
    noise = browser_noise_hosts(chromium)
    return [r for r in _raw_screenshot(html, png, chromium, size, budget_ms)
            if _host(r) not in noise and not _is_browser_service(_host(r))]


def _raw_screenshot(html: Path, png: Path, chromium: str, size, budget_ms: int) -> list[str]:
    with RecordingProxy() as proxy, tempfile.TemporaryDirectory() as profile:
        cmd = [
            chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
            "--no-first-run", "--disable-background-networking", "--disable-component-update",
            "--disable-sync", "--disable-default-apps", "--disable-extensions",
            "--disable-features=OptimizationHints,OptimizationHintsFetching,"
            "OptimizationGuideModelDownloading,MediaRouter,AutofillServerCommunication",
            f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
            f"--proxy-server=http://127.0.0.1:{proxy.port}", "--proxy-bypass-list=<-loopback>",
            f"--virtual-time-budget={budget_ms}", f"--screenshot={png}", html.resolve().as_uri(),
        ]
        subprocess.run(cmd, check=True, timeout=120, capture_output=True)
        return list(proxy.requests)


def colour_fraction(png: Path, rgb_hex: str, tol: int = 40) -> float:
    """Fraction of pixels within ``tol`` (per channel) of a colour."""
    import matplotlib.image as mpimg

    img = mpimg.imread(str(png))[..., :3]
    if img.dtype != np.uint8:
        img = (img * 255).round().astype(int)
    rgb = np.array([int(rgb_hex[i:i + 2], 16) for i in (1, 3, 5)])
    close = np.all(np.abs(img.astype(int) - rgb) <= tol, axis=-1)
    return float(close.mean())


def non_background_fraction(png: Path) -> float:
    """Fraction of pixels that are not (near) white."""
    import matplotlib.image as mpimg

    img = mpimg.imread(str(png))[..., :3]
    if img.dtype == np.uint8:
        img = img / 255.0
    return float((img.min(axis=-1) < 0.9).mean())
