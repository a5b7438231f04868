"""What an operator must do before the robot moves again, from what the edge says: pure, no I/O.

The edge never resumes motion by itself (DESIGN.md, "Resume on purpose"): after a stop command or a long gap it
waits for the deadman to be released and pressed again; after a fault or the loss of the owner's session, for
control to be acquired again and then a fresh press. The clients use :func:`next_step` in two ways:

- a headless client whose intent is its command (``iorthand operator move``, ``script``) does the step itself:
  it acquires again, or presses afresh (the command stream then sends the release the edge waits for first);
- a console says the step, with the key or button that does it (:func:`hint`).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

from iorthand.protocol import RESUME_ON_ACQUIRE as REACQUIRE
from iorthand.protocol import RESUME_ON_PRESS as REPRESS
from iorthand.protocol import SafetyStatus, Status


class Step(Enum):
    NONE = "none"  # nothing stands between the operator and motion
    ACQUIRE = "acquire"  # take control (again)
    PRESS = "press"  # press the deadman afresh (a press held through the halt does not count)
    WAIT = "wait"  # nothing the operator can do from here: someone else holds control, not armed, no edge


@dataclass(frozen=True)
class NextStep:
    step: Step
    why: str


def next_step(me: str, owner_held: bool, safety: SafetyStatus | None, fresh_press: bool,
              sender_down: str = "", old_press: bool = False, unreadable: str = "") -> NextStep:
    """The step ``me`` must take. ``owner_held``: this client believes it holds a grant; ``fresh_press``: its
    deadman is pressed, and was pressed after the edge's latest halt, the latest grant and the latest start of its
    command sender; ``old_press``: it is held by a press from before the latest grant or start of its sender, which
    its commands send as released. ``sender_down``: why this client's commands cannot go out (its sender process
    died); nothing the operator does moves the robot until they do. ``unreadable``: why this console cannot read
    the edge's safety state (a newer edge's: update this console), which no step of the operator's changes."""
    if sender_down:
        return NextStep(Step.WAIT, sender_down)
    if unreadable:
        return NextStep(Step.WAIT, unreadable)
    if safety is None:
        return NextStep(Step.WAIT, "no safety status from the edge yet")
    if not safety.armed:
        return NextStep(Step.WAIT, "the robot is not armed: arming is confirmed on its side (iorthand arm)")
    if safety.owner and safety.owner != me:
        return NextStep(Step.WAIT, f"{safety.owner} holds control")
    if not owner_held or safety.owner != me or safety.status in REACQUIRE:
        why = safety.reason if safety.status in REACQUIRE else "this console does not hold control"
        return NextStep(Step.ACQUIRE, why)
    if old_press:  # whatever the edge says: these commands say "released" until the operator presses again
        return NextStep(Step.PRESS, "the deadman was pressed before control was granted or the command sender "
                                    "started again")
    # A released deadman (NO_DEADMAN: also a new grant's first state) or a halt that waits for a fresh press.
    if (safety.status in REPRESS or safety.status == Status.NO_DEADMAN) and not fresh_press:
        return NextStep(Step.PRESS, safety.reason or Status(safety.status).message)
    return NextStep(Step.NONE, "")


def hint(step: NextStep, acquire_key: str, deadman_key: str, toggle: bool) -> str:
    """The line a console shows for ``step``, naming its keys (``toggle``: the deadman key toggles)."""
    if step.step is Step.ACQUIRE:
        return f"press {acquire_key} to take control ({step.why})"
    if step.step is Step.PRESS:
        how = f"press {deadman_key}" if toggle else f"release {deadman_key} and press it again"
        return f"{how} to move again ({step.why})"
    if step.step is Step.WAIT:
        return step.why
    return ""


__all__ = ["REACQUIRE", "REPRESS", "NextStep", "Step", "hint", "next_step"]
