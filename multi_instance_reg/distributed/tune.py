"""Parameter searches: an Optuna study over some of the node's declared parameters, each
trial a run of the BOP pipeline over a labelled image set on a Ray worker.

The search space comes from the declarations (``param(default, description, low, high |
choices)``): a number's range is its declared one unless narrowed (``NAME=LO:HI``), a bool or
a choice is categorical. Two objectives: accuracy (BOP AR or MHF1, ``evaluation.bop_scoring``)
up, CPU time per image down; the chosen trial is the most accurate one within the latency
bound, if any. A trial's images go through ``tools.bop.BopImageSolver``, the code of ``mireg
bop run``, so a trial's figures are the ones ``bop run`` with its settings would give.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError

OBJECTIVES = {"mhf1": "MHF1", "ar": "AR"}
LOG_SCALE_RATIO = 100.0      # a positive range spanning this factor or more is searched on a log scale


@dataclass(frozen=True)
class TunedParam:
    name: str
    type: type
    low: float | int | None = None
    high: float | int | None = None
    choices: tuple | None = None
    default: object = None

    @property
    def log(self) -> bool:
        return self.choices is None and self.low > 0 and self.high / self.low >= LOG_SCALE_RATIO

    def describe(self) -> str:
        if self.choices is not None:
            return f"{self.name} in {{{', '.join(map(str, self.choices))}}}"
        return f"{self.name} in [{self.low:g}, {self.high:g}]" + (" (log)" if self.log else "")

    def suggest(self, trial):
        if self.choices is not None:
            return trial.suggest_categorical(self.name, list(self.choices))
        if self.type is int:
            return trial.suggest_int(self.name, int(self.low), int(self.high), log=self.log)
        return trial.suggest_float(self.name, float(self.low), float(self.high), log=self.log)


def tunable_specs() -> dict:
    """The parameters a trial can change: the pipeline's and the tracker's (``tracking.*``)."""
    from ..params import param_specs
    from ..rgbd.pipeline import PipelineConfig
    from ..tracking import TrackerConfig

    return {s.name: s for s in [*param_specs(PipelineConfig()), *param_specs(TrackerConfig(), "tracking.")]}


def search_space(items: list[str], base: dict | None = None) -> list[TunedParam]:
    """``--param NAME`` or ``NAME=LO:HI`` items -> the search space; the defaults are the
    declared ones, or ``base``'s (the --params file) where it sets them."""
    specs = tunable_specs()
    base = base or {}
    space, seen = [], set()
    for item in items or []:
        name, sep, span = item.partition("=")
        name = name.strip()
        if name not in specs:
            close = [n for n in specs if name.split(".")[-1] in n]
            raise InputError(f"--param {name}: not a pipeline or tracking parameter"
                             + (f" (did you mean {', '.join(close[:4])}?)" if close else "; see docs/parameters.md"))
        if name in seen:
            raise InputError(f"--param {name} is given twice")
        seen.add(name)
        spec = specs[name]
        default = spec.check(base[name]) if name in base else spec.default
        if spec.type is bool:
            if sep:
                raise InputError(f"--param {item}: {name} is true or false; give it without a range")
            space.append(TunedParam(name, bool, choices=(False, True), default=default))
            continue
        if spec.choices is not None:
            if sep:
                raise InputError(f"--param {item}: {name} is one of {list(spec.choices)}; give it without a range")
            space.append(TunedParam(name, str, choices=tuple(spec.choices), default=default))
            continue
        if spec.type not in (int, float):
            raise InputError(f"--param {name}: a {spec.type.__name__} parameter cannot be searched")
        low, high = spec.low, spec.high
        if sep:
            lo_text, colon, hi_text = span.partition(":")
            try:
                low, high = spec.type(float(lo_text)) if spec.type is float else int(lo_text), \
                    spec.type(float(hi_text)) if spec.type is float else int(hi_text)
            except ValueError:
                raise InputError(f"--param {item}: give the range as NAME=LO:HI with {spec.type.__name__} bounds, "
                                 f"e.g. {name}={spec.low}:{spec.high}") from None
            if not colon or not low < high:
                raise InputError(f"--param {item}: the range must be LO:HI with LO < HI")
            spec.check(low), spec.check(high)       # within the declared range, or the reason why not
        if low is None or high is None:
            raise InputError(f"--param {name} has no declared range; give one as {name}=LO:HI")
        space.append(TunedParam(name, spec.type, low, high, default=default))
    if not space:
        raise InputError("give at least one --param NAME (or NAME=LO:HI) to search over, e.g. --param frontend.ratio")
    return space


