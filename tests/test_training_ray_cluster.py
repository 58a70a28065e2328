"""Training on a real two-raylet Ray cluster on loopback, its worker node killed mid-run (issue 18).

The cluster: ``ray start --head --num-cpus=1`` and a second raylet ``ray start --address=...
--num-cpus=1`` on this machine, with Ray 2.60's token authentication (``RAY_AUTH_MODE=token``,
a fresh ``RAY_AUTH_TOKEN``), unique ports and a private temp folder; each ``ray start``
runs in its own session, so the second node is killed (and everything is cleaned up) by
killing every process of that session. The driver is ``serve-studio train --ray
<head address>`` in a subprocess. Once a training task runs on the second node and
records are arriving, the node's whole session is SIGKILLed.

Two cases: the node killed, and the node killed then the driver SIGKILLed 1 s after it
resubmitted the lost run (the report's "interrupted during the retry"). Asserted: the
training ends (exit 0, or exit 2 with a message) with no traceback, no run log holds a
repeated or missing index, a rerun resumes and completes every run (full logs, 0..n-1),
and no more than one training task ran at once per node (one CPU each). Every Ray process
the test started is killed at the end, also on failure.

Measured on the 2-core sandbox (session 14), the machine shared with other work: 6 runs of
both cases, 12 of 12 passed (53-76 s for the two); node 2 was killed after 3-7 records of its task, the
driver resubmitted the run from the 2-7 records it held, every log ended with indices 0-6
once, and at most one training task ran at a time on each node. It runs where ``CI`` is set
(reliable as measured here) or with ``STUDIO_RAY_CLUSTER_TEST=1``; ``STUDIO_RAY_CLUSTER_TEST=0``
skips it. How to run a real cluster: docs/cluster.md.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
RAY = Path(sys.executable).with_name("ray")
SEED = ROOT / "examples" / "serves" / "topspin_right.json"
ITERATIONS, POPULATION, COUNT = 3, 2, 3
EVALUATIONS = 1 + ITERATIONS * POPULATION  # the seed serve, then HEBO batches

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not sys.platform.startswith("linux"), reason="reads /proc to find and kill the node's processes"
    ),
    pytest.mark.skipif(not RAY.exists(), reason="the ray command line is not installed"),
    pytest.mark.skipif(
        os.environ.get("STUDIO_RAY_CLUSTER_TEST", "1" if os.environ.get("CI") else "0") != "1",
        reason="two-raylet cluster test (~1 min): runs in CI (CI set) or with STUDIO_RAY_CLUSTER_TEST=1",
    ),
]


def _free_ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


def _stat(pid: str) -> tuple[int, str] | None:
    """(session id, command line) of a process, None when it is gone."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return None
    fields = stat[stat.rfind(")") + 2 :].split()  # after "pid (comm) "
    return int(fields[3]), cmd


def _session(sid: int) -> list[tuple[int, str]]:
    """(pid, command line) of every live process of session ``sid``."""
    out = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            st = _stat(entry)
            if st is not None and st[0] == sid and not st[1].startswith("[") and st[1]:
                out.append((int(entry), st[1]))
    return out


def _kill_session(sid: int) -> int:
    """SIGKILL every process of session ``sid`` (until none is left); how many were killed."""
    killed = 0
    for _ in range(20):
        procs = _session(sid)
        if not procs:
            break
        for pid, _cmd in procs:
            try:
                os.kill(pid, signal.SIGKILL)
                killed += 1
            except ProcessLookupError:
                pass
        time.sleep(0.2)
    return killed


