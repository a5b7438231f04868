"""``iorthand check --config FILE``: validate a configuration and its certificate paths without starting anything.

The role is taken from ``--role`` or guessed from the file: ``*.json5`` is a router configuration, a YAML with
``robot_id`` an edge, with ``operator_id`` an operator, with ``robots``/``operators`` and no ``zenoh`` a
deployment (the input of ``iorthand certs router-config``); twin and recorder configs are loaded with their
own dataclasses when ``iorthand-cloud`` is installed, otherwise only their ``zenoh`` section is checked.

Then every Zenoh section found in the config gets the same pre-checks as a failed connection
(:func:`iorthand.security.diagnose.precheck`): files exist and are readable, certificates parse, chain to the
CA, are valid now and match their keys, passwords are readable (and not by every user). The certificate's
common name and the user name must be the role's identity as the router's ACL knows it (``edge-<robot_id>``,
``operator-<operator_id>``, ``twin``, ...). With ``--router-config`` it also checks that the router's ACL has a
subject for this certificate — a session that matches no subject connects and is then silently ignored, the
hardest failure to see — and, where the router's user dictionary is readable, that the password is the one in it.
An edge's, operator's or web console's ``bind_operator_keys`` must be its deployment's, as ``--deployment``, the
router's ACL (``--router-config``) or the web console's own deployment file says it: otherwise commands are
refused by the router or not heard by the edge, or the router binds less than the configuration expects.

A router reachable from the network must listen on TLS, with mTLS, user/password and an ACL whose default is
deny: anything less is an error (the systemd unit then does not start it); a loopback-only router (development,
the demo) may be open.

Exit status: 0 all good (warnings allowed), 1 problems found, 2 the file does not load.
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib
import json
import os
from pathlib import Path
from typing import Any

import zenoh

from iorthand.config import ConfigError, from_dict, load, read_yaml
from iorthand.security import acl, identity
from iorthand.security.diagnose import (
    Finding,
    check_certificate_files,
    clear_beyond_loopback,
    endpoint_is_local,
    file_problem,
    is_encrypted,
    precheck,
)
from iorthand.transport import ZenohConfig, forwarding_rules

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
    "web": "off on a secured link: a router generated with bind_operator_keys (the default) drops the commands and "
           "control queries the console sends for its operators on the plain keys (the browser then shows \"no "
           "answer from robot on control/acquire\"): set bind_operator_keys: true, as in deploy/configs/web.yaml",
}

# The certificate common names (= router user names) a role's configuration may present: the router's ACL
# (iorthand.security.acl) has subjects with exactly these names. None: not tied to one name.
FIXED_IDENTITIES: dict[str, set[str]] = {
    **{service: {service} for service in acl.SERVICES}, "recorder": {"recorder", acl.REPLAY},
    acl.WEB: {acl.WEB}, acl.BRIDGE: {acl.BRIDGE},
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
    try:
        zc = zenoh.Config.from_file(str(path))
    except zenoh.ZError as exc:
        raise ConfigError(str(path), "", f"not a valid Zenoh configuration: {str(exc).split(' at /', 1)[0]}") from None
    out: dict[str, Any] = {}
    for key in ("mode", "listen", "connect", "transport", "access_control", "qos"):
        out[key] = json.loads(zc.get_json(key))
    return out


def _endpoints(section: Any) -> list[str]:
    endpoints = (section or {}).get("endpoints") or []
    if isinstance(endpoints, dict):  # per-role form {router: [...], peer: [...]}
        endpoints = endpoints.get("router", [])
    return list(endpoints)


def check_router(path: Path) -> Report:
    """A router reachable from the network (any listen endpoint not on the loopback, Zenoh's default
    ``tcp/[::]:7447`` included) must encrypt, authenticate and filter: anything else would let whoever reaches
    the port command the robots, so it is an error (the systemd unit then does not start it). A loopback-only
    router (development, the demo) may be open: the same findings are warnings there."""
    cfg = _load_json5(path)
    rep = Report("router")
    paths = _router_paths(cfg)
    listen = _endpoints(cfg.get("listen"))
    exposed = [ep for ep in listen if not endpoint_is_local(ep)]
    level = "error" if exposed else "warning"
    clear = clear_beyond_loopback(listen)
    if clear:
        rep.findings.append(Finding("error", "listen.endpoints", (
            f"unencrypted endpoint reachable from the network: {', '.join(clear)}: commands, passwords and the "
            "control key would cross the network in clear and nobody would be authenticated. Listen on "
            "tls/HOST:PORT (generate the configuration with `iorthand certs router-config`), or on 127.0.0.1 "
            "for a development router")))
    if paths["listen_certificate"]:
        rep.findings += check_certificate_files(
            Path(paths["root_ca_certificate"]) if paths["root_ca_certificate"] else None,
            Path(paths["listen_certificate"]), Path(paths["listen_private_key"]) if paths["listen_private_key"] else None,
        )
    tls = cfg.get("transport", {}).get("link", {}).get("tls", {}) or {}
    # Client certificates authenticate only on a TLS listener (a TLS section beside tcp/ endpoints does nothing).
    mtls = bool(paths["listen_certificate"] and tls.get("enable_mtls") and any(is_encrypted(ep) for ep in listen))
    if paths["listen_certificate"] and not tls.get("enable_mtls"):
        rep.findings.append(Finding(level, "transport.link.tls.enable_mtls", (
            "off: clients are not authenticated by certificate, and the ACL's certificate names match nobody: "
            "set it true")))
    usr = (cfg.get("transport", {}).get("auth", {}) or {}).get("usrpwd", {}) or {}
    dictionary = usr.get("dictionary_file")
    if dictionary and not Path(dictionary).exists():
        rep.findings.append(Finding("error", dictionary, "user dictionary file does not exist"))
    elif not dictionary and exposed:
        # With mTLS a client is still authenticated by its certificate; without it, by nothing.
        rep.findings.append(Finding("warning" if mtls else "error", "transport.auth.usrpwd", (
            "no user/password authentication (no dictionary_file)" + (
                ": a stolen certificate and key are enough to connect" if mtls else
                " and no client certificates: any client that reaches the router is let in") +
            ". Set users_file in deployment.yaml (`iorthand certs password NAME` writes it) and regenerate")))
    ac = cfg.get("access_control") or {}
    who = "every authenticated client" if (mtls or dictionary) else "every client that reaches the router (no one is authenticated)"
    if not ac.get("enabled"):
        rep.findings.append(Finding(level, "access_control", (
            f"disabled: {who} may publish, subscribe and query anything, commands to the robots included"
            + (": generate the configuration with `iorthand certs router-config`" if exposed else ""))))
    else:
        if ac.get("default_permission") == "allow":
            rep.findings.append(Finding(level, "access_control.default_permission", (
                "allow: a session that matches no subject (another certificate of the CA, a wrong user name) may "
                "do whatever no rule denies: set it to deny, as `iorthand certs router-config` does")))
        rep.notes.append(f"ACL: {len(ac.get('subjects') or [])} subjects, default {ac.get('default_permission')}")
    missing = _unforwarded(cfg)
    if missing:
        rep.findings.append(Finding("warning", "qos.network", (
            f"{', '.join(missing)} forwarded as published (BLOCK): one subscriber that stops reading (a hung "
            "console) holds up these messages, and everything else the edge sends, for every other subscriber, for "
            "up to 5 s at a time. Add the egress rules of `iorthand certs router-config` (configs/router.json5 "
            "shows them)")))
    return rep


def _unforwarded(cfg: dict[str, Any]) -> list[str]:
    """The keys of :func:`~iorthand.transport.forwarding_rules` that the router's ``qos.network`` does not forward
    as they say (a hand-written or older configuration)."""
    have = [(zenoh.KeyExpr(expr), (rule.get("overwrite") or {}).get("congestion_control"))
            for rule in (cfg.get("qos") or {}).get("network") or []
            if "egress" in (rule.get("flows") or ["egress"]) and "put" in (rule.get("messages") or [])
            for expr in rule.get("key_exprs") or ["**"]]  # no key_exprs: every key
    return [expr for rule in forwarding_rules() for expr in rule["key_exprs"]
            if not any(mode == rule["overwrite"]["congestion_control"] and covering.includes(zenoh.KeyExpr(expr))
                       for covering, mode in have)]


def _users(path: Path) -> dict[str, str]:
    """Zenoh's usrpwd dictionary: ``user:password`` lines."""
    out: dict[str, str] = {}
    for line in path.read_text().splitlines():
        user, sep, password = line.partition(":")
        if sep:
            out[user] = password
    return out


