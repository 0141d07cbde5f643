"""The deployed stack over TLS: HAProxy ends it with a certificate from the cloud's CA (`make deploy`).

Browsers and robots verify it with that CA: the dashboard in Chromium over HTTPS, agents over `wss://`
with `--ca`, and an agent given another CA is refused and says why. Plain HTTP redirects to HTTPS.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import socket
import subprocess
import time
from datetime import UTC, datetime
from pathlib import Path

import httpx
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization

from network import pki
from tests.deploy.deployed import AGENT, DEPLOY, Agent, Stack, run, wait_until

pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(900)]

CHROMIUM = "/usr/bin/chromium"


def spki_sha256(pem: str) -> str:
    """Return the base64 SHA-256 of a certificate's public key, the form Chromium's SPKI list takes."""
    cert = x509.load_pem_x509_certificate(pem.encode())
    der = cert.public_key().public_bytes(serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    return base64.b64encode(hashlib.sha256(der).digest()).decode()


def start_agent(stack: Stack, robot_id: str, token: str, ca: Path, log: Path, data_dir: Path) -> Agent:
    """Start an agent from the venv over wss:// checking the cloud with the given CA file."""
    data_dir.mkdir(exist_ok=True)
    args = ["run", "--master", stack.wss, "--ca", str(ca), "--robot", robot_id, "--token", token]
    args += ["--runtime", "process", "--simulate", "--data-dir", str(data_dir)]
    with log.open("ab") as out:
        process = subprocess.Popen([str(AGENT), *args], stdout=out, stderr=subprocess.STDOUT)
    agent = Agent(robot_id, process=process)
    stack.agents[robot_id] = agent
    return agent


