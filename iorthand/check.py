"""``iorthand check --config FILE``: validate a configuration and its certificate paths without starting anything.

The role is taken from ``--role`` or guessed from the file: ``*.json5`` is a router configuration, a YAML with
``robot_id`` an edge, with ``operator_id`` an operator, with ``robots``/``operators`` and no ``zenoh`` a
deployment (the input of ``iorthand certs router-config``); twin and recorder configs are loaded with their
own dataclasses when ``iorthand-cloud`` is installed, otherwise only their ``zenoh`` section is checked.

Then every Zenoh section found in the config gets the same pre-checks as a failed connection
(:func:`iorthand.security.diagnose.precheck`): files exist and are readable, certificates parse, chain to the
CA, are valid now and match their keys, passwords are readable. With ``--router-config`` it also checks that
the router's ACL has a subject for this certificate — a session that matches no subject connects and is then
silently ignored, the hardest failure to see.

Exit status: 0 all good (warnings allowed), 1 problems found, 2 the file does not load.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
from pathlib import Path
from typing import Any

from iorthand.config import ConfigError, from_dict, load, read_yaml
from iorthand.security.diagnose import Finding, check_certificate_files, precheck
from iorthand.transport import ZenohConfig

# role → (module, dataclass name). Imported lazily: the core depends on no role package.
ROLE_CONFIGS: dict[str, tuple[str, str]] = {
    "edge": ("iorthand_edge.config", "EdgeConfig"),
    "operator": ("iorthand_operator.config", "OperatorConfig"),
    "twin": ("iorthand_cloud.twin.config", "TwinConfig"),
    "recorder": ("iorthand_cloud.recorder.config", "RecorderConfig"),
    "deployment": ("iorthand.security.acl", "Deployment"),
    "web": ("iorthand_operator.web.config", "WebConfig"),
    "bridge": ("iorthand_cloud.bridge.config", "BridgeConfig"),
}

# What an edge or operator with bind_operator_keys off meets behind a router generated with it (the default).
UNBOUND = {
    "edge": "off on a secured link: behind a router generated with bind_operator_keys (the default) operators "
            "command on .../cmd/<kind>/<their id>, which this edge does not listen to; and it cannot tell which "
            "certificate sent a command, only the name in it",
    "operator": "off on a secured link: a router generated with bind_operator_keys (the default) drops this "
                "operator's commands and control queries on the plain keys",
}


@dataclasses.dataclass
class Report:
    role: str
    findings: list[Finding] = dataclasses.field(default_factory=list)
    notes: list[str] = dataclasses.field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not any(f.level == "error" for f in self.findings)

    def text(self, path: Path) -> str:
        lines = [f"{path}: {self.role} configuration"]
        lines += [f"  note: {n}" for n in self.notes]
        lines += [f"  {f}" for f in self.findings]
        lines.append(f"  {'OK' if self.ok else 'PROBLEMS FOUND'}")
        return "\n".join(lines)


def guess_role(path: Path, data: Any) -> str:
    if path.suffix in (".json5", ".json"):
        return "router"
    if isinstance(data, dict):
        if "robot_id" in data:
            return "edge"
        if "operator_id" in data:
            return "operator"
        if ("robots" in data or "operators" in data) and "zenoh" not in data:
            return "deployment"
        if "users_file" in data and "deployment" in data:
            return "web"
        if "mappings" in data:
            return "bridge"
        name = path.name.lower()
        # A replay identity's file is a recorder configuration (``iorthand replay --config``).
        for word, role in (("twin", "twin"), ("recorder", "recorder"), ("replay", "recorder")):
            if word in name:
                return role
    raise ConfigError(str(path), "", "cannot tell the role of this file: pass --role edge|operator|twin|recorder|router|deployment|web|bridge")


def _zenoh_sections(obj: Any, where: str = "") -> list[tuple[str, ZenohConfig]]:
    if isinstance(obj, ZenohConfig):
        return [(where or "zenoh", obj)]
    out: list[tuple[str, ZenohConfig]] = []
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            out += _zenoh_sections(getattr(obj, f.name), f"{where}.{f.name}" if where else f.name)
    return out


def _router_paths(cfg: dict[str, Any]) -> dict[str, str | None]:
    tls = cfg.get("transport", {}).get("link", {}).get("tls", {}) or {}
    return {k: tls.get(k) for k in ("root_ca_certificate", "listen_certificate", "listen_private_key")}


def _subjects(router_cfg: dict[str, Any]) -> set[str]:
    ac = router_cfg.get("access_control") or {}
    return {cn for s in ac.get("subjects") or [] for cn in s.get("cert_common_names") or []}


def _load_json5(path: Path) -> dict[str, Any]:
    """Validate with Zenoh itself (it knows every key), then read the values back as JSON."""
    import zenoh

    try:
        zc = zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise ConfigError(str(path), "", f"not a valid Zenoh configuration: {str(exc).split(' at /', 1)[0]}") from None
    out: dict[str, Any] = {}
    for key in ("mode", "listen", "connect", "transport", "access_control"):
        out[key] = json.loads(zc.get_json(key))
    return out


def check_router(path: Path) -> Report:
    cfg = _load_json5(path)
    rep = Report("router")
    paths = _router_paths(cfg)
    listen = cfg.get("listen", {}).get("endpoints") or []
    if isinstance(listen, dict):
        listen = listen.get("router", [])
    if any(not ep.startswith(("tls/", "quic/")) and "127.0.0.1" not in ep and "localhost" not in ep for ep in listen):
        rep.findings.append(Finding("warning", "listen.endpoints", f"unencrypted endpoint reachable from the network: {listen}"))
    if paths["listen_certificate"]:
        rep.findings += check_certificate_files(
            Path(paths["root_ca_certificate"]) if paths["root_ca_certificate"] else None,
            Path(paths["listen_certificate"]), Path(paths["listen_private_key"]) if paths["listen_private_key"] else None,
        )
    tls = cfg.get("transport", {}).get("link", {}).get("tls", {}) or {}
    if paths["listen_certificate"] and not tls.get("enable_mtls"):
        rep.findings.append(Finding("warning", "transport.link.tls.enable_mtls", "off: clients are not authenticated by certificate"))
    usr = (cfg.get("transport", {}).get("auth", {}) or {}).get("usrpwd", {}) or {}
    if usr.get("dictionary_file") and not Path(usr["dictionary_file"]).exists():
        rep.findings.append(Finding("error", usr["dictionary_file"], "user dictionary file does not exist"))
    ac = cfg.get("access_control") or {}
    if not ac.get("enabled"):
        rep.findings.append(Finding("warning", "access_control", "disabled: every authenticated client may do anything"))
    else:
        rep.notes.append(f"ACL: {len(ac.get('subjects') or [])} subjects, default {ac.get('default_permission')}")
    return rep


def check_file(path: Path, role: str | None = None, router_config: Path | None = None) -> Report:
    path = Path(path)
    if path.suffix in (".json5", ".json") and role in (None, "router"):
        return check_router(path)
    data = read_yaml(path)
    role = role or guess_role(path, data)
    if role == "router":
        return check_router(path)
    rep = Report(role)
    module, cls_name = ROLE_CONFIGS[role]
    try:
        cls = getattr(importlib.import_module(module), cls_name)
    except (ImportError, AttributeError):
        cls = None
    if cls is not None:
        obj = load(path, cls)
    else:
        # The role's package is not installed here (e.g. checking a twin config on a laptop): check what the
        # core understands, and say so.
        rep.notes.append(f"{module} is not installed: only the zenoh section was checked")
        if not isinstance(data, dict) or "zenoh" not in data:
            raise ConfigError(str(path), "zenoh", "missing")
        obj = from_dict(data["zenoh"], ZenohConfig, source=str(path), base_dir=path.parent)
    if hasattr(obj, "warnings"):  # role-specific settings that load but defeat their purpose
        rep.findings += [Finding("warning", subject, message) for subject, message in obj.warnings()]
    if role == "deployment":
        certs_dir = Path(obj.certs_dir)
        rep.findings += check_certificate_files(certs_dir / "ca.pem", certs_dir / "router.pem", certs_dir / "router.key")
        if obj.users_file is not None and not Path(obj.users_file).exists():
            rep.findings.append(Finding("error", str(obj.users_file), "user dictionary file does not exist"))
        return rep
    sections = _zenoh_sections(obj)
    if role in UNBOUND and getattr(obj, "bind_operator_keys", True) is False and any(
        zc.tls is not None or zc.username for _, zc in sections
    ):
        rep.findings.append(Finding("warning", "bind_operator_keys", UNBOUND[role]))
    router_subjects = _subjects(_load_json5(Path(router_config))) if router_config else None
    for where, zc in sections:
        for f in precheck(zc):
            rep.findings.append(Finding(f.level, f"{where}: {f.subject}" if not f.subject.startswith("zenoh") else f.subject, f.message))
        if zc.tls is None and any(not ep.startswith(("tcp/127.", "tcp/localhost")) for ep in zc.connect):
            rep.findings.append(Finding("warning", f"{where}.connect", "plain TCP to a remote router: no encryption, no authentication"))
        if router_subjects is not None and zc.tls is not None and zc.tls.certificate and Path(zc.tls.certificate).exists():
            from iorthand.security.certs import common_name, load_certificate

            cn = common_name(load_certificate(Path(zc.tls.certificate)))
            if cn not in router_subjects:
                rep.findings.append(Finding("error", str(zc.tls.certificate), f"CN {cn!r} has no subject in the router's ACL: it would connect and be silently ignored"))
        rep.notes.append(f"{where}: {', '.join(zc.connect or zc.listen)}{' with TLS' if zc.tls else ''}{' + user/password' if zc.username else ''}")
    return rep


def _cmd(args: argparse.Namespace) -> int:
    path = Path(args.config)
    try:
        rep = check_file(path, args.role, Path(args.router_config) if args.router_config else None)
    except ConfigError as exc:
        print(f"{path}: does not load: {exc}")
        return 2
    print(rep.text(path))
    return 0 if rep.ok else 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="validate a configuration and its certificates without starting anything")
    p.add_argument("--config", required=True, help="edge/operator/twin/recorder YAML, deployment YAML or router JSON5")
    p.add_argument("--role", choices=sorted([*ROLE_CONFIGS, "router"]), help="default: guessed from the file")
    p.add_argument("--router-config", help="also check that this config's certificate has a subject in that router's ACL")
    p.set_defaults(func=_cmd)
