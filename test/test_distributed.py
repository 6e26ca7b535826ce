"""Runs on a local 2-worker Ray: `mireg bop run`, `mireg offline` over a folder of bags and
`mireg tune` give what the serial path gives, resume, retry and report failed tasks."""
import json
import os
import sys

import numpy as np
import pytest

from multi_instance_reg.datasets.bop import read_results_csv
from multi_instance_reg.errors import InputError
from multi_instance_reg.tools.cli import main

pytestmark = pytest.mark.xdist_group("ray")      # one Ray for the module, on one test worker

# No budget on the shape search: it counts CPU time, and an image that is its worker's first
# (compiling kernels inside it) is cut where a later one is not: the same image would give
# other poses depending on where it ran.
NO_DEADLINE = "instance_registration:\n  ros__parameters:\n    frontend.shape_deadline_ms: 0.0\n"


@pytest.fixture(scope="module")
def local_ray():
    import ray

    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR", log_to_driver=False)
    # The test's own worker classes travel by value: Ray's workers cannot import test modules.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Two synthetic scenes of two frames each, as bags (bags/) and as one BOP set (bop/)."""
    from multi_instance_reg.synthetic.scene import make_tabletop_scene, write_scene_bag

    d = tmp_path_factory.mktemp("ray_data")
    for scene_id in (1, 2):
        scene = make_tabletop_scene(["snack_box"], instances=2, distractors=1, frames=2, seed=scene_id)
        write_scene_bag(scene, d / "bags" / f"scene{scene_id}", imu=False, bop_dir=d / "bop", bop_scene=scene_id)
    (d / "no_deadline.yaml").write_text(NO_DEADLINE)
    return d


def mireg(capsys, *args):
    code = main([str(a) for a in args])
    return code, capsys.readouterr().err


def one_line_error(err, command):
    """The error is one line, the last (what came before it: progress notes), no traceback."""
    lines = err.strip().splitlines()
    return lines[-1].startswith(f"{command}: error: ") and "Traceback" not in err and \
        not any(line.startswith(f"{command}: error") for line in lines[:-1])


def poses(csv_path):
    return [(r.scene_id, r.im_id, r.obj_id, round(r.score, 6), np.round(r.T_m, 6).tolist())
            for r in read_results_csv(csv_path)]


def test_bop_run_on_two_workers_gives_the_serial_poses_and_resumes(local_ray, data, tmp_path, capsys):
    params = data / "no_deadline.yaml"
    code, err = mireg(capsys, "bop", "run", data / "bop", "-o", tmp_path / "serial", "--quiet", "--params", params)
    assert code == 0, err
    code, err = mireg(capsys, "bop", "run", data / "bop", "-o", tmp_path / "ray", "--quiet", "--params", params,
                      "--workers", 2)
    assert code == 0, err
    serial, spread = (poses(next((tmp_path / d).glob("*.csv"))) for d in ("serial", "ray"))
    assert serial == spread and len(serial) > 0
    summaries = [json.loads((tmp_path / d / "summary.json").read_text()) for d in ("serial", "ray")]
    for key in ("poses", "hits", "gt_instances"):
        assert [e[key] for e in summaries[0]["images"]] == [e[key] for e in summaries[1]["images"]]
    assert summaries[1]["failed_tasks"] == []
    parts = tmp_path / "ray" / "parts"
    assert sorted(p.name for p in parts.glob("0*.json")) == [
        "000001_000000.json", "000001_000001.json", "000002_000000.json", "000002_000001.json"]

    # A crash after three images: the rerun runs the fourth only and gives the same file.
    (parts / "000002_000001.json").unlink()
    (parts / "000001_000000.json").write_text('{"images": [')           # cut short while written
    code, err = mireg(capsys, "bop", "run", data / "bop", "-o", tmp_path / "ray", "--quiet", "--params", params,
                      "--workers", 2)
    assert code == 0, err
    assert "2 of 4 task(s) done before" in err
    assert poses(next((tmp_path / "ray").glob("*.csv"))) == serial

    # Other settings into the same folder: refused, not mixed.
    other = tmp_path / "other.yaml"
    other.write_text(NO_DEADLINE + "    frontend.ratio: 0.7\n")
    code, err = mireg(capsys, "bop", "run", data / "bop", "-o", tmp_path / "ray", "--quiet", "--params", other, "--ray")
    assert code == 2 and one_line_error(err, "mireg bop") and "other settings (differing: params)" in err, err


