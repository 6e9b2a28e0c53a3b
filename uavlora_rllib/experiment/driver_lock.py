"""One driver per experiment: a lock file with a heartbeat in the storage directory.

Two drivers on one Tune experiment (a `--resume` while the first run is still alive) corrupt
it: both restore the same trials, train them twice, delete each other's checkpoints and mark
each other's MLflow runs FAILED. The lock makes the second driver stop before it touches
anything, with a message naming the live one.

The lock is ``<storage>/.<experiment>.driver.json``: host, pid, a random token, when it was
taken and when its owner last beat. The owner rewrites it every `HEARTBEAT_S` seconds. A lock
is stale, and is taken over, when its heartbeat is older than `STALE_S` seconds (a driver on
another host that died or lost the shared filesystem), or at once when its owner ran on this
host and its pid is gone (a killed driver). Taking over renames the stale file to a unique
name first, so of two drivers that race for a stale lock exactly one wins the exclusive
create.

Only local (or NFS-mounted) storage paths have a lock; for a cloud URI (s3://, gs://) the
docs ask for one driver per experiment and `acquire` says so once.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
import uuid
from dataclasses import dataclass

from uavlora_rllib.config_errors import ConfigError

HEARTBEAT_S = 5.0
STALE_S = 60.0  # twelve missed heartbeats: well past an NFS hiccup or a GC pause


class ExperimentLocked(ConfigError):
    """Another live driver holds the experiment (exit code 2, one line)."""


@dataclass(frozen=True)
class LockInfo:
    host: str
    pid: int
    token: str
    started: float
    heartbeat: float

    def describe(self, now: float | None = None) -> str:
        age = (now or time.time()) - self.heartbeat
        return f"pid {self.pid} on host {self.host} (last heartbeat {age:.0f} s ago)"


def lock_path(storage: str, experiment: str) -> str:
    return os.path.join(storage, f".{experiment}.driver.json")


def _read(path: str) -> LockInfo | None:
    try:
        with open(path) as fh:
            data = json.load(fh)
        return LockInfo(
            str(data["host"]), int(data["pid"]), str(data["token"]), float(data["started"]), float(data["heartbeat"])
        )
    except FileNotFoundError:
        return None
    except (OSError, ValueError, KeyError, TypeError):
        # half-written by a driver killed mid-write: treat as a lock with no heartbeat
        return LockInfo("?", -1, "", 0.0, 0.0)


def pid_alive(pid: int) -> bool:
    """Whether process `pid` exists on this host (another user's counts)."""
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def is_stale(info: LockInfo, now: float | None = None, host: str | None = None) -> bool:
    now = time.time() if now is None else now
    if now - info.heartbeat > STALE_S:
        return True
    return info.host == (host or socket.gethostname()) and not pid_alive(info.pid)


class DriverLock:
    """Held by the driver from before the baselines until it exits (context manager)."""

    def __init__(self, storage: str, experiment: str):
        self.path = lock_path(storage, experiment)
        self.experiment = experiment
        self.host = socket.gethostname()
        self.token = uuid.uuid4().hex
        self.started = time.time()
        self.taken_over: LockInfo | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.lost = False  # set when another driver took the lock from us

    # ---- file
    def _payload(self) -> str:
        return json.dumps(
            {
                "host": self.host,
                "pid": os.getpid(),
                "token": self.token,
                "started": self.started,
                "heartbeat": time.time(),
            }
        )

    def _create(self) -> bool:
        try:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        except FileExistsError:
            return False
        with os.fdopen(fd, "w") as fh:
            fh.write(self._payload())
        return True

    def _beat(self) -> None:
        if self.lost:  # once taken over, never write again: a later write would clobber the new owner's lock
            return
        current = _read(self.path)
        if current is None or current.token != self.token:
            self.lost = True
            return
        tmp = f"{self.path}.{self.token}.tmp"
        with open(tmp, "w") as fh:
            fh.write(self._payload())
        os.replace(tmp, self.path)  # atomic: a reader never sees half a heartbeat

    # ---- API
    def acquire(self) -> DriverLock:
        os.makedirs(os.path.dirname(self.path), exist_ok=True)
        for _ in range(3):
            if self._create():
                break
            info = _read(self.path)
            if info is None:
                continue  # released between our create and read
            if not is_stale(info, host=self.host):
                raise ExperimentLocked(
                    f"experiment {self.experiment!r} is being run by a live driver: {info.describe()}; "
                    f"wait for it to finish or stop it (Ctrl+C), then use --resume (lock file {self.path})"
                )
            # stale: move it aside under a unique name; only one contender's rename succeeds
            aside = f"{self.path}.stale.{self.token}"
            try:
                os.rename(self.path, aside)
            except FileNotFoundError:
                continue
            os.unlink(aside)
            self.taken_over = info
        else:
            raise ExperimentLocked(f"experiment {self.experiment!r}: could not take the driver lock {self.path}")
        self._thread = threading.Thread(target=self._run, name="driver-lock-heartbeat", daemon=True)
        self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(HEARTBEAT_S):
            try:
                self._beat()
            except OSError:
                pass  # shared filesystem hiccup: the next beat retries; STALE_S allows many misses

    def release(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=HEARTBEAT_S + 1)
        info = _read(self.path)
        if not self.lost and info is not None and info.token == self.token:
            try:
                os.unlink(self.path)
            except FileNotFoundError:
                pass

    def __enter__(self) -> DriverLock:
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()
