"""Images of several layers of incompressible bytes, built offline, that no engine has seen before."""

from __future__ import annotations

import os
import secrets
import subprocess
import tarfile
from pathlib import Path


def build_layered_image(base: Path, name: str, layers: int, layer_bytes: int) -> str:
    """Build ``name`` in this machine's engine: a runnable ``/bin/sleep`` and ``layers`` layers of random bytes.

    The first layer is imported (no registry is reachable to pull a base image from); each further
    one is a ``COPY`` of a file of fresh random bytes, so every layer is new to every engine and
    its compressed size is about its size.
    """
    base.mkdir(parents=True, exist_ok=True)
    libs = subprocess.run(["ldd", "/bin/sleep"], capture_output=True, text=True, check=True).stdout
    files = ["/bin/sleep"] + [part for part in libs.split() if part.startswith("/")]
    with tarfile.open(base / "rootfs.tar", "w") as tar:
        for path in files:
            tar.add(Path(path).resolve(), arcname=path.lstrip("/"))
    root = f"bridgeos-test/layered-root:{secrets.token_hex(4)}"
    subprocess.run(["docker", "import", str(base / "rootfs.tar"), root], capture_output=True, check=True)
    steps = [f"FROM {root}"]
    for n in range(layers):
        (base / f"layer{n}").write_bytes(os.urandom(layer_bytes))
        steps.append(f"COPY layer{n} /data/layer{n}")
    (base / "Dockerfile").write_text("\n".join(steps) + '\nCMD ["/bin/sleep", "600"]\n')
    (base / "rootfs.tar").unlink()
    try:
        built = subprocess.run(
            ["docker", "build", "--quiet", "--tag", name, str(base)],
            capture_output=True,
            text=True,
            env={**os.environ, "DOCKER_BUILDKIT": "0"},  # the classic builder: no image to fetch
            timeout=300,
        )
        if built.returncode != 0:
            raise RuntimeError(f"docker build {name} failed: {built.stderr[-2000:]}")
    finally:
        subprocess.run(["docker", "rmi", root], capture_output=True)
        for n in range(layers):
            (base / f"layer{n}").unlink(missing_ok=True)
    return name