def test_the_stack_speaks_tls_that_robots_and_browsers_verify_with_the_clouds_ca(stack: Stack, tmp_path: Path) -> None:
    # `make deploy` printed the CA's fingerprint and the line a robot owner runs.
    ca_pem = (stack.secrets / "ca.crt").read_text()
    ca = x509.load_pem_x509_certificate(ca_pem.encode())
    fingerprint = ":".join(f"{byte:02X}" for byte in ca.fingerprint(hashes.SHA256()))
    assert f"SHA-256 fingerprint {fingerprint}" in stack.output, stack.output
    host = socket.gethostname()
    agent_line = f"bridgeos-agent run --master wss://{host}:{stack.port} --ca {stack.secrets}/ca.crt --robot ID"
    assert agent_line in stack.output, stack.output

    # The load balancer's certificate comes from the cloud's CA and names this host: verified with that CA
    # alone, and refused by a client that trusts only the system's CAs. Every answer carries HSTS.
    for name in (host, "127.0.0.1", "localhost"):
        answer = stack.http.get(f"https://{name}:{stack.port}/api/health")
        assert answer.status_code == 200 and answer.json()["status"] == "ok", answer.text
        assert answer.headers["Strict-Transport-Security"] == "max-age=31536000"
    with pytest.raises(httpx.ConnectError, match="CERTIFICATE_VERIFY_FAILED"):
        httpx.get(f"{stack.url}/api/health", timeout=10)

    # Plain HTTP is redirected to the TLS port, the method kept (308), without HSTS (meaningless in clear).
    plain = httpx.get(f"http://{host}:{stack.http_port}/accounts/login/?next=/", timeout=10)
    assert plain.status_code == 308, plain.text
    assert plain.headers["location"] == f"https://{host}:{stack.port}/accounts/login/?next=/"
    assert "Strict-Transport-Security" not in plain.headers
    post = httpx.post(f"http://127.0.0.1:{stack.http_port}/api/auth", timeout=10)
    assert post.status_code == 308 and post.headers["location"] == f"{stack.url}/api/auth"

    # Django knows the request came over TLS (the lb's X-Forwarded-Proto): its cookies are Secure, and a
    # form posted from the deployment's own origin passes the CSRF check while another origin's does not.
    origin = f"https://{host}:{stack.port}"
    with httpx.Client(base_url=origin, verify=stack.tls, timeout=15) as browser:
        login = browser.get("/accounts/login/")
        assert login.status_code == 200
        cookie = next(c for c in login.headers.get_list("set-cookie") if c.startswith("csrftoken="))
        assert "; Secure" in cookie, cookie
        form = {
            "csrfmiddlewaretoken": browser.cookies["csrftoken"],
            "username": "operator",
            "password": stack.operator_password,
        }
        forged = browser.post("/accounts/login/", data=form, headers={"Origin": "https://elsewhere.example"})
        assert forged.status_code == 403, forged.status_code
        signed_in = browser.post("/accounts/login/", data=form, headers={"Origin": origin, "Referer": f"{origin}/"})
        assert signed_in.status_code == 302, signed_in.text[-2000:]
        session = next(c for c in signed_in.headers.get_list("set-cookie") if c.startswith("sessionid="))
        assert "; Secure" in session and "; HttpOnly" in session, session

    # The registry answers behind the same certificate (/v2/ routed to it), its token realm over HTTPS.
    registry = stack.http.get(f"{stack.url}/v2/")
    assert registry.status_code == 401, registry.text
    assert f'realm="https://{host}:{stack.port}/api/registry/token"' in registry.headers["www-authenticate"]
    assert registry.headers["Strict-Transport-Security"] == "max-age=31536000"
    # ... and a Docker engine pulls through that door (make deploy made it trust the CA for NAME:TLS_PORT).
    image = run(
        "docker", "service", "inspect", "--format", "{{.Spec.TaskTemplate.ContainerSpec.Image}}", f"{stack.name}_lb"
    )
    through_lb = f"{host}:{stack.port}/{image.strip().split('/', 1)[1]}"
    client_env = {**os.environ, "DOCKER_CONFIG": str(stack.secrets / "docker")}
    login = subprocess.run(
        ["docker", "login", f"{host}:{stack.port}", "-u", "operator", "--password-stdin"],
        input=stack.operator_password, capture_output=True, text=True, env=client_env, timeout=60,
    )  # fmt: skip
    assert login.returncode == 0, login.stderr
    run("docker", "pull", "-q", through_lb, env=client_env, timeout=120)
    run("docker", "rmi", through_lb)

    # The dashboard in Chromium over HTTPS. Chromium trusts the certificate through its SPKI allow-list
    # (the key of the certificate verified against the CA above), not by ignoring certificate errors.
    if Path(CHROMIUM).exists():
        sync_api = pytest.importorskip("playwright.sync_api", reason="playwright is not installed")
        spki = spki_sha256((stack.secrets / "lb.pem").read_text())
        flags = ["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run", "--disable-quic"]
        with sync_api.sync_playwright() as playwright:
            chromium = playwright.chromium.launch(
                executable_path=CHROMIUM, args=[*flags, f"--ignore-certificate-errors-spki-list={spki}"]
            )
            try:
                page = chromium.new_page()
                page.goto(f"http://{host}:{stack.http_port}/", wait_until="load")
                # Redirected to HTTPS, then (signed out) to the login page, served from a secure context.
                assert page.url.startswith(f"{origin}/accounts/login/"), page.url
                assert page.evaluate("window.isSecureContext") is True
                sync_api.expect(page.locator("input[name=password]")).to_be_visible()
                page.fill("input[name=username]", "operator")
                page.fill("input[name=password]", stack.operator_password)
                page.locator("form button[type=submit], form input[type=submit]").first.click()
                page.wait_for_url(lambda url: "/accounts/login/" not in url)
                assert page.url.startswith(origin), page.url
                print(f"Chromium signed in over HTTPS, trusting the certificate's key {spki}: at {page.url}")
            finally:
                chromium.close()
    else:
        print(f"Chromium is not installed at {CHROMIUM}: the dashboard's HTTPS check in a browser was skipped")

    # A robot whose --ca is another CA is refused: it says why once, keeps retrying, and never connects.
    robot_id = "deploy-tls"
    token = stack.exec("daphne", "bridgeos-cloud", "manage", "create_robot", robot_id, "--owner", "operator").strip()
    _, other = pki.make_ca("not the cloud's CA", now=datetime.now(UTC))
    wrong = tmp_path / "other-ca.crt"
    wrong.write_text(pki.pem(other))
    log = tmp_path / "wrong-ca.log"
    agent = start_agent(stack, robot_id, token, wrong, log, tmp_path / "agent")
    refused = (
        f"TLS certificate of {stack.wss}/ws/robot/ not trusted by --ca {wrong}: "
        "certificate verify failed: unable to get local issuer certificate"
    )
    wait_until(lambda: refused in log.read_text(), 30, f"the agent with another CA logged {refused!r}")
    time.sleep(3)  # a few more attempts
    assert agent.process is not None and agent.process.poll() is None, "the refused agent keeps retrying"
    assert log.read_text().count(refused) == 1, log.read_text()
    assert not stack.robots().get(robot_id, (False,))[0]
    agent.stop()

    # The same robot with the CA `make deploy` printed connects over WSS.
    log = tmp_path / "right-ca.log"
    start_agent(stack, robot_id, token, stack.secrets / "ca.crt", log, tmp_path / "agent")
    wait_until(lambda: stack.robots().get(robot_id, (False,))[0], 30, "the robot with the cloud's CA connected")
    assert "connected to the cloud (over WSS)" in log.read_text(), log.read_text()
    stack.agents.pop(robot_id).stop()

    # `make deploy` again, nothing changed: the same certificate, so the load balancer is left alone.
    lb = stack.containers("lb")
    again = run("bash", str(DEPLOY), env=stack.env, timeout=600)
    assert "deploy: healthy after" in again, again
    if stack.containers("lb") != lb:
        service = json.loads(run("docker", "service", "inspect", "--format", "{{json .}}", f"{stack.name}_lb"))
        now, before = (
            service.get(k, {}).get("TaskTemplate", {}).get("ContainerSpec", {}) for k in ("Spec", "PreviousSpec")
        )
        changed = {
            key: (before.get(key), now.get(key))
            for key in now.keys() | before.keys()
            if now.get(key) != before.get(key)
        }
        pytest.fail(f"a second deploy replaced the load balancer; its container spec changed: {changed}")
    assert stack.http.get(f"{stack.url}/api/health").status_code == 200
