"""`arcade eval cartpole|quadrotor|changepoints` — the paper's tables, all methods in one run,
and the changepoint detection quality of both systems."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from arcade_io import atomicfile, jsonout

HELP = (
    "reproduce the paper's evaluations, all methods in one run (cartpole: Table I, Fig. 3, "
    "App. E and the sensitivity to the readings the paper leaves open, minutes on 2 cores; "
    "quadrotor: Tables II, III, V, Figs. 4-5, ~3 h on 2 cores with the flagship and its "
    "ablations, --methods flies fewer; "
    "changepoints: detection quality on both systems, ~1.5 h, --quick ~10 min)"
)


def add_arguments(p: argparse.ArgumentParser) -> None:
    from arcade_io.runs import count

    p.add_argument(
        "system", choices=["cartpole", "quadrotor", "changepoints"], help="which evaluation"
    )
    p.add_argument("--json", action="store_true", help="print the results as one JSON object")
    p.add_argument(
        "--trials",
        type=count(1),
        default=None,
        help="cartpole: online trajectories; quadrotor and changepoints: trials (seeds) per "
        "cell; at least 1 (default: 10; with --quick 4 for cartpole, 1 for the quadrotor)",
    )
    p.add_argument("--quick", action="store_true", help="small, fast variant (smoke test)")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="folder for figures and results.json, created if needed "
        "(default: $ARCADE_RUNS/<time>-eval-<system>, $ARCADE_RUNS defaulting to runs); "
        "quadrotor: each finished part is kept there as it finishes (progress.jsonl, "
        "removed once results.json is written), and the same command with the same --out "
        "continues an interrupted run",
    )
    p.add_argument("--seed", type=count(0), default=0, help="seed (default: %(default)s)")
    p.add_argument(
        "--condition",
        choices=["ideal", "stack"],
        default="ideal",
        help="quadrotor: ideal (the true state, no setpoint delay: the paper's setting) or "
        "stack (the estimator's state, a 20 ms setpoint delay compensated, as the service "
        "stack flies); every method is tuned and flown in it (default: %(default)s)",
    )
    p.add_argument(
        "--methods",
        type=_method_list,
        default=None,
        metavar="M1,M2,...",
        help="quadrotor: fly only these methods (default: all of them; include l1 for the "
        "paired differences)",
    )
    p.add_argument(
        "--stored-knobs",
        action="store_true",
        help="quadrotor: fly the knobs stored for the condition instead of tuning them (the "
        "stack's own in --condition stack); a shorter run, marked so in results.json",
    )


def _method_list(text: str) -> tuple[str, ...]:
    """argparse ``type=``: a comma-separated list of the quadrotor evaluation's methods."""
    from arcade_control.knobs import EVAL_METHODS

    names = tuple(dict.fromkeys(n.strip() for n in text.split(",") if n.strip()))
    unknown = [n for n in names if n not in EVAL_METHODS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(
            f"{', '.join(unknown) or 'no method'}: methods are {', '.join(EVAL_METHODS)}"
        )
    return names


def run(args: argparse.Namespace) -> int:
    from arcade_io import jaxsetup
    from arcade_io.runs import check_output_dir, check_runs_root, new_run_dir

    only = [f for f, v in (("--methods", args.methods), ("--stored-knobs", args.stored_knobs)) if v]
    if only and args.system != "quadrotor":
        print(f"error: {', '.join(only)}: for the quadrotor evaluation only", file=sys.stderr)
        return 2
    if args.condition != "ideal" and args.system != "quadrotor":
        print(
            f"error: --condition {args.condition} applies to the quadrotor evaluation only",
            file=sys.stderr,
        )
        return 2
    # The output folder is checked before the (long) evaluation starts.
    try:
        if args.out is not None:
            check_output_dir(args.out, "--out")
        else:
            check_runs_root()
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    jaxsetup.configure()
    out = args.out or new_run_dir(f"eval-{args.system}")
    out.mkdir(parents=True, exist_ok=True)
    progress = lambda m: print(f"[eval] {m}", file=sys.stderr, flush=True)  # noqa: E731
    from benchmarks.eval_progress import ProgressMismatch, discard

    if args.system == "quadrotor":
        try:
            result, table = _quadrotor(args, out, progress)
        except ProgressMismatch as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    elif args.system == "changepoints":
        result, table = _changepoints(args, progress)
    else:
        result, table = _cartpole(args, out, progress)
    from benchmarks.common import machine

    result["generated"] = time.strftime("%Y-%m-%d %H:%M")
    result["machine"] = machine()
    atomicfile.write_text(out / "results.json", jsonout.dumps(result, indent=2))
    if args.system == "quadrotor":
        discard(out)  # finished: the parts kept to continue an interrupted run go
    if args.json:
        print(jsonout.dumps(result))
    else:
        print(table)
        print(f"figures and results.json in {out}")
    return 0


def _cartpole(args, out, progress):
    from benchmarks import cartpole_eval as ce

    s = ce.EvalSettings.quick() if args.quick else ce.EvalSettings()
    overrides = {"seed": args.seed}
    if args.trials is not None:
        overrides["trials"] = args.trials
    s = type(s)(**{**s.__dict__, **overrides})
    result = ce.evaluate(s, out, progress=progress)
    return result, ce.format_table(result)


def _quadrotor(args, out, progress):
    from benchmarks import quadrotor_ablations as qa
    from benchmarks import quadrotor_closedloop as qc
    from benchmarks import quadrotor_openloop as qo
    from benchmarks.quadrotor_protocol import stored_knobs

    models = qo.prepare_models(args.quick, args.seed, progress, None)
    trials = args.trials if args.trials is not None else (1 if args.quick else 10)
    if args.stored_knobs:
        models.closedloop = stored_knobs(args.condition)
    result = qc.run_closedloop(
        quick=args.quick,
        trials=trials,
        methods=args.methods,
        out=out,
        progress=progress,
        models=models,
        seed=args.seed,
        condition_name=args.condition,
        tuning=False if args.stored_knobs else None,
        keep=out,
    )
    result["settings"]["knobs"] = "stored" if args.stored_knobs or args.quick else "tuned"
    if args.condition != "ideal" or args.methods is not None:
        # The open-loop tables and the ablations are the paper's, with every method.
        return result, qc.format_table(result)
    progress("open-loop prediction (Table II) and Gramian diagnostics (Fig. 4)")
    result["openloop"] = qo.run_openloop(
        quick=args.quick, seed=args.seed, progress=progress, models=models, out=out
    )
    if not args.quick:
        progress("beam ablation (Table V)")
        result["beam_ablation"] = qa.run_beam_ablation(models=models, progress=progress)
        progress("residual held along the warm start vs inside the rollout")
        result["residual_ablation"] = qa.run_residual_ablation(models=models, progress=progress)
    return result, qc.format_table(result)


def _changepoints(args, progress):
    from benchmarks import changepoints as qcp
    from benchmarks import changepoints_ablation as cab
    from benchmarks import changepoints_cartpole as ccp

    trials = args.trials if args.trials is not None else (1 if args.quick else 10)
    progress(
        "quadrotor: flights as the stack flies them: the flagship's own events, the detector "
        "replayed on ours' flights"
    )
    quad, flown = qcp.run_changepoints(quick=args.quick, trials=trials, progress=progress)
    progress("forgetting ablation: the learners replayed on the same flights")
    ablation = cab.run_ablation(detector=quad["detector"], progress=progress, **flown)
    progress("cartpole: the declaration rule on the evaluation's online trajectories")
    cart = ccp.cartpole_detection(quick=args.quick, progress=progress)
    result = {"quadrotor": quad, "cartpole": cart, "forgetting_ablation": ablation}
    return result, "\n".join([qcp.format_table(result), *cab.format_table(ablation)])
