"""The rollout executor: one step of every active rollout per tick, a state machine kept in PostgreSQL.

Each tick (Celery beat) takes every running or rolling-back rollout under a row lock that other
workers skip, and moves each of its robots one step: a robot of the running batch installs the
release (the old version stopped, the Skill's config set to the release's, the new version
started) and then verifies it for the soak time; the batch passes when none of its robots is
still on its way. A failed gate past the strategy's abort rule rolls every touched robot back to
the config it ran before, or pauses the rollout. The Skill's stored config is the robot's desired
version: a robot that is offline converges to it when it logs in (its controller asks the cloud
for its Skills' configs), so an offline robot is never waited for and never rolled back by hand.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from datetime import datetime, timedelta
from typing import Any

from django.conf import settings
from django.db import connection, transaction
from django.utils import timezone

from bridgeos_agent.protocol import Event, SkillStatusName
from monitoring.choices import Level
from monitoring.models import Event as LogEvent
from monitoring.services import record_event
from robots.labels import selector_q
from robots.models import Robot
from robots.services import push_to_robot, push_to_robots
from skills import services as skills
from skills.models import Component, Skill

from .health import failed_conditions, health_problem, router_problem
from .models import Rollout, RolloutRobot, UpdateHold
from .snapshot import Seen, read_seen, tally
from .strategy import Strategy, parse_strategy

S = RolloutRobot.Status
# A robot that is done with the rollout, one way or the other.
FINISHED = (S.SUCCEEDED, S.FAILED)
# A robot's status within its batch that no longer holds the batch back.
SETTLED = (S.SUCCEEDED, S.FAILED, S.OFFLINE, S.DEFERRED)
# The statuses counted against max_unavailable: robots changing now.
BUSY = (S.DOWNLOADING, S.INSTALLING, S.VERIFYING)


def install_timeout() -> timedelta:
    """How long a robot may take from the old version's stop to the new one running."""
    return timedelta(seconds=getattr(settings, "BRIDGEOS_ROLLOUT_INSTALL_TIMEOUT_S", 120.0))


def fetch_grace() -> timedelta:
    """How long a robot's first word on fetching the release's images is waited for before it installs anyway."""
    return timedelta(seconds=getattr(settings, "BRIDGEOS_ROLLOUT_FETCH_GRACE_S", 3.0))


def converge_grace() -> timedelta:
    """How long a reconnected robot's own restart of its Skills is waited for before the cloud restarts it."""
    return timedelta(seconds=getattr(settings, "BRIDGEOS_ROLLOUT_CONVERGE_GRACE_S", 3.0))


def tick(now: datetime | None = None) -> int:
    """Move every active rollout one step; return how many were moved."""
    moved = 0
    ids = list(
        Rollout.objects.filter(state__in=[Rollout.State.RUNNING, Rollout.State.ROLLING_BACK]).values_list(
            "id", flat=True
        )
    )
    for rollout_id in ids:
        moved += advance(rollout_id, now)
    return moved


def advance(rollout_id: int, now: datetime | None = None) -> bool:
    """Move one rollout a step, unless another worker is moving it; return whether it was moved."""
    now = now or timezone.now()
    with holding(rollout_id) as held:
        if not held:
            return False
        rollout = Rollout.objects.select_related("release", "organization").filter(id=rollout_id).first()
        if rollout is None:
            return False
        if rollout.state == Rollout.State.RUNNING:
            _run(rollout, now)
        elif rollout.state == Rollout.State.ROLLING_BACK:
            _roll_back(rollout, now)
        return True


def lock_key(rollout_id: int) -> str:
    return f"rollouts.rollout/{rollout_id}"


@contextlib.contextmanager
def holding(rollout_id: int) -> Iterator[bool]:
    """Hold a rollout's executor lock (a session advisory lock) for one step; yield False if another holds it.

    Each robot's step commits on its own, so a robot's reports never wait behind a whole tick; the
    lock keeps two workers (and a pause or abort, which waits for it) from stepping one rollout at once.
    """
    if connection.vendor != "postgresql":
        yield True
        return
    with connection.cursor() as cursor:
        cursor.execute("SELECT pg_try_advisory_lock(hashtextextended(%s, 0))", [lock_key(rollout_id)])
        held = bool(cursor.fetchone()[0])
    try:
        yield held
    finally:
        if held:
            with connection.cursor() as cursor:
                cursor.execute("SELECT pg_advisory_unlock(hashtextextended(%s, 0))", [lock_key(rollout_id)])


