"""Property-based hostile input for every decoder and every config loader (hypothesis).

Nothing crashes: a decoder raises only DecodeError, a config loader only ConfigError; what decodes obeys its
declared bounds (finite numbers, sizes); replayed, reordered and badly-timed commands never move the robot;
the agent's reject log is rate-limited and its inboxes are bounded.
"""

from __future__ import annotations

import contextlib
import logging
import math
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from iorthand import protocol
from iorthand.config import ConfigError, from_dict, load
from iorthand.protocol import DecodeError, Message, TwistCommand
from iorthand.security.acl import Deployment
from iorthand.transport import Inbox, ZenohConfig

FAST = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _all_messages() -> list[type[Message]]:
    seen: dict[str, type[Message]] = {}
    stack = list(Message.__subclasses__())
    while stack:
        cls = stack.pop()
        seen[cls.__name__] = cls
        stack += cls.__subclasses__()
    return sorted(seen.values(), key=lambda c: c.__name__)


MESSAGES = _all_messages()
assert len(MESSAGES) >= 15

scalars = st.one_of(
    st.none(), st.booleans(), st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=80), st.binary(max_size=80),
)
values = st.recursive(scalars, lambda inner: st.one_of(st.lists(inner, max_size=8), st.dictionaries(st.text(max_size=12), inner, max_size=8)), max_leaves=40)


def _decode_or_reject(cls: type[Message], payload: bytes) -> Message | None:
    try:
        msg = cls.decode(payload)
    except DecodeError:
        return None
    _assert_sane(msg._to_map())
    return msg


def _assert_sane(v: object) -> None:
    if isinstance(v, float):
        assert math.isfinite(v)
    elif isinstance(v, dict):
        for x in v.values():
            _assert_sane(x)
    elif isinstance(v, list):
        for x in v:
            _assert_sane(x)


@pytest.mark.parametrize("cls", MESSAGES, ids=lambda c: c.__name__)
@FAST
@given(data=st.binary(max_size=512))
def test_random_bytes(cls: type[Message], data: bytes) -> None:
    _decode_or_reject(cls, data)


@pytest.mark.parametrize("cls", MESSAGES, ids=lambda c: c.__name__)
@FAST
@given(data=values, version=st.sampled_from([1, 0, 2, True, "1", None]))
def test_random_structures(cls: type[Message], data: object, version: object) -> None:
    """Maps with the right and wrong fields, wrong types, NaN/inf, extreme numbers, nested junk."""
    if isinstance(data, dict):
        data = {**data, "v": version}
    _decode_or_reject(cls, msgpack.packb(data, use_bin_type=True))


