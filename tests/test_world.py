"""The synthetic world: deterministic, on the streets, drifting VO without outliers."""

from __future__ import annotations

import time

import numpy as np
import pytest

from nodes.edgeloc import geometry as se2
from nodes.edgeloc.world import Camera, Drive, Lighting, Obstacle, Route, Town, vo_trace


@pytest.fixture(scope="module")
def town() -> Town:
    return Town.generate()


def test_town_is_deterministic_and_seeded() -> None:
    a, b, c = Town.generate(3), Town.generate(3), Town.generate(4)
    assert np.array_equal(a.boxes, b.boxes) and np.array_equal(a.colours, b.colours)
    assert not np.array_equal(a.colours, c.colours)


def test_town_repeats_blocks_and_has_landmarks(town: Town) -> None:
    ids = town.block_template[town.block_template >= 0]
    assert len(np.unique(ids)) < len(ids)  # look-alike blocks exist on purpose
    assert np.sum(town.heights > 40) >= 3  # towers above every roof
    extent = town.boxes[:, 2:].max() - town.boxes[:, :2].min()
    assert 300 <= extent <= 500


def test_buildings_stay_off_the_roads(town: Town) -> None:
    half = town.road_width / 2
    for r in town.road_coords():
        on_x = (town.boxes[:, 0] < r + half) & (town.boxes[:, 2] > r - half)
        on_y = (town.boxes[:, 1] < r + half) & (town.boxes[:, 3] > r - half)
        assert not on_x.any() and not on_y.any()


def test_drive_is_deterministic_per_seed(town: Town) -> None:
    a, b = Drive.generate(town, 5, 20.0, 30.0), Drive.generate(town, 5, 20.0, 30.0)
    c = Drive.generate(town, 6, 20.0, 30.0)
    assert np.array_equal(a.poses, b.poses) and a.trucks == b.trucks
    assert not np.allclose(a.poses, c.poses)
    cam = Camera(town)
    img_a = cam.render(a.poses[10], a.lighting(10), a.obstacles(10), np.random.default_rng(1))
    img_b = cam.render(b.poses[10], b.lighting(10), b.obstacles(10), np.random.default_rng(1))
    img_c = cam.render(c.poses[10], c.lighting(10), c.obstacles(10), np.random.default_rng(1))
    assert np.array_equal(img_a, img_b) and not np.array_equal(img_a, img_c)


def test_route_is_a_closed_loop_on_the_right_lane(town: Town) -> None:
    route = Route.through(town, np.random.default_rng(11))
    assert 800 < route.length < 1400
    start, end = route.pose_at(0.0), route.pose_at(route.length - 1e-6)
    assert np.hypot(*(start[:2] - end[:2])) < 1.0
    p = route.pose_at(np.linspace(0, route.length, 2000, endpoint=False))
    # every point is on the asphalt: within half a road width of a centreline
    roads = town.road_coords()
    dx = np.min(np.abs(p[:, :1] - roads[None]), axis=1)
    dy = np.min(np.abs(p[:, 1:2] - roads[None]), axis=1)
    assert np.all(np.minimum(dx, dy) < town.road_width / 2)
    assert np.median(np.minimum(dx, dy)) == pytest.approx(3.5, abs=0.1)  # the right lane
    # headings follow the path: moving 1 m along s moves about 1 m along yaw
    q = route.pose_at(np.linspace(0, route.length, 2000, endpoint=False) + 0.5)
    step = se2.between(p, q)
    assert np.all(np.abs(step[:, 0] - 0.5) < 0.05) and np.all(np.abs(step[:, 1]) < 0.05)


def test_drive_speed_and_rate(town: Town) -> None:
    d = Drive.generate(town, 2, rate_hz=20.0, duration_s=60.0)
    assert len(d.t) == 1200 and np.allclose(np.diff(d.t), 0.05)
    v = np.diff(d.s) * 20.0
    assert 7.0 < v.mean() < 11.5 and v.max() < 12.0 and v.min() > 2.0


def test_camera_image_and_render_speed(town: Town) -> None:
    d = Drive.generate(town, 1, 20.0, 20.0)
    cam = Camera(town)
    img = cam.render(d.poses[0], d.lighting(0))
    assert img.shape == (48, 64, 3) and img.dtype == np.uint8
    assert img.std() > 10  # a scene, not a flat colour
    t0 = time.perf_counter()
    for i in range(100):
        cam.render(d.poses[i], d.lighting(i), d.obstacles(i))
    print(f"render: {100 / (time.perf_counter() - t0):.0f} frames/s (one core, 64x48)")


def test_lighting_and_trucks_change_the_picture(town: Town) -> None:
    cam = Camera(town)
    p = np.array([town.road_coords()[2] - 3.5, 0.0, np.pi / 2])
    day = cam.render(p, Lighting.at(0.5, 0.0))
    dusk = cam.render(p, Lighting.at(0.02, 0.8))
    assert day.mean() > dusk.mean() + 20
    truck = Obstacle(se2.compose(p, np.array([9.0, 0.0, 0.0])), colour=(0.8, 0.1, 0.1))
    blocked = cam.render(p, Lighting.at(0.5, 0.0), [truck])
    centre = (slice(14, 30), slice(24, 40))
    assert np.abs(blocked[centre].astype(int) - day[centre].astype(int)).mean() > 30


def test_vo_drift_grows_with_distance_without_outliers(town: Town) -> None:
    finals, earlies = [], []
    for seed in range(8):
        d = Drive.generate(town, seed, 20.0, 90.0)
        vo = vo_trace(d.poses, 20.0, np.random.default_rng(seed))
        err = np.hypot(*(vo[:, :2] - d.poses[:, :2]).T)
        earlies.append(err[:200].mean())
        finals.append(err[-200:].mean())
        # no outliers: each VO step is within a few cm / mrad of the true step
        step_err = se2.between(vo[:-1], vo[1:]) - se2.between(d.poses[:-1], d.poses[1:])
        assert np.abs(step_err[:, :2]).max() < 0.1
        assert np.abs(se2.wrap(step_err[:, 2])).max() < 0.01
    assert np.mean(finals) > 5 * np.mean(earlies)
    assert 8.0 < np.median(finals) < 80.0  # tens of metres after ~900 m, like real VO


def test_vo_is_deterministic(town: Town) -> None:
    d = Drive.generate(town, 1, 20.0, 10.0)
    a = vo_trace(d.poses, 20.0, np.random.default_rng(4))
    b = vo_trace(d.poses, 20.0, np.random.default_rng(4))
    assert np.array_equal(a, b) and np.array_equal(a[0], d.poses[0])


def test_bad_arguments_are_refused(town: Town) -> None:
    with pytest.raises(ValueError, match="rate_hz"):
        Drive.generate(town, 1, rate_hz=0.0)
    with pytest.raises(ValueError, match="width"):
        Camera(town, width=2)
