"""Whether the worker's latent frames are wanted now: a node whose only sink is the publisher need not render
frames that no subscriber would receive (`Publisher.wants_frames`, from the XPUB socket's subscriptions), and a
node without any sink (`--no-publish` without `--out` or `--dv-output`) renders none (`nobody_wants`).

Owns the question and the count of frames not rendered; the worker asks before rendering a batch (its causal
path without --max-fps only: --mode nearest / fused and --max-fps render every latent frame). The latent
image still moves with every event (the next frame wanted is exact), only the copies, the `Reconstruction`s
and the quality score's work are saved. The quality score is reset while nothing is shown, so it never scores
a prediction that nobody saw; it scores again once frames flow (see edi_live/quality.py on resets).
"""

from __future__ import annotations

from typing import Callable, Protocol

from edi_live.datatypes import Reconstruction


def nobody_wants() -> bool:
    """The demand of a node that has no sink: no latent frame is wanted, ever."""
    return False


class _Resettable(Protocol):
    def reset(self) -> None: ...


class _Score(_Resettable, Protocol):
    def on_emitted(self, rec: Reconstruction) -> object: ...


class FrameDemand:
    """`wanted`: asked before each batch of latent frames (None: always wanted, e.g. when --out takes them)."""

    def __init__(self, wanted: Callable[[], bool] | None = None) -> None:
        self._wanted = wanted
        self.not_rendered = 0  # latent frames counted but not rendered: nobody subscribed

    def score(self, rec: Reconstruction, quality: _Score, asked: bool = False) -> None:
        """`rec` to the quality score if someone receives it; a frame made while nobody would (a deblurred frame, a
        heartbeat, a frame of a path that renders them all) resets the score instead: the figure is of what was
        received. `asked`: rendered because skip() said it was wanted (not asked again: ~1 µs a frame)."""
        if not asked and self._wanted is not None and not self._wanted():
            quality.reset()
        else:
            quality.on_emitted(rec)

    def skip(self, n_frames: int, quality: _Resettable | None) -> bool:
        """True (and the frames counted) when nobody wants these n_frames frames."""
        if not n_frames or self._wanted is None or self._wanted():
            return False
        self.not_rendered += n_frames
        if quality is not None:
            quality.reset()
        return True
