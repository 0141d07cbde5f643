"""How long a Swarm node takes to run a cloud copy of an image it never had (issue 33, ``swarm_node_pull_s``).

A second engine in a network namespace joins this machine's Swarm as a worker; a registry
serves TLS on this machine's end of the node's link. An image of 10 MB layers of random bytes
(``--quick``: about 50 MB, else about 200 MB) is pushed with a token the cloud's signing key mints, and a
cloud copy of it, pinned by digest and constrained to the node, is created through the cloud's
Swarm runtime with the pull token the cloud gives Swarm. The figure is the time from the
service's creation to its task running on the node: the node's pull over the link included.

Needs root (namespaces, a second dockerd), this machine's Swarm and Debian's docker-registry and
skopeo. No database or daphne: the node presents the cloud's token, it never calls the realm.

    sudo .venv/bin/python -m benchmarks._swarmnode --quick
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import subprocess
import sys
import tempfile
import time
import types
from collections.abc import Iterator
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
for path in (HERE, HERE.parent):  # run as a module or imported beside _common by another benchmark
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from _common import log, setup_django  # noqa: E402

MB = 1_000_000
LAYER_MB = 10  # images of several layers, as images.py's robot pulls
OWNER = "alice"


@contextlib.contextmanager
def _owns_registry(host: str) -> Iterator[None]:
    """Make ``host`` the cloud's registry (BRIDGEOS_REGISTRY_HOST) while the block runs."""
    from django.conf import settings

    saved = settings.BRIDGEOS["REGISTRY_HOST"]
    settings.BRIDGEOS["REGISTRY_HOST"] = host
    try:
        yield
    finally:
        settings.BRIDGEOS["REGISTRY_HOST"] = saved


def _push(registry: Any, local: str, repository: str, work: Path) -> str:
    """Push a local image as the owner with a token the cloud mints; return the pushed digest."""
    from django.conf import settings

    from registry import tokens
    from registry.services import signing_key

    conf = settings.BRIDGEOS
    scope = tokens.Scope("repository", repository, ("pull", "push"))
    claims = tokens.token_claims(
        tokens.Principal(OWNER),
        [scope],
        issuer=conf["REGISTRY_ISSUER"],
        audience=conf["REGISTRY_SERVICE"],
        now=datetime.now(UTC),
        ttl_s=600,
    )
    digest_file = work / "digest"
    command = ["skopeo", "copy", "--quiet", "--dest-cert-dir", str(registry.ca_file.parent)]
    command += ["--dest-registry-token", tokens.sign(claims, signing_key()), "--digestfile", str(digest_file)]
    command += [f"docker-daemon:{local}", f"docker://{registry.host}/{repository}:1"]
    done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"skopeo could not push {local}: {done.stderr.strip()[-2000:]}")
    return digest_file.read_text().strip()


def _placed(service: str) -> bool:
    """Tell whether Swarm has given the service's task a node."""
    import docker

    return any(task.get("NodeID") for task in docker.APIClient(version="auto").tasks(filters={"service": service}))


def swarm_node_pull_s(size_mb: int = 50, *, work: Path | None = None) -> dict[str, float]:
    """Time a cloud copy of a new image of ``size_mb`` MB from its service's creation to running on a second node.

    Django must be set up (any database: none is used). Returns ``swarm_node_pull_s`` and the
    image's size in MB as pushed.
    """
    from django.contrib.auth import get_user_model

    from bridgeos_agent.runtime.base import Status
    from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec
    from skills.cloud.runtime import CloudSpec
    from skills.cloud.swarm import SwarmRuntime
    from skills.cloud.swarmauth import registry_auth
    from tests.net import engine
    from tests.net.swarmnode import swarm_node
    from tests.registry.conftest import tls_registry
    from tests.registry.layered import build_layered_image

    reason = engine.available()
    if reason:
        raise SystemExit(f"swarm_node_pull_s needs a second engine: {reason}")
    if work is None:
        with tempfile.TemporaryDirectory(prefix="bench-swarmnode-") as temporary:
            return swarm_node_pull_s(size_mb, work=Path(temporary))
    realm = types.SimpleNamespace(url="http://127.0.0.1:9")  # never called: the node presents the cloud's token
    with swarm_node("bench") as node, tls_registry(realm, work / "registry", node.host_address, notify="off") as reg:
        log(f"node {node.node_id} at {node.address}, registry {reg.host}; building a {size_mb} MB image")
        layers = max(1, size_mb // LAYER_MB)
        local = build_layered_image(work / "image", f"bridgeos-bench/node:{os.getpid():x}", layers, LAYER_MB * MB)
        try:
            digest = _push(reg, local, f"{OWNER}/bench-node", work)
        finally:
            subprocess.run(["docker", "rmi", "-f", local], capture_output=True)
        size = sum(f.stat().st_size for f in (work / "registry" / "storage").rglob("data")) / MB
        image = f"{reg.host}/{OWNER}/bench-node:1@{digest}"
        with _owns_registry(reg.host):
            auth = registry_auth(image, get_user_model()(username=OWNER))
        spec = CloudSpec(
            robot="bench-node",
            skill="bench",
            component="pull",
            location="cloud",
            launch=LaunchSpec(image=image, command=["/bin/sleep", "600"], placement=[f"node.id=={node.node_id}"]),
            resources=ComponentResources(),
            env={},
            registry_auth=auth,
        )

        async def timed() -> float:
            runtime = SwarmRuntime(spec.robot, data_dir=work / "runtime")
            try:
                name = runtime.service_name(spec.skill, spec.component)
                node.availability("active")  # paused otherwise: no other task of this machine lands there
                try:
                    started = time.perf_counter()
                    await runtime.start(spec)
                    for _ in range(3000):  # a minute at most; wait_running says why if it never is
                        if _placed(name):
                            break
                        await asyncio.sleep(0.02)
                finally:
                    node.availability("pause")
                state = await runtime.wait_running(spec.skill, spec.component, 600)
                took = time.perf_counter() - started
                if state.status is not Status.RUNNING:
                    raise RuntimeError(f"the cloud copy did not run on the node: {state.message}")
                return took
            finally:
                try:
                    await runtime.stop(spec.skill, spec.component)
                    for _ in range(100):  # Swarm detaches a removed service from the network a moment later
                        await runtime.remove_network()
                        if runtime.network not in (await runtime.networks()).values():
                            break
                        await asyncio.sleep(0.2)
                finally:
                    await runtime.close()

        took = asyncio.run(timed())
        log(f"{size:.1f} MB pulled and running on the node in {took:.2f} s")
        return {"swarm_node_pull_s": round(took, 3), "swarm_node_image_mb": round(size, 1)}


def measure(quick: bool) -> dict[str, float]:
    """Return swarm_node_pull_s for an image of about 50 MB (``quick``) or 200 MB; benchmarks/images.py calls it."""
    return swarm_node_pull_s(50 if quick else 200)


def main() -> None:
    import argparse
    import json

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="an image of about 50 MB (else about 200 MB)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-swarmnode-") as data:
        setup_django({"BRIDGEOS_DATA_DIR": data, "BRIDGEOS_CLOUD_ID": f"bench-node-{os.getpid():x}"})
        figures = measure(args.quick)
    print(json.dumps(figures), flush=True)


if __name__ == "__main__":
    main()
