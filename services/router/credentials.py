"""Credentials for an authenticated session: a password per service user, and the router's file of them.

``viewscale credentials --out deploy/zenoh/secrets`` writes, with owner-only permissions:

    users.txt            user:password, one line per user: the router's ``--users`` file
    <user>.password      that user's password alone: the service's ``bus.password_file``

The user names are those of deploy/zenoh/router-acl.json5, which grants each one its keys. Nothing
here prints a password; the files are the only copy (delete the folder to revoke, rerun with
``--force`` to rotate every password at once, then restart the router and the services).
"""

from __future__ import annotations

import os
import secrets
from collections.abc import Iterable
from pathlib import Path

from services.core.runtime import writable_dir

# The service users of deploy/zenoh/router-acl.json5 (a test keeps the two in step).
SERVICE_USERS = ("sim", "camera", "robot", "teleop", "recorder", "session", "trainer", "operator")
USERS_FILE = "users.txt"


def password_path(out: Path, user: str) -> Path:
    return Path(out) / f"{user}.password"


def _write_private(path: Path, text: str) -> None:
    """Create ``path`` readable by its owner only (0600 from the start, not chmod'ed after)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.chmod(path, 0o600)  # an existing file (--force) keeps its old mode through O_CREAT


def write_credentials(out: Path, users: Iterable[str] = SERVICE_USERS, force: bool = False) -> list[Path]:
    """A fresh random password for each of ``users`` in ``out``; returns the files written.

    Refuses to replace existing credentials unless ``force`` (running services would be locked out).
    """
    out = Path(out)
    users = list(dict.fromkeys(users))
    for user in users:
        if not user or ":" in user or user != user.strip() or "/" in user:
            raise ValueError(f"user name {user!r}: must be non-empty, without ':', '/' or surrounding spaces")
    if not users:
        raise ValueError("no users to write credentials for")
    existing = [p for p in [out / USERS_FILE, *(password_path(out, u) for u in users)] if p.exists()]
    if existing and not force:
        raise FileExistsError(
            f"{existing[0]} exists: credentials are already there (--force replaces every password; "
            "then restart the router and every service)"
        )
    writable_dir(out, "--out")
    os.chmod(out, 0o700)
    passwords = {user: secrets.token_urlsafe(24) for user in users}  # 192 random bits, [A-Za-z0-9_-]
    written = []
    for user, password in passwords.items():
        path = password_path(out, user)
        _write_private(path, password + "\n")
        written.append(path)
    _write_private(out / USERS_FILE, "".join(f"{u}:{p}\n" for u, p in passwords.items()))
    written.append(out / USERS_FILE)
    return written
