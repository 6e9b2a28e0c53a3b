"""Hosts for tests that need several machines: Linux network namespaces on this one, each with
its own address, joined by a veth pair.

A namespace is held by an `unshare --net` process and entered with `nsenter`; it and its veth
vanish with the last process in it, so nothing is registered system-wide (no `ip netns add`).
As root the namespaces are plain; otherwise both live in one user namespace of this user (where
the kernel allows those). Needs util-linux and iproute2; where it cannot work, `Unavailable`.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import time
from collections.abc import Iterator, Sequence
from typing import Any

TOOLS = ("unshare", "nsenter", "ip")


class Unavailable(RuntimeError):
    """Namespaces cannot be made here (a missing tool, no privilege, no veth support)."""


def _ns_key(pid: int | str) -> tuple[int, int]:
    """The network namespace of process `pid` ("self": ours) as (device, inode): equal keys, one namespace."""
    st = os.stat(f"/proc/{pid}/ns/net")
    return st.st_dev, st.st_ino


class Host:
    """One network namespace (a "host") and what runs in it; `close()` ends all of it by PID."""

    def __init__(self, address: str, user_ns: str | None = None):
        """A new namespace for `address` (which `two_hosts` assigns); `user_ns`: the user namespace
        to make it in and enter it with when not root ("new": make one), None: none."""
        self.address = address
        missing = [t for t in TOOLS if shutil.which(t) is None]
        if missing:
            raise Unavailable(f"missing {', '.join(missing)}")
        if user_ns is None:
            holder = ["unshare", "--net", "cat"]
        elif user_ns == "new":
            holder = ["unshare", "--user", "--map-root-user", "--net", "cat"]
        else:
            holder = ["nsenter", "--preserve-credentials", f"--user={user_ns}", "unshare", "--net", "cat"]
        # the holder lives until its stdin closes: when close() runs, or when the test process dies
        self.holder = subprocess.Popen(holder, stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        own = _ns_key("self")
        deadline = time.monotonic() + 10
        while True:
            if self.holder.poll() is not None:
                err = self.holder.stderr.read().decode(errors="replace").strip() if self.holder.stderr else ""
                raise Unavailable(f"`unshare --net` failed: {err or self.holder.returncode}")
            with contextlib.suppress(OSError):
                # until unshare has run, the holder is still in our namespace: never configure that one
                if _ns_key(self.holder.pid) != own:
                    break
            if time.monotonic() > deadline:
                self.close()
                raise Unavailable("`unshare --net` did not enter a new namespace")
            time.sleep(0.01)
        self.key = _ns_key(self.holder.pid)
        self.path = f"/proc/{self.holder.pid}/ns/net"
        self.user_ns = f"/proc/{self.holder.pid}/ns/user" if user_ns == "new" else user_ns
        user = [] if self.user_ns is None else ["--preserve-credentials", f"--user={self.user_ns}"]
        self.enter = ["nsenter", *user, f"--net={self.path}", "--"]

    def argv(self, argv: Sequence[str]) -> list[str]:
        """`argv` as run inside this namespace."""
        return [*self.enter, *argv]

    def run(self, argv: Sequence[str], **kwargs: Any) -> subprocess.CompletedProcess:
        return subprocess.run(self.argv(argv), **kwargs)

    def popen(self, argv: Sequence[str], **kwargs: Any) -> subprocess.Popen:
        return subprocess.Popen(self.argv(argv), **kwargs)

    def ip(self, *args: str) -> None:
        proc = self.run(["ip", *args], capture_output=True, text=True)
        if proc.returncode != 0:
            raise Unavailable(f"`ip {' '.join(args)}` failed: {proc.stderr.strip()}")

    def pids(self) -> list[int]:
        """Every process in this namespace but the holder."""
        out = []
        for entry in os.listdir("/proc"):
            if entry.isdigit() and int(entry) != self.holder.pid:
                with contextlib.suppress(OSError):
                    if _ns_key(entry) == self.key:
                        out.append(int(entry))
        return out

    def close(self) -> None:
        """SIGKILL whatever still runs in the namespace, then end the holder (the namespace goes with it)."""
        if hasattr(self, "key"):
            for pid in self.pids():
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
        if self.holder.stdin:
            self.holder.stdin.close()
        try:
            self.holder.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.holder.kill()
            self.holder.wait()
        if self.holder.stderr:
            self.holder.stderr.close()


@contextlib.contextmanager
def two_hosts(subnet: str = "10.77.0") -> Iterator[tuple[Host, Host]]:
    """Two hosts, SUBNET.1 and SUBNET.2 (/24) on a veth pair, loopback up in each; closed on exit.
    The subnet exists only inside the two namespaces, so it cannot clash with the machine's."""
    made: list[Host] = []
    try:
        a = Host(f"{subnet}.1", None if os.geteuid() == 0 else "new")
        made.append(a)
        b = Host(f"{subnet}.2", a.user_ns)
        made.append(b)
        a.ip("link", "add", "veth0", "type", "veth", "peer", "name", "veth1", "netns", str(b.holder.pid))
        for host, dev in ((a, "veth0"), (b, "veth1")):
            host.ip("link", "set", "lo", "up")
            host.ip("addr", "add", f"{host.address}/24", "dev", dev)
            host.ip("link", "set", dev, "up")
        yield a, b
    finally:
        for host in reversed(made):
            host.close()
