"""Protocol: every message round-trips; every kind of bad input is rejected with the field named."""

from __future__ import annotations

import dataclasses
import math

import msgpack
import pytest

from iorthand import keys, protocol
from iorthand.protocol import DecodeError, ForceLevel, MarkerPose, Markers, Message, TwistCommand, VideoFrame

ALL_MESSAGES = sorted(
    {cls for cls in vars(protocol).values() if isinstance(cls, type) and issubclass(cls, Message) and cls is not Message},
    key=lambda c: c.__name__,
)


def sample(cls: type[Message]) -> Message:
    """An instance with non-default values in every field that has a sensible one."""
    msg = cls()
    for f in dataclasses.fields(cls):
        value = getattr(msg, f.name)
        if isinstance(value, bool):
            setattr(msg, f.name, not value)
        elif isinstance(value, list) and value and isinstance(value[0], float):
            setattr(msg, f.name, [0.001 * (i + 1) for i in range(len(value))])
    if cls is protocol.VideoFrame:
        msg.width, msg.height, msg.data = 640, 480, b"\xff\xd8jpeg"
    if cls is protocol.Markers:
        msg.markers = [protocol.MarkerPose(id=7, reprojection_error=0.3, pixel_size=55.0)]
    return msg.stamp(42)


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.__name__)
def test_every_message_round_trips(cls: type[Message]) -> None:
    msg = sample(cls)
    decoded = cls.decode(msg.encode())
    assert decoded == msg
    assert decoded.seq == 42 and decoded.t > 0


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.__name__)
def test_the_encoding_is_the_wire_map_with_v_first(cls: type[Message]) -> None:
    """The wire form is exactly the map {v, then every field in declaration order} as the independent msgpack
    library writes it: a signature covers these bytes, and any other encoder of the protocol must match them."""
    msg = sample(cls)
    data = {"v": cls.VERSION, **{f.name: getattr(msg, f.name) for f in dataclasses.fields(cls)}}
    expected = msgpack.packb(data, use_bin_type=True, default=dataclasses.asdict)
    assert msg.encode() == expected


def twist_map(**changes: object) -> dict:
    data = {"v": 1, "seq": 3, "t": 1_700_000_000_000_000_000, "operator": "op", "linear": [0.01, 0.0, 0.0],
            "angular": [0.0, 0.0, 0.0], "deadman": True}
    data.update(changes)
    return data


@pytest.mark.parametrize(
    ("changes", "field", "problem"),
    [
        ({"linear": [0.0, "x", 0.0]}, "linear[1]", "expected float"),
        ({"linear": [0.0, 0.0, True]}, "linear[2]", "expected float"),
        ({"angular": [0.0, -50.0, 0.0]}, "angular[1]", "below the minimum"),
        ({"deadman": 1}, "deadman", "expected bool"),
        ({"operator": 5}, "operator", "expected str"),
        ({"linear": [math.nan, 0.0, 0.0]}, "linear[0]", "finite"),
        ({"angular": [0.0, math.inf, 0.0]}, "angular[1]", "finite"),
        ({"linear": [0.0, 0.0]}, "linear", "expected 3 elements"),
        ({"linear": [50.0, 0.0, 0.0]}, "linear[0]", "above the maximum"),
        ({"seq": -1}, "seq", "below the minimum"),
        ({"t": 2**63}, "t", "out of the 64-bit range"),
        ({"v": 2}, "v", "unknown schema version"),
        ({"surprise": 1}, "surprise", "unknown field"),
        ({"operator": "x" * 65}, "operator", "exceeds"),
    ],
)
def test_bad_fields_are_rejected_by_name(changes: dict, field: str, problem: str) -> None:
    with pytest.raises(DecodeError) as err:
        TwistCommand.decode(msgpack.packb(twist_map(**changes)))
    assert err.value.field == field
    assert problem in str(err.value)
    assert str(err.value).startswith(f"TwistCommand.{field}")


def test_integer_vector_elements_arrive_as_floats() -> None:
    """msgpack sends 1.0 as 1 from some encoders: a vector of ints is accepted and becomes floats."""
    cmd = TwistCommand.decode(msgpack.packb(twist_map(linear=[0, 1, 0], angular=[0.5, 0, -1])))
    assert cmd.linear == [0.0, 1.0, 0.0] and cmd.angular == [0.5, 0.0, -1.0]
    assert all(type(v) is float for v in (*cmd.linear, *cmd.angular))


