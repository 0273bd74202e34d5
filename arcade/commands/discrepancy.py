"""`arcade discrepancy LOG` — where do model and data disagree, and which effect is missing.

The workflow of design §6 (:mod:`arcade_core.discrepancy.workflow`: align, localise, name,
add, show) on one flight log (CSV with the columns of :mod:`arcade_io.flightlog`, any
constant rate; inputs a zero-order hold per row; or a PX4 ULog, converted in memory as
`arcade log convert` does: :mod:`arcade.commands.log`) against the current model, the
vehicle or model file (nominal model, motors, rate loop and the file's ``[effects]``). Options, the
log and the file are checked before a run folder is made; then :func:`run_workflow` runs
the workflow (:func:`arcade_io.discrepancy.run_workflow`) and writes into ``--out`` the
updated vehicle/model file (the confident effects added to its ``[effects]`` table), plots,
``report.md`` (:mod:`arcade.discrepancy_report`) and ``result.json``, which ``--json``
prints.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from arcade.commands.log import add_ulog_options
from arcade_core.discrepancy.settings import HELDOUT_RANGE, LogTooShort, Settings, check_log
from arcade_io import atomicfile, jsonout

HELP = "find where a flight log and the model disagree, name the missing effect, show the fix"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.flightlog import columns
    from arcade_io.runs import count, number

    p.formatter_class = argparse.RawDescriptionHelpFormatter
    p.epilog = (
        "flight log columns (CSV with a header row, one row per sample at a constant rate,\n"
        "SI units, world ENU, body FLU; extra columns are ignored; see arcade_io.flightlog):\n"
        f"  quadrotor: {', '.join(columns('quadrotor'))}\n"
        "      (u0 collective thrust [N], u1-u3 body-rate setpoints [rad/s], each in effect\n"
        "      from its row's t to the next row's)\n"
        f"  cartpole:  {', '.join(columns('cartpole'))}  (u: force on the cart [N])\n"
        "`arcade simulate --out LOG` writes such a log.\n"
        "A PX4 flight log (ULog, .ulg) is converted in memory as `arcade log convert` does\n"
        "(see its --help): give the vehicle's mass with --mass or --vehicle."
    )
    p.add_argument(
        "log", type=Path,
        help="flight log (CSV: the columns are listed below; or a PX4 ULog, .ulg)",
    )  # fmt: skip
    p.add_argument(
        "--system",
        choices=["quadrotor", "cartpole"],
        default="quadrotor",
        help="the system that flew the log (default: %(default)s)",
    )
    p.add_argument(
        "--vehicle", type=Path, default=None,
        help="vehicle file (quadrotor) or cartpole model file; default the shipped one",
    )  # fmt: skip
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="output folder, created if needed (default: runs/<time>-discrepancy-<system>)",
    )
    s = Settings()
    lo, hi = HELDOUT_RANGE
    p.add_argument(
        "--step",
        type=number(0.0, s.heldout_block_s, low_open=True, high_open=True),
        default=s.step_s,
        help=f"model step [s], more than 0 and less than {s.heldout_block_s:g} (the held-out "
        "block), rounded to whole log samples (default: %(default)s)",
    )
    p.add_argument(
        "--heldout",
        type=number(lo, hi),
        default=s.heldout,
        help=f"held-out fraction of the log, {lo:g} to {hi:g} (default: %(default)s)",
    )
    p.add_argument(
        "--horizon",
        type=number(0.0, s.heldout_block_s, low_open=True, high_open=True),
        default=s.horizon_s,
        help=f"CRMSE horizon [s], more than 0 and less than {s.heldout_block_s:g} (the "
        "held-out block) (default: %(default)s)",
    )
    p.add_argument(
        "--confidence",
        type=number(0.5, 1.0),
        default=s.confidence,
        help="bootstrap confidence an effect needs to be added to the model file, 0.5 to 1 "
        "(default: %(default)s)",
    )
    p.add_argument(
        "--bootstrap",
        type=count(10),
        default=s.n_boot,
        help="bootstrap resamples, at least 10 (default: %(default)s)",
    )
    p.add_argument(
        "--seed", type=count(0), default=s.seed, help="bootstrap seed (default: %(default)s)"
    )
    add_ulog_options(p, vehicle=False, defaults=False)


def _log_system(path: Path) -> str | None:
    """The system whose columns the header of the CSV at ``path`` has (``None``: neither)."""
    import csv

    from arcade_io.flightlog import columns

    try:
        with path.open(newline="") as f:
            header = next((r for r in csv.reader(f) if any(c.strip() for c in r)), [])
    except (OSError, UnicodeDecodeError, csv.Error):
        return None
    names = {h.strip() for h in header}
    found = [s for s in ("quadrotor", "cartpole") if set(columns(s)) <= names]
    return found[0] if len(found) == 1 else None


def effect_line(effect: dict[str, Any]) -> str:
    """One identified effect of the result as text: name, parameters with units (as in
    report.md), confidence, and whether it was added to the model file."""
    from arcade.discrepancy_report import added_text, format_params
    from arcade_core.discrepancy.catalog import EFFECTS

    units = {k: p.unit for k, p in EFFECTS[effect["name"]].params.items()}
    why = "" if effect["added"] else " (" + added_text(effect).replace("no", "not added", 1) + ")"
    return (
        f"{effect['name']}: {format_params(effect['params'], units)}, confidence "
        f"{effect['confidence']:.2f}{why}"
    )


def run_workflow(
    log, system: str, vehicle: Path | None, out: Path, settings: Settings, progress=None,
    log_import: dict[str, Any] | None = None,
):  # fmt: skip
    """The workflow on ``log`` with its outputs in the folder ``out`` (created if needed):
    the updated vehicle/model file, plots, ``report.md`` and ``result.json``. Returns the
    :class:`~arcade_core.discrepancy.workflow.Outcome`, its result naming those files
    (and, for a converted PX4 log, ``log_import``: what the conversion did)."""
    # Imported here, not at start-up: JAX and matplotlib are slow to import.
    from arcade.discrepancy_report import write_outputs
    from arcade_io import discrepancy

    outcome = discrepancy.run_workflow(log, system, vehicle, settings, progress)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    result = outcome.result
    if log_import is not None:
        result["log_import"] = log_import
    model_file = discrepancy.write_model_file(out, system, vehicle, outcome.model_effects)
    result["model_file"] = str(model_file)
    result.update(write_outputs(out, result, outcome.details))
    atomicfile.write_text(out / "result.json", jsonout.dumps(result, indent=2))
    return outcome


def _not_enough_data(
    args: argparse.Namespace, samples: int, reason: str, log_import: dict[str, Any] | None
) -> int:
    """The answer for a log too short to tell anything: "not enough excitation to tell",
    nothing named or added, no held-out numbers (there are no windows to hold out); the
    same ``result.json`` keys as a full run where they apply, and ``report.md``."""
    from arcade_io.runs import new_run_dir

    out = Path(args.out or new_run_dir(f"discrepancy-{args.system}"))
    out.mkdir(parents=True, exist_ok=True)
    summary = f"not enough excitation to tell: {reason}"
    result: dict[str, Any] = {
        "system": args.system,
        "summary": summary,
        "no_confident_effect": True,
        "not_enough_excitation": True,
        "too_short": reason,
        "effects": [],
        "heldout_rmse_before": None,
        "heldout_rmse_after": None,
        "heldout_components": [],
        "samples": samples,
        "model_file": None,
    }
    if log_import is not None:
        result["log_import"] = log_import
    report = out / "report.md"
    atomicfile.write_text(
        report, f"# Discrepancy: {args.log}\n\n{summary}.\n\nNo effect named or added.\n"
    )
    result["report"] = str(report)
    atomicfile.write_text(out / "result.json", jsonout.dumps(result, indent=2))
    if args.json:
        print(jsonout.dumps(result))
    else:
        print(summary)
        print(f"no model file written (nothing to add); report in {out}")
    return 0


def run(args: argparse.Namespace) -> int:
    from arcade.commands.log import is_ulog, read_ulog_args, ulog_options_given, ulog_summary
    from arcade_io.discrepancy import check_model_file
    from arcade_io.flightlog import LogError, read_log
    from arcade_io.resample import DEFAULT_MIN_AIRBORNE_S
    from arcade_io.runs import check_output_dir, check_runs_root, new_run_dir

    settings = Settings(
        step_s=args.step, heldout=args.heldout, horizon_s=args.horizon,
        confidence=args.confidence, n_boot=args.bootstrap, seed=args.seed,
    )  # fmt: skip
    # Everything is checked before the run folder is made and the work starts.
    try:
        if args.out is not None:
            check_output_dir(args.out, "--out")
        else:
            check_runs_root()
        check_model_file(args.system, args.vehicle)
        if args.log.is_dir():
            raise ValueError(f"flight log {args.log} is a directory, not a CSV file")
        log_import, too_short = None, None
        if is_ulog(args.log):
            if args.system != "quadrotor":
                raise ValueError(f"{args.log}: a PX4 ULog is a quadrotor log, not {args.system}")
            # Any airborne stretch is read; a short one is an answer, not an error.
            log_import = read_ulog_args(args, args.log, min_airborne_s=0.0)
            log = log_import.log
            need = DEFAULT_MIN_AIRBORNE_S if args.min_airborne_s is None else args.min_airborne_s
            airborne = log_import.meta["duration_s"]
            if airborne < need:
                too_short = (
                    f"the longest usable airborne stretch is {airborne:.1f} s, less than the "
                    f"{need:g} s the workflow needs to tell effects apart (--min-airborne-s)"
                )
        else:
            given = ulog_options_given(args)
            if given:
                raise ValueError(f"{', '.join(given)}: for a PX4 ULog (.ulg) only")
            try:
                log = read_log(args.log, args.system)
            except LogError:
                other = _log_system(args.log)
                if other is not None and other != args.system:
                    raise LogError(
                        f"{args.log}: this looks like a {other} log: pass --system {other}"
                    ) from None
                raise
        try:
            check_log(args.system, len(log), log.dt, settings)
        except LogTooShort as exc:
            too_short = too_short or str(exc)
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if too_short is not None:
        meta = None if log_import is None else log_import.meta
        return _not_enough_data(args, len(log), too_short, meta)

    from arcade_io import jaxsetup

    jaxsetup.configure(x64=True)
    out = args.out or new_run_dir(f"discrepancy-{args.system}")

    def progress(msg: str) -> None:
        print(f"[discrepancy] {msg}", file=sys.stderr, flush=True)

    if log_import is not None:
        from arcade_io.ulog import import_mass
        from arcade_io.vehicle import DEFAULT_VEHICLE

        for line in ulog_summary(log_import.meta):
            progress(f"{args.log}: {line}")
        model_mass = import_mass(None, args.vehicle or DEFAULT_VEHICLE)[0]
        if abs(log_import.meta["thrust_conversion"]["mass_kg"] - model_mass) > 0.01 * model_mass:
            progress(
                f"warning: the thrust is scaled to {args.mass:g} kg, the model's mass is "
                f"{model_mass:g} kg: the difference reads as a thrust_scale effect"
            )
    try:
        outcome = run_workflow(
            log, args.system, args.vehicle, out, settings, progress,
            log_import=None if log_import is None else log_import.meta,
        )  # fmt: skip
    except (ValueError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    result = outcome.result
    if args.json:
        print(jsonout.dumps(result))
    else:
        print(result["summary"])
        for e in result["effects"]:
            print(f"  {effect_line(e)}")
        print(
            f"held-out one-step RMSE on {', '.join(result['heldout_components'])}: "
            f"{result['heldout_rmse_before']:.4g} -> {result['heldout_rmse_after']:.4g}"
        )
        print(f"model file: {result['model_file']}; report in {out}")
    return 0
