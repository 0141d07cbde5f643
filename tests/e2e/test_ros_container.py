"""A rospy node inside the ROS image talks to the host's ROS master and nodes."""

from __future__ import annotations

import subprocess
import uuid

import pytest

PUBLISHER = """
import rospy
from std_msgs.msg import String
rospy.init_node("container_talker", anonymous=True)
pub = rospy.Publisher("{topic}", String, queue_size=10)
rate = rospy.Rate(10)
n = 0
while not rospy.is_shutdown():
    pub.publish(String(data="hello-from-container %d" % n))
    n += 1
    rate.sleep()
"""

SUBSCRIBER = """
import sys
import rospy
from std_msgs.msg import String
rospy.init_node("host_listener", anonymous=True, disable_signals=True)
msg = rospy.wait_for_message(sys.argv[1], String, timeout=float(sys.argv[2]))
print(msg.data, flush=True)
"""


@pytest.mark.docker
@pytest.mark.ros
def test_host_node_receives_messages_published_in_container(containers, ros_image: str, host_ros) -> None:
    run_id = uuid.uuid4().hex[:12]
    topic = f"/bridgeos_e2e/chatter_{run_id}"
    name = containers.run(
        f"bridgeos-e2e-talker-{run_id}",
        ros_image,
        "python3",
        "-c",
        PUBLISHER.format(topic=topic),
        env={"ROS_MASTER_URI": host_ros.master_uri, "ROS_IP": "127.0.0.1"},
    )

    try:
        listened = host_ros.python(SUBSCRIBER, topic, "30", timeout=45)
    except subprocess.TimeoutExpired:
        pytest.fail(f"host subscriber hung; container logs:\n{containers.logs(name)}")

    assert listened.returncode == 0, (
        f"no message on {topic} within 30 s\nsubscriber stderr:\n{listened.stderr[-2000:]}\n"
        f"container logs:\n{containers.logs(name)}"
    )
    payload = listened.stdout.strip().splitlines()[-1]
    assert payload.startswith("hello-from-container ")
    assert payload.removeprefix("hello-from-container ").isdigit()