@pytest.mark.parametrize("missing", ["v", "seq", "t", "operator", "linear", "angular", "deadman"])
def test_missing_fields_are_named(missing: str) -> None:
    data = twist_map()
    del data[missing]
    with pytest.raises(DecodeError) as err:
        TwistCommand.decode(msgpack.packb(data))
    assert err.value.field == missing
    assert "missing" in str(err.value)


def test_a_field_added_later_defaults_in_older_payloads_and_no_other_does() -> None:
    """Markers.failure came after the first release: markers from an older edge or in an older recording still
    decode (no failure), while a missing field of the first schema is still refused by name."""
    older = msgpack.unpackb(Markers(frames=3).stamp(1).encode())
    del older["failure"]
    assert Markers.decode(msgpack.packb(older)).failure == ""
    del older["frames"]
    with pytest.raises(DecodeError, match=r"Markers\.frames"):
        Markers.decode(msgpack.packb(older))
    frame = msgpack.unpackb(VideoFrame(width=2, height=2, data=b"jpeg").stamp(1).encode())
    del frame["failure"]  # VideoFrame.failure came later too
    assert VideoFrame.decode(msgpack.packb(frame)).failure == ""


def test_servo_and_torch_states_say_their_heartbeat_period_and_older_ones_still_decode() -> None:
    """ServoState.period and TorchState.period came later (the operator ages its rows by the edge's heartbeat):
    a state from an older edge, or in an older recording, decodes with period 0 (not said)."""
    for cls in (protocol.ServoState, protocol.TorchState):
        assert cls.decode(cls(period=5.0).stamp(1).encode()).period == 5.0
        older = msgpack.unpackb(cls(period=5.0).stamp(1).encode())
        del older["period"]
        assert cls.decode(msgpack.packb(older)).period == 0.0  # the fast decoder
        older["v"] = 1.0  # a version the fast schema refuses: the checked decoder, too
        assert cls.decode(msgpack.packb(older)).period == 0.0
        with pytest.raises(DecodeError, match=rf"{cls.__name__}\.period"):
            cls.decode(msgpack.packb({**older, "period": -1.0}))


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\x93\x01\x02\x03", msgpack.packb([1, 2]), msgpack.packb("text"), b"\xdd\xff\xff\xff\xff"])
def test_garbage_payloads_are_rejected(payload: bytes) -> None:
    with pytest.raises(DecodeError) as err:
        TwistCommand.decode(payload)
    assert err.value.field == "payload"


def test_numpy_values_encode_as_plain_numbers() -> None:
    import numpy as np

    cmd = protocol.ServoCommand(pan=np.radians(96.0), tilt=np.float32(1.5)).stamp(1)
    twist = TwistCommand(linear=np.array([0.01, 0.0, 0.0]), deadman=np.bool_(True)).stamp(2)
    assert protocol.ServoCommand.decode(cmd.encode()).pan == pytest.approx(np.radians(96.0))
    assert TwistCommand.decode(twist.encode()).deadman is True


def test_oversized_payload_rejected_before_parsing() -> None:
    with pytest.raises(DecodeError, match="exceeds the limit"):
        TwistCommand.decode(b"\x00" * (protocol.MAX_PAYLOAD + 1))


def test_encode_refuses_what_decode_would_refuse() -> None:
    with pytest.raises(DecodeError):
        TwistCommand(linear=[math.nan, 0, 0]).validate()


def test_nested_marker_errors_name_the_element() -> None:
    msg = sample(protocol.Markers)
    data = msgpack.unpackb(msg.encode())
    data["markers"][0]["pose"][3] = math.inf
    with pytest.raises(DecodeError) as err:
        protocol.Markers.decode(msgpack.packb(data))
    assert "markers[0]" in str(err.value) and "pose[3]" in str(err.value)


def test_force_level_codes_are_fixed() -> None:
    # The reference implementation shipped these inverted between robot and app: pin them.
    assert (ForceLevel.SAFE, ForceLevel.CAUTION, ForceLevel.DANGER) == (0, 1, 2)
    assert protocol.FORCE_LEVEL_COLOURS[ForceLevel.DANGER] == "red"


