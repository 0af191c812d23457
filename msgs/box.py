"""The one box of followbus: ``(x, y, w, h)`` float pixels, top-left origin, as every module and message uses it.

In messages a box travels as a float64 array of 4 (None: no box); in the algorithms it is this tuple. The
helpers take either.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ..bus.schemas import Message, check_shape, require

Box = tuple[float, float, float, float]


def box_centre(box: Sequence[float]) -> tuple[float, float]:
    return (float(box[0]) + float(box[2]) / 2.0, float(box[1]) + float(box[3]) / 2.0)


def box_iou(a: Sequence[float], b: Sequence[float]) -> float:
    """Intersection over union of two ``(x, y, w, h)`` boxes (continuous coordinates, no +1)."""
    ax, ay, aw, ah = a
    bx, by, bw, bh = b
    iw = min(ax + aw, bx + bw) - max(ax, bx)
    ih = min(ay + ah, by + bh) - max(ay, by)
    if iw <= 0 or ih <= 0:
        return 0.0
    inter = iw * ih
    union = aw * ah + bw * bh - inter
    return inter / union if union > 0 else 0.0


def centre_size_to_box(cx: float, cy: float, w: float, h: float) -> Box:
    return (cx - w / 2.0, cy - h / 2.0, w, h)


def box_array(box: Sequence[float] | None) -> np.ndarray | None:
    """A box as a message field carries it: float64 [x, y, w, h], or None."""
    return None if box is None else np.asarray(box, dtype=np.float64).reshape(4)


def box_tuple(box: Sequence[float] | None) -> Box | None:
    """A message's box field as the algorithms' tuple of floats, or None."""
    return None if box is None else tuple(float(v) for v in np.asarray(box).reshape(4))  # type: ignore[return-value]


def check_boxes(msg: Message, *names: str) -> None:
    """Each named box field of ``msg`` is None or [x, y, w, h] of non-negative size."""
    for name in names:
        box = getattr(msg, name)
        if box is None:
            continue
        check_shape(msg, name, box, (4,))
        require(box[2] >= 0 and box[3] >= 0, msg, f"{name}: box of negative size {box.tolist()}")


def check_box_rows(msg: Message, name: str, columns: int = 5) -> None:
    """Array field ``name`` holds N rows of x, y, w, h (and ``columns`` - 4 more), no box of negative size."""
    rows = getattr(msg, name)
    check_shape(msg, name, rows, (None, columns))
    require(not (rows[:, 2:4] < 0).any(), msg, f"{name}: box of negative size")
