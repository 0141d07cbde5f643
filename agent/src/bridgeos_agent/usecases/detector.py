"""People Detection's People Detector: find people in ``pointcloud_sampled``, publish ``people``.

Removes the floor and ceiling, clusters what stands on the floor on a 10 cm grid, and keeps
clusters of a person's height and footprint (geometry_msgs/PoseArray, in the cloud's
frame). Reports ``pointcloud_processing_ms``: from the camera's stamp to detections out,
the thesis's "time required to process a single pointcloud". With ``--http-port`` it also
serves the latest detections as JSON at ``GET /detections``.
"""

from __future__ import annotations

import argparse
import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase detector", description=__doc__.splitlines()[0])
    parser.add_argument("--http-port", type=int, default=0, help="serve GET /detections on this port (0: off)")
    parser.add_argument("--min-height", type=float, default=1.2, help="shortest person, metres")
    parser.add_argument("--max-height", type=float, default=2.1, help="tallest person, metres")
    args = parser.parse_args(argv)
    if not 0 <= args.http_port <= 65535:
        parser.error("--http-port must be 0-65535")
    if not 0 < args.min_height < args.max_height <= 3:
        parser.error("need 0 < --min-height < --max-height <= 3")
    return args


def serve(port: int, latest: dict[str, Any]) -> None:
    """Serve the latest detections on a port, or say why not and carry on without."""

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            if self.path.split("?")[0].rstrip("/") != "/detections":
                self.send_error(404, "only GET /detections")
                return
            body = json.dumps(latest).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: Any) -> None:
            pass  # no line per request

    try:
        server = ThreadingHTTPServer(("0.0.0.0", port), Handler)
    except OSError as exc:
        print(f"[detector] cannot serve HTTP on port {port} ({exc}); detections only on ROS", flush=True)
        return
    threading.Thread(target=server.serve_forever, name="http", daemon=True).start()
    print(f"[detector] serving GET /detections on port {port}", flush=True)


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from geometry_msgs.msg import Pose, PoseArray
    from sensor_msgs.msg import PointCloud2

    from bridgeos_agent.usecases.detection import DetectorSettings, detect_people
    from bridgeos_agent.usecases.rosio import BIG_BUFFER, LossCounter, Metrics, cloud_xyz

    rospy.init_node("detector")
    metrics = Metrics("detector")
    loss = LossCounter()
    settings = DetectorSettings(min_height=args.min_height, max_height=args.max_height)
    latest: dict[str, Any] = {"stamp": None, "people": []}
    publisher = rospy.Publisher("people", PoseArray, queue_size=10)

    def on_cloud(message: PointCloud2) -> None:
        loss.update(message.header.seq)
        begin = time.perf_counter()
        try:
            people = detect_people(cloud_xyz(message), settings)
        except ValueError as exc:
            rospy.logwarn_throttle(10, f"detector: skipping a cloud: {exc}")
            return
        out = PoseArray(header=message.header)
        for person in people:
            pose = Pose()
            pose.position.x, pose.position.y = person.x, person.y
            pose.orientation.w = 1.0
            out.poses.append(pose)
        publisher.publish(out)
        done = rospy.Time.now()
        latest["stamp"] = message.header.stamp.to_sec()
        latest["people"] = [{"x": round(p.x, 3), "y": round(p.y, 3), "height": round(p.height, 3)} for p in people]
        metrics.report("pointcloud_processing_ms", (done - message.header.stamp).to_sec() * 1000)
        metrics.report("detection_ms", (time.perf_counter() - begin) * 1000, people=str(len(people)))
        if loss.received % 10 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="pointcloud_sampled")

    if args.http_port:
        serve(args.http_port, latest)
    rospy.Subscriber("pointcloud_sampled", PointCloud2, on_cloud, queue_size=1, buff_size=BIG_BUFFER)
    try:
        rospy.spin()
    finally:
        metrics.close()
    return 0