# --------------------------------------------------------------------------- running


def _run(rollout: Rollout, now: datetime) -> None:
    strategy = parse_strategy(rollout.strategy)
    if rollout.follow:
        _take_followers(rollout)
    # Only robots still on their way are read (a batch of a thousand that passed is counted, not
    # read), and without the config each ran before: that is read only to roll it back.
    members = list(
        rollout.robots.filter(batch__lte=rollout.batch)
        .exclude(status__in=FINISHED)
        .select_related("robot")
        .defer("previous_config", "robot__config", "robot__ros2")
        .order_by("id")
    )
    counted = tally(rollout)
    room = strategy.at_once(counted.size(rollout.batch)) - counted.count(batch=rollout.batch, statuses=BUSY)
    seen = read_seen(rollout, members)
    stopped: list[tuple[RolloutRobot, Skill]] = []  # old versions stopped: the release starts on them together
    for member in members:
        with transaction.atomic():
            if member.status == S.PENDING and member.batch == rollout.batch:
                if room <= 0 and member.robot.connected:
                    continue
                room -= _begin(rollout, member, now, seen.holds.get(member.robot_id))
            else:
                _step(rollout, strategy, member, now, seen, stopped)
    if stopped:
        _start_release(rollout, stopped, now)
    counted = tally(rollout)
    finished, failed = counted.count(statuses=FINISHED), counted.count(statuses=(S.FAILED,))
    if failed and strategy.should_stop(finished, failed):
        why = rollout.robots.filter(status=S.FAILED).order_by("finished_at").first()
        reason = f"{failed} of {finished} robots failed; first: {why.robot_id}: {why.reason}" if why else ""
        if strategy.on_failure == "pause":
            _set_state(rollout, Rollout.State.PAUSED, f"paused on failure: {reason}")
        else:
            _set_state(rollout, Rollout.State.ROLLING_BACK, f"rolling back: {reason}", level=Level.ERROR)
        return
    unsettled = [status for status in S.values if status not in SETTLED]
    if counted.count(batch=rollout.batch, statuses=unsettled):
        return
    if rollout.batch + 1 < len(rollout.batch_sizes):
        _next_batch(rollout, strategy, now)
    elif rollout.follow:
        # A followed group has no end (Greengrass's continuous deployment): it runs until aborted.
        done = counted.count(statuses=(S.SUCCEEDED,))
        following = f"following {rollout.selector}: {done} of {counted.count()} robots run the release"
        if rollout.reason != following:
            rollout.reason = following
            _store(rollout, "reason")
    elif counted.count(statuses=(S.SUCCEEDED,)) == counted.count():
        _set_state(rollout, Rollout.State.SUCCEEDED, f"all {counted.count()} robots run the release")


def _next_batch(rollout: Rollout, strategy: Strategy, now: datetime) -> None:
    """Start the next batch once the pause after the last one is over (or an operator resumed)."""
    if rollout.next_batch_at is None:
        if strategy.pause_s is None:
            _set_state(rollout, Rollout.State.PAUSED, f"batch {rollout.batch + 1} passed; waiting to be resumed")
            rollout.next_batch_at = now  # the resume starts the next batch at once
            _store(rollout, "next_batch_at")
            return
        rollout.next_batch_at = now + timedelta(seconds=strategy.pause_s)
        _store(rollout, "next_batch_at")
    if now < rollout.next_batch_at:
        return
    rollout.batch += 1
    rollout.batch_started_at, rollout.next_batch_at = now, None
    _store(rollout, "batch", "batch_started_at", "next_batch_at")
    _log(rollout, f"batch {rollout.batch + 1} of {len(rollout.batch_sizes)} started", kind="rollout_batch")


def _take_followers(rollout: Rollout) -> None:
    """Add robots that joined the group since (follow: true) to the batch running now."""
    joined = (
        Robot.objects.filter(organization_id=rollout.organization_id)
        .filter(selector_q(rollout.selector))
        .exclude(rollouts__rollout=rollout)
        .values_list("id", flat=True)
    )
    RolloutRobot.objects.bulk_create(
        [RolloutRobot(rollout=rollout, robot_id=robot_id, batch=rollout.batch) for robot_id in joined],
        ignore_conflicts=True,
    )


