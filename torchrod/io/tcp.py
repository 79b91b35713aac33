"""Readings over TCP: ``--input tcp://HOST:PORT`` connects to a server that sends them (an interrogator's or a
shape-sensing program's stream) and reads until the server closes the connection.

torchrod is the client: it connects once, reads what the server sends, and ends when the server closes the
connection (every reading already received is answered first). The bytes are read in chunks with a short timeout,
so that a stream being flushed (Ctrl-C, SIGTERM) stops waiting at once. What the bytes hold is the protocol's
business: lines (:func:`torchrod.io.jsonl.read_lines`) or length-prefixed records (:mod:`torchrod.io.fbgs`).
"""

from __future__ import annotations

import re
import socket
import threading
from typing import Any

from ..errors import OptionsError

__all__ = ["CONNECT_TIMEOUT", "TcpReader", "is_tcp", "tcp_address"]

CONNECT_TIMEOUT = 10.0
"""[s] How long a connection may take to open before the command gives up."""

_POLL = 0.1  # [s] longest uninterrupted wait for bytes (keeps a halt responsive)
_ADDRESS = re.compile(r"tcp://(\[[0-9A-Fa-f:.]+\]|[^:/\[\]]+):([0-9]{1,5})/?")


def is_tcp(source: Any) -> bool:
    """Whether ``source`` names a TCP server (``tcp://HOST:PORT``)."""
    return isinstance(source, str) and source.lower().startswith("tcp://")


def tcp_address(text: str) -> tuple[str, int]:
    """``tcp://HOST:PORT`` (an IPv6 host in brackets) as (host, port); :class:`~torchrod.errors.OptionsError` naming
    the text otherwise."""
    match = _ADDRESS.fullmatch(text.strip())
    port = int(match.group(2)) if match else 0
    if match is None or not 0 < port < 65536:
        raise OptionsError(f"{text!r} is not a TCP address: give tcp://HOST:PORT (e.g. tcp://192.168.1.11:5001)")
    return match.group(1).strip("[]"), port


class TcpReader:
    """A connection to ``tcp://HOST:PORT``, read as a byte stream.

    :meth:`read` returns up to ``n`` bytes as they arrive, ``b""`` once the server has closed the connection, and
    None once ``halted`` (a :class:`threading.Event`) is set while it waits. Opening it raises
    :class:`~torchrod.errors.OptionsError` naming the address when the server cannot be reached.
    """

    def __init__(self, address: str, halted: threading.Event | None = None, timeout: float = CONNECT_TIMEOUT) -> None:
        self.address = address
        self.halted = halted if halted is not None else threading.Event()
        host, port = tcp_address(address)
        try:
            self._sock = socket.create_connection((host, port), timeout=timeout)
        except OSError as exc:
            raise OptionsError(f"{address}: cannot connect ({exc.strerror or exc})") from None
        self._sock.settimeout(_POLL)

    def read(self, n: int) -> bytes | None:
        while not self.halted.is_set():
            try:
                return self._sock.recv(n)
            except TimeoutError:
                continue
            except ConnectionResetError:
                return b""
        return None

    def close(self) -> None:
        self._sock.close()

    def __enter__(self) -> TcpReader:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
