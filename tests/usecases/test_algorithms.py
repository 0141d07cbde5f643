"""The use cases' algorithms as pure functions: planning, mapping, detection, kinematics."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from bridgeos_agent.usecases.__main__ import default_namespace
from bridgeos_agent.usecases.camera import POINT_DTYPE, default_scene, parse_people, render, size_for_megabytes
from bridgeos_agent.usecases.detection import detect_people, voxel_sample
from bridgeos_agent.usecases.motion import Follower, Pose, WheelOdometry, integrate
from bridgeos_agent.usecases.occupancy import LogOddsMap, ScanPairing, map_agreement
from bridgeos_agent.usecases.planning import GoalPlanner, astar, plan_path, segment_free
from bridgeos_agent.usecases.sim import SimBody
from bridgeos_agent.usecases.world import WORLDS, cast_rays, get_world, inflate


@pytest.mark.parametrize("world", sorted(WORLDS))
def test_every_tour_goal_is_reachable_on_a_collision_free_path(world: str) -> None:
    w = get_world(world)
    grid, occupied = w.grid(0.1), w.occupancy(0.1)
    blocked = inflate(occupied, 0.25 / grid.resolution)
    position = w.start[:2]
    for goal in w.goals:
        path = plan_path(occupied, grid, position, goal)
        assert path is not None, f"no path {position} -> {goal}"
        assert path[0] == position and path[-1] == goal
        for a, b in itertools.pairwise(path):
            assert segment_free(blocked, grid, a, b), f"{a} -> {b} passes closer than the robot's radius"
        position = goal


def test_astar_finds_the_shortest_way_and_refuses_walled_goals() -> None:
    blocked = np.zeros((5, 7), dtype=bool)
    blocked[0:4, 3] = True  # a wall with a gap at the bottom row
    path = astar(blocked, (0, 0), (0, 6))
    assert path is not None and path[0] == (0, 0) and path[-1] == (0, 6)
    assert (4, 3) in path  # through the gap
    assert all(not blocked[c] for c in path)
    blocked[4, 3] = True
    assert astar(blocked, (0, 0), (0, 6)) is None
    assert plan_path(get_world("room").occupancy(0.1), get_world("room").grid(0.1), (1.0, 1.0), (2.8, 1.0)) is None


def test_laser_ranges_match_the_walls() -> None:
    w = get_world("room")
    grid, occupied = w.grid(0.1), w.occupancy(0.1)
    ranges = cast_rays(occupied, grid, 1.0, 1.0, np.array([0.0, math.pi, math.pi / 2]), 6.0)
    # Ahead: the partition's face at x = 2.6; behind: the wall's face at x = 0.2; left: the top wall at y = 3.8.
    assert ranges == pytest.approx([1.6, 0.8, 2.8], abs=0.1)
    assert math.isinf(cast_rays(occupied, grid, 1.0, 1.0, np.array([0.0]), 1.0)[0])


def test_a_map_from_the_route_matches_the_world() -> None:
    w = get_world("office")
    grid, occupied = w.grid(0.1), w.occupancy(0.1)
    built = LogOddsMap(grid)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    for (x0, y0), (x1, y1) in itertools.pairwise(w.route):
        for t in np.linspace(0, 1, 8):
            x, y = x0 + (x1 - x0) * t, y0 + (y1 - y0) * t
            built.integrate(Pose(x, y, 0.3), angles, cast_rays(occupied, grid, x, y, angles + 0.3, 6.0), 6.0)
    score = map_agreement(built.occupancy(), occupied)
    assert score["observed"] > 0.8 and score["agreement"] > 0.97 and score["occupied_precision"] > 0.97, score


def test_the_detector_finds_people_and_not_furniture() -> None:
    people = [(2.5, 0.8), (4.0, -1.0), (5.5, 0.6)]
    cloud = render(default_scene(people), 320, 240)
    xyz = np.stack([cloud[a].ravel() for a in "xyz"], axis=1)
    sampled = voxel_sample(xyz, 0.05)
    assert 0 < len(sampled) < np.isfinite(xyz).all(axis=1).sum()
    found = detect_people(sampled)
    assert len(found) == 3, found
    for (x, y), d in zip(people, found, strict=True):
        assert math.dist((x, y), (d.x, d.y)) < 0.3 and 1.6 < d.height < 1.9
    assert (
        detect_people(voxel_sample(np.stack([render(default_scene([]), 160, 120)[a].ravel() for a in "xyz"], 1), 0.05))
        == []
    )


def test_clouds_are_sized_like_the_thesis_s() -> None:
    width, height = size_for_megabytes(40)
    assert width * height * POINT_DTYPE.itemsize == pytest.approx(40e6, rel=0.02)
    assert POINT_DTYPE.itemsize == 32
    with pytest.raises(ValueError, match="x,y"):
        parse_people("1,2;oops")
    with pytest.raises(ValueError, match="in front"):
        parse_people("-1,0")


def test_the_follower_drives_a_route_to_its_end() -> None:
    route = [(0.0, 0.0), (2.0, 0.0), (2.0, 2.0)]
    follower = Follower(route, max_speed=1.0)
    pose = Pose(0.0, 0.0, math.pi)  # facing away: it must turn first
    for _ in range(2000):
        if follower.done:
            break
        v, w = follower.command(pose)
        pose = integrate(pose, v, w, 0.05)
    assert follower.done and math.dist((pose.x, pose.y), route[-1]) <= 0.1


def test_integration_follows_arcs_exactly() -> None:
    quarter = integrate(Pose(0, 0, 0), v=math.pi / 2, w=math.pi / 2, dt=1.0)  # radius 1, quarter turn
    assert (quarter.x, quarter.y, quarter.theta) == pytest.approx((1.0, 1.0, math.pi / 2))


def test_nodes_without_a_router_namespace_keep_robots_and_skills_apart() -> None:
    assert default_namespace({"BRIDGEOS_ROBOT": "demo-1", "BRIDGEOS_SKILL": "people-detection"}) == (
        "/bridgeos/demo_1/people_detection"
    )
    assert default_namespace({"ROS_NAMESPACE": "/given", "BRIDGEOS_SKILL": "x"}) is None
    assert default_namespace({}) is None


def test_scan_pairing_folds_each_scan_with_the_pose_of_its_stamp_and_gives_up_on_lost_ones() -> None:
    folded: list[tuple[str, Pose]] = []
    pairing: ScanPairing[str] = ScanPairing(lambda scan, pose: folded.append((scan, pose)))
    pairing.scan(1_000, "early")  # its pose comes later
    assert folded == []
    pairing.pose(1_000, Pose(1.0, 2.0, 0.0))
    assert folded == [("early", Pose(1.0, 2.0, 0.0))]
    pairing.scan(2_000, "lost")  # its odometry never comes
    pairing.scan(3_000, "late")
    pairing.pose(3_000, Pose(3.0, 0.0, 0.0))
    assert [s for s, _ in folded] == ["early"]  # scans fold in order: "late" waits behind "lost"
    pairing.pose(2_000 + 2_000_000_001, Pose(9.0, 9.0, 0.0))  # two seconds on: "lost" is dropped
    assert [s for s, _ in folded] == ["early", "late"] and pairing.unpaired == 1


def test_goal_planner_plans_once_per_goal_and_waits_for_map_pose_and_goal() -> None:
    world = get_world("room")
    planner = GoalPlanner(0.25)
    assert planner.plan() is None
    planner.set_goal(7, *world.goals[0])
    assert planner.set_position(*world.start[:2]) is True  # a goal waits for its first plan
    assert planner.plan() is None  # no map yet
    planner.set_map(np.where(world.occupancy(0.1), 100, 0).astype(np.int8), world.grid(0.1))
    first = planner.plan()
    assert first is not None and first.fresh and first.points is not None and first.points[-1] == world.goals[0]
    again = planner.plan()
    assert again is not None and not again.fresh and again.points == first.points
    assert planner.set_position(1.2, 1.0) is False  # planned already: a new pose alone plans nothing


def test_wheel_odometry_integrates_steps_between_stamps() -> None:
    odometry = WheelOdometry(Pose(0.0, 0.0, 0.0))
    assert odometry.update(1_000_000_000, 1.0, 0.0) == Pose(0.0, 0.0, 0.0)  # the first stamp starts the clock
    assert odometry.update(1_500_000_000, 1.0, 0.0) == Pose(0.5, 0.0, 0.0)
    assert odometry.update(1_400_000_000, 1.0, 0.0) == Pose(0.5, 0.0, 0.0)  # a stamp back in time moves nothing


def test_the_simulated_body_obeys_commands_stops_at_walls_and_sees_them() -> None:
    world = get_world("room")
    body = SimBody(world, Pose(*world.start), speed=1.0, beams=36, max_range=6.0)
    body.command(1.0, 0.0, now=0.0)
    assert body.step(0.1, now=0.05) == (1.0, 0.0) and body.pose.x > world.start[0]
    assert body.step(0.1, now=1.0) == (0.0, 0.0)  # the command timed out
    body.command(-1.0, 0.0, now=2.0)
    for step in range(40):
        body.step(0.1, now=2.0 + step * 0.01)
    assert body.collisions > 0 and body.free(body.pose)  # it backed into the wall and stopped there
    ranges = body.scan()
    assert ranges.shape == (36,) and np.nanmin(ranges) < 0.5
    body.follow(5, [(body.pose.x + 1.0, body.pose.y)])
    assert body.follower is not None
    body.follow(5, [])  # the same plan's stamp again: kept
    assert body.follower is not None
