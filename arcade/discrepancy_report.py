"""Plots and the human-readable report of the discrepancy workflow (design §6, step 5)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from arcade_io import atomicfile


def write_outputs(out: Path, result: dict[str, Any], details: dict[str, Any]) -> dict[str, Any]:
    """Write plots and ``report.md`` into ``out``; returns their paths for the JSON."""
    plots = write_plots(out, result, details)
    report = out / "report.md"
    atomicfile.write_text(report, render_report(result, plots))
    return {"report": str(report), "plots": [str(p) for p in plots]}


def write_plots(out: Path, result: dict[str, Any], details: dict[str, Any]) -> list[Path]:
    """Before/after bars per component, held-out residual traces, localisation by regime."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    paths = []
    comps = details["components"]
    before = np.array([result["gap_before"][c] for c in comps])
    after = np.array([result["gap_after"][c] for c in comps])
    fig, ax = plt.subplots(figsize=(9, 3.5))
    x = np.arange(len(comps))
    ax.bar(x - 0.2, before, 0.4, label="current model")
    ax.bar(x + 0.2, after, 0.4, label="with named effects")
    ax.set_xticks(x, comps, rotation=45)
    ax.set_yscale("log")
    ax.set_ylabel(f"held-out one-step RMSE ({result['step_s']:.3g} s)")
    ax.set_title(result["summary"], fontsize=9)
    ax.legend()
    fig.tight_layout()
    paths.append(out / "gap_per_component.png")
    atomicfile.save_figure(fig, paths[-1], dpi=110)
    plt.close(fig)

    act = result["heldout_components"]
    t = np.array(details["t"][details["ho"]], dtype=float)
    # Break the lines between held-out blocks.
    gaps = np.flatnonzero(np.diff(t) > 1.5 * np.median(np.diff(t))) + 1
    t = np.insert(t, gaps, np.nan)
    err_b = np.insert(details["err_before"], gaps, np.nan, axis=0)
    err_a = np.insert(details["err_after"], gaps, np.nan, axis=0)
    fig, axes = plt.subplots(
        len(act), 1, figsize=(9, 1.6 * len(act) + 0.6), sharex=True, squeeze=False
    )
    for ax, c in zip(axes[:, 0], act):
        i = comps.index(c)
        ax.plot(t, err_b[:, i], lw=0.6, label="current model")
        ax.plot(t, err_a[:, i], lw=0.6, label="with named effects")
        ax.set_ylabel(c)
    axes[0, 0].legend(loc="upper right", fontsize=7)
    axes[-1, 0].set_xlabel("time [s] (held-out blocks)")
    fig.tight_layout()
    paths.append(out / "heldout_residuals.png")
    atomicfile.save_figure(fig, paths[-1], dpi=110)
    plt.close(fig)

    loc = details["localisation"]
    regimes = list(loc["by_regime"])
    fig, axes = plt.subplots(1, len(regimes), figsize=(3.2 * len(regimes), 3), squeeze=False)
    for ax, name in zip(axes[0], regimes):
        r = loc["by_regime"][name]
        edges = np.asarray(r["edges"])
        mids = 0.5 * (edges[:-1] + edges[1:])
        for c, v in r["rms"].items():
            ax.plot(mids, v, "o-", ms=3, label=c)
        ax.set_xlabel(name)
        ax.set_yscale("log")
    axes[0, 0].set_ylabel("one-step residual / noise level")
    axes[0, -1].legend(fontsize=6)
    fig.tight_layout()
    paths.append(out / "gap_by_regime.png")
    atomicfile.save_figure(fig, paths[-1], dpi=110)
    plt.close(fig)
    return paths


def _fmt(v) -> str:
    if isinstance(v, list):
        return "[" + ", ".join(_fmt(x) for x in v) + "]"
    return f"{v:.4g}"


def format_params(params: dict[str, Any], units: dict[str, str] | None = None) -> str:
    """``name = value`` per parameter, 4 significant digits, each followed by its unit
    from ``units`` where it has one (none for dimensionless ``1``)."""

    def unit(k: str) -> str:
        u = (units or {}).get(k, "1")
        return "" if u == "1" else f" {u}"

    return "; ".join(f"{k} = {_fmt(v)}{unit(k)}" for k, v in params.items())


