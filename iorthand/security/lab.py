"""A complete secured deployment in one directory, for tests, benchmarks and a first try on a laptop:
CA, role certificates, passwords, the router's user dictionary and its generated configuration."""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

from iorthand.security import acl, certs, identity
from iorthand.transport import TlsConfig, ZenohConfig


@dataclass
class Lab:
    directory: Path
    endpoint: str
    deployment: acl.Deployment
    router_config: Path
    passwords: dict[str, str] = field(default_factory=dict)

    def client(
        self, name: str, *, password: str | None = None, cert_dir: Path | None = None,
        endpoint: str | None = None, mtls: bool = True, retry_s: float = 0.0, tls: bool = True,
    ) -> ZenohConfig:
        """A client config for role ``name``; the keywords break it the ways an attacker or a typo would."""
        d = Path(cert_dir) if cert_dir else self.directory
        pw_file = self.directory / f"{name}.{'wrong' if password is not None else 'password'}"
        if password is not None:
            pw_file.write_text(password)
            os.chmod(pw_file, 0o600)
        return ZenohConfig(
            mode="client", connect=[endpoint or self.endpoint], connect_retry_s=retry_s,
            tls=TlsConfig(root_ca=self.directory / "ca.pem", certificate=d / f"{name}.pem",
                          private_key=d / f"{name}.key", mtls=mtls) if tls else None,
            username=name if self.deployment.users_file else "",
            password_file=pw_file if self.deployment.users_file else None,
        )


def make_lab(
    directory: Path, port: int, robots: list[str], operators: dict[str, list[str]], viewers: list[str] | None = None,
    passwords: bool = True, bind_operator_keys: bool = False, web: bool = False,
) -> Lab:
    directory = Path(directory)
    certs.init_ca(directory, force=True)
    dep = acl.Deployment(
        listen=[f"tls/127.0.0.1:{port}"], certs_dir=directory,
        users_file=directory / "users.txt" if passwords else None,
        robots=robots, operators=operators, viewers=viewers or [], bind_operator_keys=bind_operator_keys, web=web,
    )
    dep.check()
    names = ["router", "twin", "recorder", "replay", *map(identity.edge_common_name, robots),
             *map(identity.operator_common_name, operators),
             *(f"viewer-{v}" for v in dep.viewers), *(["web"] if web else [])]
    lab = Lab(directory, f"tls/127.0.0.1:{port}", dep, directory / "router.json5")
    lines = []
    for n in names:
        certs.issue(directory, n, hosts=["localhost", "127.0.0.1"] if n == "router" else None)
        if passwords:
            pw = f"pw-{n}-{os.urandom(6).hex()}"
            lab.passwords[n] = pw
            (directory / f"{n}.password").write_text(pw)
            os.chmod(directory / f"{n}.password", 0o600)
            lines.append(acl.users_line(n, pw))
    if passwords:
        (directory / "users.txt").write_text("".join(lines))
        os.chmod(directory / "users.txt", 0o600)
    lab.router_config.write_text(acl.to_json5(acl.router_config(dep)))
    return lab
