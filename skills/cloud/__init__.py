"""Cloud orchestration (thesis §3.2): run the cloud copies of components and a ROS master per robot.

The database holds what should run (`CloudInstance.desired`, set by the robot's requests);
Celery tasks make the engine match it for one component at a time (`converge`), and the
reconciler (`reconcile`, on the beat schedule) compares everything that runs with it:
it restarts crashed copies with backoff, relaunches missing ones, removes orphans and
turns container stats into metrics. Robots hear of their cloud copies through
`component_status` and `component_information` (with the address and published ports).

Every step on a component runs under that component's orchestration lock, so two workers
never act on one component at once; each request carries a fresh launch token, so a task
that was overtaken by a newer request (start, stop, start in quick succession) does nothing.
The engine's objects carry labels (see `runtime`), so a step repeated after a worker
died finds what the first attempt created instead of creating it twice.

Modules: `orchestration` (requests, the launch spec, running a runtime from sync code),
`converge` (one component), `reporting` (recording outcomes, telling robots and operators),
`masters` (ROS masters), `reconcile` (the reconciler), `stats` (usage as metrics), `runtime`
(the cloud runtime interface) with one module per backend: `swarm`, `docker`, `process`;
`locks` (orchestration locks) and `volumes` (the cloud's replica of Skill volumes).
"""
