"""A trajectory from a CSV file flown by the whole stack in lockstep (``arcade demo
--trajectory FILE``): the simulator and the controller (separate processes) fly the same
fitted path, which the controller publishes on ``reference`` and the recorder records, and
the stack tracks it.

The file: a loop of 0.6 m radius flown rest to rest in 4 s (positions only, sampled every
0.1 s), after the take-off and hover of the demo.
"""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np

from arcade.cli import main
from arcade.demo_stack import read_truth
from arcade_control.scenario import planned
from deploy.trajectories import resolve

DURATION_S = 4.0
RADIUS_M = 0.6


def _write_loop(path) -> None:
    t = np.arange(0.0, DURATION_S + 1e-9, 0.1)
    s = t / DURATION_S
    phase = 2 * np.pi * s**4 * (35 - 84 * s + 70 * s**2 - 20 * s**3)  # at rest at both ends
    rows = [
        (ti, RADIUS_M * np.sin(ph), RADIUS_M * (1 - np.cos(ph)), 2.0)
        for ti, ph in zip(t, phase, strict=True)
    ]
    path.write_text("t,px,py,pz\n" + "".join(",".join(f"{v:.6f}" for v in r) + "\n" for r in rows))


def test_csv_trajectory_flies_through_the_lockstep_stack(tmp_path):
    csv = tmp_path / "loop.csv"
    _write_loop(csv)
    out = tmp_path / "run"
    assert main(["demo", "--trajectory", str(csv), "--out", str(out), "--seed", "0"]) == 0

    metrics = json.loads((out / "metrics.json").read_text())
    assert all(code == 0 for code in metrics["exit_codes"].values()), metrics["exit_codes"]
    assert metrics["rejects"] == {} and not metrics["crashed"] and metrics["sim_timeouts"] == 0
    assert metrics["settings"]["trajectory"] == str(csv)
    for log in (out / "logs").glob("*.log"):
        text = log.read_text()
        assert " ERROR " not in text and "Traceback" not in text, log.name

    # The plan: the climb and hover, then the file's 4 s; the flight ends with it.
    scen = planned(trajectory=resolve(str(csv), 2.5))
    truth = read_truth(out / "truth.csv")
    assert truth["t"][-1] == np.float64(round(scen.t_end / 0.05) * 0.05)
    fitted = np.asarray(jax.vmap(scen.path().position)(jnp.asarray(truth["t"])))
    ref = np.stack([truth["ref_px"], truth["ref_py"], truth["ref_pz"]], axis=1)
    assert np.allclose(ref, fitted, atol=1e-4)  # the simulator flew the fitted path
    assert np.ptp(ref[:, 0]) > 1.5 * RADIUS_M  # ... the loop, not a hover

    # The controller's reference, recorded: the same path at the same instants.
    from mcap.reader import make_reader

    with (out / "bus.mcap").open("rb") as f:
        refs = [
            json.loads(m.data)
            for _, ch, m in make_reader(f).iter_messages()
            if ch.topic.endswith("/reference") and "/foxglove/" not in ch.topic
        ]
    assert len(refs) == truth["t"].size
    t_ref = np.array([r["t"] for r in refs])
    p_ref = np.array([r["x"][:3] for r in refs])
    want = np.asarray(jax.vmap(scen.path().position)(jnp.asarray(t_ref)))
    assert np.allclose(p_ref, want, atol=1e-4)

    # The stack tracks it: ground truth against the reference over the trajectory.
    sel = truth["t"] >= scen.t_figure
    p = np.stack([truth["px"], truth["py"], truth["pz"]], axis=1)
    rmse = float(np.sqrt(np.mean(np.sum((p[sel] - ref[sel]) ** 2, axis=1))))
    assert rmse < 0.1, rmse
