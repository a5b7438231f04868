"""The web console's configuration (``configs/web.yaml``)."""

from __future__ import annotations

import ipaddress
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

from iorthand.config import setting
from iorthand.security.hosts import is_loopback, own_names
from iorthand.transport import ZenohConfig
from iorthand_operator.console.settings import ConsoleSettings


@dataclass
class WebTls:
    certificate: Path = setting(Path("web.pem"), help="the server's certificate (PEM), e.g. from iorthand certs issue")
    private_key: Path = setting(Path("web.key"), help="its private key (PEM, mode 0600)")


@dataclass
class WebConfig:
    deployment: Path = setting(Path("deployment.yaml"), help="who may log in: the deployment's operators and viewers")
    users_file: Path = setting(Path("web-users.txt"), help="their web passwords (scrypt hashes: iorthand web password)")
    listen: str = setting("127.0.0.1:8443", help="HOST:PORT to serve on")
    tls: WebTls | None = setting(None, help="HTTPS; required unless the server listens on a loopback address")
    zenoh: ZenohConfig = field(default_factory=lambda: ZenohConfig(connect=["tcp/127.0.0.1:7447"]))
    bind_operator_keys: bool = setting(False, help="command on keys carrying each operator's id (the edge's setting)")
    allowed_origins: list[str] = setting(
        default_factory=list, help="origins besides the server's own that may open the console (a reverse proxy's)",
    )
    server_names: list[str] = setting(
        default_factory=list, help="names or addresses browsers open the console by, besides the listen address, the "
        "loopback names (when it listens on loopback), the TLS certificate's names and allowed_origins' hosts: a "
        "request for any other host is refused (a DNS-rebinding page names its own)",
    )
    # None listed by default, loopback included: a console on loopback is reached as much through an ssh tunnel or
    # by a local process as through a proxy, and each of those could name any address in X-Forwarded-For (one more
    # address per request: 20 password guesses a minute instead of 5). A proxy in front is listed on purpose.
    trusted_proxies: list[str] = setting(
        default_factory=list,
        help="addresses of reverse proxies whose X-Forwarded-For and X-Forwarded-Proto are believed: the browser's "
        "address limits its log-in attempts, and HTTPS there makes the session cookie Secure. None by default, "
        "loopback included: list a proxy on this host as 127.0.0.1 (or ::1)",
    )
    session_hours: float = setting(12.0, lo=0.01, hi=24 * 30, help="how long a log-in lasts")
    state_hz: float = setting(20.0, lo=1.0, hi=60.0, help="robot state pushed to each page per second")
    twist_hz: float = setting(
        60.0, lo=20.0, hi=120.0, help="twists per second a controlling page sends (its hello says so); the server "
        "forwards at most twice that, a quarter second's worth at once, and drops and reports the rest",
    )
    max_pages_per_login: int = setting(
        4, lo=1, hi=1000, help="open pages (websockets) one log-in may have at once; one more is refused, saying why",
    )
    max_pages_per_user: int = setting(
        8, lo=1, hi=1000, help="open pages one user may have at once, over all of its log-ins: a viewer's thousand "
        "pages held up the physician's commands past the edge's deadman timeout",
    )
    # The terminal console's section (configs/operator.yaml's console:), read by the same dataclass and its checks:
    # a deployment sets its consoles' bounds and choices once. The page follows force_stale_after, state_stale_after,
    # link, link_window, profiles and pan_tilt_step_deg; input, keymap, gamepad, input_hz and refresh_hz are the
    # terminal's own inputs and screen (the page has its own, and twist_hz above).
    console: ConsoleSettings = field(default_factory=ConsoleSettings)
    arm_model: str = setting("ur3e", choices=("ur3e", "ur5e"), help="the arm drawn in the 3D view")
    arm_models: dict[str, str] = setting(default_factory=dict, help="robot id → ur3e | ur5e, where not arm_model")
    release_tail: float = setting(0.3, lo=0.0, hi=5.0, help="s of released-deadman commands forwarded after a release")
    page_silence: float = setting(
        3.0, lo=0.5, hi=60.0, help="s without a message from a page that holds control (it sends twists at twist_hz "
        "while it does) before the server releases control for it: its link dropped or the browser suspended it. "
        "The edge's own lease, which ends a silent terminal console's control, is 3 s by default",
    )

    def host_port(self) -> tuple[str, int]:
        host, sep, port = self.listen.rpartition(":")
        if not sep or not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise ValueError(f"listen {self.listen!r}: expected HOST:PORT")
        return host.strip("[]"), int(port)

    def host_names(self, certificate_names: Iterable[str] = ()) -> frozenset[str]:
        """The host names a request may name (its Host header, port aside): what a browser opens this console by.
        ``certificate_names``: the TLS certificate's, which are the names a browser accepts it for."""
        host, _ = self.host_port()
        origins = [urlsplit(origin).hostname or "" for origin in self.allowed_origins]
        return own_names(host, [*certificate_names, *self.server_names, *origins])

    def check(self) -> None:
        host, _ = self.host_port()
        if self.tls is None and not is_loopback(host):
            raise ValueError(f"listen {self.listen!r}: a console reachable from the network needs tls (certificate, "
                             "private_key): passwords and the deadman must not cross a network in clear")
        for address in self.trusted_proxies:
            try:
                ipaddress.ip_address(address)
            except ValueError:
                raise ValueError(f"trusted_proxies: {address!r} is not an IP address") from None
        for origin in self.allowed_origins:
            if not origin.startswith(("https://", "http://")) or origin.endswith("/"):
                raise ValueError(f"allowed_origins: {origin!r} is not an origin like https://host[:port]")


__all__ = ["WebConfig", "WebTls"]