@dataclass
class Cluster:
    """A head and a second raylet started by this test (each ``ray start --block`` is the
    leader of its own session)."""

    tmp: Path
    env: dict[str, str]
    address: str = ""
    procs: dict[str, subprocess.Popen[bytes]] = field(default_factory=dict)

    def start(self, name: str, args: list[str]) -> None:
        ports = _free_ports(7)
        cmd = [str(RAY), "start", "--block", "--num-cpus=1", "--disable-usage-stats",
               "--object-store-memory=80000000", f"--temp-dir={self.tmp / name}",
               f"--node-manager-port={ports[0]}", f"--object-manager-port={ports[1]}",
               f"--dashboard-agent-listen-port={ports[2]}", f"--dashboard-agent-grpc-port={ports[3]}",
               f"--runtime-env-agent-port={ports[4]}", f"--metrics-export-port={ports[5]}",
               f"--dashboard-port={ports[6]}", *args]  # fmt: skip
        with open(self.tmp / f"{name}.log", "wb") as log:  # the child keeps its own descriptor
            self.procs[name] = subprocess.Popen(
                cmd, env=self.env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True
            )
        deadline = time.monotonic() + 120
        while b"Ray runtime started" not in (self.tmp / f"{name}.log").read_bytes():
            if self.procs[name].poll() is not None or time.monotonic() > deadline:
                raise AssertionError(f"ray start {name} failed:\n{(self.tmp / f'{name}.log').read_text()[-3000:]}")
            time.sleep(0.5)

    def session(self, name: str) -> list[tuple[int, str]]:
        return _session(self.procs[name].pid)

    def kill(self, name: str) -> int:
        n = _kill_session(self.procs[name].pid)
        self.procs[name].wait(timeout=30)
        return n


@pytest.fixture
def cluster() -> Iterator[Cluster]:
    tmp = Path(tempfile.mkdtemp(prefix="ssray-", dir="/tmp"))  # short: Ray's socket paths have a length limit
    env = dict(
        os.environ,
        RAY_AUTH_MODE="token",
        RAY_AUTH_TOKEN=secrets.token_hex(32),
        RAY_ENABLE_UV_RUN_RUNTIME_ENV="0",
        RAY_USAGE_STATS_ENABLED="0",
        RAY_health_check_period_ms="1000",  # a dead node is noticed in seconds, not ~30 s
        RAY_health_check_timeout_ms="2000",
        RAY_health_check_failure_threshold="5",
    )
    env.pop("RAY_ADDRESS", None)
    c = Cluster(tmp, env)
    try:
        gcs_port = _free_ports(1)[0]
        c.address = f"127.0.0.1:{gcs_port}"
        c.start("head", ["--head", f"--port={gcs_port}", "--node-ip-address=127.0.0.1", "--include-dashboard=false"])
        c.start("node2", [f"--address={c.address}", "--node-ip-address=127.0.0.1"])
        yield c
    finally:
        for name in list(c.procs):
            _kill_session(c.procs[name].pid)
            c.procs[name].wait(timeout=30)
        shutil.rmtree(tmp, ignore_errors=True)


def _train(c: Cluster, work: Path, name: str) -> subprocess.Popen[bytes]:
    cmd = [sys.executable, "-m", "studio.cli", "train", "--task", "topspin_velocity", "--count", str(COUNT),
           "--side", "right", "--iterations", str(ITERATIONS), "--population", str(POPULATION), "--tosses", "1",
           "--workers", "1", "--seeds", str(SEED), "--runs", str(work / "runs"), "--library", str(work / "lib"),
           "--ray", c.address]  # fmt: skip
    with open(work / f"{name}.out", "wb") as out:
        return subprocess.Popen(cmd, cwd=ROOT, env=c.env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)


def _logged(work: Path) -> dict[str, list[int]]:
    out = {}
    for log in sorted((work / "runs").glob("*/evaluations.jsonl")):
        out[log.parent.name] = [json.loads(line)["index"] for line in log.read_text().splitlines() if line.strip()]
    return out


def _jobs(c: Cluster, name: str) -> list[int]:
    return [pid for pid, cmd in c.session(name) if cmd.startswith("ray::_ray_job")]


