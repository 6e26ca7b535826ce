"""`mireg bench node` and `make demo` end to end, tiny: the figures and files they promise."""
import json
import subprocess
import sys

from ros_testing import REPO, ros_env


def test_bench_node_prints_latency_overload_and_memory_figures(scene_bag, object_model, tmp_path):
    out = tmp_path / "bench.json"
    done = subprocess.run(
        [sys.executable, "-m", "multi_instance_reg.tools.bench.node", "--bag", str(scene_bag), "--model",
         str(object_model), "--frames", "15", "--overload-frames", "15", "--rss-frames", "30",
         "--distinct-frames", "3", "--domain-id", "50", "--json", str(out)],
        env=ros_env(50), cwd=REPO, capture_output=True, text=True, timeout=240)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "% of camera frames" in done.stdout and "end-to-end latency" in done.stdout
    assert "resident memory" in done.stdout
    figures = json.loads(out.read_text())
    r = figures["rate_30hz"]
    assert 1 <= r["frames_with_poses"] <= 15 and r["frames_with_poses"] + r["dropped"] == 15
    assert r["share_with_poses"] == round(r["frames_with_poses"] / 15, 4) and 0 <= r["share_with_a_pose"] <= r["share_with_poses"]
    assert 0 < r["e2e_ms_p50"] <= r["e2e_ms_p95"] < 10_000
    m = figures["long_replay"]
    assert 50 < m["rss_mb_start"] <= m["rss_mb_max"] and m["rss_mb_end"] <= m["rss_mb_max"]


def test_demo_runs_end_to_end_and_leaves_overlays_and_a_summary(tmp_path):
    out = tmp_path / "demo"
    done = subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.demo", "--out", str(out),
                           "--frames", "10", "--instances", "3", "--domain-id", "51", "--rate", "0.5"],
                          env=ros_env(51), cwd=REPO, capture_output=True, text=True, timeout=400)
    assert done.returncode == 0, done.stdout + done.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] >= 1 and summary["frames_scored"] == summary["frames"]
    assert summary["MHF1"] is not None and summary["frames_dropped"] is not None
    # Two objects by default, each scored against its own ground truth by the listener.
    assert set(summary["objects"]) == {"snack_box", "can"}
    assert all(0 <= o["MHF1"] <= 100 and o["frames_scored"] == summary["frames_scored"]
               for o in summary["objects"].values())
    assert "snack_box: MHF1" in done.stdout and "can: MHF1" in done.stdout
    assert list((out / "overlays").glob("overlay_*.png"))
    assert "MHF1" in done.stdout and "mean latency" in done.stdout and "frames dropped" in done.stdout
    for log in ("node.log", "listen.log", "play.log"):
        assert (out / log).stat().st_size > 0
    # What the node published, frame by frame, as mireg offline's poses.json.
    frames = json.loads((out / "poses.json").read_text())["frames"]
    assert len(frames) == summary["frames"]
    assert all(len(i["T"]) == 4 and "object" in i and "track_id" in i for f in frames for i in f["instances"])


def test_demo_refuses_a_domain_id_fast_dds_cannot_use(tmp_path):
    done = subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.demo", "--out", str(tmp_path / "demo"),
                           "--domain-id", "240"], env=ros_env(52), cwd=REPO, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert done.stderr.strip().splitlines() == [
        "mireg demo: error: --domain-id must be 0 to 232 (the largest ROS_DOMAIN_ID Fast DDS can use), got 240"]
    assert not (tmp_path / "demo").exists()     # refused before rendering anything


def test_large_data_profile_is_used_unless_the_user_chose_one():
    from multi_instance_reg.ros.transport import PROFILE, use_large_data_profile

    assert PROFILE.is_file() and "<segment_size>" in PROFILE.read_text()
    env = {}
    assert use_large_data_profile(env, free_shared_memory=2**34)
    assert env["FASTRTPS_DEFAULT_PROFILES_FILE"] == str(PROFILE)
    own = {"FASTRTPS_DEFAULT_PROFILES_FILE": "/etc/mine.xml"}
    assert not use_large_data_profile(own) and own["FASTRTPS_DEFAULT_PROFILES_FILE"] == "/etc/mine.xml"
    other = {"RMW_IMPLEMENTATION": "rmw_cyclonedds_cpp"}
    assert not use_large_data_profile(other) and "FASTRTPS_DEFAULT_PROFILES_FILE" not in other
    small_shm = {}
    assert not use_large_data_profile(small_shm, free_shared_memory=64 * 2**20) and not small_shm
