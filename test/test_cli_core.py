"""`mireg register` and the core benches, run as a user would: a real process, real files."""
import json
import subprocess
import sys

import numpy as np
import pytest

from multi_instance_reg.metrics import evaluate_scene
from multi_instance_reg.synthetic.correspondences import make_band


def mireg(*args, **kw):
    return subprocess.run([sys.executable, "-m", "multi_instance_reg.tools.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=600, **kw)


def test_register_contract(tmp_path):
    s = make_band("10-50", 1, seed=3)[0]
    src = s.src.copy()
    src[0] = np.nan
    np.savez(tmp_path / "in.npz", src=src, tgt=s.tgt)
    out = tmp_path / "result.npz"
    p = mireg("register", tmp_path / "in.npz", "-o", out)
    assert p.returncode == 0, p.stderr
    with np.load(out, allow_pickle=False) as r:
        T, labels, counts, t = r["T"], r["labels"], r["inlier_counts"], r["time_s"]
    assert T.dtype == np.float64 and T.shape[1:] == (4, 4)
    assert labels.dtype == np.int64 and labels.shape == (len(src),) and labels[0] == -1
    assert counts.shape == (len(T),) and list(counts) == sorted(counts, reverse=True)
    assert all((labels == m).sum() == counts[m] for m in range(len(T)))
    assert t.shape == () and t > 0
    assert evaluate_scene(s.T_gt, T).hits == len(s.T_gt)


def test_register_parameters_change_the_result(tmp_path):
    s = make_band("10-50", 1, seed=3)[0]
    np.savez(tmp_path / "in.npz", src=s.src, tgt=s.tgt)
    p = mireg("register", tmp_path / "in.npz", "-o", tmp_path / "a.npz", "--min-cluster-size", "100000")
    assert p.returncode == 0, p.stderr
    assert len(np.load(tmp_path / "a.npz")["T"]) == 0


@pytest.mark.parametrize("content,message", [
    (None, "does not exist"),
    (b"not a zip", "not a readable .npz"),
    (b"", "is empty (0 bytes)"),
    (b"junk123", "not a zip archive"),
    ("missing_tgt", "no array(s) tgt"),
    ("bad_shape", "must be a numeric (N, 3) array"),
])
def test_register_bad_input_is_one_line_and_nonzero(tmp_path, content, message):
    path = tmp_path / "in.npz"
    if content == "missing_tgt":
        np.savez(path, src=np.zeros((5, 3)))
    elif content == "bad_shape":
        np.savez(path, src=np.zeros((5, 2)), tgt=np.zeros((5, 2)))
    elif content is not None:
        path.write_bytes(content)
    p = mireg("register", path, "-o", tmp_path / "out.npz")
    assert p.returncode == 2
    assert message in p.stderr and len(p.stderr.strip().splitlines()) == 1, p.stderr
    assert "Traceback" not in p.stderr
    assert str(path) in p.stderr and "pickled" not in p.stderr, p.stderr


def test_out_of_range_parameter_is_rejected(tmp_path):
    np.savez(tmp_path / "in.npz", src=np.zeros((5, 3)), tgt=np.zeros((5, 3)))
    p = mireg("register", tmp_path / "in.npz", "-o", tmp_path / "o.npz", "--gamma-thresh", "2")
    assert p.returncode == 2 and "out of range" in p.stderr


def test_bench_core_tiny(tmp_path):
    p = mireg("bench", "core", "--sizes", "256", "2048", "--repeats", "2", "--json", tmp_path / "c.json")
    assert p.returncode == 0, p.stderr
    rows = json.loads((tmp_path / "c.json").read_text())["rows"]
    assert [r["N"] for r in rows] == [256, 2048] and rows[1]["clustered"] == 1024
    assert all(r["median_ms"] > 0 for r in rows)


def test_bench_table1_tiny(tmp_path):
    p = mireg("bench", "table1", "--samples-per-band", "2", "--bands", "10-50", "--baseline-max-iters", "100",
              "--json", tmp_path / "t.json")
    assert p.returncode == 0, p.stderr
    band = json.loads((tmp_path / "t.json").read_text())["bands"]["10-50"]
    assert band["ECC (this package)"]["MHF1"] > 0.9
    assert "Sequential GC-RANSAC" in band and "MHF1" in p.stdout


def test_register_batch_equals_one_file_calls(tmp_path):
    inputs = []
    for i, band in enumerate(("10-50", "70-90")):
        s = make_band(band, 1, seed=3)[0]
        inputs.append(tmp_path / f"s{i}.npz")
        np.savez(inputs[-1], src=s.src, tgt=s.tgt)
    p = mireg("register", *inputs, "-o", tmp_path / "batch")
    assert p.returncode == 0, p.stderr
    for path in inputs:
        single = tmp_path / ("single_" + path.name)
        q = mireg("register", path, "-o", single, "--threads", "1")  # the batch used every core
        assert q.returncode == 0, q.stderr
        with np.load(tmp_path / "batch" / path.name) as b, np.load(single) as o:
            assert b.files == o.files
            for key in b.files:
                if key != "time_s":  # the one field that is a measurement
                    assert b[key].dtype == o[key].dtype and np.array_equal(b[key], o[key]), key


def test_register_batch_refuses_a_file_as_output_directory(tmp_path):
    s = make_band("10-50", 1, seed=3)[0]
    for name in ("a.npz", "b.npz"):
        np.savez(tmp_path / name, src=s.src, tgt=s.tgt)
    (tmp_path / "out.npz").write_bytes(b"")
    p = mireg("register", tmp_path / "a.npz", tmp_path / "b.npz", "-o", tmp_path / "out.npz")
    assert p.returncode == 2 and "must name a directory" in p.stderr
    assert len(p.stderr.strip().splitlines()) == 1


def test_register_threads_must_not_be_negative(tmp_path):
    s = make_band("10-50", 1, seed=3)[0]
    np.savez(tmp_path / "in.npz", src=s.src, tgt=s.tgt)
    p = mireg("register", tmp_path / "in.npz", "-o", tmp_path / "out.npz", "--threads", "-1")
    assert p.returncode == 2 and p.stderr.strip().count("\n") == 0 and "--threads" in p.stderr