def _begin(rollout: Rollout, member: RolloutRobot, now: datetime, hold: UpdateHold | None) -> int:
    """Start a pending robot on the release; return 1 if it now counts against max_unavailable."""
    skill = Skill.objects.select_for_update(no_key=True).filter(
        robot_id=member.robot_id, skill_id=rollout.release.skill_id
    )
    found = skill.first()
    member.previous_config = found.config if found is not None else None
    member.previous_running = found is not None and found.status in (SkillStatusName.RUNNING, SkillStatusName.STARTING)
    member.started_at = now
    if hold is not None and hold.active(now):
        # Held: the robot fetches the release's images now and installs once the hold ends.
        member.status, member.reason = S.DEFERRED, f"held by {hold.holder} until {hold.until:%H:%M:%S}"
        _save(member)
        _push(
            member.robot_id, Event.SKILL_CONFIG, {"skill": rollout.release.skill_id, "config": rollout.release.config}
        )
        return 0
    if not member.robot.connected:
        _converge_later(rollout, member)
        return 0
    if member.previous_running and rollout.release.robot_images:
        # The old version runs on while the robot fetches the new one's images (it keeps a running
        # Skill's config and only pulls): the install that follows does not wait for bytes.
        member.status, member.step, member.bytes_done, member.bytes_total = S.DOWNLOADING, "fetching", 0, 0
        _push(
            member.robot_id, Event.SKILL_CONFIG, {"skill": rollout.release.skill_id, "config": rollout.release.config}
        )
    else:
        _install(rollout, member, found, now)
    _save(member)
    return 1


def _install(rollout: Rollout, member: RolloutRobot, skill: Skill | None, now: datetime) -> None:
    """Put the release on the robot: the old version stopped first, the release started once it has."""
    member.touched = True
    member.status = S.INSTALLING
    _stop_then_start(rollout, member, skill, now)


def _stop_then_start(rollout: Rollout, member: RolloutRobot, skill: Skill | None, now: datetime) -> None:
    """Stop the version the robot runs (the next steps start the release once it stopped), or start at once."""
    beside = rollout.release.config.get("update", {}).get("strategy") == "beside"
    if beside and skill is not None and skill.status == SkillStatusName.RUNNING:
        # The Skill's own choice: the robot starts the release beside the running version, and stops
        # the old copies once the new ones run (or replaces it, when it cannot afford both).
        _start(rollout.release.config, member, now)
    elif skill is not None and skill.status in (SkillStatusName.RUNNING, SkillStatusName.STARTING):
        member.step = "stopping"
        Skill.objects.filter(pk=skill.pk).update(status=SkillStatusName.STOPPING)
        _push(member.robot_id, Event.SKILL_STOP, {"skill": skill.skill_id})
    else:
        _start(rollout.release.config, member, now)


def _start_release(rollout: Rollout, stopped: list[tuple[RolloutRobot, Skill]], now: datetime) -> None:
    """Start the release on the robots whose old version stopped, in one transaction and a few statements.

    The usual release changes the components' commands, not which components there are or where
    they may run: those robots' Skills take the release's config and the starting status in one
    UPDATE, and their start orders go out together. A robot whose components change takes the
    one-by-one path (the components reconciled). One at a time, a batch of 400 held a tick for seconds.
    """
    config = rollout.release.config
    placed = skills.placement(config)
    known: dict[int, dict[str, tuple[str, Any]]] = {}
    rows = Component.objects.filter(skill_id__in=[skill.pk for _, skill in stopped])
    for skill_pk, cid, location, resources in rows.values_list("skill_id", "component_id", "location", "resources"):
        known.setdefault(skill_pk, {})[cid] = (location, resources)
    alike = [(member, skill) for member, skill in stopped if known.get(skill.pk) == placed]
    changed = [member for member, skill in stopped if known.get(skill.pk) != placed]
    for member in changed:
        with transaction.atomic():
            _start(config, member, now)
            _save(member)
    if not alike:
        return
    with transaction.atomic():
        Skill.objects.filter(pk__in=[skill.pk for _, skill in alike]).update(
            config=config, name=config["skill"], status=SkillStatusName.STARTING, updated_at=now
        )
        RolloutRobot.objects.filter(pk__in=[member.pk for member, _ in alike]).update(
            step="starting", verify_from=None, updated_at=now
        )
        orders = []
        for member, skill in alike:
            member.step, member.verify_from = "starting", None
            skill.config, skill.robot = config, member.robot
            orders.append((member.robot_id, Event.SKILL_START, skills.start_order(skill)))
        transaction.on_commit(lambda: push_to_robots(orders), robust=True)