def split_values(values: dict) -> tuple[dict, dict]:
    """Dotted names -> (pipeline entries, tracking entries)."""
    pipeline = {k: v for k, v in values.items() if not k.startswith("tracking.")}
    return pipeline, {k: v for k, v in values.items() if k.startswith("tracking.")}


def score_images(dataset_root: str, split: str, pairs, estimates) -> dict:
    """BOP's AR and MHF1 (``evaluation.bop_scoring``) over the images ``pairs`` only."""
    from ..datasets.bop import BopDataset
    from ..evaluation.bop_scoring import ScoreSettings, derived_targets, score_results

    ds = BopDataset(dataset_root, split)
    chosen = {tuple(p) for p in pairs}
    targets = ds.targets if ds.targets is not None else derived_targets(ds, ScoreSettings().min_visib_fract)
    ds.targets = [t for t in targets if (t.scene_id, t.im_id) in chosen]
    if not ds.targets:
        raise InputError(f"none of the {len(chosen)} image(s) of {ds.split_dir} chosen has a labelled instance "
                         f"(scene_gt.json, at least 10 % visible): nothing to score a trial by")
    return score_results(ds, [e for e in estimates if (e.scene_id, e.im_id) in chosen])


class TrialWorker:
    """What one Ray worker of ``mireg tune`` holds: the models (loaded once). ``run(task)``
    runs the images of ``task["pairs"]`` with the base settings and ``task["values"]``
    through the pipeline (as ``mireg bop run`` would) and scores them."""

    def __init__(self, dataset_root: str, split: str, models, obj_ids, base_values: dict, tracking: bool):
        self.dataset_root, self.split = dataset_root, split
        self.models, self.obj_ids = models, obj_ids
        self.base_values, self.tracking = base_values, tracking

    def run(self, task: dict) -> dict:
        from ..datasets.bop import BopEstimate
        from ..tools.bop import BopImageSolver, bop_tasks
        from ..tools.offline import load_config, load_tracker_config

        values = {**self.base_values, **task["values"]}
        config = load_config(values)
        tracker_config = load_tracker_config(values) if self.tracking else None
        solver = BopImageSolver(self.dataset_root, self.split, self.models, self.obj_ids, config, tracker_config,
                                image_targets=True)    # each image's target objects, as bop run's default
        images, estimates, skipped = [], [], 0
        for t in bop_tasks([tuple(p) for p in task["pairs"]], self.tracking):
            out = solver.run(t)
            images += out["images"]
            skipped += len(out["skipped"])
            estimates += [BopEstimate(s, im, o, score, np.array(R).reshape(3, 3), np.array(tr), secs)
                          for s, im, o, score, R, tr, secs in out["estimates"]]
        if not images:
            raise InputError(f"no image of the {len(task['pairs'])} chosen could be processed ({skipped} skipped)")
        scores = score_images(self.dataset_root, self.split, task["pairs"], estimates)
        return {"AR": float(scores["AR"]), "MHF1": float(scores["MHF1"]),
                "cpu_ms": 1000.0 * float(np.mean([e["cpu_seconds"] for e in images])),
                "images": len(images), "skipped": skipped, "poses": len(estimates)}


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the (accuracy up, CPU down) points no other point beats on both, by CPU."""
    front = [i for i, (acc, cpu) in enumerate(points)
             if not any((a >= acc and c <= cpu) and (a > acc or c < cpu) for a, c in points)]
    return sorted(front, key=lambda i: points[i][1])


def choose(trials: list[dict], max_cpu_ms: float | None) -> dict | None:
    """The most accurate trial within the CPU bound (the fastest of equals); None if none is."""
    ok = [t for t in trials if max_cpu_ms is None or t["cpu_ms"] <= max_cpu_ms]
    return max(ok, key=lambda t: (t["accuracy"], -t["cpu_ms"])) if ok else None


def draw_front(trials: list[dict], defaults: dict | None, best: dict | None, objective: str,
               max_cpu_ms: float | None, width: int = 760, height: int = 480) -> np.ndarray:
    """BGR scatter of the trials, CPU ms per image (x) against accuracy (y): every trial grey,
    the Pareto front joined in blue, the base settings a red square, the chosen trial green."""
    import cv2

    img = np.full((height, width, 3), 255, np.uint8)
    left, right, top, bottom = 70, 20, 60, 50
    xs = np.array([t["cpu_ms"] for t in trials], float)
    ys = np.array([t["accuracy"] for t in trials], float)
    x0, x1 = float(xs.min()), float(xs.max())
    y0, y1 = float(ys.min()), float(ys.max())
    pad_x, pad_y = max((x1 - x0) * 0.08, 1.0), max((y1 - y0) * 0.08, 0.01)
    x0, x1, y0, y1 = max(0.0, x0 - pad_x), x1 + pad_x, max(0.0, y0 - pad_y), min(1.0, y1 + pad_y) + 1e-9

    def xy(cpu, acc):
        return (int(round(left + (cpu - x0) / (x1 - x0) * (width - left - right))),
                int(round(height - bottom - (acc - y0) / (y1 - y0) * (height - top - bottom))))
    black, font = (0, 0, 0), cv2.FONT_HERSHEY_SIMPLEX
    cv2.rectangle(img, (left, top), (width - right, height - bottom), black, 1)
    for k in range(5):
        v = y0 + (y1 - y0) * k / 4
        _, y = xy(x0, v)
        cv2.line(img, (left, y), (width - right, y), (230, 230, 230), 1)
        cv2.putText(img, f"{v:.3f}", (8, y + 4), font, 0.4, black, 1, cv2.LINE_AA)
        u = x0 + (x1 - x0) * k / 4
        x, _ = xy(u, y0)
        cv2.putText(img, f"{u:.0f}", (x - 12, height - bottom + 16), font, 0.4, black, 1, cv2.LINE_AA)
    cv2.putText(img, "CPU ms per image", (width // 2 - 60, height - 12), font, 0.5, black, 1, cv2.LINE_AA)
    cv2.putText(img, f"{OBJECTIVES[objective]} on the tuning images ({len(trials)} trials)", (left, 25), font, 0.5,
                black, 1, cv2.LINE_AA)
    if max_cpu_ms is not None and x0 <= max_cpu_ms <= x1:
        x, _ = xy(max_cpu_ms, y0)
        cv2.line(img, (x, top), (x, height - bottom), (0, 140, 255), 1)
    for cpu, acc in zip(xs, ys):
        cv2.circle(img, xy(cpu, acc), 4, (170, 170, 170), -1, cv2.LINE_AA)
    front = pareto_front(list(zip(ys, xs)))
    pts = np.array([xy(xs[i], ys[i]) for i in front], np.int32)
    if len(pts) > 1:
        cv2.polylines(img, [pts], False, (200, 120, 30), 2, cv2.LINE_AA)
    for p in pts:
        cv2.circle(img, tuple(int(v) for v in p), 5, (200, 120, 30), -1, cv2.LINE_AA)
    if defaults is not None:
        x, y = xy(defaults["cpu_ms"], defaults["accuracy"])
        cv2.rectangle(img, (x - 6, y - 6), (x + 6, y + 6), (0, 0, 220), 2)
    if best is not None:
        cv2.circle(img, xy(best["cpu_ms"], best["accuracy"]), 9, (0, 170, 0), 2, cv2.LINE_AA)
    for k, (label, colour) in enumerate((("trial", (170, 170, 170)), ("Pareto front", (200, 120, 30)),
                                         ("base settings", (0, 0, 220)), ("chosen", (0, 170, 0)))):
        x = left + 10 + 130 * k
        cv2.circle(img, (x, 42), 5, colour, -1 if k < 2 else 2, cv2.LINE_AA)
        cv2.putText(img, label, (x + 10, 47), font, 0.45, black, 1, cv2.LINE_AA)
    return img


def importances(study, names: list[str]) -> dict[str, float]:
    """Each parameter's share of the accuracy's variation over the trials (Optuna's PED-ANOVA
    for high accuracy, which needs no extra package); empty when there are too few trials to tell."""
    import warnings

    import optuna

    complete = [t for t in study.get_trials(deepcopy=False) if t.state == optuna.trial.TrialState.COMPLETE]
    if len(complete) < 4 or len({t.values[0] for t in complete}) < 2:
        return {}
    try:
        evaluator = optuna.importance.PedAnovaImportanceEvaluator()
        with warnings.catch_warnings():     # it warns that it ranks for low targets: the target is negated
            warnings.simplefilter("ignore")
            out = optuna.importance.get_param_importances(study, evaluator=evaluator, target=lambda t: -t.values[0],
                                                          params=names)
    except (ValueError, RuntimeError):
        return {}
    return {k: float(v) for k, v in out.items()}
