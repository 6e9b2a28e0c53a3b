"""A two-node Ray cluster on this host for tests/test_cluster.py, in its own process.

Run with the environment the cluster should have (RAY_TMPDIR, RAY_AUTH_MODE/RAY_AUTH_TOKEN,
PYTHONPATH): it starts a head (1 CPU, Ray Client server, dashboard for Ray Jobs) and a worker
(1 CPU) with `ray.cluster_utils.Cluster`, prints one JSON line (addresses and node ids), then
obeys stdin: "remove_worker" kills the worker's raylet (as a lost machine); end of input shuts
the cluster down. A process of its own keeps the test process free of Ray state (its cached
auth mode, its GCS client).
"""

import json
import sys

from ray.cluster_utils import Cluster


def main() -> None:
    client_port, dashboard_port, head_agent_port, worker_agent_port = map(int, sys.argv[1:5])
    # each raylet's dashboard agent needs its own HTTP port (default 52365 for all: the second
    # agent, or another Ray on the host, would fail to bind and Ray Jobs would find no agent)
    c = Cluster(
        initialize_head=True,
        head_node_args={
            "num_cpus": 1,
            "ray_client_server_port": client_port,
            "include_dashboard": True,
            "dashboard_host": "127.0.0.1",
            "dashboard_port": dashboard_port,
            "dashboard_agent_listen_port": head_agent_port,
        },
    )
    worker = c.add_node(num_cpus=1, dashboard_agent_listen_port=worker_agent_port)
    c.wait_for_nodes()
    print(json.dumps({"address": c.address, "head_id": c.head_node.node_id, "worker_id": worker.node_id}), flush=True)
    try:
        for line in sys.stdin:
            if line.strip() == "remove_worker":
                c.remove_node(worker, allow_graceful=False)
                print("removed", flush=True)
    finally:
        c.shutdown()


if __name__ == "__main__":
    main()
