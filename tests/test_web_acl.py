"""The web console's identity behind the deployment's mTLS + ACL: a trusted bridge that may send for each
operator exactly what that operator's own certificate may (its bound keys), and for nobody else."""

from __future__ import annotations

import time

import pytest
import zenoh

from iorthand.security.lab import make_lab
from iorthand.transport import free_port, open_session
from iorthand_operator.client import ControlRefused, OperatorClient
from tests.conftest import edge_config

pytestmark = pytest.mark.slow


def test_the_web_identity_commands_for_the_deployments_operators_only(tmp_path) -> None:
    from iorthand_edge.agent import EdgeAgent

    lab = make_lab(tmp_path, free_port(), robots=["sim1"], operators={"alice": ["sim1"]}, viewers=["sam"],
                   bind_operator_keys=True, web=True)
    router = zenoh.open(zenoh.Config.from_file(str(lab.router_config)))
    edge_zenoh = lab.client("edge-sim1", retry_s=10.0)
    agent = EdgeAgent(edge_config(lab.endpoint, "sim1", bind_operator_keys=True, zenoh={
        "mode": "client", "connect": [lab.endpoint], "connect_retry_s": 10.0,
        "tls": {"root_ca": str(edge_zenoh.tls.root_ca), "certificate": str(edge_zenoh.tls.certificate),
                "private_key": str(edge_zenoh.tls.private_key)},
        "username": edge_zenoh.username, "password_file": str(edge_zenoh.password_file)}))
    agent.start()
    web = open_session(lab.client("web"))
    try:
        alice = OperatorClient(web, "sim1", "alice", bind_keys=True, external_sender=True)
        alice.wait_for_state()
        alice.acquire()
        alice.start()
        x0 = alice.robot_state.tcp_pose[0]
        for _ in range(300):  # the page's stream: one command per message
            alice.send_now([0.004, 0.0, 0.0], [0.0, 0.0, 0.0], True)
            if alice.robot_state.tcp_pose[0] > x0 + 0.0005:
                break
            time.sleep(1 / 60)
        assert alice.robot_state.tcp_pose[0] > x0 + 0.0005, "the web identity moved alice's robot"
        alice.close()
        # In the name of someone the deployment does not make an operator, the router routes nothing.
        mallory = OperatorClient(web, "sim1", "mallory", bind_keys=True, external_sender=True, query_timeout=1.0)
        with pytest.raises(ControlRefused, match="no answer"):
            mallory.acquire()
        mallory.close()
        assert agent.supervisor.owner == ""
    finally:
        web.close()
        agent.shutdown()
        router.close()
