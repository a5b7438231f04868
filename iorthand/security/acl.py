"""The router's configuration: TLS + mTLS + user/password + an access-control list by role. Pure functions.

:func:`router_config` turns a :class:`Deployment` (robots, operators and their grants, viewers, where the
certificates are) into the JSON-able dict that ``iorthand router --config`` runs and that a stock ``zenohd -c``
reads unchanged. Nothing here opens a socket or reads a file, so the whole policy is unit-tested.

Identity: every subject matches on its certificate common name *and* a username equal to it (Zenoh requires
both to match when both are given): a stolen password without the key, or a key without the password, is not
enough. Which role may write or query which key of a robot is a column of the table of channels
(:mod:`iorthand.channels`); the rules below are derived from it. Roles (common names as issued by
:mod:`iorthand.security.certs`):

- ``edge-<robot>``: publishes only ``iorthand/<robot>/state/**``, ``markers`` and ``video/**``; declares the
  queryables (and replies) under ``iorthand/<robot>/control/**``; subscribes to its own commands; holds only
  the ``alive/edge`` token. It receives traffic of its own robot only.
- ``operator-<name>``: publishes commands and queries ``control/**`` only for the robots it is granted, with
  ``bind_operator_keys`` (the default) only on its own keys ``cmd/<kind>/<name>`` and ``control/<verb>/<name>``
  plus the shared ``cmd/stop`` (a stop is everyone's); its liveliness token is restricted to
  ``alive/operator/<name>`` so nobody can look like another operator to the edge's owner-loss logic. It sees
  only its robots and the cloud services.
- ``twin``, ``recorder`` (services) and ``viewer-<name>`` (observers): subscribe and query; the services also
  serve their own ``iorthand/_twin/**`` / ``iorthand/_recorder/**`` space, and the twin queries every robot's
  ``plan/**`` (it has the edge plan the operators' previews, and draws them), nothing else of a robot's. Viewers cannot query a robot's
  ``control/**`` (acquiring control is a query: a viewer that could query it could steal ownership), and of the
  services they may ask only what reads (:data:`READ_ONLY_QUERIES`: the twin's snapshots, the recorder's
  status): a viewer cannot start, stop or annotate a recording, nor have the edge plan a preview. With
  ``bind_operator_keys`` an operator annotates only on ``_recorder/annotate/<name>``, so a recording's
  annotations carry the author its certificate names.
- ``web`` (``iorthand web``, with ``web: true``): a trusted bridge. It logs its users in by password
  (:mod:`iorthand_operator.web`) and may send for each operator exactly what that operator's certificate may
  (its bound keys, its token) and watch every robot; its users' grants are the deployment's, as here.
- ``replay`` (``iorthand replay``): publishes ``state/**``, ``markers`` and ``video/**`` only under the ids
  reserved for replays (``<robot>-replay``, :data:`iorthand.keys.REPLAY_SUFFIX`), so a replayed recording can
  never pass for a robot; it receives traffic of those ids only.
- ``bridge`` (``iorthand bridge mqtt``, with ``bridge: true``): publishes only the rows of the table whose writers
  name :attr:`Role.BRIDGE` (``sensor/**``: readings from an MQTT broker) of the deployment's robots, and watches
  those robots to mirror their state out; it may not command, query ``control/**`` or hold a token.

Default permission is deny. A session whose identity matches no subject can connect but nothing it sends is
routed (Zenoh drops denied messages silently): that is why the edge also checks on its own (see
:mod:`iorthand.security.identity`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from iorthand import channels, keys
from iorthand.channels import Channel, Kind, OperatorKey, Role
from iorthand.config import setting
from iorthand.security.identity import edge_common_name, operator_common_name
from iorthand.transport import (
    ACCEPT_PENDING,
    ROUTER_LEASE_MS,
    SHM_POOL_SIZE,
    TX_QUEUE_SIZE,
    announced_lease,
    forwarding_rules,
    rate_limits,
)

ALL_MESSAGES = [
    "put", "delete", "declare_subscriber", "query", "declare_queryable", "reply",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
]
SUBSCRIBE = ["declare_subscriber", "declare_liveliness_subscriber", "liveliness_query"]
PUTS = ["put", "delete"]
NOT_PUTS = [m for m in ALL_MESSAGES if m not in PUTS]
SERVICES = ("twin", "recorder")
REPLAY = Role.REPLAY.value  # the identity of `iorthand replay`
WEB = "web"  # the identity of `iorthand web`
BRIDGE = Role.BRIDGE.value  # the identity of `iorthand bridge mqtt`


@dataclass
class Deployment:
    """Who may do what. Loaded from YAML (``deploy/deployment.example.yaml``) by ``iorthand certs router-config``."""

    listen: list[str] = setting(default_factory=lambda: ["tls/0.0.0.0:7447"], help="router endpoints (tls/...)")
    certs_dir: Path = setting(Path("/etc/iorthand/certs"), help="holds ca.pem, router.pem, router.key")
    users_file: Path | None = setting(None, help="Zenoh user:password dictionary; None: no user/password layer")
    robots: list[str] = setting(default_factory=list)
    operators: dict[str, list[str]] = setting(default_factory=dict, help="operator name → robots it may command")
    viewers: list[str] = setting(default_factory=list, help="observer names (certificates viewer-<name>)")
    services: list[str] = setting(default_factory=lambda: list(SERVICES))
    lease_ms: int = setting(ROUTER_LEASE_MS, lo=500, hi=60_000)
    connect: list[str] = setting(default_factory=list, help="other routers (a chain of sites)")
    bind_operator_keys: bool = setting(
        True, help="operators may put commands only on .../cmd/<kind>/<their name> and query only "
        ".../control/<verb>/<their name> (identity-scoped keys; edges and operators must set it too)"
    )
    replay: bool = setting(True, help="let the replay identity publish recordings under <robot>-replay ids")
    web: bool = setting(False, help="a web console (certificate web) may send for every operator, as that operator "
                                    "would, and watch every robot (iorthand web)")
    bridge: bool = setting(False, help="an MQTT bridge (certificate bridge) may publish sensor readings (sensor/**) "
                                       "of the robots and watch them (iorthand bridge mqtt)")

    def check(self) -> None:
        for r in self.robots:
            keys.check_edge_robot_id(r)
        for op, robots in self.operators.items():
            keys.check_operator_id(op)
            for r in robots:
                if r not in self.robots:
                    raise ValueError(f"operator {op!r} is granted robot {r!r}, which is not in robots {self.robots}")
        if self.bridge and not self.robots:
            raise ValueError("bridge: true needs robots: the bridge publishes sensor readings of the deployment's robots")
        for s in self.services:
            if s not in SERVICES:
                raise ValueError(f"service {s!r} is not one of {list(SERVICES)}")
        for ep in self.listen:
            if not ep.startswith(("tls/", "quic/")):
                raise ValueError(f"listen endpoint {ep!r} is not encrypted: use tls/HOST:PORT")

    def warnings(self) -> list[tuple[str, str]]:
        """Settings that load but weaken the deployment (``iorthand check`` prints them)."""
        if self.bind_operator_keys:
            return []
        return [("bind_operator_keys", "off: an operator may command and query on the plain keys of every robot "
                 "it is granted, so its certificate can command in another operator's name (the edge sees only "
                 "the name in the message); set it true, as on the edges and operators")]


def _rule(rid: str, messages: list[str], flows: list[str], key_exprs: list[str]) -> dict[str, Any]:
    return {"id": rid, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": key_exprs}


def _service_space(name: str) -> str:
    return f"{keys.ROOT}/_{name}/**"


# The services' queries that only read: all a viewer may ask. Starting, stopping or annotating a recording, and
# previews (the twin has the edge plan them), are an operator's.
READ_ONLY_QUERIES = {
    "twin": keys.service_key(keys.TWIN, "*", keys.TWIN_SNAPSHOT),
    "recorder": keys.service_key(keys.RECORDER, keys.RECORDER_STATUS),
}


def _operator_services(dep: Deployment, op: str) -> list[str]:
    """What operator ``op`` may ask the services: all of them, except that with bind_operator_keys it annotates a
    recording only on its own key (``annotate/<op>``): the recorder stores the author that key names."""
    out: list[str] = []
    for service in dep.services:
        if service == "recorder" and dep.bind_operator_keys:
            out += [keys.service_key(keys.RECORDER, verb)
                    for verb in (keys.RECORDER_START, keys.RECORDER_STOP, keys.RECORDER_STATUS)]
            out.append(keys.service_key(keys.RECORDER, keys.RECORDER_ANNOTATE, keys.check_operator_id(op)))
        else:
            out.append(_service_space(service))
    return out


def _grants(table: Iterable[Channel], role: Role, kind: Kind, *, query: bool = False,
            bound: str | None = None) -> list[str]:
    """The key suffixes ``role`` may write (``query``: query) among the ``kind`` rows of ``table``: each family
    whole (``state/**``, and the plain key where a row is the family itself: ``markers``). With ``bound`` (an
    operator's name, under bind_operator_keys) a bound family only on that operator's keys (``cmd/*/<name>``),
    plus the plain keys its rows share (``cmd/stop``)."""
    out: list[str] = []
    for fam, rows in channels.families(table, kind).items():
        if role not in (rows[0].callers if query else rows[0].writers):
            continue  # channels.check: every row of a family has the same writers, callers and operator key
        if bound is not None and rows[0].operator_key is OperatorKey.BOUND:
            out += [f"{fam}/*/{bound}", *(c.suffix for c in rows if c.shared)]
        else:
            out += _whole(fam, rows)
    return out


def _whole(fam: str, rows: list[Channel]) -> list[str]:
    """A family's keys whole: ``state/**``, and the plain key where a row is the family itself (``markers``)."""
    return [*([fam] if any(c.suffix == fam for c in rows) else []), f"{fam}/**"]


