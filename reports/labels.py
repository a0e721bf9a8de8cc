"""Where a point's text label goes so that it covers no other label and no marker.

Pure geometry in display pixels (no matplotlib here): `place` tries, for each label in turn,
spots around its point at growing distances and keeps the first that overlaps nothing placed
so far and stays inside the frame. Splits with close latencies and errors put their points
within a few pixels of each other, where a fixed offset stacks their names into one smudge.
"""

from __future__ import annotations

from collections.abc import Sequence

#: (x0, y0, x1, y1), pixels, y up.
Box = tuple[float, float, float, float]
#: A marker as the circle around it: (x, y, radius), pixels.
Circle = tuple[float, float, float]

#: Gaps between a point and the nearest corner or edge of its label, tried in this order.
RADII_PX = (3.0, 8.0, 14.0, 22.0, 32.0, 44.0)
#: Directions from the point (right-up first: where a reader looks for a point's name).
HEADINGS = ((1, 1), (1, -1), (-1, 1), (-1, -1), (1, 0), (-1, 0), (0, 1), (0, -1))


def overlaps(a: Box, b: Box) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def covers(box: Box, circle: Circle) -> bool:
    """Whether `box` reaches into `circle` (its nearest point is closer than the radius)."""
    x, y, r = circle
    nx, ny = min(max(x, box[0]), box[2]), min(max(y, box[1]), box[3])
    return (nx - x) ** 2 + (ny - y) ** 2 < r * r


def _box(x: float, y: float, w: float, h: float, dx: int, dy: int, r: float) -> Box:
    """The label of size (w, h) whose nearest corner (or edge, for a 0 direction) is `r`
    pixels from (x, y) along (dx, dy)."""
    x0 = x + r if dx > 0 else (x - r - w if dx < 0 else x - w / 2)
    y0 = y + r if dy > 0 else (y - r - h if dy < 0 else y - h / 2)
    return (x0, y0, x0 + w, y0 + h)


def place(
    anchors: Sequence[tuple[float, float]],
    sizes: Sequence[tuple[float, float]],
    markers: Sequence[Circle] = (),
    frame: Box | None = None,
) -> list[Box]:
    """A box per label (anchors[i] is its point, sizes[i] its width and height): the first
    spot in `RADII_PX` x `HEADINGS` that covers no marker and no label placed before it,
    inside `frame` (anywhere when no spot fits inside). A label with no free spot left gets the
    first spot: it overlaps, but is still drawn."""
    boxes: list[Box] = []
    for (x, y), (w, h) in zip(anchors, sizes, strict=True):
        spots = [_box(x, y, w, h, dx, dy, r) for r in RADII_PX for dx, dy in HEADINGS]
        inside = [b for b in spots if frame is None or _within(b, frame)] or spots
        free = (
            b
            for b in inside
            if not any(overlaps(b, p) for p in boxes) and not any(covers(b, m) for m in markers)
        )
        boxes.append(next(free, inside[0]))
    return boxes


def _within(box: Box, frame: Box) -> bool:
    return frame[0] <= box[0] and box[2] <= frame[2] and frame[1] <= box[1] and box[3] <= frame[3]
