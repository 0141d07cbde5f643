"""offloading_quality's scenario: the Skill of four burners, the robot's scripted phases, the simulated robot."""

from __future__ import annotations

import sys
from collections.abc import Callable
from dataclasses import dataclass, field

from bridgeos_agent.monitor import Sample, SimulatedRobot
from bridgeos_agent.skillconfig import SkillConfig, parse_skill_config

ROBOT_ID = "offload-bench"
SKILL_ID = "offload"
CPU_CORES = 2.0
LAN_MBITS = 100.0  # the robot's own network, which components on the robot use to reach its sensors
DECISION_INTERVAL = 0.25
SAMPLE_INTERVAL = 0.25
# Cost units (delays of 5-70): the rewards of real changes are 9 or more, the stable phase's reward
# noise 2-4 (machine load), so a hysteresis of 3 keeps a move to a barely better place from being noise.
THRESHOLD, HYSTERESIS = 2.0, 3.0
COOLDOWN = 4.0
TIMELINE_STEP = 0.1
FLAP_WINDOW = 60.0
ADAPTED_WITHIN = 1.05
SETTLE_S = 10.0  # the adaptation goal: moves later than this into the stable phase are noise
GOALS = {
    "cost_over_oracle": 1.05,
    "adapt_s": 10.0,
    "flaps_per_10min": 1.0,
    "stable_moves_per_10min": 1.0,
    "cost_over_oracle_misdeclared": 1.10,
}
# The misdeclared scenario (issue 22): this component declares a tenth of the CPU it burns. Two more
# robots run it beside the main one, same script and seed: one decides by the estimate alone (its
# network is never trained enough to be trusted), the other learns from outcomes.
MISDECLARED = "detector"
MISDECLARED_SHARE = 0.1
ESTIMATE_ROBOT, LEARNED_ROBOT = f"{ROBOT_ID}-estimate", f"{ROBOT_ID}-learned"
# Learning from outcomes: every outcome trains, three steps (one Adam step per outcome needs a stay of
# 30 decisions or more to learn a tenfold misdeclaration, three about 10), and the trust gate
# (held-out outcomes), not a sample count, decides: the network is asked from its second outcome on, so
# the one to four outcomes a first stay on the robot gives before the estimate sends it away are scored.
LEARNING = {"trained_after": 1, "warmup_train_every": 1, "train_every": 1, "train_steps": 3}
ESTIMATE_ONLY = {"trained_after": 1_000_000}

# Declared usage: cores, Mbit/s exchanged with the robot's sensors (what crosses the link in the cloud).
COMPONENTS = {
    "detector": {"cpu": 0.2, "bandwidth": 2.0},
    "sampler": {"cpu": 0.03, "bandwidth": 30.0},
    "mapper": {"cpu": 0.08, "bandwidth": 6.0},
    "planner": {"cpu": 0.1, "bandwidth": 0.5},
}
POLICY = {
    "robot": "cpu_scale * cpu / max(cpu_free, 0.05)",
    "cloud": "cloud_rtt + link_scale * bandwidth / max(bandwidth_available, 0.5)",
}
CONSTANTS = {"cpu_scale": 200.0, "cloud_rtt": 20.0, "link_scale": 100.0}
# --cloud-mb: the sampler takes the camera's clouds at this rate (benchmarks/usecases.py's big-cloud
# rate) and thins one MB of cloud in this many core-seconds (voxel sampling a 35 MB cloud: 0.56 s here).
CLOUD_RATE_HZ = 0.2
SAMPLING_S_PER_MB = 0.016


def size_clouds(megabytes: float) -> None:
    """Make the sampler declare what thesis-sized clouds cost it: their Mbit/s and sampling CPU."""
    COMPONENTS["sampler"] = {
        "cpu": SAMPLING_S_PER_MB * megabytes * CLOUD_RATE_HZ,
        "bandwidth": megabytes * 8 * CLOUD_RATE_HZ,
    }


# Burn a share of one core in short slices: what the component declares is what the runtime measures.
BURNER = """
import sys, time
share, period = float(sys.argv[1]), 0.05
while True:
    started, cpu = time.perf_counter(), time.process_time()
    while time.process_time() - cpu < share * period:
        pass
    time.sleep(max(0.0, period - (time.perf_counter() - started)))
"""
# The same burner as a ROS 2 node: its timer burns the share, in the namespace the agent gives it.
BURNER_ROS2 = """
import os, sys, time
import rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import Float32
share, period = float(sys.argv[1]), 0.05
rclpy.init()
node = rclpy.create_node("burner", namespace=os.environ.get("ROS_NAMESPACE") or "")
load = node.create_publisher(Float32, "load", 10)
def burn():
    cpu = time.process_time()
    while time.process_time() - cpu < share * period:
        pass
    load.publish(Float32(data=share))
node.create_timer(period, burn)
try:
    rclpy.spin(node)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
except Exception:
    if rclpy.ok():
        raise  # a publish racing the shutdown a signal began is no failure
"""


@dataclass(frozen=True)
class Phase:
    """Conditions held for a while: background CPU load (cores) and the link's bandwidth (Mbit/s)."""

    name: str
    load: float
    link: float
    noise: float = 1.0  # multiplies the robot's load and link noise


