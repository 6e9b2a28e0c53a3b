"""One driver per experiment: the heartbeat lock in the storage dir (no Ray needed)."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import pytest

from uavlora_rllib.experiment import driver_lock
from uavlora_rllib.experiment.driver_lock import DriverLock, ExperimentLocked, lock_path


def write_lock(path: str, host: str, pid: int, heartbeat: float) -> None:
    with open(path, "w") as fh:
        json.dump({"host": host, "pid": pid, "token": "other", "started": heartbeat, "heartbeat": heartbeat}, fh)


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_second_driver_is_refused_naming_the_live_one(tmp_path):
    with DriverLock(str(tmp_path), "exp") as first:
        assert os.path.exists(first.path)
        with pytest.raises(ExperimentLocked) as err:
            DriverLock(str(tmp_path), "exp").acquire()
        msg = str(err.value)
        assert f"pid {os.getpid()}" in msg and socket.gethostname() in msg and "--resume" in msg
        # another experiment in the same storage is independent
        with DriverLock(str(tmp_path), "other"):
            pass
    assert not os.path.exists(lock_path(str(tmp_path), "exp"))  # released
    with DriverLock(str(tmp_path), "exp") as again:
        assert again.taken_over is None


def test_lock_of_a_killed_driver_on_this_host_is_taken_over(tmp_path):
    path = lock_path(str(tmp_path), "exp")
    pid = dead_pid()
    write_lock(path, socket.gethostname(), pid, time.time())  # fresh heartbeat, but the pid is gone
    with DriverLock(str(tmp_path), "exp") as lock:
        assert lock.taken_over is not None and lock.taken_over.pid == pid
        with open(path) as fh:
            assert json.load(fh)["token"] == lock.token


def test_lock_with_an_old_heartbeat_is_taken_over_and_a_fresh_one_is_not(tmp_path):
    path = lock_path(str(tmp_path), "exp")
    write_lock(path, "some-other-host", 12345, time.time() - driver_lock.STALE_S - 5)
    with DriverLock(str(tmp_path), "exp") as lock:
        assert lock.taken_over.host == "some-other-host"
    write_lock(path, "some-other-host", 12345, time.time())  # alive elsewhere: cannot check its pid
    with pytest.raises(ExperimentLocked, match="some-other-host"):
        DriverLock(str(tmp_path), "exp").acquire()
    # a lock file cut short by a kill mid-write counts as stale
    with open(path, "w") as fh:
        fh.write('{"host": ')
    with DriverLock(str(tmp_path), "exp") as lock:
        assert lock.taken_over is not None


def test_heartbeat_advances_and_a_lost_lock_is_noticed(tmp_path, monkeypatch):
    monkeypatch.setattr(driver_lock, "HEARTBEAT_S", 0.05)
    with DriverLock(str(tmp_path), "exp") as lock:
        first = driver_lock._read(lock.path).heartbeat
        deadline = time.monotonic() + 30
        while driver_lock._read(lock.path).heartbeat == first:
            assert time.monotonic() < deadline, "no heartbeat"
            time.sleep(0.05)
        # someone took the lock over (we looked dead to them): the owner notices at its next beat, writes
        # no more beats, and does not delete the new owner's lock on release. (The heartbeat thread is
        # stopped first, so that the takeover is not raced by a beat that read the file just before it.)
        lock._stop.set()
        lock._thread.join()
        write_lock(lock.path, "h2", 1, time.time())
        lock._beat()
        assert lock.lost
        before = driver_lock._read(lock.path)
        lock._beat()
        assert driver_lock._read(lock.path) == before  # lost: no further beat
    assert driver_lock._read(lock_path(str(tmp_path), "exp")).host == "h2"


def test_tune_cli_refuses_a_second_driver_before_starting_anything(tmp_path, capsys):
    import yaml

    from uavlora_rllib import tune as tune_cli

    grid = {
        "experiment": "locked",
        "algorithms": ["mappo"],
        "baselines": ["random"],
        "seeds": [0],
        "n_eds": [6],
        "n_uavs": [2],
        "stop": {"env_steps": 20},
        "storage": str(tmp_path / "ray_results"),
        "mlflow": {"tracking_uri": f"sqlite:///{tmp_path / 'mlflow.db'}"},
    }
    path = tmp_path / "g.yaml"
    path.write_text(yaml.safe_dump(grid))
    with DriverLock(str(tmp_path / "ray_results"), "locked"):
        rc = tune_cli.main([str(path), "--resume"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "live driver" in err and f"pid {os.getpid()}" in err
    assert not (tmp_path / "mlflow.db").exists()  # nothing ran, not even MLflow