def _converge_later(rollout: Rollout, member: RolloutRobot) -> None:
    """Store the release as the offline robot's desired version: it converges when it logs in."""
    _set_config(member.robot, rollout.release.config, tell=False)  # it is read at the robot's login
    member.touched = True
    member.status, member.step, member.reason = S.OFFLINE, "", "offline: installs when it reconnects"
    _save(member)


def _start(config: dict[str, Any], member: RolloutRobot, now: datetime) -> None:
    """Make ``config`` the robot's Skill and order it started."""
    skill = _set_config(member.robot, config, tell=False)  # the start order carries it
    Skill.objects.filter(pk=skill.pk).update(status=SkillStatusName.STARTING)
    member.step, member.verify_from = "starting", None
    _push(member.robot_id, Event.SKILL_START, skills.start_order(skill))


def _set_config(robot: Robot, config: dict[str, Any], *, tell: bool = True) -> Skill:
    """Store ``config`` (a release's, or one the robot ran) as the robot's Skill config, adding the Skill if need be."""
    skill = (
        Skill.objects.select_for_update(no_key=True)
        .only("id", "robot_id", "skill_id", "status")
        .filter(robot=robot, skill_id=config["skill_id"])
        .first()
    )
    if skill is None:
        return skills.add_skill(robot, config)
    skill.robot = robot  # read already: the start order asks whether it has a ROS master
    skills.set_skill_config(skill, config, stored=True, tell=tell)
    return skill


def _step(
    rollout: Rollout,
    strategy: Strategy,
    member: RolloutRobot,
    now: datetime,
    seen: Seen,
    stopped: list[tuple[RolloutRobot, Skill]],
) -> None:
    """Move one robot of a started batch a step: install, verify, or converge after reconnecting.

    A robot whose old version has stopped is added to ``stopped``: the tick starts the release on
    all of those at once.
    """
    if member.status == S.DEFERRED:
        hold = seen.holds.get(member.robot_id)
        if hold is None or not hold.active(now):
            member.status, member.reason = S.PENDING, ""
            _save(member)
            _begin(rollout, member, now, None)
        return
    if member.status == S.OFFLINE:
        if member.robot.connected:
            # A controller that restarted runs its Skills again with the stored config (the release):
            # wait a moment for that report before restarting the Skill from here.
            member.status, member.step, member.reason, member.started_at = S.INSTALLING, "converging", "", now
            _save(member)
        return
    if member.status not in (S.DOWNLOADING, S.INSTALLING, S.VERIFYING):
        return
    if not member.robot.connected:
        _converge_later(rollout, member)
        return
    skill = seen.skills.get(member.robot_id)
    if member.status == S.DOWNLOADING:
        _download_step(rollout, member, skill, now)
        return
    if skill is None:
        _fail(rollout, member, now, "the Skill was removed during the rollout")
        return
    if member.status == S.INSTALLING:
        _install_step(rollout, strategy, member, skill, now, stopped)
    else:
        _verify_step(rollout, strategy, member, skill, now, seen.crashes.get(member.robot_id, []))


def _download_step(rollout: Rollout, member: RolloutRobot, skill: Skill | None, now: datetime) -> None:
    """Follow the robot's pull of the release's images (bytes of their layers); install once they are there.

    Each image's progress is what the robot last reported on a component of the Skill since the
    fetch began; an image already on the robot is reported at once as 0 of 0 bytes. A robot that
    says nothing within the fetch grace (an agent without an image runtime) installs anyway, as
    does one still pulling at the install timeout: the release's start pulls what is missing.
    """
    assert member.started_at is not None
    wanted = rollout.release.robot_images
    reported: dict[str, tuple[int, int]] = {}
    for component in skill.components.all() if skill is not None else ():
        pull = (component.container.get("robot") or {}).get("pull")
        if pull and pull.get("image") in wanted and component.updated_at >= member.started_at:
            reported[pull["image"]] = (int(pull.get("done", 0)), int(pull.get("total", 0)))
    done, total = sum(d for d, _ in reported.values()), sum(t for _, t in reported.values())
    fetched = len(reported) == len(wanted) and all(d >= t for d, t in reported.values())
    waited = now - member.started_at
    if fetched or (not reported and waited >= fetch_grace()) or waited >= install_timeout():
        member.bytes_done, member.bytes_total = max(done, member.bytes_done), max(total, member.bytes_total)
        member.started_at = now  # the install's own time runs from here
        _install(rollout, member, skill, now)
        _save(member)
    elif (done, total) != (member.bytes_done, member.bytes_total):
        member.bytes_done, member.bytes_total = done, total
        _save(member)


