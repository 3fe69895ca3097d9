"""Reaching the network services massviz connects to (a Ray cluster's head, a running Rerun viewer or server) within
a bounded time, and saying in one line which option named the address when nothing answers there.

``reach(option, address, host, port)`` opens a TCP connection (refused, unreachable or silent for ``timeout``
seconds: a ``MassvizError`` naming ``option`` and ``address``); ``reach_grpc`` also waits, within the same time, for
a gRPC (HTTP/2) server to answer there, so a port held by something else is reported instead of waited on.
``host_port`` splits ``HOST:PORT`` and URLs (``rerun+http://HOST:PORT/proxy``, ``ray://HOST:PORT``).
"""
from __future__ import annotations

import socket
import time
import urllib.parse

from massviz.errors import MassvizError

#: seconds massviz waits for a service to answer before it says so.
CONNECT_TIMEOUT_S = 10.0


def host_port(address: str, option: str, default_port: int | None = None) -> tuple[str, int]:
    """(host, port) of ``HOST:PORT``, ``[IPv6]:PORT`` or a URL with a host; a ``MassvizError`` naming ``option``
    when it is neither."""
    text = address.strip()
    parsed = urllib.parse.urlsplit(text if "://" in text else f"//{text}")
    try:
        host, port = parsed.hostname, parsed.port
    except ValueError:  # a port that is not a number in 0-65535
        host, port = None, None
    port = port if port is not None else default_port
    if not host or port is None:
        raise MassvizError(f"{option} {address}: not an address (give HOST:PORT, e.g. 127.0.0.1:6379)")
    return host, int(port)


def reach(option: str, address: str, host: str, port: int, timeout: float = CONNECT_TIMEOUT_S,
          hint: str = "") -> float:
    """Open (and close) a TCP connection to ``host:port`` within ``timeout`` seconds; returns the seconds left.
    Nothing there: one ``MassvizError`` line naming ``option``, ``address`` and why, then ``hint``."""
    where = f"{host}:{port}"
    t0 = time.monotonic()
    try:
        with socket.create_connection((host, port), timeout=timeout):
            pass
    except (socket.timeout, TimeoutError):
        raise MassvizError(f"{option} {address}: nothing answered at {where} within {timeout:g} s"
                           + (f"; {hint}" if hint else "")) from None
    except OSError as err:  # refused, unreachable, a name that does not resolve
        why = err.strerror or str(err) or type(err).__name__
        raise MassvizError(f"{option} {address}: cannot connect to {where} ({why})"
                           + (f"; {hint}" if hint else "")) from None
    return max(0.0, timeout - (time.monotonic() - t0))


#: what an HTTP/2 client sends first (RFC 9113, 3.4): the connection preface and an empty SETTINGS frame.
_H2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0])


def reach_grpc(option: str, address: str, host: str, port: int, timeout: float = CONNECT_TIMEOUT_S,
               hint: str = "") -> None:
    """``reach``, then check within what is left of ``timeout`` that an HTTP/2 server (gRPC's transport) answers at
    ``host:port``: its first frame must be SETTINGS (RFC 9113, 3.4). A port held by something else is one line."""
    where = f"{host}:{port}"
    left = reach(option, address, host, port, timeout, hint)
    deadline = time.monotonic() + max(left, 0.5)
    header = b""
    try:
        with socket.create_connection((host, port), timeout=max(left, 0.5)) as s:
            s.sendall(_H2_PREFACE)
            while len(header) < 9:
                s.settimeout(max(0.05, deadline - time.monotonic()))
                chunk = s.recv(9 - len(header))
                if not chunk:
                    break
                header += chunk
    except OSError:  # a timeout, or the other end closing on what it did not understand
        pass
    if len(header) < 9 or header[3] != 4:
        raise MassvizError(f"{option} {address}: {where} accepts connections but no gRPC server answered there "
                           f"within {timeout:g} s" + (f"; {hint}" if hint else ""))


__all__ = ["CONNECT_TIMEOUT_S", "host_port", "reach", "reach_grpc"]
