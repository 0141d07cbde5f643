"""The Skill Manager (thesis §3.4.1): decides, while a Skill runs, where each movable component lives.

One manager per active Skill, run by the Skill's supervisor. Every ``decision_interval`` it
costs each movable component at both locations under the Skill's policy (equations
4.1-4.6, ``policies``) from the runtime's measurements, the robot's state and the Skill
Router's traffic figures, asks each component's decision module (Algorithms 8-9,
``decision``) and moves the components whose decision says so through the controller
(Algorithm 1 for a move to the robot), without holding up the next decisions while a cloud copy
starts. A component's CPU is the mean of its latest measurements, so the runtime's coarse
per-sample figures do not become the reward's noise. Each move, done or failed, is logged in the cloud as
an ``offloading_decision`` event; each decision to stay is an ``offloading.decision`` metric
point. Decision models are kept on disk between launches.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import json
import logging
import time
from collections import deque
from typing import TYPE_CHECKING, Any, cast

from bridgeos_agent.componentsapi import ComponentsAPI, MetricStore
from bridgeos_agent.decision import (
    Decider,
    Decision,
    DecisionInput,
    DecisionModel,
    Features,
    Side,
    decide_and_learn,
    train_due,
)
from bridgeos_agent.decisioninputs import Usage, decision_event, free_share, means, observed_outcome
from bridgeos_agent.decisionmodel import _load_torch
from bridgeos_agent.heuristics import Resources
from bridgeos_agent.monitor import Reporter
from bridgeos_agent.policies import Metrics, PolicyCosts, PolicyEstimator
from bridgeos_agent.protocol import Event
from bridgeos_agent.robotconfig import RobotConfig
from bridgeos_agent.traffic import ComponentTraffic

if TYPE_CHECKING:
    from bridgeos_agent.hosts import SkillHost
    from bridgeos_agent.state import SkillRecord
    from bridgeos_agent.supervisor import SkillSupervisor

__all__ = ["SkillManager", "skill_manager_plugin"]

logger = logging.getLogger(__name__)

DECISION_METRIC = "offloading.decision"
# A decision to stay is sent when its reward changed, else at least this often (seconds): 2000
# components deciding at 1 Hz would otherwise write 2000 rows a second to the cloud.
STAY_POINT_EVERY = 30.0
# A component's CPU is averaged over its latest measurements at its location: one sample of a process's
# CPU time over a quarter second is counted in 10 ms clock ticks (0.04 of a core), noise that would
# otherwise reach the reward through the cost functions (and be amplified by a busy robot's 1/free CPU).
USAGE_WINDOW = 8


class SkillManager:
    """Decide and act on the locations of one Skill's movable components."""

    def __init__(self, host: SkillHost, skill_id: str, *, clock: Any = time.monotonic) -> None:
        self.host = host
        self.skill_id = skill_id
        self.clock = clock
        self.deciders: dict[str, Decider] = {}
        self.recommendations: dict[str, str] = {}  # component -> location a component or operator asked for
        self.last: dict[str, Decision] = {}
        # ROS message loss rate per component and location; a location it never ran at keeps its last value.
        self.loss: dict[str, dict[str, float]] = {}
        self.model_dir = host.data_dir / "models" / skill_id
        self.store = MetricStore()
        self.api: ComponentsAPI | None = None
        self._estimator: tuple[tuple[Any, ...], PolicyEstimator] | None = None
        self._cost_failures: dict[str, str] = {}  # component -> the cost function error last logged
        self._stays = Reporter(max_interval=STAY_POINT_EVERY, relative=0.05, absolute=0.01)
        # component -> (location, the measurements averaged there, the last one seen, whether one was); see _measured.
        self._usage: dict[str, tuple[str, deque[tuple[float, float]], Any, bool]] = {}
        # component -> its move in flight when run() does not wait for moves (see step).
        self._moving: dict[str, asyncio.Task[None]] = {}
        self._training: asyncio.Future[None] | None = None  # the last step's training, in a thread

    # ------------------------------------------------------------------ the Components API's view

    def components(self) -> list[dict[str, Any]]:
        """Describe every component of the Skill (Components API)."""
        return [self.component(name) for name in self.record.config.components]

    def component(self, component_id: str) -> dict[str, Any]:
        """Describe one component; KeyError if the Skill has none of that id."""
        record = self.record
        config = record.config.components[component_id]
        status = record.statuses.get(component_id)
        return {
            "id": component_id,
            "name": config.name,
            "location": config.location,
            "active_location": record.locations.get(component_id),
            "status": str(status) if status else "stopped",
        }

    def locations(self) -> dict[str, str | None]:
        """Map each component to where it runs now."""
        record = self.record
        return {name: record.locations.get(name) for name in record.config.components}

    def latest_metrics(self, names: Any, component: str | None) -> list[dict[str, Any]]:
        """Return the latest published or measured values."""
        return self.store.latest(names, component)

    def publish(self, points: list[dict[str, Any]]) -> int:
        """Keep metrics a component published and share them with the cloud."""
        applied = self.store.publish(points)
        shared = [{**point, "skill": self.skill_id} for point in points]
        self.host.spawn(self.host.emit(Event.METRICS, {"metrics": shared}))
        return applied

    async def start_api(self) -> str:
        """Serve the Components API, on the same port as last launch when it is free."""
        port_file = self.model_dir / "api.port"
        saved = int(port_file.read_text()) if port_file.exists() else 0
        for port in dict.fromkeys((saved, 0)):
            self.api = api = ComponentsAPI(self, port=port)
            try:
                url = await api.start()
                break
            except OSError:
                continue
        self.model_dir.mkdir(parents=True, exist_ok=True)
        port_file.write_text(str(api.port))
        return url

    @property
    def record(self) -> SkillRecord:
        """Return the robot's record of this Skill."""
        return self.host.skills[self.skill_id]

    def recommend(self, component: str, location: str) -> None:
        """Take a manual offloading recommendation; it wins at the next decision."""
        config = self.record.config.components.get(component)
        if config is None:
            raise ValueError(f"skill {self.skill_id!r} has no component {component!r}")
        if config.location != "either":
            raise ValueError(f"component {component!r} may only run on the {config.location}")
        if location not in ("robot", "cloud"):
            raise ValueError(f"location must be 'robot' or 'cloud', not {location!r}")
        self.recommendations[component] = location

    def hold(self, component: str, seconds: float, reason: str) -> None:
        """Hold the robot's updates on a component's behalf; the cloud keeps the hold (0 seconds releases it)."""
        data = {"skill": self.skill_id, "component": component, "seconds": seconds, "reason": reason}
        self.host.spawn(self.host.emit(Event.UPDATE_HOLD, data))

    def movable(self) -> list[str]:
        """Return the components the manager may move: movable and running somewhere."""
        record = self.record
        return [
            name
            for name, config in record.config.components.items()
            if config.location == "either" and record.locations.get(name) in ("robot", "cloud")
        ]

    def _decider(self, name: str) -> Decider:
        decider = self.deciders.get(name)
        if decider is None:
            manager_config = self.record.config.manager
            model = None
            path = self.model_dir / f"{name}.pt"
            if path.exists():
                try:
                    model = DecisionModel.load(path, manager_config.neural_network)
                except (ValueError, OSError, KeyError) as exc:
                    logger.warning("skill %s: ignoring the saved model of %s: %s", self.skill_id, name, exc)
            decider = self.deciders[name] = Decider(name, manager_config, model=model)
        return decider

    def _estimator_for(self, robot_config: RobotConfig, capacity: Resources) -> PolicyEstimator:
        """Return the policy estimator, compiled again only when a config changed."""
        manager_config = self.record.config.manager
        key = (robot_config, manager_config, capacity)
        if self._estimator is None or self._estimator[0] != key:
            self._estimator = (key, PolicyEstimator.of(robot_config, manager_config, capacity))
        return self._estimator[1]

    def _traffic(self, name: str) -> ComponentTraffic | None:
        """Ask the Skill's router what it measured of a component's traffic (None: no router or no routes)."""
        router = self.record.context("router")
        if router is None:
            return None
        try:
            traffic = router.traffic(name)
        except (KeyError, LookupError, ValueError):
            return None  # the router routes nothing of this component
        return traffic if isinstance(traffic, ComponentTraffic) else None

    def _measured(self, name: str, location: str) -> Any:
        """Return a component's CPU and RAM averaged over its latest measurements where it runs (None: none yet)."""
        if location != "robot":
            # The robot's runtime measures only the robot's copies: a figure left over from the copy that
            # just moved away must not be taken for the cloud's.
            self._usage.pop(name, None)
            return None
        latest = self.host.usage.get((self.skill_id, name))
        kept = self._usage.get(name)
        if kept is None or kept[0] != location:
            # A move starts another copy: what the old one used says nothing of the new one.
            kept = self._usage[name] = (location, deque(maxlen=USAGE_WINDOW), None, False)
        where, window, last, started = kept
        if latest is not None and latest is not last:  # a new figure (the runtime's are new objects each time)
            if started:
                window.append((float(latest.cpu), float(latest.ram)))
            # The first figure seen of a copy is left out: it may span the copy's start-up (an interpreter
            # loading, tenths of a core over a quarter second) and would send the component away as it arrives.
            self._usage[name] = (where, window, latest, True)
        if not window:
            return None
        cpu, ram = means(window)
        return Usage(cpu=cpu, ram=ram)

    def _inputs(self, names: list[str]) -> tuple[list[str], list[DecisionInput], dict[str, Any]]:
        """Build each component's decision input; return the components costed, their inputs and costs."""
        host, record = self.host, self.record
        robot_config = host.config or RobotConfig()
        capacity = Resources.of(robot_config.resources)
        estimator = self._estimator_for(robot_config, capacity)
        policy = record.config.manager.policy
        sample = host.monitor.latest
        values = sample.values if sample else {}
        free = sample.free if sample else {}
        # Latency: a component on the robot answers locally; one in the cloud is a link round
        # trip away, measured by the WebSocket keepalive.
        rtt = host.link_latency()
        robot_state = Metrics(
            latency_robot=0.0,
            latency_cloud=rtt,
            # Unknown (no sample yet) counts as the robot's whole capacity, as for the features.
            cpu_free=float(free.get("cpu", capacity.cpu)),
            ram_free=float(free.get("ram", capacity.ram)),
            bandwidth_available=float(values.get("bandwidth_available", capacity.bandwidth)),
            battery=float(values.get("battery", 100.0)),
        )
        costed, inputs, costs = [], [], {}
        for name in names:
            config = record.config.components[name]
            where = record.locations[name]
            if where is None:
                continue  # movable() returned only running components; nothing runs in between
            location: Side = "cloud" if where == "cloud" else "robot"
            needs = Resources.of(config.resources)
            measured = self._measured(name, location)
            # The runtime measures CPU and RAM only: bandwidth, GPU and I/O stay as declared.
            usage = dataclasses.replace(needs, cpu=measured.cpu, ram=measured.ram) if measured else needs
            loss = self.loss.setdefault(name, {"robot": 0.0, "cloud": 0.0})
            metrics = robot_state
            if location == "cloud":
                # What the robot would have free with this component on it: costing the robot with
                # its own share still free would call it back, only to send it away again (a flap).
                metrics = dataclasses.replace(
                    robot_state,
                    cpu_free=max(0.0, robot_state.cpu_free - needs.cpu),
                    ram_free=max(0.0, robot_state.ram_free - needs.ram),
                )
            traffic = self._traffic(name)
            if traffic is not None:
                if traffic.messages:
                    loss[location] = traffic.loss_rate
                gb_local, gb_cloud = traffic.gb_per_hour()
                metrics = dataclasses.replace(metrics, gb_local=gb_local, gb_cloud=gb_cloud)
            if config.ros:
                metrics = dataclasses.replace(metrics, loss_rate_robot=loss["robot"], loss_rate_cloud=loss["cloud"])
            try:
                estimate = estimator.estimate(policy, location, usage, metrics, bool(config.ros_version))
            except ValueError as exc:
                # A user cost function that fails here (say, a division by a zero free CPU) skips
                # this component's decision; it is logged once per distinct error, not every interval.
                if self._cost_failures.get(name) != str(exc):
                    self._cost_failures[name] = str(exc)
                    logger.warning("skill %s: cannot cost %s: %s", self.skill_id, name, exc)
                continue
            self._cost_failures.pop(name, None)
            costs[name] = estimate
            # A move to the robot needs room there; unknown (no sample yet) counts as room.
            resources_ok = location == "robot" or not free or needs.fits(Resources(**free))
            features = Features(
                cpu_available=free_share(free.get("cpu"), capacity.cpu),
                ram_available=free_share(free.get("ram"), capacity.ram),
                bandwidth_available=free_share(values.get("bandwidth_available"), capacity.bandwidth),
                battery=(values["battery"] / 100) if "battery" in values else 1.0,
                latency=rtt,
                loss=loss[location],
                location=location,
                cost_robot=estimate.cost_robot,
                cost_cloud=estimate.cost_cloud,
            )
            outcome = observed_outcome(
                estimator,
                policy,
                bool(config.ros_version),
                location,
                estimate,
                needs,
                measured,
                metrics,
                features,
                capacity,
            )
            moving = name in self._moving
            wanted = None if moving else self.recommendations.pop(name, None)  # kept for its first decision
            costed.append(name)
            inputs.append(
                DecisionInput(
                    location=location,
                    estimated_reward=estimate.reward,
                    features=features,
                    required_location=config.location,
                    mode=robot_config.offloading,
                    resources_ok=resources_ok,
                    recommendation=None if wanted is None else wanted != location,
                    outcome=outcome,
                    moving=moving,
                )
            )
        return costed, inputs, costs

    async def step(self, *, wait: bool = True) -> list[Decision]:
        """Decide once for every movable component and carry out the moves.

        wait=False starts the moves and returns: the next decisions do not wait for a slow cloud start,
        and a component whose move is still in flight is not decided for until it lands (its outcomes
        where it still runs are learnt meanwhile).
        """
        supervisor = self.record.supervisor
        if supervisor is not None and supervisor.context.get("cloud") == "lost":
            return []  # the controller has taken over the cloud's role: nothing moves meanwhile
        names, inputs, costs = self._inputs(self.movable())
        if not names:
            return []
        decisions, due = decide_and_learn([self._decider(name) for name in names], inputs, self.clock())
        # Trained in a thread (torch lets go of the GIL) while the moves start: a training step takes 50-150 ms
        # on a busy robot, which on the event loop held up these moves and everything else the agent serves.
        training = self._training = asyncio.ensure_future(asyncio.to_thread(train_due, due)) if due else None
        try:
            return await self._carry_out(decisions, costs, wait=wait)
        finally:
            if training is not None:
                await asyncio.shield(training)  # learnt before the next decision; a cancel waits for it too

    async def _carry_out(
        self, decisions: list[Decision], costs: dict[str, PolicyCosts], *, wait: bool
    ) -> list[Decision]:
        """Record the decisions, report the changed stays and start the moves (awaited with ``wait``)."""
        if not decisions:
            return []
        now = time.time()
        for decision in decisions:
            self.last[decision.component] = decision
        self.host.metrics.decided(self.skill_id, decisions)
        # A move is logged as an offloading_decision event once carried out; a stay, as a point when it changed.
        readings = [
            (DECISION_METRIC, float(d.estimated_reward), self.skill_id, d.component) for d in decisions if not d.migrate
        ]
        changed = {point["component"] for point in self._stays.select(now, readings)}
        points = []
        for decision in decisions:
            if decision.component not in changed:
                continue
            estimate = costs[decision.component]
            points.append(
                {
                    "name": DECISION_METRIC,
                    "value": round(float(decision.estimated_reward), 6),
                    "ts": now,
                    "skill": self.skill_id,
                    "component": decision.component,
                    "labels": {
                        "decision": "stay",
                        "location": decision.location,
                        "target": decision.target,
                        "cost_robot": f"{estimate.cost_robot:.6g}",
                        "cost_cloud": f"{estimate.cost_cloud:.6g}",
                        "policy": estimate.policy,
                        "decided_by": decision.decided_by,
                        "reason": decision.reason[:256],
                    },
                }
            )
        if points:
            await self.host.emit(Event.METRICS, {"metrics": points})
        # Moves decided together go together: one component's cloud start does not hold up another's.
        moves = {d.component: self._move(d, costs[d.component], now) for d in decisions if d.migrate}
        if wait:
            if moves:
                await asyncio.gather(*moves.values())
            return decisions
        for name, move in moves.items():
            task = self._moving[name] = asyncio.create_task(move, name=f"move {self.skill_id}/{name}")
            task.add_done_callback(functools.partial(self._landed, name))
        return decisions

    def _landed(self, name: str, _task: asyncio.Task[None]) -> None:
        """Forget a move once done (landed, failed or cancelled): the component is decided for again."""
        self._moving.pop(name, None)

    async def _move(self, decision: Decision, estimate: PolicyCosts, decided_at: float) -> None:
        """Move a component as decided and log the move, done or failed, in the cloud."""
        record = self.record
        started = time.perf_counter()
        error = None
        try:
            await self.host.migrate_component(record, decision.component, decision.target)
            self.save_placement()
            logger.info(
                "skill %s: %s moved to the %s in %.2f s (decided by the %s)",
                self.skill_id,
                decision.component,
                decision.target,
                time.perf_counter() - started,
                decision.decided_by,
            )
        except Exception as exc:  # e.g. no room on the robot: the next decision after the cooldown tries again
            error = str(exc) or type(exc).__name__
            logger.warning(
                "skill %s: moving %s to the %s failed: %s", self.skill_id, decision.component, decision.target, error
            )
        await self.host.emit(
            Event.OFFLOADING_DECISION,
            decision_event(decision, estimate, decided_at, time.perf_counter() - started, error, self.skill_id),
        )

    def save_placement(self) -> None:
        """Remember where the movable components run, for the Skill's next first placement."""
        record = self.record
        placement = {
            name: record.locations.get(name)
            for name, config in record.config.components.items()
            if config.location == "either" and record.locations.get(name) in ("robot", "cloud")
        }
        if placement:
            self.model_dir.mkdir(parents=True, exist_ok=True)
            tmp = self.model_dir / "placement.json.tmp"
            tmp.write_text(json.dumps(placement))
            tmp.replace(self.model_dir / "placement.json")

    def save_models(self) -> None:
        """Keep the decision models that have learnt something for the next launch."""
        for name, decider in self.deciders.items():
            model = decider._model
            if model is not None and model.samples_seen:
                self.model_dir.mkdir(parents=True, exist_ok=True)
                model.save(self.model_dir / f"{name}.pt")

    async def run(self, supervisor: SkillSupervisor) -> None:
        """Serve the Components API and decide every ``decision_interval`` seconds until the Skill stops."""
        url = await self.start_api()
        cast("dict[str, str]", supervisor.context.setdefault("env", {}))["BRIDGEOS_MANAGER_URL"] = url
        supervisor.mark_ready("manager")
        try:
            if any(c.location == "either" for c in self.record.config.components.values()):
                # The first network built imports torch: seconds on a robot (8 s on a loaded 2-core
                # machine), which in the first decision would freeze the agent's event loop, every
                # Skill's included. Imported in a thread, only the decisions wait for it.
                await asyncio.to_thread(_load_torch)
            while True:
                await self._next_decision()
                self._share_usage()
                # A cloud start takes up to a second: the other components' decisions do not wait for it.
                await self.step(wait=False)
        finally:
            # Stopped mid-move, as a step awaiting its moves was: each move rolls back or lands.
            moving = list(self._moving.values())
            for task in moving:
                task.cancel()
            if moving:
                await asyncio.gather(*moving, return_exceptions=True)
            if self._training is not None:
                await asyncio.gather(self._training, return_exceptions=True)  # not saved mid-step
            self.save_placement()
            self.save_models()
            if self.api is not None:
                await self.api.stop()

    async def _next_decision(self) -> None:
        """Wait until the next decision is due: on the robot's first reading once the interval is over.

        Deciding on a reading the last decision saw already would only add up to a sample interval to
        every adaptation (and count one reading as two confirmations); a robot sampled less often than
        the manager decides is decided for on the interval alone.
        """
        interval = self.record.config.manager.decision_interval
        sampling = self.host.settings.sample_interval
        if sampling > interval:
            await asyncio.sleep(interval)
            return
        await asyncio.sleep(interval - sampling)
        await self.host.monitor.next_sample(2 * sampling)

    def _share_usage(self) -> None:
        """Offer components the robot's metrics and the runtime's measurements of each of them."""
        now = time.time()
        points = [
            {"name": name, "value": value, "ts": now, "component": component}
            for (skill, component), usage in self.host.usage.items()
            if skill == self.skill_id
            for name, value in (("cpu", round(100 * usage.cpu, 2)), ("ram", round(usage.ram, 1)))
        ]
        sample = self.host.monitor.latest
        if sample is not None:
            points.extend({"name": name, "value": float(value), "ts": now} for name, value in sample.values.items())
        if points:
            self.store.publish(points)


async def skill_manager_plugin(supervisor: SkillSupervisor) -> None:
    """Run a Skill's manager as a supervisor plug-in (its host, the controller, is in the supervisor's context)."""
    host = cast("SkillHost", supervisor.context["controller"])
    manager = cast("SkillManager | None", supervisor.context.get("manager"))
    if manager is None:  # a restart after a crash keeps the manager's state
        manager = supervisor.context["manager"] = SkillManager(host, supervisor.skill)
    await manager.run(supervisor)
