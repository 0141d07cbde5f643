"""Offloading decisions on the robot agent (thesis Algorithms 8-9, section 4.2).

Times the per-component decision network of bridgeos_agent.decision and decisionmodel without containers or I/O:
one prediction alone and batched over 2000 components (goal <=0.2 ms a component), one training
step (goal <=1 ms), the memory a component's module holds (goal <=50 KB), the CPU share of one
core for 2000 components deciding at 1 Hz (goal <=10%, measured with time.process_time over a
simulated run with a clock argument, no sleeping), and the time to create one component's
Decider + DecisionModel. The thesis ran at most 250 components at 0.89 +- 0.16 s of init each,
container included.

It then times a whole ``SkillManager.step`` of one Skill with 2000 movable components: costing
each under the Skill's policy, deciding, and writing the decision points to the agent's outbox
(the real controller, with no cloud reachable and the components' locations set rather than
launched), warming up and trained.

    .venv/bin/python benchmarks/decisions.py --quick
    .venv/bin/python benchmarks/decisions.py

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import asyncio
import random
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import log
from _harness import arguments, report

from bridgeos_agent.decision import (
    Decider,
    DecisionInput,
    DecisionModel,
    Features,
    Outcome,
    decide_batch,
    predict_many,
)
from bridgeos_agent.decisionmodel import _load_torch
from bridgeos_agent.skillconfig import ManagerConfig, parse_skill_config

COMPONENTS = 2000


def per_call_ms(fn, repeat: int) -> float:
    """Return the mean wall time of fn() in milliseconds, after a warm-up."""
    for _ in range(min(repeat, 50)):
        fn()
    start = time.perf_counter()
    for _ in range(repeat):
        fn()
    return (time.perf_counter() - start) / repeat * 1000


def noisy_input(rng: random.Random, location: str) -> DecisionInput:
    """Return a plausible, noisy component reading."""
    cost_robot, cost_cloud = rng.uniform(0, 1), rng.uniform(0, 1)
    features = Features(
        cpu_available=rng.uniform(0, 1),
        ram_available=rng.uniform(0, 1),
        bandwidth_available=rng.uniform(0, 1),
        latency=rng.uniform(0.005, 0.2),
        loss=rng.uniform(0, 0.05),
        battery=rng.uniform(0.2, 1),
        location=location,
        cost_robot=cost_robot,
        cost_cloud=cost_cloud,
    )
    here, there = (cost_robot, cost_cloud) if location == "robot" else (cost_cloud, cost_robot)
    # What running here cost, beside the estimate from the other side: every decision brings one to learn.
    outcome = Outcome(location, here, here + rng.gauss(0, 0.1), features)
    return DecisionInput(
        location=location, estimated_reward=here - there + rng.gauss(0, 0.1), features=features, outcome=outcome
    )


def simulate(deciders: list[Decider], seconds: int, rng: random.Random) -> tuple[float, int, int]:
    """Decide for every component once a simulated second; return CPU seconds, decisions and moves."""
    locations = ["robot"] * len(deciders)
    cpu = 0.0
    moves = 0
    for second in range(seconds):
        inputs = [noisy_input(rng, location) for location in locations]
        start = time.process_time()
        decisions = decide_batch(deciders, inputs, now=float(second))
        cpu += time.process_time() - start
        for i, decision in enumerate(decisions):
            if decision.migrate:
                locations[i] = decision.target
                moves += 1
    return cpu, seconds * len(deciders), moves


def manager_steps(seconds: int, data_dir: Path) -> tuple[float, float, int]:
    """Time SkillManager.step over 2000 components: CPU seconds per step warming up and trained, and moves."""
    from bridgeos_agent.controller import AgentSettings, RobotController, SkillRecord
    from bridgeos_agent.manager import SkillManager
    from bridgeos_agent.monitor import SimulatedRobot
    from bridgeos_agent.robotconfig import parse_robot_config
    from bridgeos_agent.runtime.base import Usage

    spec = {"command": ["sleep", "1"]}
    components = {
        f"c{i}": {
            "name": f"C {i}",
            "location": "either",
            "ros": False,
            "resources": {"cpu": 0.01, "ram": 8, "bandwidth": 1},
            "robot": spec,
            "cloud": spec,
        }
        for i in range(COMPONENTS)
    }
    config = parse_skill_config(
        {"skill": "Bench", "skill_id": "bench", "manager": {"policy": "energy"}, "components": components}
    )

    async def run() -> tuple[float, float, int]:
        settings = AgentSettings(
            master="ws://127.0.0.1:9",
            robot="bench-robot",
            token="unused",
            data_dir=data_dir,
            simulate=True,
            simulated=SimulatedRobot(cpu=64, ram=65536, seed=1),
        )
        controller = RobotController(settings, plugins={}, say=lambda line: None)
        robot = {"resources": {"cpu": 64, "ram": 65536, "bandwidth": 1000, "io": 1000}}
        controller.apply_config(parse_robot_config(robot), source="local")
        record = controller.skills["bench"] = SkillRecord(config=config)
        rng = random.Random(2)
        for i, name in enumerate(components):
            record.locations[name] = "robot" if i % 2 else "cloud"
            if i % 2:
                controller.usage[("bench", name)] = Usage(cpu=rng.uniform(0, 0.02), ram=rng.uniform(4, 12))
        controller.monitor.sample(controller.placement.reserved())
        clock = [0.0]
        manager = SkillManager(controller, "bench", clock=lambda: clock[0])
        moves = 0

        async def second() -> float:
            clock[0] += 1.0
            start = time.process_time()
            moves_now = sum(d.migrate for d in await manager.step())
            return time.process_time() - start, moves_now

        warm, trained = [], []
        for _ in range(max(seconds // 2, 3)):
            cpu, moved = await second()
            warm.append(cpu)
            moves += moved
        for decider in manager.deciders.values():
            decider.model.samples_seen = max(decider.model.samples_seen, config.manager.neural_network.trained_after)
        for _ in range(seconds):
            cpu, moved = await second()
            trained.append(cpu)
            moves += moved
        controller.outbox.close()
        # The first step builds 2000 deciders and networks: report the steady state.
        return statistics.median(warm[1:]), statistics.median(trained), moves

    return asyncio.run(run())


def main() -> None:
    parser = arguments(__doc__, "fewer repetitions and simulated seconds (<1 min)")
    args = parser.parse_args()
    repeat = 300 if args.quick else 3000
    seconds = 10 if args.quick else 60
    rng = random.Random(1)

    start = time.perf_counter()
    torch = _load_torch()
    import_s = time.perf_counter() - start
    torch.manual_seed(1)
    config = ManagerConfig()
    log(f"torch imported in {import_s:.2f} s")

    init_ms = [per_call_ms(lambda: Decider("c", config).model, 1) for _ in range(200)]
    component_init_ms = statistics.fmean(init_ms)

    model = DecisionModel(config.neural_network)
    sample = noisy_input(rng, "robot")
    vector = sample.features.vector()
    for _ in range(64):
        model.record(noisy_input(rng, "robot").features.vector(), rng.uniform(-1, 1))
    inference_ms = per_call_ms(lambda: model.predict(vector), repeat)

    models = [DecisionModel(config.neural_network) for _ in range(COMPONENTS)]
    vectors = [noisy_input(rng, "robot").features.vector() for _ in models]
    batch_ms = per_call_ms(lambda: predict_many(models, vectors), max(repeat // 100, 5)) / COMPONENTS

    train_ms = {}
    sizes = {}
    for optimizer in ("adam", "sgd"):
        trainee = DecisionModel(config.neural_network, optimizer=optimizer)
        for _ in range(64):
            trainee.record(noisy_input(rng, "robot").features.vector(), rng.uniform(-1, 1))
        train_ms[optimizer] = per_call_ms(trainee.train_step, repeat)
        sizes[optimizer] = (trainee.size_bytes(), len(trainee.to_bytes()))
    module_kb = sizes["adam"][0] / 1000

    log(f"simulating {COMPONENTS} components at 1 Hz for {seconds} s (untrained, then trained)")
    deciders = [Decider(f"c{i}", config) for i in range(COMPONENTS)]
    warm_cpu, warm_decisions, warm_moves = simulate(deciders, max(seconds // 5, 2), rng)
    for decider in deciders:
        # Skip the 1000 warm-up decisions a network needs before it is trusted: steady state is what runs for hours.
        decider.model.samples_seen = max(decider.model.samples_seen, config.neural_network.trained_after)
    cpu, decisions, moves = simulate(deciders, seconds, rng)
    share = cpu / seconds
    warm_share = warm_cpu / max(seconds // 5, 2)

    log(f"timing SkillManager.step over {COMPONENTS} components for {seconds} simulated seconds")
    with tempfile.TemporaryDirectory(prefix="bridgeos-bench-decisions-") as data_dir:
        step_warm, step_trained, step_moves = manager_steps(seconds, Path(data_dir))

    rows = [
        ("torch import (first network only)", f"{import_s * 1000:.0f} ms", "lazy: never for fixed-location Skills"),
        ("inference, one component alone", f"{inference_ms:.3f} ms", "<= 0.2 ms"),
        (f"inference, batched over {COMPONENTS}", f"{batch_ms:.4f} ms/component", "<= 0.2 ms"),
        ("training step, Adam", f"{train_ms['adam']:.3f} ms", "<= 1 ms"),
        ("training step, SGD", f"{train_ms['sgd']:.3f} ms", "<= 1 ms"),
        ("module, Adam (params+state+buffer)", f"{sizes['adam'][0] / 1000:.1f} KB", "<= 50 KB"),
        ("module, SGD (params+buffer)", f"{sizes['sgd'][0] / 1000:.1f} KB", "<= 50 KB"),
        ("saved model, Adam", f"{sizes['adam'][1] / 1000:.1f} KB", ""),
        (f"CPU, {COMPONENTS} trained at 1 Hz", f"{share * 100:.1f} % of a core", "<= 10 %"),
        (f"CPU, {COMPONENTS} untrained at 1 Hz", f"{warm_share * 100:.1f} % of a core", "(trains every 4th decision)"),
        (f"SkillManager.step, {COMPONENTS} trained", f"{step_trained * 1000:.0f} ms CPU", "<= 100 ms (10 % at 1 Hz)"),
        (f"SkillManager.step, {COMPONENTS} warming up", f"{step_warm * 1000:.0f} ms CPU", "(costing + deciding + log)"),
        ("component init (Decider+model)", f"{component_init_ms:.3f} ms", "thesis 890 +- 160 ms with container"),
        ("components", f"{COMPONENTS}", "thesis max 250"),
    ]
    print(f"{'measure':40} {'value':28} goal / thesis")
    for name, value, goal in rows:
        print(f"{name:40} {value:28} {goal}")
    print(f"moves: {moves} in {decisions} trained decisions, {warm_moves} in {warm_decisions} untrained")
    print(f"SkillManager.step moves over the run: {step_moves}")
    report(
        {
            "inference_ms": round(inference_ms, 4),
            "batch_inference_ms_per_component": round(batch_ms, 5),
            "train_step_ms": round(train_ms["adam"], 4),
            "train_step_sgd_ms": round(train_ms["sgd"], 4),
            "module_kb": round(module_kb, 2),
            "cpu_share_2000_at_1hz": round(share, 4),
            "cpu_share_2000_untrained_at_1hz": round(warm_share, 4),
            "component_init_ms": round(component_init_ms, 4),
            "torch_import_ms": round(import_s * 1000, 1),
            "manager_step_ms_2000": round(step_trained * 1000, 2),
            "manager_step_warmup_ms_2000": round(step_warm * 1000, 2),
            "manager_cpu_share_2000_at_1hz": round(step_trained, 4),
        }
    )


if __name__ == "__main__":
    main()
