"""``iorthand bridge mqtt --config configs/bridge-mqtt.yaml``: mirror configured keys between Zenoh and an MQTT
broker. Registered through the ``iorthand.commands`` entry point (``bridge = "iorthand_cloud.bridge.cli:register"``)."""

from __future__ import annotations

import argparse
import signal
import sys

from iorthand.config import load
from iorthand.transport import ZenohConfig


def _mqtt(args: argparse.Namespace) -> int:
    from iorthand_cloud.bridge.config import BridgeConfig
    from iorthand_cloud.bridge.mapping import OutRoute

    cfg = load(args.config, BridgeConfig)  # a refused mapping fails here, naming the file and the mapping
    if args.connect:
        cfg.zenoh = ZenohConfig(mode="client", connect=list(args.connect), connect_retry_s=cfg.zenoh.connect_retry_s)
    if args.check:
        for r in cfg.routes():
            if isinstance(r, OutRoute):
                print(f"{r.name}: out {', '.join(r.exprs)} → mqtt {r.topic.text} (QoS {r.qos}, ≤ {r.max_hz:g} Hz per robot)")
            else:
                print(f"{r.name}: in mqtt {r.topic.subscription} → {r.key.text} ({r.message.__name__}, QoS {r.qos})")
        for key, problem in cfg.warnings():
            print(f"warning: {key}: {problem}")
        return 0
    from iorthand_cloud.bridge.mqtt import MqttBridge

    bridge = MqttBridge(cfg)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: bridge.stop_event.set())
    bridge.run_forever()
    return 0


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bridge", help="mirror keys between Zenoh and another middleware (mqtt)")
    bsub = p.add_subparsers(dest="bridge", metavar="KIND", required=True)
    m = bsub.add_parser("mqtt", help="robot state out to an MQTT broker as JSON, sensor readings in (vital signs)")
    m.add_argument("--config", required=True, help="bridge YAML, e.g. configs/bridge-mqtt.yaml")
    m.add_argument("--connect", action="append", help="Zenoh router endpoint, overrides the config (repeatable)")
    m.add_argument("--check", action="store_true", help="validate the configuration, print the mappings and exit")
    m.set_defaults(func=_mqtt)


if __name__ == "__main__":  # development, before the entry point is installed: python -m iorthand_cloud.bridge.cli
    import iorthand.cli as core

    _core_parser = core.build_parser

    def _parser_with_bridge() -> argparse.ArgumentParser:
        parser = _core_parser()
        sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
        if "bridge" not in sub.choices:
            register(sub)
        return parser

    core.build_parser = _parser_with_bridge
    sys.exit(core.main())
