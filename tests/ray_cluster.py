"""A real multi-node Ray cluster on this machine (loopback only), in a process of its own.

``python -m tests.ray_cluster --nodes 2 --cpus 1`` starts a head node and ``nodes - 1`` worker nodes
(``ray.cluster_utils.Cluster``: separate GCS/raylet processes per node, like ``ray start`` on separate
machines) whose servers all bind to 127.0.0.1, prints one JSON line ``{"address", "nodes": [node ids]}``
and then obeys lines on stdin: ``kill I`` removes node ``I`` at once (its raylet and workers are
killed, as when a machine dies) and answers ``killed I``; ``quit`` (or end of input) shuts the
cluster down.

:class:`LocalCluster` runs that process for a test or a benchmark. Its own process keeps Ray's
global state (token mode, temp dirs) out of the caller's, and its environment is the cluster's:

* ``HOME`` is a temporary folder whose ``.ray/auth_token`` holds a fresh token and ``RAY_AUTH_MODE=token``
  is set for the nodes only (a token-authenticated cluster, as a plain ``ray start --head`` of Ray 2.60
  gives when a token exists): a driver must find the token itself (:meth:`LocalCluster.driver_env`);
* ``RAY_TMPDIR`` is private, so no other Ray on the machine finds this one as "the local cluster";
* ``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` keeps Ray from replacing 127.0.0.1 with the machine's
  network address (Ray's servers bind to the node's address).
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _serve(nodes: int, cpus: float) -> None:
    from ray.cluster_utils import Cluster

    common = {"node_ip_address": "127.0.0.1", "num_cpus": cpus, "object_store_memory": 80 * 1024 * 1024}
    cluster = Cluster(initialize_head=True, head_node_args={**common, "include_dashboard": False})
    handles = [cluster.head_node] + [cluster.add_node(**common) for _ in range(nodes - 1)]
    cluster.wait_for_nodes()
    print(json.dumps({"address": cluster.address, "nodes": [n.node_id for n in handles]}), flush=True)
    try:
        for line in sys.stdin:
            cmd = line.split()
            if cmd[:1] == ["kill"]:
                i = int(cmd[1])
                cluster.remove_node(handles[i], allow_graceful=False)
                print(f"killed {i}", flush=True)
            elif cmd[:1] == ["quit"]:
                break
    finally:
        cluster.shutdown()


class LocalCluster:
    """``with LocalCluster(2) as c:`` a cluster of ``nodes`` x ``cpus`` at ``c.address``; ``c.kill(i)``.

    ``auth=False``: a cluster without token authentication (``RAY_AUTH_MODE=disabled`` on its nodes)."""

    def __init__(self, nodes: int = 2, cpus: float = 1, auth: bool = True):
        self.tmp = Path(tempfile.mkdtemp(prefix="r19c", dir="/tmp"))   # short: Ray's socket paths
        self.home = self.tmp / "home"
        (self.home / ".ray").mkdir(parents=True)
        self.token = secrets.token_hex(32)
        (self.home / ".ray" / "auth_token").write_text(self.token)
        env = self.base_env()
        env["RAY_AUTH_MODE"] = "token" if auth else "disabled"
        self.proc = subprocess.Popen([sys.executable, "-m", "tests.ray_cluster", "--nodes", str(nodes),
                                      "--cpus", str(cpus)], cwd=ROOT, env=env, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=open(self.tmp / "cluster.log", "wb"),  # noqa: SIM115
                                     text=True, start_new_session=True)
        line = self.proc.stdout.readline()
        if not line:
            self.close()
            raise RuntimeError(f"the test cluster did not start: {(self.tmp / 'cluster.log').read_text()[-2000:]}")
        info = json.loads(line)
        self.address: str = info["address"]
        self.node_ids: list[str] = info["nodes"]

    def base_env(self) -> dict:
        env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_")}
        env.update(HOME=str(self.home), RAY_TMPDIR=str(self.tmp), RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER="0",
                   PYTHONPATH=os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH")) if p))
        return env

    def driver_env(self) -> dict:
        """The environment of a driver on this machine: the token in ``~/.ray/auth_token``, no ``RAY_AUTH_MODE``."""
        return self.base_env()

    def kill(self, i: int) -> None:
        self.proc.stdin.write(f"kill {i}\n")
        self.proc.stdin.flush()
        answer = self.proc.stdout.readline().strip()
        if answer != f"killed {i}":
            raise RuntimeError(f"could not kill node {i}: {answer!r}")

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.close()
                self.proc.wait(timeout=60)
            except (OSError, subprocess.TimeoutExpired):
                os.killpg(self.proc.pid, signal.SIGKILL)   # the cluster's own process group (started above)
                self.proc.wait()
        shutil.rmtree(self.tmp, ignore_errors=True)

    def __enter__(self) -> LocalCluster:  # noqa: PYI034
        return self

    def __exit__(self, *exc) -> None:
        self.close()


if __name__ == "__main__":
    ap = argparse.ArgumentParser()
    ap.add_argument("--nodes", type=int, default=2)
    ap.add_argument("--cpus", type=float, default=1)
    a = ap.parse_args()
    _serve(a.nodes, a.cpus)
