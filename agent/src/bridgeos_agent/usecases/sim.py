"""The simulated robot (a Husky-like differential drive): kinematics, laser, wheel encoders.

Subscribes ``cmd_vel`` (geometry_msgs/Twist, obeyed for half a second) and ``path``
(nav_msgs/Path, followed by its on-board controller); publishes ``pose``
(geometry_msgs/PoseStamped, its localisation), ``wheels`` (geometry_msgs/TwistStamped, the
speeds its wheels turned at over the step ending at the stamp) and ``scan``
(sensor_msgs/LaserScan, taken at a step's stamp). The motors and sensors are the fake part;
everything it says travels over real ROS topics.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from bridgeos_agent.usecases.motion import Follower, Pose, integrate
from bridgeos_agent.usecases.world import World, cast_rays, disk_offsets, get_world

ROBOT_RADIUS = 0.2
CMD_TIMEOUT = 0.5


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase sim", description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office", help="world to drive in (office, room)")
    parser.add_argument("--rate", type=float, default=20.0, help="physics steps a second")
    parser.add_argument("--scan-rate", type=float, default=10.0, help="laser scans a second")
    parser.add_argument("--beams", type=int, default=360, help="laser beams over 360 degrees")
    parser.add_argument("--range", type=float, default=6.0, dest="max_range", help="laser range, metres")
    parser.add_argument("--speed", type=float, default=0.5, help="top speed when following a path, m/s")
    parser.add_argument("--start", default=None, help="x,y,theta to start at (default: the world's start)")
    args = parser.parse_args(argv)
    if not (1 <= args.rate <= 200 and 0 < args.scan_rate <= args.rate and 8 <= args.beams <= 4096):
        parser.error("need 1 <= --rate <= 200, 0 < --scan-rate <= --rate and 8 <= --beams <= 4096")
    if not (0 < args.max_range <= 50 and 0 < args.speed <= 5):
        parser.error("need 0 < --range <= 50 and 0 < --speed <= 5")
    try:
        args.world = get_world(args.world)
        args.start = Pose(*(float(v) for v in args.start.split(","))) if args.start else Pose(*args.world.start)
    except (ValueError, TypeError) as exc:
        parser.error(str(exc))
    return args


class SimBody:
    """The robot's body without ROS: obeys commands or follows a path, bumps into walls, casts its laser."""

    def __init__(self, world: World, start: Pose, speed: float, beams: int, max_range: float) -> None:
        self.world, self.speed, self.max_range = world, speed, max_range
        self.grid = world.grid(0.1)
        self.occupied = world.occupancy(0.1)
        self.body_dy, self.body_dx = disk_offsets(ROBOT_RADIUS / self.grid.resolution)
        self.angles = np.linspace(-math.pi, math.pi, beams, endpoint=False)
        self.pose = start
        self.cmd = (0.0, 0.0)
        self.cmd_at = -math.inf
        self.follower: Follower | None = None
        self.path_stamp: int | None = None
        self.collisions = 0

    def command(self, v: float, w: float, now: float) -> None:
        """Obey (v, w) for CMD_TIMEOUT seconds from now (monotonic); someone drives by hand: drop the path."""
        self.cmd, self.cmd_at, self.follower = (v, w), now, None

    def follow(self, stamp_ns: int, points: list[tuple[float, float]]) -> None:
        """Follow a path, unless it is the plan of that stamp again."""
        if stamp_ns == self.path_stamp:
            return
        self.path_stamp = stamp_ns
        self.follower = Follower(points, max_speed=self.speed) if points else None

    def free(self, pose: Pose) -> bool:
        """Say whether the body fits at a pose."""
        iy, ix = self.grid.cell(pose.x, pose.y)
        cy, cx = self.body_dy + iy, self.body_dx + ix
        return bool(self.grid.inside(cy, cx).all() and not self.occupied[cy, cx].any())

    def step(self, dt: float, now: float) -> tuple[float, float]:
        """Move for dt seconds; return the (v, w) the wheels turned at."""
        follower = self.follower
        if follower is not None and not follower.done:
            v, w = follower.command(self.pose)
        elif now - self.cmd_at < CMD_TIMEOUT:
            v, w = self.cmd
        else:
            v, w = 0.0, 0.0
        moved = integrate(self.pose, v, w, dt)
        if not self.free(moved):
            self.collisions += 1
            v = 0.0  # the bumper stops the wheels; turning on the spot is still allowed
            moved = integrate(self.pose, 0.0, w, dt)
        self.pose = moved
        return v, w

    def scan(self) -> np.ndarray:
        """Return the laser's ranges from the current pose (beams from -pi, counter-clockwise)."""
        pose = self.pose
        return cast_rays(self.occupied, self.grid, pose.x, pose.y, self.angles + pose.theta, self.max_range)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from geometry_msgs.msg import PoseStamped, Twist, TwistStamped
    from nav_msgs.msg import Path
    from sensor_msgs.msg import LaserScan

    from bridgeos_agent.usecases.rosio import quaternion

    rospy.init_node("sim")
    world = args.world
    body = SimBody(world, args.start, args.speed, args.beams, args.max_range)
    angles = body.angles

    def on_cmd(msg: Twist) -> None:
        body.command(msg.linear.x, msg.angular.z, time.monotonic())

    def on_path(msg: Path) -> None:
        body.follow(msg.header.stamp.to_nsec(), [(p.pose.position.x, p.pose.position.y) for p in msg.poses])

    rospy.Subscriber("cmd_vel", Twist, on_cmd, queue_size=10)
    rospy.Subscriber("path", Path, on_path, queue_size=2)
    pose_pub = rospy.Publisher("pose", PoseStamped, queue_size=10)
    wheels_pub = rospy.Publisher("wheels", TwistStamped, queue_size=50)
    scan_pub = rospy.Publisher("scan", LaserScan, queue_size=5)
    scan_every = max(1, round(args.rate / args.scan_rate))
    rate = rospy.Rate(args.rate)
    last = rospy.Time.now()
    step = 0
    print(f"[sim] {world.name} world, start {args.start}, {args.rate:g} Hz physics", flush=True)
    while not rospy.is_shutdown():
        try:
            rate.sleep()
        except rospy.ROSInterruptException:
            break
        now = rospy.Time.now()
        dt = (now - last).to_sec()
        last = now
        if dt <= 0:
            continue
        v, w = body.step(dt, time.monotonic())
        moved = body.pose
        wheels = TwistStamped()
        wheels.header.stamp = now
        wheels.header.frame_id = "base_link"
        wheels.twist.linear.x, wheels.twist.angular.z = v, w
        wheels_pub.publish(wheels)
        stamped = PoseStamped()
        stamped.header.stamp = now
        stamped.header.frame_id = "map"
        stamped.pose.position.x, stamped.pose.position.y = moved.x, moved.y
        (
            stamped.pose.orientation.x,
            stamped.pose.orientation.y,
            stamped.pose.orientation.z,
            stamped.pose.orientation.w,
        ) = quaternion(moved.theta)
        pose_pub.publish(stamped)
        if step % scan_every == 0:
            scan = LaserScan()
            scan.header.stamp = now
            scan.header.frame_id = "base_laser"
            scan.angle_min, scan.angle_max = float(angles[0]), float(angles[-1])
            scan.angle_increment = float(angles[1] - angles[0])
            scan.time_increment = 0.0
            scan.scan_time = 1.0 / args.scan_rate
            scan.range_min, scan.range_max = 0.05, args.max_range
            scan.ranges = body.scan().astype(np.float32).tolist()
            scan_pub.publish(scan)
        if step % round(args.rate * 10) == 0:
            print(
                f"[sim] pose x={moved.x:.2f} y={moved.y:.2f} theta={moved.theta:.2f} collisions={body.collisions}",
                flush=True,
            )
        step += 1
    return 0
