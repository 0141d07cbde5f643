"""Attack (b): schemathesis over every operation of the served OpenAPI schema."""

from __future__ import annotations

import time
from typing import Any

from benchmarks.chaos import Outcome
from benchmarks.chaos.hostile.world import NAME, SKILL, World, daphne_errors
from benchmarks.chaos.rig import changed, snapshot


def schemathesis_outcome(world: World, daphne: Any, examples: int) -> Outcome:
    """Fuzz every operation of the served OpenAPI schema: no 5xx, and nothing written by a refused request."""
    import schemathesis
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    from schemathesis import GenerationMode

    schema = schemathesis.openapi.from_url(world.http + "/api/schema/?format=json")
    operations = sorted((method.upper(), path) for path, ops in schema.raw_schema["paths"].items() for method in ops)
    real_ids = {"robot_id": "carol-bot", "skill_id": SKILL, "component_id": "sampler", "template_id": world.template_id}
    calls, server_errors, wrote_when_refused = 0, 0, 0
    failures: list[str] = []
    log_before = len(daphne.log_tail(10**9))
    started = time.monotonic()
    state = [snapshot()]
    for method, path in operations:
        operation = schema[path][method]
        token = world.tokens["ops"] if path.startswith("/api/templates") else world.tokens["carol"]
        cases = st.one_of(
            operation.as_strategy(GenerationMode.POSITIVE), operation.as_strategy(GenerationMode.NEGATIVE)
        )

        @given(case=cases, aim=st.booleans(), method=st.just(method), token=st.just(token))
        @settings(
            max_examples=examples,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=list(HealthCheck),
        )
        def one(case: Any, aim: bool, method: str, token: str) -> None:
            nonlocal calls, server_errors, wrote_when_refused
            if aim:
                for name, value in real_ids.items():
                    if name in (case.path_parameters or {}):
                        case.path_parameters[name] = value
            response = case.call(base_url=world.http, headers={"Authorization": f"Token {token}"}, timeout=15)
            calls += 1
            status = response.status_code
            if status >= 500:
                server_errors += 1
                if len(failures) < 5:
                    failures.append(f"{method} {case.formatted_path}: {status} {response.text[:200]}")
            # Even a GET may write (GET /api/auth/renew renews), so every request is followed by a
            # snapshot, which is also the state before the next request.
            after = snapshot()
            diff = changed(state[0], after)
            state[0] = after
            if 400 <= status < 500 and diff:
                wrote_when_refused += 1
                if len(failures) < 5:
                    failures.append(f"{method} {case.formatted_path} refused with {status} but wrote {diff}")

        one()
    in_log = daphne_errors(daphne.log_tail(10**9)[log_before:])
    errors = server_errors + in_log
    return Outcome(
        scenario=NAME,
        injected=f"schemathesis over {len(operations)} API operations",
        sent=calls,
        passed=errors == 0 and wrote_when_refused == 0 and len(operations) > 0,
        detail=(
            f"{calls} requests in {time.monotonic() - started:.1f} s; {server_errors} 5xx, "
            f"{in_log} errors in daphne's log; "
            f"{wrote_when_refused} refused requests that wrote" + (f"; first: {failures}" if failures else "")
        ),
        figures={"fuzz_server_errors": errors},
    )
