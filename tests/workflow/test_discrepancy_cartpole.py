"""The discrepancy workflow on the cartpole: the paper's true system against its nominal
model (Appendix D), and hidden effects through the command line.

The true system (``simulator.cartpole.CartpoleSim``) has cart friction 0.25, pole
friction 0.05, a N(-0.5, 0.5) force disturbance and M, m, L = 1.0, 0.1, 1.5 against the
nominal 1.7, 0.25, 1.7. It is logged at its 20 Hz for 180 s (3600 samples): the pole
friction is small next to the random force (std 0.71 N), and fewer samples leave its
bootstrap confidence short of 0.9 on some flights.
"""

from __future__ import annotations

import json

import jax
import numpy as np
import pytest

from arcade import cli
from arcade_core.discrepancy import cartpole as cp
from arcade_core.dynamics.params import CARTPOLE_TRUE
from arcade_io.discrepancy import load_cartpole_file, run_workflow
from simulator.cartpole import CartpoleSim
from simulator.log_flights import fly_cartpole


@pytest.fixture(scope="module")
def paper():
    log = fly_cartpole(None, 180.0, seed=3, system=CartpoleSim(seed=1003))
    return run_workflow(log, "cartpole").result


def test_friction_terms_and_force_bias_are_named(paper):
    added = {e["name"]: e for e in paper["effects"] if e["added"]}
    for name in ("cart_viscous_friction", "pole_viscous_friction", "force_bias"):
        assert name in added, paper["summary"]
        assert added[name]["confidence"] >= 0.9
    assert added["cart_viscous_friction"]["params"]["mu_c"] == pytest.approx(
        CARTPOLE_TRUE.mu_c, rel=0.2
    )
    assert added["pole_viscous_friction"]["params"]["mu_p"] == pytest.approx(
        CARTPOLE_TRUE.mu_p, rel=0.2
    )
    assert added["force_bias"]["params"]["mean_n"] == pytest.approx(
        CARTPOLE_TRUE.dist_mean, abs=0.1
    )
    # The other differences of the true system are found too; nothing else is added.
    assert set(added) == {
        "cart_viscous_friction",
        "pole_viscous_friction",
        "force_bias",
        "mass_mismatch",
        "length_mismatch",
    }
    assert added["length_mismatch"]["params"]["pole_length_m"] == pytest.approx(
        CARTPOLE_TRUE.L, rel=0.05
    )


def test_cartpole_gap_shrinks_on_heldout_data(paper):
    assert paper["heldout_components"] == ["xdot", "thetadot"]
    assert paper["heldout_rmse_after"] < 0.5 * paper["heldout_rmse_before"]
    for c in ("xdot", "thetadot"):
        assert paper["gap_after"][c] < 0.6 * paper["gap_before"][c]
        assert paper["crmse_after"][c] < paper["crmse_before"][c]


def test_cartpole_command_line_with_coulomb_friction(tmp_path, capsys):
    effects = tmp_path / "effects.toml"
    effects.write_text(
        "[coulomb_friction]\nforce_n = 1.0\n\n[force_bias]\nmean_n = 0.5\nstd_n = 0.3\n"
    )
    log = tmp_path / "cartpole.csv"
    assert (
        cli.main(
            [
                "simulate",
                "--system",
                "cartpole",
                "--effects",
                str(effects),
                "--duration",
                "90",
                "--seed",
                "4",
                "--out",
                str(log),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        cli.main(
            [
                "discrepancy",
                str(log),
                "--system",
                "cartpole",
                "--json",
                "--out",
                str(tmp_path / "out"),
            ]
        )
        == 0
    )
    result = json.loads(capsys.readouterr().out)
    added = {e["name"]: e["params"] for e in result["effects"] if e["added"]}
    assert set(added) == {"coulomb_friction", "force_bias"}, result["summary"]
    assert added["coulomb_friction"]["force_n"] == pytest.approx(1.0, rel=0.2)
    assert added["force_bias"]["mean_n"] == pytest.approx(0.5, abs=0.1)
    # The model file carries the effects; the JAX model reads them back.
    model_file = load_cartpole_file(result["model_file"])
    model = cp.CartpoleModel(**{k: model_file["cartpole"][k] for k in ("M", "m", "L", "g")})
    theta = cp.theta_from_effects(model, model_file["effects"])
    assert float(theta[2]) == pytest.approx(added["coulomb_friction"]["force_n"])
    assert np.isclose(float(theta[4]), model.M)  # masses untouched


def test_cartpole_log_errors_are_reported(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("t,x,xdot,theta,u\n" + "".join(f"{0.05 * k},0,0,0,0\n" for k in range(30)))
    assert (
        cli.main(
            [
                "discrepancy",
                str(bad),
                "--system",
                "cartpole",
                "--json",
                "--out",
                str(tmp_path / "o"),
            ]
        )
        == 2
    )
    assert "missing column(s) thetadot" in capsys.readouterr().err


def test_the_workflow_runs_in_float64_whatever_the_callers_setting():
    from arcade_io import jaxsetup

    log = fly_cartpole(None, 60.0, seed=5, system=CartpoleSim(seed=1005))
    with jaxsetup.x64(False):
        in_float32_process = run_workflow(log, "cartpole").result
        assert not jax.config.jax_enable_x64  # the caller's setting is restored
    assert json.dumps(in_float32_process, sort_keys=True) == json.dumps(
        run_workflow(log, "cartpole").result, sort_keys=True
    )