def _identity_findings(role: str, obj: Any, data: Any, where: str, zc: ZenohConfig, cn: str | None) -> list[Finding]:
    """The certificate's common name and the user name must be the ones the router's ACL has for this role:
    otherwise the session connects and nothing it sends is routed, or it speaks as someone else."""
    out: list[Finding] = []
    expected: set[str] | None
    why = ""
    # From the loaded config, or the YAML where the role's package is not installed (only zenoh was loaded).
    robot_id = getattr(obj, "robot_id", None) or (data.get("robot_id") if isinstance(data, dict) else None)
    operator_id = getattr(obj, "operator_id", None) or (data.get("operator_id") if isinstance(data, dict) else None)
    if role == "edge" and robot_id:
        name = identity.edge_common_name(robot_id)
        expected = {name}
        why = (f"the router grants the keys of robot {robot_id!r} to {name} only: this edge would "
               f"connect and be ignored, or act as another robot. Use {name}.pem/.key, or fix robot_id")
    elif role == "operator" and operator_id:
        name = identity.operator_common_name(operator_id)
        expected = {name}
        why = (f"the router lets operator {operator_id!r} command only with the certificate {name}: "
               f"every command and control request would be dropped or refused. Use {name}.pem/.key, "
               "or set operator_id to the name the certificate carries")
    else:
        expected = FIXED_IDENTITIES.get(role)
        why = "the router's ACL has a subject for that name only: nothing this service sends would be routed"
    names = " or ".join(sorted(expected)) if expected else ""
    if cn is not None and expected and cn not in expected:
        out.append(Finding("error", str(zc.tls.certificate if zc.tls else where),
                           f"certificate CN {cn!r} is not this {role}'s identity {names!r}: {why}"))
    if zc.username:
        # The name to match: the role's own where it has one name (a wrong CN is reported above), else the CN.
        target = next(iter(expected)) if expected and len(expected) == 1 else cn
        if target is not None and zc.username != target:
            out.append(Finding("error", f"{where}.username", (
                f"{zc.username!r} is not {target!r}" + (", the certificate's CN" if target == cn else f", this {role}'s identity")
                + ": the router's ACL matches a session on its certificate name and its user name together, so this "
                "one would connect and be silently ignored. Set username to the certificate's name, with its password_file")))
    return out