def added_text(effect: dict[str, Any]) -> str:
    """Whether an effect was added, and why not when the held-out data contradict it."""
    gate = effect.get("heldout")
    if effect["added"]:
        together = (gate or {}).get("with")
        return f"yes, together with {', '.join(together)}" if together else "yes"
    if gate and not gate["confirmed"]:
        return (
            f"no: not confirmed on held-out data ({'+'.join(gate['components'])} "
            f"{gate['before']:.4g} -> {gate['after']:.4g})"
        )
    return "no"


def render_report(result: dict[str, Any], plots: list[Path]) -> str:
    """Markdown report: verdict, effects, gap before/after, where the gap was."""
    lines = [
        f"# Model discrepancy report ({result['system']})",
        "",
        f"**{result['summary']}**",
        "",
        f"Log: {result['samples']} samples; {result['fit_samples']} in the fitted blocks, "
        f"the rest held out. Model step {result['step_s']:.3g} s; "
        f"{result['outlier_windows']} outlier windows left out.",
        "",
    ]
    if result.get("cannot_tell"):
        reach = result["reach"]
        told = ", ".join(f"{n} ({reach[n]:.2f})" for n in result["cannot_tell"])
        lines += [
            "Not enough excitation to tell (how far each effect, at the edge of its "
            f"plausible range, would stand out of the noise; {3**0.5:.2f} is needed): {told}.",
            "",
        ]
    if result["effects"]:
        lines += [
            "## Effects",
            "",
            "| effect | parameters | 90 % interval | confidence | share explained | added |",
            "|---|---|---|---|---|---|",
        ]
        for e in result["effects"]:
            params = format_params(e["params"])
            interval = "; ".join(f"{k} in {_fmt(v)}" for k, v in e["interval"].items()) or "-"
            lines.append(
                f"| {e['name']} | {params} | {interval} | {e['confidence']:.2f} | "
                f"{e['explained']:.2f} | {added_text(e)} |"
            )
        lines.append("")
    else:
        lines += ["No library effect explains the residual better than noise.", ""]
    lines += [
        "## Gap before / after (held-out)",
        "",
        f"One-step RMSE over {', '.join(result['heldout_components'])}: "
        f"{result['heldout_rmse_before']:.4g} -> {result['heldout_rmse_after']:.4g}.",
        "",
        f"| component | one-step RMSE before | after | CRMSE ({result['horizon_s']:.3g} s) "
        "before | after |",
        "|---|---|---|---|---|",
    ]
    for c, b in result["gap_before"].items():
        cb = result["crmse_before"].get(c, float("nan"))
        ca = result["crmse_after"].get(c, float("nan"))
        lines.append(f"| {c} | {b:.4g} | {result['gap_after'][c]:.4g} | {cb:.4g} | {ca:.4g} |")
    loc = result["localisation"]
    lines += ["", "## Where the gap is (current model, fitted part)", ""]
    noise = ", ".join(f"{c} {v:.2f}" for c, v in loc["rms_noise"].items())
    lines.append(f"One-step residual in noise levels (1 = noise only): {noise}.")
    lines.append(f"Largest: {loc['largest']}.")
    for r in loc["regimes"]:
        lines.append(
            f"- {r['component']}: {r['rms_noise']:.2f} x noise ({r['ratio']:.2f} x its mean) "
            f"for {r['regime']} in [{r['bin'][0]:.3g}, {r['bin'][1]:.3g}]"
        )
    lines.append(
        f"- {len(loc['segments'])} time segment(s) (changepoints of Algorithm 1); "
        "the ones with the largest gap:"
    )
    worst_first = sorted(loc["segments"], key=lambda s: -max(s["rms_noise"].values()))
    for s in sorted(worst_first[:6], key=lambda s: s["t_start"]):
        worst = max(s["rms_noise"], key=s["rms_noise"].get)
        lines.append(
            f"  - {s['t_start']:.1f}-{s['t_end']:.1f} s: largest {worst} "
            f"({s['rms_noise'][worst]:.2f} x noise)"
        )
    lines += ["", f"Model file: `{result['model_file']}`", ""]
    lines += [f"![{p.stem}]({p.name})" for p in plots]
    return "\n".join(lines) + "\n"