def _readable(table: Iterable[Channel]) -> list[str]:
    """The key suffixes whose puts a reader that is no robot receives: every family but the commands (the streams
    operators write). Commands are forwarded BLOCK (a stop is never dropped, see iorthand.transport.CONTROL), so
    a session that received them and stopped reading would hold up every operator's commands at the router. The
    router does not send them to it (an egress rule: a subscription to ``iorthand/<robot>/**`` still gets the rest)."""
    table = tuple(table)
    return [key for kind in Kind for fam, rows in channels.families(table, kind).items()
            if not (kind is Kind.PUT and Role.OPERATOR in rows[0].writers) for key in _whole(fam, rows)]


def _tokens(table: Iterable[Channel], role: Role, operator: str = "") -> list[str]:
    """The liveliness tokens ``role`` may declare, by exact key (an operator's carries its name)."""
    return [f"{c.suffix}/{keys.check_operator_id(operator)}" if c.operator_key is OperatorKey.ALWAYS else c.suffix
            for c in table if c.kind is Kind.TOKEN and role in c.writers]


def acl_rules(dep: Deployment, table: Iterable[Channel] = channels.TABLE) -> dict[str, Any]:
    """The ``access_control`` section (rules, subjects, policies) for ``dep``; who may write or query which
    key comes from ``table``, the table of channels."""
    table = tuple(table)
    channels.check(table)  # a family is granted whole: only sound where its rows agree
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    services = [_service_space(s) for s in dep.services]

    def add(subject: str, rule_list: list[dict[str, Any]]) -> None:
        # A rule with no key expression allows nothing, and Zenoh refuses the whole configuration for it ("Given
        # collection was empty"): a cloud router set up before its first robot, an operator granted no robot yet.
        rule_list = [r for r in rule_list if r["key_exprs"]]
        if not rule_list:
            return  # nothing granted: the default, deny
        subjects.append({"id": subject, "cert_common_names": [subject], "usernames": [subject]} if dep.users_file
                        else {"id": subject, "cert_common_names": [subject]})
        rules.extend(rule_list)
        policies.append({"id": f"policy-{subject}", "rules": [r["id"] for r in rule_list], "subjects": [subject]})

    for robot in dep.robots:
        k = keys.RobotKeys(robot)
        sid = edge_common_name(robot)
        add(sid, [
            _rule(f"{sid}-publish", ["put", "delete"], ["ingress"], [k.key(s) for s in _grants(table, Role.EDGE, Kind.PUT)]),
            _rule(f"{sid}-serve", ["declare_queryable", "reply"], ["ingress"],
                  [k.key(s) for s in _grants(table, Role.EDGE, Kind.QUERY)]),
            _rule(f"{sid}-subscribe", SUBSCRIBE, ["ingress"], [k.all]),
            _rule(f"{sid}-alive", ["liveliness_token"], ["ingress"], [k.key(s) for s in _tokens(table, Role.EDGE)]),
            _rule(f"{sid}-receive", ALL_MESSAGES, ["egress"], [k.all]),
        ])

    def operator_rules(rid: str, op: str, robots: list[str]) -> list[dict[str, Any]]:
        """What operator ``op`` may send to its robots (commands, control queries, its token)."""
        rks = [keys.RobotKeys(r) for r in robots]
        bound = op if dep.bind_operator_keys else None
        if not rks:
            return []
        return [
            _rule(f"{rid}-command", ["put"], ["ingress"],
                  [k.key(s) for k in rks for s in _grants(table, Role.OPERATOR, Kind.PUT, bound=bound)]),
            _rule(f"{rid}-control", ["query"], ["ingress"],
                  [k.key(s) for k in rks for s in _grants(table, Role.OPERATOR, Kind.QUERY, query=True, bound=bound)]),
            _rule(f"{rid}-alive", ["liveliness_token"], ["ingress"],
                  [k.key(s) for k in rks for s in _tokens(table, Role.OPERATOR, op)]),
        ]

    for op, robots in dep.operators.items():
        sid = operator_common_name(op)
        rks = [keys.RobotKeys(r) for r in robots]
        rl = [
            _rule(f"{sid}-subscribe", SUBSCRIBE, ["ingress"], [k.all for k in rks] + services),
            _rule(f"{sid}-receive", NOT_PUTS, ["egress"], [k.all for k in rks] + services),
            _rule(f"{sid}-read", PUTS, ["egress"], [k.key(s) for k in rks for s in _readable(table)] + services),
            *operator_rules(sid, op, robots),
        ]
        if services:
            rl.append(_rule(f"{sid}-services", ["query"], ["ingress"], _operator_services(dep, op)))
        add(sid, rl)

    if dep.web:
        # The web console logs its users in and sends for each operator exactly what that operator's own
        # certificate may send (on its bound keys), and watches every robot for viewers: a trusted bridge.
        everything_robots = [keys.RobotKeys(r).all for r in dep.robots]
        rl = [
            _rule(f"{WEB}-subscribe", SUBSCRIBE, ["ingress"], everything_robots + services),
            _rule(f"{WEB}-receive", ALL_MESSAGES, ["egress"], everything_robots + services),
        ]
        for op, robots in dep.operators.items():
            rl += operator_rules(f"{WEB}-{op}", op, robots)
        if services:
            rl.append(_rule(f"{WEB}-services", ["query"], ["ingress"], services))
        add(WEB, rl)

    everything = f"{keys.ROOT}/**"
    for name in [*dep.services, *(f"viewer-{v}" for v in dep.viewers)]:
        rl = [_rule(f"{name}-subscribe", SUBSCRIBE, ["ingress"], [everything])]
        if name in dep.services:  # the recorder keeps the commands; services queue what they receive
            rl.append(_rule(f"{name}-receive", ALL_MESSAGES, ["egress"], [everything]))
        else:  # an observer: what an operator reads, of every robot
            rl += [_rule(f"{name}-receive", NOT_PUTS, ["egress"], [everything]),
                   _rule(f"{name}-read", PUTS, ["egress"],
                         [f"{keys.ROOT}/*/{s}" for s in _readable(table)] + services)]
        if services:
            asked = services if name in SERVICES else [READ_ONLY_QUERIES[s] for s in dep.services]
            rl.append(_rule(f"{name}-query", ["query"], ["ingress"], asked))
        if name == Role.TWIN:  # previews for the operators (plan/**), nothing else of the robots'
            rl.append(_rule(f"{name}-plan", ["query"], ["ingress"],
                            [keys.RobotKeys(r).key(s) for r in dep.robots for s in _grants(table, Role.TWIN, Kind.QUERY, query=True)]))
        if name in SERVICES:
            own = _service_space(name)
            rl.append(_rule(f"{name}-serve", ["put", "delete", "declare_queryable", "reply", "liveliness_token"], ["ingress"], [own]))
        add(name, rl)

    if dep.bridge:
        # Writes exactly the rows naming its role (sensor readings), of the deployment's robots only: whatever an
        # MQTT broker lets through, nothing it sends reaches cmd/, control/, state/ or a liveliness token.
        bridged = [keys.RobotKeys(r) for r in dep.robots]
        add(BRIDGE, [
            _rule(f"{BRIDGE}-publish", ["put"], ["ingress"],
                  [k.key(s) for k in bridged for s in _grants(table, Role.BRIDGE, Kind.PUT)]),
            _rule(f"{BRIDGE}-subscribe", SUBSCRIBE, ["ingress"], [k.all for k in bridged]),
            _rule(f"{BRIDGE}-receive", ALL_MESSAGES, ["egress"], [k.all for k in bridged]),
        ])

    if dep.replay:
        add(REPLAY, [
            _rule(f"{REPLAY}-publish", ["put"], ["ingress"],
                  [keys.all_replays(s) for s in _grants(table, Role.REPLAY, Kind.PUT)]),
            _rule(f"{REPLAY}-receive", ALL_MESSAGES, ["egress"], [keys.all_replays("**")]),
        ])

    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def router_config(dep: Deployment) -> dict[str, Any]:
    """The full router configuration (a plain dict; :func:`to_json5` writes it)."""
    certs = Path(dep.certs_dir)
    tls = {
        "root_ca_certificate": str(certs / "ca.pem"),
        "listen_certificate": str(certs / "router.pem"),
        "listen_private_key": str(certs / "router.key"),
        "enable_mtls": True,
        # A certificate that expires while connected ends the link instead of living on until the next restart.
        "close_link_on_expiration": True,
    }
    tx = {"lease": announced_lease(dep.lease_ms, bool(dep.connect)), "queue": {"size": dict(TX_QUEUE_SIZE)}}
    transport: dict[str, Any] = {"link": {"tls": tls, "tx": tx}, "unicast": {"accept_pending": ACCEPT_PENDING},
                                 "shared_memory": {"transport_optimization": {"pool_size": SHM_POOL_SIZE}}}
    if dep.users_file is not None:
        transport["auth"] = {"usrpwd": {"dictionary_file": str(dep.users_file)}}
    cfg: dict[str, Any] = {
        "mode": "router",
        "listen": {"endpoints": list(dep.listen)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "access_control": acl_rules(dep),
        "qos": {"network": forwarding_rules()},  # a subscriber that stops reading holds up nobody
    }
    if dep.connect:
        cfg["connect"] = {"endpoints": list(dep.connect)}
    elif dep.robots:  # the router operators connect to: each session's flood of set-points is capped here (with
        # no robot yet there is nothing to cap, and Zenoh refuses an empty list of rules)
        cfg["downsampling"] = rate_limits(dep.robots)
    return cfg


def bound_operator_keys(router_cfg: dict[str, Any]) -> bool | None:
    """Whether a router configuration made by :func:`router_config` holds operators to their own command keys
    (its deployment's ``bind_operator_keys``), read back from its operators' command rules (``.../cmd/**``
    without it); None when it has none to tell by (no operator, or not made here)."""
    rules = (router_cfg.get("access_control") or {}).get("rules") or []
    commands = [k for r in rules if str(r.get("id", "")).endswith("-command") for k in r.get("key_exprs") or []]
    if not commands:
        return None
    return not any(k.endswith(f"/{channels.COMMANDS}/**") for k in commands)


def to_json5(cfg: dict[str, Any]) -> str:
    """JSON is valid JSON5; the header says where it came from so nobody hand-edits a generated file."""
    return "// generated by `iorthand certs router-config`: edit the deployment YAML and regenerate\n" + json.dumps(cfg, indent=2) + "\n"


def users_line(user: str, password: str) -> str:
    """One line of Zenoh's usrpwd dictionary file (``user:password``)."""
    if ":" in user or "\n" in user or "\n" in password:
        raise ValueError("user names may not contain ':' or newlines, passwords no newlines")
    return f"{user}:{password}\n"


__all__ = ["Deployment", "acl_rules", "bound_operator_keys", "field", "router_config", "to_json5", "users_line"]
