"""How fast a video stream may send, from how the link takes it: pure, no I/O, tested in milliseconds.

Two signals, both measured where they happen:

- the link's own congestion, at the sender: video is published with ``CongestionControl.BLOCK``, so a ``put``
  that takes longer than a share of the frame period means Zenoh's queue toward the router was full (the uplink
  is slower than the stream), and frames the capture had to replace in the one-frame slot mean the sender fell
  behind;
- the viewers' reports (``VideoFeedback``): frames missing by sequence and the delay from capture to arrival at
  the worst viewer.

The control is AIMD, as TCP's: on congestion the bitrate drops by ``decrease`` at once (and not again before
``hold`` s, so one burst of slow puts is one cut), otherwise it rises by ``increase`` every ``hold`` s, within
[min, max]. A new target is applied by the encoder at its next keyframe: a cut costs one keyframe.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class BitrateSettings:
    start: float  # bit/s
    min: float
    max: float
    decrease: float = 0.7  # × on congestion
    increase: float = 1.1  # × every hold s without it
    hold: float = 2.0  # s
    slow_put: float = 0.5  # a put longer than this share of the frame period is congestion
    skipped_share: float = 0.1  # replaced frames above this share of the captured ones (per hold) is congestion
    max_lost_share: float = 0.02  # a viewer missing more than this share of the frames is congestion
    max_delay: float = 0.25  # s capture → viewer (p90) above which the link is queueing


class BitrateController:
    def __init__(self, settings: BitrateSettings, frame_period: float) -> None:
        self.s = settings
        self.period = frame_period
        self.target = settings.start
        self._last_change = -1e9
        self._captured = 0
        self._skipped = 0
        self._congested = ""  # why, since the last decision ("" = not congested)
        self.cuts = 0
        self.reason = ""  # why the latest change happened

    def on_put(self, seconds: float) -> None:
        """One frame published; ``seconds`` its put took."""
        if seconds > self.s.slow_put * self.period:
            self._congested = self._congested or f"a put took {1000 * seconds:.0f} ms"

    def on_capture(self, skipped: int) -> None:
        """One frame captured; ``skipped`` frames the slot replaced since the previous capture (the sender is
        behind)."""
        self._captured += 1
        self._skipped += skipped

    def on_feedback(self, received: int, lost: int, delay_p90: float) -> None:
        """A viewer's report: frames received and missing since its previous report, the p90 delay (s, -1 if
        unknown)."""
        total = received + lost
        if total and lost / total > self.s.max_lost_share:
            self._congested = self._congested or f"a viewer lost {lost} of {total} frames"
        if delay_p90 > self.s.max_delay:
            self._congested = self._congested or f"a viewer sees frames {1000 * delay_p90:.0f} ms late"

    def decide(self, now: float) -> float:
        """The bitrate to use from ``now`` (monotonic s)."""
        if self._captured and self._skipped / self._captured > self.s.skipped_share:
            self._congested = self._congested or f"{self._skipped} of {self._captured} frames skipped"
        if now - self._last_change < self.s.hold:
            return self.target
        if self._congested:
            new = max(self.s.min, self.target * self.s.decrease)
            if new < self.target:
                self.cuts += 1
            self.reason = f"congestion ({self._congested}): {self.target / 1e3:.0f} → {new / 1e3:.0f} kbit/s"
        else:
            new = min(self.s.max, self.target * self.s.increase)
            self.reason = f"no congestion: {self.target / 1e3:.0f} → {new / 1e3:.0f} kbit/s" if new != self.target else ""
        self.target, self._last_change = new, now
        self._congested, self._captured, self._skipped = "", 0, 0
        return self.target


__all__ = ["BitrateController", "BitrateSettings"]
