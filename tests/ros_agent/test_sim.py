"""The simulated robot's trajectory and camera scenes (the publishing is tested end to end)."""

import math

import numpy as np

from ros_agent import sim
from ros_agent.extractors import encode_png


def test_figure_eight_twist_matches_the_motion():
    dt = 1e-3
    for t in np.linspace(0.0, sim.LAP_SECONDS, 37):
        here, ahead = sim.figure_eight(t), sim.figure_eight(t + dt)
        moved = math.hypot(ahead.x - here.x, ahead.y - here.y)
        assert math.isclose(moved / dt, here.speed, rel_tol=1e-2)
        assert math.isclose(math.atan2(ahead.y - here.y, ahead.x - here.x), here.yaw, abs_tol=1e-2)
        turned = math.remainder(ahead.yaw - here.yaw, 2 * math.pi)
        assert math.isclose(turned / dt, here.yaw_rate, rel_tol=1e-2, abs_tol=1e-3)
        assert abs(here.x) <= sim.HALF_WIDTH
        assert abs(here.y) <= sim.HALF_WIDTH / 2
        assert 0 < here.speed < 0.5  # a walking-pace robot


def test_the_loop_closes():
    start, end = sim.figure_eight(0.0), sim.figure_eight(sim.LAP_SECONDS)
    assert math.isclose(start.x, end.x, abs_tol=1e-9)
    assert math.isclose(start.y, end.y, abs_tol=1e-9)


def test_scenes_change_and_encode_to_about_58_kb():
    scenes = [sim.draw_scene(frame) for frame in range(10)]
    assert all(scene.shape == (240, 320, 3) and scene.dtype == np.uint8 for scene in scenes)
    assert not np.array_equal(scenes[0], scenes[1])
    sizes = [len(encode_png(scene, "bgr8")) for scene in scenes]
    assert all(55_000 <= size <= 62_000 for size in sizes), sizes
    assert 57_000 <= sum(sizes) / len(sizes) <= 60_500
