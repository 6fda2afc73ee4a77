"""When the ring's producer wakes a waiting consumer: at once (the default), or only once enough has arrived.

Owns `WakeWhen`, the condition a consumer may attach to `EventRing.wait`. On a quiet stream (a still camera's
background noise: a few dozen events per 1 ms packet) a wake-up per packet costs far more than the events in it
(a futex, a GIL hand-over and the consumer's per-read bookkeeping), so the consumer asks to be woken only when
`events` unread events or sensor time `t_us` has arrived, or at once for an APS frame, close or poke. The ring
checks the condition under its lock on every push, so no data is ever missed, only read in fewer, larger steps.
An APS frame the consumer already holds back (waiting for its late events) need not wake it again on every push:
`frames` says how many queued frames it has seen, and only one more wakes it; with `frame_late_us`, only once the
watermark is past that frame's exposure end plus its late events (the consumer could not deblur it before).
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class WakeWhen:
    """Wake the consumer once the ring's head index reaches `head` or its watermark reaches `t_us` (µs), or more
    than `frames` APS frames are queued (the next one's late events in, with `frame_late_us`). With `rate_per_us`,
    also once the events pushed since index `head0` (watermark `t0_us`) exceed what that rate gives by `slack`: an
    excess early in a long wait wakes it as soon as one at its end would."""

    head: int
    t_us: int
    frames: int = 0
    frame_late_us: int | None = None
    rate_per_us: float = 0.0
    head0: int = 0
    t0_us: int = 0
    slack: float = 0.0

    def met(self, head: int, watermark_us: int) -> bool:
        return (head >= self.head or watermark_us >= self.t_us or (
            self.rate_per_us > 0 and head - self.head0 > self.rate_per_us * (watermark_us - self.t0_us) + self.slack))