def _scratch_records(pid: int) -> int:
    """Records in the scratch log of the training task ``pid`` (found through its open files)."""
    try:
        for fd in os.listdir(f"/proc/{pid}/fd"):
            target = os.readlink(f"/proc/{pid}/fd/{fd}")
            if target.endswith("/run/evaluations.jsonl"):
                return Path(target).read_bytes().count(b"\n")
    except OSError:
        pass
    return 0


def _run_and_kill_node2(c: Cluster, work: Path, kill_driver: bool) -> tuple[int | None, int, dict[str, int]]:
    """The first training, node 2 killed once its task logged 3 records (mid-run: the seed
    and the first batch), with ``kill_driver`` the driver SIGKILLed 1 s after it resubmitted
    the lost run; (exit code or None when killed, records of the lost task when its node
    was killed, most training tasks seen at once per node)."""
    driver = _train(c, work, "first")
    most, killed_at, resubmitted = {"head": 0, "node2": 0}, 0, 0.0
    try:
        deadline = time.monotonic() + 300
        while driver.poll() is None:
            assert time.monotonic() < deadline, "the training did not end within 300 s"
            for name in ("head", "node2") if not killed_at else ("head",):
                most[name] = max(most[name], len(_jobs(c, name)))
            on_node2 = _jobs(c, "node2") if not killed_at else []
            if on_node2 and (n := _scratch_records(on_node2[0])) >= 3:
                c.kill("node2")
                killed_at = n
            if kill_driver and killed_at and not resubmitted and b"resubmitted" in (work / "first.out").read_bytes():
                resubmitted = time.monotonic()
            if resubmitted and time.monotonic() > resubmitted + 1.0:
                os.killpg(driver.pid, signal.SIGKILL)
                driver.wait()
                return None, killed_at, most
            time.sleep(0.05)
        return driver.returncode, killed_at, most
    finally:
        if driver.poll() is None:
            os.killpg(driver.pid, signal.SIGKILL)
            driver.wait()


@pytest.mark.parametrize("kill_driver", [False, True], ids=["node-killed", "node-then-driver-killed"])
def test_a_killed_worker_node_leaves_logs_without_repeats_that_resume(
    cluster: Cluster, tmp_path: Path, kill_driver: bool
) -> None:
    code, killed_at, most = _run_and_kill_node2(cluster, tmp_path, kill_driver)
    first = (tmp_path / "first.out").read_text(errors="replace")
    assert killed_at, f"no training task ran on the second node:\n{first[-3000:]}"
    assert "Traceback" not in first, first[-3000:]
    if kill_driver:
        assert code is None, f"the training ended before its driver was killed:\n{first[-3000:]}"
    else:
        assert code in (0, 2), first[-3000:]
    if code == 2:
        assert "Run the same command again to resume" in first or "run the same command again" in first, first
    assert most["head"] <= 1 and most["node2"] <= 1, most  # one CPU each: one training task at a time
    for run, indices in _logged(tmp_path).items():
        assert indices == list(range(len(indices))), (run, indices)  # no repeated or missing index
    first_logs = {run: len(v) for run, v in _logged(tmp_path).items()}
    rerun = _train(cluster, tmp_path, "rerun")
    try:
        assert rerun.wait(timeout=300) == 0, (tmp_path / "rerun.out").read_text(errors="replace")[-3000:]
    finally:
        if rerun.poll() is None:
            os.killpg(rerun.pid, signal.SIGKILL)
            rerun.wait()
    logs = _logged(tmp_path)
    assert len(logs) == COUNT and all(v == list(range(EVALUATIONS)) for v in logs.values()), logs
    assert len(list((tmp_path / "runs").glob("*/exported.json"))) == COUNT
    lines = {run: len(v) for run, v in logs.items()}
    held = re.findall(r"resubmitted in \d+ s from the (\d+) evaluations", first)
    print(f"\nnode 2 killed at {killed_at} records of its task, resubmitted from {held} held by the driver; "
          f"first training: exit {code}, logs {first_logs}; rerun: exit 0, logs {lines}; most tasks at once: {most}")  # fmt: skip
