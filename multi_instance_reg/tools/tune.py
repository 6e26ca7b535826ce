"""``mireg tune``: search the node's parameters on a labelled BOP set with Optuna, trials on Ray.

    mireg tune DATASET -o OUT --param NAME[=LO:HI] [--param ...] [--trials 20] [--split test]
               [--scenes 1,2] [--holdout-scenes 3] [--images 0,5] [--all-images] [--objects 1,2]
               [--model ID=MODEL.npz ...] [--params BASE.yaml] [--tracking] [--objective mhf1|ar]
               [--max-cpu-ms MS] [--storage URL] [--study NAME] [--seed 0]
               [--workers N] [--address ADDR] [--retries N]

Each trial runs the tuning images (``--scenes``/``--images``) through ``mireg bop run``'s
code with the base settings (``--params``, else the defaults) and the trial's values of the
``--param``s, and is scored by the objective (BOP AR, or MHF1 at 10 deg / 2 cm) and the CPU
time per image. The first trial of a new study is the base settings. The study lives in
``--storage`` (default ``sqlite:///OUT/study.db``): a rerun with the same command and a larger
``--trials`` goes on where it stopped; ``optuna`` reads it too. The chosen trial is the
most accurate within ``--max-cpu-ms``. The held-out images (``--holdout-scenes``), never
seen by the search, are scored afterwards with the base settings and the chosen ones.

Writes OUT/params.yaml (config/params.yaml's layout with the chosen values: the node and
``--params`` of the tools load it as is), OUT/report.md (both figures on both sets, the
Pareto front, the parameters that mattered), OUT/front.png and OUT/tune.json.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

from ..errors import InputError

HELP = "search parameters on a labelled BOP set (Optuna, trials on Ray): params.yaml and a report"


def add_arguments(parser) -> None:
    from ..distributed.ray_runner import add_ray_arguments
    from ..distributed.tune import OBJECTIVES

    parser.add_argument("dataset", help="BOP dataset folder with ground truth (camera.json, models/, the splits)")
    parser.add_argument("-o", "--output", required=True, help="output folder (params.yaml, report.md, front.png, study.db)")
    parser.add_argument("--param", action="append", metavar="NAME[=LO:HI]",
                        help="a pipeline or tracking parameter to search (docs/parameters.md), over its declared range "
                             "or LO:HI within it; give it again for more")
    parser.add_argument("--trials", type=int, default=20,
                        help="trials the study should hold when done (a rerun adds the missing ones; default 20)")
    parser.add_argument("--split", default="test", help="split folder (default test)")
    parser.add_argument("--scenes", default=None, metavar="1,2", help="scenes the search runs on (default: all but the held-out)")
    parser.add_argument("--holdout-scenes", default=None, metavar="3",
                        help="scenes scored only after the search, with the base and the chosen settings (default none)")
    parser.add_argument("--images", default=None, metavar="0,5", help="image ids to use, in every chosen scene (default all)")
    parser.add_argument("--all-images", action="store_true", help="every image, not only those the targets file names")
    parser.add_argument("--objects", default=None, metavar="1,2", help="object ids to look for (as bop run)")
    parser.add_argument("--model", action="append", metavar="ID=MODEL.npz", help="a BOP object's model file (as bop run)")
    parser.add_argument("--params", default=None, help="base parameter YAML (the node's layout); the search starts from it")
    parser.add_argument("--tracking", action="store_true", help="each scene's images in order through the tracker (as bop run)")
    parser.add_argument("--objective", choices=tuple(OBJECTIVES), default="mhf1",
                        help="accuracy to raise: mhf1 (MHF1 at 10 deg / 2 cm, default) or ar (BOP AR of VSD, MSSD, MSPD)")
    parser.add_argument("--max-cpu-ms", type=float, default=None, metavar="MS",
                        help="latency bound: choose the most accurate trial whose CPU time per image is at most this")
    parser.add_argument("--storage", default=None, help="Optuna storage URL (default sqlite:///OUT/study.db)")
    parser.add_argument("--study", default="mireg", help="study name in the storage (default mireg)")
    parser.add_argument("--seed", type=int, default=0, help="the sampler's seed (default 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_ray_arguments(parser, "trials")


def _study(args, space, pairs, objective_key, storage_url):
    """The study, new or resumed; a stored study searching something else is refused."""
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    sampler = optuna.samplers.TPESampler(seed=args.seed, n_startup_trials=max(4, args.trials // 3))
    try:
        study = optuna.create_study(study_name=args.study, storage=storage_url, sampler=sampler,
                                    directions=["maximize", "minimize"], load_if_exists=True)
    except (ValueError, ImportError) as exc:
        raise InputError(f"--storage {storage_url}: {str(exc).splitlines()[0]}") from None
    setup = {"space": [p.describe() for p in space], "objective": objective_key,
             "dataset": str(Path(args.dataset).resolve()), "split": args.split, "pairs": [list(p) for p in pairs],
             "params": args.params and str(Path(args.params).resolve()), "tracking": bool(args.tracking)}
    before = study.user_attrs.get("setup")
    if before is None:
        study.set_user_attr("setup", setup)
        study.enqueue_trial({p.name: p.default for p in space})       # the base settings: trial 0
    elif before != setup:
        differ = sorted(k for k in setup if before.get(k) != setup[k])
        raise InputError(f"study '{args.study}' in {storage_url} searched something else (differing: {', '.join(differ)}); "
                         f"give another --study name or --storage")
    # Trials left running by a run that was stopped will never end: mark them failed.
    for t in study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.RUNNING,)):
        study._storage.set_trial_state_values(t._trial_id, state=optuna.trial.TrialState.FAIL)
    return study


def run(args) -> int:
    import cv2
    import optuna

    from ..datasets.bop import BopDataset
    from ..distributed.ray_runner import connect, run_tasks, wants_ray
    from ..progress import Progress
    from ..distributed.tune import (OBJECTIVES, TrialWorker, choose, draw_front, importances, pareto_front,
                                    search_space)
    from ..params import read_params_yaml
    from ..ros.parameters import default_params_yaml
    from .bop import chosen_objects, load_bop_models, parse_ids, parse_model_args
    from .offline import load_config, load_tracker_config

    wants_ray(args)      # checks --workers / --retries; trials always run on Ray (a local one without --address)
    if args.trials < 1:
        raise InputError(f"--trials must be at least 1, got {args.trials}")
    out_dir = Path(args.output)
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"output {out_dir} exists and is not a folder")
    base = read_params_yaml(args.params) if args.params else {}
    load_config(base), load_tracker_config(base)         # a bad base file fails here, with its reason
    space = search_space(args.param, base)
    ds = BopDataset(args.dataset, args.split)
    images = parse_ids(args.images, "images")
    holdout_scenes = parse_ids(args.holdout_scenes, "holdout-scenes") or []
    scenes = parse_ids(args.scenes, "scenes") or [s for s in ds.scene_ids if s not in holdout_scenes]
    if set(scenes) & set(holdout_scenes):
        raise InputError(f"--scenes and --holdout-scenes share scene(s) {sorted(set(scenes) & set(holdout_scenes))}: "
                         f"held-out images must not be searched on")
    pairs = ds.images(scenes, images, not args.all_images)
    holdout = ds.images(holdout_scenes, images, not args.all_images) if holdout_scenes else []
    if not pairs:
        raise InputError(f"no image of {ds.split_dir} is left to search on (scenes {scenes}); check --scenes/--images")
    given = parse_model_args(args.model)
    obj_ids = chosen_objects(ds, pairs + holdout, parse_ids(args.objects, "objects"), given)
    out_dir.mkdir(parents=True, exist_ok=True)
    storage_url = args.storage or f"sqlite:///{(out_dir / 'study.db').resolve()}"
    key = OBJECTIVES[args.objective]
    study = _study(args, space, pairs, key, storage_url)
    complete = [t for t in study.get_trials(deepcopy=False) if t.state == optuna.trial.TrialState.COMPLETE]
    missing = max(0, args.trials - len(complete))
    models = load_bop_models(ds, obj_ids, given, out_dir / "models")
    worker_args = (str(ds.root), ds.split, models, obj_ids, base, bool(args.tracking))
    workers = connect(args.address, args.workers)
    asked: dict[int, object] = {}

    def trial_tasks():
        for _ in range(missing):
            trial = study.ask()
            asked[trial.number] = trial
            yield {"number": trial.number, "values": {p.name: p.suggest(trial) for p in space}, "pairs": pairs}

    def told(task, result):
        trial = asked.pop(task["number"])
        for name, value in result.items():
            trial.set_user_attr(name, value)
        study.tell(trial, [result[key], result["cpu_ms"]])

    if missing:
        print(f"mireg tune: {len(complete)} trial(s) in study '{args.study}' ({storage_url}); running {missing} more "
              f"on {min(workers, missing)} Ray worker(s), {len(pairs)} image(s) each: "
              f"{'; '.join(p.describe() for p in space)}", file=sys.stderr)
    bar = Progress(missing, not args.quiet, unit="trials")
    try:
        failures = run_tasks(TrialWorker, worker_args, trial_tasks(), lambda t: f"trial {t['number']} {t['values']}",
                             told, workers, args.retries, bar) if missing else []
    finally:
        bar.close()
    for failure in failures:         # its trial stays FAIL in the study, with the error
        number = int(failure.task.split()[1])
        asked[number].set_user_attr("error", failure.error)
        study.tell(asked.pop(number), state=optuna.trial.TrialState.FAIL)
    trials = [{"number": t.number, "values": dict(t.params), "accuracy": t.values[0], "cpu_ms": t.values[1],
               **{k: t.user_attrs[k] for k in ("AR", "MHF1", "poses") if k in t.user_attrs}}
              for t in study.get_trials(deepcopy=False) if t.state == optuna.trial.TrialState.COMPLETE]
    if not trials:
        raise InputError(f"no trial finished ({len(failures)} failed; first: "
                         f"{failures[0].error if failures else 'none ran'})")
    base_values = {p.name: p.default for p in space}
    defaults = next((t for t in trials if t["values"] == base_values), None)
    best = choose(trials, args.max_cpu_ms)
    if best is None:
        fastest = min(t["cpu_ms"] for t in trials)
        raise InputError(f"no trial kept within --max-cpu-ms {args.max_cpu_ms:g} (the fastest took {fastest:.0f} ms "
                         f"per image); raise the bound or search settings that save time")

    # Held out: scored only now, the base settings and the chosen ones side by side.
    held = {}
    if holdout:
        checks = [{"number": "base", "values": {}, "pairs": holdout},
                  {"number": "chosen", "values": best["values"], "pairs": holdout}]
        holdout_failures = run_tasks(TrialWorker, worker_args, checks, lambda t: f"held-out run with the {t['number']} settings",
                                     lambda t, r: held.__setitem__(t["number"], r), workers, args.retries)
        if holdout_failures:
            raise InputError(f"the held-out images could not be scored: {holdout_failures[0].task}: "
                             f"{holdout_failures[0].error}")

    chosen_values = {**base, **best["values"]}
    names = [p.name for p in space]
    ranked = importances(study, names)
    figures = (f"{key} {best['accuracy']:.3f} on the {len(pairs)} tuning image(s) (base settings "
               f"{'-' if defaults is None else format(defaults['accuracy'], '.3f')})")
    if held:
        figures += f", held-out {key} {held['chosen'][key]:.3f} on {len(holdout)} image(s) (base {held['base'][key]:.3f})"
    header = [f"Found by `mireg tune` on {ds.root} ({ds.split}), study '{args.study}', trial {best['number']}:",
              f"{figures}; {best['cpu_ms']:.0f} ms CPU per image.",
              "The node's parameter file (config/params.yaml's layout) with the chosen values."]
    (out_dir / "params.yaml").write_text(default_params_yaml(values=chosen_values, header=header))
    front = [trials[i] for i in pareto_front([(t["accuracy"], t["cpu_ms"]) for t in trials])]
    cv2.imwrite(str(out_dir / "front.png"), draw_front(trials, defaults, best, args.objective, args.max_cpu_ms))
    report = {"dataset": str(ds.root), "split": ds.split, "objective": key, "storage": storage_url, "study": args.study,
              "space": [p.describe() for p in space], "tuning_images": len(pairs), "holdout_images": len(holdout),
              "trials": len(trials), "failed_trials": [f.as_json() for f in failures],
              "base": defaults, "chosen": best, "pareto_front": front, "importances": ranked,
              "holdout": {"base": held.get("base"), "chosen": held.get("chosen")} if held else None}
    (out_dir / "tune.json").write_text(json.dumps(report, indent=1, default=str))
    (out_dir / "report.md").write_text(report_markdown(report, space, args.max_cpu_ms))
    verdict = ""
    if held:
        gain = held["chosen"][key] - held["base"][key]
        verdict = (f"; held out: {held['chosen'][key]:.3f} against {held['base'][key]:.3f} with the base settings ("
                   + ("better" if gain > 0 else "no better: keep the base settings" if gain < 0 else "the same") + ")")
    print(f"mireg tune: {len(trials)} trial(s); chosen trial {best['number']}: {figures}{verdict}; "
          f"wrote {out_dir / 'params.yaml'} and {out_dir / 'report.md'}", file=sys.stderr)
    if failures:
        print(f"mireg tune: {len(failures)} trial(s) failed (first: {failures[0].task}: {failures[0].error})",
              file=sys.stderr)
    return 0


def report_markdown(report: dict, space, max_cpu_ms) -> str:
    key = report["objective"]
    best, base, held = report["chosen"], report["base"], report["holdout"]

    def cell(r, name):
        return "-" if r is None else f"{r[name]:.3f}" if name != "cpu_ms" else f"{r[name]:.0f}"
    lines = [f"# mireg tune: {report['dataset']} ({report['split']})", "",
             f"{report['trials']} trials ({len(report['failed_trials'])} failed) over {report['tuning_images']} tuning "
             f"image(s); objective {key} up and CPU ms per image down"
             + (f", chosen within {max_cpu_ms:g} ms" if max_cpu_ms is not None else "") + ". Study: "
             f"`{report['study']}` in `{report['storage']}`.", "",
             "Searched: " + "; ".join(p.describe() for p in space) + ".", "",
             "| settings | tuning AR | tuning MHF1 | CPU ms / image | held-out AR | held-out MHF1 |", "|---|---|---|---|---|---|",
             f"| base (trial {'-' if base is None else base['number']}) | {cell(base, 'AR')} | {cell(base, 'MHF1')} | "
             f"{cell(base, 'cpu_ms')} | {cell(held and held['base'], 'AR')} | {cell(held and held['base'], 'MHF1')} |",
             f"| chosen (trial {best['number']}) | {cell(best, 'AR')} | {cell(best, 'MHF1')} | {cell(best, 'cpu_ms')} | "
             f"{cell(held and held['chosen'], 'AR')} | {cell(held and held['chosen'], 'MHF1')} |", ""]
    if held:
        gain = held["chosen"][key] - held["base"][key]
        lines += [("The chosen settings raise" if gain > 0 else "The chosen settings do not raise")
                  + f" the held-out {key} ({held['base'][key]:.3f} -> {held['chosen'][key]:.3f})"
                  + ("." if gain > 0 else ": what the search found on the tuning images does not carry over; keep the base "
                                          "settings or search on more images."), ""]
    else:
        lines += ["No held-out images (--holdout-scenes): the tuning figure overstates what the settings give on new data.", ""]
    lines += ["Chosen values: " + ", ".join(f"`{k}: {v}`" for k, v in best["values"].items()), "",
              "## Accuracy against latency", "", "![front](front.png)", "",
              "Pareto front (no trial is both more accurate and faster):", "",
              f"| trial | {key} | CPU ms / image | values |", "|---|---|---|---|"]
    lines += [f"| {t['number']} | {t['accuracy']:.3f} | {t['cpu_ms']:.0f} | "
              + ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in t["values"].items()) + " |"
              for t in report["pareto_front"]]
    lines += ["", "## Parameters that mattered", ""]
    if report["importances"]:
        lines += [f"Share of the variation of {key} over the trials (Optuna PED-ANOVA):", ""]
        lines += [f"- `{k}`: {v:.2f}" for k, v in sorted(report["importances"].items(), key=lambda kv: -kv[1])]
    else:
        lines += ["Too few trials, or all scored alike, to tell which parameters mattered."]
    return "\n".join(lines) + "\n"