def _install_step(
    rollout: Rollout,
    strategy: Strategy,
    member: RolloutRobot,
    skill: Skill,
    now: datetime,
    stopped: list[tuple[RolloutRobot, Skill]],
) -> None:
    if member.step == "converging":
        assert member.started_at is not None
        reported = skill.updated_at >= member.started_at
        if reported and skill.status == SkillStatusName.RUNNING:
            member.status, member.step, member.verify_from = S.VERIFYING, "", now
        elif reported and skill.status == SkillStatusName.FAILED:
            _fail(rollout, member, now, "the release failed to start after the robot reconnected")
            return
        elif now - member.started_at >= converge_grace():
            # No report: the controller kept running through a link outage (the old version), or never ran it.
            _stop_then_start(rollout, member, skill, now)
        _save(member)
        return
    if member.step == "stopping":
        if skill.status in (SkillStatusName.STOPPED, SkillStatusName.FAILED):
            stopped.append((member, skill))
        elif member.started_at and now - member.started_at > install_timeout():
            _fail(rollout, member, now, f"the old version did not stop within {install_timeout().seconds} s")
        return
    if skill.status == SkillStatusName.RUNNING:
        member.status, member.step, member.verify_from = S.VERIFYING, "", now
        _save(member)
    elif skill.status == SkillStatusName.FAILED and member.step == "starting":
        _fail(rollout, member, now, "the release failed to start")
    elif member.started_at and now - member.started_at > install_timeout():
        _fail(rollout, member, now, f"the release did not run within {install_timeout().seconds} s")


def _verify_step(
    rollout: Rollout, strategy: Strategy, member: RolloutRobot, skill: Skill, now: datetime, crashes: list[LogEvent]
) -> None:
    """Fail a robot whose new version is unhealthy; pass it once healthy for the whole soak time."""
    problem = health_problem(member, skill, crashes)
    if problem:
        _fail(rollout, member, now, problem)
        return
    assert member.verify_from is not None
    if now - member.verify_from < timedelta(seconds=strategy.soak_s):
        return
    failed = failed_conditions(rollout, member, now) or router_problem(rollout, member, now)
    if failed:
        _fail(rollout, member, now, failed)
        return
    member.status, member.reason, member.finished_at = S.SUCCEEDED, "", now
    _save(member)


def _save(member: RolloutRobot) -> None:
    """Store a robot's step; a row gone meanwhile (its robot or organization deleted) is not made again."""
    unread = member.get_deferred_fields()
    fields = {
        f.attname: getattr(member, f.attname)
        for f in RolloutRobot._meta.concrete_fields
        if not f.primary_key and f.attname not in unread
    }
    RolloutRobot.objects.filter(pk=member.pk).update(**{**fields, "updated_at": timezone.now()})


def _fail(rollout: Rollout, member: RolloutRobot, now: datetime, reason: str) -> None:
    member.status, member.reason, member.finished_at = S.FAILED, reason, now
    _save(member)
    _log(rollout, f"robot {member.robot_id} failed its gate: {reason}", robot_id=member.robot_id, level=Level.ERROR)


# --------------------------------------------------------------------------- rolling back


def _roll_back(rollout: Rollout, now: datetime) -> None:
    """Put every touched robot back on the version it ran before; done when all are back."""
    # A robot still fetching was never changed: it keeps its version and is no longer waited for.
    rollout.robots.filter(status=S.DOWNLOADING, touched=False).update(
        status=S.PENDING, step="", reason="not installed: the rollout stopped", updated_at=now
    )
    members = list(rollout.robots.filter(touched=True).select_related("robot"))
    for member in members:
        if member.status == S.ROLLED_BACK:
            continue
        with transaction.atomic():
            if member.status != S.ROLLING_BACK:
                _begin_rollback(rollout, member, now)
            else:
                _rollback_step(rollout, member, now)
    if all(member.status == S.ROLLED_BACK for member in members):
        if rollout.reason.startswith("aborted"):
            _set_state(
                rollout, Rollout.State.ABORTED, f"{rollout.reason}; {len(members)} robots back on the old version"
            )
        else:
            _set_state(rollout, Rollout.State.ROLLED_BACK, rollout.reason.replace("rolling back", "rolled back", 1))


