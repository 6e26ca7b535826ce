"""interfaces/install_vision_msgs.py, what `make install` runs: vision_msgs built here is up to
date; a vision_msgs from elsewhere (the user's ROS) is left alone; the wheels' cmake trap is fixed."""
import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "interfaces" / "install_vision_msgs.py"
sys.path.insert(0, str(SCRIPT.parent))
from install_vision_msgs import fix_wheel_cmake_paths, installed_state  # noqa: E402

sys.path.pop(0)


@pytest.fixture()
def built_here():
    if installed_state(Path(sys.prefix)) == "foreign":
        pytest.skip("vision_msgs comes from the ROS installed here: make install left it alone")


def run_script(env=None):
    return subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, timeout=300,
                          env=env, cwd=REPO)


def test_the_vision_msgs_make_install_built_is_up_to_date_and_imports(built_here):
    done = run_script()
    assert done.returncode == 0 and done.stdout.strip() == "vision_msgs: up to date", done.stdout + done.stderr
    from vision_msgs.msg import Detection3DArray, LabelInfo

    # Installed into this Python's prefix: no environment variables needed at run time.
    import vision_msgs
    assert Path(vision_msgs.__file__).resolve().is_relative_to(Path(sys.prefix).resolve())
    assert Detection3DArray.__module__.startswith("vision_msgs") and LabelInfo


def test_a_vision_msgs_from_elsewhere_is_left_alone(tmp_path):
    (tmp_path / "vision_msgs").mkdir()
    (tmp_path / "vision_msgs" / "__init__.py").write_text("")
    (tmp_path / "vision_msgs" / "msg.py").write_text("Detection3DArray = LabelInfo = object\n")
    env = dict(os.environ, PYTHONPATH=str(tmp_path) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    done = run_script(env)
    assert done.returncode == 0, done.stderr
    assert "already installed (not built here), left alone" in done.stdout


def test_the_wheels_cmake_files_name_this_machines_include_directories(built_here):
    assert fix_wheel_cmake_paths(Path(sys.prefix)) == 0   # make install fixed them already
    files = list(Path(sys.prefix).glob("share/*/cmake/*__rosidl_generator_pyExport.cmake"))
    assert files
    for path in files:
        assert "/opt/python/" not in path.read_text(), path
