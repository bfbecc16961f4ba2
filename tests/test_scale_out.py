"""Data parallelism: the pose-regression training step runs unchanged under torch
DistributedDataParallel (gloo, 2 CPU processes, localhost) and under jax sharding over 2 host devices,
and gives the loss of one process on the same global batch."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

WORKERS = Path(__file__).resolve().parent / "scale_out_workers.py"


def command(*args: str) -> list[str]:
    return [sys.executable, str(WORKERS), *args]


def check(done: subprocess.CompletedProcess[str]) -> None:
    assert done.returncode == 0, done.stderr[-4000:]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_torch_ddp_two_processes_give_the_single_process_loss(tmp_path: Path) -> None:
    import scale_out_workers as w

    out = tmp_path / "ddp.json"
    port = str(free_port())
    ranks = [
        subprocess.Popen(command("torch", str(rank), port, str(out)), stderr=subprocess.PIPE, text=True)
        for rank in range(w.WORLD)
    ]
    # Wait for (and close the pipes of) every rank before asserting: an early failure must not leave a
    # process and its pipe behind for the garbage collector to warn about in a later test.
    errors = []
    for rank in ranks:
        try:
            errors.append(rank.communicate(timeout=300)[1])
        except subprocess.TimeoutExpired:
            rank.kill()
            errors.append(rank.communicate()[1] + "\n(timed out)")
    for rank, stderr in zip(ranks, errors, strict=True):
        assert rank.returncode == 0, stderr[-4000:]
    ddp = json.loads(out.read_text())
    model = w.pr.torch_model(w.CONFIG, w.REPRESENTATION)
    single = w.torch_run(model)
    np.testing.assert_allclose(ddp["losses"], single, rtol=1e-5)
    for theirs, ours in zip(ddp["params"], model.parameters(), strict=True):
        np.testing.assert_allclose(np.asarray(theirs), ours.detach().numpy(), rtol=1e-4, atol=1e-6)
    # The steps changed the model: the comparison is not between two untouched initialisations.
    assert not torch.equal(model[0].weight, w.pr.torch_model(w.CONFIG, w.REPRESENTATION)[0].weight)


def test_jax_sharded_over_two_devices_gives_the_single_device_loss(tmp_path: Path) -> None:
    out = tmp_path / "jax.json"
    env = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    check(subprocess.run(command("jax", str(out)), env=env, capture_output=True, text=True, timeout=300))
    result = json.loads(out.read_text())
    assert result["devices"] == [1, 2]  # the batch really was split over two devices
    np.testing.assert_allclose(result["sharded"], result["single"], rtol=1e-5)
    assert result["max_param_diff"] < 1e-5
    assert len(set(result["single"])) == len(result["single"])  # the loss moved: real steps were taken