def test_keys_are_built_in_one_place() -> None:
    k = keys.RobotKeys("ur3e-lab_1")
    assert k.key(keys.CMD_TWIST) == "iorthand/ur3e-lab_1/cmd/twist"
    assert keys.split_key(k.key(keys.STATE_ROBOT)) == ("ur3e-lab_1", "state/robot")
    assert protocol.message_type_for(k.key(keys.STATE_ROBOT)) is protocol.RobotState
    assert protocol.message_type_for("iorthand/_twin/x/snapshot") is None
    assert all(keys.is_command_key(k.key(s)) for s in (keys.CMD_TWIST, keys.CMD_STOP, f"{keys.CMD_TWIST}/alice"))
    assert not any(keys.is_command_key(x) for x in (k.key(keys.STATE_APPLIED), "iorthand/_recorder/cmd/x", "other/r/cmd/x"))
    for bad in ("UR3", "a/b", "", "x" * 65, "*"):
        with pytest.raises(keys.KeyExprError):
            keys.RobotKeys(bad)


# ------------------------------------------------------------------------ the fast decoder never accepts more

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_edges = st.sampled_from([math.nan, math.inf, -math.inf, 1e308, 2**63 - 1, 2**63, -(2**63), 2**64 - 1, 0, -1, True,
                          "", b"", 1.0])
_hostile = st.one_of(
    _edges, st.lists(_edges, min_size=1, max_size=17),
    st.none(), st.booleans(), st.integers(min_value=-(2**63), max_value=2**64 - 1),
    st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=300), st.binary(max_size=40),
    st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**63), 2**63), st.booleans(),
                       st.text(max_size=3)),
             max_size=20),
)


def _outcome(decode, payload: bytes):
    try:
        return decode(payload)
    except DecodeError:
        return None


@pytest.mark.parametrize("cls", ALL_MESSAGES, ids=lambda c: c.__name__)
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_the_fast_decoder_accepts_only_what_the_checked_one_accepts(cls: type[Message], data) -> None:
    """Message.decode takes msgspec's compiled schema first and the checked decoder for everything else: a payload
    that the schema accepts must decode to the very message the checked decoder makes of it (the schema is
    derived from the same declarations; a mistake there would let through what the bounds refuse)."""
    base = msgpack.unpackb(sample(cls).encode())
    name = data.draw(st.sampled_from([*base, "v", "surprise"]))
    mutated = dict(base)
    if data.draw(st.booleans()) and name in mutated:
        del mutated[name]
    else:
        mutated[name] = data.draw(_hostile)
    payload = msgpack.packb(mutated, use_bin_type=True)
    try:
        fast = cls._from_wire(cls._decoder().decode(payload))
    except Exception:
        return  # the checked decoder decides (test_bad_fields_are_rejected_by_name and the hostile tests)
    checked = _outcome(cls._decode_checked, payload)
    assert checked is not None, f"the fast decoder accepted what the checked one refuses: {mutated!r}"
    assert fast == checked


def test_a_signed_message_ends_with_its_mac() -> None:
    """auth signs the bytes before the MAC: every signed type declares mac last, and encodes it last."""
    signed = [cls for cls in ALL_MESSAGES if cls.SIGNED]
    assert {c.__name__ for c in signed} >= {"TwistCommand", "ServoCommand", "TorchCommand", "ControlRequest"}
    for cls in signed:
        payload = sample(cls).encode()
        assert list(msgpack.unpackb(payload))[-1] == "mac", cls.__name__


def test_a_sequencer_counts_from_one_without_duplicates_across_threads() -> None:
    import threading

    seq = protocol.Sequencer()
    drawn: list[list[int]] = [[] for _ in range(4)]

    def draw(out: list[int]) -> None:
        for _ in range(20_000):
            out.append(seq.next())

    threads = [threading.Thread(target=draw, args=(out,)) for out in drawn]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    every = sorted(n for out in drawn for n in out)
    assert every == list(range(1, 80_001))
    assert all(out == sorted(out) for out in drawn)  # each publisher's own numbers only rise


# ---------------------------------------------------------------------------------------------------------
# Releases of different ages (tests/test_version_skew.py runs them against each other)


def _with(msg: Message, **added: object) -> bytes:
    return msgpack.packb({**msgpack.unpackb(msg.encode()), **added})


