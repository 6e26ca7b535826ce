"""Build the vision_msgs interface package (``interfaces/vision_msgs``) and install it into the
prefix of the Python that runs this script (the venv), unless vision_msgs already imports.

Why: ROS 2 perception stacks read detections as vision_msgs/Detection3DArray, and rclpy can
publish a type only when its generated Python package is installed. vision_msgs has no wheel
on PyPI, but the ROS interface generators do (pinned in requirements.txt), so ``make install``
builds it here with cmake and g++, with the venv as the ROS prefix. A user whose ROS already
has vision_msgs (apt's ros-jazzy-vision-msgs) is left alone.

Usage: ``python interfaces/install_vision_msgs.py [--force]`` (what ``make install`` runs).
"""
from __future__ import annotations

import argparse
import hashlib
import os
import re
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from pathlib import Path

SOURCE = Path(__file__).resolve().parent / "vision_msgs"
STAMP_NAME = "multi_instance_reg_build.sha256"   # under <prefix>/share/vision_msgs: "we built this one"


def source_digest() -> str:
    digest = hashlib.sha256()
    for path in sorted(p for p in SOURCE.rglob("*") if p.is_file()):
        digest.update(path.relative_to(SOURCE).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def installed_state(prefix: Path) -> str:
    """'absent', 'ours' (built by this script from the current sources), 'stale' (built by this
    script from other sources) or 'foreign' (vision_msgs from somewhere else, e.g. apt)."""
    probe = subprocess.run([sys.executable, "-c", "import vision_msgs.msg as m; m.Detection3DArray; m.LabelInfo;"
                            "print(m.__file__)"], capture_output=True, text=True)
    stamp = prefix / "share" / "vision_msgs" / STAMP_NAME
    if probe.returncode != 0:
        return "absent"
    if not stamp.exists() or not Path(probe.stdout.strip()).resolve().is_relative_to(prefix.resolve()):
        return "foreign"
    return "ours" if stamp.read_text().strip() == source_digest() else "stale"


def fix_wheel_cmake_paths(prefix: Path) -> int:
    """The ROS wheels' ``*__rosidl_generator_pyExport.cmake`` files name the Python and numpy
    include directories of the machine the wheels were built on (/opt/python/cp311-cp311/...);
    cmake refuses a missing include directory, so point them at this Python's own. Returns
    how many files were rewritten (0 when already fixed)."""
    import numpy

    python_include = sysconfig.get_paths()["include"]
    numpy_include = numpy.get_include()

    def replace(match: re.Match) -> str:
        paths = []
        for path in match.group(2).split(";"):
            if path and not os.path.isdir(path):
                if "numpy" in path:
                    path = numpy_include
                elif re.search(r"include/python3\.\d+$", path):
                    path = python_include
            paths.append(path)
        return match.group(1) + ";".join(paths) + match.group(3)

    changed = 0
    for path in sorted((prefix / "share").glob("*/cmake/*__rosidl_generator_pyExport.cmake")):
        text = path.read_text()
        fixed = re.sub(r'(INTERFACE_INCLUDE_DIRECTORIES ")([^"]*)(")', replace, text)
        if fixed != text:
            path.write_text(fixed)
            changed += 1
    return changed


def build_and_install(prefix: Path) -> None:
    missing = [tool for tool in ("cmake", "g++") if shutil.which(tool) is None]
    if missing:
        raise SystemExit(f"install_vision_msgs: error: building vision_msgs needs {' and '.join(missing)} "
                         "(e.g. `apt-get install cmake g++`); or install ROS' ros-jazzy-vision-msgs")
    if not (Path(sysconfig.get_paths()["include"]) / "Python.h").exists():
        raise SystemExit("install_vision_msgs: error: building vision_msgs needs the Python headers "
                         f"(no Python.h in {sysconfig.get_paths()['include']}; e.g. `apt-get install python3-dev`)")
    fix_wheel_cmake_paths(prefix)
    env = dict(os.environ, CMAKE_PREFIX_PATH=str(prefix), AMENT_PREFIX_PATH=str(prefix),
               PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))
    with tempfile.TemporaryDirectory(prefix="vision_msgs_build_") as build:
        steps = [
            ["cmake", "-S", str(SOURCE), "-B", build, f"-DCMAKE_INSTALL_PREFIX={prefix}",
             f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF", "-DCMAKE_BUILD_TYPE=Release"],
            ["cmake", "--build", build, "--parallel", str(os.cpu_count() or 1)],
            ["cmake", "--install", build],
        ]
        for step in steps:
            done = subprocess.run(step, env=env, capture_output=True, text=True)
            if done.returncode != 0:
                tail = "\n".join((done.stdout + done.stderr).splitlines()[-30:])
                raise SystemExit(f"{tail}\ninstall_vision_msgs: error: `{' '.join(step[:2])} ...` failed "
                                 "(output above); the node runs without vision_msgs, with detections off")
    (prefix / "share" / "vision_msgs" / STAMP_NAME).write_text(source_digest() + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--force", action="store_true", help="build even if vision_msgs already imports")
    args = parser.parse_args(argv)
    prefix = Path(sys.prefix)
    state = installed_state(prefix)
    if state == "foreign" and not args.force:
        print("vision_msgs: already installed (not built here), left alone")
        return 0
    if state == "ours" and not args.force:
        print("vision_msgs: up to date")
        return 0
    start = time.monotonic()
    build_and_install(prefix)
    if installed_state(prefix) != "ours":
        raise SystemExit("install_vision_msgs: error: vision_msgs was built but does not import")
    print(f"vision_msgs: built and installed into {prefix} in {time.monotonic() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
