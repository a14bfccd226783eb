"""``bbcity demo``: the default street from synthesis to evaluation, with each step's cost
(what ``make demo`` runs; the steps are :func:`bbcity.demo.demo_steps`)."""

from __future__ import annotations

from pathlib import Path

from ..demo import cost_table, demo_steps, run_steps


def add(sub) -> None:
    """The ``demo`` command on the subcommands ``sub``."""
    p = sub.add_parser(
        "demo", help="synthesise, reconstruct, build, render, export and evaluate the default street",
        description="""Run the demo's commands one after another, each printed before it runs and its cost (wall
                       and CPU seconds, peak memory) after: synth street, recon, build (every 10th frame held
                       out), a 300-frame fly-through, the web site and eval. A step that fails stops the demo with
                       its exit code; running the demo again resumes what the steps resume. The costs are written
                       to OUT/demo_report.json.""")
    p.add_argument("--out", type=Path, required=True, help="the demo's directory (street/, work/, model/, …)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    costs = run_steps(demo_steps(out), out, profile=args.profile)
    if costs and costs[-1].exit_code != 0:
        return costs[-1].exit_code
    print("\n" + cost_table(costs))
    looks = [(str(out / "flythrough.mp4"), "the fly-through along the capture path"),
             (str(out / "eval" / "eval.md"), "held-out views against ground truth, with side-by-side images"),
             (f"bbcity view {out / 'model'}", "walk the model (a window; --window offscreen without a display)"),
             (f"bbcity serve {out / 'site'}", "the web viewer at http://127.0.0.1:8000/")]
    width = max(len(a) for a, _ in looks)
    print("Where to look:\n" + "\n".join(f"  {a:<{width}}  {b}" for a, b in looks))
    return 0