def _password_findings(where: str, zc: ZenohConfig, router_cfg: dict[str, Any], rep: Report) -> list[Finding]:
    """Compare this config's user and password with the router's dictionary file, where it can be read."""
    usr = (router_cfg.get("transport", {}).get("auth", {}) or {}).get("usrpwd", {}) or {}
    dictionary = usr.get("dictionary_file")
    if not dictionary:
        return []
    if not zc.username:
        return [Finding("error", f"{where}.username", (
            f"the router asks every client for a user and password (its dictionary {dictionary}) and none is set: "
            "set username (the certificate's name) and password_file"))]
    try:
        users = _users(Path(dictionary))
    except OSError as exc:
        rep.notes.append(f"{where}: the router's dictionary {dictionary} is not readable here ({exc.strerror or exc}): "
                         "password not compared")
        return []
    if zc.username not in users:
        return [Finding("error", f"{where}.username", (
            f"user {zc.username!r} is not in the router's dictionary {dictionary}: add it with `iorthand certs "
            f"password {zc.username}` on the CA machine, install the new users.txt and restart the router"))]
    if zc.password_file is None or not Path(zc.password_file).exists() or not os.access(zc.password_file, os.R_OK):
        return []  # precheck reports the file
    if Path(zc.password_file).read_text().strip() != users[zc.username].strip():
        return [Finding("error", str(zc.password_file), (
            f"this is not {zc.username!r}'s password in the router's dictionary {dictionary}: the router would refuse "
            f"the session. Install {zc.username}.password and users.txt from the same `iorthand certs password` run"))]
    return []