@pytest.mark.parametrize("msg", [protocol.ServoState(), protocol.TorchState(), protocol.ForceSample(), Markers(),
                                 VideoFrame(width=2, height=2), protocol.SensorReading(), protocol.TwinSnapshot()],
                         ids=lambda m: type(m).__name__)
def test_a_display_only_message_with_a_newer_field_is_read_without_it(msg: Message) -> None:
    cls = type(msg)
    read = cls.decode(_with(msg.stamp(4, 5), zoom=2.0, later={"a": 1}))
    assert read == msg and read.ignored == ("zoom", "later")
    assert cls.decode(msg.encode()).ignored == ()


@pytest.mark.parametrize("cls", [TwistCommand, protocol.StopCommand, protocol.ServoCommand, protocol.TorchCommand,
                                 protocol.RobotState, protocol.SafetyStatus, protocol.AppliedCommand,
                                 protocol.ForceLevelState, protocol.ControlRequest, protocol.ControlReply])
def test_a_command_or_safety_state_with_a_newer_field_is_refused_whole_and_says_the_sender_is_newer(
        cls: type[Message]) -> None:
    with pytest.raises(DecodeError) as err:
        cls.decode(_with(cls().stamp(1, 1), surprise=1))
    assert err.value.field == "surprise" and err.value.newer
    assert "unknown field: the sender is newer: update this program" in str(err.value)


def test_a_newer_senders_refusals_are_logged_once_per_key(caplog: pytest.LogCaptureFixture) -> None:
    rejects = protocol.RejectCounter()
    payload = _with(protocol.SafetyStatus().stamp(1, 1), surprise=1)
    for _ in range(50):
        for key in ("iorthand/r1/state/safety", "iorthand/r2/state/safety"):
            try:
                protocol.SafetyStatus.decode(payload)
            except DecodeError as exc:
                rejects.add(key, str(exc))
    rejects.add("iorthand/r1/state/safety", "SafetyStatus.armed: expected bool, got int")  # not a newer sender's
    lines = [r.getMessage() for r in caplog.records if r.name == "iorthand.protocol"]
    assert len(lines) == 2 and rejects.counts["iorthand/r1/state/safety"] == 51
    assert lines[0].startswith("iorthand/r1/state/safety: refused: SafetyStatus.surprise: unknown field: the sender "
                               "is newer: update this program")


def test_what_a_receiver_of_an_older_revision_cannot_read() -> None:
    sent = [protocol.RobotState, protocol.SafetyStatus, protocol.ServoState, protocol.TorchState, Markers]
    assert protocol.unreadable_by(1, sent) == ["ServoState.period", "TorchState.period"]
    assert protocol.unreadable_by(protocol.REVISION, sent) == []
    assert protocol.unreadable_by(1, [protocol.RobotState]) == []
    # From TOLERANT_SINCE on, a field added to a display-only message costs an older receiver nothing, and one added
    # to safety state or a command costs it the whole message (nested maps count with theirs).
    later = protocol.REVISION + 1
    added = {"ServoState": frozenset({"zoom"}), "MarkerPose": frozenset({"size"}),
             "SafetyStatus": frozenset({"why"})}
    original = dict(protocol.ADDED_IN)
    protocol.ADDED_IN[later] = added
    try:
        assert protocol.unreadable_by(protocol.REVISION, sent) == ["SafetyStatus.why"]
        assert protocol.unreadable_by(1, sent) == ["ServoState.period", "TorchState.period", "ServoState.zoom",
                                                   "MarkerPose.size", "SafetyStatus.why"]
    finally:
        protocol.ADDED_IN.clear()
        protocol.ADDED_IN.update(original)


def _with_nested(msg: Message, field_name: str, extras: list[dict[str, object]], **added: object) -> bytes:
    """``msg``'s payload with ``extras[i]`` added to the i-th nested map of ``field_name`` (and ``added`` to its own)."""
    data = msgpack.unpackb(msg.encode())
    for item, extra in zip(data[field_name], extras, strict=True):
        item.update(extra)
    return msgpack.packb({**data, **added})