def test_offline_over_a_folder_of_bags_on_ray_gives_the_serial_files(local_ray, data, tmp_path, capsys):
    from multi_instance_reg.tools.bop import model_from_bop_mesh
    from multi_instance_reg.datasets.bop import BopDataset
    from multi_instance_reg.models.model import save_model

    ds = BopDataset(data / "bop")
    model = save_model(model_from_bop_mesh(ds, next(iter(ds.models_info))), tmp_path / "snack.npz")
    args = ["--model", model, "--params", data / "no_deadline.yaml", "--quiet"]
    code, err = mireg(capsys, "offline", data / "bags", "-o", tmp_path / "serial", *args)
    assert code == 0, err
    code, err = mireg(capsys, "offline", data / "bags", "-o", tmp_path / "ray", "--workers", 2, *args)
    assert code == 0, err
    for bag in ("scene1", "scene2"):
        frames = []
        for run in ("serial", "ray"):
            d = json.loads((tmp_path / run / bag / "poses.json").read_text())["frames"]
            for f in d:
                f.pop("latency_ms")        # a time, not a result
            frames.append(d)
        assert frames[0] == frames[1] and len(frames[0]) == 2
        assert (tmp_path / "ray" / bag / "metrics.json").is_file()
    summary = json.loads((tmp_path / "ray" / "summary.json").read_text())
    assert [b["frames"] for b in summary["bags"]] == [2, 2] and summary["failed_tasks"] == []
    # Done bags are skipped on a rerun.
    code, err = mireg(capsys, "offline", data / "bags", "-o", tmp_path / "ray", "--workers", 2, *args)
    assert code == 0 and "2 of 2 bag(s) done before" in err, err


class FlakyWorker:
    """Task "once": fails on its first attempt; "dies": its worker process exits on the
    first attempt; "always": fails every time; "input": a bad input (not tried again)."""

    def __init__(self, folder):
        self.folder = folder

    def run(self, task):
        from pathlib import Path

        mark = Path(self.folder) / task
        attempt = len(list(Path(self.folder).glob(f"{task}.*"))) + 1
        (mark.with_suffix(f".{attempt}")).touch()
        if task == "input":
            raise InputError("frame 3 of this bag is 4x4")
        if task == "always" or (task == "once" and attempt == 1):
            raise ValueError(f"attempt {attempt} went wrong")
        if task == "dies" and attempt == 1:
            os._exit(3)
        return f"{task} done at attempt {attempt}"


def test_a_failed_task_is_tried_again_then_reported_with_its_input(local_ray, tmp_path):
    from multi_instance_reg.distributed.ray_runner import run_tasks

    results = {}
    failures = run_tasks(FlakyWorker, (str(tmp_path),), ["fine", "once", "dies", "always", "input"],
                         lambda t: f"task '{t}'", results.__setitem__, workers=2, retries=1)
    assert results == {"fine": "fine done at attempt 1", "once": "once done at attempt 2",
                       "dies": "dies done at attempt 2"}
    assert [(f.task, f.error) for f in failures] in (
        [("task 'always'", "ValueError: attempt 2 went wrong"), ("task 'input'", "InputError: frame 3 of this bag is 4x4")],
        [("task 'input'", "InputError: frame 3 of this bag is 4x4"), ("task 'always'", "ValueError: attempt 2 went wrong")])
    assert len(list(tmp_path.glob("input.*"))) == 1          # a bad input is not tried again


