"""``mireg offline`` tracks over a generated pan (instances entering and leaving the view),
tested from the outside: run the command, read poses.json and metrics.json."""
import json
import subprocess
import sys

import pytest

# Its module fixture (pan_run) runs `mireg offline`: one pytest-xdist worker takes the whole module, so
# that it runs once.
pytestmark = pytest.mark.xdist_group("test_offline_tracking")


@pytest.fixture(scope="module")
def pan_run(object_model, tmp_path_factory):
    from multi_instance_reg.synthetic.scene import generate_scene_bag

    out = tmp_path_factory.mktemp("tracking")
    generate_scene_bag(out / "pan", instances=6, distractors=2, frames=45, seed=3, motion="pan")
    proc = subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.cli", "offline", str(out / "pan"),
                           "--model", str(object_model), "-o", str(out / "res"), "--quiet"],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    return json.loads((out / "res" / "poses.json").read_text()), json.loads((out / "res" / "metrics.json").read_text())


def test_poses_json_carries_tracks(pan_run):
    poses, _ = pan_run
    frames = poses["frames"]
    assert len(frames) == 45
    insts = [i for f in frames for i in f["instances"]]
    assert insts
    for i in insts:
        assert {"id", "T", "inliers", "score", "track_id", "state", "source"} <= set(i)
        assert i["state"] in ("tentative", "confirmed")         # a coasting track (a prediction) is not published
        assert i["source"] in ("detection", "tracking")
    for f in frames:                                             # id keeps its meaning: rank in the frame
        assert sorted(i["id"] for i in f["instances"]) == list(range(len(f["instances"])))
        assert len({i["track_id"] for i in f["instances"]}) == len(f["instances"])


def test_identity_holds_over_the_pan(pan_run):
    _, metrics = pan_run
    ident = metrics["identity"]
    assert ident["IDF1"] >= 0.9
    assert ident["id_switches"] <= 1
    assert ident["MOTA"] >= 0.8
    assert metrics["MHF1"] >= metrics["detection_only"]["MHF1"] - 0.03


def test_node_parameter_file_drives_offline_tracking(tmp_path):
    from multi_instance_reg.tools.offline import load_tracker_config

    params = tmp_path / "params.yaml"
    params.write_text("instance_registration:\n  ros__parameters:\n    tracking:\n      smoothing: 0.3\n"
                      "      catch_up_frames: 5\n")
    assert load_tracker_config(params).smoothing == 0.3          # live-only settings are ignored offline
    params.write_text("instance_registration:\n  ros__parameters:\n    tracking:\n      enabled: false\n")
    assert load_tracker_config(params) is None                  # as --no-tracking
    assert load_tracker_config(None).smoothing == 0.0


@pytest.mark.parametrize("options", [dict(motion="jumps", frame_rate=10.0, seed=21),
                                     dict(motion="shaky_pan", loop=True, seed=22)], ids=["jumps_10Hz", "shaky_loop"])
def test_tracking_never_makes_the_output_worse_than_detection_alone(object_model, tmp_path, options):
    # The invariant of bench tracking on short sequences as recorded elsewhere (realistic
    # sensor): per-frame MHF1 and MHP with tracking at least the detector's on the same frames
    # - 1 point, and never more poses published than objects in view and hidden tracks.
    from multi_instance_reg.metrics import summarize
    from multi_instance_reg.models.model import load_model
    from multi_instance_reg.rgbd.pipeline import PipelineConfig
    from multi_instance_reg.synthetic.scene import generate_scene_bag
    from multi_instance_reg.tools.offline import replay
    from multi_instance_reg.tracking import TrackerConfig

    generate_scene_bag(tmp_path / "seq", instances=5, distractors=2, frames=12, sensor="realistic", **options)
    r = replay(tmp_path / "seq", load_model(object_model), PipelineConfig(), min_visibility=0.25, progress=False,
               tracker_config=TrackerConfig())
    tracked, detected = summarize(r.scores), summarize(r.detection_scores)
    assert len(r.scores) == len(r.detection_scores) == (24 if options.get("loop") else 12)   # a loop plays twice
    assert tracked["MHF1"] >= detected["MHF1"] - 0.01 and tracked["MHP"] >= detected["MHP"] - 0.01
    assert detected["MHF1"] > 0.5                               # the detector does find them
    hidden = [sum(i["state"] == "coasting" for i in f["instances"]) for f in r.frames]
    assert all(f - h <= v for f, h, v in zip(r.found, hidden, r.in_view))