def test_a_nested_maps_newer_field_is_named_by_its_path_once_for_all_its_elements() -> None:
    sent = Markers(markers=[MarkerPose(id=i, pixel_size=10.0 + i) for i in range(3)]).stamp(4, 5)
    read = Markers.decode(_with_nested(sent, "markers", [{"zoom": 1.0}, {}, {"zoom": 2.0, "tint": "red"}], later=1))
    assert read == sent  # every marker shown, without what this build does not know
    assert read.ignored == ("later", "markers[].zoom", "markers[].tint")
    snapshot = protocol.TwinSnapshot(images=[protocol.ImageInfo(source="camera")],
                                     streams=[protocol.StreamInfo(key="state/robot")]).stamp(1, 1)
    payload = _with_nested(snapshot, "streams", [{"jitter": 0.1}])
    assert protocol.TwinSnapshot.decode(payload).ignored == ("streams[].jitter",)
    assert protocol.TwinSnapshot.decode(_with_nested(snapshot, "images", [{"zoom": 1}])).ignored == ("images[].zoom",)
    # What a receiver passes on is what it read, without the names of what it left out: the twin's snapshot carries
    # the markers of the edge's Markers message.
    relayed = protocol.TwinSnapshot(markers=read.markers).stamp(2, 2).encode()
    assert [sorted(m) for m in msgpack.unpackb(relayed)["markers"]] == [sorted(f.name for f in
                                                                            dataclasses.fields(MarkerPose))] * 3
    assert protocol.TwinSnapshot.decode(relayed).ignored == ()


def test_what_a_display_only_message_names_as_ignored_stays_bounded() -> None:
    """A sender chooses the names: 100 markers with two new fields each must not make ``ignored`` 200 long."""
    sent = Markers(markers=[MarkerPose(id=i) for i in range(100)]).stamp(1, 1)
    extras: list[dict[str, object]] = [{f"a{i}": 0, f"b{i}": 1} for i in range(100)]
    read = Markers.decode(_with_nested(sent, "markers", extras))
    assert read == sent and read.ignored == ("markers[].a0", "markers[].b0", "markers[].a1", "markers[].b1",
                                             "markers[].a2", "markers[].b2", "markers[].a3", "markers[].b3")


@dataclasses.dataclass(kw_only=True)
class _Route(Message):
    """Not a message of the protocol: one read whole that carries display-only nested maps (markers to pass by),
    as a command or a safety state may one day."""

    markers: list[MarkerPose] = protocol.spec(default_factory=list, max_len=4)


def test_a_message_read_whole_is_refused_for_a_nested_maps_newer_field_too() -> None:
    sent = _Route(markers=[MarkerPose(id=1), MarkerPose(id=2)]).stamp(1, 1)
    assert _Route.decode(sent.encode()) == sent
    with pytest.raises(DecodeError) as err:
        _Route.decode(_with_nested(sent, "markers", [{}, {"zoom": 1.0}]))
    assert err.value.message_type == "_Route.markers[1]" and err.value.field == "zoom" and err.value.newer
    # The protocol's own messages with nested maps are all display-only; the edge's check agrees with the decoder.
    assert all(cls.DISPLAY_ONLY for cls in ALL_MESSAGES if cls._nested())
    later = protocol.REVISION + 1
    original = dict(protocol.ADDED_IN)
    protocol.ADDED_IN[later] = {"MarkerPose": frozenset({"size"})}
    try:
        assert protocol.unreadable_by(protocol.REVISION, [Markers, protocol.TwinSnapshot]) == []
        assert protocol.unreadable_by(protocol.REVISION, [Markers, _Route]) == ["MarkerPose.size"]
        assert protocol.unreadable_by(protocol.REVISION, [_Route, Markers]) == ["MarkerPose.size"]
    finally:
        protocol.ADDED_IN.clear()
        protocol.ADDED_IN.update(original)


def test_every_field_added_in_a_revision_decodes_when_absent() -> None:
    for added in protocol.ADDED_IN.values():
        for name, fields in added.items():
            cls = getattr(protocol, name)
            payload = msgpack.unpackb(cls().stamp(1, 1).encode())
            for f in fields:
                del payload[f]
            cls.decode(msgpack.packb(payload))


@pytest.mark.parametrize(("text", "revision"), [("", 1), ('{"revision": 2}', 2), ('{"revision": 7}', 7),
                                                ('{"force": 4.0}', 1), ("[2]", 1), ("not json", 1),
                                                ('{"revision": true}', 1), ('{"revision": 0}', 1)])
def test_the_revision_an_acquire_or_its_answer_says(text: str, revision: int) -> None:
    assert protocol.said_revision(text) == revision
    assert protocol.said_revision(protocol.revision_json()) == protocol.REVISION