IDLE_GOOD = Phase("idle robot, good link", 0.2, 100.0)
BUSY_GOOD = Phase("busy robot, good link", 1.5, 100.0)
BUSY_POOR = Phase("busy robot, poor link", 1.5, 4.0)
IDLE_POOR = Phase("idle robot, poor link", 0.2, 4.0)
QUICK_SCRIPT = [IDLE_GOOD, BUSY_GOOD, BUSY_POOR, IDLE_POOR]
FULL_SCRIPT = [IDLE_GOOD, BUSY_GOOD, BUSY_POOR, IDLE_POOR, IDLE_GOOD, BUSY_POOR, BUSY_GOOD, IDLE_POOR]
# The planner's robot and cloud costs differ by about 1 here (a tenth of a core of load swings it by 3):
# the stable phase where noise, not conditions, would move a component.
STABLE = Phase("moderate load, noisier", 0.65, 100.0, noise=3.0)


@dataclass
class Script:
    """Scripted phases from ``start`` (a time.time() value, set when the Skill runs).

    The changing phases last ``phase_s`` each; the last phase, when ``stable_s`` is set, is the stable one.
    """

    phases: list[Phase]
    phase_s: float
    start: float | None = None
    stable_s: float = 0.0

    @property
    def changing(self) -> int:
        """Return how many phases are the changing ones (the stable phase, if any, comes after them)."""
        return len(self.phases) - 1 if self.stable_s else len(self.phases)

    def bounds(self, index: int) -> tuple[float, float]:
        """Return a phase's start and end, in seconds since the script's start."""
        start = index * self.phase_s
        return start, start + (self.stable_s if index >= self.changing else self.phase_s)

    def index(self, elapsed: float) -> int:
        """Return the phase in force ``elapsed`` seconds after the start."""
        return max(0, min(len(self.phases) - 1, int(elapsed // self.phase_s)))

    def at(self, now: float) -> Phase:
        """Return the phase in force at ``now`` (the first until the script starts)."""
        return self.phases[0] if self.start is None else self.phases[self.index(now - self.start)]

    @property
    def duration(self) -> float:
        """Return the script's length in seconds."""
        return self.bounds(len(self.phases) - 1)[1]


@dataclass(slots=True)
class ScriptedRobot(SimulatedRobot):
    """A SimulatedRobot whose background CPU load and link bandwidth follow a script, with noise."""

    script: Script = field(default_factory=lambda: Script([IDLE_GOOD], 1.0))
    load_noise: float = 0.03  # cores, standard deviation
    link_noise: float = 0.03  # share of the link, standard deviation
    # Cores the components on the robot burn beyond what they declare (the misdeclared scenario): the
    # simulated load follows declarations, a real robot's reading what is burnt, as the costing charges it.
    undeclared: Callable[[], float] | None = None

    def bandwidth_now(self, now: float) -> float:
        """Return the link's bandwidth at ``now`` (Mbit/s)."""
        phase = self.script.at(now)
        return max(0.1, phase.link * (1 + self._random.gauss(0, self.link_noise * phase.noise)))

    def sample(self, now: float, used, cloud_bytes: tuple[float, float]) -> Sample:
        """Read the robot with the scripted background load on top of what its components use."""
        phase = self.script.at(now)
        load = max(0.0, phase.load + self._random.gauss(0, self.load_noise * phase.noise))
        if self.undeclared is not None:
            load += self.undeclared()
        sample = SimulatedRobot.sample(self, now, {**used, "cpu": used.get("cpu", 0.0) + load}, cloud_bytes)
        # bandwidth_available is the link to the cloud; components on the robot reach its sensors over the LAN.
        sample.free["bandwidth"] = max(0.0, self.bandwidth - used.get("bandwidth", 0.0))
        return sample


def skill_config(
    noise_margin: float | None = None,
    ros: int = 0,
    ros_domain: int = 0,
    *,
    misdeclared: bool = False,
    learn: bool = True,
) -> SkillConfig:
    """Return the benchmark's Skill: four movable burners (ROS 2 nodes with ros=2; MISDECLARED's CPU understated)."""
    components = {}
    # ROS 2 burners' graph: the benchmark's own domain, discovery kept on loopback.
    graph = {"ROS_DOMAIN_ID": str(ros_domain), "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"} if ros == 2 else {}
    for name, usage in COMPONENTS.items():
        command = [sys.executable, "-c", BURNER_ROS2 if ros == 2 else BURNER, str(usage["cpu"])]
        declared = usage["cpu"] * (MISDECLARED_SHARE if misdeclared and name == MISDECLARED else 1.0)
        components[name] = {
            "name": name.title(),
            "location": "either",
            "ros": 2 if ros == 2 else False,
            "resources": {"cpu": declared, "ram": 32, "bandwidth": usage["bandwidth"]},
            "robot": {"command": command, "env": graph},
            "cloud": {"command": command, "env": graph},
        }
    return parse_skill_config(
        {
            "skill": "Offloading quality",
            "skill_id": SKILL_ID,
            "manager": {
                "policy": "custom",
                "threshold": THRESHOLD,
                "hysteresis": HYSTERESIS,
                "cooldown": COOLDOWN,
                **({} if noise_margin is None else {"noise_margin": noise_margin}),
                "decision_interval": DECISION_INTERVAL,
                "neural_network": LEARNING if learn else ESTIMATE_ONLY,
                "constants": CONSTANTS,
                "cost_functions": POLICY,
            },
            "components": components,
        }
    )


ROBOT_CONFIG = {
    "offloading": "auto",
    "resources": {"cpu": CPU_CORES, "ram": 4096, "bandwidth": LAN_MBITS, "io": 100},
}