@pytest.mark.parametrize("cls", MESSAGES, ids=lambda c: c.__name__)
@FAST
@given(data=st.data())
def test_valid_fields_with_one_poisoned(cls: type[Message], data: st.DataObject) -> None:
    """A valid message with one field replaced by something hostile; and every truncation of a valid one."""
    valid = cls().stamp(1).encode()
    for cut in range(0, len(valid), max(1, len(valid) // 7)):
        _decode_or_reject(cls, valid[:cut])
    wire = msgpack.unpackb(valid)
    name = data.draw(st.sampled_from(sorted(wire)))
    wire[name] = data.draw(st.one_of(scalars, st.just(float("nan")), st.just(float("-inf")), st.just(2**64 - 1), st.just(-(2**63)),
                                     st.just([1e308] * 3), st.just([0.0] * 100_000)))
    _decode_or_reject(cls, msgpack.packb(wire, use_bin_type=True))


@pytest.mark.parametrize(
    "payload",
    [
        b"\x91" * 100_000 + b"\xc0",  # deep nesting
        b"\x81\xa1a" * 50_000 + b"\xc0",  # deep maps
        b"\xdd\xff\xff\xff\xff",  # array claiming 4 G elements, no data
        b"\xdf\xff\xff\xff\xff",  # map claiming 4 G pairs
        b"\xc6\xff\xff\xff\xff",  # bin claiming 4 GB
        msgpack.packb(list(range(200_000))),  # a huge real array (over the size limit)
        b"\xc1",  # never-used byte
        b"",
    ],
    ids=["deep-arrays", "deep-maps", "huge-array-header", "huge-map-header", "huge-bin-header", "huge-array", "c1", "empty"],
)
def test_pathological_payloads(payload: bytes) -> None:
    for cls in MESSAGES:
        t0 = time.perf_counter()
        _decode_or_reject(cls, payload)
        assert time.perf_counter() - t0 < 1.0


# ------------------------------------------------------------------------------------------------ configs


def _role_configs() -> list[type]:
    from iorthand_edge.config import EdgeConfig
    from iorthand_operator.config import OperatorConfig

    return [EdgeConfig, OperatorConfig, ZenohConfig, Deployment]


@pytest.mark.parametrize("cls", _role_configs(), ids=lambda c: c.__name__)
@FAST
@given(data=values)
def test_config_loaders_reject_garbage_cleanly(cls: type, data: object) -> None:
    with contextlib.suppress(ConfigError):
        from_dict(data, cls, source="<hostile>")


@pytest.mark.parametrize("cls", _role_configs(), ids=lambda c: c.__name__)
@FAST
@given(data=st.data())
def test_config_loaders_with_one_poisoned_key(cls: type, data: st.DataObject) -> None:
    base = {
        "robot_id": "sim1", "operator_id": "alice", "robot": {"kind": "sim"},
        "zenoh": {"mode": "client", "connect": ["tcp/127.0.0.1:7447"]}, "connect": ["tcp/127.0.0.1:7447"],
        "robots": ["sim1"], "operators": {"alice": ["sim1"]},
    }
    import dataclasses

    names = {f.name for f in dataclasses.fields(cls)}
    doc = {k: v for k, v in base.items() if k in names}
    key = data.draw(st.sampled_from(sorted(names)))
    doc[key] = data.draw(values)
    with contextlib.suppress(ConfigError):
        from_dict(doc, cls, source="<hostile>")


@FAST
@given(text=st.text(max_size=400))
def test_yaml_files_of_garbage(tmp_path_factory: pytest.TempPathFactory, text: str) -> None:
    from iorthand_edge.config import EdgeConfig

    p = tmp_path_factory.mktemp("y") / "edge.yaml"
    p.write_text(text)
    with contextlib.suppress(ConfigError):
        load(p, EdgeConfig)


def test_yaml_alias_bomb_is_fast(tmp_path: Path) -> None:
    """A billion-laughs document must fail fast, not expand."""
    from iorthand_edge.config import EdgeConfig

    lines = ['a: &a ["x","x","x","x","x","x","x","x","x"]']
    for i in range(1, 9):
        prev = chr(ord("a") + i - 1)
        cur = chr(ord("a") + i)
        lines.append(f"{cur}: &{cur} [*{prev},*{prev},*{prev},*{prev},*{prev},*{prev},*{prev},*{prev},*{prev}]")
    lines.append("robot_id: *i")
    p = tmp_path / "bomb.yaml"
    p.write_text("\n".join(lines))
    t0 = time.perf_counter()
    with pytest.raises(ConfigError):
        load(p, EdgeConfig)
    assert time.perf_counter() - t0 < 2.0


# ------------------------------------------------------------------------------------------------ sequences


@FAST
@given(events=st.lists(st.tuples(st.integers(min_value=0, max_value=40), st.floats(min_value=-1e4, max_value=1e4)), min_size=1, max_size=60))
def test_replayed_reordered_and_mistimed_commands_never_move(events: list[tuple[int, float]]) -> None:
    """seq replays/reorders and source times from the far past/future: an accepted command is always newer than
    every earlier accepted one and within max_command_age of the receive time."""
    from iorthand_edge.supervisor import SafetyConfig, Supervisor
    from tests.grants import Grants

    cfg = SafetyConfig(auto_arm=True)
    sup = Supervisor(cfg)
    now = 1000.0
    alice = Grants()
    assert alice.acquire(sup, "alice", now)[0]
    last_seq = 0
    wall = 1.7e9
    for seq, offset in events:
        cmd = TwistCommand(operator="alice", linear=[0.001, 0, 0], deadman=True, state_age=0.02)
        cmd.seq, cmd.t = seq, max(0, int((wall + offset) * 1e9))
        alice.sign(sup, "alice", cmd)  # alice's own session: only the sequence and the time are hostile
        before = sup._target.copy()
        d = sup.on_command(cmd, wall, now, np.array([0.3, 0, 0.2, 3.14, 0, 0]))
        if d.accepted:
            assert seq > last_seq
            assert abs(offset) <= cfg.max_command_age + 1e-6
            last_seq = seq
        else:  # a refused command changes nothing: the robot keeps doing what the last accepted one said
            assert np.array_equal(sup._target, before)
        now += 0.01
        wall += 0.01


def test_inbox_is_bounded_under_a_flood() -> None:
    box = Inbox(64, keep="newest")
    for i in range(100_000):
        box.put(i)
    assert len(box) == 64 and box.dropped == 100_000 - 64
    assert box.drain()[-1] == 99_999


def test_a_set_point_inbox_keeps_the_newest_of_each_key_and_a_flood_on_one_key_pushes_out_no_other() -> None:
    box = Inbox(4, keep="newest_per_key")
    box.put(("cmd/servo/alice", "alice-1", 0), 10)
    for i in range(100_000):
        box.put(("cmd/servo/mallory", f"mallory-{i}", 0), 10)
    box.put(("cmd/torch/alice", "torch", 0), 10)
    assert box.drain() == [("cmd/servo/alice", "alice-1", 0), ("cmd/servo/mallory", "mallory-99999", 0),
                           ("cmd/torch/alice", "torch", 0)]
    assert box.dropped == 99_999
    for i in range(6):  # more keys than it holds: the oldest key's goes
        box.put((f"k{i}", i, 0))
    assert [item[0] for item in box.drain()] == ["k2", "k3", "k4", "k5"] and box.nbytes == 0


def test_inbox_is_bounded_in_bytes_too() -> None:
    """A queue of large items (video frames) is bounded by their bytes, not only by their count."""
    oldest = Inbox(10_000, keep="oldest", max_bytes=1_000_000)
    for i in range(100):
        oldest.put(i, 300_000)
    assert len(oldest) == 3 and oldest.nbytes == 900_000 and oldest.dropped == 97
    assert oldest.get() == 0 and oldest.nbytes == 600_000
    oldest.put("small", 10)  # room again: accepted
    assert oldest.drain() == [1, 2, "small"] and oldest.nbytes == 0
    newest = Inbox(10_000, keep="newest", max_bytes=1_000_000)
    for i in range(10):
        newest.put(i, 300_000)
    newest.put("big", 700_000)  # makes room by dropping as many of the oldest as needed
    assert newest.drain() == [9, "big"] and newest.dropped == 9
    single = Inbox(10, keep="oldest", max_bytes=100)
    single.put("larger than the bound", 500)  # an empty queue takes any one item: nothing is stuck forever
    assert len(single) == 1


def test_inbox_hands_a_waiting_worker_its_item_and_loses_none_when_waits_time_out() -> None:
    """The worker waiting in get() gets the next put directly; items that come while it works wait in order; a
    wait that times out as an item arrives loses nothing; close() wakes a waiting worker."""
    box = Inbox(10_000, keep="oldest")
    got: list = []
    worker = threading.Thread(target=lambda: got.append(box.get(timeout=5.0)))
    worker.start()
    time.sleep(0.05)  # the worker waits
    box.put("handed over", 10)
    worker.join(2.0)
    assert got == ["handed over"] and len(box) == 0 and box.nbytes == 0
    assert box.get(timeout=0.01) is None  # nothing left, not the same item twice

    # Timeouts racing the producer: every item arrives once, in order.
    n, received = 5_000, []

    def consume() -> None:
        while len(received) < n:
            item = box.get(timeout=0.0002)
            if item is not None:
                received.append(item)

    consumer = threading.Thread(target=consume)
    consumer.start()
    for i in range(n):
        box.put(i)
        if i % 7 == 0:
            time.sleep(0.0001)
    consumer.join(30.0)
    assert received == list(range(n))

    waiter = threading.Thread(target=lambda: got.append(box.get()))
    waiter.start()
    time.sleep(0.05)
    box.close()
    waiter.join(2.0)
    assert not waiter.is_alive() and got[-1] is None


def test_reject_log_is_rate_limited(caplog: pytest.LogCaptureFixture) -> None:
    from iorthand_edge.agent import RateLimitedLog

    rl = RateLimitedLog(logging.getLogger("test.ratelimit"), interval=60.0)
    with caplog.at_level(logging.WARNING, logger="test.ratelimit"):
        for i in range(10_000):
            rl.warning("malformed:k", f"rejected {i}")
    assert len(caplog.records) == 1


def test_every_decoder_is_covered() -> None:
    assert set(protocol.MESSAGES_BY_KEY.values()) <= set(MESSAGES)


def test_items_put_ahead_go_first_into_room_of_their_own() -> None:
    """The planning queue's reserve for the owner (EdgeAgent: OWNER_PLANNING): a full queue still takes an item
    put ahead, serves it before the others, and beyond the reserve treats it as any other."""
    inbox = Inbox(2, keep="oldest", reserve=1)
    assert inbox.put("a") and inbox.put("b") and not inbox.put("c")
    assert inbox.put("owner", ahead=True)
    assert not inbox.put("owner again", ahead=True)  # the reserve holds one: a full queue refuses the next
    assert [inbox.get(0), inbox.get(0), inbox.get(0), inbox.get(0)] == ["owner", "a", "b", None]
    assert inbox.put("x") and inbox.put("owner 2", ahead=True) and inbox.put("y")
    assert [inbox.get(0), inbox.get(0), inbox.get(0)] == ["owner 2", "x", "y"]
    with pytest.raises(ValueError, match="reserve"):
        Inbox(2, keep="newest", reserve=1)
