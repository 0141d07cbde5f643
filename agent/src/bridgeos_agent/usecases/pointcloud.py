"""People Detection's Publisher: the robot's simulated RGB-D camera publishing ``pointcloud``.

Renders the room (people, a table, a cabinet, a lamp pole) once into an organised
sensor_msgs/PointCloud2 of PCL PointXYZRGB points (32 bytes each) and publishes it at
``--rate`` with a fresh stamp: ``--megabytes 40`` gives the thesis's 30-40 MB clouds.
"""

from __future__ import annotations

import argparse
import time

from bridgeos_agent.usecases.camera import default_scene, parse_people, render, size_for_megabytes


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase pointcloud", description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=320, help="pixels across (default 320)")
    parser.add_argument("--height", type=int, default=240, help="pixels down (default 240)")
    parser.add_argument("--megabytes", type=float, default=None, help="pick a 4:3 size of about this many MB")
    parser.add_argument("--rate", type=float, default=1.0, help="clouds a second")
    parser.add_argument("--people", default=None, help="people as 'x,y;x,y' metres (default: three)")
    parser.add_argument("--count", type=int, default=0, help="stop publishing after this many clouds (0: never)")
    args = parser.parse_args(argv)
    if args.megabytes is not None:
        if not 0.01 <= args.megabytes <= 200:
            parser.error("--megabytes must be between 0.01 and 200")
        args.width, args.height = size_for_megabytes(args.megabytes)
    if not (4 <= args.width <= 4096 and 3 <= args.height <= 4096):
        parser.error("--width must be 4-4096 and --height 3-4096")
    if not 0 < args.rate <= 100 or args.count < 0:
        parser.error("--rate must be in (0, 100] and --count >= 0")
    try:
        args.people = parse_people(args.people) if args.people is not None else None
    except ValueError as exc:
        parser.error(str(exc))
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Header

    from bridgeos_agent.usecases.rosio import Metrics, cloud_message

    rospy.init_node("pointcloud")
    metrics = Metrics("pointcloud")
    started = time.perf_counter()
    scene = default_scene(args.people)
    points = render(scene, args.width, args.height)
    message = cloud_message(Header(frame_id="camera"), points, height=args.height)
    megabytes = len(message.data) / 1e6
    print(
        f"[pointcloud] {args.width}x{args.height} cloud, {megabytes:.1f} MB, {len(scene.people)} people, "
        f"rendered in {time.perf_counter() - started:.2f} s, {args.rate:g} Hz",
        flush=True,
    )
    publisher = rospy.Publisher("pointcloud", PointCloud2, queue_size=1)
    rate = rospy.Rate(args.rate)
    sent = 0
    try:
        while not rospy.is_shutdown() and (args.count == 0 or sent < args.count):
            message.header.stamp = rospy.Time.now()
            begin = time.perf_counter()
            publisher.publish(message)
            sent += 1
            if sent % max(1, round(args.rate * 10)) == 1:
                metrics.report("pointcloud_publish_ms", (time.perf_counter() - begin) * 1000, mb=f"{megabytes:.1f}")
            rate.sleep()
        if not rospy.is_shutdown():
            rospy.spin()  # --count reached: stay up, as a sensor driver would
    except rospy.ROSInterruptException:
        pass
    finally:
        metrics.close()
    return 0
