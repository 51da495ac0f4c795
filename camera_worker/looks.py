"""The camera side of appearance: answer the fusion server's look requests from a frame.

:class:`LookAnswerer` keeps the newest :class:`~common.messages.LookRequest`
and, on the next frame the worker segments, describes the people it names
(:func:`common.appearance.describe_people`): only histograms leave the
worker, never pixels. A request is answered once, and not at all once older
than its ``ttl_ms`` (the people have moved on).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from common import appearance
from common.messages import Appearance, LookRequest, PersonRegion

__all__ = ["LookAnswerer", "describe"]


def describe(people: Sequence[PersonRegion], image: np.ndarray, mask: np.ndarray, *,
             scale: float = 1.0) -> list[Appearance]:
    """The descriptors of ``people`` in ``image`` (BGR) under ``mask`` (the frame's
    foreground mask, at the image's resolution or downscaled from it). ``scale``: the
    image's size over the capture's, in which the people's boxes are given (a recording
    kept at a reduced size)."""
    if not people:
        return []
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    boxes = [p.boxes if scale == 1.0 else [tuple(int(round(v * scale)) for v in b) for b in p.boxes] for p in people]
    measured = appearance.describe_people(image, mask, [(p.depth_m, b) for p, b in zip(people, boxes)])
    return [
        Appearance(track=p.track, hist=b"".join(appearance.quantise(h) for h in hist),
                   pixels=[int(v) for v in pixels], visible=[float(round(v, 3)) for v in visible])
        for p, (hist, pixels, visible) in zip(people, measured)
    ]


class LookAnswerer:
    """Holds the newest look request until a frame answers it."""

    def __init__(self) -> None:
        self._request: LookRequest | None = None
        self.last: list[Appearance] = []  # the last answer
        self.answered = 0
        self.expired = 0

    @property
    def pending(self) -> bool:
        """Whether a request waits for a frame."""
        return self._request is not None

    def ask(self, request: LookRequest) -> None:
        """A new request replaces one not yet answered (same people, newer boxes)."""
        self._request = request

    def answer(self, image: np.ndarray | None, mask: np.ndarray, stamp_ns: int, *,
               scale: float = 1.0) -> list[Appearance]:
        """The descriptors for the pending request on this frame (captured at
        ``stamp_ns``; ``image`` None when the frame's colours are unknown; ``scale`` as
        for :func:`describe`), or []
        when nothing is pending or the request is too old. Kept in ``last``."""
        req, self._request = self._request, None
        self.last = []
        if req is None or image is None:
            return self.last
        if stamp_ns - req.stamp_ns > req.ttl_ms * 1_000_000:
            self.expired += 1
            return self.last
        self.answered += 1
        self.last = describe(req.people, image, mask, scale=scale)
        return self.last
