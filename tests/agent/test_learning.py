"""The Skill Manager learns from outcomes: a component that declares a tenth of the CPU it burns ends up placed right."""

from __future__ import annotations

import asyncio
import sys

import pytest

from bridgeos_agent.manager import SkillManager
from bridgeos_agent.runtime.cgroups import Cgroups
from bridgeos_agent.skillconfig import parse_skill_config
from tests.conftest import eventually

from .conftest import SKILL, robot_agent, skill_config
from .test_manager import moves_logged

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]

torch = pytest.importorskip("torch")

# Burn a share of one core in short slices, as benchmarks/offloading_quality.py's components do.
BURNER = """
import sys, time
share, period = float(sys.argv[1]), 0.05
while True:
    started, cpu = time.perf_counter(), time.process_time()
    while time.process_time() - cpu < share * period:
        pass
    time.sleep(max(0.0, period - (time.perf_counter() - started)))
"""
BURNS, DECLARES = 0.2, 0.02


def misdeclared_skill() -> dict:
    """Return a Skill whose worker-0 burns BURNS cores but declares DECLARES; worker-1 sleeps, fixed on the robot."""
    config = skill_config(location="either", count=1)
    worker = config["components"]["worker-0"]
    command = {"command": [sys.executable, "-c", BURNER, str(BURNS)]}
    worker.update(robot=command, cloud=command, resources={"cpu": DECLARES, "ram": 32})
    config["manager"] = {
        "policy": "custom",
        # A delay per core used on the robot; a fixed round trip in the cloud. Burning 0.2 cores the
        # robot costs 40 against 22: the cloud is right. Declaring 0.02 it looks like 4: the robot.
        "cost_functions": {"robot": "200 * cpu", "cloud": "22"},
        "threshold": 2.0,
        "hysteresis": 3.0,
        "cooldown": 0.0,
        "decision_interval": 60.0,  # the test steps the manager itself
        "neural_network": {"trained_after": 5, "warmup_train_every": 1, "train_every": 1, "train_steps": 3},
    }
    return parse_skill_config(config).model_dump(mode="json")


async def test_a_misdeclared_component_is_placed_by_what_it_was_measured_to_cost(cloud, tmp_path):
    torch.manual_seed(1)
    config = misdeclared_skill()
    # No cgroup limits: held to what it declares, the component would be throttled rather than burn 0.2 cores.
    options = {"cgroups": Cgroups("learn-1", hierarchy=None)}
    async with robot_agent(
        cloud, "learn-1", tmp_path / "agent", skill=config, plugins={}, runtime_options=options
    ) as controller:
        record = await controller.start_skill(parse_skill_config(config))
        assert record.locations["worker-0"] == "robot"
        manager = SkillManager(controller, SKILL)

        async def measured() -> float:
            usage = controller.usage.get((SKILL, "worker-0"))
            return usage.cpu if usage is not None and usage.cpu > BURNS / 2 else 0.0

        await eventually(measured, what="the runtime measuring the burner", timeout=30)
        decider = manager._decider("worker-0")
        # Held on the robot for a while (as after a move, cooling down), the network learns what it costs there.
        decider.cooldown = 3600.0
        decider.last_move = manager.clock()
        for _ in range(30):
            decisions = await manager.step()
            # Held by the cooldown, or, when a loaded machine starves the burner for a moment, below the threshold.
            assert not decisions[0].migrate, decisions[0].reason
            await asyncio.sleep(0.05)
            if decider.trust("robot"):
                break
        network, estimate = decider.errors("robot")
        assert decider.trust("robot"), (network, estimate)
        # Errors on the network's (logarithmic) scale: measured ~40 against the declared 4 is off by about 1.6.
        assert estimate is not None and estimate > 1.0
        decider.cooldown = 0.0
        # Its measured cost on the robot sends it to the cloud (estimate and network agree there) ...
        first = (await manager.step())[0]
        assert first.migrate and first.target == "cloud" and record.locations["worker-0"] == "cloud"
        # ... and in the cloud, where the estimate sees only the declared 0.02 cores and would send it back
        # every decision, the network keeps it there.
        for _ in range(5):
            decision = (await manager.step())[0]
            assert decision.location == "cloud" and decision.estimated_reward >= 2.0 + 3.0
            assert decision.decided_by == "network" and not decision.migrate, decision.reason
            assert decision.prediction is not None and decision.prediction < 0
        assert record.locations["worker-0"] == "cloud"
        # The move in the cloud's log says who decided and why.
        moves = await eventually(lambda: moves_logged("learn-1"), what="the move logged")
        move = moves[-1].data
        # Never in the cloud before: nothing scored there, so the estimate decided that move.
        assert move["target"] == "cloud" and move["decided_by"] == "estimate" and move["estimate_error"] is None