def test_a_tiny_study_writes_params_the_node_accepts_and_a_report(local_ray, data, tmp_path, capsys):
    from multi_instance_reg.params import read_params_yaml
    from multi_instance_reg.ros.parameters import all_specs

    out = tmp_path / "tune"
    search = ["--param", "frontend.shape_min_support=0.6:0.9", "--param", "frontend.shape_faces",
              "--holdout-scenes", 2, "--params", data / "no_deadline.yaml", "--workers", 2, "--quiet"]
    code, err = mireg(capsys, "tune", data / "bop", "-o", out, "--trials", 2, *search)
    assert code == 0, err
    report = json.loads((out / "tune.json").read_text())
    assert report["trials"] == 2 and report["tuning_images"] == 2 and report["holdout_images"] == 2
    assert report["base"]["values"] == {"frontend.shape_min_support": 0.75, "frontend.shape_faces": True}
    chosen = report["chosen"]
    assert chosen["accuracy"] >= report["base"]["accuracy"]
    assert set(report["holdout"]) == {"base", "chosen"} and 0 <= report["holdout"]["chosen"]["MHF1"] <= 1
    # params.yaml: the layout of config/params.yaml, every value one the node's declarations accept.
    values = read_params_yaml(out / "params.yaml")
    specs = {s.name: s for s in all_specs()}
    assert set(values) == set(specs)
    for name, value in values.items():
        specs[name].check(value)
    for name, value in chosen["values"].items():
        assert values[name] == pytest.approx(value)
    assert values["frontend.shape_deadline_ms"] == 0.0                  # the base file's setting kept
    text = (out / "report.md").read_text()
    assert "held-out MHF1" in text and "front.png" in text
    import cv2
    assert cv2.imread(str(out / "front.png")) is not None

    # Resumed: one more trial, the two before kept in the study.
    code, err = mireg(capsys, "tune", data / "bop", "-o", out, "--trials", 3, *search)
    assert code == 0 and "2 trial(s) in study 'mireg'" in err, err
    assert json.loads((out / "tune.json").read_text())["trials"] == 3
    # Another search in the same study: refused with the reason.
    code, err = mireg(capsys, "tune", data / "bop", "-o", out, "--trials", 3, *search[2:], "--param", "frontend.ratio")
    assert code == 2 and one_line_error(err, "mireg tune") and "searched something else (differing: space)" in err, err


def test_search_space_comes_from_the_declarations():
    from multi_instance_reg.distributed.tune import search_space

    ratio, refine, matcher, checks = search_space(["frontend.ratio", "frontend.refine", "frontend.matcher",
                                                   "frontend.flann_checks=8:64"], {"frontend.ratio": 0.7})
    assert (ratio.low, ratio.high, ratio.default, ratio.log) == (0.1, 1.0, 0.7, False)
    assert refine.choices == (False, True) and matcher.choices == ("flann", "brute_force")
    assert (checks.low, checks.high, checks.type, checks.log) == (8, 64, int, False)
    assert search_space(["frontend.sift_contrast_threshold"])[0].log         # 0.001 to 0.5: log scale
    for items, fragment in ((["frontend.nope"], "not a pipeline or tracking parameter"),
                            (["frontend.ratio=0.5:2"], "out of range"),
                            (["frontend.ratio=0.9:0.5"], "LO < HI"),
                            (["frontend.refine=0:1"], "without a range"),
                            (["frontend.ratio", "frontend.ratio"], "given twice"),
                            ([], "at least one --param")):
        with pytest.raises(InputError, match=fragment):
            search_space(items)


def test_the_chosen_trial_and_the_front():
    from multi_instance_reg.distributed.tune import choose, pareto_front

    trials = [{"accuracy": 0.5, "cpu_ms": 100}, {"accuracy": 0.7, "cpu_ms": 300}, {"accuracy": 0.6, "cpu_ms": 400},
              {"accuracy": 0.7, "cpu_ms": 250}]
    assert pareto_front([(t["accuracy"], t["cpu_ms"]) for t in trials]) == [0, 3]
    assert choose(trials, None) is trials[3]           # the fastest of the most accurate
    assert choose(trials, 200) is trials[0]
    assert choose(trials, 50) is None