def _begin_rollback(rollout: Rollout, member: RolloutRobot, now: datetime) -> None:
    member.status, member.started_at = S.ROLLING_BACK, now
    skill = (
        Skill.objects.select_for_update(no_key=True)
        .filter(robot_id=member.robot_id, skill_id=rollout.release.skill_id)
        .first()
    )
    if not member.robot.connected:
        _restore(member, skill)
        member.status, member.step, member.finished_at = S.ROLLED_BACK, "", now
        member.reason = "offline: stays on the old version when it reconnects"
    elif skill is not None and skill.status in (SkillStatusName.RUNNING, SkillStatusName.STARTING):
        member.step = "stopping"
        Skill.objects.filter(pk=skill.pk).update(status=SkillStatusName.STOPPING)
        _push(member.robot_id, Event.SKILL_STOP, {"skill": skill.skill_id})
    else:
        _restart_previous(member, skill, now)
    _save(member)


def _rollback_step(rollout: Rollout, member: RolloutRobot, now: datetime) -> None:
    skill = Skill.objects.filter(robot_id=member.robot_id, skill_id=rollout.release.skill_id).first()
    if not member.robot.connected:
        _restore(member, skill)
        member.status, member.step, member.finished_at = S.ROLLED_BACK, "", now
    elif member.step == "stopping":
        if skill is None or skill.status in (SkillStatusName.STOPPED, SkillStatusName.FAILED):
            _restart_previous(member, skill, now)
    elif skill is None or not member.previous_running or skill.status == SkillStatusName.RUNNING:
        member.status, member.step, member.finished_at = S.ROLLED_BACK, "", now
    elif member.started_at and now - member.started_at > install_timeout():
        member.status, member.step, member.finished_at = S.ROLLED_BACK, "", now
        member.reason = f"the old version did not run again within {install_timeout().seconds} s"
    _save(member)


def _restore(member: RolloutRobot, skill: Skill | None) -> Skill | None:
    """Put the robot's stored Skill config back as it was (removing a Skill the rollout added)."""
    if member.previous_config is None:
        if skill is not None:
            skill.delete()
        return None
    return _set_config(member.robot, member.previous_config)


def _restart_previous(member: RolloutRobot, skill: Skill | None, now: datetime) -> None:
    restored = _restore(member, skill)
    if restored is not None and member.previous_running:
        Skill.objects.filter(pk=restored.pk).update(status=SkillStatusName.STARTING)
        _push(member.robot_id, Event.SKILL_START, skills.start_order(restored))
        member.step = "starting"
    else:
        member.status, member.step, member.finished_at = S.ROLLED_BACK, "", now


# --------------------------------------------------------------------------- state


def _push(robot_id: str, event: Event, data: dict[str, Any]) -> None:
    """Send an order to the robot once the step that decided it is stored (after the Skill's new config)."""
    transaction.on_commit(lambda: push_to_robot(robot_id, event, data), robust=True)


def _set_state(rollout: Rollout, state: object, reason: str, *, level: str = Level.INFO) -> None:
    # A TextChoices member: its str() is its value.
    rollout.state, rollout.reason = str(state), reason
    fields = ["state", "reason"]
    if state in (Rollout.State.SUCCEEDED, Rollout.State.ROLLED_BACK, Rollout.State.ABORTED):
        rollout.finished_at = timezone.now()
        fields.append("finished_at")
    _store(rollout, *fields)
    _log(rollout, f"rollout {rollout.id} {rollout.state.replace('_', ' ')}: {reason}", level=level)


def _store(rollout: Rollout, *fields: str) -> None:
    """Store fields of a rollout; one deleted meanwhile (with its organization) stays deleted."""
    values = {field: getattr(rollout, field) for field in fields}
    Rollout.objects.filter(pk=rollout.pk).update(**values, updated_at=timezone.now())


def _log(
    rollout: Rollout, message: str, *, robot_id: str | None = None, level: str = Level.INFO, kind: str = ""
) -> None:
    record_event(
        message,
        robot_id=robot_id,
        level=level,
        kind=kind or "rollout",
        skill=rollout.release.skill_id,
        data={"rollout": rollout.id, "release": rollout.release.number, "state": rollout.state},
        organization_id=rollout.organization_id,
    )
