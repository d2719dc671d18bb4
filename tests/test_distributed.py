"""Monte Carlo over several processes (`jax.distributed`) equals one process bit for bit on CPU.

Two local CPU processes on the loopback address, each with one device, run `montecarlo` with
the same arguments; a third, single process runs it alone. The same for the command line's
`jdrkf reproduce --distributed`. Slow tier: three child processes per test, each importing JAX
and compiling (one to three minutes on 2 cores).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import textwrap

import numpy as np
import pytest

CHILD = textwrap.dedent(
    """
    import sys
    import jax
    jax.config.update("jax_enable_x64", True)
    nproc, pid, port, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3], sys.argv[4]
    if nproc > 1:
        jax.distributed.initialize(coordinator_address=f"127.0.0.1:{port}", num_processes=nproc, process_id=pid)
    import jax.numpy as jnp
    import numpy as np
    import jdrkf

    model = jdrkf.LinearModel(F=jnp.array([[0.98, 0.02], [0.0, 0.97]]), H=jnp.array([[1.0, -1.0]]),
                              Q=jnp.eye(2), R=jnp.eye(1))
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    traj = jdrkf.simulate(jax.random.key(0), model, prior, num_steps=30, num_runs=11)
    filters = {
        "KF": jdrkf.KalmanFilter(),
        "DRKF": jdrkf.DRKF(jdrkf.sets.Wasserstein(0.1), jdrkf.sets.Wasserstein(0.1)),
        "HKF": jdrkf.HuberKF(),
    }
    res = jdrkf.montecarlo(filters, model, prior, traj, key=jax.random.key(1), chunk_size=4)
    assert jax.device_count() == nproc, jax.devices()
    np.savez(out, **{f"{f}/{m}": v for f, d in res.items() for m, v in d.items()})
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_two_processes_equal_one_process_bit_for_bit(tmp_path):
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XLA_FLAGS", "JAX_"))}
    port = str(_free_port())
    outs = [tmp_path / f"p{i}.npz" for i in range(2)]
    procs = [subprocess.Popen([sys.executable, str(script), "2", str(i), port, str(outs[i])], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for i in range(2)]
    single = subprocess.run([sys.executable, str(script), "1", "0", "0", str(tmp_path / "single.npz")], env=env,
                            capture_output=True, text=True, timeout=600)
    logs = [p.communicate(timeout=600)[0] for p in procs]
    assert single.returncode == 0, single.stderr[-3000:]
    for p, log in zip(procs, logs):
        assert p.returncode == 0, log[-3000:]
    ref = np.load(tmp_path / "single.npz")
    assert set(ref.files) == {f"{f}/{m}" for f in ("KF", "DRKF", "HKF") for m in ("rmse", "success")}
    for out in outs:  # every process returns all runs
        got = np.load(out)
        assert set(got.files) == set(ref.files)
        for name in ref.files:
            assert got[name].shape == ref[name].shape == (11,), name
            np.testing.assert_array_equal(got[name], ref[name], err_msg=name)
    assert ref["KF/rmse"].std() > 0 and np.all(ref["KF/success"])
    assert not np.array_equal(ref["KF/rmse"], ref["DRKF/rmse"])  # the filters did differ


def _report_lines(text: str) -> str:
    """The CLI's output without its wall time and without the line that JAX's CPU collectives
    (Gloo) print to stdout when they connect."""
    return "\n".join(line for line in text.splitlines() if "wall time" not in line and not line.startswith("[Gloo]"))


@pytest.mark.slow
def test_cli_distributed_equals_one_process_and_only_process_0_reports(tmp_path):
    """`jdrkf reproduce --distributed` in two local processes: process 0 prints and writes the
    report of a plain one-process run (bit for bit, but for the wall time); process 1 neither
    prints nor writes.

    The one-process run gets two CPU devices, so that each device filters the same runs as a
    process of the pair does: XLA's CPU code for a vmapped filter may round differently for
    another number of runs per device (for this experiment, in the last bits of TMKF's
    per-run RMSE with one device of four runs against two of two).
    """
    env = {k: v for k, v in os.environ.items() if not k.startswith(("XLA_FLAGS", "JAX_"))}
    command = [sys.executable, "-m", "jdrkf.cli", "reproduce", "wang-ye-table3", "--quick", "--runs", "4", "--seed", "3",
               "--no-progress"]
    manual = ["--distributed", "--coordinator", f"127.0.0.1:{_free_port()}", "--num-processes", "2", "--process-id"]
    procs = [subprocess.Popen(command + ["--json", str(tmp_path / f"p{i}.json")] + manual + [str(i)], env=env, cwd=tmp_path,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for i in range(2)]
    two_devices = env | {"XLA_FLAGS": "--xla_force_host_platform_device_count=2"}
    single = subprocess.run(command + ["--json", str(tmp_path / "single.json")], env=two_devices, cwd=tmp_path,
                            capture_output=True, text=True, timeout=600)
    outs = [p.communicate(timeout=600) for p in procs]
    assert single.returncode == 0, single.stderr[-3000:]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    assert _report_lines(outs[1][0]) == "" and sorted(f.name for f in tmp_path.iterdir()) == ["p0.json", "single.json"]
    assert "| TMKF | rmse |" in outs[0][0]
    assert _report_lines(outs[0][0]).replace("p0.json", "single.json") == _report_lines(single.stdout)
    got, ref = (json.loads((tmp_path / f).read_text()) for f in ("p0.json", "single.json"))
    assert got["settings"].pop("wall time") and ref["settings"].pop("wall time")
    assert got == ref  # floats written with repr: equal here means bit for bit
    assert ref["rows"][0]["runs"] == 4 and len({r["mean"] for r in ref["rows"]}) > 1