def _web_findings(obj: Any, secured: bool) -> list[Finding]:
    """The web console: its deployment must let the ``web`` certificate in, its users file and HTTPS files exist."""
    out: list[Finding] = []
    dep_path = Path(obj.deployment)
    if secured and dep_path.is_file() and os.access(dep_path, os.R_OK):
        try:
            dep = load(dep_path, acl.Deployment)
        except ConfigError as exc:
            out.append(Finding("error", str(dep_path), f"the deployment does not load: {exc}"))
        else:
            if not dep.web:
                out.append(Finding("error", str(dep_path), (
                    "has no `web: true`: the router generated from it has no subject for certificate web, so the "
                    "console connects and nothing it sends is routed. Add `web: true` to this file, regenerate "
                    "router.json5 (`iorthand certs router-config`) and restart the router (docs/DEPLOY.md §5)")))
    problem = file_problem(Path(obj.users_file), "web users file")
    if problem:
        # The console does not start without it; a development console may be checked before its first user.
        out.append(Finding("error" if secured else "warning", problem.subject, problem.message + (
            " (add a user with `iorthand web password NAME --users-file FILE`)")))
    if obj.tls is not None:
        out += check_certificate_files(None, Path(obj.tls.certificate), Path(obj.tls.private_key))
    return out


def _recorder_findings(obj: Any, replay: bool) -> list[Finding]:
    """The recorder's folder must be one it can write (a replay's, read): otherwise the service starts and every
    recording is refused. A calibration file it cannot read is left out of every recording."""
    out: list[Finding] = []
    root = Path(obj.output_dir)
    there = root  # the folder itself, or the nearest existing folder above it (the recorder creates the rest)
    while not there.exists() and there != there.parent:
        there = there.parent
    need, what = (os.R_OK | os.X_OK, "readable") if replay else (os.W_OK | os.X_OK, "writable")
    if not there.is_dir():
        out.append(Finding("error", "output_dir", f"{root}: {there} is not a folder: no recording can be "
                           + ("read" if replay else "made")))
    elif not os.access(there, need):
        out.append(Finding("error", "output_dir", f"{root}: {there} is not {what} by this user (uid {os.getuid()}): "
                           + ("no recording can be read" if replay else "every recording would be refused")))
    for path in obj.calibration_files:
        problem = file_problem(Path(path), "calibration file")
        if problem:
            out.append(Finding("warning", problem.subject, problem.message + ": recordings are made without it"))
    return out


def _deployed_bindings(role: str, obj: Any, secured: bool, deployment: Path | None,
                       router_cfg: dict[str, Any] | None, router_config: Path | None, rep: Report) -> list[tuple[bool, str]]:
    """The deployment's ``bind_operator_keys`` as each source given says it: ``--deployment``, the router's ACL
    (``--router-config``), and a secured web console's own deployment file; with where it was read."""
    out: list[tuple[bool, str]] = []
    files = [Path(deployment)] if deployment else []
    if role == "web" and secured and Path(obj.deployment) not in files:
        files.append(Path(obj.deployment))  # (_web_findings reports one that is missing or does not load)
    for dep_path in files:
        if not dep_path.is_file() or not os.access(dep_path, os.R_OK):
            if dep_path == deployment:
                rep.findings.append(Finding("error", str(dep_path), "deployment file missing or not readable"))
            continue
        try:
            out.append((load(dep_path, acl.Deployment).bind_operator_keys, str(dep_path)))
        except ConfigError as exc:
            if dep_path == deployment:
                rep.findings.append(Finding("error", str(dep_path), f"the deployment does not load: {exc}"))
    bound = acl.bound_operator_keys(router_cfg) if router_cfg is not None else None
    if bound is not None:
        out.append((bound, f"{router_config} (its operators' command rules)"))
    return out


def _binding_finding(role: str, value: bool, deployed: bool, where: str) -> Finding:
    """An edge, operator or web console whose ``bind_operator_keys`` is not its deployment's."""
    if deployed:  # this config is unbound, the router is bound
        why = ("operators command on .../cmd/<kind>/<their id>, which this edge does not listen to" if role == "edge"
               else f"the router drops this {role}'s commands and control queries on the plain keys")
    else:
        why = (("operators command on the plain keys, which this edge does not listen to" if role == "edge" else
                f"the edges of this deployment listen on the plain keys, not on this {role}'s own")
               + "; and the router holds no operator to its own keys (a weaker binding than this configuration's)")
    return Finding("error", "bind_operator_keys", (
        f"{str(value).lower()} here but {str(deployed).lower()} in {where}: {why}. Set it alike on the deployment, "
        "its router (`iorthand certs router-config`), the edges and the operators"))


