"""A MAVLink-over-UDP endpoint given as a URL, the way PX4 and MAVSDK name them.

- ``udpout://HOST:PORT``: send to HOST:PORT from an ephemeral port and take replies on it
  (PX4 SITL's link to an offboard computer listening on 14540);
- ``udpin://HOST:PORT`` (also ``udp://``): listen on HOST:PORT and answer whoever spoke
  last (a client then connects with ``udpout://``).
"""

from __future__ import annotations

import socket
from urllib.parse import urlsplit


def parse_url(url: str) -> tuple[str, str, int]:
    """``(mode, host, port)`` of a ``udpin://`` / ``udpout://`` / ``udp://`` URL."""
    parts = urlsplit(url)
    mode = {"udpin": "in", "udp": "in", "udpout": "out"}.get(parts.scheme)
    if mode is None or parts.port is None:
        raise ValueError(f"expected udpin://HOST:PORT or udpout://HOST:PORT, got {url!r}")
    host = parts.hostname or ("0.0.0.0" if mode == "in" else "127.0.0.1")
    return mode, host, int(parts.port)


class UdpLink:
    """Datagram transport for one MAVLink peer (module docstring)."""

    def __init__(self, url: str):
        self.url = url
        self.mode, host, port = parse_url(url)
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if self.mode == "in":
            self.sock.bind((host, port))
            self.peer: tuple[str, int] | None = None
        else:
            self.sock.bind(("0.0.0.0", 0))
            self.peer = (host, port)

    @property
    def local_port(self) -> int:
        return self.sock.getsockname()[1]

    def send(self, data: bytes) -> bool:
        """Send one datagram to the peer; False while no peer is known or unreachable."""
        if self.peer is None:
            return False
        try:
            self.sock.sendto(data, self.peer)
        except OSError:  # e.g. ECONNREFUSED from an earlier datagram: nobody listens yet
            return False
        return True

    def recv(self, timeout: float) -> bytes | None:
        """One datagram, or ``None`` after ``timeout`` seconds (or once closed)."""
        try:
            self.sock.settimeout(timeout)
            data, addr = self.sock.recvfrom(65535)
        except (TimeoutError, OSError):
            return None
        if self.mode == "in":
            self.peer = addr
        return data

    def close(self) -> None:
        self.sock.close()
