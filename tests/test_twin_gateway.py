"""The twin's viewer is read-only: the real rerun relay behind the viewer's gateway (gateway.py).

Found by a review of the cloud side: the relay's gRPC port, which every viewer reads from (through the
authenticating reverse proxy DEPLOY.md asks for), took writes from anyone who reached it: a robot, a force or an
image drawn into what every viewer sees. The browser's reads still pass (test_twin_browser renders the arm
through the gateway); writes, in either of the protocols the relay speaks, do not.
"""

from __future__ import annotations

import socket
import subprocess
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import rerun as rr

from iorthand.config import from_dict
from iorthand.transport import free_port
from iorthand_cloud.twin.config import ViewerConfig
from iorthand_cloud.twin.gateway import data_allowed
from iorthand_cloud.twin.server import ViewerServer, viewer_hosts

SERVICE = "/rerun.sdk_comms.v1alpha1.MessageProxyService"
EMPTY_GRPC_WEB_MESSAGE = b"\x00\x00\x00\x00\x00"  # one uncompressed, empty protobuf message


@pytest.fixture
def viewer(tmp_path: Path):
    config = from_dict({"serve": True, "bind": "127.0.0.1", "grpc_port": free_port(), "web_port": free_port(),
                        "memory_limit": "32MiB"}, ViewerConfig, source="<test>")
    server = ViewerServer(config, log_dir=tmp_path)
    server.start(rr.RecordingStream("iorthand-gateway-test"))
    yield server
    server.stop()


def _post(port: int, path: str) -> tuple[int, bytes]:
    req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", data=EMPTY_GRPC_WEB_MESSAGE,
                                 headers={"Content-Type": "application/grpc-web+proto", "X-Grpc-Web": "1"})
    try:
        with urllib.request.urlopen(req, timeout=2.0) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as refused:
        return refused.code, refused.read()
    except TimeoutError:  # a stream that goes on (a read): answered, not refused
        return 200, b""


def test_the_viewer_reads_through_its_gateway_and_nothing_writes(viewer: ViewerServer) -> None:
    c = viewer.config
    # The page and its wasm, as a browser loads them.
    with urllib.request.urlopen(f"http://127.0.0.1:{c.web_port}/", timeout=10) as r:
        assert r.status == 200 and b"wasm" in r.read()
    status, body = _post(c.web_port, "/")
    assert status == 403 and b"read-only" in body
    # A viewer's read: the stream opens (its headers say gRPC-Web).
    reading = socket.create_connection(("127.0.0.1", c.grpc_port), timeout=5)
    try:
        reading.sendall(f"POST {SERVICE}/ReadMessages HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: "
                        "application/grpc-web+proto\r\nX-Grpc-Web: 1\r\nContent-Length: 5\r\n\r\n".encode()
                        + EMPTY_GRPC_WEB_MESSAGE)
        head = reading.recv(4096).decode("latin-1")
    finally:
        reading.close()
    assert head.startswith("HTTP/1.1 200") and "application/grpc-web+proto" in head, head
    # Writes as gRPC-Web (a page's script), and anything else of the relay's services, are refused with why.
    for method in ("WriteMessages", "WriteTable"):
        status, body = _post(c.grpc_port, f"{SERVICE}/{method}")
        assert status == 403 and b"read-only" in body, (method, status, body)
    status, body = _post(c.grpc_port, "/rerun.viewer_control.v1alpha1.ViewerControlService/SaveScreenshot")
    assert status == 403
    # Native gRPC (HTTP/2, how the SDK writes, and what a gRPC-capable proxy would pass on) is not spoken here.
    h2 = subprocess.run(["curl", "-s", "-o", "/dev/null", "-w", "%{http_code} %{http_version}", "--http2-prior-knowledge",
                         "-m", "3", "-X", "POST", "-H", "content-type: application/grpc", "--data-binary", "@-",
                         f"http://127.0.0.1:{c.grpc_port}{SERVICE}/WriteMessages"],
                        input=EMPTY_GRPC_WEB_MESSAGE, capture_output=True, timeout=10)
    assert not h2.stdout.decode().endswith(" 2"), f"an HTTP/2 write was answered: {h2.stdout!r}"


def test_a_page_of_another_host_name_gets_nothing_from_the_viewer(viewer: ViewerServer) -> None:
    """DNS rebinding: a page at evil.example, its name made to resolve to the viewer's address, is the viewer's own
    origin under that name and could read the patient's images from a browser that reaches the viewer. Requests
    naming a host the viewer is not are refused (421); the viewer's own names still answer."""
    c = viewer.config
    for port, path in ((c.web_port, "/"), (c.grpc_port, f"{SERVICE}/ReadMessages")):
        req = urllib.request.Request(f"http://127.0.0.1:{port}{path}", headers={"Host": f"evil.example:{port}"},
                                     data=EMPTY_GRPC_WEB_MESSAGE if port == c.grpc_port else None)
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(req, timeout=5)
        assert refused.value.code == 421 and b"does not answer to host" in refused.value.read()
    with urllib.request.urlopen(f"http://localhost:{c.web_port}/", timeout=10) as r:
        assert r.status == 200


def test_the_viewer_answers_to_its_own_names() -> None:
    def hosts(**viewer: object) -> frozenset[str]:
        return viewer_hosts(from_dict(viewer, ViewerConfig, source="<test>"))

    assert hosts(bind="127.0.0.1") == {"127.0.0.1", "localhost", "::1"}
    assert hosts(bind="127.0.0.1", public_host="twin.example.org") == {"twin.example.org", "127.0.0.1", "localhost",
                                                                      "::1"}
    assert hosts(bind="0.0.0.0", unauthenticated_network=True, public_host="twin.lan") == {"twin.lan"}
    assert hosts(bind="0.0.0.0", unauthenticated_network=True) == set()  # the machine's addresses are not known


def test_only_the_read_methods_pass() -> None:
    assert data_allowed("POST", f"{SERVICE}/ReadMessages") and data_allowed("OPTIONS", f"{SERVICE}/ReadMessages")
    for method, path in (("POST", f"{SERVICE}/WriteMessages"), ("GET", f"{SERVICE}/ReadMessages"),
                         ("POST", f"{SERVICE}/ReadMessages/../WriteMessages"), ("POST", "/proxy")):
        assert not data_allowed(method, path), (method, path)
