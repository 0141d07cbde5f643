"""The robot's token kept in a file (``--token-file``): read at start, replaced whole when the cloud re-keys it."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

__all__ = ["TokenFileError", "read_token_file", "write_token_file"]

MAX_TOKEN_CHARS = 256


class TokenFileError(ValueError):
    """The token file cannot be read, or holds no usable token."""


def read_token_file(path: Path) -> str:
    """Return the token a file holds (surrounding whitespace ignored); TokenFileError if it holds none."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise TokenFileError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from None
    token = text.strip()
    # The file's content is a secret: the errors name what is wrong, never what is there.
    if not token:
        raise TokenFileError(f"{path} is empty")
    if len(token) > MAX_TOKEN_CHARS or any(ch.isspace() or not ch.isprintable() for ch in token):
        raise TokenFileError(f"{path} does not hold a token (one line of printable characters without spaces)")
    return token


def write_token_file(path: Path, token: str) -> None:
    """Replace the token file with one holding ``token``, readable by this user only, all or nothing.

    Written beside it, synced, then renamed over it: a crash or a full disk leaves the old file whole.
    """
    path = Path(path)
    temp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as out:
            # O_CREAT's mode only applies to a new file: a stale temp file keeps its own otherwise.
            os.fchmod(out.fileno(), 0o600)
            out.write(token + "\n")
            out.flush()
            os.fsync(out.fileno())
        os.replace(temp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            temp.unlink()
        raise
    # The rename itself is durable only once the directory is synced.
    directory = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(directory)
    finally:
        os.close(directory)
