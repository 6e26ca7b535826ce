"""Build the vision_msgs interface package (``interfaces/vision_msgs``) and install it into the
prefix of the Python that runs this script (the venv), unless vision_msgs already imports.

Why: ROS 2 perception stacks read detections as vision_msgs/Detection3DArray, and rclpy can
publish a type only when its generated Python package is installed. vision_msgs has no wheel
on PyPI, but the ROS interface generators do (pinned in requirements.txt), so ``make install``
builds it here with cmake and g++, with the venv as the ROS prefix. A user whose ROS already
has vision_msgs (apt's ros-jazzy-vision-msgs) is left alone.

The same for realsense2_camera_msgs (``interfaces/realsense2_camera_msgs``: only its
Extrinsics, the depth to colour extrinsics the node reads from a camera that records depth
unaligned), with ``--package realsense2_camera_msgs``; a realsense-ros install's is left alone.

Usage: ``python interfaces/install_vision_msgs.py [--package NAME] [--force]`` (what ``make
install`` runs, once per package).
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

INTERFACES = Path(__file__).resolve().parent
# package -> the messages the project uses from it (what must import)
PACKAGES = {"vision_msgs": ("Detection3DArray", "LabelInfo"), "realsense2_camera_msgs": ("Extrinsics",)}
STAMP_NAME = "multi_instance_reg_build.sha256"   # under <prefix>/share/<package>: "we built this one"


def source_digest(package: str = "vision_msgs") -> str:
    source = INTERFACES / package
    digest = hashlib.sha256()
    for path in sorted(p for p in source.rglob("*") if p.is_file()):
        digest.update(path.relative_to(source).as_posix().encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def installed_state(prefix: Path, package: str = "vision_msgs") -> str:
    """'absent', 'ours' (built by this script from the current sources), 'stale' (built by this
    script from other sources) or 'foreign' (the package from somewhere else, e.g. apt)."""
    uses = "".join(f" m.{name};" for name in PACKAGES[package])
    probe = subprocess.run([sys.executable, "-c", f"import {package}.msg as m;{uses} print(m.__file__)"],
                           capture_output=True, text=True)
    stamp = prefix / "share" / package / STAMP_NAME
    if probe.returncode != 0:
        return "absent"
    if not stamp.exists() or not Path(probe.stdout.strip()).resolve().is_relative_to(prefix.resolve()):
        return "foreign"
    return "ours" if stamp.read_text().strip() == source_digest(package) else "stale"


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


def build_and_install(prefix: Path, package: str = "vision_msgs") -> None:
    missing = [tool for tool in ("cmake", "g++") if shutil.which(tool) is None]
    apt = "ros-jazzy-" + package.replace("_", "-")
    if missing:
        raise SystemExit(f"install_vision_msgs: error: building {package} needs {' and '.join(missing)} "
                         f"(e.g. `apt-get install cmake g++`); or install ROS' {apt}")
    if not (Path(sysconfig.get_paths()["include"]) / "Python.h").exists():
        raise SystemExit(f"install_vision_msgs: error: building {package} needs the Python headers "
                         f"(no Python.h in {sysconfig.get_paths()['include']}; e.g. `apt-get install python3-dev`)")
    fix_wheel_cmake_paths(prefix)
    env = dict(os.environ, CMAKE_PREFIX_PATH=str(prefix), AMENT_PREFIX_PATH=str(prefix),
               PATH=str(Path(sys.executable).parent) + os.pathsep + os.environ.get("PATH", ""))
    without = {"vision_msgs": "the node runs without vision_msgs, with detections off",
               "realsense2_camera_msgs": "the node then reads only depth aligned to colour"}[package]
    with tempfile.TemporaryDirectory(prefix=f"{package}_build_") as build:
        steps = [
            ["cmake", "-S", str(INTERFACES / package), "-B", build, f"-DCMAKE_INSTALL_PREFIX={prefix}",
             f"-DPython3_EXECUTABLE={sys.executable}", "-DBUILD_TESTING=OFF", "-DCMAKE_BUILD_TYPE=Release"],
            ["cmake", "--build", build, "--parallel", str(os.cpu_count() or 1)],
            ["cmake", "--install", build],
        ]
        for step in steps:
            done = subprocess.run(step, env=env, capture_output=True, text=True)
            if done.returncode != 0:
                tail = "\n".join((done.stdout + done.stderr).splitlines()[-30:])
                raise SystemExit(f"{tail}\ninstall_vision_msgs: error: `{' '.join(step[:2])} ...` failed "
                                 f"(output above); {without}")
    (prefix / "share" / package / STAMP_NAME).write_text(source_digest(package) + "\n")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--package", choices=tuple(PACKAGES), default="vision_msgs",
                        help="which interface package (default vision_msgs)")
    parser.add_argument("--force", action="store_true", help="build even if the package already imports")
    args = parser.parse_args(argv)
    prefix, package = Path(sys.prefix), args.package
    state = installed_state(prefix, package)
    if state == "foreign" and not args.force:
        print(f"{package}: already installed (not built here), left alone")
        return 0
    if state == "ours" and not args.force:
        print(f"{package}: up to date")
        return 0
    start = time.monotonic()
    build_and_install(prefix, package)
    if installed_state(prefix, package) != "ours":
        raise SystemExit(f"install_vision_msgs: error: {package} was built but does not import")
    print(f"{package}: built and installed into {prefix} in {time.monotonic() - start:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
