"""Registration of a hand-held exposure stack before fusion.

A tripod stack (and the probe's own bracket) needs none. A hand-held one is misregistered by a
few pixels from frame to frame, and a merge then mixes neighbouring scene points: edges double,
and subsets of the stack disagree (``../shared/data/exposure_stacks/pku_campus_trees``, 2-4 px:
even-vs-odd median |d log L| 0.176 unregistered, 0.096 registered; measured in BENCHMARKS.md).

Method: median threshold bitmaps (Ward 2003, "Fast, robust image registration for compositing
high dynamic range photographs from hand-held exposures", J. Graphics Tools 8(2)), through
OpenCV's implementation (``cv2.AlignMTB.calculateShift``: an image pyramid, each level's shift
by the XOR of the two bitmaps thresholded at their medians, pixels near the median excluded):
invariant to the exposure, integer pixels, translation only. Choices:

- Neighbours, not one reference: each frame is registered to the next one towards the reference
  (the frame with the most mid-tone codes) and the shifts are chained, since bitmaps of frames
  several stops apart share too little.
- A frame with under ``MIN_MIDTONE`` of its pixels in the mid-tones (16..240: nearly all white or
  black) carries no usable bitmap; it takes its neighbour's shift. A shift at the search's bound
  (``2^levels - 1`` pixels) is a failed search and counts as none.
- Shifts are applied with the border replicated, so the frames keep their size and every pixel
  a sample (a border a few pixels wide is then a copy of its neighbour).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MIN_MIDTONE", "align_stack", "apply_shifts", "stack_shifts"]

MIN_MIDTONE = 0.1  # share of a frame's pixels in the mid-tones for its bitmap to count
MIDTONES = (16, 240)


def _gray(frame: np.ndarray) -> np.ndarray:
    import cv2

    f = np.ascontiguousarray(frame)
    return f if f.ndim == 2 else cv2.cvtColor(f, cv2.COLOR_RGB2GRAY)


def stack_shifts(frames: list[np.ndarray], levels: int = 6) -> list[tuple[int, int]]:
    """Per frame, the (x, y) shift in pixels that registers it to the stack's reference frame
    (the reference's own is (0, 0)). ``frames``: RGB or grey uint8 of one size."""
    import cv2

    gray = [_gray(f) for f in frames]
    lo, hi = MIDTONES
    mid = [float(((g >= lo) & (g <= hi)).mean()) for g in gray]
    n = len(gray)
    if n == 0:
        return []
    ref = int(np.argmax(mid))
    mtb = cv2.createAlignMTB(levels)
    bound = 2 ** levels - 1
    shift = [np.zeros(2, np.int64) for _ in range(n)]
    for step in (1, -1):
        prev, i = ref, ref + step
        while 0 <= i < n:
            shift[i] = shift[prev].copy()
            if mid[i] >= MIN_MIDTONE and mid[prev] >= MIN_MIDTONE:
                s = np.asarray(mtb.calculateShift(gray[prev], gray[i]), np.int64)
                if np.abs(s).max() < bound:
                    shift[i] += s
                prev = i
            i += step
    return [(int(s[0]), int(s[1])) for s in shift]


def apply_shifts(frames: list[np.ndarray], shifts: list[tuple[int, int]]) -> list[np.ndarray]:
    """The frames moved by whole pixels (``shifts`` as :func:`stack_shifts` gives them), the
    border replicated."""
    import cv2

    out = []
    for f, (dx, dy) in zip(frames, shifts, strict=True):
        if dx == 0 and dy == 0:
            out.append(f)
            continue
        m = np.array([[1, 0, dx], [0, 1, dy]], np.float32)
        out.append(cv2.warpAffine(np.ascontiguousarray(f), m, (f.shape[1], f.shape[0]), flags=cv2.INTER_NEAREST,
                                  borderMode=cv2.BORDER_REPLICATE))
    return out


def align_stack(frames: list[np.ndarray], levels: int = 6) -> tuple[list[np.ndarray], list[tuple[int, int]]]:
    """The stack registered to its reference frame, and the shifts applied."""
    shifts = stack_shifts(frames, levels)
    return apply_shifts(frames, shifts), shifts
