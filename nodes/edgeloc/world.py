"""A deterministic synthetic driving world: the stand-in for a RobotCar/KITTI recording.

The nouns a user imagines when they picture a test drive:

- `Town`: a road grid of square blocks lined with buildings (varied colour, height and facade
  texture), a few tall landmark towers, a park or two, and mountains on the horizon. Blocks are
  drawn from a small set of templates, so some streets look alike and genuinely confuse a
  pose-regressing DNN, as repetitive city streets do.
- `Route`: a closed loop through the streets (the boundary of a random set of blocks), driven
  in the right-hand lane with rounded corners.
- `Drive`: the vehicle on that route at ~10 m/s, slowing for corners, sampled at the workload
  rate; it owns the ground-truth SE(2) poses, time of day and the trucks that pass by.
- `Lighting` and `Obstacle`: what changes the pictures without changing the place.
- `Camera`: renders a small forward RGB image from the world geometry by vectorised ray casting
  (one ray per image column against all building footprints, painter's algorithm over the
  nearest hits, floor casting for the road).
- `vo_trace`: visual odometry as it really behaves: ground-truth increments with a scale bias, a
  heading-drift random walk and small per-frame noise. It drifts; it has no outliers.

Everything random comes from `numpy.random.default_rng(seed)` (or a seed sequence derived from
it), so the same seed gives identical poses and images.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from nodes.edgeloc import geometry as se2

F64 = NDArray[np.float64]
U8 = NDArray[np.uint8]

DEFAULT_TOWN_SEED = 7  # the town the committed DNN weights were trained on

# Facade texture kinds (one per building).
TEX_WINDOWS, TEX_VSTRIPES, TEX_HBANDS, TEX_PLAIN = 0, 1, 2, 3


# ---- the town --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Town:
    """Static geometry: axis-aligned building boxes on a square road grid.

    Roads run along x = origin + i*pitch and y = origin + j*pitch (i, j = 0..blocks); every
    building is a box [xmin, ymin, xmax, ymax] with a height, a colour and a facade texture.
    """

    seed: int
    blocks: int  # blocks per side
    pitch: float  # metres between parallel road centrelines
    road_width: float  # kerb to kerb, metres; sidewalks are 2 m on each side beyond it
    boxes: F64  # (N, 4) xmin, ymin, xmax, ymax
    heights: F64  # (N,)
    colours: F64  # (N, 3) in [0, 1]
    textures: F64  # (N, 4) kind, horizontal period (m), floor height (m), window fraction
    accent: F64  # (N, 3) window/stripe colour
    mountains: F64  # (5, 2) amplitude (rad) and phase of the horizon profile harmonics
    block_template: NDArray[np.int64]  # (blocks, blocks) template id of each block, -1 = park

    @property
    def origin(self) -> float:
        return -self.blocks * self.pitch / 2

    @property
    def extent(self) -> float:
        """Side of the square spanned by the outer road centrelines, metres."""
        return self.blocks * self.pitch

    def road_coords(self) -> F64:
        """Centreline coordinates of the roads (the same for x and y)."""
        return self.origin + self.pitch * np.arange(self.blocks + 1)

    @classmethod
    def generate(
        cls,
        seed: int = DEFAULT_TOWN_SEED,
        blocks: int = 5,
        pitch: float = 80.0,
        road_width: float = 14.0,
        templates: int = 10,
        landmarks: int = 4,
        parks: int = 2,
    ) -> Town:
        """A town of `blocks`² blocks drawn from `templates` layouts (repeats are intended)."""
        if blocks < 2 or templates < 1 or pitch <= road_width + 20:
            raise ValueError("a town needs >= 2 blocks, >= 1 template and pitch > road_width + 20")
        rng = np.random.default_rng(seed)
        inner = pitch - road_width - 4.0  # buildable side of one block (sidewalks of 2 m)
        layouts = [_block_layout(rng, inner) for _ in range(templates)]
        assign = rng.integers(0, templates, size=(blocks, blocks))
        cells = rng.permutation(blocks * blocks)
        for c in cells[:parks]:
            assign[c // blocks, c % blocks] = -1
        tower_cells = cells[parks : parks + landmarks]  # landmarks stand in non-park blocks

        boxes, heights, colours, textures, accent = [], [], [], [], []
        origin = -blocks * pitch / 2
        for bi in range(blocks):
            for bj in range(blocks):
                x0 = origin + bi * pitch + road_width / 2 + 2.0
                y0 = origin + bj * pitch + road_width / 2 + 2.0
                if assign[bi, bj] < 0:  # a park: low hedges and a kiosk
                    for hx, hy, hw, hd, hh in _park_layout(rng, inner):
                        boxes.append([x0 + hx, y0 + hy, x0 + hx + hw, y0 + hy + hd])
                        heights.append(hh)
                        colours.append([0.18, 0.42, 0.16] if hh < 2 else [0.6, 0.5, 0.3])
                        textures.append([TEX_PLAIN, 4.0, 3.0, 0.0])
                        accent.append([0.1, 0.3, 0.1])
                    continue
                for b in layouts[assign[bi, bj]]:
                    boxes.append([x0 + b[0], y0 + b[1], x0 + b[2], y0 + b[3]])
                    heights.append(b[4])
                    colours.append(b[5:8])
                    textures.append(b[8:12])
                    accent.append(b[12:15])
        for n, c in enumerate(tower_cells):
            bi, bj = c // blocks, c % blocks
            cx = origin + (bi + 0.5) * pitch + rng.uniform(-6, 6)
            cy = origin + (bj + 0.5) * pitch + rng.uniform(-6, 6)
            half = rng.uniform(5.0, 8.0)
            boxes.append([cx - half, cy - half, cx + half, cy + half])
            heights.append(rng.uniform(45.0, 75.0))
            hue = n / max(landmarks, 1)
            colours.append(_hsv(hue, 0.85, 0.9))  # saturated, unlike the muted houses
            textures.append([TEX_HBANDS, 5.0, rng.uniform(4.0, 9.0), 0.5])
            accent.append(_hsv((hue + 0.5) % 1.0, 0.6, 0.95))
        mountains = np.stack(
            [rng.uniform(0.01, 0.04, 5), rng.uniform(0, 2 * np.pi, 5)], axis=1
        )  # harmonics 1..5 of the skyline: a yaw cue that no street repeats
        return cls(
            seed=seed,
            blocks=blocks,
            pitch=pitch,
            road_width=road_width,
            boxes=np.asarray(boxes, dtype=np.float64),
            heights=np.asarray(heights, dtype=np.float64),
            colours=np.asarray(colours, dtype=np.float64),
            textures=np.asarray(textures, dtype=np.float64),
            accent=np.asarray(accent, dtype=np.float64),
            mountains=mountains,
            block_template=assign.astype(np.int64),
        )


def _hsv(h: float, s: float, v: float) -> list[float]:
    i = int(h * 6) % 6
    f = h * 6 - int(h * 6)
    p, q, t = v * (1 - s), v * (1 - f * s), v * (1 - (1 - f) * s)
    return [[v, t, p], [q, v, p], [p, v, t], [p, q, v], [t, p, v], [v, p, q]][i]


def _split_side(rng: np.random.Generator, length: float) -> list[tuple[float, float]]:
    """Cut one block side into building frontages (with the odd alley between them)."""
    spans, pos = [], 0.0
    while pos < length - 6.0:
        w = min(rng.uniform(10.0, 26.0), length - pos)
        if length - pos - w < 8.0:  # do not leave a sliver
            w = length - pos
        gap = rng.uniform(1.5, 4.0) if rng.random() < 0.3 else 0.0
        spans.append((pos, pos + w - gap))
        pos += w
    return spans


def _building_look(rng: np.random.Generator) -> list[float]:
    """Height, colour, texture and accent colour of one building (muted city palette)."""
    height = float(rng.choice([rng.uniform(6, 12), rng.uniform(10, 20), rng.uniform(18, 30)]))
    colour = _hsv(rng.uniform(0, 1), rng.uniform(0.1, 0.45), rng.uniform(0.45, 0.9))
    kind = float(rng.choice([TEX_WINDOWS, TEX_WINDOWS, TEX_VSTRIPES, TEX_HBANDS, TEX_PLAIN]))
    texture = [kind, rng.uniform(2.5, 5.0), rng.uniform(2.8, 3.6), rng.uniform(0.35, 0.65)]
    accent = _hsv(rng.uniform(0.5, 0.7), rng.uniform(0.1, 0.4), rng.uniform(0.15, 0.45))
    return [height, *colour, *texture, *accent]


def _block_layout(rng: np.random.Generator, inner: float) -> list[list[float]]:
    """Buildings around the perimeter of one block, in block coordinates [0, inner]²."""
    out: list[list[float]] = []
    depth_s, depth_n = rng.uniform(10, 20), rng.uniform(10, 20)
    for a, b in _split_side(rng, inner):  # south and north rows span the full width
        out.append([a, 0.0, b, depth_s, *_building_look(rng)])
    for a, b in _split_side(rng, inner):
        out.append([a, inner - depth_n, b, inner, *_building_look(rng)])
    for side in (0, 1):  # west and east rows fill between them
        depth = rng.uniform(10, 20)
        for a, b in _split_side(rng, inner - depth_s - depth_n - 2.0):
            y0, y1 = depth_s + 1.0 + a, depth_s + 1.0 + b
            x0, x1 = (0.0, depth) if side == 0 else (inner - depth, inner)
            out.append([x0, y0, x1, y1, *_building_look(rng)])
    return out


def _park_layout(rng: np.random.Generator, inner: float) -> list[tuple[float, ...]]:
    """Hedges along the kerbs and a kiosk: a block you can see through."""
    m = 1.0
    hedges = [
        (m, m, inner - 2 * m, 1.5, 1.2),
        (m, inner - m - 1.5, inner - 2 * m, 1.5, 1.2),
        (m, m + 8, 1.5, inner - 2 * m - 16, 1.2),
        (inner - m - 1.5, m + 8, 1.5, inner - 2 * m - 16, 1.2),
    ]
    k = rng.uniform(15, inner - 25)
    return [*hedges, (k, k, 8.0, 6.0, 4.5)]


# ---- lighting and moving obstacles -----------------------------------------------------------


@dataclass(frozen=True)
class Lighting:
    """How bright the scene is and from where the sun shines (changes pictures, not places)."""

    brightness: float  # overall gain, ~0.3 (dusk, overcast) .. 1.15 (bright noon)
    tint: tuple[float, float, float]  # colour of the light
    sun_azimuth: float  # rad, world frame; faces towards it are lit, the others shaded
    contrast: float  # 0 overcast (no shading difference) .. 1 sunny
    sky_top: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]

    @classmethod
    def at(cls, time_of_day: float, overcast: float = 0.0) -> Lighting:
        """Lighting at `time_of_day` in [0, 1] (0 dawn, 0.5 noon, 1 dusk) under `overcast`."""
        tod = float(np.clip(time_of_day, 0.0, 1.0))
        oc = float(np.clip(overcast, 0.0, 1.0))
        sun = np.sin(np.pi * tod)  # elevation proxy
        brightness = (0.35 + 0.8 * sun) * (1.0 - 0.35 * oc)
        warm = 1.0 - sun  # low sun is orange
        tint = (1.0, 1.0 - 0.15 * warm, 1.0 - 0.35 * warm)
        grey = np.array([0.62, 0.64, 0.68])
        top = (1 - oc) * np.array([0.25, 0.45, 0.85]) * (0.4 + 0.6 * sun) + oc * grey * 0.8
        hor = (1 - oc) * np.array([0.75 + 0.2 * warm, 0.75, 0.8 - 0.3 * warm]) + oc * grey
        return cls(
            brightness=float(brightness),
            tint=tint,
            sun_azimuth=float(np.pi * (1.5 - tod)),  # east in the morning, west at dusk
            contrast=float((1.0 - oc) * (0.3 + 0.7 * sun)),
            sky_top=tuple(float(v) for v in top * (0.5 + 0.5 * brightness)),
            sky_horizon=tuple(float(v) for v in hor * (0.5 + 0.5 * brightness)),
        )


@dataclass(frozen=True)
class Obstacle:
    """A moving box (a truck): centre pose [x, y, yaw], footprint and colour."""

    pose: F64
    length: float = 10.0
    width: float = 2.6
    height: float = 4.0
    colour: tuple[float, float, float] = (0.85, 0.85, 0.82)


# ---- the camera ------------------------------------------------------------------------------


@dataclass
class Camera:
    """A forward pinhole camera on the vehicle that renders the town by column ray casting."""

    town: Town
    width: int = 64
    height: int = 48
    fov_deg: float = 90.0
    mount_height: float = 1.6  # metres above the road
    layers: int = 4  # nearest hits painted per column (taller buildings behind show above)
    max_range: float = 300.0
    _cache: dict[str, F64] = field(default_factory=dict, repr=False)

    def __post_init__(self) -> None:
        if self.width < 8 or self.height < 8 or not 10.0 <= self.fov_deg <= 170.0:
            raise ValueError("camera needs width, height >= 8 and 10 <= fov_deg <= 170")
        w, h = self.width, self.height
        self.focal = (w / 2) / np.tan(np.radians(self.fov_deg) / 2)
        self.horizon = h / 2
        cols = np.arange(w) + 0.5
        self.col_angle = np.arctan((w / 2 - cols) / self.focal)  # left of the axis is positive
        self.cos_col = np.cos(self.col_angle)
        self.rows = (np.arange(h) + 0.5)[:, None]  # pixel-centre rows, (H, 1)
        t = self.town
        self.layers = min(self.layers, len(t.boxes))
        self._tall = np.nonzero(t.heights > 40.0)[0]
        below = np.arange(h) + 0.5 > self.horizon
        self.ground_rows = np.nonzero(below)[0]
        # perpendicular distance of each ground row (flat road), (G, 1)
        self.ground_depth = (
            self.focal * self.mount_height / (self.ground_rows + 0.5 - self.horizon)
        )[:, None]

    def render(
        self,
        pose: F64,
        light: Lighting,
        obstacles: Sequence[Obstacle] = (),
        noise_rng: np.random.Generator | None = None,
    ) -> U8:
        """The (H, W, 3) uint8 image seen from `pose` under `light`, trucks included."""
        x, y, yaw = (float(v) for v in pose)
        f, hz = self.focal, self.horizon
        ang = yaw + self.col_angle
        dx, dy = np.cos(ang), np.sin(ang)
        tint = np.asarray(light.tint) * light.brightness

        img = self._sky_and_mountains(ang, light)
        img[self.ground_rows] = self._ground(x, y, dx, dy, light)

        t, face, bid = self._hits(x, y, dx, dy, obstacles)  # (W, L) nearest first
        heights, colours, textures, accent = self._attributes(obstacles)
        ok = np.isfinite(t)
        d = np.where(ok, t, 1.0) * self.cos_col[:, None]  # perpendicular depth, (W, L)
        top = hz - f * (heights[bid] - self.mount_height) / d
        bottom = hz + f * self.mount_height / d
        rows = self.rows[..., None]  # (H, 1, 1)
        cover = (rows >= top) & (rows < bottom) & ok  # (H, W, L): which hits cover a pixel
        seen = cover.any(axis=2)
        if seen.any():  # the nearest covering hit is the one we see (z-buffer by layer order)
            r, c = np.nonzero(seen)
            k = cover[r, c].argmax(axis=1)
            tk, dk, b, fk = t[c, k], d[c, k], bid[c, k], face[c, k]
            u = np.where(fk, y + tk * dy[c], x + tk * dx[c])  # along-facade coordinate
            v = self.mount_height + (hz - self.rows[r, 0]) * dk / f  # height on the facade
            pattern = _facade_pattern(textures[b], u, v)
            col = np.where(pattern[:, None], accent[b], colours[b])  # (P, 3)
            normal = np.where(
                fk, np.where(dx[c] > 0, np.pi, 0.0), np.where(dy[c] > 0, -0.5, 0.5) * np.pi
            )
            lit = np.cos(normal - light.sun_azimuth)
            shade = 1.0 - light.contrast * (0.45 - 0.3 * lit)
            col = col * (shade[:, None] * tint)
            fog = (1.0 - np.exp(-dk / 220.0))[:, None]
            img[r, c] = col + (np.asarray(light.sky_horizon) - col) * fog

        if noise_rng is not None:  # sensor noise, a few grey levels
            img = img + noise_rng.normal(0.0, 0.012, size=img.shape)
        return (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)

    # -- pieces of a frame --------------------------------------------------------------------

    def _sky_and_mountains(self, ang: F64, light: Lighting) -> F64:
        h, w = self.height, self.width
        up = np.clip((self.horizon - self.rows) / self.horizon, 0, 1)  # 0 at horizon, 1 at top
        top, hor = np.asarray(light.sky_top), np.asarray(light.sky_horizon)
        sky = hor + (top - hor) * up[..., None]  # (H, 1, 3)
        img = np.broadcast_to(sky, (h, w, 3)).copy()
        m = self.town.mountains
        k = np.arange(1, len(m) + 1)[:, None]
        elev = 0.03 + np.sum(m[:, :1] * (1 + np.sin(k * ang[None] + m[:, 1:2])), axis=0)
        ridge = self.horizon - self.focal * np.tan(elev) / self.cos_col  # (W,)
        mtn = (np.array([0.42, 0.46, 0.55]) * np.asarray(light.tint) * light.brightness) * 0.8
        mtn = mtn + (hor - mtn) * 0.45  # haze
        img[(self.rows >= ridge) & (self.rows < self.horizon)] = mtn
        return img

    def _ground(self, x: float, y: float, dx: F64, dy: F64, light: Lighting) -> F64:
        """Floor casting: asphalt, dashed centre lines, sidewalks, courtyards, grass outside."""
        t = self.town
        dist = self.ground_depth / self.cos_col[None]  # along-ray distance, (G, W)
        gx, gy = x + dist * dx[None], y + dist * dy[None]
        ax, ay = (gx - t.origin) % t.pitch, (gy - t.origin) % t.pitch
        ex, ey = np.minimum(ax, t.pitch - ax), np.minimum(ay, t.pitch - ay)  # to centrelines
        half = t.road_width / 2
        road = (ex < half) | (ey < half)
        walk = ~road & ((ex < half + 2) | (ey < half + 2))
        inside = (np.abs(gx) < t.extent / 2 + half) & (np.abs(gy) < t.extent / 2 + half)
        dash_y = (ex < 0.2) & (ey > half) & ((gy % 6.0) < 3.0)  # street along y
        dash_x = (ey < 0.2) & (ex > half) & ((gx % 6.0) < 3.0)
        col = np.empty((*gx.shape, 3))
        col[:] = (0.2, 0.42, 0.15)  # grass beyond the town
        col[inside] = (0.55, 0.52, 0.46)  # courtyards
        col[inside & walk] = (0.62, 0.62, 0.6)
        col[inside & road] = (0.3, 0.3, 0.32)
        col[inside & (dash_x | dash_y)] = (0.85, 0.85, 0.75)
        col = col * (np.asarray(light.tint) * light.brightness)
        fog = (1.0 - np.exp(-dist / 220.0))[..., None]
        return col + (np.asarray(light.sky_horizon) - col) * fog

    def _hits(
        self, x: float, y: float, dx: F64, dy: F64, obstacles: Sequence[Obstacle]
    ) -> tuple[F64, NDArray[np.bool_], NDArray[np.int64]]:
        """Distances, hit face (True: a face normal to x) and box id of the nearest hits."""
        b = self.town.boxes
        sdx = np.where(np.abs(dx) < 1e-9, 1e-9, dx)[:, None]
        sdy = np.where(np.abs(dy) < 1e-9, 1e-9, dy)[:, None]
        t, xface = _slab(x, y, sdx, sdy, b)
        if obstacles:  # oriented boxes: cast the rays in each box's own frame
            ts, fs = [t], [xface]
            for ob in obstacles:
                c, s = np.cos(ob.pose[2]), np.sin(ob.pose[2])
                ox, oy = x - ob.pose[0], y - ob.pose[1]
                lx, ly = c * ox + s * oy, -s * ox + c * oy
                ldx, ldy = c * sdx + s * sdy, -s * sdx + c * sdy
                ldx = np.where(np.abs(ldx) < 1e-9, 1e-9, ldx)
                ldy = np.where(np.abs(ldy) < 1e-9, 1e-9, ldy)
                box = np.array([[-ob.length / 2, -ob.width / 2, ob.length / 2, ob.width / 2]])
                tt, ff = _slab(lx, ly, ldx, ldy, box)
                ts.append(tt)
                fs.append(ff)
            t, xface = np.concatenate(ts, axis=1), np.concatenate(fs, axis=1)
        k = min(self.layers, t.shape[1])
        if k < t.shape[1]:
            idx = np.argpartition(t, k - 1, axis=1)[:, :k]
        else:
            idx = np.broadcast_to(np.arange(t.shape[1]), t.shape)
        if len(self._tall):  # landmarks always take part: they show above nearer roofs
            idx = np.concatenate([idx, np.broadcast_to(self._tall, (len(t), len(self._tall)))], 1)
        tk = np.take_along_axis(t, idx, axis=1)
        order = np.argsort(tk, axis=1)
        idx = np.take_along_axis(idx, order, axis=1)
        return (
            np.take_along_axis(t, idx, axis=1),
            np.take_along_axis(xface, idx, axis=1),
            idx,
        )

    def _attributes(self, obstacles: Sequence[Obstacle]) -> tuple[F64, F64, F64, F64]:
        t = self.town
        if not obstacles:
            return t.heights, t.colours, t.textures, t.accent
        h = np.concatenate([t.heights, [o.height for o in obstacles]])
        c = np.concatenate([t.colours, [o.colour for o in obstacles]])
        tex = np.concatenate([t.textures, [[TEX_VSTRIPES, 2.0, 3.0, 0.08] for _ in obstacles]])
        acc = np.concatenate([t.accent, [[0.2, 0.2, 0.2] for _ in obstacles]])
        return h, c, tex, acc


def _slab(
    x: float | F64, y: float | F64, dx: F64, dy: F64, boxes: F64
) -> tuple[F64, NDArray[np.bool_]]:
    """Ray/box slab test: entry distance (inf on a miss) and whether the face hit is x-normal."""
    tx1, tx2 = (boxes[:, 0] - x) / dx, (boxes[:, 2] - x) / dx
    ty1, ty2 = (boxes[:, 1] - y) / dy, (boxes[:, 3] - y) / dy
    tminx, tminy = np.minimum(tx1, tx2), np.minimum(ty1, ty2)
    tnear = np.maximum(tminx, tminy)
    tfar = np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2))
    hit = (tnear < tfar) & (tnear > 0.05)
    return np.where(hit, tnear, np.inf), tminx > tminy


def _facade_pattern(tex: F64, u: F64, v: F64) -> NDArray[np.bool_]:
    """Where a facade shows its accent colour (windows, stripes or bands), per pixel."""
    kind, period, floor, frac = tex[:, 0], tex[:, 1], tex[:, 2], tex[:, 3]
    pu = (u % period) / period
    pv = (v % floor) / floor
    windows = (pu < frac) & (pv > 0.35) & (pv < 0.8) & (v > 3.0)
    vstripes = pu < 0.3 * frac + 0.1
    hbands = pv < 0.35
    return np.where(
        kind == TEX_WINDOWS,
        windows,
        np.where(kind == TEX_VSTRIPES, vstripes, (kind == TEX_HBANDS) & hbands),
    )


# ---- the route and the drive -----------------------------------------------------------------


@dataclass(frozen=True)
class Route:
    """A closed loop through the streets, as a dense polyline of the right-hand lane."""

    points: F64  # (M, 2) lane centre, closed (the last point connects to the first)
    s: F64  # (M + 1,) arc length at each point, s[-1] is the lap length
    heading: F64  # (M,) unwrapped yaw at each point (mean of the segments around it)
    curvature: F64  # (M,) |dyaw/ds|, smoothed, 1/m

    @property
    def length(self) -> float:
        return float(self.s[-1])

    def pose_at(self, s: F64 | float, lateral: float = 0.0) -> F64:
        """Pose(s) [x, y, yaw] at arc length `s` (wraps around the lap), shifted `lateral` m
        to the left of the lane centre. Works on arrays of `s`, giving (N, 3)."""
        s = np.asarray(s, dtype=np.float64) % self.length
        closed = np.vstack([self.points, self.points[:1]])
        x = np.interp(s, self.s, closed[:, 0])
        y = np.interp(s, self.s, closed[:, 1])
        yaw = np.interp(s, self.s, np.append(self.heading, self.heading[0] + _turns(self.heading)))
        x = x - np.sin(yaw) * lateral
        y = y + np.cos(yaw) * lateral
        return np.stack([x, y, np.asarray(se2.wrap(yaw))], axis=-1)

    @classmethod
    def through(cls, town: Town, rng: np.random.Generator, lane: float = 3.5) -> Route:
        """A random simple loop around a connected set of blocks, driven on the right."""
        corners = _block_loop(rng, town.blocks, target_edges=(12, 16))
        if rng.random() < 0.5:
            corners = corners[::-1]  # clockwise instead of counter-clockwise
        xy = town.origin + town.pitch * np.asarray(corners, dtype=np.float64)
        return cls.from_corners(xy, lane=lane, radius=8.0)

    @classmethod
    def from_corners(cls, corners: F64, lane: float = 3.5, radius: float = 8.0) -> Route:
        """Offset a rectilinear loop `lane` m to the right and round its corners."""
        n = len(corners)
        inc = np.roll(corners, -1, axis=0) - corners
        d = inc / np.linalg.norm(inc, axis=1, keepdims=True)  # leaving direction per corner
        right = np.stack([d[:, 1], -d[:, 0]], axis=1)
        prev_right = np.roll(right, 1, axis=0)
        prev_d = np.roll(d, 1, axis=0)
        cross = prev_d[:, 0] * d[:, 1] - prev_d[:, 1] * d[:, 0]  # > 0: left turn
        # offset corner where the two shifted lines meet (perpendicular segments)
        off = corners + lane * (right + prev_right)
        pts: list[F64] = []
        for i in range(n):
            a, b = prev_d[i], d[i]
            if abs(cross[i]) < 1e-9:  # straight through
                pts.append(off[i][None])
                continue
            start, end = off[i] - radius * a, off[i] + radius * b
            left = np.array([-a[1], a[0]])
            centre = start + radius * (left if cross[i] > 0 else -left)
            a0 = np.arctan2(start[1] - centre[1], start[0] - centre[0])
            a1 = np.arctan2(end[1] - centre[1], end[0] - centre[0])
            sweep = float(se2.wrap(a1 - a0))
            phi = a0 + sweep * np.linspace(0.0, 1.0, 9)
            pts.append(centre + radius * np.stack([np.cos(phi), np.sin(phi)], axis=1))
        poly = np.vstack(pts)
        dense = _resample_closed(poly, step=0.5)
        seg = np.roll(dense, -1, axis=0) - dense
        seglen = np.linalg.norm(seg, axis=1)
        s = np.concatenate([[0.0], np.cumsum(seglen)])
        seg_head = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
        heading = seg_head - se2.wrap(seg_head - np.roll(seg_head, 1)) / 2
        kappa = np.abs(se2.wrap(seg_head - np.roll(seg_head, 1))) / np.maximum(seglen, 1e-6)
        kernel = np.ones(31) / 31  # ±7.5 m: anticipate corners
        kappa = np.convolve(np.concatenate([kappa[-15:], kappa, kappa[:15]]), kernel, "valid")
        return cls(points=dense, s=s, heading=heading, curvature=kappa)


def _turns(heading: F64) -> float:
    """Total unwrapped heading change over one lap (±2π for a simple loop)."""
    return float(heading[-1] - heading[0] + se2.wrap(heading[0] - heading[-1]))


def _resample_closed(poly: F64, step: float) -> F64:
    closed = np.vstack([poly, poly[:1]])
    seg = np.linalg.norm(np.diff(closed, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(int(s[-1] / step), 8)
    q = np.linspace(0.0, s[-1], n, endpoint=False)
    return np.stack([np.interp(q, s, closed[:, 0]), np.interp(q, s, closed[:, 1])], axis=1)


def _block_loop(
    rng: np.random.Generator, blocks: int, target_edges: tuple[int, int]
) -> list[tuple[int, int]]:
    """Corners (grid indices) of the counter-clockwise boundary of a random polyomino of
    blocks with no holes and no pinch points, whose perimeter is within `target_edges`."""
    for _ in range(1000):
        start = (int(rng.integers(0, blocks)), int(rng.integers(0, blocks)))
        cells = {start}
        size = int(rng.integers(3, 9))
        while len(cells) < size:
            cx, cy = list(cells)[int(rng.integers(0, len(cells)))]
            nx, ny = (cx, cy) + np.array([(1, 0), (-1, 0), (0, 1), (0, -1)])[rng.integers(0, 4)]
            if 0 <= nx < blocks and 0 <= ny < blocks:
                cells.add((int(nx), int(ny)))
        loop = _boundary(cells)
        if loop is not None and target_edges[0] <= len(loop) <= target_edges[1]:
            return _corners_only(loop)
    raise RuntimeError("could not find a route loop; the town is too small")


def _boundary(cells: set[tuple[int, int]]) -> list[tuple[int, int]] | None:
    """Grid vertices along the boundary, counter-clockwise; None if it is not one simple loop."""
    nxt: dict[tuple[int, int], tuple[int, int]] = {}
    for cx, cy in cells:
        sides = [
            ((cx, cy - 1), (cx, cy), (cx + 1, cy)),  # south edge, walked east
            ((cx + 1, cy), (cx + 1, cy), (cx + 1, cy + 1)),  # east edge, walked north
            ((cx, cy + 1), (cx + 1, cy + 1), (cx, cy + 1)),  # north edge, walked west
            ((cx - 1, cy), (cx, cy + 1), (cx, cy)),  # west edge, walked south
        ]
        for nb, a, b in sides:
            if nb not in cells:
                if a in nxt:  # two boundary edges leave one vertex: a pinch point
                    return None
                nxt[a] = b
    start = next(iter(nxt))
    loop, v = [start], nxt[start]
    while v != start:
        loop.append(v)
        v = nxt[v]
        if len(loop) > len(nxt):
            return None
    return loop if len(loop) == len(nxt) else None  # a hole leaves edges unvisited


def _corners_only(loop: list[tuple[int, int]]) -> list[tuple[int, int]]:
    n = len(loop)
    keep = []
    for i in range(n):
        a, b, c = np.array(loop[i - 1]), np.array(loop[i]), np.array(loop[(i + 1) % n])
        if (b - a)[0] * (c - b)[1] - (b - a)[1] * (c - b)[0] != 0:
            keep.append(loop[i])
    return keep


@dataclass(frozen=True)
class Truck:
    """A truck that occludes the camera for a while: following ahead, or oncoming."""

    start_s: float  # seconds into the drive
    end_s: float
    oncoming: bool
    gap: float  # metres ahead of the vehicle (when following) at the start
    colour: tuple[float, float, float]


@dataclass
class Drive:
    """The vehicle on its route: time stamps, ground-truth poses, lighting and traffic."""

    town: Town
    route: Route
    rate_hz: float
    t: F64  # (N,) seconds from the start
    s: F64  # (N,) arc length driven (grows past the lap length on later laps)
    poses: F64  # (N, 3) ground truth
    time_of_day: F64  # (N,)
    overcast: F64  # (N,)
    trucks: tuple[Truck, ...]

    @classmethod
    def generate(
        cls,
        town: Town,
        seed: int,
        rate_hz: float = 20.0,
        duration_s: float = 90.0,
        cruise: float = 10.0,
        trucks_per_minute: float = 2.5,
    ) -> Drive:
        if rate_hz <= 0 or duration_s <= 0:
            raise ValueError("rate_hz and duration_s must be positive")
        rng = np.random.default_rng(seed)
        route = Route.through(town, rng)
        n = max(round(duration_s * rate_hz), 1)
        dt = 1.0 / rate_hz
        t = np.arange(n) * dt
        phase, period = rng.uniform(0, 2 * np.pi), rng.uniform(20, 40)
        cruise_v = cruise * (1.0 + 0.12 * np.sin(2 * np.pi * t / period + phase))
        s = np.empty(n)
        s[0] = rng.uniform(0, route.length)
        v_prev = 0.8 * cruise
        m = len(route.curvature)
        for i in range(1, n):  # corners cap speed (lateral acceleration <= 2.5 m/s²)
            k = route.curvature[int((s[i - 1] % route.length) / route.length * m)]
            v = min(cruise_v[i - 1], np.sqrt(2.5 / max(k, 1e-6)))
            v = float(np.clip(v, v_prev - 3.0 * dt, v_prev + 2.0 * dt))  # brake 3, accelerate 2
            s[i] = s[i - 1] + v * dt
            v_prev = v
        poses = route.pose_at(s)
        tod0 = rng.uniform(0.05, 0.95)
        tod = np.clip(tod0 + (rng.uniform(-1, 1) * 0.1) * t / max(duration_s, 1.0), 0.0, 1.0)
        oc_phase, oc_base = rng.uniform(0, 2 * np.pi), rng.uniform(0.0, 0.7)
        overcast = np.clip(oc_base + 0.25 * np.sin(2 * np.pi * t / 50.0 + oc_phase), 0, 1)
        trucks = []
        at = rng.exponential(60.0 / trucks_per_minute) if trucks_per_minute > 0 else np.inf
        while at < t[-1]:
            oncoming = bool(rng.random() < 0.4)
            length = rng.uniform(3.0, 5.0) if oncoming else rng.uniform(4.0, 12.0)
            colour = tuple(float(c) for c in rng.choice(_TRUCK_COLOURS))
            trucks.append(Truck(at, at + length, oncoming, rng.uniform(6.0, 12.0), colour))
            at += length + rng.exponential(60.0 / trucks_per_minute)
        return cls(town, route, rate_hz, t, s, poses, tod, overcast, tuple(trucks))

    def lighting(self, i: int) -> Lighting:
        return Lighting.at(float(self.time_of_day[i]), float(self.overcast[i]))

    def obstacles(self, i: int) -> tuple[Obstacle, ...]:
        """The trucks on the road at frame `i`, placed along the route."""
        now = float(self.t[i])
        out = []
        for tr in self.trucks:
            if not tr.start_s <= now < tr.end_s:
                continue
            u = now - tr.start_s
            if tr.oncoming:  # meets us mid-way, 7 m to our left, at 9 m/s
                rel = (tr.end_s - tr.start_s) / 2 * (9.0 + 10.0) - u * (9.0 + 10.0)
                p = self.route.pose_at(self.s[i] + rel, lateral=7.0)
                p[2] = float(se2.wrap(p[2] + np.pi))
            else:  # pulls away slowly: the gap opens by 1 m/s
                p = self.route.pose_at(self.s[i] + tr.gap + 5.0 + u * 1.0)
            out.append(Obstacle(pose=p, colour=tr.colour))
        return tuple(out)


_TRUCK_COLOURS = np.array(
    [[0.88, 0.88, 0.85], [0.75, 0.15, 0.12], [0.15, 0.25, 0.6], [0.85, 0.7, 0.15]]
)


# ---- visual odometry -------------------------------------------------------------------------


@dataclass(frozen=True)
class VoNoise:
    """How the VO drifts: a scale bias, a heading-rate bias random walk and per-frame noise.

    Rates are per second (or per metre) so the drift does not depend on the frame rate.
    """

    scale_bias_std: float = 0.03  # relative, drawn once per trace
    yaw_rate_bias_std: float = 1e-3  # rad/s, drawn once per trace
    yaw_rate_walk: float = 3e-4  # rad/s per sqrt(s): the bias wanders
    trans_noise: float = 0.02  # m per sqrt(m) travelled
    yaw_noise: float = 1e-3  # rad per sqrt(s)


def vo_trace(gt: F64, rate_hz: float, rng: np.random.Generator, noise: VoNoise = VoNoise()) -> F64:
    """VO poses (N, 3): ground-truth increments, biased and noisy, integrated from gt[0]."""
    gt = np.asarray(gt, dtype=np.float64)
    n = len(gt)
    dt = 1.0 / rate_hz
    inc = se2.between(gt[:-1], gt[1:])  # (N-1, 3) motion per frame in the vehicle frame
    scale = 1.0 + rng.normal(0.0, noise.scale_bias_std)
    bias = rng.normal(0.0, noise.yaw_rate_bias_std) + np.cumsum(
        rng.normal(0.0, noise.yaw_rate_walk * np.sqrt(dt), size=n - 1)
    )
    step = np.hypot(inc[:, 0], inc[:, 1])
    tn = rng.normal(0.0, 1.0, size=(n - 1, 2)) * (noise.trans_noise * np.sqrt(step))[:, None]
    yn = rng.normal(0.0, noise.yaw_noise * np.sqrt(dt), size=n - 1)
    meas = np.stack(
        [inc[:, 0] * scale + tn[:, 0], inc[:, 1] * scale + tn[:, 1], inc[:, 2] + bias * dt + yn],
        axis=1,
    )
    # integrate: headings first, then each step rotated into the world by the heading before it
    yaw = gt[0, 2] + np.concatenate([[0.0], np.cumsum(meas[:, 2])])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    dxy = np.stack([c * meas[:, 0] - s * meas[:, 1], s * meas[:, 0] + c * meas[:, 1]], axis=1)
    xy = gt[0, :2] + np.concatenate([np.zeros((1, 2)), np.cumsum(dxy, axis=0)])
    return np.concatenate([xy, np.asarray(se2.wrap(yaw))[:, None]], axis=1)
