"""Client helpers for the recorder's queryables (used by the CLI, tests, benchmarks and the demo)."""

from __future__ import annotations

import zenoh

from iorthand import keys
from iorthand.protocol import Annotation, RecorderRequest, RecorderStatus, Sequencer
from iorthand.transport import query

_seq = Sequencer()


class RecorderUnavailable(RuntimeError):
    pass


def _ask(session: zenoh.Session, action: str, payload: bytes, timeout: float) -> RecorderStatus:
    key = keys.service_key(keys.RECORDER, action)
    replies = query(session, key, payload, timeout=timeout)
    if not replies:
        raise RecorderUnavailable(f"no recorder answered on {key} (is `iorthand recorder` running?)")
    return RecorderStatus.decode(replies[0])


def start(session: zenoh.Session, session_id: str = "", operator: str = "", robots: list[str] | None = None,
          note: str = "", timeout: float = 5.0) -> RecorderStatus:
    req = RecorderRequest(operator=operator, session=session_id, robots=list(robots or []), note=note)
    return _ask(session, keys.RECORDER_START, req.stamp(_seq.next()).encode(), timeout)


def stop(session: zenoh.Session, timeout: float = 10.0) -> RecorderStatus:
    return _ask(session, keys.RECORDER_STOP, RecorderRequest().stamp(_seq.next()).encode(), timeout)


def status(session: zenoh.Session, timeout: float = 2.0) -> RecorderStatus:
    return _ask(session, keys.RECORDER_STATUS, b"", timeout)


def annotate(session: zenoh.Session, text: str, author: str = "", tags: list[str] | None = None,
             score: float | None = None, timeout: float = 5.0) -> RecorderStatus:
    """An author that is an operator id goes on the key ``annotate/<author>``, which the deployment's router lets
    only that operator's certificate query (bind_operator_keys); any other author is the sender's claim."""
    ann = Annotation(author=author, text=text, tags=list(tags or []), score=score)
    verb = keys.RECORDER_ANNOTATE
    if author and keys.OPERATOR_ID_PATTERN.match(author):
        verb = f"{verb}/{author}"
    return _ask(session, verb, ann.stamp(_seq.next()).encode(), timeout)
