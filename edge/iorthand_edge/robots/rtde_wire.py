"""RTDE's wire format (port 30004): every message is ``uint16 size (the 3-byte header included) | uint8 type |
payload``, big-endian. One copy for the UR emulator's server and the edge's UR driver."""

from __future__ import annotations

import socket
import struct

PORT = 30004

# Package types (ASCII letters in the protocol).
REQUEST_PROTOCOL_VERSION = 86  # 'V'
GET_URCONTROL_VERSION = 118  # 'v'
TEXT_MESSAGE = 77  # 'M'
DATA_PACKAGE = 85  # 'U'
CONTROL_PACKAGE_SETUP_OUTPUTS = 79  # 'O'
CONTROL_PACKAGE_SETUP_INPUTS = 73  # 'I'
CONTROL_PACKAGE_START = 83  # 'S'
CONTROL_PACKAGE_PAUSE = 80  # 'P'

HEADER = struct.Struct(">HB")


def pack_message(msg_type: int, payload: bytes = b"") -> bytes:
    return HEADER.pack(HEADER.size + len(payload), msg_type) + payload


def recv_exact(sock: socket.socket, n: int) -> bytes:
    """Read exactly ``n`` bytes; raise ConnectionError on EOF."""
    chunks = bytearray()
    while len(chunks) < n:
        chunk = sock.recv(n - len(chunks))
        if not chunk:
            raise ConnectionError("peer closed the connection")
        chunks += chunk
    return bytes(chunks)


def read_message(sock: socket.socket) -> tuple[int, bytes]:
    size, msg_type = HEADER.unpack(recv_exact(sock, HEADER.size))
    if size < HEADER.size:
        raise ConnectionError(f"malformed RTDE header: size {size}")
    return msg_type, recv_exact(sock, size - HEADER.size)
