"""The stack's Docker API proxy in front of the real dockerd: what orchestration needs passes, the rest is 403."""

from __future__ import annotations

import subprocess
import sys
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

import docker
from bridgeos_cloud.dockerproxy import Policy, Refused, strip_version
from tests.conftest import free_port, wait_for_port

pytestmark = [pytest.mark.docker]

IMAGE = "bridgeos/base:bookworm"


def docker_cli(*args: str) -> str:
    """Run the docker CLI on the raw socket (the test's own door, not the proxy's)."""
    return subprocess.run(["docker", *args], capture_output=True, text=True, timeout=60, check=True).stdout


@pytest.fixture(scope="module")
def volumes_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("volumes")


@pytest.fixture(scope="module")
def proxy(volumes_dir: Path) -> Iterator[str]:
    """Run the proxy on a free port in front of this machine's engine; yield its base URL."""
    try:
        docker_cli("info", "--format", "{{.ID}}")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("needs a running dockerd: scripts/services.sh docker")
    port = free_port()
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "bridgeos_cloud.dockerproxy",
            "--listen",
            f"127.0.0.1:{port}",
            "--volumes-dir",
            str(volumes_dir),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        wait_for_port(port, process)
        yield f"http://127.0.0.1:{port}"
    finally:
        process.terminate()
        process.wait(timeout=10)


def refusal(answer: httpx.Response) -> str:
    """Return the message of a 403 answer in Docker's error shape, failing if it is anything else."""
    assert answer.status_code == 403, (
        f"{answer.request.method} {answer.request.url}: {answer.status_code} {answer.text}"
    )
    assert answer.headers["content-type"] == "application/json"
    return answer.json()["message"]


def test_the_orchestrations_reads_pass_with_or_without_a_version_prefix(proxy: str) -> None:
    client = docker.APIClient(base_url=proxy.replace("http", "tcp"), version="auto")
    try:
        assert client.version()["ApiVersion"]
        assert client.info()["ID"] == docker_cli("info", "--format", "{{.ID}}").strip()
        assert client.images(name=IMAGE), "the image list passes"
        assert client.inspect_image(IMAGE)["Id"]
    finally:
        client.close()
    for path in ("/_ping", "/v1.41/_ping", "/v1.40/version", "/v1.41/containers/json?all=1", "/v1.41/networks"):
        answer = httpx.get(proxy + path, timeout=10)
        assert answer.status_code == 200, f"{path}: {answer.status_code} {answer.text}"


def test_container_logs_stream_through_the_proxy(proxy: str) -> None:
    name = f"proxy-logs-{uuid.uuid4().hex[:8]}"
    docker_cli("run", "-d", "--name", name, IMAGE, "sh", "-c", "echo first-line; sleep 60; echo second-line")
    try:
        started = time.monotonic()
        url = f"{proxy}/v1.41/containers/{name}/logs?follow=1&stdout=1&stderr=1"
        with httpx.stream("GET", url, timeout=20) as answer:
            assert answer.status_code == 200
            received = b""
            for chunk in answer.iter_bytes():
                received += chunk
                if b"first-line" in received:
                    break
        # The container runs on for a minute: the first line came while the answer was still open.
        assert b"first-line" in received and b"second-line" not in received
        assert time.monotonic() - started < 15
    finally:
        subprocess.run(["docker", "rm", "-f", name], capture_output=True, timeout=60, check=False)


def test_a_privileged_container_create_is_refused_and_nothing_is_created(proxy: str) -> None:
    name = f"proxy-privileged-{uuid.uuid4().hex[:8]}"
    body = {"Image": IMAGE, "Cmd": ["true"], "HostConfig": {"Privileged": True}}
    message = refusal(httpx.post(f"{proxy}/v1.47/containers/create?name={name}", json=body, timeout=10))
    assert "POST /containers/create with HostConfig.Privileged" in message
    assert docker_cli("ps", "-aq", "--filter", f"name={name}").strip() == ""
    # An ordinary container is refused too: the orchestration makes services, never containers.
    message = refusal(httpx.post(f"{proxy}/containers/create?name={name}", json={"Image": IMAGE}, timeout=10))
    assert "POST /containers/create is refused" in message
    assert docker_cli("ps", "-aq", "--filter", f"name={name}").strip() == ""


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("POST", "/v1.41/containers/abc/exec"),
        ("POST", "/containers/abc/kill"),
        ("DELETE", "/v1.47/containers/abc"),
        ("POST", "/exec/abc/start"),
        ("POST", "/volumes/create"),
        ("DELETE", "/volumes/data"),
        ("GET", "/plugins"),
        ("POST", "/swarm/leave"),
        ("POST", "/v1.41/swarm/update"),
        ("GET", "/secrets"),
        ("POST", "/build"),
        ("POST", "/nodes/abc/update"),
        ("DELETE", "/images/bridgeos/base:bookworm"),
        ("POST", "/images/bridgeos/base:bookworm/push"),
    ],
)
def test_calls_outside_the_orchestration_are_refused(proxy: str, method: str, path: str) -> None:
    message = refusal(httpx.request(method, proxy + path, json={}, timeout=10))
    assert f"{method} {strip_version(path)} is refused" in message


def test_an_image_import_and_a_connection_upgrade_are_refused(proxy: str) -> None:
    assert "import" in refusal(httpx.post(f"{proxy}/images/create?fromSrc=-", timeout=10))
    answer = httpx.get(f"{proxy}/_ping", headers={"Upgrade": "tcp", "Connection": "Upgrade"}, timeout=10)
    assert "upgrades" in refusal(answer)