def check_file(path: Path, role: str | None = None, router_config: Path | None = None,
               deployment: Path | None = None) -> Report:
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
    secured = any(zc.tls is not None or zc.username for _, zc in sections)
    router_cfg = _load_json5(Path(router_config)) if router_config else None
    bind = getattr(obj, "bind_operator_keys", None)  # (None: the role's package is not installed here)
    if role in UNBOUND and bind is not None:
        # A mismatch: commands refused by the router's ACL, or not heard by the edge, or a weaker binding than
        # the deployment's; only the deployment (or the router made from it) tells.
        known = _deployed_bindings(role, obj, secured, deployment, router_cfg, router_config, rep)
        rep.findings += [_binding_finding(role, bind, deployed, where) for deployed, where in known if deployed != bind]
        if bind is False and secured and not known:  # (UNBOUND: behind the default deployment)
            rep.findings.append(Finding("warning", "bind_operator_keys", UNBOUND[role]))
    if role == "web":
        rep.findings += _web_findings(obj, secured)
    if role == "recorder" and hasattr(obj, "output_dir"):  # (not when only its zenoh section was loaded)
        replay = any(_common_name(zc) == acl.REPLAY or zc.username == acl.REPLAY for _, zc in sections)
        rep.findings += _recorder_findings(obj, replay)
    router_subjects = _subjects(router_cfg) if router_cfg is not None else None
    for where, zc in sections:
        for f in precheck(zc):
            rep.findings.append(Finding(f.level, f"{where}: {f.subject}" if not f.subject.startswith("zenoh") else f.subject, f.message))
        if zc.tls is None and any(not endpoint_is_local(ep) for ep in zc.connect):
            rep.findings.append(Finding("warning", f"{where}.connect", "plain TCP to a remote router: no encryption, no authentication"))
        cn = _common_name(zc)
        rep.findings += _identity_findings(role, obj, data, where, zc, cn)
        if router_subjects is not None and cn is not None and cn not in router_subjects:
            rep.findings.append(Finding("error", str(zc.tls.certificate), f"CN {cn!r} has no subject in the router's ACL: it would connect and be silently ignored"))
        if router_cfg is not None:
            rep.findings += _password_findings(where, zc, router_cfg, rep)
        rep.notes.append(f"{where}: {', '.join(zc.connect or zc.listen)}{' with TLS' if zc.tls else ''}{' + user/password' if zc.username else ''}")
    return rep


def _common_name(zc: ZenohConfig) -> str | None:
    """The CN of the certificate a Zenoh section presents; None without one or when it cannot be read (precheck
    says why)."""
    if zc.tls is None or not zc.tls.certificate:
        return None
    from iorthand.security.certs import CertError, common_name, load_certificate

    try:
        return common_name(load_certificate(Path(zc.tls.certificate)))
    except CertError:
        return None


def _cmd(args: argparse.Namespace) -> int:
    path = Path(args.config)
    try:
        rep = check_file(path, args.role, Path(args.router_config) if args.router_config else None,
                         Path(args.deployment) if args.deployment else None)
    except ConfigError as exc:
        print(f"{path}: does not load: {exc}")
        return 2
    print(rep.text(path))
    return 0 if rep.ok else 1


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="validate a configuration and its certificates without starting anything")
    p.add_argument("--config", required=True, help="edge/operator/twin/recorder YAML, deployment YAML or router JSON5")
    p.add_argument("--role", choices=sorted([*ROLE_CONFIGS, "router"]), help="default: guessed from the file")
    p.add_argument("--router-config", help="also check that this config's certificate has a subject in that router's ACL "
                   "and, if its user dictionary is readable here, that the password is the one in it")
    p.add_argument("--deployment", help="the deployment YAML: an edge's, operator's or web console's "
                   "bind_operator_keys must be the deployment's (a mismatch: commands refused or not heard)")
    p.set_defaults(func=_cmd)
