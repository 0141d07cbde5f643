"""Images no engine has seen: a static-enough `sleep` with a layer of random bytes, imported into this machine's engine."""

from __future__ import annotations

import secrets
import subprocess
import tarfile
from pathlib import Path

__all__ = ["sleeper_image"]


def sleeper_image(base: Path, *, padding_bytes: int = 0) -> str:
    """Import an image that runs /bin/sleep and carries ``padding_bytes`` of random data; return its local name.

    Random bytes do not compress, so the image's size on the wire is about ``padding_bytes``;
    the random marker makes its digest new to every registry and engine. Remove it from this
    machine's engine (``docker rmi``) once it is pushed.
    """
    base.mkdir(parents=True, exist_ok=True)
    (base / "run.txt").write_text(secrets.token_hex(16))
    libs = subprocess.run(["ldd", "/bin/sleep"], capture_output=True, text=True, check=True).stdout
    files = ["/bin/sleep"] + [part for part in libs.split() if part.startswith("/")]
    with tarfile.open(base / "rootfs.tar", "w") as tar:
        for path in files:
            tar.add(Path(path).resolve(), arcname=path.lstrip("/"))
        tar.add(base / "run.txt", arcname="run.txt")
        if padding_bytes:
            padding = base / "padding.bin"
            with padding.open("wb") as out:
                for done in range(0, padding_bytes, 1 << 20):
                    out.write(secrets.token_bytes(min(1 << 20, padding_bytes - done)))
            tar.add(padding, arcname="padding.bin")
    name = f"bridgeos-test/sleeper:{secrets.token_hex(6)}"
    done = subprocess.run(["docker", "import", str(base / "rootfs.tar"), name], capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"docker import failed: {done.stderr.strip()}")
    (base / "rootfs.tar").unlink()
    return name