def service_body(name: str, **container: object) -> dict[str, object]:
    return {"Name": name, "TaskTemplate": {"ContainerSpec": {"Image": IMAGE, "Args": ["sleep", "60"], **container}}}


@pytest.mark.parametrize(
    ("container", "named"),
    [
        ({"Privileges": {"SELinuxContext": None, "Seccomp": {"Mode": "unconfined"}}}, "Privileges"),
        ({"CapabilityAdd": ["CAP_SYS_ADMIN"]}, "CapabilityAdd"),
        ({"PidMode": "host"}, "PidMode=host"),
        ({"Mounts": [{"Type": "bind", "Source": "/var/run/docker.sock", "Target": "/s"}]}, "/var/run/docker.sock"),
        ({"Mounts": [{"Type": "bind", "Source": "/", "Target": "/host"}]}, "bind mount of '/'"),
        (
            {
                "Mounts": [
                    {"Type": "volume", "Target": "/x", "VolumeOptions": {"DriverConfig": {"Options": {"o": "bind"}}}}
                ]
            },
            "driver options",
        ),
    ],
)
def test_service_specs_asking_for_host_access_are_refused(proxy: str, container: dict, named: str) -> None:
    name = f"proxy-svc-{uuid.uuid4().hex[:8]}"
    message = refusal(httpx.post(f"{proxy}/v1.41/services/create", json=service_body(name, **container), timeout=10))
    assert named in message
    assert docker_cli("service", "ls", "-q", "--filter", f"name={name}").strip() == ""


def test_a_bind_mount_that_escapes_the_volume_directory_is_refused(volumes_dir: Path) -> None:
    policy = Policy(str(volumes_dir))
    policy.check_service_spec(service_body("ok", Mounts=[{"Type": "bind", "Source": f"{volumes_dir}/r/s/v"}]))
    with pytest.raises(Refused, match="bind only directories under"):
        policy.check_service_spec(service_body("escape", Mounts=[{"Type": "bind", "Source": f"{volumes_dir}/../etc"}]))
    with pytest.raises(Refused, match="bind only directories under"):
        policy.check_service_spec(service_body("sibling", Mounts=[{"Type": "bind", "Source": f"{volumes_dir}x/a"}]))


def test_a_service_the_orchestration_makes_is_created_inspected_and_removed_through_the_proxy(
    proxy: str, volumes_dir: Path
) -> None:
    if docker_cli("info", "--format", "{{.Swarm.LocalNodeState}}").strip() != "active":
        pytest.skip("needs dockerd in an active Swarm: scripts/services.sh swarm")
    client = docker.APIClient(base_url=proxy.replace("http", "tcp"), version="auto")
    name = f"proxy-svc-{uuid.uuid4().hex[:8]}"
    (volumes_dir / "data").mkdir()
    try:
        spec = docker.types.ContainerSpec(
            IMAGE,
            args=["sleep", "60"],
            mounts=[docker.types.Mount("/data", str(volumes_dir / "data"), type="bind")],
        )
        created = client.create_service(docker.types.TaskTemplate(spec), name=name)
        assert client.inspect_service(created["ID"])["Spec"]["Name"] == name
        assert client.tasks(filters={"service": name}) is not None
        assert client.nodes() and client.networks()
        client.remove_service(created["ID"])
        assert docker_cli("service", "ls", "-q", "--filter", f"name={name}").strip() == ""
    finally:
        subprocess.run(["docker", "service", "rm", name], capture_output=True, timeout=60, check=False)
        client.close()


def test_a_network_on_the_hosts_own_segment_is_refused(proxy: str) -> None:
    name = f"proxy-net-{uuid.uuid4().hex[:8]}"
    body = {"Name": name, "Driver": "macvlan", "Options": {"parent": "eth0"}}
    assert "driver 'macvlan' is refused" in refusal(httpx.post(f"{proxy}/v1.41/networks/create", json=body, timeout=10))
    assert docker_cli("network", "ls", "-q", "--filter", f"name={name}").strip() == ""
    Policy("/x").check("POST", "/networks/create", b'{"Name": "n", "Driver": "overlay", "Attachable": true}')


def test_only_a_cloud_copys_container_may_be_stopped(proxy: str) -> None:
    plain = f"bridgeos-proxy-plain-{uuid.uuid4().hex[:8]}"
    copy = f"bridgeos-proxy-copy-{uuid.uuid4().hex[:8]}"
    docker_cli("run", "-d", "--init", "--name", plain, IMAGE, "sleep", "600")
    docker_cli("run", "-d", "--init", "--name", copy, "--label", "io.bridgeos.cloud=test", IMAGE, "sleep", "600")
    try:
        message = refusal(httpx.post(f"{proxy}/v1.41/containers/{plain}/stop?t=1", timeout=20))
        assert "only a cloud copy's container" in message
        assert docker_cli("inspect", "-f", "{{.State.Running}}", plain).strip() == "true"
        refusal(httpx.post(f"{proxy}/containers/no-such-container/stop", timeout=20))
        answer = httpx.post(f"{proxy}/v1.41/containers/{copy}/stop?t=1", timeout=20)
        assert answer.status_code == 204, answer.text
        assert docker_cli("inspect", "-f", "{{.State.Running}}", copy).strip() == "false"
    finally:
        docker_cli("rm", "-f", plain, copy)
