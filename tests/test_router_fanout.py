"""A subscriber that stops reading costs the others nothing at the router.

Found by trial (2026-11-29): a second console whose subscriber callback hung (its session alive, its keep-alives
flowing) made the router stop forwarding the edge's state to everyone for 5 s, about 40 s after it hung, and the
edge lost its link: a message published with congestion control BLOCK (the safety status, the force level) is
forwarded with it, so the router's thread that reads the publisher's link waited for room in the hung
subscriber's queue (Zenoh's ``wait_before_close``, 5 s) and read nothing else from that link meanwhile. The
router now drops them for a subscriber whose link is full (:func:`iorthand.transport.forwarding_rules`). Here
the publisher sends faster than a hung link can absorb, so that its queues fill within seconds. (Commands stay
BLOCK when forwarded: see ``iorthand.transport.CONTROL``.)
"""

from __future__ import annotations

import threading
import time

import pytest
import zenoh

from iorthand import keys
from iorthand.transport import client_config, open_session, publisher

PAYLOAD = bytes(2048)
RATE_HZ = 1000  # ~2 MB/s: a hung subscriber's socket buffers and queues fill in a few seconds
SECONDS = 10.0


@pytest.mark.parametrize("suffix", [keys.STATE_SAFETY, keys.STATE_FORCE_LEVEL])
def test_a_subscriber_that_stops_reading_does_not_hold_up_the_others(router_endpoint: str, suffix: str) -> None:
    key = keys.RobotKeys("r1").key(suffix)
    source = open_session(client_config(router_endpoint))
    healthy = open_session(client_config(router_endpoint))
    hung = open_session(client_config(router_endpoint))
    release = threading.Event()
    arrivals: list[float] = []
    try:
        healthy_sub = healthy.declare_subscriber(key, lambda _s: arrivals.append(time.monotonic()))

        def stuck(_sample: zenoh.Sample) -> None:  # a console whose callback never returns: it reads no more
            release.wait(60)

        hung_sub = hung.declare_subscriber(key, stuck)
        pub = publisher(source, key)  # the channel's own QoS: BLOCK, reliable
        time.sleep(0.5)
        start = time.monotonic()
        longest_put = 0.0
        n = 0
        while (now := time.monotonic()) - start < SECONDS:
            pub.put(PAYLOAD)
            longest_put = max(longest_put, time.monotonic() - now)
            n += 1
            time.sleep(max(0.0, start + n / RATE_HZ - time.monotonic()))
        end = time.monotonic()
        time.sleep(0.3)
        seen = [t for t in arrivals if start <= t <= end]
        gaps = [b - a for a, b in zip([start, *seen], [*seen, end], strict=True)]
        # Before: the healthy subscriber got nothing for 2.7-5 s once the hung one's queues were full, and the
        # publisher's puts waited as long.
        assert max(gaps) < 1.0, f"the healthy subscriber waited {max(gaps):.2f} s ({len(seen)} of {n} arrived)"
        assert longest_put < 1.0, f"a put waited {longest_put:.2f} s"
        assert len(seen) > 0.5 * n, f"only {len(seen)} of {n} reached the healthy subscriber"
    finally:
        release.set()
        for s in (source, healthy, hung):
            s.close()
    del healthy_sub, hung_sub
