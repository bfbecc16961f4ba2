"""Workers for ``test_scale_out.py``, run in subprocesses: the pose-regression training step under
torch DistributedDataParallel (gloo, 2 processes, localhost) and under jax sharding over 2 host devices.

    python tests/scale_out_workers.py torch RANK PORT OUT.json     (one process per rank)
    XLA_FLAGS=--xla_force_host_platform_device_count=2 python tests/scale_out_workers.py jax OUT.json
"""

from __future__ import annotations

import json
import os
import sys
from dataclasses import replace
from datetime import timedelta
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "notebooks"))

import pose_regression as pr

CONFIG = replace(pr.SMALL, hidden=16, batch=16)
REPRESENTATION = "9d"  # the SVD head: the heaviest backward pass of the set
STEPS = 3
WORLD = 2


def global_batches() -> list[tuple[np.ndarray, np.ndarray]]:
    """The same global batches for every run: STEPS of them, ``CONFIG.batch`` samples each."""
    rng, cloud = np.random.default_rng(7), pr.point_cloud(CONFIG)
    return [pr.make_batch(CONFIG, CONFIG.batch, rng, cloud) for _ in range(STEPS)]


def torch_run(model: Any, rank: int = 0, world: int = 1) -> list[float]:
    """The unchanged training step on this process's share of every global batch. Returns the global
    loss per step: the mean of the processes' losses (equal shares, so the mean over the batch)."""
    import torch
    import torch.distributed as dist

    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    share = CONFIG.batch // world
    losses = []
    for features, rotations in global_batches():
        rows = slice(rank * share, (rank + 1) * share)
        loss = pr.torch_train_step(
            model, optimizer, torch.from_numpy(features[rows]), torch.from_numpy(rotations[rows])
        )
        if world > 1:
            dist.all_reduce(loss)
            loss = loss / world
        losses.append(float(loss))
    return losses


def ddp_process(rank: int, port: int, out: str) -> None:
    import torch
    import torch.distributed as dist
    from torch.nn.parallel import DistributedDataParallel

    torch.set_num_threads(1)
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    # A rank that fails must not leave the other waiting forever.
    dist.init_process_group("gloo", rank=rank, world_size=WORLD, timeout=timedelta(seconds=120))
    try:
        model = DistributedDataParallel(pr.torch_model(CONFIG, REPRESENTATION))
        losses = torch_run(model, rank, WORLD)
        if rank == 0:
            params = [p.detach().numpy().tolist() for p in model.module.parameters()]
            Path(out).write_text(json.dumps({"losses": losses, "params": params}))
    finally:
        dist.destroy_process_group()


def jax_main(out: str) -> None:
    import jax
    import optax
    from jax.sharding import Mesh, NamedSharding, PartitionSpec

    devices = jax.devices()
    assert len(devices) == WORLD, devices
    optimizer = optax.adam(1e-2)
    step = pr.make_jax_train_step(REPRESENTATION, optimizer)
    params = pr.jax_init(CONFIG, REPRESENTATION, jax.random.key(0))

    def run(place_batch: Any, place_state: Any) -> tuple[list[float], Any, int]:
        p = place_state(params)
        state = place_state(optimizer.init(params))
        losses, n_devices = [], 0
        for features, rotations in global_batches():
            f, r = place_batch(features), place_batch(rotations)
            n_devices = len(f.sharding.device_set)
            p, state, loss = step(p, state, f, r)
            losses.append(float(loss))
        return losses, p, n_devices

    one = lambda x: jax.device_put(x, devices[0])  # noqa: E731
    single_losses, single_params, single_devices = run(one, one)
    mesh = Mesh(np.array(devices), ("data",))
    by_rows = NamedSharding(mesh, PartitionSpec("data"))
    replicated = NamedSharding(mesh, PartitionSpec())
    sharded_losses, sharded_params, sharded_devices = run(
        lambda x: jax.device_put(x, by_rows), lambda tree: jax.device_put(tree, replicated)
    )
    diff = jax.tree.reduce(
        max,
        jax.tree.map(
            lambda a, b: float(np.max(np.abs(np.asarray(a) - np.asarray(b)))), single_params, sharded_params
        ),
    )
    Path(out).write_text(
        json.dumps(
            {
                "single": single_losses,
                "sharded": sharded_losses,
                "devices": [single_devices, sharded_devices],
                "max_param_diff": diff,
            }
        )
    )


if __name__ == "__main__":
    if sys.argv[1] == "torch":
        ddp_process(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])
    else:
        jax_main(sys.argv[2])
